//! Evaluating the fitted networks: the running sum of a trajectory network's velocities, and
//! forward/backward Euler through pair flows.

use crate::geometry::Point;
use crate::nn::{Mlp, Workspace};

use super::encoding::encode_points;

/// The fitted network(s) behind a model.
#[derive(Debug, Clone)]
pub(super) enum Motion {
    /// One trajectory network (NTP, MBNT): input [x, y, z, time embedding], output the
    /// velocities v_0..v_{T-2}.
    Trajectory(Mlp<f32>),
    /// Per pair k -> k+1 a forward flow f_k and a backward flow g_k (NSFP, MBNSF).
    PairFlows {
        /// f_k, k = 0..T-2.
        forward: Vec<Mlp<f32>>,
        /// g_k, k = 0..T-2.
        backward: Vec<Mlp<f32>>,
    },
    /// A log fitted as overlapping windows, each with its own model (`model::windows`).
    Windows(Vec<super::windows::Window>),
}

/// Trajectory position at fractional frame index `u` from one point's velocity row: the
/// running sum of the velocities, linear within a step.
fn trajectory_at(row: &[f32], u: f64) -> [f64; 3] {
    let steps = row.len() / 3;
    let whole = (u.floor() as usize).min(steps);
    let frac = u - whole as f64;
    let mut d = [0f64; 3];
    for k in 0..whole {
        for c in 0..3 {
            d[c] += f64::from(row[3 * k + c]);
        }
    }
    if whole < steps && frac > 0.0 {
        for c in 0..3 {
            d[c] += frac * f64::from(row[3 * whole + c]);
        }
    }
    d
}

pub(super) fn trajectory_positions(
    mlp: &Mlp<f32>,
    frames: usize,
    points: &[Point],
    u_obs: f64,
    u_times: &[f64],
    out: &mut [Point],
) {
    let mut input = Vec::new();
    let mut workspace = Workspace::default();
    encode_points(points, u_obs, frames, &mut input);
    let velocities = mlp.forward(&input, points.len(), &mut workspace);
    let width = 3 * (frames - 1);
    for (i, p) in points.iter().enumerate() {
        let row = &velocities[i * width..][..width];
        let anchor = trajectory_at(row, u_obs);
        for (j, &u) in u_times.iter().enumerate() {
            let at = trajectory_at(row, u);
            out[i * u_times.len() + j] = std::array::from_fn(|c| (f64::from(p[c]) + at[c] - anchor[c]) as f32);
        }
    }
}

/// Forward/backward Euler through pair flows. Within a step, motion is linear: a point at
/// fractional index k + a moves by the fraction of f_k (forward) or g_k (backward) it has left.
pub(super) fn euler_positions(
    forward: &[Mlp<f32>],
    backward: &[Mlp<f32>],
    points: &[Point],
    u_obs: f64,
    u_times: &[f64],
    out: &mut [Point],
) {
    let n_times = u_times.len();
    let mut workspace = Workspace::default();
    // f or g of `current` scaled by `fraction`, added with `sign`.
    let mut step = |net: &Mlp<f32>, current: &mut Vec<Point>, fraction: f64, sign: f32| {
        let flow = net.forward(current.as_flattened(), current.len(), &mut workspace);
        for (p, v) in current.iter_mut().zip(flow.chunks_exact(3)) {
            for c in 0..3 {
                p[c] += sign * fraction as f32 * v[c];
            }
        }
    };
    let steps = forward.len();
    // One sweep forward through the later times (ascending) and one backward through the
    // earlier ones (descending), so each crossed step is evaluated once.
    let mut later: Vec<usize> = (0..n_times).filter(|&j| u_times[j] >= u_obs).collect();
    let mut earlier: Vec<usize> = (0..n_times).filter(|&j| u_times[j] < u_obs).collect();
    later.sort_by(|&a, &b| u_times[a].total_cmp(&u_times[b]));
    earlier.sort_by(|&a, &b| u_times[b].total_cmp(&u_times[a]));
    for (order, forward_in_time) in [(later, true), (earlier, false)] {
        let mut current = points.to_vec();
        let mut at = u_obs;
        for j in order {
            let u = u_times[j];
            if forward_in_time {
                while u - at > 1e-9 {
                    let k = (at.floor() as usize).min(steps - 1);
                    let next = ((k + 1) as f64).min(u);
                    step(&forward[k], &mut current, next - at, 1.0);
                    at = next;
                }
            } else {
                while at - u > 1e-9 {
                    let k = ((at.ceil() as usize).max(1) - 1).min(steps - 1);
                    let prev = (k as f64).max(u);
                    step(&backward[k], &mut current, at - prev, -1.0);
                    at = prev;
                }
            }
            for (i, p) in current.iter().enumerate() {
                out[i * n_times + j] = *p;
            }
        }
    }
}
