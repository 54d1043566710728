//! A fitted motion model answers where a point is at any time of its sequence.
//!
//! Times are in the sequence's own axis: its timestamps in seconds when it has them, frame
//! indices 0..T-1 otherwise. Positions at time s are in the sensor frame of the sweep at s.

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::fit::Method;
use crate::fit::bodies::MovingBody;
use crate::fit::encoding::encode_points;
use crate::fit::prepare::FrameReport;
use crate::fit::tracks::RigidTrack;
use crate::geometry::Point;
use crate::geometry::knn::KdTree;
use crate::geometry::rigid::Rigid;
use crate::nn::{Mlp, Workspace};

/// Maps the sequence's time axis to fractional frame indices, piecewise linearly.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TimeAxis {
    /// Timestamps (s) per frame, or `None` when times are frame indices.
    timestamps_s: Option<Vec<f64>>,
    frames: usize,
}

/// A query that cannot be answered.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum QueryError {
    /// A time outside [t_0, t_{T-1}] (or not finite).
    #[error("time {time} is outside the sequence's time range [{first}, {last}]")]
    TimeOutOfRange {
        /// The offending time.
        time: f64,
        /// First time of the sequence.
        first: f64,
        /// Last time of the sequence.
        last: f64,
    },
    /// A query point with a non-finite coordinate.
    #[error("point {index} has a non-finite coordinate")]
    NonFinitePoint {
        /// Index of the point in the query.
        index: usize,
    },
}

impl TimeAxis {
    /// A time axis over `frames` frames, in seconds when `timestamps_s` is given.
    pub fn new(timestamps_s: Option<Vec<f64>>, frames: usize) -> Self {
        Self { timestamps_s, frames }
    }

    /// Number of frames T.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The timestamps, when the axis has them.
    pub fn timestamps_s(&self) -> Option<&[f64]> {
        self.timestamps_s.as_deref()
    }

    /// The time of frame `k` on this axis.
    pub fn frame_time(&self, k: usize) -> f64 {
        match &self.timestamps_s {
            Some(ts) => ts[k],
            None => k as f64,
        }
    }

    /// The fractional frame index of `time` (linear between neighbouring frames).
    pub fn to_frame_index(&self, time: f64) -> Result<f64, QueryError> {
        let first = self.frame_time(0);
        let last = self.frame_time(self.frames - 1);
        if !time.is_finite() || time < first || time > last {
            return Err(QueryError::TimeOutOfRange { time, first, last });
        }
        let Some(ts) = &self.timestamps_s else {
            return Ok(time);
        };
        // The last k with ts[k] <= time, so that ts[k] <= time < ts[k + 1].
        let k = ts.partition_point(|&t| t <= time).saturating_sub(1).min(self.frames - 2);
        Ok(k as f64 + (time - ts[k]) / (ts[k + 1] - ts[k]))
    }
}

/// The fitted network(s) behind a model.
#[derive(Debug, Clone)]
enum Motion {
    /// One trajectory network (NTP, MBNT): input [x, y, z, time embedding], output the
    /// velocities v_0..v_{T-2}.
    Trajectory(Mlp<f32>),
    /// Per pair k -> k+1 a forward flow f_k and a backward flow g_k (NSFP, MBNSF).
    PairFlows {
        /// f_k, k = 0..T-2.
        forward: Vec<Mlp<f32>>,
        /// g_k, k = 0..T-2.
        backward: Vec<Mlp<f32>>,
    },
}

/// What the fit did, kept with the model so that users can see it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    /// Per frame: points received, removed as ground or out of range, fitted, clusters.
    pub frames: Vec<FrameReport>,
    /// Optimiser iterations run (summed over pairs for pair-wise methods).
    pub iterations: usize,
    /// Iteration of the selected checkpoint (trajectory methods).
    pub best_iteration: Option<usize>,
    /// Validation loss of the selected checkpoint (trajectory methods).
    pub best_validation_loss: Option<f64>,
    /// Iterations run per pair (pair-wise methods; early stopping may end a pair sooner).
    pub iterations_per_pair: Vec<usize>,
    /// Wall time of the fit (s).
    pub fit_seconds: f64,
    /// Wall time per phase of the trajectory loop (zero for pair-wise methods).
    #[serde(default)]
    pub phase_times: crate::fit::PhaseTimes,
    /// The checked hyper-parameters the fit ran with.
    #[serde(default)]
    pub params: Option<crate::fit::ValidFitParams>,
    /// Moving clusters found and followed by rigid tracks (`rigid_tracks`), summed over frames.
    #[serde(default)]
    pub rigid_tracks: usize,
    /// Wall time of finding and following them, or the moving bodies (s), included in
    /// `fit_seconds`.
    #[serde(default)]
    pub rigid_tracks_seconds: f64,
    /// Moving bodies of the scene model (`moving_bodies`).
    #[serde(default)]
    pub moving_bodies: usize,
    /// Points of the scene model the network answers, summed over frames (the rest of the
    /// points on no body follow the still world).
    #[serde(default)]
    pub free_points: usize,
    /// The sensor-to-world poses (row-major 4 x 4, frame 0 the identity) the LiDAR odometry
    /// estimated, when the fit ran it (`odometry` parameter) instead of using given poses.
    #[serde(default)]
    pub estimated_poses: Option<Vec<[f64; 16]>>,
}

/// A fitted motion model of one sequence.
#[derive(Debug, Clone)]
pub struct FittedModel {
    method: Method,
    time_axis: TimeAxis,
    report: FitReport,
    motion: Motion,
    /// Per frame, sensor coordinates -> the fit's frame (frame 0's sensor coordinates with the
    /// ego motion removed), when the fit used poses. None: the fit worked in sensor coordinates.
    frame_poses: Option<Vec<Rigid>>,
    /// Rigid tracks of moving clusters (`rigid_tracks`); a query point on one follows it
    /// instead of the network. Empty when the option is off or nothing moved.
    tracks: Vec<RigidTrack>,
    /// The scene model's moving bodies (`moving_bodies`).
    bodies: Vec<MovingBody>,
    /// Whether the model is a scene model: points on no body follow the still world (the poses)
    /// instead of the network, except the network's free points.
    still_world: bool,
    /// Per frame (fit coordinates): points whose motion the network explains clearly better than
    /// the still world (`true`), and the still points around them (`false`), so that a query
    /// point takes the kind of its nearest neighbour. Empty without a still world.
    free_points: Vec<Vec<(Point, bool)>>,
}

/// A query point within this distance (m) of a tracked cluster's points, at the query's time,
/// follows the cluster's track: half the DBSCAN radius, so points of the cluster's own sweep
/// (distance 0) and of its surface between sweeps qualify, and the static neighbours a metre
/// away do not.
const TRACK_MEMBER_RADIUS_M: f32 = 0.4;

/// Query points are evaluated in chunks of this many, bounding memory for large queries.
const QUERY_CHUNK: usize = 16_384;

impl FittedModel {
    /// A model from a fitted trajectory network.
    pub(crate) fn trajectory(
        method: Method,
        time_axis: TimeAxis,
        report: FitReport,
        mlp: Mlp<f32>,
        frame_poses: Option<Vec<Rigid>>,
    ) -> Self {
        Self {
            method,
            time_axis,
            report,
            motion: Motion::Trajectory(mlp),
            frame_poses,
            tracks: Vec::new(),
            bodies: Vec::new(),
            still_world: false,
            free_points: Vec::new(),
        }
    }

    /// A model from fitted pair flows.
    pub(crate) fn pair_flows(
        method: Method,
        time_axis: TimeAxis,
        report: FitReport,
        forward: Vec<Mlp<f32>>,
        backward: Vec<Mlp<f32>>,
        frame_poses: Option<Vec<Rigid>>,
    ) -> Self {
        Self {
            method,
            time_axis,
            report,
            motion: Motion::PairFlows { forward, backward },
            frame_poses,
            tracks: Vec::new(),
            bodies: Vec::new(),
            still_world: false,
            free_points: Vec::new(),
        }
    }

    /// The method that produced the model.
    pub fn method(&self) -> Method {
        self.method
    }

    /// The sequence's time axis.
    pub fn time_axis(&self) -> &TimeAxis {
        &self.time_axis
    }

    /// What the fit did (pre-processing counts, iterations, checkpoint).
    pub fn report(&self) -> &FitReport {
        &self.report
    }

    /// The model with rigid tracks of moving clusters (fit coordinates) answering for their
    /// points; tracks whose motions do not cover every frame are dropped.
    pub(crate) fn with_tracks(mut self, tracks: Vec<RigidTrack>) -> Self {
        let frames = self.time_axis.frames();
        self.tracks = tracks.into_iter().filter(|t| t.fits(frames)).collect();
        self.report.rigid_tracks = self.tracks.len();
        self
    }

    /// The scene model: moving bodies (fit coordinates) answer for their points, and the still
    /// world (the poses) for every other point. Bodies that do not cover every frame are dropped.
    /// Without poses there is no still world and the network answers the other points.
    pub(crate) fn with_bodies(mut self, bodies: Vec<MovingBody>) -> Self {
        let frames = self.time_axis.frames();
        self.bodies = bodies.into_iter().filter(|b| b.fits(frames)).collect();
        self.report.moving_bodies = self.bodies.len();
        self.still_world = self.frame_poses.is_some();
        self
    }

    /// Sets the network's free points of a scene model (see [`FittedModel::network_positions`]):
    /// per frame, points (fit coordinates) the network answers (`true`) and still points near
    /// them (`false`).
    pub(crate) fn with_free_points(mut self, free_points: Vec<Vec<(Point, bool)>>) -> Self {
        if self.still_world && free_points.len() == self.time_axis.frames() {
            self.report.free_points = free_points.iter().map(|f| f.iter().filter(|(_, free)| *free).count()).sum();
            self.free_points = free_points;
        }
        self
    }

    /// The network's answer for `points` in fit coordinates observed at fractional frame `u_obs`,
    /// at each of `u_times` (point-major, fit coordinates): what a scene model uses for points
    /// that neither a body nor the still world explains.
    pub(crate) fn network_positions(&self, points: &[Point], u_obs: f64, u_times: &[f64]) -> Vec<Point> {
        let mut out = vec![[0f32; 3]; points.len() * u_times.len()];
        self.network_positions_into(points, u_obs, u_times, &mut out);
        out
    }

    /// [`FittedModel::network_positions`] into `out` (point-major), in chunks of
    /// [`QUERY_CHUNK`] points so that large queries stay bounded in memory.
    fn network_positions_into(&self, points: &[Point], u_obs: f64, u_times: &[f64], out: &mut [Point]) {
        if u_times.is_empty() {
            return;
        }
        let frames = self.time_axis.frames();
        for (chunk, out_chunk) in points.chunks(QUERY_CHUNK).zip(out.chunks_mut(QUERY_CHUNK * u_times.len())) {
            match &self.motion {
                Motion::Trajectory(mlp) => trajectory_positions(mlp, frames, chunk, u_obs, u_times, out_chunk),
                Motion::PairFlows { forward, backward } => {
                    euler_positions(forward, backward, chunk, u_obs, u_times, out_chunk)
                }
            }
        }
    }

    /// Per frame, the transform from sensor coordinates to the fit's coordinates, when the fit
    /// used poses.
    pub fn frame_poses(&self) -> Option<&[Rigid]> {
        self.frame_poses.as_deref()
    }

    /// The scene model's moving bodies (fit coordinates: frame 0's sensor coordinates with the
    /// ego motion removed).
    pub fn bodies(&self) -> &[MovingBody] {
        &self.bodies
    }

    /// Sets the reported fit time (s), once post-fit work has been added to it.
    pub(crate) fn set_fit_seconds(&mut self, seconds: f64, rigid_tracks_seconds: f64) {
        self.report.fit_seconds = seconds;
        self.report.rigid_tracks_seconds = rigid_tracks_seconds;
    }

    /// The same model answering from the network alone (for comparisons): no tracks, no bodies,
    /// no still world.
    pub fn without_tracks(&self) -> Self {
        Self { tracks: Vec::new(), bodies: Vec::new(), still_world: false, free_points: Vec::new(), ..self.clone() }
    }

    /// Rigid tracks of moving clusters the model holds.
    pub fn tracks(&self) -> &[RigidTrack] {
        &self.tracks
    }

    /// Positions of `points`, observed at time `t_obs`, at each of `times`.
    ///
    /// Returns a point-major array: entry `i * times.len() + j` is point i at `times[j]`, in
    /// the sensor frame of time `times[j]`. Cost: one network evaluation per point for
    /// trajectory models; one per point and crossed frame for pair-wise models.
    pub fn positions(&self, points: &[Point], t_obs: f64, times: &[f64]) -> Result<Vec<Point>, QueryError> {
        if let Some(index) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
            return Err(QueryError::NonFinitePoint { index });
        }
        let u_obs = self.time_axis.to_frame_index(t_obs)?;
        let u_times = times.iter().map(|&t| self.time_axis.to_frame_index(t)).collect::<Result<Vec<_>, _>>()?;
        let mut out = vec![[0f32; 3]; points.len() * times.len()];
        if times.is_empty() {
            return Ok(out);
        }
        // With poses, queries go into the fit's frame and answers come back into the sensor
        // frame of each queried time.
        let moved_in;
        let points = match &self.frame_poses {
            Some(poses) => {
                let to_fit = pose_at(poses, u_obs);
                moved_in = points.iter().map(|p| to_fit.apply(p)).collect::<Vec<_>>();
                &moved_in[..]
            }
            None => points,
        };
        if self.still_world {
            // The still world: in the fit's (ego-motion-free) coordinates nothing moves; the
            // network answers its free points only.
            for (p, row) in points.iter().zip(out.chunks_mut(times.len())) {
                row.fill(*p);
            }
            self.apply_free_points(points, u_obs, &u_times, &mut out);
        } else {
            self.network_positions_into(points, u_obs, &u_times, &mut out);
        }
        self.apply_tracks(points, u_obs, &u_times, &mut out);
        self.apply_bodies(points, u_obs, &u_times, &mut out);
        if let Some(poses) = &self.frame_poses {
            let to_sensor: Vec<Rigid> = u_times.iter().map(|&u| pose_at(poses, u).inverse()).collect();
            for row in out.chunks_mut(times.len()) {
                for (p, back) in row.iter_mut().zip(&to_sensor) {
                    *p = back.apply(p);
                }
            }
        }
        Ok(out)
    }

    /// Overwrites the answers (fit coordinates) of query points that lie on a tracked cluster
    /// at `u_obs` with the cluster's rigid motion from `u_obs` to each queried time.
    fn apply_tracks(&self, points: &[Point], u_obs: f64, u_times: &[f64], out: &mut [Point]) {
        // Tracks of the frames around u_obs, their points moved to u_obs.
        let near: Vec<&RigidTrack> = self.tracks.iter().filter(|t| (t.frame as f64 - u_obs).abs() < 1.0).collect();
        if near.is_empty() {
            return;
        }
        let mut members = Vec::new();
        let mut owner = Vec::new();
        // Per nearby track, its motion from u_obs to each queried time.
        let mut motions: Vec<Vec<Rigid>> = Vec::with_capacity(near.len());
        for (n, track) in near.iter().enumerate() {
            let at_obs = pose_at(&track.motions, u_obs);
            members.extend(track.points.iter().map(|p| at_obs.apply(p)));
            owner.extend(std::iter::repeat_n(n, track.points.len()));
            let back = at_obs.inverse();
            motions.push(u_times.iter().map(|&u| pose_at(&track.motions, u).compose(&back)).collect());
        }
        let tree = KdTree::new(&members);
        let max_d2 = TRACK_MEMBER_RADIUS_M * TRACK_MEMBER_RADIUS_M;
        for (i, p) in points.iter().enumerate() {
            let Some(hit) = tree.nearest(p) else { continue };
            if hit.dist2 > max_d2 {
                continue;
            }
            let motion = &motions[owner[hit.index]];
            for (j, m) in motion.iter().enumerate() {
                out[i * u_times.len() + j] = m.apply(p);
            }
        }
    }

    /// Overwrites the still answers (fit coordinates) of query points nearest to one of the
    /// network's free points of the frame nearest `u_obs` (within [`TRACK_MEMBER_RADIUS_M`]) with
    /// the network's answer.
    fn apply_free_points(&self, points: &[Point], u_obs: f64, u_times: &[f64], out: &mut [Point]) {
        let Some(labelled) = self.free_points.get(u_obs.round() as usize) else { return };
        if !labelled.iter().any(|(_, free)| *free) {
            return;
        }
        let positions: Vec<Point> = labelled.iter().map(|(p, _)| *p).collect();
        let tree = KdTree::new(&positions);
        let max_d2 = TRACK_MEMBER_RADIUS_M * TRACK_MEMBER_RADIUS_M;
        let chosen: Vec<usize> = (0..points.len())
            .filter(|&i| tree.nearest(&points[i]).is_some_and(|h| h.dist2 <= max_d2 && labelled[h.index].1))
            .collect();
        if chosen.is_empty() {
            return;
        }
        let query: Vec<Point> = chosen.iter().map(|&i| points[i]).collect();
        let answers = self.network_positions(&query, u_obs, u_times);
        for (n, &i) in chosen.iter().enumerate() {
            out[i * u_times.len()..][..u_times.len()].copy_from_slice(&answers[n * u_times.len()..][..u_times.len()]);
        }
    }

    /// Overwrites the answers (fit coordinates) of query points that lie on a moving body at
    /// `u_obs` with the body's motion from `u_obs` to each queried time.
    fn apply_bodies(&self, points: &[Point], u_obs: f64, u_times: &[f64], out: &mut [Point]) {
        if self.bodies.is_empty() {
            return;
        }
        let owners = self.body_members(points, u_obs);
        for (n, body) in self.bodies.iter().enumerate() {
            let back = pose_at(&body.poses, u_obs).inverse();
            let motions: Vec<Rigid> = u_times.iter().map(|&u| pose_at(&body.poses, u).compose(&back)).collect();
            for (i, p) in points.iter().enumerate().filter(|&(i, _)| owners[i] == Some(n)) {
                for (j, m) in motions.iter().enumerate() {
                    out[i * u_times.len() + j] = m.apply(p);
                }
            }
        }
    }

    /// Per point (fit coordinates, observed at fractional frame `u_obs`): the index of the body
    /// it lies on, if any: within [`TRACK_MEMBER_RADIUS_M`] of the body's member points of the
    /// frames around `u_obs`, moved to `u_obs` along the body.
    pub(crate) fn body_members(&self, points: &[Point], u_obs: f64) -> Vec<Option<usize>> {
        let last = self.time_axis.frames() - 1;
        let below = (u_obs.floor() as usize).min(last);
        let above = (u_obs.ceil() as usize).min(last);
        let mut members = Vec::new();
        let mut owner = Vec::new();
        for (n, body) in self.bodies.iter().enumerate() {
            let at_obs = pose_at(&body.poses, u_obs);
            for frame in if below == above { vec![below] } else { vec![below, above] } {
                let to_obs = at_obs.compose(&body.poses[frame].inverse());
                members.extend(body.members[frame].iter().map(|p| to_obs.apply(p)));
                owner.extend(std::iter::repeat_n(n, body.members[frame].len()));
            }
        }
        if members.is_empty() {
            return vec![None; points.len()];
        }
        let tree = KdTree::new(&members);
        let max_d2 = TRACK_MEMBER_RADIUS_M * TRACK_MEMBER_RADIUS_M;
        points.iter().map(|p| tree.nearest(p).filter(|h| h.dist2 <= max_d2).map(|h| owner[h.index])).collect()
    }

    /// Per frame k, the moving body (its [`MovingBody::id`]) each of `frames[k]`'s points (sensor
    /// coordinates of sweep k) lies on, -1 for none: the `object_id` of the labels.
    pub fn object_ids(&self, frames: &[Vec<Point>]) -> Vec<Vec<i32>> {
        frames
            .iter()
            .enumerate()
            .map(|(k, points)| {
                if self.bodies.is_empty() || k >= self.time_axis.frames() {
                    return vec![-1; points.len()];
                }
                let in_fit: Vec<Point> = match &self.frame_poses {
                    Some(poses) => points.iter().map(|p| poses[k].apply(p)).collect(),
                    None => points.clone(),
                };
                self.body_members(&in_fit, k as f64)
                    .into_iter()
                    .map(|owner| owner.map_or(-1, |n| self.bodies[n].id as i32))
                    .collect()
            })
            .collect()
    }

    /// Scene flow of every frame's points to the next frame: entry k has one vector (m) per
    /// point of `frames[k]`, for k in 0..T-1.
    pub fn scene_flow(&self, frames: &[Vec<Point>]) -> Vec<Vec<Point>> {
        let t = self.time_axis.frames();
        (0..t.saturating_sub(1))
            .map(|k| {
                let from = self.time_axis.frame_time(k);
                let to = self.time_axis.frame_time(k + 1);
                let moved = self.positions(&frames[k], from, &[to]).expect("frame times are in range");
                frames[k].iter().zip(&moved).map(|(p, q)| [q[0] - p[0], q[1] - p[1], q[2] - p[2]]).collect()
            })
            .collect()
    }

    /// Serialises the model: magic and version, a JSON header, then each network's own
    /// versioned binary encoding behind a length prefix.
    pub fn to_bytes(&self) -> Vec<u8> {
        let (kind, networks): (&str, Vec<&Mlp<f32>>) = match &self.motion {
            Motion::Trajectory(mlp) => ("trajectory", vec![mlp]),
            Motion::PairFlows { forward, backward } => ("pair_flows", forward.iter().chain(backward).collect()),
        };
        let header = Header {
            method: self.method,
            time_axis: self.time_axis.clone(),
            report: self.report.clone(),
            kind: kind.to_string(),
            networks: networks.len(),
            frame_poses: self.frame_poses.clone(),
            tracks: self.tracks.clone(),
            bodies: self.bodies.clone(),
            still_world: self.still_world,
            free_points: self.free_points.clone(),
        };
        let header = serde_json::to_vec(&header).expect("a header always serialises");
        let mut out = MODEL_MAGIC.to_vec();
        out.extend((header.len() as u64).to_le_bytes());
        out.extend(header);
        for net in networks {
            let bytes = net.to_bytes();
            out.extend((bytes.len() as u64).to_le_bytes());
            out.extend(bytes);
        }
        out
    }

    /// Reads a model written by [`FittedModel::to_bytes`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        let mut rest = bytes.strip_prefix(MODEL_MAGIC).ok_or("not an mbnt model file (bad magic or version)")?;
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
        let header: Header =
            serde_json::from_slice(take("the header")?).map_err(|e| format!("corrupt model header: {e}"))?;
        let mut networks = Vec::with_capacity(header.networks.min(1024));
        for i in 0..header.networks {
            let body = take("a network")?;
            networks.push(Mlp::<f32>::from_bytes(body).map_err(|e| format!("corrupt network {i}: {e}"))?);
        }
        let frames = header.time_axis.frames();
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
        Ok(Self {
            method: header.method,
            time_axis: header.time_axis,
            report: header.report,
            motion,
            frame_poses: header.frame_poses,
            tracks: header.tracks,
            bodies: header.bodies,
            still_world: header.still_world,
            free_points: header.free_points,
        })
    }
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
}

/// Trajectory position at fractional frame index `u` from one point's velocity row: the
/// running sum of the velocities, linear within a step.
fn trajectory_at(row: &[f32], u: f64) -> [f64; 3] {
    let steps = row.len() / 3;
    let whole = (u.floor() as usize).min(steps);
    let frac = u - whole as f64;
    let mut d = [0f64; 3];
    for k in 0..whole {
        for c in 0..3 {
            d[c] += f64::from(row[3 * k + c]);
        }
    }
    if whole < steps && frac > 0.0 {
        for c in 0..3 {
            d[c] += frac * f64::from(row[3 * whole + c]);
        }
    }
    d
}

fn trajectory_positions(
    mlp: &Mlp<f32>,
    frames: usize,
    points: &[Point],
    u_obs: f64,
    u_times: &[f64],
    out: &mut [Point],
) {
    let mut input = Vec::new();
    let mut workspace = Workspace::default();
    encode_points(points, u_obs, frames, &mut input);
    let velocities = mlp.forward(&input, points.len(), &mut workspace);
    let width = 3 * (frames - 1);
    for (i, p) in points.iter().enumerate() {
        let row = &velocities[i * width..][..width];
        let anchor = trajectory_at(row, u_obs);
        for (j, &u) in u_times.iter().enumerate() {
            let at = trajectory_at(row, u);
            out[i * u_times.len() + j] = std::array::from_fn(|c| (f64::from(p[c]) + at[c] - anchor[c]) as f32);
        }
    }
}

/// Forward/backward Euler through pair flows. Within a step, motion is linear: a point at
/// fractional index k + a moves by the fraction of f_k (forward) or g_k (backward) it has left.
fn euler_positions(
    forward: &[Mlp<f32>],
    backward: &[Mlp<f32>],
    points: &[Point],
    u_obs: f64,
    u_times: &[f64],
    out: &mut [Point],
) {
    let n_times = u_times.len();
    let mut workspace = Workspace::default();
    // f or g of `current` scaled by `fraction`, added with `sign`.
    let mut step = |net: &Mlp<f32>, current: &mut Vec<Point>, fraction: f64, sign: f32| {
        let flow = net.forward(current.as_flattened(), current.len(), &mut workspace);
        for (p, v) in current.iter_mut().zip(flow.chunks_exact(3)) {
            for c in 0..3 {
                p[c] += sign * fraction as f32 * v[c];
            }
        }
    };
    let steps = forward.len();
    // One sweep forward through the later times (ascending) and one backward through the
    // earlier ones (descending), so each crossed step is evaluated once.
    let mut later: Vec<usize> = (0..n_times).filter(|&j| u_times[j] >= u_obs).collect();
    let mut earlier: Vec<usize> = (0..n_times).filter(|&j| u_times[j] < u_obs).collect();
    later.sort_by(|&a, &b| u_times[a].total_cmp(&u_times[b]));
    earlier.sort_by(|&a, &b| u_times[b].total_cmp(&u_times[a]));
    for (order, forward_in_time) in [(later, true), (earlier, false)] {
        let mut current = points.to_vec();
        let mut at = u_obs;
        for j in order {
            let u = u_times[j];
            if forward_in_time {
                while u - at > 1e-9 {
                    let k = (at.floor() as usize).min(steps - 1);
                    let next = ((k + 1) as f64).min(u);
                    step(&forward[k], &mut current, next - at, 1.0);
                    at = next;
                }
            } else {
                while at - u > 1e-9 {
                    let k = ((at.ceil() as usize).max(1) - 1).min(steps - 1);
                    let prev = (k as f64).max(u);
                    step(&backward[k], &mut current, at - prev, -1.0);
                    at = prev;
                }
            }
            for (i, p) in current.iter().enumerate() {
                out[i * n_times + j] = *p;
            }
        }
    }
}

/// The sensor-to-fit-frame transform at fractional frame index `u`: between two frames the
/// rotation turns at a constant rate about one axis (slerp) and the translation moves linearly.
fn pose_at(poses: &[Rigid], u: f64) -> Rigid {
    let k = (u.max(0.0).floor() as usize).min(poses.len() - 1);
    let a = u - k as f64;
    if k + 1 >= poses.len() || a <= 0.0 {
        return poses[k];
    }
    let (p, q) = (poses[k].to_isometry(), poses[k + 1].to_isometry());
    // try_slerp declines only for two rotations equal to rounding (no arc to follow), where
    // either is the answer; the shorter arc is taken otherwise, as a turn between frames is.
    let rotation = p.rotation.try_slerp(&q.rotation, a, f64::EPSILON).unwrap_or(p.rotation);
    Isometry3::from_parts(p.translation.vector.lerp(&q.translation.vector, a).into(), rotation).into()
}

/// File magic and format version of serialised models.
const MODEL_MAGIC: &[u8] = b"MBNTMDL1";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_interpolate_by_constant_turn_rate_and_linear_translation() {
        let yaw = |a: f64| Rigid {
            rotation: [[a.cos(), -a.sin(), 0.0], [a.sin(), a.cos(), 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
        };
        let mut end = yaw(std::f64::consts::FRAC_PI_2);
        end.translation = [2.0, 4.0, -2.0];
        let poses = [Rigid::identity(), end];
        let mid = pose_at(&poses, 0.5);
        let expected = yaw(std::f64::consts::FRAC_PI_4);
        for i in 0..3 {
            for j in 0..3 {
                assert!((mid.rotation[i][j] - expected.rotation[i][j]).abs() < 1e-12, "{mid:?}");
            }
        }
        assert_eq!(mid.translation, [1.0, 2.0, -1.0]);
        assert_eq!(pose_at(&poses, 1.0), end);
        assert_eq!(pose_at(&poses, 0.0), Rigid::identity());
    }

    #[test]
    fn points_on_a_rigid_track_follow_it_at_any_time_and_the_others_the_network() {
        use rand::SeedableRng;
        let frames = 4;
        let mut mlp = Mlp::<f32>::new(
            &[crate::fit::encoding::input_width(frames), 8, 3 * (frames - 1)],
            &mut rand_chacha::ChaCha8Rng::seed_from_u64(1),
        );
        mlp.zero_output_layer(); // the network: nothing moves
        let axis = TimeAxis::new(None, frames);
        let model = FittedModel::trajectory(Method::Mbnt, axis, FitReport::default(), mlp, None);
        // A track found in frame 1: the body drives 1 m per frame along x.
        let shift = |j: usize| Rigid { translation: [j as f64 - 1.0, 0.0, 0.0], ..Rigid::identity() };
        let body: Vec<Point> = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let track = RigidTrack { frame: 1, points: body.clone(), motions: (0..frames).map(shift).collect() };
        let short = RigidTrack { frame: 1, points: body.clone(), motions: vec![Rigid::identity(); 2] };
        let model = model.with_tracks(vec![track, short]);
        assert_eq!(model.tracks().len(), 1, "a track that does not cover every frame is dropped");
        assert_eq!(model.report().rigid_tracks, 1);
        // Observed at time 1.5 the body has moved half a metre on from frame 1; a point 5 m away
        // is static.
        let queries = [[0.5, 0.1, 0.0], [5.5, 5.0, 0.0]];
        let at = model.positions(&queries, 1.5, &[0.0, 1.5, 3.0]).unwrap();
        let expected =
            [[-1.0, 0.1, 0.0], [0.5, 0.1, 0.0], [2.0, 0.1, 0.0], [5.5, 5.0, 0.0], [5.5, 5.0, 0.0], [5.5, 5.0, 0.0]];
        for (got, want) in at.iter().zip(&expected) {
            assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-5), "{at:?}");
        }
        let alone = model.without_tracks().positions(&queries, 1.5, &[3.0]).unwrap();
        assert_eq!(alone[0], queries[0], "without tracks the network answers");
    }

    /// A 4-frame scene model with identity poses: a network that moves everything 1 m per frame
    /// along y, a body driving 1 m per frame along x (3 member points per frame), and one free
    /// point at (20, 0, 0) with a still neighbour at (20.5, 0, 0) in every frame.
    fn scene_model() -> FittedModel {
        use rand::SeedableRng;
        let frames = 4;
        let mut mlp = Mlp::<f32>::new(
            &[crate::fit::encoding::input_width(frames), 8, 3 * (frames - 1)],
            &mut rand_chacha::ChaCha8Rng::seed_from_u64(1),
        );
        mlp.zero_output_layer();
        let params = mlp.parameters_mut();
        let bias_start = params.len() - 3 * (frames - 1);
        for (i, b) in params[bias_start..].iter_mut().enumerate() {
            *b = if i % 3 == 1 { 1.0 } else { 0.0 }; // velocity (0, 1, 0) m per frame
        }
        let axis = TimeAxis::new(None, frames);
        let model = FittedModel::trajectory(
            Method::Mbnt,
            axis,
            FitReport::default(),
            mlp,
            Some(vec![Rigid::identity(); frames]),
        );
        let shift = |j: usize| Rigid { translation: [j as f64, 0.0, 0.0], ..Rigid::identity() };
        let body = MovingBody {
            id: 0,
            poses: (0..frames).map(shift).collect(),
            observed: vec![true; frames],
            members: (0..frames)
                .map(|j| {
                    let x = j as f32;
                    vec![[x, 0.0, 0.0], [x + 1.0, 0.0, 0.0], [x, 1.0, 0.0]]
                })
                .collect(),
            member_counts: vec![3; frames],
            extent_min_m: [-0.5, -0.5, 0.0],
            extent_max_m: [0.5, 0.5, 0.0],
        };
        model
            .with_bodies(vec![body])
            .with_free_points(vec![vec![([20.0, 0.0, 0.0], true), ([20.5, 0.0, 0.0], false)]; frames])
    }

    #[test]
    fn a_scene_model_answers_from_bodies_free_points_and_the_still_world() {
        let model = scene_model();
        assert_eq!(model.report().moving_bodies, 1);
        assert_eq!(model.report().free_points, 4);
        let queries = [[1.2, 0.1, 0.0], [20.1, 0.0, 0.0], [20.55, 0.0, 0.0], [50.0, 50.0, 0.0]];
        let expected = [
            [3.2, 0.1, 0.0],   // on the body: 2 m along x from t = 1 to t = 3
            [20.1, 2.0, 0.0],  // nearest a free point: the network, 2 m along y
            [20.55, 0.0, 0.0], // nearest the still neighbour: still
            [50.0, 50.0, 0.0], // nothing near: the still world
        ];
        let check = |model: &FittedModel, expected: &[[f32; 3]]| {
            let at = model.positions(&queries, 1.0, &[3.0]).unwrap();
            for (got, want) in at.iter().zip(expected) {
                assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-5), "{at:?}");
            }
        };
        check(&model, &expected);
        // The labels' object ids: frame 2's points on the body (x = 2..3) are object 0.
        let ids = model.object_ids(&[vec![], vec![], vec![[2.2, 0.0, 0.0], [20.0, 0.0, 0.0]], vec![]]);
        assert_eq!(ids[2], vec![0, -1]);
        // The same answers after a round trip through the file format.
        let back = FittedModel::from_bytes(&model.to_bytes()).unwrap();
        check(&back, &expected);
        assert_eq!(back.bodies(), model.bodies());
        // The network alone moves everything along y.
        let alone = model.without_tracks().positions(&queries[3..], 1.0, &[3.0]).unwrap();
        assert_eq!(alone[0], [50.0, 52.0, 0.0]);
    }

    #[test]
    fn a_model_file_from_before_the_scene_model_still_loads() {
        // The previous version's header has no bodies, still world or free points.
        let model = scene_model();
        let bytes = model.to_bytes();
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

    #[test]
    fn timestamps_map_piecewise_linearly_to_frame_indices() {
        let axis = TimeAxis::new(Some(vec![10.0, 10.1, 10.3]), 3);
        assert!((axis.to_frame_index(10.05).unwrap() - 0.5).abs() < 1e-9);
        assert!((axis.to_frame_index(10.2).unwrap() - 1.5).abs() < 1e-9);
        assert_eq!(axis.to_frame_index(10.3).unwrap(), 2.0);
        assert!(axis.to_frame_index(10.31).is_err());
        assert!(axis.to_frame_index(f64::NAN).is_err());
    }
}
