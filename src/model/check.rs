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
}
