//! Voxel grids: downsampling a cloud to one point per voxel, and the voxel-hashed local map the
//! frames are registered against.
//!
//! Results never depend on the hash map's iteration order (std's hasher is seeded at random):
//! downsampling keeps points in input order, a neighbour search visits voxels in a fixed order
//! and points in insertion order, and removal keeps or drops each voxel on its own.

use std::collections::HashMap;
use std::collections::hash_map::Entry;

use nalgebra::{Isometry3, Matrix3, Point3, SymmetricEigen, Vector3};
use rayon::prelude::*;

use crate::geometry::Point;
use crate::geometry::knn::dist2;

/// Integer voxel coordinates of a point (floor of coordinate / voxel size).
pub(crate) type VoxelKey = [i32; 3];

/// The voxel holding `p` on a grid of `voxel_m` cells.
pub(crate) fn voxel_key(p: &Point, voxel_m: f32) -> VoxelKey {
    // Coordinates are finite and bounded by the range crop, so the casts do not saturate.
    [(p[0] / voxel_m).floor() as i32, (p[1] / voxel_m).floor() as i32, (p[2] / voxel_m).floor() as i32]
}

/// Keeps the first point (in input order) of every occupied voxel of size `voxel_m`.
///
/// Cost O(N) expected; the output is a subsequence of `points`.
pub fn voxel_downsample(points: &[Point], voxel_m: f32) -> Vec<Point> {
    let mut seen: HashMap<VoxelKey, ()> = HashMap::with_capacity(points.len() / 4);
    points.iter().filter(|p| seen.insert(voxel_key(p, voxel_m), ()).is_none()).copied().collect()
}

/// Applies `world_from_sensor` to sensor-frame points (f64 maths, f32 storage).
pub fn transform_points(world_from_sensor: &Isometry3<f64>, points: &[Point]) -> Vec<Point> {
    points
        .iter()
        .map(|p| {
            let q = world_from_sensor * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            [q.x as f32, q.y as f32, q.z as f32]
        })
        .collect()
}

/// The local map: world points hashed by voxel, at most `max_points_per_voxel` per voxel.
#[derive(Debug, Clone)]
pub struct VoxelMap {
    voxel_m: f32,
    max_points_per_voxel: usize,
    voxels: HashMap<VoxelKey, Vec<Point>>,
}

impl VoxelMap {
    /// An empty map on a grid of `voxel_m` cells.
    pub fn new(voxel_m: f32, max_points_per_voxel: usize) -> Self {
        Self { voxel_m, max_points_per_voxel, voxels: HashMap::new() }
    }

    /// Number of points held.
    pub fn len(&self) -> usize {
        self.voxels.values().map(Vec::len).sum()
    }

    /// Whether the map holds no point.
    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }

    /// Adds world points; a full voxel ignores further points (the first ones stay, so the map
    /// does not drift towards the newest frames' sampling).
    pub fn add(&mut self, world_points: &[Point]) {
        for p in world_points {
            match self.voxels.entry(voxel_key(p, self.voxel_m)) {
                Entry::Occupied(mut e) => {
                    if e.get().len() < self.max_points_per_voxel {
                        e.get_mut().push(*p);
                    }
                }
                Entry::Vacant(e) => {
                    let mut v = Vec::with_capacity(self.max_points_per_voxel.min(4));
                    v.push(*p);
                    e.insert(v);
                }
            }
        }
    }

    /// Drops every voxel whose first point is farther than `max_range_m` from `origin` (m).
    pub fn remove_far(&mut self, origin: [f64; 3], max_range_m: f64) {
        let max2 = max_range_m * max_range_m;
        self.voxels.retain(|_, pts| {
            let p = pts[0];
            let d2: f64 = (0..3).map(|i| (f64::from(p[i]) - origin[i]).powi(2)).sum();
            d2 <= max2
        });
    }

    /// The nearest map point to `q` among the voxels within `reach` cells of q's voxel (a cube
    /// of (2 reach + 1)^3 voxels), with its squared distance (m^2). Ties keep the first point met
    /// in a fixed visiting order.
    pub fn nearest(&self, q: &Point, reach: i32) -> Option<(Point, f32)> {
        let k = voxel_key(q, self.voxel_m);
        let mut best: Option<(Point, f32)> = None;
        for dx in -reach..=reach {
            for dy in -reach..=reach {
                for dz in -reach..=reach {
                    let Some(pts) = self.voxels.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) else {
                        continue;
                    };
                    for p in pts {
                        let d2 = dist2(p, q);
                        if best.is_none_or(|(_, b)| d2 < b) {
                            best = Some((*p, d2));
                        }
                    }
                }
            }
        }
        best
    }

    /// The voxel edge length (m).
    pub fn voxel_m(&self) -> f32 {
        self.voxel_m
    }

    /// How each voxel's neighbourhood constrains a point registered against it: the projector of
    /// the [`LocalShape`] of the map points within one voxel edge of the voxel's centroid (its
    /// own and its 26 neighbours'). Voxels left out (too few points, a horizontal line, or
    /// scatter unless `with_scatter`) take no correspondence.
    ///
    /// Why: a spinning LiDAR samples surfaces on rings and scan lines that move with the
    /// sensor. The nearest map point of a point on a road or a facade lies wherever the last
    /// frame's ring happened to be, so point-to-point residuals along a surface pull the estimate
    /// towards standing still, where the rings coincide (measured: the first registration of a
    /// turning drive came out 0.14 m for 0.8 m). Measured along a plane's normal, or across a
    /// vertical line, a surface constrains only what it can observe.
    ///
    /// Cost: one pass over the voxels, 27 lookups and a 3 x 3 eigen-decomposition each (in
    /// parallel). Deterministic: each voxel's shape depends only on the map's points.
    pub fn local_shapes(&self, max_thickness_m: f64, with_scatter: bool) -> Shapes {
        let keys: Vec<VoxelKey> = self.voxels.keys().copied().collect();
        let edge_m = f64::from(self.voxel_m);
        keys.par_iter()
            .filter_map(|k| {
                let own = &self.voxels[k];
                let centroid = own.iter().fold(Vector3::zeros(), |s, p| s + as_vector(p)) / own.len() as f64;
                let mut near: Vec<Vector3<f64>> = Vec::with_capacity(64);
                for dx in -1..=1 {
                    for dy in -1..=1 {
                        for dz in -1..=1 {
                            let Some(pts) = self.voxels.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) else { continue };
                            near.extend(pts.iter().map(as_vector).filter(|v| (v - centroid).norm() <= edge_m));
                        }
                    }
                }
                local_shape(&near, max_thickness_m, MIN_SPREAD * edge_m)
                    .filter(|shape| with_scatter || *shape != LocalShape::Scatter)
                    .map(|shape| (*k, shape.projector()))
            })
            .collect()
    }
}

/// Per map voxel, the projection of a residual onto what its neighbourhood observes
/// ([`VoxelMap::local_shapes`]); voxels missing take no correspondence.
pub(crate) type Shapes = HashMap<VoxelKey, Matrix3<f64>>;

/// A residual against scattered points is scaled by this (its weight in the normal equations
/// by the square, 0.09): such a neighbourhood is often where surfaces meet (a wall's foot, a
/// car's corner), sampled on rings that move with the sensor, so its point-to-point residual
/// still leans towards standing still, but vegetation and clutter carry real information.
/// Measured (docs/benchmarks.md section 8): at full weight a corridor's first registration
/// slid back to standing still; left out, the simulator's seed 104 drifted 0.23 m in 24 m
/// against 0.10 m at full weight; at 0.3 both held.
pub(crate) const SCATTER_SCALE: f64 = 0.3;

/// Fewest points whose shape is judged: fewer say nothing reliable (a far, sparse ring).
pub(crate) const MIN_SHAPE_POINTS: usize = 6;

/// Least spread (standard deviation along a principal axis) that counts as extent, as a share
/// of the voxel edge: below it in all but one direction, the points are a line.
pub(crate) const MIN_SPREAD: f64 = 0.15;

/// An elongated neighbourhood (an edge) is this many times longer than wide (ratio of the
/// standard deviations along its largest and middle axes).
const ELONGATION: f64 = 2.0;

/// A line within this angle of the vertical (cosine) is a pole or an edge; flatter ones are
/// taken for scan lines (degrees: 30).
const VERTICAL_LINE_COS: f64 = 0.866;

/// What a map neighbourhood can tell about a point registered against it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum LocalShape {
    /// A plane with this unit normal: measured along the normal only.
    Plane(Vector3<f64>),
    /// A near-vertical line (a pole, a wall's edge) with this unit direction: measured across
    /// it only.
    VerticalLine(Vector3<f64>),
    /// An edge where surfaces meet (a wall's foot on the road, a kerb), elongated along this
    /// unit direction: measured across it only, since where along it a ring or scan line
    /// crosses it moves with the sensor.
    Edge(Vector3<f64>),
    /// Spread in every direction (a corner, vegetation): the full distance, scaled by
    /// [`SCATTER_SCALE`].
    Scatter,
}

impl LocalShape {
    /// The projection of a residual onto what the shape observes.
    pub fn projector(&self) -> Matrix3<f64> {
        match self {
            LocalShape::Plane(n) => n * n.transpose(),
            LocalShape::VerticalLine(d) | LocalShape::Edge(d) => Matrix3::identity() - d * d.transpose(),
            LocalShape::Scatter => Matrix3::identity() * SCATTER_SCALE,
        }
    }
}

fn as_vector(p: &Point) -> Vector3<f64> {
    Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
}

/// The shape of `points` (principal axes of their scatter): a plane when at most
/// `max_thickness_m` thick and at least `min_spread_m` wide both ways, a vertical line when
/// spread along one axis only and that axis is near vertical, an edge when spread in all three
/// but [`ELONGATION`] times more along one, scatter otherwise;
/// `None` for too few points or a horizontal line (a ring on the road, a scan line on a wall,
/// which moves with the sensor). A direction's sign is fixed (largest component positive) so it
/// does not depend on the eigen-solver's.
pub(crate) fn local_shape(points: &[Vector3<f64>], max_thickness_m: f64, min_spread_m: f64) -> Option<LocalShape> {
    if points.len() < MIN_SHAPE_POINTS {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().sum::<Vector3<f64>>() / n;
    let scatter = points.iter().fold(Matrix3::zeros(), |s, p| {
        let d = p - mean;
        s + d * d.transpose()
    }) / n;
    let eigen = SymmetricEigen::new(scatter);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    let axis = |i: usize| {
        let v = eigen.eigenvectors.column(order[i]).into_owned().normalize();
        if v[v.iamax()] < 0.0 { -v } else { v }
    };
    let [smallest, middle, largest] = order.map(|i| eigen.eigenvalues[i].max(0.0));
    let spread2 = min_spread_m * min_spread_m;
    if middle < spread2 {
        let direction = axis(2);
        return (direction.z.abs() >= VERTICAL_LINE_COS).then_some(LocalShape::VerticalLine(direction));
    }
    if smallest <= max_thickness_m * max_thickness_m {
        return Some(LocalShape::Plane(axis(0)));
    }
    if largest >= ELONGATION * ELONGATION * middle {
        return Some(LocalShape::Edge(axis(2)));
    }
    Some(LocalShape::Scatter)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::knn::nearest_linear;

    #[test]
    fn downsampling_keeps_one_point_per_voxel_in_input_order() {
        let pts = [[0.1, 0.1, 0.1], [0.2, 0.3, 0.4], [1.5, 0.0, 0.0], [-0.1, 0.0, 0.0], [1.9, 0.9, 0.9]];
        assert_eq!(voxel_downsample(&pts, 1.0), vec![[0.1, 0.1, 0.1], [1.5, 0.0, 0.0], [-0.1, 0.0, 0.0]]);
    }

    #[test]
    fn the_map_nearest_point_matches_a_brute_force_search_within_its_reach() {
        // A flat, axis-aligned grid (like LiDAR ground) plus a few raised points.
        let mut pts: Vec<Point> = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                pts.push([i as f32 * 0.25, j as f32 * 0.25, 0.0]);
            }
        }
        pts.extend([[3.1, 2.2, 0.7], [5.0, 5.0, 1.1], [0.3, 9.0, 0.4]]);
        let mut map = VoxelMap::new(1.0, 1000);
        map.add(&pts);
        assert_eq!(map.len(), pts.len());
        for q in [[3.0f32, 2.1, 0.5], [4.9, 5.2, 0.9], [0.01, 0.01, 0.01], [7.3, 1.1, -0.4]] {
            let (p, d2) = map.nearest(&q, 1).unwrap();
            let brute = nearest_linear(&pts, &q).unwrap();
            assert_eq!(d2, brute.dist2, "query {q:?}");
            assert_eq!(p, pts[brute.index]);
        }
    }

    #[test]
    fn full_voxels_keep_their_first_points_and_far_voxels_are_dropped() {
        let mut map = VoxelMap::new(1.0, 2);
        map.add(&[[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3], [50.5, 0.0, 0.0]]);
        assert_eq!(map.len(), 3);
        map.remove_far([0.0, 0.0, 0.0], 10.0);
        assert_eq!(map.len(), 2);
        assert_eq!(map.nearest(&[0.3, 0.3, 0.3], 1).unwrap().0, [0.2, 0.2, 0.2]);
    }
}
