//! The Adam optimiser with PyTorch's semantics, and the step learning-rate schedule.

use super::{Gradients, Mlp, Scalar};

/// Exponential decay of the first-moment estimate (PyTorch default).
pub const BETA1: f64 = 0.9;
/// Exponential decay of the second-moment estimate (PyTorch default).
pub const BETA2: f64 = 0.999;
/// Added to `sqrt(v_hat)` in the denominator (PyTorch default).
pub const EPS: f64 = 1e-8;

/// Adam state for one network: first and second moments per parameter and the step count.
///
/// One [`Adam::step`] is exactly PyTorch's `torch.optim.Adam` (single-tensor path, no weight
/// decay, no amsgrad): with `t` the step count after incrementing,
/// `m = m + (1 - β1)(g - m)`, `v = β2·v + (1 - β2)·g²`,
/// `p -= (lr / (1 - β1^t)) · m / (sqrt(v) / sqrt(1 - β2^t) + ε)`.
/// Bias corrections are computed in f64 and applied in `T`, as PyTorch does with Python floats.
#[derive(Clone)]
pub struct Adam<T> {
    lr: f32,
    m: Vec<T>,
    v: Vec<T>,
    steps: u64,
}

impl<T> std::fmt::Debug for Adam<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Adam")
            .field("lr", &self.lr)
            .field("steps", &self.steps)
            .field("parameters", &self.m.len())
            .finish()
    }
}

impl<T: Scalar> Adam<T> {
    /// Fresh state (zero moments, no steps taken) for `mlp`, learning rate `lr`.
    pub fn new(mlp: &Mlp<T>, lr: f32) -> Self {
        let n = mlp.parameters().len();
        Self { lr, m: vec![T::zero(); n], v: vec![T::zero(); n], steps: 0 }
    }

    /// Sets the learning rate used by the next steps (moments are kept).
    pub fn set_lr(&mut self, lr: f32) {
        self.lr = lr;
    }

    /// The current learning rate.
    pub fn lr(&self) -> f32 {
        self.lr
    }

    /// Number of steps taken so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The first and second moments, one per parameter (for a checkpoint).
    pub fn moments(&self) -> (&[T], &[T]) {
        (&self.m, &self.v)
    }

    /// State taken from a checkpoint: moments `m` and `v` after `steps` steps, learning rate
    /// `lr`. `None` when the moments' lengths differ.
    pub fn from_moments(lr: f32, m: Vec<T>, v: Vec<T>, steps: u64) -> Option<Self> {
        (m.len() == v.len()).then_some(Self { lr, m, v, steps })
    }

    /// One update of `mlp`'s parameters from `grads` (the gradient of the loss to minimise).
    ///
    /// # Panics
    /// If `mlp` or `grads` do not have the parameter count this state was created for.
    pub fn step(&mut self, mlp: &mut Mlp<T>, grads: &Gradients<T>) {
        let params = mlp.parameters_mut();
        let g = grads.values();
        assert!(params.len() == self.m.len() && g.len() == self.m.len(), "Adam state belongs to another network");
        self.steps += 1;
        let t = self.steps.min(i32::MAX as u64) as i32;
        let bias_correction1 = 1.0 - BETA1.powi(t);
        let bias_correction2_sqrt = (1.0 - BETA2.powi(t)).sqrt();
        let cast = |x: f64| T::from(x).unwrap_or_else(T::nan);
        let step_size = cast(f64::from(self.lr) / bias_correction1);
        let (one_minus_b1, b2, one_minus_b2) = (cast(1.0 - BETA1), cast(BETA2), cast(1.0 - BETA2));
        let (bc2_sqrt, eps) = (cast(bias_correction2_sqrt), cast(EPS));
        for (((p, &g), m), v) in params.iter_mut().zip(g).zip(&mut self.m).zip(&mut self.v) {
            // PyTorch: exp_avg.lerp_(grad, 1 - beta1), which for weight < 0.5 is m + w (g - m).
            *m = *m + one_minus_b1 * (g - *m);
            *v = *v * b2 + one_minus_b2 * g * g;
            let denom = v.sqrt() / bc2_sqrt + eps;
            *p = *p - step_size * (*m / denom);
        }
    }
}

/// Step schedule: `base_lr · 0.5^(iteration / halve_every)` (integer division), i.e. the rate
/// halves after every `halve_every` iterations. `halve_every = 0` means never halve.
pub fn step_lr(base_lr: f32, iteration: usize, halve_every: usize) -> f32 {
    if halve_every == 0 {
        return base_lr;
    }
    // Past 2^-200 every f32 is zero anyway; the clamp keeps powi's exponent in range.
    let halvings = (iteration / halve_every).min(200) as i32;
    (f64::from(base_lr) * 0.5f64.powi(halvings)) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1-input, 1-output linear network: parameters are [w, b].
    fn two_parameter_net(w: f64, b: f64) -> Mlp<f64> {
        Mlp { dims: vec![1, 1], params: vec![w, b], negative_slope: 0.0 }
    }

    fn grads_of(mlp: &Mlp<f64>, values: [f64; 2]) -> Gradients<f64> {
        let mut g = Gradients::zeros_like(mlp);
        g.values_mut().copy_from_slice(&values);
        g
    }

    #[test]
    fn adam_matches_a_hand_computed_two_step_reference() {
        let mut mlp = two_parameter_net(1.0, -2.0);
        let mut adam = Adam::new(&mlp, 0.1);
        let lr = f64::from(0.1_f32); // the rate is an f32, as in the fitting loop

        // Step 1, gradients (0.5, 0): m = 0.1 g = (0.05, 0), v = 0.001 g² = (0.00025, 0);
        // m_hat = m / 0.1 = (0.5, 0), sqrt(v_hat) = sqrt(v / 0.001) = (0.5, 0).
        // w -= lr · 0.5 / (0.5 + 1e-8); b has m = 0 and does not move.
        let g = grads_of(&mlp, [0.5, 0.0]);
        adam.step(&mut mlp, &g);
        let w1 = 1.0 - lr * 0.5 / (0.5 + 1e-8);
        assert!((mlp.params[0] - w1).abs() < 1e-15, "{} vs {w1}", mlp.params[0]);
        assert_eq!(mlp.params[1], -2.0);
        // Adam's first step moves by ~lr whatever the gradient's size.
        assert!((1.0 - mlp.params[0] - lr).abs() < 1e-8);

        // Step 2, gradients (-0.25, 3):
        // w: m = 0.9·0.05 + 0.1·(-0.25) = 0.02, v = 0.999·0.00025 + 0.001·0.0625 = 0.00031225,
        //    bias corrections 1 - 0.9² = 0.19 and 1 - 0.999² = 0.001999,
        //    w -= (lr / 0.19) · 0.02 / (sqrt(0.00031225) / sqrt(0.001999) + 1e-8).
        // b: m = 0.3, v = 0.009 → b -= (lr / 0.19) · 0.3 / (sqrt(0.009) / sqrt(0.001999) + 1e-8).
        let g = grads_of(&mlp, [-0.25, 3.0]);
        adam.step(&mut mlp, &g);
        let w2 = w1 - (lr / 0.19) * 0.02 / (0.00031225_f64.sqrt() / 0.001999_f64.sqrt() + 1e-8);
        let b2 = -2.0 - (lr / 0.19) * 0.3 / (0.009_f64.sqrt() / 0.001999_f64.sqrt() + 1e-8);
        // The reference and the implementation round differently (lerp form, β powers): a few ulps.
        assert!((mlp.params[0] - w2).abs() < 1e-14, "{} vs {w2}", mlp.params[0]);
        assert!((mlp.params[1] - b2).abs() < 1e-14, "{} vs {b2}", mlp.params[1]);
        // Numbers written out (w2 ≈ 0.873366, b2 ≈ -2.074414, from the formulas above) so a formula slip above shows too.
        assert!((w2 - 0.873_366_3).abs() < 1e-6, "{w2}");
        assert!((b2 + 2.074_413_7).abs() < 1e-6, "{b2}");
        assert_eq!(adam.steps(), 2);
    }

    #[test]
    fn adam_in_f32_follows_the_f64_trajectory() {
        let mut m32 = Mlp::<f32> { dims: vec![1, 1], params: vec![0.3, 0.7], negative_slope: 0.0 };
        let mut m64 = m32.cast::<f64>();
        let mut a32 = Adam::new(&m32, 0.01);
        let mut a64 = Adam::new(&m64, 0.01);
        for k in 0..20 {
            let g = [((k as f64) * 0.7).sin(), 0.1 * ((k as f64) * 1.3).cos()];
            let mut g64 = Gradients::zeros_like(&m64);
            g64.values_mut().copy_from_slice(&g);
            let mut g32 = Gradients::zeros_like(&m32);
            g32.values_mut().copy_from_slice(&[g[0] as f32, g[1] as f32]);
            a32.step(&mut m32, &g32);
            a64.step(&mut m64, &g64);
        }
        // 20 steps of size ≤ lr = 0.01, each with f32 relative rounding ~1e-7: drift ≪ 1e-5.
        for (a, b) in m32.params.iter().zip(&m64.params) {
            assert!((f64::from(*a) - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn set_lr_changes_the_step_size_only() {
        let mut a = two_parameter_net(0.0, 0.0);
        let mut b = a.clone();
        let mut opt_a = Adam::new(&a, 0.1);
        let mut opt_b = Adam::new(&b, 0.1);
        opt_b.set_lr(0.05);
        assert_eq!(opt_b.lr(), 0.05);
        let g = grads_of(&a, [1.0, -1.0]);
        opt_a.step(&mut a, &g);
        opt_b.step(&mut b, &g);
        // Same moments, so the update scales exactly with the rate (up to rounding).
        for (x, y) in a.params.iter().zip(&b.params) {
            assert!((x * f64::from(0.05_f32) / f64::from(0.1_f32) - y).abs() < 1e-15);
        }
    }

    #[test]
    fn step_lr_halves_every_period() {
        assert_eq!(step_lr(0.003, 0, 500), 0.003);
        assert_eq!(step_lr(0.003, 499, 500), 0.003);
        assert_eq!(step_lr(0.003, 500, 500), 0.0015);
        assert_eq!(step_lr(0.003, 999, 500), 0.0015);
        assert_eq!(step_lr(0.003, 1000, 500), 0.00075);
        assert_eq!(step_lr(1.0, 3, 1), 0.125);
        assert_eq!(step_lr(0.003, 10_000, 0), 0.003);
        assert_eq!(step_lr(1.0, usize::MAX, 1), 0.0);
    }
}
