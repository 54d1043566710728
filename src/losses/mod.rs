//! The loss functions of method.md section 2, each returning its value and adding its gradient
//! with respect to the moved points (or network outputs) into a caller-owned buffer.
//!
//! - [`chamfer`]: truncated Chamfer distance between a moved cloud and a fixed target frame.
//! - [`cycle`]: mean squared difference of two velocity outputs (cycle consistency).
//! - [`multibody`]: the multi-body (spatial-consistency) score of one cluster, `-ln(s)`.
//!
//! Conventions shared by all three: the returned value is unweighted; the gradient buffer gets
//! `weight * d(value)/d(input)` *added* (never overwritten) so several terms can accumulate into
//! one buffer; production numerics are f32, and each gradient has a generic twin tested against
//! finite differences in f64. Synchronous, allocation-free in the hot loops (scratch is reused).

pub mod chamfer;
pub mod cycle;
pub mod multibody;

pub use chamfer::{ChamferScratch, ReverseSearch, truncated_chamfer, truncated_chamfer_brute};
pub use cycle::mean_squared_difference;
pub use multibody::{
    DEFAULT_POWER_TOLERANCE, MultibodyScratch, MultibodyValue, multibody_loss, multibody_loss_generic,
    subsample_indices,
};
