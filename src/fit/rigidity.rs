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
    pub(crate) fn loss(
        &mut self,
        d_thr_m: f32,
        power_iterations: usize,
        weight: f32,
        moved_of: impl Fn(usize) -> Point,
        mut add_grad: impl FnMut(usize, &Point),
    ) -> Option<MultibodyValue> {
        self.moved.clear();
        self.moved.extend(self.members.iter().map(|&i| moved_of(i)));
        self.grad.clear();
        self.grad.resize(self.members.len(), [0.0; 3]);
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
