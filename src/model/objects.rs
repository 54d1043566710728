//! The moving things of a scene model, as the model keeps them: moving bodies and rigid tracks
//! (the fit finds them: `fit::bodies`, `fit::tracks`).

use serde::{Deserialize, Serialize};

use crate::geometry::Point;
use crate::geometry::rigid::Rigid;

/// One moving object over the whole sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MovingBody {
    /// Identity of the body within its sequence (0, 1, ... in the order found).
    pub id: u32,
    /// Per frame: the body-to-fit-coordinates motion (the body frame has its origin at the centre
    /// of the body's points and its x axis along its direction of travel, z up).
    pub poses: Vec<Rigid>,
    /// Per frame: whether the body was seen (clusters associated) or its pose predicted.
    pub observed: Vec<bool>,
    /// Per frame: the body's points (fit coordinates), thinned to one per
    /// `fit::bodies::BodyParams::member_voxel_m` cube; empty where it was not seen, and in every
    /// frame of the objects of a model stitched from windows (the windows' own bodies hold the
    /// members that queries and labels use).
    pub members: Vec<Vec<Point>>,
    /// Per frame: the number of the frame's fitted points on the body (before thinning).
    pub member_counts: Vec<usize>,
    /// The box holding the body's model points, in body coordinates: lower corner (m).
    pub extent_min_m: [f32; 3],
    /// Upper corner (m).
    pub extent_max_m: [f32; 3],
}

impl MovingBody {
    /// Whether the body belongs to a sequence of `frames` frames.
    pub fn fits(&self, frames: usize) -> bool {
        self.poses.len() == frames
            && self.observed.len() == frames
            && self.members.len() == frames
            && self.member_counts.len() == frames
    }

    /// The frames the body was seen in.
    pub fn frames_seen(&self) -> Vec<usize> {
        (0..self.observed.len()).filter(|&k| self.observed[k]).collect()
    }
}

/// One moving cluster of one frame and its rigid motion to every frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigidTrack {
    /// The frame the cluster was found in.
    pub frame: usize,
    /// The cluster's points (fit coordinates): queries near them follow this track.
    pub points: Vec<Point>,
    /// Motion (fit coordinates) from frame `frame` to frame j, for every j; identity at `frame`.
    pub motions: Vec<Rigid>,
}

impl RigidTrack {
    /// Whether the track belongs to a sequence of `frames` frames: found in one of them, with a
    /// motion to each.
    pub fn fits(&self, frames: usize) -> bool {
        self.frame < frames && self.motions.len() == frames
    }
}
