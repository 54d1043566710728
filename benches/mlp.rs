//! The trajectory network's hot path: dims [9, 128 × 8, 72] (T = 25) on N = 30 000 rows.
//! `forward` alone, and one training step `forward + backward + Adam`, on 1 and 2 threads.
//! `batching`: the lever of evaluating a reference frame's three cycle-consistency passes as
//! one pass of 3 x 8192 rows instead of three passes of 8192 rows (fast mode's part size).

use criterion::{BenchmarkId, Criterion, Throughput, black_box, criterion_group, criterion_main};
use mbnt::nn::{Adam, Gradients, Mlp, Workspace};
use rand::{Rng, SeedableRng};
use std::time::Duration;

fn bench_mlp(c: &mut Criterion) {
    let rows = 30_000;
    let mut dims = vec![9];
    dims.extend([128; 8]);
    dims.push(72);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut mlp = Mlp::<f32>::new(&dims, &mut rng);
    let input: Vec<f32> = (0..rows * 9).map(|_| rng.random_range(-30.0..30.0)).collect();
    let grad_out: Vec<f32> = (0..rows * 72).map(|_| rng.random_range(-1e-3..1e-3)).collect();
    let mut ws = Workspace::default();
    let mut grads = Gradients::zeros_like(&mlp);
    let mut grad_in = vec![0.0_f32; rows * 9];
    let mut adam = Adam::new(&mlp, 1e-6);

    let mut group = c.benchmark_group(format!("mlp {dims:?} N={rows}"));
    group.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(3));
    group.throughput(Throughput::Elements(rows as u64));
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        group.bench_function(BenchmarkId::new("forward", format!("{threads} threads")), |b| {
            b.iter(|| pool.install(|| black_box(mlp.forward(&input, rows, &mut ws)[0])))
        });
        group.bench_function(BenchmarkId::new("forward+backward+adam", format!("{threads} threads")), |b| {
            b.iter(|| {
                pool.install(|| {
                    grads.fill_zero();
                    mlp.forward(&input, rows, &mut ws);
                    mlp.backward(&mut ws, &grad_out, &mut grads, Some(&mut grad_in));
                    adam.step(&mut mlp, &grads);
                });
                black_box(&grad_in);
            })
        });
    }
    group.finish();
}

fn bench_batching(c: &mut Criterion) {
    let part = 8192;
    let mut dims = vec![9];
    dims.extend([128; 8]);
    dims.push(72);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
    let mlp = Mlp::<f32>::new(&dims, &mut rng);
    let input: Vec<f32> = (0..3 * part * 9).map(|_| rng.random_range(-30.0..30.0)).collect();
    let grad_out: Vec<f32> = (0..3 * part * 72).map(|_| rng.random_range(-1e-3..1e-3)).collect();
    let mut ws = Workspace::default();
    let mut grads = Gradients::zeros_like(&mlp);
    let mut grad_in = vec![0.0_f32; 3 * part * 9];
    let mut group = c.benchmark_group(format!("batching forward+backward, 3 x {part} rows"));
    group.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(3));
    group.throughput(Throughput::Elements(3 * part as u64));
    group.bench_function("three passes", |b| {
        b.iter(|| {
            for k in 0..3 {
                mlp.forward(&input[k * part * 9..(k + 1) * part * 9], part, &mut ws);
                let g = &grad_out[k * part * 72..(k + 1) * part * 72];
                mlp.backward(&mut ws, g, &mut grads, Some(&mut grad_in[k * part * 9..(k + 1) * part * 9]));
            }
            black_box(&grad_in);
        })
    });
    group.bench_function("one batched pass", |b| {
        b.iter(|| {
            mlp.forward(&input, 3 * part, &mut ws);
            mlp.backward(&mut ws, &grad_out, &mut grads, Some(&mut grad_in));
            black_box(&grad_in);
        })
    });
    group.finish();
}

criterion_group!(benches, bench_mlp, bench_batching);
criterion_main!(benches);
