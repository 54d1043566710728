//! Synthetic LiDAR sequences with exact ground truth, for tests, benchmarks and demos.
//!
//! A spinning multi-beam LiDAR rides on an ego car along a street (straight, then curved) and
//! is ray cast against the ground plane, buildings, poles, trees, parked cars, moving cars
//! (same direction, oncoming, crossing, turning) and pedestrians. See [`SimParams`] for the
//! knobs and [`simulate`] for the model.
//!
//! # Ground truth
//! Every body moves rigidly (yaw and planar translation as closed-form functions of time), and
//! every point records the body it hit. A point p seen in sweep k (time t_k) is, at sweep j,
//! `S_j^-1 B(t_j) B(t_k)^-1 S_k p`, with S the sensor-to-world pose and B the body-to-world pose.
//! This is exact for the *measured* point: the range noise is part of the point and travels with
//! its body (the truth of a noisy point is where that noisy point goes, not where the noiseless
//! surface point goes).
//!
//! # Simplifications
//! Each sweep is instantaneous at its timestamp (no rolling-shutter distortion within a sweep);
//! the ego's own body is not ray cast (sensors filter self-returns); the ground is flat; beams
//! are evenly spaced in elevation. Synchronous and free of I/O: the PNG comes back as bytes.

mod motion;
mod params;
mod png;
mod raycast;
mod scene;
mod shapes;
#[cfg(test)]
mod tests;

pub use params::{LidarParams, SceneParams, SimParams};
pub use png::render_top_down_png;
pub use scene::{Behaviour, ObjectCounts, ObjectKind};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::geometry::Point;
use motion::{apply, mat_mul, rigid_inverse};
use raycast::{Caster, RayPattern};

/// Why a simulation or a ground-truth query failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    /// A parameter is out of its valid range (the message names it).
    #[error("invalid simulation parameters: {0}")]
    InvalidParams(String),
    /// A frame index is not in `0..frames`.
    #[error("frame index {index} out of range (the sequence has {frames} frames)")]
    FrameOutOfRange {
        /// The offending index.
        index: usize,
        /// Number of frames in the sequence.
        frames: usize,
    },
    /// The PNG encoder failed.
    #[error("png encoding failed: {0}")]
    Encode(String),
}

/// Ground truth of one point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameTruth {
    /// Index into [`SimSequence::objects`] of the body the ray hit (0 is the ground).
    pub object_id: u32,
    /// Whether the point lies on the ground plane.
    pub is_ground: bool,
}

/// One body of the scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectInfo {
    /// Its index in [`SimSequence::objects`].
    pub id: u32,
    /// What it is.
    pub kind: ObjectKind,
    /// How it moves.
    pub behaviour: Behaviour,
    /// Whether it moves in the world.
    pub dynamic: bool,
    /// Body-to-world pose at each frame time (row-major 4 x 4, rigid, yaw only).
    pub poses: Vec<[f64; 16]>,
}

/// Counts describing a simulated sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimSummary {
    /// Number of frames.
    pub frames: usize,
    /// Rays per sweep (beams x azimuth columns).
    pub rays_per_frame: usize,
    /// Points in each frame.
    pub points_per_frame: Vec<usize>,
    /// Ground points in each frame.
    pub ground_points_per_frame: Vec<usize>,
    /// Points on moving bodies in each frame.
    pub dynamic_points_per_frame: Vec<usize>,
    /// Share of all points that lie on moving bodies.
    pub dynamic_point_share: f64,
    /// Share of the non-ground points that lie on moving bodies.
    pub dynamic_share_of_non_ground: f64,
    /// Objects in the scene, by category.
    pub placed: ObjectCounts,
    /// Requested objects that found no collision-free place.
    pub unplaced: ObjectCounts,
}

/// A simulated sequence and its ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct SimSequence {
    /// Points of each sweep in that sweep's sensor frame (x forward, y left, z up; metres; no
    /// ego-motion compensation), in firing order (azimuth-major).
    pub frames: Vec<Vec<Point>>,
    /// Time of each sweep (s), `k / frame_rate_hz`.
    pub timestamps_s: Vec<f64>,
    /// Sensor-to-world pose of each sweep, row-major 4 x 4.
    pub ego_poses: Vec<[f64; 16]>,
    /// Per frame, per point: the body hit and the ground flag.
    pub truth: Vec<Vec<FrameTruth>>,
    /// Every body; `objects[i].id == i`, object 0 is the ground.
    pub objects: Vec<ObjectInfo>,
    /// Counts.
    pub summary: SimSummary,
}

/// Simulates a sequence. Deterministic: the same parameters give bit-identical output.
///
/// Each sweep is modelled as instantaneous at `k / frame_rate_hz`. Cost: scene placement
/// O(objects^2 x frames) once, then per frame O(rays x candidate primitives per azimuth column)
/// on the rayon pool.
pub fn simulate(params: &SimParams) -> Result<SimSequence, SimError> {
    params.validate()?;
    let timestamps_s: Vec<f64> = (0..params.frames).map(|k| k as f64 / params.frame_rate_hz).collect();
    let scene = scene::generate(params, &timestamps_s);
    let pattern = RayPattern::new(&params.lidar);
    let mut caster = Caster::default();
    let mut prims = Vec::new();
    let n = params.frames;
    let (mut frames, mut truth, mut ego_poses) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
    for (k, &t) in timestamps_s.iter().enumerate() {
        prims.clear();
        for (id, body) in scene.bodies.iter().enumerate() {
            body.prims_at(t, id as u32, &mut prims);
        }
        let ego = scene.ego.motion.pose_at(t);
        let origin = raycast::sensor_origin(&ego, params.lidar.mount_height_m);
        let hits = caster.trace(&prims, origin, &pattern, ego.yaw, params.lidar.max_range_m);
        // Stream 0 places the scene; stream k + 1 draws the noise of sweep k.
        let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
        rng.set_stream(k as u64 + 1);
        let sweep = raycast::measure(hits, &pattern, &params.lidar, &mut rng);
        frames.push(sweep.points);
        truth.push(sweep.bodies.iter().map(|&b| FrameTruth { object_id: b, is_ground: b == 0 }).collect());
        ego_poses.push(ego.matrix(params.lidar.mount_height_m));
    }
    let objects: Vec<ObjectInfo> = scene
        .bodies
        .iter()
        .enumerate()
        .map(|(id, b)| ObjectInfo {
            id: id as u32,
            kind: b.kind,
            behaviour: b.behaviour,
            dynamic: b.motion.is_dynamic(),
            poses: timestamps_s.iter().map(|&t| b.motion.pose_at(t).matrix(0.0)).collect(),
        })
        .collect();
    let mut placed = ObjectCounts::default();
    for o in &objects {
        placed.add(o.kind, o.behaviour);
    }
    let count = |f: &dyn Fn(&FrameTruth) -> bool| -> Vec<usize> {
        truth.iter().map(|fr: &Vec<FrameTruth>| fr.iter().filter(|t| f(t)).count()).collect()
    };
    let points_per_frame: Vec<usize> = frames.iter().map(Vec::len).collect();
    let ground_points_per_frame = count(&|t| t.is_ground);
    let dynamic_points_per_frame = count(&|t| objects[t.object_id as usize].dynamic);
    let total: usize = points_per_frame.iter().sum();
    let ground: usize = ground_points_per_frame.iter().sum();
    let dynamic: usize = dynamic_points_per_frame.iter().sum();
    let share = |num: usize, den: usize| if den == 0 { 0.0 } else { num as f64 / den as f64 };
    let summary = SimSummary {
        frames: n,
        rays_per_frame: pattern.azimuths.len() * pattern.elevations.len(),
        dynamic_point_share: share(dynamic, total),
        dynamic_share_of_non_ground: share(dynamic, total - ground),
        points_per_frame,
        ground_points_per_frame,
        dynamic_points_per_frame,
        placed,
        unplaced: scene.unplaced,
    };
    Ok(SimSequence { frames, timestamps_s, ego_poses, truth, objects, summary })
}

impl SimSequence {
    fn check_frame(&self, index: usize) -> Result<(), SimError> {
        if index >= self.frames.len() {
            return Err(SimError::FrameOutOfRange { index, frames: self.frames.len() });
        }
        Ok(())
    }

    /// Exact position of every point of frame `k` at the time of frame `j`, in frame `j`'s
    /// sensor coordinates (m), in frame `k`'s point order. Computed in f64 from the rigid motion
    /// of the body each point hit and the ego poses; O(points of frame k).
    pub fn positions_at(&self, k: usize, j: usize) -> Result<Vec<Point>, SimError> {
        self.check_frame(k)?;
        self.check_frame(j)?;
        let sensor_k = &self.ego_poses[k];
        let world_to_sensor_j = rigid_inverse(&self.ego_poses[j]);
        // One transform per body: sensor k -> world (t_k) -> body -> world (t_j) -> sensor j.
        let per_object: Vec<[f64; 16]> = self
            .objects
            .iter()
            .map(|o| {
                let body_motion = mat_mul(&o.poses[j], &rigid_inverse(&o.poses[k]));
                mat_mul(&world_to_sensor_j, &mat_mul(&body_motion, sensor_k))
            })
            .collect();
        Ok(self.frames[k]
            .iter()
            .zip(&self.truth[k])
            .map(|(p, t)| {
                let q = apply(&per_object[t.object_id as usize], [p[0] as f64, p[1] as f64, p[2] as f64]);
                [q[0] as f32, q[1] as f32, q[2] as f32]
            })
            .collect())
    }

    /// Ground-truth scene flow of frame `k` (m): `positions_at(k, k + 1)` minus frame `k`'s
    /// points, in frame `k + 1`'s sensor coordinates minus frame `k`'s, i.e. including the
    /// apparent motion of the static world caused by the ego motion. Needs `k + 1 < frames`.
    pub fn scene_flow(&self, k: usize) -> Result<Vec<Point>, SimError> {
        self.check_frame(k + 1)?;
        let moved = self.positions_at(k, k + 1)?;
        Ok(moved.iter().zip(&self.frames[k]).map(|(m, p)| [m[0] - p[0], m[1] - p[1], m[2] - p[2]]).collect())
    }

    /// Whether each point of frame `k` lies on a body that moves in the world.
    pub fn is_dynamic(&self, k: usize) -> Result<Vec<bool>, SimError> {
        self.check_frame(k)?;
        Ok(self.truth[k].iter().map(|t| self.objects[t.object_id as usize].dynamic).collect())
    }

    /// The frames `range` of the sequence as a sequence of their own (their times, poses, truth
    /// and the objects' poses at those frames; the scene is the whole sequence's): a window of a
    /// long log scored as a short job on the same frames.
    pub fn frames_range(&self, range: std::ops::Range<usize>) -> Result<SimSequence, SimError> {
        if range.is_empty() {
            return Err(SimError::FrameOutOfRange { index: range.start, frames: self.frames.len() });
        }
        self.check_frame(range.end - 1)?;
        let objects =
            self.objects.iter().map(|o| ObjectInfo { poses: o.poses[range.clone()].to_vec(), ..o.clone() }).collect();
        let mut summary = self.summary.clone();
        summary.frames = range.len();
        summary.points_per_frame = summary.points_per_frame[range.clone()].to_vec();
        summary.ground_points_per_frame = summary.ground_points_per_frame[range.clone()].to_vec();
        summary.dynamic_points_per_frame = summary.dynamic_points_per_frame[range.clone()].to_vec();
        Ok(SimSequence {
            frames: self.frames[range.clone()].to_vec(),
            timestamps_s: self.timestamps_s[range.clone()].to_vec(),
            ego_poses: self.ego_poses[range.clone()].to_vec(),
            truth: self.truth[range].to_vec(),
            objects,
            summary,
        })
    }

    /// The sequence as the fitting code takes it: frames, timestamps and sensor poses.
    pub fn to_fit_sequence(&self) -> crate::fit::Sequence {
        crate::fit::Sequence {
            frames: self.frames.clone(),
            timestamps_s: Some(self.timestamps_s.clone()),
            poses: Some(self.ego_poses.clone()),
        }
    }
}
