//! Voxel grids: downsampling a cloud to one point per voxel, and the voxel-hashed local map the
//! frames are registered against.
//!
//! Results never depend on the hash map's iteration order (std's hasher is seeded at random):
//! downsampling keeps points in input order, a neighbour search visits voxels in a fixed order
//! and points in insertion order, and removal keeps or drops each voxel on its own.

use std::collections::HashMap;
use std::collections::hash_map::Entry;

use nalgebra::{Isometry3, Point3};

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
