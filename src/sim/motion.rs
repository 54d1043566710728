//! Rigid motions of bodies on the ground plane: planar poses, paths made of straight and
//! circular segments (closed form, so a pose is an exact function of time), and 4 x 4 helpers.

/// A planar pose: position (m) and heading (rad, counter-clockwise from +x).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Pose2 {
    pub x: f64,
    pub y: f64,
    pub yaw: f64,
}

impl Pose2 {
    /// Unit vector of the heading.
    pub fn dir(&self) -> [f64; 2] {
        [self.yaw.cos(), self.yaw.sin()]
    }

    /// This pose moved by `along` metres forward and `left` metres to the left, same heading.
    pub fn offset(&self, along: f64, left: f64) -> Pose2 {
        let [dx, dy] = self.dir();
        Pose2 { x: self.x + along * dx - left * dy, y: self.y + along * dy + left * dx, yaw: self.yaw }
    }

    /// Row-major 4 x 4 body-to-world matrix, the body origin lifted to height `z`.
    pub fn matrix(&self, z: f64) -> [f64; 16] {
        let (s, c) = self.yaw.sin_cos();
        [c, -s, 0.0, self.x, s, c, 0.0, self.y, 0.0, 0.0, 1.0, z, 0.0, 0.0, 0.0, 1.0]
    }
}

/// sin(x) / x, accurate near 0.
fn sinc(x: f64) -> f64 {
    if x.abs() < 1e-4 { 1.0 - x * x / 6.0 } else { x.sin() / x }
}

/// Moves `p` by arc length `ds` (may be negative) along a curve of constant curvature.
///
/// The chord of an arc of length ds has length ds * sinc(k ds / 2) and points along the mean
/// heading; this form is exact for arcs and degrades gracefully to a straight line as k -> 0.
fn advance(p: Pose2, curvature_per_m: f64, ds: f64) -> Pose2 {
    let half = 0.5 * curvature_per_m * ds;
    let chord = ds * sinc(half);
    let mid = p.yaw + half;
    Pose2 { x: p.x + chord * mid.cos(), y: p.y + chord * mid.sin(), yaw: p.yaw + 2.0 * half }
}

/// One piece of a path: `length_m` of constant curvature (0 = straight).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Segment {
    pub length_m: f64,
    pub curvature_per_m: f64,
}

/// A planar path parameterised by arc length u. Before u = 0 the first segment is continued
/// backwards, after its end the last segment is continued forwards, so every u is valid.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Path {
    segments: Vec<Segment>,
    /// Pose at the start of each segment.
    starts: Vec<Pose2>,
}

impl Path {
    /// A path from `start` through `segments` (at least one).
    pub fn new(start: Pose2, segments: Vec<Segment>) -> Path {
        assert!(!segments.is_empty(), "a path needs a segment");
        let mut starts = Vec::with_capacity(segments.len());
        let mut p = start;
        for seg in &segments {
            starts.push(p);
            p = advance(p, seg.curvature_per_m, seg.length_m);
        }
        Path { segments, starts }
    }

    /// Pose at arc length `u_m`.
    pub fn eval(&self, u_m: f64) -> Pose2 {
        if u_m <= 0.0 {
            return advance(self.starts[0], self.segments[0].curvature_per_m, u_m);
        }
        let mut seg_start = 0.0;
        let last = self.segments.len() - 1;
        for (i, seg) in self.segments.iter().enumerate() {
            if u_m <= seg_start + seg.length_m || i == last {
                return advance(self.starts[i], seg.curvature_per_m, u_m - seg_start);
            }
            seg_start += seg.length_m;
        }
        unreachable!("the loop returns at the last segment")
    }

    /// The parallel path `left_m` to the left. Valid while `1 - curvature * left_m > 0` on every
    /// segment (the offset stays on this side of each centre of curvature); arc length u on the
    /// offset path maps to the same segment boundaries.
    pub fn offset(&self, left_m: f64) -> Path {
        let segments = self
            .segments
            .iter()
            .map(|s| {
                let f = 1.0 - s.curvature_per_m * left_m;
                Segment { length_m: s.length_m * f, curvature_per_m: s.curvature_per_m / f }
            })
            .collect();
        Path::new(self.starts[0].offset(0.0, left_m), segments)
    }
}

/// How a body moves: not at all, or along a path at constant speed.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Motion {
    /// A fixed pose.
    Static(Pose2),
    /// At time t the body is at `path.eval(u0_m + speed_mps * t)`, its heading turned by
    /// `yaw_offset_rad` (pi for a body driving the path backwards).
    Path { path: Path, u0_m: f64, speed_mps: f64, yaw_offset_rad: f64 },
}

impl Motion {
    /// Body pose at time `t_s`.
    pub fn pose_at(&self, t_s: f64) -> Pose2 {
        match self {
            Motion::Static(p) => *p,
            Motion::Path { path, u0_m, speed_mps, yaw_offset_rad } => {
                let mut p = path.eval(u0_m + speed_mps * t_s);
                p.yaw += yaw_offset_rad;
                p
            }
        }
    }

    /// Whether the body moves in the world.
    pub fn is_dynamic(&self) -> bool {
        matches!(self, Motion::Path { speed_mps, .. } if *speed_mps != 0.0)
    }
}

/// Product of two row-major 4 x 4 matrices.
pub(crate) fn mat_mul(a: &[f64; 16], b: &[f64; 16]) -> [f64; 16] {
    let mut out = [0.0; 16];
    for r in 0..4 {
        for c in 0..4 {
            out[r * 4 + c] = (0..4).map(|k| a[r * 4 + k] * b[k * 4 + c]).sum();
        }
    }
    out
}

/// Inverse of a rigid row-major 4 x 4 transform [R t; 0 1]: [R^T -R^T t; 0 1].
pub(crate) fn rigid_inverse(m: &[f64; 16]) -> [f64; 16] {
    let mut out = [0.0; 16];
    for r in 0..3 {
        for c in 0..3 {
            out[r * 4 + c] = m[c * 4 + r];
        }
        out[r * 4 + 3] = -(0..3).map(|k| m[k * 4 + r] * m[k * 4 + 3]).sum::<f64>();
    }
    out[15] = 1.0;
    out
}

/// Applies a row-major 4 x 4 rigid transform to a point.
pub(crate) fn apply(m: &[f64; 16], p: [f64; 3]) -> [f64; 3] {
    let row = |r: usize| m[r * 4] * p[0] + m[r * 4 + 1] * p[1] + m[r * 4 + 2] * p[2] + m[r * 4 + 3];
    [row(0), row(1), row(2)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_arc_path_stays_on_its_circle_and_its_offset_is_parallel() {
        let k = 1.0 / 20.0;
        let path = Path::new(Pose2 { x: 0.0, y: 0.0, yaw: 0.0 }, vec![Segment { length_m: 100.0, curvature_per_m: k }]);
        for i in 0..50 {
            let u = i as f64 * 2.0 - 10.0;
            let p = path.eval(u);
            // Centre of curvature at (0, 20).
            assert!((p.x.hypot(p.y - 20.0) - 20.0).abs() < 1e-9, "u {u}");
            assert!((p.yaw - k * u).abs() < 1e-12);
            let q = path.offset(3.0).eval(u * (1.0 - 3.0 * k));
            assert!((q.x.hypot(q.y - 20.0) - 17.0).abs() < 1e-9);
            assert!((q.yaw - p.yaw).abs() < 1e-12);
        }
    }

    #[test]
    fn a_path_is_continuous_across_segment_joints() {
        let path = Path::new(
            Pose2 { x: 1.0, y: 2.0, yaw: 0.3 },
            vec![
                Segment { length_m: 5.0, curvature_per_m: 0.0 },
                Segment { length_m: 7.0, curvature_per_m: -0.2 },
                Segment { length_m: 5.0, curvature_per_m: 0.0 },
            ],
        );
        for joint in [5.0, 12.0] {
            let a = path.eval(joint - 1e-7);
            let b = path.eval(joint + 1e-7);
            assert!((a.x - b.x).abs() < 1e-6 && (a.y - b.y).abs() < 1e-6 && (a.yaw - b.yaw).abs() < 1e-6);
        }
        // Straight first segment: 5 m along heading 0.3.
        let p = path.eval(5.0);
        assert!((p.x - (1.0 + 5.0 * 0.3f64.cos())).abs() < 1e-12);
        assert!((path.eval(12.0).yaw - (0.3 - 1.4)).abs() < 1e-12);
    }

    #[test]
    fn rigid_inverse_undoes_the_transform() {
        let m = Pose2 { x: 3.0, y: -4.0, yaw: 1.1 }.matrix(1.8);
        let id = mat_mul(&m, &rigid_inverse(&m));
        for (i, v) in id.iter().enumerate() {
            let want = if i % 5 == 0 { 1.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-12);
        }
        let p = [1.0, 2.0, 3.0];
        let q = apply(&rigid_inverse(&m), apply(&m, p));
        assert!(p.iter().zip(q).all(|(a, b)| (a - b).abs() < 1e-12));
    }
}
