//! The finiteness check a model passes before it is saved (and after it is read).
//!
//! JSON has no NaN or infinity: serde writes them as `null`, and the header then no longer
//! parses ("invalid type: null, expected f64"). A job that succeeded with such a model answered
//! 500 on every query (issue 21), so a model with a non-finite number is refused at save time,
//! with a reason naming the part, and the job fails with that reason instead.

use super::networks::Motion;
use super::{FitReport, FittedModel, MovingBody, RigidTrack};
use crate::geometry::Point;
use crate::geometry::rigid::Rigid;
use crate::nn::Mlp;

/// A model holding a non-finite number (NaN or infinity), and where: it cannot be saved.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{part} is not finite")]
pub struct NonFiniteModel {
    /// The part holding it, e.g. "moving body 3, pose at frame 57".
    pub part: String,
}

/// `Err` naming `part()` when any of `values` is not finite (the name is built only then).
fn finite_all(values: impl IntoIterator<Item = f64>, part: impl FnOnce() -> String) -> Result<(), NonFiniteModel> {
    if values.into_iter().all(f64::is_finite) { Ok(()) } else { Err(NonFiniteModel { part: part() }) }
}

fn rigid_values(r: &Rigid) -> impl Iterator<Item = f64> + '_ {
    r.rotation.iter().flatten().chain(&r.translation).copied()
}

fn point_values(p: &Point) -> impl Iterator<Item = f64> + '_ {
    p.iter().map(|&c| f64::from(c))
}

/// The first non-finite pose of `poses`, named `what` and its frame.
fn check_poses(poses: &[Rigid], what: impl Fn(usize) -> String) -> Result<(), NonFiniteModel> {
    for (k, pose) in poses.iter().enumerate() {
        finite_all(rigid_values(pose), || what(k))?;
    }
    Ok(())
}

fn check_network(mlp: &Mlp<f32>, what: impl FnOnce() -> String) -> Result<(), NonFiniteModel> {
    match mlp.parameters().iter().position(|w| !w.is_finite()) {
        None => Ok(()),
        Some(i) => Err(NonFiniteModel { part: format!("{}, parameter {i}", what()) }),
    }
}

fn check_body(body: &MovingBody) -> Result<(), NonFiniteModel> {
    let id = body.id;
    check_poses(&body.poses, |k| format!("moving body {id}, pose at frame {k}"))?;
    finite_all(body.extent_min_m.iter().chain(&body.extent_max_m).map(|&c| f64::from(c)), || {
        format!("moving body {id}, extent")
    })?;
    for (k, members) in body.members.iter().enumerate() {
        for (i, p) in members.iter().enumerate() {
            finite_all(point_values(p), || format!("moving body {id}, member point {i} at frame {k}"))?;
        }
    }
    Ok(())
}

fn check_track(n: usize, track: &RigidTrack) -> Result<(), NonFiniteModel> {
    let frame = track.frame;
    check_poses(&track.motions, |j| format!("rigid track {n} (of frame {frame}), motion to frame {j}"))?;
    for (i, p) in track.points.iter().enumerate() {
        finite_all(point_values(p), || format!("rigid track {n} (of frame {frame}), point {i}"))?;
    }
    Ok(())
}

fn check_report(report: &FitReport) -> Result<(), NonFiniteModel> {
    let p = &report.phase_times;
    let named = [
        ("fit_seconds", report.fit_seconds),
        ("rigid_tracks_seconds", report.rigid_tracks_seconds),
        ("best_validation_loss", report.best_validation_loss.unwrap_or(0.0)),
        ("phase_times.mlp_forward_s", p.mlp_forward_s),
        ("phase_times.mlp_backward_s", p.mlp_backward_s),
        ("phase_times.nearest_s", p.nearest_s),
        ("phase_times.cycle_s", p.cycle_s),
        ("phase_times.multibody_s", p.multibody_s),
        ("phase_times.optimiser_s", p.optimiser_s),
        ("phase_times.mlp_gflop", p.mlp_gflop),
        ("phase_times.total_s", p.total_s),
    ];
    for (name, value) in named {
        finite_all([value], || format!("the fit report's {name}"))?;
    }
    for (k, pose) in report.estimated_poses.iter().flatten().enumerate() {
        finite_all(pose.iter().copied(), || format!("the fit report's estimated pose of frame {k}"))?;
    }
    // The hyper-parameters' floats are checked finite when the parameters are validated
    // (`FitParams::check`), and JSON cannot carry any other into a loaded model.
    Ok(())
}

impl FittedModel {
    /// Checks that every number the model holds is finite: the networks' weights, the frame
    /// poses, the time axis, the moving bodies (poses, extents, members), the rigid tracks, the
    /// network's free points and the report's numbers. The error names the first offending part.
    pub fn check_finite(&self) -> Result<(), NonFiniteModel> {
        match &self.motion {
            Motion::Trajectory(mlp) => check_network(mlp, || "the trajectory network".to_string())?,
            Motion::PairFlows { forward, backward } => {
                for (k, mlp) in forward.iter().enumerate() {
                    check_network(mlp, || format!("the forward flow of frames {k} -> {}", k + 1))?;
                }
                for (k, mlp) in backward.iter().enumerate() {
                    check_network(mlp, || format!("the backward flow of frames {} -> {k}", k + 1))?;
                }
            }
            // Only windows written from their model are checked (built by a fit, or read and
            // decoded); a window still holding its file's bytes is written back as read, and is
            // checked when it is decoded.
            Motion::Windows(windows) => {
                for (w, window) in windows.iter().enumerate() {
                    let Some(model) = window.written_from_model() else { continue };
                    model.check_finite().map_err(|e| NonFiniteModel {
                        part: format!("window {w} (from frame {}): {}", window.start, e.part),
                    })?;
                }
            }
        }
        for (k, &t) in self.time_axis.timestamps_s().unwrap_or_default().iter().enumerate() {
            finite_all([t], || format!("the timestamp of frame {k}"))?;
        }
        if let Some(poses) = &self.frame_poses {
            check_poses(poses, |k| format!("the sensor pose of frame {k}"))?;
        }
        for body in &self.bodies {
            check_body(body)?;
        }
        for (n, track) in self.tracks.iter().enumerate() {
            check_track(n, track)?;
        }
        for (k, points) in self.free_points.iter().enumerate() {
            for (i, (p, _)) in points.iter().enumerate() {
                finite_all(point_values(p), || format!("free point {i} of frame {k}"))?;
            }
        }
        check_report(&self.report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::tests::scene_model;

    #[test]
    fn a_finite_model_passes_and_each_poisoned_part_is_named() {
        let model = scene_model();
        assert_eq!(model.check_finite(), Ok(()));
        let refused = |m: FittedModel| m.check_finite().unwrap_err().to_string();

        let mut m = scene_model();
        m.bodies[0].poses[2].translation[1] = f64::NAN;
        assert_eq!(refused(m), "moving body 0, pose at frame 2 is not finite");

        let mut m = scene_model();
        m.bodies[0].members[3][1][0] = f32::INFINITY;
        assert_eq!(refused(m), "moving body 0, member point 1 at frame 3 is not finite");

        let mut m = scene_model();
        m.bodies[0].extent_max_m[2] = f32::NAN;
        assert_eq!(refused(m), "moving body 0, extent is not finite");

        let mut m = scene_model();
        m.frame_poses.as_mut().unwrap()[1].rotation[0][0] = f64::NEG_INFINITY;
        assert_eq!(refused(m), "the sensor pose of frame 1 is not finite");

        let mut m = scene_model();
        m.tracks.push(RigidTrack {
            frame: 1,
            points: vec![[0.0; 3]],
            motions: vec![
                Rigid::identity(),
                Rigid::identity(),
                Rigid { translation: [1e300 * 1e10, 0.0, 0.0], ..Rigid::identity() },
                Rigid::identity(),
            ],
        });
        assert_eq!(refused(m), "rigid track 0 (of frame 1), motion to frame 2 is not finite");

        let mut m = scene_model();
        m.free_points[0][1].0[2] = f32::NAN;
        assert_eq!(refused(m), "free point 1 of frame 0 is not finite");

        let mut m = scene_model();
        m.report.best_validation_loss = Some(f64::NAN);
        assert_eq!(refused(m), "the fit report's best_validation_loss is not finite");

        let mut m = scene_model();
        m.report.estimated_poses = Some(vec![[0.0; 16], [f64::NAN; 16]]);
        assert_eq!(refused(m), "the fit report's estimated pose of frame 1 is not finite");

        let mut m = scene_model();
        m.time_axis = crate::model::TimeAxis::new(Some(vec![0.0, 0.1, f64::NAN, 0.3]), 4);
        assert_eq!(refused(m), "the timestamp of frame 2 is not finite");

        let mut m = scene_model();
        let Motion::Trajectory(mlp) = &mut m.motion else { unreachable!("a trajectory model") };
        mlp.parameters_mut()[5] = f32::NAN;
        assert_eq!(refused(m), "the trajectory network, parameter 5 is not finite");
    }

    #[test]
    fn a_model_with_a_nan_is_refused_at_save_time_and_a_file_holding_one_is_refused_at_load() {
        let mut m = scene_model();
        m.bodies[0].poses[3].rotation[2][2] = f64::NAN;
        assert_eq!(m.to_bytes().unwrap_err().part, "moving body 0, pose at frame 3");
        // A network's weights are binary, so a NaN there survives the file: the reader refuses it.
        let mut m = scene_model();
        let bytes = m.to_bytes().unwrap();
        let Motion::Trajectory(mlp) = &mut m.motion else { unreachable!("a trajectory model") };
        mlp.parameters_mut()[0] = f32::NAN;
        let poisoned = m.encode();
        assert_ne!(bytes, poisoned);
        let e = FittedModel::from_bytes(&poisoned).unwrap_err();
        assert!(e.contains("parameter 0 is not finite"), "{e}");
    }

    mod random {
        use proptest::prelude::*;
        use rand::{Rng, SeedableRng};
        use rand_chacha::ChaCha8Rng;
        use std::cell::Cell;

        use super::*;
        use crate::model::TimeAxis;
        use crate::model::params::Method;

        /// Draws the numbers of a random model; about one in `1 / poison_rate` is NaN or infinite,
        /// and `poisoned` says whether any was.
        struct Numbers {
            rng: ChaCha8Rng,
            poison_rate: f64,
            poisoned: Cell<bool>,
        }

        impl Numbers {
            /// NaN or an infinity, recorded.
            fn bad(&mut self) -> f64 {
                self.poisoned.set(true);
                [f64::NAN, f64::INFINITY, f64::NEG_INFINITY][self.rng.random_range(0..3)]
            }
            fn f64(&mut self, range: std::ops::Range<f64>) -> f64 {
                if self.rng.random_bool(self.poison_rate) { self.bad() } else { self.rng.random_range(range) }
            }
            fn f32(&mut self, range: std::ops::Range<f64>) -> f32 {
                self.f64(range) as f32
            }
            fn point(&mut self) -> Point {
                std::array::from_fn(|_| self.f32(-50.0..50.0))
            }
            fn pose(&mut self) -> Rigid {
                let mut pose = Rigid::from_yaw(self.rng.random_range(-3.0..3.0), [0.0; 3]);
                pose.translation = std::array::from_fn(|_| self.f64(-50.0..50.0));
                // A poisoned rotation entry too, now and then.
                pose.rotation[0][0] =
                    if self.rng.random_bool(self.poison_rate) { self.bad() } else { pose.rotation[0][0] };
                pose
            }
            fn points(&mut self, most: usize) -> Vec<Point> {
                let n = self.rng.random_range(0..=most);
                (0..n).map(|_| self.point()).collect()
            }
        }

        /// A model with random contents of every kind a model file holds (networks, poses,
        /// timestamps, bodies, tracks, free points, report), and whether a number in it is not
        /// finite.
        fn random_model(seed: u64) -> (FittedModel, bool) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let poison_rate = [0.0, 0.002, 0.02][rng.random_range(0..3)];
            let mut n =
                Numbers { rng: ChaCha8Rng::seed_from_u64(seed ^ 0x5eed), poison_rate, poisoned: Cell::new(false) };
            let frames = rng.random_range(2..6);
            let poison_net = |n: &mut Numbers, mlp: &mut Mlp<f32>| {
                for w in mlp.parameters_mut() {
                    if n.rng.random_bool(n.poison_rate / 10.0) {
                        *w = n.bad() as f32;
                    }
                }
            };
            let (method, motion) = if rng.random_bool(0.5) {
                let width = crate::model::encoding::input_width(frames);
                let mut mlp = Mlp::<f32>::new(&[width, 8, 3 * (frames - 1)], &mut rng);
                poison_net(&mut n, &mut mlp);
                (Method::Mbnt, Motion::Trajectory(mlp))
            } else {
                let mut nets: Vec<Mlp<f32>> =
                    (0..2 * (frames - 1)).map(|_| Mlp::<f32>::new(&[3, 8, 3], &mut rng)).collect();
                for mlp in &mut nets {
                    poison_net(&mut n, mlp);
                }
                let backward = nets.split_off(frames - 1);
                (Method::Mbnsf, Motion::PairFlows { forward: nets, backward })
            };
            let timestamps = rng.random_bool(0.5).then(|| {
                let mut t = 0.0;
                (0..frames)
                    .map(|_| {
                        t += 0.05 + n.rng.random_range(0.0..0.1);
                        if n.rng.random_bool(n.poison_rate) { n.bad() } else { t }
                    })
                    .collect()
            });
            let frame_poses = rng.random_bool(0.5).then(|| (0..frames).map(|_| n.pose()).collect::<Vec<_>>());
            let bodies = (0..rng.random_range(0..3))
                .map(|id| MovingBody {
                    id,
                    poses: (0..frames).map(|_| n.pose()).collect(),
                    observed: (0..frames).map(|_| n.rng.random_bool(0.5)).collect(),
                    members: (0..frames).map(|_| n.points(4)).collect(),
                    member_counts: (0..frames).map(|_| n.rng.random_range(0..100)).collect(),
                    extent_min_m: std::array::from_fn(|_| n.f32(-3.0..0.0)),
                    extent_max_m: std::array::from_fn(|_| n.f32(0.0..3.0)),
                })
                .collect();
            let tracks = (0..rng.random_range(0..3))
                .map(|_| RigidTrack {
                    frame: n.rng.random_range(0..frames),
                    points: n.points(5),
                    motions: (0..frames).map(|_| n.pose()).collect(),
                })
                .collect();
            let still_world = frame_poses.is_some() && rng.random_bool(0.5);
            let free_points = if still_world {
                (0..frames).map(|_| n.points(3).into_iter().map(|p| (p, n.rng.random_bool(0.5))).collect()).collect()
            } else {
                Vec::new()
            };
            let report = FitReport {
                iterations: rng.random_range(0..1000),
                best_validation_loss: rng.random_bool(0.5).then(|| n.f64(0.0..1.0)),
                fit_seconds: n.f64(0.0..100.0),
                estimated_poses: rng
                    .random_bool(0.3)
                    .then(|| (0..frames).map(|_| std::array::from_fn(|_| n.f64(-1.0..1.0))).collect()),
                ..FitReport::default()
            };
            let model = FittedModel {
                method,
                time_axis: TimeAxis::new(timestamps, frames),
                report,
                motion,
                frame_poses,
                tracks,
                bodies,
                still_world,
                free_points,
            };
            (model, n.poisoned.get())
        }

        /// A query over the whole time axis, which must not panic.
        fn answers(model: &FittedModel) -> bool {
            let axis = model.time_axis();
            let (first, last) = (axis.frame_time(0), axis.frame_time(axis.frames() - 1));
            model.positions(&[[1.0, 2.0, 0.5], [-20.0, 3.0, 1.0]], first, &[first, (first + last) / 2.0, last]).is_ok()
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(256))]

            /// Through the save path, a random model either is refused (exactly when it holds a
            /// non-finite number) or loads back to the same bytes and answers.
            #[test]
            fn a_saved_model_either_loads_back_and_answers_or_was_refused(seed in any::<u64>()) {
                let (model, poisoned) = random_model(seed);
                match model.to_bytes() {
                    Err(e) => prop_assert!(poisoned, "a finite model refused: {e}"),
                    Ok(bytes) => {
                        prop_assert!(!poisoned, "a model with a non-finite number was saved");
                        let back = FittedModel::from_bytes(&bytes).map_err(TestCaseError::fail)?;
                        prop_assert!(back.to_bytes().unwrap() == bytes);
                        prop_assert!(answers(&back));
                    }
                }
            }

            /// A damaged model file (bytes changed, cut short or lengthened) is refused, or what
            /// it loads as is finite and answers: reading never panics, and a loaded model works.
            #[test]
            fn a_damaged_model_file_is_refused_or_loads_a_model_that_answers(
                seed in any::<u64>(),
                edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
                cut in prop::option::of(any::<prop::sample::Index>()),
            ) {
                let (model, _) = random_model(seed);
                let mut bytes = model.encode();
                for (at, value) in edits {
                    let i = at.index(bytes.len());
                    bytes[i] = value;
                }
                if let Some(cut) = cut {
                    bytes.truncate(cut.index(bytes.len()));
                }
                if let Ok(loaded) = FittedModel::from_bytes(&bytes) {
                    prop_assert!(loaded.check_finite().is_ok());
                    prop_assert!(answers(&loaded));
                }
            }
        }
    }
}
