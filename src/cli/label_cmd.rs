//! `mbnt label`: from a log directory in a dataset's own layout to one scene-flow label file per
//! frame, in one command: the frames, their times and poses are read, the whole log is fitted as
//! one job (as `mbnt fit` does: windows for a long log) and the flow of every frame to the next
//! is written.
//!
//! Flow convention (that of the service's label export): the flow of a point of frame k is its
//! position at frame k+1's time in frame k+1's sensor (AV2: ego-vehicle) coordinates minus its
//! position in frame k's, so a still point's flow is the apparent motion the ego motion gives
//! it, as in Argoverse 2's scene-flow labels ("in the first sweep's egovehicle frame", the rigid
//! ego flow of a static point being `ego_1_SE3_ego_0 * p - p`). The last frame has no next
//! frame and gets no label file, as in the service's export and AV2's labels.
//!
//! Output files, one per frame but the last, named after the frame:
//! - `feather` (default for AV2, named `<timestamp_ns>.feather`): Feather v2 with `flow_tx_m`,
//!   `flow_ty_m`, `flow_tz_m` (float32, m), `is_valid` (bool, all true: the model gives every
//!   point a flow) and `object_id` (int32, the moving body of the point, -1 for none): the
//!   column names ZeroFlow / SceneFlowZoo read (AV2's challenge files store float16 flows and
//!   `is_dynamic`; float32 keeps the model's precision).
//! - `npz` (default for KITTI, named `<frame>.npz`): `flow` (float32, (N, 3)), `is_valid`,
//!   `object_id`, read with `numpy.load`.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use nalgebra::Isometry3;

use super::fit_cmd::{FitOptions, fit_reported, read_timestamps};
use super::frames::FileFrames;
use super::progress;
use crate::fit::FrameSource;
use crate::geometry::Point;
use crate::io::labels::write_flow_npz;
use crate::odometry::{from_row_major, to_row_major};

/// Arguments of `mbnt label`.
#[derive(Debug, clap::Args)]
pub struct LabelArgs {
    /// The dataset layout of the log.
    #[command(subcommand)]
    pub layout: Layout,
}

/// The log layouts `mbnt label` reads.
#[derive(Debug, clap::Subcommand)]
pub enum Layout {
    /// An Argoverse 2 sensor log: LOG_DIR/sensors/lidar/<timestamp_ns>.feather sweeps and
    /// LOG_DIR/city_SE3_egovehicle.feather ego poses.
    Av2(Av2Args),
    /// A KITTI odometry sequence: SEQ_DIR/velodyne/*.bin, SEQ_DIR/times.txt, and
    /// SEQ_DIR/poses.txt (camera-0 poses, converted with SEQ_DIR/calib.txt's Tr) when present.
    Kitti(KittiArgs),
}

/// Arguments of `mbnt label av2`.
#[derive(Debug, clap::Args)]
pub struct Av2Args {
    /// The log directory.
    pub log_dir: PathBuf,
    /// Where the labels go.
    #[command(flatten)]
    pub output: OutputOptions,
    /// The method and its parameters.
    #[command(flatten)]
    pub fit: FitOptions,
}

/// Arguments of `mbnt label kitti`.
#[derive(Debug, clap::Args)]
pub struct KittiArgs {
    /// The sequence directory.
    pub seq_dir: PathBuf,
    /// LiDAR (Velodyne) sensor-to-world poses, 12 or 16 numbers per line as `mbnt fit --poses`,
    /// used instead of SEQ_DIR/poses.txt (e.g. poses already converted to the Velodyne frame).
    #[arg(long, conflicts_with = "no_poses")]
    pub poses: Option<PathBuf>,
    /// Ignore SEQ_DIR/poses.txt: the fit estimates the ego motion itself.
    #[arg(long)]
    pub no_poses: bool,
    /// Where the labels go.
    #[command(flatten)]
    pub output: OutputOptions,
    /// The method and its parameters.
    #[command(flatten)]
    pub fit: FitOptions,
}

/// Output options of `mbnt label`.
#[derive(Debug, Clone, clap::Args)]
pub struct OutputOptions {
    /// Output directory (created if missing); one label file per frame but the last.
    #[arg(long)]
    pub out: PathBuf,
    /// Label file format: `feather` (Argoverse 2 / ZeroFlow columns) or `npz` (NumPy). Default:
    /// feather for av2, npz for kitti.
    #[arg(long)]
    pub format: Option<LabelFormat>,
}

/// Format of a label file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LabelFormat {
    /// Feather v2: `flow_tx_m`, `flow_ty_m`, `flow_tz_m`, `is_valid`, `object_id`.
    Feather,
    /// NumPy `.npz`: `flow`, `is_valid`, `object_id`.
    Npz,
}

impl LabelFormat {
    fn extension(self) -> &'static str {
        match self {
            LabelFormat::Feather => "feather",
            LabelFormat::Npz => "npz",
        }
    }
}

/// A log on disk: the fit's input and the name of each frame's label file.
struct Log {
    /// The frame files with their times and poses, read when needed (a long log's fit reads
    /// one window at a time, the labels one frame at a time).
    frames: FileFrames,
    /// Label file name of each frame, without extension.
    names: Vec<String>,
}

/// Runs `mbnt label`.
pub fn run(args: LabelArgs) -> anyhow::Result<()> {
    match args.layout {
        Layout::Av2(a) => {
            let log = read_av2(&a.log_dir)?;
            label(log, &a.fit, &a.output.out, a.output.format.unwrap_or(LabelFormat::Feather))
        }
        Layout::Kitti(a) => {
            let log = read_kitti(&a.seq_dir, a.poses.as_deref(), a.no_poses)?;
            label(log, &a.fit, &a.output.out, a.output.format.unwrap_or(LabelFormat::Npz))
        }
    }
}

/// Fits `log` as one job and writes a label file per frame but the last into `out`.
fn label(log: Log, fit: &FitOptions, out: &Path, format: LabelFormat) -> anyhow::Result<()> {
    if cfg!(not(feature = "av2")) && format == LabelFormat::Feather {
        bail!("feather labels need the `av2` cargo feature (this build has none): use --format npz");
    }
    let params = fit.params()?;
    let points = log.frames.check()?.iter().sum();
    let model = fit_reported(&log.frames, points, fit.method, &params)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    // One frame at a time: memory bounded by the fit's window, not by the log.
    let labelled = log.frames.frame_count().saturating_sub(1);
    let bar = progress::bar(labelled, "writing labels");
    for k in 0..labelled {
        let points = log.frames.frame(k)?;
        let flow = model.frame_scene_flow(k, &points)?;
        let path = out.join(format!("{}.{}", log.names[k], format.extension()));
        write_label_file(&path, format, &flow, &model.frame_object_ids(k, &points)?)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    eprintln!(
        "wrote {} label files to {} (the last frame, {}, has no next frame and no labels)",
        labelled,
        out.display(),
        log.names.last().map_or("", String::as_str)
    );
    Ok(())
}

fn write_label_file(path: &Path, format: LabelFormat, flow: &[Point], object_ids: &[i32]) -> anyhow::Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let w = std::io::BufWriter::new(file);
    let w = match format {
        LabelFormat::Npz => write_flow_npz(w, flow, None, Some(object_ids)),
        #[cfg(feature = "av2")]
        LabelFormat::Feather => crate::io::labels::write_flow_feather(w, flow, None, Some(object_ids)),
        #[cfg(not(feature = "av2"))]
        LabelFormat::Feather => bail!("feather labels need the `av2` cargo feature: use --format npz"),
    }
    .with_context(|| format!("writing {}", path.display()))?;
    w.into_inner().map_err(|e| e.into_error()).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Reads an AV2 log: sweeps by timestamp, times in seconds from the first sweep, ego poses.
#[cfg(feature = "av2")]
fn read_av2(dir: &Path) -> anyhow::Result<Log> {
    let log = crate::io::av2::read_log(dir).with_context(|| format!("reading the AV2 log {}", dir.display()))?;
    Ok(Log {
        names: log.timestamps_ns.iter().map(i64::to_string).collect(),
        frames: FileFrames::new(log.sweep_paths.clone(), Some(log.timestamps_s()), Some(log.poses))?,
    })
}

#[cfg(not(feature = "av2"))]
fn read_av2(_dir: &Path) -> anyhow::Result<Log> {
    bail!("AV2 logs need the `av2` cargo feature (Arrow support), which this build lacks")
}

/// Reads a KITTI odometry sequence (see [`Layout::Kitti`]); `poses` (LiDAR poses) replaces
/// `poses.txt`, `no_poses` ignores it.
fn read_kitti(dir: &Path, poses: Option<&Path>, no_poses: bool) -> anyhow::Result<Log> {
    let velodyne = dir.join("velodyne");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&velodyne)
        .with_context(|| format!("listing {} (a KITTI sequence keeps its scans in velodyne/)", velodyne.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().and_then(|e| e.to_str()) == Some("bin"))
        .collect();
    paths.sort();
    if paths.is_empty() {
        bail!("no .bin scans in {}", velodyne.display());
    }
    let names: Vec<String> =
        paths.iter().map(|p| p.file_stem().and_then(|s| s.to_str()).unwrap_or_default().to_owned()).collect();
    let times_path = dir.join("times.txt");
    let timestamps_s = if times_path.exists() {
        let times = read_timestamps(&times_path)?;
        if times.len() != paths.len() {
            bail!("{} has {} times for {} scans", times_path.display(), times.len(), paths.len());
        }
        Some(times)
    } else {
        eprintln!("no {}: frame indices are the time axis", times_path.display());
        None
    };
    let poses_path = dir.join("poses.txt");
    let poses: Option<Vec<[f64; 16]>> = match poses {
        Some(path) => Some(super::odometry_cmd::read_poses(path, paths.len())?.iter().map(to_row_major).collect()),
        None if no_poses || !poses_path.exists() => {
            eprintln!("no poses: the fit estimates the ego motion");
            None
        }
        None => {
            let calib_path = dir.join("calib.txt");
            if !calib_path.exists() {
                bail!(
                    "{} holds KITTI's camera-0 poses; {} (its Tr line) is needed to turn them into Velodyne poses \
                     (or give Velodyne poses with --poses, or ignore poses.txt with --no-poses)",
                    poses_path.display(),
                    calib_path.display()
                );
            }
            let velo_to_cam = read_velo_to_cam(&calib_path)?;
            let camera = super::odometry_cmd::read_poses(&poses_path, paths.len())?;
            Some(camera.iter().map(|p| to_row_major(&velodyne_pose(p, &velo_to_cam))).collect())
        }
    };
    Ok(Log { frames: FileFrames::new(paths, timestamps_s, poses)?, names })
}

/// The Velodyne-to-camera-0 transform `Tr` of a KITTI odometry calib.txt (line `Tr:` or
/// `Tr_velo_to_cam:`, 12 numbers, row-major 3 x 4).
pub fn read_velo_to_cam(path: &Path) -> anyhow::Result<Isometry3<f64>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let line = text
        .lines()
        .find_map(|l| l.strip_prefix("Tr:").or_else(|| l.strip_prefix("Tr_velo_to_cam:")))
        .with_context(|| format!("{} has no Tr: line", path.display()))?;
    let numbers: Vec<f64> = line
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .with_context(|| format!("{}: Tr is not numbers", path.display()))?;
    if numbers.len() != 12 {
        bail!("{}: Tr has {} numbers, not 12", path.display(), numbers.len());
    }
    from_row_major(&numbers).with_context(|| format!("{}: Tr is not a rigid transform", path.display()))
}

/// A KITTI camera-0 pose (camera k to camera 0) as the Velodyne pose (Velodyne k to Velodyne 0):
/// `Tr^-1 * P * Tr`, `Tr` taking Velodyne to camera coordinates.
pub fn velodyne_pose(camera: &Isometry3<f64>, velo_to_cam: &Isometry3<f64>) -> Isometry3<f64> {
    velo_to_cam.inverse() * camera * velo_to_cam
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::simulate_cmd::kitti_bytes;
    use crate::fit::Method;
    use crate::io::npy::NpyData;
    use crate::sim::{SimParams, SimSequence, simulate};

    /// A short log of a sparse sensor (16 beams, 0.6 degree steps: about 6k points a sweep),
    /// so that a fit takes seconds on two cores.
    fn small_sim() -> SimSequence {
        let mut params = SimParams::log(3, 5);
        params.lidar.beams = 16;
        params.lidar.azimuth_step_deg = 0.6;
        simulate(&params).unwrap()
    }

    /// Few iterations of a narrow network: with the sensor poses given, the still world's flow
    /// comes from the poses, not from training.
    fn quick_fit() -> FitOptions {
        FitOptions {
            method: Method::Mbnt,
            params: Some(r#"{"hidden_width": 32}"#.into()),
            iterations: Some(10),
            seed: Some(1),
            mode: None,
        }
    }

    /// Checks frame k's labelled flow against the simulator's exact flow (same convention: frame
    /// k+1's sensor coordinates minus frame k's). Still points (not on a moving body, ground
    /// included) move only by the ego motion, which the poses give: their error must be small
    /// against that motion, which is itself large (the ego drives about 1 m a frame), so that
    /// zero or uncompensated flows fail. Moving bodies are left to the method's own tests.
    fn check_flow(sim: &SimSequence, k: usize, flow: &[Point], tolerance_m: f32) {
        let truth = sim.scene_flow(k).unwrap();
        let dynamic = sim.is_dynamic(k).unwrap();
        assert_eq!(flow.len(), truth.len(), "frame {k}: one row per point");
        let norm = |v: [f32; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let mut errors: Vec<f32> = Vec::new();
        let mut motion: Vec<f32> = Vec::new();
        for i in (0..flow.len()).filter(|&i| !dynamic[i]) {
            let (f, t) = (flow[i], truth[i]);
            errors.push(norm([f[0] - t[0], f[1] - t[1], f[2] - t[2]]));
            motion.push(norm(t));
        }
        let quantile = |v: &mut Vec<f32>, q: f64| {
            v.sort_by(f32::total_cmp);
            v[((v.len() - 1) as f64 * q) as usize]
        };
        let (median_motion, p95) = (quantile(&mut motion, 0.5), quantile(&mut errors, 0.95));
        assert!(
            median_motion > 0.5,
            "frame {k}: still points move {median_motion} m: the test would not see ego motion"
        );
        assert!(p95 < tolerance_m, "frame {k}: 95 % of still points within {p95} m of the truth (limit {tolerance_m})");
    }

    #[cfg(feature = "av2")]
    #[test]
    fn label_av2_writes_one_feather_per_sweep_matching_the_simulation() {
        let sim = small_sim();
        let dir = tempfile::tempdir().unwrap();
        let (log_dir, out) = (dir.path().join("log"), dir.path().join("labels"));
        crate::cli::simulate_cmd::write_sequence(&sim, &log_dir, "av2").unwrap();
        let output = OutputOptions { out: out.clone(), format: None };
        run(LabelArgs { layout: Layout::Av2(Av2Args { log_dir, output, fit: quick_fit() }) }).unwrap();

        let first = crate::cli::simulate_cmd::AV2_FIRST_TIMESTAMP_NS;
        let mut names: Vec<String> =
            std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        names.sort();
        // One per sweep with a next sweep, named by the sweep's timestamp (10 Hz).
        let expected: Vec<String> = (0..4).map(|k| format!("{}.feather", first + k * 100_000_000)).collect();
        assert_eq!(names, expected);
        for (k, name) in names.iter().enumerate() {
            let bytes = std::fs::read(out.join(name)).unwrap();
            let reader = arrow_ipc::reader::FileReader::try_new(std::io::Cursor::new(bytes.clone()), None).unwrap();
            let schema = reader.schema();
            let columns: Vec<(&str, String)> =
                schema.fields().iter().map(|f| (f.name().as_str(), f.data_type().to_string())).collect();
            assert_eq!(
                columns,
                [
                    ("flow_tx_m", "Float32".into()),
                    ("flow_ty_m", "Float32".into()),
                    ("flow_tz_m", "Float32".into()),
                    ("is_valid", "Boolean".into()),
                    ("object_id", "Int32".into())
                ]
            );
            let read = crate::io::feather::read_columns(&bytes, &["flow_tx_m", "flow_ty_m", "flow_tz_m", "object_id"])
                .unwrap();
            let axis = |a: usize| match &read[a] {
                crate::io::feather::Values::Float(v) => v.clone(),
                other => panic!("flow column {a}: {other:?}"),
            };
            let (x, y, z) = (axis(0), axis(1), axis(2));
            let flow: Vec<Point> = (0..x.len()).map(|i| [x[i] as f32, y[i] as f32, z[i] as f32]).collect();
            // The sweeps were stored as float16 (up to 3 cm off at 64 m): the labels are the
            // flows of those points, the truth of the exact ones; the ego turns little in a frame.
            check_flow(&sim, k, &flow, 0.05);
        }
    }

    #[test]
    fn label_kitti_converts_camera_poses_with_calib_and_writes_npz() {
        let sim = small_sim();
        let dir = tempfile::tempdir().unwrap();
        let (seq, out) = (dir.path().join("00"), dir.path().join("labels"));
        std::fs::create_dir_all(seq.join("velodyne")).unwrap();
        for (k, frame) in sim.frames.iter().enumerate() {
            std::fs::write(seq.join("velodyne").join(format!("{k:06}.bin")), kitti_bytes(frame)).unwrap();
        }
        let times: String = sim.timestamps_s.iter().map(|t| format!("{t:e}\n")).collect();
        std::fs::write(seq.join("times.txt"), times).unwrap();
        // KITTI's Velodyne-to-camera axes (camera z forward = Velodyne x, x right, y down) and
        // an offset: poses read as if in the Velodyne frame would move the world sideways.
        let tr = [0.0, -1.0, 0.0, -0.004, 0.0, 0.0, -1.0, -0.076, 1.0, 0.0, 0.0, -0.27];
        let calib = format!("P0: 7 0 6 0 0 7 1 0 0 0 1 0\nTr: {}\n", tr.map(|v| v.to_string()).join(" "));
        std::fs::write(seq.join("calib.txt"), calib).unwrap();
        let velo_to_cam = from_row_major(&tr).unwrap();
        let camera: String = sim
            .ego_poses
            .iter()
            .map(|m| {
                // Camera poses relative to frame 0's camera, as KITTI's.
                let world_velo = from_row_major(&sim.ego_poses[0]).unwrap().inverse() * from_row_major(m).unwrap();
                let cam = velo_to_cam * world_velo * velo_to_cam.inverse();
                to_row_major(&cam)[..12].iter().map(|v| format!("{v:e}")).collect::<Vec<_>>().join(" ") + "\n"
            })
            .collect();
        std::fs::write(seq.join("poses.txt"), camera).unwrap();

        let output = OutputOptions { out: out.clone(), format: None };
        let args = KittiArgs { seq_dir: seq.clone(), poses: None, no_poses: false, output, fit: quick_fit() };
        run(LabelArgs { layout: Layout::Kitti(args) }).unwrap();
        for k in 0..sim.frames.len() {
            let path = out.join(format!("{k:06}.npz"));
            if k + 1 == sim.frames.len() {
                assert!(!path.exists(), "the last frame has no next frame, so no labels");
                continue;
            }
            let arrays = crate::io::npz::read_npz(&std::fs::read(&path).unwrap()).unwrap();
            let n = sim.frames[k].len();
            let NpyData::F32(flow) = &arrays["flow"].data else { panic!("flow: {:?}", arrays["flow"]) };
            assert_eq!(arrays["flow"].shape, [n, 3]);
            assert_eq!(arrays["is_valid"].data, NpyData::Bool(vec![true; n]));
            assert_eq!(arrays["object_id"].shape, [n]);
            let flow: Vec<Point> = flow.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            // Exact float32 input: the still world's flow is the pose arithmetic's.
            check_flow(&sim, k, &flow, 0.02);
        }

        // Camera poses without the calibration cannot be used, and say so.
        std::fs::remove_file(seq.join("calib.txt")).unwrap();
        let output = OutputOptions { out, format: Some(LabelFormat::Npz) };
        let args = KittiArgs { seq_dir: seq, poses: None, no_poses: false, output, fit: quick_fit() };
        let err = run(LabelArgs { layout: Layout::Kitti(args) }).unwrap_err().to_string();
        assert!(err.contains("poses.txt holds KITTI's camera-0 poses") && err.contains("calib.txt"), "{err}");
    }

    #[test]
    fn kitti_velodyne_poses_are_the_camera_poses_seen_through_tr() {
        // A camera moving 1 m forward (camera z) is a Velodyne moving 1 m along its x.
        let tr = [0.0, -1.0, 0.0, 0.1, 0.0, 0.0, -1.0, 0.2, 1.0, 0.0, 0.0, 0.3];
        let velo_to_cam = from_row_major(&tr).unwrap();
        let camera = from_row_major(&[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0]).unwrap();
        let velodyne = velodyne_pose(&camera, &velo_to_cam);
        assert!((velodyne.translation.vector - nalgebra::Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
        assert!(velodyne.rotation.angle() < 1e-12);
        let dir = tempfile::tempdir().unwrap();
        let calib = dir.path().join("calib.txt");
        std::fs::write(&calib, "P0: 1 2 3\nTr: 1 0 0\n").unwrap();
        assert!(read_velo_to_cam(&calib).unwrap_err().to_string().ends_with("Tr has 3 numbers, not 12"));
    }
}
