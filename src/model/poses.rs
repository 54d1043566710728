//! Pose interpolation between frames.

use nalgebra::Isometry3;

use crate::geometry::rigid::Rigid;

/// The sensor-to-fit-frame transform at fractional frame index `u`: between two frames the
/// rotation turns at a constant rate about one axis (slerp) and the translation moves linearly.
pub(super) fn pose_at(poses: &[Rigid], u: f64) -> Rigid {
    let k = (u.max(0.0).floor() as usize).min(poses.len() - 1);
    let a = u - k as f64;
    if k + 1 >= poses.len() || a <= 0.0 {
        return poses[k];
    }
    let (p, q) = (poses[k].to_isometry(), poses[k + 1].to_isometry());
    // try_slerp declines only for two rotations equal to rounding (no arc to follow), where
    // either is the answer; the shorter arc is taken otherwise, as a turn between frames is.
    let rotation = p.rotation.try_slerp(&q.rotation, a, f64::EPSILON).unwrap_or(p.rotation);
    Isometry3::from_parts(p.translation.vector.lerp(&q.translation.vector, a).into(), rotation).into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_interpolate_by_constant_turn_rate_and_linear_translation() {
        let yaw = |a: f64| Rigid {
            rotation: [[a.cos(), -a.sin(), 0.0], [a.sin(), a.cos(), 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
        };
        let mut end = yaw(std::f64::consts::FRAC_PI_2);
        end.translation = [2.0, 4.0, -2.0];
        let poses = [Rigid::identity(), end];
        let mid = pose_at(&poses, 0.5);
        let expected = yaw(std::f64::consts::FRAC_PI_4);
        for i in 0..3 {
            for j in 0..3 {
                assert!((mid.rotation[i][j] - expected.rotation[i][j]).abs() < 1e-12, "{mid:?}");
            }
        }
        assert_eq!(mid.translation, [1.0, 2.0, -1.0]);
        assert_eq!(pose_at(&poses, 1.0), end);
        assert_eq!(pose_at(&poses, 0.0), Rigid::identity());
    }
}
