//! The adaptive correspondence threshold: how far the constant-velocity prediction has been
//! off so far, as a running RMS, so that the search radius follows how the sensor moves.

use nalgebra::Isometry3;

/// Running RMS of the prediction's errors (m), the ICP's threshold sigma.
#[derive(Debug, Clone)]
pub(crate) struct AdaptiveThreshold {
    initial_m: f64,
    min_error_m: f64,
    max_range_m: f64,
    sum_error2_m2: f64,
    samples: usize,
}

impl AdaptiveThreshold {
    /// `initial_m` until a prediction has been off by more than `min_error_m`.
    pub fn new(initial_m: f64, min_error_m: f64, max_range_m: f64) -> Self {
        Self { initial_m, min_error_m, max_range_m, sum_error2_m2: 0.0, samples: 0 }
    }

    /// The current sigma (m).
    pub fn sigma_m(&self) -> f64 {
        if self.samples == 0 {
            return self.initial_m;
        }
        (self.sum_error2_m2 / self.samples as f64).sqrt()
    }

    /// Takes one frame's `deviation` (prediction^-1 * estimate) when it is larger than the
    /// minimum error. Smaller ones do not count: while the motion is steady, sigma keeps the
    /// size of the last real surprises (a turn, braking), so that the next one still finds its
    /// correspondences; averaging in steady frames would shrink it until a turn's points fall
    /// outside the search and only the prediction is left.
    pub fn update(&mut self, deviation: &Isometry3<f64>) {
        let error = model_error_m(deviation, self.max_range_m);
        if error <= self.min_error_m {
            return;
        }
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
    fn the_threshold_is_the_rms_of_the_errors_above_the_minimum() {
        let mut t = AdaptiveThreshold::new(2.0, 0.1, 100.0);
        assert_eq!(t.sigma_m(), 2.0);
        t.update(&Isometry3::translation(0.05, 0.0, 0.0));
        assert_eq!(t.sigma_m(), 2.0, "a small error does not count");
        t.update(&Isometry3::translation(0.3, 0.0, 0.0));
        t.update(&Isometry3::translation(0.0, 0.4, 0.0));
        t.update(&Isometry3::identity());
        assert!((t.sigma_m() - (0.125f64).sqrt()).abs() < 1e-12);
        // 0.01 rad at 100 m sweeps 1 m.
        let turn = Isometry3::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 0.01));
        assert!((model_error_m(&turn, 100.0) - 1.0).abs() < 1e-4);
    }
}
