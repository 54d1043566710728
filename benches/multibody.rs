//! Multi-body loss of one cluster at n = 1000 and n = 3000 (the research code's subsampling
//! cap): value only (weight 0, no gradient pass) and value + gradient, 10 power steps.

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use mbnt::geometry::Point;
use mbnt::losses::{MultibodyScratch, multibody_loss};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A car-sized cluster and a slightly non-rigid moved copy, so A is dense but not all ones and
/// the power iteration runs its full 10 steps.
fn cluster(n: usize) -> (Vec<Point>, Vec<Point>) {
    let mut rng = ChaCha8Rng::seed_from_u64(n as u64);
    let points: Vec<Point> =
        (0..n).map(|_| [rng.random_range(0.0..4.5), rng.random_range(0.0..1.8), rng.random_range(0.0..1.5)]).collect();
    let moved = points
        .iter()
        .map(|p| [p[0] + 1.0 + rng.random_range(-0.03..0.03), p[1] + rng.random_range(-0.03..0.03), p[2]])
        .collect();
    (points, moved)
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("multibody");
    group.sample_size(20);
    for n in [1000, 3000] {
        let (points, moved) = cluster(n);
        let mut scratch = MultibodyScratch::new();
        let mut grad = vec![[0.0f32; 3]; n];
        group.throughput(Throughput::Elements((n * (n - 1) / 2) as u64));
        for (label, weight) in [("value", 0.0), ("value_and_gradient", 1.0)] {
            group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                b.iter(|| black_box(multibody_loss(&points, &moved, 0.1, 10, weight, &mut grad, &mut scratch)))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
