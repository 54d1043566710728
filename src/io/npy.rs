//! NumPy `.npy` arrays: a reader for float32, float64, int32, int64, uint8 and bool arrays of any
//! shape (C or Fortran order, little-endian) and typed writers (format version 1.0, or 2.0 when
//! the header is too long for 1.0).
//!
//! Layout (NEP 1): `\x93NUMPY`, major and minor version bytes, header length (u16 LE in v1,
//! u32 LE in v2/v3), an ASCII Python dict `{'descr': '<f4', 'fortran_order': False, 'shape': (N, 3), }`
//! padded with spaces and a final `\n` so the data starts at a multiple of 64 bytes, then the data.

use std::io::Write;

use super::{Format, ReadError, WriteError, finite_point};
use crate::geometry::Point;

/// The 6 bytes every `.npy` file starts with.
pub const MAGIC: &[u8] = b"\x93NUMPY";

/// Data start alignment written by current NumPy.
const ALIGN: usize = 64;

/// Element types this module reads and writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DType {
    /// `<f4`
    F32,
    /// `<f8`
    F64,
    /// `<i4`
    I32,
    /// `<i8` (NumPy's default integer, e.g. index arrays)
    I64,
    /// `|u1`
    U8,
    /// `|b1` (one byte, 0 or 1)
    Bool,
}

impl DType {
    /// NumPy's `descr` string for this type, little-endian.
    pub fn descr(self) -> &'static str {
        match self {
            DType::F32 => "<f4",
            DType::F64 => "<f8",
            DType::I32 => "<i4",
            DType::I64 => "<i8",
            DType::U8 => "|u1",
            DType::Bool => "|b1",
        }
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::F32 | DType::I32 => 4,
            DType::F64 | DType::I64 => 8,
            DType::U8 | DType::Bool => 1,
        }
    }

    fn from_descr(descr: &str) -> Result<DType, ReadError> {
        let unsupported = || ReadError::Unsupported { format: Format::Npy, what: format!("dtype '{descr}'") };
        let (order, code) = descr.split_at_checked(1).ok_or_else(unsupported)?;
        let dtype = match code {
            "f4" => DType::F32,
            "f8" => DType::F64,
            "i4" => DType::I32,
            "i8" => DType::I64,
            "u1" => DType::U8,
            "b1" => DType::Bool,
            _ => return Err(unsupported()),
        };
        match order {
            "<" => Ok(dtype),
            // One-byte types have no byte order: NumPy writes '|', '=' would mean native.
            "|" | "=" if dtype.size() == 1 => Ok(dtype),
            ">" => Err(ReadError::Unsupported {
                format: Format::Npy,
                what: format!("big-endian dtype '{descr}' (save with '<' byte order)"),
            }),
            _ => Err(unsupported()),
        }
    }
}

/// The elements of an array, in C (row-major) order.
#[derive(Debug, Clone, PartialEq)]
pub enum NpyData {
    /// float32
    F32(Vec<f32>),
    /// float64
    F64(Vec<f64>),
    /// int32
    I32(Vec<i32>),
    /// int64
    I64(Vec<i64>),
    /// uint8
    U8(Vec<u8>),
    /// bool
    Bool(Vec<bool>),
}

impl NpyData {
    /// The element type.
    pub fn dtype(&self) -> DType {
        match self {
            NpyData::F32(_) => DType::F32,
            NpyData::F64(_) => DType::F64,
            NpyData::I32(_) => DType::I32,
            NpyData::I64(_) => DType::I64,
            NpyData::U8(_) => DType::U8,
            NpyData::Bool(_) => DType::Bool,
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            NpyData::F32(v) => v.len(),
            NpyData::F64(v) => v.len(),
            NpyData::I32(v) => v.len(),
            NpyData::I64(v) => v.len(),
            NpyData::U8(v) => v.len(),
            NpyData::Bool(v) => v.len(),
        }
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// An array read from a `.npy` file: shape and elements in C order (Fortran-order files are
/// transposed on reading).
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Dimensions, outermost first; `[]` is a scalar.
    pub shape: Vec<usize>,
    /// Elements, `shape.iter().product()` of them.
    pub data: NpyData,
}

fn header_err(message: impl Into<String>) -> ReadError {
    ReadError::Header { format: Format::Npy, message: message.into() }
}

fn data_err(message: impl Into<String>) -> ReadError {
    ReadError::Data { format: Format::Npy, message: message.into() }
}

/// A parsed header dict value.
#[derive(Debug)]
enum Value {
    Str(String),
    Bool(bool),
    Tuple(Vec<usize>),
    Other,
}

/// Minimal parser for the Python dict literal of a `.npy` header.
struct DictParser<'a> {
    s: &'a [u8],
    pos: usize,
}

impl DictParser<'_> {
    fn skip_ws(&mut self) {
        while self.s.get(self.pos).is_some_and(|b| b.is_ascii_whitespace()) {
            self.pos += 1;
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.pos).copied()
    }

    fn expect(&mut self, c: u8) -> Result<(), ReadError> {
        if self.peek() == Some(c) {
            self.pos += 1;
            Ok(())
        } else {
            Err(header_err(format!("expected '{}' at byte {} of the header dict", c as char, self.pos)))
        }
    }

    fn string(&mut self) -> Result<String, ReadError> {
        let q =
            self.peek().filter(|&c| c == b'\'' || c == b'"').ok_or_else(|| header_err("expected a quoted string"))?;
        self.pos += 1;
        let start = self.pos;
        while self.s.get(self.pos).is_some_and(|&c| c != q) {
            self.pos += 1;
        }
        if self.pos >= self.s.len() {
            return Err(header_err("unterminated string in header dict"));
        }
        let text = String::from_utf8_lossy(&self.s[start..self.pos]).into_owned();
        self.pos += 1;
        Ok(text)
    }

    fn word(&mut self) -> &[u8] {
        self.skip_ws();
        let start = self.pos;
        while self.s.get(self.pos).is_some_and(|c| c.is_ascii_alphanumeric() || *c == b'_') {
            self.pos += 1;
        }
        &self.s[start..self.pos]
    }

    fn value(&mut self) -> Result<Value, ReadError> {
        match self.peek() {
            Some(b'\'' | b'"') => Ok(Value::Str(self.string()?)),
            Some(b'(') => {
                self.pos += 1;
                let mut dims = Vec::new();
                loop {
                    if self.peek() == Some(b')') {
                        self.pos += 1;
                        break;
                    }
                    let w = self.word();
                    // Python 2 wrote longs as `3L`.
                    let w = w.strip_suffix(b"L").unwrap_or(w);
                    let dim = std::str::from_utf8(w).ok().and_then(|t| t.parse::<usize>().ok()).ok_or_else(|| {
                        header_err(format!("shape entry '{}' is not a count", String::from_utf8_lossy(w)))
                    })?;
                    dims.push(dim);
                    match self.peek() {
                        Some(b',') => self.pos += 1,
                        Some(b')') => {}
                        _ => return Err(header_err("malformed shape tuple")),
                    }
                }
                Ok(Value::Tuple(dims))
            }
            Some(b'[' | b'{') => Ok(Value::Other),
            _ => match self.word() {
                b"True" => Ok(Value::Bool(true)),
                b"False" => Ok(Value::Bool(false)),
                _ => Err(header_err("unexpected value in header dict")),
            },
        }
    }

    /// Parses `{key: value, ...}`; values of unknown shape (lists, dicts) end the parse early
    /// only if they are not needed, which is reported by the caller.
    fn dict(&mut self) -> Result<Vec<(String, Value)>, ReadError> {
        self.expect(b'{')?;
        let mut entries = Vec::new();
        loop {
            if self.peek() == Some(b'}') {
                return Ok(entries);
            }
            let key = self.string()?;
            self.expect(b':')?;
            let value = self.value()?;
            let other = matches!(value, Value::Other);
            entries.push((key, value));
            if other {
                // A structured dtype (list of fields): nothing after it is needed to reject it.
                return Ok(entries);
            }
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(b'}') => {}
                _ => return Err(header_err("expected ',' or '}' in header dict")),
            }
        }
    }
}

/// Parsed preamble: type, order, shape and the data bytes that follow it.
struct Preamble<'a> {
    dtype: DType,
    fortran_order: bool,
    shape: Vec<usize>,
    data: &'a [u8],
}

fn parse_preamble(bytes: &[u8]) -> Result<Preamble<'_>, ReadError> {
    if !bytes.starts_with(MAGIC) {
        return Err(header_err("missing '\\x93NUMPY' magic"));
    }
    let major = *bytes.get(6).ok_or_else(|| header_err("missing version bytes"))?;
    let (len_bytes, start) = match major {
        1 => (2, 10),
        2 | 3 => (4, 12),
        v => return Err(ReadError::Unsupported { format: Format::Npy, what: format!("format version {v}") }),
    };
    let len_field = bytes.get(8..8 + len_bytes).ok_or_else(|| header_err("missing header length"))?;
    let header_len = len_field.iter().rev().fold(0usize, |acc, &b| (acc << 8) | b as usize);
    let end = start + header_len;
    let header = bytes.get(start..end).ok_or_else(|| ReadError::Truncated {
        what: "bytes of header".into(),
        expected: header_len,
        got: bytes.len().saturating_sub(start),
    })?;
    let entries = DictParser { s: header, pos: 0 }.dict()?;
    let get = |k: &str| entries.iter().find(|(key, _)| key == k).map(|(_, v)| v);
    let dtype = match get("descr") {
        Some(Value::Str(d)) => DType::from_descr(d)?,
        Some(_) => {
            return Err(ReadError::Unsupported { format: Format::Npy, what: "structured dtype".into() });
        }
        None => return Err(header_err("no 'descr' key")),
    };
    let fortran_order = match get("fortran_order") {
        Some(Value::Bool(b)) => *b,
        _ => return Err(header_err("no boolean 'fortran_order' key")),
    };
    let shape = match get("shape") {
        Some(Value::Tuple(s)) => s.clone(),
        _ => return Err(header_err("no tuple 'shape' key")),
    };
    Ok(Preamble { dtype, fortran_order, shape, data: &bytes[end..] })
}

/// Reorders a Fortran-order (column-major) buffer of `shape` into C order.
fn fortran_to_c<T: Copy>(src: Vec<T>, shape: &[usize]) -> Vec<T> {
    if shape.len() <= 1 || src.is_empty() {
        return src;
    }
    let nd = shape.len();
    // Fortran strides in elements: the first axis varies fastest.
    let mut f_stride = vec![0usize; nd];
    let mut s = 1;
    for k in 0..nd {
        f_stride[k] = s;
        s *= shape[k];
    }
    let mut idx = vec![0usize; nd];
    let mut off = 0usize;
    let mut out = Vec::with_capacity(src.len());
    for _ in 0..src.len() {
        out.push(src[off]);
        // Advance the C multi-index, last axis fastest, and track the Fortran offset.
        for k in (0..nd).rev() {
            idx[k] += 1;
            off += f_stride[k];
            if idx[k] < shape[k] {
                break;
            }
            off -= f_stride[k] * shape[k];
            idx[k] = 0;
        }
    }
    out
}

fn decode<T: Copy, const N: usize>(data: &[u8], f: impl Fn([u8; N]) -> T, shape: &[usize], fortran: bool) -> Vec<T> {
    let v: Vec<T> = data.chunks_exact(N).map(|c| f(c.try_into().unwrap_or([0; N]))).collect();
    if fortran { fortran_to_c(v, shape) } else { v }
}

/// Reads an `.npy` array of float32, float64, int32, int64, uint8 or bool, little-endian, C or Fortran
/// order. The declared size is checked against the byte length before anything is allocated.
///
/// Errors: bad magic or header, unsupported dtype (big-endian, other types, structured), fewer
/// bytes than the shape needs, trailing bytes, bool bytes other than 0 and 1.
pub fn read_npy(bytes: &[u8]) -> Result<NpyArray, ReadError> {
    let p = parse_preamble(bytes)?;
    let count = p
        .shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| header_err(format!("shape {:?} overflows", p.shape)))?;
    let needed = count.saturating_mul(p.dtype.size());
    if needed > p.data.len() {
        return Err(ReadError::Truncated { what: "bytes of array data".into(), expected: needed, got: p.data.len() });
    }
    if needed < p.data.len() {
        return Err(data_err(format!("{} trailing bytes after the array data", p.data.len() - needed)));
    }
    let (d, s, fo) = (p.data, p.shape.as_slice(), p.fortran_order);
    let data = match p.dtype {
        DType::F32 => NpyData::F32(decode(d, f32::from_le_bytes, s, fo)),
        DType::F64 => NpyData::F64(decode(d, f64::from_le_bytes, s, fo)),
        DType::I32 => NpyData::I32(decode(d, i32::from_le_bytes, s, fo)),
        DType::I64 => NpyData::I64(decode(d, i64::from_le_bytes, s, fo)),
        DType::U8 => NpyData::U8(decode(d, |b: [u8; 1]| b[0], s, fo)),
        DType::Bool => {
            if let Some(i) = d.iter().position(|&b| b > 1) {
                return Err(data_err(format!("bool element {i} has byte value {}", d[i])));
            }
            NpyData::Bool(decode(d, |b: [u8; 1]| b[0] == 1, s, fo))
        }
    };
    Ok(NpyArray { shape: p.shape, data })
}

/// Reads an (N, C) float32 or float64 `.npy` array with C >= 3 as points, taking the first three
/// columns as x, y, z.
pub fn read_npy_points(bytes: &[u8]) -> Result<Vec<Point>, ReadError> {
    let arr = read_npy(bytes)?;
    let cols = match arr.shape.as_slice() {
        [_, c] if *c >= 3 => *c,
        s => return Err(data_err(format!("shape {s:?} is not (N, C) with C >= 3"))),
    };
    match &arr.data {
        NpyData::F32(v) => v
            .chunks_exact(cols)
            .enumerate()
            .map(|(i, r)| finite_point(i, r[0] as f64, r[1] as f64, r[2] as f64))
            .collect(),
        NpyData::F64(v) => v.chunks_exact(cols).enumerate().map(|(i, r)| finite_point(i, r[0], r[1], r[2])).collect(),
        other => Err(ReadError::Unsupported {
            format: Format::Npy,
            what: format!("point array of dtype '{}'; expected float32 or float64", other.dtype().descr()),
        }),
    }
}

/// A type that can be written as an `.npy` element.
pub trait NpyElement: Copy {
    /// Its dtype.
    const DTYPE: DType;
    /// Appends the little-endian bytes of `self`.
    fn push_le(self, out: &mut Vec<u8>);
}

macro_rules! npy_element {
    ($t:ty, $d:expr) => {
        impl NpyElement for $t {
            const DTYPE: DType = $d;
            fn push_le(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
        }
    };
}
npy_element!(f32, DType::F32);
npy_element!(f64, DType::F64);
npy_element!(i32, DType::I32);
npy_element!(i64, DType::I64);
npy_element!(u8, DType::U8);

impl NpyElement for bool {
    const DTYPE: DType = DType::Bool;
    fn push_le(self, out: &mut Vec<u8>) {
        out.push(self as u8);
    }
}

/// Python tuple text of a shape: `()`, `(5,)`, `(5, 3)`.
pub fn shape_text(shape: &[usize]) -> String {
    match shape {
        [] => "()".into(),
        [n] => format!("({n},)"),
        _ => format!("({})", shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
    }
}

/// The full preamble (magic, version, length, dict, padding) of a C-order little-endian array;
/// the data starts right after it, at a multiple of 64 bytes.
pub fn npy_header(dtype: DType, shape: &[usize]) -> Vec<u8> {
    let dict = format!("{{'descr': '{}', 'fortran_order': False, 'shape': {}, }}", dtype.descr(), shape_text(shape));
    // Version 1.0 has a u16 header length; longer headers (huge ndim) need 2.0.
    let (version, prefix) = if 10 + dict.len() < u16::MAX as usize - ALIGN { (1u8, 10) } else { (2u8, 12) };
    let total = (prefix + dict.len() + 1).div_ceil(ALIGN) * ALIGN;
    let header_len = total - prefix;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[version, 0]);
    if version == 1 {
        out.extend_from_slice(&(header_len as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header_len as u32).to_le_bytes());
    }
    out.extend_from_slice(dict.as_bytes());
    out.resize(total - 1, b' ');
    out.push(b'\n');
    out
}

/// Checks that `len` elements fill `shape`.
pub(crate) fn check_shape(name: &str, shape: &[usize], len: usize) -> Result<(), WriteError> {
    let expected = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
    if expected == Some(len) {
        Ok(())
    } else {
        Err(WriteError::ShapeMismatch {
            name: name.to_owned(),
            shape: shape.to_vec(),
            expected: expected.unwrap_or(usize::MAX),
            got: len,
        })
    }
}

/// Writes `data` (C order) as an `.npy` array of `shape`. Converts in 64 KiB chunks, so the
/// extra memory is bounded whatever the array size.
pub fn write_npy<T: NpyElement, W: Write>(w: &mut W, shape: &[usize], data: &[T]) -> Result<(), WriteError> {
    write_npy_named(w, "npy", shape, data)
}

/// [`write_npy`] with the array name used in a shape error.
pub(crate) fn write_npy_named<T: NpyElement, W: Write>(
    w: &mut W,
    name: &str,
    shape: &[usize],
    data: &[T],
) -> Result<(), WriteError> {
    check_shape(name, shape, data.len())?;
    w.write_all(&npy_header(T::DTYPE, shape))?;
    let per_chunk = (64 * 1024 / T::DTYPE.size()).max(1);
    let mut buf = Vec::with_capacity(per_chunk * T::DTYPE.size());
    for chunk in data.chunks(per_chunk) {
        buf.clear();
        for &x in chunk {
            x.push_le(&mut buf);
        }
        w.write_all(&buf)?;
    }
    Ok(())
}

/// Writes a float32 `.npy` array; see [`write_npy`].
pub fn write_npy_f32<W: Write>(w: &mut W, shape: &[usize], data: &[f32]) -> Result<(), WriteError> {
    write_npy(w, shape, data)
}

/// Writes a float64 `.npy` array; see [`write_npy`].
pub fn write_npy_f64<W: Write>(w: &mut W, shape: &[usize], data: &[f64]) -> Result<(), WriteError> {
    write_npy(w, shape, data)
}

/// Writes an int32 `.npy` array; see [`write_npy`].
pub fn write_npy_i32<W: Write>(w: &mut W, shape: &[usize], data: &[i32]) -> Result<(), WriteError> {
    write_npy(w, shape, data)
}

/// Writes a uint8 `.npy` array; see [`write_npy`].
pub fn write_npy_u8<W: Write>(w: &mut W, shape: &[usize], data: &[u8]) -> Result<(), WriteError> {
    write_npy(w, shape, data)
}

/// Writes a bool `.npy` array; see [`write_npy`].
pub fn write_npy_bool<W: Write>(w: &mut W, shape: &[usize], data: &[bool]) -> Result<(), WriteError> {
    write_npy(w, shape, data)
}
