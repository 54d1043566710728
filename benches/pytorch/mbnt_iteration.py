"""Faithful MBNT iterations in PyTorch on the CPU: the baseline `mbnt bench` is compared with.

What this times is docs method.md sections 1-3 written the way a PyTorch user would write them:
the 8-layer trajectory MLP, 4 reference frames per iteration, every point of every reference frame,
truncated Chamfer to both neighbouring frames, the three cycle-consistency passes, the multi-body
score of every DBSCAN cluster (at most 3000 points) projected to the first and last frames, one
Adam step. It is ours, not the authors' research code, and it is written to be fast rather than
literal: nearest neighbours come from SciPy's k-d tree (the assignment is not differentiated, as
method.md says), and the multi-body gradient uses the fixed-eigenvector rule of method.md instead of
differentiating the power iteration. So it is a conservative baseline: the research code is slower.

`--variant research` instead does those two parts the way the authors' public code does them, to
stand in for it on machines where it cannot run (it needs CUDA and pytorch3d): nearest neighbours by
brute force over all pairs (what pytorch3d's `knn_points` does on the CPU; here as chunked
`torch.cdist`), and the multi-body score with pairwise distances by broadcasting and autograd
through the power iteration (at most 10 steps, stopping when `torch.allclose` says it has settled).

Input: the directory `mbnt bench --export-prepared DIR` writes (the frames exactly as faithful mode
fits them). Output: one JSON object on stdout with seconds per iteration and a split by component.

    python3 -m venv venv && venv/bin/pip install torch scipy numpy
    cargo run --release -- bench --seed 100 --iterations 26 --modes faithful --export-prepared prep
    venv/bin/python benches/pytorch/mbnt_iteration.py prep --iterations 6
"""

import argparse
import glob
import json
import math
import os
import statistics
import sys
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

WIDTH = 128
HIDDEN_LAYERS = 8
MAX_CLUSTER_POINTS = 3000
POWER_ITERATIONS = 10
TRUNCATE_M2 = 2.0


def load(directory):
    names = sorted(glob.glob(os.path.join(directory, "points_*.npy")))
    if not names:
        raise SystemExit(f"no points_*.npy in {directory}: run mbnt bench --export-prepared first")
    frames, clusters = [], []
    for name in names:
        points = np.load(name).astype(np.float32)
        labels = np.load(name.replace("points_", "clusters_"))
        frames.append(points)
        clusters.append([np.flatnonzero(labels == c) for c in range(labels.max() + 1) if (labels == c).sum() > 2])
    return frames, clusters


def network(frames, input_width):
    layers, width = [], input_width
    for _ in range(HIDDEN_LAYERS):
        layers += [torch.nn.Linear(width, WIDTH), torch.nn.ReLU()]
        width = WIDTH
    layers.append(torch.nn.Linear(width, 3 * (frames - 1)))
    return torch.nn.Sequential(*layers)


class Timer:
    def __init__(self):
        self.seconds = {}

    def add(self, name, started):
        self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - started


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("prepared", help="directory written by mbnt bench --export-prepared")
    parser.add_argument("--iterations", type=int, default=6, help="timed iterations (after one warm-up)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--variant", choices=["fast", "research"], default="fast",
                        help="fast: k-d tree neighbours, analytic eigenvector gradient; research: as the authors' code")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)

    frames_np, clusters = load(args.prepared)
    count = len(frames_np)
    frequencies = 1 + math.ceil(math.log2(count))
    frames = [torch.from_numpy(f) for f in frames_np]
    trees = [cKDTree(f) for f in frames_np]  # built once per frame, as in mbnt
    mlp = network(count, 3 + frequencies)
    optimiser = torch.optim.Adam(mlp.parameters(), lr=0.003)
    middle = count // 2
    timer = Timer()

    def velocities(points, t):
        tau = (t + 0.5) / count
        codes = torch.tensor([math.cos(2.0**k * math.pi * tau) for k in range(frequencies)], dtype=torch.float32)
        inputs = torch.cat([points, codes.expand(points.shape[0], frequencies)], dim=1)
        started = time.perf_counter()
        out = mlp(inputs).view(points.shape[0], count - 1, 3)
        timer.add("mlp_forward", started)
        return out

    def displacement(v, start, end):
        # Running sum of the per-step velocities between two frames (signed).
        if end >= start:
            return v[:, start:end].sum(dim=1)
        return -v[:, end:start].sum(dim=1)

    def nearest_brute_force(queries, points):
        # All pairs, in row chunks that keep the distance block near 256 MB.
        chunk = max(1, (64 << 20) // max(1, points.shape[0]))
        return torch.cat([torch.cdist(q, points).argmin(dim=1) for q in queries.split(chunk)]).numpy()

    def chamfer(moved, k):
        started = time.perf_counter()
        if args.variant == "research":
            with torch.no_grad():
                forward_index = nearest_brute_force(moved, frames[k])
                backward_index = nearest_brute_force(frames[k], moved)
            timer.add("nearest", started)
            return chamfer_terms(moved, k, forward_index, backward_index)
        _, forward_index = trees[k].query(moved.detach().numpy(), k=1, workers=args.threads)
        _, backward_index = cKDTree(moved.detach().numpy()).query(frames_np[k], k=1, workers=args.threads)
        timer.add("nearest", started)
        return chamfer_terms(moved, k, forward_index, backward_index)

    def chamfer_terms(moved, k, forward_index, backward_index):
        target = frames[k]
        d2_forward = ((moved - target[torch.from_numpy(forward_index)]) ** 2).sum(dim=1)
        d2_backward = ((target - moved[torch.from_numpy(backward_index)]) ** 2).sum(dim=1)
        return (d2_forward * (d2_forward < TRUNCATE_M2)).mean() + (d2_backward * (d2_backward < TRUNCATE_M2)).mean()

    def multibody_research(points, moved, d_thr):
        src = torch.norm(points[:, None, :] - points[None, :, :], dim=-1)
        dst = torch.norm(moved[:, None, :] - moved[None, :, :], dim=-1)
        a = torch.clamp(1.0 - torch.abs(src - dst) ** 2 / d_thr**2, min=0.0)
        v = torch.ones(a.shape[0], 1)
        last = v
        for _ in range(POWER_ITERATIONS):
            v = a @ v
            v = v / (torch.norm(v) + 1e-6)
            if torch.allclose(v, last):
                break
            last = v
        return -torch.log((v.T @ a @ v).squeeze() / a.shape[0])

    def multibody(points, moved, d_thr):
        if args.variant == "research":
            return multibody_research(points, moved, d_thr)
        n = points.shape[0]
        a = 1.0 - (torch.cdist(points, points) - torch.cdist(moved, moved)) ** 2 / d_thr**2
        a = torch.clamp(a, min=0.0)
        with torch.no_grad():
            v = torch.ones(n, 1)
            for _ in range(POWER_ITERATIONS):
                nv = a @ v
                nv = nv / nv.norm()
                done = (nv - v).abs().max() < 1e-6
                v = nv
                if done:
                    break
        score = (v.T @ a @ v).squeeze() / n
        return -torch.log(score)

    def reference_loss(t):
        x = frames[t]
        v = velocities(x, t)
        loss = 0.0
        if t + 1 < count:
            loss = loss + chamfer(x + v[:, t], t + 1)
        if t > 0:
            loss = loss + chamfer(x - v[:, t - 1], t - 1)
        for target in (min(t + 1, count - 1), max(t - 1, 0), middle):
            if target != t:
                moved = x + displacement(v, t, target)
                loss = loss + ((v - velocities(moved, target)) ** 2).mean()
        started = time.perf_counter()
        for end, d_thr in ((0, 0.10 + 0.39 * t / count), (count - 1, 0.10 + 0.39 * (count - t) / count)):
            if end == t or not clusters[t]:
                continue
            terms = []
            for members in clusters[t]:
                if len(members) > MAX_CLUSTER_POINTS:
                    members = rng.choice(members, MAX_CLUSTER_POINTS, replace=False)
                index = torch.from_numpy(np.asarray(members))
                terms.append(multibody(x[index], x[index] + displacement(v[index], t, end), d_thr))
            loss = loss + torch.stack(terms).mean()
        timer.add("multibody_forward", started)
        return loss

    def iteration():
        optimiser.zero_grad(set_to_none=True)
        total = 0.0
        for t in rng.integers(0, count, size=4):
            started = time.perf_counter()
            loss = reference_loss(int(t))
            timer.add("forward_all", started)
            started = time.perf_counter()
            loss.backward()
            timer.add("backward", started)
            total += float(loss.detach())
        started = time.perf_counter()
        optimiser.step()
        timer.add("adam", started)
        if not math.isfinite(total):
            raise SystemExit(f"the loss is not finite ({total}): the timing would not be of a real fit")
        return total

    iteration()  # warm-up: first-call allocations and thread start
    timer.seconds.clear()
    seconds = []
    for i in range(args.iterations):
        started = time.perf_counter()
        loss = iteration()
        seconds.append(time.perf_counter() - started)
        print(f"iteration {i + 1}/{args.iterations}: {seconds[-1]:.2f} s, loss {loss:.5f}", file=sys.stderr)
    per_iteration = {k: v / args.iterations for k, v in sorted(timer.seconds.items())}
    print(
        json.dumps(
            {
                "torch": torch.__version__,
                "variant": args.variant,
                "threads": args.threads,
                "frames": count,
                "points_per_frame": sum(len(f) for f in frames_np) / count,
                "clusters_per_frame": sum(len(c) for c in clusters) / count,
                "iterations": args.iterations,
                "seconds_per_iteration": statistics.mean(seconds),
                "median_seconds_per_iteration": statistics.median(seconds),
                "seconds_per_iteration_by_part": per_iteration,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
