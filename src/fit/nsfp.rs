//! NSFP and MBNSF: a forward-flow and a backward-flow network per frame pair, fitted pair by
//! pair with early stopping and warm start (method.md section 4). Trajectories chain the pair
//! flows by forward Euler (see `trajectory`).

use std::ops::ControlFlow;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::prepare::{PointSet, PreparedFrame};
use super::rigidity::ClusterRigidity;
use super::{FitError, LossTerms, Progress, ValidFitParams};
use crate::geometry::Point;
use crate::losses::chamfer::{ChamferScratch, truncated_chamfer};
use crate::nn::{Adam, Gradients, Mlp, Workspace};

/// Layer widths of a pair-flow MLP: 3 inputs, hidden layers, 3 outputs.
pub fn flow_dims(params: &ValidFitParams) -> Vec<usize> {
    let mut dims = vec![3];
    dims.extend(std::iter::repeat_n(params.hidden_width, params.hidden_layers));
    dims.push(3);
    dims
}

/// The best forward and backward networks of every pair k -> k+1.
pub struct PairFits {
    /// Forward flow f_k of frame k's points, k = 0..T-2.
    pub forward: Vec<Mlp<f32>>,
    /// Backward flow g_k of points at frame k+1 (y - g_k(y) lies in frame k).
    pub backward: Vec<Mlp<f32>>,
    /// Iterations run per pair (early stopping may end a pair sooner).
    pub iterations_per_pair: Vec<usize>,
}

/// Buffers reused across iterations and pairs.
#[derive(Default)]
struct Scratch {
    input: Vec<f32>,
    flow: Vec<f32>,
    grad_flow: Vec<f32>,
    back_flow: Vec<f32>,
    grad_back: Vec<f32>,
    grad_input: Vec<f32>,
    moved: Vec<Point>,
    returned: Vec<Point>,
    grad_moved: Vec<Point>,
    grad_returned: Vec<Point>,
    ws_forward: Workspace<f32>,
    ws_backward: Workspace<f32>,
    chamfer: ChamferScratch,
    rigidity: ClusterRigidity,
}

/// One loss evaluation of pair (p1 -> p2) with its gradients in `grads_f`, `grads_g`.
#[allow(clippy::too_many_arguments)]
fn pair_loss(
    f: &Mlp<f32>,
    g: &Mlp<f32>,
    p1: &PointSet,
    p2: &PointSet,
    params: &ValidFitParams,
    rigidity: bool,
    grads_f: &mut Gradients<f32>,
    grads_g: &mut Gradients<f32>,
    s: &mut Scratch,
    rng: &mut ChaCha8Rng,
) -> LossTerms {
    let x = &p1.points;
    let n = x.len();
    let trunc = params.chamfer_truncation_m2;
    s.input.clear();
    s.input.extend_from_slice(x.as_flattened());
    let out = f.forward(&s.input, n, &mut s.ws_forward);
    s.flow.clear();
    s.flow.extend_from_slice(out);
    s.grad_flow.clear();
    s.grad_flow.resize(3 * n, 0.0);

    // Forward term: CD(x + f(x), P2).
    s.moved.clear();
    s.moved.extend(x.iter().zip(s.flow.chunks_exact(3)).map(|(p, v)| [p[0] + v[0], p[1] + v[1], p[2] + v[2]]));
    s.grad_moved.clear();
    s.grad_moved.resize(n, [0.0; 3]);
    let forward_cd =
        truncated_chamfer(&s.moved, &p2.points, &p2.tree, trunc, 1.0, &mut s.grad_moved, None, &mut s.chamfer);

    // Backward term: CD(y - g(y), P1) with y = x + f(x); y depends on f, so gradients of the
    // backward term reach f as well.
    let y_flat = s.moved.as_flattened();
    let back = g.forward(y_flat, n, &mut s.ws_backward);
    s.back_flow.clear();
    s.back_flow.extend_from_slice(back);
    s.returned.clear();
    s.returned
        .extend(s.moved.iter().zip(s.back_flow.chunks_exact(3)).map(|(p, v)| [p[0] - v[0], p[1] - v[1], p[2] - v[2]]));
    s.grad_returned.clear();
    s.grad_returned.resize(n, [0.0; 3]);
    let backward_cd =
        truncated_chamfer(&s.returned, &p1.points, &p1.tree, trunc, 1.0, &mut s.grad_returned, None, &mut s.chamfer);
    s.grad_back.clear();
    s.grad_back.extend(s.grad_returned.iter().flat_map(|g| [-g[0], -g[1], -g[2]]));
    s.grad_input.clear();
    s.grad_input.resize(3 * n, 0.0);
    g.backward(&mut s.ws_backward, &s.grad_back, grads_g, Some(&mut s.grad_input[..]));
    for i in 0..n {
        for c in 0..3 {
            // d(returned)/dy = I - dg/dy: the identity part plus g's input gradient.
            s.grad_flow[3 * i + c] += s.grad_moved[i][c] + s.grad_returned[i][c] + s.grad_input[3 * i + c];
        }
    }

    let mut terms = LossTerms { chamfer: f64::from(forward_cd + backward_cd), ..LossTerms::default() };
    if rigidity && params.rigidity_weight > 0.0 && !p1.clusters.is_empty() {
        let weight = params.rigidity_weight / p1.clusters.len() as f32;
        for cluster in &p1.clusters {
            s.rigidity.select(cluster, x, params.max_cluster_points, rng);
            let (moved, grad_flow) = (&s.moved, &mut s.grad_flow);
            let add_grad = |i: usize, g: &Point| {
                for (acc, v) in grad_flow[3 * i..3 * i + 3].iter_mut().zip(g) {
                    *acc += v;
                }
            };
            let power = params.power_iterations;
            if let Some(value) = s.rigidity.loss(params.pair_d_thr_m, 0.0, power, weight, |i| moved[i], add_grad) {
                terms.rigidity += value.loss / p1.clusters.len() as f64;
            }
        }
    }
    f.backward(&mut s.ws_forward, &s.grad_flow, grads_f, None);
    terms.total = terms.chamfer + f64::from(params.rigidity_weight) * terms.rigidity * f64::from(u8::from(rigidity));
    terms
}

/// Fits every pair in turn. `rigidity` selects MBNSF (true) or NSFP. Pair k+1 starts from pair
/// k's final weights and optimiser state; each pair's result is its best-loss weights.
pub fn fit_pairs(
    frames: &[PreparedFrame],
    params: &ValidFitParams,
    rigidity: bool,
    on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
) -> Result<PairFits, FitError> {
    let pairs = frames.len() - 1;
    let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
    let dims = flow_dims(params);
    let mut f = Mlp::<f32>::new(&dims, &mut rng);
    let mut g = Mlp::<f32>::new(&dims, &mut rng);
    if params.zero_output_init {
        f.zero_output_layer();
        g.zero_output_layer();
    }
    let mut adam_f = Adam::new(&f, params.learning_rate);
    let mut adam_g = Adam::new(&g, params.learning_rate);
    let mut grads_f = Gradients::zeros_like(&f);
    let mut grads_g = Gradients::zeros_like(&g);
    let mut scratch = Scratch::default();
    let mut result = PairFits { forward: Vec::new(), backward: Vec::new(), iterations_per_pair: Vec::new() };
    let total_iterations = params.iterations * pairs;
    let mut done = 0;

    for k in 0..pairs {
        // Fast mode: each iteration fits a random part of each frame (the whole frame otherwise).
        let pick = |frame: &PreparedFrame, rng: &mut ChaCha8Rng| -> usize {
            if frame.part_count() == 1 { 0 } else { rng.random_range(0..frame.part_count()) }
        };
        let mut best = (f64::INFINITY, f.clone(), g.clone());
        let mut since_best = 0;
        let mut ran = 0;
        for iteration in 0..params.iterations {
            grads_f.fill_zero();
            grads_g.fill_zero();
            let (a, b) = (pick(&frames[k], &mut rng), pick(&frames[k + 1], &mut rng));
            let (p1, p2) = (frames[k].part(a), frames[k + 1].part(b));
            let terms = pair_loss(&f, &g, p1, p2, params, rigidity, &mut grads_f, &mut grads_g, &mut scratch, &mut rng);
            if !terms.total.is_finite() {
                return Err(FitError::Diverged { iteration: done, loss: terms.total });
            }
            // The loss belongs to the weights before this update: those are the checkpoint.
            if terms.total < best.0 - f64::from(params.early_stop_min_delta) {
                best = (terms.total, f.clone(), g.clone());
                since_best = 0;
            } else {
                since_best += 1;
            }
            adam_f.step(&mut f, &grads_f);
            adam_g.step(&mut g, &grads_g);
            done += 1;
            ran = iteration + 1;
            let progress = Progress {
                iteration: done,
                iterations: total_iterations,
                loss: terms,
                best_validation_loss: Some(best.0),
                validation_loss: None,
                fewest_live_units: None,
                rigid_tracks: None,
                window: None,
            };
            if on_progress(&progress).is_break() {
                return Err(FitError::Cancelled { iteration: done });
            }
            if since_best >= params.early_stop_patience {
                break;
            }
        }
        // Early stopping leaves iterations unused; the progress total stays an upper bound.
        tracing::debug!(pair = k, iterations = ran, loss = best.0, "pair fitted");
        result.forward.push(best.1);
        result.backward.push(best.2);
        result.iterations_per_pair.push(ran);
    }
    Ok(result)
}
