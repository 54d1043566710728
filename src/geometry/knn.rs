//! Nearest-neighbour search over a fixed point set: a `kiddo` k-d tree built once and queried many
//! times, with brute-force twins used by the tests.

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::Point;

/// An immutable k-d tree over one point set (a frame, or a moved copy of one).
///
/// Build once per target frame and reuse it across iterations: building costs O(n log n)
/// (about 5 ms for 50k points), each exact nearest query O(log n).
pub struct KdTree {
    /// `None` when the point set is empty: every query then finds nothing.
    tree: Option<ImmutableKdTree<f32, 3>>,
    len: usize,
}

/// The nearest neighbour of a query point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nearest {
    /// Index of the neighbour in the point set the tree was built from.
    pub index: usize,
    /// Squared Euclidean distance to it (m^2).
    pub dist2: f32,
}

impl KdTree {
    /// Builds the tree over `points` (metric coordinates). Points must be finite.
    pub fn new(points: &[Point]) -> Self {
        let tree = if points.is_empty() {
            None
        } else {
            // Only fails when the index overflows u32 (> 4 billion points): a caller bug.
            Some(ImmutableKdTree::new_from_slice(points).expect("point count fits in u32"))
        };
        Self { tree, len: points.len() }
    }

    /// Number of points in the tree.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the tree holds no point.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The exact nearest neighbour of `query`, or `None` for an empty tree.
    pub fn nearest(&self, query: &Point) -> Option<Nearest> {
        let tree = self.tree.as_ref()?;
        let hit = tree.query(query).nearest_one::<SquaredEuclidean<f32>>().execute();
        Some(Nearest { index: hit.item as usize, dist2: hit.distance })
    }

    /// Nearest neighbours of every query, written into `out` (same length as `queries`), in
    /// parallel over the rayon pool. Leaves `out` untouched when the tree is empty and returns
    /// `false` then.
    pub fn nearest_batch(&self, queries: &[Point], out: &mut [Nearest]) -> bool {
        assert_eq!(queries.len(), out.len(), "one output slot per query");
        let Some(tree) = self.tree.as_ref() else {
            return false;
        };
        queries.par_iter().zip(out.par_iter_mut()).with_min_len(512).for_each(|(q, o)| {
            let hit = tree.query(q).nearest_one::<SquaredEuclidean<f32>>().execute();
            *o = Nearest { index: hit.item as usize, dist2: hit.distance };
        });
        true
    }

    /// Appends to `out` the indices of all points within `radius_m` of `query` (inclusive),
    /// in no particular order. `out` is cleared first so callers can reuse one buffer.
    pub fn within(&self, query: &Point, radius_m: f32, out: &mut Vec<usize>) {
        out.clear();
        let Some(tree) = self.tree.as_ref() else {
            return;
        };
        let hits = tree.query(query).within::<SquaredEuclidean<f32>>(radius_m * radius_m).unsorted().execute();
        out.extend(hits.into_iter().map(|h| h.item as usize));
    }

    /// Calls `visit` with the index of every point within `radius_m` of `query` (inclusive), in
    /// no particular order, without allocating: the streaming form of [`KdTree::within`] for hot
    /// loops that only count or scan the neighbours.
    pub fn for_each_within(&self, query: &Point, radius_m: f32, mut visit: impl FnMut(usize)) {
        let Some(tree) = self.tree.as_ref() else {
            return;
        };
        tree.query(query)
            .within::<SquaredEuclidean<f32>>(radius_m * radius_m)
            .unsorted()
            .visit(|h| visit(h.item as usize));
    }
}

/// Brute-force twin of [`KdTree::nearest`]: a linear scan, O(n) per query.
pub fn nearest_linear(points: &[Point], query: &Point) -> Option<Nearest> {
    points
        .iter()
        .enumerate()
        .map(|(index, p)| Nearest { index, dist2: dist2(p, query) })
        .min_by(|a, b| a.dist2.total_cmp(&b.dist2))
}

/// Brute-force twin of [`KdTree::within`]: every index whose point lies within `radius_m`.
pub fn within_linear(points: &[Point], query: &Point, radius_m: f32) -> Vec<usize> {
    let r2 = radius_m * radius_m;
    (0..points.len()).filter(|&i| dist2(&points[i], query) <= r2).collect()
}

/// Squared Euclidean distance (m^2).
#[inline]
pub fn dist2(a: &Point, b: &Point) -> f32 {
    let dx = a[0] - b[0];
    let dy = a[1] - b[1];
    let dz = a[2] - b[2];
    dx * dx + dy * dy + dz * dz
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_cloud(n: usize, seed: u64) -> Vec<Point> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| [rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0), rng.random_range(-2.0..2.0)])
            .collect()
    }

    /// LiDAR ground is flat and axis aligned: many points share exactly one coordinate.
    fn flat_grid(n_side: usize) -> Vec<Point> {
        let mut pts = Vec::new();
        for i in 0..n_side {
            for j in 0..n_side {
                pts.push([i as f32 * 0.1, j as f32 * 0.1, 0.0]);
            }
        }
        pts
    }

    fn check_nearest_matches_linear(points: &[Point], queries: &[Point]) {
        let tree = KdTree::new(points);
        let mut batch = vec![Nearest { index: 0, dist2: 0.0 }; queries.len()];
        assert!(tree.nearest_batch(queries, &mut batch));
        for (q, b) in queries.iter().zip(&batch) {
            let fast = tree.nearest(q).unwrap();
            let slow = nearest_linear(points, q).unwrap();
            // Ties may pick different indices; the distance must agree exactly.
            assert_eq!(fast.dist2, slow.dist2, "query {q:?}");
            assert_eq!(b.dist2, slow.dist2);
            assert_eq!(dist2(&points[fast.index], q), slow.dist2);
        }
    }

    #[test]
    fn kd_tree_nearest_matches_a_linear_scan_on_random_points() {
        let points = random_cloud(3000, 1);
        let queries = random_cloud(500, 2);
        check_nearest_matches_linear(&points, &queries);
    }

    #[test]
    fn kd_tree_nearest_matches_a_linear_scan_on_a_flat_ground_plane() {
        let points = flat_grid(60);
        let mut queries = random_cloud(300, 3);
        queries.extend(points.iter().step_by(37).copied());
        check_nearest_matches_linear(&points, &queries);
    }

    #[test]
    fn kd_tree_radius_query_matches_a_linear_scan() {
        for points in [random_cloud(2000, 4), flat_grid(40)] {
            let tree = KdTree::new(&points);
            let mut out = Vec::new();
            for q in random_cloud(100, 5).iter().chain(points.iter().step_by(53)) {
                tree.within(q, 0.8, &mut out);
                let mut fast = out.clone();
                fast.sort_unstable();
                assert_eq!(fast, within_linear(&points, q, 0.8));
            }
        }
    }

    #[test]
    fn streaming_radius_query_visits_the_same_points_as_within() {
        for points in [random_cloud(2000, 6), flat_grid(40)] {
            let tree = KdTree::new(&points);
            let mut out = Vec::new();
            let mut streamed = Vec::new();
            for q in random_cloud(50, 7).iter().chain(points.iter().step_by(41)) {
                tree.within(q, 0.8, &mut out);
                out.sort_unstable();
                streamed.clear();
                tree.for_each_within(q, 0.8, |i| streamed.push(i));
                streamed.sort_unstable();
                assert_eq!(streamed, out);
            }
        }
    }

    #[test]
    fn an_empty_tree_finds_nothing() {
        let tree = KdTree::new(&[]);
        assert!(tree.nearest(&[0.0, 0.0, 0.0]).is_none());
        let mut out = vec![1];
        tree.within(&[0.0, 0.0, 0.0], 1.0, &mut out);
        assert!(out.is_empty());
    }
}
