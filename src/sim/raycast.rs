//! Ray casting of one sweep: every (azimuth, beam) ray against the ground plane and the placed
//! primitives, nearest hit wins; then range noise and dropout.
//!
//! Culling: each primitive's horizontal bounding circle, seen from the sensor, covers an azimuth
//! interval; primitives are listed per azimuth column, sorted by their nearest possible
//! horizontal distance, so a ray stops testing once the next candidate cannot beat its best hit.
//! Columns are traced in parallel (rayon); the result equals the brute-force twin
//! `trace_brute` ray for ray.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use super::motion::Pose2;
use super::params::LidarParams;
use super::shapes::WorldPrim;

/// Object id meaning "no return".
pub(crate) const NO_HIT: u32 = u32::MAX;

/// The ray directions of a sweep, in the sensor frame (x forward, y left, z up).
#[derive(Debug, Clone)]
pub(crate) struct RayPattern {
    /// (sin, cos) of each beam's elevation.
    pub elevations: Vec<(f64, f64)>,
    /// Azimuth of each column (rad), counter-clockwise from +x.
    pub azimuths: Vec<f64>,
    pub step_rad: f64,
}

impl RayPattern {
    pub fn new(l: &LidarParams) -> RayPattern {
        let columns = ((360.0 / l.azimuth_step_deg).round() as usize).max(1);
        let step_rad = std::f64::consts::TAU / columns as f64;
        let elevations = (0..l.beams)
            .map(|b| {
                let f = if l.beams > 1 { b as f64 / (l.beams - 1) as f64 } else { 0.5 };
                let e = (l.elevation_min_deg + f * (l.elevation_max_deg - l.elevation_min_deg)).to_radians();
                e.sin_cos()
            })
            .collect();
        let azimuths = (0..columns).map(|c| c as f64 * step_rad).collect();
        RayPattern { elevations, azimuths, step_rad }
    }

    /// Unit direction of ray (column, beam) in the sensor frame.
    pub fn dir(&self, column: usize, beam: usize) -> [f64; 3] {
        let (se, ce) = self.elevations[beam];
        let (sa, ca) = self.azimuths[column].sin_cos();
        [ce * ca, ce * sa, se]
    }
}

/// Nearest hit of one ray: true range (m) and object id ([`NO_HIT`] if none within range).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct RayHit {
    pub range_m: f64,
    pub body: u32,
}

/// Scratch buffers reused from sweep to sweep.
#[derive(Default)]
pub(crate) struct Caster {
    order: Vec<(f64, u32)>,
    col_start: Vec<usize>,
    col_items: Vec<(f64, u32)>,
    fill: Vec<usize>,
    hits: Vec<RayHit>,
}

/// Ground (object 0) or nothing, before any primitive is tested.
fn ground_or_nothing(o: [f64; 3], d: [f64; 3], max_range_m: f64) -> RayHit {
    if d[2] < 0.0 {
        let t = -o[2] / d[2];
        if t <= max_range_m {
            return RayHit { range_m: t, body: 0 };
        }
    }
    RayHit { range_m: max_range_m, body: NO_HIT }
}

/// World direction of a sensor-frame ray for a sensor heading `yaw`.
fn world_dir(pattern: &RayPattern, yaw: f64, column: usize, beam: usize) -> [f64; 3] {
    let (se, ce) = pattern.elevations[beam];
    let (sa, ca) = (pattern.azimuths[column] + yaw).sin_cos();
    [ce * ca, ce * sa, se]
}

/// Nearest hit by testing every primitive: the reference the culled caster must match.
#[cfg(test)]
pub(crate) fn trace_brute(
    prims: &[WorldPrim],
    origin: [f64; 3],
    pattern: &RayPattern,
    yaw: f64,
    max_range_m: f64,
) -> Vec<RayHit> {
    let beams = pattern.elevations.len();
    let mut out = Vec::with_capacity(beams * pattern.azimuths.len());
    for column in 0..pattern.azimuths.len() {
        for beam in 0..beams {
            let d = world_dir(pattern, yaw, column, beam);
            let mut best = ground_or_nothing(origin, d, max_range_m);
            for p in prims {
                if let Some(t) = p.geom.intersect(origin, d)
                    && t < best.range_m
                {
                    best = RayHit { range_m: t, body: p.body };
                }
            }
            out.push(best);
        }
    }
    out
}

impl Caster {
    /// Nearest hit of every ray of `pattern` from a sensor at `origin` (world) heading `yaw`,
    /// column-major (all beams of column 0, then column 1, ...). Cost: O(rays x candidates per
    /// column), candidates cut by azimuth and by distance.
    pub fn trace(
        &mut self,
        prims: &[WorldPrim],
        origin: [f64; 3],
        pattern: &RayPattern,
        yaw: f64,
        max_range_m: f64,
    ) -> &[RayHit] {
        let columns = pattern.azimuths.len();
        let beams = pattern.elevations.len();
        let step = pattern.step_rad;
        let (sy, cy) = yaw.sin_cos();

        // Nearest horizontal distance of each primitive and its column interval.
        self.order.clear();
        for (i, p) in prims.iter().enumerate() {
            let [px, py] = p.geom.centre_xy();
            let near = ((px - origin[0]).hypot(py - origin[1]) - p.geom.bound_r()).max(0.0);
            if near <= max_range_m {
                self.order.push((near, i as u32));
            }
        }
        self.order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let interval = |p: &WorldPrim| -> Option<(i64, i64)> {
            let [px, py] = p.geom.centre_xy();
            let (dx, dy) = (px - origin[0], py - origin[1]);
            let (rx, ry) = (cy * dx + sy * dy, -sy * dx + cy * dy);
            let rho = rx.hypot(ry);
            let rb = p.geom.bound_r();
            if rho <= rb * (1.0 + 1e-9) + 1e-9 {
                return None; // the sensor is inside the bounding circle: every column
            }
            let phi = ry.atan2(rx);
            let half = (rb / rho).asin();
            // One column of padding on each side absorbs rounding in the angles.
            let lo = ((phi - half) / step).ceil() as i64 - 1;
            let hi = ((phi + half) / step).floor() as i64 + 1;
            (hi - lo + 1 < columns as i64).then_some((lo, hi))
        };
        let for_each_column = |p: &WorldPrim, f: &mut dyn FnMut(usize)| match interval(p) {
            Some((lo, hi)) => (lo..=hi).for_each(|c| f(c.rem_euclid(columns as i64) as usize)),
            None => (0..columns).for_each(f),
        };
        self.col_start.clear();
        self.col_start.resize(columns + 1, 0);
        for &(_, i) in &self.order {
            for_each_column(&prims[i as usize], &mut |c| self.col_start[c + 1] += 1);
        }
        for c in 0..columns {
            self.col_start[c + 1] += self.col_start[c];
        }
        self.fill.clear();
        self.fill.extend_from_slice(&self.col_start[..columns]);
        self.col_items.clear();
        self.col_items.resize(self.col_start[columns], (0.0, 0));
        for &(near, i) in &self.order {
            for_each_column(&prims[i as usize], &mut |c| {
                self.col_items[self.fill[c]] = (near, i);
                self.fill[c] += 1;
            });
        }

        self.hits.clear();
        self.hits.resize(columns * beams, RayHit { range_m: 0.0, body: NO_HIT });
        let (col_start, col_items) = (&self.col_start, &self.col_items);
        self.hits.par_chunks_mut(beams).enumerate().for_each(|(column, out)| {
            let candidates = &col_items[col_start[column]..col_start[column + 1]];
            for (beam, hit) in out.iter_mut().enumerate() {
                let d = world_dir(pattern, yaw, column, beam);
                let cos_e = pattern.elevations[beam].1;
                let mut best = ground_or_nothing(origin, d, max_range_m);
                for &(near, i) in candidates {
                    // Horizontal distance to the best hit is range * cos(elevation).
                    if near > best.range_m * cos_e {
                        break;
                    }
                    let p = &prims[i as usize];
                    if let Some(t) = p.geom.intersect(origin, d)
                        && t < best.range_m
                    {
                        best = RayHit { range_m: t, body: p.body };
                    }
                }
                *hit = best;
            }
        });
        &self.hits
    }
}

/// A sweep's returns: points in the sensor frame and the object id of each.
pub(crate) struct Sweep {
    pub points: Vec<crate::geometry::Point>,
    pub bodies: Vec<u32>,
}

/// Turns traced hits into measurements: drops returns outside [min, max] range and, with
/// probability `dropout`, at random; adds Gaussian noise to each range along its ray. Exactly
/// three random numbers are drawn per ray, so a ray's noise does not depend on other rays.
pub(crate) fn measure(hits: &[RayHit], pattern: &RayPattern, l: &LidarParams, rng: &mut ChaCha8Rng) -> Sweep {
    let beams = pattern.elevations.len();
    let mut points = Vec::with_capacity(hits.len());
    let mut bodies = Vec::with_capacity(hits.len());
    for (i, hit) in hits.iter().enumerate() {
        let u_drop: f64 = rng.random();
        let u1: f64 = rng.random();
        let u2: f64 = rng.random();
        if hit.body == NO_HIT || hit.range_m < l.min_range_m || u_drop < l.dropout {
            continue;
        }
        // Box-Muller; 1 - u1 lies in (0, 1], so the logarithm is finite.
        let normal = (-2.0 * (1.0 - u1).ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        let range_m = hit.range_m + l.range_noise_m * normal;
        if range_m <= 0.0 {
            continue;
        }
        let d = pattern.dir(i / beams, i % beams);
        points.push([(d[0] * range_m) as f32, (d[1] * range_m) as f32, (d[2] * range_m) as f32]);
        bodies.push(hit.body);
    }
    Sweep { points, bodies }
}

/// Sensor origin in the world for an ego pose and mount height.
pub(crate) fn sensor_origin(ego: &Pose2, mount_height_m: f64) -> [f64; 3] {
    [ego.x, ego.y, mount_height_m]
}
