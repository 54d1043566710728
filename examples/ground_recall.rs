//! What the fit's ground removal leaves of the moving objects, by range, on simulated sequences.
//!
//! The bodies are tracked in the points the fit keeps (`geometry::ground::preprocess`, default
//! parameters). A far car seen by one or two laser rings may lose every point there: a grid cell
//! holding only the car's lowest ring takes that ring for its ground. This prints, per 10 m band
//! of range from the sensor, how many of the moving objects' non-ground points (the simulator's
//! truth) the removal keeps, and how many true ground points it keeps; then every frame in which
//! a moving object of at least `MIN_POINTS` points keeps under half of them:
//!
//! ```text
//! cargo run --release --example ground_recall -- 168,170 [FRAMES]
//! cargo run --release --example ground_recall -- --kitti ../shared/data/kitti-odometry-00
//! ```
//!
//! `GROUND_RECALL_MAX_SLOPE=S` measures the removal with another largest ground slope.
//! With `--kitti DIR`, the share of points kept per band in the six real frames there (no labels:
//! what a change to the removal does to a real street, not whether it is right).

use std::collections::BTreeMap;

use mbnt::geometry::Point;
use mbnt::geometry::ground::{PreprocessParams, preprocess};
use mbnt::io::kitti::read_kitti_bin;
use mbnt::sim::{SimParams, simulate};

/// Width (m) of a range band.
const BAND_M: f32 = 10.0;
/// Bands reported; the last holds everything beyond.
const BANDS: usize = 6;
/// An object's frame is listed when it shows at least this many non-ground points...
const MIN_POINTS: usize = 5;
/// ...and the removal keeps less than this share of them.
const LISTED_BELOW_SHARE: f64 = 0.5;

/// Points seen and kept.
#[derive(Default, Clone, Copy)]
struct Tally {
    seen: usize,
    kept: usize,
}

impl Tally {
    fn add(&mut self, kept: bool) {
        self.seen += 1;
        self.kept += usize::from(kept);
    }

    fn share_pct(&self) -> f64 {
        100.0 * self.kept as f64 / self.seen.max(1) as f64
    }
}

/// The band of a point's horizontal range from the sensor.
fn band(p: &Point) -> usize {
    ((p[0].hypot(p[1]) / BAND_M) as usize).min(BANDS - 1)
}

/// The pre-filter's parameters: the fit's defaults, with the ground's largest slope taken from
/// `GROUND_RECALL_MAX_SLOPE` when set (to measure a change before making it).
fn filter_params() -> anyhow::Result<PreprocessParams> {
    let mut params = PreprocessParams::default();
    if let Ok(slope) = std::env::var("GROUND_RECALL_MAX_SLOPE") {
        params.ground.max_slope = slope.parse()?;
    }
    Ok(params)
}

/// Per point of `points`, whether the pre-filter with `params` keeps it.
fn kept_mask(points: &[Point], params: &PreprocessParams) -> anyhow::Result<Vec<bool>> {
    let (kept, _) = preprocess(points, params)?;
    let mut mask = vec![false; points.len()];
    for i in kept {
        mask[i as usize] = true;
    }
    Ok(mask)
}

fn band_label(b: usize) -> String {
    let lo = b as f32 * BAND_M;
    if b + 1 == BANDS { format!(">= {lo:.0} m") } else { format!("{lo:.0}-{:.0} m", lo + BAND_M) }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let params = filter_params()?;
    if args.get(1).map(String::as_str) == Some("--kitti") {
        let dir = std::path::Path::new(args.get(2).map_or("../shared/data/kitti-odometry-00", String::as_str));
        return kitti(dir, &params);
    }
    let seeds: Vec<u64> =
        args.get(1).map_or("168", String::as_str).split(',').map(str::parse).collect::<Result<_, _>>()?;
    let frames: usize = args.get(2).map_or(Ok(25), |s| s.parse())?;
    let mut moving = [Tally::default(); BANDS];
    let mut ground = [Tally::default(); BANDS];
    for seed in seeds {
        let sim = simulate(&SimParams::log(seed, frames))?;
        for (k, frame) in sim.frames.iter().enumerate() {
            let keep = kept_mask(frame, &params)?;
            // Per moving object: its points seen and kept, and the sum of their ranges.
            let mut objects: BTreeMap<u32, (Tally, f32)> = BTreeMap::new();
            for ((p, truth), &kept) in frame.iter().zip(&sim.truth[k]).zip(&keep) {
                if truth.is_ground {
                    ground[band(p)].add(kept);
                } else if sim.objects[truth.object_id as usize].dynamic {
                    moving[band(p)].add(kept);
                    let entry = objects.entry(truth.object_id).or_default();
                    entry.0.add(kept);
                    entry.1 += p[0].hypot(p[1]);
                }
            }
            for (id, (tally, range_sum_m)) in objects {
                if tally.seen >= MIN_POINTS && (tally.kept as f64) < LISTED_BELOW_SHARE * tally.seen as f64 {
                    println!(
                        "seed {seed} frame {k:>2}: object {id} ({:?}) keeps {} of {} points, {:.1} m away",
                        sim.objects[id as usize].kind,
                        tally.kept,
                        tally.seen,
                        range_sum_m / tally.seen as f32
                    );
                }
            }
        }
    }
    println!("{:<10} {:>28} {:>28}", "range", "moving non-ground kept", "true ground kept");
    for b in 0..BANDS {
        let (m, g) = (moving[b], ground[b]);
        println!(
            "{:<10} {:>28} {:>28}",
            band_label(b),
            format!("{} of {} ({:.1} %)", m.kept, m.seen, m.share_pct()),
            format!("{} of {} ({:.2} %)", g.kept, g.seen, g.share_pct())
        );
    }
    Ok(())
}

/// The share of points the pre-filter with `params` keeps per band in the six KITTI frames of
/// `dir`.
fn kitti(dir: &std::path::Path, params: &PreprocessParams) -> anyhow::Result<()> {
    for k in 0..6 {
        let path = dir.join(format!("{k:06}.bin"));
        let bytes = std::fs::read(&path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let points = read_kitti_bin(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let keep = kept_mask(&points, params)?;
        let mut bands = [Tally::default(); BANDS];
        for (p, &kept) in points.iter().zip(&keep) {
            bands[band(p)].add(kept);
        }
        let line: Vec<String> =
            (0..BANDS).map(|b| format!("{} {:.1} %", band_label(b), bands[b].share_pct())).collect();
        println!("KITTI frame {k}: kept {}", line.join(", "));
    }
    Ok(())
}
