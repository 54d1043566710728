//! `mbnt simulate`: write a synthetic LiDAR sequence with exact ground truth to a directory.
//!
//! Layout of `--out DIR`:
//! - `frames/000000.bin` ... (KITTI float32 x, y, z, intensity = 0) or `.ply` (binary PLY); or,
//!   with `--format av2`, an Argoverse 2 log instead: `sensors/lidar/<timestamp_ns>.feather`
//!   sweeps (LZ4, float16 x, y, z) and `city_SE3_egovehicle.feather` (the sensor poses), frame k
//!   at [`AV2_FIRST_TIMESTAMP_NS`] + k / frame rate;
//! - `timestamps.txt`: one time (s) per line;
//! - `poses.txt`: one sensor-to-world pose per line, 16 numbers, row-major 4 x 4;
//! - `ground_truth.npz`: per frame k, `flow_KKK` (N_k x 3, exact scene flow to frame k+1, in
//!   frame k+1's sensor coordinates minus the point), `object_id_KKK`, `is_ground_KKK`,
//!   `is_dynamic_KKK`; `traj_000` (N_0 x T x 3, frame 0's points at every frame time, each in
//!   that frame's sensor coordinates); `timestamps`; `ego_poses` (T x 4 x 4);
//! - `top_down_KKK.png` for the frames chosen by `--png`, and `summary.json`.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::geometry::Point;
use crate::io::npz::NpzWriter;
use crate::sim::{SimParams, SimSequence, render_top_down_png, simulate};

/// Arguments of `mbnt simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Seed of the scene, the motions and the sensor noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Number of frames (sweeps).
    #[arg(long, default_value_t = 25)]
    pub frames: usize,
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Frame file format: `bin` (KITTI), `ply` (binary little-endian) or `av2` (an Argoverse 2
    /// log layout, for `mbnt label av2`).
    #[arg(long, default_value = "bin")]
    pub format: String,
    /// Frames rendered as top-down PNG pictures (comma-separated indices).
    #[arg(long, value_delimiter = ',', default_value = "0")]
    pub png: Vec<usize>,
    /// Picture size (pixels per side).
    #[arg(long, default_value_t = 1024)]
    pub png_size: u32,
}

/// Runs `mbnt simulate`.
pub fn run(args: SimulateArgs) -> anyhow::Result<()> {
    if !["bin", "ply", "av2"].contains(&args.format.as_str()) {
        anyhow::bail!("--format must be bin, ply or av2, got {:?}", args.format);
    }
    let started = std::time::Instant::now();
    let sim = simulate(&SimParams::log(args.seed, args.frames))?;
    eprintln!(
        "simulated {} frames in {:.2} s ({} points in frame 0)",
        sim.frames.len(),
        started.elapsed().as_secs_f64(),
        sim.frames[0].len()
    );
    write_sequence(&sim, &args.out, &args.format)?;
    for &k in &args.png {
        let png = render_top_down_png(&sim, k, args.png_size)?;
        let path = args.out.join(format!("top_down_{k:03}.png"));
        std::fs::write(&path, png).with_context(|| format!("writing {}", path.display()))?;
    }
    eprintln!("wrote {}", args.out.display());
    Ok(())
}

/// Timestamp (ns) of frame 0 of a simulated AV2 log: of the size of AV2's own (nanoseconds of
/// the GPS epoch in 2020), so that readers meet realistic 18-digit names.
pub const AV2_FIRST_TIMESTAMP_NS: i64 = 315_966_000_000_000_000;

/// Writes frames, timestamps, poses, ground truth and a summary of `sim` under `dir`; `format`
/// is `bin`, `ply` or `av2` (see the module documentation).
pub fn write_sequence(sim: &SimSequence, dir: &Path, format: &str) -> anyhow::Result<()> {
    if format == "av2" {
        write_av2_log(sim, dir)?;
    } else {
        let frames_dir = dir.join("frames");
        std::fs::create_dir_all(&frames_dir).with_context(|| format!("creating {}", frames_dir.display()))?;
        for (k, frame) in sim.frames.iter().enumerate() {
            let path = frames_dir.join(format!("{k:06}.{format}"));
            let bytes = if format == "ply" { ply_bytes(frame) } else { kitti_bytes(frame) };
            std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
        }
    }
    let timestamps: String = sim.timestamps_s.iter().map(|t| format!("{t:.6}\n")).collect();
    std::fs::write(dir.join("timestamps.txt"), timestamps)?;
    let poses: String = sim
        .ego_poses
        .iter()
        .map(|p| p.iter().map(|v| format!("{v:.9}")).collect::<Vec<_>>().join(" ") + "\n")
        .collect();
    std::fs::write(dir.join("poses.txt"), poses)?;

    let t = sim.frames.len();
    let path = dir.join("ground_truth.npz");
    let file = std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    let mut npz = NpzWriter::new(std::io::BufWriter::new(file));
    for k in 0..t {
        let n = sim.frames[k].len();
        if k + 1 < t {
            npz.add_f32(&format!("flow_{k:03}"), &[n, 3], sim.scene_flow(k)?.as_flattened())?;
        }
        let ids: Vec<i32> = sim.truth[k].iter().map(|p| p.object_id as i32).collect();
        npz.add_i32(&format!("object_id_{k:03}"), &[n], &ids)?;
        let ground: Vec<bool> = sim.truth[k].iter().map(|p| p.is_ground).collect();
        npz.add_bool(&format!("is_ground_{k:03}"), &[n], &ground)?;
        npz.add_bool(&format!("is_dynamic_{k:03}"), &[n], &sim.is_dynamic(k)?)?;
    }
    let n0 = sim.frames[0].len();
    let mut traj = vec![[0f32; 3]; n0 * t];
    for j in 0..t {
        for (i, p) in sim.positions_at(0, j)?.into_iter().enumerate() {
            traj[i * t + j] = p;
        }
    }
    npz.add_f32("traj_000", &[n0, t, 3], traj.as_flattened())?;
    npz.add_f64("timestamps", &[t], &sim.timestamps_s)?;
    npz.add_f64("ego_poses", &[t, 4, 4], sim.ego_poses.as_flattened())?;
    npz.finish()?.flush()?;
    std::fs::write(dir.join("summary.json"), serde_json::to_vec_pretty(&sim.summary)?)?;
    Ok(())
}

/// The sweeps and poses of `sim` as an Argoverse 2 log under `dir`.
#[cfg(feature = "av2")]
fn write_av2_log(sim: &SimSequence, dir: &Path) -> anyhow::Result<()> {
    use crate::io::av2::{LIDAR_DIR, POSES_FILE, write_city_poses, write_sweep};
    let lidar = dir.join(LIDAR_DIR);
    std::fs::create_dir_all(&lidar).with_context(|| format!("creating {}", lidar.display()))?;
    let timestamps_ns: Vec<i64> =
        sim.timestamps_s.iter().map(|&t| AV2_FIRST_TIMESTAMP_NS + (t * 1e9).round() as i64).collect();
    for (frame, timestamp_ns) in sim.frames.iter().zip(&timestamps_ns) {
        let path = lidar.join(format!("{timestamp_ns}.feather"));
        let bytes = write_sweep(Vec::new(), frame)?;
        std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
    }
    let path = dir.join(POSES_FILE);
    std::fs::write(&path, write_city_poses(Vec::new(), &timestamps_ns, &sim.ego_poses)?)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

#[cfg(not(feature = "av2"))]
fn write_av2_log(_sim: &SimSequence, _dir: &Path) -> anyhow::Result<()> {
    anyhow::bail!("--format av2 needs the `av2` cargo feature (Arrow support), which this build lacks")
}

/// KITTI velodyne layout: float32 x, y, z, intensity per point (intensity 0: not simulated).
pub fn kitti_bytes(points: &[Point]) -> Vec<u8> {
    let mut out = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in [p[0], p[1], p[2], 0.0] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Binary little-endian PLY with float x, y, z.
fn ply_bytes(points: &[Point]) -> Vec<u8> {
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment mbnt simulate\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nend_header\n",
        points.len()
    );
    let mut out = header.into_bytes();
    out.reserve(points.len() * 12);
    for p in points {
        for v in p {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}
