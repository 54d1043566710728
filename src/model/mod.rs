//! A fitted motion model answers where a point is at any time of its sequence.
//!
//! Times are in the sequence's own axis: its timestamps in seconds when it has them, frame
//! indices 0..T-1 otherwise. Positions at time s are in the sensor frame of the sweep at s.
//!
//! # Layout
//! - this module: [`FittedModel`] and its queries (the network, the still world, moving bodies
//!   and rigid tracks);
//! - `time`: [`TimeAxis`] and [`QueryError`]; `poses`: pose interpolation between frames;
//!   `networks`: evaluating the fitted networks (velocity sums, Euler through pair flows);
//! - `format`: the versioned model file ([`FittedModel::to_bytes`], [`FittedModel::from_bytes`]);
//!   `check`: the finiteness check a model passes before it is saved ([`NonFiniteModel`]);
//! - `objects`: [`MovingBody`] and [`RigidTrack`]; `report`: [`FitReport`] and its parts;
//! - [`params`]: the hyper-parameters a model is fitted with (its report records them);
//! - [`encoding`]: the networks' input encoding;
//! - `windows`: a log fitted as overlapping windows, stitched into one model.
//!
//! The model owns every type a model file holds. `fit` builds models and imports from here; this
//! module imports nothing from `fit`, so the two do not depend on each other in a cycle.

mod check;
pub mod encoding;
mod format;
mod networks;
mod objects;
pub mod params;
mod poses;
mod report;
mod time;
mod windows;

pub use check::NonFiniteModel;
pub use objects::{MovingBody, RigidTrack};
pub use report::{FitReport, FrameReport, LossCurve, LossRecord, LossTerms, PhaseTimes};
pub use time::{MAX_EXTRAPOLATION_S, QueryError, TimeAxis};
pub use windows::LinkShare;
pub(crate) use windows::unlinked_bodies;

use crate::geometry::Point;
use crate::geometry::knn::KdTree;
use crate::geometry::rigid::Rigid;
use crate::nn::Mlp;
use networks::{Motion, euler_positions, trajectory_positions};
use params::Method;
use poses::pose_at;

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

/// The fit keeps no point within this height (m) of the local ground (the default ground
/// tolerance), so a body's lowest part (wheels, bumpers, sills) has no member point: a query
/// point that lies within [`TRACK_MEMBER_RADIUS_M`] of a body's members once raised by this much
/// is on the body too. On the real pair of docs/benchmarks.md this brings the cars' lowest 0.3 m
/// (156 of 3,568 moving points, held still before) onto their bodies.
const BODY_UNDERSIDE_M: f32 = crate::geometry::ground::GROUND_TOLERANCE_M;

/// Query points are evaluated in chunks of this many, bounding memory for large queries.
const QUERY_CHUNK: usize = 16_384;

/// What a stitched model's window decided about a query point it hands over to the next window
/// ([`FittedModel::positions_carried`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Carry {
    /// On this body of the receiving window (the giving window's body of the same object).
    Body(usize),
    /// Still world where it was observed: it stays still, as a still point of a model of one fit
    /// does at every time. (Decided again, a still point lying within reach of a body that passes
    /// it at the hand-over frame would leave with that body.)
    Still,
    /// Nothing carried: the receiving window decides (the network's free points, and points on
    /// a body whose object the receiving window lacks).
    Open,
}

impl FittedModel {
    /// A model from a fitted trajectory network.
    pub(crate) fn trajectory(
        method: Method,
        time_axis: TimeAxis,
        report: FitReport,
        mlp: Mlp<f32>,
        frame_poses: Option<Vec<Rigid>>,
    ) -> Self {
        Self::fitted(method, time_axis, report, Motion::Trajectory(mlp), frame_poses)
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
        Self::fitted(method, time_axis, report, Motion::PairFlows { forward, backward }, frame_poses)
    }

    /// A network-only model: no tracks, bodies or free points yet.
    fn fitted(
        method: Method,
        time_axis: TimeAxis,
        report: FitReport,
        motion: Motion,
        frame_poses: Option<Vec<Rigid>>,
    ) -> Self {
        Self {
            method,
            time_axis,
            report,
            motion,
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
                // A stitched model has no network of its own: `positions` asks its windows
                // before the network is reached, and the fit's free-point test runs on the
                // windows' own models. Nothing moves is the answer of no network.
                Motion::Windows(_) => {
                    for (p, row) in chunk.iter().zip(out_chunk.chunks_mut(u_times.len())) {
                        row.fill(*p);
                    }
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
    /// no still world. Decodes every window of a stitched model read from a file; fails if one
    /// cannot be read.
    pub fn without_tracks(&self) -> Result<Self, QueryError> {
        let motion = match &self.motion {
            // A stitched model: each window's network alone.
            Motion::Windows(_) => Motion::Windows(
                self.windows()?
                    .into_iter()
                    .map(|(start, model)| Ok(windows::Window::decoded(start, model.without_tracks()?, Vec::new())))
                    .collect::<Result<_, QueryError>>()?,
            ),
            motion => motion.clone(),
        };
        Ok(Self {
            method: self.method,
            time_axis: self.time_axis.clone(),
            report: self.report.clone(),
            motion,
            frame_poses: self.frame_poses.clone(),
            tracks: Vec::new(),
            bodies: Vec::new(),
            still_world: false,
            free_points: Vec::new(),
        })
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
        if let Motion::Windows(windows) = &self.motion {
            return windows::positions(self, windows, points, t_obs, times);
        }
        Ok(self.positions_carried(points, t_obs, times, None)?.0)
    }

    /// [`FittedModel::positions`] of a model of one fit (the points checked finite), where
    /// `carried[i]`, when given, is what a stitched model's previous window decided about point
    /// i ([`Carry`]): on a body, it follows that body whether or not it lies near the body's
    /// points of `t_obs`; still, it stays still. Also returns what this model decided about each
    /// point, to carry into the next window.
    pub(super) fn positions_carried(
        &self,
        points: &[Point],
        t_obs: f64,
        times: &[f64],
        carried: Option<&[Carry]>,
    ) -> Result<(Vec<Point>, Vec<Carry>), QueryError> {
        let u_obs = self.time_axis.to_frame_index(t_obs)?;
        let u_times = times.iter().map(|&t| self.time_axis.to_frame_index(t)).collect::<Result<Vec<_>, _>>()?;
        let mut out = vec![[0f32; 3]; points.len() * times.len()];
        if times.is_empty() {
            return Ok((out, vec![Carry::Open; points.len()]));
        }
        let kept_still: Vec<bool> = match carried {
            Some(carried) => carried.iter().map(|c| *c == Carry::Still).collect(),
            None => vec![false; points.len()],
        };
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
        let mut free = vec![false; points.len()];
        if self.still_world {
            // The still world: in the fit's (ego-motion-free) coordinates nothing moves; the
            // network answers its free points only.
            for (p, row) in points.iter().zip(out.chunks_mut(times.len())) {
                row.fill(*p);
            }
            free = self.apply_free_points(points, u_obs, &u_times, &mut out, &kept_still);
        } else {
            self.network_positions_into(points, u_obs, &u_times, &mut out);
        }
        self.apply_tracks(points, u_obs, &u_times, &mut out);
        let mut owners =
            if self.bodies.is_empty() { vec![None; points.len()] } else { self.body_members(points, u_obs) };
        if let Some(carried) = carried {
            for (owner, known) in owners.iter_mut().zip(carried) {
                *owner = match *known {
                    Carry::Body(n) if n < self.bodies.len() => Some(n),
                    Carry::Still => None,
                    _ => *owner,
                };
            }
        }
        self.apply_bodies(points, &owners, u_obs, &u_times, &mut out);
        if let Some(poses) = &self.frame_poses {
            let to_sensor: Vec<Rigid> = u_times.iter().map(|&u| pose_at(poses, u).inverse()).collect();
            for row in out.chunks_mut(times.len()) {
                for (p, back) in row.iter_mut().zip(&to_sensor) {
                    *p = back.apply(p);
                }
            }
        }
        let decided = owners
            .iter()
            .zip(&free)
            .map(|(owner, &free)| match owner {
                Some(n) => Carry::Body(*n),
                None if self.still_world && self.tracks.is_empty() && !free => Carry::Still,
                None => Carry::Open,
            })
            .collect();
        Ok((out, decided))
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
    /// the network's answer. Points marked in `skip` are left alone (still points a stitched model's previous window
    /// handed over). Returns which points the network answered.
    fn apply_free_points(
        &self,
        points: &[Point],
        u_obs: f64,
        u_times: &[f64],
        out: &mut [Point],
        skip: &[bool],
    ) -> Vec<bool> {
        let mut answered = vec![false; points.len()];
        let Some(labelled) = self.free_points.get(u_obs.round() as usize) else { return answered };
        if !labelled.iter().any(|(_, free)| *free) {
            return answered;
        }
        let positions: Vec<Point> = labelled.iter().map(|(p, _)| *p).collect();
        let tree = KdTree::new(&positions);
        let max_d2 = TRACK_MEMBER_RADIUS_M * TRACK_MEMBER_RADIUS_M;
        let chosen: Vec<usize> = (0..points.len())
            .filter(|&i| !skip[i] && tree.nearest(&points[i]).is_some_and(|h| h.dist2 <= max_d2 && labelled[h.index].1))
            .collect();
        if chosen.is_empty() {
            return answered;
        }
        let query: Vec<Point> = chosen.iter().map(|&i| points[i]).collect();
        let answers = self.network_positions(&query, u_obs, u_times);
        for (n, &i) in chosen.iter().enumerate() {
            out[i * u_times.len()..][..u_times.len()].copy_from_slice(&answers[n * u_times.len()..][..u_times.len()]);
            answered[i] = true;
        }
        answered
    }

    /// Overwrites the answers (fit coordinates) of query points that lie on a moving body at
    /// `u_obs` (`owners`: the body of each point, if any) with the body's motion from `u_obs` to
    /// each queried time.
    fn apply_bodies(&self, points: &[Point], owners: &[Option<usize>], u_obs: f64, u_times: &[f64], out: &mut [Point]) {
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
    /// frames around `u_obs`, moved to `u_obs` along the body, or so once raised by
    /// [`BODY_UNDERSIDE_M`] when the fit removed the ground.
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
        // Only a fit that removed the ground lacks the bodies' undersides (a model file without
        // its parameters is from a default fit, which removes it).
        let underside = self.report.params.as_ref().is_none_or(|p| p.remove_ground);
        points
            .iter()
            .map(|p| {
                let near = |q: &Point| tree.nearest(q).filter(|h| h.dist2 <= max_d2).map(|h| owner[h.index]);
                near(p).or_else(|| if underside { near(&[p[0], p[1], p[2] + BODY_UNDERSIDE_M]) } else { None })
            })
            .collect()
    }

    /// Per frame k, the moving body (its [`MovingBody::id`]) each of `frames[k]`'s points (sensor
    /// coordinates of sweep k) lies on, -1 for none: the `object_id` of the labels. Fails only
    /// for a stitched model whose window cannot be read ([`QueryError::CorruptWindow`]).
    pub fn object_ids(&self, frames: &[Vec<Point>]) -> Result<Vec<Vec<i32>>, QueryError> {
        frames.iter().enumerate().map(|(k, points)| self.frame_object_ids(k, points)).collect()
    }

    /// [`FittedModel::object_ids`] of frame `k`'s `points` (sensor coordinates of sweep k): a
    /// long log's labels are written one frame at a time.
    pub fn frame_object_ids(&self, k: usize, points: &[Point]) -> Result<Vec<i32>, QueryError> {
        if self.bodies.is_empty() || k >= self.time_axis.frames() {
            return Ok(vec![-1; points.len()]);
        }
        if let Motion::Windows(windows) = &self.motion {
            return windows::frame_object_ids(self, windows, k, points);
        }
        let in_fit: Vec<Point> = match &self.frame_poses {
            Some(poses) => points.iter().map(|p| poses[k].apply(p)).collect(),
            None => points.to_vec(),
        };
        Ok(self
            .body_members(&in_fit, k as f64)
            .into_iter()
            .map(|owner| owner.map_or(-1, |n| self.bodies[n].id as i32))
            .collect())
    }

    /// Scene flow of every frame's points to the next frame: entry k has one vector (m) per
    /// point of `frames[k]`, for k in 0..T-1. Fails only for a stitched model whose window
    /// cannot be read ([`QueryError::CorruptWindow`]) or for non-finite points.
    pub fn scene_flow(&self, frames: &[Vec<Point>]) -> Result<Vec<Vec<Point>>, QueryError> {
        let t = self.time_axis.frames();
        (0..t.saturating_sub(1)).map(|k| self.frame_scene_flow(k, &frames[k])).collect()
    }

    /// [`FittedModel::scene_flow`] of frame `k`'s `points` (`k + 1` a frame of the model): a long
    /// log's labels are written one frame at a time.
    /// Fails as [`FittedModel::scene_flow`] does.
    pub fn frame_scene_flow(&self, k: usize, points: &[Point]) -> Result<Vec<Point>, QueryError> {
        let from = self.time_axis.frame_time(k);
        let to = self.time_axis.frame_time(k + 1);
        let moved = self.positions(points, from, &[to])?;
        Ok(points.iter().zip(&moved).map(|(p, q)| [q[0] - p[0], q[1] - p[1], q[2] - p[2]]).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_on_a_rigid_track_follow_it_at_any_time_and_the_others_the_network() {
        use rand::SeedableRng;
        let frames = 4;
        let mut mlp = Mlp::<f32>::new(
            &[crate::model::encoding::input_width(frames), 8, 3 * (frames - 1)],
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
        let alone = model.without_tracks().unwrap().positions(&queries, 1.5, &[3.0]).unwrap();
        assert_eq!(alone[0], queries[0], "without tracks the network answers");
    }

    /// A 4-frame scene model with identity poses: a network that moves everything 1 m per frame
    /// along y, a body driving 1 m per frame along x (3 member points per frame), and one free
    /// point at (20, 0, 0) with a still neighbour at (20.5, 0, 0) in every frame.
    pub(super) fn scene_model() -> FittedModel {
        use rand::SeedableRng;
        let frames = 4;
        let mut mlp = Mlp::<f32>::new(
            &[crate::model::encoding::input_width(frames), 8, 3 * (frames - 1)],
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
        let ids = model.object_ids(&[vec![], vec![], vec![[2.2, 0.0, 0.0], [20.0, 0.0, 0.0]], vec![]]).unwrap();
        assert_eq!(ids[2], vec![0, -1]);
        // The same answers after a round trip through the file format.
        let back = FittedModel::from_bytes(&model.to_bytes().unwrap()).unwrap();
        check(&back, &expected);
        assert_eq!(back.bodies(), model.bodies());
        // The network alone moves everything along y.
        let alone = model.without_tracks().unwrap().positions(&queries[3..], 1.0, &[3.0]).unwrap();
        assert_eq!(alone[0], [50.0, 52.0, 0.0]);
    }

    #[test]
    fn a_point_under_a_body_where_the_ground_removal_left_no_member_follows_the_body() {
        let model = scene_model();
        // At t = 1 the body's members are (1, 0, 0), (2, 0, 0), (1, 1, 0).
        let queries = [
            [1.1, 0.1, -0.45], // 0.47 m below a member: on the body once raised by 0.3 m
            [1.1, 0.1, -0.8],  // 0.5 m under the body even raised: still
            [0.4, -0.3, -0.3], // beside the body (0.67 m across when raised): still
        ];
        let expected = [[3.1, 0.1, -0.45], [1.1, 0.1, -0.8], [0.4, -0.3, -0.3]];
        let at = model.positions(&queries, 1.0, &[3.0]).unwrap();
        for (got, want) in at.iter().zip(&expected) {
            assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-5), "{at:?}");
        }
        let ids = model.object_ids(&[vec![], queries.to_vec(), vec![], vec![]]).unwrap();
        assert_eq!(ids[1], vec![0, -1, -1]);
        // A fit that kept the ground has the bodies' undersides among their members: the point
        // 0.47 m below a member is the road there, and stays.
        let mut kept_ground = scene_model();
        let params = crate::model::params::FitParams { remove_ground: Some(false), ..Default::default() };
        kept_ground.report.params = Some(params.check(Method::Mbnt).unwrap());
        let ids = kept_ground.object_ids(&[vec![], queries.to_vec(), vec![], vec![]]).unwrap();
        assert_eq!(ids[1], vec![-1, -1, -1]);
    }
}
