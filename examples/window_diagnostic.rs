//! Where a stitched (windowed) model loses its moving points along a long log.
//!
//! Loads a model kept by `mbnt eval --models DIR` for a simulated seed and, for points of frame
//! `FROM` (not ground, within the evaluation range), prints per moving object of the simulator
//! the share of its points within 0.5 m of the exact position at every frame from `FROM` to
//! `FROM + SPAN`, and which window owns each frame, so that a loss at a hand-over shows:
//!
//! ```text
//! cargo run --release --example window_diagnostic -- SEED FRAMES MODEL_FILE FROM [SPAN]
//! ```

use mbnt::model::FittedModel;
use mbnt::sim::{SimParams, simulate};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 5 {
        anyhow::bail!("usage: window_diagnostic SEED FRAMES MODEL_FILE FROM [SPAN]");
    }
    let seed: u64 = args[1].parse()?;
    let frames: usize = args[2].parse()?;
    let model = FittedModel::from_bytes(&std::fs::read(&args[3])?).map_err(anyhow::Error::msg)?;
    let from: usize = args[4].parse()?;
    let span: usize = args.get(5).map_or(Ok(24), |s| s.parse())?;
    let sim = simulate(&SimParams::log(seed, frames))?;
    let ts = &sim.timestamps_s;
    let to = (from + span).min(frames - 1);
    let starts = model.window_starts();
    println!("windows from {starts:?}; bodies (objects) {}", model.bodies().len());
    for (start, window) in model.windows()? {
        let seen: Vec<String> = window
            .bodies()
            .iter()
            .map(|b| {
                let f = b.frames_seen();
                format!(
                    "{}:{}-{}",
                    b.id,
                    start + f.first().copied().unwrap_or(0),
                    start + f.last().copied().unwrap_or(0)
                )
            })
            .collect();
        println!("  window from {start}: bodies (id: frames seen) {}", seen.join(" "));
    }
    println!("  object ids per window: {:?}", model.window_object_ids());
    for (w, shares) in model.window_link_shares()?.iter().enumerate() {
        let listed: Vec<String> =
            shares.iter().filter(|s| s.2 > 0.02).map(|(a, b, s)| format!("{a}-{b}:{:.2}", s)).collect();
        println!("  windows {w}-{}: shared members {}", w + 1, listed.join(" "));
    }
    let frame = &sim.frames[from];
    let truth = &sim.truth[from];
    let ids = &model.object_ids(&sim.frames)?[from];
    // Moving objects with at least 30 points in frame `from` (not ground).
    let mut objects: Vec<(u32, Vec<usize>)> = Vec::new();
    for (i, t) in truth.iter().enumerate() {
        if t.is_ground || !sim.objects[t.object_id as usize].dynamic {
            continue;
        }
        match objects.iter_mut().find(|(o, _)| *o == t.object_id) {
            Some((_, members)) => members.push(i),
            None => objects.push((t.object_id, vec![i])),
        }
    }
    objects.retain(|(_, m)| m.len() >= 30);
    let targets: Vec<usize> = (from + 1..=to).collect();
    let times: Vec<f64> = targets.iter().map(|&j| ts[j]).collect();
    let predicted = model.positions(frame, ts[from], &times)?;
    let exact: Vec<Vec<[f32; 3]>> = targets.iter().map(|&j| sim.positions_at(from, j)).collect::<Result<_, _>>()?;
    for (object, members) in &objects {
        let labels: std::collections::BTreeMap<i32, usize> = members.iter().fold(Default::default(), |mut m, &i| {
            *m.entry(ids[i]).or_default() += 1;
            m
        });
        println!("object {object}: {} points, labelled {labels:?}", members.len());
        let mut line = String::new();
        for (n, &j) in targets.iter().enumerate() {
            let (mut within, mut sum_m) = (0usize, 0f64);
            for &i in members {
                let p = predicted[i * targets.len() + n];
                let d = (0..3).map(|c| f64::from(p[c] - exact[n][i][c]).powi(2)).sum::<f64>().sqrt();
                sum_m += d;
                within += usize::from(d < 0.5);
            }
            line += &format!(
                " {j}:{:.0}%/{:.2}m",
                100.0 * within as f64 / members.len() as f64,
                sum_m / members.len() as f64
            );
        }
        println!("  {line}");
        let seen: Vec<String> = (from..=to)
            .map(|k| {
                let n = sim.truth[k].iter().filter(|t| t.object_id == *object && !t.is_ground).count();
                format!("{k}:{n}")
            })
            .collect();
        println!("  points per frame: {}", seen.join(" "));
    }
    // Still points (not ground) that end 0.5 m or more off at `to`, by the model's label at
    // `from` and the simulator's object.
    let n = targets.len();
    let exact = &exact[n - 1];
    let mut off: std::collections::BTreeMap<(i32, u32), (usize, f64)> = Default::default();
    let mut still = 0usize;
    for (i, t) in truth.iter().enumerate() {
        if t.is_ground || sim.objects[t.object_id as usize].dynamic {
            continue;
        }
        still += 1;
        let p = predicted[i * n + n - 1];
        let d = (0..3).map(|c| f64::from(p[c] - exact[i][c]).powi(2)).sum::<f64>().sqrt();
        if d >= 0.5 {
            let e = off.entry((ids[i], t.object_id)).or_default();
            e.0 += 1;
            e.1 += d;
        }
    }
    let total: usize = off.values().map(|v| v.0).sum();
    println!("still points of frame {from} 0.5 m or more off at {to}: {total} of {still}");
    for ((label, object), (count, sum)) in off {
        println!("  label {label}, sim object {object}: {count} points, mean {:.2} m", sum / count as f64);
    }
    Ok(())
}
