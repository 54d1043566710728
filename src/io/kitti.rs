//! KITTI Velodyne `.bin` reader: headerless float32 little-endian records of x, y, z, reflectance.

use super::{Format, ReadError, finite_point};
use crate::geometry::Point;

/// Bytes per record: four float32.
pub const RECORD_BYTES: usize = 16;

fn record(chunk: &[u8]) -> [f32; 4] {
    let f = |i: usize| f32::from_le_bytes([chunk[i], chunk[i + 1], chunk[i + 2], chunk[i + 3]]);
    [f(0), f(4), f(8), f(12)]
}

/// Reads the x, y, z (m, sensor frame) of every record; reflectance is dropped.
///
/// Errors: a length that is not a multiple of 16 bytes, a non-finite coordinate. Zero bytes are
/// an empty cloud. Cost: O(N).
pub fn read_kitti_bin(bytes: &[u8]) -> Result<Vec<Point>, ReadError> {
    if bytes.len() % RECORD_BYTES != 0 {
        return Err(ReadError::Data {
            format: Format::KittiBin,
            message: format!(
                "length {} bytes is not a multiple of 16 (float32 x, y, z, reflectance per point)",
                bytes.len()
            ),
        });
    }
    let mut points = Vec::with_capacity(bytes.len() / RECORD_BYTES);
    for (i, chunk) in bytes.chunks_exact(RECORD_BYTES).enumerate() {
        let [x, y, z, _] = record(chunk);
        points.push(finite_point(i, x as f64, y as f64, z as f64)?);
    }
    Ok(points)
}

/// Whether headerless `bytes` are plausibly KITTI: whole records, every float finite and every
/// coordinate within `max_abs_m` of the sensor. Used to guess the format when nothing else does.
pub(crate) fn looks_like_kitti(bytes: &[u8], max_abs_m: f32) -> bool {
    bytes.len() % RECORD_BYTES == 0
        && bytes.chunks_exact(RECORD_BYTES).all(|c| {
            let r = record(c);
            r.iter().all(|v| v.is_finite()) && r[..3].iter().all(|v| v.abs() <= max_abs_m)
        })
}
