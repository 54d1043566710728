//! `mbnt eval`: run methods on simulated sequences with exact ground truth and report
//! scene-flow and long-term trajectory metrics beside two baselines (zero motion, and the
//! best single rigid motion of the whole frame).

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;

use crate::fit::{FitParams, Method, Sequence, ValidFitParams, fit_sequence, poses_relative_to_first};
use crate::geometry::Point;
use crate::geometry::ground::{PreprocessParams, preprocess};
use crate::geometry::knn::KdTree;
use crate::geometry::rigid::{Rigid, fit_rigid_icp};
use crate::io::npy::{NpyArray, NpyData, read_npy};
use crate::io::read_points_file;
use crate::metrics::{SceneFlowMetrics, TrajectoryMetrics, average_over_pairs, scene_flow_metrics, trajectory_metrics};
use crate::sim::{SimParams, SimSequence, simulate};

/// Arguments of `mbnt eval`.
#[derive(Debug, clap::Args)]
pub struct EvalArgs {
    /// Simulator seeds, one sequence each (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub seeds: Vec<u64>,
    /// Directories written by `mbnt simulate` to evaluate instead of simulating (repeatable).
    #[arg(long)]
    pub dir: Vec<PathBuf>,
    /// Frames per simulated sequence.
    #[arg(long, default_value_t = 25)]
    pub frames: usize,
    /// Methods to run (comma-separated; the baselines always run).
    #[arg(long, value_delimiter = ',', default_value = "mbnt,ntp,mbnsf,nsfp")]
    pub methods: Vec<Method>,
    /// Run the baselines only (no fit).
    #[arg(long)]
    pub baselines_only: bool,
    /// Hyper-parameters as JSON, applied to every method (e.g. '{"iterations": 300}').
    #[arg(long)]
    pub params: Option<String>,
    /// Write the machine-readable results here (JSON).
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Metrics of one method on one sequence.
#[derive(Debug, Clone, Serialize)]
pub struct MethodResult {
    /// Method or baseline name.
    pub method: String,
    /// The sequence (simulator seed or directory).
    pub sequence: String,
    /// Scene flow, averaged over pairs (evaluated points: see [`evaluated_points`]).
    pub scene_flow: SceneFlowMetrics,
    /// Scene flow per pair k -> k+1.
    pub scene_flow_per_pair: Vec<SceneFlowMetrics>,
    /// Frame 0 to frame T-1, evaluated points.
    pub long_term: TrajectoryMetrics,
    /// The same, static points only.
    pub long_term_static: TrajectoryMetrics,
    /// The same, dynamic points only.
    pub long_term_dynamic: TrajectoryMetrics,
    /// Frame 0 to frame T-1 for the non-ground points outside the fit's range and height
    /// limits: the fit never saw them and answers by extrapolating the field.
    pub long_term_outside: TrajectoryMetrics,
    /// Wall time of the fit (s).
    pub fit_seconds: f64,
}

/// A sequence with the ground truth the metrics need, from the simulator or from a directory
/// written by `mbnt simulate`.
pub struct Labelled {
    /// Name shown in the results (seed or directory).
    pub name: String,
    /// Frames (sensor frame of each sweep).
    pub frames: Vec<Vec<Point>>,
    /// Timestamps (s).
    pub timestamps_s: Vec<f64>,
    /// True scene flow of frame k's points to frame k+1, k = 0..T-2.
    pub flows: Vec<Vec<Point>>,
    /// True positions of frame 0's points at frame T-1.
    pub end_positions: Vec<Point>,
    /// Ground flags per frame and point (ground is left out of every metric).
    pub is_ground: Vec<Vec<bool>>,
    /// Dynamic flags of frame 0's points.
    pub dynamic_0: Vec<bool>,
    /// Sensor-to-world poses (row-major 4 x 4), when known; fits use them unless
    /// `{"use_poses": false}` is passed in the parameters.
    pub poses: Option<Vec<[f64; 16]>>,
}

impl Labelled {
    /// Ground truth of a simulated sequence.
    pub fn from_sim(name: String, sim: &SimSequence) -> anyhow::Result<Self> {
        let t = sim.frames.len();
        Ok(Labelled {
            name,
            frames: sim.frames.clone(),
            timestamps_s: sim.timestamps_s.clone(),
            flows: (0..t - 1).map(|k| sim.scene_flow(k)).collect::<Result<_, _>>()?,
            end_positions: sim.positions_at(0, t - 1)?,
            is_ground: sim.truth.iter().map(|f| f.iter().map(|p| p.is_ground).collect()).collect(),
            dynamic_0: sim.is_dynamic(0)?,
            poses: Some(sim.ego_poses.clone()),
        })
    }

    /// Reads a directory written by `mbnt simulate` (frames/, timestamps.txt, ground_truth.npz).
    pub fn from_dir(dir: &Path) -> anyhow::Result<Self> {
        let frame_paths = super::fit_cmd::frame_paths(&[dir.join("frames")])?;
        let frames = frame_paths
            .iter()
            .map(|p| read_points_file(p).with_context(|| format!("reading {}", p.display())))
            .collect::<anyhow::Result<Vec<_>>>()?;
        let timestamps_s = super::fit_cmd::read_timestamps(&dir.join("timestamps.txt"))?;
        let path = dir.join("ground_truth.npz");
        let file = std::fs::File::open(&path).with_context(|| format!("opening {}", path.display()))?;
        let mut zip = zip::ZipArchive::new(std::io::BufReader::new(file))?;
        let mut array = |name: &str| -> anyhow::Result<NpyArray> {
            let mut entry =
                zip.by_name(&format!("{name}.npy")).with_context(|| format!("{name} missing in {}", path.display()))?;
            let mut bytes = Vec::new();
            std::io::Read::read_to_end(&mut entry, &mut bytes)?;
            read_npy(&bytes).with_context(|| format!("{name} in {}", path.display()))
        };
        let t = frames.len();
        let points = |a: NpyArray| -> anyhow::Result<Vec<Point>> {
            let v = as_f32(a).context("expected a float array")?;
            Ok(v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
        };
        let mut flows = Vec::new();
        let mut is_ground = Vec::new();
        for k in 0..t {
            if k + 1 < t {
                flows.push(points(array(&format!("flow_{k:03}"))?)?);
            }
            is_ground.push(as_bool(array(&format!("is_ground_{k:03}"))?).context("is_ground must be bool")?);
        }
        let traj = as_f32(array("traj_000")?).context("traj_000 must be float")?;
        let end_positions = traj
            .chunks_exact(3 * t)
            .map(|row| {
                let c = &row[3 * (t - 1)..];
                [c[0], c[1], c[2]]
            })
            .collect();
        let dynamic_0 = as_bool(array("is_dynamic_000")?).context("is_dynamic must be bool")?;
        let poses = match std::fs::read_to_string(dir.join("poses.txt")) {
            Ok(text) => Some(
                text.lines()
                    .filter(|l| !l.trim().is_empty())
                    .map(|l| {
                        let v: Vec<f64> = l.split_whitespace().map(str::parse).collect::<Result<_, _>>()?;
                        <[f64; 16]>::try_from(v).map_err(|_| anyhow::anyhow!("poses.txt: 16 numbers per line expected"))
                    })
                    .collect::<anyhow::Result<Vec<_>>>()?,
            ),
            Err(_) => None,
        };
        Ok(Labelled {
            name: dir.display().to_string(),
            frames,
            timestamps_s,
            flows,
            end_positions,
            is_ground,
            dynamic_0,
            poses,
        })
    }
}

fn as_f32(a: NpyArray) -> Option<Vec<f32>> {
    match a.data {
        NpyData::F32(v) => Some(v),
        NpyData::F64(v) => Some(v.into_iter().map(|x| x as f32).collect()),
        _ => None,
    }
}

fn as_bool(a: NpyArray) -> Option<Vec<bool>> {
    match a.data {
        NpyData::Bool(v) => Some(v),
        NpyData::U8(v) => Some(v.into_iter().map(|x| x != 0).collect()),
        _ => None,
    }
}

/// Predicted scene flows (per pair) and end positions of frame 0's points at frame T-1.
struct Prediction {
    flows: Vec<Vec<Point>>,
    end_positions: Vec<Point>,
    fit_seconds: f64,
}

/// The points every metric is computed on, per frame: not ground (by the ground truth) and
/// kept by the fit's own pre-processing (range, height over the local ground, ground
/// estimate), as in the research code's evaluation. The rest of the non-ground points are
/// scored separately ([`MethodResult::long_term_outside`]).
pub fn evaluated_points(seq: &Labelled, params: &ValidFitParams) -> anyhow::Result<Vec<Vec<bool>>> {
    seq.frames.iter().zip(&seq.is_ground).map(|(frame, ground)| evaluated_in_frame(frame, ground, params)).collect()
}

/// [`evaluated_points`] of one frame, given its ground-truth ground flags.
pub fn evaluated_in_frame(frame: &[Point], is_ground: &[bool], params: &ValidFitParams) -> anyhow::Result<Vec<bool>> {
    let pre = PreprocessParams {
        remove_ground: params.remove_ground,
        max_range_m: params.max_range_m,
        ..PreprocessParams::default()
    };
    let (kept, _) = preprocess(frame, &pre)?;
    let mut mask = vec![false; frame.len()];
    for i in kept {
        mask[i as usize] = !is_ground[i as usize];
    }
    Ok(mask)
}

fn score(name: &str, seq: &Labelled, evaluated: &[Vec<bool>], pred: &Prediction) -> MethodResult {
    let t = seq.frames.len();
    let per_pair: Vec<SceneFlowMetrics> =
        (0..t - 1).map(|k| scene_flow_metrics(&pred.flows[k], &seq.flows[k], Some(&evaluated[k]))).collect();
    let ground = &seq.is_ground[0];
    let inside = &evaluated[0];
    let select = |want_dynamic: Option<bool>| -> Vec<bool> {
        (0..seq.end_positions.len()).map(|i| inside[i] && want_dynamic.is_none_or(|d| seq.dynamic_0[i] == d)).collect()
    };
    let outside: Vec<bool> = (0..seq.end_positions.len()).map(|i| !ground[i] && !inside[i]).collect();
    let truth_end = &seq.end_positions;
    MethodResult {
        method: name.to_string(),
        sequence: seq.name.clone(),
        scene_flow: average_over_pairs(&per_pair),
        scene_flow_per_pair: per_pair,
        long_term: trajectory_metrics(&pred.end_positions, truth_end, Some(&select(None))),
        long_term_static: trajectory_metrics(&pred.end_positions, truth_end, Some(&select(Some(false)))),
        long_term_dynamic: trajectory_metrics(&pred.end_positions, truth_end, Some(&select(Some(true)))),
        long_term_outside: trajectory_metrics(&pred.end_positions, truth_end, Some(&outside)),
        fit_seconds: pred.fit_seconds,
    }
}

fn zero_motion(sim: &Labelled) -> Prediction {
    Prediction {
        flows: sim.frames[..sim.frames.len() - 1].iter().map(|f| vec![[0.0; 3]; f.len()]).collect(),
        end_positions: sim.frames[0].clone(),
        fit_seconds: 0.0,
    }
}

/// The best single rigid motion of each whole frame (ICP on non-ground points), chained over
/// the sequence: what an ego-motion-only estimate achieves.
fn rigid_frame_motion(sim: &Labelled) -> Prediction {
    let started = std::time::Instant::now();
    let non_ground = |k: usize| -> Vec<Point> {
        sim.frames[k].iter().zip(&sim.is_ground[k]).filter(|(_, g)| !**g).map(|(p, _)| *p).collect()
    };
    let t = sim.frames.len();
    let mut transforms = Vec::with_capacity(t - 1);
    for k in 0..t - 1 {
        let (src, dst) = (non_ground(k), non_ground(k + 1));
        let tree = KdTree::new(&dst);
        transforms.push(fit_rigid_icp(&src, &tree, &dst, Rigid::identity(), 30, 1.0));
    }
    let flows = flows_from(sim, |k, p| transforms[k].apply(p));
    let end_positions = sim.frames[0].iter().map(|p| transforms.iter().fold(*p, |q, tr| tr.apply(&q))).collect();
    Prediction { flows, end_positions, fit_seconds: started.elapsed().as_secs_f64() }
}

/// The static world seen through the sensor poses (when known): every point keeps its world
/// position. Exact for static points, blind to moving ones: what the poses alone give.
fn ego_poses_motion(sim: &Labelled) -> anyhow::Result<Option<Prediction>> {
    let Some(poses) = &sim.poses else { return Ok(None) };
    let to_first = poses_relative_to_first(poses)?;
    let from_first: Vec<Rigid> = to_first.iter().map(Rigid::inverse).collect();
    let moved = |k: usize, j: usize, p: &Point| from_first[j].apply(&to_first[k].apply(p));
    let t = sim.frames.len();
    let flows = flows_from(sim, |k, p| moved(k, k + 1, p));
    let end_positions = sim.frames[0].iter().map(|p| moved(0, t - 1, p)).collect();
    Ok(Some(Prediction { flows, end_positions, fit_seconds: 0.0 }))
}

/// Scene flows k -> k+1 of every frame's points, given where a point of frame k lands in k+1.
fn flows_from(sim: &Labelled, next_position: impl Fn(usize, &Point) -> Point) -> Vec<Vec<Point>> {
    (0..sim.frames.len() - 1)
        .map(|k| {
            sim.frames[k]
                .iter()
                .map(|p| {
                    let q = next_position(k, p);
                    [q[0] - p[0], q[1] - p[1], q[2] - p[2]]
                })
                .collect()
        })
        .collect()
}

fn run_method(sim: &Labelled, method: Method, params: &FitParams) -> anyhow::Result<Prediction> {
    let params = params.check(method)?;
    let sequence =
        Sequence { frames: sim.frames.clone(), timestamps_s: Some(sim.timestamps_s.clone()), poses: sim.poses.clone() };
    let mut last_print = std::time::Instant::now();
    let model = fit_sequence(&sequence, method, &params, &mut |p| {
        if last_print.elapsed().as_secs_f64() > 10.0 {
            last_print = std::time::Instant::now();
            eprintln!("  {} iteration {}/{} loss {:.5}", method.name(), p.iteration, p.iterations, p.loss.total);
        }
        ControlFlow::Continue(())
    })?;
    let flows = model.scene_flow(&sequence.frames);
    let ts = &sim.timestamps_s;
    let end_positions = model.positions(&sim.frames[0], ts[0], &[ts[ts.len() - 1]])?;
    Ok(Prediction { flows, end_positions, fit_seconds: model.report().fit_seconds })
}

/// Runs `mbnt eval` and prints a table (and JSON when asked).
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let params: FitParams = match &args.params {
        Some(json) => serde_json::from_str(json).context("--params is not a valid parameter object")?,
        None => FitParams::default(),
    };
    let mut sequences = Vec::new();
    for dir in &args.dir {
        sequences.push(Labelled::from_dir(dir)?);
    }
    if args.dir.is_empty() {
        for &seed in &args.seeds {
            let sim = simulate(&SimParams { seed, frames: args.frames, ..SimParams::default() })?;
            sequences.push(Labelled::from_sim(format!("seed {seed}"), &sim)?);
        }
    }
    let mut results = Vec::new();
    for seq in &sequences {
        eprintln!("{}: {} frames, {} points in frame 0", seq.name, seq.frames.len(), seq.frames[0].len());
        let evaluated = evaluated_points(seq, &params.check(Method::Ntp)?)?;
        results.push(score("zero", seq, &evaluated, &zero_motion(seq)));
        results.push(score("rigid-frame", seq, &evaluated, &rigid_frame_motion(seq)));
        if let Some(pred) = ego_poses_motion(seq)? {
            results.push(score("ego-poses", seq, &evaluated, &pred));
        }
        let methods: &[Method] = if args.baselines_only { &[] } else { &args.methods };
        for &method in methods {
            eprintln!("{}: fitting {}", seq.name, method.name());
            let pred = run_method(seq, method, &params)?;
            let result = score(method.name(), seq, &evaluated, &pred);
            eprintln!(
                "  {}: long-term EPE {:.3} m, Acc.5 {:.1} %, scene-flow EPE {:.3} m, fit {:.0} s",
                method.name(),
                result.long_term.epe_m,
                100.0 * result.long_term.acc_0_5,
                result.scene_flow.epe_m,
                result.fit_seconds
            );
            results.push(result);
        }
    }
    print_table(&results);
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_vec_pretty(&results)?)
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

fn print_table(results: &[MethodResult]) {
    println!(
        "{:<12} {:>10} | {:>7} {:>7} {:>7} {:>7} {:>6} | {:>7} {:>6} {:>6} | {:>6} {:>6} {:>6} | {:>8}",
        "method",
        "sequence",
        "EPE",
        "Acc.05",
        "Acc.10",
        "Outl.",
        "Angle",
        "LT-EPE",
        "Acc.5",
        "Acc1.0",
        "St.5",
        "Dyn.5",
        "Out.5",
        "fit s"
    );
    for r in results {
        println!(
            "{:<12} {:>10} | {:>7.4} {:>7.2} {:>7.2} {:>7.2} {:>6.3} | {:>7.3} {:>6.2} {:>6.2} | {:>6.2} {:>6.2} {:>6.2} | {:>8.1}",
            r.method,
            r.sequence,
            r.scene_flow.epe_m,
            100.0 * r.scene_flow.acc_strict,
            100.0 * r.scene_flow.acc_relaxed,
            100.0 * r.scene_flow.outliers,
            r.scene_flow.angle_rad,
            r.long_term.epe_m,
            100.0 * r.long_term.acc_0_5,
            100.0 * r.long_term.acc_1_0,
            100.0 * r.long_term_static.acc_0_5,
            100.0 * r.long_term_dynamic.acc_0_5,
            100.0 * r.long_term_outside.acc_0_5,
            r.fit_seconds
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ego_poses_baseline_is_exact_on_static_points_only() {
        let sim = simulate(&SimParams { seed: 5, frames: 4, ..SimParams::default() }).unwrap();
        let seq = Labelled::from_sim("seed 5".into(), &sim).unwrap();
        let params = FitParams::default().check(Method::Mbnt).unwrap();
        let result = score(
            "ego-poses",
            &seq,
            &evaluated_points(&seq, &params).unwrap(),
            &ego_poses_motion(&seq).unwrap().unwrap(),
        );
        assert!(result.long_term_static.epe_m < 1e-3, "{:?}", result.long_term_static);
        assert_eq!(result.long_term_static.acc_0_5, 1.0);
        assert!(
            result.long_term_dynamic.points > 0 && result.long_term_dynamic.epe_m > 0.5,
            "{:?}",
            result.long_term_dynamic
        );
        let without = Labelled { poses: None, ..seq };
        assert!(ego_poses_motion(&without).unwrap().is_none());
    }

    #[test]
    fn evaluated_points_are_the_non_ground_points_the_fit_keeps() {
        let sim = simulate(&SimParams { seed: 5, frames: 2, ..SimParams::default() }).unwrap();
        let seq = Labelled::from_sim("seed 5".into(), &sim).unwrap();
        let params = FitParams::default().check(Method::Mbnt).unwrap();
        let masks = evaluated_points(&seq, &params).unwrap();
        for (k, mask) in masks.iter().enumerate() {
            let frame = &seq.frames[k];
            assert_eq!(mask.len(), frame.len());
            let non_ground = seq.is_ground[k].iter().filter(|g| !**g).count();
            let inside = mask.iter().filter(|m| **m).count();
            // Most non-ground points are scored; the rest are beyond the range or height limits.
            assert!(inside > non_ground / 2 && inside < non_ground, "{inside} of {non_ground}");
            for (i, p) in frame.iter().enumerate() {
                let range_m = p.iter().map(|c| c * c).sum::<f32>().sqrt();
                assert!(!mask[i] || (!seq.is_ground[k][i] && range_m <= params.max_range_m), "point {i} of frame {k}");
            }
        }
    }
}
