//! Truncated Chamfer on a LiDAR-sized frame pair: KITTI odometry 00 frames 0 -> 1 when
//! `../shared/data/kitti-odometry-00/` exists (ground and far points cut crudely, capped at
//! 50k points), else two synthetic 50k clouds. Compares the default hash-grid reverse search
//! with a k-d tree built over the moved cloud on every call.

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use mbnt::geometry::Point;
use mbnt::geometry::knn::KdTree;
use mbnt::losses::{ChamferScratch, ReverseSearch, truncated_chamfer};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const MAX_POINTS: usize = 50_000;

/// KITTI `.bin`: float32 x, y, z, reflectance. Keeps points above a crude ground cut (the
/// sensor is 1.73 m up) and within 50 m, then every k-th so at most `MAX_POINTS` remain.
fn kitti_frame(path: &Path) -> Option<Vec<Point>> {
    let bytes = std::fs::read(path).ok()?;
    let pts: Vec<Point> = bytes
        .chunks_exact(16)
        .map(|c| std::array::from_fn(|k| f32::from_le_bytes(c[4 * k..4 * k + 4].try_into().unwrap())))
        .filter(|p: &Point| p[2] > -1.4 && p[0] * p[0] + p[1] * p[1] < 50.0 * 50.0)
        .collect();
    let step = pts.len().div_ceil(MAX_POINTS).max(1);
    Some(pts.into_iter().step_by(step).collect())
}

fn clouds() -> (Vec<Point>, Vec<Point>, &'static str) {
    let dir = Path::new("../shared/data/kitti-odometry-00");
    if let (Some(a), Some(b)) = (kitti_frame(&dir.join("000000.bin")), kitti_frame(&dir.join("000001.bin"))) {
        return (a, b, "kitti");
    }
    eprintln!("KITTI frames not found under {}: using synthetic clouds", dir.display());
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let a: Vec<Point> = (0..MAX_POINTS)
        .map(|_| [rng.random_range(-40.0..40.0), rng.random_range(-40.0..40.0), rng.random_range(-1.0..2.0)])
        .collect();
    let b = a.iter().map(|p| [p[0] + rng.random_range(-0.3..0.3), p[1] + 0.5, p[2]]).collect();
    (a, b, "synthetic")
}

fn bench(c: &mut Criterion) {
    let (moved, target, name) = clouds();
    eprintln!("{name}: {} moved, {} target points", moved.len(), target.len());
    let target_tree = KdTree::new(&target);
    let mut scratch = ChamferScratch::new();
    let mut grad = vec![[0.0f32; 3]; moved.len()];

    let mut group = c.benchmark_group(format!("chamfer_{name}"));
    group.throughput(Throughput::Elements((moved.len() + target.len()) as u64));
    group.sample_size(20);
    group.bench_function("value_and_gradient_grid", |b| {
        b.iter(|| black_box(truncated_chamfer(&moved, &target, &target_tree, 2.0, 1.0, &mut grad, None, &mut scratch)))
    });
    group.bench_function("value_and_gradient_tree_rebuilt", |b| {
        b.iter(|| {
            let own = KdTree::new(&moved);
            let reverse = Some(ReverseSearch::from_tree(&own));
            black_box(truncated_chamfer(&moved, &target, &target_tree, 2.0, 1.0, &mut grad, reverse, &mut scratch))
        })
    });
    group.bench_function("kd_tree_build", |b| b.iter(|| black_box(KdTree::new(&moved))));
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
