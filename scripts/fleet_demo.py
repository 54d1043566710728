#!/usr/bin/env python3
"""The fleet on one machine, shown and measured: `mbnt serve --workers 0` and N `mbnt worker`
processes on one PostgreSQL database and one object store (a local directory).

    python3 scripts/fleet_demo.py kill          # 2 workers, 4 jobs, one worker killed mid-fit
    python3 scripts/fleet_demo.py throughput    # jobs per hour with 1 and with 2 workers
    python3 scripts/fleet_demo.py windows       # one long log: its windows on 1 and on 2 workers

Needs a PostgreSQL server (MBNT_TEST_DATABASE_URL, default postgres://postgres@127.0.0.1:5432/postgres,
whose user may create databases) and `psql`; builds nothing: set MBNT_BIN (default
target/release/mbnt). Uses only Python's standard library.
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
import uuid

ADMIN_URL = os.environ.get("MBNT_TEST_DATABASE_URL", "postgres://postgres@127.0.0.1:5432/postgres")
MBNT = os.environ.get("MBNT_BIN", "target/release/mbnt")
TIMEOUT_S = 900


def psql(sql):
    subprocess.run(["psql", ADMIN_URL, "-q", "-c", sql], check=True, stdout=subprocess.DEVNULL)


class Proc:
    """An mbnt child process whose stderr (its log) goes to a file."""

    def __init__(self, args, env, log_path, ready):
        self.log_path = log_path
        self.log = open(log_path, "w")
        self.p = subprocess.Popen([MBNT, *args], env=env, stdin=subprocess.DEVNULL,
                                  stdout=subprocess.DEVNULL, stderr=self.log)
        deadline = time.time() + 120
        while True:
            text = open(log_path).read()
            if ready in text:
                self.ready_line = next(l for l in text.splitlines() if ready in l)
                return
            if self.p.poll() is not None or time.time() > deadline:
                sys.exit(f"{args[0]} did not start:\n{text}")
            time.sleep(0.05)

    def kill(self):
        self.p.send_signal(signal.SIGKILL)
        self.p.wait()

    def stop(self):
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            self.p.wait(timeout=120)


class Fleet:
    def __init__(self, workers, checkpoint_every_s="0"):
        self.root = tempfile.mkdtemp(prefix="mbnt-fleet-")
        self.db = f"mbnt_demo_{uuid.uuid4().hex}"
        psql(f"CREATE DATABASE {self.db}")
        base = ADMIN_URL.rsplit("/", 1)[0]
        os.makedirs(f"{self.root}/objects")
        self.env = dict(os.environ, RUST_LOG="info", NO_COLOR="1",
                        MBNT_DATABASE_URL=f"{base}/{self.db}",
                        MBNT_OBJECT_STORE_URL=f"file://{self.root}/objects",
                        MBNT_LEASE_S="2", MBNT_CHECKPOINT_EVERY_S=checkpoint_every_s)
        self.env.pop("MBNT_API_TOKEN", None)
        self.api = self.start_api()
        self.workers = [Proc(["worker", "--threads-per-job", "1", "--data-dir", f"{self.root}/w{i}"], self.env,
                             f"{self.root}/worker{i}.log", "mbnt worker ready") for i in range(workers)]

    def start_api(self):
        api = Proc(["serve", "--workers", "0", "--bind", "127.0.0.1:0", "--data-dir", f"{self.root}/api"],
                   self.env, f"{self.root}/api.log", "mbnt service listening")
        self.base = "http://" + re.search(r"addr=(\S+)", api.ready_line).group(1)
        return api

    def call(self, method, path, body=None):
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers={"content-type": "application/json"})
        with urllib.request.urlopen(req, timeout=60) as r:
            return json.loads(r.read())

    def close(self):
        for p in [*self.workers, self.api]:
            if p.p.poll() is None:
                p.stop()
        psql(f"DROP DATABASE IF EXISTS {self.db} WITH (FORCE)")
        shutil.rmtree(self.root, ignore_errors=True)


def grid_frames(frames=3, points=300):
    """A small rigid grid moving 0.1 m a frame (as the API tests' frames)."""
    out = []
    for k in range(frames):
        out.append([[(i % 10) * 0.3 + 0.1 * k, ((i // 10) % 10) * 0.3, (i // 100) * 0.5 + 1.0]
                    for i in range(points)])
    return out


def submit(fleet, jobs, iterations):
    seq = fleet.call("POST", "/v1/sequences", {"name": "fleet-demo", "frames": grid_frames()})["id"]
    params = {"iterations": iterations, "validate_every": 10, "validation_patience": 0, "hidden_width": 64,
              "remove_ground": False}
    return [fleet.call("POST", "/v1/jobs", {"sequence_id": seq, "method": "ntp", "params": params})["id"]
            for _ in range(jobs)]


def wait_all(fleet, ids):
    deadline = time.time() + TIMEOUT_S
    while True:
        views = {i: fleet.call("GET", f"/v1/jobs/{i}") for i in ids}
        failed = [v for v in views.values() if v["status"] == "failed"]
        if failed:
            sys.exit(f"a job failed: {failed[0]}")
        if all(v["status"] == "succeeded" for v in views.values()):
            return views
        if time.time() > deadline:
            sys.exit("timed out")
        time.sleep(0.2)


def ts(rfc3339):
    from datetime import datetime
    return datetime.fromisoformat(rfc3339.replace("Z", "+00:00")).timestamp()


def kill_demo():
    fleet = Fleet(workers=2)
    try:
        ids = submit(fleet, 4, iterations=1500)
        victim = None
        while victim is None:
            for i in ids:
                v = fleet.call("GET", f"/v1/jobs/{i}")
                if v["status"] == "running" and v["progress"]["iteration"] >= 35:
                    victim = v
                    break
            time.sleep(0.05)
        pid = int(victim["worker"].split(":")[1])
        killed = next(w for w in fleet.workers if w.p.pid == pid)
        print(f"killing worker {victim['worker']} (SIGKILL) holding job {victim['id']} at iteration "
              f"{victim['progress']['iteration']}")
        killed.kill()
        print("restarting the API while the other worker works")
        fleet.api.stop()
        fleet.api = fleet.start_api()
        views = wait_all(fleet, ids)
        print(f"{'job':38} {'status':10} attempts resumed_from")
        for i in ids:
            v = views[i]
            print(f"{i:38} {v['status']:10} {v['attempts']:8} {v['resumed_from_iteration']}")
        logs = [open(w.log_path).read() for w in fleet.workers]
        for i in ids:
            ends = sum(len(re.findall(rf"job_id={i}[^\n]*fit succeeded", log)) for log in logs)
            assert ends == 1, f"job {i} was fitted to its end {ends} times"
        v = views[victim["id"]]
        assert v["attempts"] == 2 and (v["resumed_from_iteration"] or 0) >= 30, v
        print("every job succeeded; the killed one went on from its checkpoint; each was fitted to its end once")
    finally:
        fleet.close()


def throughput(jobs=8, iterations=400):
    print(f"{jobs} NTP jobs of {iterations} iterations each (3 frames x 300 points, hidden width 64), "
          f"workers of one thread each")
    rows = []
    for n in (1, 2):
        fleet = Fleet(workers=n, checkpoint_every_s="30")
        try:
            t0 = time.time()
            ids = submit(fleet, jobs, iterations)
            views = wait_all(fleet, ids)
            wall = time.time() - t0
            runs = [ts(v["finished_at"]) - ts(v["started_at"]) for v in views.values()]
            waits = sorted(ts(v["started_at"]) - ts(v["created_at"]) for v in views.values())
            overhead = (wall * n - sum(runs)) / jobs
            rows.append((n, wall, jobs / wall * 3600, sum(runs) / jobs, overhead, waits[0]))
        finally:
            fleet.close()
    print(f"{'workers':>7} {'wall s':>8} {'jobs/h':>8} {'run s/job':>9} {'overhead s/job':>14} {'first claim s':>13}")
    for n, wall, per_hour, run, overhead, first in rows:
        print(f"{n:>7} {wall:>8.1f} {per_hour:>8.0f} {run:>9.2f} {overhead:>14.2f} {first:>13.2f}")
    print(f"speed-up with 2 workers: {rows[0][1] / rows[1][1]:.2f}x")


def upload_simulated(fleet, seed, frames):
    """Uploads `mbnt simulate --seed SEED --frames FRAMES` (KITTI .bin frames, times, poses)."""
    out = f"{fleet.root}/sim{seed}"
    subprocess.run([MBNT, "simulate", "--seed", str(seed), "--frames", str(frames), "--out", out], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    times = [float(x) for x in open(f"{out}/timestamps.txt").read().split()]
    poses = [[float(x) for x in line.split()] for line in open(f"{out}/poses.txt") if line.strip()]
    meta = json.dumps({"name": f"sim{seed}", "timestamps": times, "poses": poses})
    files = sorted(os.listdir(f"{out}/frames"))
    args = ["curl", "-s", "-F", f"meta={meta};type=application/json"]
    for f in files:
        args += ["-F", f"frame=@{out}/frames/{f}"]
    answer = subprocess.run([*args, fleet.base + "/v1/sequences"], check=True, capture_output=True).stdout
    return json.loads(answer)["id"]


def windows(seed=135, frames=60, window_iterations=40):
    print(f"one MBNT job (defaults, window_iterations {window_iterations}) on simulated log {seed} of {frames} "
          f"frames with poses; workers of one thread each")
    rows = []
    for n in (1, 2):
        fleet = Fleet(workers=n, checkpoint_every_s="30")
        try:
            seq = upload_simulated(fleet, seed, frames)
            t0 = time.time()
            job = fleet.call("POST", "/v1/jobs", {"sequence_id": seq, "method": "mbnt",
                                                 "params": {"window_iterations": window_iterations}})["id"]
            view = wait_all(fleet, [job])[job]
            wall = time.time() - t0
            logs = "".join(open(w.log_path).read() for w in fleet.workers)
            helped = logs.count("helping: window kept")
            windows_total = view["progress"]["window"]["windows"] if view["progress"].get("window") else 1
            rows.append((n, wall, helped, windows_total))
        finally:
            fleet.close()
    print(f"{'workers':>7} {'wall s':>8} {'windows':>7} {'fitted by the helper':>20}")
    for n, wall, helped, total in rows:
        print(f"{n:>7} {wall:>8.1f} {total:>7} {helped:>20}")
    print(f"speed-up with 2 workers: {rows[0][1] / rows[1][1]:.2f}x")


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "kill"
    {"kill": kill_demo, "throughput": throughput, "windows": windows}[what]()
