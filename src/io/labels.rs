//! Label export: per-point flows of a sequence as `.npz` (NumPy) or, with the `av2` feature, as
//! a zip of Feather v2 files in the ZeroFlow / SceneFlowZoo Argoverse 2 layout; and one frame's
//! labels as a file of its own in either format (`mbnt label`).

use std::io::{Seek, Write};

use super::WriteError;
use super::npz::NpzWriter;
use crate::geometry::Point;

/// A writer of a log's labels one frame at a time, so that a long log's labels never hold more
/// than a frame ([`LabelsNpzWriter`], and [`LabelsAv2Writer`] with the `av2` feature): call
/// [`LabelsWriter::frame`] for k = 0, 1, ..., then the writer's own `finish`.
pub trait LabelsWriter {
    /// Writes the next frame's labels: its flow to the next frame (`None` for the last frame,
    /// which has none) and the moving body of each of its points (-1 for none).
    fn frame(&mut self, flow: Option<&[Point]>, object_ids: &[i32]) -> Result<(), WriteError>;
}

/// Writes labels as an `.npz`, one frame at a time (so that a long log's labels never hold more
/// than a frame): arrays `flow_000`, `flow_001`, ... (float32, shape (N_k, 3), metres, frame k's
/// sensor coordinates, point order of frame k; none for the last frame, which has no next),
/// `object_000`, ... (int32, shape (N_k,): the moving body each point of frame k lies on, -1 for
/// none) and `timestamps` (float64, shape (T,), seconds). Names have at least three digits,
/// more beyond 1000 frames. Call [`LabelsNpzWriter::frame`] for k = 0, 1, ..., then
/// [`LabelsNpzWriter::finish`].
pub struct LabelsNpzWriter<W: Write + Seek> {
    npz: NpzWriter<W>,
    frames: usize,
}

impl<W: Write + Seek> LabelsNpzWriter<W> {
    /// A writer of labels into `w`.
    pub fn new(w: W) -> Self {
        Self { npz: NpzWriter::new(w), frames: 0 }
    }

    /// Writes the timestamps (s, one per frame) and closes the archive.
    pub fn finish(mut self, timestamps_s: &[f64]) -> Result<W, WriteError> {
        self.npz.add_f64("timestamps", &[timestamps_s.len()], timestamps_s)?;
        self.npz.finish()
    }
}

impl<W: Write + Seek> LabelsWriter for LabelsNpzWriter<W> {
    fn frame(&mut self, flow: Option<&[Point]>, object_ids: &[i32]) -> Result<(), WriteError> {
        let k = self.frames;
        if let Some(flow) = flow {
            if flow.len() != object_ids.len() {
                return Err(WriteError::Inconsistent(format!(
                    "frame {k}: {} object ids for {} flows",
                    object_ids.len(),
                    flow.len()
                )));
            }
            self.npz.add_f32(&format!("flow_{k:03}"), &[flow.len(), 3], flow.as_flattened())?;
        }
        self.npz.add_i32(&format!("object_{k:03}"), &[object_ids.len()], object_ids)?;
        self.frames += 1;
        Ok(())
    }
}

/// Writes labels as [`write_labels_av2_zip`] does, one frame at a time (so that a long log's
/// labels never hold more than a frame): a Feather entry per frame with a flow, every point
/// valid. Call [`LabelsWriter::frame`] for k = 0, 1, ... (the last frame's object ids, which
/// have no flow, are not written: the layout has flows only), then [`LabelsAv2Writer::finish`].
#[cfg(feature = "av2")]
pub struct LabelsAv2Writer<W: Write + Seek> {
    zip: zip::ZipWriter<W>,
    /// Frames written so far (the next entry's index).
    frames: usize,
    /// One entry's Feather bytes, reused from frame to frame.
    buf: Vec<u8>,
}

#[cfg(feature = "av2")]
impl<W: Write + Seek> LabelsAv2Writer<W> {
    /// A writer of labels into `w`.
    pub fn new(w: W) -> Self {
        Self { zip: zip::ZipWriter::new(w), frames: 0, buf: Vec::new() }
    }

    /// Writes the next frame's entry (see [`write_flow_feather`] for `valid` and `object_ids`).
    fn entry(&mut self, flow: &[Point], valid: Option<&[bool]>, object_ids: Option<&[i32]>) -> Result<(), WriteError> {
        use zip::write::SimpleFileOptions;

        self.buf.clear();
        write_flow_feather(&mut self.buf, flow, valid, object_ids)?;
        let options = SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
        // zip64 records only when an entry could exceed the classic u32 sizes.
        let large = self.buf.len() as u64 >= u32::MAX as u64 - 4096;
        self.zip.start_file(format!("{:06}.feather", self.frames), options.large_file(large))?;
        self.zip.write_all(&self.buf)?;
        self.frames += 1;
        Ok(())
    }

    /// Closes the archive.
    pub fn finish(self) -> Result<W, WriteError> {
        Ok(self.zip.finish()?)
    }
}

#[cfg(feature = "av2")]
impl<W: Write + Seek> LabelsWriter for LabelsAv2Writer<W> {
    fn frame(&mut self, flow: Option<&[Point]>, object_ids: &[i32]) -> Result<(), WriteError> {
        match flow {
            Some(flow) => self.entry(flow, None, Some(object_ids)).map_err(|e| match e {
                WriteError::Inconsistent(what) => WriteError::Inconsistent(format!("frame {}: {what}", self.frames)),
                e => e,
            }),
            None => Ok(()),
        }
    }
}

/// Writes one Feather v2 (uncompressed Arrow IPC file) per frame into a zip: `000000.feather`,
/// `000001.feather`, ..., each with columns `flow_tx_m`, `flow_ty_m`, `flow_tz_m` (float32,
/// metres), `is_valid` (bool; all true when `valid` is `None`) and `object_id` (int32: the
/// moving body the point lies on, -1 for none; all -1 when `object_ids` is `None`), one row per
/// point of frame k in its point order. This is the per-frame flow layout ZeroFlow /
/// SceneFlowZoo read for Argoverse 2, plus the object column.
///
/// Errors: `valid` or `object_ids` with fewer frames, or other numbers of points in a frame,
/// than `flows`.
#[cfg(feature = "av2")]
pub fn write_labels_av2_zip<W: Write + Seek>(
    w: W,
    flows: &[Vec<Point>],
    valid: Option<&[Vec<bool>]>,
    object_ids: Option<&[Vec<i32>]>,
) -> Result<W, WriteError> {
    if let Some(ids) = object_ids {
        // One id array per frame: the last frame (no flow) may have one too.
        if ids.len() < flows.len() {
            return Err(WriteError::Inconsistent(format!(
                "{} object id arrays for {} flow frames",
                ids.len(),
                flows.len()
            )));
        }
        if let Some(k) = (0..flows.len()).find(|&k| ids[k].len() != flows[k].len()) {
            return Err(WriteError::Inconsistent(format!(
                "frame {k}: {} object ids for {} points",
                ids[k].len(),
                flows[k].len()
            )));
        }
    }
    if let Some(v) = valid {
        if v.len() != flows.len() {
            return Err(WriteError::Inconsistent(format!(
                "{} validity masks for {} flow frames",
                v.len(),
                flows.len()
            )));
        }
        if let Some(k) = (0..flows.len()).find(|&k| v[k].len() != flows[k].len()) {
            return Err(WriteError::Inconsistent(format!(
                "frame {k}: validity mask has {} entries for {} points",
                v[k].len(),
                flows[k].len()
            )));
        }
    }
    let mut labels = LabelsAv2Writer::new(w);
    for (k, flow) in flows.iter().enumerate() {
        labels.entry(flow, valid.map(|v| v[k].as_slice()), object_ids.map(|ids| ids[k].as_slice()))?;
    }
    labels.finish()
}

/// Writes the labels of one frame as a Feather v2 file (uncompressed Arrow IPC): the columns of
/// [`write_labels_av2_zip`], one row per point of `flow`. `valid` (all true when `None`) and
/// `object_ids` (all -1 when `None`) must have one entry per point.
#[cfg(feature = "av2")]
pub fn write_flow_feather<W: Write>(
    w: W,
    flow: &[Point],
    valid: Option<&[bool]>,
    object_ids: Option<&[i32]>,
) -> Result<W, WriteError> {
    use std::sync::Arc;

    use arrow_array::{ArrayRef, BooleanArray, Float32Array, Int32Array, RecordBatch};
    use arrow_schema::{DataType, Field, Schema};

    let (valid, ids) = filled_masks(flow.len(), valid, object_ids)?;
    let schema = Arc::new(Schema::new(vec![
        Field::new("flow_tx_m", DataType::Float32, false),
        Field::new("flow_ty_m", DataType::Float32, false),
        Field::new("flow_tz_m", DataType::Float32, false),
        Field::new("is_valid", DataType::Boolean, false),
        Field::new("object_id", DataType::Int32, false),
    ]));
    let column = |axis: usize| -> ArrayRef { Arc::new(Float32Array::from_iter_values(flow.iter().map(|f| f[axis]))) };
    let columns: Vec<ArrayRef> =
        vec![column(0), column(1), column(2), Arc::new(BooleanArray::from(valid)), Arc::new(Int32Array::from(ids))];
    super::feather::write_batch(w, &RecordBatch::try_new(schema, columns)?, false)
}

/// Writes the labels of one frame as an `.npz`: `flow` (float32, (N, 3), metres, the layout of
/// [`write_labels_npz`]'s `flow_KKK`), `is_valid` (bool, (N,)) and `object_id` (int32, (N,), -1
/// for none), with the defaults and checks of [`write_flow_feather`].
pub fn write_flow_npz<W: Write + Seek>(
    w: W,
    flow: &[Point],
    valid: Option<&[bool]>,
    object_ids: Option<&[i32]>,
) -> Result<W, WriteError> {
    let n = flow.len();
    let (valid, ids) = filled_masks(n, valid, object_ids)?;
    let mut npz = NpzWriter::new(w);
    npz.add_f32("flow", &[n, 3], flow.as_flattened())?;
    npz.add_bool("is_valid", &[n], &valid)?;
    npz.add_i32("object_id", &[n], &ids)?;
    npz.finish()
}

/// A frame's validity mask and object ids, with their defaults (all valid, no object) for
/// `None`. Errors: a given array whose length is not the frame's `n` points.
fn filled_masks(
    n: usize,
    valid: Option<&[bool]>,
    object_ids: Option<&[i32]>,
) -> Result<(Vec<bool>, Vec<i32>), WriteError> {
    for (what, len) in
        [("validity mask entries", valid.map(<[bool]>::len)), ("object ids", object_ids.map(<[i32]>::len))]
    {
        if let Some(len) = len.filter(|&len| len != n) {
            return Err(WriteError::Inconsistent(format!("{len} {what} for {n} points")));
        }
    }
    Ok((valid.map_or_else(|| vec![true; n], <[bool]>::to_vec), object_ids.map_or_else(|| vec![-1; n], <[i32]>::to_vec)))
}
