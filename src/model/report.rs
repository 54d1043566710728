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
