//! Checks shared by the fuzz targets: what a successful read promises, and canonical encodings
//! for round trips (a second read of what the first returned must give it back).

use mbnt::geometry::Point;
use mbnt::io::npy::{NpyArray, NpyData, write_npy};

/// What every point reader promises on success (`src/io/mod.rs`): every coordinate finite, and
/// no more points than the bytes could hold (every format spends at least one byte per point, so
/// a larger count would mean a header size was trusted).
pub fn assert_cloud(points: &[Point], input_len: usize) {
    assert!(points.len() <= input_len, "{} points from {input_len} bytes", points.len());
    assert_finite(points);
}

/// Every coordinate finite (the size bound of [`assert_cloud`] does not hold for compressed
/// archives).
pub fn assert_finite(points: &[Point]) {
    if let Some(i) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        panic!("point {i} is {:?}, readers promise finite coordinates", points[i]);
    }
}

/// `points` as a binary little-endian PLY with float x, y, z: the simplest valid file the PLY
/// reader must read back exactly.
pub fn ply_binary(points: &[Point]) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
        points.len()
    )
    .into_bytes();
    for c in points.iter().flatten() {
        out.extend_from_slice(&c.to_le_bytes());
    }
    out
}

/// `array` written back with the project's `.npy` writer. Comparing these bytes compares shape,
/// dtype and every element bit for bit (NaN included, which `==` on floats would not).
pub fn npy_bytes(array: &NpyArray) -> Vec<u8> {
    let mut out = Vec::new();
    let shape = &array.shape;
    let written = match &array.data {
        NpyData::F32(v) => write_npy(&mut out, shape, v),
        NpyData::F64(v) => write_npy(&mut out, shape, v),
        NpyData::I32(v) => write_npy(&mut out, shape, v),
        NpyData::I64(v) => write_npy(&mut out, shape, v),
        NpyData::U8(v) => write_npy(&mut out, shape, v),
        NpyData::Bool(v) => write_npy(&mut out, shape, v),
    };
    written.unwrap_or_else(|e| panic!("an array the reader returned cannot be written: {e}"));
    out
}

/// The element count a shape declares; the reader checked it does not overflow.
pub fn shape_len(shape: &[usize]) -> usize {
    shape.iter().product()
}
