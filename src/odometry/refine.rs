//! The refinement after the forward pass: every frame registered again, [`REFINE_SWEEPS`] times
//! in order, against a map of its neighbours on both sides at their current poses, so that a
//! frame is held by the sweeps after it as well as before, and the first frames by more than
//! the one or two sweeps they met.
//!
//! It runs as the frames arrive ([`Refinement::push`]): sweep s refines frame k once sweep s - 1
//! (or the forward pass) has placed frame k + window, and a frame's clouds are dropped once the
//! last sweep has gone `window` frames past it, so memory holds about `window` times
//! ([`REFINE_SWEEPS`] + 1) frames, not the log. Every registration sees exactly the poses it
//! would see if each sweep ran over the whole log in turn ([`refine_all`], the twin it is tested
//! against), so the result has the same bits.

use nalgebra::Isometry3;

use super::registration::{IcpSettings, align_to_map};
use super::voxel::{VoxelMap, transform_points, voxel_downsample};
use super::{OdometryParams, PLANE_THICKNESS_M};
use crate::geometry::Point;

/// Sweeps of the refinement over the frames ([`OdometryParams::refine_window_frames`]). Each
/// sweep in order carries a correction one window further; measured on the braking corridor
/// (docs/benchmarks.md section 32): worst step 5.1 cm after 2 sweeps, 1.4 after 4, 1.4 after 6.
pub const REFINE_SWEEPS: usize = 4;

/// Correspondences farther than this are ignored in the refinement (m): the poses are already
/// within centimetres, so anything farther is another surface or something moving.
const REFINE_MAX_DISTANCE_M: f64 = 0.5;

/// Geman-McClure scale of the refinement (m).
const REFINE_KERNEL_M: f64 = 0.1;

/// The refinement's map takes each frame downsampled at this share of the voxel edge, and each
/// frame is registered there with its forward-pass map cloud (half the edge): the nearest map
/// point of a point on a pole or a corner, where the residual is point-to-point, is then
/// centimetres away rather than a quarter of a metre (measured on the corridor, each frame
/// registered from its true pose against its true neighbours: 1.34 cm rms along the street with
/// the forward pass's clouds, 0.52 cm with these; docs/benchmarks.md section 32).
const REFINE_MAP_VOXEL_SHARE: f32 = 0.2;

/// Points kept per voxel of the refinement's map: the neighbours' denser clouds.
const REFINE_POINTS_PER_VOXEL: usize = 50;

/// One frame as the refinement uses it (sensor coordinates).
#[derive(Debug, Clone)]
pub(crate) struct RefineFrame {
    /// What the neighbours' map takes of it.
    map_cloud: Vec<Point>,
    /// What is registered against its neighbours.
    source: Vec<Point>,
}

impl RefineFrame {
    /// The clouds of a cropped frame and its forward-pass map cloud.
    pub(crate) fn new(cropped: &[Point], for_map: Vec<Point>, params: &OdometryParams) -> Self {
        Self { map_cloud: voxel_downsample(cropped, REFINE_MAP_VOXEL_SHARE * params.voxel_m), source: for_map }
    }
}

/// Frame `k` registered against a map of the frames within `window` of it at `poses`, starting
/// from `poses[k]`; `None` when the registration fails. `frames[j]` must hold every frame of the
/// window.
pub(crate) fn refine_frame(
    k: usize,
    poses: &[Isometry3<f64>],
    frames: &[Option<RefineFrame>],
    window: usize,
    params: &OdometryParams,
) -> Option<Isometry3<f64>> {
    let settings = IcpSettings {
        max_distance_m: REFINE_MAX_DISTANCE_M,
        kernel_m: REFINE_KERNEL_M,
        max_iterations: params.max_iterations,
        convergence_m: params.convergence_m,
    };
    let cloud = |j: usize| frames[j].as_ref().expect("a frame of the refinement's window was dropped");
    let mut map = VoxelMap::new(params.voxel_m, REFINE_POINTS_PER_VOXEL);
    // Nearest frames first, so that full voxels keep the likeliest-overlapping points.
    let mut neighbours: Vec<usize> =
        (k.saturating_sub(window)..=(k + window).min(poses.len() - 1)).filter(|&j| j != k).collect();
    neighbours.sort_by_key(|&j| (j.abs_diff(k), j));
    for j in neighbours {
        map.add(&transform_points(&poses[j], &cloud(j).map_cloud));
    }
    let shapes = map.local_shapes(PLANE_THICKNESS_M, true);
    align_to_map(&cloud(k).source, &map, &shapes, poses[k], &settings).map(|fit| fit.world_from_sensor)
}

/// Re-expresses `poses` from frame 0's refined pose, so that frame 0 is the identity again
/// (frame 0 is refined like the others: held fixed, an offset its neighbours share could only
/// leave through frame 0's few neighbours).
fn anchor_on_first(poses: &mut [Isometry3<f64>]) {
    let first_from_world = poses[0].inverse();
    for pose in poses.iter_mut() {
        *pose = first_from_world * *pose;
    }
    poses[0] = Isometry3::identity();
}

/// The refinement of a log whose frames arrive one at a time.
#[derive(Debug)]
pub(crate) struct Refinement {
    window: usize,
    /// Per frame, its clouds until no sweep needs them any more.
    frames: Vec<Option<RefineFrame>>,
    /// Per sweep, how many frames it has refined (it refines them in order).
    refined: [usize; REFINE_SWEEPS],
}

impl Refinement {
    /// An empty refinement over windows of `window` frames on each side (at least 1).
    pub(crate) fn new(window: usize) -> Self {
        assert!(window > 0, "a refinement needs neighbours");
        Self { window, frames: Vec::new(), refined: [0; REFINE_SWEEPS] }
    }

    /// Takes the next frame (its forward-pass pose is `poses[frames so far]`) and refines every
    /// frame whose neighbours are all placed, as far as each sweep can go.
    pub(crate) fn push(&mut self, frame: RefineFrame, poses: &mut [Isometry3<f64>], params: &OdometryParams) {
        self.frames.push(Some(frame));
        self.advance(poses, false, params);
    }

    /// Refines what is left once every frame has been pushed, and anchors the poses on frame 0.
    pub(crate) fn finish(mut self, poses: &mut [Isometry3<f64>], params: &OdometryParams) {
        self.advance(poses, true, params);
        anchor_on_first(poses);
    }

    /// Frames held (for tests of the memory bound).
    #[cfg(test)]
    pub(crate) fn frames_held(&self) -> usize {
        self.frames.iter().filter(|f| f.is_some()).count()
    }

    fn advance(&mut self, poses: &mut [Isometry3<f64>], all_pushed: bool, params: &OdometryParams) {
        let pushed = self.frames.len();
        // Sweep s waits only on sweep s - 1 (or the forward pass), so one pass in sweep order
        // takes each as far as it can go.
        for s in 0..REFINE_SWEEPS {
            // Frame k needs its last neighbour placed by the sweep before; while frames still
            // come, frame k + window must have come.
            let placed = if s == 0 { pushed } else { self.refined[s - 1] };
            while self.refined[s] < pushed {
                let k = self.refined[s];
                let last_needed = if all_pushed { (k + self.window).min(pushed - 1) } else { k + self.window };
                if last_needed >= placed {
                    break;
                }
                if let Some(pose) = refine_frame(k, &poses[..pushed], &self.frames, self.window, params) {
                    poses[k] = pose;
                }
                self.refined[s] += 1;
            }
        }
        // The last sweep, the furthest behind, still needs the window before its next frame.
        let keep_from = self.refined[REFINE_SWEEPS - 1].saturating_sub(self.window);
        for frame in &mut self.frames[..keep_from] {
            *frame = None;
        }
    }
}

/// The same refinement with every frame at hand: each sweep over the whole log in turn, then
/// anchored on frame 0. The twin [`Refinement`] is tested against.
#[cfg(test)]
pub(crate) fn refine_all(poses: &mut [Isometry3<f64>], frames: &[RefineFrame], window: usize, params: &OdometryParams) {
    let frames: Vec<Option<RefineFrame>> = frames.iter().cloned().map(Some).collect();
    for _ in 0..REFINE_SWEEPS {
        for k in 0..poses.len() {
            if let Some(pose) = refine_frame(k, poses, &frames, window, params) {
                poses[k] = pose;
            }
        }
    }
    anchor_on_first(poses);
}
