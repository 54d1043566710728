//! PCL `.pcd` reader: ascii and binary data with any fields, of which float32 or float64 `x`,
//! `y`, `z` are kept. `binary_compressed` (LZF) is rejected as unsupported.

use super::{Format, ReadError, Scalar, finite_point, split_line};
use crate::geometry::Point;

fn header_err(message: impl Into<String>) -> ReadError {
    ReadError::Header { format: Format::Pcd, message: message.into() }
}

fn data_err(message: impl Into<String>) -> ReadError {
    ReadError::Data { format: Format::Pcd, message: message.into() }
}

/// Whether `bytes` start like a PCD file: `# .PCD`, or `VERSION` / `FIELDS` as the first line
/// that is not a `#` comment.
pub(crate) fn looks_like_pcd(bytes: &[u8]) -> bool {
    if bytes.starts_with(b"# .PCD") {
        return true;
    }
    let mut rest = bytes;
    // A PCD header has a handful of comment lines at most; do not scan a large binary file.
    for _ in 0..16 {
        let (line, next) = split_line(rest).unwrap_or((rest, &[]));
        let line = line.trim_ascii_start();
        if line.starts_with(b"#") {
            rest = next;
            continue;
        }
        return line.starts_with(b"VERSION") || line.starts_with(b"FIELDS");
    }
    false
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DataKind {
    Ascii,
    Binary,
}

struct Header {
    fields: Vec<String>,
    types: Vec<Scalar>,
    counts: Vec<usize>,
    points: usize,
    data: DataKind,
    /// Number of header lines, to give ascii line numbers.
    lines: usize,
}

fn parse_usize(word: &str, key: &str, line_no: usize) -> Result<usize, ReadError> {
    word.parse().map_err(|_| header_err(format!("line {line_no}: {key} value '{word}' is not a count")))
}

fn parse_header(bytes: &[u8]) -> Result<(Header, &[u8]), ReadError> {
    let mut rest = bytes;
    let mut line_no = 0;
    let mut fields: Option<Vec<String>> = None;
    let mut sizes: Option<Vec<usize>> = None;
    let mut type_chars: Option<Vec<String>> = None;
    let mut counts: Option<Vec<usize>> = None;
    let (mut width, mut height, mut points) = (None, None, None);
    let data = loop {
        line_no += 1;
        let Some((line, next)) = split_line(rest) else {
            return Err(header_err("missing 'DATA' line"));
        };
        rest = next;
        let line = std::str::from_utf8(line).map_err(|_| header_err(format!("line {line_no}: not valid text")))?;
        let mut words = line.split_ascii_whitespace();
        let Some(key) = words.next() else { continue };
        if key.starts_with('#') {
            continue;
        }
        let values: Vec<&str> = words.collect();
        let single = || -> Result<&str, ReadError> {
            match values.as_slice() {
                [v] => Ok(*v),
                _ => Err(header_err(format!("line {line_no}: {key} takes one value"))),
            }
        };
        match key.to_ascii_uppercase().as_str() {
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" => fields = Some(values.iter().map(|s| (*s).to_owned()).collect()),
            "SIZE" => sizes = Some(values.iter().map(|v| parse_usize(v, "SIZE", line_no)).collect::<Result<_, _>>()?),
            "TYPE" => type_chars = Some(values.iter().map(|s| s.to_ascii_uppercase()).collect()),
            "COUNT" => {
                counts = Some(values.iter().map(|v| parse_usize(v, "COUNT", line_no)).collect::<Result<_, _>>()?)
            }
            "WIDTH" => width = Some(parse_usize(single()?, "WIDTH", line_no)?),
            "HEIGHT" => height = Some(parse_usize(single()?, "HEIGHT", line_no)?),
            "POINTS" => points = Some(parse_usize(single()?, "POINTS", line_no)?),
            "DATA" => {
                break match single()? {
                    "ascii" => DataKind::Ascii,
                    "binary" => DataKind::Binary,
                    "binary_compressed" => {
                        return Err(ReadError::Unsupported {
                            format: Format::Pcd,
                            what: "DATA binary_compressed (re-save as binary or ascii)".into(),
                        });
                    }
                    other => return Err(header_err(format!("line {line_no}: unknown DATA kind '{other}'"))),
                };
            }
            other => return Err(header_err(format!("line {line_no}: unknown keyword '{other}'"))),
        }
    };
    let fields = fields.ok_or_else(|| header_err("missing FIELDS line"))?;
    let sizes = sizes.ok_or_else(|| header_err("missing SIZE line"))?;
    let type_chars = type_chars.ok_or_else(|| header_err("missing TYPE line"))?;
    let counts = counts.unwrap_or_else(|| vec![1; fields.len()]);
    if fields.is_empty() {
        return Err(header_err("FIELDS is empty"));
    }
    for (name, len) in [("SIZE", sizes.len()), ("TYPE", type_chars.len()), ("COUNT", counts.len())] {
        if len != fields.len() {
            return Err(header_err(format!("{name} has {len} entries for {} FIELDS", fields.len())));
        }
    }
    let mut types = Vec::with_capacity(fields.len());
    for ((field, t), &size) in fields.iter().zip(&type_chars).zip(&sizes) {
        types.push(match (t.as_str(), size) {
            ("F", 4) => Scalar::F32,
            ("F", 8) => Scalar::F64,
            ("I", 1) => Scalar::I8,
            ("I", 2) => Scalar::I16,
            ("I", 4) => Scalar::I32,
            ("I", 8) => Scalar::I64,
            ("U", 1) => Scalar::U8,
            ("U", 2) => Scalar::U16,
            ("U", 4) => Scalar::U32,
            ("U", 8) => Scalar::U64,
            _ => return Err(header_err(format!("field '{field}': TYPE {t} with SIZE {size} is not a known type"))),
        });
    }
    let from_grid = match (width, height) {
        (Some(w), h) => Some(w.checked_mul(h.unwrap_or(1)).ok_or_else(|| header_err("WIDTH x HEIGHT overflows"))?),
        (None, Some(_)) => return Err(header_err("HEIGHT without WIDTH")),
        (None, None) => None,
    };
    let points = match (points, from_grid) {
        (Some(p), Some(g)) if p != g => {
            return Err(header_err(format!("POINTS {p} disagrees with WIDTH x HEIGHT = {g}")));
        }
        (Some(p), _) | (None, Some(p)) => p,
        (None, None) => return Err(header_err("missing POINTS and WIDTH")),
    };
    Ok((Header { fields, types, counts, points, data, lines: line_no }, rest))
}

/// Reads the x, y, z of every point of a PCD file.
///
/// Errors: missing or inconsistent header lines, x/y/z missing or not float (`F` 4 or 8, count 1),
/// `binary_compressed`, fewer points or bytes than declared, more ascii points than declared, a
/// non-numeric or non-finite coordinate. Note that PCL writes NaN for invalid returns of organised
/// clouds: such files are rejected (the error names the first bad point). Cost: O(file size).
pub fn read_pcd(bytes: &[u8]) -> Result<Vec<Point>, ReadError> {
    let (h, body) = parse_header(bytes)?;
    let mut xyz_field = [0usize; 3];
    for (slot, axis) in ["x", "y", "z"].iter().enumerate() {
        let i = h.fields.iter().position(|f| f == axis).ok_or_else(|| header_err(format!("FIELDS has no '{axis}'")))?;
        if !h.types[i].is_float() {
            return Err(ReadError::Unsupported {
                format: Format::Pcd,
                what: format!("field '{axis}' of type {:?}; expected F 4 or F 8", h.types[i]),
            });
        }
        if h.counts[i] != 1 {
            return Err(header_err(format!("field '{axis}' has COUNT {}; expected 1", h.counts[i])));
        }
        xyz_field[slot] = i;
    }
    match h.data {
        DataKind::Ascii => read_ascii(&h, body, xyz_field),
        DataKind::Binary => read_binary(&h, body, xyz_field),
    }
}

fn read_ascii(h: &Header, body: &[u8], xyz_field: [usize; 3]) -> Result<Vec<Point>, ReadError> {
    // Token index of each field's first value on a line.
    let mut first_token = Vec::with_capacity(h.fields.len());
    let mut per_line = 0usize;
    for &c in &h.counts {
        first_token.push(per_line);
        per_line = per_line.checked_add(c).ok_or_else(|| header_err("COUNT total overflows"))?;
    }
    let xyz_token = xyz_field.map(|f| first_token[f]);
    // Each point needs at least three one-byte numbers and separators.
    let mut points = Vec::with_capacity(h.points.min(body.len() / 6));
    let mut rest = body;
    let mut line_no = h.lines;
    while !rest.is_empty() {
        line_no += 1;
        let (line, next) = split_line(rest).unwrap_or((rest, &[]));
        rest = next;
        let mut n_tokens = 0usize;
        let mut values = [0.0f64; 3];
        for tok in line.split(|b| b.is_ascii_whitespace()).filter(|t| !t.is_empty()) {
            if let Some(slot) = xyz_token.iter().position(|&t| t == n_tokens) {
                values[slot] = std::str::from_utf8(tok).ok().and_then(|s| s.parse::<f64>().ok()).ok_or_else(|| {
                    data_err(format!("line {line_no}: '{}' is not a number", String::from_utf8_lossy(tok)))
                })?;
            }
            n_tokens += 1;
        }
        if n_tokens == 0 {
            continue;
        }
        if n_tokens != per_line {
            return Err(data_err(format!("line {line_no}: expected {per_line} values, got {n_tokens}")));
        }
        if points.len() == h.points {
            return Err(data_err(format!("line {line_no}: more than the {} declared points", h.points)));
        }
        points.push(finite_point(points.len(), values[0], values[1], values[2])?);
    }
    if points.len() < h.points {
        return Err(ReadError::Truncated { what: "points".into(), expected: h.points, got: points.len() });
    }
    Ok(points)
}

fn read_binary(h: &Header, body: &[u8], xyz_field: [usize; 3]) -> Result<Vec<Point>, ReadError> {
    let mut offsets = Vec::with_capacity(h.fields.len());
    let mut stride = 0usize;
    for (t, &c) in h.types.iter().zip(&h.counts) {
        offsets.push(stride);
        stride = t
            .size()
            .checked_mul(c)
            .and_then(|b| stride.checked_add(b))
            .ok_or_else(|| header_err("record size overflows"))?;
    }
    let needed = h.points.saturating_mul(stride);
    if needed > body.len() {
        return Err(ReadError::Truncated { what: "bytes of point data".into(), expected: needed, got: body.len() });
    }
    let mut points = Vec::with_capacity(h.points);
    // x, y, z have count 1, so stride > 0 here.
    let axes = xyz_field.map(|f| (offsets[f], h.types[f]));
    for (i, rec) in body[..needed].chunks_exact(stride).enumerate() {
        let [x, y, z] = axes.map(|(off, t)| t.read_le_f64(&rec[off..]));
        points.push(finite_point(i, x, y, z)?);
    }
    Ok(points)
}
