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
use crate::sim::{Behaviour, ObjectKind, SimParams, SimSequence, simulate};

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
    /// Skip the `rigid-frame` baseline (chained whole-frame ICP, the slowest baseline).
    #[arg(long)]
    pub no_rigid_frame: bool,
    /// Hyper-parameters as JSON, applied to every method (e.g. '{"iterations": 300}').
    #[arg(long)]
    pub params: Option<String>,
    /// Write the machine-readable results here (JSON).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Score a real pair with ground-truth flow instead (an `.npz` in ICP-Flow's demo layout, or
    /// a directory holding one): dynamic and static points, beside zero flow and the file's own
    /// estimate. See `cli::real_pair`.
    #[arg(long, value_name = "DIR_OR_NPZ", conflicts_with_all = ["dir", "seeds", "frames"])]
    pub real_pair: Option<PathBuf>,
    /// Also score trajectories of this many frames starting every `--span-every` frames of each
    /// simulated sequence (frame s to s + N; 0 = off): how a long log does along its length
    /// (issue 21 scores 24-frame spans from frames 0, 25, 50, 75).
    #[arg(long, default_value_t = 0, conflicts_with = "dir")]
    pub span_frames: usize,
    /// First frames of the spans of `--span-frames`: 0, this, twice this, ...
    #[arg(long, default_value_t = 25, value_parser = clap::value_parser!(u64).range(1..))]
    pub span_every: u64,
    /// Score frames `FIRST` to `FIRST + frames - 1` of a simulated sequence of `--log-frames`
    /// frames, as a job of their own: a window of a long log fitted alone, for comparison with
    /// the log's windowed fit (issue 21).
    #[arg(long, value_name = "FIRST", default_value_t = 0, conflicts_with = "dir")]
    pub first_frame: usize,
    /// Frames of the simulated sequence `--first-frame` takes its frames from (default: just
    /// enough). The simulator places its scene for the whole sequence, so a log's window is
    /// scored on the log's own frames only when this is the log's length.
    #[arg(long, value_name = "FRAMES", conflicts_with = "dir")]
    pub log_frames: Option<usize>,
    /// Keep each fitted model in this directory and score a model found there instead of
    /// fitting it again (one file per sequence, method, frames and parameters): re-scoring a
    /// fit after a change to how models answer takes seconds instead of a fit.
    #[arg(long, value_name = "DIR")]
    pub models: Option<PathBuf>,
}

/// Long-term metrics of one span of frames (`--span-frames`).
#[derive(Debug, Clone, Serialize)]
pub struct SpanResult {
    /// The span's first frame: its evaluated points are the ones scored.
    pub start: usize,
    /// Its last frame.
    pub end: usize,
    /// Evaluated points of frame `start`, from there to frame `end`.
    pub long_term: TrajectoryMetrics,
    /// The same, static points only.
    pub long_term_static: TrajectoryMetrics,
    /// The same, dynamic points only.
    pub long_term_dynamic: TrajectoryMetrics,
}

/// The ground truth of one span (`--span-frames`).
pub struct SpanTruth {
    /// First frame.
    pub start: usize,
    /// Last frame.
    pub end: usize,
    /// True positions of frame `start`'s points at frame `end`.
    pub end_positions: Vec<Point>,
    /// Dynamic flags of frame `start`'s points.
    pub dynamic: Vec<bool>,
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
    /// Optimiser iterations the fit ran (0 for baselines; early stopping may end a fit sooner).
    pub iterations: usize,
    /// Iteration of the checkpoint the fit kept (trajectory methods).
    pub best_iteration: Option<usize>,
    /// Every moving body on its own (empty when the ground truth has no object ids).
    pub moving_objects: Vec<ObjectResult>,
    /// Per span of `--span-frames` (fitted methods only; empty otherwise).
    pub spans: Vec<SpanResult>,
}

/// Metrics of one moving body of the ground truth. Motions are taken relative to the static
/// world (the poses' motion of a still point is subtracted from prediction and truth) when the
/// poses are known, so that a body held still scores 0 % captured, a perfectly tracked one 100 %.
#[derive(Debug, Clone, Serialize)]
pub struct ObjectResult {
    /// Object id of the ground truth (the simulator's body index).
    pub object_id: u32,
    /// What the body is, e.g. `moving car, turning` (`object N` when the ground truth does not say).
    pub label: String,
    /// Its evaluated frame-0 points, frame 0 to frame T-1.
    pub long_term: TrajectoryMetrics,
    /// Share of its true frame 0 -> T-1 displacement the prediction reproduces:
    /// sum(pred . truth) / sum(|truth|^2) over its points, displacements relative to the static world.
    pub long_term_captured: f64,
    /// Mean true displacement of its frame-0 points from frame 0 to frame T-1, relative to the static world (m).
    pub long_term_true_m: f64,
    /// Scene-flow end-point error, mean over all its evaluated points of every pair (m).
    pub scene_flow_epe_m: f64,
    /// Share of its true per-frame motion the predicted scene flow reproduces (as `long_term_captured`).
    pub scene_flow_captured: f64,
    /// Mean true motion of its points per frame, relative to the static world (m).
    pub scene_flow_true_m: f64,
    /// Its evaluated points summed over all pairs.
    pub scene_flow_points: usize,
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
    /// Object id of every point per frame, when the ground truth has them.
    pub object_ids: Option<Vec<Vec<u32>>>,
    /// Id and label of every moving body.
    pub moving_objects: Vec<(u32, String)>,
    /// Sensor-to-world poses (row-major 4 x 4), when known; fits use them unless
    /// `{"use_poses": false}` is passed in the parameters.
    pub poses: Option<Vec<[f64; 16]>>,
    /// Spans scored besides frame 0 to T-1 (`--span-frames`; simulated sequences only).
    pub spans: Vec<SpanTruth>,
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
            object_ids: Some(sim.truth.iter().map(|f| f.iter().map(|p| p.object_id).collect()).collect()),
            moving_objects: sim
                .objects
                .iter()
                .filter(|o| o.dynamic)
                .map(|o| (o.id, object_label(o.kind, o.behaviour)))
                .collect(),
            poses: Some(sim.ego_poses.clone()),
            spans: Vec::new(),
        })
    }

    /// Adds the truth of spans of `frames` frames starting at 0, `every`, 2 `every`, ... as far
    /// as the sequence reaches.
    pub fn with_spans(mut self, sim: &SimSequence, frames: usize, every: usize) -> anyhow::Result<Self> {
        let t = sim.frames.len();
        for start in (0..t).step_by(every.max(1)).take_while(|s| s + frames < t) {
            self.spans.push(SpanTruth {
                start,
                end: start + frames,
                end_positions: sim.positions_at(start, start + frames)?,
                dynamic: sim.is_dynamic(start)?,
            });
        }
        Ok(self)
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
        let mut object_ids = Some(Vec::new());
        let mut moving = std::collections::BTreeSet::new();
        for k in 0..t {
            if k + 1 < t {
                flows.push(points(array(&format!("flow_{k:03}"))?)?);
            }
            is_ground.push(as_bool(array(&format!("is_ground_{k:03}"))?).context("is_ground must be bool")?);
            // Object ids came later than the other arrays: directories without them still evaluate.
            let ids = array(&format!("object_id_{k:03}")).ok().and_then(as_u32);
            match (ids, object_ids.as_mut()) {
                (Some(ids), Some(all)) => {
                    let dynamic = as_bool(array(&format!("is_dynamic_{k:03}"))?).context("is_dynamic must be bool")?;
                    anyhow::ensure!(
                        ids.len() == dynamic.len(),
                        "object_id_{k:03} and is_dynamic_{k:03} differ in length"
                    );
                    moving.extend(ids.iter().zip(&dynamic).filter(|(_, d)| **d).map(|(id, _)| *id));
                    all.push(ids);
                }
                _ => object_ids = None,
            }
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
            moving_objects: if object_ids.is_some() {
                moving.into_iter().map(|id| (id, format!("object {id}"))).collect()
            } else {
                Vec::new()
            },
            object_ids,
            poses,
            spans: Vec::new(),
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

fn as_u32(a: NpyArray) -> Option<Vec<u32>> {
    match a.data {
        NpyData::I32(v) => v.into_iter().map(|x| u32::try_from(x).ok()).collect(),
        _ => None,
    }
}

/// `moving car, turning`, `pedestrian, walking`: what a body is, for the per-object tables.
fn object_label(kind: ObjectKind, behaviour: Behaviour) -> String {
    let kind = match kind {
        ObjectKind::Ground => "ground",
        ObjectKind::Building => "building",
        ObjectKind::Pole => "pole",
        ObjectKind::Tree => "tree",
        ObjectKind::ParkedCar => "parked car",
        ObjectKind::MovingCar => "moving car",
        ObjectKind::Pedestrian => "pedestrian",
    };
    let behaviour = match behaviour {
        Behaviour::Static => "static",
        Behaviour::SameDirection => "same direction",
        Behaviour::Oncoming => "oncoming",
        Behaviour::Crossing => "crossing",
        Behaviour::Turning => "turning",
        Behaviour::Walking => "walking",
    };
    format!("{kind}, {behaviour}")
}

fn as_bool(a: NpyArray) -> Option<Vec<bool>> {
    match a.data {
        NpyData::Bool(v) => Some(v),
        NpyData::U8(v) => Some(v.into_iter().map(|x| x != 0).collect()),
        _ => None,
    }
}

/// Predicted scene flows (per pair) and end positions of frame 0's points at frame T-1; the fit
/// fields stay 0 / `None` for baselines.
#[derive(Default)]
struct Prediction {
    flows: Vec<Vec<Point>>,
    end_positions: Vec<Point>,
    fit_seconds: f64,
    iterations: usize,
    best_iteration: Option<usize>,
    /// Per span of the sequence (`Labelled::spans`): frame start's points at frame end; empty for
    /// baselines.
    spans: Vec<Vec<Point>>,
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

/// Scores `pred`; `still` is the static world seen through the poses (the `ego-poses`
/// prediction), against which the moving bodies' motions are measured.
fn score(
    name: &str,
    seq: &Labelled,
    evaluated: &[Vec<bool>],
    pred: &Prediction,
    still: Option<&Prediction>,
) -> MethodResult {
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
        iterations: pred.iterations,
        best_iteration: pred.best_iteration,
        moving_objects: score_objects(seq, evaluated, pred, still),
        spans: if pred.spans.len() == seq.spans.len() {
            seq.spans
                .iter()
                .zip(&pred.spans)
                .map(|(span, predicted)| {
                    let select = |want_dynamic: Option<bool>| -> Vec<bool> {
                        (0..span.end_positions.len())
                            .map(|i| evaluated[span.start][i] && want_dynamic.is_none_or(|d| span.dynamic[i] == d))
                            .collect()
                    };
                    let metrics =
                        |want_dynamic| trajectory_metrics(predicted, &span.end_positions, Some(&select(want_dynamic)));
                    SpanResult {
                        start: span.start,
                        end: span.end,
                        long_term: metrics(None),
                        long_term_static: metrics(Some(false)),
                        long_term_dynamic: metrics(Some(true)),
                    }
                })
                .collect()
        } else {
            Vec::new()
        },
    }
}

/// Sums for the share of a true motion that a prediction captures.
#[derive(Default)]
struct Captured {
    dot: f64,
    true_sq: f64,
    true_norm: f64,
    err: f64,
    points: usize,
}

impl Captured {
    /// Adds one point: predicted and true displacement, and the still world's displacement of it.
    fn add(&mut self, pred: &Point, truth: &Point, still: &Point) {
        let rel = |v: &Point| [0, 1, 2].map(|c| f64::from(v[c]) - f64::from(still[c]));
        let (p, g) = (rel(pred), rel(truth));
        self.dot += p[0] * g[0] + p[1] * g[1] + p[2] * g[2];
        let g_sq = g[0] * g[0] + g[1] * g[1] + g[2] * g[2];
        self.true_sq += g_sq;
        self.true_norm += g_sq.sqrt();
        self.err += ((p[0] - g[0]).powi(2) + (p[1] - g[1]).powi(2) + (p[2] - g[2]).powi(2)).sqrt();
        self.points += 1;
    }

    fn share(&self) -> f64 {
        if self.true_sq > 0.0 { self.dot / self.true_sq } else { 0.0 }
    }

    fn mean(&self, sum: f64) -> f64 {
        if self.points > 0 { sum / self.points as f64 } else { 0.0 }
    }
}

fn score_objects(
    seq: &Labelled,
    evaluated: &[Vec<bool>],
    pred: &Prediction,
    still: Option<&Prediction>,
) -> Vec<ObjectResult> {
    let Some(ids) = &seq.object_ids else { return Vec::new() };
    // One pass over every evaluated point, summing per moving body.
    let slot: std::collections::HashMap<u32, usize> =
        seq.moving_objects.iter().enumerate().map(|(s, (id, _))| (*id, s)).collect();
    let n_objects = seq.moving_objects.len();
    let zero = [0.0f32; 3];
    let mut flow: Vec<Captured> = (0..n_objects).map(|_| Captured::default()).collect();
    for k in 0..seq.frames.len() - 1 {
        for (i, id) in ids[k].iter().enumerate().filter(|(i, _)| evaluated[k][*i]) {
            if let Some(&s) = slot.get(id) {
                let still_flow = still.map_or(&zero, |w| &w.flows[k][i]);
                flow[s].add(&pred.flows[k][i], &seq.flows[k][i], still_flow);
            }
        }
    }
    let start = &seq.frames[0];
    let displacement = |a: &Point, b: &Point| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let mut end: Vec<Captured> = (0..n_objects).map(|_| Captured::default()).collect();
    let mut masks = vec![vec![false; start.len()]; n_objects];
    for (i, id) in ids[0].iter().enumerate().filter(|(i, _)| evaluated[0][*i]) {
        if let Some(&s) = slot.get(id) {
            masks[s][i] = true;
            let still_d = still.map_or(zero, |w| displacement(&w.end_positions[i], &start[i]));
            end[s].add(
                &displacement(&pred.end_positions[i], &start[i]),
                &displacement(&seq.end_positions[i], &start[i]),
                &still_d,
            );
        }
    }
    seq.moving_objects
        .iter()
        .zip(flow.iter().zip(&end).zip(&masks))
        .filter(|(_, ((flow, end), _))| flow.points > 0 || end.points > 0)
        .map(|((id, label), ((flow, end), mask))| ObjectResult {
            object_id: *id,
            label: label.clone(),
            long_term: trajectory_metrics(&pred.end_positions, &seq.end_positions, Some(mask)),
            long_term_captured: end.share(),
            long_term_true_m: end.mean(end.true_norm),
            scene_flow_epe_m: flow.mean(flow.err),
            scene_flow_captured: flow.share(),
            scene_flow_true_m: flow.mean(flow.true_norm),
            scene_flow_points: flow.points,
        })
        .collect()
}

fn zero_motion(sim: &Labelled) -> Prediction {
    Prediction {
        flows: sim.frames[..sim.frames.len() - 1].iter().map(|f| vec![[0.0; 3]; f.len()]).collect(),
        end_positions: sim.frames[0].clone(),
        fit_seconds: 0.0,
        ..Default::default()
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
    Prediction { flows, end_positions, fit_seconds: started.elapsed().as_secs_f64(), ..Default::default() }
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
    Ok(Some(Prediction { flows, end_positions, fit_seconds: 0.0, ..Default::default() }))
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

/// Fits `method` and predicts with the model; with rigid tracks or moving bodies also the same
/// fit's network alone (the second prediction), so both come from one fit.
/// Where `--models DIR` keeps the model of `method` fitted with `params` on `sim`: the file name
/// carries the sequence's name and frames, the method and a hash of the checked parameters.
fn model_path(dir: &Path, sim: &Labelled, method: Method, params: &ValidFitParams) -> anyhow::Result<PathBuf> {
    let json = serde_json::to_string(params)?;
    // FNV-1a: a stable name for the parameters (std's hasher may change between releases).
    let hash = json.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3));
    let name: String = sim.name.chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '-' }).collect();
    Ok(dir.join(format!("{name}-{}f-{}-{hash:016x}.mbnt", sim.frames.len(), method.name())))
}

fn run_method(
    sim: &Labelled,
    method: Method,
    params: &FitParams,
    models: Option<&Path>,
) -> anyhow::Result<(Prediction, Option<Prediction>)> {
    let params = params.check(method)?;
    let sequence =
        Sequence { frames: sim.frames.clone(), timestamps_s: Some(sim.timestamps_s.clone()), poses: sim.poses.clone() };
    let cached = models.map(|dir| model_path(dir, sim, method, &params)).transpose()?;
    let model = match &cached {
        Some(path) if path.exists() => {
            eprintln!("  {}: scoring the model kept in {}", method.name(), path.display());
            let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            crate::model::FittedModel::from_bytes(&bytes)
                .map_err(|e| anyhow::anyhow!("{} is not a model: {e}", path.display()))?
        }
        _ => {
            let model = fit_with_progress(&sequence, method, &params)?;
            if let Some(path) = &cached {
                std::fs::create_dir_all(path.parent().expect("a file in a directory"))?;
                std::fs::write(path, model.to_bytes()?).with_context(|| format!("writing {}", path.display()))?;
            }
            model
        }
    };
    score_model(sim, &sequence, method, &params, &model)
}

/// Fits `method`, printing its progress on stderr.
fn fit_with_progress(
    sequence: &Sequence,
    method: Method,
    params: &ValidFitParams,
) -> anyhow::Result<crate::model::FittedModel> {
    let mut last_print = std::time::Instant::now();
    let model = fit_sequence(sequence, method, params, &mut |p| {
        if let Some(v) = &p.validation_loss {
            eprintln!(
                "  {} validation at iteration {}: loss {:.5} = chamfer {:.5} + cycle {:.5} + rigidity {:.5}; \
                 fewest live units of a layer {}",
                method.name(),
                p.iteration - 1,
                v.total,
                v.chamfer,
                v.cycle,
                v.rigidity,
                p.fewest_live_units.map_or_else(|| "-".to_string(), |u| u.to_string()),
            );
        } else if last_print.elapsed().as_secs_f64() > 10.0 {
            last_print = std::time::Instant::now();
            let best = p.best_validation_loss.unwrap_or(f64::NAN);
            eprintln!(
                "  {} iteration {}/{} loss {:.5} (best validation {best:.5})",
                method.name(),
                p.iteration,
                p.iterations,
                p.loss.total
            );
        }
        ControlFlow::Continue(())
    })?;
    Ok(model)
}

/// The predictions of a fitted model (and of its network alone, when it has tracks or bodies).
fn score_model(
    sim: &Labelled,
    sequence: &Sequence,
    method: Method,
    params: &ValidFitParams,
    model: &crate::model::FittedModel,
) -> anyhow::Result<(Prediction, Option<Prediction>)> {
    let predict = |model: &crate::model::FittedModel| -> anyhow::Result<Prediction> {
        let flows = model.scene_flow(&sequence.frames)?;
        let ts = &sim.timestamps_s;
        let end_positions = model.positions(&sim.frames[0], ts[0], &[ts[ts.len() - 1]])?;
        let spans = sim
            .spans
            .iter()
            .map(|span| model.positions(&sim.frames[span.start], ts[span.start], &[ts[span.end]]))
            .collect::<Result<_, _>>()?;
        let report = model.report();
        Ok(Prediction {
            flows,
            end_positions,
            fit_seconds: report.fit_seconds,
            iterations: report.iterations,
            best_iteration: report.best_iteration,
            spans,
        })
    };
    let network_alone = if params.rigid_tracks || params.moving_bodies {
        eprintln!(
            "  {}: {} rigid tracks of moving clusters, {} moving bodies ({:.1} s)",
            method.name(),
            model.tracks().len(),
            model.bodies().len(),
            model.report().rigid_tracks_seconds
        );
        Some(predict(&model.without_tracks()?)?)
    } else {
        None
    };
    Ok((predict(model)?, network_alone))
}

/// Runs `mbnt eval` and prints a table (and JSON when asked).
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let params: FitParams = match &args.params {
        Some(json) => serde_json::from_str(json).context("--params is not a valid parameter object")?,
        None => FitParams::default(),
    };
    if let Some(path) = &args.real_pair {
        return super::real_pair::run(path, &args.methods, args.baselines_only, &params, args.json.as_ref());
    }
    let mut sequences = Vec::new();
    for dir in &args.dir {
        sequences.push(Labelled::from_dir(dir)?);
    }
    if args.dir.is_empty() {
        for &seed in &args.seeds {
            let whole = args.log_frames.unwrap_or(args.first_frame + args.frames);
            anyhow::ensure!(
                args.first_frame + args.frames <= whole,
                "--log-frames {whole} is shorter than --first-frame + --frames"
            );
            let mut sim = simulate(&SimParams::log(seed, whole))?;
            let mut name = format!("seed {seed}");
            if whole > args.frames {
                let range = args.first_frame..args.first_frame + args.frames;
                name = format!("seed {seed} frames {}-{} of {whole}", range.start, range.end - 1);
                sim = sim.frames_range(range)?;
            }
            let labelled = Labelled::from_sim(name, &sim)?;
            sequences.push(if args.span_frames > 0 {
                labelled.with_spans(&sim, args.span_frames, args.span_every as usize)?
            } else {
                labelled
            });
        }
    }
    let mut results = Vec::new();
    for seq in &sequences {
        eprintln!("{}: {} frames, {} points in frame 0", seq.name, seq.frames.len(), seq.frames[0].len());
        let evaluated = evaluated_points(seq, &params.check(Method::Ntp)?)?;
        let still = ego_poses_motion(seq)?;
        let still = still.as_ref();
        results.push(score("zero", seq, &evaluated, &zero_motion(seq), still));
        if !args.no_rigid_frame {
            results.push(score("rigid-frame", seq, &evaluated, &rigid_frame_motion(seq), still));
        }
        if let Some(pred) = still {
            results.push(score("ego-poses", seq, &evaluated, pred, still));
        }
        let methods: &[Method] = if args.baselines_only { &[] } else { &args.methods };
        for &method in methods {
            eprintln!("{}: fitting {}", seq.name, method.name());
            let (pred, network_alone) = run_method(seq, method, &params, args.models.as_deref())?;
            if let Some(alone) = network_alone {
                let name = format!("{} (same fit, without tracks)", method.name());
                results.push(score(&name, seq, &evaluated, &alone, still));
            }
            let result = score(method.name(), seq, &evaluated, &pred, still);
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
        "{:<12} {:>10} | {:>7} {:>7} {:>7} {:>7} {:>6} | {:>7} {:>6} {:>6} | {:>6} {:>6} {:>6} | {:>8} {:>11}",
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
        "fit s",
        "iter (best)"
    );
    for r in results {
        println!(
            "{:<12} {:>10} | {:>7.4} {:>7.2} {:>7.2} {:>7.2} {:>6.3} | {:>7.3} {:>6.2} {:>6.2} | {:>6.2} {:>6.2} {:>6.2} | {:>8.1} {:>11}",
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
            r.fit_seconds,
            match r.best_iteration {
                Some(best) => format!("{} ({best})", r.iterations),
                None if r.iterations > 0 => r.iterations.to_string(),
                None => "-".to_string(),
            }
        );
    }
    for r in results.iter().filter(|r| !r.spans.is_empty()) {
        println!("\nspans, {} on {} (frame start's points at frame end)", r.method, r.sequence);
        println!("{:>5} {:>5} | {:>7} {:>6} {:>6} {:>6}", "start", "end", "LT-EPE", "Acc.5", "St.5", "Dyn.5");
        for span in &r.spans {
            println!(
                "{:>5} {:>5} | {:>7.3} {:>6.2} {:>6.2} {:>6.2}",
                span.start,
                span.end,
                span.long_term.epe_m,
                100.0 * span.long_term.acc_0_5,
                100.0 * span.long_term_static.acc_0_5,
                100.0 * span.long_term_dynamic.acc_0_5
            );
        }
    }
    for r in results.iter().filter(|r| !BASELINES.contains(&r.method.as_str()) && !r.moving_objects.is_empty()) {
        println!(
            "\nmoving bodies, {} on {} (captured: share of the true motion relative to the still world)",
            r.method, r.sequence
        );
        println!(
            "{:>4} {:<28} | {:>6} {:>7} {:>6} {:>7} {:>8} | {:>6} {:>7} {:>7} {:>8}",
            "id", "body", "pts 0", "LT-EPE", "Acc.5", "true m", "captured", "pts", "SF-EPE", "true m", "captured"
        );
        for o in &r.moving_objects {
            println!(
                "{:>4} {:<28} | {:>6} {:>7.3} {:>6.1} {:>7.2} {:>7.1}% | {:>6} {:>7.3} {:>7.3} {:>7.1}%",
                o.object_id,
                o.label,
                o.long_term.points,
                o.long_term.epe_m,
                100.0 * o.long_term.acc_0_5,
                o.long_term_true_m,
                100.0 * o.long_term_captured,
                o.scene_flow_points,
                o.scene_flow_epe_m,
                o.scene_flow_true_m,
                100.0 * o.scene_flow_captured
            );
        }
    }
}

/// The baselines' names (they get no per-object table).
const BASELINES: [&str; 3] = ["zero", "rigid-frame", "ego-poses"];

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
            None,
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
    fn a_kept_model_is_scored_again_without_a_fit_and_answers_the_same() {
        let sim = simulate(&SimParams { seed: 5, frames: 3, ..SimParams::default() }).unwrap();
        let seq = Labelled::from_sim("seed 5".into(), &sim).unwrap();
        let params: FitParams =
            serde_json::from_str(r#"{"iterations": 2, "hidden_width": 16, "hidden_layers": 2, "sample_points": 512}"#)
                .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let (fitted, _) = run_method(&seq, Method::Mbnt, &params, Some(dir.path())).unwrap();
        let kept: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(kept.len(), 1, "one model file");
        let (again, _) = run_method(&seq, Method::Mbnt, &params, Some(dir.path())).unwrap();
        assert_eq!(again.end_positions, fitted.end_positions);
        assert_eq!(again.flows, fitted.flows);
        // Other parameters are another model.
        let other = FitParams { iterations: Some(3), ..params.clone() }.check(Method::Mbnt).unwrap();
        let same = params.check(Method::Mbnt).unwrap();
        assert_ne!(
            model_path(dir.path(), &seq, Method::Mbnt, &other).unwrap(),
            model_path(dir.path(), &seq, Method::Mbnt, &same).unwrap()
        );
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

    #[test]
    fn spans_score_each_start_frame_against_its_own_truth() {
        let sim = simulate(&SimParams { seed: 5, frames: 10, ..SimParams::default() }).unwrap();
        let seq = Labelled::from_sim("seed 5".into(), &sim).unwrap().with_spans(&sim, 4, 3).unwrap();
        // Spans 0 -> 4 and 3 -> 7; 6 -> 10 would run past the last frame (9).
        let bounds: Vec<(usize, usize)> = seq.spans.iter().map(|s| (s.start, s.end)).collect();
        assert_eq!(bounds, vec![(0, 4), (3, 7)]);
        let evaluated = evaluated_points(&seq, &FitParams::default().check(Method::Mbnt).unwrap()).unwrap();
        let exact = Prediction { spans: seq.spans.iter().map(|s| s.end_positions.clone()).collect(), ..truth_of(&seq) };
        let result = score("truth", &seq, &evaluated, &exact, None);
        assert_eq!(result.spans.len(), 2);
        for span in &result.spans {
            assert!(span.long_term.points > 1000, "{span:?}");
            assert!(span.long_term.epe_m < 1e-6 && span.long_term.acc_0_5 == 1.0, "{span:?}");
        }
        // Points left where they were seen score as far off as the span's true motion.
        let still =
            Prediction { spans: seq.spans.iter().map(|s| sim.frames[s.start].clone()).collect(), ..truth_of(&seq) };
        let held = score("held", &seq, &evaluated, &still, None);
        assert!(held.spans.iter().all(|s| s.long_term.epe_m > 0.5), "{:?}", held.spans);
        // A baseline without span predictions has no span rows.
        assert!(score("zero", &seq, &evaluated, &zero_motion(&seq), None).spans.is_empty());
    }

    fn truth_of(seq: &Labelled) -> Prediction {
        Prediction {
            flows: seq.flows.clone(),
            end_positions: seq.end_positions.clone(),
            fit_seconds: 0.0,
            ..Default::default()
        }
    }

    #[test]
    fn per_object_scores_tell_a_tracked_body_from_one_held_still() {
        let sim = simulate(&SimParams { seed: 5, frames: 4, ..SimParams::default() }).unwrap();
        let seq = Labelled::from_sim("seed 5".into(), &sim).unwrap();
        let evaluated = evaluated_points(&seq, &FitParams::default().check(Method::Mbnt).unwrap()).unwrap();
        let still = ego_poses_motion(&seq).unwrap().unwrap();

        let exact = score("truth", &seq, &evaluated, &truth_of(&seq), Some(&still));
        assert!(exact.moving_objects.len() >= 2, "{:?}", exact.moving_objects);
        for o in &exact.moving_objects {
            assert!(sim.objects[o.object_id as usize].dynamic, "{o:?}");
            assert!(o.scene_flow_points > 0 && o.scene_flow_true_m > 0.05, "{o:?}");
            assert!(o.scene_flow_epe_m < 1e-5 && (o.scene_flow_captured - 1.0).abs() < 1e-4, "{o:?}");
            if o.long_term.points > 0 {
                assert!(o.long_term.epe_m < 1e-5 && (o.long_term_captured - 1.0).abs() < 1e-4, "{o:?}");
                assert!(o.long_term_true_m > 0.1, "{o:?}");
            }
        }

        // The poses alone hold every body still: nothing of its motion is captured, and the
        // error is the whole true motion.
        let held = score("ego-poses", &seq, &evaluated, &still, Some(&still));
        assert_eq!(held.moving_objects.len(), exact.moving_objects.len());
        for (o, e) in held.moving_objects.iter().zip(&exact.moving_objects) {
            assert!(o.scene_flow_captured.abs() < 1e-6, "{o:?}");
            assert!((o.scene_flow_epe_m - e.scene_flow_true_m).abs() < 1e-3, "{o:?} vs {e:?}");
            assert!((o.long_term.epe_m - e.long_term_true_m).abs() < 1e-3, "{o:?} vs {e:?}");
        }

        // Half the true motion (relative to the still world) is half captured.
        let half = Prediction {
            flows: (0..seq.flows.len())
                .map(|k| {
                    seq.flows[k]
                        .iter()
                        .zip(&still.flows[k])
                        .map(|(g, s)| [0, 1, 2].map(|c| 0.5 * (g[c] + s[c])))
                        .collect()
                })
                .collect(),
            end_positions: seq
                .end_positions
                .iter()
                .zip(&still.end_positions)
                .map(|(g, s)| [0, 1, 2].map(|c| 0.5 * (g[c] + s[c])))
                .collect(),
            fit_seconds: 0.0,
            ..Default::default()
        };
        for o in &score("half", &seq, &evaluated, &half, Some(&still)).moving_objects {
            assert!((o.scene_flow_captured - 0.5).abs() < 1e-3, "{o:?}");
            if o.long_term.points > 0 {
                assert!((o.long_term_captured - 0.5).abs() < 1e-3, "{o:?}");
            }
        }
    }

    #[test]
    fn a_directory_written_by_simulate_reads_back_as_the_same_ground_truth() {
        let sim = simulate(&SimParams { seed: 6, frames: 3, ..SimParams::default() }).unwrap();
        let dir = tempfile::tempdir().unwrap();
        crate::cli::simulate_cmd::write_sequence(&sim, dir.path(), "bin").unwrap();
        let read = Labelled::from_dir(dir.path()).unwrap();
        let direct = Labelled::from_sim("seed 6".into(), &sim).unwrap();
        assert_eq!(read.frames, direct.frames);
        assert_eq!(read.flows, direct.flows);
        assert_eq!(read.end_positions, direct.end_positions);
        assert_eq!(read.is_ground, direct.is_ground);
        assert_eq!(read.dynamic_0, direct.dynamic_0);
        assert_eq!(read.object_ids, direct.object_ids);
        let poses = read.poses.unwrap();
        for (a, b) in poses.iter().zip(direct.poses.as_ref().unwrap()) {
            assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-8));
        }
        // The directory knows the moving bodies that appear in its frames, not their kinds.
        let seen: Vec<u32> = direct
            .moving_objects
            .iter()
            .map(|(id, _)| *id)
            .filter(|id| direct.object_ids.as_ref().unwrap().iter().any(|f| f.contains(id)))
            .collect();
        assert!(!seen.is_empty());
        assert_eq!(read.moving_objects.iter().map(|(id, _)| *id).collect::<Vec<_>>(), seen);
    }
}
