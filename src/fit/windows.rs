//! Whole logs: a sequence longer than `window_frames` is fitted as overlapping windows, each an
//! ordinary fit of its frames ([`super::fit_single`]), stitched into one model
//! ([`FittedModel::stitched`], which describes how a stitched model answers).
//!
//! Why windows: one network over a whole log loses its start (issue 21: long-term Acc.5 0 % on
//! the first 24 frames of a 100-frame sequence, one network), while the method is tuned for
//! about 25 frames; and the cost of an iteration and the memory of a fit grow with the frames
//! one network covers.
//!
//! - The poses are settled once for the whole log (given, or one odometry run over every frame)
//!   and each window is fitted with its slice of them, so that every window works in the same
//!   world and a still point stays still across a hand-over. Without poses each window works in
//!   sensor coordinates, as the whole log would.
//! - Windows are fitted one after the other; each is a unit of work with its own progress
//!   ([`WindowProgress`]); only its frames are read from the [`FrameSource`] and prepared, and
//!   they are dropped once it is fitted (memory bounded by a window, not by the log; the
//!   odometry of a log without poses reads every frame once, before the windows). A cancel stops the window being fitted, as it stops any fit. Finished windows
//!   can be kept ([`FinishedWindows`]: the service keeps them in its store), so that a fit run
//!   again after a restart takes them instead of fitting them again; a window's fit depends
//!   only on its frames and the parameters (seeded), so a kept window is the one it would fit.
//! - Windows have `window_frames` frames each, as few as overlaps of at least
//!   `window_overlap_frames` allow, spread evenly from the first frame to the last (the overlaps
//!   differ by at most a frame), so that no window is shorter than asked and no window is spent
//!   on a few frames at the end.

use std::ops::ControlFlow;

use super::bodies::BodyPrior;
use super::checkpoint::Checkpoints;
use super::{FitError, FrameSource, Progress, Sequence, fit_coordinates, fit_single, validate_log};
use crate::geometry::rigid::Rigid;
use crate::model::FittedModel;
use crate::model::params::{Method, ValidFitParams};

/// Where a windowed fit is: which window is being fitted, of how many.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct WindowProgress {
    /// The window being fitted (0-based, in log order); the iteration fields of the progress
    /// are this window's.
    pub window: usize,
    /// Windows finished.
    pub windows_done: usize,
    /// Windows of the log.
    pub windows: usize,
    /// The window's first frame in the log.
    pub first_frame: usize,
    /// The window's frames.
    pub frames: usize,
}

/// Where a windowed fit keeps the windows it has finished, for a later run of the same fit (same
/// sequence, method and parameters) to take.
pub trait FinishedWindows {
    /// The model of the window of `frames` frames from `first_frame`, when an earlier run of the
    /// same fit finished it.
    fn take(&mut self, first_frame: usize, frames: usize) -> Option<FittedModel>;
    /// Keeps the model of the window of `frames` frames from `first_frame`, just fitted.
    fn keep(&mut self, first_frame: usize, frames: usize, model: &FittedModel);
    /// Whether a mid-fit checkpoint should be taken now ([`Checkpoints::due`]).
    fn checkpoint_due(&mut self) -> bool {
        false
    }
    /// The latest mid-fit checkpoint of the window, kept by an earlier run.
    fn checkpoint(&mut self, first_frame: usize, frames: usize) -> Option<Vec<u8>> {
        let _ = (first_frame, frames);
        None
    }
    /// Keeps a mid-fit checkpoint of the window, replacing the previous one.
    fn keep_checkpoint(&mut self, first_frame: usize, frames: usize, bytes: &[u8]) {
        let _ = (first_frame, frames, bytes);
    }
    /// Told when the window's fit goes on from its checkpoint, at `iteration`.
    fn resumed(&mut self, first_frame: usize, frames: usize, iteration: usize) {
        let _ = (first_frame, frames, iteration);
    }
    /// Asks to fit the window here: `false` when another worker is fitting it now (it will
    /// [`keep`](FinishedWindows::keep) it where [`take`](FinishedWindows::take) finds it). The
    /// default: every window is fitted here.
    fn claim(&mut self, first_frame: usize, frames: usize) -> bool {
        let _ = (first_frame, frames);
        true
    }
    /// The window claimed by [`FinishedWindows::claim`] is fitted (or its fit stopped).
    fn release(&mut self, first_frame: usize, frames: usize) {
        let _ = (first_frame, frames);
    }
}

/// How long a fit waiting for windows fitted elsewhere sleeps between looks.
const WAIT_FOR_OTHERS: std::time::Duration = std::time::Duration::from_millis(500);

/// Whether another process may fit windows of `sequence` beside the job's own worker
/// ([`fit_window`]): the log is fitted as windows and settling its world needs no odometry run
/// over every frame (that would be repeated by each helper).
pub fn windows_can_be_shared(sequence: &dyn FrameSource, params: &ValidFitParams) -> bool {
    is_windowed(sequence, params)
        && (!params.use_poses
            || matches!(
                (params.odometry, sequence.poses()),
                (crate::model::params::OdometryMode::Off, _) | (crate::model::params::OdometryMode::Auto, Some(_))
            ))
}

/// Window `window` of a log (see [`window_starts`]) read from `sequence`: its frames, times and
/// slice of the log's world poses.
fn window_part(
    sequence: &dyn FrameSource,
    world: Option<&[[f64; 16]]>,
    range: std::ops::Range<usize>,
) -> Result<Sequence, FitError> {
    Ok(Sequence {
        frames: sequence.read_frames(range.clone())?,
        timestamps_s: sequence.timestamps_s().map(|ts| ts[range.clone()].to_vec()),
        poses: world.map(|poses| poses[range].to_vec()),
    })
}

/// The log's poses as the windows use them (relative to frame 0, row-major), settled once.
fn world_poses(coordinates: &super::FitCoordinates) -> Option<Vec<[f64; 16]>> {
    coordinates.frame_poses.as_ref().map(|poses| poses.iter().map(|p| p.to_row_major()).collect())
}

/// The bodies of window `before` (its model and first frame) that window `after` has no body
/// for in the frames they share ([`crate::model::unlinked_bodies`]), as priors for following
/// them on through `after`'s frames: each one's model from its members of every frame it was
/// seen in, and its poses at the shared frames. `log_poses` are the log's poses (each frame's
/// sensor coordinates to frame 0's).
fn body_priors(
    (before, before_start): (&FittedModel, usize),
    (after, after_start): (&FittedModel, usize),
    log_poses: &[Rigid],
) -> Vec<BodyPrior> {
    let frames = after.time_axis().frames();
    crate::model::unlinked_bodies(
        (before, before_start, &log_poses[before_start]),
        (after, after_start, &log_poses[after_start]),
    )
    .into_iter()
    .map(|(b, shared)| {
        let body = &before.bodies()[b];
        let model = body
            .frames_seen()
            .into_iter()
            .flat_map(|j| {
                let to_body = body.poses[j].inverse();
                body.members[j].iter().map(move |p| to_body.apply(p))
            })
            .collect();
        let mut poses = vec![None; frames];
        for (pose, slot) in shared.into_iter().zip(&mut poses) {
            *slot = Some(pose);
        }
        BodyPrior { model, poses }
    })
    .collect()
}

/// Fits window `window` of a log alone, as [`fit_log`] fits it (same frames, poses and
/// parameters, so the same model bit for bit): the work a helper does for a job whose own
/// worker is busy with other windows. Returns the window's first frame, frame count and model.
pub fn fit_window(
    sequence: &dyn FrameSource,
    method: Method,
    params: &ValidFitParams,
    window: usize,
    checkpoints: &mut dyn Checkpoints,
    on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
) -> Result<FittedModel, FitError> {
    validate_log(sequence)?;
    let starts = window_starts(sequence.frame_count(), params.window_frames, params.window_overlap_frames);
    let start = *starts.get(window).ok_or_else(|| {
        FitError::InvalidSequence(format!("the log has {} windows, not {}", starts.len(), window + 1))
    })?;
    let world = world_poses(&fit_coordinates(sequence, params)?);
    let part = window_part(sequence, world.as_deref(), start..start + params.window_frames)?;
    fit_single(&part, method, &params.for_window(), checkpoints, on_progress)
}

/// The [`Checkpoints`] of one window, kept by a [`FinishedWindows`] (for [`fit_window`]).
pub struct KeptCheckpoints<'a>(WindowCheckpoints<'a>);

impl<'a> KeptCheckpoints<'a> {
    /// The checkpoints of the window of `frames` frames from `first_frame`, kept by `finished`.
    pub fn new(finished: &'a mut dyn FinishedWindows, first_frame: usize, frames: usize) -> Self {
        Self(WindowCheckpoints { finished, first_frame, frames })
    }
}

impl Checkpoints for KeptCheckpoints<'_> {
    fn due(&mut self) -> bool {
        self.0.due()
    }
    fn latest(&mut self) -> Option<Vec<u8>> {
        self.0.latest()
    }
    fn keep(&mut self, bytes: &[u8]) {
        self.0.keep(bytes);
    }
    fn resumed(&mut self, iteration: usize) {
        self.0.resumed(iteration);
    }
}

/// The [`Checkpoints`] of one window, kept by a [`FinishedWindows`].
struct WindowCheckpoints<'a> {
    finished: &'a mut dyn FinishedWindows,
    first_frame: usize,
    frames: usize,
}

impl Checkpoints for WindowCheckpoints<'_> {
    fn due(&mut self) -> bool {
        self.finished.checkpoint_due()
    }
    fn latest(&mut self) -> Option<Vec<u8>> {
        self.finished.checkpoint(self.first_frame, self.frames)
    }
    fn keep(&mut self, bytes: &[u8]) {
        self.finished.keep_checkpoint(self.first_frame, self.frames, bytes);
    }
    fn resumed(&mut self, iteration: usize) {
        self.finished.resumed(self.first_frame, self.frames, iteration);
    }
}

/// Keeps nothing: every window is fitted.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoFinishedWindows;

impl FinishedWindows for NoFinishedWindows {
    fn take(&mut self, _first_frame: usize, _frames: usize) -> Option<FittedModel> {
        None
    }

    fn keep(&mut self, _first_frame: usize, _frames: usize, _model: &FittedModel) {}
}

/// The first frame of each window of a log of `frames` frames, for windows of `window_frames`
/// frames overlapping by at least `overlap_frames` (`1 <= overlap_frames < window_frames`): one
/// window `[0]` when the log fits in one.
pub fn window_starts(frames: usize, window_frames: usize, overlap_frames: usize) -> Vec<usize> {
    if frames <= window_frames {
        return vec![0];
    }
    let step = window_frames - overlap_frames;
    let last = frames - window_frames;
    // Gaps between starts: as few as steps of at most `step` allow, then equal up to rounding
    // (each at most `step`, since `step` is a whole number no smaller than their mean).
    let gaps = last.div_ceil(step);
    (0..=gaps).map(|w| (w * last + gaps / 2) / gaps).collect()
}

/// Whether `sequence` is fitted as windows with `params` (it has more frames than a window).
pub fn is_windowed(sequence: &dyn FrameSource, params: &ValidFitParams) -> bool {
    sequence.frame_count() > params.window_frames
}

/// [`fit_sequence`](super::fit_sequence) of a sequence whose frames are read when needed,
/// taking the windows an earlier run of the same fit finished from `finished` and keeping
/// there each window it finishes. A sequence of at most one window is one fit, as in
/// `fit_sequence`; a longer one is fitted window by window and stitched (see the module's
/// documentation), reading each window's frames when it is fitted (a window taken from
/// `finished` reads none). Progress then carries [`Progress::window`]; a `Break` from
/// `on_progress` cancels the fit.
pub fn fit_log(
    sequence: &dyn FrameSource,
    method: Method,
    params: &ValidFitParams,
    finished: &mut dyn FinishedWindows,
    on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
) -> Result<FittedModel, FitError> {
    if !is_windowed(sequence, params) {
        let frames = sequence.frame_count();
        let mut checkpoints = WindowCheckpoints { finished, first_frame: 0, frames };
        return match sequence.in_memory() {
            Some(all) => fit_single(all, method, params, &mut checkpoints, on_progress),
            None => fit_single(&sequence.part(0..frames)?, method, params, &mut checkpoints, on_progress),
        };
    }
    validate_log(sequence)?;
    let started = std::time::Instant::now();
    let coordinates = fit_coordinates(sequence, params)?;
    // Each window gets its slice of the log's poses and is told not to estimate its own: the
    // windows then share the log's world. (Poses relative to frame 0 serve as world poses: a
    // window re-expresses them relative to its own first frame.)
    let world = world_poses(&coordinates);
    let window_params = params.for_window();
    let frames = sequence.frame_count();
    let starts = window_starts(frames, params.window_frames, params.window_overlap_frames);
    let mut windows: Vec<Option<FittedModel>> = starts.iter().map(|_| None).collect();
    let mut done = 0;
    // First pass in order; windows another worker was fitting are looked at again (and fitted
    // here if their worker stopped) until every one is there.
    let mut first_pass = true;
    let mut last_progress: Option<Progress> = None;
    while done < starts.len() {
        let mut waiting = false;
        for (w, &start) in starts.iter().enumerate() {
            if windows[w].is_some() {
                continue;
            }
            let position = WindowProgress {
                window: w,
                windows_done: done,
                windows: starts.len(),
                first_frame: start,
                frames: params.window_frames,
            };
            if let Some(model) = finished.take(start, params.window_frames) {
                tracing::info!(window = w, windows = starts.len(), first_frame = start, "taking a finished window");
                // One report for the window, so that progress shows it done and a cancel is heard.
                let report = Progress {
                    iteration: model.report().iterations,
                    iterations: window_params.iterations,
                    loss: super::LossTerms::default(),
                    best_validation_loss: model.report().best_validation_loss,
                    validation_loss: None,
                    fewest_live_units: None,
                    rigid_tracks: None,
                    window: Some(WindowProgress { windows_done: done + 1, ..position }),
                };
                if on_progress(&report).is_break() {
                    return Err(FitError::Cancelled { iteration: report.iteration });
                }
                windows[w] = Some(model);
                done += 1;
                continue;
            }
            if !finished.claim(start, params.window_frames) {
                if first_pass {
                    tracing::info!(window = w, first_frame = start, "another worker is fitting this window");
                }
                waiting = true;
                continue;
            }
            // Another worker may have kept it between the look above and the claim.
            if let Some(model) = finished.take(start, params.window_frames) {
                finished.release(start, params.window_frames);
                windows[w] = Some(model);
                done += 1;
                continue;
            }
            tracing::info!(window = w, windows = starts.len(), first_frame = start, "fitting a window");
            // Read here, and dropped once the window is fitted: one window's frames at a time.
            let part = window_part(sequence, world.as_deref(), start..start + params.window_frames)?;
            let mut checkpoints =
                WindowCheckpoints { finished: &mut *finished, first_frame: start, frames: params.window_frames };
            let fitted = fit_single(&part, method, &window_params, &mut checkpoints, &mut |p: &Progress| {
                let p = Progress { window: Some(position), ..p.clone() };
                last_progress = Some(p.clone());
                on_progress(&p)
            });
            finished.release(start, params.window_frames);
            let model = fitted?;
            finished.keep(start, params.window_frames, &model);
            windows[w] = Some(model);
            done += 1;
        }
        first_pass = false;
        if waiting && done < starts.len() {
            // Heard by a cancel while others fit; repeats the last report.
            let idle = last_progress.clone().unwrap_or(Progress {
                iteration: 0,
                iterations: window_params.iterations,
                loss: super::LossTerms::default(),
                best_validation_loss: None,
                validation_loss: None,
                fewest_live_units: None,
                rigid_tracks: None,
                window: None,
            });
            if on_progress(&idle).is_break() {
                return Err(FitError::Cancelled { iteration: idle.iteration });
            }
            std::thread::sleep(WAIT_FOR_OTHERS);
        }
    }
    // A body a window followed into the next one's frames, and which that window's own search
    // did not find there, is followed on through them (in log order, so that it can go on into
    // the windows after). Done here, where every window is at hand: each window's own fit stays
    // a unit of work that depends on its frames only.
    if let (Some(log_poses), true) = (coordinates.frame_poses.as_deref(), window_params.moving_bodies) {
        for w in 1..starts.len() {
            let before = windows[w - 1].as_ref().expect("every window is done");
            let after = windows[w].as_ref().expect("every window is done");
            let priors = body_priors((before, starts[w - 1]), (after, starts[w]), log_poses);
            if priors.is_empty() {
                continue;
            }
            if let Some(p) = &last_progress
                && on_progress(p).is_break()
            {
                return Err(FitError::Cancelled { iteration: p.iteration });
            }
            tracing::info!(window = w, bodies = priors.len(), "following bodies of the window before on");
            let part = window_part(sequence, world.as_deref(), starts[w]..starts[w] + params.window_frames)?;
            let model = windows[w].take().expect("every window is done");
            windows[w] = Some(super::continue_window_bodies(model, &part, &window_params, &priors)?);
        }
    }
    let windows: Vec<(usize, FittedModel)> =
        starts.iter().copied().zip(windows.into_iter().map(|m| m.expect("every window is done"))).collect();
    let report = crate::model::FitReport {
        params: Some(params.clone()),
        estimated_poses: coordinates.estimated_poses,
        fit_seconds: started.elapsed().as_secs_f64(),
        ..Default::default()
    };
    let time_axis = crate::model::TimeAxis::new(sequence.timestamps_s().map(<[f64]>::to_vec), frames);
    FittedModel::stitched(method, time_axis, coordinates.frame_poses, report, windows)
        .map_err(|e| FitError::InvalidSequence(format!("stitching the windows: {e}")))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::geometry::Point;
    use crate::model::params::FitParams;
    use crate::sim::{LidarParams, SimParams, SimSequence, simulate};

    /// A simulated street with poses, seen by a sparse sensor (16 beams, 1 degree steps: about
    /// 5,800 rays a sweep) so that a debug-build fit of it takes seconds.
    pub(crate) fn small_log(seed: u64, frames: usize) -> SimSequence {
        let lidar = LidarParams { beams: 16, azimuth_step_deg: 1.0, ..LidarParams::default() };
        simulate(&SimParams { seed, frames, lidar, ..SimParams::default() }).unwrap()
    }

    /// Few, small iterations: what is tested is the windows, not the fit's accuracy.
    pub(crate) fn quick_params(window_frames: usize, overlap: usize) -> ValidFitParams {
        FitParams {
            iterations: Some(3),
            hidden_width: Some(16),
            hidden_layers: Some(2),
            sample_points: Some(1024),
            cycle_sample_points: Some(256),
            seed: Some(3),
            window_frames: Some(window_frames),
            window_overlap_frames: Some(overlap),
            ..FitParams::default()
        }
        .check(Method::Mbnt)
        .unwrap()
    }

    /// Sensor coordinates of frame `k` -> world, from a row-major pose.
    fn to_world(pose: &[f64; 16], p: &Point) -> [f64; 3] {
        let q = [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])];
        std::array::from_fn(|r| pose[4 * r] * q[0] + pose[4 * r + 1] * q[1] + pose[4 * r + 2] * q[2] + pose[4 * r + 3])
    }

    #[test]
    fn a_log_fitted_as_windows_answers_everywhere_and_still_points_stay_put_across_hand_overs() {
        let sim = small_log(5, 12);
        let sequence = sim.to_fit_sequence();
        // Windows of 6 frames overlapping by at least 2: starts 0, 3, 6; hand-overs at 4 and 7.
        let params = quick_params(6, 2);
        let mut seen = Vec::new();
        let model = fit_sequence_with(&sequence, &params, &mut |p| {
            let w = p.window.expect("a windowed fit reports its window");
            if seen.last() != Some(&(w.window, w.windows_done, w.windows, w.first_frame)) {
                seen.push((w.window, w.windows_done, w.windows, w.first_frame));
            }
            ControlFlow::Continue(())
        })
        .unwrap();
        assert_eq!(seen, vec![(0, 0, 3, 0), (1, 1, 3, 3), (2, 2, 3, 6)], "every window reports, in order");
        let starts = model.window_starts();
        assert_eq!(starts, vec![0, 3, 6]);
        assert!(model.windows().unwrap().iter().all(|(_, m)| m.time_axis().frames() == 6));
        assert_eq!(model.time_axis().frames(), 12);
        assert_eq!(model.report().frames.len(), 12);
        assert_eq!(model.report().iterations, 9, "3 iterations in each of 3 windows");
        // The loss curve lists window after window, each counting its iterations from 1.
        let curve: Vec<(Option<usize>, usize)> =
            model.report().losses.iter().map(|r| (r.window, r.iteration)).collect();
        let expected: Vec<(Option<usize>, usize)> = (0..3).flat_map(|w| (1..=3).map(move |i| (Some(w), i))).collect();
        assert_eq!(curve, expected);

        // Still points of frame 0 (not ground, on no moving object) observed at t = 0 stay where
        // they are in the world at every frame time and between frames, in every window.
        let still: Vec<Point> = (0..sim.frames[0].len())
            .filter(|&i| {
                let truth = &sim.truth[0][i];
                !truth.is_ground && !sim.objects[truth.object_id as usize].dynamic
            })
            .map(|i| sim.frames[0][i])
            .step_by(7)
            .collect();
        assert!(still.len() > 50, "{} still points", still.len());
        let frame_times = &sim.timestamps_s;
        let at = model.positions(&still, 0.0, frame_times).unwrap();
        let mut drift_m = Vec::new();
        for (i, p) in still.iter().enumerate() {
            let start = to_world(&sim.ego_poses[0], p);
            for (k, pose) in sim.ego_poses.iter().enumerate() {
                let q = to_world(pose, &at[i * frame_times.len() + k]);
                drift_m.push((0..3).map(|c| (q[c] - start[c]).powi(2)).sum::<f64>().sqrt());
            }
        }
        drift_m.sort_by(f64::total_cmp);
        // The still world follows the poses exactly (f32 rounding: well under a millimetre);
        // a point taken by a body or the network may move, and few are.
        let median = drift_m[drift_m.len() / 2];
        let within = drift_m.iter().filter(|&&d| d < 0.01).count() as f64 / drift_m.len() as f64;
        assert!(median < 1e-3 && within > 0.95, "median drift {median} m, {within} within 1 cm");

        // Continuity at the hand-over frames (4 and 7): just before and at the hand-over time
        // a point is where the ego motion of 1 ms puts it (the sensor moves < 0.05 m in 1 ms).
        for handoff in [4usize, 7] {
            let t = frame_times[handoff];
            let around = model.positions(&still, 0.0, &[t - 1e-3, t]).unwrap();
            for pair in around.chunks(2) {
                let jump: f32 = (0..3).map(|c| (pair[1][c] - pair[0][c]).powi(2)).sum::<f32>().sqrt();
                assert!(jump < 0.05, "jump of {jump} m at the hand-over of frame {handoff}");
            }
        }

        // Any time answers, finite: points of every frame, observed inside and outside overlaps,
        // at every frame time and half-way between.
        let mut times = frame_times.clone();
        times.extend(frame_times.windows(2).map(|w| 0.5 * (w[0] + w[1])));
        for (k, frame) in sim.frames.iter().enumerate() {
            let some: Vec<Point> = frame.iter().step_by(97).copied().collect();
            let answers = model.positions(&some, frame_times[k], &times).unwrap();
            assert!(answers.iter().flatten().all(|c| c.is_finite()), "frame {k}");
            // Observed and asked at the same time, a point is where it was seen.
            let same = model.positions(&some, frame_times[k], &[frame_times[k]]).unwrap();
            for (p, q) in some.iter().zip(&same) {
                assert!((0..3).all(|c| (p[c] - q[c]).abs() < 1e-3), "frame {k}: {p:?} -> {q:?}");
            }
        }

        // Labels for every frame: scene flow of frames 0..T-2, object ids of every frame.
        let flows = model.scene_flow(&sequence.frames).unwrap();
        let ids = model.object_ids(&sequence.frames).unwrap();
        assert_eq!(flows.len(), 11);
        assert_eq!(ids.len(), 12);
        for k in 0..12 {
            assert_eq!(ids[k].len(), sequence.frames[k].len());
            if k < 11 {
                assert_eq!(flows[k].len(), sequence.frames[k].len());
                assert!(flows[k].iter().flatten().all(|c| c.is_finite()));
            }
            let known: Vec<i32> = model.bodies().iter().map(|b| b.id as i32).collect();
            assert!(ids[k].iter().all(|&id| id == -1 || known.contains(&id)), "frame {k}");
        }
        for body in model.bodies() {
            assert!(body.fits(12), "every object covers the log");
        }

        // The model file keeps the windows and answers the same.
        let back = crate::model::FittedModel::from_bytes(&model.to_bytes().unwrap()).unwrap();
        assert_eq!(back.window_starts().len(), 3);
        assert_eq!(back.positions(&still, 0.0, frame_times).unwrap(), at);
        assert_eq!(back.bodies(), model.bodies());
    }

    /// [`fit_sequence`](super::super::fit_sequence) of MBNT.
    fn fit_sequence_with(
        sequence: &Sequence,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        super::super::fit_sequence(sequence, Method::Mbnt, params, on_progress)
    }

    #[test]
    fn a_log_of_at_most_one_window_is_one_fit_bit_for_bit() {
        let sequence = small_log(6, 6).to_fit_sequence();
        // A window exactly as long as the log, and one far longer: the same single fit.
        let exact = fit_sequence_with(&sequence, &quick_params(6, 2), &mut |p| {
            assert!(p.window.is_none());
            ControlFlow::Continue(())
        })
        .unwrap();
        let long = fit_sequence_with(&sequence, &quick_params(1000, 5), &mut |_| ControlFlow::Continue(())).unwrap();
        assert!(exact.window_starts().is_empty() && long.window_starts().is_empty());
        let times = sequence.timestamps_s.clone().unwrap();
        for (k, frame) in sequence.frames.iter().enumerate() {
            let a = exact.positions(frame, times[k], &times).unwrap();
            let b = long.positions(frame, times[k], &times).unwrap();
            assert!(a.iter().flatten().zip(b.iter().flatten()).all(|(x, y)| x.to_bits() == y.to_bits()), "frame {k}");
        }
        assert_eq!(exact.bodies(), long.bodies());
        assert_eq!(exact.object_ids(&sequence.frames).unwrap(), long.object_ids(&sequence.frames).unwrap());
        // A model of one fit is still written as version 1 of the file format.
        assert!(exact.to_bytes().unwrap().starts_with(b"MBNTMDL1"));
    }

    /// Issue 21: a body moving through an overlap keeps its track across the hand-over. Points
    /// of moving objects seen two frames before the hand-over are followed to two frames after
    /// it (each window answers part of the way) and compared with the simulator's exact
    /// positions, beside one fit of all the frames; the object keeps one id across the windows.
    #[test]
    fn a_body_moving_through_an_overlap_keeps_its_track() {
        // Seed 8: two bodies found in both windows (picked by listing the bodies of seeds 1-11;
        // seed 4's second body, seen in frames 0-9, is no longer found in the second window's
        // four frames of it since the bodies' registration slides along their travel).
        let sim = small_log(8, 16);
        let sequence = sim.to_fit_sequence();
        // Windows of 10 frames overlapping by at least 4: starts 0 and 6, hand-over at frame 8.
        let windowed = fit_sequence_with(&sequence, &quick_params(10, 4), &mut |_| ControlFlow::Continue(())).unwrap();
        let starts = windowed.window_starts();
        assert_eq!(starts, vec![0, 6]);
        let single = fit_sequence_with(&sequence, &quick_params(16, 4), &mut |_| ControlFlow::Continue(())).unwrap();
        assert!(single.window_starts().is_empty());
        // Every body of either window is one object of the log, seen on both sides of the overlap.
        let per_window: Vec<usize> = windowed.windows().unwrap().iter().map(|(_, m)| m.bodies().len()).collect();
        assert_eq!(per_window, vec![2, 2]);
        assert_eq!(windowed.bodies().len(), 2, "the bodies are linked across the overlap");
        for body in windowed.bodies() {
            let seen = body.frames_seen();
            assert!(seen.first() < Some(&6) && seen.last() > Some(&9), "object {}: {seen:?}", body.id);
        }
        let (from, to) = (6, 10);
        let truth = sim.positions_at(from, to).unwrap();
        let dynamic = sim.is_dynamic(from).unwrap();
        let ts = &sim.timestamps_s;
        // Median error (m) and count of the dynamic points of frame `from` that `model` puts on a body.
        let median_error = |model: &FittedModel| -> (f64, usize) {
            let ids = &model.object_ids(&sequence.frames).unwrap()[from];
            let predicted = model.positions(&sim.frames[from], ts[from], &[ts[to]]).unwrap();
            let mut errors_m: Vec<f64> = (0..truth.len())
                .filter(|&i| dynamic[i] && ids[i] >= 0)
                .map(|i| (0..3).map(|c| f64::from(predicted[i][c] - truth[i][c]).powi(2)).sum::<f64>().sqrt())
                .collect();
            errors_m.sort_by(f64::total_cmp);
            (errors_m.get(errors_m.len() / 2).copied().unwrap_or(f64::INFINITY), errors_m.len())
        };
        let (windowed_m, windowed_points) = median_error(&windowed);
        let (single_m, _) = median_error(&single);
        assert!(windowed_points > 100, "{windowed_points} moving points on bodies");
        // Measured (seed 8): 0.044 m windowed, 0.013 m one fit, 444 points (seed 4 before the
        // slide: 0.098 and 0.101 m).
        assert!(windowed_m < single_m + 0.1, "windowed {windowed_m} m, one fit {single_m} m");
        assert!(windowed_m < 0.3, "windowed {windowed_m} m");
    }

    /// A sequence read window by window, recording every read.
    struct CountingSource {
        sequence: Sequence,
        reads: std::cell::RefCell<Vec<std::ops::Range<usize>>>,
    }

    impl FrameSource for CountingSource {
        fn frame_count(&self) -> usize {
            self.sequence.frames.len()
        }
        fn timestamps_s(&self) -> Option<&[f64]> {
            self.sequence.timestamps_s.as_deref()
        }
        fn poses(&self) -> Option<&[[f64; 16]]> {
            self.sequence.poses.as_deref()
        }
        fn read_frames(&self, range: std::ops::Range<usize>) -> Result<Vec<Vec<Point>>, FitError> {
            self.reads.borrow_mut().push(range.clone());
            Ok(self.sequence.frames[range].to_vec())
        }
    }

    /// Keeps every window in memory, for a second run to take.
    #[derive(Default)]
    struct KeptInMemory(std::collections::BTreeMap<usize, FittedModel>);

    impl FinishedWindows for KeptInMemory {
        fn take(&mut self, first_frame: usize, _frames: usize) -> Option<FittedModel> {
            self.0.get(&first_frame).cloned()
        }
        fn keep(&mut self, first_frame: usize, _frames: usize, model: &FittedModel) {
            self.0.insert(first_frame, model.clone());
        }
    }

    #[test]
    fn a_log_read_from_a_source_reads_one_window_at_a_time_and_a_kept_window_not_at_all() {
        let sequence = small_log(5, 12).to_fit_sequence();
        let params = quick_params(6, 2);
        let source = CountingSource { sequence: sequence.clone(), reads: Default::default() };
        let mut kept = KeptInMemory::default();
        let model = fit_log(&source, Method::Mbnt, &params, &mut kept, &mut |_| ControlFlow::Continue(())).unwrap();
        // Windows from frames 0, 3 and 6: each read once, when fitted, and nothing else (with poses
        // the fit reads no frame to settle its coordinates).
        assert_eq!(*source.reads.borrow(), vec![0..6, 3..9, 6..12]);
        // The same model as from the frames in memory.
        let in_memory = fit_sequence_with(&sequence, &params, &mut |_| ControlFlow::Continue(())).unwrap();
        let still: Vec<Point> = sequence.frames[0].iter().take(200).copied().collect();
        let times = [0.0, 0.55, 1.1];
        let t0 = sequence.timestamps_s.as_ref().unwrap()[0];
        assert_eq!(model.positions(&still, t0, &times).unwrap(), in_memory.positions(&still, t0, &times).unwrap());
        // A second run takes every window kept by the first and reads no frame.
        source.reads.borrow_mut().clear();
        let again = fit_log(&source, Method::Mbnt, &params, &mut kept, &mut |_| ControlFlow::Continue(())).unwrap();
        assert!(source.reads.borrow().is_empty(), "{:?}", source.reads.borrow());
        assert_eq!(again.positions(&still, t0, &times).unwrap(), model.positions(&still, t0, &times).unwrap());
        // Without poses the odometry reads every frame once, one at a time and in order (so it
        // holds one full frame, not the log), before the windows.
        let raw = CountingSource { sequence: Sequence { poses: None, ..sequence }, reads: Default::default() };
        fit_log(&raw, Method::Mbnt, &params, &mut NoFinishedWindows, &mut |_| ControlFlow::Continue(())).unwrap();
        let one_at_a_time = (0..12).map(|k| k..k + 1);
        assert_eq!(*raw.reads.borrow(), one_at_a_time.chain([0..6, 3..9, 6..12]).collect::<Vec<_>>());
    }

    #[test]
    fn a_cancel_inside_a_later_window_stops_the_fit() {
        let sequence = small_log(7, 9).to_fit_sequence();
        let mut windows_seen = 0;
        let result = fit_sequence_with(&sequence, &quick_params(5, 1), &mut |p| {
            let w = p.window.expect("windowed");
            windows_seen = windows_seen.max(w.window + 1);
            if w.window == 1 && p.iteration == 2 { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
        });
        assert!(matches!(result, Err(FitError::Cancelled { iteration: 2 })), "{result:?}");
        assert_eq!(windows_seen, 2, "the third window never started");
    }

    #[test]
    fn windows_cover_the_log_with_the_asked_overlap_and_full_length() {
        assert_eq!(window_starts(25, 25, 5), vec![0]);
        assert_eq!(window_starts(10, 25, 5), vec![0]);
        assert_eq!(window_starts(26, 25, 5), vec![0, 1]);
        assert_eq!(window_starts(45, 25, 5), vec![0, 20]);
        assert_eq!(window_starts(100, 25, 5), vec![0, 19, 38, 56, 75]);
        assert_eq!(window_starts(150, 25, 5), vec![0, 18, 36, 54, 71, 89, 107, 125]);
        for (frames, window, overlap) in [(100, 25, 5), (31, 7, 1), (9, 2, 1), (50, 10, 9), (151, 25, 12)] {
            let starts = window_starts(frames, window, overlap);
            assert_eq!(starts[0], 0);
            assert_eq!(starts.last().unwrap() + window, frames, "the last window ends at the last frame");
            for pair in starts.windows(2) {
                let shared = pair[0] + window - pair[1];
                assert!(
                    pair[1] > pair[0] && shared >= overlap && shared < window,
                    "{frames} {window} {overlap}: {starts:?}"
                );
            }
        }
    }
}
