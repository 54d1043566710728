//! A model stitched from overlapping windows: how a log longer than one window answers
//! (`fit::windows` fits the windows; issue 21).
//!
//! # Design
//! Each window is an ordinary model of its frames ([`FittedModel`], its own time axis, poses,
//! network, bodies and free points), so a window answers exactly as a fit of those frames
//! alone would. The stitched model owns its windows and adds only:
//! - **ownership of time**: neighbouring windows `w` and `w + 1` hand over at the middle frame
//!   of their overlap (`handoff`), away from both windows' least constrained end frames;
//!   window `w` answers the times in `[handoff(w - 1), handoff(w))`;
//! - **chaining**: a point observed at `t_obs` is moved by the window owning `t_obs` to the
//!   hand-over frame towards the queried time, continues from there in the next window, and so
//!   on until the window owning the queried time answers. Queries stay in sensor coordinates
//!   between windows (each window's `positions` takes and gives them), so the chaining needs no
//!   knowledge of a window's fit coordinates, with or without poses. A trajectory is continuous
//!   at a hand-over: at the hand-over time the next window is asked for its own time, the
//!   identity. A point that followed a moving body carries the body's object into the next
//!   window and follows that window's part of the object: whether a point lies on a body is
//!   decided once, at the time it was observed, as in a model of one fit, and not again at each
//!   hand-over (the sweep there may show the body from another side, away from the point);
//! - **object identity**: a moving body of one window and one of the next are one object when
//!   their member points lie on each other in the overlap's frames ([`link_bodies`]); the
//!   stitched model lists each object once over the whole log with the labels' ids.
//!
//! Memory: a window model holds what its queries need (network, body members, free points);
//! the frames a window was fitted on are not kept. A stitched model read from a file keeps the
//! file's bytes and decodes a window the first time a query needs it ([`Window`]), so that
//! loading a long log's model reads its header only and a query decodes the windows its chain
//! touches. A window lets go of the file once decoded: when every window is, the file's bytes
//! are freed and the model holds its decoded windows only.

use std::ops::Range;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

use serde::{Deserialize, Serialize};

use super::networks::Motion;
use super::poses::pose_at;
use super::{Carry, FitReport, FittedModel, LossRecord, MovingBody, QueryError, TRACK_MEMBER_RADIUS_M, TimeAxis};
use crate::geometry::Point;
use crate::geometry::knn::KdTree;
use crate::geometry::rigid::Rigid;
use crate::model::params::Method;

/// One window of a stitched model.
///
/// A window read from a model file is decoded the first time a query needs it: loading a long
/// log's model reads only the file's header, and a query decodes only the windows its chain
/// touches (issue 21). A window that cannot be read is refused at that first use
/// ([`QueryError::CorruptWindow`]); loading checks only the file's structure (each window's
/// length and version). A built window ([`Window::decoded`]) is decoded from the start.
#[derive(Debug)]
pub(super) struct Window {
    /// The window's first frame in the log.
    pub(super) start: usize,
    /// The window's frames (its model's time axis: its slice of the log's timestamps, or frame
    /// indices 0..frames-1 without timestamps).
    pub(super) frames: usize,
    /// The log-wide object id of each of the model's bodies, in their order.
    pub(super) object_ids: Vec<u32>,
    /// The model of the window's frames alone, once decoded (or its decoding error).
    model: OnceLock<Result<FittedModel, QueryError>>,
    /// Where the window's own model file (version 1) lies in the stitched model's file, for a
    /// window read from one and not yet decoded (or whose decoding failed): decoded from there on
    /// first use, and written back unchanged. Taken once the window is decoded, so that the
    /// file's bytes are freed when no window needs them (its decoded model encodes to the same
    /// bytes).
    source: Mutex<Option<WindowBytes>>,
}

impl Clone for Window {
    fn clone(&self) -> Self {
        Self {
            start: self.start,
            frames: self.frames,
            object_ids: self.object_ids.clone(),
            model: self.model.clone(),
            source: Mutex::new(self.source_bytes()),
        }
    }
}

/// A window's bytes in the stitched model's file.
#[derive(Debug, Clone)]
pub(super) struct WindowBytes {
    /// The whole file, shared by its windows.
    pub(super) file: Arc<Vec<u8>>,
    /// The window's own model file within it.
    pub(super) range: Range<usize>,
}

/// A pair of bodies of neighbouring windows `(w - 1, w)` and how much they overlap: (index in
/// window `w - 1`, index in window `w`, share of their members lying on the other's).
pub type LinkShare = (usize, usize, f64);

/// What the model file keeps of a window besides its model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct WindowHeader {
    /// See [`Window::start`].
    pub(super) start: usize,
    /// See [`Window::frames`]; absent in files written before windows loaded lazily (the
    /// window's own header says it then).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) frames: Option<usize>,
    /// See [`Window::object_ids`].
    pub(super) object_ids: Vec<u32>,
}

/// Two bodies of neighbouring windows are one object when at least this share of their member
/// points in the overlap's frames (both bodies' together) lie within [`TRACK_MEMBER_RADIUS_M`]
/// of the other's members of the same frame. Both windows see the same sweeps there, so one
/// object's members are mostly the same points; a neighbouring car's are metres away.
const LINK_MIN_SHARE: f64 = 0.5;

impl Window {
    /// A window built from its model (a fit's, or a test's): decoded from the start.
    pub(super) fn decoded(start: usize, model: FittedModel, object_ids: Vec<u32>) -> Self {
        Self {
            start,
            frames: model.time_axis.frames(),
            object_ids,
            model: OnceLock::from(Ok(model)),
            source: Mutex::new(None),
        }
    }

    /// A window of a model file, decoded on first use ([`Window::model`]).
    pub(super) fn lazy(header: WindowHeader, frames: usize, source: WindowBytes) -> Self {
        Self {
            start: header.start,
            frames,
            object_ids: header.object_ids,
            model: OnceLock::new(),
            source: Mutex::new(Some(source)),
        }
    }

    /// The window's bytes in its file, while it holds them. A poisoned lock is only a panic
    /// elsewhere while it was held; the `Option` inside is whole either way.
    fn source_bytes(&self) -> Option<WindowBytes> {
        self.source.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }

    /// The window's entry in the file's header.
    pub(super) fn header(&self) -> WindowHeader {
        WindowHeader { start: self.start, frames: Some(self.frames), object_ids: self.object_ids.clone() }
    }

    /// The window's own model file (version 1): the bytes it was read from, unchanged, while it
    /// holds them, or its model encoded (a built window, or a read one once decoded: the same
    /// bytes, since decoding keeps every field and number). A window read from a file is thus
    /// written back as read, decoded or not (a corrupt one keeps its bytes and stays refused at
    /// first use when that file is loaded again).
    pub(super) fn encode(&self) -> Vec<u8> {
        match (self.source_bytes(), self.model.get()) {
            (Some(source), _) => source.file[source.range].to_vec(),
            (None, Some(Ok(model))) => model.encode(),
            (None, _) => unreachable!("a window without bytes is decoded"),
        }
    }

    /// The model a window is written from (one built by a fit, or read and decoded), when it
    /// holds no file bytes.
    pub(super) fn written_from_model(&self) -> Option<&FittedModel> {
        match self.model.get() {
            Some(Ok(model)) if self.source_bytes().is_none() => Some(model),
            _ => None,
        }
    }

    /// Whether the window's model has been decoded (successfully or not).
    pub(super) fn is_decoded(&self) -> bool {
        self.model.get().is_some()
    }

    /// The window's model, decoded from the file on first use and checked against the log's
    /// time axis (`log_axis`) and whether the log was fitted with poses; `w` is the window's
    /// index, for the error.
    pub(super) fn model(&self, w: usize, log_axis: &TimeAxis, with_poses: bool) -> Result<&FittedModel, QueryError> {
        let decoded = self.model.get_or_init(|| {
            let mut source = self.source.lock().unwrap_or_else(PoisonError::into_inner);
            let bytes = source.as_ref().expect("a window without bytes is decoded");
            let decoded = FittedModel::from_bytes(&bytes.file[bytes.range.clone()])
                .and_then(|model| check_window(self, &model, log_axis, with_poses).map(|()| model))
                .map_err(|detail| QueryError::CorruptWindow { window: w, detail });
            // Decoded, the window needs the file no more: the last window to let go frees it.
            if decoded.is_ok() {
                *source = None;
            }
            decoded
        });
        decoded.as_ref().map_err(Clone::clone)
    }

    /// The decoded model, for changing it (tests); the window is then written from the model.
    #[cfg(test)]
    pub(super) fn model_mut(&mut self) -> &mut FittedModel {
        *self.source.get_mut().unwrap_or_else(PoisonError::into_inner) = None;
        self.model.get_mut().expect("a decoded window").as_mut().expect("a readable window")
    }

    /// One past the window's last frame in the log.
    fn end(&self) -> usize {
        self.start + self.frames
    }

    /// `t` (the log's axis) on the window's own axis: the same seconds with timestamps, the
    /// frame index less the window's start without.
    fn local_time(&self, log_axis: &TimeAxis, t: f64) -> f64 {
        if log_axis.timestamps_s().is_some() { t } else { t - self.start as f64 }
    }
}

/// Every window's model, in order (decoding those not decoded yet).
fn models<'a>(model: &FittedModel, windows: &'a [Window]) -> Result<Vec<&'a FittedModel>, QueryError> {
    let with_poses = model.frame_poses.is_some();
    windows.iter().enumerate().map(|(w, window)| window.model(w, &model.time_axis, with_poses)).collect()
}

/// The hand-over frame (in the log) between each window and the next: the middle of their
/// overlap.
fn handoffs(windows: &[Window]) -> Vec<usize> {
    windows.windows(2).map(|pair| pair[1].start + (pair[0].end() - pair[1].start) / 2).collect()
}

/// The window answering fractional frame `u` of the log: the number of hand-overs at or before it.
fn owner(handoffs: &[usize], u: f64) -> usize {
    handoffs.partition_point(|&h| h as f64 <= u)
}

/// The checks a stitched model's windows pass (when built and when read from a file, before
/// any window is decoded): they cover the log's frames in order, each overlapping the next by
/// at least one frame and of at least 2 frames. Each window's model is checked against the log
/// by [`check_window`] when it is decoded.
pub(super) fn check_windows(axis: &TimeAxis, windows: &[Window]) -> Result<(), String> {
    let Some(first) = windows.first() else { return Err("a stitched model without windows".into()) };
    if first.start != 0 {
        return Err("the first window does not start at frame 0".into());
    }
    let last = windows.last().expect("not empty");
    if last.end() != axis.frames() {
        return Err(format!("the windows end at frame {}, the log has {} frames", last.end(), axis.frames()));
    }
    for (w, window) in windows.iter().enumerate() {
        if window.frames < 2 {
            return Err(format!("window {w} has fewer than 2 frames"));
        }
        if let Some(next) = windows.get(w + 1)
            && (next.start <= window.start || next.start >= window.end())
        {
            return Err(format!("windows {w} and {} do not overlap in order", w + 1));
        }
    }
    Ok(())
}

/// The checks a window's model passes against its place in the log: a single model on its
/// slice of the log's time axis, fitted with poses as the log was, with one object id per
/// moving body.
fn check_window(window: &Window, model: &FittedModel, axis: &TimeAxis, with_poses: bool) -> Result<(), String> {
    if matches!(model.motion, Motion::Windows(_)) {
        return Err("the window is itself stitched".into());
    }
    if model.time_axis.frames() != window.frames {
        return Err(format!("{} frames, the file's header says {}", model.time_axis.frames(), window.frames));
    }
    let expected = axis.timestamps_s().map(|ts| ts[window.start..window.end()].to_vec());
    if model.time_axis.timestamps_s().map(<[f64]>::to_vec) != expected {
        return Err("the window's times are not its frames' times in the log".into());
    }
    if model.frame_poses.is_some() != with_poses {
        return Err("the window and the log disagree on whether the fit used poses".into());
    }
    if window.object_ids.len() != model.bodies.len() {
        return Err("one object id per moving body expected".into());
    }
    Ok(())
}

impl FittedModel {
    /// The model of a log fitted as `windows` (each `(first frame, model of its frames)`, in
    /// order, covering the log's frames with overlaps): moving bodies linked across the
    /// overlaps into one object each, and a report for the whole log.
    ///
    /// `frame_poses` are the log's (sensor coordinates -> frame 0's), when the windows were
    /// fitted with poses; `report` carries what the windows do not know (the parameters, the
    /// log's estimated poses, the total wall time); the rest is summed over the windows.
    pub(crate) fn stitched(
        method: Method,
        time_axis: TimeAxis,
        frame_poses: Option<Vec<Rigid>>,
        mut report: FitReport,
        windows: Vec<(usize, FittedModel)>,
    ) -> Result<Self, String> {
        let mut windows: Vec<Window> = windows
            .into_iter()
            .map(|(start, model)| {
                let ids = vec![0; model.bodies.len()];
                Window::decoded(start, model, ids)
            })
            .collect();
        check_windows(&time_axis, &windows)?;
        // The models are held apart while the windows' object ids are set, and put back at the end.
        let models: Vec<FittedModel> =
            windows.iter_mut().map(|w| w.model.take().expect("built decoded").expect("built from a model")).collect();
        for (w, (window, model)) in windows.iter().zip(&models).enumerate() {
            check_window(window, model, &time_axis, frame_poses.is_some()).map_err(|e| format!("window {w}: {e}"))?;
        }
        let parts: Vec<&FittedModel> = models.iter().collect();
        // Window-to-log transforms of fit coordinates: a window's fit coordinates are its first
        // frame's sensor coordinates (with poses), the log's are frame 0's.
        let to_log = window_to_log(frame_poses.as_deref(), &windows);
        let objects = link_bodies(&windows, &parts, &to_log);
        for (window, ids) in windows.iter_mut().zip(&objects.ids) {
            window.object_ids.clone_from(ids);
        }
        let handoffs = handoffs(&windows);
        let bodies = log_bodies(&windows, &parts, &to_log, &handoffs, objects.count, time_axis.frames());
        report.frames = (0..time_axis.frames())
            .map(|k| {
                let w = owner(&handoffs, k as f64);
                parts[w].report.frames.get(k - windows[w].start).copied().unwrap_or_default()
            })
            .collect();
        for (k, part) in parts.iter().enumerate() {
            let r = &part.report;
            report.losses.extend(r.losses.iter().map(|l| LossRecord { window: Some(k), ..*l }));
            report.iterations += r.iterations;
            report.rigid_tracks += r.rigid_tracks;
            report.rigid_tracks_seconds += r.rigid_tracks_seconds;
            report.free_points += r.free_points;
            report.phase_times += r.phase_times;
        }
        report.moving_bodies = bodies.len();
        let still_world = parts.iter().any(|m| m.still_world);
        for (window, model) in windows.iter_mut().zip(models) {
            window.model = OnceLock::from(Ok(model));
        }
        Ok(Self {
            method,
            time_axis,
            report,
            motion: Motion::Windows(windows),
            frame_poses,
            tracks: Vec::new(),
            bodies,
            still_world,
            free_points: Vec::new(),
        })
    }

    /// The log-wide object id of each window's moving bodies (per window, in the order of its
    /// model's bodies); empty for a model of one fit.
    pub fn window_object_ids(&self) -> Vec<Vec<u32>> {
        match &self.motion {
            Motion::Windows(windows) => windows.iter().map(|w| w.object_ids.clone()).collect(),
            _ => Vec::new(),
        }
    }

    /// How the bodies of neighbouring windows overlap, as the linking into objects sees it: per
    /// pair of windows `(w - 1, w)`, each pair of bodies (index in window `w - 1`, index in
    /// window `w`) with members in the overlap and the share of those members lying on the
    /// other body's (pairs at 0.5 or more are linked, the highest first). Empty for a model of
    /// one fit. Decodes every window of a model read from a file; fails if one cannot be read.
    pub fn window_link_shares(&self) -> Result<Vec<Vec<LinkShare>>, QueryError> {
        let Motion::Windows(windows) = &self.motion else { return Ok(Vec::new()) };
        let parts = models(self, windows)?;
        let to_log = window_to_log(self.frame_poses.as_deref(), windows);
        Ok((1..windows.len())
            .map(|w| link_shares(windows, &parts, &to_log, w).into_iter().map(|(share, a, b)| (a, b, share)).collect())
            .collect())
    }

    /// The windows of a stitched model (first frame in the log, and the window's own model);
    /// empty for a model of one fit. Decodes every window of a model read from a file; fails if
    /// one cannot be read.
    pub fn windows(&self) -> Result<Vec<(usize, &FittedModel)>, QueryError> {
        match &self.motion {
            Motion::Windows(windows) => {
                Ok(windows.iter().zip(models(self, windows)?).map(|(w, model)| (w.start, model)).collect())
            }
            _ => Ok(Vec::new()),
        }
    }

    /// The first frame in the log of each window of a stitched model, without decoding any;
    /// empty for a model of one fit.
    pub fn window_starts(&self) -> Vec<usize> {
        match &self.motion {
            Motion::Windows(windows) => windows.iter().map(|w| w.start).collect(),
            _ => Vec::new(),
        }
    }

    /// How many of a stitched model's windows have been decoded (all of a model built by a fit;
    /// those queries have needed of a model read from a file); 0 for a model of one fit.
    pub fn decoded_windows(&self) -> usize {
        match &self.motion {
            Motion::Windows(windows) => windows.iter().filter(|w| w.is_decoded()).count(),
            _ => 0,
        }
    }
}

/// [`FittedModel::positions`] of a stitched model (the caller has checked the points finite).
pub(super) fn positions(
    model: &FittedModel,
    windows: &[Window],
    points: &[Point],
    t_obs: f64,
    times: &[f64],
) -> Result<Vec<Point>, QueryError> {
    let axis = &model.time_axis;
    let u_obs = axis.to_frame_index(t_obs)?;
    let u_times = times.iter().map(|&t| axis.to_frame_index(t)).collect::<Result<Vec<_>, _>>()?;
    let mut out = vec![[0f32; 3]; points.len() * times.len()];
    if times.is_empty() {
        return Ok(out);
    }
    let handoffs = handoffs(windows);
    let home = owner(&handoffs, u_obs);
    let owners: Vec<usize> = u_times.iter().map(|&u| owner(&handoffs, u)).collect();
    let lo = owners.iter().copied().min().expect("times not empty").min(home);
    let hi = owners.iter().copied().max().expect("times not empty").max(home);
    // Per window from lo to hi: the points (sensor coordinates), the log time at which that
    // window takes them over, and the body of that window each one arrives on.
    let mut entry: Vec<Option<Entry>> = vec![None; hi - lo + 1];
    entry[home - lo] = Some(Entry { points: points.to_vec(), t: t_obs, carried: None });
    let to_log = window_to_log(model.frame_poses.as_deref(), windows);
    // Only the windows from lo to hi are decoded (a window read from a file, on first use).
    let with_poses = model.frame_poses.is_some();
    let part = |w: usize| windows[w].model(w, axis, with_poses);
    // Points that leave a window on a body whose object the next window does not hold (a car
    // that window saw too sparsely to find again): they stay on that body, carried on past its
    // window (`body_pose_beyond`), for every time past the hand-over.
    let hand_over = |from: usize,
                     to: usize,
                     current: &Entry,
                     handoff: usize,
                     orphans: &mut [Option<Orphan>]|
     -> Result<Entry, QueryError> {
        let window = &windows[from];
        let t_handoff = axis.frame_time(handoff);
        let (moved, owners) = part(from)?.positions_carried(
            &current.points,
            window.local_time(axis, current.t),
            &[window.local_time(axis, t_handoff)],
            current.carried.as_deref(),
        )?;
        // The next window's part of each point's object, if it has one; still points stay still.
        let next = &windows[to];
        let carried: Vec<Carry> = owners
            .iter()
            .map(|decided| match *decided {
                Carry::Body(body) => {
                    let object = window.object_ids[body];
                    next.object_ids.iter().position(|&o| o == object).map_or(Carry::Open, Carry::Body)
                }
                other => other,
            })
            .collect();
        let sensor_to_log = model.frame_poses.as_ref().map(|poses| pose_at(poses, handoff as f64));
        for (i, (decided, next_part)) in owners.iter().zip(&carried).enumerate() {
            if let (Carry::Body(body), Carry::Open, None) = (*decided, next_part, &orphans[i]) {
                let in_log = sensor_to_log.map_or(moved[i], |pose| pose.apply(&moved[i]));
                let on_body = body_pose_beyond(part(from)?, body, window.local_time(axis, t_handoff)).inverse();
                let at = on_body.apply(&to_log[from].inverse().apply(&in_log));
                orphans[i] = Some(Orphan { window: from, body, at, first_owner: to });
            }
        }
        Ok(Entry { points: moved, t: t_handoff, carried: Some(carried) })
    };
    // Orphans forward and backward from the home window are kept apart: a time is answered
    // from one side of home only.
    let mut forward_orphans: Vec<Option<Orphan>> = vec![None; points.len()];
    for w in home + 1..=hi {
        let from = entry[w - 1 - lo].as_ref().expect("filled in order");
        let next = hand_over(w - 1, w, from, handoffs[w - 1], &mut forward_orphans)?;
        entry[w - lo] = Some(next);
    }
    let mut backward_orphans: Vec<Option<Orphan>> = vec![None; points.len()];
    for w in (lo..home).rev() {
        let from = entry[w + 1 - lo].as_ref().expect("filled in order");
        let next = hand_over(w + 1, w, from, handoffs[w], &mut backward_orphans)?;
        entry[w - lo] = Some(next);
    }
    let n_times = times.len();
    for w in lo..=hi {
        let asked: Vec<usize> = (0..n_times).filter(|&j| owners[j] == w).collect();
        if asked.is_empty() {
            continue;
        }
        let window = &windows[w];
        let at = entry[w - lo].as_ref().expect("every window from lo to hi is entered");
        let local: Vec<f64> = asked.iter().map(|&j| window.local_time(axis, times[j])).collect();
        let (answers, _) =
            part(w)?.positions_carried(&at.points, window.local_time(axis, at.t), &local, at.carried.as_deref())?;
        let orphans = if w > home { &forward_orphans } else { &backward_orphans };
        for i in 0..points.len() {
            let orphan = orphans[i].as_ref().filter(|o| if w > home { w >= o.first_owner } else { w <= o.first_owner });
            for (n, &j) in asked.iter().enumerate() {
                out[i * n_times + j] = match orphan {
                    Some(o) => o.position(model, windows, part(o.window)?, &to_log, times[j], u_times[j]),
                    None => answers[i * asked.len() + n],
                };
            }
        }
    }
    Ok(out)
}

/// Each window's fit coordinates -> the log's: its first frame's sensor coordinates with poses
/// (`frame_poses`, sensor -> frame 0's), as the log's are frame 0's; the identity without.
fn window_to_log(frame_poses: Option<&[Rigid]>, windows: &[Window]) -> Vec<Rigid> {
    match frame_poses {
        Some(poses) => windows.iter().map(|w| poses[w.start]).collect(),
        None => vec![Rigid::identity(); windows.len()],
    }
}

/// A query point that left `window` on its body `body` (`at`: its position in the body's own
/// coordinates) into a window without that body's object: the times of window `first_owner` and
/// beyond (away from where the query started) follow the body, carried on past its window
/// ([`body_pose_beyond`]).
#[derive(Debug, Clone)]
struct Orphan {
    window: usize,
    body: usize,
    at: Point,
    first_owner: usize,
}

impl Orphan {
    /// Where the point is at log time `time` (fractional log frame `u`), in the sensor
    /// coordinates of that time.
    /// `part` is the model of the point's window.
    fn position(
        &self,
        model: &FittedModel,
        windows: &[Window],
        part: &FittedModel,
        to_log: &[Rigid],
        time: f64,
        u: f64,
    ) -> Point {
        let window = &windows[self.window];
        let body_pose = body_pose_beyond(part, self.body, window.local_time(&model.time_axis, time));
        let in_log = to_log[self.window].apply(&body_pose.apply(&self.at));
        match &model.frame_poses {
            Some(poses) => pose_at(poses, u).inverse().apply(&in_log),
            None => in_log,
        }
    }
}

/// The pose of body `b` of a window's model `window` (the window's fit coordinates) at `t` on the window's own
/// time axis, also outside its frames. Inside, as the window's model answers. Past the last
/// frame (before the first), the body's motion at that end goes on at constant velocity and
/// turn rate (the end step repeated, as the fit carries a body on inside its window), up to the
/// axis's extrapolation horizon past the last (first) frame the body was seen in, and is held
/// after that: a body that leaves a window keeps moving as it did while the next window, which
/// does not know it, owns the time.
fn body_pose_beyond(window: &FittedModel, b: usize, t: f64) -> Rigid {
    let axis = &window.time_axis;
    let body = &window.bodies[b];
    let last = axis.frames() - 1;
    if let Ok(u) = axis.to_frame_index(t) {
        return pose_at(&body.poses, u);
    }
    let forward = t > axis.frame_time(last);
    let (edge, inner) = if forward { (last, last - 1) } else { (0, 1) };
    let horizon = axis.extrapolation_horizon();
    let seen = body.frames_seen();
    let t = if forward {
        let bound = seen.last().map_or(f64::NEG_INFINITY, |&k| axis.frame_time(k) + horizon);
        t.min(bound.max(axis.frame_time(edge)))
    } else {
        let bound = seen.first().map_or(f64::INFINITY, |&k| axis.frame_time(k) - horizon);
        t.max(bound.min(axis.frame_time(edge)))
    };
    let step = (axis.frame_time(edge) - axis.frame_time(inner)).abs();
    let steps = (t - axis.frame_time(edge)).abs() / step;
    if !steps.is_finite() || steps <= 0.0 {
        return body.poses[edge];
    }
    // The last step, edge from its inner neighbour, applied again `steps` times (whole steps,
    // then the fraction of one interpolated as between frames).
    let delta = body.poses[edge].compose(&body.poses[inner].inverse());
    let whole = steps.floor();
    let mut before = body.poses[edge];
    for _ in 0..whole as usize {
        before = delta.compose(&before);
    }
    pose_at(&[before, delta.compose(&before)], steps - whole)
}

/// Where a query enters a window of a stitched model.
#[derive(Debug, Clone)]
struct Entry {
    /// The query points (sensor coordinates of time `t`).
    points: Vec<Point>,
    /// The log's time at which the window takes them over.
    t: f64,
    /// Per point, what the previous window decided about it ([`Carry`]); `None` for the window
    /// the points were observed in.
    carried: Option<Vec<Carry>>,
}

/// [`FittedModel::frame_object_ids`] of a stitched model: the window owning frame `k` labels its
/// points, with the log-wide ids (decoding that window only).
pub(super) fn frame_object_ids(
    model: &FittedModel,
    windows: &[Window],
    k: usize,
    points: &[Point],
) -> Result<Vec<i32>, QueryError> {
    let w = owner(&handoffs(windows), k as f64);
    let window = &windows[w];
    let part = window.model(w, &model.time_axis, model.frame_poses.is_some())?;
    let ids = part.frame_object_ids(k - window.start, points)?;
    Ok(ids
        .into_iter()
        .map(|id| part.bodies.iter().position(|b| b.id as i32 == id).map_or(-1, |n| window.object_ids[n] as i32))
        .collect())
}

/// Log-wide object ids of every window's bodies, and how many objects there are.
struct Objects {
    /// Per window, per body (in the window's order): its object id.
    ids: Vec<Vec<u32>>,
    /// Objects in the log.
    count: usize,
}

/// Links the bodies of neighbouring windows (see [`LINK_MIN_SHARE`]) and numbers the objects
/// in order of first appearance. Each body links to at most one of the next window's, the
/// pairs sharing the most points first.
fn link_bodies(windows: &[Window], parts: &[&FittedModel], to_log: &[Rigid]) -> Objects {
    let mut ids: Vec<Vec<u32>> = Vec::with_capacity(windows.len());
    let mut count = 0u32;
    for (w, part) in parts.iter().enumerate() {
        let mut mine: Vec<Option<u32>> = vec![None; part.bodies.len()];
        if w > 0 {
            let mut pairs: Vec<(f64, usize, usize)> = link_shares(windows, parts, to_log, w)
                .into_iter()
                .filter(|&(share, _, _)| share >= LINK_MIN_SHARE)
                .collect();
            pairs.sort_by(|x, y| y.0.total_cmp(&x.0));
            let mut taken = vec![false; parts[w - 1].bodies.len()];
            for (_, a, b) in pairs {
                if !taken[a] && mine[b].is_none() {
                    taken[a] = true;
                    mine[b] = Some(ids[w - 1][a]);
                }
            }
        }
        ids.push(
            mine.into_iter()
                .map(|id| {
                    id.unwrap_or_else(|| {
                        count += 1;
                        count - 1
                    })
                })
                .collect(),
        );
    }
    Objects { ids, count: count as usize }
}

/// For each pair of a body of window `w - 1` and one of window `w` (`w >= 1`) with members in
/// their overlap: the share of both bodies' member points in the overlap's frames that lie
/// within [`TRACK_MEMBER_RADIUS_M`] of the other's members of the same frame, and the pair.
fn link_shares(windows: &[Window], parts: &[&FittedModel], to_log: &[Rigid], w: usize) -> Vec<(f64, usize, usize)> {
    let (previous, window) = (&windows[w - 1], &windows[w]);
    body_link_shares(
        (parts[w - 1], previous.start, &to_log[w - 1]),
        (parts[w], window.start, &to_log[w]),
        window.start..previous.end(),
    )
}

/// [`link_shares`] of two windows' models, each given with its first frame in the log and its
/// fit-to-log transform, over the log frames `overlap` they share.
fn body_link_shares(
    (before_part, before_start, before_to_log): (&FittedModel, usize, &Rigid),
    (after_part, after_start, after_to_log): (&FittedModel, usize, &Rigid),
    overlap: Range<usize>,
) -> Vec<(f64, usize, usize)> {
    // Each body's members in each overlap frame, in the log's fit coordinates.
    let members = |part: &FittedModel, start: usize, to: &Rigid| -> Vec<Vec<Vec<Point>>> {
        part.bodies
            .iter()
            .map(|body| {
                overlap.clone().map(|k| body.members[k - start].iter().map(|p| to.apply(p)).collect()).collect()
            })
            .collect()
    };
    let before = members(before_part, before_start, before_to_log);
    let after = members(after_part, after_start, after_to_log);
    let mut pairs = Vec::new();
    for (a, frames_a) in before.iter().enumerate() {
        for (b, frames_b) in after.iter().enumerate() {
            let (mut near, mut total) = (0usize, 0usize);
            for (pa, pb) in frames_a.iter().zip(frames_b) {
                near += near_count(pa, pb) + near_count(pb, pa);
                total += pa.len() + pb.len();
            }
            if total > 0 {
                pairs.push((near as f64 / total as f64, a, b));
            }
        }
    }
    pairs
}

/// The bodies of `before` (a window's model from log frame `before_start`) that no body of
/// `after` (the next window's, from `after_start`, starting inside `before`) would be linked to
/// when the two are stitched: each with its pose at every frame the two windows share, taken
/// into `after`'s fit coordinates (`to_log` gives each window's fit-to-log transform). Only
/// bodies seen in at least one of the shared frames are listed: the next window may carry on
/// following them (`fit::windows`).
pub(crate) fn unlinked_bodies(
    (before, before_start, before_to_log): (&FittedModel, usize, &Rigid),
    (after, after_start, after_to_log): (&FittedModel, usize, &Rigid),
) -> Vec<(usize, Vec<Rigid>)> {
    let overlap = after_start..before_start + before.time_axis.frames();
    let shares =
        body_link_shares((before, before_start, before_to_log), (after, after_start, after_to_log), overlap.clone());
    let to_after = after_to_log.inverse().compose(before_to_log);
    before
        .bodies
        .iter()
        .enumerate()
        .filter(|&(a, body)| {
            let linked = shares.iter().any(|&(share, pa, _)| pa == a && share >= LINK_MIN_SHARE);
            !linked && overlap.clone().any(|k| body.observed[k - before_start])
        })
        .map(|(a, body)| (a, overlap.clone().map(|k| to_after.compose(&body.poses[k - before_start])).collect()))
        .collect()
}

/// How many of `points` lie within [`TRACK_MEMBER_RADIUS_M`] of one of `others`.
fn near_count(points: &[Point], others: &[Point]) -> usize {
    if points.is_empty() || others.is_empty() {
        return 0;
    }
    let tree = KdTree::new(others);
    let max_d2 = TRACK_MEMBER_RADIUS_M * TRACK_MEMBER_RADIUS_M;
    points.iter().filter(|p| tree.nearest(p).is_some_and(|h| h.dist2 <= max_d2)).count()
}

/// Each object over the whole log (fit coordinates of the log): at frame k, the pose, sighting
/// and point count its part in the window owning k gives, else its part in the nearest window
/// holding it (held at that window's end frame beyond it, as a body is held beyond its bounded
/// extrapolation). Members are left empty: queries use the windows' bodies, which hold them.
fn log_bodies(
    windows: &[Window],
    models: &[&FittedModel],
    to_log: &[Rigid],
    handoffs: &[usize],
    objects: usize,
    frames: usize,
) -> Vec<MovingBody> {
    (0..objects)
        .map(|id| {
            // The object's parts: (window, body index), in window order.
            let parts: Vec<(usize, usize)> = windows
                .iter()
                .enumerate()
                .flat_map(|(w, window)| {
                    window.object_ids.iter().enumerate().filter(|&(_, &o)| o as usize == id).map(move |(b, _)| (w, b))
                })
                .collect();
            let mut body = MovingBody {
                id: id as u32,
                poses: Vec::with_capacity(frames),
                observed: Vec::with_capacity(frames),
                members: vec![Vec::new(); frames],
                member_counts: Vec::with_capacity(frames),
                extent_min_m: [0.0; 3],
                extent_max_m: [0.0; 3],
            };
            for k in 0..frames {
                let own = owner(handoffs, k as f64);
                // The part in the owning window, else the nearest window's (by window index,
                // which orders windows by time).
                let &(w, b) = parts.iter().min_by_key(|(w, _)| w.abs_diff(own)).expect("an object has a part");
                let window = &windows[w];
                let part = &models[w].bodies[b];
                let local = k.clamp(window.start, window.end() - 1) - window.start;
                let inside = (window.start..window.end()).contains(&k);
                body.poses.push(to_log[w].compose(&pose_at(&part.poses, local as f64)));
                body.observed.push(inside && part.observed[local]);
                body.member_counts.push(if inside { part.member_counts[local] } else { 0 });
            }
            // The extent the window seeing the object most often measured.
            let &(w, b) = parts
                .iter()
                .max_by_key(|&&(w, b)| models[w].bodies[b].observed.iter().filter(|&&o| o).count())
                .expect("an object has a part");
            let part = &models[w].bodies[b];
            body.extent_min_m = part.extent_min_m;
            body.extent_max_m = part.extent_max_m;
            body
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::tests::scene_model;

    /// A 6-frame log with identity poses stitched from two 4-frame windows starting at frames 0
    /// and 2 (hand-over at frame 3).
    fn two_windows(first: FittedModel, second: FittedModel) -> FittedModel {
        FittedModel::stitched(
            Method::Mbnt,
            TimeAxis::new(None, 6),
            Some(vec![Rigid::identity(); 6]),
            FitReport::default(),
            vec![(0, first), (2, second)],
        )
        .unwrap()
    }

    #[test]
    fn hand_overs_lie_in_the_middle_of_the_overlaps_and_own_every_time_once() {
        let window = |start: usize| Window::decoded(start, scene_model(), vec![0]);
        // Three 4-frame windows over 9 frames (starts 0, 3, 5): overlaps {3} and {5, 6}.
        let windows = [window(0), window(3), window(5)];
        let h = handoffs(&windows);
        assert_eq!(h, vec![3, 6]);
        let owners: Vec<usize> = (0..9).map(|k| owner(&h, k as f64)).collect();
        assert_eq!(owners, vec![0, 0, 0, 1, 1, 1, 2, 2, 2]);
        assert_eq!(owner(&h, 2.999), 0);
        assert!(check_windows(&TimeAxis::new(None, 9), &windows).is_ok());
        // Gaps, a wrong end and a missing start are refused.
        let gap = [window(0), window(4)];
        assert!(check_windows(&TimeAxis::new(None, 8), &gap).unwrap_err().contains("overlap"));
        assert!(check_windows(&TimeAxis::new(None, 10), &windows).unwrap_err().contains("end at frame 9"));
        assert!(check_windows(&TimeAxis::new(None, 8), &windows[1..]).unwrap_err().contains("frame 0"));
        // A window's model fitted without poses in a log fitted with them is refused.
        let e = check_window(&windows[0], &scene_model(), &TimeAxis::new(None, 9), false).unwrap_err();
        assert!(e.contains("poses"), "{e}");
    }

    #[test]
    fn a_body_leaving_its_window_goes_on_at_its_last_velocity_up_to_the_horizon() {
        // scene_model()'s body drives 1 m per frame along x; frames 1 s apart, so the horizon
        // is 3 s past the last frame seen.
        let mut model = scene_model();
        model.time_axis = TimeAxis::new(Some(vec![0.0, 1.0, 2.0, 3.0]), 4);
        let x = |t: f64| body_pose_beyond(&model, 0, t).translation[0];
        for (t, want) in [(1.5, 1.5), (4.0, 4.0), (5.5, 5.5), (6.0, 6.0), (10.0, 6.0), (-2.5, -2.5), (-9.0, -3.0)] {
            assert!((x(t) - want).abs() < 1e-9, "t = {t}: x = {} instead of {want}", x(t));
        }
        // Seen last at frame 1: carried on inside the window already, held 3 s after frame 1.
        let mut early = model.clone();
        early.bodies[0].observed = vec![true, true, false, false];
        let x = |t: f64| body_pose_beyond(&early, 0, t).translation[0];
        assert!((x(3.5) - 3.5).abs() < 1e-9 && (x(7.0) - 4.0).abs() < 1e-9, "{} {}", x(3.5), x(7.0));
    }

    #[test]
    fn a_point_whose_body_the_next_window_lacks_stays_on_it() {
        // Two 4-frame windows over 6 frames (starts 0 and 2, hand-over at frame 3): the car is a
        // body of the first window only (the second did not find it again: too far, too sparse).
        let first = scene_model();
        let mut second = scene_model();
        second.bodies.clear();
        let stitched = two_windows(first.clone(), second.clone());
        // Past the hand-over the point follows the first window's car, 1 m per frame; a point
        // of the still world stays.
        let at = stitched.positions(&[[0.2, 0.1, 0.0], [10.0, 10.0, 0.0]], 0.0, &[2.0, 4.0, 5.0]).unwrap();
        let want = [
            [2.2, 0.1, 0.0],
            [4.2, 0.1, 0.0],
            [5.2, 0.1, 0.0],
            [10.0, 10.0, 0.0],
            [10.0, 10.0, 0.0],
            [10.0, 10.0, 0.0],
        ];
        for (got, want) in at.iter().zip(&want) {
            assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-4), "{at:?}");
        }
        // Backward: the car is a body of the second window only; a point on it at frame 5
        // (x = 3.2 in the second window, which starts at frame 2) is followed back to frame 0.
        let mut empty = first;
        empty.bodies.clear();
        let mut car = scene_model();
        car.bodies[0].poses.iter_mut().for_each(|p| p.translation[0] += 2.0);
        car.bodies[0].members.iter_mut().flatten().for_each(|p| p[0] += 2.0);
        let stitched = two_windows(empty, car);
        let back = stitched.positions(&[[5.2, 0.1, 0.0]], 5.0, &[4.0, 0.0]).unwrap();
        for (got, want) in back.iter().zip([[4.2, 0.1, 0.0], [0.2, 0.1, 0.0]]) {
            assert!(got.iter().zip(&want).all(|(g, w)| (g - w).abs() < 1e-4), "{back:?}");
        }
    }

    #[test]
    fn a_body_the_next_window_has_no_part_of_is_listed_with_its_poses_in_that_windows_coordinates() {
        // Windows of 4 frames from log frames 0 and 2 (shared: 2 and 3). The log's poses put
        // frame 2's sensor 5 m along y from frame 0's.
        let first = scene_model();
        let mut empty = scene_model();
        empty.bodies.clear();
        let identity = Rigid::identity();
        let shifted = Rigid { translation: [0.0, 5.0, 0.0], ..Rigid::identity() };
        let listed = unlinked_bodies((&first, 0, &identity), (&empty, 2, &shifted));
        assert_eq!(listed.len(), 1);
        let (body, poses) = &listed[0];
        assert_eq!(*body, 0);
        assert_eq!(poses.len(), 2);
        for (pose, k) in poses.iter().zip(2..4) {
            let want = shifted.inverse().compose(&first.bodies[0].poses[k]);
            let (got, want) = (pose.apply_f64([0.5, 0.5, 0.5]), want.apply_f64([0.5, 0.5, 0.5]));
            assert!((0..3).all(|c| (got[c] - want[c]).abs() < 1e-9), "{got:?} {want:?}");
            assert!((got[1] - (0.5 - 5.0)).abs() < 1e-9, "{got:?}");
        }
        // The same car as a body of the next window (where it is at its log frames): linked, not listed.
        let mut car = scene_model();
        car.bodies[0].poses.iter_mut().for_each(|p| p.translation[0] += 2.0);
        car.bodies[0].members.iter_mut().flatten().for_each(|p| p[0] += 2.0);
        assert!(unlinked_bodies((&first, 0, &identity), (&car, 2, &identity)).is_empty());
        // A body not seen in the shared frames is not listed: the next window has nothing to go on.
        let mut early = scene_model();
        early.bodies[0].observed = vec![true, true, false, false];
        assert!(unlinked_bodies((&early, 0, &identity), (&empty, 2, &identity)).is_empty());
    }

    #[test]
    fn a_still_point_stays_still_when_a_body_of_the_next_window_passes_it_at_the_hand_over() {
        // Two 4-frame windows over 6 frames (starts 0 and 2, hand-over at frame 3): the car is a
        // body of the second window only, at x = 1.2 at log frame 3 (its local frame 1). A point
        // of the still world observed at frame 0 where the car will pass at the hand-over stays
        // still at every time, as in a model of one fit; the car's own point follows the car.
        let mut first = scene_model();
        first.bodies.clear();
        let stitched = two_windows(first, scene_model());
        let still = [1.2, 0.1, 0.0];
        let at = stitched.positions(&[still], 0.0, &[3.0, 4.0, 5.0]).unwrap();
        assert!(at.iter().all(|p| p.iter().zip(&still).all(|(g, w)| (g - w).abs() < 1e-4)), "{at:?}");
        // Observed at the hand-over itself, the point is the second window's to decide: on the car.
        let on_car = stitched.positions(&[still], 3.0, &[5.0]).unwrap();
        assert!((on_car[0][0] - 3.2).abs() < 1e-4, "{on_car:?}");
    }

    #[test]
    fn bodies_sharing_their_points_in_the_overlap_are_one_object() {
        // scene_model(): a 4-frame window whose body drives 1 m per frame along x from x = 0.
        // The next window starts at frame 2 of the first: in its own coordinates (identity
        // poses, so the same as the log's) its body is the same car, 2 m on.
        let first = scene_model();
        let mut second = scene_model();
        let car = &mut second.bodies[0];
        let shift = Rigid { translation: [2.0, 0.0, 0.0], ..Rigid::identity() };
        car.poses = car.poses.iter().map(|p| shift.compose(p)).collect();
        car.members = car.members.iter().map(|m| m.iter().map(|p| shift.apply(p)).collect()).collect();
        // A second body far away in the second window: a new object.
        let mut other = car.clone();
        other.id = 1;
        other.members = other.members.iter().map(|m| m.iter().map(|p| [p[0], p[1] + 30.0, p[2]]).collect()).collect();
        second.bodies.push(other);
        let stitched = two_windows(first, second);
        let ids: Vec<u32> = stitched.bodies().iter().map(|b| b.id).collect();
        assert_eq!(ids, vec![0, 1], "the car is one object, the far body another");
        let car = &stitched.bodies()[0];
        // The car's pose at every frame of the log: 1 m per frame along x throughout.
        for (k, pose) in car.poses.iter().enumerate() {
            assert!((pose.translation[0] - k as f64).abs() < 1e-9, "frame {k}: {pose:?}");
        }
        // Labels: frame 5 (owned by the second window) has the car at x = 5..6, the far body
        // at y = 30.
        let labels = stitched
            .object_ids(&[vec![], vec![], vec![], vec![], vec![], vec![[5.2, 0.0, 0.0], [5.0, 30.0, 0.0]]])
            .unwrap();
        assert_eq!(labels[5], vec![0, 1]);
        // A point on the car at frame 0 follows it to frame 5, through the hand-over at frame 3.
        let at = stitched.positions(&[[0.2, 0.1, 0.0]], 0.0, &[2.5, 3.0, 5.0]).unwrap();
        for (got, want) in at.iter().zip([[2.7, 0.1, 0.0], [3.2, 0.1, 0.0], [5.2, 0.1, 0.0]]) {
            assert!(got.iter().zip(&want).all(|(g, w)| (g - w).abs() < 1e-4), "{at:?}");
        }
        // A point of the car seen only in frame 0 (its rear: the first window's frame-0 members
        // hold it, no later sweep does) follows the car through the hand-over: it arrives 3 m from
        // the second window's members of frame 3 but carries the car's object with it.
        let mut seen_once = stitched.clone();
        if let Motion::Windows(windows) = &mut seen_once.motion {
            windows[0].model_mut().bodies[0].members[0].push([0.0, 3.0, 0.0]);
        }
        let at = seen_once.positions(&[[0.1, 3.0, 0.0]], 0.0, &[3.0, 5.0]).unwrap();
        for (got, want) in at.iter().zip([[3.1, 3.0, 0.0], [5.1, 3.0, 0.0]]) {
            assert!(got.iter().zip(&want).all(|(g, w)| (g - w).abs() < 1e-4), "{at:?}");
        }
        // And back.
        let back = stitched.positions(&[[5.2, 0.1, 0.0]], 5.0, &[0.0]).unwrap();
        assert!(back[0].iter().zip(&[0.2, 0.1, 0.0]).all(|(g, w)| (g - w).abs() < 1e-4), "{back:?}");
        // Through the file format (version 2, each window a version 1 file).
        let bytes = stitched.to_bytes().unwrap();
        assert!(bytes.starts_with(b"MBNTMDL2"));
        let window_at = bytes.windows(8).skip(8).position(|w| w == b"MBNTMDL1").unwrap() + 8;
        let mut nested = bytes.clone();
        nested[window_at..window_at + 8].copy_from_slice(b"MBNTMDL2");
        let e = FittedModel::from_bytes(&nested).unwrap_err();
        assert!(e.contains("window 0 is not the model of one fit"), "{e}");
        let loaded = FittedModel::from_bytes(&bytes).unwrap();
        assert_eq!(loaded.bodies(), stitched.bodies());
        assert_eq!(
            loaded.positions(&[[0.2, 0.1, 0.0]], 0.0, &[5.0]).unwrap(),
            stitched.positions(&[[0.2, 0.1, 0.0]], 0.0, &[5.0]).unwrap()
        );
        // A window holding a NaN is refused at save time, naming the window.
        let mut poisoned = stitched.clone();
        if let Motion::Windows(windows) = &mut poisoned.motion {
            windows[1].model_mut().bodies[0].poses[3].translation[0] = f64::NAN;
        }
        let e = poisoned.to_bytes().unwrap_err().to_string();
        assert!(e.contains("window 1 (from frame 2): moving body 0, pose at frame 3"), "{e}");
    }

    /// An 8-frame log with identity poses stitched from three 4-frame windows starting at frames
    /// 0, 2 and 4 (hand-overs at frames 3 and 5): scene_model()'s car in each, where it is in
    /// the log (1 m per frame along x), so that the three parts are one object.
    fn three_windows() -> FittedModel {
        let car_from = |start: usize| {
            let mut model = scene_model();
            let shift = Rigid { translation: [start as f64, 0.0, 0.0], ..Rigid::identity() };
            let car = &mut model.bodies[0];
            car.poses = car.poses.iter().map(|p| shift.compose(p)).collect();
            car.members = car.members.iter().map(|m| m.iter().map(|p| shift.apply(p)).collect()).collect();
            (start, model)
        };
        FittedModel::stitched(
            Method::Mbnt,
            TimeAxis::new(None, 8),
            Some(vec![Rigid::identity(); 8]),
            FitReport::default(),
            vec![car_from(0), car_from(2), car_from(4)],
        )
        .unwrap()
    }

    /// Whether two arrays of points are the same bit for bit.
    fn same_bits(a: &[Point], b: &[Point]) -> bool {
        a.len() == b.len() && a.iter().flatten().zip(b.iter().flatten()).all(|(x, y)| x.to_bits() == y.to_bits())
    }

    #[test]
    fn a_loaded_stitched_model_decodes_only_the_windows_its_queries_need_and_answers_as_built() {
        let built = three_windows();
        assert_eq!(built.decoded_windows(), 3, "a fit's windows are decoded from the start");
        assert_eq!(built.bodies().len(), 1, "the car is one object over the three windows");
        let bytes = built.to_bytes().unwrap();
        let loaded = FittedModel::from_bytes(&bytes).unwrap();
        // Loading reads the header only: the log's objects, poses, report and windows' ids.
        assert_eq!(loaded.decoded_windows(), 0);
        // The file's bytes, watched without keeping them alive.
        let Motion::Windows(windows) = &loaded.motion else { panic!("a stitched model") };
        let file = Arc::downgrade(&windows[0].source_bytes().expect("an undecoded window holds its bytes").file);
        assert_eq!(loaded.bodies(), built.bodies());
        assert_eq!(loaded.report(), built.report());
        assert_eq!(loaded.window_object_ids(), built.window_object_ids());
        assert_eq!(loaded.window_starts(), vec![0, 2, 4]);
        assert_eq!(loaded.decoded_windows(), 0);
        // Written back undecoded, the file is the same bytes.
        assert_eq!(loaded.to_bytes().unwrap(), bytes);
        // A query within the first window's time decodes that window only.
        let points = [[0.2, 0.1, 0.0], [10.0, 10.0, 0.0], [20.1, 0.0, 0.0]];
        let near = loaded.positions(&points, 0.0, &[1.0, 2.5]).unwrap();
        assert!(same_bits(&near, &built.positions(&points, 0.0, &[1.0, 2.5]).unwrap()));
        assert_eq!(loaded.decoded_windows(), 1);
        // Past the first hand-over (frame 3), the chain reaches the second window.
        let next = loaded.positions(&points, 0.0, &[3.5]).unwrap();
        assert!(same_bits(&next, &built.positions(&points, 0.0, &[3.5]).unwrap()));
        assert_eq!(loaded.decoded_windows(), 2);
        // Two windows re-encoded from their models, one from its bytes: the file as read, which
        // the undecoded window still holds.
        assert_eq!(loaded.to_bytes().unwrap(), bytes);
        assert!(file.upgrade().is_some());
        // Bit-identical answers at every time across both hand-overs, from every window.
        let times = [0.0, 1.0, 2.5, 3.0, 4.0, 4.5, 5.0, 6.0, 7.0];
        for t_obs in [0.0, 3.0, 5.5, 7.0] {
            let (a, b) =
                (loaded.positions(&points, t_obs, &times).unwrap(), built.positions(&points, t_obs, &times).unwrap());
            assert!(same_bits(&a, &b), "observed at {t_obs}: {a:?} vs {b:?}");
        }
        assert_eq!(loaded.decoded_windows(), 3);
        // Every window decoded, none needs the file: its bytes are freed.
        assert!(file.upgrade().is_none(), "the file's bytes outlive its decoded windows");
        // A partly or wholly decoded model is still written back as it was read.
        assert_eq!(loaded.to_bytes().unwrap(), bytes);
        // Labels: frame 6 is the last window's; a fresh load decodes that window alone.
        let fresh = FittedModel::from_bytes(&bytes).unwrap();
        let on_car = vec![[6.2, 0.0, 0.0], [30.0, 0.0, 0.0]];
        assert_eq!(fresh.frame_object_ids(6, &on_car).unwrap(), vec![0, -1]);
        assert_eq!(fresh.decoded_windows(), 1);
        let frames: Vec<Vec<Point>> =
            (0..8).map(|k| vec![[k as f32 + 0.2, 0.1, 0.0], [10.0, 10.0, 0.0], [20.1, 0.0, 0.0]]).collect();
        assert_eq!(fresh.object_ids(&frames).unwrap(), built.object_ids(&frames).unwrap());
        let (flow_loaded, flow_built) = (fresh.scene_flow(&frames).unwrap(), built.scene_flow(&frames).unwrap());
        assert!(flow_loaded.iter().zip(&flow_built).all(|(a, b)| same_bits(a, b)));
        assert!((flow_built[5][0][0] - 1.0).abs() < 1e-4, "the car moves 1 m per frame: {:?}", flow_built[5]);
        // Every window, and the network-alone model, as the built ones.
        let windows = fresh.windows().unwrap();
        assert_eq!(
            windows.iter().map(|(s, m)| (*s, m.bodies().len())).collect::<Vec<_>>(),
            vec![(0, 1), (2, 1), (4, 1)]
        );
        assert_eq!(fresh.window_link_shares().unwrap(), built.window_link_shares().unwrap());
        let alone = |m: &FittedModel| m.without_tracks().unwrap().positions(&points, 0.0, &times).unwrap();
        assert!(same_bits(&alone(&fresh), &alone(&built)));
    }

    /// The bytes of `model`'s file with `change` applied to window `w`'s own file (version 1).
    fn with_window_changed(bytes: &[u8], w: usize, change: impl FnOnce(&mut [u8])) -> Vec<u8> {
        let mut out = bytes.to_vec();
        let at = (8..bytes.len() - 8).filter(|&i| &bytes[i..i + 8] == b"MBNTMDL1").nth(w).unwrap();
        let len = u64::from_le_bytes(bytes[at - 8..at].try_into().unwrap()) as usize;
        change(&mut out[at..at + len]);
        out
    }

    #[test]
    fn a_damaged_window_loads_and_is_refused_with_its_index_when_a_query_first_needs_it() {
        let built = three_windows();
        let bytes = built.to_bytes().unwrap();
        // Window 1's own header made unreadable JSON.
        let damaged = with_window_changed(&bytes, 1, |window| window[16] = b'#');
        let loaded = FittedModel::from_bytes(&damaged).unwrap();
        assert_eq!(loaded.decoded_windows(), 0);
        // Queries within window 0 answer; one reaching window 1 is refused, every time it is asked.
        let points = [[0.2, 0.1, 0.0]];
        assert_eq!(loaded.positions(&points, 0.0, &[2.0]).unwrap(), built.positions(&points, 0.0, &[2.0]).unwrap());
        for _ in 0..2 {
            let e = loaded.positions(&points, 0.0, &[4.0]).unwrap_err();
            assert!(
                matches!(&e, QueryError::CorruptWindow { window: 1, detail } if detail.contains("corrupt model header")),
                "{e}"
            );
        }
        assert!(matches!(loaded.frame_object_ids(4, &points), Err(QueryError::CorruptWindow { window: 1, .. })));
        assert!(loaded.frame_scene_flow(3, &points).is_err());
        assert!(loaded.windows().is_err() && loaded.without_tracks().is_err());
        assert!(loaded.to_bytes().unwrap() == damaged, "written back as read");
        // Window 2's network damaged (its last bytes, the network's checksum): refused when a
        // query at the last window's time decodes it.
        let flipped = with_window_changed(&bytes, 2, |window| {
            let end = window.len();
            window[end - 4..].copy_from_slice(&[0xff; 4]);
        });
        let loaded = FittedModel::from_bytes(&flipped).unwrap();
        let e = loaded.positions(&points, 7.0, &[7.0]).unwrap_err();
        assert!(
            matches!(&e, QueryError::CorruptWindow { window: 2, detail } if detail.contains("corrupt network")),
            "{e}"
        );
        // A window whose own times are not its slice of the log: refused when decoded.
        let mut shifted = three_windows();
        if let Motion::Windows(windows) = &mut shifted.motion {
            windows[1].model_mut().time_axis = TimeAxis::new(Some(vec![0.0, 1.0, 2.0, 3.0]), 4);
        }
        let loaded = FittedModel::from_bytes(&shifted.to_bytes().unwrap()).unwrap();
        let e = loaded.positions(&points, 3.0, &[3.0]).unwrap_err();
        assert!(e.to_string().contains("window 1 of the stitched model cannot be read: the window's times"), "{e}");
        // A window whose length prefix runs past the end of the file is refused at load.
        let mut truncated = bytes.clone();
        truncated.truncate(bytes.len() - 3);
        assert!(FittedModel::from_bytes(&truncated).unwrap_err().contains("truncated inside a window"));
    }

    #[test]
    fn a_stitched_model_file_without_the_windows_frames_in_its_header_still_loads() {
        // Files written before windows loaded lazily name each window's start and objects only.
        let built = three_windows();
        let bytes = built.to_bytes().unwrap();
        let len = u64::from_le_bytes(bytes[8..16].try_into().unwrap()) as usize;
        let mut header: serde_json::Value = serde_json::from_slice(&bytes[16..16 + len]).unwrap();
        for window in header["windows"].as_array_mut().unwrap() {
            window.as_object_mut().unwrap().remove("frames").expect("the current header has the field");
        }
        let old_header = serde_json::to_vec(&header).unwrap();
        let mut old = b"MBNTMDL2".to_vec();
        old.extend((old_header.len() as u64).to_le_bytes());
        old.extend(old_header);
        old.extend(&bytes[16 + len..]);
        let loaded = FittedModel::from_bytes(&old).unwrap();
        assert_eq!(loaded.decoded_windows(), 0);
        let times = [0.0, 3.0, 4.5, 7.0];
        let points = [[0.2, 0.1, 0.0]];
        assert!(same_bits(
            &loaded.positions(&points, 0.0, &times).unwrap(),
            &built.positions(&points, 0.0, &times).unwrap()
        ));
        assert_eq!(loaded.to_bytes().unwrap(), bytes, "written back with the frames");
    }
}
