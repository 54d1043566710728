//! **Ours:** rigid tracks of moving clusters, a refinement applied after the network fit.
//!
//! On the benchmark's sequences the multi-body term holds every moving car still
//! (docs/benchmarks.md, section 3): the fitted field answers the static world well and the moving
//! bodies not at all. A car, though, is what point-to-point ICP registers well: a compact rigid
//! cluster that moves by less than a metre between sweeps. So after the fit, every DBSCAN cluster
//! of every frame is tested: does one rigid motion to the neighbouring frame explain it clearly
//! better than standing still? If so it is a moving body, and its motion to every other frame is
//! followed by ICP, frame by frame, from a constant-velocity guess. Queries on a point of such a
//! cluster are then answered by the cluster's rigid track instead of the network.
//!
//! The test is deliberately strict (a static cluster seen from a moving sensor is resampled, so
//! any motion aligns its samples a little better): the mean distance to the neighbouring frame must
//! drop by at least [`TrackParams::min_gain_m`] and to at most half. Static clusters stay with the
//! network; a moving body the test misses loses nothing against the network alone.
//!
//! Pure computation on prepared frames (fit coordinates): no I/O, parallel over clusters on
//! rayon, with a progress callback that can stop it.

use std::ops::ControlFlow;

use rayon::prelude::*;

use crate::geometry::Point;
use crate::geometry::knn::{KdTree, Nearest};
use crate::geometry::rigid::{Rigid, fit_rigid_icp};
use crate::model::RigidTrack;

/// Parameters of the tracker; the defaults are what docs/benchmarks.md measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackParams {
    /// A cluster is moving when one rigid motion to the next frame lowers its mean distance to
    /// that frame by at least this much (m)...
    pub min_gain_m: f64,
    /// ...and to at most this share of the standing-still distance.
    pub max_residual_share: f64,
    /// ICP correspondences farther than this are dropped, and distances are capped here (m).
    pub max_corr_dist_m: f32,
    /// The first step searches translations on a square grid of this half-width (m)...
    pub search_half_width_m: f64,
    /// ...with this spacing (m), refining each start by a few ICP rounds.
    pub search_step_m: f64,
    /// ICP rounds per step of a track.
    pub icp_iterations: usize,
    /// Clusters are registered on an even subsample of at most this many points.
    pub max_track_points: usize,
}

impl TrackParams {
    /// The seed test's verdict on a cluster's mean distances (m) to another sweep, left standing
    /// (`still_m`) and carried by a motion (`moved_m`): the motion explains it clearly better.
    pub fn clearly_moved(&self, still_m: f64, moved_m: f64) -> bool {
        still_m - moved_m >= self.min_gain_m && moved_m <= self.max_residual_share * still_m
    }
}

impl Default for TrackParams {
    fn default() -> Self {
        Self {
            min_gain_m: 0.12,
            max_residual_share: 0.5,
            max_corr_dist_m: 1.0,
            search_half_width_m: 1.6,
            search_step_m: 0.4,
            icp_iterations: 30,
            max_track_points: 512,
        }
    }
}

/// Buffers of [`mean_distance_m`], reused across the many calls of one cluster's search.
#[derive(Default)]
pub(crate) struct DistanceScratch {
    moved: Vec<Point>,
    hits: Vec<Nearest>,
}

/// Mean distance (m) from `src` moved by `motion` to the nearest point of `tree`, each distance
/// capped at `cap_m` so that a few stray points do not dominate.
pub(crate) fn mean_distance_m(
    src: &[Point],
    motion: &Rigid,
    tree: &KdTree,
    cap_m: f32,
    scratch: &mut DistanceScratch,
) -> f64 {
    scratch.moved.clear();
    scratch.moved.extend(src.iter().map(|p| motion.apply(p)));
    scratch.hits.resize(src.len(), Nearest { index: 0, dist2: 0.0 });
    if src.is_empty() || !tree.nearest_batch(&scratch.moved, &mut scratch.hits) {
        return f64::from(cap_m);
    }
    scratch.hits.iter().map(|h| f64::from(h.dist2.sqrt().min(cap_m))).sum::<f64>() / src.len() as f64
}

/// Length of a motion's translation (m).
fn shift_m(m: &Rigid) -> f64 {
    m.translation.iter().map(|t| t * t).sum::<f64>().sqrt()
}

/// The best first step of `src` onto `target`: ICP from every start of a translation grid, the
/// lowest mean distance winning (the smaller motion on a tie within 1 mm). Returns the motion
/// and its mean distance.
fn search_first_step(
    src: &[Point],
    tree: &KdTree,
    target: &[Point],
    params: &TrackParams,
    scratch: &mut DistanceScratch,
) -> (Rigid, f64) {
    let half = (params.search_half_width_m / params.search_step_m).round() as i32;
    let mut best = (Rigid::identity(), f64::INFINITY);
    for ix in -half..=half {
        for iy in -half..=half {
            let mut start = Rigid::identity();
            start.translation = [f64::from(ix) * params.search_step_m, f64::from(iy) * params.search_step_m, 0.0];
            let motion = fit_rigid_icp(src, tree, target, start, 8, params.max_corr_dist_m);
            let distance = mean_distance_m(src, &motion, tree, params.max_corr_dist_m, scratch);
            let better = distance < best.1 - 1e-3 || (distance < best.1 + 1e-3 && shift_m(&motion) < shift_m(&best.0));
            if better {
                best = (motion, distance.min(best.1));
            }
        }
    }
    best
}

/// Clusters the tracker tests between two calls of its progress callback: small enough that a
/// cancel takes effect within about a second, large enough to keep both cores busy.
pub(crate) const CLUSTERS_PER_STEP: usize = 16;

/// Tracks of the moving clusters of every frame. `frames[k]` are frame k's points in fit
/// coordinates with `trees[k]` built over them, and `clusters[k]` its DBSCAN clusters (indices
/// into `frames[k]`), and `times[k]` its time (s, or the frame index). Deterministic: no
/// randomness, and the result does not depend on the thread count.
///
/// A track is followed at most `max_extrapolation` (in the units of `times`) past the last frame
/// its cluster was found in (see [`TRACK_MIN_SUPPORT`]); beyond, its motion is held (see
/// `super::extrapolation_horizon`).
///
/// `on_step(done, total)` is called from the calling thread after every
/// [`CLUSTERS_PER_STEP`] clusters tested (and once at the end) with the clusters tested so far;
/// returning `ControlFlow::Break` stops the search, and the function returns `None`.
pub fn track_moving_clusters(
    frames: &[&[Point]],
    trees: &[&KdTree],
    clusters: &[&[Vec<u32>]],
    times: &[f64],
    max_extrapolation: f64,
    params: &TrackParams,
    on_step: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Option<Vec<RigidTrack>> {
    let t = frames.len();
    if t < 2 {
        return Some(Vec::new());
    }
    // Every (frame, cluster) pair in frame order: the order of the result.
    let work: Vec<(usize, &[u32])> = (0..t).flat_map(|k| clusters[k].iter().map(move |c| (k, c.as_slice()))).collect();
    let mut tracks = Vec::new();
    for (step, chunk) in work.chunks(CLUSTERS_PER_STEP).enumerate() {
        let found: Vec<RigidTrack> = chunk
            .par_iter()
            .filter_map(|&(k, cluster)| track_cluster(k, cluster, frames, trees, times, max_extrapolation, params))
            .collect();
        tracks.extend(found);
        let done = (step * CLUSTERS_PER_STEP + chunk.len()).min(work.len());
        if on_step(done, work.len()).is_break() {
            return None;
        }
    }
    Some(tracks)
}

/// The test step of one cluster of frame `k`: when one rigid motion to the frame `gap` frames
/// later (earlier, near the end) explains the cluster clearly better than standing still, that
/// frame and the motion; `None` when the cluster is not clearly moving. `src` is the cluster's
/// registration subsample.
pub(crate) fn moving_step(
    k: usize,
    gap: usize,
    src: &[Point],
    frames: &[&[Point]],
    trees: &[&KdTree],
    params: &TrackParams,
) -> Option<(usize, Rigid)> {
    let t = frames.len();
    if src.len() < 3 || gap == 0 {
        return None;
    }
    let probe = if k + gap < t {
        k + gap
    } else if k >= gap {
        k - gap
    } else {
        return None;
    };
    let mut scratch = DistanceScratch::default();
    let still = mean_distance_m(src, &Rigid::identity(), trees[probe], params.max_corr_dist_m, &mut scratch);
    if still < params.min_gain_m {
        return None; // no motion can gain enough
    }
    let (first, moved) = search_first_step(src, trees[probe], frames[probe], params, &mut scratch);
    if !params.clearly_moved(still, moved) {
        return None;
    }
    Some((probe, first))
}

/// An even subsample of at most `max_points` of a cluster's points.
pub(crate) fn cluster_subsample(frame: &[Point], cluster: &[u32], max_points: usize) -> Vec<Point> {
    let stride = cluster.len().div_ceil(max_points).max(1);
    cluster.iter().step_by(stride).map(|&i| frame[i as usize]).collect()
}

/// A step of a track finds its cluster when the cluster moved there lies this close to the
/// frame's points, as a share of [`TrackParams::max_corr_dist_m`] (mean capped distance): a
/// registered cluster is within its sampling spacing (~0.1 m), one predicted into empty space
/// at the cap.
pub const TRACK_MIN_SUPPORT: f64 = 0.5;

/// The track of one cluster of frame `k`, or `None` when it is not clearly moving.
fn track_cluster(
    k: usize,
    cluster: &[u32],
    frames: &[&[Point]],
    trees: &[&KdTree],
    times: &[f64],
    max_extrapolation: f64,
    params: &TrackParams,
) -> Option<RigidTrack> {
    let t = frames.len();
    let src = cluster_subsample(frames[k], cluster, params.max_track_points);
    let (probe, first) = moving_step(k, 1, &src, frames, trees, params)?;
    let mut motions = vec![Rigid::identity(); t];
    let mut scratch = DistanceScratch::default();
    // Forward from k, then backward from k: each step starts from the constant-velocity guess
    // (the last step repeated) and is refined by ICP against that frame. The compositions go
    // through unit quaternions (`Rigid::compose`), so the chain stays a rotation however long.
    for forward in [true, false] {
        let steps: Vec<usize> = if forward { (k + 1..t).collect() } else { (0..k).rev().collect() };
        let mut previous = Rigid::identity();
        let mut current = Rigid::identity();
        let mut last_seen = times[k];
        for (n, j) in steps.into_iter().enumerate() {
            if (times[j] - last_seen).abs() > max_extrapolation {
                // Past the horizon the cluster is no longer predicted (issue 21: a car that left
                // the view was driven on for 75 frames): the track holds its last motion.
                motions[j] = current;
                continue;
            }
            let guess = if n == 0 {
                // The test step, reversed when this chain runs the other way.
                if forward == (probe > k) { first } else { first.inverse() }
            } else {
                current.compose(&previous.inverse()).compose(&current)
            };
            let next = fit_rigid_icp(&src, trees[j], frames[j], guess, params.icp_iterations, params.max_corr_dist_m);
            let cap_m = params.max_corr_dist_m;
            if mean_distance_m(&src, &next, trees[j], cap_m, &mut scratch) < TRACK_MIN_SUPPORT * f64::from(cap_m) {
                last_seen = times[j];
            }
            previous = current;
            current = next;
            motions[j] = current;
        }
    }
    let points = cluster.iter().map(|&i| frames[k][i as usize]).collect();
    Some(RigidTrack { frame: k, points, motions })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Points on the surface of an axis-aligned box, resampled at random each frame as a sensor
    /// would (a new draw per frame, not the same points moved).
    fn box_surface(rng: &mut ChaCha8Rng, n: usize, min: [f32; 3], size: [f32; 3]) -> Vec<Point> {
        (0..n)
            .map(|_| {
                let mut p: [f32; 3] = std::array::from_fn(|c| min[c] + rng.random_range(0.0..size[c]));
                let face = rng.random_range(0..6);
                let axis = face / 2;
                p[axis] = if face % 2 == 0 { min[axis] } else { min[axis] + size[axis] };
                p
            })
            .collect()
    }

    /// Frames of a scene, one cluster per box in every frame, and the car's true motion per frame.
    struct Scene {
        frames: Vec<Vec<Point>>,
        clusters: Vec<Vec<Vec<u32>>>,
        car_motion: Vec<Rigid>,
    }

    impl Scene {
        fn tracks(&self, params: &TrackParams) -> Vec<RigidTrack> {
            let trees: Vec<KdTree> = self.frames.iter().map(|f| KdTree::new(f)).collect();
            let frames: Vec<&[Point]> = self.frames.iter().map(Vec::as_slice).collect();
            let trees: Vec<&KdTree> = trees.iter().collect();
            let clusters: Vec<&[Vec<u32>]> = self.clusters.iter().map(Vec::as_slice).collect();
            let times: Vec<f64> = (0..frames.len()).map(|k| 0.1 * k as f64).collect();
            track_moving_clusters(
                &frames,
                &trees,
                &clusters,
                &times,
                3.0,
                params,
                &mut |_, _| ControlFlow::Continue(()),
            )
            .expect("never stopped")
        }
    }

    /// A static wall-like box and a car-sized box driving 0.8 m per frame along x, turning a
    /// little (the clusters, the tracker's input, are given: one per box).
    fn scene(frames: usize) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut scene = Scene { frames: Vec::new(), clusters: Vec::new(), car_motion: Vec::new() };
        for k in 0..frames {
            let yaw = 0.02 * k as f64;
            let motion = Rigid::from_yaw(yaw, [0.8 * k as f64, 0.005 * (k * k) as f64, 0.0]);
            let mut frame = box_surface(&mut rng, 600, [-5.0, 6.0, 0.0], [30.0, 0.5, 3.0]);
            frame.extend(box_surface(&mut rng, 400, [0.0, 0.0, 0.0], [4.2, 1.8, 1.5]).iter().map(|p| motion.apply(p)));
            scene.frames.push(frame);
            scene.clusters.push(vec![(0..600).collect(), (600..1000).collect()]);
            scene.car_motion.push(motion);
        }
        scene
    }

    #[test]
    fn the_moving_box_is_tracked_and_the_static_one_left_alone() {
        let scene = scene(8);
        let tracks = scene.tracks(&TrackParams::default());
        // One track per frame, all of the car (the wall's points are indices 0..600).
        assert_eq!(tracks.len(), 8, "{:?}", tracks.iter().map(|t| (t.frame, t.points.len())).collect::<Vec<_>>());
        for track in &tracks {
            assert_eq!(track.points.len(), 400);
            assert_eq!(track.motions[track.frame], Rigid::identity());
            // The track's motion from its frame to every frame matches the truth at the car's
            // centre to within the resampling noise (surface samples, not the same points):
            // 0.15 m is well under the 0.8 m per-frame motion and the 0.5 m of Acc.5.
            let centre = [2.1f64, 0.9, 0.75];
            let at_k = scene.car_motion[track.frame].apply_f64(centre);
            for (j, motion) in track.motions.iter().enumerate() {
                let expected = scene.car_motion[j].apply_f64(centre);
                let got = motion.apply_f64(at_k);
                let err = (0..3).map(|c| (got[c] - expected[c]).powi(2)).sum::<f64>().sqrt();
                assert!(err < 0.15, "track of frame {} to frame {j}: {err:.3} m off", track.frame);
            }
        }
    }

    #[test]
    fn a_car_that_leaves_the_view_is_followed_up_to_the_horizon_then_held_and_stays_a_rotation() {
        // 100 frames at 10 Hz: a wall, and a car turning a little as it drives 0.8 m per frame
        // along x, well clear of the wall, seen in frames 0..=20 only (issue 21's runaway case).
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let mut scene = Scene { frames: Vec::new(), clusters: Vec::new(), car_motion: Vec::new() };
        for k in 0..100 {
            let motion = Rigid::from_yaw(0.01 * k as f64, [0.8 * k as f64, 0.0, 0.0]);
            let mut frame = box_surface(&mut rng, 600, [-5.0, 8.0, 0.0], [30.0, 0.5, 3.0]);
            let mut clusters = vec![(0..600).collect()];
            if k <= 20 {
                frame.extend(
                    box_surface(&mut rng, 400, [0.0, 0.0, 0.0], [4.2, 1.8, 1.5]).iter().map(|p| motion.apply(p)),
                );
                clusters.push((600..1000).collect());
            }
            scene.frames.push(frame);
            scene.clusters.push(clusters);
            scene.car_motion.push(motion);
        }
        let tracks = scene.tracks(&TrackParams::default());
        // One track per frame the car is seen in but the last, whose test step (to frame 21)
        // finds no car.
        assert_eq!(tracks.len(), 20, "{:?}", tracks.iter().map(|t| t.frame).collect::<Vec<_>>());
        let centre = [2.1f64, 0.9, 0.75];
        for track in &tracks {
            for (j, m) in track.motions.iter().enumerate() {
                assert!(m.rotation.iter().flatten().chain(&m.translation).all(|v| v.is_finite()), "frame {j}");
                // Still a rotation: R R^T = I (a hand-composed 3 x 3 drifted to 1e212 here).
                let r = m.rotation_matrix().into_inner();
                let off = (r * r.transpose() - nalgebra::Matrix3::identity()).abs().max();
                assert!(off < 1e-9, "track of frame {} to frame {j}: R R^T off by {off:e}", track.frame);
            }
            // Followed at constant velocity for 3 s past frame 20 (to frame 50, 30 x 0.8 m on),
            // held after.
            for j in 51..100 {
                assert_eq!(track.motions[j], track.motions[50], "track of frame {} at frame {j}", track.frame);
            }
            let at_k = scene.car_motion[track.frame].apply_f64(centre);
            let last_seen = track.motions[20].apply_f64(at_k);
            let held = track.motions[99].apply_f64(at_k);
            let ahead = (0..3).map(|c| (held[c] - last_seen[c]).powi(2)).sum::<f64>().sqrt();
            assert!((20.0..=26.0).contains(&ahead), "track of frame {}: held {ahead:.1} m on", track.frame);
        }
    }

    #[test]
    fn a_static_scene_gives_no_track_and_the_result_is_deterministic() {
        let mut parked = scene(4);
        // Park the car: every frame draws it again at its frame-0 place.
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for frame in parked.frames.iter_mut() {
            frame.truncate(600);
            frame.extend(box_surface(&mut rng, 400, [0.0, 0.0, 0.0], [4.2, 1.8, 1.5]));
        }
        let params = TrackParams::default();
        assert!(parked.tracks(&params).is_empty());

        let driving = scene(5);
        let a = driving.tracks(&params);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let b = pool.install(|| driving.tracks(&params));
        assert!(!a.is_empty());
        assert_eq!(a, b);
    }

    #[test]
    fn progress_counts_every_cluster_once_and_a_break_stops_the_search() {
        // 12 frames x 2 clusters = 24 clusters: steps of 16 and 24.
        let scene = scene(12);
        let trees: Vec<KdTree> = scene.frames.iter().map(|f| KdTree::new(f)).collect();
        let frames: Vec<&[Point]> = scene.frames.iter().map(Vec::as_slice).collect();
        let trees: Vec<&KdTree> = trees.iter().collect();
        let clusters: Vec<&[Vec<u32>]> = scene.clusters.iter().map(Vec::as_slice).collect();
        let params = TrackParams::default();
        let times: Vec<f64> = (0..12).map(f64::from).collect();
        let mut seen = Vec::new();
        let all = track_moving_clusters(&frames, &trees, &clusters, &times, 30.0, &params, &mut |done, total| {
            seen.push((done, total));
            ControlFlow::Continue(())
        });
        assert_eq!(seen, vec![(16, 24), (24, 24)]);
        let all = all.expect("not stopped");
        assert_eq!(
            all.len(),
            12,
            "one track per frame, the car's: {:?}",
            all.iter().map(|t| t.points.len()).collect::<Vec<_>>()
        );
        assert!(all.iter().all(|t| t.points.len() == 400));

        let mut calls = 0;
        let stopped = track_moving_clusters(&frames, &trees, &clusters, &times, 30.0, &params, &mut |_, _| {
            calls += 1;
            ControlFlow::Break(())
        });
        assert!(stopped.is_none());
        assert_eq!(calls, 1, "the search stops at the first step that asks it to");
    }
}
