//! DBSCAN clustering of one frame (method.md section 3: eps 0.8 m, min_points 30), with a
//! brute-force twin for the tests.
//!
//! Semantics shared by both implementations, so that they agree label for label:
//! - the eps-neighbourhood of p is every point q with ‖p − q‖ ≤ eps (p itself included);
//!   p is a core point when it has at least `min_points` neighbours;
//! - core points within eps of each other are in one cluster (connected components);
//! - a non-core point within eps of a core point is a border point and joins the cluster of its
//!   lowest-index core neighbour; every other point is [`NOISE`];
//! - clusters are numbered 0..k in the order of their smallest point index;
//! - points with a non-finite coordinate are noise and neighbours of nothing.

use std::sync::atomic::{AtomicU32, Ordering};

use rayon::prelude::*;

use super::Point;
use super::knn::{KdTree, dist2};

/// Label of a point that belongs to no cluster.
pub const NOISE: i32 = -1;

/// Marks "no core neighbour" while border points are assigned.
const NONE: u32 = u32::MAX;

/// Clusters `points` with DBSCAN; returns one label per point (clusters 0..k−1, [`NOISE`]).
///
/// `eps_m` is the neighbourhood radius (m); a NaN or negative radius is treated as 0 (only
/// coincident points are neighbours). `min_points` counts the point itself; 0 behaves as 1.
/// Deterministic whatever the thread count (see the module doc for the exact rules).
///
/// Cost: a k-d tree build and up to two radius queries per point, both passes parallel over the
/// rayon pool (the counting query is skipped where a dense grid cell already proves a point
/// core); connectivity by a lock-free union-find whose roots are the smallest index of each
/// component, so the result does not depend on the order the threads link edges in.
pub fn dbscan(points: &[Point], eps_m: f32, min_points: usize) -> Vec<i32> {
    let n = points.len();
    if n == 0 {
        return Vec::new();
    }
    assert!(n < NONE as usize, "point count fits in u32");
    let eps_m = sanitize_eps(eps_m);
    let min_points = min_points.max(1);
    // Non-finite points stay out of the tree (kiddo needs finite coordinates); tree indices map
    // back to point indices through `ids`, which is increasing, so index order is preserved.
    let all_finite = points.iter().all(is_finite);
    let (finite, ids): (Vec<Point>, Vec<u32>) = if all_finite {
        (Vec::new(), Vec::new())
    } else {
        points.iter().enumerate().filter(|(_, p)| is_finite(p)).map(|(i, p)| (*p, i as u32)).unzip()
    };
    let cloud: &[Point] = if all_finite { points } else { &finite };
    let to_point = |t: usize| if all_finite { t } else { ids[t] as usize };
    let tree = KdTree::new(cloud);

    // Pass 1: core flags from neighbour counts. A point whose dense cell already holds
    // min_points points is core without a query: those are exactly the points whose queries
    // visit hundreds of neighbours (on KITTI most of the cost).
    let cell_count = dense_cell_counts(cloud, eps_m);
    let core: Vec<bool> = cloud
        .par_iter()
        .zip(&cell_count)
        .with_min_len(256)
        .map(|(p, &in_cell)| {
            if in_cell as usize >= min_points {
                return true;
            }
            let mut count = 0usize;
            tree.for_each_within(p, eps_m, |_| count += 1);
            count >= min_points
        })
        .collect();

    // Pass 2: link core neighbours; remember each non-core point's lowest-index core neighbour.
    let parent: Vec<AtomicU32> = (0..cloud.len() as u32).map(AtomicU32::new).collect();
    let border_of: Vec<u32> = cloud
        .par_iter()
        .enumerate()
        .with_min_len(256)
        .map(|(i, p)| {
            let mut lowest_core = NONE;
            if core[i] {
                // A root of i's component seen last; a neighbour whose parent is that root is
                // already linked (components only ever merge), which skips almost every union.
                let mut root = i as u32;
                tree.for_each_within(p, eps_m, |j| {
                    if j < i && core[j] && parent[j].load(Ordering::Relaxed) != root {
                        root = union(&parent, root, j as u32);
                    }
                });
            } else {
                tree.for_each_within(p, eps_m, |j| {
                    if core[j] && (j as u32) < lowest_core {
                        lowest_core = j as u32;
                    }
                });
            }
            lowest_core
        })
        .collect();

    // Sequential labelling in index order; the root of a core point's component is its smallest
    // core index, the border's cluster is that of its lowest-index core neighbour.
    let mut root_label = vec![NOISE; cloud.len()];
    let mut labels = vec![NOISE; n];
    let mut next = 0i32;
    for t in 0..cloud.len() {
        let anchor = if core[t] {
            t
        } else if border_of[t] != NONE {
            border_of[t] as usize
        } else {
            continue;
        };
        let root = find(&parent, anchor as u32) as usize;
        if root_label[root] == NOISE {
            root_label[root] = next;
            next += 1;
        }
        labels[to_point(t)] = root_label[root];
    }
    labels
}

/// The O(n²) twin of [`dbscan`] with the same rules: explicit neighbour scans and a breadth-first
/// expansion from each unvisited core point in index order. For tests on small clouds.
pub fn dbscan_brute_force(points: &[Point], eps_m: f32, min_points: usize) -> Vec<i32> {
    let n = points.len();
    let eps_m = sanitize_eps(eps_m);
    let r2 = eps_m * eps_m;
    let min_points = min_points.max(1);
    let neighbours: Vec<Vec<usize>> = (0..n)
        .map(|i| {
            if !is_finite(&points[i]) {
                return Vec::new();
            }
            (0..n).filter(|&j| is_finite(&points[j]) && dist2(&points[i], &points[j]) <= r2).collect()
        })
        .collect();
    let core: Vec<bool> = neighbours.iter().map(|nb| nb.len() >= min_points).collect();
    // Components of core points, first numbered by their smallest core index.
    let mut component = vec![usize::MAX; n];
    let mut n_components = 0;
    let mut queue = std::collections::VecDeque::new();
    for start in 0..n {
        if !core[start] || component[start] != usize::MAX {
            continue;
        }
        component[start] = n_components;
        queue.push_back(start);
        while let Some(i) = queue.pop_front() {
            for &j in &neighbours[i] {
                if core[j] && component[j] == usize::MAX {
                    component[j] = n_components;
                    queue.push_back(j);
                }
            }
        }
        n_components += 1;
    }
    for i in 0..n {
        if !core[i]
            && let Some(&j) = neighbours[i].iter().filter(|&&j| core[j]).min()
        {
            component[i] = component[j];
        }
    }
    // Renumber by smallest member index, borders included.
    let mut relabel = vec![NOISE; n_components];
    let mut next = 0;
    component
        .iter()
        .map(|&c| {
            if c == usize::MAX {
                return NOISE;
            }
            if relabel[c] == NOISE {
                relabel[c] = next;
                next += 1;
            }
            relabel[c]
        })
        .collect()
}

/// Point indices of each cluster, in label order (cluster k at position k); noise is left out.
/// Indices within a cluster are increasing.
pub fn clusters(labels: &[i32]) -> Vec<Vec<u32>> {
    let k = labels.iter().copied().max().map_or(0, |m| (m + 1).max(0) as usize);
    let mut out = vec![Vec::new(); k];
    for (i, &l) in labels.iter().enumerate() {
        if l >= 0 {
            out[l as usize].push(i as u32);
        }
    }
    out
}

/// For every point, the number of points in its cell of a grid with side 0.99 · eps / √3: any two
/// points of one cell are within eps of each other, so this is a lower bound on the neighbour
/// count. The 1 % margin keeps the bound exact under f32 rounding of the cell index and of the
/// distance test (both ~1e-7 relative); points farther than 1e4 cells from the origin, where the
/// index rounding grows, count only themselves. O(n log n) for the sort.
fn dense_cell_counts(points: &[Point], eps_m: f32) -> Vec<u32> {
    let side_m = 0.99 * eps_m / 3f32.sqrt();
    let mut counts = vec![1u32; points.len()];
    let usable = side_m > 0.0 && side_m.is_finite();
    if !usable {
        return counts;
    }
    let inv = 1.0 / side_m;
    let mut keyed: Vec<([i32; 3], u32)> = points
        .iter()
        .enumerate()
        .filter_map(|(i, p)| {
            let c = p.map(|v| (v * inv).floor());
            c.iter().all(|v| v.abs() < 1e4).then(|| (c.map(|v| v as i32), i as u32))
        })
        .collect();
    keyed.par_sort_unstable_by_key(|k| k.0);
    for run in keyed.chunk_by(|a, b| a.0 == b.0) {
        for &(_, i) in run {
            counts[i as usize] = run.len() as u32;
        }
    }
    counts
}

fn sanitize_eps(eps_m: f32) -> f32 {
    if eps_m >= 0.0 { eps_m } else { 0.0 }
}

fn is_finite(p: &Point) -> bool {
    p.iter().all(|c| c.is_finite())
}

/// Root of `x` with path halving. Parents only ever point to smaller indices, so this terminates
/// and concurrent halving never creates a cycle.
fn find(parent: &[AtomicU32], mut x: u32) -> u32 {
    loop {
        let p = parent[x as usize].load(Ordering::Acquire);
        if p == x {
            return x;
        }
        let gp = parent[p as usize].load(Ordering::Acquire);
        if gp != p {
            // Failure just means another thread moved x up already.
            let _ = parent[x as usize].compare_exchange(p, gp, Ordering::AcqRel, Ordering::Acquire);
        }
        x = p;
    }
}

/// Links the components of `a` and `b`, the larger root under the smaller one, so that every
/// component ends rooted at its smallest index whatever the interleaving. Returns the root of the
/// merged component at the time of linking.
fn union(parent: &[AtomicU32], a: u32, b: u32) -> u32 {
    let (mut a, mut b) = (a, b);
    loop {
        a = find(parent, a);
        b = find(parent, b);
        if a == b {
            return a;
        }
        let (lo, hi) = if a < b { (a, b) } else { (b, a) };
        if parent[hi as usize].compare_exchange(hi, lo, Ordering::AcqRel, Ordering::Acquire).is_ok() {
            return lo;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::seq::SliceRandom;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Gaussian-ish blobs (sum of uniforms) plus uniform background noise.
    fn random_clusters(n_blobs: usize, per_blob: usize, n_noise: usize, seed: u64) -> Vec<Point> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut pts = Vec::new();
        for _ in 0..n_blobs {
            let c: [f32; 3] =
                [rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0), rng.random_range(-1.0..1.0)];
            for _ in 0..per_blob {
                let mut p = c;
                for v in &mut p {
                    *v += (0..3).map(|_| rng.random_range(-0.6f32..0.6)).sum::<f32>();
                }
                pts.push(p);
            }
        }
        for _ in 0..n_noise {
            pts.push([rng.random_range(-25.0..25.0), rng.random_range(-25.0..25.0), rng.random_range(-2.0..2.0)]);
        }
        pts.shuffle(&mut rng);
        pts
    }

    /// A flat, axis-aligned ground grid (kiddo's README warns about exactly this) with gaps, so
    /// that several clusters, borders and noise appear.
    fn flat_ground(seed: u64) -> Vec<Point> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut pts = Vec::new();
        for i in 0..60 {
            for j in 0..40 {
                // Thin the grid randomly so densities differ from place to place.
                if (i / 15 + j / 10) % 3 == 0 || rng.random_bool(0.3) {
                    pts.push([i as f32 * 0.25, j as f32 * 0.25, -1.73]);
                }
            }
        }
        pts
    }

    fn core_flags(points: &[Point], eps_m: f32, min_points: usize) -> Vec<bool> {
        let r2 = eps_m * eps_m;
        points.iter().map(|p| points.iter().filter(|q| dist2(p, q) <= r2).count() >= min_points).collect()
    }

    #[test]
    fn dbscan_matches_brute_force_on_random_clusters() {
        for (seed, eps, min_pts) in [(1, 0.8, 30), (2, 0.5, 10), (3, 1.2, 5), (4, 0.8, 1)] {
            let pts = random_clusters(12, 150, 300, seed);
            let fast = dbscan(&pts, eps, min_pts);
            let slow = dbscan_brute_force(&pts, eps, min_pts);
            // Same deterministic rules, same inclusive distance test: identical labels.
            assert_eq!(fast, slow, "seed {seed}");
            assert!(clusters(&fast).len() > 1, "the fixture must produce several clusters");
        }
    }

    #[test]
    fn dbscan_matches_brute_force_on_a_flat_ground_plane() {
        for (eps, min_pts) in [(0.8, 30), (0.3, 5), (0.25, 5)] {
            let pts = flat_ground(5);
            let fast = dbscan(&pts, eps, min_pts);
            let slow = dbscan_brute_force(&pts, eps, min_pts);
            assert_eq!(fast, slow, "eps {eps} min {min_pts}");
        }
    }

    /// Canonical form of a labelling restricted to `keep`: each kept point's label replaced by
    /// the smallest kept index with the same label (noise stays noise).
    fn canonical(labels: &[i32], keep: &[bool]) -> Vec<i64> {
        let mut first = std::collections::HashMap::new();
        labels
            .iter()
            .enumerate()
            .map(|(i, &l)| if !keep[i] || l == NOISE { -1 } else { *first.entry(l).or_insert(i as i64) })
            .collect()
    }

    #[test]
    fn min_points_one_leaves_no_noise() {
        let pts = random_clusters(3, 20, 50, 6);
        let labels = dbscan(&pts, 0.5, 1);
        assert!(labels.iter().all(|&l| l >= 0));
        assert_eq!(labels, dbscan_brute_force(&pts, 0.5, 1));
    }

    #[test]
    fn edge_cases_give_sane_labels() {
        assert!(dbscan(&[], 0.8, 30).is_empty());
        assert!(clusters(&[]).is_empty());
        assert_eq!(dbscan(&[[1.0, 2.0, 3.0]], 0.8, 1), vec![0]);
        assert_eq!(dbscan(&[[1.0, 2.0, 3.0]], 0.8, 2), vec![NOISE]);
        // Non-finite points are noise and do not connect anything; NaN eps acts as 0.
        let pts = [[0.0, 0.0, 0.0], [f32::NAN, 0.0, 0.0], [0.1, 0.0, 0.0], [f32::INFINITY, 0.0, 0.0]];
        assert_eq!(dbscan(&pts, 0.5, 1), vec![0, NOISE, 0, NOISE]);
        assert_eq!(dbscan(&pts, 0.5, 1), dbscan_brute_force(&pts, 0.5, 1));
        assert_eq!(dbscan(&pts, f32::NAN, 1), vec![0, NOISE, 1, NOISE]);
        assert_eq!(dbscan(&pts, -1.0, 1), dbscan_brute_force(&pts, -1.0, 1));
        // Coincident points with eps 0 are still neighbours.
        assert_eq!(dbscan(&[[1.0; 3], [1.0; 3]], 0.0, 2), vec![0, 0]);
        assert_eq!(clusters(&[NOISE, 1, 0, 1]), vec![vec![2], vec![1, 3]]);
    }

    #[test]
    fn dense_cell_counts_never_exceed_the_true_neighbour_count() {
        // Tight blobs make many dense cells; the shortcut must only ever under-count.
        let mut pts = random_clusters(3, 300, 0, 8);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        pts.extend(
            (0..3000).map(|_| [rng.random_range(5.0..6.0), rng.random_range(5.0..6.0), rng.random_range(0.0..1.0)]),
        );
        for eps in [0.3f32, 0.8] {
            let counts = dense_cell_counts(&pts, eps);
            assert!(counts.iter().any(|&c| c >= 10), "fixture has dense cells");
            for (p, &c) in pts.iter().zip(&counts) {
                let truth = pts.iter().filter(|q| dist2(p, q) <= eps * eps).count();
                assert!(c as usize <= truth);
            }
        }
    }

    #[test]
    fn labels_are_numbered_by_smallest_member_index() {
        let pts = random_clusters(8, 80, 100, 7);
        let labels = dbscan(&pts, 0.8, 10);
        let firsts: Vec<u32> = clusters(&labels).iter().map(|c| c[0]).collect();
        assert!(firsts.windows(2).all(|w| w[0] < w[1]));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        /// Permuting the points permutes the labelling: core points and noise are identical up
        /// to relabelling; a border point may change cluster only if it is within eps of a core
        /// point of its new cluster (ties between clusters are broken by index).
        #[test]
        fn dbscan_is_invariant_under_permutation(seed in 0u64..1000, min_pts in 2usize..20) {
            let pts = random_clusters(6, 60, 80, seed);
            let eps = 0.7;
            let mut perm: Vec<usize> = (0..pts.len()).collect();
            perm.shuffle(&mut ChaCha8Rng::seed_from_u64(seed + 1));
            let permuted: Vec<Point> = perm.iter().map(|&i| pts[i]).collect();
            let a = dbscan(&pts, eps, min_pts);
            let b_perm = dbscan(&permuted, eps, min_pts);
            let mut b = vec![0; pts.len()];
            for (k, &i) in perm.iter().enumerate() {
                b[i] = b_perm[k];
            }
            let core = core_flags(&pts, eps, min_pts);
            prop_assert_eq!(canonical(&a, &core), canonical(&b, &core));
            // Noise sets agree exactly.
            for i in 0..pts.len() {
                prop_assert_eq!(a[i] == NOISE, b[i] == NOISE);
            }
            // Each border point sits within eps of a core point of its cluster in both labellings.
            for i in (0..pts.len()).filter(|&i| !core[i] && a[i] != NOISE) {
                for labels in [&a, &b] {
                    let ok = (0..pts.len()).any(|j| core[j] && labels[j] == labels[i] && dist2(&pts[i], &pts[j]) <= eps * eps);
                    prop_assert!(ok);
                }
            }
        }
    }
}
