//! Label export: per-point flows of a sequence as `.npz` (NumPy) or, with the `av2` feature, as
//! a zip of Feather v2 files in the ZeroFlow / SceneFlowZoo Argoverse 2 layout.

use std::io::{Seek, Write};

use super::WriteError;
use super::npz::NpzWriter;
use crate::geometry::Point;

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

    /// Writes the next frame's labels: its flow to the next frame (`None` for the last frame,
    /// which has none) and the moving body of each of its points.
    pub fn frame(&mut self, flow: Option<&[Point]>, object_ids: &[i32]) -> Result<(), WriteError> {
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

    /// Writes the timestamps (s, one per frame) and closes the archive.
    pub fn finish(mut self, timestamps_s: &[f64]) -> Result<W, WriteError> {
        self.npz.add_f64("timestamps", &[timestamps_s.len()], timestamps_s)?;
        self.npz.finish()
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
    use std::sync::Arc;

    use arrow_array::{ArrayRef, BooleanArray, Float32Array, Int32Array, RecordBatch};
    use arrow_schema::{DataType, Field, Schema};
    use zip::write::SimpleFileOptions;

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
    let schema = Arc::new(Schema::new(vec![
        Field::new("flow_tx_m", DataType::Float32, false),
        Field::new("flow_ty_m", DataType::Float32, false),
        Field::new("flow_tz_m", DataType::Float32, false),
        Field::new("is_valid", DataType::Boolean, false),
        Field::new("object_id", DataType::Int32, false),
    ]));
    let mut zip = zip::ZipWriter::new(w);
    let options = SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    let mut buf = Vec::new();
    for (k, flow) in flows.iter().enumerate() {
        let column =
            |axis: usize| -> ArrayRef { Arc::new(Float32Array::from_iter_values(flow.iter().map(|f| f[axis]))) };
        let is_valid: BooleanArray = match valid {
            Some(v) => v[k].iter().map(|&b| Some(b)).collect(),
            None => std::iter::repeat_n(Some(true), flow.len()).collect(),
        };
        let object_id: Int32Array = match object_ids {
            Some(ids) => Int32Array::from(ids[k].clone()),
            None => Int32Array::from(vec![-1; flow.len()]),
        };
        let batch = RecordBatch::try_new(
            schema.clone(),
            vec![column(0), column(1), column(2), Arc::new(is_valid) as ArrayRef, Arc::new(object_id) as ArrayRef],
        )?;
        buf.clear();
        let mut writer = arrow_ipc::writer::FileWriter::try_new(&mut buf, &schema)?;
        writer.write(&batch)?;
        writer.finish()?;
        drop(writer);
        // zip64 records only when an entry could exceed the classic u32 sizes.
        zip.start_file(format!("{k:06}.feather"), options.large_file(buf.len() as u64 >= u32::MAX as u64 - 4096))?;
        zip.write_all(&buf)?;
    }
    Ok(zip.finish()?)
}
