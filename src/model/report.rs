//! The fit's report, kept with the model: per-frame preparation, iterations, phase timings.

use serde::{Deserialize, Serialize};

use super::params::ValidFitParams;

/// What the fit did, kept with the model so that users can see it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    /// Per frame: points received, removed as ground or out of range, fitted, clusters.
    pub frames: Vec<FrameReport>,
    /// Optimiser iterations run (summed over pairs for pair-wise methods).
    pub iterations: usize,
    /// Iteration of the selected checkpoint (trajectory methods).
    pub best_iteration: Option<usize>,
    /// Validation loss of the selected checkpoint (trajectory methods).
    pub best_validation_loss: Option<f64>,
    /// Iterations run per pair (pair-wise methods; early stopping may end a pair sooner).
    pub iterations_per_pair: Vec<usize>,
    /// Wall time of the fit (s).
    pub fit_seconds: f64,
    /// Wall time per phase of the trajectory loop (zero for pair-wise methods).
    #[serde(default)]
    pub phase_times: PhaseTimes,
    /// The checked hyper-parameters the fit ran with.
    #[serde(default)]
    pub params: Option<ValidFitParams>,
    /// Moving clusters found and followed by rigid tracks (`rigid_tracks`), summed over frames.
    #[serde(default)]
    pub rigid_tracks: usize,
    /// Wall time of finding and following them, or the moving bodies (s), included in
    /// `fit_seconds`.
    #[serde(default)]
    pub rigid_tracks_seconds: f64,
    /// Moving bodies of the scene model (`moving_bodies`).
    #[serde(default)]
    pub moving_bodies: usize,
    /// Points of the scene model the network answers, summed over frames (the rest of the
    /// points on no body follow the still world).
    #[serde(default)]
    pub free_points: usize,
    /// The sensor-to-world poses (row-major 4 x 4, frame 0 the identity) the LiDAR odometry
    /// estimated, when the fit ran it (`odometry` parameter) instead of using given poses.
    #[serde(default)]
    pub estimated_poses: Option<Vec<[f64; 16]>>,
    /// The loss curve: the loss terms of the optimiser's iterations, in order (pair-wise
    /// methods: pair after pair; a log fitted as windows: window after window), thinned to at
    /// most [`LossCurve::MAX_RECORDS`] per fit. Empty in files written before it existed.
    #[serde(default)]
    pub losses: Vec<LossRecord>,
}

/// Loss terms of one iteration (means over the reference frames used).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
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

impl LossTerms {
    fn is_finite(&self) -> bool {
        [self.chamfer, self.cycle, self.rigidity, self.total].iter().all(|v| v.is_finite())
    }
}

/// One iteration of the loss curve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LossRecord {
    /// The iteration (1-based; pair-wise methods count on across pairs).
    pub iteration: usize,
    /// The window of a log fitted as windows (0-based), whose iterations count from 1 again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<usize>,
    /// The training loss terms of the iteration.
    pub loss: LossTerms,
    /// The validation pass's loss terms, when the iteration was a validation iteration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validation: Option<LossTerms>,
}

/// Records a fit's loss curve within a fixed size: once [`LossCurve::MAX_RECORDS`] are held,
/// every other record is dropped and only every second iteration of those kept before is
/// recorded from then on, so a curve of any length keeps its shape in bounded memory (and in
/// the model file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LossCurve {
    /// Iterations 1, 1 + stride, 1 + 2 stride, ... are kept.
    stride: usize,
    records: Vec<LossRecord>,
}

impl Default for LossCurve {
    fn default() -> Self {
        Self { stride: 1, records: Vec::new() }
    }
}

impl LossCurve {
    /// Most records kept per fit: enough to draw a curve, small beside a model.
    pub const MAX_RECORDS: usize = 2048;

    /// Records iteration `iteration` (1-based) unless the thinning skips it. A record with a
    /// non-finite term is left out: the fit stops on it, and a model file cannot hold it.
    pub fn push(&mut self, iteration: usize, loss: LossTerms, validation: Option<LossTerms>) {
        if iteration == 0 || !(iteration - 1).is_multiple_of(self.stride) || !loss.is_finite() {
            return;
        }
        let validation = validation.filter(LossTerms::is_finite);
        if self.records.last().is_some_and(|r| r.iteration >= iteration) {
            return;
        }
        self.records.push(LossRecord { iteration, window: None, loss, validation });
        if self.records.len() > Self::MAX_RECORDS {
            self.stride *= 2;
            let stride = self.stride;
            self.records.retain(|r| (r.iteration - 1).is_multiple_of(stride));
        }
    }

    /// The records, in iteration order.
    pub fn into_records(self) -> Vec<LossRecord> {
        self.records
    }
}

/// What preparation did to one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameReport {
    /// Points received.
    pub input_points: usize,
    /// Points taken as ground and left out of the fit.
    pub ground_points: usize,
    /// Points beyond the range or height limits, left out of the fit.
    pub out_of_range_points: usize,
    /// Points the fit used.
    pub fitted_points: usize,
    /// DBSCAN clusters found (0 when the method has no rigidity term).
    pub clusters: usize,
    /// Points in clusters (the rest are DBSCAN noise).
    pub clustered_points: usize,
}

impl std::ops::AddAssign for PhaseTimes {
    /// Adds another fit's times, phase by phase (a log's windows).
    fn add_assign(&mut self, other: Self) {
        self.mlp_forward_s += other.mlp_forward_s;
        self.mlp_backward_s += other.mlp_backward_s;
        self.nearest_s += other.nearest_s;
        self.cycle_s += other.cycle_s;
        self.multibody_s += other.multibody_s;
        self.optimiser_s += other.optimiser_s;
        self.mlp_gflop += other.mlp_gflop;
        self.total_s += other.total_s;
    }
}

/// Wall time spent per phase of a fit (s), summed over iterations: what `mbnt bench` prints.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PhaseTimes {
    /// MLP forward passes (input encoding included).
    pub mlp_forward_s: f64,
    /// MLP backward passes.
    pub mlp_backward_s: f64,
    /// Truncated Chamfer: nearest neighbours both ways, value and gradient.
    pub nearest_s: f64,
    /// Cycle consistency outside the MLP: moving points, the loss, chaining gradients.
    pub cycle_s: f64,
    /// Multi-body loss: subsampling, pairwise distances, power iteration, gradient.
    pub multibody_s: f64,
    /// Adam steps.
    pub optimiser_s: f64,
    /// Floating-point operations of the MLP passes (GFLOP), for achieved GFLOP/s.
    pub mlp_gflop: f64,
    /// The whole loop; the rest (total minus the phases) is bookkeeping and checkpoints.
    pub total_s: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn terms(total: f64) -> LossTerms {
        LossTerms { total, ..LossTerms::default() }
    }

    #[test]
    fn a_short_curve_keeps_every_iteration() {
        let mut curve = LossCurve::default();
        for i in 1..=10 {
            curve.push(i, terms(1.0 / i as f64), (i % 5 == 1).then(|| terms(2.0)));
        }
        let records = curve.into_records();
        assert_eq!(records.iter().map(|r| r.iteration).collect::<Vec<_>>(), (1..=10).collect::<Vec<_>>());
        assert_eq!(records[5].validation, Some(terms(2.0)));
        assert_eq!(records[4].validation, None);
    }

    #[test]
    fn a_long_curve_is_thinned_within_the_bound_and_keeps_its_start_and_order() {
        let mut curve = LossCurve::default();
        let n = 10 * LossCurve::MAX_RECORDS + 7;
        for i in 1..=n {
            curve.push(i, terms(i as f64), None);
        }
        let records = curve.into_records();
        assert!(records.len() <= LossCurve::MAX_RECORDS && records.len() > LossCurve::MAX_RECORDS / 2);
        assert_eq!(records[0].iteration, 1);
        let step = records[1].iteration - records[0].iteration;
        assert!(step.is_power_of_two() && step > 1);
        assert!(records.windows(2).all(|w| w[1].iteration - w[0].iteration == step));
        assert!(records.iter().all(|r| r.loss.total == r.iteration as f64));
        assert!(n - records.last().unwrap().iteration < step);
    }

    #[test]
    fn non_finite_and_repeated_iterations_are_left_out() {
        let mut curve = LossCurve::default();
        curve.push(1, terms(1.0), Some(terms(f64::NAN)));
        curve.push(2, terms(f64::INFINITY), None);
        curve.push(1, terms(5.0), None);
        curve.push(0, terms(5.0), None);
        let records = curve.into_records();
        assert_eq!(records.len(), 1);
        assert_eq!(records[0].validation, None);
    }
}
