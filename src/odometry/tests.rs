//! Known ego motions through synthetic scenes, sampled like a spinning LiDAR, recovered by the
//! odometry; bad input; the real KITTI frames when present.

use std::ops::ControlFlow;

use nalgebra::{Isometry3, Matrix3, Point3, Translation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;

/// An axis-aligned box in world coordinates (m): ground, facades, buildings, poles, cars.
#[derive(Debug, Clone, Copy)]
struct Aabb {
    min: [f64; 3],
    max: [f64; 3],
}

impl Aabb {
    fn new(min: [f64; 3], max: [f64; 3]) -> Self {
        Self { min, max }
    }

    fn shifted(&self, by: [f64; 3]) -> Self {
        Self::new(std::array::from_fn(|i| self.min[i] + by[i]), std::array::from_fn(|i| self.max[i] + by[i]))
    }

    /// Distance along the ray `o + s d` to the box's surface (slab test), if hit from outside.
    fn hit(&self, o: &[f64; 3], d: &[f64; 3]) -> Option<f64> {
        let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
        for i in 0..3 {
            let inv = 1.0 / d[i];
            let (a, b) = ((self.min[i] - o[i]) * inv, (self.max[i] - o[i]) * inv);
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
        (near <= far && near > 0.0).then_some(near)
    }
}

/// A spinning LiDAR: `beams` elevations in [-24, +8] degrees, `columns` azimuths, each sweep's
/// azimuths offset at random (so no two frames sample the same surface points), 1 cm range
/// noise, 70 m range.
struct Lidar {
    beams: usize,
    columns: usize,
}

impl Lidar {
    const DEFAULT: Lidar = Lidar { beams: 32, columns: 900 };

    /// The sweep from `world_from_sensor` of the static boxes and the `moving` ones, in sensor
    /// coordinates, and how many of the points fell on a moving box.
    fn sweep(
        &self,
        world_from_sensor: &Isometry3<f64>,
        scene: &[Aabb],
        moving: &[Aabb],
        rng: &mut ChaCha8Rng,
    ) -> (Vec<Point>, usize) {
        let origin = world_from_sensor.translation.vector;
        let o = [origin.x, origin.y, origin.z];
        let azimuth_offset: f64 = rng.random::<f64>();
        let mut points = Vec::new();
        let mut on_moving = 0;
        for b in 0..self.beams {
            let elevation = (-24.0 + 32.0 * b as f64 / (self.beams - 1) as f64).to_radians();
            for c in 0..self.columns {
                let azimuth = std::f64::consts::TAU * (c as f64 + azimuth_offset) / self.columns as f64;
                let local =
                    Vector3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
                let w = world_from_sensor.rotation * local;
                let d = [w.x, w.y, w.z];
                let nearest = |boxes: &[Aabb]| boxes.iter().filter_map(|a| a.hit(&o, &d)).fold(f64::INFINITY, f64::min);
                let (s_static, s_moving) = (nearest(scene), nearest(moving));
                let s = s_static.min(s_moving);
                if s > 70.0 {
                    continue;
                }
                let noisy = s + 0.01 * (rng.random::<f64>() * 2.0 - 1.0) * 1.7;
                let p = local * noisy;
                points.push([p.x as f32, p.y as f32, p.z as f32]);
                on_moving += usize::from(s_moving < s_static);
            }
        }
        (points, on_moving)
    }
}

/// A street along +x: ground, two facades with recesses and gaps, parked cars, poles and
/// buildings at the ends, so that every direction of motion is observed.
fn street(seed: u64) -> Vec<Aabb> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut scene = vec![Aabb::new([-100.0, -60.0, -0.5], [200.0, 60.0, 0.0])];
    // Facades in 6-14 m segments, each set back by up to 1.5 m, with gaps between some.
    for side in [-1.0f64, 1.0] {
        let mut x = -60.0;
        while x < 160.0 {
            let len = rng.random_range(6.0..14.0);
            let setback = rng.random_range(0.0..1.5);
            let y0 = side * (9.0 + setback);
            let height = rng.random_range(6.0..15.0);
            scene.push(Aabb::new([x, y0.min(y0 + side * 8.0), 0.0], [x + len, y0.max(y0 + side * 8.0), height]));
            x += len + if rng.random_bool(0.3) { rng.random_range(2.0..5.0) } else { 0.0 };
        }
    }
    // Parked cars and poles on both kerbs.
    for _ in 0..40 {
        let x = rng.random_range(-50.0..150.0);
        let side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        if rng.random_bool(0.5) {
            let y = side * 6.5;
            scene.push(Aabb::new([x, y - 0.9, 0.0], [x + 4.3, y + 0.9, 1.5]));
        } else {
            let y = side * 7.8;
            scene.push(Aabb::new([x, y - 0.1, 0.0], [x + 0.2, y + 0.1, 4.0]));
        }
    }
    // Cross streets' far walls.
    scene.push(Aabb::new([-70.0, -60.0, 0.0], [-68.0, 60.0, 12.0]));
    scene.push(Aabb::new([170.0, -60.0, 0.0], [172.0, 60.0, 12.0]));
    scene
}

/// World-from-sensor poses of a vehicle at `y_m`, 1.8 m above the road, starting at x = 0 with
/// heading 0, speed `speed(t_s)` (m/s) and yaw rate `yaw_rate(t_s)` (rad/s), integrated finely.
fn drive(times_s: &[f64], y_m: f64, speed: impl Fn(f64) -> f64, yaw_rate: impl Fn(f64) -> f64) -> Vec<Isometry3<f64>> {
    let (mut x, mut y, mut yaw, mut t) = (0.0, y_m, 0.0f64, 0.0);
    let step_s: f64 = 1e-4;
    times_s
        .iter()
        .map(|&until| {
            while t < until - 1e-12 {
                let h = step_s.min(until - t);
                let (v, w) = (speed(t + h / 2.0), yaw_rate(t + h / 2.0));
                let mid = yaw + w * h / 2.0;
                x += v * h * mid.cos();
                y += v * h * mid.sin();
                yaw += w * h;
                t += h;
            }
            Isometry3::new(Vector3::new(x, y, 1.8), Vector3::new(0.0, 0.0, yaw))
        })
        .collect()
}

/// Sweeps of `scene` from `poses` (and `moving(k)` boxes at frame k).
fn sweeps(
    poses: &[Isometry3<f64>],
    scene: &[Aabb],
    moving: impl Fn(usize) -> Vec<Aabb>,
    seed: u64,
) -> (Vec<Vec<Point>>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut shares = Vec::new();
    let frames = poses
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            let (points, on_moving) = Lidar::DEFAULT.sweep(pose, scene, &moving(k), &mut rng);
            shares.push(on_moving as f64 / points.len() as f64);
            points
        })
        .collect();
    (frames, shares)
}

fn run(frames: &[Vec<Point>], times_s: &[f64]) -> Odometry {
    estimate_poses(frames, Some(times_s), &OdometryParams::default(), &mut |_, _| ControlFlow::Continue(())).unwrap()
}

/// Largest per-frame error of the estimated frame-to-frame motions: (m, degrees).
fn worst_step_error(estimate: &Odometry, truth: &[Isometry3<f64>]) -> (f64, f64) {
    let mut worst = (0.0f64, 0.0f64);
    for k in 1..truth.len() {
        let true_step = truth[k - 1].inverse() * truth[k];
        let est_step = estimate.world_from_sensor[k - 1].inverse() * estimate.world_from_sensor[k];
        let e = true_step.inverse() * est_step;
        worst.0 = worst.0.max(e.translation.vector.norm());
        worst.1 = worst.1.max(e.rotation.angle().to_degrees());
    }
    worst
}

/// The estimate's end pose error against the truth re-expressed from frame 0: (m, degrees).
fn end_error(estimate: &Odometry, truth: &[Isometry3<f64>]) -> (f64, f64) {
    let n = truth.len() - 1;
    let e = (truth[0].inverse() * truth[n]).inverse() * estimate.world_from_sensor[n];
    (e.translation.vector.norm(), e.rotation.angle().to_degrees())
}

fn times(frames: usize) -> Vec<f64> {
    (0..frames).map(|k| 0.1 * k as f64).collect()
}

/// With `ODO_DUMP=DIR`, writes a test's sequence to DIR/NAME (KITTI `.bin` frames, 4 x 4 poses,
/// timestamps), so that another odometry can be run on exactly the same frames.
fn dump(name: &str, frames: &[Vec<Point>], truth: &[Isometry3<f64>], t: &[f64]) {
    let Some(root) = std::env::var_os("ODO_DUMP") else { return };
    let dir = std::path::Path::new(&root).join(name);
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    for (k, f) in frames.iter().enumerate() {
        let bytes: Vec<u8> = f.iter().flat_map(|p| [p[0], p[1], p[2], 0.0f32]).flat_map(f32::to_le_bytes).collect();
        std::fs::write(dir.join(format!("frames/{k:06}.bin")), bytes).unwrap();
    }
    let poses: String = truth.iter().map(|p| to_row_major(p).map(|v| v.to_string()).join(" ") + "\n").collect();
    std::fs::write(dir.join("poses.txt"), poses).unwrap();
    std::fs::write(dir.join("timestamps.txt"), t.iter().map(|v| format!("{v}\n")).collect::<String>()).unwrap();
}

/// With `ODO_STEPS=1`, prints every step: where a sequence goes wrong, not only how far.
fn print_steps(name: &str, estimate: &Odometry, truth: &[Isometry3<f64>]) {
    if std::env::var_os("ODO_STEPS").is_none() {
        return;
    }
    for k in 1..truth.len() {
        let ts = truth[k - 1].inverse() * truth[k];
        let es = estimate.world_from_sensor[k - 1].inverse() * estimate.world_from_sensor[k];
        let e = ts.inverse() * es;
        let d = estimate.frames[k];
        eprintln!(
            "{name} {k}: true {:.3} est {:.3} err {:.1} cm {:.3} deg  it {} corr {} sigma {:.3} med {:.3}",
            ts.translation.vector.norm(),
            es.translation.vector.norm(),
            100.0 * e.translation.vector.norm(),
            e.rotation.angle().to_degrees(),
            d.iterations,
            d.correspondences,
            d.threshold_m,
            d.median_residual_m
        );
    }
}

fn assert_recovered(name: &str, estimate: &Odometry, truth: &[Isometry3<f64>]) {
    print_steps(name, estimate, truth);
    let (m, deg) = worst_step_error(estimate, truth);
    eprintln!("{name}: worst step error {:.2} cm, {:.4} deg; end {:?}", 100.0 * m, deg, end_error(estimate, truth));
    assert!(m <= 0.02, "{name}: a frame-to-frame motion is off by {m} m");
    assert!(deg <= 0.1, "{name}: a frame-to-frame rotation is off by {deg} degrees");
    assert_eq!(estimate.world_from_sensor[0], Isometry3::identity());
}

#[test]
fn a_straight_drive_is_recovered_within_2_cm_and_a_tenth_of_a_degree_per_frame() {
    let t = times(12);
    let truth = drive(&t, -2.0, |_| 10.0, |_| 0.0);
    let (frames, _) = sweeps(&truth, &street(1), |_| Vec::new(), 11);
    dump("straight", &frames, &truth, &t);
    assert_recovered("straight", &run(&frames, &t), &truth);
}

#[test]
fn a_turn_is_recovered_within_2_cm_and_a_tenth_of_a_degree_per_frame() {
    let t = times(12);
    // 8 m/s turning left at 17 degrees per second: 20 degrees over the sequence.
    let truth = drive(&t, -4.0, |_| 8.0, |_| 0.3);
    let (frames, _) = sweeps(&truth, &street(2), |_| Vec::new(), 12);
    dump("turning", &frames, &truth, &t);
    assert_recovered("turning", &run(&frames, &t), &truth);
}

#[test]
fn an_accelerating_drive_with_uneven_frame_times_is_recovered() {
    // From 3 m/s at 4 m/s^2, frames 80-120 ms apart: the prediction scales with each time step.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut t = vec![0.0];
    for _ in 1..12 {
        t.push(t.last().unwrap() + rng.random_range(0.08..0.12));
    }
    let truth = drive(&t, -2.0, |t_s| 3.0 + 4.0 * t_s, |t_s| 0.1 * t_s);
    let (frames, _) = sweeps(&truth, &street(3), |_| Vec::new(), 13);
    dump("accelerating", &frames, &truth, &t);
    assert_recovered("accelerating", &run(&frames, &t), &truth);
}

/// Two long parallel facades, poles on alternate kerbs every 11 m and a parked car every third
/// pole, driven through braking from 12 m/s at 5 m/s^2: frames, true poses, times.
fn corridor() -> (Vec<Vec<Point>>, Vec<Isometry3<f64>>, Vec<f64>) {
    let mut scene = vec![
        Aabb::new([-200.0, -60.0, -0.5], [300.0, 60.0, 0.0]),
        Aabb::new([-200.0, 7.0, 0.0], [300.0, 9.0, 12.0]),
        Aabb::new([-200.0, -9.0, 0.0], [300.0, -7.0, 12.0]),
    ];
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for i in 0..16 {
        let x = -20.0 + 11.0 * i as f64 + rng.random_range(0.0..3.0);
        let side = if i % 2 == 0 { 1.0 } else { -1.0 };
        scene.push(Aabb::new([x, side * 5.5 - 0.1, 0.0], [x + 0.2, side * 5.5 + 0.1, 4.0]));
        if i % 3 == 0 {
            scene.push(Aabb::new([x + 3.0, -side * 5.0 - 0.9, 0.0], [x + 7.3, -side * 5.0 + 0.9, 1.5]));
        }
    }
    // Braking: the constant-velocity prediction is wrong along the street every frame.
    let t = times(15);
    let truth = drive(&t, 0.0, |t_s| 12.0 - 5.0 * t_s, |_| 0.0);
    let (frames, _) = sweeps(&truth, &scene, |_| Vec::new(), 14);
    (frames, truth, t)
}

#[test]
fn a_street_corridor_with_poles_and_parked_cars_does_not_slide() {
    // Two long parallel facades: along the street only the poles, the cars and the facade
    // ends pin the motion. With pure planes, point-to-point residuals carry no information
    // along the street: each point's nearest map point lies about as far ahead as behind, the
    // update along the street averages to nothing, and the estimate keeps the constant-velocity
    // prediction there; a constant speed is then still recovered, but any acceleration along
    // the street would be missed (the aperture problem, filled by the prior, not observed).
    let (frames, truth, t) = corridor();
    dump("corridor", &frames, &truth, &t);
    let estimate = run(&frames, &t);
    assert_recovered("corridor", &estimate, &truth);
    let n = t.len() - 1;
    let along_m = estimate.world_from_sensor[n].translation.x - (truth[n].translation.x - truth[0].translation.x);
    assert!(along_m.abs() < 0.05, "slid {along_m} m along the street over {n} frames");
}

/// The refinement's clouds of `frames` (as the forward pass hands them over).
fn refine_frames(frames: &[Vec<Point>], params: &OdometryParams) -> Vec<refine::RefineFrame> {
    frames
        .iter()
        .map(|f| {
            let cropped = crop(f, params);
            let for_map = voxel_downsample(&cropped, 0.5 * params.voxel_m);
            refine::RefineFrame::new(&cropped, for_map, params)
        })
        .collect()
}

#[test]
fn in_the_corridor_each_frame_registered_against_its_true_neighbours_stays_within_2_cm() {
    // What the refinement can do at best: every frame from its true pose against a map of its
    // true neighbours. With the forward pass's clouds (1.5 m sources, 0.5 m maps) frame 2 moved
    // 3.7 cm along the street: the nearest map point on a pole or a corner lay a quarter of a
    // metre off (docs/benchmarks.md section 32).
    let (frames, truth, _) = corridor();
    let params = OdometryParams::default();
    let clouds: Vec<Option<refine::RefineFrame>> = refine_frames(&frames, &params).into_iter().map(Some).collect();
    let from_first: Vec<Isometry3<f64>> = truth.iter().map(|p| truth[0].inverse() * p).collect();
    for k in 0..frames.len() {
        let pose = refine::refine_frame(k, &from_first, &clouds, params.refine_window_frames, &params).unwrap();
        let off = from_first[k].inverse() * pose;
        eprintln!("frame {k}: {:+.2} cm along the street", 100.0 * off.translation.x);
        let moved_m = off.translation.vector.norm();
        assert!(moved_m < 0.02, "frame {k} moved {moved_m} m from its true pose");
    }
}

#[test]
fn the_refinement_as_frames_arrive_gives_the_bits_of_whole_sweeps_and_holds_a_few_windows() {
    let (frames, truth, _) = corridor();
    let params = OdometryParams::default();
    let clouds = refine_frames(&frames, &params);
    // Forward-pass poses a few centimetres off, differently for every frame.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let start: Vec<Isometry3<f64>> = truth
        .iter()
        .map(|p| {
            let jitter = Vector3::new(rng.random_range(-0.05..0.05), rng.random_range(-0.05..0.05), 0.0);
            Translation3::from(jitter) * truth[0].inverse() * p
        })
        .collect();
    let window = 2;
    let mut whole = start.clone();
    refine::refine_all(&mut whole, &clouds, window, &params);
    let mut streamed: Vec<Isometry3<f64>> = Vec::new();
    let mut refinement = refine::Refinement::new(window);
    let mut most_held = 0;
    for (k, cloud) in clouds.into_iter().enumerate() {
        streamed.push(start[k]);
        refinement.push(cloud, &mut streamed, &params);
        most_held = most_held.max(refinement.frames_held());
    }
    refinement.finish(&mut streamed, &params);
    assert_eq!(streamed, whole);
    assert!(most_held <= window * (REFINE_SWEEPS + 1) + 1, "held {most_held} of {} frames", frames.len());
    assert!(most_held < frames.len());
    // And it did refine: the jitter is mostly gone.
    let worst = |poses: &[Isometry3<f64>]| {
        worst_step_error(&Odometry { world_from_sensor: poses.to_vec(), frames: Vec::new() }, &truth).0
    };
    assert!(worst(&whole) < 0.5 * worst(&start), "{} -> {}", worst(&start), worst(&whole));
}

#[test]
fn a_third_of_the_points_moving_rigidly_does_not_pull_the_estimate() {
    let t = times(12);
    let truth = drive(&t, -2.0, |_| 8.0, |_| 0.0);
    // A long, tall truck overtaking on the right at 13 m/s (5 m/s relative), close by: it
    // covers a wide arc of the sweep.
    let truck = Aabb::new([-6.0, -6.6, 0.0], [10.0, -4.0, 4.5]);
    let (frames, shares) = sweeps(&truth, &street(6), |k| vec![truck.shifted([13.0 * t[k], 0.0, 0.0])], 16);
    dump("moving_third", &frames, &truth, &t);
    let mean_share = shares.iter().sum::<f64>() / shares.len() as f64;
    assert!(mean_share > 0.3, "the truck holds only {:.0} % of the points", 100.0 * mean_share);
    assert_recovered("moving third", &run(&frames, &t), &truth);
}

#[test]
fn the_estimate_has_the_same_bits_on_one_thread_and_many() {
    let t = times(5);
    let truth = drive(&t, -2.0, |_| 10.0, |_| 0.2);
    let (frames, _) = sweeps(&truth, &street(7), |_| Vec::new(), 17);
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(|| run(&frames, &t));
    let many = rayon::ThreadPoolBuilder::new().num_threads(4).build().unwrap().install(|| run(&frames, &t));
    assert_eq!(one.row_major(), many.row_major());
}

#[test]
fn bad_input_gives_a_clear_error() {
    let none = &mut |_: usize, _: usize| ControlFlow::Continue(());
    let p = OdometryParams::default();
    let frame: Vec<Point> = (0..100).map(|i| [10.0 + i as f32 * 0.1, 5.0, 0.0]).collect();
    let e = estimate_poses(std::slice::from_ref(&frame), None, &p, none).unwrap_err();
    assert_eq!(e, OdometryError::TooFewFrames { frames: 1 });
    assert!(e.to_string().contains("at least 2 frames"), "{e}");
    let e = estimate_poses(&[frame.clone(), Vec::new()], None, &p, none).unwrap_err();
    assert!(matches!(e, OdometryError::EmptyFrame { frame: 1, .. }), "{e:?}");
    assert!(e.to_string().contains("frame 1 has no points"), "{e}");
    // Only returns from the vehicle itself: empty once cropped.
    let e = estimate_poses(&[frame.clone(), vec![[0.5, 0.0, 0.0]]], None, &p, none).unwrap_err();
    assert!(matches!(e, OdometryError::EmptyFrame { frame: 1, .. }), "{e:?}");
    let mut bad = frame.clone();
    bad[7][2] = f32::NAN;
    let e = estimate_poses(&[frame.clone(), bad], None, &p, none).unwrap_err();
    assert_eq!(e, OdometryError::NonFinitePoint { frame: 1, index: 7 });
    let e = estimate_poses(&[frame.clone(), frame.clone()], Some(&[0.0, 0.0]), &p, none).unwrap_err();
    assert!(matches!(e, OdometryError::BadTimestamps(_)), "{e:?}");
    let e = estimate_poses(&[frame.clone(), frame.clone()], None, &OdometryParams { voxel_m: 0.0, ..p.clone() }, none)
        .unwrap_err();
    assert!(matches!(e, OdometryError::InvalidParams { name: "voxel_m", .. }), "{e:?}");
    let too_wide = OdometryParams { refine_window_frames: 51, ..p.clone() };
    let e = estimate_poses(&[frame.clone(), frame.clone()], None, &too_wide, none).unwrap_err();
    assert!(matches!(e, OdometryError::InvalidParams { name: "refine_window_frames", .. }), "{e:?}");
    let mut calls = 0;
    let e = estimate_poses(&[frame.clone(), frame.clone(), frame], None, &p, &mut |_, _| {
        calls += 1;
        ControlFlow::Break(())
    })
    .unwrap_err();
    assert_eq!((e, calls), (OdometryError::Cancelled { frames_done: 1 }, 1));
}

/// Frames read one at a time, each an owned copy as a store would give it: the same poses and
/// diagnostics, bit for bit, as from the frames in memory.
#[test]
fn frames_read_one_at_a_time_give_the_same_bits_as_frames_in_memory() {
    let sim = crate::sim::simulate(&crate::sim::SimParams { seed: 3, frames: 8, ..Default::default() }).unwrap();
    let p = OdometryParams::default();
    let none = &mut |_: usize, _: usize| ControlFlow::Continue(());
    let in_memory = estimate_poses(&sim.frames, Some(&sim.timestamps_s), &p, none).unwrap();
    let mut read = |k: usize| Ok::<_, String>(Cow::Owned(sim.frames[k].clone()));
    let one_at_a_time = estimate_poses_from(sim.frames.len(), &mut read, Some(&sim.timestamps_s), &p, none).unwrap();
    assert_eq!(one_at_a_time.row_major(), in_memory.row_major());
    assert_eq!(one_at_a_time.frames, in_memory.frames);
    // Not trivially equal: the sensor moved.
    assert!(in_memory.world_from_sensor[7].translation.vector.norm() > 1.0);
}

#[test]
fn the_reader_is_called_once_per_frame_in_order_and_a_bad_frame_stops_it_with_the_same_error() {
    let none = &mut |_: usize, _: usize| ControlFlow::Continue(());
    let p = OdometryParams { refine_window_frames: 1, ..OdometryParams::default() };
    let t = times(4);
    let truth = drive(&t, -2.0, |_| 10.0, |_| 0.0);
    let (frames, _) = sweeps(&truth, &street(7), |_| Vec::new(), 5);
    let calls = std::cell::RefCell::new(Vec::new());
    let reader = |frames: &[Vec<Point>]| {
        let calls = &calls;
        let frames = frames.to_vec();
        move |k: usize| {
            calls.borrow_mut().push(k);
            Ok::<_, String>(Cow::Owned(frames[k].clone()))
        }
    };
    let mut read = reader(&frames);
    estimate_poses_from(4, &mut read, Some(&t), &p, none).unwrap();
    assert_eq!(*calls.borrow(), vec![0, 1, 2, 3]);
    // A frame with nothing in range, then one with a NaN, read third: the errors of the frames in
    // memory, and nothing read after the bad frame.
    let mut empty = frames.clone();
    empty[2] = vec![[0.5, 0.0, 0.0]];
    let mut nan = frames.clone();
    nan[2][11][1] = f32::NAN;
    let empty_error = OdometryError::EmptyFrame { frame: 2, min_range_m: p.min_range_m, max_range_m: p.max_range_m };
    for (bad, expected) in [(empty, empty_error), (nan, OdometryError::NonFinitePoint { frame: 2, index: 11 })] {
        assert_eq!(estimate_poses(&bad, Some(&t), &p, none).unwrap_err(), expected);
        calls.borrow_mut().clear();
        let mut read = reader(&bad);
        let e = estimate_poses_from(4, &mut read, Some(&t), &p, none).unwrap_err();
        assert!(matches!(&e, ReadOrOdometryError::Odometry(e) if *e == expected), "{e:?}, expected {expected:?}");
        assert_eq!(e.to_string(), expected.to_string());
        assert_eq!(*calls.borrow(), vec![0, 1, 2]);
    }
    // The reader's own error names the frame and stops the reading there.
    calls.borrow_mut().clear();
    let mut failing = |k: usize| {
        calls.borrow_mut().push(k);
        if k == 1 { Err("disk gone".to_string()) } else { Ok(Cow::Owned(frames[k].clone())) }
    };
    let e = estimate_poses_from(4, &mut failing, Some(&t), &p, none).unwrap_err();
    assert!(matches!(&e, ReadOrOdometryError::Read { frame: 1, error } if error == "disk gone"), "{e:?}");
    assert_eq!(e.to_string(), "frame 1 could not be read: disk gone");
    assert_eq!(*calls.borrow(), vec![0, 1]);
    // The count and the timestamps are checked before any frame is read.
    calls.borrow_mut().clear();
    let mut read = reader(&frames);
    let e = estimate_poses_from(4, &mut read, Some(&t[..3]), &p, none).unwrap_err();
    assert!(matches!(e, ReadOrOdometryError::Odometry(OdometryError::BadTimestamps(_))), "{e:?}");
    assert!(calls.borrow().is_empty());
}

#[test]
fn row_major_matrices_round_trip_and_non_rotations_are_refused() {
    let pose = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.1, -0.2, 0.3));
    let m = to_row_major(&pose);
    assert_eq!(&m[12..], &[0.0, 0.0, 0.0, 1.0]);
    let back = from_row_major(&m).unwrap();
    let p = Point3::new(3.0, 4.0, 5.0);
    assert!((back * p - pose * p).norm() < 1e-12);
    assert!(from_row_major(&m[..12]).is_some());
    let mut scaled = m;
    scaled[0] *= 1.1;
    assert!(from_row_major(&scaled).is_none());
    assert!(from_row_major(&[1.0; 9]).is_none());
}

/// Frames, their timestamps (s) and their ground-truth poses.
type Sequence = (Vec<Vec<Point>>, Vec<f64>, Vec<Isometry3<f64>>);

/// KITTI odometry sequence 00, frames 0-5, with its ground truth in the Velodyne frame; `None`
/// when ../shared/data is absent.
fn kitti_00() -> Option<Sequence> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/kitti-odometry-00");
    if !dir.join("poses_velodyne.txt").exists() {
        eprintln!("skipped: {} is absent", dir.display());
        return None;
    }
    let frames: Vec<Vec<Point>> =
        (0..6).map(|k| crate::io::read_points_file(&dir.join(format!("{k:06}.bin"))).unwrap()).collect();
    let read_numbers = |name: &str| -> Vec<f64> {
        std::fs::read_to_string(dir.join(name)).unwrap().split_whitespace().map(|w| w.parse().unwrap()).collect()
    };
    let t = read_numbers("times.txt");
    let truth = read_numbers("poses_velodyne.txt").chunks(12).map(|m| from_row_major(m).unwrap()).collect();
    Some((frames, t, truth))
}

#[test]
#[ignore = "target not met, and not reachable by registration on these frames: the scans themselves put frame 1 \
            0.67-0.69 m from frame 0 where the ground truth says 0.859 m (see the test below); KISS-ICP 1.3.0 \
            gives 16.7 % here, ours 16.9 % (docs/benchmarks.md section 8)"]
fn kitti_00_first_six_frames_are_within_one_percent_and_a_tenth_of_a_degree() {
    let Some((frames, t, truth)) = kitti_00() else { return };
    let estimate =
        estimate_poses(&frames, Some(&t), &OdometryParams::default(), &mut |_, _| ControlFlow::Continue(())).unwrap();
    let travelled_m: f64 = truth.windows(2).map(|w| (w[1].translation.vector - w[0].translation.vector).norm()).sum();
    let (m, deg) = end_error(&estimate, &truth);
    eprintln!("KITTI 00 0-5: {:.3} % of {travelled_m:.2} m, {deg:.4} deg", 100.0 * m / travelled_m);
    assert!(m / travelled_m < 0.01, "translation error {m} m over {travelled_m} m");
    assert!(deg < 0.1, "heading error {deg} degrees");
}

/// Why the KITTI target is out of reach: with the ground truth's rotation, frame 1 fits the full
/// resolution frame 0 best when moved only about 0.8 of the ground truth's translation, and our
/// first step lands there. (Every azimuth sector and range band agrees within 0.75-0.93, and the
/// reference KISS-ICP, run on these files, gives 0.70 m: docs/benchmarks.md section 8.)
#[test]
fn kitti_00_scans_put_frame_1_short_of_the_ground_truth_and_the_odometry_follows_the_scans() {
    let Some((frames, t, truth)) = kitti_00() else { return };
    let in_range = |f: &[Point]| -> Vec<Point> {
        f.iter().filter(|p| (3.0..100.0).contains(&(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())).copied().collect()
    };
    let target = in_range(&frames[0]);
    let tree = crate::geometry::knn::KdTree::new(&target);
    let source = voxel_downsample(&in_range(&frames[1]), 0.3);
    let step = truth[0].inverse() * truth[1];
    // Mean Geman-McClure cost (scale 0.1 m) of frame 1 moved by `scale` times the true translation.
    let cost = |scale: f64| -> f64 {
        let pose = Isometry3::from_parts(Translation3::from(step.translation.vector * scale), step.rotation);
        let sum: f64 = source
            .iter()
            .map(|p| {
                let q = pose * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                let d2 = f64::from(tree.nearest(&[q.x as f32, q.y as f32, q.z as f32]).unwrap().dist2);
                d2 / (d2 + 0.01)
            })
            .sum();
        sum / source.len() as f64
    };
    let profile: Vec<(f64, f64)> = (0..=24).map(|i| 0.5 + 0.025 * f64::from(i)).map(|s| (s, cost(s))).collect();
    let best = profile.iter().copied().fold((0.0, f64::INFINITY), |b, c| if c.1 < b.1 { c } else { b });
    let true_m = step.translation.vector.norm();
    eprintln!(
        "cost at the truth {:.4}, best {:.4} at {:.3} of it ({:.3} m)",
        cost(1.0),
        best.1,
        best.0,
        best.0 * true_m
    );
    assert!((0.7..0.88).contains(&best.0), "the scans' best scale is {}", best.0);
    assert!(best.1 < cost(1.0) - 0.02);
    let estimate =
        estimate_poses(&frames[..2], Some(&t[..2]), &OdometryParams::default(), &mut |_, _| ControlFlow::Continue(()))
            .unwrap();
    let ours_m = estimate.world_from_sensor[1].translation.vector.norm();
    assert!((ours_m - best.0 * true_m).abs() < 0.05, "ours {ours_m} m, the scans' best {} m", best.0 * true_m);
}

/// The project's own street simulator (trees, parked and moving cars, a turn from frame 13 on),
/// 25 frames: the end pose within 1 % of the distance and 0.3 degrees. `SEEDS=a,b` picks
/// other seeds, `ODO_STEPS=1` prints every step's error.
#[test]
fn the_simulators_streets_are_followed_within_one_percent_and_a_third_of_a_degree() {
    let seeds: Vec<u64> = std::env::var("SEEDS")
        .unwrap_or_else(|_| "1,2".into())
        .split(',')
        .map(|s| s.parse().expect("SEEDS: comma-separated integers"))
        .collect();
    for seed in seeds {
        let sim = crate::sim::simulate(&crate::sim::SimParams { seed, frames: 25, ..Default::default() }).unwrap();
        let truth: Vec<Isometry3<f64>> = sim.ego_poses.iter().map(|m| from_row_major(m).unwrap()).collect();
        let est = run(&sim.frames, &sim.timestamps_s);
        print_steps(&format!("seed {seed}"), &est, &truth);
        let (step_m, step_deg) = worst_step_error(&est, &truth);
        let (end_m, end_deg) = end_error(&est, &truth);
        let dist = (truth[0].inverse() * truth[24]).translation.vector.norm();
        eprintln!(
            "seed {seed}: worst step {:.2} cm {step_deg:.3} deg, end {end_m:.3} m ({:.2} % of {dist:.1} m) {end_deg:.3} deg",
            100.0 * step_m,
            100.0 * end_m / dist,
        );
        assert!(end_m < 0.01 * dist, "seed {seed}: end {end_m} m off after {dist} m");
        assert!(end_deg < 0.3, "seed {seed}: end rotation {end_deg} degrees off");
    }
}

#[test]
fn a_flat_patch_is_a_plane_a_pole_a_line_and_a_ring_on_the_road_says_nothing() {
    let grid = |f: &dyn Fn(f64, f64) -> Vector3<f64>| -> Vec<Vector3<f64>> {
        (0..8).flat_map(|i| (0..8).map(move |j| (i, j))).map(|(i, j)| f(0.1 * i as f64, 0.1 * j as f64)).collect()
    };
    // A road patch, tilted a little: a plane whose normal is near z.
    let road = grid(&|u, v| Vector3::new(u, v, 0.02 * u));
    match voxel::local_shape(&road, 0.05, 0.15) {
        Some(voxel::LocalShape::Plane(n)) => assert!(n.z > 0.99, "normal {n:?}"),
        other => panic!("road patch: {other:?}"),
    }
    // A wall: normal along y; the projector measures along y only.
    let wall = grid(&|u, v| Vector3::new(u, 5.0, v));
    let projector = voxel::local_shape(&wall, 0.05, 0.15).unwrap().projector();
    let moved = projector * Vector3::new(0.3, 0.2, -0.1);
    assert!((moved - Vector3::new(0.0, 0.2, 0.0)).norm() < 1e-9, "{moved:?}");
    // A pole: vertical line, measured across it.
    let pole: Vec<Vector3<f64>> = (0..20).map(|k| Vector3::new(0.01 * (k % 2) as f64, 0.0, 0.05 * k as f64)).collect();
    match voxel::local_shape(&pole, 0.05, 0.15) {
        Some(voxel::LocalShape::VerticalLine(d)) => assert!(d.z > 0.99),
        other => panic!("pole: {other:?}"),
    }
    // A ring on the road (a horizontal line): where along it the points lie moves with the sensor.
    let ring: Vec<Vector3<f64>> = (0..20).map(|k| Vector3::new(0.05 * k as f64, 0.002 * k as f64, 0.0)).collect();
    assert_eq!(voxel::local_shape(&ring, 0.05, 0.15), None);
    // A wall's foot on the road: an edge along x.
    let foot: Vec<Vector3<f64>> = (0..30)
        .flat_map(|i| (0..5).map(move |j| (i, j)))
        .flat_map(|(i, j)| {
            let x = 0.1 * i as f64;
            let s = 0.1 * j as f64;
            [Vector3::new(x, -s, 0.0), Vector3::new(x, 0.0, s)]
        })
        .collect();
    match voxel::local_shape(&foot, 0.05, 0.15) {
        Some(voxel::LocalShape::Edge(d)) => assert!(d.x > 0.99, "direction {d:?}"),
        other => panic!("wall foot: {other:?}"),
    }
    // A bush: scatter; too few points: nothing.
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let bush: Vec<Vector3<f64>> =
        (0..50).map(|_| Vector3::new(rng.random::<f64>(), rng.random::<f64>(), rng.random::<f64>())).collect();
    assert_eq!(voxel::local_shape(&bush, 0.05, 0.15), Some(voxel::LocalShape::Scatter));
    assert_eq!(voxel::local_shape(&bush[..5], 0.05, 0.15), None);
}

#[test]
fn map_shapes_follow_the_surfaces_a_sweep_hits() {
    // One sweep of a street: most voxels on the road are planes with a vertical normal, and no
    // voxel's projector is anything but a symmetric projection (P P = P) or a scaled identity.
    let truth = drive(&times(1), -2.0, |_| 0.0, |_| 0.0);
    let (frames, _) = sweeps(&truth, &street(8), |_| Vec::new(), 18);
    let world = transform_points(&truth[0], &frames[0]);
    let mut map = VoxelMap::new(1.0, 20);
    map.add(&voxel_downsample(&world, 0.5));
    let shapes = map.local_shapes(PLANE_THICKNESS_M, true);
    let mut road_planes = 0;
    let mut road = 0;
    for (key, p) in &shapes {
        let scatter = (p - Matrix3::identity() * voxel::SCATTER_SCALE).abs().max() < 1e-12;
        assert!(scatter || (p * p - p).abs().max() < 1e-9, "voxel {key:?}: {p:?} is not a projection");
        if (-1..=0).contains(&key[2]) && key[0].abs() < 15 && (-5..=4).contains(&key[1]) {
            road += 1;
            road_planes += usize::from((p[(2, 2)] - 1.0).abs() < 0.01 && p.trace() < 1.01);
        }
    }
    assert!(road >= 50, "only {road} road voxels with a shape");
    assert!(road_planes * 10 >= road * 9, "{road_planes} of {road} road voxels are horizontal planes");
}
