//! Safe, strided matrix product over the `gemm` crate, and its brute-force twin.
//!
//! Operands are views with arbitrary (non-negative) row and column strides, so a transposed
//! operand is the same buffer with its strides swapped ([`MatRef::t`]): the backward pass computes
//! `Xᵀ·dY` and `dY·Wᵀ` without copying anything.

use super::Scalar;

/// A read-only matrix view: element `(i, j)` is `data[i * row_stride + j * col_stride]`.
#[derive(Debug, Clone, Copy)]
pub struct MatRef<'a, T> {
    data: &'a [T],
    rows: usize,
    cols: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<'a, T> MatRef<'a, T> {
    /// A dense row-major `rows × cols` view of `data[..rows * cols]`.
    ///
    /// # Panics
    /// If `data` holds fewer than `rows * cols` elements.
    pub fn row_major(data: &'a [T], rows: usize, cols: usize) -> Self {
        Self::strided(data, rows, cols, cols, 1)
    }

    /// A view with explicit strides (in elements).
    ///
    /// # Panics
    /// If the largest addressed index is outside `data`, or the index arithmetic overflows.
    pub fn strided(data: &'a [T], rows: usize, cols: usize, row_stride: usize, col_stride: usize) -> Self {
        let needed = extent(rows, cols, row_stride, col_stride);
        assert!(needed <= data.len(), "matrix view needs {needed} elements, buffer has {}", data.len());
        Self { data, rows, cols, row_stride, col_stride }
    }

    /// The transposed view of the same buffer (no copy).
    pub fn t(self) -> Self {
        Self {
            data: self.data,
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
        }
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Number of columns.
    pub fn cols(&self) -> usize {
        self.cols
    }

    fn at(&self, i: usize, j: usize) -> &T {
        &self.data[i * self.row_stride + j * self.col_stride]
    }
}

/// A mutable row-major destination: element `(i, j)` is `data[i * row_stride + j]`.
#[derive(Debug)]
pub struct MatMut<'a, T> {
    data: &'a mut [T],
    rows: usize,
    cols: usize,
    row_stride: usize,
}

impl<'a, T> MatMut<'a, T> {
    /// A dense row-major `rows × cols` destination in `data[..rows * cols]`.
    ///
    /// # Panics
    /// If `data` holds fewer than `rows * cols` elements.
    pub fn row_major(data: &'a mut [T], rows: usize, cols: usize) -> Self {
        let needed = extent(rows, cols, cols, 1);
        assert!(needed <= data.len(), "matrix view needs {needed} elements, buffer has {}", data.len());
        Self { data, rows, cols, row_stride: cols }
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Number of columns.
    pub fn cols(&self) -> usize {
        self.cols
    }
}

/// One past the largest index a view touches (0 for an empty view).
fn extent(rows: usize, cols: usize, row_stride: usize, col_stride: usize) -> usize {
    if rows == 0 || cols == 0 {
        return 0;
    }
    (rows - 1)
        .checked_mul(row_stride)
        .and_then(|r| (cols - 1).checked_mul(col_stride).and_then(|c| r.checked_add(c)))
        .and_then(|e| e.checked_add(1))
        .filter(|&e| e <= isize::MAX as usize)
        .expect("matrix view extent overflows")
}

/// How many threads a product may use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Threads {
    /// The calling thread only.
    Single,
    /// Every thread of the current rayon pool (the global one unless called inside `install`).
    /// `gemm` itself falls back to one thread for products too small to split.
    Pool,
}

impl Threads {
    fn parallelism(self) -> gemm::Parallelism {
        match self {
            Threads::Single => gemm::Parallelism::None,
            Threads::Pool => match rayon::current_num_threads() {
                0 | 1 => gemm::Parallelism::None,
                n => gemm::Parallelism::Rayon(n),
            },
        }
    }
}

/// `dst = a·b` (or `dst += a·b` when `accumulate`), with `a` m × k, `b` k × n, `dst` m × n.
///
/// Cost: 2·m·n·k flops. `a` and `b` may be transposed views; `dst` must not alias them
/// (guaranteed by the borrow checker).
///
/// # Panics
/// If the shapes do not agree.
pub fn matmul<T: Scalar>(dst: MatMut<'_, T>, a: MatRef<'_, T>, b: MatRef<'_, T>, accumulate: bool, threads: Threads) {
    let (m, n, k) = (dst.rows, dst.cols, a.cols);
    assert!(
        a.rows == m && b.rows == k && b.cols == n,
        "matmul shape mismatch: ({m}×{n}) = ({}×{}) · ({}×{})",
        a.rows,
        a.cols,
        b.rows,
        b.cols
    );
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        // An empty sum: gemm's behaviour for k = 0 is not documented, so do it here.
        if !accumulate {
            for row in dst.data.chunks_mut(dst.row_stride).take(m) {
                row[..n].fill(T::zero());
            }
        }
        return;
    }
    // SAFETY: the views were bounds-checked at construction (largest index < len, extent fits in
    // isize), strides are non-negative, `dst` is a unique borrow so it aliases neither operand, and
    // `T` is f32 or f64 (sealed `Scalar`), which `gemm` dispatches on.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.data.as_mut_ptr(),
            1,
            dst.row_stride as isize,
            accumulate,
            a.data.as_ptr(),
            a.col_stride as isize,
            a.row_stride as isize,
            b.data.as_ptr(),
            b.col_stride as isize,
            b.row_stride as isize,
            T::one(),
            T::one(),
            false,
            false,
            false,
            threads.parallelism(),
        );
    }
}

/// Brute-force twin of [`matmul`]: the textbook triple loop, accumulated in f64.
///
/// # Panics
/// If the shapes do not agree.
pub fn matmul_naive<T: Scalar>(dst: MatMut<'_, T>, a: MatRef<'_, T>, b: MatRef<'_, T>, accumulate: bool) {
    let (m, n, k) = (dst.rows, dst.cols, a.cols);
    assert!(a.rows == m && b.rows == k && b.cols == n, "matmul shape mismatch");
    for i in 0..m {
        for j in 0..n {
            let mut sum = 0.0_f64;
            for p in 0..k {
                sum += a.at(i, p).to_f64().unwrap_or(f64::NAN) * b.at(p, j).to_f64().unwrap_or(f64::NAN);
            }
            let d = &mut dst.data[i * dst.row_stride + j];
            let prev = if accumulate { d.to_f64().unwrap_or(f64::NAN) } else { 0.0 };
            *d = T::from(prev + sum).unwrap_or_else(T::nan);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(len: usize, rng: &mut ChaCha8Rng) -> Vec<f64> {
        (0..len).map(|_| rng.random_range(-1.0..1.0)).collect()
    }

    /// Runs `matmul` and `matmul_naive` on every transpose combination and compares.
    fn check(m: usize, n: usize, k: usize, accumulate: bool, threads: Threads, seed: u64) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a_buf = random(m * k, &mut rng);
        let b_buf = random(k * n, &mut rng);
        let init = random(m * n, &mut rng);
        for (ta, tb) in [(false, false), (true, false), (false, true), (true, true)] {
            // A transposed operand is stored as its transpose (k × m) and viewed through `t()`.
            let a = if ta { MatRef::row_major(&a_buf, k, m).t() } else { MatRef::row_major(&a_buf, m, k) };
            let b = if tb { MatRef::row_major(&b_buf, n, k).t() } else { MatRef::row_major(&b_buf, k, n) };
            let mut fast = init.clone();
            let mut slow = init.clone();
            matmul(MatMut::row_major(&mut fast, m, n), a, b, accumulate, threads);
            matmul_naive(MatMut::row_major(&mut slow, m, n), a, b, accumulate);
            // Entries are sums of k products of numbers in [-1, 1]: the two summation orders
            // differ by at most ~k·eps_f64 per entry, far below 1e-12 for k ≤ a few hundred.
            for (x, y) in fast.iter().zip(&slow) {
                assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()), "m{m} n{n} k{k} ta{ta} tb{tb}: {x} vs {y}");
            }
        }
    }

    #[test]
    fn matmul_matches_the_triple_loop_on_odd_shapes_and_transposes() {
        let shapes = [(1, 1, 1), (3, 5, 7), (17, 9, 13), (33, 1, 65), (1, 31, 2), (129, 72, 128), (200, 3, 9)];
        for (s, &(m, n, k)) in shapes.iter().enumerate() {
            for accumulate in [false, true] {
                check(m, n, k, accumulate, Threads::Single, s as u64);
                check(m, n, k, accumulate, Threads::Pool, 100 + s as u64);
            }
        }
    }

    #[test]
    fn matmul_with_many_rows_matches_on_the_thread_pool() {
        // Large enough for gemm to actually split the work across threads.
        check(1500, 128, 128, true, Threads::Pool, 9);
        check(128, 128, 1500, false, Threads::Pool, 10);
    }

    #[test]
    fn matmul_in_f32_agrees_with_f64_reference() {
        let (m, n, k) = (37, 19, 23);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let a: Vec<f32> = (0..m * k).map(|_| rng.random_range(-1.0..1.0)).collect();
        let b: Vec<f32> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut fast = vec![0.0_f32; m * n];
        let mut slow = vec![0.0_f32; m * n];
        let (av, bv) = (MatRef::row_major(&a, k, m).t(), MatRef::row_major(&b, k, n));
        matmul(MatMut::row_major(&mut fast, m, n), av, bv, false, Threads::Single);
        matmul_naive(MatMut::row_major(&mut slow, m, n), av, bv, false);
        // f32 sums of 23 products in [-1, 1]: rounding error ≤ k·2^-24·Σ|a||b| ≤ 23·6e-8·23 ≈ 3e-5.
        for (x, y) in fast.iter().zip(&slow) {
            assert!((x - y).abs() <= 3e-5, "{x} vs {y}");
        }
    }

    #[test]
    fn empty_inner_dimension_gives_zeros_or_keeps_dst() {
        let a: [f64; 0] = [];
        let mut dst = vec![5.0_f64; 6];
        matmul(
            MatMut::row_major(&mut dst, 2, 3),
            MatRef::row_major(&a, 2, 0),
            MatRef::row_major(&a, 0, 3),
            true,
            Threads::Single,
        );
        assert_eq!(dst, vec![5.0; 6]);
        matmul(
            MatMut::row_major(&mut dst, 2, 3),
            MatRef::row_major(&a, 2, 0),
            MatRef::row_major(&a, 0, 3),
            false,
            Threads::Single,
        );
        assert_eq!(dst, vec![0.0; 6]);
    }

    #[test]
    #[should_panic(expected = "shape mismatch")]
    fn mismatched_shapes_are_refused() {
        let a = [0.0_f64; 6];
        let mut dst = [0.0_f64; 4];
        matmul(
            MatMut::row_major(&mut dst, 2, 2),
            MatRef::row_major(&a, 2, 3),
            MatRef::row_major(&a, 2, 3),
            false,
            Threads::Single,
        );
    }

    #[test]
    #[should_panic(expected = "matrix view needs")]
    fn views_past_the_buffer_are_refused() {
        let a = [0.0_f64; 5];
        let _ = MatRef::row_major(&a, 2, 3);
    }
}
