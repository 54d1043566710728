//! `mbnt fit`: fit a method to frame files offline and write trajectories and labels.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

use super::frames::{FileFrames, peak_rss_bytes};
use super::progress;
use crate::fit::windows::{NoFinishedWindows, fit_log};
use crate::fit::{FitParams, FrameSource, Method, Mode, ValidFitParams};
use crate::io::npz::NpzWriter;
use crate::model::FittedModel;

/// Arguments of `mbnt fit`.
#[derive(Debug, clap::Args)]
pub struct FitArgs {
    /// Frame files in time order, or one directory whose point-cloud files sort in time order.
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// A text file with one timestamp (s) per frame; frame indices are the time axis otherwise.
    #[arg(long)]
    pub timestamps: Option<PathBuf>,
    /// A text file of sensor-to-world poses, one per frame, 12 (KITTI poses.txt, row-major 3 x 4)
    /// or 16 (row-major 4 x 4) numbers per line: the ego motion is then removed and MBNT's scene
    /// model (still world + moving bodies) applies.
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// The method and its parameters.
    #[command(flatten)]
    pub fit: FitOptions,
    /// Output `.npz`: `traj_KKK` (N_k x T x 3 positions of frame k's points at every frame
    /// time) for the frames chosen by --trajectories, `flow_KKK` scene-flow labels, `object_KKK`
    /// (the moving body of each point of frame k, -1 for none), `timestamps`.
    #[arg(long, default_value = "mbnt-fit.npz")]
    pub out: PathBuf,
    /// Frames whose dense trajectories are written: `first` (frame 0), `all`, or `none`.
    #[arg(long, default_value = "first")]
    pub trajectories: String,
    /// Also write the fitted model (loadable by the service's format) to this file.
    #[arg(long)]
    pub model_out: Option<PathBuf>,
}

/// The method and parameter options shared by `mbnt fit` and `mbnt label`.
#[derive(Debug, Clone, clap::Args)]
pub struct FitOptions {
    /// The method.
    #[arg(long, default_value = "mbnt")]
    pub method: Method,
    /// Hyper-parameters as JSON (the job `params` object of the API), e.g. '{"iterations": 200}'.
    #[arg(long)]
    pub params: Option<String>,
    /// Shorthand for the `iterations` parameter.
    #[arg(long)]
    pub iterations: Option<usize>,
    /// Shorthand for the `seed` parameter.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Shorthand for the `mode` parameter: `fast` (default) or `faithful` (method.md exactly).
    #[arg(long)]
    pub mode: Option<Mode>,
}

impl FitOptions {
    /// The parameters: `--params` with the shorthands over it, checked for the method.
    pub fn params(&self) -> anyhow::Result<ValidFitParams> {
        let mut params: FitParams = match &self.params {
            Some(json) => serde_json::from_str(json).context("--params is not a valid parameter object")?,
            None => FitParams::default(),
        };
        params.iterations = self.iterations.or(params.iterations);
        params.seed = self.seed.or(params.seed);
        params.mode = self.mode.or(params.mode);
        Ok(params.check(self.method)?)
    }
}

/// Point-cloud file endings taken from a directory.
const FRAME_EXTENSIONS: [&str; 6] = ["bin", "ply", "pcd", "npy", "kitti", "feather"];

pub(crate) fn frame_paths(inputs: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    if let [dir] = inputs
        && dir.is_dir()
    {
        let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
            .with_context(|| format!("reading directory {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().and_then(|e| e.to_str()).is_some_and(|e| FRAME_EXTENSIONS.contains(&e)))
            .collect();
        paths.sort();
        if paths.is_empty() {
            bail!("no point-cloud files ({}) in {}", FRAME_EXTENSIONS.join(", "), dir.display());
        }
        return Ok(paths);
    }
    Ok(inputs.to_vec())
}

/// Reads whitespace-separated timestamps (s), one per frame.
pub fn read_timestamps(path: &Path) -> anyhow::Result<Vec<f64>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    text.split_whitespace()
        .map(|w| w.parse::<f64>().with_context(|| format!("bad timestamp {w:?} in {}", path.display())))
        .collect()
}

/// Fits `sequence` (of `points` points in all) as one job, showing a bar, and prints the plan
/// before and the report after to stderr. A long log's frames are read one window at a time.
pub fn fit_reported(
    sequence: &dyn FrameSource,
    points: usize,
    method: Method,
    params: &ValidFitParams,
) -> anyhow::Result<FittedModel> {
    let iterations = if crate::fit::windows::is_windowed(sequence, params) {
        format!(
            "windows of {} frames overlapping by {} or more, {} iterations each",
            params.window_frames,
            params.window_overlap_frames,
            params.iterations_per_window()
        )
    } else {
        format!("{} iterations", params.iterations)
    };
    eprintln!("fitting {} to {} frames ({} points) with {iterations}", method.name(), sequence.frame_count(), points,);
    let mut bar = progress::FitBar::new();
    let fitted = fit_log(sequence, method, params, &mut NoFinishedWindows, &mut |p| bar.update(p));
    bar.finish();
    let model = fitted?;
    let report = model.report();
    for (k, f) in report.frames.iter().enumerate() {
        eprintln!(
            "frame {k}: {} points, {} ground, {} out of range, {} fitted, {} clusters",
            f.input_points, f.ground_points, f.out_of_range_points, f.fitted_points, f.clusters
        );
    }
    if params.moving_bodies || params.rigid_tracks {
        eprintln!(
            "{} moving bodies, {} rigid tracks, {} points answered by the network ({:.1} s)",
            report.moving_bodies, report.rigid_tracks, report.free_points, report.rigid_tracks_seconds
        );
    }
    eprintln!("fit took {:.1} s", report.fit_seconds);
    Ok(model)
}

/// Runs `mbnt fit`.
pub fn run(args: FitArgs) -> anyhow::Result<()> {
    let paths = frame_paths(&args.frames)?;
    let timestamps_s = args.timestamps.as_deref().map(read_timestamps).transpose()?;
    let params = args.fit.params()?;
    let poses = match &args.poses {
        Some(path) => Some(
            super::odometry_cmd::read_poses(path, paths.len())?.iter().map(crate::odometry::to_row_major).collect(),
        ),
        None => None,
    };
    // Frames are read when the fit needs them (a long log one window at a time) and again, one
    // at a time, for the labels: memory is bounded by a window, not by the log. Reading each
    // once first fails on a bad file before any fitting.
    let sequence = FileFrames::new(paths, timestamps_s, poses)?;
    let point_counts = sequence.check()?;
    let model = fit_reported(&sequence, point_counts.iter().sum(), args.fit.method, &params)?;

    let axis = model.time_axis().clone();
    let times: Vec<f64> = (0..axis.frames()).map(|k| axis.frame_time(k)).collect();
    let file = std::fs::File::create(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut npz = NpzWriter::new(std::io::BufWriter::new(file));
    let traj_frames: Vec<usize> = match args.trajectories.as_str() {
        "first" => vec![0],
        "all" => (0..axis.frames()).collect(),
        "none" => Vec::new(),
        other => bail!("--trajectories must be first, all or none, not {other:?}"),
    };
    // One frame at a time: its trajectories when asked, its scene flow to the next frame (none
    // for the last), and the moving body (object id) of every point, -1 for none, as the
    // service's labels.
    let bar = progress::bar(axis.frames(), "writing labels");
    for k in 0..axis.frames() {
        let points = sequence.frame(k)?;
        if traj_frames.contains(&k) {
            let positions = model.positions(&points, times[k], &times)?;
            npz.add_f32(&format!("traj_{k:03}"), &[points.len(), times.len(), 3], positions.as_flattened())?;
        }
        if k + 1 < axis.frames() {
            let flow = model.frame_scene_flow(k, &points)?;
            npz.add_f32(&format!("flow_{k:03}"), &[flow.len(), 3], flow.as_flattened())?;
        }
        let ids = model.frame_object_ids(k, &points)?;
        npz.add_i32(&format!("object_{k:03}"), &[ids.len()], &ids)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    npz.add_f64("timestamps", &[times.len()], &times)?;
    npz.finish()?.flush()?;
    eprintln!("wrote {}", args.out.display());
    if let Some(path) = &args.model_out {
        let bytes = model.to_bytes().context("the model is not saved")?;
        std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    if let Some(peak) = peak_rss_bytes() {
        eprintln!("peak memory {:.0} MB", peak as f64 / 1e6);
    }
    Ok(())
}
