//! Cycle consistency: the mean squared difference of two equally shaped arrays (e.g. the
//! N x (T-1) x 3 velocity outputs of the trajectory network at a point and at its moved copy).

use num_traits::Float;
use rayon::prelude::*;

/// Entries per rayon task: large enough that task overhead is negligible, small enough that
/// 3.6M entries (50k points x 24 steps x 3) still split over both cores.
const CHUNK: usize = 16 * 1024;

/// Mean over all entries of `(a - b)^2` (unweighted, in the squared unit of the inputs).
///
/// Adds `weight * d/da` into `grad_a` and `weight * d/db` into `grad_b`, i.e.
/// `+-weight * 2 (a - b) / len`. Empty inputs give 0 and leave the gradients untouched.
/// Cost O(len), parallel over chunks; the sum is accumulated in f64.
///
/// # Panics
/// If the four slices do not all have the same length (a caller bug, not bad data).
pub fn mean_squared_difference(a: &[f32], b: &[f32], weight: f32, grad_a: &mut [f32], grad_b: &mut [f32]) -> f32 {
    mean_squared_difference_generic(a, b, weight, grad_a, grad_b) as f32
}

/// [`mean_squared_difference`] for any float type (f64 for finite-difference tests). Returns
/// the value in f64 whatever `F` is.
///
/// # Panics
/// If the four slices do not all have the same length.
pub fn mean_squared_difference_generic<F: Float + Send + Sync>(
    a: &[F],
    b: &[F],
    weight: F,
    grad_a: &mut [F],
    grad_b: &mut [F],
) -> f64 {
    let n = a.len();
    assert!(b.len() == n && grad_a.len() == n && grad_b.len() == n, "mean_squared_difference: length mismatch");
    if n == 0 {
        return 0.0;
    }
    // d/da of mean (a - b)^2 is 2 (a - b) / n; d/db its negative.
    let scale = weight * F::from(2.0 / n as f64).expect("finite scale");
    let sum: f64 = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .zip(grad_a.par_chunks_mut(CHUNK))
        .zip(grad_b.par_chunks_mut(CHUNK))
        .map(|(((a, b), ga), gb)| {
            // The per-chunk sum stays in F so the loop vectorises; chunks add up in f64.
            let mut acc = F::zero();
            for (((&ai, &bi), ga), gb) in a.iter().zip(b).zip(ga.iter_mut()).zip(gb.iter_mut()) {
                let d = ai - bi;
                acc = acc + d * d;
                let g = scale * d;
                *ga = *ga + g;
                *gb = *gb - g;
            }
            acc.to_f64().unwrap_or(f64::NAN)
        })
        .sum();
    sum / n as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_vec(n: usize, rng: &mut ChaCha8Rng) -> Vec<f64> {
        (0..n).map(|_| rng.random_range(-2.0..2.0)).collect()
    }

    #[test]
    fn mean_squared_difference_matches_its_definition() {
        let a = [1.0f32, 2.0, 3.0, -1.0];
        let b = [1.0f32, 0.0, 4.0, 1.0];
        let mut ga = [10.0f32; 4];
        let mut gb = [0.0f32; 4];
        let v = mean_squared_difference(&a, &b, 0.5, &mut ga, &mut gb);
        // (0 + 4 + 1 + 4) / 4
        assert_eq!(v, 2.25);
        // Added to the existing 10: 0.5 * 2 (a - b) / 4.
        assert_eq!(ga, [10.0, 10.5, 9.75, 9.5]);
        assert_eq!(gb, [0.0, -0.5, 0.25, 0.5]);
    }

    #[test]
    fn mean_squared_difference_gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        // Longer than one chunk so the parallel split is exercised.
        let n = CHUNK + 123;
        let a = random_vec(n, &mut rng);
        let b = random_vec(n, &mut rng);
        let (weight, h) = (1.7, 1e-4);
        let mut ga = vec![0.0; n];
        let mut gb = vec![0.0; n];
        mean_squared_difference_generic(&a, &b, weight, &mut ga, &mut gb);
        let value = |a: &[f64], b: &[f64]| {
            let (mut x, mut y) = (vec![0.0; n], vec![0.0; n]);
            weight * mean_squared_difference_generic(a, b, 0.0, &mut x, &mut y)
        };
        for k in [0, 5, CHUNK - 1, CHUNK, n - 1] {
            for (which, g) in [(0, ga[k]), (1, gb[k])] {
                let (mut ap, mut bp) = (a.clone(), b.clone());
                let (mut am, mut bm) = (a.clone(), b.clone());
                if which == 0 {
                    ap[k] += h;
                    am[k] -= h;
                } else {
                    bp[k] += h;
                    bm[k] -= h;
                }
                let fd = (value(&ap, &bp) - value(&am, &bm)) / (2.0 * h);
                // The value is quadratic, so central differences are exact up to rounding: the
                // mean (~2.7) carries ~1e-15 absolute error, / 2h gives ~1e-11. Gradients are
                // ~2e-4 here, so 1e-9 absolute is a 5e-6 relative check far above rounding.
                assert!((fd - g).abs() < 1e-9, "entry {k} ({which}): fd {fd} vs analytic {g}");
            }
        }
    }

    #[test]
    fn mean_squared_difference_of_empty_inputs_is_zero() {
        assert_eq!(mean_squared_difference(&[], &[], 1.0, &mut [], &mut []), 0.0);
    }
}
