//! Fitting hyper-parameters: what users may set (`FitParams`, every field optional with the
//! defaults of method.md), checked once into `ValidFitParams` that the loops trust.

use serde::{Deserialize, Serialize};

/// The fitting method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Neural trajectory prior with the multi-body rigidity loss (the default).
    #[default]
    Mbnt,
    /// Neural trajectory prior (Chamfer + cycle consistency).
    Ntp,
    /// Pair-wise neural scene-flow prior with the multi-body loss, chained by forward Euler.
    Mbnsf,
    /// Pair-wise neural scene-flow prior, chained by forward Euler.
    Nsfp,
}

impl Method {
    /// All methods, in a stable order.
    pub const ALL: [Method; 4] = [Method::Mbnt, Method::Ntp, Method::Mbnsf, Method::Nsfp];

    /// The lower-case name used in the API and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Method::Mbnt => "mbnt",
            Method::Ntp => "ntp",
            Method::Mbnsf => "mbnsf",
            Method::Nsfp => "nsfp",
        }
    }

    /// Whether the method fits one trajectory network for the whole sequence.
    pub fn is_trajectory(self) -> bool {
        matches!(self, Method::Mbnt | Method::Ntp)
    }

    /// Whether the method uses the multi-body rigidity loss.
    pub fn uses_rigidity(self) -> bool {
        matches!(self, Method::Mbnt | Method::Mbnsf)
    }
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Method::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown method {s:?} (expected mbnt, ntp, mbnsf or nsfp)"))
    }
}

/// How faithfully a fit follows method.md.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Exactly method.md: every point of a reference frame every iteration, 3000-point cluster
    /// cap, all iterations run.
    Faithful,
    /// Ours (the service default): a random subset of each reference frame per iteration, a
    /// smaller cluster cap and early stopping on the validation loss; validated against
    /// `Faithful` in docs/benchmarks.md.
    #[default]
    Fast,
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "faithful" => Ok(Mode::Faithful),
            "fast" => Ok(Mode::Fast),
            _ => Err(format!("unknown mode {s:?} (expected fast or faithful)")),
        }
    }
}

impl Mode {
    /// The lower-case name used in the API and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Mode::Faithful => "faithful",
            Mode::Fast => "fast",
        }
    }
}

/// When a fit estimates the sensor poses itself (LiDAR odometry, `crate::odometry`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum OdometryMode {
    /// Estimate the poses when the sequence has none (the default of fast mode).
    #[default]
    Auto,
    /// Estimate the poses even when the sequence has them, and ignore the given ones.
    On,
    /// Never estimate: a sequence without poses is fitted with each frame in its own sensor
    /// coordinates (method.md; the default of faithful mode).
    Off,
}

impl OdometryMode {
    /// The lower-case name used in the API.
    pub fn name(self) -> &'static str {
        match self {
            OdometryMode::Auto => "auto",
            OdometryMode::On => "on",
            OdometryMode::Off => "off",
        }
    }
}

/// User-facing hyper-parameters. Every field is optional; `None` takes the method's default
/// (method.md). Unknown fields are rejected when deserialising.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitParams {
    /// `faithful` (method.md exactly) or `fast` (default): sets the defaults of
    /// `sample_points`, `max_cluster_points` and `validation_patience`; explicit values win.
    pub mode: Option<Mode>,
    /// Points of a frame used per iteration (a reference frame, or each frame of a pair),
    /// drawn at random (0 = all points; fast default 8192, faithful 0).
    pub sample_points: Option<usize>,
    /// Trajectory methods: stop once this many validations in a row did not improve the best
    /// validation loss (0 = never; fast default 8, faithful 0). MBNT counts them from the end of
    /// the rigidity warm-up on.
    pub validation_patience: Option<usize>,
    /// Optimiser iterations: 1001 for NTP/MBNT; at most 1000 per pair for NSFP/MBNSF.
    pub iterations: Option<usize>,
    /// Seed of every random choice (initialisation, reference frames, subsampling).
    pub seed: Option<u64>,
    /// Adam learning rate (default 0.003).
    pub learning_rate: Option<f32>,
    /// The learning rate halves every this many iterations (default 500; trajectory methods).
    pub lr_halve_every: Option<usize>,
    /// Reference frames drawn (with replacement) per iteration (default 4; trajectory methods).
    pub reference_frames: Option<usize>,
    /// Every this many iterations is a validation iteration (default 25; trajectory methods).
    pub validate_every: Option<usize>,
    /// Hidden width of the MLP (default 128).
    pub hidden_width: Option<usize>,
    /// Number of hidden Linear+ReLU layers (default 8).
    pub hidden_layers: Option<usize>,
    /// Chamfer truncation on the squared distance, m^2 (default 2.0).
    pub chamfer_truncation_m2: Option<f32>,
    /// Weight of the cycle-consistency loss (default 1.0; trajectory methods).
    pub cycle_weight: Option<f32>,
    /// Weight of the multi-body loss (default 1.0; MBNT and MBNSF).
    pub rigidity_weight: Option<f32>,
    /// DBSCAN radius, m (default 0.8).
    pub dbscan_eps_m: Option<f32>,
    /// DBSCAN minimum neighbourhood size, the point itself included (default 30).
    pub dbscan_min_points: Option<usize>,
    /// Larger clusters are randomly subsampled to this many points per evaluation (default 3000).
    pub max_cluster_points: Option<usize>,
    /// Power-iteration steps at most (default 10).
    pub power_iterations: Option<usize>,
    /// MBNT distance threshold at t = 0, m (default 0.10); grows by `d_thr_slope_m * t / T`.
    pub d_thr_base_m: Option<f32>,
    /// MBNT distance-threshold growth over the sequence, m (default 0.39).
    pub d_thr_slope_m: Option<f32>,
    /// MBNSF distance threshold, m (default 0.03).
    pub pair_d_thr_m: Option<f32>,
    /// NSFP/MBNSF early-stopping patience in iterations (default 100).
    pub early_stop_patience: Option<usize>,
    /// NSFP/MBNSF early-stopping minimum improvement of the loss (default 1e-4).
    pub early_stop_min_delta: Option<f32>,
    /// Remove ground points before fitting (default true).
    pub remove_ground: Option<bool>,
    /// When the sequence has sensor poses, fit in frame 0's sensor coordinates with every
    /// frame's ego motion removed, so static points stand still (default true). Answers stay
    /// in the sensor frame of the time they refer to either way.
    pub use_poses: Option<bool>,
    /// **Ours (default `auto` in fast mode, `off` in faithful mode, which fits as method.md
    /// does):** estimate the sensor poses by LiDAR odometry
    /// (`crate::odometry`) when the sequence has none (`auto`), always, ignoring given poses
    /// (`on`), or never (`off`). The fit then runs as with given poses. Has no effect when
    /// `use_poses` is false. Measured in docs/benchmarks.md section 8.
    pub odometry: Option<OdometryMode>,
    /// **Ours (default true for MBNT in fast mode, false otherwise):** start the network's output
    /// layer at zero, so the initial field is "nothing moves" (in the fit's coordinates: the
    /// static world when poses are used) instead of PyTorch's random initial velocities; the slide
    /// along facades that Chamfer cannot see then has nothing to start from, and points and times
    /// that no loss term reaches keep that answer instead of the random one.
    pub zero_output_init: Option<bool>,
    /// **Ours (fast default 250, faithful 0 = off):** MBNT's multi-body gradient grows linearly
    /// from 0 to its full weight over this many iterations, so Chamfer can place the scene before
    /// rigidity holds clusters together (at full strength from the start, it is satisfied fastest
    /// by a globally rigid drift). The validation loss always uses the full weight.
    pub rigidity_warmup_iterations: Option<usize>,
    /// **Ours (fast default 2048, faithful 0 = all):** trajectory methods evaluate the three
    /// cycle-consistency terms of a reference frame on this many of its points, drawn at random
    /// each time (an unbiased estimate of the mean; the three extra network passes are three
    /// quarters of an iteration's work).
    pub cycle_sample_points: Option<usize>,
    /// **Ours (fast default 0.05, faithful 0):** MBNT's rigidity threshold of a cluster grows by
    /// this share of the length of the cluster's mean predicted displacement (m per m travelled,
    /// a constant of each evaluation). A body standing still is exactly rigid whatever its velocity
    /// error, while one travelling 20 m deviates by 0.2 m at 1 % velocity error: with a fixed
    /// threshold the term holds moving bodies still. Static clusters keep the fixed threshold.
    pub d_thr_motion_fraction: Option<f32>,
    /// **Ours (default 0 = ReLU, as method.md):** trajectory methods use a leaky ReLU with this
    /// slope for negative inputs in the hidden layers, in [0, 1). With ReLU the multi-body and
    /// cycle terms, which are smallest for a field that does not vary, can drive a whole layer to
    /// zero for every input; the network is then constant and no gradient reaches it again.
    pub hidden_negative_slope: Option<f32>,
    /// **Ours (default 0 = off):** when a validation finds a hidden layer with no live unit on
    /// frame 0's points (the network has collapsed to one motion for everything, from which no
    /// gradient recovers it), go back to the best checkpoint with fresh optimiser moments and half
    /// the learning rate, at most this many times per fit.
    pub collapse_restarts: Option<usize>,
    /// **Ours (default true for MBNT in fast mode, false otherwise):** the scene model. After the
    /// fit, find the moving bodies (`fit::bodies`): clusters that move rigidly, linked over the
    /// sequence into one object each with an SE(3) trajectory registered to the body's own
    /// accumulated shape; queries on their points follow the body. With poses (given or
    /// estimated), the other points follow the still world exactly (docs/benchmarks.md, section 8).
    /// Supersedes `rigid_tracks` (default off when this is on).
    pub moving_bodies: Option<bool>,
    /// **Ours (default false):** the earlier overlay: after the fit, find the
    /// clusters that one rigid motion to the next frame explains clearly better than standing
    /// still, follow each by ICP through the sequence, and answer queries on their points from
    /// these rigid tracks instead of the network (`fit::tracks`): the multi-body term holds moving
    /// bodies still (docs/benchmarks.md, section 7). Any method may ask for it; clusters are
    /// computed for it when the method has none.
    pub rigid_tracks: Option<bool>,
    /// Drop points farther than this from the sensor, m (default 80).
    pub max_range_m: Option<f32>,
    /// **Ours (default 25, the sequence length of method.md):** a sequence of more frames is
    /// fitted as overlapping windows of this many frames, each an ordinary fit of its frames,
    /// stitched into one model (`fit::windows`). One network over a whole log loses its start
    /// (issue 21: long-term Acc.5 0 % on the first 24 frames of a 100-frame sequence). At most
    /// this many frames: one fit exactly as before.
    pub window_frames: Option<usize>,
    /// **Ours (default 5):** frames two neighbouring windows share, at least 1 and fewer than
    /// `window_frames`. A trajectory passes from one window to the next at the middle frame of
    /// the overlap, and moving bodies are linked by their points there.
    pub window_overlap_frames: Option<usize>,
    /// **Ours (fast default 100; otherwise, or when `iterations` is given, `iterations`):** the
    /// iterations of each window of a sequence fitted as windows; the rigidity warm-up of a
    /// window is at most half of them. Why fewer than a 25-frame job's: a window's answers come
    /// from the still world and the moving bodies, which do not depend on the network, and the
    /// network answers only the free points (docs/benchmarks.md section 23: spans of 100- and
    /// 150-frame logs within 2 points of 25-frame default jobs at a fraction of the time).
    pub window_iterations: Option<usize>,
}

/// A parameter that is out of range, by name.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("parameter `{name}` {problem}")]
pub struct FitParamsError {
    /// The parameter's field name.
    pub name: &'static str,
    /// What is wrong with it.
    pub problem: String,
}

/// Hyper-parameters checked for one method, with every default filled in.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValidFitParams {
    /// See [`FitParams::mode`].
    pub mode: Mode,
    /// See [`FitParams::sample_points`] (0 = all).
    pub sample_points: usize,
    /// See [`FitParams::validation_patience`] (0 = never).
    pub validation_patience: usize,
    /// See [`FitParams::iterations`].
    pub iterations: usize,
    /// See [`FitParams::seed`].
    pub seed: u64,
    /// See [`FitParams::learning_rate`].
    pub learning_rate: f32,
    /// See [`FitParams::lr_halve_every`].
    pub lr_halve_every: usize,
    /// See [`FitParams::reference_frames`].
    pub reference_frames: usize,
    /// See [`FitParams::validate_every`].
    pub validate_every: usize,
    /// See [`FitParams::hidden_width`].
    pub hidden_width: usize,
    /// See [`FitParams::hidden_layers`].
    pub hidden_layers: usize,
    /// See [`FitParams::chamfer_truncation_m2`].
    pub chamfer_truncation_m2: f32,
    /// See [`FitParams::cycle_weight`].
    pub cycle_weight: f32,
    /// See [`FitParams::rigidity_weight`].
    pub rigidity_weight: f32,
    /// See [`FitParams::dbscan_eps_m`].
    pub dbscan_eps_m: f32,
    /// See [`FitParams::dbscan_min_points`].
    pub dbscan_min_points: usize,
    /// See [`FitParams::max_cluster_points`].
    pub max_cluster_points: usize,
    /// See [`FitParams::power_iterations`].
    pub power_iterations: usize,
    /// See [`FitParams::d_thr_base_m`].
    pub d_thr_base_m: f32,
    /// See [`FitParams::d_thr_slope_m`].
    pub d_thr_slope_m: f32,
    /// See [`FitParams::pair_d_thr_m`].
    pub pair_d_thr_m: f32,
    /// See [`FitParams::early_stop_patience`].
    pub early_stop_patience: usize,
    /// See [`FitParams::early_stop_min_delta`].
    pub early_stop_min_delta: f32,
    /// See [`FitParams::remove_ground`].
    pub remove_ground: bool,
    /// See [`FitParams::max_range_m`].
    pub max_range_m: f32,
    /// See [`FitParams::use_poses`].
    #[serde(default = "default_true")]
    pub use_poses: bool,
    /// See [`FitParams::odometry`]. Models saved before it existed did not estimate poses.
    #[serde(default = "default_odometry_off")]
    pub odometry: OdometryMode,
    /// See [`FitParams::zero_output_init`].
    #[serde(default)]
    pub zero_output_init: bool,
    /// See [`FitParams::rigidity_warmup_iterations`].
    #[serde(default)]
    pub rigidity_warmup_iterations: usize,
    /// See [`FitParams::cycle_sample_points`] (0 = all).
    #[serde(default)]
    pub cycle_sample_points: usize,
    /// See [`FitParams::d_thr_motion_fraction`].
    #[serde(default)]
    pub d_thr_motion_fraction: f32,
    /// See [`FitParams::hidden_negative_slope`] (0 = ReLU).
    #[serde(default)]
    pub hidden_negative_slope: f32,
    /// See [`FitParams::collapse_restarts`] (0 = off).
    #[serde(default)]
    pub collapse_restarts: usize,
    /// See [`FitParams::rigid_tracks`].
    #[serde(default)]
    pub rigid_tracks: bool,
    /// See [`FitParams::moving_bodies`].
    #[serde(default)]
    pub moving_bodies: bool,
    /// See [`FitParams::window_frames`]. Models saved before it existed were one fit of every
    /// frame; they read back as the default, which they record no differently.
    #[serde(default = "default_window_frames")]
    pub window_frames: usize,
    /// See [`FitParams::window_overlap_frames`].
    #[serde(default = "default_window_overlap_frames")]
    pub window_overlap_frames: usize,
    /// See [`FitParams::window_iterations`]; `None` in records written before it existed, whose
    /// windows ran `iterations` ([`ValidFitParams::iterations_per_window`]).
    #[serde(default)]
    pub window_iterations: Option<usize>,
}

impl ValidFitParams {
    /// Iterations of each window of a sequence fitted as windows.
    pub fn iterations_per_window(&self) -> usize {
        self.window_iterations.unwrap_or(self.iterations)
    }

    /// The parameters each window of a sequence fitted as windows is fitted with: its
    /// iterations, the rigidity warm-up at most half of them (so that the multi-body term
    /// reaches its full weight inside the window's budget), and no odometry of its own (the
    /// log's poses are settled once, for every window).
    pub fn for_window(&self) -> ValidFitParams {
        let iterations = self.iterations_per_window();
        ValidFitParams {
            iterations,
            rigidity_warmup_iterations: self.rigidity_warmup_iterations.min(iterations / 2),
            odometry: OdometryMode::Off,
            ..self.clone()
        }
    }
}

/// Default of [`FitParams::window_iterations`] in fast mode.
pub const DEFAULT_FAST_WINDOW_ITERATIONS: usize = 100;

/// Default of [`FitParams::window_frames`]: the 25 frames method.md fits at a time.
pub const DEFAULT_WINDOW_FRAMES: usize = 25;

/// Default of [`FitParams::window_overlap_frames`]. A window's first and last frames are its
/// least constrained (Chamfer and cycle terms see neighbours on one side only), so the hand-over
/// frame (the middle of the overlap) should lie a few frames inside both windows: 5 puts it 2
/// frames from either end, and a moving body seen in the overlap is seen by both windows in up
/// to 5 frames to link it. The cost is 5 / 20 = 25 % more frames fitted than without overlap.
pub const DEFAULT_WINDOW_OVERLAP_FRAMES: usize = 5;

/// Largest `window_frames` accepted: the frame limit of a network's output width that a
/// service would ever be configured for (the upload limit is 300 by default).
pub const MAX_WINDOW_FRAMES: usize = 100_000;

fn default_window_frames() -> usize {
    DEFAULT_WINDOW_FRAMES
}

fn default_window_overlap_frames() -> usize {
    DEFAULT_WINDOW_OVERLAP_FRAMES
}

fn default_true() -> bool {
    true
}

fn default_odometry_off() -> OdometryMode {
    OdometryMode::Off
}

/// Upper bound on iterations accepted from users, so one job cannot occupy a worker for days.
pub const MAX_ITERATIONS: usize = 100_000;

impl FitParams {
    /// Fills in `method`'s defaults and checks every range; the error names the parameter.
    pub fn check(&self, method: Method) -> Result<ValidFitParams, FitParamsError> {
        fn bad(name: &'static str, problem: impl Into<String>) -> FitParamsError {
            FitParamsError { name, problem: problem.into() }
        }
        fn int_in(
            name: &'static str,
            v: Option<usize>,
            default: usize,
            lo: usize,
            hi: usize,
        ) -> Result<usize, FitParamsError> {
            let v = v.unwrap_or(default);
            if v < lo || v > hi {
                return Err(bad(name, format!("must be in [{lo}, {hi}], got {v}")));
            }
            Ok(v)
        }
        fn float_in(name: &'static str, v: Option<f32>, default: f32, lo: f32, hi: f32) -> Result<f32, FitParamsError> {
            let v = v.unwrap_or(default);
            if !v.is_finite() || v < lo || v > hi {
                return Err(bad(name, format!("must be a finite number in [{lo}, {hi}], got {v}")));
            }
            Ok(v)
        }
        let default_iterations = if method.is_trajectory() { 1001 } else { 1000 };
        let mode = self.mode.unwrap_or_default();
        let fast = mode == Mode::Fast;
        let window_frames = int_in("window_frames", self.window_frames, DEFAULT_WINDOW_FRAMES, 2, MAX_WINDOW_FRAMES)?;
        // The overlap must leave each window at least one frame of its own, and share at least
        // the hand-over frame.
        let window_overlap_frames = int_in(
            "window_overlap_frames",
            self.window_overlap_frames,
            DEFAULT_WINDOW_OVERLAP_FRAMES.min(window_frames - 1),
            1,
            window_frames - 1,
        )?;
        let iterations = int_in("iterations", self.iterations, default_iterations, 1, MAX_ITERATIONS)?;
        // An explicit `iterations` is what the user asked of every fit, windows included.
        let default_window_iterations = match self.iterations {
            None if fast && method.is_trajectory() => DEFAULT_FAST_WINDOW_ITERATIONS,
            _ => iterations,
        };
        let window_iterations =
            int_in("window_iterations", self.window_iterations, default_window_iterations, 1, MAX_ITERATIONS)?;
        Ok(ValidFitParams {
            mode,
            sample_points: int_in("sample_points", self.sample_points, if fast { 8192 } else { 0 }, 0, 10_000_000)?,
            validation_patience: int_in(
                "validation_patience",
                self.validation_patience,
                if fast { 8 } else { 0 },
                0,
                MAX_ITERATIONS,
            )?,
            iterations,
            seed: self.seed.unwrap_or(0),
            learning_rate: float_in("learning_rate", self.learning_rate, 0.003, 1e-7, 1.0)?,
            lr_halve_every: int_in("lr_halve_every", self.lr_halve_every, 500, 1, MAX_ITERATIONS)?,
            reference_frames: int_in("reference_frames", self.reference_frames, 4, 1, 64)?,
            validate_every: int_in("validate_every", self.validate_every, 25, 1, MAX_ITERATIONS)?,
            hidden_width: int_in("hidden_width", self.hidden_width, 128, 4, 1024)?,
            hidden_layers: int_in("hidden_layers", self.hidden_layers, 8, 1, 16)?,
            chamfer_truncation_m2: float_in("chamfer_truncation_m2", self.chamfer_truncation_m2, 2.0, 1e-6, 1e6)?,
            cycle_weight: float_in("cycle_weight", self.cycle_weight, 1.0, 0.0, 1e3)?,
            rigidity_weight: float_in("rigidity_weight", self.rigidity_weight, 1.0, 0.0, 1e3)?,
            dbscan_eps_m: float_in("dbscan_eps_m", self.dbscan_eps_m, 0.8, 1e-3, 10.0)?,
            dbscan_min_points: int_in("dbscan_min_points", self.dbscan_min_points, 30, 1, 10_000)?,
            max_cluster_points: int_in(
                "max_cluster_points",
                self.max_cluster_points,
                if fast { 1024 } else { 3000 },
                3,
                20_000,
            )?,
            power_iterations: int_in("power_iterations", self.power_iterations, 10, 1, 1000)?,
            d_thr_base_m: float_in("d_thr_base_m", self.d_thr_base_m, 0.10, 1e-4, 10.0)?,
            d_thr_slope_m: float_in("d_thr_slope_m", self.d_thr_slope_m, 0.39, 0.0, 10.0)?,
            pair_d_thr_m: float_in("pair_d_thr_m", self.pair_d_thr_m, 0.03, 1e-4, 10.0)?,
            early_stop_patience: int_in("early_stop_patience", self.early_stop_patience, 100, 1, MAX_ITERATIONS)?,
            early_stop_min_delta: float_in("early_stop_min_delta", self.early_stop_min_delta, 1e-4, 0.0, 1e3)?,
            remove_ground: self.remove_ground.unwrap_or(true),
            use_poses: self.use_poses.unwrap_or(true),
            odometry: self.odometry.unwrap_or(if fast { OdometryMode::Auto } else { OdometryMode::Off }),
            zero_output_init: self.zero_output_init.unwrap_or(fast && method == Method::Mbnt),
            rigidity_warmup_iterations: int_in(
                "rigidity_warmup_iterations",
                self.rigidity_warmup_iterations,
                if fast { 250 } else { 0 },
                0,
                MAX_ITERATIONS,
            )?,
            cycle_sample_points: int_in(
                "cycle_sample_points",
                self.cycle_sample_points,
                if fast { 2048 } else { 0 },
                0,
                10_000_000,
            )?,
            d_thr_motion_fraction: float_in(
                "d_thr_motion_fraction",
                self.d_thr_motion_fraction,
                if fast { 0.05 } else { 0.0 },
                0.0,
                10.0,
            )?,
            hidden_negative_slope: float_in("hidden_negative_slope", self.hidden_negative_slope, 0.0, 0.0, 0.99)?,
            collapse_restarts: int_in("collapse_restarts", self.collapse_restarts, 0, 0, 100)?,
            rigid_tracks: self.rigid_tracks.unwrap_or(false),
            moving_bodies: self.moving_bodies.unwrap_or(fast && method == Method::Mbnt),
            max_range_m: float_in("max_range_m", self.max_range_m, 80.0, 1.0, 10_000.0)?,
            window_frames,
            window_overlap_frames,
            window_iterations: Some(window_iterations),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_follow_the_method_document() {
        let p = FitParams { mode: Some(Mode::Faithful), ..Default::default() }.check(Method::Mbnt).unwrap();
        assert_eq!(p.iterations, 1001);
        assert_eq!(p.sample_points, 0);
        assert_eq!(p.max_cluster_points, 3000);
        assert_eq!(p.validation_patience, 0);
        assert_eq!(p.rigidity_warmup_iterations, 0);
        assert_eq!(p.cycle_sample_points, 0);
        assert_eq!(p.d_thr_motion_fraction, 0.0);
        assert!(!p.zero_output_init);
        assert!(!p.rigid_tracks && !p.moving_bodies);
        assert_eq!(p.odometry, OdometryMode::Off);
        assert_eq!(FitParams::default().check(Method::Mbnt).unwrap().odometry, OdometryMode::Auto);
        assert_eq!(FitParams::default().check(Method::Nsfp).unwrap().odometry, OdometryMode::Auto);
        assert!(FitParams::default().check(Method::Mbnt).unwrap().moving_bodies);
        assert!(!FitParams::default().check(Method::Mbnt).unwrap().rigid_tracks);
        assert!(!FitParams::default().check(Method::Ntp).unwrap().moving_bodies);
        assert!(FitParams::default().check(Method::Mbnt).unwrap().zero_output_init);
        assert!(!FitParams::default().check(Method::Ntp).unwrap().zero_output_init);
        assert_eq!(p.learning_rate, 0.003);
        assert_eq!(p.dbscan_min_points, 30);
        assert_eq!(FitParams::default().check(Method::Nsfp).unwrap().iterations, 1000);
    }

    #[test]
    fn fast_mode_is_the_default_and_explicit_values_win() {
        let p = FitParams::default().check(Method::Mbnt).unwrap();
        assert_eq!(p.mode, Mode::Fast);
        assert!(p.sample_points > 0 && p.validation_patience > 0 && p.rigidity_warmup_iterations == 250);
        let p = FitParams { sample_points: Some(0), ..Default::default() }.check(Method::Mbnt).unwrap();
        assert_eq!(p.sample_points, 0);
        let e = serde_json::from_str::<FitParams>(r#"{"mode": "turbo"}"#).unwrap_err();
        assert!(e.to_string().contains("turbo"), "{e}");
    }

    #[test]
    fn an_out_of_range_parameter_is_named() {
        let p = FitParams { learning_rate: Some(-1.0), ..Default::default() };
        assert_eq!(p.check(Method::Ntp).unwrap_err().name, "learning_rate");
        // Found by fuzzing (target `job_params`): read through a `Value`, as the job handler
        // reads `params`, a finite JSON number beyond f32's range becomes infinity; it must be
        // refused here, or it would be stored as `null`.
        let p = serde_json::from_value::<FitParams>(serde_json::json!({"mode": "faithful", "learning_rate": 22e271}))
            .unwrap();
        assert_eq!(p.learning_rate, Some(f32::INFINITY));
        assert_eq!(p.check(Method::Mbnt).unwrap_err().name, "learning_rate");
        let e = serde_json::from_str::<FitParams>(r#"{"iterations": 5, "bogus": 1}"#).unwrap_err();
        assert!(e.to_string().contains("bogus"), "{e}");
    }

    #[test]
    fn window_parameters_are_checked_against_each_other() {
        let p = FitParams::default().check(Method::Mbnt).unwrap();
        assert_eq!((p.window_frames, p.window_overlap_frames), (25, 5));
        let check = |frames: Option<usize>, overlap: Option<usize>| {
            FitParams { window_frames: frames, window_overlap_frames: overlap, ..Default::default() }.check(Method::Ntp)
        };
        let e = check(Some(1), None).unwrap_err();
        assert_eq!(e.name, "window_frames");
        assert!(e.problem.contains("[2, 100000]"), "{e}");
        assert_eq!(check(Some(0), None).unwrap_err().name, "window_frames");
        // The overlap leaves each window a frame of its own...
        let e = check(Some(10), Some(10)).unwrap_err();
        assert_eq!(e.name, "window_overlap_frames");
        assert!(e.problem.contains("[1, 9]"), "{e}");
        // ...and shares at least the hand-over frame.
        assert_eq!(check(None, Some(0)).unwrap_err().name, "window_overlap_frames");
        // A short window takes the default overlap only as far as it fits.
        let p = check(Some(3), None).unwrap();
        assert_eq!((p.window_frames, p.window_overlap_frames), (3, 2));
        assert_eq!(check(Some(2), Some(1)).unwrap().window_overlap_frames, 1);
        // Records written before the fields existed read back with the defaults.
        let mut old = serde_json::to_value(FitParams::default().check(Method::Mbnt).unwrap()).unwrap();
        let object = old.as_object_mut().unwrap();
        object.remove("window_frames");
        object.remove("window_overlap_frames");
        let back: ValidFitParams = serde_json::from_value(old).unwrap();
        assert_eq!((back.window_frames, back.window_overlap_frames), (25, 5));
    }

    #[test]
    fn windows_run_fewer_iterations_in_fast_mode_unless_iterations_are_given() {
        let fast = FitParams::default().check(Method::Mbnt).unwrap();
        assert_eq!((fast.iterations, fast.iterations_per_window()), (1001, DEFAULT_FAST_WINDOW_ITERATIONS));
        let window = fast.for_window();
        assert_eq!(window.iterations, DEFAULT_FAST_WINDOW_ITERATIONS);
        // The multi-body term reaches its full weight inside the window's budget.
        assert_eq!(window.rigidity_warmup_iterations, DEFAULT_FAST_WINDOW_ITERATIONS / 2);
        assert_eq!(window.odometry, OdometryMode::Off);
        // Nothing else changes.
        let restored = ValidFitParams {
            odometry: fast.odometry,
            iterations: fast.iterations,
            rigidity_warmup_iterations: fast.rigidity_warmup_iterations,
            ..window
        };
        assert_eq!(restored, fast);
        // An explicit `iterations` holds for every window; an explicit `window_iterations` wins.
        let given = FitParams { iterations: Some(300), ..Default::default() }.check(Method::Mbnt).unwrap();
        assert_eq!(given.iterations_per_window(), 300);
        assert_eq!(given.for_window().rigidity_warmup_iterations, 150);
        let both = FitParams { iterations: Some(300), window_iterations: Some(40), ..Default::default() };
        assert_eq!(both.check(Method::Mbnt).unwrap().for_window().iterations, 40);
        // Faithful mode and the pair methods keep their iterations.
        let faithful = FitParams { mode: Some(Mode::Faithful), ..Default::default() }.check(Method::Mbnt).unwrap();
        assert_eq!(faithful.iterations_per_window(), 1001);
        assert_eq!(faithful.for_window().rigidity_warmup_iterations, 0);
        assert_eq!(FitParams::default().check(Method::Nsfp).unwrap().iterations_per_window(), 1000);
        let e = FitParams { window_iterations: Some(0), ..Default::default() }.check(Method::Mbnt).unwrap_err();
        assert_eq!(e.name, "window_iterations");
        // A record written before the field existed ran `iterations` per window.
        let mut old = serde_json::to_value(&fast).unwrap();
        old.as_object_mut().unwrap().remove("window_iterations");
        let back: ValidFitParams = serde_json::from_value(old).unwrap();
        assert_eq!(back.iterations_per_window(), 1001);
    }
}
