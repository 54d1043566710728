//! A fitted motion model answers where a point is at any time of its sequence.
//!
//! Times are in the sequence's own axis: its timestamps in seconds when it has them, frame
//! indices 0..T-1 otherwise. Positions at time s are in the sensor frame of the sweep at s.

use serde::{Deserialize, Serialize};

use crate::fit::Method;
use crate::geometry::Point;

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
}

impl TimeAxis {
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

/// The fitted network(s) behind a model.
#[derive(Debug, Clone, Serialize, Deserialize)]
enum Motion {
    /// TEMPORARY until the fitting loops land (issue 2): no motion.
    Zero,
}

/// A fitted motion model of one sequence.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FittedModel {
    method: Method,
    time_axis: TimeAxis,
    motion: Motion,
}

impl FittedModel {
    /// TEMPORARY (issue 2): a model in which nothing moves.
    pub fn zero_motion(time_axis: TimeAxis) -> Self {
        Self { method: Method::Mbnt, time_axis, motion: Motion::Zero }
    }

    /// The method that produced the model.
    pub fn method(&self) -> Method {
        self.method
    }

    /// The sequence's time axis.
    pub fn time_axis(&self) -> &TimeAxis {
        &self.time_axis
    }

    /// Positions of `points`, observed at time `t_obs`, at each of `times`.
    ///
    /// Returns a point-major array: entry `i * times.len() + j` is point i at `times[j]`, in
    /// the sensor frame of time `times[j]`.
    pub fn positions(&self, points: &[Point], t_obs: f64, times: &[f64]) -> Result<Vec<Point>, QueryError> {
        if let Some(index) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
            return Err(QueryError::NonFinitePoint { index });
        }
        self.time_axis.to_frame_index(t_obs)?;
        for &t in times {
            self.time_axis.to_frame_index(t)?;
        }
        match self.motion {
            Motion::Zero => Ok(points.iter().flat_map(|p| std::iter::repeat_n(*p, times.len())).collect()),
        }
    }

    /// Scene flow of every frame's points to the next frame: entry k has one vector (m) per
    /// point of `frames[k]`, for k in 0..T-1.
    pub fn scene_flow(&self, frames: &[Vec<Point>]) -> Vec<Vec<Point>> {
        let t = self.time_axis.frames();
        (0..t.saturating_sub(1))
            .map(|k| {
                let from = self.time_axis.frame_time(k);
                let to = self.time_axis.frame_time(k + 1);
                let moved = self.positions(&frames[k], from, &[to]).expect("frame times are in range");
                frames[k].iter().zip(&moved).map(|(p, q)| [q[0] - p[0], q[1] - p[1], q[2] - p[2]]).collect()
            })
            .collect()
    }

    /// Serialises the model (versioned binary format).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = MODEL_MAGIC.to_vec();
        out.extend(serde_json::to_vec(self).expect("a model always serialises"));
        out
    }

    /// Reads a model written by [`FittedModel::to_bytes`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        let body = bytes.strip_prefix(MODEL_MAGIC).ok_or("not an mbnt model file (bad magic or version)")?;
        serde_json::from_slice(body).map_err(|e| format!("corrupt model file: {e}"))
    }
}

/// File magic and format version of serialised models.
const MODEL_MAGIC: &[u8] = b"MBNTMDL1";

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
