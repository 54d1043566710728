//! Parameters of the simulator (sensor, scene, sequence) with documented defaults, and their
//! validation into [`SimError::InvalidParams`].

use serde::{Deserialize, Serialize};

use super::SimError;

/// Everything that defines a simulated sequence. Same parameters (seed included), same sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SimParams {
    /// Seed of every random choice (scene layout, motions, range noise, dropout).
    pub seed: u64,
    /// Number of sweeps (frames) to produce; at least 1.
    pub frames: usize,
    /// Sweep rate (Hz): frame k is taken at `k / frame_rate_hz` seconds.
    pub frame_rate_hz: f64,
    /// The sensor.
    pub lidar: LidarParams,
    /// The street and what is on it.
    pub scene: SceneParams,
}

impl Default for SimParams {
    fn default() -> Self {
        Self { seed: 0, frames: 25, frame_rate_hz: 10.0, lidar: LidarParams::default(), scene: SceneParams::default() }
    }
}

/// Street (m) the default scene keeps ahead of the ego's last position when a log needs a
/// longer street than the default: a 100-frame log of the default scene ends 29 m before the
/// street's end.
pub const STREET_AHEAD_OF_EGO_M: f64 = 30.0;

impl SimParams {
    /// The default scene for a log of `frames` frames: [`SimParams::default`] with the street
    /// lengthened, only when the ego would otherwise drive off its end (beyond 100 frames at the
    /// default speed), to [`STREET_AHEAD_OF_EGO_M`] past the ego's last position. Logs that fit
    /// on the default street are exactly the default scene.
    pub fn log(seed: u64, frames: usize) -> Self {
        let mut params = Self { seed, frames, ..Self::default() };
        let scene = &mut params.scene;
        let duration_s = frames.saturating_sub(1) as f64 / params.frame_rate_hz;
        let ego_end_m = scene.ego_start_m + scene.ego_speed_mps * duration_s;
        if ego_end_m > scene.street_length_m {
            scene.street_length_m = ego_end_m + STREET_AHEAD_OF_EGO_M;
        }
        params
    }
}

/// A spinning multi-beam LiDAR: `beams` lasers at evenly spaced elevations, fired at every
/// azimuth step of a full turn. Each sweep is modelled as instantaneous at its timestamp (no
/// rolling shutter), so a frame is one rigid snapshot of the world.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LidarParams {
    /// Number of lasers (rows).
    pub beams: usize,
    /// Elevation of the lowest beam (degrees, negative = below the horizon).
    pub elevation_min_deg: f64,
    /// Elevation of the highest beam (degrees).
    pub elevation_max_deg: f64,
    /// Horizontal angle between two firings (degrees); 360 / step columns per sweep.
    pub azimuth_step_deg: f64,
    /// Returns farther than this (true range, m) are not reported.
    pub max_range_m: f64,
    /// Returns nearer than this (true range, m) are not reported.
    pub min_range_m: f64,
    /// Standard deviation of the Gaussian noise added to each measured range (m).
    pub range_noise_m: f64,
    /// Probability that a return is lost (independent per ray), in [0, 1).
    pub dropout: f64,
    /// Height of the sensor origin above the ground (m).
    pub mount_height_m: f64,
}

impl Default for LidarParams {
    /// A 32-beam automotive sensor at 10 Hz: -25 to +15 degrees, 0.14 degree azimuth step
    /// (82,304 rays), 100 m range, 2 cm range noise, 3 % dropout, 1.8 m above the road.
    /// In the default street this gives about 67k points per frame, about 43k of them off the
    /// ground and about 30k within the fit's default range and height limits (80 m, 4 m above
    /// the ground): the reference size of method.md.
    fn default() -> Self {
        Self {
            beams: 32,
            elevation_min_deg: -25.0,
            elevation_max_deg: 15.0,
            azimuth_step_deg: 0.14,
            max_range_m: 100.0,
            min_range_m: 1.0,
            range_noise_m: 0.02,
            dropout: 0.03,
            mount_height_m: 1.8,
        }
    }
}

/// The street: a two-lane road (3.5 m lanes, right-hand traffic) along a centreline that is
/// straight for `curve_start_m` and then an arc of curvature `curvature_per_m`, with parking
/// strips, sidewalks, building facades on both sides and one perpendicular side street.
/// The ego vehicle drives in the right lane at constant speed. Buildings fill both sides of the
/// street (their number follows from the street length); the other counts are requests: an
/// object that cannot be placed without touching another one (after many random tries) is
/// left out and counted in [`super::SimSummary::unplaced`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SceneParams {
    /// Length of the built street along the centreline (m), from arc length 0.
    pub street_length_m: f64,
    /// Arc length where the straight part ends and the curve begins (m).
    pub curve_start_m: f64,
    /// Curvature of the curved part (1/m, positive turns left); |curvature| <= 0.05.
    pub curvature_per_m: f64,
    /// Arc length of the perpendicular side street (m).
    pub intersection_s_m: f64,
    /// Arc length where the ego vehicle is at time 0 (m).
    pub ego_start_m: f64,
    /// Ego speed along its lane (m/s, >= 0).
    pub ego_speed_mps: f64,
    /// Trunks of lamp posts and sign poles (thin cylinders) requested.
    pub poles: usize,
    /// Trees (trunk cylinder and spherical crown) requested.
    pub trees: usize,
    /// Parked cars in the parking strips requested.
    pub parked_cars: usize,
    /// Cars driving in the ego direction requested.
    pub same_direction_cars: usize,
    /// Cars driving in the opposite lane requested.
    pub oncoming_cars: usize,
    /// Cars driving straight along the side street, across the main road, requested.
    pub crossing_cars: usize,
    /// Cars turning from the side street into the main road (rotating bodies) requested.
    pub turning_cars: usize,
    /// Pedestrians walking along the sidewalks requested.
    pub pedestrians: usize,
}

impl Default for SceneParams {
    /// An urban street: straight, then a left curve of 70 m radius that the ego enters half-way
    /// through a 25-frame sequence at 10 m/s; the side street is 12 m behind the ego's start.
    fn default() -> Self {
        Self {
            street_length_m: 200.0,
            curve_start_m: 84.0,
            curvature_per_m: 1.0 / 70.0,
            intersection_s_m: 60.0,
            ego_start_m: 72.0,
            ego_speed_mps: 10.0,
            poles: 10,
            trees: 14,
            parked_cars: 14,
            same_direction_cars: 3,
            oncoming_cars: 4,
            crossing_cars: 1,
            turning_cars: 1,
            pedestrians: 12,
        }
    }
}

/// Upper bound on rays per sweep, so that a typo cannot ask for gigabytes.
const MAX_RAYS_PER_SWEEP: f64 = 4.0e6;

fn invalid(msg: impl Into<String>) -> SimError {
    SimError::InvalidParams(msg.into())
}

fn finite_in(name: &str, value: f64, lo: f64, hi: f64) -> Result<(), SimError> {
    if !value.is_finite() || value < lo || value > hi {
        return Err(invalid(format!("{name} = {value} must be finite and in [{lo}, {hi}]")));
    }
    Ok(())
}

impl SimParams {
    /// Checks every parameter; the simulator itself never re-checks.
    pub fn validate(&self) -> Result<(), SimError> {
        if self.frames == 0 {
            return Err(invalid("frames must be at least 1"));
        }
        if !(self.frame_rate_hz.is_finite() && self.frame_rate_hz > 0.0) {
            return Err(invalid(format!("frame_rate_hz = {} must be finite and positive", self.frame_rate_hz)));
        }
        let l = &self.lidar;
        if l.beams == 0 || l.beams > 1024 {
            return Err(invalid(format!("lidar.beams = {} must be in 1..=1024", l.beams)));
        }
        finite_in("lidar.elevation_min_deg", l.elevation_min_deg, -89.0, 89.0)?;
        finite_in("lidar.elevation_max_deg", l.elevation_max_deg, -89.0, 89.0)?;
        if l.elevation_max_deg < l.elevation_min_deg || (l.beams > 1 && l.elevation_max_deg == l.elevation_min_deg) {
            return Err(invalid("lidar.elevation_max_deg must exceed lidar.elevation_min_deg"));
        }
        finite_in("lidar.azimuth_step_deg", l.azimuth_step_deg, 1e-3, 360.0)?;
        let rays = l.beams as f64 * (360.0 / l.azimuth_step_deg).round();
        if rays > MAX_RAYS_PER_SWEEP {
            return Err(invalid(format!("{rays} rays per sweep exceed the limit of {MAX_RAYS_PER_SWEEP}")));
        }
        finite_in("lidar.max_range_m", l.max_range_m, 1e-3, 1e4)?;
        finite_in("lidar.min_range_m", l.min_range_m, 0.0, l.max_range_m)?;
        finite_in("lidar.range_noise_m", l.range_noise_m, 0.0, 10.0)?;
        finite_in("lidar.dropout", l.dropout, 0.0, 0.999)?;
        finite_in("lidar.mount_height_m", l.mount_height_m, 0.1, 100.0)?;
        let s = &self.scene;
        finite_in("scene.street_length_m", s.street_length_m, 20.0, 1e5)?;
        finite_in("scene.curve_start_m", s.curve_start_m, 0.0, 1e5)?;
        // Offsets of up to ~30 m from the centreline (lanes, sidewalks, building backs) must
        // stay on the same side of the centre of curvature.
        finite_in("scene.curvature_per_m", s.curvature_per_m, -0.05, 0.05)?;
        finite_in("scene.intersection_s_m", s.intersection_s_m, 0.0, s.street_length_m)?;
        finite_in("scene.ego_start_m", s.ego_start_m, 0.0, s.street_length_m)?;
        finite_in("scene.ego_speed_mps", s.ego_speed_mps, 0.0, 70.0)?;
        let duration_s = (self.frames - 1) as f64 / self.frame_rate_hz;
        let ego_end_m = s.ego_start_m + s.ego_speed_mps * duration_s;
        if ego_end_m > s.street_length_m {
            return Err(invalid(format!(
                "the ego would leave the street: it ends at {ego_end_m:.1} m of a {:.1} m street \
                 (lengthen the street, or lower the speed or the frame count)",
                s.street_length_m
            )));
        }
        let counts = [
            s.poles,
            s.trees,
            s.parked_cars,
            s.same_direction_cars,
            s.oncoming_cars,
            s.crossing_cars,
            s.turning_cars,
            s.pedestrians,
        ];
        if counts.iter().any(|&c| c > 10_000) {
            return Err(invalid("object counts must be at most 10000 each"));
        }
        Ok(())
    }
}
