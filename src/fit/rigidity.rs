//! The multi-body term of one cluster as both fitting loops use it: draw the members evaluated
//! this time (subsampling large clusters), gather their points and moved copies, score them, and
//! hand each member's gradient back to the loop.

use rand::Rng;

use crate::geometry::Point;
use crate::losses::multibody::{MultibodyScratch, MultibodyValue, multibody_loss, subsample_indices};

/// Buffers of one cluster evaluation, reused across clusters and iterations.
#[derive(Default)]
pub(crate) struct ClusterRigidity {
    multibody: MultibodyScratch,
    subsample: Vec<u32>,
    /// Frame indices of the selected members.
    members: Vec<usize>,
    points: Vec<Point>,
    moved: Vec<Point>,
    grad: Vec<Point>,
}

impl ClusterRigidity {
    /// Selects the members of `cluster` (indices into `points`) evaluated this time: all of
    /// them, or `max_points` drawn at random.
    pub(crate) fn select(&mut self, cluster: &[u32], points: &[Point], max_points: usize, rng: &mut impl Rng) {
        subsample_indices(cluster.len(), max_points, rng, &mut self.subsample);
        self.members.clear();
        self.members.extend(self.subsample.iter().map(|&j| cluster[j as usize] as usize));
        self.points.clear();
        self.points.extend(self.members.iter().map(|&i| points[i]));
    }

    /// Multi-body loss of the selected members moved to `moved_of(i)`; `add_grad(i, g)` receives
    /// each member's weighted gradient. `None` when the cluster is too small to score.
    ///
    /// The threshold is `d_thr_m` plus `motion_fraction` times the length of the members' mean
    /// displacement, taken as a constant of this evaluation (not differentiated), so a body that
    /// travels far may deviate in proportion (see `FitParams::d_thr_motion_fraction`).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn loss(
        &mut self,
        d_thr_m: f32,
        motion_fraction: f32,
        power_iterations: usize,
        weight: f32,
        moved_of: impl Fn(usize) -> Point,
        mut add_grad: impl FnMut(usize, &Point),
    ) -> Option<MultibodyValue> {
        self.moved.clear();
        self.moved.extend(self.members.iter().map(|&i| moved_of(i)));
        self.grad.clear();
        self.grad.resize(self.members.len(), [0.0; 3]);
        let d_thr_m = d_thr_m + motion_fraction * mean_displacement_m(&self.points, &self.moved);
        let value = multibody_loss(
            &self.points,
            &self.moved,
            d_thr_m,
            power_iterations,
            weight,
            &mut self.grad,
            &mut self.multibody,
        )?;
        for (&i, g) in self.members.iter().zip(&self.grad) {
            add_grad(i, g);
        }
        Some(value)
    }
}

/// Length of the mean displacement from `points` to `moved` (same order), m; 0 when empty.
pub(crate) fn mean_displacement_m(points: &[Point], moved: &[Point]) -> f32 {
    if points.is_empty() {
        return 0.0;
    }
    let mut sum = [0f64; 3];
    for (p, m) in points.iter().zip(moved) {
        for c in 0..3 {
            sum[c] += f64::from(m[c] - p[c]);
        }
    }
    let n = points.len() as f64;
    (sum.iter().map(|s| (s / n) * (s / n)).sum::<f64>().sqrt()) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn mean_displacement_is_the_length_of_the_mean_shift() {
        let points = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
        let shifted: Vec<Point> = points.iter().map(|p| [p[0] + 3.0, p[1] + 4.0, p[2]]).collect();
        assert!((mean_displacement_m(&points, &shifted) - 5.0).abs() < 1e-6);
        // Opposite moves cancel: a spin about the centroid is no displacement.
        let spun = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]];
        let base = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]];
        assert!(mean_displacement_m(&base, &spun).abs() < 1e-6);
        assert_eq!(mean_displacement_m(&[], &[]), 0.0);
    }

    /// A bent cluster: the front half shifted 0.3 m further than the back half along x.
    fn bent(shift_m: f32) -> (Vec<Point>, Vec<Point>) {
        let points: Vec<Point> = (0..40).map(|i| [i as f32 * 0.1, (i % 4) as f32 * 0.3, 0.0]).collect();
        let moved = points.iter().map(|p| [p[0] + shift_m + if p[0] >= 2.0 { 0.3 } else { 0.0 }, p[1], p[2]]).collect();
        (points, moved)
    }

    fn loss_of(points: &[Point], moved: &[Point], motion_fraction: f32) -> f64 {
        let mut r = ClusterRigidity::default();
        let members: Vec<u32> = (0..points.len() as u32).collect();
        r.select(&members, points, 1000, &mut ChaCha8Rng::seed_from_u64(1));
        r.loss(0.1, motion_fraction, 10, 1.0, |i| moved[i], |_, _| {}).unwrap().loss
    }

    #[test]
    fn the_motion_fraction_loosens_the_threshold_of_travelling_clusters_only() {
        // The same 0.3 m bend costs the same standing still whatever the fraction...
        let (points, still) = bent(0.0);
        let at_rest = loss_of(&points, &still, 0.0);
        assert!(at_rest > 0.1, "{at_rest}");
        assert!((loss_of(&points, &still, 0.05) - at_rest).abs() < 0.05 * at_rest);
        // ...and much less on a body that travelled 20 m (threshold 0.1 + 0.05 x 20 m = 1.1 m).
        let (points, far) = bent(20.0);
        assert!((loss_of(&points, &far, 0.0) - at_rest).abs() < 1e-3, "a translation alone changes nothing");
        let loosened = loss_of(&points, &far, 0.05);
        assert!(loosened < 0.2 * at_rest, "{loosened} vs {at_rest}");
    }
}
