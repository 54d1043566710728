//! DBSCAN (eps 0.8 m, min_points 30, method.md section 3) and ground removal on KITTI frame 0
//! (when `../shared/data` is present) and on a synthetic 30k-point street scene.

use std::hint::black_box;
use std::time::Instant;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use mbnt::geometry::Point;
use mbnt::geometry::dbscan::{NOISE, clusters, dbscan};
use mbnt::geometry::ground::{PreprocessParams, preprocess};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const EPS_M: f32 = 0.8;
const MIN_POINTS: usize = 30;

fn read_kitti_bin(path: &str) -> Option<Vec<Point>> {
    let bytes = std::fs::read(path).ok()?;
    let floats: Vec<f32> = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    Some(floats.chunks_exact(4).map(|c| [c[0], c[1], c[2]]).collect())
}

/// 30k points: 40 car-sized boxes, 20 thin poles and a scatter of vegetation-like noise.
fn synthetic_30k(seed: u64) -> Vec<Point> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pts = Vec::with_capacity(30_000);
    for _ in 0..40 {
        let c = [rng.random_range(-40.0f32..40.0), rng.random_range(-40.0f32..40.0)];
        for _ in 0..600 {
            pts.push([
                c[0] + rng.random_range(0.0..4.2),
                c[1] + rng.random_range(0.0..1.8),
                rng.random_range(-1.5..-0.2),
            ]);
        }
    }
    for _ in 0..20 {
        let c = [rng.random_range(-40.0f32..40.0), rng.random_range(-40.0f32..40.0)];
        for _ in 0..150 {
            pts.push([
                c[0] + rng.random_range(0.0..0.2),
                c[1] + rng.random_range(0.0..0.2),
                rng.random_range(-1.7..3.0),
            ]);
        }
    }
    while pts.len() < 30_000 {
        pts.push([rng.random_range(-50.0..50.0), rng.random_range(-50.0..50.0), rng.random_range(-1.7..2.0)]);
    }
    pts
}

fn describe(name: &str, pts: &[Point]) {
    let t = Instant::now();
    let labels = dbscan(pts, EPS_M, MIN_POINTS);
    let dt = t.elapsed();
    let noise = labels.iter().filter(|&&l| l == NOISE).count();
    eprintln!("{name}: {} points, {} clusters, {noise} noise, one run {dt:.2?}", pts.len(), clusters(&labels).len());
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("dbscan");
    group.sample_size(10);
    let synthetic = synthetic_30k(1);
    describe("synthetic", &synthetic);
    group.throughput(Throughput::Elements(synthetic.len() as u64));
    group.bench_with_input(BenchmarkId::new("synthetic", synthetic.len()), &synthetic, |b, pts| {
        b.iter(|| black_box(dbscan(pts, EPS_M, MIN_POINTS)))
    });
    match read_kitti_bin("../shared/data/kitti-odometry-00/000000.bin") {
        None => eprintln!("KITTI frame 0 not found: skipping the KITTI benchmarks"),
        Some(raw) => {
            let params = PreprocessParams::default();
            let (kept, report) = preprocess(&raw, &params).expect("default parameters are valid");
            eprintln!("KITTI frame 0 pre-processing: {report:?}");
            let pts: Vec<Point> = kept.iter().map(|&i| raw[i as usize]).collect();
            describe("kitti_frame0", &pts);
            group.throughput(Throughput::Elements(pts.len() as u64));
            group.bench_with_input(BenchmarkId::new("kitti_frame0_no_ground", pts.len()), &pts, |b, pts| {
                b.iter(|| black_box(dbscan(pts, EPS_M, MIN_POINTS)))
            });
            group.throughput(Throughput::Elements(raw.len() as u64));
            group.bench_with_input(BenchmarkId::new("preprocess_kitti_frame0", raw.len()), &raw, |b, raw| {
                b.iter(|| black_box(preprocess(raw, &params)))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
