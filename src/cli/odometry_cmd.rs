//! `mbnt odometry`: estimate the sensor poses of frame files and print them in KITTI's
//! poses.txt layout (per frame, the first three rows of the 4 x 4 sensor-to-world matrix,
//! row-major, 12 numbers per line; frame 0 is the identity).

use std::io::Write;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use nalgebra::Isometry3;

use super::fit_cmd::{frame_paths, read_frames, read_timestamps};
use crate::odometry::{OdometryParams, estimate_poses, from_row_major, to_row_major};

/// Arguments of `mbnt odometry`.
#[derive(Debug, clap::Args)]
pub struct OdometryArgs {
    /// Frame files in time order, or one directory whose point-cloud files sort in time order.
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// A text file with one timestamp (s) per frame; frames are taken as evenly spaced otherwise.
    #[arg(long)]
    pub timestamps: Option<PathBuf>,
    /// Ground-truth poses, 12 (KITTI poses.txt) or 16 numbers per line, sensor-to-world,
    /// row-major; the first line per frame is used. Prints the translation error (% of the distance travelled)
    /// and the rotation error (degrees) of the last frame, relative to frame 0, to stderr.
    #[arg(long)]
    pub ground_truth: Option<PathBuf>,
    /// Voxel edge of the local map (m).
    #[arg(long, default_value_t = OdometryParams::default().voxel_m)]
    pub voxel_m: f32,
    /// Points farther than this from the sensor are ignored (m).
    #[arg(long, default_value_t = OdometryParams::default().max_range_m)]
    pub max_range_m: f32,
    /// Points nearer than this are ignored (m).
    #[arg(long, default_value_t = OdometryParams::default().min_range_m)]
    pub min_range_m: f32,
    /// Write the poses to this file instead of stdout.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Runs `mbnt odometry`.
pub fn run(args: OdometryArgs) -> anyhow::Result<()> {
    let paths = frame_paths(&args.frames)?;
    let frames = read_frames(&paths)?;
    let timestamps_s = args.timestamps.as_deref().map(read_timestamps).transpose()?;
    let truth = args.ground_truth.as_deref().map(|p| read_poses(p, frames.len())).transpose()?;
    let params = OdometryParams {
        voxel_m: args.voxel_m,
        max_range_m: args.max_range_m,
        min_range_m: args.min_range_m,
        ..OdometryParams::default()
    };
    let started = std::time::Instant::now();
    let estimate = estimate_poses(&frames, timestamps_s.as_deref(), &params, &mut |_, _| ControlFlow::Continue(()))?;
    let seconds = started.elapsed().as_secs_f64();
    let mut text = String::new();
    for pose in &estimate.world_from_sensor {
        let m = to_row_major(pose);
        let line: Vec<String> = m[..12].iter().map(|v| format!("{v:.9e}")).collect();
        text.push_str(&line.join(" "));
        text.push('\n');
    }
    match &args.out {
        Some(path) => std::fs::write(path, &text).with_context(|| format!("writing {}", path.display()))?,
        None => std::io::stdout().lock().write_all(text.as_bytes())?,
    }
    eprintln!(
        "odometry of {} frames ({} points) in {seconds:.2} s",
        frames.len(),
        frames.iter().map(Vec::len).sum::<usize>()
    );
    if let Some(truth) = truth {
        let e = pose_errors(&estimate.world_from_sensor, &truth);
        eprintln!(
            "against the ground truth after {} frames: translation {:.3} m = {:.3} % of {:.2} m travelled, \
             rotation {:.4} deg (heading {:.4} deg)",
            frames.len() - 1,
            e.translation_m,
            100.0 * e.translation_m / e.travelled_m,
            e.travelled_m,
            e.rotation_deg,
            e.heading_deg
        );
    }
    Ok(())
}

/// How far an estimate's last pose is from the truth's, both relative to their frame 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseErrors {
    /// Distance between the last positions (m).
    pub translation_m: f64,
    /// Path length of the truth (m).
    pub travelled_m: f64,
    /// Angle of the relative rotation of the last poses (degrees).
    pub rotation_deg: f64,
    /// Difference of the yaw angles about the world z axis (degrees, absolute).
    pub heading_deg: f64,
}

/// The errors of `estimate` (frame 0 = identity) against `truth` (any world frame).
pub fn pose_errors(estimate: &[Isometry3<f64>], truth: &[Isometry3<f64>]) -> PoseErrors {
    let n = truth.len() - 1;
    let truth_n = truth[0].inverse() * truth[n];
    let e = truth_n.inverse() * estimate[n];
    let travelled_m = truth.windows(2).map(|w| (w[1].translation.vector - w[0].translation.vector).norm()).sum();
    let yaw = |p: &Isometry3<f64>| p.rotation.euler_angles().2;
    let d = yaw(&estimate[n]) - yaw(&truth_n);
    let heading_rad = d.sin().atan2(d.cos()).abs();
    PoseErrors {
        translation_m: (estimate[n].translation.vector - truth_n.translation.vector).norm(),
        travelled_m,
        rotation_deg: e.rotation.angle().to_degrees(),
        heading_deg: heading_rad.to_degrees(),
    }
}

/// Reads `frames` poses, 12 or 16 numbers each, all in one layout.
pub fn read_poses(path: &Path, frames: usize) -> anyhow::Result<Vec<Isometry3<f64>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut poses = Vec::new();
    for (line_no, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let numbers: Vec<f64> = line
            .split_whitespace()
            .map(|w| w.parse::<f64>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("{} line {}: not numbers", path.display(), line_no + 1))?;
        let pose = from_row_major(&numbers).with_context(|| {
            format!("{} line {}: not a rigid transform of 12 or 16 numbers", path.display(), line_no + 1)
        })?;
        poses.push(pose);
    }
    if poses.len() < frames {
        bail!("{} has {} poses for {frames} frames", path.display(), poses.len());
    }
    poses.truncate(frames);
    Ok(poses)
}
