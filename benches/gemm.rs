//! GEMM throughput on the MLP's shapes: the `gemm` crate (through `mbnt::nn::matmul`) against
//! `matrixmultiply`, for the three products of a 128 → 128 layer on N rows:
//! forward `X·W`, input gradient `dY·Wᵀ` and weight gradient `Xᵀ·dY`.
//!
//! Throughput is reported in "elements" = floating-point operations (2·N·128·128 per product), so
//! criterion's `Melem/s` reads as MFLOP/s. `matrixmultiply` reads its thread count once per
//! process from `MATMUL_NUM_THREADS`; its rows are labelled with that value (run the bench twice,
//! with `MATMUL_NUM_THREADS=1` and `=2`, to get both).

use criterion::{BenchmarkId, Criterion, Throughput, black_box, criterion_group, criterion_main};
use mbnt::nn::matmul::{MatMut, MatRef, Threads, matmul};
use rand::{Rng, SeedableRng};
use std::time::Duration;

const WIDTH: usize = 128;

#[derive(Clone, Copy)]
enum Op {
    Forward,
    InputGrad,
    WeightGrad,
}

impl Op {
    fn name(self) -> &'static str {
        match self {
            Op::Forward => "forward X·W",
            Op::InputGrad => "dX = dY·Wᵀ",
            Op::WeightGrad => "dW = Xᵀ·dY",
        }
    }
}

/// `(m, n, k)` and operand views of one product; `tall` is N × 128, `w` 128 × 128.
fn operands<'a>(op: Op, tall: &'a [f32], w: &'a [f32], n: usize) -> (usize, usize, MatRef<'a, f32>, MatRef<'a, f32>) {
    match op {
        Op::Forward => (n, WIDTH, MatRef::row_major(tall, n, WIDTH), MatRef::row_major(w, WIDTH, WIDTH)),
        Op::InputGrad => (n, WIDTH, MatRef::row_major(tall, n, WIDTH), MatRef::row_major(w, WIDTH, WIDTH).t()),
        // Xᵀ·dY with X = dY = `tall` stand-ins (the values do not change the cost).
        Op::WeightGrad => (WIDTH, WIDTH, MatRef::row_major(tall, n, WIDTH).t(), MatRef::row_major(tall, n, WIDTH)),
    }
}

/// `matrixmultiply::sgemm` with the same strides; `c` is written (beta 0) or accumulated (beta 1).
fn mm_sgemm(op: Op, tall: &[f32], w: &[f32], n: usize, c: &mut [f32]) {
    let wd = WIDTH as isize;
    // (m, k, n, a, rsa, csa, b, rsb, csb, beta)
    let (m, k, nn, a, rsa, csa, b, rsb, csb, beta) = match op {
        Op::Forward => (n, WIDTH, WIDTH, tall.as_ptr(), wd, 1, w.as_ptr(), wd, 1, 0.0),
        Op::InputGrad => (n, WIDTH, WIDTH, tall.as_ptr(), wd, 1, w.as_ptr(), 1, wd, 0.0),
        Op::WeightGrad => (WIDTH, n, WIDTH, tall.as_ptr(), 1, wd, tall.as_ptr(), wd, 1, 1.0),
    };
    assert!(c.len() >= m * nn && tall.len() >= n * WIDTH && w.len() >= WIDTH * WIDTH);
    // SAFETY: all views lie inside their buffers (checked above) and `c` does not alias them.
    unsafe { matrixmultiply::sgemm(m, k, nn, 1.0, a, rsa, csa, b, rsb, csb, beta, c.as_mut_ptr(), wd, 1) };
}

fn bench_gemm(c: &mut Criterion) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mm_threads = std::env::var("MATMUL_NUM_THREADS").unwrap_or_else(|_| "default".into());
    let pools: Vec<_> =
        [1, 2].iter().map(|&t| (t, rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap())).collect();
    for n in [8192, 50_000] {
        let tall: Vec<f32> = (0..n * WIDTH).map(|_| rng.random_range(-1.0..1.0)).collect();
        let w: Vec<f32> = (0..WIDTH * WIDTH).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut out = vec![0.0_f32; n * WIDTH];
        for op in [Op::Forward, Op::InputGrad, Op::WeightGrad] {
            let mut group = c.benchmark_group(format!("{} N={n}", op.name()));
            group.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(2));
            group.throughput(Throughput::Elements((2 * n * WIDTH * WIDTH) as u64));
            let accumulate = matches!(op, Op::WeightGrad);
            for (threads, pool) in &pools {
                group.bench_function(BenchmarkId::new("gemm", format!("{threads} threads")), |b| {
                    b.iter(|| {
                        pool.install(|| {
                            let (m, nn, a, bm) = operands(op, &tall, &w, n);
                            matmul(MatMut::row_major(&mut out, m, nn), a, bm, accumulate, Threads::Pool);
                        });
                        black_box(&out);
                    })
                });
            }
            group.bench_function(BenchmarkId::new("matrixmultiply", format!("MATMUL_NUM_THREADS={mm_threads}")), |b| {
                b.iter(|| {
                    mm_sgemm(op, &tall, &w, n, &mut out);
                    black_box(&out);
                })
            });
            group.finish();
        }
    }
}

criterion_group!(benches, bench_gemm);
criterion_main!(benches);
