//! The sequence's time axis, and the queries it cannot answer.

use serde::{Deserialize, Serialize};

/// Maps the sequence's time axis to fractional frame indices, piecewise linearly.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TimeAxis {
    /// Timestamps (s) per frame, or `None` when times are frame indices.
    timestamps_s: Option<Vec<f64>>,
    frames: usize,
}

/// A query that cannot be answered.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum QueryError {
    /// A time outside [t_0, t_{T-1}] (or not finite).
    #[error("time {time} is outside the sequence's time range [{first}, {last}]")]
    TimeOutOfRange {
        /// The offending time.
        time: f64,
        /// First time of the sequence.
        first: f64,
        /// Last time of the sequence.
        last: f64,
    },
    /// A query point with a non-finite coordinate.
    #[error("point {index} has a non-finite coordinate")]
    NonFinitePoint {
        /// Index of the point in the query.
        index: usize,
    },
    /// A window of a stitched model file that cannot be read. A stitched model's windows are
    /// decoded when a query first needs them, so a damaged window is found then, not when the
    /// file is loaded.
    #[error("window {window} of the stitched model cannot be read: {detail}")]
    CorruptWindow {
        /// The window's index.
        window: usize,
        /// What is wrong with it.
        detail: String,
    },
}

/// How long (s) a moving body or rigid track is predicted past the frames it was seen in;
/// beyond, its pose is held. A body that left the view is otherwise driven on at constant
/// velocity for the rest of a long log (issue 21: 75 frames, until the numbers overflowed).
/// 3 s is longer than a 25-frame window at 10 Hz (2.4 s), whose results it leaves unchanged.
pub const MAX_EXTRAPOLATION_S: f64 = 3.0;

/// The frame rate taken for a sequence without timestamps (its times are frame indices): the
/// 10 Hz of the datasets' LiDARs, so that the horizon is [`MAX_EXTRAPOLATION_S`] there too.
const FRAME_RATE_WITHOUT_TIMESTAMPS_HZ: f64 = 10.0;

impl TimeAxis {
    /// [`MAX_EXTRAPOLATION_S`] in the units of the axis's times (s, or frame indices).
    pub fn extrapolation_horizon(&self) -> f64 {
        if self.timestamps_s.is_some() {
            MAX_EXTRAPOLATION_S
        } else {
            MAX_EXTRAPOLATION_S * FRAME_RATE_WITHOUT_TIMESTAMPS_HZ
        }
    }

    /// A time axis over `frames` frames, in seconds when `timestamps_s` is given.
    pub fn new(timestamps_s: Option<Vec<f64>>, frames: usize) -> Self {
        Self { timestamps_s, frames }
    }

    /// Number of frames T.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The timestamps, when the axis has them.
    pub fn timestamps_s(&self) -> Option<&[f64]> {
        self.timestamps_s.as_deref()
    }

    /// The time of frame `k` on this axis.
    pub fn frame_time(&self, k: usize) -> f64 {
        match &self.timestamps_s {
            Some(ts) => ts[k],
            None => k as f64,
        }
    }

    /// The fractional frame index of `time` (linear between neighbouring frames).
    pub fn to_frame_index(&self, time: f64) -> Result<f64, QueryError> {
        let first = self.frame_time(0);
        let last = self.frame_time(self.frames - 1);
        if !time.is_finite() || time < first || time > last {
            return Err(QueryError::TimeOutOfRange { time, first, last });
        }
        let Some(ts) = &self.timestamps_s else {
            return Ok(time);
        };
        // The last k with ts[k] <= time, so that ts[k] <= time < ts[k + 1].
        let k = ts.partition_point(|&t| t <= time).saturating_sub(1).min(self.frames - 2);
        Ok(k as f64 + (time - ts[k]) / (ts[k + 1] - ts[k]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timestamps_map_piecewise_linearly_to_frame_indices() {
        let axis = TimeAxis::new(Some(vec![10.0, 10.1, 10.3]), 3);
        assert!((axis.to_frame_index(10.05).unwrap() - 0.5).abs() < 1e-9);
        assert!((axis.to_frame_index(10.2).unwrap() - 1.5).abs() < 1e-9);
        assert_eq!(axis.to_frame_index(10.3).unwrap(), 2.0);
        assert!(axis.to_frame_index(10.31).is_err());
        assert!(axis.to_frame_index(f64::NAN).is_err());
    }
}
