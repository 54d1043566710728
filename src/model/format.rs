//! The model file: magic and version, a JSON header, then each network's own versioned binary
//! encoding behind a length prefix.
//!
//! Version 1 (`MBNTMDL1`) holds one fit; version 2 (`MBNTMDL2`) a log stitched from windows: its
//! header names each window's first frame and object ids, and each window's own model file
//! (version 1) follows behind a length prefix in place of a network. A model of one fit is
//! still written as version 1, so that a server of before the windows reads it; both versions
//! load. A version 2 file's windows are decoded when a query first needs them (`windows`); its
//! header also names each window's frames, so that loading reads no window (files written
//! before that are read by each window's own header).

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::networks::Motion;
use super::params::Method;
use super::windows::{Window, WindowBytes, WindowHeader, check_windows};
use super::{FitReport, FittedModel, MovingBody, NonFiniteModel, RigidTrack, TimeAxis};
use crate::geometry::Point;
use crate::geometry::rigid::Rigid;
use crate::nn::Mlp;

impl FittedModel {
    /// Serialises the model: magic and version, a JSON header, then each network's own
    /// versioned binary encoding behind a length prefix. A model holding a non-finite number
    /// is refused ([`FittedModel::check_finite`]): JSON would write it as `null`, and the file
    /// would not load back.
    pub fn to_bytes(&self) -> Result<Vec<u8>, NonFiniteModel> {
        self.check_finite()?;
        Ok(self.encode())
    }

    /// [`FittedModel::to_bytes`] without the check.
    pub(super) fn encode(&self) -> Vec<u8> {
        let (kind, parts, windows): (&str, Vec<Vec<u8>>, Vec<WindowHeader>) = match &self.motion {
            Motion::Trajectory(mlp) => ("trajectory", vec![mlp.to_bytes()], Vec::new()),
            Motion::PairFlows { forward, backward } => {
                ("pair_flows", forward.iter().chain(backward).map(Mlp::to_bytes).collect(), Vec::new())
            }
            Motion::Windows(windows) => (
                WINDOWS_KIND,
                windows.iter().map(Window::encode).collect(),
                windows.iter().map(Window::header).collect(),
            ),
        };
        let header = Header {
            method: self.method,
            time_axis: self.time_axis.clone(),
            report: self.report.clone(),
            kind: kind.to_string(),
            networks: parts.len(),
            frame_poses: self.frame_poses.clone(),
            tracks: self.tracks.clone(),
            bodies: self.bodies.clone(),
            still_world: self.still_world,
            free_points: self.free_points.clone(),
            windows,
        };
        let header = serde_json::to_vec(&header).expect("a header always serialises");
        let mut out = if kind == WINDOWS_KIND { WINDOWS_MAGIC.to_vec() } else { MODEL_MAGIC.to_vec() };
        out.extend((header.len() as u64).to_le_bytes());
        out.extend(header);
        for bytes in parts {
            out.extend((bytes.len() as u64).to_le_bytes());
            out.extend(bytes);
        }
        out
    }

    /// Reads a model written by [`FittedModel::to_bytes`]; a model holding a non-finite
    /// number (possible in the networks' binary weights) is refused as corrupt.
    ///
    /// A stitched model (version 2) keeps a copy of the file and decodes each window when a
    /// query first needs it ([`FittedModel::from_vec`] keeps the file without copying it).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        if bytes.starts_with(WINDOWS_MAGIC) {
            return Self::from_vec(bytes.to_vec());
        }
        Self::read(bytes, None)
    }

    /// [`FittedModel::from_bytes`] of a file read into `bytes`, which a stitched model keeps
    /// for its windows.
    ///
    /// Loading a stitched model reads its header and checks the file's structure (each
    /// window's length prefix and version, the windows' frames covering the log in order)
    /// without decoding a window: a window whose model is damaged is refused when a query first
    /// needs it, with [`crate::model::QueryError::CorruptWindow`].
    pub fn from_vec(bytes: Vec<u8>) -> Result<Self, String> {
        if bytes.starts_with(WINDOWS_MAGIC) {
            let file = Arc::new(bytes);
            return Self::read(&file, Some(&file));
        }
        Self::read(&bytes, None)
    }

    /// [`FittedModel::from_bytes`] of `bytes`; `shared` is the same bytes, kept by the windows of
    /// a stitched model (required for version 2).
    fn read(bytes: &[u8], shared: Option<&Arc<Vec<u8>>>) -> Result<Self, String> {
        let (mut rest, stitched) = match (bytes.strip_prefix(MODEL_MAGIC), bytes.strip_prefix(WINDOWS_MAGIC)) {
            (Some(rest), _) => (rest, false),
            (_, Some(rest)) => (rest, true),
            _ => return Err("not an mbnt model file (bad magic or version)".into()),
        };
        let mut take = |what: &str| -> Result<&[u8], String> {
            if rest.len() < 8 {
                return Err(format!("model file truncated before {what}"));
            }
            let len = u64::from_le_bytes(rest[..8].try_into().expect("8 bytes")) as usize;
            if rest.len() - 8 < len {
                return Err(format!("model file truncated inside {what}"));
            }
            let (body, tail) = rest[8..].split_at(len);
            rest = tail;
            Ok(body)
        };
        let mut header: Header =
            serde_json::from_slice(take("the header")?).map_err(|e| format!("corrupt model header: {e}"))?;
        if stitched != (header.kind == WINDOWS_KIND) {
            return Err(format!("model kind {:?} in a file of the other version", header.kind));
        }
        if stitched {
            let mut windows = Vec::with_capacity(header.windows.len().min(1024));
            if header.windows.len() != header.networks {
                return Err("model header: one entry per window expected".into());
            }
            let file = shared.expect("a stitched model is read from a shared file");
            for (w, entry) in std::mem::take(&mut header.windows).into_iter().enumerate() {
                let window = take("a window")?;
                // A window is one fit (version 1): refused here, so that a crafted file cannot
                // nest windows until the stack overflows when the window is decoded.
                if !window.starts_with(MODEL_MAGIC) {
                    return Err(format!("window {w} is not the model of one fit"));
                }
                let frames = match entry.frames {
                    Some(frames) => frames,
                    // A file written before the header said each window's frames: the window's
                    // own header says it (parsed, not kept).
                    None => window_frames(window).map_err(|e| format!("window {w}: {e}"))?,
                };
                let start = window.as_ptr() as usize - bytes.as_ptr() as usize;
                let source = WindowBytes { file: file.clone(), range: start..start + window.len() };
                windows.push(Window::lazy(entry, frames, source));
            }
            return Self::from_windows(header, windows);
        }
        let mut networks = Vec::with_capacity(header.networks.min(1024));
        for i in 0..header.networks {
            let body = take("a network")?;
            networks.push(Mlp::<f32>::from_bytes(body).map_err(|e| format!("corrupt network {i}: {e}"))?);
        }
        let frames = header.time_axis.frames();
        if frames < 2 {
            return Err(format!("model header: a sequence of {frames} frames (at least 2 expected)"));
        }
        if let Some(ts) = header.time_axis.timestamps_s()
            && (ts.len() != frames || ts.windows(2).any(|w| w[1] <= w[0]))
        {
            return Err("model header: one increasing timestamp per frame expected".into());
        }
        // The networks must take the inputs and give the outputs the queries will use, or a
        // query on a loaded model would panic.
        let (input, output) = match header.kind.as_str() {
            "trajectory" => (super::encoding::input_width(frames), 3 * (frames - 1)),
            _ => (3, 3),
        };
        if let Some(i) = networks.iter().position(|n| n.input_dim() != input || n.output_dim() != output) {
            return Err(format!(
                "network {i} takes {} inputs and gives {} outputs; {input} and {output} expected for {frames} frames",
                networks[i].input_dim(),
                networks[i].output_dim()
            ));
        }
        let motion = match header.kind.as_str() {
            "trajectory" if networks.len() == 1 => Motion::Trajectory(networks.pop().expect("one network")),
            "pair_flows" if networks.len() == 2 * frames.saturating_sub(1) => {
                let backward = networks.split_off(frames - 1);
                Motion::PairFlows { forward: networks, backward }
            }
            kind => {
                return Err(format!(
                    "model kind {kind:?} with {} networks does not fit {frames} frames",
                    header.networks
                ));
            }
        };
        if header.frame_poses.as_ref().is_some_and(|p| p.len() != frames) {
            return Err("model header: one pose per frame expected".into());
        }
        if header.tracks.iter().any(|t| !t.fits(frames)) {
            return Err("model header: a rigid track does not cover the sequence's frames".into());
        }
        if header.bodies.iter().any(|b| !b.fits(frames)) {
            return Err("model header: a moving body does not cover the sequence's frames".into());
        }
        if !header.free_points.is_empty() && header.free_points.len() != frames {
            return Err("model header: free points of every frame expected".into());
        }
        if header.still_world && header.frame_poses.is_none() {
            return Err("model header: a still world needs the frames' poses".into());
        }
        let model = Self {
            method: header.method,
            time_axis: header.time_axis,
            report: header.report,
            motion,
            frame_poses: header.frame_poses,
            tracks: header.tracks,
            bodies: header.bodies,
            still_world: header.still_world,
            free_points: header.free_points,
        };
        model.check_finite().map_err(|e| format!("corrupt model: {e}"))?;
        Ok(model)
    }

    /// A stitched model from its header and its windows (not decoded), checked as
    /// [`FittedModel::stitched`] builds them as far as the header tells.
    fn from_windows(header: Header, windows: Vec<Window>) -> Result<Self, String> {
        let frames = header.time_axis.frames();
        if header.frame_poses.as_ref().is_some_and(|p| p.len() != frames) {
            return Err("model header: one pose per frame expected".into());
        }
        if header.bodies.iter().any(|b| !b.fits(frames)) {
            return Err("model header: a moving body does not cover the sequence's frames".into());
        }
        check_windows(&header.time_axis, &windows)?;
        let known: Vec<u32> = header.bodies.iter().map(|b| b.id).collect();
        if windows.iter().flat_map(|w| &w.object_ids).any(|id| !known.contains(id)) {
            return Err("model header: a window's body is no object of the log".into());
        }
        let model = Self {
            method: header.method,
            time_axis: header.time_axis,
            report: header.report,
            motion: Motion::Windows(windows),
            frame_poses: header.frame_poses,
            tracks: Vec::new(),
            bodies: header.bodies,
            still_world: header.still_world,
            free_points: Vec::new(),
        };
        model.check_finite().map_err(|e| format!("corrupt model: {e}"))?;
        Ok(model)
    }
}

/// The frames of a window's own model file (version 1) `bytes`, from its header alone.
fn window_frames(bytes: &[u8]) -> Result<usize, String> {
    /// The one field of the header read here; serde skips the others.
    #[derive(Deserialize)]
    struct AxisOnly {
        time_axis: TimeAxis,
    }
    let rest = &bytes[MODEL_MAGIC.len()..];
    let len = rest.get(..8).map(|l| u64::from_le_bytes(l.try_into().expect("8 bytes")) as usize);
    let header =
        len.and_then(|len| rest.get(8..8usize.checked_add(len)?)).ok_or("model file truncated in the header")?;
    let axis: AxisOnly = serde_json::from_slice(header).map_err(|e| format!("corrupt model header: {e}"))?;
    Ok(axis.time_axis.frames())
}

/// The serialised description of a model, ahead of its networks.
#[derive(Serialize, Deserialize)]
struct Header {
    method: Method,
    time_axis: TimeAxis,
    report: FitReport,
    kind: String,
    networks: usize,
    /// Absent in models fitted without poses.
    #[serde(default)]
    frame_poses: Option<Vec<Rigid>>,
    /// Absent in models fitted without `rigid_tracks`.
    #[serde(default)]
    tracks: Vec<RigidTrack>,
    /// Absent in models fitted without `moving_bodies` (and in files written before them).
    #[serde(default)]
    bodies: Vec<MovingBody>,
    /// See [`FittedModel::still_world`]; absent (false) in earlier files.
    #[serde(default)]
    still_world: bool,
    /// See [`FittedModel::free_points`]; absent (empty) in earlier files.
    #[serde(default)]
    free_points: Vec<Vec<(Point, bool)>>,
    /// A stitched model's windows (version 2 files only), in order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    windows: Vec<WindowHeader>,
}

/// File magic and format version of serialised models of one fit.
const MODEL_MAGIC: &[u8] = b"MBNTMDL1";

/// File magic and format version of stitched models (a log fitted as windows).
const WINDOWS_MAGIC: &[u8] = b"MBNTMDL2";

/// The header's `kind` of a stitched model.
const WINDOWS_KIND: &str = "windows";

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::tests::scene_model;

    #[test]
    fn a_model_file_from_before_the_scene_model_still_loads() {
        // The previous version's header has no bodies, still world or free points.
        let model = scene_model();
        let bytes = model.to_bytes().unwrap();
        let rest = &bytes[MODEL_MAGIC.len()..];
        let len = u64::from_le_bytes(rest[..8].try_into().unwrap()) as usize;
        let mut header: serde_json::Value = serde_json::from_slice(&rest[8..8 + len]).unwrap();
        for field in ["bodies", "still_world", "free_points"] {
            header.as_object_mut().unwrap().remove(field).expect("the current header has the field");
        }
        header["report"].as_object_mut().unwrap().remove("moving_bodies");
        header["report"].as_object_mut().unwrap().remove("free_points");
        let old_header = serde_json::to_vec(&header).unwrap();
        let mut old = MODEL_MAGIC.to_vec();
        old.extend((old_header.len() as u64).to_le_bytes());
        old.extend(old_header);
        old.extend(&rest[8 + len..]);
        let loaded = FittedModel::from_bytes(&old).unwrap();
        assert!(loaded.bodies().is_empty());
        // Without the scene model the network answers every point, as models of that version did.
        let at = loaded.positions(&[[50.0, 50.0, 0.0]], 1.0, &[3.0]).unwrap();
        assert_eq!(at[0], [50.0, 52.0, 0.0]);
    }
}
