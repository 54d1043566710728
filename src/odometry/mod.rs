//! LiDAR odometry: the sensor's poses of a sequence recorded without them, by registering each
//! frame to a voxel-hashed local map of the previous ones (the KISS-ICP recipe, written anew).
//!
//! One frame, in order ([`estimate_poses`]):
//! 1. crop to [`OdometryParams::min_range_m`, `max_range_m`] and voxelise twice: the map takes
//!    the frame at half the voxel size, registration uses 1.5 times the voxel size;
//! 2. predict the pose by constant velocity (the last frame-to-frame motion, scaled by the time
//!    step when timestamps are given);
//! 3. the first registration, with no motion to predict from, starts from the best of a grid
//!    of translations instead (`initial_search_m`), scored on planes, poles and edges only;
//! 4. ICP against the map ([`registration`]): correspondences within three times the adaptive
//!    threshold sigma ([`threshold`]), a Geman-McClure weight of scale sigma / 3, so points that
//!    move on their own hardly pull once sigma has adapted; each residual measured only along
//!    what the map's neighbourhood observes ([`voxel::VoxelMap::local_shapes`]: a plane's
//!    normal, across a pole, across an edge), since the rings a LiDAR draws on a road or a wall
//!    move with the sensor and pull point-to-point residuals towards standing still;
//! 5. the prediction's error feeds the threshold; the map ([`voxel`]) takes the frame at its new
//!    pose and drops voxels beyond `max_range_m`;
//! 6. the refinement ([`refine`]) registers each frame again against its neighbours on both
//!    sides, with denser clouds, as soon as they are placed, and finally re-expresses every pose
//!    from frame 0's.
//!
//! Synchronous and free of I/O. Points stay `f32` until they meet a pose; poses and the normal
//! equations are `f64` (nalgebra). Deterministic: the same input gives the same bits on any
//! number of threads.

mod refine;
mod registration;
mod threshold;
pub mod voxel;

#[cfg(test)]
mod tests;

use std::borrow::Cow;
use std::ops::ControlFlow;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::geometry::Point;
pub use refine::REFINE_SWEEPS;
use refine::{RefineFrame, Refinement};
use registration::{IcpSettings, align_to_map, search_translation};
use threshold::AdaptiveThreshold;
use voxel::{VoxelMap, transform_points, voxel_downsample};

/// The largest thickness of a local plane of the map (m, standard deviation across it): a
/// road, a wall or a car's side, sampled with a few centimetres of range noise.
const PLANE_THICKNESS_M: f64 = 0.05;

/// The odometry's parameters, with the defaults of a 64-beam automotive LiDAR (KITTI).
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryParams {
    /// Points farther than this from the sensor are ignored, and map voxels farther than this
    /// from the current pose are dropped (m; default 100).
    pub max_range_m: f32,
    /// Points nearer than this are ignored: returns from the vehicle itself (m; default 3).
    pub min_range_m: f32,
    /// Voxel edge of the local map (m; default 1 = max range / 100). The frame enters the map
    /// downsampled at half of it and is registered downsampled at 1.5 times it.
    pub voxel_m: f32,
    /// Points kept per map voxel (default 20).
    pub max_points_per_voxel: usize,
    /// Threshold sigma until a prediction has been off (m; default 2): correspondences are
    /// sought within 3 sigma.
    pub initial_threshold_m: f64,
    /// Prediction errors up to this do not update sigma (m; default 0.1): see `threshold`.
    pub min_prediction_error_m: f64,
    /// The first registration (no motion to predict from yet) starts from the best of a grid
    /// of forward and sideways translations within this distance (m; default 3, 0 = none): a
    /// guess a metre off pairs points with the wrong surfaces, from which ICP does not recover.
    pub initial_search_m: f64,
    /// Step of that grid (m; default 0.2).
    pub initial_search_step_m: f64,
    /// Each frame is registered again, [`REFINE_SWEEPS`] times, against a map of the frames up
    /// to this many before and after it, as soon as they are placed (default 4, 0 = no
    /// refinement): the first frames met a map of one or two sweeps, and every frame met only
    /// the past. Memory holds about this many times [`REFINE_SWEEPS`] + 1 frames' clouds.
    pub refine_window_frames: usize,
    /// ICP iterations per frame at most (default 500).
    pub max_iterations: usize,
    /// ICP stops once an update is smaller than this (m, translation plus rotation in radians;
    /// default 1e-4).
    pub convergence_m: f64,
}

impl Default for OdometryParams {
    fn default() -> Self {
        Self {
            max_range_m: 100.0,
            min_range_m: 3.0,
            voxel_m: 1.0,
            max_points_per_voxel: 20,
            initial_threshold_m: 2.0,
            min_prediction_error_m: 0.1,
            initial_search_m: 3.0,
            initial_search_step_m: 0.2,
            refine_window_frames: 4,
            max_iterations: 500,
            convergence_m: 1e-4,
        }
    }
}

impl OdometryParams {
    /// Checks every range; the error names the parameter.
    pub fn check(&self) -> Result<(), OdometryError> {
        let bad = |name: &'static str, problem: String| Err(OdometryError::InvalidParams { name, problem });
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(f64::from(self.max_range_m)) {
            return bad("max_range_m", format!("must be positive, got {}", self.max_range_m));
        }
        if !(self.min_range_m >= 0.0 && self.min_range_m < self.max_range_m) {
            return bad("min_range_m", format!("must be in [0, max_range_m), got {}", self.min_range_m));
        }
        if !positive(f64::from(self.voxel_m)) || self.voxel_m > self.max_range_m {
            return bad("voxel_m", format!("must be positive and at most max_range_m, got {}", self.voxel_m));
        }
        if self.max_points_per_voxel == 0 {
            return bad("max_points_per_voxel", "must be at least 1".into());
        }
        for (name, v) in [
            ("initial_threshold_m", self.initial_threshold_m),
            ("min_prediction_error_m", self.min_prediction_error_m),
            ("initial_search_step_m", self.initial_search_step_m),
            ("convergence_m", self.convergence_m),
        ] {
            if !positive(v) {
                return bad(name, format!("must be positive, got {v}"));
            }
        }
        if !(self.initial_search_m >= 0.0 && self.initial_search_m <= 50.0 * self.initial_search_step_m) {
            return bad(
                "initial_search_m",
                format!("must be in [0, 50 initial_search_step_m], got {}", self.initial_search_m),
            );
        }
        if self.refine_window_frames > 50 {
            return bad("refine_window_frames", format!("must be at most 50, got {}", self.refine_window_frames));
        }
        if self.max_iterations == 0 {
            return bad("max_iterations", "must be at least 1".into());
        }
        Ok(())
    }
}

/// Why the poses could not be estimated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OdometryError {
    /// Odometry needs at least two frames.
    #[error("odometry needs at least 2 frames, got {frames}")]
    TooFewFrames {
        /// Frames given.
        frames: usize,
    },
    /// A frame with no point within the odometry's range.
    #[error("frame {frame} has no points between {min_range_m} m and {max_range_m} m from the sensor")]
    EmptyFrame {
        /// The frame's index.
        frame: usize,
        /// See [`OdometryParams::min_range_m`].
        min_range_m: f32,
        /// See [`OdometryParams::max_range_m`].
        max_range_m: f32,
    },
    /// A point with a NaN or infinite coordinate.
    #[error("frame {frame}, point {index} has a non-finite coordinate")]
    NonFinitePoint {
        /// The frame's index.
        frame: usize,
        /// The point's index in the frame.
        index: usize,
    },
    /// Timestamps that are not one per frame, finite and strictly increasing.
    #[error("timestamps: {0}")]
    BadTimestamps(String),
    /// A parameter out of range.
    #[error("odometry parameter `{name}` {problem}")]
    InvalidParams {
        /// The field's name.
        name: &'static str,
        /// What is wrong with it.
        problem: String,
    },
    /// Registration found too few correspondences (the frame does not overlap the map).
    #[error("frame {frame} could not be registered: fewer than 6 points near the local map")]
    RegistrationFailed {
        /// The frame's index.
        frame: usize,
    },
    /// The progress callback asked to stop.
    #[error("cancelled after {frames_done} frames")]
    Cancelled {
        /// Frames registered before the stop.
        frames_done: usize,
    },
}

/// How one frame was registered.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FrameDiagnostics {
    /// Points used for registration (after cropping and downsampling; 0 for frame 0).
    pub source_points: usize,
    /// Correspondences in the last ICP iteration.
    pub correspondences: usize,
    /// ICP iterations run.
    pub iterations: usize,
    /// Threshold sigma used (m); correspondences were sought within 3 sigma.
    pub threshold_m: f64,
    /// Geman-McClure scale of the last iteration (m).
    pub kernel_m: f64,
    /// Median correspondence distance of the last iteration (m).
    pub median_residual_m: f64,
    /// How far the constant-velocity prediction was off (m, at max range; see `threshold`).
    pub prediction_error_m: f64,
    /// Points in the local map after this frame was added.
    pub map_points: usize,
}

/// The estimate of a sequence.
#[derive(Debug, Clone)]
pub struct Odometry {
    /// Per frame, the transform from its sensor coordinates to the world's (frame 0's sensor
    /// coordinates): frame 0 is the identity.
    pub world_from_sensor: Vec<Isometry3<f64>>,
    /// Per frame, how it was registered.
    pub frames: Vec<FrameDiagnostics>,
}

impl Odometry {
    /// The poses as row-major 4 x 4 sensor-to-world matrices (the API's layout).
    pub fn row_major(&self) -> Vec<[f64; 16]> {
        self.world_from_sensor.iter().map(to_row_major).collect()
    }
}

/// A pose as a row-major 4 x 4 matrix.
pub fn to_row_major(pose: &Isometry3<f64>) -> [f64; 16] {
    let m = pose.to_homogeneous();
    std::array::from_fn(|i| m[(i / 4, i % 4)])
}

/// A row-major 3 x 4 or 4 x 4 rigid transform as an isometry; `None` when the rotation block is
/// not orthonormal within 1e-3 or is a reflection, or an entry is not finite.
pub fn from_row_major(m: &[f64]) -> Option<Isometry3<f64>> {
    if (m.len() != 12 && m.len() != 16) || m.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let r = Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
    if (r.transpose() * r - Matrix3::identity()).abs().max() > 1e-3 || r.determinant() <= 0.0 {
        return None;
    }
    // Project onto the nearest rotation: text files round the matrices.
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r));
    Some(Isometry3::from_parts(Translation3::new(m[3], m[7], m[11]), rotation))
}

/// Estimates each frame's sensor-to-world pose (frame 0 = identity) of `frames` (points in
/// each frame's sensor coordinates, m), calling `on_progress(frames_done, frames)` after every
/// frame; `ControlFlow::Break` cancels.
///
/// `timestamps_s` (one per frame, strictly increasing) scale the constant-velocity prediction
/// when the frame rate varies; without them frames are taken as evenly spaced.
///
/// Blocking and CPU-bound (rayon inside): a few hundred ms per 120k-point frame. For frames
/// held in memory already; [`estimate_poses_from`] reads them one at a time (same poses, bit
/// for bit).
pub fn estimate_poses(
    frames: &[Vec<Point>],
    timestamps_s: Option<&[f64]>,
    params: &OdometryParams,
    on_progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<Odometry, OdometryError> {
    let mut borrow = |k: usize| Ok::<_, std::convert::Infallible>(Cow::Borrowed(frames[k].as_slice()));
    estimate_poses_from(frames.len(), &mut borrow, timestamps_s, params, on_progress).map_err(|e| match e {
        ReadOrOdometryError::Read { error, .. } => match error {},
        ReadOrOdometryError::Odometry(e) => e,
    })
}

/// Why [`estimate_poses_from`] returned no poses: a frame could not be read, or the odometry
/// failed.
#[derive(Debug, thiserror::Error)]
pub enum ReadOrOdometryError<E> {
    /// The reader's error for frame `frame`.
    #[error("frame {frame} could not be read: {error}")]
    Read {
        /// The frame's index.
        frame: usize,
        /// What the reader said.
        error: E,
    },
    /// The odometry's own error.
    #[error(transparent)]
    Odometry(#[from] OdometryError),
}

/// [`estimate_poses`] of `frame_count` frames read one at a time by `read_frame(k)`, each once
/// and in order (0, 1, ...): only the current frame is held in full, besides the downsampled
/// clouds the refinement keeps, so a long log need not be in memory. A frame's points are
/// checked when it is read (errors as [`estimate_poses`]'s); the frame count and the
/// timestamps before any is read.
pub fn estimate_poses_from<'a, E>(
    frame_count: usize,
    read_frame: &mut dyn FnMut(usize) -> Result<Cow<'a, [Point]>, E>,
    timestamps_s: Option<&[f64]>,
    params: &OdometryParams,
    on_progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<Odometry, ReadOrOdometryError<E>> {
    params.check()?;
    validate_log(frame_count, timestamps_s)?;
    let mut map = VoxelMap::new(params.voxel_m, params.max_points_per_voxel);
    let mut threshold = AdaptiveThreshold::new(
        params.initial_threshold_m,
        params.min_prediction_error_m,
        f64::from(params.max_range_m),
    );
    let mut poses: Vec<Isometry3<f64>> = Vec::with_capacity(frame_count);
    let mut diagnostics = Vec::with_capacity(frame_count);
    // The last frame-to-frame motion (in the previous sensor's coordinates) and its time step.
    let mut last_motion = Isometry3::<f64>::identity();
    let mut last_dt_s = 1.0;
    // Refines the frames as they come, holding only the clouds its windows still need.
    let mut refinement = (params.refine_window_frames > 0).then(|| Refinement::new(params.refine_window_frames));
    for k in 0..frame_count {
        let frame = read_frame(k).map_err(|error| ReadOrOdometryError::Read { frame: k, error })?;
        check_points(k, &frame)?;
        let cropped = crop(&frame, params);
        // The full frame is not needed past this point: drop it before the next is read.
        drop(frame);
        if cropped.is_empty() {
            return Err(OdometryError::EmptyFrame {
                frame: k,
                min_range_m: params.min_range_m,
                max_range_m: params.max_range_m,
            }
            .into());
        }
        let for_map = voxel_downsample(&cropped, 0.5 * params.voxel_m);
        if k == 0 {
            map.add(&for_map);
            poses.push(Isometry3::identity());
            if let Some(refinement) = &mut refinement {
                refinement.push(RefineFrame::new(&cropped, for_map, params), &mut poses, params);
            }
            diagnostics.push(FrameDiagnostics {
                source_points: 0,
                correspondences: 0,
                iterations: 0,
                threshold_m: threshold.sigma_m(),
                kernel_m: 0.0,
                median_residual_m: 0.0,
                prediction_error_m: 0.0,
                map_points: map.len(),
            });
            if on_progress(1, frame_count).is_break() {
                return Err(OdometryError::Cancelled { frames_done: 1 }.into());
            }
            continue;
        }
        let source = voxel_downsample(&for_map, 1.5 * params.voxel_m);
        let dt_s = timestamps_s.map_or(1.0, |t| t[k] - t[k - 1]);
        let predicted_motion = scale_motion(&last_motion, dt_s / last_dt_s);
        let previous = poses[k - 1];
        let sigma_m = threshold.sigma_m();
        let mut guess = previous * predicted_motion;
        let shapes = map.local_shapes(PLANE_THICKNESS_M, true);
        if k == 1 && params.initial_search_m > 0.0 {
            // Without scatter: a map of one sweep samples every corner on the rings of one
            // sensor position, and standing still would match them best.
            let no_scatter = map.local_shapes(PLANE_THICKNESS_M, false);
            guess = search_translation(
                &source,
                &map,
                &no_scatter,
                guess,
                params.initial_search_m,
                params.initial_search_step_m,
                f64::from(params.voxel_m) / 2.0,
            );
        }
        let settings = IcpSettings {
            max_distance_m: 3.0 * sigma_m,
            kernel_m: sigma_m / 3.0,
            max_iterations: params.max_iterations,
            convergence_m: params.convergence_m,
        };
        let fit = align_to_map(&source, &map, &shapes, guess, &settings)
            .ok_or(OdometryError::RegistrationFailed { frame: k })?;
        let pose = fit.world_from_sensor;
        let motion = previous.inverse() * pose;
        let deviation = guess.inverse() * pose;
        threshold.update(&deviation);
        map.add(&transform_points(&pose, &for_map));
        let t = pose.translation.vector;
        map.remove_far([t.x, t.y, t.z], f64::from(params.max_range_m));
        tracing::debug!(frame = k, iterations = fit.iterations, sigma_m, "odometry frame registered");
        diagnostics.push(FrameDiagnostics {
            source_points: source.len(),
            correspondences: fit.correspondences,
            iterations: fit.iterations,
            threshold_m: sigma_m,
            kernel_m: fit.kernel_m,
            median_residual_m: fit.median_residual_m,
            prediction_error_m: threshold::model_error_m(&deviation, f64::from(params.max_range_m)),
            map_points: map.len(),
        });
        poses.push(pose);
        if let Some(refinement) = &mut refinement {
            refinement.push(RefineFrame::new(&cropped, for_map, params), &mut poses, params);
        }
        last_motion = motion;
        last_dt_s = dt_s;
        if on_progress(k + 1, frame_count).is_break() {
            return Err(OdometryError::Cancelled { frames_done: k + 1 }.into());
        }
    }
    if let Some(refinement) = refinement {
        refinement.finish(&mut poses, params);
    }
    Ok(Odometry { world_from_sensor: poses, frames: diagnostics })
}

/// The points within the odometry's range.
fn crop(frame: &[Point], params: &OdometryParams) -> Vec<Point> {
    let (min2, max2) = (params.min_range_m * params.min_range_m, params.max_range_m * params.max_range_m);
    frame
        .iter()
        .filter(|p| {
            let r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
            r2 >= min2 && r2 <= max2
        })
        .copied()
        .collect()
}

/// `motion` carried on for `ratio` of its duration: the rotation by slerp from the identity, the
/// translation linearly (exact for a constant turn rate up to the chord's small curvature).
fn scale_motion(motion: &Isometry3<f64>, ratio: f64) -> Isometry3<f64> {
    if ratio == 1.0 {
        return *motion;
    }
    let rotation = UnitQuaternion::identity().slerp(&motion.rotation, ratio);
    let translation: Vector3<f64> = motion.translation.vector * ratio;
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

/// What can be checked before any frame is read: the frame count and the timestamps.
fn validate_log(frame_count: usize, timestamps_s: Option<&[f64]>) -> Result<(), OdometryError> {
    if frame_count < 2 {
        return Err(OdometryError::TooFewFrames { frames: frame_count });
    }
    if let Some(ts) = timestamps_s {
        if ts.len() != frame_count {
            return Err(OdometryError::BadTimestamps(format!("{} timestamps for {frame_count} frames", ts.len())));
        }
        if ts.iter().any(|t| !t.is_finite()) || ts.windows(2).any(|w| w[1] <= w[0]) {
            return Err(OdometryError::BadTimestamps("must be finite and strictly increasing".into()));
        }
    }
    Ok(())
}

/// Frame `frame`'s points, checked as it is read: all finite.
fn check_points(frame: usize, points: &[Point]) -> Result<(), OdometryError> {
    match points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        Some(index) => Err(OdometryError::NonFinitePoint { frame, index }),
        None => Ok(()),
    }
}
