//! The adaptive correspondence threshold: how far the constant-velocity prediction has been
//! off so far, as a running RMS, so that the search radius follows how the sensor moves.

use nalgebra::Isometry3;

/// Running RMS of the prediction's errors (m), the ICP's threshold sigma.
#[derive(Debug, Clone)]
pub(crate) struct AdaptiveThreshold {
    initial_m: f64,
    min_m: f64,
    min_motion_m: f64,
    max_range_m: f64,
    sum_error2_m2: f64,
    samples: usize,
}

impl AdaptiveThreshold {
    /// `initial_m` until a frame has moved by more than `min_motion_m`; never below `min_m`.
    pub fn new(initial_m: f64, min_m: f64, min_motion_m: f64, max_range_m: f64) -> Self {
        Self { initial_m, min_m, min_motion_m, max_range_m, sum_error2_m2: 0.0, samples: 0 }
    }

    /// The current sigma (m).
    pub fn sigma_m(&self) -> f64 {
        if self.samples == 0 {
            return self.initial_m;
        }
        (self.sum_error2_m2 / self.samples as f64).sqrt().max(self.min_m)
    }

    /// Takes one frame's `deviation` (prediction^-1 * estimate) when the frame moved by more
    /// than the minimum motion: a standing sensor's deviations are noise, not prediction error.
    pub fn update(&mut self, deviation: &Isometry3<f64>, frame_motion: &Isometry3<f64>) {
        if frame_motion.translation.vector.norm() < self.min_motion_m {
            return;
        }
        let error = model_error_m(deviation, self.max_range_m);
        self.sum_error2_m2 += error * error;
        self.samples += 1;
    }
}

/// The largest displacement `deviation` causes to a point within `max_range_m`: its translation
/// plus the chord its rotation sweeps at that range.
pub(crate) fn model_error_m(deviation: &Isometry3<f64>, max_range_m: f64) -> f64 {
    let angle_rad = deviation.rotation.angle();
    deviation.translation.vector.norm() + 2.0 * max_range_m * (angle_rad / 2.0).sin()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn the_threshold_is_the_rms_of_the_moving_frames_errors_and_has_a_floor() {
        let mut t = AdaptiveThreshold::new(2.0, 0.1, 0.1, 100.0);
        assert_eq!(t.sigma_m(), 2.0);
        let moved = Isometry3::translation(1.0, 0.0, 0.0);
        let still = Isometry3::identity();
        t.update(&Isometry3::translation(0.3, 0.0, 0.0), &still);
        assert_eq!(t.sigma_m(), 2.0, "a standing frame does not count");
        t.update(&Isometry3::translation(0.3, 0.0, 0.0), &moved);
        t.update(&Isometry3::translation(0.0, 0.4, 0.0), &moved);
        assert!((t.sigma_m() - (0.125f64).sqrt()).abs() < 1e-12);
        let mut t = AdaptiveThreshold::new(2.0, 0.1, 0.1, 100.0);
        t.update(&Isometry3::identity(), &moved);
        assert_eq!(t.sigma_m(), 0.1);
        // 0.01 rad at 100 m sweeps 1 m.
        let turn = Isometry3::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 0.01));
        assert!((model_error_m(&turn, 100.0) - 1.0).abs() < 1e-4);
    }
}
