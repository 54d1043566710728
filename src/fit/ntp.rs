//! NTP and MBNT: one trajectory network for the whole sequence (method.md section 3).
//!
//! The network maps a point observed at frame t to the velocities v_0..v_{T-2} of its
//! trajectory; positions are running sums of them. Each iteration draws reference frames and
//! adds up, per frame, the truncated Chamfer terms to the neighbouring frames, the three
//! cycle-consistency terms and (MBNT) the multi-body rigidity of the frame's clusters projected
//! to the first and last frames.

use std::ops::ControlFlow;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use std::time::Instant;

use super::checkpoint::{Checkpoints, Scalars, TrajectoryState, fingerprint};
use super::prepare::{PointSet, PreparedFrame};
use super::rigidity::ClusterRigidity;
use super::{FitError, LossTerms, PhaseTimes, Progress, ValidFitParams};
use crate::geometry::Point;
use crate::losses::chamfer::{ChamferScratch, truncated_chamfer};
use crate::losses::cycle::mean_squared_difference;
use crate::model::LossCurve;
use crate::model::encoding::{encode_points, input_width};
use crate::nn::adam::step_lr;
use crate::nn::{Adam, Gradients, Mlp, Workspace};

/// Layer widths of the trajectory MLP for T frames: input, hidden layers, 3 (T - 1) outputs.
pub fn trajectory_dims(frames: usize, params: &ValidFitParams) -> Vec<usize> {
    let mut dims = vec![input_width(frames)];
    dims.extend(std::iter::repeat_n(params.hidden_width, params.hidden_layers));
    dims.push(3 * (frames - 1));
    dims
}

/// The outcome of a trajectory fit.
pub struct TrajectoryFit {
    /// The best-validation checkpoint.
    pub mlp: Mlp<f32>,
    /// Iterations run.
    pub iterations: usize,
    /// Iteration whose validation selected the checkpoint.
    pub best_iteration: usize,
    /// Its validation loss.
    pub best_validation_loss: f64,
    /// Where the time went (of this run: a fit that went on from a checkpoint counts from it).
    pub times: PhaseTimes,
    /// The loss curve of every iteration, those before a checkpoint this run went on from too.
    pub losses: LossCurve,
}

/// Reusable buffers of one reference-frame evaluation; sized on first use, then reused.
#[derive(Default)]
struct Scratch {
    input: Vec<f32>,
    velocities: Vec<f32>,
    grad_velocities: Vec<f32>,
    other_velocities: Vec<f32>,
    grad_other: Vec<f32>,
    grad_input: Vec<f32>,
    /// Rows of the reference frame the cycle terms use, their points, velocities and gradient.
    cycle_index: Vec<usize>,
    cycle_points: Vec<Point>,
    cycle_velocities: Vec<f32>,
    cycle_grad: Vec<f32>,
    moved: Vec<Point>,
    grad_moved: Vec<Point>,
    primary: Workspace<f32>,
    secondary: Workspace<f32>,
    chamfer: ChamferScratch,
    rigidity: ClusterRigidity,
    times: PhaseTimes,
    /// Fewest live hidden units of a layer on frame 0's last validation pass.
    fewest_live_units: Option<usize>,
}

/// Everything an iteration reads: prepared frames and the fixed parameters.
struct Problem<'a> {
    frames: &'a [PreparedFrame],
    params: &'a ValidFitParams,
    rigidity: bool,
    /// Multiply-adds of one MLP row: the sum of in x out over layers.
    macs_per_row: f64,
}

impl Problem<'_> {
    fn len(&self) -> usize {
        self.frames.len()
    }

    /// The point set of frame `k` an evaluation uses: part 0 when validating (a fixed subset),
    /// a random part otherwise (the whole frame when frames are not split).
    fn pick<'f>(&'f self, k: usize, validation: bool, rng: &mut ChaCha8Rng) -> &'f PointSet {
        let frame = &self.frames[k];
        if validation || frame.part_count() == 1 {
            frame.part(0)
        } else {
            frame.part(rng.random_range(0..frame.part_count()))
        }
    }

    /// Loss terms of reference frame `t`; adds their gradients into `grads`. The multi-body
    /// gradient is scaled by `rigidity_ramp` (in [0, 1], the warm-up); the terms are not.
    #[allow(clippy::too_many_arguments)]
    fn reference_frame(
        &self,
        mlp: &Mlp<f32>,
        t: usize,
        validation: bool,
        rigidity_ramp: f32,
        grads: &mut Gradients<f32>,
        s: &mut Scratch,
        rng: &mut ChaCha8Rng,
    ) -> LossTerms {
        let frames = self.len();
        let steps = frames - 1;
        let width = 3 * steps;
        let source = self.pick(t, validation, rng);
        let x = &source.points;
        let n = x.len();

        let clock = Instant::now();
        encode_points(x, t as f64, frames, &mut s.input);
        let out = mlp.forward(&s.input, n, &mut s.primary);
        s.times.mlp_forward_s += clock.elapsed().as_secs_f64();
        // A forward pass costs 2 n macs flops; a backward pass twice that (weights and inputs).
        let pass_gflop = 2.0 * n as f64 * self.macs_per_row * 1e-9;
        s.times.mlp_gflop += pass_gflop;
        s.velocities.clear();
        s.velocities.extend_from_slice(out);
        if validation && t == 0 {
            let live = s.primary.live_hidden_units();
            tracing::debug!(?live, "live hidden units per layer on frame 0's validation points");
            s.fewest_live_units = live.into_iter().min();
        }
        s.grad_velocities.clear();
        s.grad_velocities.resize(n * width, 0.0);

        let mut terms = LossTerms::default();
        let trunc = self.params.chamfer_truncation_m2;

        // Chamfer to the next frame (x + v_t) and to the previous one (x - v_{t-1}).
        for (neighbour, step, sign) in [(t + 1, t, 1.0f32), (t.wrapping_sub(1), t.wrapping_sub(1), -1.0)] {
            if neighbour >= frames {
                continue;
            }
            s.moved.clear();
            s.moved.extend(x.iter().enumerate().map(|(i, p)| {
                let v = &s.velocities[i * width + 3 * step..][..3];
                [p[0] + sign * v[0], p[1] + sign * v[1], p[2] + sign * v[2]]
            }));
            s.grad_moved.clear();
            s.grad_moved.resize(n, [0.0; 3]);
            let target = self.pick(neighbour, validation, rng);
            let clock = Instant::now();
            let cd = truncated_chamfer(
                &s.moved,
                &target.points,
                &target.tree,
                trunc,
                1.0,
                &mut s.grad_moved,
                None,
                &mut s.chamfer,
            );
            s.times.nearest_s += clock.elapsed().as_secs_f64();
            terms.chamfer += f64::from(cd);
            for (i, g) in s.grad_moved.iter().enumerate() {
                let gv = &mut s.grad_velocities[i * width + 3 * step..][..3];
                for c in 0..3 {
                    gv[c] += sign * g[c];
                }
            }
        }

        // Cycle consistency: the trajectory predicted from a moved copy must agree. Evaluated on
        // `cycle_sample_points` points drawn with replacement (all points, in order, when 0).
        let middle = frames / 2;
        let cycle_weight = self.params.cycle_weight;
        let cycle_rows = match self.params.cycle_sample_points {
            0 => n,
            c => c.min(n),
        };
        s.cycle_index.clear();
        if cycle_rows == n {
            s.cycle_index.extend(0..n);
        } else if validation {
            // A fixed, evenly spread subset, so validation losses stay comparable.
            s.cycle_index.extend((0..cycle_rows).map(|j| j * n / cycle_rows));
        } else {
            s.cycle_index.extend((0..cycle_rows).map(|_| rng.random_range(0..n)));
        }
        s.cycle_points.clear();
        s.cycle_points.extend(s.cycle_index.iter().map(|&i| x[i]));
        s.cycle_velocities.clear();
        for &i in &s.cycle_index {
            s.cycle_velocities.extend_from_slice(&s.velocities[i * width..][..width]);
        }
        s.cycle_grad.clear();
        s.cycle_grad.resize(cycle_rows * width, 0.0);
        let cycle_gflop = 2.0 * cycle_rows as f64 * self.macs_per_row * 1e-9;
        for target in [(t + 1).min(frames - 1), t.saturating_sub(1), middle] {
            if target == t || cycle_weight == 0.0 {
                // V(x, t) against itself: zero value and gradient, still one of the three terms.
                continue;
            }
            let clock = Instant::now();
            move_points(&s.cycle_points, &s.cycle_velocities, width, t, target, &mut s.moved);
            encode_points(&s.moved, target as f64, frames, &mut s.input);
            s.times.cycle_s += clock.elapsed().as_secs_f64();
            let clock = Instant::now();
            let other = mlp.forward(&s.input, cycle_rows, &mut s.secondary);
            s.other_velocities.clear();
            s.other_velocities.extend_from_slice(other);
            s.times.mlp_forward_s += clock.elapsed().as_secs_f64();
            s.times.mlp_gflop += cycle_gflop;
            let clock = Instant::now();
            s.grad_other.clear();
            s.grad_other.resize(cycle_rows * width, 0.0);
            let value = mean_squared_difference(
                &s.cycle_velocities,
                &s.other_velocities,
                cycle_weight,
                &mut s.cycle_grad,
                &mut s.grad_other,
            );
            terms.cycle += f64::from(value);
            s.grad_input.clear();
            s.grad_input.resize(cycle_rows * input_width(frames), 0.0);
            s.times.cycle_s += clock.elapsed().as_secs_f64();
            let clock = Instant::now();
            mlp.backward(&mut s.secondary, &s.grad_other, grads, Some(&mut s.grad_input[..]));
            s.times.mlp_backward_s += clock.elapsed().as_secs_f64();
            s.times.mlp_gflop += 2.0 * cycle_gflop;
            let clock = Instant::now();
            // The moved points depend on the primary velocities between t and target.
            let in_width = input_width(frames);
            for r in 0..cycle_rows {
                let g = &s.grad_input[r * in_width..][..3];
                add_along_path(&mut s.cycle_grad[r * width..][..width], t, target, g);
            }
            s.times.cycle_s += clock.elapsed().as_secs_f64();
        }
        // Rows drawn twice add up, as the estimate's gradient should.
        for (r, &i) in s.cycle_index.iter().enumerate() {
            let row = &mut s.grad_velocities[i * width..][..width];
            for (g, c) in row.iter_mut().zip(&s.cycle_grad[r * width..][..width]) {
                *g += c;
            }
        }

        // Multi-body rigidity of frame t's clusters projected to the first and last frames.
        let clock = Instant::now();
        if self.rigidity && self.params.rigidity_weight > 0.0 {
            let clusters = &source.clusters;
            if !clusters.is_empty() {
                let weight = rigidity_ramp * self.params.rigidity_weight / clusters.len() as f32;
                let tf = t as f32 / frames as f32;
                let tb = (frames - t) as f32 / frames as f32;
                let d_thr_first = self.params.d_thr_base_m + self.params.d_thr_slope_m * tf;
                let d_thr_last = self.params.d_thr_base_m + self.params.d_thr_slope_m * tb;
                for cluster in clusters {
                    s.rigidity.select(cluster, x, self.params.max_cluster_points, rng);
                    for (target, d_thr) in [(0, d_thr_first), (frames - 1, d_thr_last)] {
                        if target == t {
                            continue; // the projection is the identity: score 1, loss 0
                        }
                        let (velocities, grad_velocities) = (&s.velocities, &mut s.grad_velocities);
                        let moved_of = |i: usize| {
                            let d = displacement(&velocities[i * width..][..width], t, target);
                            [x[i][0] + d[0], x[i][1] + d[1], x[i][2] + d[2]]
                        };
                        let add_grad = |i: usize, g: &Point| {
                            add_along_path(&mut grad_velocities[i * width..][..width], t, target, g);
                        };
                        let power = self.params.power_iterations;
                        let relative = self.params.d_thr_motion_fraction;
                        if let Some(value) = s.rigidity.loss(d_thr, relative, power, weight, moved_of, add_grad) {
                            terms.rigidity += value.loss / clusters.len() as f64;
                        }
                    }
                }
            }
        }
        s.times.multibody_s += clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        mlp.backward(&mut s.primary, &s.grad_velocities, grads, None);
        s.times.mlp_backward_s += clock.elapsed().as_secs_f64();
        s.times.mlp_gflop += 2.0 * pass_gflop;
        terms.total = terms.chamfer
            + f64::from(cycle_weight) * terms.cycle
            + f64::from(self.params.rigidity_weight) * terms.rigidity * f64::from(u8::from(self.rigidity));
        terms
    }
}

/// Displacement from frame `from` to frame `to` along one point's velocity row (3 (T-1)).
pub(crate) fn displacement(row: &[f32], from: usize, to: usize) -> Point {
    let (lo, hi, sign) = if to >= from { (from, to, 1.0) } else { (to, from, -1.0) };
    let mut d = [0f32; 3];
    for k in lo..hi {
        for c in 0..3 {
            d[c] += row[3 * k + c];
        }
    }
    d.map(|v| sign * v)
}

/// Adds the gradient `g` of a point moved from `from` to `to` into the velocities it summed.
fn add_along_path(grad_row: &mut [f32], from: usize, to: usize, g: &[f32]) {
    let (lo, hi, sign) = if to >= from { (from, to, 1.0) } else { (to, from, -1.0) };
    for k in lo..hi {
        for c in 0..3 {
            grad_row[3 * k + c] += sign * g[c];
        }
    }
}

/// Moves every point of frame `from` to frame `to` with its predicted velocities.
fn move_points(x: &[Point], velocities: &[f32], width: usize, from: usize, to: usize, out: &mut Vec<Point>) {
    out.clear();
    out.extend(x.iter().enumerate().map(|(i, p)| {
        let d = displacement(&velocities[i * width..][..width], from, to);
        [p[0] + d[0], p[1] + d[1], p[2] + d[2]]
    }));
}

/// Identifies a trajectory fit for its checkpoints: parameters, method and every frame's
/// validation points, bit for bit.
fn fit_fingerprint(frames: &[PreparedFrame], params: &ValidFitParams, rigidity: bool) -> u64 {
    let params_json = serde_json::to_vec(params).expect("plain data always serialises");
    let points: Vec<u8> = frames
        .iter()
        .flat_map(|f| {
            let part = &f.part(0).points;
            (part.len() as u64).to_le_bytes().into_iter().chain(part.iter().flatten().flat_map(|c| c.to_le_bytes()))
        })
        .collect();
    fingerprint(&[&params_json, &[u8::from(rigidity)], &points])
}

/// Fits a trajectory network to prepared frames. `rigidity` selects MBNT (true) or NTP.
///
/// At the start of a validation iteration for which `checkpoints` says a checkpoint is due,
/// the whole state of the fit is kept there; a fit that finds a checkpoint of the same fit
/// there goes on from it, and ends with the same bits as one that never stopped.
pub fn fit_trajectory(
    frames: &[PreparedFrame],
    params: &ValidFitParams,
    rigidity: bool,
    checkpoints: &mut dyn Checkpoints,
    on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
) -> Result<TrajectoryFit, FitError> {
    let t_count = frames.len();
    let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
    let mut mlp = Mlp::<f32>::new(&trajectory_dims(t_count, params), &mut rng);
    mlp.set_negative_slope(params.hidden_negative_slope);
    if params.zero_output_init {
        mlp.zero_output_layer();
    }
    let mut adam = Adam::new(&mlp, params.learning_rate);
    let mut grads = Gradients::zeros_like(&mlp);
    let mut scratch = Scratch::default();
    let dims = mlp.dims();
    let macs_per_row = dims.windows(2).map(|w| (w[0] * w[1]) as f64).sum();
    let problem = Problem { frames, params, rigidity, macs_per_row };
    let mut best: Option<(f64, usize, Mlp<f32>)> = None;
    let mut references = Vec::with_capacity(t_count.max(params.reference_frames));
    let mut validations_since_best = 0;
    let mut restarts = 0;
    // Halves at each collapse restart; multiplies the scheduled learning rate.
    let mut lr_scale = 1.0f32;
    let mut losses = LossCurve::default();
    let mut first_iteration = 0;
    let fit_id = fit_fingerprint(frames, params, rigidity);
    if let Some(bytes) = checkpoints.latest() {
        match TrajectoryState::from_bytes(&bytes) {
            Ok(state)
                if state.scalars.fingerprint == fit_id
                    && state.mlp.dims() == dims
                    && state.scalars.next_iteration < params.iterations
                    && state.scalars.rng_word_pos.parse::<u128>().is_ok() =>
            {
                let s = state.scalars;
                rng.set_word_pos(s.rng_word_pos.parse::<u128>().expect("checked above"));
                mlp = state.mlp;
                adam = state.adam;
                best = match (s.best, state.best_mlp) {
                    (Some((loss, iteration)), Some(net)) => Some((loss, iteration, net)),
                    _ => None,
                };
                validations_since_best = s.validations_since_best;
                restarts = s.restarts;
                lr_scale = s.lr_scale;
                losses = s.losses;
                first_iteration = s.next_iteration;
                tracing::info!(iteration = first_iteration, "going on from a checkpoint");
                checkpoints.resumed(first_iteration);
            }
            Ok(_) => tracing::warn!("a checkpoint of another fit was found and ignored"),
            Err(e) => tracing::warn!(error = %e, "a damaged checkpoint was found and ignored"),
        }
    }
    let mut iterations_run = first_iteration;
    let started = Instant::now();

    for iteration in first_iteration..params.iterations {
        let validation = iteration % params.validate_every == 0;
        if validation && iteration > first_iteration && checkpoints.due() {
            let state = TrajectoryState {
                scalars: Scalars {
                    fingerprint: fit_id,
                    next_iteration: iteration,
                    adam_steps: adam.steps(),
                    adam_lr: adam.lr(),
                    rng_word_pos: rng.get_word_pos().to_string(),
                    best: best.as_ref().map(|(loss, at, _)| (*loss, *at)),
                    validations_since_best,
                    restarts,
                    lr_scale,
                    losses: losses.clone(),
                },
                mlp: mlp.clone(),
                adam: adam.clone(),
                best_mlp: best.as_ref().map(|(_, _, net)| net.clone()),
            };
            checkpoints.keep(&state.to_bytes());
        }
        adam.set_lr(lr_scale * step_lr(params.learning_rate, iteration, params.lr_halve_every));
        references.clear();
        if validation {
            references.extend(0..t_count);
        } else {
            references.extend((0..params.reference_frames).map(|_| rng.random_range(0..t_count)));
        }
        grads.fill_zero();
        // The validation loss keeps the full weight, so checkpoints stay comparable.
        let ramp = match params.rigidity_warmup_iterations {
            0 => 1.0,
            warmup => (iteration as f32 / warmup as f32).min(1.0),
        };
        let mut sum = LossTerms::default();
        let mut validation_terms = LossTerms::default();
        for &t in &references {
            let terms = problem.reference_frame(&mlp, t, validation, ramp, &mut grads, &mut scratch, &mut rng);
            if !terms.total.is_finite() {
                return Err(FitError::Diverged { iteration, loss: terms.total });
            }
            if t + 1 < t_count {
                validation_terms.chamfer += terms.chamfer;
                validation_terms.cycle += terms.cycle;
                validation_terms.rigidity += terms.rigidity;
                validation_terms.total += terms.total;
            }
            sum.chamfer += terms.chamfer;
            sum.cycle += terms.cycle;
            sum.rigidity += terms.rigidity;
            sum.total += terms.total;
        }
        if validation {
            // Measured before this iteration's update: the checkpoint is the current weights.
            let frames = (t_count - 1) as f64;
            validation_terms = LossTerms {
                chamfer: validation_terms.chamfer / frames,
                cycle: validation_terms.cycle / frames,
                rigidity: validation_terms.rigidity / frames,
                total: validation_terms.total / frames,
            };
            let loss = validation_terms.total;
            let collapsed = scratch.fewest_live_units == Some(0);
            // Without a checkpoint (a network dead from iteration 0) there is nothing to go back to.
            let restart_from = best.as_ref().filter(|_| collapsed && restarts < params.collapse_restarts);
            if let Some((_, best_iteration, best_mlp)) = restart_from {
                restarts += 1;
                lr_scale *= 0.5;
                tracing::info!(
                    iteration,
                    best_iteration,
                    restarts,
                    lr_scale,
                    "network collapsed: back to the best checkpoint"
                );
                mlp = best_mlp.clone();
                adam = Adam::new(&mlp, lr_scale * step_lr(params.learning_rate, iteration, params.lr_halve_every));
                // This iteration's gradients belong to the collapsed weights.
                grads.fill_zero();
            } else if best.as_ref().is_none_or(|(b, _, _)| loss < *b) {
                best = Some((loss, iteration, mlp.clone()));
                validations_since_best = 0;
            } else if !rigidity || iteration >= params.rigidity_warmup_iterations {
                // While the multi-body weight still ramps up the objective itself changes, so
                // patience only counts validations from the end of the warm-up on.
                validations_since_best += 1;
            }
        }
        let clock = Instant::now();
        adam.step(&mut mlp, &grads);
        scratch.times.optimiser_s += clock.elapsed().as_secs_f64();
        iterations_run = iteration + 1;
        let r = references.len() as f64;
        let progress = Progress {
            iteration: iteration + 1,
            iterations: params.iterations,
            loss: LossTerms {
                chamfer: sum.chamfer / r,
                cycle: sum.cycle / r,
                rigidity: sum.rigidity / r,
                total: sum.total / r,
            },
            best_validation_loss: best.as_ref().map(|b| b.0),
            validation_loss: validation.then_some(validation_terms),
            fewest_live_units: if validation { scratch.fewest_live_units } else { None },
            rigid_tracks: None,
            window: None,
        };
        losses.push(progress.iteration, progress.loss, progress.validation_loss);
        tracing::debug!(iteration, loss = progress.loss.total, "trajectory iteration");
        if on_progress(&progress).is_break() {
            return Err(FitError::Cancelled { iteration: iteration + 1 });
        }
        if params.validation_patience > 0 && validations_since_best >= params.validation_patience {
            tracing::debug!(iteration, "validation loss stopped improving");
            break;
        }
    }
    let (best_validation_loss, best_iteration, mlp) = best.expect("iteration 0 always validates");
    let mut times = scratch.times;
    times.total_s = started.elapsed().as_secs_f64();
    Ok(TrajectoryFit { mlp, iterations: iterations_run, best_iteration, best_validation_loss, times, losses })
}
