//! `.npz` archives as `numpy.savez_compressed` writes them: a zip of `NAME.npy` entries,
//! deflate-compressed, each a little-endian C-order array readable by `numpy.load`. The writer
//! produces them; [`read_npz`] reads them (stored or deflated entries, as `numpy.savez` and
//! `numpy.savez_compressed` write).

use std::collections::{BTreeMap, HashSet};
use std::io::{Cursor, Read, Seek, Write};

use zip::write::SimpleFileOptions;

use super::npy::{NpyArray, NpyElement, check_shape, npy_header, read_npy, write_npy_named};
use super::{ReadError, WriteError};

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

    /// Adds an int64 array; see [`NpzWriter::add_f32`].
    pub fn add_i64(&mut self, name: &str, shape: &[usize], data: &[i64]) -> Result<(), WriteError> {
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

/// Largest uncompressed entry [`read_npz`] accepts (bytes): a corrupt or hostile size field must
/// not make it allocate without bound. 4 GiB is ten times the largest array mbnt writes.
pub const MAX_NPZ_ENTRY_BYTES: u64 = 4 << 30;

/// Why an `.npz` archive could not be read.
#[derive(Debug, thiserror::Error)]
pub enum NpzReadError {
    /// The bytes are not a readable zip archive (bad signature, truncated directory, CRC mismatch,
    /// unsupported compression).
    #[error("not a readable .npz (zip) archive: {0}")]
    Zip(#[from] zip::result::ZipError),
    /// An entry is not a `NAME.npy` file, as NumPy writes them.
    #[error(".npz entry '{0}' is not a NAME.npy array")]
    NotNpy(String),
    /// Two entries have the same array name.
    #[error(".npz entry '{0}' appears twice")]
    Duplicate(String),
    /// An entry declares more than [`MAX_NPZ_ENTRY_BYTES`] uncompressed bytes.
    #[error(".npz entry '{name}' declares {bytes} bytes, more than the {max} accepted")]
    TooLarge {
        /// The array name.
        name: String,
        /// Its declared uncompressed size.
        bytes: u64,
        /// The limit.
        max: u64,
    },
    /// Reading or decompressing an entry failed.
    #[error(".npz entry '{name}': {source}")]
    Io {
        /// The array name.
        name: String,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// An entry is not a valid `.npy` array.
    #[error(".npz array '{name}': {source}")]
    Array {
        /// The array name.
        name: String,
        /// What is wrong with it.
        #[source]
        source: ReadError,
    },
}

/// Most bytes one byte of DEFLATE data can inflate to (RFC 1951's longest match, 258 bytes, in
/// under two bits, about 1032:1); stored entries are 1:1.
const DEFLATE_MAX_RATIO: u64 = 1032;

/// The buffer to reserve for an entry that declares `declared` uncompressed bytes in an archive
/// of `archive_len` bytes: the declared size, but never more than the whole archive can inflate
/// to, so that a header that lies cannot reserve gigabytes for a few hundred bytes (found by
/// fuzzing: a 371-byte archive declaring 3.9 GB).
pub(crate) fn entry_capacity(declared: u64, archive_len: usize) -> usize {
    let most = (archive_len as u64).saturating_mul(DEFLATE_MAX_RATIO);
    usize::try_from(declared.min(most)).unwrap_or(usize::MAX)
}

/// Reads every array of an `.npz` archive, by name (the entry name without `.npy`). Arrays are
/// read as [`read_npy`] reads them (float32/64, int32/64, uint8, bool). Errors: not a zip, an
/// entry that is not `NAME.npy` or not a valid array, a repeated name, an oversized entry.
pub fn read_npz(bytes: &[u8]) -> Result<BTreeMap<String, NpyArray>, NpzReadError> {
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes))?;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let mut entry = zip.by_index(i)?;
        if entry.is_dir() {
            continue;
        }
        let full = entry.name().to_owned();
        let Some(name) = full.strip_suffix(".npy").filter(|n| !n.is_empty()) else {
            return Err(NpzReadError::NotNpy(full));
        };
        let name = name.to_owned();
        let declared = entry.size();
        if declared > MAX_NPZ_ENTRY_BYTES {
            return Err(NpzReadError::TooLarge { name, bytes: declared, max: MAX_NPZ_ENTRY_BYTES });
        }
        // `take` bounds what a lying header can make us read.
        let mut buf = Vec::with_capacity(entry_capacity(declared, bytes.len()));
        if let Err(source) = (&mut entry).take(MAX_NPZ_ENTRY_BYTES + 1).read_to_end(&mut buf) {
            return Err(NpzReadError::Io { name, source });
        }
        let array = read_npy(&buf).map_err(|source| NpzReadError::Array { name: name.clone(), source })?;
        if out.insert(name.clone(), array).is_some() {
            return Err(NpzReadError::Duplicate(name));
        }
    }
    Ok(out)
}
