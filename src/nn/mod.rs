//! Dense ReLU networks with hand-written forward and backward passes over a fast GEMM, and Adam.
//!
//! The trajectory network (N × 9 → 128 × 8 → 3(T-1)) and the NSFP flow networks are plain
//! multi-layer perceptrons: Linear, ReLU, ..., Linear. Their cost is almost entirely the
//! N × 128 × 128 matrix products, so every product goes through [`gemm`](::gemm) (strided,
//! no transposed copies) and the element-wise work (bias + ReLU, ReLU mask, bias gradients) is one
//! cache-friendly pass each, split over rayon's pool for large batches.
//!
//! Everything is generic over [`Scalar`] (`f32` in production, `f64` for finite-difference tests).
//!
//! ```
//! use mbnt::nn::{Adam, Gradients, Mlp, Workspace};
//! use rand::SeedableRng;
//!
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
//! let mut mlp = Mlp::<f32>::new(&[3, 16, 16, 2], &mut rng);
//! let mut ws = Workspace::default();
//! let mut grads = Gradients::zeros_like(&mlp);
//! let mut adam = Adam::new(&mlp, 1e-3);
//! let x = [0.1_f32, 0.2, 0.3, -0.1, 0.0, 0.5];
//! let y = mlp.forward(&x, 2, &mut ws).to_vec();
//! grads.fill_zero();
//! mlp.backward(&mut ws, &y, &mut grads, None); // gradient of 0.5 * |y|^2
//! adam.step(&mut mlp, &grads);
//! ```

pub mod adam;
mod format;
pub mod matmul;
mod mlp;

pub use adam::Adam;
pub use format::FormatError;
pub use mlp::{Gradients, Mlp, Workspace};

mod sealed {
    /// Restricts [`super::Scalar`] to the types the GEMM kernels dispatch on.
    pub trait Sealed {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

/// Floating-point element type of a network: `f32` (production) or `f64` (gradient checks).
///
/// Sealed: the GEMM backend only has kernels for these two types.
pub trait Scalar: num_traits::Float + Default + Send + Sync + std::fmt::Debug + 'static + sealed::Sealed {}

impl Scalar for f32 {}
impl Scalar for f64 {}
