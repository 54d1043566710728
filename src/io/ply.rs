//! Stanford PLY reader: ascii and binary little-endian, `vertex` element with float or double
//! x, y, z. Other vertex properties (of any type, lists included) and other elements, before or
//! after the vertex element, are skipped. Binary big-endian is rejected as unsupported.

use super::{Format, ReadError, Scalar, finite_point, split_line};
use crate::geometry::Point;

fn header_err(message: impl Into<String>) -> ReadError {
    ReadError::Header { format: Format::Ply, message: message.into() }
}

fn data_err(message: impl Into<String>) -> ReadError {
    ReadError::Data { format: Format::Ply, message: message.into() }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Ascii,
    BinaryLe,
}

#[derive(Debug, Clone, Copy)]
enum PropKind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug)]
struct Property {
    name: String,
    kind: PropKind,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

/// Where x, y, z sit among the vertex properties.
struct XyzIndex {
    x: usize,
    y: usize,
    z: usize,
}

fn parse_type(name: &str, line_no: usize) -> Result<Scalar, ReadError> {
    Ok(match name {
        "char" | "int8" => Scalar::I8,
        "uchar" | "uint8" => Scalar::U8,
        "short" | "int16" => Scalar::I16,
        "ushort" | "uint16" => Scalar::U16,
        "int" | "int32" => Scalar::I32,
        "uint" | "uint32" => Scalar::U32,
        "float" | "float32" => Scalar::F32,
        "double" | "float64" => Scalar::F64,
        other => return Err(header_err(format!("line {line_no}: unknown property type '{other}'"))),
    })
}

/// Parses the header; returns the encoding, the elements and the body after `end_header`.
fn parse_header(bytes: &[u8]) -> Result<(Encoding, Vec<Element>, &[u8]), ReadError> {
    let (first, mut rest) = split_line(bytes).ok_or_else(|| header_err("missing 'ply' magic line"))?;
    if first != b"ply" {
        return Err(header_err("missing 'ply' magic line"));
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut line_no = 1;
    loop {
        line_no += 1;
        let Some((line, next)) = split_line(rest) else {
            return Err(header_err("missing 'end_header'"));
        };
        rest = next;
        let line = std::str::from_utf8(line).map_err(|_| header_err(format!("line {line_no}: not valid text")))?;
        let mut words = line.split_ascii_whitespace();
        match words.next() {
            None | Some("comment") | Some("obj_info") => {}
            Some("end_header") => break,
            Some("format") => {
                encoding = Some(match words.next() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::BinaryLe,
                    Some("binary_big_endian") => {
                        return Err(ReadError::Unsupported {
                            format: Format::Ply,
                            what: "binary_big_endian encoding (convert to binary_little_endian or ascii)".into(),
                        });
                    }
                    other => {
                        return Err(header_err(format!("line {line_no}: unknown format {:?}", other.unwrap_or(""))));
                    }
                });
            }
            Some("element") => {
                let (Some(name), Some(count), None) = (words.next(), words.next(), words.next()) else {
                    return Err(header_err(format!("line {line_no}: expected 'element NAME COUNT'")));
                };
                let count = count
                    .parse::<usize>()
                    .map_err(|_| header_err(format!("line {line_no}: element count '{count}' is not a count")))?;
                elements.push(Element { name: name.to_owned(), count, props: Vec::new() });
            }
            Some("property") => {
                let element = elements
                    .last_mut()
                    .ok_or_else(|| header_err(format!("line {line_no}: property before any element")))?;
                let words: Vec<&str> = words.collect();
                let prop = match words.as_slice() {
                    ["list", count, item, name] => {
                        let count = parse_type(count, line_no)?;
                        if count.is_float() {
                            return Err(header_err(format!("line {line_no}: list count type must be an integer")));
                        }
                        Property {
                            name: (*name).to_owned(),
                            kind: PropKind::List { count, item: parse_type(item, line_no)? },
                        }
                    }
                    [ty, name] => {
                        Property { name: (*name).to_owned(), kind: PropKind::Scalar(parse_type(ty, line_no)?) }
                    }
                    _ => return Err(header_err(format!("line {line_no}: malformed property line '{line}'"))),
                };
                element.props.push(prop);
            }
            Some(other) => return Err(header_err(format!("line {line_no}: unknown keyword '{other}'"))),
        }
    }
    let encoding = encoding.ok_or_else(|| header_err("missing 'format' line"))?;
    Ok((encoding, elements, rest))
}

fn xyz_index(vertex: &Element) -> Result<XyzIndex, ReadError> {
    let find = |axis: &str| -> Result<usize, ReadError> {
        let i = vertex
            .props
            .iter()
            .position(|p| p.name == axis)
            .ok_or_else(|| header_err(format!("vertex element has no property '{axis}'")))?;
        match vertex.props[i].kind {
            PropKind::Scalar(s) if s.is_float() => Ok(i),
            PropKind::Scalar(s) => Err(ReadError::Unsupported {
                format: Format::Ply,
                what: format!("vertex property '{axis}' of type {s:?}; expected float or double"),
            }),
            PropKind::List { .. } => Err(header_err(format!("vertex property '{axis}' is a list"))),
        }
    };
    Ok(XyzIndex { x: find("x")?, y: find("y")?, z: find("z")? })
}

/// Reads the vertex positions of a PLY file.
///
/// Errors: no `ply` magic, no `end_header`, no `vertex` element or no float x/y/z in it,
/// big-endian encoding, fewer bytes or tokens than the element counts declare, a non-numeric
/// coordinate, a non-finite coordinate. Cost: O(file size).
pub fn read_ply(bytes: &[u8]) -> Result<Vec<Point>, ReadError> {
    let (encoding, elements, body) = parse_header(bytes)?;
    let vi = elements.iter().position(|e| e.name == "vertex").ok_or_else(|| header_err("no 'vertex' element"))?;
    let xyz = xyz_index(&elements[vi])?;
    match encoding {
        Encoding::Ascii => read_ascii(body, &elements, vi, &xyz),
        Encoding::BinaryLe => read_binary(body, &elements, vi, &xyz),
    }
}

/// ASCII body: a stream of whitespace-separated tokens, record after record.
fn read_ascii(body: &[u8], elements: &[Element], vi: usize, xyz: &XyzIndex) -> Result<Vec<Point>, ReadError> {
    let mut tokens = body.split(|b| b.is_ascii_whitespace()).filter(|t| !t.is_empty());
    for e in &elements[..vi] {
        if e.props.is_empty() {
            continue;
        }
        for r in 0..e.count {
            skip_ascii_record(&mut tokens, e).ok_or_else(|| ReadError::Truncated {
                what: format!("'{}' records", e.name),
                expected: e.count,
                got: r,
            })??;
        }
    }
    let vertex = &elements[vi];
    // Each vertex takes at least three one-byte tokens and their separators.
    let mut points = Vec::with_capacity(vertex.count.min(body.len() / 6));
    let mut values = [0.0f64; 3];
    for r in 0..vertex.count {
        let truncated = || ReadError::Truncated { what: "vertices".into(), expected: vertex.count, got: r };
        for (pi, prop) in vertex.props.iter().enumerate() {
            match prop.kind {
                PropKind::Scalar(_) => {
                    let tok = tokens.next().ok_or_else(truncated)?;
                    let slot = if pi == xyz.x {
                        0
                    } else if pi == xyz.y {
                        1
                    } else if pi == xyz.z {
                        2
                    } else {
                        continue;
                    };
                    values[slot] = parse_f64(tok).ok_or_else(|| {
                        data_err(format!("vertex {r}: '{}' is not a number", String::from_utf8_lossy(tok)))
                    })?;
                }
                PropKind::List { .. } => {
                    let n = parse_count(tokens.next().ok_or_else(truncated)?, r)?;
                    for _ in 0..n {
                        tokens.next().ok_or_else(truncated)?;
                    }
                }
            }
        }
        points.push(finite_point(r, values[0], values[1], values[2])?);
    }
    Ok(points)
}

/// Skips one record; `None` when tokens run out, `Some(Err)` on a bad list count.
fn skip_ascii_record<'a>(tokens: &mut impl Iterator<Item = &'a [u8]>, e: &Element) -> Option<Result<(), ReadError>> {
    for prop in &e.props {
        let tok = tokens.next()?;
        if let PropKind::List { .. } = prop.kind {
            let n = match parse_count(tok, 0) {
                Ok(n) => n,
                Err(err) => return Some(Err(err)),
            };
            for _ in 0..n {
                tokens.next()?;
            }
        }
    }
    Some(Ok(()))
}

fn parse_f64(tok: &[u8]) -> Option<f64> {
    std::str::from_utf8(tok).ok()?.parse().ok()
}

fn parse_count(tok: &[u8], record: usize) -> Result<usize, ReadError> {
    std::str::from_utf8(tok).ok().and_then(|s| s.parse::<usize>().ok()).ok_or_else(|| {
        data_err(format!("record {record}: list count '{}' is not a count", String::from_utf8_lossy(tok)))
    })
}

/// Binary little-endian body: records packed back to back.
fn read_binary(body: &[u8], elements: &[Element], vi: usize, xyz: &XyzIndex) -> Result<Vec<Point>, ReadError> {
    let mut pos = 0usize;
    for e in &elements[..vi] {
        if e.props.is_empty() {
            continue;
        }
        for r in 0..e.count {
            pos = skip_binary_record(body, pos, e).ok_or_else(|| ReadError::Truncated {
                what: format!("'{}' records", e.name),
                expected: e.count,
                got: r,
            })?;
        }
    }
    let vertex = &elements[vi];
    let data = &body[pos..];
    let fixed: Option<Vec<(usize, Scalar)>> = vertex
        .props
        .iter()
        .map(|p| match p.kind {
            PropKind::Scalar(s) => Some((0, s)),
            PropKind::List { .. } => None,
        })
        .collect();
    if let Some(mut layout) = fixed {
        // Offsets of each property inside a fixed-size record.
        let mut stride = 0;
        for (off, s) in layout.iter_mut() {
            *off = stride;
            stride += s.size();
        }
        let needed = vertex.count.saturating_mul(stride);
        if needed > data.len() {
            return Err(ReadError::Truncated {
                what: "bytes of vertex data".into(),
                expected: needed,
                got: data.len(),
            });
        }
        let (ox, sx) = layout[xyz.x];
        let (oy, sy) = layout[xyz.y];
        let (oz, sz) = layout[xyz.z];
        let mut points = Vec::with_capacity(vertex.count);
        if stride == 0 {
            return Ok(points);
        }
        for (r, rec) in data[..needed].chunks_exact(stride).enumerate() {
            points.push(finite_point(
                r,
                sx.read_le_f64(&rec[ox..]),
                sy.read_le_f64(&rec[oy..]),
                sz.read_le_f64(&rec[oz..]),
            )?);
        }
        return Ok(points);
    }
    // Vertex records with list properties: variable size, walk them one by one.
    let min_record: usize = vertex
        .props
        .iter()
        .map(|p| match p.kind {
            PropKind::Scalar(s) => s.size(),
            PropKind::List { count, .. } => count.size(),
        })
        .sum();
    let mut points = Vec::with_capacity(vertex.count.min(data.len() / min_record.max(1)));
    let mut values = [0.0f64; 3];
    let mut pos = 0usize;
    for r in 0..vertex.count {
        let truncated = || ReadError::Truncated { what: "vertices".into(), expected: vertex.count, got: r };
        for (pi, prop) in vertex.props.iter().enumerate() {
            match prop.kind {
                PropKind::Scalar(s) => {
                    let b = data.get(pos..pos + s.size()).ok_or_else(truncated)?;
                    pos += s.size();
                    if pi == xyz.x {
                        values[0] = s.read_le_f64(b);
                    } else if pi == xyz.y {
                        values[1] = s.read_le_f64(b);
                    } else if pi == xyz.z {
                        values[2] = s.read_le_f64(b);
                    }
                }
                PropKind::List { count, item } => {
                    pos = skip_list(data, pos, count, item).ok_or_else(truncated)?;
                }
            }
        }
        points.push(finite_point(r, values[0], values[1], values[2])?);
    }
    Ok(points)
}

/// Skips one binary record starting at `pos`; `None` if it runs past the end.
fn skip_binary_record(body: &[u8], mut pos: usize, e: &Element) -> Option<usize> {
    for prop in &e.props {
        pos = match prop.kind {
            PropKind::Scalar(s) => {
                let end = pos.checked_add(s.size())?;
                (end <= body.len()).then_some(end)?
            }
            PropKind::List { count, item } => skip_list(body, pos, count, item)?,
        };
    }
    Some(pos)
}

/// Skips a binary list (count, then items); `None` if it runs past the end or the count is negative.
fn skip_list(body: &[u8], pos: usize, count: Scalar, item: Scalar) -> Option<usize> {
    let b = body.get(pos..pos.checked_add(count.size())?)?;
    let n = count.read_le_f64(b);
    if n < 0.0 {
        return None;
    }
    let end = (pos + count.size()).checked_add((n as usize).checked_mul(item.size())?)?;
    (end <= body.len()).then_some(end)
}
