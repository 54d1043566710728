//! End-to-end tests of the fitting loops on small synthetic scenes with known motion.

use std::ops::ControlFlow;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;
use crate::geometry::Point;
use crate::metrics::trajectory_metrics;

/// Points on the surface of an axis-aligned box (centre, half sizes), about `n` of them.
fn box_surface(centre: Point, half: Point, n: usize, rng: &mut ChaCha8Rng) -> Vec<Point> {
    (0..n)
        .map(|_| {
            let face = rng.random_range(0..6);
            let axis = face / 2;
            let sign = if face % 2 == 0 { -1.0 } else { 1.0 };
            std::array::from_fn(|c| {
                if c == axis { centre[c] + sign * half[c] } else { centre[c] + rng.random_range(-half[c]..half[c]) }
            })
        })
        .collect()
}

/// Rotation about z by `yaw` rad around `pivot`, then translation.
fn move_rigidly(p: &Point, pivot: &Point, yaw: f32, shift: &Point) -> Point {
    let (s, c) = yaw.sin_cos();
    let (dx, dy) = (p[0] - pivot[0], p[1] - pivot[1]);
    [pivot[0] + c * dx - s * dy + shift[0], pivot[1] + s * dx + c * dy + shift[1], p[2] + shift[2]]
}

/// Two rigid bodies over `frames` frames: a car-sized box driving +x at 0.5 m/frame and a
/// second box turning (yaw 0.05 rad/frame) while moving -y at 0.3 m/frame. Each frame samples
/// the surfaces anew (no point correspondences, like LiDAR). Returns the sequence, and frame
/// 0's points with their true positions at the last frame.
fn two_bodies(frames: usize, points_per_body: usize, seed: u64) -> (Sequence, Vec<Point>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let a_centre = [0.0, 0.0, 0.8];
    let b_centre = [0.0, 6.0, 0.8];
    let motion_a = |k: usize| (0.0, [0.5 * k as f32, 0.0, 0.0]);
    let motion_b = |k: usize| (0.05 * k as f32, [0.0, -0.3 * k as f32, 0.0]);
    let mut seq_frames = Vec::new();
    for k in 0..frames {
        let (ya, sa) = motion_a(k);
        let (yb, sb) = motion_b(k);
        let mut frame: Vec<Point> = box_surface(a_centre, [2.0, 0.9, 0.7], points_per_body, &mut rng)
            .iter()
            .map(|p| move_rigidly(p, &a_centre, ya, &sa))
            .collect();
        frame.extend(
            box_surface(b_centre, [1.0, 1.0, 0.7], points_per_body, &mut rng)
                .iter()
                .map(|p| move_rigidly(p, &b_centre, yb, &sb)),
        );
        seq_frames.push(frame);
    }
    // Frame 0 is unmoved, so its points' rest positions are themselves.
    let last = frames - 1;
    let (ya, sa) = motion_a(last);
    let (yb, sb) = motion_b(last);
    let truth = seq_frames[0]
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if i < points_per_body { move_rigidly(p, &a_centre, ya, &sa) } else { move_rigidly(p, &b_centre, yb, &sb) }
        })
        .collect();
    (Sequence { frames: seq_frames, timestamps_s: None, poses: None }, truth)
}

fn small_params(method: Method, iterations: usize) -> ValidFitParams {
    FitParams {
        iterations: Some(iterations),
        seed: Some(7),
        remove_ground: Some(false),
        hidden_width: Some(64),
        dbscan_min_points: Some(10),
        ..FitParams::default()
    }
    .check(method)
    .unwrap()
}

fn long_term_accuracy(method: Method, iterations: usize) -> crate::metrics::TrajectoryMetrics {
    long_term_accuracy_with(method, small_params(method, iterations))
}

fn long_term_accuracy_with(method: Method, params: ValidFitParams) -> crate::metrics::TrajectoryMetrics {
    let (sequence, truth) = two_bodies(5, 400, 3);
    let model = fit_sequence(&sequence, method, &params, &mut |_| ControlFlow::Continue(())).unwrap();
    let last = (sequence.frames.len() - 1) as f64;
    let predicted = model.positions(&sequence.frames[0], 0.0, &[last]).unwrap();
    trajectory_metrics(&predicted, &truth, None)
}

#[test]
fn mbnt_recovers_two_rigid_motions_over_five_frames() {
    let m = long_term_accuracy(Method::Mbnt, 300);
    eprintln!("MBNT two bodies: {m:?}");
    // The bodies move 2.0 m and 1.2 m (+ rotation) over the sequence; surfaces are resampled
    // each frame, so correspondence is only up to the sampling spacing (~0.1-0.2 m).
    assert!(m.epe_m < 0.25, "{m:?}");
    assert!(m.acc_0_5 > 0.9, "{m:?}");
}

#[test]
fn mbnt_with_a_rigidity_warm_up_still_recovers_two_rigid_motions() {
    let base = params_of(&small_params(Method::Mbnt, 300));
    let params =
        FitParams { iterations: Some(300), rigidity_warmup_iterations: Some(150), ..base }.check(Method::Mbnt).unwrap();
    assert_eq!(params.rigidity_warmup_iterations, 150);
    let m = long_term_accuracy_with(Method::Mbnt, params);
    assert!(m.epe_m < 0.25, "{m:?}");
    assert!(m.acc_0_5 > 0.9, "{m:?}");
}

#[test]
fn mbnt_with_a_fixed_rigidity_threshold_still_recovers_two_rigid_motions() {
    let base = params_of(&small_params(Method::Mbnt, 300));
    let params =
        FitParams { iterations: Some(300), d_thr_motion_fraction: Some(0.0), ..base }.check(Method::Mbnt).unwrap();
    let m = long_term_accuracy_with(Method::Mbnt, params);
    assert!(m.epe_m < 0.25, "{m:?}");
    assert!(m.acc_0_5 > 0.9, "{m:?}");
}

#[test]
fn ntp_recovers_two_rigid_motions_over_five_frames() {
    let m = long_term_accuracy(Method::Ntp, 300);
    eprintln!("NTP two bodies: {m:?}");
    assert!(m.epe_m < 0.35, "{m:?}");
    assert!(m.acc_0_5 > 0.8, "{m:?}");
}

#[test]
fn mbnsf_recovers_two_rigid_motions_by_forward_euler() {
    let m = long_term_accuracy(Method::Mbnsf, 150);
    eprintln!("MBNSF two bodies: {m:?}");
    assert!(m.epe_m < 0.35, "{m:?}");
    assert!(m.acc_0_5 > 0.8, "{m:?}");
}

#[test]
fn fast_mode_fitting_random_parts_still_recovers_the_motions() {
    // Frames of 800 points split into parts of ~200: every iteration sees a quarter of them.
    let params = FitParams {
        iterations: Some(300),
        seed: Some(7),
        remove_ground: Some(false),
        hidden_width: Some(64),
        dbscan_min_points: Some(10),
        sample_points: Some(200),
        // The cycle terms on a random quarter of each part.
        cycle_sample_points: Some(50),
        validation_patience: Some(0),
        ..FitParams::default()
    }
    .check(Method::Mbnt)
    .unwrap();
    assert!(params.d_thr_motion_fraction > 0.0, "fast mode's default");
    let m = long_term_accuracy_with(Method::Mbnt, params.clone());
    eprintln!("MBNT on parts: {m:?}");
    // Sparser Chamfer targets (about 0.3 m spacing instead of 0.15 m) loosen the fit a little.
    assert!(m.epe_m < 0.35, "{m:?}");
    assert!(m.acc_0_5 > 0.8, "{m:?}");
    let m = long_term_accuracy_with(
        Method::Mbnsf,
        FitParams { iterations: Some(150), ..params_of(&params) }.check(Method::Mbnsf).unwrap(),
    );
    eprintln!("MBNSF on parts: {m:?}");
    assert!(m.epe_m < 0.45, "{m:?}");
}

/// The user-facing parameters that reproduce `p` (for deriving a variant).
fn params_of(p: &ValidFitParams) -> FitParams {
    FitParams {
        seed: Some(p.seed),
        remove_ground: Some(p.remove_ground),
        hidden_width: Some(p.hidden_width),
        dbscan_min_points: Some(p.dbscan_min_points),
        sample_points: Some(p.sample_points),
        validation_patience: Some(p.validation_patience),
        cycle_sample_points: Some(p.cycle_sample_points),
        d_thr_motion_fraction: Some(p.d_thr_motion_fraction),
        ..FitParams::default()
    }
}

#[test]
fn the_same_seed_gives_the_same_model() {
    let (sequence, _) = two_bodies(3, 150, 1);
    let params = small_params(Method::Mbnt, 20);
    let a = fit_sequence(&sequence, Method::Mbnt, &params, &mut |_| ControlFlow::Continue(())).unwrap();
    let b = fit_sequence(&sequence, Method::Mbnt, &params, &mut |_| ControlFlow::Continue(())).unwrap();
    // Bytes differ only in the report's wall times; the weights must be bit-identical, so the
    // answers are.
    let times = [0.0, 1.0, 2.0];
    assert_eq!(
        a.positions(&sequence.frames[0], 0.0, &times).unwrap(),
        b.positions(&sequence.frames[0], 0.0, &times).unwrap()
    );
    assert_eq!(a.report().best_iteration, b.report().best_iteration);
}

#[test]
fn a_query_at_the_observation_time_returns_the_point_itself() {
    let (sequence, _) = two_bodies(4, 100, 2);
    for method in [Method::Ntp, Method::Nsfp] {
        let model =
            fit_sequence(&sequence, method, &small_params(method, 5), &mut |_| ControlFlow::Continue(())).unwrap();
        for t in [0.0, 1.0, 2.5, 3.0] {
            let pts = &sequence.frames[1][..20];
            let at = model.positions(pts, t, &[t]).unwrap();
            for (p, q) in pts.iter().zip(&at) {
                for c in 0..3 {
                    assert!((p[c] - q[c]).abs() < 1e-5, "{method:?} t={t}: {p:?} vs {q:?}");
                }
            }
        }
    }
}

#[test]
fn progress_reports_every_iteration_and_cancel_stops_the_fit() {
    let (sequence, _) = two_bodies(3, 100, 4);
    let params = small_params(Method::Ntp, 50);
    let mut seen = Vec::new();
    let result = fit_sequence(&sequence, Method::Ntp, &params, &mut |p| {
        seen.push(p.iteration);
        if p.iteration == 7 { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
    });
    assert!(matches!(result, Err(FitError::Cancelled { iteration: 7 })));
    assert_eq!(seen, (1..=7).collect::<Vec<_>>());
}

#[test]
fn early_stopping_waits_for_the_end_of_the_rigidity_warm_up() {
    let (sequence, _) = two_bodies(3, 100, 4);
    let base = params_of(&small_params(Method::Mbnt, 200));
    // Patience of two validations, one validation per iteration: without the rule a fit stops
    // at the first two validations in a row that do not improve on the best.
    let params = FitParams {
        iterations: Some(200),
        validate_every: Some(1),
        validation_patience: Some(2),
        rigidity_warmup_iterations: Some(40),
        ..base
    };
    for method in [Method::Mbnt, Method::Ntp] {
        let p = params.check(method).unwrap();
        let model = fit_sequence(&sequence, method, &p, &mut |_| ControlFlow::Continue(())).unwrap();
        let report = model.report();
        let best = report.best_iteration.unwrap();
        assert!(report.iterations == 200 || report.iterations > best + 2, "{method:?}: {report:?}");
        if method == Method::Mbnt {
            assert!(report.iterations > 40, "stopped inside the warm-up: {report:?}");
        }
    }
}

#[test]
fn a_model_survives_serialisation_and_bad_bytes_are_an_error() {
    let (sequence, _) = two_bodies(3, 100, 5);
    for method in [Method::Mbnt, Method::Mbnsf] {
        let model =
            fit_sequence(&sequence, method, &small_params(method, 3), &mut |_| ControlFlow::Continue(())).unwrap();
        let bytes = model.to_bytes().unwrap();
        let back = crate::model::FittedModel::from_bytes(&bytes).unwrap();
        assert!(back.to_bytes().unwrap() == bytes, "a model must serialise back to the same bytes");
        let q = &sequence.frames[0][..10];
        assert_eq!(model.positions(q, 0.0, &[2.0]).unwrap(), back.positions(q, 0.0, &[2.0]).unwrap());
        assert!(crate::model::FittedModel::from_bytes(&bytes[..bytes.len() / 2]).is_err());
        assert!(crate::model::FittedModel::from_bytes(b"garbage").is_err());
    }
}

#[test]
fn bad_sequences_are_rejected_with_a_reason() {
    let params = small_params(Method::Ntp, 1);
    let run = |frames: Vec<Vec<Point>>| {
        let seq = Sequence { frames, timestamps_s: None, poses: None };
        fit_sequence(&seq, Method::Ntp, &params, &mut |_| ControlFlow::Continue(())).unwrap_err().to_string()
    };
    assert!(run(vec![vec![[0.0; 3]]]).contains("at least 2 frames"));
    assert!(run(vec![vec![[0.0; 3]], vec![]]).contains("frame 1 has no points"));
    assert!(run(vec![vec![[0.0; 3]], vec![[f32::NAN, 0.0, 0.0]]]).contains("non-finite"));
}

#[test]
fn with_poses_the_ego_motion_is_removed_and_answers_stay_in_sensor_frames() {
    // A static box and a box driving +x at 0.5 m/frame, seen by a sensor that itself drives +x
    // at 1 m/frame and turns 0.02 rad/frame: in sensor coordinates everything moves.
    let frames = 5;
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let ego = |k: usize| (0.02 * k as f32, [1.0 * k as f32, 0.0, 0.0]);
    let static_centre = [6.0, 4.0, 0.8];
    let moving_centre = [3.0, -5.0, 0.8];
    let to_sensor = |p: &Point, k: usize| -> Point {
        let (yaw, t) = ego(k);
        let (s, c) = yaw.sin_cos();
        let (dx, dy) = (p[0] - t[0], p[1] - t[1]);
        [c * dx + s * dy, -s * dx + c * dy, p[2]]
    };
    let world_at =
        |p: &Point, moving: bool, k: usize| -> Point { if moving { [p[0] + 0.5 * k as f32, p[1], p[2]] } else { *p } };
    let mut seq_frames = Vec::new();
    let mut frame0_world = Vec::new();
    for k in 0..frames {
        let mut frame = Vec::new();
        for (centre, moving) in [(static_centre, false), (moving_centre, true)] {
            for p in box_surface(centre, [1.5, 0.9, 0.7], 300, &mut rng) {
                if k == 0 {
                    frame0_world.push((p, moving));
                }
                frame.push(to_sensor(&world_at(&p, moving, k), k));
            }
        }
        seq_frames.push(frame);
    }
    let poses: Vec<[f64; 16]> = (0..frames)
        .map(|k| {
            let (yaw, t) = ego(k);
            let (s, c) = (f64::from(yaw).sin(), f64::from(yaw).cos());
            [c, -s, 0.0, f64::from(t[0]), s, c, 0.0, f64::from(t[1]), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        })
        .collect();
    let last = frames - 1;
    let truth: Vec<Point> =
        frame0_world.iter().map(|(p, moving)| to_sensor(&world_at(p, *moving, last), last)).collect();
    let sequence = Sequence { frames: seq_frames, timestamps_s: None, poses: Some(poses) };
    let params = small_params(Method::Ntp, 300);
    let model = fit_sequence(&sequence, Method::Ntp, &params, &mut |_| ControlFlow::Continue(())).unwrap();
    let predicted = model.positions(&sequence.frames[0], 0.0, &[last as f64]).unwrap();
    let m = trajectory_metrics(&predicted, &truth, None);
    eprintln!("NTP with poses: {m:?}");
    // The sensor moves 4 m and turns 4.6 degrees; the box 2 m in the world.
    assert!(m.epe_m < 0.3, "{m:?}");
    assert!(m.acc_0_5 > 0.85, "{m:?}");
    // At the observation time a point is itself, in its own sensor frame (also mid-way).
    for t in [0.0, 2.5] {
        let pts = &sequence.frames[0][..20];
        for (p, q) in pts.iter().zip(model.positions(pts, t, &[t]).unwrap()) {
            assert!((0..3).all(|c| (p[c] - q[c]).abs() < 1e-4), "t={t}: {p:?} vs {q:?}");
        }
    }
    // Broken poses are an error that says which.
    let mut bad = sequence.clone();
    bad.poses.as_mut().unwrap()[2][0] = 2.0;
    let e = fit_sequence(&bad, Method::Ntp, &params, &mut |_| ControlFlow::Continue(())).unwrap_err();
    assert!(e.to_string().contains("pose 2"), "{e}");
}

/// The multi-body term holds every cluster to one rigid motion, so a DBSCAN cluster that joins
/// a moving body to static structure would hold the body back. On a simulated street (ego
/// motion removed with the poses, as fits do) clusters must keep moving and static bodies
/// apart: at most 5 % of the clustered dynamic points may share a cluster with another body.
#[test]
fn dbscan_clusters_of_a_street_scene_keep_moving_bodies_apart() {
    use crate::geometry::dbscan::{clusters, dbscan};
    use crate::geometry::ground::{PreprocessParams, preprocess};
    use crate::sim::{SimParams, simulate};

    let sim = simulate(&SimParams { seed: 7, frames: 9, ..SimParams::default() }).unwrap();
    let poses = poses_relative_to_first(&sim.ego_poses).unwrap();
    let params = FitParams::default().check(Method::Mbnt).unwrap();
    let (mut dynamic_clustered, mut dynamic_mixed) = (0usize, 0usize);
    for k in [0, 8] {
        let frame = &sim.frames[k];
        let (kept, _) = preprocess(frame, &PreprocessParams::default()).unwrap();
        let points: Vec<Point> = kept.iter().map(|&i| poses[k].apply(&frame[i as usize])).collect();
        let body = |i: u32| sim.truth[k][kept[i as usize] as usize].object_id;
        let labels = dbscan(&points, params.dbscan_eps_m, params.dbscan_min_points);
        for cluster in clusters(&labels) {
            let dynamic = cluster.iter().filter(|&&i| sim.objects[body(i) as usize].dynamic).count();
            dynamic_clustered += dynamic;
            if dynamic > 0 && cluster.iter().any(|&i| body(i) != body(cluster[0])) {
                dynamic_mixed += dynamic;
            }
        }
    }
    assert!(dynamic_clustered > 500, "the scene has moving bodies in clusters: {dynamic_clustered}");
    assert!(
        dynamic_mixed * 20 <= dynamic_clustered,
        "{dynamic_mixed} of {dynamic_clustered} clustered dynamic points share a cluster with another body"
    );
}

/// Fewest live units of each validation, in order, for a fit that validates every iteration.
fn live_units_per_validation(params: &FitParams) -> Vec<usize> {
    let (sequence, _) = two_bodies(3, 100, 4);
    let p = params.check(Method::Mbnt).unwrap();
    let mut live = Vec::new();
    fit_sequence(&sequence, Method::Mbnt, &p, &mut |progress| {
        live.extend(progress.fewest_live_units);
        ControlFlow::Continue(())
    })
    .unwrap();
    live
}

#[test]
fn a_collapsed_network_goes_back_to_its_best_checkpoint_once_per_allowed_restart() {
    let base = params_of(&small_params(Method::Mbnt, 60));
    // A rate this large kills a ReLU layer within a few Adam steps on this problem (a scan of
    // 0.03-1.0: 0.03 never, 0.1 from the eighth iteration on and for good).
    // Sensor coordinates, as the scan of rates was made in: estimated poses change the problem.
    let params = FitParams {
        iterations: Some(60),
        validate_every: Some(1),
        learning_rate: Some(0.1),
        odometry: Some(crate::fit::OdometryMode::Off),
        ..base
    };
    let without = live_units_per_validation(&params);
    let first_dead = without.iter().position(|&n| n == 0).expect("the rate is meant to kill a layer");
    assert!(without[first_dead..].iter().all(|&n| n == 0), "a dead layer stays dead: {without:?}");

    let with = live_units_per_validation(&FitParams { collapse_restarts: Some(1), ..params });
    assert_eq!(with[..=first_dead], without[..=first_dead], "identical until the first collapse");
    assert!(with[first_dead + 1] > 0, "the next validation sees the restored checkpoint: {with:?}");
    let revivals = with.windows(2).filter(|w| w[0] == 0 && w[1] > 0).count();
    assert_eq!(revivals, 1, "one restart allowed: {with:?}");
}

#[test]
fn a_network_dead_from_its_first_validation_still_returns_a_model_with_restarts_allowed() {
    let base = params_of(&small_params(Method::Mbnt, 3));
    // Sixteen layers of four units: for some seeds a layer is negative for every input from the
    // start, so there is no checkpoint to go back to; the fit must still end with a model.
    let dead_at_start = (0..64).find_map(|seed| {
        let params = FitParams {
            seed: Some(seed),
            iterations: Some(3),
            validate_every: Some(1),
            hidden_width: Some(4),
            hidden_layers: Some(16),
            zero_output_init: Some(false),
            collapse_restarts: Some(3),
            ..base.clone()
        };
        let live = live_units_per_validation(&params);
        (live[0] == 0).then_some(live)
    });
    let live = dead_at_start.expect("some seed starts dead");
    assert_eq!(live.len(), 3, "every iteration validated: {live:?}");
}

#[test]
fn rigid_tracks_carry_a_moving_body_the_network_has_not_learnt_and_survive_serialisation() {
    // Three iterations teach the network nothing; the tracks alone must carry body A (a 4 m box
    // driving 0.5 m per frame, sampled about as densely as a car near the sensor) 2.5 m on.
    let frames = 6;
    let (sequence, truth) = two_bodies(frames, 1500, 3);
    let params =
        FitParams { rigid_tracks: Some(true), iterations: Some(3), ..params_of(&small_params(Method::Mbnt, 3)) };
    let p = params.check(Method::Mbnt).unwrap();
    let model = fit_sequence(&sequence, Method::Mbnt, &p, &mut |_| ControlFlow::Continue(())).unwrap();
    assert!(model.report().rigid_tracks > 0 && model.report().rigid_tracks == model.tracks().len());
    let last = (frames - 1) as f64;
    let body_a = &sequence.frames[0][..1500];
    let error = |m: &crate::model::FittedModel| -> f64 {
        let at = m.positions(body_a, 0.0, &[last]).unwrap();
        at.iter().zip(&truth[..1500]).map(|(p, q)| crate::geometry::knn::dist2(p, q).sqrt() as f64).sum::<f64>()
            / 1500.0
    };
    let (tracked, alone) = (error(&model), error(&model.without_tracks().unwrap()));
    // Resampled surfaces register to about their sample spacing (~0.1 m here); 0.2 m leaves room.
    assert!(tracked < 0.2 && tracked < alone / 3.0, "with tracks {tracked:.3} m, network alone {alone:.3} m");

    let bytes = model.to_bytes().unwrap();
    let back = crate::model::FittedModel::from_bytes(&bytes).unwrap();
    assert_eq!(back.tracks(), model.tracks());
    assert!(back.to_bytes().unwrap() == bytes);
    assert_eq!(model.positions(body_a, 0.5, &[0.0, 3.2]).unwrap(), back.positions(body_a, 0.5, &[0.0, 3.2]).unwrap());
}

#[test]
fn building_the_rigid_tracks_reports_progress_and_can_be_cancelled() {
    let frames = 6;
    let (sequence, _) = two_bodies(frames, 1500, 3);
    let params =
        FitParams { rigid_tracks: Some(true), iterations: Some(3), ..params_of(&small_params(Method::Mbnt, 3)) };
    let p = params.check(Method::Mbnt).unwrap();
    let mut tracking = Vec::new();
    fit_sequence(&sequence, Method::Mbnt, &p, &mut |progress| {
        if let Some(t) = progress.rigid_tracks {
            // The iteration fields keep the last iteration's values meanwhile.
            assert_eq!(progress.iteration, 3);
            // ...but no validation is reported again.
            assert!(progress.validation_loss.is_none() && progress.fewest_live_units.is_none());
            tracking.push(t);
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    let last = tracking.last().expect("tracking reported progress");
    assert!(last.clusters > 0 && last.clusters_done == last.clusters);
    assert!(tracking.windows(2).all(|w| w[0].clusters_done < w[1].clusters_done));

    // A cancel while the tracks are built ends the fit like a cancel between iterations.
    let result = fit_sequence(&sequence, Method::Mbnt, &p, &mut |progress| {
        if progress.rigid_tracks.is_some() { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
    });
    assert!(matches!(result, Err(FitError::Cancelled { iteration: 3 })), "{result:?}");
}
