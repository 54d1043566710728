//! Point-cloud readers (PLY, PCD, KITTI `.bin`, NumPy `.npy`, Argoverse 2 Feather sweeps) and
//! NumPy / label writers.
//!
//! Readers take the whole file as bytes and return metric x, y, z per point. They never panic
//! and never trust a size written in a header: every declared count is checked against the
//! number of bytes actually present before anything is allocated. Points with a NaN or infinite
//! coordinate are an error (the fitting code needs finite input); an empty cloud is valid.
//! Feather sweeps need the `av2` cargo feature; without it they are recognised and refused with
//! [`ReadError::Unsupported`].
//!
//! Writers produce `.npy` arrays, `.npz` archives ([`npz::NpzWriter`]) and the label exports of
//! [`labels`]; [`npz::read_npz`] reads archives back, and [`flow_pair`] loads a real pair with
//! ground-truth scene flow from one.

#[cfg(feature = "av2")]
pub mod av2;
#[cfg(feature = "av2")]
pub mod feather;
pub mod flow_pair;
pub mod kitti;
pub mod labels;
pub mod npy;
pub mod npz;
pub mod pcd;
pub mod ply;

use std::fmt;
use std::path::{Path, PathBuf};

use crate::geometry::Point;

/// A point-cloud file format that [`read_points`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Format {
    /// Stanford PLY, ascii or binary little-endian, with a `vertex` element.
    Ply,
    /// PCL's PCD, ascii or binary (not `binary_compressed`).
    Pcd,
    /// KITTI Velodyne `.bin`: float32 x, y, z, reflectance records, no header.
    KittiBin,
    /// NumPy `.npy` with an (N, >=3) float32 or float64 array.
    Npy,
    /// Feather v2 (Arrow IPC file), uncompressed or LZ4, with float16/32/64 columns `x`, `y`,
    /// `z`: Argoverse 2 sweeps. Read only with the `av2` cargo feature.
    Feather,
}

impl fmt::Display for Format {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Format::Ply => "PLY",
            Format::Pcd => "PCD",
            Format::KittiBin => "KITTI .bin",
            Format::Npy => "NPY",
            Format::Feather => "Feather",
        })
    }
}

/// Why a file could not be read as a point cloud. Messages say what is wrong and where.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The header is malformed or inconsistent.
    #[error("{format} header: {message}")]
    Header {
        /// Format whose header was being parsed.
        format: Format,
        /// What is wrong, e.g. "missing 'end_header'".
        message: String,
    },
    /// The body does not parse (bad number, wrong token count, invalid value).
    #[error("{format} data: {message}")]
    Data {
        /// Format whose body was being parsed.
        format: Format,
        /// What is wrong and where, e.g. "line 12: 'abc' is not a number".
        message: String,
    },
    /// Fewer bytes or records than the header declares.
    #[error("file truncated: expected {expected} {what}, got {got}")]
    Truncated {
        /// Unit of the counts, e.g. "bytes of vertex data" or "vertices".
        what: String,
        /// How many the header declares.
        expected: usize,
        /// How many are present.
        got: usize,
    },
    /// A point has a NaN or infinite coordinate.
    #[error("point {index} has a non-finite coordinate")]
    NonFinite {
        /// Zero-based index of the first such point.
        index: usize,
    },
    /// A valid file that uses a feature this reader does not implement.
    #[error("unsupported {format}: {what}")]
    Unsupported {
        /// The format.
        format: Format,
        /// The feature, e.g. "binary_big_endian".
        what: String,
    },
    /// The content matches no known format.
    #[error(
        "unknown point-cloud format{}: no PLY/PCD/NPY/Arrow magic and not a plausible KITTI .bin",
        hint_text(.name_hint)
    )]
    UnknownFormat {
        /// The file name given as a hint, if any.
        name_hint: Option<String>,
    },
    /// The file could not be read.
    #[error("reading {}: {source}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
}

fn hint_text(hint: &Option<String>) -> String {
    match hint {
        Some(h) => format!(" ('{h}')"),
        None => String::new(),
    }
}

/// Why an array or archive could not be written.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    /// The underlying writer failed.
    #[error("write failed: {0}")]
    Io(#[from] std::io::Error),
    /// The zip container failed.
    #[error("zip archive: {0}")]
    Zip(#[from] zip::result::ZipError),
    /// The data length does not match the product of the shape.
    #[error("array '{name}': shape {shape:?} needs {expected} elements, got {got}")]
    ShapeMismatch {
        /// Array name.
        name: String,
        /// Declared shape.
        shape: Vec<usize>,
        /// Product of the shape (`usize::MAX` if it overflows).
        expected: usize,
        /// Elements given.
        got: usize,
    },
    /// An array name is empty, repeated, or contains a character a zip entry cannot hold.
    #[error("invalid array name '{name}': {reason}")]
    InvalidName {
        /// The name.
        name: String,
        /// Why it is rejected.
        reason: &'static str,
    },
    /// Inputs that must correspond do not (e.g. a validity mask per frame).
    #[error("inconsistent input: {0}")]
    Inconsistent(String),
    /// The Arrow IPC writer failed.
    #[cfg(feature = "av2")]
    #[error("arrow: {0}")]
    Arrow(#[from] arrow_schema::ArrowError),
}

/// First bytes of an Arrow IPC file (Feather v2); kept here too so that detection works in
/// builds without the `av2` feature.
pub(crate) const FEATHER_MAGIC: &[u8; 6] = b"ARROW1";
/// First bytes of a Feather v1 file.
pub(crate) const FEATHER_V1_MAGIC: &[u8; 4] = b"FEA1";

/// Largest plausible |coordinate| (m) of a KITTI `.bin` point, used only when guessing the format
/// of a headerless file: LiDAR returns lie within a few hundred metres, random bytes as floats
/// are mostly astronomically large or tiny.
const KITTI_PLAUSIBLE_ABS_M: f32 = 1.0e4;

/// Which format `bytes` are in, from their content; `name_hint` (a file name) only decides for
/// headerless data.
///
/// Order: the magic of PLY (`ply` line), PCD (`# .PCD` or a first `VERSION`/`FIELDS` line), NPY
/// (`\x93NUMPY`) and Feather (`ARROW1`, or Feather v1's `FEA1`, which the reader refuses by name)
/// wins over any name; then a name ending in `.bin` means KITTI; then data whose length is a
/// multiple of 16 bytes and whose floats are all finite with plausible coordinates is KITTI; then
/// a `.ply`/`.pcd`/`.npy`/`.feather`/`.arrow` name picks that reader (which then reports what is
/// wrong with the header). Cost: O(len) for the KITTI check.
pub fn detect_format(bytes: &[u8], name_hint: Option<&str>) -> Result<Format, ReadError> {
    if bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n") {
        return Ok(Format::Ply);
    }
    if bytes.starts_with(npy::MAGIC) {
        return Ok(Format::Npy);
    }
    if pcd::looks_like_pcd(bytes) {
        return Ok(Format::Pcd);
    }
    if bytes.starts_with(FEATHER_MAGIC) || bytes.starts_with(FEATHER_V1_MAGIC) {
        return Ok(Format::Feather);
    }
    let ext = name_hint.and_then(|n| Path::new(n).extension()).and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if ext.as_deref() == Some("bin") {
        return Ok(Format::KittiBin);
    }
    if !bytes.is_empty() && kitti::looks_like_kitti(bytes, KITTI_PLAUSIBLE_ABS_M) {
        return Ok(Format::KittiBin);
    }
    match ext.as_deref() {
        Some("ply") => Ok(Format::Ply),
        Some("pcd") => Ok(Format::Pcd),
        Some("npy") => Ok(Format::Npy),
        Some("feather" | "arrow") => Ok(Format::Feather),
        _ => Err(ReadError::UnknownFormat { name_hint: name_hint.map(str::to_owned) }),
    }
}

/// Reads a point cloud in any [`Format`], detected with [`detect_format`].
///
/// Returns metric x, y, z per point in file order; other attributes are dropped.
pub fn read_points(bytes: &[u8], name_hint: Option<&str>) -> Result<Vec<Point>, ReadError> {
    read_points_as(bytes, detect_format(bytes, name_hint)?)
}

/// Reads a point cloud in a known format.
pub fn read_points_as(bytes: &[u8], format: Format) -> Result<Vec<Point>, ReadError> {
    match format {
        Format::Ply => ply::read_ply(bytes),
        Format::Pcd => pcd::read_pcd(bytes),
        Format::KittiBin => kitti::read_kitti_bin(bytes),
        Format::Npy => npy::read_npy_points(bytes),
        #[cfg(feature = "av2")]
        Format::Feather => feather::read_feather(bytes),
        #[cfg(not(feature = "av2"))]
        Format::Feather => Err(ReadError::Unsupported {
            format: Format::Feather,
            what: "this build has no Arrow support: rebuild with the `av2` cargo feature (on by default)".into(),
        }),
    }
}

/// Reads a point-cloud file; the file name is the hint for [`detect_format`].
pub fn read_points_file(path: &Path) -> Result<Vec<Point>, ReadError> {
    let bytes = std::fs::read(path).map_err(|source| ReadError::Io { path: path.to_owned(), source })?;
    let name = path.file_name().and_then(|n| n.to_str());
    read_points(&bytes, name)
}

/// Builds a point from f64 coordinates, rejecting values that are non-finite either as read or
/// after rounding to f32 (a finite f64 beyond f32's range becomes infinite).
pub(crate) fn finite_point(index: usize, x: f64, y: f64, z: f64) -> Result<Point, ReadError> {
    let p = [x as f32, y as f32, z as f32];
    if p.iter().all(|c| c.is_finite()) { Ok(p) } else { Err(ReadError::NonFinite { index }) }
}

/// Splits off the first line (without its `\n` or `\r\n`) and returns it with the rest.
pub(crate) fn split_line(bytes: &[u8]) -> Option<(&[u8], &[u8])> {
    let nl = bytes.iter().position(|&b| b == b'\n')?;
    let line = &bytes[..nl];
    let line = line.strip_suffix(b"\r").unwrap_or(line);
    Some((line, &bytes[nl + 1..]))
}

/// Scalar types shared by PLY and PCD headers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    pub(crate) fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::I64 | Scalar::U64 | Scalar::F64 => 8,
        }
    }

    /// Reads a little-endian value as f64; `b` must hold at least `size()` bytes.
    pub(crate) fn read_le_f64(self, b: &[u8]) -> f64 {
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::I64 => i64::from_le_bytes(le8(b)) as f64,
            Scalar::U64 => u64::from_le_bytes(le8(b)) as f64,
            Scalar::F64 => f64::from_le_bytes(le8(b)),
        }
    }

    pub(crate) fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }
}

fn le8(b: &[u8]) -> [u8; 8] {
    [b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]
}

#[cfg(test)]
mod tests;
