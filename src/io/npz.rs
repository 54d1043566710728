//! `.npz` archives as `numpy.savez_compressed` writes them: a zip of `NAME.npy` entries,
//! deflate-compressed, each a little-endian C-order array readable by `numpy.load`.

use std::collections::HashSet;
use std::io::{Seek, Write};

use zip::write::SimpleFileOptions;

use super::WriteError;
use super::npy::{NpyElement, check_shape, npy_header, write_npy_named};

/// Above this many bytes an entry needs zip64 records (the classic fields are u32).
const ZIP64_THRESHOLD_BYTES: u64 = u32::MAX as u64 - 4096;

/// Writes named arrays into an `.npz` archive; call [`NpzWriter::finish`] to write the zip
/// directory (an unfinished archive is not readable).
pub struct NpzWriter<W: Write + Seek> {
    zip: zip::ZipWriter<W>,
    names: HashSet<String>,
}

impl<W: Write + Seek> NpzWriter<W> {
    /// Starts an empty archive on `w`.
    pub fn new(w: W) -> Self {
        NpzWriter { zip: zip::ZipWriter::new(w), names: HashSet::new() }
    }

    fn add<T: NpyElement>(&mut self, name: &str, shape: &[usize], data: &[T]) -> Result<(), WriteError> {
        if name.is_empty() {
            return Err(WriteError::InvalidName { name: name.into(), reason: "empty" });
        }
        if name.contains('\0') {
            return Err(WriteError::InvalidName { name: name.into(), reason: "contains a NUL byte" });
        }
        if self.names.contains(name) {
            return Err(WriteError::InvalidName { name: name.into(), reason: "already in the archive" });
        }
        // Check before starting the entry, so a bad call leaves the archive consistent.
        check_shape(name, shape, data.len())?;
        let bytes = (npy_header(T::DTYPE, shape).len() + std::mem::size_of_val(data)) as u64;
        let options = SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Deflated)
            .large_file(bytes >= ZIP64_THRESHOLD_BYTES);
        self.zip.start_file(format!("{name}.npy"), options)?;
        write_npy_named(&mut self.zip, name, shape, data)?;
        self.names.insert(name.to_owned());
        Ok(())
    }

    /// Adds a float32 array `name` (stored as `name.npy`) of `shape`, `data` in C order.
    /// Errors if `data.len()` is not the product of `shape` or the name is empty or repeated.
    pub fn add_f32(&mut self, name: &str, shape: &[usize], data: &[f32]) -> Result<(), WriteError> {
        self.add(name, shape, data)
    }

    /// Adds a float64 array; see [`NpzWriter::add_f32`].
    pub fn add_f64(&mut self, name: &str, shape: &[usize], data: &[f64]) -> Result<(), WriteError> {
        self.add(name, shape, data)
    }

    /// Adds an int32 array; see [`NpzWriter::add_f32`].
    pub fn add_i32(&mut self, name: &str, shape: &[usize], data: &[i32]) -> Result<(), WriteError> {
        self.add(name, shape, data)
    }

    /// Adds a uint8 array; see [`NpzWriter::add_f32`].
    pub fn add_u8(&mut self, name: &str, shape: &[usize], data: &[u8]) -> Result<(), WriteError> {
        self.add(name, shape, data)
    }

    /// Adds a bool array; see [`NpzWriter::add_f32`].
    pub fn add_bool(&mut self, name: &str, shape: &[usize], data: &[bool]) -> Result<(), WriteError> {
        self.add(name, shape, data)
    }

    /// Writes the zip directory and returns the underlying writer.
    pub fn finish(self) -> Result<W, WriteError> {
        Ok(self.zip.finish()?)
    }
}
