//! Fitting a motion model to a sequence: the NTP/MBNT trajectory loop and the NSFP/MBNSF
//! pair-wise loop, their parameters, progress reporting and cancellation.
//!
//! The service and the CLI drive this through [`fit_sequence`], a plain blocking call that
//! reports progress through a callback which may also cancel between iterations.

pub mod bodies;
pub mod checkpoint;
pub mod nsfp;
pub mod ntp;
pub mod prepare;
mod rigidity;
pub mod tracks;
pub mod visibility;
pub mod windows;

pub use crate::model::params::{FitParams, FitParamsError, MAX_ITERATIONS, Method, Mode, OdometryMode, ValidFitParams};
pub use crate::model::{LossTerms, PhaseTimes};
pub use windows::WindowProgress;

use std::ops::ControlFlow;

use rayon::prelude::*;

use crate::geometry::Point;
use crate::geometry::knn::KdTree;
use crate::geometry::rigid::Rigid;
use crate::model::{FitReport, FittedModel, TimeAxis};
use crate::odometry::ReadOrOdometryError;

/// A sequence to fit: T frames of points, each in its own sensor frame, and its time axis.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Frame k's points (metric, sensor frame of sweep k). Every point is finite.
    pub frames: Vec<Vec<Point>>,
    /// Timestamps (s, strictly increasing), one per frame; `None` means frame indices.
    pub timestamps_s: Option<Vec<f64>>,
    /// Sensor-to-world poses, row-major 4 x 4, one per frame, when known.
    pub poses: Option<Vec<[f64; 16]>>,
}

impl Sequence {
    /// The time axis answers are expressed in (timestamps, or frame indices 0..T-1).
    pub fn time_axis(&self) -> TimeAxis {
        TimeAxis::new(self.timestamps_s.clone(), self.frames.len())
    }
}

/// A sequence whose frames are read when the fit needs them: a fit of a whole log reads one
/// window's frames at a time, so that it holds a window's frames, not the log's
/// ([`windows::fit_log`]). [`Sequence`] is the source whose frames are all in memory.
pub trait FrameSource {
    /// The sequence's frames.
    fn frame_count(&self) -> usize;
    /// Timestamps (s), one per frame, when known.
    fn timestamps_s(&self) -> Option<&[f64]>;
    /// Sensor-to-world poses (row-major 4 x 4), one per frame, when known.
    fn poses(&self) -> Option<&[[f64; 16]]>;
    /// Frames `range` (`range.end <= frame_count()`), in order, each in its own sensor frame.
    fn read_frames(&self, range: std::ops::Range<usize>) -> Result<Vec<Vec<Point>>, FitError>;
    /// The whole sequence, when its frames are all in memory already.
    fn in_memory(&self) -> Option<&Sequence> {
        None
    }
    /// Frame `frame` (`< frame_count()`) alone: [`FrameSource::read_frames`] of it, borrowed
    /// when the frames are in memory. The odometry reads a log this way, one frame at a time.
    fn read_frame(&self, frame: usize) -> Result<std::borrow::Cow<'_, [Point]>, FitError> {
        if let Some(sequence) = self.in_memory() {
            return Ok(std::borrow::Cow::Borrowed(&sequence.frames[frame]));
        }
        let mut read = self.read_frames(frame..frame + 1)?;
        match read.len() {
            1 => Ok(std::borrow::Cow::Owned(read.swap_remove(0))),
            n => Err(FitError::FrameRead(format!("frame {frame}: the source gave {n} frames for one"))),
        }
    }
    /// Frames `range` with their timestamps and poses, as a sequence of their own.
    fn part(&self, range: std::ops::Range<usize>) -> Result<Sequence, FitError> {
        Ok(Sequence {
            timestamps_s: self.timestamps_s().map(|ts| ts[range.clone()].to_vec()),
            poses: self.poses().map(|poses| poses[range.clone()].to_vec()),
            frames: self.read_frames(range)?,
        })
    }
}

impl FrameSource for Sequence {
    fn frame_count(&self) -> usize {
        self.frames.len()
    }

    fn timestamps_s(&self) -> Option<&[f64]> {
        self.timestamps_s.as_deref()
    }

    fn poses(&self) -> Option<&[[f64; 16]]> {
        self.poses.as_deref()
    }

    fn read_frames(&self, range: std::ops::Range<usize>) -> Result<Vec<Vec<Point>>, FitError> {
        Ok(self.frames[range].to_vec())
    }

    fn in_memory(&self) -> Option<&Sequence> {
        Some(self)
    }
}

/// What the fitting loop reports after each iteration.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Progress {
    /// Iterations completed so far (1-based once the first is done).
    pub iteration: usize,
    /// Total iterations planned (an upper bound when early stopping may end sooner).
    pub iterations: usize,
    /// The loss terms of the iteration just done.
    pub loss: LossTerms,
    /// Best validation loss so far, if a validation pass has run.
    pub best_validation_loss: Option<f64>,
    /// The loss terms of this iteration's validation pass (mean over frames 0..T-2, before the
    /// update), when it was a validation iteration of a trajectory fit.
    pub validation_loss: Option<LossTerms>,
    /// On a validation iteration of a trajectory fit: the fewest live hidden units of any layer
    /// (units positive for at least one of frame 0's validation points). 0 means the network has
    /// collapsed to a constant function, which no further step can undo.
    pub fewest_live_units: Option<usize>,
    /// Set once the network is fitted and the rigid tracks (`rigid_tracks`) are being built; the
    /// iteration, loss and best-validation fields then repeat the last iteration's, and the
    /// validation-only fields (`validation_loss`, `fewest_live_units`) are `None`.
    pub rigid_tracks: Option<TrackingProgress>,
    /// Set when the sequence is fitted as windows (`window_frames`): the window the other
    /// fields are about, and how many are done. `None` for a fit of one window.
    #[serde(default)]
    pub window: Option<WindowProgress>,
}

/// How far the search for rigid tracks has come.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct TrackingProgress {
    /// Clusters tested so far.
    pub clusters_done: usize,
    /// Clusters to test (every DBSCAN cluster of every frame).
    pub clusters: usize,
}

/// Why a fit did not produce a model.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// The sequence cannot be fitted (too few frames, an empty frame, ...).
    #[error("invalid sequence: {0}")]
    InvalidSequence(String),
    /// The loss became non-finite.
    #[error("fit diverged at iteration {iteration} (loss {loss})")]
    Diverged {
        /// Iteration at which the loss stopped being finite.
        iteration: usize,
        /// The offending loss value.
        loss: f64,
    },
    /// The sequence's frames could not be read (a [`FrameSource`] reading them from a store).
    #[error("could not read the sequence's frames: {0}")]
    FrameRead(String),
    /// The progress callback asked to stop.
    #[error("cancelled at iteration {iteration}")]
    Cancelled {
        /// Iterations completed before the stop.
        iteration: usize,
    },
}

/// Fits `method` to `sequence` with `params`, calling `on_progress` after every iteration.
///
/// A sequence of more than `params.window_frames` frames is fitted as overlapping windows
/// ([`windows`]), each a fit of its frames by [`fit_single`], and stitched into one model; a
/// shorter one is one fit, as before windows existed.
///
/// Blocking and CPU-heavy (runs on the calling thread and the rayon pool): call it from a
/// worker thread, never from an async executor. Returning `ControlFlow::Break` from the
/// callback cancels the fit between iterations.
pub fn fit_sequence(
    sequence: &Sequence,
    method: Method,
    params: &ValidFitParams,
    on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
) -> Result<FittedModel, FitError> {
    windows::fit_log(sequence, method, params, &mut windows::NoFinishedWindows, on_progress)
}

/// One fit of every frame of `sequence` (a sequence of at most one window, or one window of a
/// log): [`fit_sequence`] without windows.
pub(crate) fn fit_single(
    sequence: &Sequence,
    method: Method,
    params: &ValidFitParams,
    checkpoints: &mut dyn checkpoint::Checkpoints,
    on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
) -> Result<FittedModel, FitError> {
    validate_sequence(sequence)?;
    let started = std::time::Instant::now();
    let FitCoordinates { frame_poses, estimated_poses } = fit_coordinates(sequence, params)?;
    let with_clusters = method.uses_rigidity() || params.rigid_tracks || params.moving_bodies;
    let (frames, frame_reports) =
        prepare::prepare_frames(sequence, params, with_clusters, true, frame_poses.as_deref())?;
    let mut report =
        FitReport { frames: frame_reports, params: Some(params.clone()), estimated_poses, ..FitReport::default() };
    // The last iteration's progress, repeated while the rigid tracks are built.
    let mut last = None::<Progress>;
    let mut losses = crate::model::LossCurve::default();
    let mut on_iteration = |p: &Progress| {
        losses.push(p.iteration, p.loss, p.validation_loss);
        last = Some(p.clone());
        on_progress(p)
    };
    let model = if method.is_trajectory() {
        let fit = ntp::fit_trajectory(&frames, params, method.uses_rigidity(), checkpoints, &mut on_iteration)?;
        // The fit's own curve: it holds the iterations before a checkpoint it went on from.
        report.losses = fit.losses.into_records();
        report.iterations = fit.iterations;
        report.best_iteration = Some(fit.best_iteration);
        report.best_validation_loss = Some(fit.best_validation_loss);
        report.phase_times = fit.times;
        report.fit_seconds = started.elapsed().as_secs_f64();
        FittedModel::trajectory(method, sequence.time_axis(), report, fit.mlp, frame_poses)
    } else {
        let fit = nsfp::fit_pairs(&frames, params, method.uses_rigidity(), &mut on_iteration)?;
        report.losses = losses.into_records();
        report.iterations = fit.iterations_per_pair.iter().sum();
        report.iterations_per_pair = fit.iterations_per_pair;
        report.fit_seconds = started.elapsed().as_secs_f64();
        FittedModel::pair_flows(method, sequence.time_axis(), report, fit.forward, fit.backward, frame_poses)
    };
    // The scene model's bodies need the ego motion removed: without poses every static cluster
    // would look like a moving one.
    let bodies = params.moving_bodies && model.frame_poses().is_some();
    if !params.rigid_tracks && !bodies {
        return Ok(model);
    }
    let tracking = std::time::Instant::now();
    let (points, trees, clusters) = search_inputs(&frames);
    let mut last = last.unwrap_or(Progress {
        iteration: 0,
        iterations: params.iterations,
        loss: LossTerms::default(),
        best_validation_loss: None,
        validation_loss: None,
        fewest_live_units: None,
        rigid_tracks: None,
        window: None,
    });
    // A validation happened once, at its iteration: not again on every tracking step.
    last.validation_loss = None;
    last.fewest_live_units = None;
    let iteration = last.iteration;
    let mut on_step = |clusters_done, clusters| {
        last.rigid_tracks = Some(TrackingProgress { clusters_done, clusters });
        on_progress(&last)
    };
    let axis = sequence.time_axis();
    let times = frame_times(&axis);
    let horizon = extrapolation_horizon(&axis);
    let mut model = if bodies {
        // What each sweep's rays saw, ground and far returns included: a body's registration
        // along its flank is checked against where the sensor looked through.
        let rays: Option<Vec<visibility::SweepRays>> = model.frame_poses().map(|poses| sweep_rays(sequence, poses));
        let (with_sparse, dense) = body_clusters(&points, &trees, &clusters, model.frame_poses(), params.dbscan_eps_m);
        let clusters: Vec<&[Vec<u32>]> = with_sparse.iter().map(Vec::as_slice).collect();
        let found = bodies::find_moving_bodies(
            &points,
            &trees,
            &clusters,
            &dense,
            rays.as_deref(),
            &times,
            horizon,
            &bodies::BodyParams::default(),
            &mut on_step,
        )
        .ok_or(FitError::Cancelled { iteration })?;
        let model = model.with_bodies(found);
        let free = network_free_points(&model, &points, &trees);
        model.with_free_points(free)
    } else {
        let tracks = tracks::track_moving_clusters(
            &points,
            &trees,
            &clusters,
            &times,
            horizon,
            &tracks::TrackParams::default(),
            &mut on_step,
        )
        .ok_or(FitError::Cancelled { iteration })?;
        model.with_tracks(tracks)
    };
    model.set_fit_seconds(started.elapsed().as_secs_f64(), tracking.elapsed().as_secs_f64());
    Ok(model)
}

/// `model` (a window of a log, fitted with its poses, frames `part`) with the bodies of
/// `priors` followed on through its frames where they are found ([`bodies::continue_bodies`]),
/// and its free points decided again with them. `model` is returned unchanged when no prior is
/// found or it has no poses (no bodies then).
pub(crate) fn continue_window_bodies(
    model: FittedModel,
    part: &Sequence,
    params: &ValidFitParams,
    priors: &[bodies::BodyPrior],
) -> Result<FittedModel, FitError> {
    let Some(poses) = model.frame_poses().map(<[Rigid]>::to_vec) else {
        return Ok(model);
    };
    // The same points, clusters and rays the window's own fit found its bodies in.
    let (frames, _) = prepare::prepare_frames(part, params, true, false, Some(&poses))?;
    let (points, trees, clusters) = search_inputs(&frames);
    let rays = sweep_rays(part, &poses);
    let axis = part.time_axis();
    let times = frame_times(&axis);
    let (with_sparse, dense) = body_clusters(&points, &trees, &clusters, Some(&poses), params.dbscan_eps_m);
    let clusters: Vec<&[Vec<u32>]> = with_sparse.iter().map(Vec::as_slice).collect();
    let found = bodies::continue_bodies(
        priors,
        model.bodies(),
        &points,
        &trees,
        &clusters,
        &dense,
        Some(&rays),
        &times,
        extrapolation_horizon(&axis),
        &bodies::BodyParams::default(),
    );
    if found.is_empty() {
        return Ok(model);
    }
    let mut all = model.bodies().to_vec();
    for mut body in found {
        body.id = all.len() as u32;
        all.push(body);
    }
    let model = model.with_bodies(all);
    let free = network_free_points(&model, &points, &trees);
    Ok(model.with_free_points(free))
}

/// Per frame: its points, their tree and their clusters (indices into the points).
type SearchInputs<'a> = (Vec<&'a [Point]>, Vec<&'a KdTree>, Vec<&'a [Vec<u32>]>);

/// What the moving-body search reads of prepared frames: each frame's points, tree and clusters.
fn search_inputs(frames: &[prepare::PreparedFrame]) -> SearchInputs<'_> {
    (
        frames.iter().map(|f| f.full.points.as_slice()).collect(),
        frames.iter().map(|f| &f.full.tree).collect(),
        frames.iter().map(|f| f.full.clusters.as_slice()).collect(),
    )
}

/// The clusters the moving-body search looks at, per frame: its DBSCAN clusters, then the sparse
/// clusters of the far points they leave out ([`bodies::sparse_clusters`]; only with `poses`,
/// which place the sensor), with the count of the DBSCAN ones.
type BodyClusters = (Vec<Vec<Vec<u32>>>, Vec<usize>);

/// See [`BodyClusters`].
fn body_clusters(
    points: &[&[Point]],
    trees: &[&KdTree],
    clusters: &[&[Vec<u32>]],
    poses: Option<&[Rigid]>,
    eps_m: f32,
) -> BodyClusters {
    let dense = clusters.iter().map(|c| c.len()).collect();
    let all = (0..points.len())
        .into_par_iter()
        .map(|k| {
            let mut all = clusters[k].to_vec();
            if let Some(sensor) = poses.map(|p| p[k].translation) {
                let sensor_xy = [sensor[0] as f32, sensor[1] as f32];
                all.extend(bodies::sparse_clusters(points[k], trees[k], clusters[k], sensor_xy, eps_m));
            }
            all
        })
        .collect();
    (all, dense)
}

/// What each sweep's rays saw (its raw points, ground and far returns included, with its pose).
fn sweep_rays(sequence: &Sequence, poses: &[Rigid]) -> Vec<visibility::SweepRays> {
    sequence.frames.par_iter().zip(poses).map(|(f, pose)| visibility::SweepRays::new(f, pose)).collect()
}

/// Each frame's time on `axis` (s, or the frame index).
fn frame_times(axis: &TimeAxis) -> Vec<f64> {
    (0..axis.frames()).map(|k| axis.frame_time(k)).collect()
}

pub use crate::model::MAX_EXTRAPOLATION_S;

/// [`MAX_EXTRAPOLATION_S`] in the units of `axis`'s times (s, or frame indices).
pub(crate) fn extrapolation_horizon(axis: &TimeAxis) -> f64 {
    axis.extrapolation_horizon()
}

/// A point on no body is *free* (the network answers it instead of the still world) when the
/// network's positions of it in the neighbouring frames lie this much closer (m, mean capped
/// nearest-neighbour distance) to those frames' points than its still position does...
const FREE_MIN_GAIN_M: f64 = 0.1;
/// ...and at most this share of the still distance...
const FREE_MAX_SHARE: f64 = 0.5;
/// ...and the network moves it by at least this much per frame along the ground (m; 0.8 m/s at 10 Hz, slower
/// than a walk): a network that slid the still world (0.5-1 m over 25 frames, docs/benchmarks.md
/// section 11) moves it by 0.02-0.04 m per frame, and some of those slid points happen to land
/// nearer the sparse neighbouring sweeps.
const FREE_MIN_MOTION_M: f64 = 0.08;
/// A point the network moves by at least this much per frame along the ground (m; 3 m/s at 10 Hz, ten times the
/// static slide of section 3) is free too when its network positions are no farther from the
/// neighbouring sweeps than its still position: a car moving along its own length keeps part of
/// its still position on its own next sweep (the aperture problem), so the gain test alone misses
/// it, and in a pair the bodies (which need four frames) cannot carry it.
const FREE_MIN_TRAVEL_M: f64 = 0.3;
/// Frames on each side compared by the free-point test.
const FREE_FRAMES_EACH_SIDE: usize = 2;
/// Still points within this distance (m) of a free point are kept beside it, so that a query
/// takes the kind of its nearest fitted point.
const FREE_GUARD_M: f32 = 0.5;

/// The network's part of a scene model (fit coordinates, frames with poses): per frame, the
/// points on no body whose motion the network explains clearly better than the still world
/// (`true`) and the still points around them (`false`). Non-rigid and unclustered motion the
/// bodies miss is what the network is left to answer; everything else follows the poses exactly.
fn network_free_points(model: &FittedModel, frames: &[&[Point]], trees: &[&KdTree]) -> Vec<Vec<(Point, bool)>> {
    use rayon::prelude::*;
    let t = frames.len();
    let cap_m = 1.0f64;
    (0..t)
        .into_par_iter()
        .map(|k| {
            let points = frames[k];
            let owners = model.body_members(points, k as f64);
            let near: Vec<usize> = (k.saturating_sub(FREE_FRAMES_EACH_SIDE)..(k + FREE_FRAMES_EACH_SIDE + 1).min(t))
                .filter(|&j| j != k)
                .collect();
            let u_times: Vec<f64> = near.iter().map(|&j| j as f64).collect();
            let moved = model.network_positions(points, k as f64, &u_times);
            let distance =
                |j: usize, p: &Point| trees[j].nearest(p).map_or(cap_m, |h| f64::from(h.dist2).sqrt().min(cap_m));
            let free: Vec<bool> = (0..points.len())
                .map(|i| {
                    if owners[i].is_some() {
                        return false;
                    }
                    let (mut still, mut net) = (0.0, 0.0);
                    for (n, &j) in near.iter().enumerate() {
                        still += distance(j, &points[i]);
                        net += distance(j, &moved[i * near.len() + n]);
                    }
                    let count = near.len().max(1) as f64;
                    let (still, net) = (still / count, net / count);
                    // Mean horizontal displacement per frame the network gives the point. Street
                    // things that move move along the ground; a network that lifts a wall's points
                    // by a ring spacing onto the next sweep's ring (0.4 m on the real pair,
                    // docs/benchmarks.md section 20) explains the sweeps better than the still
                    // world without anything having moved.
                    let travel: f64 = near
                        .iter()
                        .enumerate()
                        .map(|(n, &j)| {
                            let q = &moved[i * near.len() + n];
                            let d: f64 = (0..2).map(|c| f64::from(q[c] - points[i][c]).powi(2)).sum::<f64>().sqrt();
                            d / (j.abs_diff(k) as f64)
                        })
                        .sum::<f64>()
                        / count;
                    (travel >= FREE_MIN_MOTION_M && still - net >= FREE_MIN_GAIN_M && net <= FREE_MAX_SHARE * still)
                        || (travel >= FREE_MIN_TRAVEL_M && net <= still)
                })
                .collect();
            let free_set: Vec<Point> = (0..points.len()).filter(|&i| free[i]).map(|i| points[i]).collect();
            if free_set.is_empty() {
                return Vec::new();
            }
            let free_tree = KdTree::new(&free_set);
            let guard2 = FREE_GUARD_M * FREE_GUARD_M;
            (0..points.len())
                .filter(|&i| free[i] || free_tree.nearest(&points[i]).is_some_and(|h| h.dist2 <= guard2))
                .map(|i| (points[i], free[i]))
                .collect()
        })
        .collect()
}

/// The transforms from each frame's sensor coordinates to the coordinates the fit works in:
/// frame 0's, when the sequence has poses or `params.odometry` estimates them (and
/// `params.use_poses`); `None` (each frame in its own sensor coordinates) otherwise.
pub fn fit_frame_poses(sequence: &Sequence, params: &ValidFitParams) -> Result<Option<Vec<Rigid>>, FitError> {
    Ok(fit_coordinates(sequence, params)?.frame_poses)
}

/// The coordinates a fit works in, and where they came from.
#[derive(Debug, Clone, Default)]
pub struct FitCoordinates {
    /// Transforms from each frame's sensor coordinates to frame 0's; `None`: each frame in its
    /// own sensor coordinates.
    pub frame_poses: Option<Vec<Rigid>>,
    /// The odometry's sensor-to-world poses (row-major 4 x 4, frame 0 the identity), when it
    /// estimated them.
    pub estimated_poses: Option<Vec<[f64; 16]>>,
}

/// [`fit_frame_poses`], and the odometry's sensor-to-world poses (row-major 4 x 4, frame 0 the
/// identity) when it estimated them.
///
/// In `auto` mode a sequence the odometry cannot register (e.g. every point within its minimum
/// range) is fitted in sensor coordinates, as without odometry, with a warning; in `on` mode
/// that is an error.
///
/// Only the odometry reads the frames, one at a time and each once: with poses, none is read.
pub fn fit_coordinates(sequence: &dyn FrameSource, params: &ValidFitParams) -> Result<FitCoordinates, FitError> {
    if !params.use_poses {
        return Ok(FitCoordinates::default());
    }
    let estimate = match (params.odometry, sequence.poses()) {
        (OdometryMode::On, _) | (OdometryMode::Auto, None) => {
            let odometry_params = crate::odometry::OdometryParams::default();
            // One frame at a time: the odometry keeps only downsampled clouds, so a long log
            // read from a store need not be held in memory whole.
            match crate::odometry::estimate_poses_from(
                sequence.frame_count(),
                &mut |k| sequence.read_frame(k),
                sequence.timestamps_s(),
                &odometry_params,
                &mut |_, _| ControlFlow::Continue(()),
            ) {
                Ok(odometry) => Some(odometry.row_major()),
                // The log could not be read: not a sequence the odometry failed on.
                Err(ReadOrOdometryError::Read { error, .. }) => return Err(error),
                Err(ReadOrOdometryError::Odometry(e)) if params.odometry == OdometryMode::Auto => {
                    tracing::warn!("odometry failed ({e}); fitting each frame in its own sensor coordinates");
                    None
                }
                Err(ReadOrOdometryError::Odometry(e)) => {
                    return Err(FitError::InvalidSequence(format!("odometry: {e}")));
                }
            }
        }
        _ => None,
    };
    match estimate.as_deref().or(sequence.poses()) {
        Some(poses) => {
            Ok(FitCoordinates { frame_poses: Some(poses_relative_to_first(poses)?), estimated_poses: estimate })
        }
        None => Ok(FitCoordinates::default()),
    }
}

/// Converts sensor-to-world poses (row-major 4 x 4) into transforms from each frame's sensor
/// coordinates to frame 0's: the frame a pose-compensated fit works in.
pub fn poses_relative_to_first(poses: &[[f64; 16]]) -> Result<Vec<Rigid>, FitError> {
    let rigid = |k: usize, m: &[f64; 16]| -> Result<Rigid, FitError> {
        let bad = |why: &str| FitError::InvalidSequence(format!("pose {k} is not a rigid transform: {why}"));
        if m.iter().any(|v| !v.is_finite()) {
            return Err(bad("non-finite entry"));
        }
        if m[12].abs() > 1e-6 || m[13].abs() > 1e-6 || m[14].abs() > 1e-6 || (m[15] - 1.0).abs() > 1e-6 {
            return Err(bad("last row must be 0 0 0 1"));
        }
        let rotation = nalgebra::Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
        if (rotation * rotation.transpose() - nalgebra::Matrix3::identity()).abs().max() > 1e-3 {
            return Err(bad("rotation block is not orthonormal"));
        }
        if rotation.determinant() <= 0.0 {
            return Err(bad("rotation block is a reflection"));
        }
        Ok(Rigid::from_rotation(&nalgebra::Rotation3::from_matrix_unchecked(rotation), [m[3], m[7], m[11]]))
    };
    let world = poses.iter().enumerate().map(|(k, m)| rigid(k, m)).collect::<Result<Vec<_>, _>>()?;
    let to_first = world[0].inverse();
    Ok(world.iter().map(|w| to_first.compose(w)).collect())
}

/// Checks what every method needs: at least two frames, none empty, all points finite.
pub fn validate_sequence(sequence: &Sequence) -> Result<(), FitError> {
    validate_log(sequence)?;
    if let Some(k) = sequence.frames.iter().position(|f| f.is_empty()) {
        return Err(FitError::InvalidSequence(format!("frame {k} has no points")));
    }
    if let Some(k) = sequence.frames.iter().position(|f| f.iter().flatten().any(|c| !c.is_finite())) {
        return Err(FitError::InvalidSequence(format!("frame {k} has a non-finite coordinate")));
    }
    Ok(())
}

/// What [`validate_sequence`] checks without reading the frames: their count, the timestamps
/// and the poses (each window's fit checks its frames).
pub fn validate_log(sequence: &dyn FrameSource) -> Result<(), FitError> {
    let frames = sequence.frame_count();
    if frames < 2 {
        return Err(FitError::InvalidSequence(format!("needs at least 2 frames, got {frames}")));
    }
    if let Some(ts) = sequence.timestamps_s() {
        if ts.len() != frames {
            return Err(FitError::InvalidSequence(format!("{} timestamps for {frames} frames", ts.len())));
        }
        if ts.windows(2).any(|w| w[1] <= w[0]) || ts.iter().any(|t| !t.is_finite()) {
            return Err(FitError::InvalidSequence("timestamps must be finite and strictly increasing".into()));
        }
    }
    if let Some(poses) = sequence.poses() {
        if poses.len() != frames {
            return Err(FitError::InvalidSequence(format!("{} poses for {frames} frames", poses.len())));
        }
        poses_relative_to_first(poses)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests;
