//! Rigid transforms of point clouds: the least-squares fit for corresponding points (Horn's
//! quaternion method) and point-to-point ICP on top of it.
//!
//! The arithmetic is f64: fits sum tens of thousands of products of metric coordinates, and the
//! result is only a 3 x 4 matrix, so precision costs nothing here.

use serde::{Deserialize, Serialize};

use super::Point;
use super::knn::{KdTree, Nearest};

/// A proper rigid motion x ↦ R x + t (R orthonormal, det R = +1), metric (m).
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

impl Rigid {
    /// The identity motion.
    pub fn identity() -> Self {
        Self { rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], translation: [0.0; 3] }
    }

    /// Applies the motion to a point: R p + t, computed in f64 and rounded to f32.
    pub fn apply(&self, p: &Point) -> Point {
        let q = self.apply_f64([p[0] as f64, p[1] as f64, p[2] as f64]);
        [q[0] as f32, q[1] as f32, q[2] as f32]
    }

    /// Applies the motion to an f64 point.
    pub fn apply_f64(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        let t = &self.translation;
        [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2] + t[0],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2] + t[1],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + t[2],
        ]
    }

    /// `a.compose(&b)` is the motion x ↦ a(b(x)): `b` first, then `a` (the matrix product a b).
    pub fn compose(&self, other: &Rigid) -> Rigid {
        let a = &self.rotation;
        let b = &other.rotation;
        let mut rotation = [[0.0; 3]; 3];
        for (i, row) in rotation.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
            }
        }
        let translation = self.apply_f64(other.translation);
        Rigid { rotation, translation }
    }

    /// The inverse motion x ↦ Rᵀ (x − t).
    pub fn inverse(&self) -> Rigid {
        let r = &self.rotation;
        let rotation = [[r[0][0], r[1][0], r[2][0]], [r[0][1], r[1][1], r[2][1]], [r[0][2], r[1][2], r[2][2]]];
        let t = &self.translation;
        let translation = [
            -(rotation[0][0] * t[0] + rotation[0][1] * t[1] + rotation[0][2] * t[2]),
            -(rotation[1][0] * t[0] + rotation[1][1] * t[1] + rotation[1][2] * t[2]),
            -(rotation[2][0] * t[0] + rotation[2][1] * t[1] + rotation[2][2] * t[2]),
        ];
        Rigid { rotation, translation }
    }

    /// The rotation of a unit quaternion (w, x, y, z) with zero translation.
    pub fn from_quaternion(q: [f64; 4]) -> Rigid {
        let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        let (w, x, y, z) = (q[0] / n, q[1] / n, q[2] / n, q[3] / n);
        Rigid {
            rotation: [
                [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
                [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
                [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
            ],
            translation: [0.0; 3],
        }
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
        let r = &self.rotation;
        ((r[0][0] + r[1][1] + r[2][2] - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
    }
}

/// The least-squares rigid motion taking `src[i]` onto `dst[i]`: minimises Σ ‖R src_i + t − dst_i‖²
/// over proper rotations (det = +1) by Horn's closed-form quaternion method, O(n).
///
/// `None` when the slices differ in length, are empty, hold a non-finite coordinate, or the
/// rotation is not determined (fewer than three non-collinear points: all points coincide or lie
/// on one line).
pub fn fit_rigid(src: &[Point], dst: &[Point]) -> Option<Rigid> {
    if src.len() != dst.len() || src.is_empty() {
        return None;
    }
    if src.iter().chain(dst).any(|p| p.iter().any(|c| !c.is_finite())) {
        return None;
    }
    let n = src.len() as f64;
    let mut cs = [0.0f64; 3];
    let mut cd = [0.0f64; 3];
    for (s, d) in src.iter().zip(dst) {
        for k in 0..3 {
            cs[k] += s[k] as f64;
            cd[k] += d[k] as f64;
        }
    }
    for k in 0..3 {
        cs[k] /= n;
        cd[k] /= n;
    }
    // Cross-covariance S_ab = Σ (src_a − c_src)(dst_b − c_dst), from centred coordinates for accuracy.
    let mut s = [[0.0f64; 3]; 3];
    let mut spread = 0.0f64;
    for (p, q) in src.iter().zip(dst) {
        let a = [p[0] as f64 - cs[0], p[1] as f64 - cs[1], p[2] as f64 - cs[2]];
        let b = [q[0] as f64 - cd[0], q[1] as f64 - cd[1], q[2] as f64 - cd[2]];
        for i in 0..3 {
            for j in 0..3 {
                s[i][j] += a[i] * b[j];
            }
        }
        spread += a[0] * a[0] + a[1] * a[1] + a[2] * a[2] + b[0] * b[0] + b[1] * b[1] + b[2] * b[2];
    }
    let (sxx, sxy, sxz) = (s[0][0], s[0][1], s[0][2]);
    let (syx, syy, syz) = (s[1][0], s[1][1], s[1][2]);
    let (szx, szy, szz) = (s[2][0], s[2][1], s[2][2]);
    // Horn (1987): the optimal unit quaternion is the leading eigenvector of this symmetric matrix.
    let nm = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (values, vectors) = jacobi_eigen4(nm);
    let mut order = [0usize, 1, 2, 3];
    order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
    // Collinear or coincident points leave a tie between the two largest eigenvalues (a free
    // rotation about the line). The gap scales with the spread Σ|a|² + |b|²; 1e-9 relative sits far
    // above f64 round-off (~1e-15) and far below any well-posed configuration.
    let gap = values[order[0]] - values[order[1]];
    let well_posed = gap > 1e-9 * spread;
    if !well_posed {
        return None;
    }
    let e = order[0];
    let q = [vectors[0][e], vectors[1][e], vectors[2][e], vectors[3][e]];
    let mut rigid = Rigid::from_quaternion(q);
    let rc = rigid.apply_f64(cs);
    rigid.translation = [cd[0] - rc[0], cd[1] - rc[1], cd[2] - rc[2]];
    Some(rigid)
}

/// Eigen-decomposition of a symmetric 4 x 4 matrix by cyclic Jacobi rotations: eigenvalues and
/// the eigenvectors as the columns of the second matrix. Converges quadratically; 50 sweeps is
/// a bound never reached in practice.
#[allow(clippy::needless_range_loop)] // index form mirrors the rotation formulas
fn jacobi_eigen4(mut a: [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0f64; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..50 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        let diag: f64 = (0..4).map(|i| a[i][i] * a[i][i]).sum();
        if off <= 1e-30 * diag || off == 0.0 {
            break;
        }
        for p in 0..3 {
            for q in p + 1..4 {
                if a[p][q] == 0.0 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..4 {
                    let akp = a[k][p];
                    let akq = a[k][q];
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..4 {
                    let apk = a[p][k];
                    let aqk = a[q][k];
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for row in v.iter_mut() {
                    let vp = row[p];
                    let vq = row[q];
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2], a[3][3]], v)
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
        let Some(next) = fit_rigid(&pair_src, &pair_dst) else {
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

    fn det(r: &[[f64; 3]; 3]) -> f64 {
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
            + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
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
            assert!((det(&fit.rotation) - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn fit_rigid_gives_a_proper_rotation_for_a_reflected_planar_set() {
        // dst is a mirror image of src: the best proper rotation is not the reflection.
        let src: Vec<Point> = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 1.0, 0.0]];
        let dst: Vec<Point> = src.iter().map(|p| [-p[0], p[1], p[2]]).collect();
        let fit = fit_rigid(&src, &dst).unwrap();
        assert!((det(&fit.rotation) - 1.0).abs() < 1e-12);
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
