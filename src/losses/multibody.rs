//! The multi-body (spatial-consistency) loss of one cluster (method.md section 2), value and
//! gradient with respect to the moved cluster.
//!
//! For a cluster C of n points and its moved copy C' (same order):
//! `A_ij = max(0, 1 - (|c_i - c_j| - |c'_i - c'_j|)^2 / d_thr^2)`, `A_ii = 1`; `v` is the leading
//! eigenvector of A by power iteration from the ones vector; score `s = v^T A v / n` and
//! loss `-ln(s)`. The gradient treats `v` as fixed (`d(v^T A v)/dA_ij = v_i v_j`, exact for the
//! leading eigenvalue of a symmetric matrix) and flows through A into C' only.
//!
//! A is symmetric with a unit diagonal, so only its strict upper triangle is stored, packed row
//! by row (n = 3000: 4.5M entries, 18 MB in f32, half the memory traffic of the full matrix).
//! Rows are split into chunks of equal pair count that rayon runs in parallel; the symmetric
//! half of each product is scattered into a per-chunk buffer and the buffers summed afterwards.

use num_traits::Float;
use rayon::prelude::*;

use crate::geometry::Point;

/// Default stopping tolerance of the power iteration: it stops once no entry of the unit
/// eigenvector estimate moves by more than this times its largest entry (the relative test of
/// the research code's `allclose`).
pub const DEFAULT_POWER_TOLERANCE: f32 = 1e-5;

/// Width of the manual accumulators: eight f32 lanes fill one AVX2 register, so reductions
/// written over `[F; LANES]` vectorise without reassociating a scalar sum.
const LANES: usize = 8;

/// Reusable buffers for [`multibody_loss`]: the packed adjacency triangle (n(n-1)/2 entries),
/// both clouds as structure-of-arrays, the power-iteration vectors and per-chunk partial sums.
/// Keep one per fitting thread; it grows to the largest cluster seen and is then reused.
#[derive(Default)]
pub struct MultibodyScratch<F = f32> {
    /// Original cluster, x / y / z columns.
    p: [Vec<F>; 3],
    /// Moved cluster, x / y / z columns.
    m: [Vec<F>; 3],
    /// Strict upper triangle of A, row i holding columns i+1..n.
    a: Vec<F>,
    /// Current eigenvector estimate and its product with A.
    v: Vec<F>,
    w: Vec<F>,
    /// Per-chunk partial sums: n per chunk for products, 3n for gradients.
    partial: Vec<F>,
    /// Row boundaries of the chunks (first row of each, then n).
    bounds: Vec<usize>,
}

impl<F: Float + Default> MultibodyScratch<F> {
    /// Empty scratch; buffers grow on first use.
    pub fn new() -> Self {
        Self::default()
    }
}

/// Value of the multi-body loss of one cluster.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MultibodyValue {
    /// `-ln(score)`, dimensionless, >= 0 (0 for a rigid motion).
    pub loss: f64,
    /// `v^T A v / n` in (0, 1]: 1 when every pairwise distance is preserved.
    pub score: f64,
    /// Power-iteration steps taken (at most the requested maximum).
    pub power_steps: usize,
}

/// Multi-body loss of cluster `points` moved to `moved` (same order), f32 production path.
///
/// `d_thr_m` is the distance-difference threshold (m) beyond which a pair scores 0;
/// `max_power_iterations` bounds the power iteration (10 in method.md), which stops earlier
/// once converged to [`DEFAULT_POWER_TOLERANCE`]. Adds `weight * dloss/dmoved` into
/// `grad_moved`; `points` is data and gets no gradient. Returns `None` (and touches nothing)
/// for n <= 2, where the loss is skipped.
///
/// Cost: O(n^2) time per power step plus two O(n^2) passes with square roots (building A, the
/// gradient; the latter skipped when `weight == 0`), O(n^2 / 2) scratch memory.
///
/// # Panics
/// If the three slices differ in length, or `d_thr_m` is not positive and finite (caller bugs:
/// thresholds come from validated parameters).
pub fn multibody_loss(
    points: &[Point],
    moved: &[Point],
    d_thr_m: f32,
    max_power_iterations: usize,
    weight: f32,
    grad_moved: &mut [Point],
    scratch: &mut MultibodyScratch,
) -> Option<MultibodyValue> {
    multibody_loss_generic(
        points,
        moved,
        d_thr_m,
        max_power_iterations,
        DEFAULT_POWER_TOLERANCE,
        weight,
        grad_moved,
        scratch,
    )
}

/// [`multibody_loss`] for any float type, with an explicit power-iteration `tolerance` (f64 with
/// many steps and a tiny tolerance gives the converged eigenvector for finite-difference tests).
///
/// # Panics
/// As [`multibody_loss`].
#[allow(clippy::too_many_arguments)] // mirrors multibody_loss plus the tolerance
pub fn multibody_loss_generic<F: Float + Send + Sync>(
    points: &[[F; 3]],
    moved: &[[F; 3]],
    d_thr_m: F,
    max_power_iterations: usize,
    tolerance: F,
    weight: F,
    grad_moved: &mut [[F; 3]],
    scratch: &mut MultibodyScratch<F>,
) -> Option<MultibodyValue> {
    let n = points.len();
    assert!(moved.len() == n && grad_moved.len() == n, "multibody_loss: length mismatch");
    assert!(d_thr_m > F::zero() && d_thr_m.is_finite(), "multibody_loss: d_thr_m must be positive and finite");
    if n <= 2 {
        return None;
    }
    let inv_thr2 = (d_thr_m * d_thr_m).recip();
    scratch.prepare(points, moved);
    scratch.build_adjacency(inv_thr2);

    // Power iteration from the unit ones vector (same direction as method.md's v_0 = 1, so the
    // score is a Rayleigh quotient even with zero steps). A is non-negative with a unit
    // diagonal, so A v >= v > 0 entry-wise: the norm never vanishes for finite input.
    let v0 = F::from(1.0 / (n as f64).sqrt()).expect("finite");
    scratch.v.clear();
    scratch.v.resize(n, v0);
    scratch.w.resize(n, F::zero());
    scratch.product();
    let mut steps = 0;
    while steps < max_power_iterations {
        let norm = scratch.w.iter().map(|&x| to_f64(x) * to_f64(x)).sum::<f64>().sqrt();
        let inv_norm = F::from(1.0 / norm).unwrap_or(F::nan());
        let (mut change, mut largest) = (F::zero(), F::zero());
        for (v, &w) in scratch.v.iter_mut().zip(&scratch.w) {
            let next = w * inv_norm;
            change = change.max((next - *v).abs());
            largest = largest.max(next.abs());
            *v = next;
        }
        steps += 1;
        scratch.product();
        if change <= tolerance * largest {
            break;
        }
    }
    let quadratic = scratch.v.iter().zip(&scratch.w).map(|(&v, &w)| to_f64(v) * to_f64(w)).sum::<f64>();
    let score = quadratic / n as f64;

    if weight != F::zero() {
        // dloss/dq = -1/q; each unordered pair appears twice in v^T A v; dA/dd' = 2 r / thr^2.
        let coef = -F::from(4.0 / quadratic).unwrap_or(F::nan()) * weight * inv_thr2;
        scratch.gradient(inv_thr2, coef, grad_moved);
    }
    Some(MultibodyValue { loss: -score.ln(), score, power_steps: steps })
}

#[inline]
fn to_f64<F: Float>(x: F) -> f64 {
    x.to_f64().unwrap_or(f64::NAN)
}

/// Offset of row i in the packed strict upper triangle of an n x n matrix.
#[inline]
fn row_offset(i: usize, n: usize) -> usize {
    i * (2 * n - i - 1) / 2
}

impl<F: Float + Send + Sync> MultibodyScratch<F> {
    /// Copies both clouds into columns and sizes the buffers and chunk boundaries for n points.
    fn prepare(&mut self, points: &[[F; 3]], moved: &[[F; 3]]) {
        let n = points.len();
        for k in 0..3 {
            self.p[k].clear();
            self.p[k].extend(points.iter().map(|p| p[k]));
            self.m[k].clear();
            self.m[k].extend(moved.iter().map(|p| p[k]));
        }
        self.a.resize(n * (n - 1) / 2, F::zero());
        // A few chunks per thread so uneven progress still balances; each covers about the
        // same number of pairs (early rows are long, late rows short).
        let chunks = (4 * rayon::current_num_threads()).clamp(1, n);
        let total = n * (n - 1) / 2;
        self.bounds.clear();
        self.bounds.push(0);
        let mut done = 0;
        for i in 0..n {
            done += n - 1 - i;
            let cut = self.bounds.len() * total / chunks;
            if done >= cut && self.bounds.len() < chunks && i + 1 < n {
                self.bounds.push(i + 1);
            }
        }
        self.bounds.push(n);
        self.partial.resize(3 * n * (self.bounds.len() - 1), F::zero());
    }

    /// Fills the packed triangle with A_ij, both clouds' distances computed in one pass.
    fn build_adjacency(&mut self, inv_thr2: F) {
        let n = self.p[0].len();
        let (p, m) = (&self.p, &self.m);
        let mut rest = self.a.as_mut_slice();
        let mut jobs = Vec::with_capacity(self.bounds.len());
        for w in self.bounds.windows(2) {
            let (chunk, tail) = rest.split_at_mut(row_offset(w[1], n) - row_offset(w[0], n));
            jobs.push((w[0], w[1], chunk));
            rest = tail;
        }
        jobs.into_par_iter().for_each(|(first, last, chunk)| {
            let base = row_offset(first, n);
            for i in first..last {
                let row = &mut chunk[row_offset(i, n) - base..row_offset(i + 1, n) - base];
                let (pi, mi) = ([p[0][i], p[1][i], p[2][i]], [m[0][i], m[1][i], m[2][i]]);
                let (px, py, pz) = (&p[0][i + 1..], &p[1][i + 1..], &p[2][i + 1..]);
                let (mx, my, mz) = (&m[0][i + 1..], &m[1][i + 1..], &m[2][i + 1..]);
                for (j, a) in row.iter_mut().enumerate() {
                    let d = norm3(pi[0] - px[j], pi[1] - py[j], pi[2] - pz[j]);
                    let dm = norm3(mi[0] - mx[j], mi[1] - my[j], mi[2] - mz[j]);
                    let r = d - dm;
                    *a = (F::one() - r * r * inv_thr2).max(F::zero());
                }
            }
        });
    }

    /// `w = A v` with A's unit diagonal and the packed triangle used twice (row and column).
    fn product(&mut self) {
        let n = self.v.len();
        let (a, v) = (&self.a, &self.v);
        let partial = &mut self.partial[..n * (self.bounds.len() - 1)];
        partial.par_chunks_mut(n).zip(self.bounds.par_windows(2)).for_each(|(y, rows)| {
            y.fill(F::zero());
            for i in rows[0]..rows[1] {
                let row = &a[row_offset(i, n)..row_offset(i + 1, n)];
                let (y_head, y_tail) = y.split_at_mut(i + 1);
                y_head[i] = y_head[i] + row_times(row, &v[i + 1..], y_tail, v[i]);
            }
        });
        self.w.copy_from_slice(v);
        for y in self.partial[..n * (self.bounds.len() - 1)].chunks_exact(n) {
            for (w, &y) in self.w.iter_mut().zip(y) {
                *w = *w + y;
            }
        }
    }

    /// Adds `coef * v_i v_j * r_ij / d'_ij * (c'_i - c'_j)` to row i of `grad` and subtracts it
    /// from row j, for every pair with `A_ij > 0` and `d'_ij > 0` (`r = d - d'`).
    fn gradient(&mut self, inv_thr2: F, coef: F, grad: &mut [[F; 3]]) {
        let n = self.v.len();
        let (p, m, v) = (&self.p, &self.m, &self.v);
        let partial = &mut self.partial[..3 * n * (self.bounds.len() - 1)];
        partial.par_chunks_mut(3 * n).zip(self.bounds.par_windows(2)).for_each(|(g, rows)| {
            g.fill(F::zero());
            let (gx, rest) = g.split_at_mut(n);
            let (gy, gz) = rest.split_at_mut(n);
            for i in rows[0]..rows[1] {
                let pair = Pair {
                    pi: [p[0][i], p[1][i], p[2][i]],
                    mi: [m[0][i], m[1][i], m[2][i]],
                    ci: coef * v[i],
                    inv_thr2,
                };
                let tails = RowTails {
                    p: [&p[0][i + 1..], &p[1][i + 1..], &p[2][i + 1..]],
                    m: [&m[0][i + 1..], &m[1][i + 1..], &m[2][i + 1..]],
                    v: &v[i + 1..],
                };
                let (gx_head, gx_tail) = gx.split_at_mut(i + 1);
                let (gy_head, gy_tail) = gy.split_at_mut(i + 1);
                let (gz_head, gz_tail) = gz.split_at_mut(i + 1);
                let gi = pair.row(&tails, [gx_tail, gy_tail, gz_tail]);
                gx_head[i] = gx_head[i] + gi[0];
                gy_head[i] = gy_head[i] + gi[1];
                gz_head[i] = gz_head[i] + gi[2];
            }
        });
        for g in self.partial[..3 * n * (self.bounds.len() - 1)].chunks_exact(3 * n) {
            for (j, out) in grad.iter_mut().enumerate() {
                for k in 0..3 {
                    out[k] = out[k] + g[k * n + j];
                }
            }
        }
    }
}

#[inline(always)]
fn norm3<F: Float>(x: F, y: F, z: F) -> F {
    (x * x + y * y + z * z).sqrt()
}

/// `sum_k row[k] v[k]`, and `y[k] += vi row[k]` on the way (the transposed half of A v).
#[inline(always)]
fn row_times<F: Float>(row: &[F], v: &[F], y: &mut [F], vi: F) -> F {
    let len = row.len();
    let (v, y) = (&v[..len], &mut y[..len]);
    let full = len / LANES * LANES;
    let mut acc = [F::zero(); LANES];
    for b in (0..full).step_by(LANES) {
        let r: &[F; LANES] = row[b..b + LANES].try_into().expect("block");
        let vb: &[F; LANES] = v[b..b + LANES].try_into().expect("block");
        let yb: &mut [F; LANES] = (&mut y[b..b + LANES]).try_into().expect("block");
        for l in 0..LANES {
            acc[l] = acc[l] + r[l] * vb[l];
            yb[l] = yb[l] + vi * r[l];
        }
    }
    let mut dot = acc.iter().fold(F::zero(), |s, &x| s + x);
    for k in full..len {
        dot = dot + row[k] * v[k];
        y[k] = y[k] + vi * row[k];
    }
    dot
}

/// The fixed side i of a gradient row.
struct Pair<F> {
    pi: [F; 3],
    mi: [F; 3],
    /// `coef * v_i`.
    ci: F,
    inv_thr2: F,
}

/// Columns j > i of both clouds and of v.
struct RowTails<'a, F> {
    p: [&'a [F]; 3],
    m: [&'a [F]; 3],
    v: &'a [F],
}

impl<F: Float> Pair<F> {
    /// The gradient term of pair (i, j) on c'_i as a vector (c'_j gets its negative).
    #[inline(always)]
    fn term(&self, pj: [F; 3], mj: [F; 3], vj: F) -> [F; 3] {
        let d = norm3(self.pi[0] - pj[0], self.pi[1] - pj[1], self.pi[2] - pj[2]);
        let dm_vec = [self.mi[0] - mj[0], self.mi[1] - mj[1], self.mi[2] - mj[2]];
        let dm = norm3(dm_vec[0], dm_vec[1], dm_vec[2]);
        let r = d - dm;
        // Outside the clamp (A_ij = 0) and for coincident moved points the gradient is zero.
        let s = if F::one() - r * r * self.inv_thr2 > F::zero() && dm > F::zero() {
            self.ci * vj * r / dm
        } else {
            F::zero()
        };
        [s * dm_vec[0], s * dm_vec[1], s * dm_vec[2]]
    }

    /// Sums the terms of row i (returned, for c'_i) and subtracts each from c'_j in `g`.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // one index over ten columns reads clearer than a zip
    fn row(&self, t: &RowTails<'_, F>, g: [&mut [F]; 3]) -> [F; 3] {
        let len = t.v.len();
        let [gx, gy, gz] = g;
        let (gx, gy, gz) = (&mut gx[..len], &mut gy[..len], &mut gz[..len]);
        let (px, py, pz) = (&t.p[0][..len], &t.p[1][..len], &t.p[2][..len]);
        let (mx, my, mz) = (&t.m[0][..len], &t.m[1][..len], &t.m[2][..len]);
        let full = len / LANES * LANES;
        let mut acc = [[F::zero(); LANES]; 3];
        for b in (0..full).step_by(LANES) {
            for l in 0..LANES {
                let j = b + l;
                let s = self.term([px[j], py[j], pz[j]], [mx[j], my[j], mz[j]], t.v[j]);
                acc[0][l] = acc[0][l] + s[0];
                acc[1][l] = acc[1][l] + s[1];
                acc[2][l] = acc[2][l] + s[2];
                gx[j] = gx[j] - s[0];
                gy[j] = gy[j] - s[1];
                gz[j] = gz[j] - s[2];
            }
        }
        let mut out = acc.map(|lanes| lanes.iter().fold(F::zero(), |s, &x| s + x));
        for j in full..len {
            let s = self.term([px[j], py[j], pz[j]], [mx[j], my[j], mz[j]], t.v[j]);
            for k in 0..3 {
                out[k] = out[k] + s[k];
            }
            gx[j] = gx[j] - s[0];
            gy[j] = gy[j] - s[1];
            gz[j] = gz[j] - s[2];
        }
        out
    }
}

/// Indices of the cluster points to use: all of `0..n` when `n <= max`, otherwise `max`
/// distinct indices drawn uniformly without replacement, sorted ascending. Writes into `out`
/// (cleared first). Deterministic for a given generator state.
pub fn subsample_indices(n: usize, max: usize, rng: &mut impl rand::Rng, out: &mut Vec<u32>) {
    out.clear();
    if n <= max {
        out.extend((0..n).map(|i| i as u32));
        return;
    }
    let picked = rand::seq::index::sample(rng, n, max);
    out.extend(picked.iter().map(|i| i as u32));
    out.sort_unstable();
}
