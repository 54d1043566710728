//! Geometric primitives of the bodies (vertical boxes, vertical cylinders, spheres), placed in
//! the world at a body pose, with exact ray intersections and conservative footprint overlap
//! tests used to keep bodies apart.

use super::motion::Pose2;

/// A primitive in its body's frame (x forward, y left, z up from the ground).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Shape {
    /// Box aligned with the body axes: centre (cx, cy), half extents (hx, hy), heights z0..z1.
    Box { cx: f64, cy: f64, hx: f64, hy: f64, z0: f64, z1: f64 },
    /// Vertical cylinder: axis at (cx, cy), radius r, heights z0..z1.
    Cylinder { cx: f64, cy: f64, r: f64, z0: f64, z1: f64 },
    /// Sphere: centre (cx, cy, cz), radius r.
    Sphere { cx: f64, cy: f64, cz: f64, r: f64 },
}

/// A primitive placed in the world, tagged with the body (object id) it belongs to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct WorldPrim {
    pub geom: WorldGeom,
    /// Object id of the body.
    pub body: u32,
}

/// World geometry of a primitive. Boxes keep the cosine and sine of their yaw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum WorldGeom {
    Box { cx: f64, cy: f64, cos: f64, sin: f64, hx: f64, hy: f64, z0: f64, z1: f64 },
    Cylinder { cx: f64, cy: f64, r: f64, z0: f64, z1: f64 },
    Sphere { cx: f64, cy: f64, cz: f64, r: f64 },
}

/// Smallest ray parameter counted as a hit (m): rays start at the sensor, outside every body.
const T_MIN: f64 = 1e-9;

impl Shape {
    /// This primitive at body pose `pose`.
    pub fn place(&self, pose: &Pose2, body: u32) -> WorldPrim {
        let (sin, cos) = pose.yaw.sin_cos();
        let to_world = |x: f64, y: f64| (pose.x + cos * x - sin * y, pose.y + sin * x + cos * y);
        let geom = match *self {
            Shape::Box { cx, cy, hx, hy, z0, z1 } => {
                let (cx, cy) = to_world(cx, cy);
                WorldGeom::Box { cx, cy, cos, sin, hx, hy, z0, z1 }
            }
            Shape::Cylinder { cx, cy, r, z0, z1 } => {
                let (cx, cy) = to_world(cx, cy);
                WorldGeom::Cylinder { cx, cy, r, z0, z1 }
            }
            Shape::Sphere { cx, cy, cz, r } => {
                let (cx, cy) = to_world(cx, cy);
                WorldGeom::Sphere { cx, cy, cz, r }
            }
        };
        WorldPrim { geom, body }
    }

    /// Radius of a horizontal circle around the body origin that contains this primitive.
    pub fn reach_m(&self) -> f64 {
        match *self {
            Shape::Box { cx, cy, hx, hy, .. } => cx.hypot(cy) + hx.hypot(hy),
            Shape::Cylinder { cx, cy, r, .. } | Shape::Sphere { cx, cy, r, .. } => cx.hypot(cy) + r,
        }
    }
}

impl WorldGeom {
    /// Centre of the horizontal bounding circle.
    pub fn centre_xy(&self) -> [f64; 2] {
        match *self {
            WorldGeom::Box { cx, cy, .. } | WorldGeom::Cylinder { cx, cy, .. } | WorldGeom::Sphere { cx, cy, .. } => {
                [cx, cy]
            }
        }
    }

    /// Radius of the horizontal bounding circle (m).
    pub fn bound_r(&self) -> f64 {
        match *self {
            WorldGeom::Box { hx, hy, .. } => hx.hypot(hy),
            WorldGeom::Cylinder { r, .. } | WorldGeom::Sphere { r, .. } => r,
        }
    }

    /// Height interval (m).
    pub fn z_range(&self) -> (f64, f64) {
        match *self {
            WorldGeom::Box { z0, z1, .. } | WorldGeom::Cylinder { z0, z1, .. } => (z0, z1),
            WorldGeom::Sphere { cz, r, .. } => (cz - r, cz + r),
        }
    }

    /// Smallest t > 0 with `o + t d` on the surface, if any. `d` need not be unit length;
    /// t is in units of |d|.
    pub fn intersect(&self, o: [f64; 3], d: [f64; 3]) -> Option<f64> {
        match *self {
            WorldGeom::Box { cx, cy, cos, sin, hx, hy, z0, z1 } => {
                // Into the box frame (rotate by -yaw), then the slab test.
                let (px, py) = (o[0] - cx, o[1] - cy);
                let lo = [cos * px + sin * py, -sin * px + cos * py, o[2]];
                let ld = [cos * d[0] + sin * d[1], -sin * d[0] + cos * d[1], d[2]];
                let bounds = [(-hx, hx), (-hy, hy), (z0, z1)];
                let (mut t_in, mut t_out) = (f64::NEG_INFINITY, f64::INFINITY);
                for a in 0..3 {
                    let (lo_b, hi_b) = bounds[a];
                    if ld[a] == 0.0 {
                        if lo[a] < lo_b || lo[a] > hi_b {
                            return None;
                        }
                        continue;
                    }
                    let inv = 1.0 / ld[a];
                    let (mut t0, mut t1) = ((lo_b - lo[a]) * inv, (hi_b - lo[a]) * inv);
                    if t0 > t1 {
                        std::mem::swap(&mut t0, &mut t1);
                    }
                    t_in = t_in.max(t0);
                    t_out = t_out.min(t1);
                }
                (t_in <= t_out && t_in > T_MIN).then_some(t_in)
            }
            WorldGeom::Cylinder { cx, cy, r, z0, z1 } => {
                let (px, py) = (o[0] - cx, o[1] - cy);
                let mut best = f64::INFINITY;
                let a = d[0] * d[0] + d[1] * d[1];
                if a > 0.0 {
                    let b = px * d[0] + py * d[1];
                    let c = px * px + py * py - r * r;
                    let disc = b * b - a * c;
                    if disc >= 0.0 {
                        let t = (-b - disc.sqrt()) / a;
                        let z = o[2] + t * d[2];
                        if t > T_MIN && z >= z0 && z <= z1 {
                            best = t;
                        }
                    }
                }
                // End caps, seen only from above the top or below the bottom.
                for (zc, outside) in [(z1, o[2] > z1), (z0, o[2] < z0)] {
                    if outside && d[2] != 0.0 {
                        let t = (zc - o[2]) / d[2];
                        let (x, y) = (px + t * d[0], py + t * d[1]);
                        if t > T_MIN && x * x + y * y <= r * r && t < best {
                            best = t;
                        }
                    }
                }
                best.is_finite().then_some(best)
            }
            WorldGeom::Sphere { cx, cy, cz, r } => {
                let p = [o[0] - cx, o[1] - cy, o[2] - cz];
                let a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                let b = p[0] * d[0] + p[1] * d[1] + p[2] * d[2];
                let c = p[0] * p[0] + p[1] * p[1] + p[2] * p[2] - r * r;
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return None;
                }
                let t = (-b - disc.sqrt()) / a;
                (t > T_MIN).then_some(t)
            }
        }
    }

    /// Whether two primitives may interpenetrate: their height intervals overlap and their
    /// footprints come closer than `margin_m`. Spheres count as their bounding vertical
    /// cylinders, and box-box uses the separating-axis test with the margin on each axis, so the
    /// test can only err towards reporting an overlap.
    pub fn overlaps(&self, other: &WorldGeom, margin_m: f64) -> bool {
        let (a0, a1) = self.z_range();
        let (b0, b1) = other.z_range();
        if !(a0 < b1 && b0 < a1) {
            return false;
        }
        match (self.as_footprint(), other.as_footprint()) {
            (Footprint::Circle(c1, r1), Footprint::Circle(c2, r2)) => {
                (c1[0] - c2[0]).hypot(c1[1] - c2[1]) < r1 + r2 + margin_m
            }
            (Footprint::Rect(rect), Footprint::Circle(c, r)) | (Footprint::Circle(c, r), Footprint::Rect(rect)) => {
                rect.distance_to(c) < r + margin_m
            }
            (Footprint::Rect(p), Footprint::Rect(q)) => {
                let axes = [p.axis_x(), p.axis_y(), q.axis_x(), q.axis_y()];
                axes.iter().all(|ax| {
                    let (p0, p1) = p.project(*ax);
                    let (q0, q1) = q.project(*ax);
                    p0 < q1 + margin_m && q0 < p1 + margin_m
                })
            }
        }
    }

    fn as_footprint(&self) -> Footprint {
        match *self {
            WorldGeom::Box { cx, cy, cos, sin, hx, hy, .. } => Footprint::Rect(Rect { c: [cx, cy], cos, sin, hx, hy }),
            WorldGeom::Cylinder { cx, cy, r, .. } | WorldGeom::Sphere { cx, cy, r, .. } => {
                Footprint::Circle([cx, cy], r)
            }
        }
    }
}

enum Footprint {
    Circle([f64; 2], f64),
    Rect(Rect),
}

struct Rect {
    c: [f64; 2],
    cos: f64,
    sin: f64,
    hx: f64,
    hy: f64,
}

impl Rect {
    fn axis_x(&self) -> [f64; 2] {
        [self.cos, self.sin]
    }

    fn axis_y(&self) -> [f64; 2] {
        [-self.sin, self.cos]
    }

    /// Interval of the rectangle projected on unit axis `a`.
    fn project(&self, a: [f64; 2]) -> (f64, f64) {
        let centre = self.c[0] * a[0] + self.c[1] * a[1];
        let half =
            self.hx * (self.cos * a[0] + self.sin * a[1]).abs() + self.hy * (-self.sin * a[0] + self.cos * a[1]).abs();
        (centre - half, centre + half)
    }

    /// Euclidean distance from point `p` to the rectangle (0 inside).
    fn distance_to(&self, p: [f64; 2]) -> f64 {
        let (dx, dy) = (p[0] - self.c[0], p[1] - self.c[1]);
        let lx = (self.cos * dx + self.sin * dy).abs() - self.hx;
        let ly = (-self.sin * dx + self.cos * dy).abs() - self.hy;
        lx.max(0.0).hypot(ly.max(0.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(d: [f64; 3]) -> [f64; 3] {
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        [d[0] / n, d[1] / n, d[2] / n]
    }

    #[test]
    fn ray_hits_a_rotated_box_on_its_near_face() {
        let pose = Pose2 { x: 10.0, y: 0.0, yaw: std::f64::consts::FRAC_PI_2 };
        let b = Shape::Box { cx: 0.0, cy: 0.0, hx: 2.0, hy: 1.0, z0: 0.0, z1: 2.0 }.place(&pose, 1);
        // Rotated by 90 degrees, the box spans x in [9, 11]: the ray along +x at z = 1 enters at 9.
        let t = b.geom.intersect([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]).unwrap();
        assert!((t - 9.0).abs() < 1e-12);
        // Above the box: no hit.
        assert!(b.geom.intersect([0.0, 0.0, 2.5], [1.0, 0.0, 0.0]).is_none());
        // Pointing away: no hit.
        assert!(b.geom.intersect([0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]).is_none());
    }

    #[test]
    fn ray_hits_cylinder_side_and_top_cap() {
        let c = WorldGeom::Cylinder { cx: 5.0, cy: 0.0, r: 0.5, z0: 0.0, z1: 1.0 };
        assert!((c.intersect([0.0, 0.0, 0.5], [1.0, 0.0, 0.0]).unwrap() - 4.5).abs() < 1e-12);
        // From above, straight down onto the top cap at z = 1.
        let t = c.intersect([5.0, 0.2, 3.0], [0.0, 0.0, -1.0]).unwrap();
        assert!((t - 2.0).abs() < 1e-12);
        // Grazing past.
        assert!(c.intersect([0.0, 0.6, 0.5], [1.0, 0.0, 0.0]).is_none());
        // Hit on the side but above the top.
        assert!(c.intersect([0.0, 0.0, 1.5], [1.0, 0.0, 0.0]).is_none());
    }

    #[test]
    fn ray_hits_sphere_at_the_nearer_root() {
        let s = WorldGeom::Sphere { cx: 0.0, cy: 10.0, cz: 2.0, r: 1.0 };
        let d = unit([0.0, 1.0, 0.0]);
        assert!((s.intersect([0.0, 0.0, 2.0], d).unwrap() - 9.0).abs() < 1e-12);
        assert!(s.intersect([0.0, 0.0, 3.5], d).is_none());
    }

    #[test]
    fn footprint_overlap_respects_heights_margin_and_rotation() {
        let a = WorldGeom::Box { cx: 0.0, cy: 0.0, cos: 1.0, sin: 0.0, hx: 1.0, hy: 1.0, z0: 0.0, z1: 1.0 };
        let (s, c) = std::f64::consts::FRAC_PI_4.sin_cos();
        // A diamond whose corner is at x = 1 + 0.2 + ... : centre at 2.6, half diagonal sqrt(2).
        let b = WorldGeom::Box { cx: 2.6, cy: 0.0, cos: c, sin: s, hx: 1.0, hy: 1.0, z0: 0.0, z1: 1.0 };
        // Gap along x: 2.6 - sqrt(2) - 1 = 0.186 m.
        assert!(!a.overlaps(&b, 0.1));
        assert!(a.overlaps(&b, 0.3));
        let high = WorldGeom::Cylinder { cx: 0.0, cy: 0.0, r: 3.0, z0: 1.5, z1: 3.0 };
        assert!(!a.overlaps(&high, 0.1), "disjoint heights never overlap");
        let circle = WorldGeom::Cylinder { cx: 1.5, cy: 1.5, r: 0.6, z0: 0.0, z1: 3.0 };
        // Distance from (1.5, 1.5) to the corner (1, 1) is 0.707 > 0.6 + 0.05.
        assert!(!a.overlaps(&circle, 0.05));
        assert!(a.overlaps(&circle, 0.2));
    }
}
