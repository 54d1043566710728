//! A versioned little-endian byte format for f32 networks (checkpoints, fitted models).
//!
//! Layout, version 2 (all integers little-endian):
//! ```text
//! magic       8 bytes  b"MBNTMLP\0"
//! version     u32      2
//! n_dims      u32      number of widths (2..=64)
//! dims        u32 × n_dims, each 1..=65536
//! slope       f32      the hidden activation's negative slope, in [0, 1) (0 = ReLU)
//! n_params    u64      must equal Σ (in·out + out) over layers
//! params      f32 × n_params, the layout of `Mlp::parameters`, all finite
//! checksum    u64      FNV-1a 64 of every preceding byte
//! ```
//! Version 1 is the same without `slope` (ReLU networks) and is still read.
//! Decoding checks every length against the bytes actually present before allocating, so a bogus
//! header can never cause a large allocation; any corruption is an error, never a panic.

use super::Mlp;
use super::mlp::parameter_count;

const MAGIC: &[u8; 8] = b"MBNTMLP\0";
/// The format version this build writes (it reads this one and version 1).
const FORMAT_VERSION: u32 = 2;
const MAX_DIMS: usize = 64;
const MAX_WIDTH: usize = 1 << 16;

/// Why bytes could not be decoded into a network.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FormatError {
    /// The bytes do not start with the format's magic number.
    #[error("not an mbnt MLP (bad magic number)")]
    BadMagic,
    /// Written by a format version this build does not read.
    #[error("unsupported MLP format version {found} (this build reads version {supported})")]
    UnsupportedVersion {
        /// Version found in the header.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// The data ends before the header says it should.
    #[error("truncated MLP data: {needed} bytes needed, {available} present")]
    Truncated {
        /// Bytes the header implies (or the fixed header size).
        needed: usize,
        /// Bytes present.
        available: usize,
    },
    /// Layer widths out of range, or a parameter count that does not match them.
    #[error("invalid MLP shape: {0}")]
    InvalidShape(String),
    /// Bytes follow the checksum.
    #[error("{0} unexpected bytes after the MLP data")]
    TrailingBytes(usize),
    /// The checksum does not match the content.
    #[error("MLP data checksum mismatch (corrupt data)")]
    ChecksumMismatch,
    /// A stored parameter is NaN or infinite.
    #[error("MLP parameter {index} is not finite")]
    NonFinite {
        /// Index in the flat parameter layout.
        index: usize,
    },
}

/// FNV-1a, 64 bit: simple, dependency-free, and enough to catch accidental corruption.
fn fnv1a64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// Reads little-endian fields from a byte slice, reporting truncation.
struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], FormatError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        let end =
            end.ok_or(FormatError::Truncated { needed: self.pos.saturating_add(n), available: self.bytes.len() })?;
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u32(&mut self) -> Result<u32, FormatError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&mut self) -> Result<u64, FormatError> {
        let b = self.take(8)?;
        Ok(u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
    }
}

impl Mlp<f32> {
    /// Encodes the network (widths and every parameter, bit-exact) in the versioned format above.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(8 + 4 + 4 + 4 * self.dims.len() + 8 + 4 * self.params.len() + 8);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&(self.dims.len() as u32).to_le_bytes());
        for &d in &self.dims {
            out.extend_from_slice(&(d as u32).to_le_bytes());
        }
        out.extend_from_slice(&self.negative_slope.to_le_bytes());
        out.extend_from_slice(&(self.params.len() as u64).to_le_bytes());
        for p in &self.params {
            out.extend_from_slice(&p.to_le_bytes());
        }
        let checksum = fnv1a64(&out);
        out.extend_from_slice(&checksum.to_le_bytes());
        out
    }

    /// Decodes bytes written by [`Mlp::to_bytes`].
    ///
    /// # Errors
    /// Wrong magic or version, truncated data, widths out of range (more than 64 layers' widths,
    /// a width of 0 or above 65536), a parameter count that does not match the widths, trailing
    /// bytes, a checksum mismatch or a non-finite parameter.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, FormatError> {
        let mut r = Reader { bytes, pos: 0 };
        if r.take(MAGIC.len()).map_err(|_| FormatError::BadMagic)? != MAGIC {
            return Err(FormatError::BadMagic);
        }
        let version = r.u32()?;
        if version != FORMAT_VERSION && version != 1 {
            return Err(FormatError::UnsupportedVersion { found: version, supported: FORMAT_VERSION });
        }
        let n_dims = r.u32()? as usize;
        if !(2..=MAX_DIMS).contains(&n_dims) {
            return Err(FormatError::InvalidShape(format!("{n_dims} widths (2..={MAX_DIMS} allowed)")));
        }
        let dims_bytes = r.take(4 * n_dims)?;
        let dims: Vec<usize> =
            dims_bytes.chunks_exact(4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize).collect();
        if let Some(d) = dims.iter().find(|&&d| d == 0 || d > MAX_WIDTH) {
            return Err(FormatError::InvalidShape(format!("width {d} (1..={MAX_WIDTH} allowed)")));
        }
        let negative_slope = if version >= 2 {
            let b = r.take(4)?;
            let slope = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            if !(0.0..1.0).contains(&slope) {
                return Err(FormatError::InvalidShape(format!("negative slope {slope} (0..1 allowed)")));
            }
            slope
        } else {
            0.0
        };
        let count =
            parameter_count(&dims).ok_or_else(|| FormatError::InvalidShape("parameter count overflows".into()))?;
        let stored = r.u64()?;
        if stored != count as u64 {
            return Err(FormatError::InvalidShape(format!("{stored} parameters stored, widths imply {count}")));
        }
        // `take` checks the length against the bytes present before anything is allocated.
        let data_len = count.checked_mul(4).ok_or_else(|| FormatError::InvalidShape("data size overflows".into()))?;
        let data = r.take(data_len)?;
        let body_end = r.pos;
        let checksum = r.u64()?;
        if r.pos != bytes.len() {
            return Err(FormatError::TrailingBytes(bytes.len() - r.pos));
        }
        if fnv1a64(&bytes[..body_end]) != checksum {
            return Err(FormatError::ChecksumMismatch);
        }
        let params: Vec<f32> = data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        if let Some(index) = params.iter().position(|p| !p.is_finite()) {
            return Err(FormatError::NonFinite { index });
        }
        Ok(Mlp { dims, params, negative_slope })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn model() -> Mlp<f32> {
        Mlp::new(&[9, 16, 16, 72], &mut ChaCha8Rng::seed_from_u64(11))
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let mut mlp = model();
        // Include values whose bits matter: negative zero, subnormals, extremes.
        let p = mlp.parameters_mut();
        p[0] = -0.0;
        p[1] = f32::MIN_POSITIVE / 3.0;
        p[2] = f32::MAX;
        p[3] = -f32::MIN_POSITIVE;
        mlp.set_negative_slope(0.01);
        let back = Mlp::from_bytes(&mlp.to_bytes()).unwrap();
        assert_eq!(back.dims(), mlp.dims());
        assert_eq!(back.negative_slope(), 0.01);
        let bits = |m: &Mlp<f32>| m.parameters().iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back), bits(&mlp));
    }

    #[test]
    fn every_truncation_is_an_error() {
        let bytes = model().to_bytes();
        for len in 0..bytes.len() {
            assert!(Mlp::from_bytes(&bytes[..len]).is_err(), "prefix of {len} bytes accepted");
        }
    }

    #[test]
    fn wrong_magic_version_and_trailing_bytes_are_rejected() {
        let bytes = model().to_bytes();
        let mut b = bytes.clone();
        b[0] = b'X';
        assert_eq!(Mlp::from_bytes(&b).unwrap_err(), FormatError::BadMagic);
        let mut b = bytes.clone();
        b[8..12].copy_from_slice(&3u32.to_le_bytes());
        assert_eq!(Mlp::from_bytes(&b).unwrap_err(), FormatError::UnsupportedVersion { found: 3, supported: 2 });
        let mut b = bytes.clone();
        b.push(0);
        assert_eq!(Mlp::from_bytes(&b).unwrap_err(), FormatError::TrailingBytes(1));
    }

    #[test]
    fn flipped_bits_anywhere_are_rejected() {
        let bytes = model().to_bytes();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..500 {
            let mut b = bytes.clone();
            let i = rng.random_range(0..b.len());
            b[i] ^= 1 << rng.random_range(0..8);
            assert!(Mlp::from_bytes(&b).is_err(), "flip at byte {i} accepted");
        }
    }

    #[test]
    fn bogus_lengths_fail_without_allocating() {
        // A header claiming 64 widths of 65536 (≈ 2^38 parameters) followed by nothing.
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&1u32.to_le_bytes());
        b.extend_from_slice(&64u32.to_le_bytes());
        for _ in 0..64 {
            b.extend_from_slice(&65536u32.to_le_bytes());
        }
        let count = parameter_count(&[65536; 64]).unwrap() as u64;
        b.extend_from_slice(&count.to_le_bytes());
        assert!(matches!(Mlp::from_bytes(&b), Err(FormatError::Truncated { .. })));
        // Absurd width count and zero widths.
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&1u32.to_le_bytes());
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(Mlp::from_bytes(&b), Err(FormatError::InvalidShape(_))));
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&1u32.to_le_bytes());
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(&0u32.to_le_bytes());
        b.extend_from_slice(&3u32.to_le_bytes());
        assert!(matches!(Mlp::from_bytes(&b), Err(FormatError::InvalidShape(_))));
    }

    #[test]
    fn random_garbage_is_rejected_without_panicking() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        for len in [0, 1, 7, 8, 12, 16, 100, 4096] {
            let mut b: Vec<u8> = (0..len).map(|_| rng.random()).collect();
            assert!(Mlp::from_bytes(&b).is_err());
            // Garbage behind a valid magic and version reaches the deeper checks.
            if len >= 12 {
                b[..8].copy_from_slice(MAGIC);
                b[8..12].copy_from_slice(&1u32.to_le_bytes());
                assert!(Mlp::from_bytes(&b).is_err());
            }
        }
    }

    /// Version 1 bytes of `mlp`: version 2 without the slope field, checksum recomputed.
    fn version_1_bytes(mlp: &Mlp<f32>) -> Vec<u8> {
        let v2 = mlp.to_bytes();
        let slope_at = 16 + 4 * mlp.dims().len();
        let mut b = v2[..slope_at].to_vec();
        b[8..12].copy_from_slice(&1u32.to_le_bytes());
        b.extend_from_slice(&v2[slope_at + 4..v2.len() - 8]);
        let checksum = fnv1a64(&b);
        b.extend_from_slice(&checksum.to_le_bytes());
        b
    }

    #[test]
    fn version_1_files_read_as_relu_networks() {
        let mlp = model();
        let back = Mlp::from_bytes(&version_1_bytes(&mlp)).unwrap();
        assert_eq!(back, mlp);
        assert_eq!(back.negative_slope(), 0.0);
    }

    #[test]
    fn a_slope_outside_0_to_1_is_rejected() {
        let mlp = model();
        let mut b = mlp.to_bytes();
        let slope_at = 16 + 4 * mlp.dims().len();
        b[slope_at..slope_at + 4].copy_from_slice(&1.5f32.to_le_bytes());
        let body = b.len() - 8;
        let checksum = fnv1a64(&b[..body]);
        b[body..].copy_from_slice(&checksum.to_le_bytes());
        assert!(matches!(Mlp::from_bytes(&b), Err(FormatError::InvalidShape(_))));
    }

    #[test]
    fn non_finite_parameters_are_rejected() {
        let mut mlp = model();
        mlp.parameters_mut()[5] = f32::NAN;
        assert_eq!(Mlp::from_bytes(&mlp.to_bytes()).unwrap_err(), FormatError::NonFinite { index: 5 });
    }
}
