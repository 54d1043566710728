//! ICP of one frame against the local map: Gauss-Newton on SE(3) with a Geman-McClure robust
//! weight, the 6 x 6 normal equations solved by Cholesky (nalgebra). Each residual is projected
//! onto what the map's neighbourhood of its nearest point observes ([`VoxelMap::local_shapes`]):
//! along a plane's normal, across a pole or an edge, or the full distance (scaled down) in
//! scattered points.

use nalgebra::{Isometry3, Matrix3, Matrix3x6, Matrix6, Point3, Translation3, Vector3, Vector6};
use rayon::prelude::*;

use super::voxel::{Shapes, VoxelMap, voxel_key};
use crate::geometry::Point;

/// Damping of the normal equations, relative to the mean diagonal of each block (translation,
/// rotation): a direction no correspondence observes (along a corridor whose walls are planes)
/// keeps its starting value, the prediction, instead of making the system singular.
const DAMPING: f64 = 1e-6;

/// Correspondences per block of the normal-equation sums: the blocks are summed in index
/// order, so the result has the same bits on any number of threads.
const SUM_BLOCK: usize = 1024;

/// How one frame was registered.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Registration {
    /// The estimate (sensor to world).
    pub world_from_sensor: Isometry3<f64>,
    /// Gauss-Newton iterations run.
    pub iterations: usize,
    /// Correspondences of the last iteration.
    pub correspondences: usize,
    /// Geman-McClure scale of the last iteration (m).
    pub kernel_m: f64,
    /// Median point-to-point residual of the last iteration (m).
    pub median_residual_m: f64,
}

/// What the ICP loop needs to know besides the points.
#[derive(Debug, Clone, Copy)]
pub(crate) struct IcpSettings {
    /// Correspondences farther than this are ignored (m).
    pub max_distance_m: f64,
    /// Geman-McClure scale (m).
    pub kernel_m: f64,
    /// Iterations at most.
    pub max_iterations: usize,
    /// Stop once an update moves points by less than this (m, translation plus rotation at 1 m).
    pub convergence_m: f64,
}

/// Geman-McClure weight of a residual of squared length `r2` (m^2) at scale `c` (m):
/// c^4 / (c^2 + r^2)^2, 1 at zero and 1/4 at r = c; residuals well beyond c hardly count.
fn geman_mcclure_weight(r2: f64, c: f64) -> f64 {
    let c2 = c * c;
    c2 * c2 / ((c2 + r2) * (c2 + r2))
}

/// One correspondence: the source point in world coordinates, its map point, and the
/// projector of the map's local shape there.
type Pair = (Vector3<f64>, Vector3<f64>, Matrix3<f64>);

/// The map point nearest to world point `q` (within `reach` voxels), its squared distance, and
/// its local shape's projector; `None` when there is none, or its shape says nothing.
fn correspond(
    map: &VoxelMap,
    shapes: &Shapes,
    q: &Vector3<f64>,
    reach: i32,
) -> Option<(Vector3<f64>, f32, Matrix3<f64>)> {
    let (m, d2) = map.nearest(&[q.x as f32, q.y as f32, q.z as f32], reach)?;
    let projector = shapes.get(&voxel_key(&m, map.voxel_m()))?;
    Some((Vector3::new(f64::from(m[0]), f64::from(m[1]), f64::from(m[2])), d2, *projector))
}

/// The residual r = P (q - m) of world point `q` against map point `m` (P: the map's local
/// shape's projector, symmetric), and its Jacobian P J with respect to a small motion
/// (translation, rotation vector) of the sensor about `centre`: q moves to
/// q + t + w x (q - centre).
fn residual_and_jacobian(
    q: &Vector3<f64>,
    m: &Vector3<f64>,
    projector: &Matrix3<f64>,
    centre: &Vector3<f64>,
) -> (Vector3<f64>, Matrix3x6<f64>) {
    let a = q - centre;
    // d(w x a) / dw = -[a]x.
    let skew = -Matrix3::new(0.0, -a.z, a.y, a.z, 0.0, -a.x, -a.y, a.x, 0.0);
    let mut j = Matrix3x6::<f64>::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&Matrix3::identity());
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&skew);
    (projector * (q - m), projector * j)
}

/// Aligns `source` (sensor frame) to `map`, starting at `guess` (sensor to world).
///
/// Returns `None` when fewer than 6 correspondences are found or the normal equations are
/// singular. Cost: per iteration one map search per source point (in parallel).
pub(crate) fn align_to_map(
    source: &[Point],
    map: &VoxelMap,
    shapes: &Shapes,
    guess: Isometry3<f64>,
    settings: &IcpSettings,
) -> Option<Registration> {
    let max2 = settings.max_distance_m * settings.max_distance_m;
    // Neighbour voxels searched: enough to cover the correspondence distance, at most 2 on each
    // side (the distance is large only for the first frames, before the threshold adapts).
    let reach = ((settings.max_distance_m / f64::from(map.voxel_m())).ceil() as i32).clamp(1, 2);
    let mut world_from_sensor = guess;
    let mut last = Registration {
        world_from_sensor,
        iterations: 0,
        correspondences: 0,
        kernel_m: settings.kernel_m,
        median_residual_m: f64::NAN,
    };
    for iteration in 1..=settings.max_iterations {
        let pairs: Vec<Pair> = source
            .par_iter()
            .filter_map(|p| {
                let q = (world_from_sensor * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))).coords;
                let (m, d2, projector) = correspond(map, shapes, &q, reach)?;
                (f64::from(d2) <= max2).then_some((q, m, projector))
            })
            .collect();
        if pairs.len() < 6 {
            return None;
        }
        let mut r2: Vec<f64> = pairs.iter().map(|(q, m, _)| (q - m).norm_squared()).collect();
        let mid = r2.len() / 2;
        let median_residual_m = r2.select_nth_unstable_by(mid, f64::total_cmp).1.sqrt();
        let kernel_m = settings.kernel_m;
        // Linearise about the sensor's current position, so that the rotation and translation
        // columns stay well conditioned however far the sensor is from the world origin.
        let centre = world_from_sensor.translation.vector;
        let (jtj, jtr) = pairs
            .par_chunks(SUM_BLOCK)
            .map(|block| {
                let mut jtj = Matrix6::<f64>::zeros();
                let mut jtr = Vector6::<f64>::zeros();
                for (q, m, projector) in block {
                    let (r, jacobian) = residual_and_jacobian(q, m, projector, &centre);
                    let w = geman_mcclure_weight(r.norm_squared(), kernel_m);
                    jtj += jacobian.transpose() * jacobian * w;
                    jtr += jacobian.transpose() * r * w;
                }
                (jtj, jtr)
            })
            .collect::<Vec<_>>()
            .into_iter()
            .fold((Matrix6::zeros(), Vector6::zeros()), |(a, b), (c, d)| (a + c, b + d));
        let mut jtj = jtj;
        for block in [0, 3] {
            let mean_diagonal = (block..block + 3).map(|i| jtj[(i, i)]).sum::<f64>() / 3.0;
            for i in block..block + 3 {
                jtj[(i, i)] += DAMPING * mean_diagonal;
            }
        }
        let step = match jtj.cholesky() {
            Some(c) => c.solve(&(-jtr)),
            None => jtj.lu().solve(&(-jtr))?,
        };
        let translation = Vector3::new(step[0], step[1], step[2]);
        let rotation = Vector3::new(step[3], step[4], step[5]);
        let about_centre =
            Translation3::from(centre) * Isometry3::new(translation, rotation) * Translation3::from(-centre);
        world_from_sensor = about_centre * world_from_sensor;
        world_from_sensor.rotation.renormalize();
        last = Registration {
            world_from_sensor,
            iterations: iteration,
            correspondences: pairs.len(),
            kernel_m,
            median_residual_m,
        };
        if translation.norm() + rotation.norm() < settings.convergence_m {
            break;
        }
    }
    Some(last)
}

/// The best of a grid of translations of `guess` (in the sensor's x-y plane, +-`half_width_m`
/// in steps of `step_m`) by the robust cost of `source` against `map`: a starting point for a
/// registration that has no motion to predict from (the first pair of frames), where the
/// nearest map points of a guess a metre off belong to the wrong surfaces.
///
/// The cost is the Geman-McClure loss r^2 / (r^2 + c^2) with c = `kernel_m` (r projected as in
/// [`align_to_map`]), a point without a map point within the search counting 1; ties keep the
/// earlier candidate (grid order).
pub(crate) fn search_translation(
    source: &[Point],
    map: &VoxelMap,
    shapes: &Shapes,
    guess: Isometry3<f64>,
    half_width_m: f64,
    step_m: f64,
    kernel_m: f64,
) -> Isometry3<f64> {
    let steps = (half_width_m / step_m).round() as i32;
    let c2 = kernel_m * kernel_m;
    let candidates: Vec<Isometry3<f64>> = (-steps..=steps)
        .flat_map(|i| (-steps..=steps).map(move |j| (i, j)))
        .map(|(i, j)| guess * Translation3::new(f64::from(i) * step_m, f64::from(j) * step_m, 0.0))
        .collect();
    let costs: Vec<f64> = candidates
        .par_iter()
        .map(|pose| {
            source
                .iter()
                .map(|p| {
                    let q = (pose * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))).coords;
                    match correspond(map, shapes, &q, 1) {
                        Some((m, _, projector)) => {
                            let r2 = (projector * (q - m)).norm_squared();
                            r2 / (r2 + c2)
                        }
                        None => 1.0,
                    }
                })
                .sum()
        })
        .collect();
    let best = (0..costs.len()).fold(0, |b, i| if costs[i] < costs[b] { i } else { b });
    candidates[best]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_geman_mcclure_weight_is_one_at_zero_and_a_quarter_at_its_scale() {
        assert_eq!(geman_mcclure_weight(0.0, 0.3), 1.0);
        assert!((geman_mcclure_weight(0.09, 0.3) - 0.25).abs() < 1e-12);
        assert!(geman_mcclure_weight(9.0, 0.3) < 1e-3);
    }

    #[test]
    fn the_residual_jacobian_matches_finite_differences() {
        // A plane's projector, a vertical line's, and a scaled identity (scatter), at a point
        // far from the linearisation centre so that the rotation columns matter.
        let n = Vector3::new(0.3, -0.5, 0.8).normalize();
        let d = Vector3::new(0.1, 0.05, 1.0).normalize();
        let projectors = [n * n.transpose(), Matrix3::identity() - d * d.transpose(), Matrix3::identity() * 0.3];
        let q = Vector3::new(12.0, -7.5, 1.3);
        let m = Vector3::new(11.7, -7.2, 1.1);
        let centre = Vector3::new(2.0, 1.0, 1.8);
        let h = 1e-6;
        for projector in &projectors {
            let (_, jacobian) = residual_and_jacobian(&q, &m, projector, &centre);
            for k in 0..6 {
                let mut step = Vector6::zeros();
                step[k] = h;
                let moved = |s: Vector6<f64>| {
                    let motion = Translation3::from(centre)
                        * Isometry3::new(Vector3::new(s[0], s[1], s[2]), Vector3::new(s[3], s[4], s[5]))
                        * Translation3::from(-centre);
                    (motion * Point3::from(q)).coords
                };
                let r = |s: Vector6<f64>| residual_and_jacobian(&moved(s), &m, projector, &centre).0;
                let numeric = (r(step) - r(-step)) / (2.0 * h);
                let analytic = jacobian.column(k);
                assert!((numeric - analytic).norm() < 1e-6, "column {k}: {numeric:?} vs {analytic:?}");
            }
        }
    }
}
