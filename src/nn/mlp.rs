//! The multi-layer perceptron: parameters, forward pass, backward pass and their scratch buffers.
//!
//! Layout: layer `l` maps `dims[l]` inputs to `dims[l + 1]` outputs, `y = x·W + b` with `W` stored
//! row-major as `dims[l] × dims[l + 1]` (so a batch is one `N × in` by `in × out` product) followed
//! by `b`. All layers' `W` and `b` sit in one flat vector in layer order; [`Gradients`] and the Adam
//! state use the same layout, which makes the optimiser a single element-wise loop.

use rayon::prelude::*;

use super::Scalar;
use super::matmul::{MatMut, MatRef, Threads, matmul};

/// Rows per chunk of the element-wise passes. Fixed (not derived from the thread count) so that
/// the bias-gradient partial sums, and hence the results, do not depend on the machine.
const CHUNK_ROWS: usize = 512;

/// Rows per chunk of the weight-gradient sums (long enough for an efficient product, short enough
/// to split a 10k-row batch between threads).
const DW_CHUNK_ROWS: usize = 4096;

/// A dense network `Linear, ReLU, ..., Linear` (no activation after the last layer).
///
/// The hidden activation is ReLU, or leaky ReLU (`x` for `x > 0`, `negative_slope · x` otherwise)
/// when [`Mlp::set_negative_slope`] gave it a slope.
#[derive(Clone, PartialEq)]
pub struct Mlp<T> {
    /// Layer widths `[in, hidden.., out]`.
    pub(super) dims: Vec<usize>,
    /// All weights and biases, layer by layer (`W` row-major `in × out`, then `b`).
    pub(super) params: Vec<T>,
    /// Slope of the hidden activation for negative inputs (0 = ReLU).
    pub(super) negative_slope: f32,
}

impl<T> std::fmt::Debug for Mlp<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mlp").field("dims", &self.dims).field("parameters", &self.params.len()).finish()
    }
}

/// Offsets of layer `l`'s weights and bias in the flat parameter vector, for widths `dims`.
fn layer_ranges(dims: &[usize], l: usize) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
    let start: usize = dims.windows(2).take(l).map(|w| w[0] * w[1] + w[1]).sum();
    let (n_in, n_out) = (dims[l], dims[l + 1]);
    let w = start..start + n_in * n_out;
    let b = w.end..w.end + n_out;
    (w, b)
}

/// Number of parameters of a network with widths `dims`, or `None` on overflow.
pub(super) fn parameter_count(dims: &[usize]) -> Option<usize> {
    dims.windows(2).try_fold(0usize, |acc, w| w[0].checked_mul(w[1])?.checked_add(w[1])?.checked_add(acc))
}

impl<T: Scalar> Mlp<T> {
    /// A freshly initialised network with layer widths `dims = [in, hidden.., out]`.
    ///
    /// Initialisation is PyTorch's default for `Linear`: every weight and bias of a layer with
    /// `fan_in` inputs is uniform in `±1/sqrt(fan_in)`. Layers are drawn in order, weights before
    /// biases, so the same seeded `rng` gives the same network.
    ///
    /// # Panics
    /// If `dims` has fewer than two entries or a zero width (a programming error: sizes come from
    /// validated parameters).
    pub fn new(dims: &[usize], rng: &mut impl rand::Rng) -> Self {
        assert!(dims.len() >= 2 && dims.iter().all(|&d| d > 0), "MLP widths must be >= 2 positive entries: {dims:?}");
        let count = parameter_count(dims).expect("MLP parameter count overflows");
        let mut params = Vec::with_capacity(count);
        for w in dims.windows(2) {
            let bound = 1.0 / (w[0] as f64).sqrt();
            for _ in 0..w[0] * w[1] + w[1] {
                let u: f64 = rng.random();
                params.push(T::from((2.0 * u - 1.0) * bound).unwrap_or_else(T::zero));
            }
        }
        Self { dims: dims.to_vec(), params, negative_slope: 0.0 }
    }

    /// Makes the hidden activation a leaky ReLU with this slope for negative inputs (0 = ReLU).
    /// A leaky unit never stops passing gradient, so no layer can die for every input.
    ///
    /// # Panics
    /// If the slope is not in [0, 1) (a programming error: it comes from validated parameters).
    pub fn set_negative_slope(&mut self, slope: f32) {
        assert!((0.0..1.0).contains(&slope), "negative slope must be in [0, 1), got {slope}");
        self.negative_slope = slope;
    }

    /// Slope of the hidden activation for negative inputs (0 = ReLU).
    pub fn negative_slope(&self) -> f32 {
        self.negative_slope
    }

    /// Layer widths `[in, hidden.., out]`.
    pub fn dims(&self) -> Vec<usize> {
        self.dims.clone()
    }

    /// Number of inputs per row.
    pub fn input_dim(&self) -> usize {
        self.dims[0]
    }

    /// Number of outputs per row.
    pub fn output_dim(&self) -> usize {
        self.dims[self.dims.len() - 1]
    }

    /// Number of linear layers.
    pub fn layers(&self) -> usize {
        self.dims.len() - 1
    }

    /// All weights and biases, layer by layer: `W` (row-major `in × out`), then `b`.
    pub fn parameters(&self) -> &[T] {
        &self.params
    }

    /// Mutable view of [`Mlp::parameters`] (for finite differences and loading).
    pub fn parameters_mut(&mut self) -> &mut [T] {
        &mut self.params
    }

    /// Layer `l`'s weights, row-major `dims[l] × dims[l + 1]`.
    ///
    /// # Panics
    /// If `l >= self.layers()`.
    pub fn weights(&self, l: usize) -> &[T] {
        &self.params[layer_ranges(&self.dims, l).0]
    }

    /// Layer `l`'s bias, `dims[l + 1]` values.
    ///
    /// # Panics
    /// If `l >= self.layers()`.
    pub fn bias(&self, l: usize) -> &[T] {
        &self.params[layer_ranges(&self.dims, l).1]
    }

    /// Sets the last layer's weights and bias to zero: the network then outputs zero for every
    /// input, and the first gradient step moves only that layer.
    pub fn zero_output_layer(&mut self) {
        let last = self.layers() - 1;
        let (w, b) = layer_ranges(&self.dims, last);
        self.params[w].fill(T::zero());
        self.params[b].fill(T::zero());
    }

    /// The same network in another float type (values rounded to nearest).
    pub fn cast<U: Scalar>(&self) -> Mlp<U> {
        Mlp {
            dims: self.dims.clone(),
            params: self.params.iter().map(|p| p.to_f64().and_then(U::from).unwrap_or_else(U::nan)).collect(),
            negative_slope: self.negative_slope,
        }
    }

    /// Evaluates the network on `rows` inputs (`input` is row-major `rows × dims[0]`) and returns
    /// the row-major `rows × out` outputs, which live in `ws`.
    ///
    /// The input and every layer's activations are kept in `ws` for [`Mlp::backward`]. Buffers only
    /// grow, so after the largest batch has been seen no call allocates. Products use every thread of
    /// the current rayon pool (run inside a one-thread pool's `install` for a single thread).
    /// Cost: `2·rows·Σ in·out` flops.
    ///
    /// # Panics
    /// If `input.len() != rows * dims[0]`.
    pub fn forward<'w>(&self, input: &[T], rows: usize, ws: &'w mut Workspace<T>) -> &'w [T] {
        let n_in = self.input_dim();
        assert_eq!(input.len(), rows * n_in, "MLP input must be rows × {n_in}");
        ws.prepare(&self.dims, rows);
        ws.acts[0][..input.len()].copy_from_slice(input);
        let layers = self.layers();
        let slope = T::from(self.negative_slope).unwrap_or_else(T::zero);
        for l in 0..layers {
            let (n_in, n_out) = (self.dims[l], self.dims[l + 1]);
            let (w, b) = layer_ranges(&self.dims, l);
            let (w, b, relu) = (MatRef::row_major(&self.params[w], n_in, n_out), &self.params[b], l + 1 < layers);
            let (before, after) = ws.acts.split_at_mut(l + 1);
            let x = &before[l][..rows * n_in];
            let y = &mut after[0][..rows * n_out];
            // Row blocks in parallel, each a single-threaded product followed by bias + ReLU while
            // the block is still in cache.
            y.par_chunks_mut(CHUNK_ROWS * n_out).zip(x.par_chunks(CHUNK_ROWS * n_in)).for_each(|(y, x)| {
                let r = x.len() / n_in;
                matmul(MatMut::row_major(y, r, n_out), MatRef::row_major(x, r, n_in), w, false, Threads::Single);
                add_bias(y, b, relu, slope);
            });
        }
        ws.output()
    }

    /// Back-propagates `grad_output` (dL/d output, row-major `rows × out`) through the activations
    /// stored by the last [`Mlp::forward`] on `ws`.
    ///
    /// Parameter gradients are ADDED to `grads` (several passes accumulate; call
    /// [`Gradients::fill_zero`] between optimiser steps). When `grad_input` is given (`rows × in`)
    /// it is OVERWRITTEN with dL/d input. Per layer: `dW += Xᵀ·dY`, `db += column sums of dY`,
    /// `dX = dY·Wᵀ`, then the ReLU mask of the layer below (zero where its output was not positive,
    /// as PyTorch). Cost: about twice the forward pass.
    ///
    /// # Panics
    /// If `ws` does not hold a forward pass of a network with these widths, or a slice length does
    /// not match (`grad_output`: rows × out, `grad_input`: rows × in, `grads`: this network).
    pub fn backward(
        &self,
        ws: &mut Workspace<T>,
        grad_output: &[T],
        grads: &mut Gradients<T>,
        grad_input: Option<&mut [T]>,
    ) {
        assert!(ws.dims == self.dims, "workspace holds no forward pass of this network");
        assert!(grads.dims == self.dims, "gradients belong to another network shape");
        let rows = ws.rows;
        let n_out = self.output_dim();
        assert_eq!(grad_output.len(), rows * n_out, "grad_output must be rows × {n_out}");
        if let Some(gi) = &grad_input {
            assert_eq!(gi.len(), rows * self.input_dim(), "grad_input must be rows × {}", self.input_dim());
        }
        let layers = self.layers();
        let slope = T::from(self.negative_slope).unwrap_or_else(T::zero);
        let max_width = self.dims[1..].iter().copied().max().unwrap_or(0);
        let max_weights = self.dims.windows(2).map(|w| w[0] * w[1]).max().unwrap_or(0);
        ensure_len(&mut ws.grad_a, rows * max_width);
        ensure_len(&mut ws.grad_b, rows * max_width);
        ensure_len(&mut ws.partials, rows.div_ceil(CHUNK_ROWS) * max_width);
        ensure_len(&mut ws.dw_partials, rows.div_ceil(DW_CHUNK_ROWS) * max_weights);
        let mut cur = std::mem::take(&mut ws.grad_a);
        let mut next = std::mem::take(&mut ws.grad_b);
        let mut grad_input = grad_input;

        // The output layer is linear: its bias gradient is the plain column sum.
        let (_, b_last) = layer_ranges(&self.dims, layers - 1);
        column_sums_add(grad_output, n_out, &mut ws.partials, &mut grads.values[b_last]);

        for l in (0..layers).rev() {
            let (n_in, n_out) = (self.dims[l], self.dims[l + 1]);
            let (w, _) = layer_ranges(&self.dims, l);
            let g: &[T] = if l + 1 == layers { grad_output } else { &cur[..rows * n_out] };
            let x = &ws.acts[l][..rows * n_in];
            weight_grad_add(&mut grads.values[w.clone()], x, g, n_in, n_out, &mut ws.dw_partials);
            let w_t = MatRef::row_major(&self.params[w], n_in, n_out).t();
            if l > 0 {
                // dX is dL/d(ReLU output) of layer l-1: mask it into dL/d(pre-activation) and take
                // that layer's bias gradient, block by block while each block is in cache.
                let (_, b_prev) = layer_ranges(&self.dims, l - 1);
                let dx = &mut next[..rows * n_in];
                let partials = &mut ws.partials[..rows.div_ceil(CHUNK_ROWS) * n_in];
                dx.par_chunks_mut(CHUNK_ROWS * n_in)
                    .zip(g.par_chunks(CHUNK_ROWS * n_out))
                    .zip(x.par_chunks(CHUNK_ROWS * n_in))
                    .zip(partials.par_chunks_mut(n_in))
                    .for_each(|(((dx, g), act), acc)| {
                        let r = g.len() / n_out;
                        matmul(
                            MatMut::row_major(dx, r, n_in),
                            MatRef::row_major(g, r, n_out),
                            w_t,
                            false,
                            Threads::Single,
                        );
                        relu_mask_column_sums(dx, act, acc, slope);
                    });
                reduce_partials(partials, n_in, &mut grads.values[b_prev]);
                std::mem::swap(&mut cur, &mut next);
            } else if let Some(gi) = grad_input.as_deref_mut() {
                gi.par_chunks_mut(CHUNK_ROWS * n_in).zip(g.par_chunks(CHUNK_ROWS * n_out)).for_each(|(gi, g)| {
                    let r = g.len() / n_out;
                    matmul(MatMut::row_major(gi, r, n_in), MatRef::row_major(g, r, n_out), w_t, false, Threads::Single);
                });
            }
        }
        ws.grad_a = cur;
        ws.grad_b = next;
    }
}

/// `y[r, c] += b[c]`, then (leaky, with `slope`) ReLU when `relu` (NaN passes through, as in
/// PyTorch).
fn add_bias<T: Scalar>(y: &mut [T], b: &[T], relu: bool, slope: T) {
    let width = b.len();
    // Two loops rather than a `relu` test per element, and a select rather than a branch on the
    // sign (random signs would mispredict half the time): both loops vectorise.
    let pass = |chunk: &mut [T]| {
        if relu {
            for row in chunk.chunks_exact_mut(width) {
                for (v, &bias) in row.iter_mut().zip(b) {
                    let s = *v + bias;
                    *v = if s < T::zero() { slope * s } else { s };
                }
            }
        } else {
            for row in chunk.chunks_exact_mut(width) {
                for (v, &bias) in row.iter_mut().zip(b) {
                    *v = *v + bias;
                }
            }
        }
    };
    if y.len() > CHUNK_ROWS * width {
        y.par_chunks_mut(CHUNK_ROWS * width).for_each(pass);
    } else {
        pass(y);
    }
}

/// Adds the column sums of the row-major `g` (`width` columns) to `sums`. Row chunks are summed in
/// parallel into `partials`, then reduced in chunk order (deterministic for any thread count).
fn column_sums_add<T: Scalar>(g: &[T], width: usize, partials: &mut [T], sums: &mut [T]) {
    let chunk_len = CHUNK_ROWS * width;
    let n_chunks = g.len().div_ceil(chunk_len);
    let partials = &mut partials[..n_chunks * width];
    let sum_chunk = |(chunk, acc): (&[T], &mut [T])| {
        acc.fill(T::zero());
        for row in chunk.chunks_exact(width) {
            for (&v, s) in row.iter().zip(acc.iter_mut()) {
                *s = *s + v;
            }
        }
    };
    if n_chunks > 1 {
        g.par_chunks(chunk_len).zip(partials.par_chunks_mut(width)).for_each(sum_chunk);
    } else if n_chunks == 1 {
        sum_chunk((g, partials));
    }
    reduce_partials(partials, width, sums);
}

/// Applies the (leaky) ReLU derivative to the row block `g` in place (`slope`, 0 for ReLU,
/// wherever the stored activation `act <= 0`, PyTorch's convention at the kink; a leaky
/// activation has the sign of its input) and writes the column sums of the masked block to `acc`
/// (`acc.len()` columns), in one pass.
fn relu_mask_column_sums<T: Scalar>(g: &mut [T], act: &[T], acc: &mut [T], slope: T) {
    let width = acc.len();
    acc.fill(T::zero());
    for (row, arow) in g.chunks_exact_mut(width).zip(act.chunks_exact(width)) {
        for ((v, &a), s) in row.iter_mut().zip(arow).zip(acc.iter_mut()) {
            let masked = if a > T::zero() { *v } else { slope * *v };
            *v = masked;
            *s = *s + masked;
        }
    }
}

/// `dw += xᵀ·g` for row-major `x` (rows × n_in) and `g` (rows × n_out). The sum over rows is split
/// into fixed chunks of `DW_CHUNK_ROWS` computed in parallel into `partials` and then added in
/// chunk order: the inner dimension is the long one here, which `gemm` does not split across
/// threads itself, and fixed chunks keep the result independent of the thread count.
fn weight_grad_add<T: Scalar>(dw: &mut [T], x: &[T], g: &[T], n_in: usize, n_out: usize, partials: &mut [T]) {
    let rows = x.len() / n_in;
    let size = n_in * n_out;
    let n_chunks = rows.div_ceil(DW_CHUNK_ROWS);
    if n_chunks <= 1 {
        let (xv, gv) = (MatRef::row_major(x, rows, n_in).t(), MatRef::row_major(g, rows, n_out));
        matmul(MatMut::row_major(dw, n_in, n_out), xv, gv, true, Threads::Single);
        return;
    }
    let partials = &mut partials[..n_chunks * size];
    partials
        .par_chunks_mut(size)
        .zip(x.par_chunks(DW_CHUNK_ROWS * n_in))
        .zip(g.par_chunks(DW_CHUNK_ROWS * n_out))
        .for_each(|((acc, x), g)| {
            let r = x.len() / n_in;
            let (xv, gv) = (MatRef::row_major(x, r, n_in).t(), MatRef::row_major(g, r, n_out));
            matmul(MatMut::row_major(acc, n_in, n_out), xv, gv, false, Threads::Single);
        });
    reduce_partials(partials, size, dw);
}

fn reduce_partials<T: Scalar>(partials: &[T], width: usize, sums: &mut [T]) {
    for acc in partials.chunks_exact(width) {
        for (s, &p) in sums.iter_mut().zip(acc) {
            *s = *s + p;
        }
    }
}

fn ensure_len<T: Scalar>(v: &mut Vec<T>, len: usize) {
    if v.len() < len {
        v.resize(len, T::zero());
    }
}

/// Scratch buffers of forward and backward passes: the input and each layer's activations (kept
/// for backward) and the back-propagated gradients. Reused across calls: buffers only grow.
///
/// A workspace holds one forward pass at a time; keep one per network evaluation whose gradient
/// is still needed.
pub struct Workspace<T> {
    /// `acts[0]` = input, `acts[l + 1]` = output of layer `l` (after ReLU for hidden layers).
    acts: Vec<Vec<T>>,
    grad_a: Vec<T>,
    grad_b: Vec<T>,
    /// Per-chunk partial column sums for the bias gradients.
    partials: Vec<T>,
    /// Per-chunk partial weight gradients.
    dw_partials: Vec<T>,
    rows: usize,
    dims: Vec<usize>,
}

impl<T> Default for Workspace<T> {
    fn default() -> Self {
        Self {
            acts: Vec::new(),
            grad_a: Vec::new(),
            grad_b: Vec::new(),
            partials: Vec::new(),
            dw_partials: Vec::new(),
            rows: 0,
            dims: Vec::new(),
        }
    }
}

impl<T> std::fmt::Debug for Workspace<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Workspace").field("rows", &self.rows).field("dims", &self.dims).finish_non_exhaustive()
    }
}

impl<T: Scalar> Workspace<T> {
    fn prepare(&mut self, dims: &[usize], rows: usize) {
        if self.dims != dims {
            self.dims.clear();
            self.dims.extend_from_slice(dims);
        }
        self.rows = rows;
        if self.acts.len() != dims.len() {
            self.acts.resize_with(dims.len(), Vec::new);
        }
        for (buf, &width) in self.acts.iter_mut().zip(dims) {
            ensure_len(buf, rows * width);
        }
    }

    /// Rows of the last forward pass.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Per hidden layer, how many of its units were positive for at least one row of the last
    /// forward pass. A unit at zero for every row passes no gradient ("dead" ReLU); a layer with
    /// no live unit leaves the network a constant function of its input.
    pub fn live_hidden_units(&self) -> Vec<usize> {
        let hidden = self.dims.len().saturating_sub(2);
        (1..=hidden)
            .map(|l| {
                let width = self.dims[l];
                let acts = &self.acts[l][..self.rows * width];
                (0..width).filter(|&u| acts.iter().skip(u).step_by(width).any(|&a| a > T::zero())).count()
            })
            .collect()
    }

    /// Output of the last forward pass, row-major `rows × out` (empty before any forward pass).
    pub fn output(&self) -> &[T] {
        match (self.acts.last(), self.dims.last()) {
            (Some(out), Some(&width)) => &out[..self.rows * width],
            _ => &[],
        }
    }
}

/// Gradients of a loss with respect to every parameter of an [`Mlp`], in the same flat layout as
/// [`Mlp::parameters`].
#[derive(Clone, PartialEq)]
pub struct Gradients<T> {
    pub(super) values: Vec<T>,
    dims: Vec<usize>,
}

impl<T> std::fmt::Debug for Gradients<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gradients").field("dims", &self.dims).field("parameters", &self.values.len()).finish()
    }
}

impl<T: Scalar> Gradients<T> {
    /// All-zero gradients shaped like `mlp`.
    pub fn zeros_like(mlp: &Mlp<T>) -> Self {
        Self { values: vec![T::zero(); mlp.params.len()], dims: mlp.dims.clone() }
    }

    /// Resets every gradient to zero (before accumulating the next step's passes).
    pub fn fill_zero(&mut self) {
        self.values.fill(T::zero());
    }

    /// All gradients, in the layout of [`Mlp::parameters`].
    pub fn values(&self) -> &[T] {
        &self.values
    }

    /// Mutable gradients (e.g. to scale an accumulated sum into a mean).
    pub fn values_mut(&mut self) -> &mut [T] {
        &mut self.values
    }

    /// Gradient of layer `l`'s weights, row-major `dims[l] × dims[l + 1]`.
    ///
    /// # Panics
    /// If `l` is not a layer index.
    pub fn weights(&self, l: usize) -> &[T] {
        &self.values[layer_ranges(&self.dims, l).0]
    }

    /// Gradient of layer `l`'s bias.
    ///
    /// # Panics
    /// If `l` is not a layer index.
    pub fn bias(&self, l: usize) -> &[T] {
        &self.values[layer_ranges(&self.dims, l).1]
    }

    /// Layer widths of the network these gradients belong to.
    pub fn dims(&self) -> &[usize] {
        &self.dims
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const H: f64 = 1e-6;

    /// Reference forward pass, written independently of the GEMM path: returns every layer's
    /// pre-activation (rows × out per layer).
    fn naive_pre_activations(mlp: &Mlp<f64>, input: &[f64], rows: usize) -> Vec<Vec<f64>> {
        let mut x = input.to_vec();
        let mut pre = Vec::new();
        for l in 0..mlp.layers() {
            let (n_in, n_out) = (mlp.dims[l], mlp.dims[l + 1]);
            let (w, b) = (mlp.weights(l), mlp.bias(l));
            let mut z = vec![0.0; rows * n_out];
            for r in 0..rows {
                for o in 0..n_out {
                    z[r * n_out + o] = b[o] + (0..n_in).map(|i| x[r * n_in + i] * w[i * n_out + o]).sum::<f64>();
                }
            }
            let slope = f64::from(mlp.negative_slope);
            x = if l + 1 < mlp.layers() {
                z.iter().map(|&v| if v > 0.0 { v } else { slope * v }).collect()
            } else {
                z.clone()
            };
            pre.push(z);
        }
        pre
    }

    #[test]
    fn a_zeroed_output_layer_answers_zero_and_learns_first_in_that_layer() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut mlp = Mlp::<f64>::new(&[3, 8, 8, 2], &mut rng);
        let before = mlp.parameters().to_vec();
        mlp.zero_output_layer();
        let input = random(5 * 3, 10.0, &mut rng);
        let mut ws = Workspace::default();
        assert!(mlp.forward(&input, 5, &mut ws).iter().all(|&y| y == 0.0));
        // Hidden layers keep their random weights, so the output layer gets a gradient at once...
        let last = mlp.layers() - 1;
        let hidden_len = layer_ranges(&mlp.dims, last).0.start;
        assert_eq!(&mlp.parameters()[..hidden_len], &before[..hidden_len]);
        let mut grads = Gradients::zeros_like(&mlp);
        mlp.backward(&mut ws, &[1.0; 10], &mut grads, None);
        assert!(grads.weights(last).iter().any(|&g| g != 0.0));
        // ...while nothing flows back through the zero weights yet.
        assert!(grads.values()[..hidden_len].iter().all(|&g| g == 0.0));
    }

    /// Test loss: L = Σ c ⊙ y + ½ Σ y², so dL/dy = c + y (nonlinear, so second-order terms of the
    /// central difference are exercised too).
    fn loss(mlp: &Mlp<f64>, input: &[f64], rows: usize, c: &[f64]) -> f64 {
        let pre = naive_pre_activations(mlp, input, rows);
        pre.last().unwrap().iter().zip(c).map(|(y, c)| c * y + 0.5 * y * y).sum()
    }

    fn random(len: usize, scale: f64, rng: &mut ChaCha8Rng) -> Vec<f64> {
        (0..len).map(|_| rng.random_range(-scale..scale)).collect()
    }

    /// Smallest |pre-activation| over the hidden layers: perturbations of size H move a
    /// pre-activation by at most ~H·(|x| + 1)·(fan-in) ≪ this margin, so no finite difference
    /// crosses a ReLU kink.
    fn kink_margin(mlp: &Mlp<f64>, input: &[f64], rows: usize) -> f64 {
        let pre = naive_pre_activations(mlp, input, rows);
        pre[..pre.len() - 1].iter().flatten().fold(f64::INFINITY, |m, v| m.min(v.abs()))
    }

    /// Compares analytic gradients of `loss` with central differences for every parameter and
    /// every input, and checks that some hidden units were inactive (the ReLU mask mattered).
    ///
    /// Tolerance: the central difference has truncation error h²/6·|L'''| ~ 1e-13 and rounding
    /// error ~ eps·|L|/h ≈ 2e-16·|L|/1e-6 = 2e-10·|L| (plus summation-order noise of the same
    /// order). We accept |fd − an| ≤ 1e-6·max(|an|, 1e-2·(1 + |L|)): relative 1e-6 for gradient
    /// components of normal size, and an absolute floor 1e-8·(1 + |L|), 50× above the rounding
    /// error, for components near zero.
    fn check_gradients(dims: &[usize], rows: usize, seed: u64) {
        check_gradients_with_slope(dims, rows, seed, 0.0);
    }

    fn check_gradients_with_slope(dims: &[usize], rows: usize, seed: u64, slope: f32) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut mlp = Mlp::<f64>::new(dims, &mut rng);
        mlp.set_negative_slope(slope);
        let input = random(rows * dims[0], 1.0, &mut rng);
        let c = random(rows * dims[dims.len() - 1], 1.0, &mut rng);
        let margin = kink_margin(&mlp, &input, rows);
        assert!(margin > 1e-4, "fixture sits on a ReLU kink (margin {margin}); pick another seed");
        if dims.len() > 2 {
            let pre = naive_pre_activations(&mlp, &input, rows);
            let hidden = pre[..pre.len() - 1].iter().flatten();
            let dead = hidden.clone().filter(|&&v| v < 0.0).count();
            assert!(dead > 0 && dead < hidden.count(), "fixture must have active and inactive units");
        }

        let mut ws = Workspace::default();
        let y = mlp.forward(&input, rows, &mut ws).to_vec();
        let grad_out: Vec<f64> = y.iter().zip(&c).map(|(y, c)| c + y).collect();
        let mut grads = Gradients::zeros_like(&mlp);
        let mut grad_in = vec![f64::NAN; input.len()]; // must be overwritten
        mlp.backward(&mut ws, &grad_out, &mut grads, Some(&mut grad_in));

        let l0 = loss(&mlp, &input, rows, &c);
        let tol = |an: f64| 1e-6 * an.abs().max(1e-2 * (1.0 + l0.abs()));
        for i in 0..mlp.params.len() {
            let p = mlp.params[i];
            mlp.params[i] = p + H;
            let lp = loss(&mlp, &input, rows, &c);
            mlp.params[i] = p - H;
            let lm = loss(&mlp, &input, rows, &c);
            mlp.params[i] = p;
            let fd = (lp - lm) / (2.0 * H);
            let an = grads.values[i];
            assert!((fd - an).abs() <= tol(an), "dims {dims:?} parameter {i}: fd {fd} vs analytic {an}");
        }
        let mut x = input.clone();
        for i in 0..x.len() {
            let v = x[i];
            x[i] = v + H;
            let lp = loss(&mlp, &x, rows, &c);
            x[i] = v - H;
            let lm = loss(&mlp, &x, rows, &c);
            x[i] = v;
            let fd = (lp - lm) / (2.0 * H);
            assert!((fd - grad_in[i]).abs() <= tol(grad_in[i]), "dims {dims:?} input {i}: fd {fd} vs {}", grad_in[i]);
        }
    }

    #[test]
    fn single_linear_layer_gradients_match_finite_differences() {
        check_gradients(&[3, 4], 5, 1);
    }

    #[test]
    fn relu_layer_gradients_match_finite_differences() {
        check_gradients(&[3, 6, 2], 7, 2);
    }

    #[test]
    fn deep_mlp_gradients_match_finite_differences() {
        check_gradients(&[4, 8, 8, 8, 8, 3], 6, 3);
    }

    #[test]
    fn leaky_mlp_gradients_match_finite_differences() {
        check_gradients_with_slope(&[4, 8, 8, 8, 8, 3], 6, 3, 0.1);
    }

    #[test]
    fn a_leaky_unit_passes_its_negative_inputs_scaled() {
        // One hidden unit with weight 1 and bias 0 between a scalar input and output.
        let mut mlp = Mlp::<f64> { dims: vec![1, 1, 1], params: vec![1.0, 0.0, 1.0, 0.0], negative_slope: 0.0 };
        let mut ws = Workspace::default();
        assert_eq!(mlp.forward(&[-2.0, 3.0], 2, &mut ws), &[0.0, 3.0]);
        mlp.set_negative_slope(0.25);
        assert_eq!(mlp.forward(&[-2.0, 3.0], 2, &mut ws), &[-0.5, 3.0]);
        let mut grads = Gradients::zeros_like(&mlp);
        let mut grad_in = [0.0; 2];
        mlp.backward(&mut ws, &[1.0, 1.0], &mut grads, Some(&mut grad_in));
        assert_eq!(grad_in, [0.25, 1.0]);
    }

    #[test]
    fn live_hidden_units_counts_units_positive_for_some_row() {
        let dims = [3, 6, 5, 2];
        let mut mlp = Mlp::<f32>::new(&dims, &mut ChaCha8Rng::seed_from_u64(5));
        let input64 = random(40 * 3, 1.0, &mut ChaCha8Rng::seed_from_u64(6));
        let input: Vec<f32> = input64.iter().map(|&x| x as f32).collect();
        let mut ws = Workspace::default();
        mlp.forward(&input, 40, &mut ws);
        let live = ws.live_hidden_units();
        assert_eq!(live.len(), 2);
        // Brute force from the pre-activations: a unit is live when some row's value is > 0.
        let input_f64: Vec<f64> = input.iter().map(|&x| f64::from(x)).collect();
        let pre = naive_pre_activations(&mlp.cast::<f64>(), &input_f64, 40);
        for (l, &count) in live.iter().enumerate() {
            let width = dims[l + 1];
            let expected = (0..width).filter(|&u| (0..40).any(|r| pre[l][r * width + u] > 0.0)).count();
            assert_eq!(count, expected, "layer {l}");
        }
        // Zero weights and a negative bias kill every unit of the second hidden layer.
        let (w, b) = layer_ranges(&dims, 1);
        let params = mlp.parameters_mut();
        params[w].iter_mut().for_each(|x| *x = 0.0);
        params[b].iter_mut().for_each(|x| *x = -1.0);
        mlp.forward(&input, 40, &mut ws);
        assert_eq!(ws.live_hidden_units()[1], 0);
    }

    #[test]
    fn gradients_match_on_more_rows_than_one_chunk() {
        // 9000 rows: several CHUNK_ROWS blocks and DW_CHUNK_ROWS chunks, the last ones partial.
        let dims = [2, 5, 3];
        let rows = 9000;
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mlp = Mlp::<f64>::new(&dims, &mut rng);
        let input = random(rows * 2, 1.0, &mut rng);
        let c = random(rows * 3, 1.0, &mut rng);
        let mut ws = Workspace::default();
        let y = mlp.forward(&input, rows, &mut ws).to_vec();
        let pre = naive_pre_activations(&mlp, &input, rows);
        for (a, b) in y.iter().zip(pre.last().unwrap()) {
            assert!((a - b).abs() < 1e-12);
        }
        let grad_out: Vec<f64> = y.iter().zip(&c).map(|(y, c)| c + y).collect();
        let mut grads = Gradients::zeros_like(&mlp);
        mlp.backward(&mut ws, &grad_out, &mut grads, None);
        // Reference by hand: dz2 = grad_out; db2 = Σ dz2; dh = dz2·W2ᵀ masked by z1 > 0; db1 = Σ dh;
        // dW1 = xᵀ·dh.
        let (w2, z1) = (mlp.weights(1), &pre[0]);
        let mut db1 = [0.0; 5];
        let mut dw1 = [0.0; 10];
        let mut db2 = [0.0; 3];
        for r in 0..rows {
            for o in 0..3 {
                db2[o] += grad_out[r * 3 + o];
            }
            for h in 0..5 {
                if z1[r * 5 + h] > 0.0 {
                    let d: f64 = (0..3).map(|o| grad_out[r * 3 + o] * w2[h * 3 + o]).sum();
                    db1[h] += d;
                    for i in 0..2 {
                        dw1[i * 5 + h] += input[r * 2 + i] * d;
                    }
                }
            }
        }
        // Sums of ~9000 terms of size O(1): summation-order differences ~1e-12.
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-10);
        assert!(close(grads.bias(1), &db2), "{:?} vs {db2:?}", grads.bias(1));
        assert!(close(grads.bias(0), &db1), "{:?} vs {db1:?}", grads.bias(0));
        assert!(close(grads.weights(0), &dw1));
    }

    #[test]
    fn backward_adds_into_gradients() {
        let dims = [3, 7, 7, 2];
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mlp = Mlp::<f64>::new(&dims, &mut rng);
        let (x1, x2) = (random(4 * 3, 1.0, &mut rng), random(9 * 3, 1.0, &mut rng));
        let (g1, g2) = (random(4 * 2, 1.0, &mut rng), random(9 * 2, 1.0, &mut rng));
        let mut ws = Workspace::default();
        let run = |x: &[f64], rows: usize, g: &[f64], ws: &mut Workspace<f64>, grads: &mut Gradients<f64>| {
            mlp.forward(x, rows, ws);
            mlp.backward(ws, g, grads, None);
        };
        let mut a = Gradients::zeros_like(&mlp);
        let mut b = Gradients::zeros_like(&mlp);
        let mut both = Gradients::zeros_like(&mlp);
        run(&x1, 4, &g1, &mut ws, &mut a);
        run(&x2, 9, &g2, &mut ws, &mut b);
        run(&x1, 4, &g1, &mut ws, &mut both);
        run(&x2, 9, &g2, &mut ws, &mut both);
        // Same terms, possibly summed in another order: agreement to a few ulps.
        for ((s, x), y) in both.values().iter().zip(a.values()).zip(b.values()) {
            assert!((s - (x + y)).abs() <= 1e-14 * (1.0 + s.abs()), "{s} vs {}", x + y);
        }
        assert!(a.values().iter().any(|v| *v != 0.0) && b.values().iter().any(|v| *v != 0.0));
        both.fill_zero();
        assert!(both.values().iter().all(|v| *v == 0.0));
    }

    #[test]
    fn workspace_reuse_across_batch_sizes_gives_fresh_results() {
        let dims = [3, 16, 16, 4];
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let mlp = Mlp::<f64>::new(&dims, &mut rng);
        let mut shared = Workspace::default();
        for rows in [700, 3, 1200, 1, 50] {
            let x = random(rows * 3, 2.0, &mut rng);
            let g = random(rows * 4, 1.0, &mut rng);
            let mut fresh = Workspace::default();
            let (mut ga, mut gb) = (Gradients::zeros_like(&mlp), Gradients::zeros_like(&mlp));
            let (mut ia, mut ib) = (vec![0.0; rows * 3], vec![0.0; rows * 3]);
            let ya = mlp.forward(&x, rows, &mut shared).to_vec();
            mlp.backward(&mut shared, &g, &mut ga, Some(&mut ia));
            let yb = mlp.forward(&x, rows, &mut fresh).to_vec();
            mlp.backward(&mut fresh, &g, &mut gb, Some(&mut ib));
            assert_eq!(ya, yb);
            assert_eq!(ga, gb);
            assert_eq!(ia, ib);
            assert_eq!(shared.output(), &ya[..]);
            assert_eq!(shared.rows(), rows);
        }
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let dims = [9, 64, 64, 12];
        let rows = 2000;
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let mlp = Mlp::<f32>::new(&dims, &mut rng);
        let x: Vec<f32> = (0..rows * 9).map(|_| rng.random_range(-3.0..3.0)).collect();
        let g: Vec<f32> = (0..rows * 12).map(|_| rng.random_range(-1.0..1.0)).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let mut ws = Workspace::default();
                let y = mlp.forward(&x, rows, &mut ws).to_vec();
                let mut grads = Gradients::zeros_like(&mlp);
                mlp.backward(&mut ws, &g, &mut grads, None);
                (y, grads)
            })
        };
        let (y1, g1) = run(1);
        let (y2, g2) = run(2);
        // gemm splits rows/columns (not the inner sum) across threads and the bias sums use fixed
        // chunks, so the results should agree bit for bit; allow f32 rounding noise in case a
        // kernel choice differs with the thread count.
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + x.abs()));
        assert!(close(&y1, &y2));
        assert!(close(g1.values(), g2.values()));
    }

    #[test]
    fn init_is_pytorch_uniform_and_seeded() {
        let dims = [9, 128, 128, 72];
        let a = Mlp::<f32>::new(&dims, &mut ChaCha8Rng::seed_from_u64(42));
        let b = Mlp::<f32>::new(&dims, &mut ChaCha8Rng::seed_from_u64(42));
        let c = Mlp::<f32>::new(&dims, &mut ChaCha8Rng::seed_from_u64(43));
        assert_eq!(a.parameters(), b.parameters());
        assert_ne!(a.parameters(), c.parameters());
        assert_eq!(a.parameters().len(), 9 * 128 + 128 + 128 * 128 + 128 + 128 * 72 + 72);
        for (l, &fan_in) in dims[..a.layers()].iter().enumerate() {
            let bound = 1.0 / (fan_in as f32).sqrt();
            for part in [a.weights(l), a.bias(l)] {
                let max = part.iter().fold(0.0_f32, |m, v| m.max(v.abs()));
                assert!(max <= bound, "layer {l}: {max} > {bound}");
                // ≥ 72 uniform draws: the largest |value| is within 10 % of the bound with
                // probability > 1 − 0.9^72 ≈ 0.9995; it is a fixed seed, so this cannot flake.
                assert!(max > 0.9 * bound, "layer {l}: values fill only ±{max} of ±{bound}");
                let mean = part.iter().sum::<f32>() / part.len() as f32;
                assert!(mean.abs() < 0.25 * bound, "layer {l}: mean {mean} not centred");
            }
        }
    }

    #[test]
    fn cast_round_trips_and_debug_is_compact() {
        let a = Mlp::<f32>::new(&[3, 5, 2], &mut ChaCha8Rng::seed_from_u64(1));
        let back: Mlp<f32> = a.cast::<f64>().cast();
        assert_eq!(a, back);
        assert_eq!(format!("{a:?}"), "Mlp { dims: [3, 5, 2], parameters: 32 }");
        assert_eq!(a.dims(), vec![3, 5, 2]);
        assert_eq!((a.input_dim(), a.output_dim(), a.layers()), (3, 2, 2));
    }

    #[test]
    fn f32_forward_agrees_with_the_f64_reference() {
        let dims = [9, 128, 128, 128, 72];
        let rows = 300;
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let mlp = Mlp::<f32>::new(&dims, &mut rng);
        let x: Vec<f32> = (0..rows * 9).map(|_| rng.random_range(-20.0..20.0)).collect();
        let mut ws = Workspace::default();
        let y = mlp.forward(&x, rows, &mut ws).to_vec();
        let x64: Vec<f64> = x.iter().map(|&v| v.into()).collect();
        let pre = naive_pre_activations(&mlp.cast(), &x64, rows);
        let max_ref = pre.last().unwrap().iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        // f32 with 128-term dot products over 4 layers: relative error ≲ 4·128·6e-8 ≈ 3e-5 of the
        // output scale.
        for (a, b) in y.iter().zip(pre.last().unwrap()) {
            assert!((f64::from(*a) - b).abs() <= 3e-5 * max_ref, "{a} vs {b}");
        }
    }

    #[test]
    fn nan_inputs_propagate_to_the_output() {
        let mlp = Mlp::<f32>::new(&[2, 4, 1], &mut ChaCha8Rng::seed_from_u64(1));
        let mut ws = Workspace::default();
        let y = mlp.forward(&[f32::NAN, 0.0], 1, &mut ws);
        assert!(y[0].is_nan(), "ReLU must not hide a NaN (divergence detection relies on it)");
    }
}
