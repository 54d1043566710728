//! Rigid transforms of point clouds: the least-squares fit for corresponding points (Horn's
//! quaternion method) and point-to-point ICP on top of it.
//!
//! The arithmetic is f64 and goes through nalgebra: fits sum tens of thousands of products of
//! metric coordinates, and the result is only a 3 x 4 matrix, so precision costs nothing here.

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Quaternion, Rotation3, SymmetricEigen, Translation3, UnitQuaternion, Vector3,
};
use serde::{Deserialize, Serialize};

use super::Point;
use super::knn::{KdTree, Nearest};

/// A proper rigid motion x ↦ R x + t (R orthonormal, det R = +1), metric (m).
///
/// The fields are the model files' layout (`{"rotation": [[..], [..], [..]], "translation": [..]}`)
/// and hold R as given, so that poses read from a file are applied exactly as written; the
/// algebra (compose, inverse, interpolation) goes through [`Rigid::to_isometry`], whose unit
/// quaternion keeps every product a rotation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rigid {
    /// Rotation matrix R, row-major.
    pub rotation: [[f64; 3]; 3],
    /// Translation t (m).
    pub translation: [f64; 3],
}

impl Default for Rigid {
    fn default() -> Self {
        Self::identity()
    }
}

impl From<Isometry3<f64>> for Rigid {
    fn from(isometry: Isometry3<f64>) -> Self {
        Self::from_rotation(&isometry.rotation.to_rotation_matrix(), isometry.translation.vector.into())
    }
}

impl From<&Rigid> for Isometry3<f64> {
    fn from(rigid: &Rigid) -> Self {
        rigid.to_isometry()
    }
}

impl Rigid {
    /// The identity motion.
    pub fn identity() -> Self {
        Self { rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], translation: [0.0; 3] }
    }

    /// The motion with rotation `rotation` (taken as is) and translation `translation` (m).
    pub fn from_rotation(rotation: &Rotation3<f64>, translation: [f64; 3]) -> Self {
        let m = rotation.matrix();
        Self { rotation: std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)])), translation }
    }

    /// A turn of `yaw_rad` about z, then the translation `translation` (m).
    pub fn from_yaw(yaw_rad: f64, translation: [f64; 3]) -> Self {
        Self::from_rotation(&Rotation3::from_axis_angle(&Vector3::z_axis(), yaw_rad), translation)
    }

    /// R as nalgebra's rotation type, exactly as stored (no re-orthonormalisation).
    pub fn rotation_matrix(&self) -> Rotation3<f64> {
        Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(self.rotation.as_flattened()))
    }

    /// The motion as an isometry with a unit-quaternion rotation. The quaternion is normalised,
    /// so a stored R that is orthonormal only to its rounding (or to the digits of a pose file)
    /// becomes an exact rotation, and compositions of isometries stay rotations.
    pub fn to_isometry(&self) -> Isometry3<f64> {
        let q = UnitQuaternion::from_rotation_matrix(&self.rotation_matrix());
        Isometry3::from_parts(Translation3::from(self.translation), UnitQuaternion::new_normalize(q.into_inner()))
    }

    /// Applies the motion to a point: R p + t, computed in f64 and rounded to f32.
    pub fn apply(&self, p: &Point) -> Point {
        let q = self.apply_f64([p[0] as f64, p[1] as f64, p[2] as f64]);
        [q[0] as f32, q[1] as f32, q[2] as f32]
    }

    /// Applies the motion to an f64 point.
    pub fn apply_f64(&self, p: [f64; 3]) -> [f64; 3] {
        (self.rotation_matrix() * Vector3::from(p) + Vector3::from(self.translation)).into()
    }

    /// `a.compose(&b)` is the motion x ↦ a(b(x)): `b` first, then `a` (the matrix product a b).
    pub fn compose(&self, other: &Rigid) -> Rigid {
        (self.to_isometry() * other.to_isometry()).into()
    }

    /// The inverse motion x ↦ Rᵀ (x − t).
    pub fn inverse(&self) -> Rigid {
        self.to_isometry().inverse().into()
    }

    /// The rotation of a unit quaternion (w, x, y, z) with zero translation.
    pub fn from_quaternion(q: [f64; 4]) -> Rigid {
        let q = UnitQuaternion::new_normalize(Quaternion::new(q[0], q[1], q[2], q[3]));
        Self::from_rotation(&q.to_rotation_matrix(), [0.0; 3])
    }

    /// The motion as a row-major 4 x 4 matrix (the API's layout).
    pub fn to_row_major(&self) -> [f64; 16] {
        let (r, t) = (&self.rotation, &self.translation);
        [
            r[0][0], r[0][1], r[0][2], t[0], r[1][0], r[1][1], r[1][2], t[1], r[2][0], r[2][1], r[2][2], t[2], 0.0,
            0.0, 0.0, 1.0,
        ]
    }

    /// Rotation angle of R (rad, in [0, π]).
    pub fn angle_rad(&self) -> f64 {
        self.rotation_matrix().angle()
    }
}

/// The least-squares rigid motion taking `src[i]` onto `dst[i]`: minimises Σ ‖R src_i + t − dst_i‖²
/// over proper rotations (det = +1) by Horn's closed-form quaternion method, O(n).
///
/// `None` when the slices differ in length, are empty, hold a non-finite coordinate, or the
/// rotation is not determined (fewer than three non-collinear points: all points coincide or lie
/// on one line).
pub fn fit_rigid(src: &[Point], dst: &[Point]) -> Option<Rigid> {
    fit_rigid_points(src, dst)
}

/// [`fit_rigid`] for points of any float width (f32 clouds; f64 in the tests, where the fit's
/// own accuracy is visible without the rounding of f32 inputs).
fn fit_rigid_points<T: Copy + Into<f64>>(src: &[[T; 3]], dst: &[[T; 3]]) -> Option<Rigid> {
    if src.len() != dst.len() || src.is_empty() {
        return None;
    }
    let as_f64 = |p: &[T; 3]| Vector3::new(p[0].into(), p[1].into(), p[2].into());
    if src.iter().chain(dst).any(|p| !as_f64(p).iter().all(|c| c.is_finite())) {
        return None;
    }
    let n = src.len() as f64;
    let cs = src.iter().map(as_f64).sum::<Vector3<f64>>() / n;
    let cd = dst.iter().map(as_f64).sum::<Vector3<f64>>() / n;
    // Cross-covariance S_ab = Σ (src_a − c_src)(dst_b − c_dst), from centred coordinates for accuracy.
    let mut s = Matrix3::<f64>::zeros();
    let mut spread = 0.0f64;
    for (p, q) in src.iter().zip(dst) {
        let a = as_f64(p) - cs;
        let b = as_f64(q) - cd;
        s += a * b.transpose();
        spread += a.norm_squared() + b.norm_squared();
    }
    let (sxx, sxy, sxz) = (s[(0, 0)], s[(0, 1)], s[(0, 2)]);
    let (syx, syy, syz) = (s[(1, 0)], s[(1, 1)], s[(1, 2)]);
    let (szx, szy, szz) = (s[(2, 0)], s[(2, 1)], s[(2, 2)]);
    // Horn (1987): the optimal unit quaternion (w, x, y, z) is the leading eigenvector of this
    // symmetric matrix; an eigenvector is a unit quaternion, so R is a proper rotation.
    #[rustfmt::skip]
    let horn = Matrix4::new(
        sxx + syy + szz, syz - szy, szx - sxz, sxy - syx,
        syz - szy, sxx - syy - szz, sxy + syx, szx + sxz,
        szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy,
        sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz,
    );
    let eigen = SymmetricEigen::new(horn);
    let mut order = [0usize, 1, 2, 3];
    order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
    // Collinear or coincident points leave a tie between the two largest eigenvalues (a free
    // rotation about the line). The gap scales with the spread Σ|a|² + |b|²; 1e-9 relative sits far
    // above f64 round-off (~1e-15) and far below any well-posed configuration.
    let gap = eigen.eigenvalues[order[0]] - eigen.eigenvalues[order[1]];
    let well_posed = gap > 1e-9 * spread;
    if !well_posed {
        return None;
    }
    let v = eigen.eigenvectors.column(order[0]);
    let rotation = UnitQuaternion::new_normalize(Quaternion::new(v[0], v[1], v[2], v[3])).to_rotation_matrix();
    Some(Rigid::from_rotation(&rotation, (cd - rotation * cs).into()))
}

/// Point-to-point ICP: refines `init` so that `src` moved by it lies on `dst`.
///
/// Each iteration matches every moved source point to its nearest `dst` point (through
/// `dst_tree`, which must be built from `dst`; queries run in parallel), drops pairs farther than
/// `max_corr_dist_m`, and refits the whole motion from the original `src` with [`fit_rigid`].
/// Stops after `iterations` rounds, or earlier once the motion changes by less than 1e-7 m / rad.
/// Keeps the last good motion when fewer than three pairs remain or the fit is degenerate.
/// Cost per iteration: O(n log m) queries plus O(n) for the fit.
pub fn fit_rigid_icp(
    src: &[Point],
    dst_tree: &KdTree,
    dst: &[Point],
    init: Rigid,
    iterations: usize,
    max_corr_dist_m: f32,
) -> Rigid {
    icp(src, dst_tree, dst, init, iterations, max_corr_dist_m, fit_rigid)
}

/// [`fit_rigid_icp`] restricted to motions on the ground plane: the result is a turn about the
/// z axis and a horizontal shift applied after `init`, so `init`'s height and tilt are kept.
/// For road users, whose height on the road and tilt a sweep's horizontal rings leave free to
/// drift (the ground under a car is removed, and a ring's height on its flank is the sensor's).
pub fn fit_planar_icp(
    src: &[Point],
    dst_tree: &KdTree,
    dst: &[Point],
    init: Rigid,
    iterations: usize,
    max_corr_dist_m: f32,
) -> Rigid {
    let base_src: Vec<Point> = src.iter().map(|p| init.apply(p)).collect();
    icp(&base_src, dst_tree, dst, Rigid::identity(), iterations, max_corr_dist_m, fit_planar).compose(&init)
}

/// The ICP loop of [`fit_rigid_icp`] with the motion refitted by `solve`.
fn icp(
    src: &[Point],
    dst_tree: &KdTree,
    dst: &[Point],
    init: Rigid,
    iterations: usize,
    max_corr_dist_m: f32,
    solve: fn(&[Point], &[Point]) -> Option<Rigid>,
) -> Rigid {
    let mut current = init;
    if src.is_empty() || dst.is_empty() || dst_tree.len() != dst.len() {
        return current;
    }
    let max_d2 = max_corr_dist_m * max_corr_dist_m;
    let mut moved = vec![[0.0f32; 3]; src.len()];
    let mut hits = vec![Nearest { index: 0, dist2: 0.0 }; src.len()];
    let mut pair_src = Vec::with_capacity(src.len());
    let mut pair_dst = Vec::with_capacity(src.len());
    for _ in 0..iterations {
        for (m, p) in moved.iter_mut().zip(src) {
            *m = current.apply(p);
        }
        if !dst_tree.nearest_batch(&moved, &mut hits) {
            break;
        }
        pair_src.clear();
        pair_dst.clear();
        for (p, h) in src.iter().zip(&hits) {
            if h.dist2 <= max_d2 {
                pair_src.push(*p);
                pair_dst.push(dst[h.index]);
            }
        }
        if pair_src.len() < 3 {
            break;
        }
        let Some(next) = solve(&pair_src, &pair_dst) else {
            break;
        };
        let step = next.compose(&current.inverse());
        let dt = step.translation.iter().map(|t| t * t).sum::<f64>().sqrt();
        current = next;
        if dt < 1e-7 && step.angle_rad() < 1e-7 {
            break;
        }
    }
    current
}

/// The least-squares motion on the ground plane (a turn about the z axis and a horizontal
/// shift) taking `src[i]` onto `dst[i]`, in closed form (two-dimensional Procrustes on x and
/// y; heights are ignored). `None` under the conditions of [`fit_rigid`], or when the points
/// coincide in x and y (the turn is not determined).
pub fn fit_planar(src: &[Point], dst: &[Point]) -> Option<Rigid> {
    if src.len() != dst.len() || src.is_empty() {
        return None;
    }
    if src.iter().chain(dst).any(|p| !p.iter().all(|c| c.is_finite())) {
        return None;
    }
    let n = src.len() as f64;
    let mean = |points: &[Point], c: usize| points.iter().map(|p| f64::from(p[c])).sum::<f64>() / n;
    let (sx, sy, dx, dy) = (mean(src, 0), mean(src, 1), mean(dst, 0), mean(dst, 1));
    // The turn maximising Σ b · R a over centred pairs: atan2 of the cross and dot sums.
    let (mut dot, mut cross, mut spread) = (0.0f64, 0.0f64, 0.0f64);
    for (p, q) in src.iter().zip(dst) {
        let (ax, ay) = (f64::from(p[0]) - sx, f64::from(p[1]) - sy);
        let (bx, by) = (f64::from(q[0]) - dx, f64::from(q[1]) - dy);
        dot += ax * bx + ay * by;
        cross += ax * by - ay * bx;
        spread += ax * ax + ay * ay + bx * bx + by * by;
    }
    // Coincident points leave every turn equally good; the threshold is relative, as in fit_rigid.
    if dot.hypot(cross) <= 1e-9 * spread || spread == 0.0 {
        return None;
    }
    let yaw = cross.atan2(dot);
    let (sin, cos) = yaw.sin_cos();
    Some(Rigid::from_yaw(yaw, [dx - (cos * sx - sin * sy), dy - (sin * sx + cos * sy), 0.0]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_rigid(rng: &mut ChaCha8Rng, max_angle_rad: f64, max_shift_m: f64) -> Rigid {
        // A random axis and an angle up to max_angle_rad, as a unit quaternion.
        let axis: [f64; 3] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
        let angle = rng.random_range(-max_angle_rad..max_angle_rad);
        let (s, c) = (angle / 2.0).sin_cos();
        let mut r = Rigid::from_quaternion([c, s * axis[0] / n, s * axis[1] / n, s * axis[2] / n]);
        r.translation = [
            rng.random_range(-max_shift_m..max_shift_m),
            rng.random_range(-max_shift_m..max_shift_m),
            rng.random_range(-max_shift_m..max_shift_m),
        ];
        r
    }

    fn assert_close(a: &Rigid, b: &Rigid, tol: f64) {
        for i in 0..3 {
            for j in 0..3 {
                assert!((a.rotation[i][j] - b.rotation[i][j]).abs() < tol, "{a:?} vs {b:?}");
            }
            assert!((a.translation[i] - b.translation[i]).abs() < tol, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn fit_rigid_recovers_a_random_rigid_motion() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..20 {
            let truth = random_rigid(&mut rng, std::f64::consts::PI, 10.0);
            let src: Vec<Point> = (0..200)
                .map(|_| [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0), rng.random_range(-2.0..2.0)])
                .collect();
            let dst: Vec<Point> = src.iter().map(|p| truth.apply(p)).collect();
            let fit = fit_rigid(&src, &dst).unwrap();
            // The only error source is the f32 rounding of dst (~1e-6 m at 10 m): 1e-5 bounds it.
            assert_close(&fit, &truth, 1e-5);
            assert!((fit.rotation_matrix().matrix().determinant() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn fit_planar_agrees_with_fit_rigid_on_planar_motions_and_ignores_heights() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for _ in 0..20 {
            let truth = Rigid::from_yaw(
                rng.random_range(-3.0..3.0),
                [rng.random_range(-10.0..10.0), rng.random_range(-10.0..10.0), 0.0],
            );
            let src: Vec<Point> = (0..200)
                .map(|_| [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0), rng.random_range(-2.0..2.0)])
                .collect();
            let dst: Vec<Point> = src.iter().map(|p| truth.apply(p)).collect();
            // The general fit is the twin: on a planar motion both give it (f32 rounding only).
            assert_close(&fit_planar(&src, &dst).unwrap(), &truth, 1e-5);
            assert_close(&fit_rigid(&src, &dst).unwrap(), &truth, 1e-5);
            // Targets lifted by 1.5 m change neither the turn nor the horizontal shift.
            let lifted: Vec<Point> = dst.iter().map(|p| [p[0], p[1], p[2] + 1.5]).collect();
            assert_close(&fit_planar(&src, &lifted).unwrap(), &truth, 1e-5);
        }
        let point = vec![[1.0f32, 2.0, 0.0]; 4];
        let stacked: Vec<Point> = (0..4).map(|i| [1.0, 2.0, i as f32]).collect();
        assert!(fit_planar(&point, &point).is_none(), "coincident points leave the turn free");
        assert!(fit_planar(&stacked, &stacked).is_none(), "a vertical line leaves the turn free");
        assert!(fit_planar(&point, &point[..2]).is_none());
    }

    #[test]
    fn planar_icp_recovers_a_turn_and_shift_and_keeps_the_height_and_tilt_it_started_from() {
        let mut rng = ChaCha8Rng::seed_from_u64(18);
        // A car-sized cloud of scattered points (a shape with no sliding direction).
        let dst: Vec<Point> = (0..600)
            .map(|_| [rng.random_range(0.0..4.5), rng.random_range(0.0..1.8), rng.random_range(0.0..1.5)])
            .collect();
        let tree = KdTree::new(&dst);
        let truth = Rigid::from_yaw(0.02, [0.06, -0.04, 0.0]);
        let src: Vec<Point> = dst.iter().map(|p| truth.inverse().apply(p)).collect();
        let found = fit_planar_icp(&src, &tree, &dst, Rigid::identity(), 100, 1.0);
        assert_close(&found, &truth, 1e-4);
        // The general ICP is the twin: on a planar motion both find it.
        assert_close(&fit_rigid_icp(&src, &tree, &dst, Rigid::identity(), 100, 1.0), &truth, 1e-4);
        // Started from a guess lifted by 0.1 m and tilted by 0.05 rad about x, the height and
        // the tilt stay as they were (the general ICP would undo both): only a turn about z and
        // a horizontal shift are added.
        let tilted = Rigid::from_rotation(&Rotation3::from_axis_angle(&Vector3::x_axis(), 0.05), [0.0, 0.0, 0.1]);
        let found = fit_planar_icp(&src, &tree, &dst, tilted, 100, 1.0);
        let added = found.compose(&tilted.inverse());
        assert!((added.translation[2]).abs() < 1e-9, "{added:?}");
        assert!((added.rotation[2][2] - 1.0).abs() < 1e-12 && added.rotation[0][2].abs() < 1e-12, "{added:?}");
        let general = fit_rigid_icp(&src, &tree, &dst, tilted, 100, 1.0);
        assert_close(&general, &truth, 1e-4);
        // A source scattered by noise still lands within the noise of the truth.
        let noisy: Vec<Point> = src
            .iter()
            .map(|p| [p[0] + rng.random_range(-0.01..0.01), p[1] + rng.random_range(-0.01..0.01), p[2]])
            .collect();
        let found = fit_planar_icp(&noisy, &tree, &dst, Rigid::identity(), 100, 1.0);
        assert_close(&found, &truth, 5e-3);
    }

    #[test]
    fn fit_rigid_recovers_a_random_rigid_motion_exactly_from_f64_points() {
        // Without the f32 rounding of the inputs the fit's own error shows: f64 round-off only.
        let mut rng = ChaCha8Rng::seed_from_u64(14);
        for _ in 0..20 {
            let truth = random_rigid(&mut rng, std::f64::consts::PI, 10.0);
            let src: Vec<[f64; 3]> = (0..200)
                .map(|_| [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0), rng.random_range(-2.0..2.0)])
                .collect();
            let dst: Vec<[f64; 3]> = src.iter().map(|&p| truth.apply_f64(p)).collect();
            let fit = fit_rigid_points(&src, &dst).unwrap();
            assert_close(&fit, &truth, 1e-9);
        }
    }

    #[test]
    fn compositions_of_many_motions_stay_rotations() {
        let mut rng = ChaCha8Rng::seed_from_u64(15);
        let mut chain = Rigid::identity();
        for _ in 0..1000 {
            chain = random_rigid(&mut rng, std::f64::consts::PI, 10.0).compose(&chain);
        }
        let r = chain.rotation_matrix().into_inner();
        assert!((r.determinant() - 1.0).abs() < 1e-9, "{r}");
        assert!((r.transpose() * r - Matrix3::identity()).abs().max() < 1e-9, "{r}");
        // The inverse undoes the whole chain.
        assert_close(&chain.inverse().compose(&chain), &Rigid::identity(), 1e-9);
    }

    #[test]
    fn isometries_convert_both_ways() {
        let mut rng = ChaCha8Rng::seed_from_u64(16);
        let a = random_rigid(&mut rng, 3.0, 5.0);
        assert_close(&Rigid::from(a.to_isometry()), &a, 1e-12);
        let p = [1.5, -2.0, 0.25];
        let q = a.to_isometry() * nalgebra::Point3::from(p);
        let r = a.apply_f64(p);
        for k in 0..3 {
            assert!((q[k] - r[k]).abs() < 1e-12);
        }
        let yaw = Rigid::from_yaw(0.3, [1.0, 2.0, 3.0]);
        let (s, c) = 0.3f64.sin_cos();
        assert_eq!(yaw.rotation, [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]);
        assert_eq!(yaw.translation, [1.0, 2.0, 3.0]);
    }

    #[test]
    fn fit_rigid_gives_a_proper_rotation_for_a_reflected_planar_set() {
        // dst is a mirror image of src: the best proper rotation is not the reflection.
        let src: Vec<Point> = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 1.0, 0.0]];
        let dst: Vec<Point> = src.iter().map(|p| [-p[0], p[1], p[2]]).collect();
        let fit = fit_rigid(&src, &dst).unwrap();
        assert!((fit.rotation_matrix().matrix().determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn fit_rigid_rejects_bad_or_degenerate_input() {
        let p: Vec<Point> = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        assert!(fit_rigid(&p, &p[..2]).is_none());
        assert!(fit_rigid(&[], &[]).is_none());
        let line: Vec<Point> = (0..5).map(|i| [i as f32, 0.0, 0.0]).collect();
        assert!(fit_rigid(&line, &line).is_none());
        let mut nan = p.clone();
        nan[1][2] = f32::NAN;
        assert!(fit_rigid(&nan, &p).is_none());
        assert_close(&fit_rigid(&p, &p).unwrap(), &Rigid::identity(), 1e-12);
    }

    #[test]
    fn compose_and_inverse_are_consistent() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let a = random_rigid(&mut rng, 3.0, 5.0);
        let b = random_rigid(&mut rng, 3.0, 5.0);
        let p = [1.5f32, -2.0, 0.25];
        let ab = a.compose(&b).apply(&p);
        let a_b = a.apply(&b.apply(&p));
        for k in 0..3 {
            assert!((ab[k] - a_b[k]).abs() < 1e-5);
        }
        assert_close(&a.compose(&a.inverse()), &Rigid::identity(), 1e-12);
        assert_close(&a.inverse().compose(&a), &Rigid::identity(), 1e-12);
    }

    /// A street-like scene: ground, two walls, a box; structure in all three axes so ICP is well posed.
    fn structured_cloud(rng: &mut ChaCha8Rng) -> Vec<Point> {
        let mut pts = Vec::new();
        for _ in 0..3000 {
            pts.push([rng.random_range(-15.0..15.0), rng.random_range(-8.0..8.0), -1.7]);
        }
        for _ in 0..1500 {
            pts.push([rng.random_range(-15.0..15.0), 8.0, rng.random_range(-1.7..3.0)]);
            pts.push([-15.0, rng.random_range(-8.0..8.0), rng.random_range(-1.7..3.0)]);
        }
        for _ in 0..1000 {
            let face = rng.random_range(0..3);
            let (u, v): (f32, f32) = (rng.random_range(0.0..1.0), rng.random_range(0.0..1.0));
            pts.push(match face {
                0 => [3.0 + 4.0 * u, 2.0, -1.7 + 1.5 * v],
                1 => [3.0, 2.0 + 1.8 * u, -1.7 + 1.5 * v],
                _ => [3.0 + 4.0 * u, 2.0 + 1.8 * v, -0.2],
            });
        }
        pts
    }

    #[test]
    fn icp_recovers_a_small_motion_of_a_structured_cloud() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let dst = structured_cloud(&mut rng);
        let truth = random_rigid(&mut rng, 0.05, 0.3);
        // src is dst seen from a moved sensor: dst = truth(src).
        let inv = truth.inverse();
        let src: Vec<Point> = dst.iter().map(|p| inv.apply(p)).collect();
        let tree = KdTree::new(&dst);
        let fit = fit_rigid_icp(&src, &tree, &dst, Rigid::identity(), 60, 1.0);
        // Exact correspondences exist, so ICP converges to the truth up to f32 rounding.
        assert_close(&fit, &truth, 1e-4);
    }
}
