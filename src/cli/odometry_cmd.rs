//! `mbnt odometry`: estimate the sensor poses of frame files and print them in KITTI's
//! poses.txt layout (per frame, the first three rows of the 4 x 4 sensor-to-world matrix,
//! row-major, 12 numbers per line; frame 0 is the identity).

use std::io::Write;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use nalgebra::Isometry3;

use super::fit_cmd::{frame_paths, read_timestamps};
use super::frames::FileFrames;
use crate::odometry::{OdometryParams, ReadOrOdometryError, estimate_poses_from, from_row_major, to_row_major};

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

/// Runs `mbnt odometry`. The frames are read one at a time as the odometry reaches them (it keeps
/// only their downsampled clouds), so a long log never sits in memory whole.
pub fn run(args: OdometryArgs) -> anyhow::Result<()> {
    let paths = frame_paths(&args.frames)?;
    let frame_count = paths.len();
    let timestamps_s = args.timestamps.as_deref().map(read_timestamps).transpose()?;
    let truth = args.ground_truth.as_deref().map(|p| read_poses(p, frame_count)).transpose()?;
    let files = FileFrames::new(paths, None, None)?;
    let params = OdometryParams {
        voxel_m: args.voxel_m,
        max_range_m: args.max_range_m,
        min_range_m: args.min_range_m,
        ..OdometryParams::default()
    };
    let started = std::time::Instant::now();
    let mut points_read = 0usize;
    let bar = super::progress::bar(frame_count, "odometry");
    let mut read_frame = |k: usize| {
        let frame = files.frame(k)?;
        points_read += frame.len();
        Ok::<_, anyhow::Error>(frame.into())
    };
    let estimate =
        estimate_poses_from(frame_count, &mut read_frame, timestamps_s.as_deref(), &params, &mut |done, _| {
            bar.set_position(done as u64);
            ControlFlow::Continue(())
        })
        .map_err(|e| match e {
            // The reader's error already names the file.
            ReadOrOdometryError::Read { error, .. } => error,
            ReadOrOdometryError::Odometry(e) => e.into(),
        })?;
    bar.finish_and_clear();
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
    eprintln!("odometry of {frame_count} frames ({points_read} points) in {seconds:.2} s");
    if let Some(truth) = truth {
        let e = pose_errors(&estimate.world_from_sensor, &truth);
        eprintln!(
            "against the ground truth after {} frames: translation {:.3} m = {:.3} % of {:.2} m travelled, \
             rotation {:.4} deg (heading {:.4} deg)",
            frame_count - 1,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Point;
    use crate::odometry::estimate_poses;
    use crate::sim::{SimParams, simulate};

    fn write_bin(path: &Path, points: &[Point]) {
        let bytes: Vec<u8> = points.iter().flat_map(|p| [p[0], p[1], p[2], 0.0]).flat_map(f32::to_le_bytes).collect();
        std::fs::write(path, bytes).unwrap();
    }

    fn args(frames: Vec<PathBuf>, timestamps: PathBuf, out: PathBuf) -> OdometryArgs {
        let defaults = OdometryParams::default();
        OdometryArgs {
            frames,
            timestamps: Some(timestamps),
            ground_truth: None,
            voxel_m: defaults.voxel_m,
            max_range_m: defaults.max_range_m,
            min_range_m: defaults.min_range_m,
            out: Some(out),
        }
    }

    /// The command reads its files one at a time; what it prints must be what the odometry gives
    /// for the same frames held in memory, to the printed digit, and a file that does not read
    /// stops it with the file's name.
    #[test]
    fn the_command_prints_the_poses_of_the_frames_in_memory_and_names_a_file_that_does_not_read() {
        let sim = simulate(&SimParams::log(3, 4)).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let paths: Vec<PathBuf> = (0..sim.frames.len()).map(|k| dir.path().join(format!("{k:06}.bin"))).collect();
        for (path, frame) in paths.iter().zip(&sim.frames) {
            write_bin(path, frame);
        }
        let times = dir.path().join("times.txt");
        let text: Vec<String> = sim.timestamps_s.iter().map(|t| format!("{t}")).collect();
        std::fs::write(&times, text.join("\n")).unwrap();
        let out = dir.path().join("poses.txt");
        run(args(vec![dir.path().to_path_buf()], times.clone(), out.clone())).unwrap();
        let printed = std::fs::read_to_string(&out).unwrap();

        // The .bin files hold f32 coordinates, as the simulator's frames do: the same points.
        let in_memory =
            estimate_poses(&sim.frames, Some(&sim.timestamps_s), &OdometryParams::default(), &mut |_, _| {
                ControlFlow::Continue(())
            })
            .unwrap();
        let expected: Vec<String> = in_memory
            .world_from_sensor
            .iter()
            .map(|pose| to_row_major(pose)[..12].iter().map(|v| format!("{v:.9e}")).collect::<Vec<_>>().join(" "))
            .collect();
        assert_eq!(printed.lines().collect::<Vec<_>>(), expected);
        // The sequence moves: the poses are not all the identity.
        assert!(in_memory.world_from_sensor[3].translation.vector.norm() > 1.0);

        // Frame 2 removed after the paths were listed: the error names it.
        let mut listed = paths.clone();
        let gone = dir.path().join("gone.bin");
        listed[2] = gone;
        let err = run(args(listed, times, out)).unwrap_err();
        assert!(format!("{err:#}").contains("gone.bin"), "{err:#}");
    }
}
