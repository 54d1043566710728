//! The Argoverse 2 sensor-log layout: `LOG_DIR/sensors/lidar/<timestamp_ns>.feather` sweeps
//! (points in the ego-vehicle frame at the sweep's time) and `LOG_DIR/city_SE3_egovehicle.feather`
//! (the ego-to-city pose of every timestamp: columns `timestamp_ns`, `qw`, `qx`, `qy`, `qz`,
//! `tx_m`, `ty_m`, `tz_m`). Reads a log's index and poses, and writes both files (the simulator
//! writes logs in this layout, e.g. for the label throughput measurement).

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow_array::{ArrayRef, Float64Array, Int32Array, Int64Array, RecordBatch, UInt8Array};
use arrow_schema::{DataType, Field, Schema};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use super::feather::{Values, read_columns, write_batch};
use super::{ReadError, WriteError};
use crate::geometry::Point;

/// Sweeps of a log, relative to the log directory.
pub const LIDAR_DIR: &str = "sensors/lidar";
/// Ego poses of a log, relative to the log directory.
pub const POSES_FILE: &str = "city_SE3_egovehicle.feather";
/// Columns of [`POSES_FILE`] after `timestamp_ns`, in the order [`read_city_poses`] takes them.
const POSE_COLUMNS: [&str; 7] = ["qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"];
/// A quaternion whose norm is further than this from 1 is not a rotation written by a logger
/// (they are written normalised, to float64 precision).
const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// Why an AV2 log directory cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// A directory could not be listed.
    #[error("listing {}: {source}", .path.display())]
    List {
        /// The directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// No sweeps in the lidar directory.
    #[error("no <timestamp_ns>.feather sweeps in {}", .0.display())]
    NoSweeps(PathBuf),
    /// A `.feather` file in the lidar directory whose name is not a timestamp.
    #[error("{}: a sweep's file name must be its timestamp in nanoseconds", .0.display())]
    BadSweepName(PathBuf),
    /// The pose file could not be read.
    #[error("{}: {source}", .path.display())]
    Poses {
        /// The pose file.
        path: PathBuf,
        /// What is wrong with it.
        #[source]
        source: ReadError,
    },
    /// A pose row is not a rigid transform.
    #[error("{}: row {row} (timestamp_ns {timestamp_ns}): {what}", .path.display())]
    BadPose {
        /// The pose file.
        path: PathBuf,
        /// Zero-based row.
        row: usize,
        /// Its timestamp.
        timestamp_ns: i64,
        /// What is wrong.
        what: String,
    },
    /// A sweep has no pose of the same timestamp.
    #[error("sweep {timestamp_ns}.feather has no pose of that timestamp in {}", .path.display())]
    MissingPose {
        /// The pose file.
        path: PathBuf,
        /// The sweep's timestamp.
        timestamp_ns: i64,
    },
}

/// The sweeps of a log in time order, with their ego poses.
#[derive(Debug, Clone, PartialEq)]
pub struct Av2Log {
    /// Sweep files, sorted by timestamp.
    pub sweep_paths: Vec<PathBuf>,
    /// Timestamp of each sweep (ns), increasing.
    pub timestamps_ns: Vec<i64>,
    /// Ego-to-city pose of each sweep, row-major 4 x 4 (the sweeps' points are in the ego frame,
    /// so this is the sensor-to-world pose the fit takes).
    pub poses: Vec<[f64; 16]>,
}

impl Av2Log {
    /// Sweep times (s) relative to the first sweep: f64 holds nanosecond offsets of a log exactly,
    /// which it would not for absolute epoch nanoseconds.
    pub fn timestamps_s(&self) -> Vec<f64> {
        let first = self.timestamps_ns.first().copied().unwrap_or(0);
        self.timestamps_ns.iter().map(|&t| (t - first) as f64 * 1e-9).collect()
    }
}

/// Lists the sweeps of the log at `dir` and matches each with its pose by timestamp.
///
/// Errors: no sweeps, a `.feather` sweep not named by an integer timestamp, an unreadable pose
/// file, a pose that is not a rigid transform, a sweep without a pose. Sweeps only are read
/// here, not their points.
pub fn read_log(dir: &Path) -> Result<Av2Log, LogError> {
    let lidar = dir.join(LIDAR_DIR);
    let entries = std::fs::read_dir(&lidar).map_err(|source| LogError::List { path: lidar.clone(), source })?;
    let mut sweeps: Vec<(i64, PathBuf)> = Vec::new();
    for entry in entries {
        let path = entry.map_err(|source| LogError::List { path: lidar.clone(), source })?.path();
        if path.extension().and_then(|e| e.to_str()) != Some("feather") {
            continue;
        }
        let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or_default();
        let timestamp_ns = stem.parse::<i64>().map_err(|_| LogError::BadSweepName(path.clone()))?;
        sweeps.push((timestamp_ns, path));
    }
    if sweeps.is_empty() {
        return Err(LogError::NoSweeps(lidar));
    }
    // By timestamp, not by name: names of different digit counts do not sort as numbers.
    sweeps.sort();
    let poses_path = dir.join(POSES_FILE);
    let bytes = std::fs::read(&poses_path).map_err(|source| LogError::Poses {
        path: poses_path.clone(),
        source: ReadError::Io { path: poses_path.clone(), source },
    })?;
    let by_time = read_city_poses(&bytes, &poses_path)?;
    let poses = sweeps
        .iter()
        .map(|&(timestamp_ns, _)| {
            by_time.get(&timestamp_ns).copied().ok_or(LogError::MissingPose { path: poses_path.clone(), timestamp_ns })
        })
        .collect::<Result<_, _>>()?;
    Ok(Av2Log {
        timestamps_ns: sweeps.iter().map(|s| s.0).collect(),
        sweep_paths: sweeps.into_iter().map(|s| s.1).collect(),
        poses,
    })
}

/// The ego-to-city poses of a `city_SE3_egovehicle.feather` (`path` only names it in errors),
/// by timestamp (ns), as row-major 4 x 4 matrices.
pub fn read_city_poses(bytes: &[u8], path: &Path) -> Result<HashMap<i64, [f64; 16]>, LogError> {
    let mut names = vec!["timestamp_ns"];
    names.extend(POSE_COLUMNS);
    let columns = read_columns(bytes, &names).map_err(|source| LogError::Poses { path: path.to_owned(), source })?;
    let not_float = |name: &str| LogError::Poses {
        path: path.to_owned(),
        source: ReadError::Unsupported { format: super::Format::Feather, what: format!("integer column '{name}'") },
    };
    let Values::Int(timestamps_ns) = &columns[0] else {
        return Err(LogError::Poses {
            path: path.to_owned(),
            source: ReadError::Unsupported {
                format: super::Format::Feather,
                what: "float column 'timestamp_ns' (nanoseconds are integers)".into(),
            },
        });
    };
    let mut values: Vec<&[f64]> = Vec::with_capacity(POSE_COLUMNS.len());
    for (name, column) in POSE_COLUMNS.iter().zip(&columns[1..]) {
        match column {
            Values::Float(v) => values.push(v),
            Values::Int(_) => return Err(not_float(name)),
        }
    }
    let mut poses = HashMap::with_capacity(timestamps_ns.len());
    for (row, &timestamp_ns) in timestamps_ns.iter().enumerate() {
        let v: [f64; 7] = std::array::from_fn(|c| values[c][row]);
        let bad = |what: String| LogError::BadPose { path: path.to_owned(), row, timestamp_ns, what };
        if v.iter().any(|x| !x.is_finite()) {
            return Err(bad(format!("non-finite value in {v:?}")));
        }
        let q = Quaternion::new(v[0], v[1], v[2], v[3]);
        if (q.norm() - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
            return Err(bad(format!("quaternion (qw, qx, qy, qz) = {:?} has norm {:.6}, not 1", &v[..4], q.norm())));
        }
        let pose = Isometry3::from_parts(Translation3::new(v[4], v[5], v[6]), UnitQuaternion::from_quaternion(q));
        poses.insert(timestamp_ns, crate::odometry::to_row_major(&pose));
    }
    Ok(poses)
}

/// Writes a sweep as AV2 does: LZ4-compressed Feather v2 with `x`, `y`, `z` (float16, m, ego
/// frame), `intensity` (uint8), `laser_number` (uint8) and `offset_ns` (int32). Intensity, laser
/// number and offset are 0: nothing here knows them. float16 rounds coordinates to 11
/// significant bits (under 0.032 m up to 64 m from the ego, as AV2's own files).
pub fn write_sweep<W: Write>(w: W, points: &[Point]) -> Result<W, WriteError> {
    use arrow_array::Float16Array;
    use arrow_array::types::{ArrowPrimitiveType, Float16Type};
    type F16 = <Float16Type as ArrowPrimitiveType>::Native;

    let axis =
        |a: usize| -> ArrayRef { Arc::new(Float16Array::from_iter_values(points.iter().map(|p| F16::from_f32(p[a])))) };
    let n = points.len();
    let schema = Arc::new(Schema::new(vec![
        Field::new("x", DataType::Float16, false),
        Field::new("y", DataType::Float16, false),
        Field::new("z", DataType::Float16, false),
        Field::new("intensity", DataType::UInt8, false),
        Field::new("laser_number", DataType::UInt8, false),
        Field::new("offset_ns", DataType::Int32, false),
    ]));
    let columns: Vec<ArrayRef> = vec![
        axis(0),
        axis(1),
        axis(2),
        Arc::new(UInt8Array::from(vec![0; n])),
        Arc::new(UInt8Array::from(vec![0; n])),
        Arc::new(Int32Array::from(vec![0; n])),
    ];
    write_batch(w, &RecordBatch::try_new(schema, columns)?, true)
}

/// Writes a `city_SE3_egovehicle.feather`: one row per timestamp (ns) with the ego-to-city pose
/// (row-major 4 x 4 rigid transform) as a quaternion and a translation. Errors: lengths differ,
/// a pose is not a rigid transform.
pub fn write_city_poses<W: Write>(w: W, timestamps_ns: &[i64], poses: &[[f64; 16]]) -> Result<W, WriteError> {
    if timestamps_ns.len() != poses.len() {
        return Err(WriteError::Inconsistent(format!("{} timestamps for {} poses", timestamps_ns.len(), poses.len())));
    }
    let mut values: [Vec<f64>; 7] = Default::default();
    for (k, m) in poses.iter().enumerate() {
        let pose = crate::odometry::from_row_major(m)
            .ok_or_else(|| WriteError::Inconsistent(format!("pose {k} is not a rigid transform")))?;
        let q = pose.rotation.quaternion();
        let t = pose.translation.vector;
        for (column, v) in values.iter_mut().zip([q.w, q.i, q.j, q.k, t.x, t.y, t.z]) {
            column.push(v);
        }
    }
    let mut fields = vec![Field::new("timestamp_ns", DataType::Int64, false)];
    let mut columns: Vec<ArrayRef> = vec![Arc::new(Int64Array::from(timestamps_ns.to_vec()))];
    for (name, v) in POSE_COLUMNS.iter().zip(values) {
        fields.push(Field::new(*name, DataType::Float64, false));
        columns.push(Arc::new(Float64Array::from(v)));
    }
    write_batch(w, &RecordBatch::try_new(Arc::new(Schema::new(fields)), columns)?, true)
}
