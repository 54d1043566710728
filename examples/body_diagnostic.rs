//! Where the scene model's moving bodies lose accuracy, frame by frame, on simulated sequences.
//!
//! For every moving object of the simulator with at least 50 non-ground frame-0 points: the mean
//! error (m) of its frame-0 points carried by the model to frames 4, 8, ..., T-1 against the exact
//! positions, the share within 0.5 m at the end, and which fitted bodies hold its frame-0 points.
//! Also the static non-ground frame-0 points that end 0.5 m or more off, and the body or free
//! points responsible. The bodies do not depend on the network, so one-iteration fits (the
//! default here) show them in about a minute per seed:
//!
//! ```text
//! cargo run --release --example body_diagnostic -- 100,101 [FRAMES] ['{"iterations": 1}']
//! ```
//!
//! Under each object, the same errors for its points that a body holds. With
//! `BODY_DIAG_LOG=LOG_FRAMES,FIRST`, frames FIRST.. of a longer simulated log. With
//! `BODY_DIAG_PATH=1`, also the object's true path (centre of its frame-0 points, fit
//! coordinates, every frame) and where the model carries the same points; with `BODY_DIAG_PROBE=N`, what N rounds of point-to-point ICP (30 when N
//! is not a number) recover between two of its sweeps (its own points only, from standing
//! still) against the true motion.

use std::collections::BTreeMap;

use mbnt::fit::{FitParams, Method, fit_sequence};
use mbnt::geometry::Point;
use mbnt::geometry::knn::KdTree;
use mbnt::geometry::rigid::{Rigid, fit_rigid_icp};
use mbnt::sim::{SimParams, simulate};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let seeds: Vec<u64> =
        args.get(1).map_or("100", String::as_str).split(',').map(str::parse).collect::<Result<_, _>>()?;
    let frames: usize = args.get(2).map_or(Ok(25), |s| s.parse())?;
    let params: FitParams = serde_json::from_str(args.get(3).map_or(r#"{"iterations": 1}"#, String::as_str))?;
    let params = params.check(Method::Mbnt)?;
    let probe_rounds: Option<usize> = std::env::var("BODY_DIAG_PROBE").ok().map(|s| s.parse().unwrap_or(30));
    let show_path = std::env::var("BODY_DIAG_PATH").is_ok();
    for seed in seeds {
        // `BODY_DIAG_LOG=LOG_FRAMES,FIRST`: frames FIRST.. of a LOG_FRAMES-frame log (a window of
        // a whole log, as `mbnt eval --first-frame FIRST --log-frames LOG_FRAMES` scores it).
        let sim = match std::env::var("BODY_DIAG_LOG").ok() {
            Some(spec) => {
                let (log, first) =
                    spec.split_once(',').ok_or_else(|| anyhow::anyhow!("BODY_DIAG_LOG=LOG_FRAMES,FIRST"))?;
                let first: usize = first.parse()?;
                simulate(&SimParams::log(seed, log.parse()?))?.frames_range(first..first + frames)?
            }
            None => simulate(&SimParams::log(seed, frames))?,
        };
        let sequence = sim.to_fit_sequence();
        let started = std::time::Instant::now();
        let model = fit_sequence(&sequence, Method::Mbnt, &params, &mut |_| std::ops::ControlFlow::Continue(()))?;
        println!(
            "seed {seed}: {} bodies, fit {:.1} s (bodies {:.1} s)",
            model.bodies().len(),
            started.elapsed().as_secs_f64(),
            model.report().rigid_tracks_seconds
        );
        let ts = &sim.timestamps_s;
        let last = frames - 1;
        let checkpoints: Vec<usize> = (4..last).step_by(4).chain([last]).collect();
        let times: Vec<f64> = checkpoints.iter().map(|&j| ts[j]).collect();
        let predicted = model.positions(&sim.frames[0], ts[0], &times)?;
        let truth: Vec<Vec<[f32; 3]>> =
            checkpoints.iter().map(|&j| sim.positions_at(0, j)).collect::<Result<_, _>>()?;
        // Where the still world (the poses) would put frame 0's points at each checkpoint.
        let to_first = mbnt::fit::poses_relative_to_first(&sim.ego_poses)?;
        let sim_still: Vec<Vec<[f32; 3]>> = checkpoints
            .iter()
            .map(|&j| {
                let back = to_first[j].inverse();
                sim.frames[0].iter().map(|p| back.apply(p)).collect()
            })
            .collect();
        // Frame 0's points at every frame, exact, in fit coordinates (for the path and the probe).
        let exact_fit: Vec<Vec<Point>> = if show_path || probe_rounds.is_some() {
            to_first
                .iter()
                .enumerate()
                .map(|(j, to_fit)| Ok(sim.positions_at(0, j)?.iter().map(|p| to_fit.apply(p)).collect()))
                .collect::<anyhow::Result<_>>()?
        } else {
            Vec::new()
        };
        let owners = model.object_ids(&sim.frames[..1])?[0].clone();
        let error = |i: usize, n: usize| -> f64 {
            let (p, q) = (predicted[i * checkpoints.len() + n], truth[n][i]);
            (0..3).map(|c| f64::from(p[c] - q[c]).powi(2)).sum::<f64>().sqrt()
        };
        print!("  {:<28} {:>5} {:>6} {:>8}", "object", "pts", "end<.5", "bodies");
        for j in &checkpoints {
            print!(" {:>6}", format!("f{j}"));
        }
        println!();
        let mut per_object: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
        for (i, t) in sim.truth[0].iter().enumerate() {
            if !t.is_ground {
                per_object.entry(t.object_id).or_default().push(i);
            }
        }
        let end = checkpoints.len() - 1;
        let (mut moving_within, mut moving_points) = (0usize, 0usize);
        for (id, members) in &per_object {
            let object = &sim.objects[*id as usize];
            if !object.dynamic || members.len() < 50 {
                continue;
            }
            let within = members.iter().filter(|&&i| error(i, end) < 0.5).count();
            moving_within += within;
            moving_points += members.len();
            let mut bodies: BTreeMap<i32, usize> = BTreeMap::new();
            for &i in members {
                *bodies.entry(owners[i]).or_default() += 1;
            }
            let held: Vec<String> = bodies.iter().filter(|(b, _)| **b >= 0).map(|(b, n)| format!("{b}:{n}")).collect();
            let centre: Vec<f32> = (0..3)
                .map(|c| members.iter().map(|&i| sim.frames[0][i][c]).sum::<f32>() / members.len() as f32)
                .collect();
            print!(
                "  {:<28} ({:>5.1},{:>5.1}) {:>5} {:>5.0}% {:>8}",
                format!("{id} {:?} {:?}", object.kind, object.behaviour),
                centre[0],
                centre[1],
                members.len(),
                100.0 * within as f64 / members.len() as f64,
                if held.is_empty() { "-".to_string() } else { held.join(",") }
            );
            for n in 0..checkpoints.len() {
                let mean = members.iter().map(|&i| error(i, n)).sum::<f64>() / members.len() as f64;
                print!(" {mean:>6.2}");
            }
            // At the end: the true travel (in frame T-1's sensor coordinates, from where the
            // still world would put the points) and the error along and across it.
            let still = &sim_still[end];
            let (mut travel, mut along, mut across) = (0.0, 0.0, 0.0);
            for &i in members {
                let (p, q, s0) = (predicted[i * checkpoints.len() + end], truth[end][i], still[i]);
                let d: [f64; 3] = std::array::from_fn(|c| f64::from(q[c] - s0[c]));
                let norm = (d[0] * d[0] + d[1] * d[1]).sqrt().max(1e-9);
                let e: [f64; 3] = std::array::from_fn(|c| f64::from(p[c] - q[c]));
                travel += norm;
                along += (e[0] * d[0] + e[1] * d[1]) / norm;
                across += (e[1] * d[0] - e[0] * d[1]) / norm;
            }
            let n = members.len() as f64;
            print!("   travel {:.2} m, along {:+.2}, across {:+.2}", travel / n, along / n, across / n);
            // The observed frames of the body holding most of its points.
            let main_body = bodies.iter().filter(|(b, _)| **b >= 0).max_by_key(|(_, n)| **n).map(|(&id, _)| id);
            if let Some(body) = main_body.and_then(|id| model.bodies().iter().find(|b| b.id as i32 == id)) {
                let seen: String = body.observed.iter().map(|&o| if o { '#' } else { '.' }).collect();
                print!("  body {}: {seen}", body.id);
            }
            println!();
            if let Some(rounds) = probe_rounds {
                // The object's own non-ground points of frame k, in fit coordinates.
                let own = |k: usize| -> Vec<Point> {
                    sim.frames[k]
                        .iter()
                        .zip(&sim.truth[k])
                        .filter(|(_, t)| t.object_id == *id && !t.is_ground)
                        .map(|(p, _)| to_first[k].apply(p))
                        .collect()
                };
                let mean = |points: &[Point]| -> [f64; 3] {
                    std::array::from_fn(|c| {
                        points.iter().map(|p| f64::from(p[c])).sum::<f64>() / points.len().max(1) as f64
                    })
                };
                for (a, b) in [(0usize, 1usize), (1, 2), (0, 2), (0, 4)] {
                    let (from, to) = (own(b), own(a));
                    let tree = KdTree::new(&to);
                    let back = fit_rigid_icp(&from, &tree, &to, Rigid::identity(), rounds, 1.0);
                    let centre = mean(&from);
                    let moved_back = back.apply_f64(centre);
                    // The true motion of the frame-0 points from frame a to frame b.
                    let true_a: Vec<Point> = members.iter().map(|&i| exact_fit[a][i]).collect();
                    let true_b: Vec<Point> = members.iter().map(|&i| exact_fit[b][i]).collect();
                    let (ca, cb) = (mean(&true_a), mean(&true_b));
                    println!(
                        "    ICP {a} -> {b} ({} / {} pts): recovered ({:+.2}, {:+.2}) m, true ({:+.2}, {:+.2}) m",
                        to.len(),
                        from.len(),
                        centre[0] - moved_back[0],
                        centre[1] - moved_back[1],
                        cb[0] - ca[0],
                        cb[1] - ca[1]
                    );
                }
            }
            // The same errors for the points a body holds: how well the bodies move what they took.
            let on: Vec<usize> = members.iter().copied().filter(|&i| owners[i] >= 0).collect();
            if !on.is_empty() {
                let errs: Vec<String> = (0..checkpoints.len())
                    .map(|n| format!("{:>6.2}", on.iter().map(|&i| error(i, n)).sum::<f64>() / on.len() as f64))
                    .collect();
                println!("    {:<49} {}", format!("on a body: {} pts", on.len()), errs.join(" "));
            }
            if show_path {
                let mut line = String::new();
                for (j, at) in exact_fit.iter().enumerate() {
                    let c: Vec<f32> =
                        (0..2).map(|d| members.iter().map(|&i| at[i][d]).sum::<f32>() / members.len() as f32).collect();
                    line += &format!(" {j}:({:.2},{:.2})", c[0], c[1]);
                }
                println!("    truth{line}");
                // How many of the object's own (non-ground) points each sweep saw.
                let visible: Vec<String> = (0..sim.frames.len())
                    .map(|k| {
                        let n = sim.truth[k].iter().filter(|t| t.object_id == *id && !t.is_ground).count();
                        format!("{k}:{n}")
                    })
                    .collect();
                println!("    seen {}", visible.join(" "));
                // Where the model carries the same points, in fit coordinates.
                let member_points: Vec<Point> = members.iter().map(|&i| sim.frames[0][i]).collect();
                let every: Vec<f64> = ts.to_vec();
                let carried = model.positions(&member_points, ts[0], &every)?;
                let mut line = String::new();
                for (j, to_fit) in to_first.iter().enumerate() {
                    let c: Vec<f32> = (0..2)
                        .map(|d| {
                            (0..member_points.len())
                                .map(|i| to_fit.apply(&carried[i * every.len() + j])[d])
                                .sum::<f32>()
                                / member_points.len() as f32
                        })
                        .collect();
                    line += &format!(" {j}:({:.2},{:.2})", c[0], c[1]);
                }
                println!("    model{line}");
            }
        }
        println!(
            "  moving objects' frame-0 points within 0.5 m at the end: {moving_within} of {moving_points} ({:.1} %)",
            100.0 * moving_within as f64 / moving_points.max(1) as f64
        );
        // What each body holds over all frames, by the kind of the simulator's objects.
        let all_owners = model.object_ids(&sim.frames)?;
        for body in model.bodies() {
            let mut held: BTreeMap<String, usize> = BTreeMap::new();
            for (k, owners) in all_owners.iter().enumerate() {
                for (i, &o) in owners.iter().enumerate() {
                    if o == body.id as i32 && !sim.truth[k][i].is_ground {
                        let object = &sim.objects[sim.truth[k][i].object_id as usize];
                        let kind = if object.dynamic { format!("{}", object.id) } else { format!("{:?}", object.kind) };
                        *held.entry(kind).or_default() += 1;
                    }
                }
            }
            let size: Vec<String> =
                (0..3).map(|c| format!("{:.1}", body.extent_max_m[c] - body.extent_min_m[c])).collect();
            let seen: String = body.observed.iter().map(|&o| if o { '#' } else { '.' }).collect();
            println!("  body {:>2} size {} {seen} holds {held:?}", body.id, size.join("x"));
        }
        // Static points that end off, by what carried them.
        let mut off: BTreeMap<String, usize> = BTreeMap::new();
        let mut statics = 0usize;
        for (i, t) in sim.truth[0].iter().enumerate() {
            if t.is_ground || sim.objects[t.object_id as usize].dynamic {
                continue;
            }
            statics += 1;
            if error(i, end) >= 0.5 {
                let by = if owners[i] >= 0 { format!("body {}", owners[i]) } else { "network".to_string() };
                *off.entry(format!("{by} ({:?})", sim.objects[t.object_id as usize].kind)).or_default() += 1;
            }
        }
        let total_off: usize = off.values().sum();
        println!("  static non-ground frame-0 points ending >= 0.5 m off: {total_off} of {statics} {off:?}");
    }
    Ok(())
}
