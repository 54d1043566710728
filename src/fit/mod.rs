//! Fitting a motion model to a sequence: the NTP/MBNT trajectory loop and the NSFP/MBNSF
//! pair-wise loop, their parameters, progress reporting and cancellation.
//!
//! The service and the CLI drive this through [`fit_sequence`], a plain blocking call that
//! reports progress through a callback which may also cancel between iterations.

mod params;

pub use params::{FitParams, FitParamsError, Method, ValidFitParams};

use std::ops::ControlFlow;

use crate::geometry::Point;
use crate::trajectory::{FittedModel, TimeAxis};

/// A sequence to fit: T frames of points, each in its own sensor frame, and its time axis.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Frame k's points (metric, sensor frame of sweep k). Every point is finite.
    pub frames: Vec<Vec<Point>>,
    /// Timestamps (s, strictly increasing), one per frame; `None` means frame indices.
    pub timestamps_s: Option<Vec<f64>>,
    /// Sensor-to-world poses, row-major 4 x 4, one per frame, when known.
    pub poses: Option<Vec<[f64; 16]>>,
}

impl Sequence {
    /// The time axis answers are expressed in (timestamps, or frame indices 0..T-1).
    pub fn time_axis(&self) -> TimeAxis {
        TimeAxis::new(self.timestamps_s.clone(), self.frames.len())
    }
}

/// Loss terms of one iteration (means over the reference frames used).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LossTerms {
    /// Truncated Chamfer terms (m^2).
    pub chamfer: f64,
    /// Cycle-consistency term (m^2).
    pub cycle: f64,
    /// Multi-body rigidity term (-ln score, dimensionless).
    pub rigidity: f64,
    /// Weighted total that the optimiser minimises.
    pub total: f64,
}

/// What the fitting loop reports after each iteration.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Progress {
    /// Iterations completed so far (1-based once the first is done).
    pub iteration: usize,
    /// Total iterations planned (an upper bound when early stopping may end sooner).
    pub iterations: usize,
    /// The loss terms of the iteration just done.
    pub loss: LossTerms,
    /// Best validation loss so far, if a validation pass has run.
    pub best_validation_loss: Option<f64>,
}

/// Why a fit did not produce a model.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// The sequence cannot be fitted (too few frames, an empty frame, ...).
    #[error("invalid sequence: {0}")]
    InvalidSequence(String),
    /// The loss became non-finite.
    #[error("fit diverged at iteration {iteration} (loss {loss})")]
    Diverged {
        /// Iteration at which the loss stopped being finite.
        iteration: usize,
        /// The offending loss value.
        loss: f64,
    },
    /// The progress callback asked to stop.
    #[error("cancelled at iteration {iteration}")]
    Cancelled {
        /// Iterations completed before the stop.
        iteration: usize,
    },
}

/// Fits `method` to `sequence` with `params`, calling `on_progress` after every iteration.
///
/// Blocking and CPU-heavy (runs on the calling thread and the rayon pool): call it from a
/// worker thread, never from an async executor. Returning `ControlFlow::Break` from the
/// callback cancels the fit between iterations.
pub fn fit_sequence(
    sequence: &Sequence,
    method: Method,
    params: &ValidFitParams,
    on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
) -> Result<FittedModel, FitError> {
    validate_sequence(sequence)?;
    // TEMPORARY until the fitting loops land (issue 2): a zero-motion model, so that the
    // service can be built against this signature. Replaced before the issue is closed.
    let _ = (method, params);
    let iterations = 3;
    for iteration in 1..=iterations {
        let progress = Progress { iteration, iterations, loss: LossTerms::default(), best_validation_loss: None };
        if on_progress(&progress).is_break() {
            return Err(FitError::Cancelled { iteration });
        }
    }
    Ok(FittedModel::zero_motion(sequence.time_axis()))
}

/// Checks what every method needs: at least two frames, none empty, all points finite.
pub fn validate_sequence(sequence: &Sequence) -> Result<(), FitError> {
    let frames = sequence.frames.len();
    if frames < 2 {
        return Err(FitError::InvalidSequence(format!("needs at least 2 frames, got {frames}")));
    }
    if let Some(k) = sequence.frames.iter().position(|f| f.is_empty()) {
        return Err(FitError::InvalidSequence(format!("frame {k} has no points")));
    }
    if let Some(k) = sequence.frames.iter().position(|f| f.iter().flatten().any(|c| !c.is_finite())) {
        return Err(FitError::InvalidSequence(format!("frame {k} has a non-finite coordinate")));
    }
    if let Some(ts) = &sequence.timestamps_s {
        if ts.len() != frames {
            return Err(FitError::InvalidSequence(format!("{} timestamps for {frames} frames", ts.len())));
        }
        if ts.windows(2).any(|w| w[1] <= w[0]) || ts.iter().any(|t| !t.is_finite()) {
            return Err(FitError::InvalidSequence("timestamps must be finite and strictly increasing".into()));
        }
    }
    Ok(())
}
