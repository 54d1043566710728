//! Feather v2 (the Arrow IPC file format) reader, uncompressed or with LZ4-frame compressed
//! record batches: Argoverse 2 sweeps ([`read_feather`]: columns `x`, `y`, `z`, float16 in AV2,
//! float32 and float64 read too, among any other flat columns; AV2 adds `intensity`,
//! `laser_number`, `offset_ns`, which are dropped) and any numeric columns ([`read_columns`],
//! e.g. AV2's `city_SE3_egovehicle.feather` poses); [`write_batch`] writes one.
//!
//! The file's footer, record-batch messages and buffer table are checked here, before arrow-ipc
//! decodes anything: arrow-ipc trusts the lengths a file declares (it allocates a block's body
//! length and each buffer's declared uncompressed length, and slices buffers with asserting
//! calls), so a hostile upload could otherwise abort the process or panic. Only flat columns of
//! integer, float and bool type are accepted, which makes every column exactly one field node
//! and two buffers (validity, values) and lets the schema be built here rather than by
//! arrow-ipc's converter (which panics on some malformed type descriptions).

use std::collections::HashMap;
use std::sync::Arc;

use arrow_array::Array;
use arrow_array::cast::AsArray;
use arrow_array::types::{
    ArrowPrimitiveType, Float16Type, Float32Type, Float64Type, Int8Type, Int16Type, Int32Type, Int64Type, UInt8Type,
    UInt16Type, UInt32Type, UInt64Type,
};
use arrow_ipc::{CompressionType, Precision, Type};
use arrow_schema::{DataType, Field, Schema};

use super::{FEATHER_MAGIC as MAGIC, FEATHER_V1_MAGIC as MAGIC_V1, Format, ReadError, finite_point};
use crate::geometry::Point;

/// Marker before an encapsulated message's metadata length (format version 0.15 and later).
const CONTINUATION: [u8; 4] = [0xff; 4];
/// Bytes after the footer: its int32 length and the magic.
const TRAILER_BYTES: usize = 4 + MAGIC.len();
/// LZ4's best compression ratio is just under 255:1 (a maximal match costs one byte per 255
/// bytes of output), so a buffer declaring more than this many output bytes per input byte is
/// malformed; the check runs before arrow-ipc reserves the declared size.
const LZ4_MAX_RATIO: u64 = 256;
/// Frame overhead allowance (header, block checksums) of an LZ4 frame, on top of the ratio.
const LZ4_SLACK_BYTES: u64 = 1024;
/// Upper bound on the total decompressed size of one file's record batches: an AV2 sweep is
/// about 1.2 MB decompressed (100k points x 12 bytes), so 2 GiB only refuses bombs.
pub const MAX_DECOMPRESSED_BYTES: u64 = 2 << 30;
/// An uncompressed-length prefix of -1 marks a buffer stored uncompressed in a compressed batch.
const LENGTH_NO_COMPRESSED_DATA: i64 = -1;

fn data_error(message: impl Into<String>) -> ReadError {
    ReadError::Data { format: Format::Feather, message: message.into() }
}

fn header_error(message: impl Into<String>) -> ReadError {
    ReadError::Header { format: Format::Feather, message: message.into() }
}

fn unsupported(what: impl Into<String>) -> ReadError {
    ReadError::Unsupported { format: Format::Feather, what: what.into() }
}

/// A column of a flat schema, as declared in the file.
struct Column {
    name: String,
    data_type: DataType,
    nullable: bool,
}

/// Values of one column over every record batch of a file.
#[derive(Debug, Clone, PartialEq)]
pub enum Values {
    /// A float16, float32 or float64 column, widened to f64.
    Float(Vec<f64>),
    /// A signed or unsigned integer column (a uint64 value above `i64::MAX` is an error).
    Int(Vec<i64>),
}

impl Values {
    /// Number of rows.
    pub fn len(&self) -> usize {
        match self {
            Values::Float(v) => v.len(),
            Values::Int(v) => v.len(),
        }
    }

    /// Whether there are no rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Reads the x, y, z (m) of every row of every record batch, in file order; other columns are
/// dropped.
///
/// Errors: those of [`read_columns`], a coordinate column that is not float16/32/64, a
/// non-finite coordinate. An empty table is an empty cloud. Cost: O(file size + decompressed
/// size).
pub fn read_feather(bytes: &[u8]) -> Result<Vec<Point>, ReadError> {
    let columns = read_columns(bytes, &["x", "y", "z"])?;
    let mut axes = Vec::with_capacity(3);
    for (name, values) in ["x", "y", "z"].into_iter().zip(columns) {
        match values {
            Values::Float(v) => axes.push(v),
            Values::Int(_) => {
                return Err(unsupported(format!(
                    "integer column '{name}': x, y, z must be float16, float32 or float64"
                )));
            }
        }
    }
    (0..axes[0].len()).map(|i| finite_point(i, axes[0][i], axes[1][i], axes[2][i])).collect()
}

/// Reads the columns `names` (in that order) of a Feather v2 file, concatenated over its record
/// batches.
///
/// Errors: not an Arrow IPC file (or Feather v1), a footer, message or buffer that does not fit
/// in the file, a compressed buffer declaring more than LZ4 can expand to, ZSTD compression,
/// big-endian data, a column that is not a flat integer / float / bool column, a missing
/// column, a requested bool column, a null value. Cost: O(file size + decompressed size).
pub fn read_columns(bytes: &[u8], names: &[&str]) -> Result<Vec<Values>, ReadError> {
    if bytes.starts_with(MAGIC_V1) {
        return Err(unsupported("Feather v1 ('FEA1'); write Feather v2 (pyarrow.feather.write_feather(version=2))"));
    }
    if !bytes.starts_with(MAGIC) {
        return Err(header_error("no 'ARROW1' magic at the start: not an Arrow IPC / Feather v2 file"));
    }
    let footer = read_footer(bytes)?;
    let fb_schema = footer.schema().ok_or_else(|| header_error("the footer has no schema"))?;
    if fb_schema.endianness() != arrow_ipc::Endianness::Little {
        return Err(unsupported("big-endian data"));
    }
    let columns = read_schema(&fb_schema)?;
    if footer.dictionaries().is_some_and(|d| !d.is_empty()) {
        return Err(unsupported("dictionary batches (dictionary-encoded columns)"));
    }
    let projection: Vec<usize> = names
        .iter()
        .map(|name| {
            let i = columns.iter().position(|c| c.name == *name).ok_or_else(|| {
                let present: Vec<&str> = columns.iter().map(|c| c.name.as_str()).collect();
                header_error(format!("no column '{name}' (columns: {})", present.join(", ")))
            })?;
            if columns[i].data_type == DataType::Boolean {
                return Err(unsupported(format!("bool column '{name}' where a number is expected")));
            }
            Ok(i)
        })
        .collect::<Result<_, _>>()?;
    let schema = Arc::new(Schema::new(
        columns.iter().map(|c| Field::new(c.name.clone(), c.data_type.clone(), c.nullable)).collect::<Vec<_>>(),
    ));
    let blocks = footer.recordBatches().ok_or_else(|| header_error("the footer lists no record batches"))?;
    let mut out: Vec<Values> = projection
        .iter()
        .map(|&i| if is_float(&columns[i].data_type) { Values::Float(Vec::new()) } else { Values::Int(Vec::new()) })
        .collect();
    let mut decompressed_total = 0u64;
    for (b, block) in blocks.iter().enumerate() {
        let (message, body) = read_message(bytes, b, block)?;
        let batch =
            message.header_as_record_batch().ok_or_else(|| data_error(format!("block {b} is not a record batch")))?;
        decompressed_total += check_batch(b, &batch, columns.len(), body)?;
        if decompressed_total > MAX_DECOMPRESSED_BYTES {
            return Err(data_error(format!(
                "record batches decompress to over {MAX_DECOMPRESSED_BYTES} bytes (limit of one file)"
            )));
        }
        let rows_before = out.first().map_or(0, Values::len);
        let body = arrow_buffer::Buffer::from(body);
        let version = message.version();
        // The checks above cover what arrow-ipc is known to trust; an unwind from its decoder on
        // a case they miss still becomes an error rather than a crash of the upload path.
        let decoded = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            arrow_ipc::reader::read_record_batch(
                &body,
                batch,
                schema.clone(),
                &HashMap::new(),
                Some(&projection),
                &version,
            )
        }))
        .map_err(|_| data_error(format!("record batch {b}: malformed (the Arrow decoder refused it)")))?
        .map_err(|e| data_error(format!("record batch {b}: {e}")))?;
        for ((name, column), values) in names.iter().zip(decoded.columns()).zip(&mut out) {
            append_values(name, column.as_ref(), rows_before, values)?;
        }
    }
    Ok(out)
}

fn is_float(t: &DataType) -> bool {
    matches!(t, DataType::Float16 | DataType::Float32 | DataType::Float64)
}

/// Appends a decoded column to `values` (of the kind [`read_columns`] chose from its type);
/// `first_row` is the file row of its first value, for messages.
fn append_values(name: &str, column: &dyn Array, first_row: usize, values: &mut Values) -> Result<(), ReadError> {
    if let Some(row) = (0..column.len()).find(|&r| column.is_null(r)) {
        return Err(data_error(format!("row {}: '{name}' is null", first_row + row)));
    }
    let wrong = || data_error(format!("column '{name}' changed type between record batches"));
    match values {
        Values::Float(v) => match column.data_type() {
            DataType::Float16 => v.extend(column.as_primitive::<Float16Type>().values().iter().map(|x| x.to_f64())),
            DataType::Float32 => v.extend(column.as_primitive::<Float32Type>().values().iter().map(|&x| x as f64)),
            DataType::Float64 => v.extend_from_slice(column.as_primitive::<Float64Type>().values()),
            _ => return Err(wrong()),
        },
        Values::Int(v) => {
            fn widen<T: ArrowPrimitiveType>(column: &dyn Array, v: &mut Vec<i64>)
            where
                T::Native: Into<i64>,
            {
                v.extend(column.as_primitive::<T>().values().iter().map(|&x| x.into()));
            }
            match column.data_type() {
                DataType::Int8 => widen::<Int8Type>(column, v),
                DataType::Int16 => widen::<Int16Type>(column, v),
                DataType::Int32 => widen::<Int32Type>(column, v),
                DataType::Int64 => widen::<Int64Type>(column, v),
                DataType::UInt8 => widen::<UInt8Type>(column, v),
                DataType::UInt16 => widen::<UInt16Type>(column, v),
                DataType::UInt32 => widen::<UInt32Type>(column, v),
                DataType::UInt64 => {
                    for (r, &x) in column.as_primitive::<UInt64Type>().values().iter().enumerate() {
                        let x = i64::try_from(x)
                            .map_err(|_| data_error(format!("row {}: '{name}' = {x} exceeds int64", first_row + r)))?;
                        v.push(x);
                    }
                }
                _ => return Err(wrong()),
            }
        }
    }
    Ok(())
}

/// The footer of an Arrow IPC file, bounds-checked and verified.
fn read_footer(bytes: &[u8]) -> Result<arrow_ipc::Footer<'_>, ReadError> {
    // Leading magic padded to 8 bytes, then at least the trailer.
    let min_len = 8 + TRAILER_BYTES;
    if bytes.len() < min_len {
        return Err(ReadError::Truncated {
            what: "bytes of Arrow IPC file".into(),
            expected: min_len,
            got: bytes.len(),
        });
    }
    let trailer = &bytes[bytes.len() - TRAILER_BYTES..];
    if &trailer[4..] != MAGIC {
        return Err(data_error("no 'ARROW1' magic at the end: the file is truncated (or an IPC stream, not a file)"));
    }
    let footer_len = i32::from_le_bytes([trailer[0], trailer[1], trailer[2], trailer[3]]);
    let room = bytes.len() - TRAILER_BYTES - 8;
    let footer_len = usize::try_from(footer_len)
        .ok()
        .filter(|&n| n <= room)
        .ok_or_else(|| data_error(format!("footer length {footer_len} does not fit in {} bytes", bytes.len())))?;
    let end = bytes.len() - TRAILER_BYTES;
    arrow_ipc::root_as_footer(&bytes[end - footer_len..end]).map_err(|e| data_error(format!("footer: {e}")))
}

/// The columns of a flat schema; anything nested, dictionary-encoded or of another type is
/// refused (see the module documentation for why).
fn read_schema(schema: &arrow_ipc::Schema<'_>) -> Result<Vec<Column>, ReadError> {
    let fields = schema.fields().ok_or_else(|| header_error("the schema has no field list"))?;
    let mut columns = Vec::with_capacity(fields.len());
    for (i, field) in fields.iter().enumerate() {
        let name = field.name().unwrap_or_default().to_owned();
        let shown = if name.is_empty() { format!("#{i}") } else { format!("'{name}'") };
        if field.dictionary().is_some() || field.children().is_some_and(|c| !c.is_empty()) {
            return Err(unsupported(format!("column {shown} is dictionary-encoded or nested")));
        }
        let data_type = match field.type_type() {
            Type::Bool => DataType::Boolean,
            Type::Int => {
                let int = field.type_as_int().ok_or_else(|| header_error(format!("column {shown}: no int type")))?;
                match (int.bitWidth(), int.is_signed()) {
                    (8, true) => DataType::Int8,
                    (16, true) => DataType::Int16,
                    (32, true) => DataType::Int32,
                    (64, true) => DataType::Int64,
                    (8, false) => DataType::UInt8,
                    (16, false) => DataType::UInt16,
                    (32, false) => DataType::UInt32,
                    (64, false) => DataType::UInt64,
                    (bits, _) => return Err(header_error(format!("column {shown}: integer of {bits} bits"))),
                }
            }
            Type::FloatingPoint => {
                let float = field
                    .type_as_floating_point()
                    .ok_or_else(|| header_error(format!("column {shown}: no floating-point type")))?;
                match float.precision() {
                    Precision::HALF => DataType::Float16,
                    Precision::SINGLE => DataType::Float32,
                    Precision::DOUBLE => DataType::Float64,
                    other => return Err(header_error(format!("column {shown}: float precision {}", other.0))),
                }
            }
            other => {
                return Err(unsupported(format!(
                    "column {shown} of type {}: only flat integer, float and bool columns are read",
                    other.variant_name().unwrap_or("unknown")
                )));
            }
        };
        columns.push(Column { name, data_type, nullable: field.nullable() });
    }
    Ok(columns)
}

/// The message and body of record-batch block `b`, both checked to lie inside `bytes`.
fn read_message<'a>(
    bytes: &'a [u8],
    b: usize,
    block: &arrow_ipc::Block,
) -> Result<(arrow_ipc::Message<'a>, &'a [u8]), ReadError> {
    let bad = |what: &str| data_error(format!("record batch {b}: {what}"));
    let offset = usize::try_from(block.offset()).map_err(|_| bad("negative offset"))?;
    let meta_len = usize::try_from(block.metaDataLength()).map_err(|_| bad("negative metadata length"))?;
    let body_len = usize::try_from(block.bodyLength()).map_err(|_| bad("negative body length"))?;
    let end = offset.checked_add(meta_len).and_then(|e| e.checked_add(body_len)).unwrap_or(usize::MAX);
    if end > bytes.len() {
        return Err(ReadError::Truncated {
            what: format!("bytes (record batch {b} ends at byte {end})"),
            expected: end,
            got: bytes.len(),
        });
    }
    let meta = &bytes[offset..offset + meta_len];
    let body = &bytes[offset + meta_len..end];
    // Encapsulated message: [continuation] int32 length, then the flatbuffer.
    let (len_at, flat_at) = if meta.starts_with(&CONTINUATION) { (4, 8) } else { (0, 4) };
    if meta.len() < flat_at {
        return Err(bad("metadata shorter than its length prefix"));
    }
    let flat_len = i32::from_le_bytes([meta[len_at], meta[len_at + 1], meta[len_at + 2], meta[len_at + 3]]);
    let flat_end = usize::try_from(flat_len)
        .ok()
        .and_then(|n| n.checked_add(flat_at))
        .filter(|&e| e <= meta.len())
        .ok_or_else(|| bad("message length does not fit in its block"))?;
    let message = arrow_ipc::root_as_message(&meta[flat_at..flat_end]).map_err(|e| bad(&format!("message: {e}")))?;
    Ok((message, body))
}

/// Checks a record batch of a flat schema of `columns` columns against its body: one field node
/// per column with a length equal to the batch's, two buffers per column inside the body, and
/// (when compressed with LZ4) declared uncompressed lengths LZ4 can reach. Returns the bytes the
/// batch decompresses to.
fn check_batch(b: usize, batch: &arrow_ipc::RecordBatch<'_>, columns: usize, body: &[u8]) -> Result<u64, ReadError> {
    let body_len = body.len();
    let bad = |what: String| data_error(format!("record batch {b}: {what}"));
    let rows = batch.length();
    if rows < 0 {
        return Err(bad(format!("negative row count {rows}")));
    }
    let nodes = batch.nodes().ok_or_else(|| bad("no field nodes".into()))?;
    if nodes.len() != columns {
        return Err(bad(format!("{} field nodes for {columns} columns", nodes.len())));
    }
    for (i, node) in nodes.iter().enumerate() {
        if node.length() != rows || !(0..=rows).contains(&node.null_count()) {
            return Err(bad(format!(
                "column {i}: {} values with {} nulls in a batch of {rows} rows",
                node.length(),
                node.null_count()
            )));
        }
    }
    let buffers = batch.buffers().ok_or_else(|| bad("no buffer list".into()))?;
    if buffers.len() != 2 * columns {
        return Err(bad(format!("{} buffers for {columns} flat columns (2 each)", buffers.len())));
    }
    let compression = match batch.compression() {
        None => None,
        Some(c) if c.codec() == CompressionType::LZ4_FRAME => Some(c),
        Some(c) => return Err(unsupported(format!("{:?} compression (LZ4 and uncompressed are read)", c.codec()))),
    };
    let mut decompressed = 0u64;
    for (i, buffer) in buffers.iter().enumerate() {
        let (offset, len) = (buffer.offset(), buffer.length());
        let fits = offset >= 0 && len >= 0 && offset.checked_add(len).is_some_and(|e| e as u64 <= body_len as u64);
        if !fits {
            return Err(bad(format!(
                "buffer {i} (offset {offset}, {len} bytes) lies outside the {body_len}-byte body"
            )));
        }
        let (offset, len) = (offset as usize, len as usize);
        if compression.is_none() || len == 0 {
            decompressed += len as u64;
            continue;
        }
        // A compressed buffer starts with its uncompressed length (int64), then the LZ4 frame;
        // the buffer lies inside the body (checked above), so its first 8 bytes do too.
        if len < 8 {
            return Err(bad(format!("compressed buffer {i} has {len} bytes, fewer than its 8-byte length prefix")));
        }
        let prefix = &body[offset..offset + 8];
        let declared = i64::from_le_bytes(prefix.try_into().expect("8 bytes"));
        if declared == LENGTH_NO_COMPRESSED_DATA {
            decompressed += len as u64 - 8;
            continue;
        }
        let limit = (len as u64 - 8) * LZ4_MAX_RATIO + LZ4_SLACK_BYTES;
        if declared < 0 || declared as u64 > limit {
            return Err(bad(format!(
                "compressed buffer {i} declares {declared} bytes, more than {} LZ4 bytes can hold",
                len - 8
            )));
        }
        decompressed += declared as u64;
    }
    Ok(decompressed)
}

/// Writes `batch` as a Feather v2 file (one record batch), its buffers LZ4-compressed when `lz4`
/// (as Argoverse 2's files) or plain.
pub fn write_batch<W: std::io::Write>(
    w: W,
    batch: &arrow_array::RecordBatch,
    lz4: bool,
) -> Result<W, super::WriteError> {
    let compression = lz4.then_some(CompressionType::LZ4_FRAME);
    let options = arrow_ipc::writer::IpcWriteOptions::default().try_with_compression(compression)?;
    let mut writer = arrow_ipc::writer::FileWriter::try_new_with_options(w, &batch.schema(), options)?;
    writer.write(batch)?;
    writer.finish()?;
    Ok(writer.into_inner()?)
}
