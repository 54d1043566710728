//! What a sweep saw along its rays: whether a point placed in the scene would have been seen by
//! the sensor, hidden behind a nearer return, or lies in space its rays passed through.
//!
//! A body's registration to its model from the body's own points is blind along a flank (the
//! aperture problem: the rings along a car's side look the same wherever the car is along
//! them). The rays are not: a model placed too far back leaves its front end where the sensor
//! looked through to the road behind.

use crate::geometry::Point;
use crate::geometry::ground::{GroundEstimate, GroundParams};
use crate::geometry::knn::KdTree;
use crate::geometry::rigid::Rigid;

/// A direction counts as a ray's when it lies within this angle (rad) of it: 1 degree, more
/// than half the elevation spacing of a 32-beam sensor (1.3 degrees over 40), so a point
/// between two rings still finds one.
const MAX_RAY_ANGLE_RAD: f32 = 0.0175;

/// How a point relates to one sweep's rays (the ray nearest its direction, and a margin).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sight {
    /// The ray ends at the point, within the margin: the sensor saw something there.
    Seen,
    /// The ray ends the margin or more beyond the point: it passed through empty space there.
    Passed,
    /// The ray ends the margin or more before the point: something nearer hides it.
    Hidden,
    /// No ray passed near its direction (out of the field of view, sky, a dropped return).
    Unknown,
}

/// One sweep's rays: the direction and range of every return, with the pose that takes fit
/// coordinates to the sensor's.
pub struct SweepRays {
    fit_to_sensor: Rigid,
    /// Unit directions of the returns, in sensor coordinates.
    directions: KdTree,
    ranges_m: Vec<f32>,
    /// The local ground under the sweep (sensor coordinates), estimated from all its returns.
    ground: Option<GroundEstimate>,
}

impl SweepRays {
    /// The rays of a sweep given in sensor coordinates (ground and far points included: they
    /// are what the sensor saw past a body), whose sensor-to-fit pose is `sensor_to_fit`.
    pub fn new(sensor_points: &[Point], sensor_to_fit: &Rigid) -> Self {
        let mut unit = Vec::with_capacity(sensor_points.len());
        let mut ranges_m = Vec::with_capacity(sensor_points.len());
        for p in sensor_points {
            let r = range_m(p);
            if r.is_finite() && r > 1e-3 {
                unit.push([p[0] / r, p[1] / r, p[2] / r]);
                ranges_m.push(r);
            }
        }
        let ground = GroundEstimate::new(sensor_points, &GroundParams::default())
            .expect("the default ground parameters are valid");
        Self { fit_to_sensor: sensor_to_fit.inverse(), directions: KdTree::new(&unit), ranges_m, ground }
    }

    /// Height (m) of `point` (fit coordinates) above the local ground this sweep saw under it
    /// (the estimate of the fit's ground removal); `None` where the sweep saw no ground.
    pub fn height_above_ground_m(&self, point: &Point) -> Option<f32> {
        self.ground.as_ref()?.height_above(&self.fit_to_sensor.apply(point))
    }

    /// The share of `points` (fit coordinates: a body's model where it is thought to be) that
    /// the sweep shows hidden behind something else: the ray nearest a point's direction ended
    /// at least `margin_m` nearer than the nearest of all the points, so the return is not the
    /// body's own near side. Points no ray passed near are left out; `None` when none is left.
    pub fn hidden_share(&self, points: &[Point], margin_m: f32) -> Option<f32> {
        let in_sensor: Vec<Point> = points.iter().map(|p| self.fit_to_sensor.apply(p)).collect();
        let nearest_m = in_sensor.iter().map(range_m).filter(|r| r.is_finite()).fold(f32::INFINITY, f32::min);
        let (mut rayed, mut hidden) = (0usize, 0usize);
        for (_, ray_m) in in_sensor.iter().filter_map(|p| self.ray_towards(p)) {
            rayed += 1;
            hidden += usize::from(ray_m <= nearest_m - margin_m);
        }
        (rayed > 0).then(|| hidden as f32 / rayed as f32)
    }

    /// The range of `p` (sensor coordinates) and of the return of the ray nearest its
    /// direction, when one lies within [`MAX_RAY_ANGLE_RAD`] of it.
    fn ray_towards(&self, p: &Point) -> Option<(f32, f32)> {
        let r = range_m(p);
        if !r.is_finite() || r <= 1e-3 {
            return None;
        }
        // Chord length on the unit sphere: the angle for small angles.
        let max_chord2 = MAX_RAY_ANGLE_RAD * MAX_RAY_ANGLE_RAD;
        let hit = self.directions.nearest(&[p[0] / r, p[1] / r, p[2] / r])?;
        (hit.dist2 <= max_chord2).then(|| (r, self.ranges_m[hit.index]))
    }

    /// How the sensor saw `point` (fit coordinates), with the ray nearest its direction and a
    /// margin `margin_m` on the ray's range.
    pub fn sight(&self, point: &Point, margin_m: f32) -> Sight {
        match self.ray_towards(&self.fit_to_sensor.apply(point)) {
            Some((r, range_m)) if range_m <= r - margin_m => Sight::Hidden,
            Some((r, range_m)) if range_m >= r + margin_m => Sight::Passed,
            Some(_) => Sight::Seen,
            None => Sight::Unknown,
        }
    }
}

/// Distance (m) of `p` from the origin.
fn range_m(p: &Point) -> f32 {
    (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sensor at `origin` (fit coordinates) that sees a wall 20 m ahead along x, and a post
    /// 5 m ahead that covers the directions within 0.1 rad of the x axis.
    fn wall_with_post(origin: [f64; 3]) -> (Vec<Point>, Rigid) {
        let mut points = Vec::new();
        for i in -40..=40 {
            for e in -10..=10 {
                let (az, el) = (i as f32 * 0.01, e as f32 * 0.01);
                let range = if az.abs() <= 0.1 && el.abs() <= 0.1 { 5.0 } else { 20.0 };
                points.push([range * el.cos() * az.cos(), range * el.cos() * az.sin(), range * el.sin()]);
            }
        }
        (points, Rigid::from_yaw(0.0, origin))
    }

    #[test]
    fn a_point_before_the_wall_is_passed_one_on_it_seen_one_behind_the_post_hidden_one_off_the_rays_unknown() {
        let origin = [3.0, -2.0, 1.0];
        let (points, pose) = wall_with_post(origin);
        let rays = SweepRays::new(&points, &pose);
        // A point at range_m along azimuth and elevation (rad) from the sensor, in fit coordinates.
        let at = |range_m: f32, az: f32, el: f32| {
            let d = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
            std::array::from_fn(|c| range_m * d[c] + origin[c] as f32)
        };
        // In the open, 10 m out along a ray that reaches the wall at 20 m; between two rays.
        assert_eq!(rays.sight(&at(10.0, 0.25, 0.0), 0.3), Sight::Passed);
        assert_eq!(rays.sight(&at(10.0, 0.255, 0.035), 0.3), Sight::Passed);
        assert_eq!(rays.sight(&at(19.8, 0.25, 0.0), 0.3), Sight::Seen);
        // On the wall itself, and just behind it within the margin.
        assert_eq!(rays.sight(&at(20.0, 0.25, 0.0), 0.3), Sight::Seen);
        assert_eq!(rays.sight(&at(20.2, 0.25, 0.0), 0.3), Sight::Seen);
        assert_eq!(rays.sight(&at(5.0, 0.0, 0.05), 0.3), Sight::Seen);
        // Behind the post (5 m) at 10 m along the axis.
        assert_eq!(rays.sight(&at(10.0, 0.0, 0.0), 0.3), Sight::Hidden);
        // Behind the wall by more than the margin.
        assert_eq!(rays.sight(&at(21.0, 0.25, 0.0), 0.3), Sight::Hidden);
        // Above the field of view (0.1 rad, and the margin of a ray's reach) and behind the sensor.
        assert_eq!(rays.sight(&at(10.0, 0.0, 0.3), 0.3), Sight::Unknown);
        assert_eq!(rays.sight(&at(10.0, 3.1, 0.0), 0.3), Sight::Unknown);
    }

    #[test]
    fn the_hidden_share_counts_what_something_nearer_than_the_whole_body_hides() {
        let origin = [3.0, -2.0, 1.0];
        let (points, pose) = wall_with_post(origin);
        let rays = SweepRays::new(&points, &pose);
        let at = |range_m: f32, az: f32, el: f32| -> Point {
            let d = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
            std::array::from_fn(|c| range_m * d[c] + origin[c] as f32)
        };
        // A body 10-12 m out across azimuths -0.3..0.3 rad: the post (5 m) hides the third of
        // its directions within 0.1 rad of the axis; every point has a ray.
        let body: Vec<Point> =
            (-30..=30).flat_map(|i| [10.0, 12.0].map(|range_m| at(range_m, i as f32 * 0.01, 0.0))).collect();
        let share = rays.hidden_share(&body, 0.5).expect("in view");
        // The same by `sight`: hidden with the margin that reaches 0.5 m before the nearest point.
        let range = |p: &Point| (0..3).map(|c| (p[c] - origin[c] as f32).powi(2)).sum::<f32>().sqrt();
        let brute = body.iter().filter(|p| rays.sight(p, range(p) - 9.5) == Sight::Hidden);
        assert!((share - 21.0 / 61.0).abs() < 0.02, "{share}");
        assert_eq!((share * body.len() as f32).round() as usize, brute.count());
        // The wall seen from in front: nothing nearer than the body's own nearest point hides
        // its far part (a body 19.5-20 m out, part of it behind its own front, none of it
        // behind the post's directions).
        let own: Vec<Point> = (20..=30).flat_map(|i| [19.5, 19.9].map(|r| at(r, i as f32 * 0.01, 0.0))).collect();
        assert_eq!(rays.hidden_share(&own, 0.5), Some(0.0));
        // Nothing in view.
        assert_eq!(rays.hidden_share(&[at(10.0, 3.1, 0.0)], 0.5), None);
    }
}
