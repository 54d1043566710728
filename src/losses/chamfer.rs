//! Truncated Chamfer distance between a moved cloud X and a fixed target cloud Y (method.md
//! section 2), value and gradient with respect to X.
//!
//! `CD(X, Y) = (1/|X|) sum_x d2(x, Y) [d2 < trunc] + (1/|Y|) sum_y d2(y, X) [d2 < trunc]`, where
//! `d2` is the squared distance (m^2) to the nearest neighbour. Truncated terms count 0 but stay
//! in the denominators. The nearest-neighbour assignment is not differentiated.
//!
//! X -> Y queries a k-d tree over the target that the caller builds once per frame. Y -> X needs
//! the nearest *moved* point of each target point, and X changes every iteration. Only
//! neighbours closer than `sqrt(trunc)` matter (anything farther contributes 0), so a hash grid
//! over X with cells a fraction of that radius, searched ring by ring until no closer point can
//! exist, is exact for the truncated loss and is rebuilt in about a millisecond for 50k points.

use num_traits::Float;
use rayon::prelude::*;

use crate::geometry::Point;
use crate::geometry::knn::{KdTree, dist2};

/// Marks a target point with no moved point within the truncation radius.
const NO_MATCH: u32 = u32::MAX;

/// Grid cells per truncation radius: the search covers at most `(2k+1)^3` cells and stops early
/// once the rings left cannot hold a closer point. Measured on KITTI (benches/chamfer.rs).
const CELLS_PER_RADIUS: i64 = 2;

/// Reusable buffers for [`truncated_chamfer`]: one per fitting thread, kept across iterations so
/// the hot path allocates nothing once the buffers have grown to the cloud sizes.
#[derive(Default)]
pub struct ChamferScratch {
    /// Per target point: index of its nearest moved point within the truncation radius, or
    /// [`NO_MATCH`].
    reverse: Vec<u32>,
    /// Hash grid over the moved points, rebuilt on every call.
    grid: HashGrid,
}

impl ChamferScratch {
    /// Empty scratch; buffers grow on first use.
    pub fn new() -> Self {
        Self::default()
    }
}

/// A prebuilt search structure over the *moved* points for the Y -> X direction.
///
/// Pass one when a k-d tree over exactly the `moved` slice already exists (e.g. the same moved
/// cloud is compared with several targets); otherwise pass `None` and the loss builds its own
/// hash grid, which is cheaper than building a tree.
pub struct ReverseSearch<'a> {
    tree: &'a KdTree,
}

impl<'a> ReverseSearch<'a> {
    /// Wraps a tree built over the same `moved` slice (same points, same order) that the loss
    /// is then called with.
    pub fn from_tree(tree_over_moved: &'a KdTree) -> Self {
        Self { tree: tree_over_moved }
    }
}

/// Truncated Chamfer distance `CD(moved, target)` (m^2), unweighted.
///
/// Adds `weight * dCD/dmoved` into `grad_moved` (same length as `moved`): each moved point x
/// gets `2 (x - y) / |X|` from its own nearest target y, and `2 (x - y) / |Y|` from every target
/// point y whose nearest moved point it is, for pairs with `d2 < truncation_m2`. The target is
/// data and gets no gradient. `target_tree` must be built over `target`. `reverse` optionally
/// supplies a search structure over `moved` for the Y -> X direction (see [`ReverseSearch`]).
///
/// An empty cloud, or a non-positive truncation, truncates every term: the value is 0.
/// Cost: |X| tree queries plus a grid build over X and |Y| grid queries, parallel over points.
///
/// # Panics
/// If `grad_moved.len() != moved.len()`, `target_tree.len() != target.len()`, or a given
/// `reverse` tree does not have `moved.len()` points (caller bugs).
#[allow(clippy::too_many_arguments)] // the signature is the contract the fitting loop uses
pub fn truncated_chamfer(
    moved: &[Point],
    target: &[Point],
    target_tree: &KdTree,
    truncation_m2: f32,
    weight: f32,
    grad_moved: &mut [Point],
    reverse: Option<ReverseSearch<'_>>,
    scratch: &mut ChamferScratch,
) -> f32 {
    assert_eq!(grad_moved.len(), moved.len(), "one gradient row per moved point");
    assert_eq!(target_tree.len(), target.len(), "target_tree must be built over target");
    if let Some(r) = &reverse {
        assert_eq!(r.tree.len(), moved.len(), "the reverse tree must be built over moved");
    }
    // d2 >= 0 is never < a non-positive (or NaN) truncation: every term is truncated.
    if moved.is_empty() || target.is_empty() || truncation_m2.is_nan() || truncation_m2 <= 0.0 {
        return 0.0;
    }
    let (nx, ny) = (moved.len(), target.len());

    // X -> Y: every moved point owns its gradient row, so this direction writes in place.
    let gx = 2.0 * weight / nx as f32;
    let forward: f64 = moved
        .par_iter()
        .zip(grad_moved.par_iter_mut())
        .with_min_len(256)
        .map(|(x, g)| {
            let Some(hit) = target_tree.nearest(x) else { return 0.0 };
            let y = &target[hit.index];
            // Recomputed here so value, truncation test and gradient use one formula.
            let d2 = dist2(x, y);
            if d2 < truncation_m2 {
                for k in 0..3 {
                    g[k] += gx * (x[k] - y[k]);
                }
                f64::from(d2)
            } else {
                0.0
            }
        })
        .sum();

    // Y -> X: find each target point's nearest moved point in parallel, then scatter the
    // gradient sequentially (several target points may share a moved point).
    let ChamferScratch { reverse: matches, grid } = scratch;
    matches.clear();
    matches.resize(ny, NO_MATCH);
    let backward: f64 = match reverse {
        Some(r) => reverse_pass(target, matches, truncation_m2, |y| {
            r.tree.nearest(y).map(|h| (h.index as u32, dist2(&moved[h.index], y)))
        }),
        None if grid.build(moved, truncation_m2) => {
            let grid = &*grid;
            reverse_pass(target, matches, truncation_m2, |y| grid.nearest_within(y, truncation_m2))
        }
        None => {
            // Infinite truncation or coordinates beyond the grid's range: a tree is exact too.
            let tree = KdTree::new(moved);
            reverse_pass(target, matches, truncation_m2, |y| {
                tree.nearest(y).map(|h| (h.index as u32, dist2(&moved[h.index], y)))
            })
        }
    };
    let gy = 2.0 * weight / ny as f32;
    for (y, &m) in target.iter().zip(matches.iter()) {
        if m != NO_MATCH {
            let i = m as usize;
            let x = &moved[i];
            for k in 0..3 {
                grad_moved[i][k] += gy * (x[k] - y[k]);
            }
        }
    }

    (forward / nx as f64 + backward / ny as f64) as f32
}

/// Runs `nearest` for every target point in parallel, records in `matches` the neighbours with
/// `d2 < truncation_m2` (others stay [`NO_MATCH`]) and returns the sum of their `d2`.
fn reverse_pass<Q>(target: &[Point], matches: &mut [u32], truncation_m2: f32, nearest: Q) -> f64
where
    Q: Fn(&Point) -> Option<(u32, f32)> + Sync,
{
    target
        .par_iter()
        .zip(matches.par_iter_mut())
        .with_min_len(256)
        .map(|(y, m)| match nearest(y) {
            Some((index, dist2)) if dist2 < truncation_m2 => {
                *m = index;
                f64::from(dist2)
            }
            _ => 0.0,
        })
        .sum::<f64>()
}

/// Brute-force twin of [`truncated_chamfer`]: O(|X| |Y|) linear scans, same value and gradient
/// (up to ties between equidistant neighbours). For tests and small clouds.
///
/// # Panics
/// If `grad_moved.len() != moved.len()`.
pub fn truncated_chamfer_brute(
    moved: &[Point],
    target: &[Point],
    truncation_m2: f32,
    weight: f32,
    grad_moved: &mut [Point],
) -> f32 {
    truncated_chamfer_brute_generic(moved, target, truncation_m2, weight, grad_moved) as f32
}

/// [`truncated_chamfer_brute`] for any float type (f64 for finite-difference tests). Returns the
/// value in f64 whatever `F` is; sums are accumulated in f64.
///
/// # Panics
/// If `grad_moved.len() != moved.len()`.
pub fn truncated_chamfer_brute_generic<F: Float + Send + Sync>(
    moved: &[[F; 3]],
    target: &[[F; 3]],
    truncation_m2: F,
    weight: F,
    grad_moved: &mut [[F; 3]],
) -> f64 {
    assert_eq!(grad_moved.len(), moved.len(), "one gradient row per moved point");
    if moved.is_empty() || target.is_empty() {
        return 0.0;
    }
    let (nx, ny) = (moved.len(), target.len());
    let two = F::one() + F::one();
    let gx = two * weight / F::from(nx).expect("count fits F");
    let forward: f64 = moved
        .par_iter()
        .zip(grad_moved.par_iter_mut())
        .map(|(x, g)| {
            let (j, d2) = nearest_linear_generic(target, x);
            if d2 < truncation_m2 {
                for k in 0..3 {
                    g[k] = g[k] + gx * (x[k] - target[j][k]);
                }
                d2.to_f64().unwrap_or(f64::NAN)
            } else {
                0.0
            }
        })
        .sum();
    let matches: Vec<(usize, F)> = target.par_iter().map(|y| nearest_linear_generic(moved, y)).collect();
    let gy = two * weight / F::from(ny).expect("count fits F");
    let mut backward = 0.0;
    for (y, &(i, d2)) in target.iter().zip(&matches) {
        if d2 < truncation_m2 {
            backward += d2.to_f64().unwrap_or(f64::NAN);
            for k in 0..3 {
                grad_moved[i][k] = grad_moved[i][k] + gy * (moved[i][k] - y[k]);
            }
        }
    }
    forward / nx as f64 + backward / ny as f64
}

/// Index and squared distance of the nearest point of a non-empty `points` (first on ties).
fn nearest_linear_generic<F: Float>(points: &[[F; 3]], q: &[F; 3]) -> (usize, F) {
    let mut best = (0, F::infinity());
    for (i, p) in points.iter().enumerate() {
        let (dx, dy, dz) = (p[0] - q[0], p[1] - q[1], p[2] - q[2]);
        let d2 = dx * dx + dy * dy + dz * dz;
        if d2 < best.1 {
            best = (i, d2);
        }
    }
    best
}

/// Bits per axis in a packed cell key; 21 x 3 = 63 bits, so `u64::MAX` can mark empty slots.
const KEY_BITS: u32 = 21;
const KEY_MAX: i64 = (1 << KEY_BITS) - 1;
const EMPTY_KEY: u64 = u64::MAX;

/// A sparse voxel grid over one point set: points sorted by cell, and an open-addressing table
/// from a packed cell key to the cell's range in the sorted arrays. All buffers are reused.
#[derive(Default)]
struct HashGrid {
    cell_m: f64,
    inv_cell: f64,
    /// Corner of cell (0, 0, 0), one cell below the bounding box so neighbours stay >= 0.
    origin: [f64; 3],
    /// (cell key, original index), sorted.
    entries: Vec<(u64, u32)>,
    /// Points in sorted order (contiguous per cell) and their original indices.
    points: Vec<Point>,
    index: Vec<u32>,
    table: Vec<Slot>,
    /// `64 - log2(table.len())`, the shift of the multiplicative hash.
    shift: u32,
}

#[derive(Debug, Clone, Copy)]
struct Slot {
    key: u64,
    start: u32,
    end: u32,
}

impl HashGrid {
    /// Rebuilds the grid over `points` for searches within `sqrt(truncation_m2)`. Returns
    /// `false` (grid unusable) when the radius is not finite or the cloud spans more than
    /// 2^21 cells along an axis; the caller then falls back to a tree.
    fn build(&mut self, points: &[Point], truncation_m2: f32) -> bool {
        let radius_m = f64::from(truncation_m2).sqrt();
        if !radius_m.is_finite() || radius_m <= 0.0 {
            return false;
        }
        // The 0.1 % margin keeps every point within the radius inside the searched rings
        // despite rounding in the cell-index arithmetic.
        self.cell_m = radius_m / CELLS_PER_RADIUS as f64 * 1.001;
        self.inv_cell = 1.0 / self.cell_m;
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in points {
            for k in 0..3 {
                lo[k] = lo[k].min(f64::from(p[k]));
                hi[k] = hi[k].max(f64::from(p[k]));
            }
        }
        for k in 0..3 {
            self.origin[k] = lo[k] - self.cell_m;
            let span = (hi[k] - self.origin[k]) * self.inv_cell;
            if span.is_nan() || span >= (KEY_MAX - 2 * CELLS_PER_RADIUS - 2) as f64 {
                return false;
            }
        }

        let n = points.len();
        self.entries.clear();
        self.entries.resize(n, (0, 0));
        let (origin, inv_cell) = (self.origin, self.inv_cell);
        self.entries.par_iter_mut().zip(points.par_iter()).enumerate().with_min_len(1024).for_each(|(i, (e, p))| {
            *e = (HashGrid::key(cell_coords(&origin, inv_cell, p)), i as u32);
        });
        self.entries.par_sort_unstable();

        self.points.clear();
        self.index.clear();
        self.points.extend(self.entries.iter().map(|&(_, i)| points[i as usize]));
        self.index.extend(self.entries.iter().map(|&(_, i)| i));

        let mut cells = 0;
        for w in self.entries.windows(2) {
            cells += usize::from(w[0].0 != w[1].0);
        }
        cells += 1;
        // Load factor <= 1/2 keeps linear probing short, including for misses (empty cells).
        let capacity = (2 * cells).next_power_of_two().max(16);
        self.shift = 64 - capacity.trailing_zeros();
        self.table.clear();
        self.table.resize(capacity, Slot { key: EMPTY_KEY, start: 0, end: 0 });
        let mut start = 0;
        while start < n {
            let key = self.entries[start].0;
            let mut end = start + 1;
            while end < n && self.entries[end].0 == key {
                end += 1;
            }
            let mut s = self.slot_of(key);
            while self.table[s].key != EMPTY_KEY {
                s = (s + 1) & (capacity - 1);
            }
            self.table[s] = Slot { key, start: start as u32, end: end as u32 };
            start = end;
        }
        true
    }

    #[inline]
    fn slot_of(&self, key: u64) -> usize {
        (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> self.shift) as usize
    }

    #[inline]
    fn key(c: [i64; 3]) -> u64 {
        c[0] as u64 | (c[1] as u64) << KEY_BITS | (c[2] as u64) << (2 * KEY_BITS)
    }

    #[inline]
    fn lookup(&self, key: u64) -> Option<(usize, usize)> {
        let mask = self.table.len() - 1;
        let mut s = self.slot_of(key);
        loop {
            let slot = self.table[s];
            if slot.key == key {
                return Some((slot.start as usize, slot.end as usize));
            }
            if slot.key == EMPTY_KEY {
                return None;
            }
            s = (s + 1) & mask;
        }
    }

    /// The nearest grid point strictly closer than `sqrt(truncation_m2)` to `q`: (original
    /// index, squared distance), or `None`. Exact: rings are searched outward until the next
    /// ring's lower distance bound reaches the best distance so far.
    fn nearest_within(&self, q: &Point, truncation_m2: f32) -> Option<(u32, f32)> {
        let c = cell_coords(&self.origin, self.inv_cell, q);
        let mut best = (NO_MATCH, truncation_m2);
        for s in 0..=CELLS_PER_RADIUS {
            // Cells of ring s lie at least (s - 1) cells away along some axis.
            let ring_lb = ((s - 1).max(0) as f64 * self.cell_m).powi(2);
            if ring_lb * (1.0 - 1e-5) >= f64::from(best.1) {
                break;
            }
            for dz in -s..=s {
                for dy in -s..=s {
                    let on_face = dz.abs() == s || dy.abs() == s;
                    let step = if on_face || s == 0 { 1 } else { 2 * s as usize };
                    for dx in (-s..=s).step_by(step) {
                        self.scan_cell(q, [c[0] + dx, c[1] + dy, c[2] + dz], &mut best);
                    }
                }
            }
        }
        (best.0 != NO_MATCH).then_some(best)
    }

    /// Updates `best` with the points of cell `cc` closer than `best.1`.
    #[inline]
    fn scan_cell(&self, q: &Point, cc: [i64; 3], best: &mut (u32, f32)) {
        if cc.iter().any(|&v| !(0..=KEY_MAX).contains(&v)) {
            return;
        }
        // Lower bound of the distance from q to the cell box; the small relative slack covers
        // f32 rounding in the point distances, so no cell holding a closer point is skipped.
        let mut lb = 0.0;
        for k in 0..3 {
            let lo = self.origin[k] + cc[k] as f64 * self.cell_m;
            let qk = f64::from(q[k]);
            let gap = (lo - qk).max(qk - lo - self.cell_m).max(0.0);
            lb += gap * gap;
        }
        if lb * (1.0 - 1e-5) >= f64::from(best.1) {
            return;
        }
        let Some((start, end)) = self.lookup(Self::key(cc)) else { return };
        for (p, &i) in self.points[start..end].iter().zip(&self.index[start..end]) {
            let d2 = dist2(p, q);
            if d2 < best.1 {
                *best = (i, d2);
            }
        }
    }
}

/// Integer cell coordinates of `p` in a grid with corner `origin` and cells `1 / inv_cell` wide
/// (f64, so far-from-origin coordinates keep their sub-cell position).
#[inline]
fn cell_coords(origin: &[f64; 3], inv_cell: f64, p: &Point) -> [i64; 3] {
    std::array::from_fn(|k| ((f64::from(p[k]) - origin[k]) * inv_cell).floor() as i64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::knn::nearest_linear;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_cloud(n: usize, half_extent_m: f32, rng: &mut ChaCha8Rng) -> Vec<Point> {
        (0..n)
            .map(|_| {
                [
                    rng.random_range(-half_extent_m..half_extent_m),
                    rng.random_range(-half_extent_m..half_extent_m),
                    rng.random_range(-2.0..2.0),
                ]
            })
            .collect()
    }

    /// LiDAR ground: a flat, axis-aligned grid where many points share exact coordinates.
    fn flat_ground(n_side: usize, spacing_m: f32) -> Vec<Point> {
        let mut pts = Vec::new();
        for i in 0..n_side {
            for j in 0..n_side {
                pts.push([i as f32 * spacing_m, j as f32 * spacing_m, -1.7]);
            }
        }
        pts
    }

    fn fast(moved: &[Point], target: &[Point], trunc: f32, weight: f32, reverse_tree: bool) -> (f32, Vec<Point>) {
        let tree = KdTree::new(target);
        let own = reverse_tree.then(|| KdTree::new(moved));
        let mut grad = vec![[0.0; 3]; moved.len()];
        let mut scratch = ChamferScratch::new();
        let v = truncated_chamfer(
            moved,
            target,
            &tree,
            trunc,
            weight,
            &mut grad,
            own.as_ref().map(ReverseSearch::from_tree),
            &mut scratch,
        );
        (v, grad)
    }

    fn brute(moved: &[Point], target: &[Point], trunc: f32, weight: f32) -> (f32, Vec<Point>) {
        let mut grad = vec![[0.0; 3]; moved.len()];
        let v = truncated_chamfer_brute(moved, target, trunc, weight, &mut grad);
        (v, grad)
    }

    /// Compares value (relative) and gradient (absolute, relative to the largest entry).
    fn assert_close(a: &(f32, Vec<Point>), b: &(f32, Vec<Point>), what: &str) {
        // Values are f64 sums of the same f32 terms in different orders: ~1e-7 relative.
        assert!((a.0 - b.0).abs() <= 1e-5 * b.0.abs().max(1e-12), "{what}: value {} vs {}", a.0, b.0);
        let scale = b.1.iter().flatten().fold(0.0f32, |m, g| m.max(g.abs())).max(1e-12);
        for (i, (ga, gb)) in a.1.iter().zip(&b.1).enumerate() {
            for k in 0..3 {
                // Each entry is a sum of a few f32 terms added in a different order: 1e-5 of
                // the largest entry is far above that rounding and far below one term.
                assert!((ga[k] - gb[k]).abs() <= 1e-5 * scale, "{what}: grad[{i}][{k}] {} vs {}", ga[k], gb[k]);
            }
        }
    }

    #[test]
    fn chamfer_of_a_cloud_with_itself_is_zero() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for cloud in [random_cloud(2000, 20.0, &mut rng), flat_ground(40, 0.2)] {
            for reverse_tree in [false, true] {
                let (v, grad) = fast(&cloud, &cloud, 2.0, 1.0, reverse_tree);
                assert_eq!(v, 0.0);
                assert!(grad.iter().flatten().all(|&g| g == 0.0));
            }
        }
    }

    #[test]
    fn truncation_drops_far_pairs_but_keeps_them_in_the_denominator() {
        let moved = [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]];
        let target = [[0.5, 0.0, 0.0]];
        // X -> Y: (0.25 + truncated 90.25) / 2; Y -> X: 0.25 / 1.
        let expected = 0.25 / 2.0 + 0.25;
        for (v, grad) in [fast(&moved, &target, 2.0, 3.0, false), brute(&moved, &target, 2.0, 3.0)] {
            assert_eq!(v, expected);
            // weight 3 * (2 (0 - 0.5) / 2 + 2 (0 - 0.5) / 1) = -4.5 on x; the far point gets 0.
            assert_eq!(grad, vec![[-4.5, 0.0, 0.0], [0.0, 0.0, 0.0]]);
        }
        // Without truncation the far pair counts.
        let (v, _) = brute(&moved, &target, f32::INFINITY, 1.0);
        assert_eq!(v, (0.25 + 90.25) / 2.0 + 0.25);
    }

    #[test]
    fn fast_chamfer_matches_brute_force_on_random_clouds() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for (nx, ny, extent) in [(3000, 2500, 30.0), (500, 4000, 5.0), (1, 300, 3.0), (300, 1, 3.0)] {
            let moved = random_cloud(nx, extent, &mut rng);
            let target = random_cloud(ny, extent, &mut rng);
            let slow = brute(&moved, &target, 2.0, 0.7);
            assert!(slow.0 > 0.0);
            for reverse_tree in [false, true] {
                assert_close(&fast(&moved, &target, 2.0, 0.7, reverse_tree), &slow, &format!("{nx}x{ny}"));
            }
        }
    }

    #[test]
    fn fast_chamfer_matches_brute_force_on_flat_ground() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let target = flat_ground(50, 0.3);
        // Moved: the ground shifted by a fraction of the spacing, plus scattered points.
        let mut moved: Vec<Point> = target.iter().map(|p| [p[0] + 0.11, p[1] - 0.07, p[2]]).collect();
        moved.extend(random_cloud(300, 10.0, &mut rng));
        for trunc in [2.0, 0.05, 0.0001] {
            let slow = brute(&moved, &target, trunc, 1.0);
            assert_close(&fast(&moved, &target, trunc, 1.0, false), &slow, &format!("trunc {trunc}"));
        }
    }

    #[test]
    fn fast_chamfer_falls_back_exactly_for_huge_spans_and_infinite_truncation() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut moved = random_cloud(400, 5.0, &mut rng);
        let target = random_cloud(400, 5.0, &mut rng);
        // One point 3e6 m away: more than 2^21 cells of 0.7 m, so the grid declines.
        moved.push([3.0e6, 0.0, 0.0]);
        assert_close(&fast(&moved, &target, 2.0, 1.0, false), &brute(&moved, &target, 2.0, 1.0), "far point");
        assert_close(
            &fast(&moved, &target, f32::INFINITY, 1.0, false),
            &brute(&moved, &target, f32::INFINITY, 1.0),
            "infinite truncation",
        );
    }

    #[test]
    fn grid_nearest_within_matches_a_linear_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut points = random_cloud(3000, 8.0, &mut rng);
        points.extend(flat_ground(30, 0.05));
        let trunc = 0.3;
        let mut grid = HashGrid::default();
        assert!(grid.build(&points, trunc));
        // Queries inside, around and far outside the bounding box.
        for q in random_cloud(2000, 12.0, &mut rng).iter().chain(points.iter().step_by(41)) {
            let slow = nearest_linear(&points, q).unwrap();
            match grid.nearest_within(q, trunc) {
                Some((i, d2)) => {
                    assert_eq!(d2, slow.dist2, "query {q:?}");
                    assert_eq!(dist2(&points[i as usize], q), d2);
                }
                None => assert!(slow.dist2 >= trunc, "query {q:?}: missed {slow:?}"),
            }
        }
    }

    #[test]
    fn empty_clouds_give_zero() {
        let cloud = [[1.0, 2.0, 3.0]];
        assert_eq!(fast(&[], &cloud, 2.0, 1.0, false).0, 0.0);
        let (v, grad) = fast(&cloud, &[], 2.0, 1.0, false);
        assert_eq!((v, grad), (0.0, vec![[0.0; 3]]));
        assert_eq!(brute(&[], &cloud, 2.0, 1.0).0, 0.0);
    }

    #[test]
    fn chamfer_gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let n = 40;
        let moved: Vec<[f64; 3]> = (0..n).map(|_| std::array::from_fn(|_| rng.random_range(-3.0..3.0))).collect();
        // Target: a noisy copy plus a few far points, so both truncated and kept terms occur.
        let mut target: Vec<[f64; 3]> =
            moved.iter().map(|p| std::array::from_fn(|k| p[k] + rng.random_range(-0.8..0.8))).collect();
        target.extend((0..5).map(|i| [20.0 + i as f64, 0.0, 0.0]));
        let (trunc, weight, h) = (2.0, 1.3, 1e-6);

        // The fixture must keep every nearest-neighbour assignment and truncation decision under
        // +-h: nearest and second nearest differ by far more than the ~2 * 6 * h a move can
        // change a squared distance, and no kept distance is near the truncation.
        let margin = 1e-3;
        let check = |a: &[[f64; 3]], b: &[[f64; 3]]| {
            for q in a {
                let mut d: Vec<f64> = b.iter().map(|p| (0..3).map(|k| (p[k] - q[k]) * (p[k] - q[k])).sum()).collect();
                d.sort_by(f64::total_cmp);
                assert!(d[1] - d[0] > margin && (d[0] - trunc).abs() > margin, "fixture too close to a kink");
            }
        };
        check(&moved, &target);
        check(&target, &moved);

        let mut grad = vec![[0.0; 3]; n];
        truncated_chamfer_brute_generic(&moved, &target, trunc, weight, &mut grad);
        let value = |m: &[[f64; 3]]| {
            let mut g = vec![[0.0; 3]; n];
            weight * truncated_chamfer_brute_generic(m, &target, trunc, 0.0, &mut g)
        };
        for i in 0..n {
            for k in 0..3 {
                let (mut plus, mut minus) = (moved.clone(), moved.clone());
                plus[i][k] += h;
                minus[i][k] -= h;
                let fd = (value(&plus) - value(&minus)) / (2.0 * h);
                // Piecewise quadratic with fixed assignments: central differences are exact up
                // to rounding (~1e-16 * value / h ≈ 1e-10).
                assert!((fd - grad[i][k]).abs() < 1e-7, "point {i} axis {k}: fd {fd} vs {}", grad[i][k]);
            }
        }
    }
}
