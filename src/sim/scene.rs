//! The street scene: the road geometry, the bodies on it (shapes and motions), and their random
//! placement without interpenetration.
//!
//! Cross-section of the street (lateral offset d from the centreline, left positive): lanes at
//! |d| < 3.5 (ego direction on the right), parking strips to 5.5, sidewalks to 9, facades from 9
//! to 10.5. A side street crosses at arc length `intersection_s_m`; nothing static stands in it.
//! Every candidate body is checked against all bodies already placed (the ego included) at every
//! frame time and half-way between frames, and rejected if any two primitives could touch.

use std::f64::consts::{FRAC_PI_2, PI};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::motion::{Motion, Path, Pose2, Segment};
use super::params::{SceneParams, SimParams};
use super::shapes::{Shape, WorldGeom, WorldPrim};

/// What a body is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum ObjectKind {
    /// The road surface (object id 0): the plane z = 0.
    Ground,
    /// A building (a box behind the facade line).
    Building,
    /// A lamp post or sign pole (thin cylinder).
    Pole,
    /// A tree: trunk cylinder and spherical crown.
    Tree,
    /// A car that does not move.
    ParkedCar,
    /// A driving car.
    MovingCar,
    /// A walking person.
    Pedestrian,
}

/// How a body moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Behaviour {
    /// Does not move.
    Static,
    /// Drives in the ego lane direction.
    SameDirection,
    /// Drives in the opposite lane.
    Oncoming,
    /// Drives straight along the side street, across the main road.
    Crossing,
    /// Turns from the side street into the main road (non-zero yaw rate while turning).
    Turning,
    /// Walks along a sidewalk.
    Walking,
}

/// Numbers of objects by category.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ObjectCounts {
    /// Buildings.
    pub buildings: usize,
    /// Poles.
    pub poles: usize,
    /// Trees.
    pub trees: usize,
    /// Parked cars.
    pub parked_cars: usize,
    /// Cars driving in the ego direction.
    pub same_direction_cars: usize,
    /// Cars driving in the opposite lane.
    pub oncoming_cars: usize,
    /// Cars crossing along the side street.
    pub crossing_cars: usize,
    /// Cars turning from the side street.
    pub turning_cars: usize,
    /// Pedestrians.
    pub pedestrians: usize,
}

impl ObjectCounts {
    fn slot(&mut self, kind: ObjectKind, behaviour: Behaviour) -> Option<&mut usize> {
        Some(match (kind, behaviour) {
            (ObjectKind::Building, _) => &mut self.buildings,
            (ObjectKind::Pole, _) => &mut self.poles,
            (ObjectKind::Tree, _) => &mut self.trees,
            (ObjectKind::ParkedCar, _) => &mut self.parked_cars,
            (ObjectKind::Pedestrian, _) => &mut self.pedestrians,
            (ObjectKind::MovingCar, Behaviour::SameDirection) => &mut self.same_direction_cars,
            (ObjectKind::MovingCar, Behaviour::Oncoming) => &mut self.oncoming_cars,
            (ObjectKind::MovingCar, Behaviour::Crossing) => &mut self.crossing_cars,
            (ObjectKind::MovingCar, Behaviour::Turning) => &mut self.turning_cars,
            _ => return None,
        })
    }

    /// Counts `kind` / `behaviour` once.
    pub(crate) fn add(&mut self, kind: ObjectKind, behaviour: Behaviour) {
        if let Some(n) = self.slot(kind, behaviour) {
            *n += 1;
        }
    }
}

/// A rigid body: shapes in its own frame and a motion.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Body {
    pub kind: ObjectKind,
    pub behaviour: Behaviour,
    pub motion: Motion,
    pub shapes: Vec<Shape>,
    /// Horizontal radius around the body origin containing every shape (m).
    pub reach_m: f64,
}

impl Body {
    fn new(kind: ObjectKind, behaviour: Behaviour, motion: Motion, shapes: Vec<Shape>) -> Body {
        let reach_m = shapes.iter().map(Shape::reach_m).fold(0.0, f64::max);
        Body { kind, behaviour, motion, shapes, reach_m }
    }

    /// Appends this body's primitives at time `t_s`, tagged with object id `id`.
    pub fn prims_at(&self, t_s: f64, id: u32, out: &mut Vec<WorldPrim>) {
        let pose = self.motion.pose_at(t_s);
        out.extend(self.shapes.iter().map(|s| s.place(&pose, id)));
    }
}

/// Road geometry: the centreline (straight, then an arc) and the side street position.
#[derive(Debug, Clone)]
pub(crate) struct Street {
    centre: Path,
    intersection_s_m: f64,
}

/// Lateral offset of the centre of the ego lane, and of the opposite lane (m).
const LANE_D_M: f64 = 1.75;
/// Distance from the centreline at which facades start (m).
const FACADE_D_M: f64 = 9.0;
/// Clearance every pair of bodies keeps (m).
const CLEARANCE_M: f64 = 0.15;
/// Random candidates tried per requested object before giving up on it.
const ATTEMPTS: usize = 300;

impl Street {
    pub fn new(p: &SceneParams) -> Street {
        let centre = Path::new(
            Pose2 { x: 0.0, y: 0.0, yaw: 0.0 },
            vec![
                Segment { length_m: p.curve_start_m, curvature_per_m: 0.0 },
                Segment { length_m: 1.0, curvature_per_m: p.curvature_per_m },
            ],
        );
        Street { centre, intersection_s_m: p.intersection_s_m }
    }

    /// Pose at arc length `s_m` and lateral offset `d_m`, heading along the street.
    pub fn pose(&self, s_m: f64, d_m: f64) -> Pose2 {
        self.centre.eval(s_m).offset(0.0, d_m)
    }

    /// The path parallel to the centreline at offset `d_m`.
    pub fn lane(&self, d_m: f64) -> Path {
        self.centre.offset(d_m)
    }

    fn near_intersection(&self, s_m: f64, half_width_m: f64) -> bool {
        (s_m - self.intersection_s_m).abs() < half_width_m
    }
}

/// A body's primitives at the collision-check times (once for a static body).
struct Footprint {
    per_time: Vec<Vec<WorldGeom>>,
    centres: Vec<[f64; 2]>,
    reach_m: f64,
}

/// Keeps the footprints of the bodies placed so far and rejects candidates that would touch them.
struct Checker {
    times_s: Vec<f64>,
    placed: Vec<Footprint>,
}

impl Checker {
    fn footprint(&self, body: &Body) -> Footprint {
        let times: &[f64] = if body.motion.is_dynamic() { &self.times_s } else { &self.times_s[..1] };
        let mut per_time = Vec::with_capacity(times.len());
        let mut centres = Vec::with_capacity(times.len());
        let mut prims = Vec::new();
        for &t in times {
            prims.clear();
            body.prims_at(t, 0, &mut prims);
            per_time.push(prims.iter().map(|p| p.geom).collect());
            let pose = body.motion.pose_at(t);
            centres.push([pose.x, pose.y]);
        }
        Footprint { per_time, centres, reach_m: body.reach_m }
    }

    fn collides(&self, cand: &Footprint) -> bool {
        let n = self.times_s.len();
        self.placed.iter().any(|other| {
            let steps = if cand.per_time.len() == 1 && other.per_time.len() == 1 { 1 } else { n };
            (0..steps).any(|i| {
                let (ia, ib) = (i.min(cand.per_time.len() - 1), i.min(other.per_time.len() - 1));
                let (ca, cb) = (cand.centres[ia], other.centres[ib]);
                if (ca[0] - cb[0]).hypot(ca[1] - cb[1]) >= cand.reach_m + other.reach_m + CLEARANCE_M {
                    return false;
                }
                cand.per_time[ia].iter().any(|a| other.per_time[ib].iter().any(|b| a.overlaps(b, CLEARANCE_M)))
            })
        })
    }
}

/// The generated scene: bodies indexed by object id (0 is the ground), the ego vehicle, and the
/// requested objects that could not be placed.
pub(crate) struct Scene {
    pub bodies: Vec<Body>,
    pub ego: Body,
    pub unplaced: ObjectCounts,
}

struct Builder {
    rng: ChaCha8Rng,
    street: Street,
    checker: Checker,
    bodies: Vec<Body>,
    unplaced: ObjectCounts,
}

impl Builder {
    /// Places `body` if it touches nothing placed so far.
    fn try_add(&mut self, body: Body) -> bool {
        let fp = self.checker.footprint(&body);
        if self.checker.collides(&fp) {
            return false;
        }
        self.checker.placed.push(fp);
        self.bodies.push(body);
        true
    }

    /// Draws up to [`ATTEMPTS`] candidates from `make` (which may decline with `None`) and places
    /// the first that fits, `count` times; failures are counted as unplaced `kind` / `behaviour`.
    fn place_many(
        &mut self,
        count: usize,
        (kind, behaviour): (ObjectKind, Behaviour),
        mut make: impl FnMut(&mut ChaCha8Rng, &Street) -> Option<Body>,
    ) {
        for _ in 0..count {
            let placed =
                (0..ATTEMPTS).any(|_| make(&mut self.rng, &self.street).is_some_and(|body| self.try_add(body)));
            if !placed {
                self.unplaced.add(kind, behaviour);
            }
        }
    }
}

fn side(rng: &mut ChaCha8Rng) -> f64 {
    if rng.random_bool(0.5) { 1.0 } else { -1.0 }
}

fn car_shapes(rng: &mut ChaCha8Rng) -> Vec<Shape> {
    let length = rng.random_range(3.9..4.9);
    let width = rng.random_range(1.7..1.95);
    let roof = rng.random_range(1.4..1.6);
    vec![
        Shape::Box { cx: 0.0, cy: 0.0, hx: 0.5 * length, hy: 0.5 * width, z0: 0.2, z1: 0.95 },
        Shape::Box { cx: -0.08 * length, cy: 0.0, hx: 0.27 * length, hy: 0.5 * width - 0.1, z0: 0.95, z1: roof },
    ]
}

fn pedestrian_shapes(rng: &mut ChaCha8Rng) -> Vec<Shape> {
    let r = rng.random_range(0.18..0.26);
    let shoulders = rng.random_range(1.3..1.55);
    vec![
        Shape::Cylinder { cx: 0.0, cy: 0.0, r, z0: 0.0, z1: shoulders },
        Shape::Sphere { cx: 0.0, cy: 0.0, cz: shoulders + 0.16, r: 0.11 },
    ]
}

/// Builds the scene of `params` (validated). Deterministic in `params.seed`.
pub(crate) fn generate(params: &SimParams, times_s: &[f64]) -> Scene {
    let sp = &params.scene;
    let street = Street::new(sp);
    // Frame times and the instants half-way between them.
    let mut check_times = Vec::with_capacity(2 * times_s.len());
    for (k, &t) in times_s.iter().enumerate() {
        check_times.push(t);
        if let Some(next) = times_s.get(k + 1) {
            check_times.push(0.5 * (t + next));
        }
    }
    let ground = Body::new(ObjectKind::Ground, Behaviour::Static, Motion::Static(street.pose(0.0, 0.0)), vec![]);
    let ego = Body::new(
        ObjectKind::MovingCar,
        Behaviour::SameDirection,
        Motion::Path {
            path: street.lane(-LANE_D_M),
            u0_m: sp.ego_start_m,
            speed_mps: sp.ego_speed_mps,
            yaw_offset_rad: 0.0,
        },
        vec![Shape::Box { cx: 0.0, cy: 0.0, hx: 2.3, hy: 0.95, z0: 0.2, z1: 1.6 }],
    );
    let mut b = Builder {
        rng: ChaCha8Rng::seed_from_u64(params.seed),
        street,
        checker: Checker { times_s: check_times, placed: Vec::new() },
        bodies: vec![ground],
        unplaced: ObjectCounts::default(),
    };
    let ego_fp = b.checker.footprint(&ego);
    b.checker.placed.push(ego_fp);

    place_buildings(&mut b, sp.street_length_m);
    let len = sp.street_length_m;
    b.place_many(sp.poles, (ObjectKind::Pole, Behaviour::Static), |rng, st| {
        let s = rng.random_range(0.0..len);
        let d = side(rng) * rng.random_range(5.7..6.0);
        let r = rng.random_range(0.08..0.14);
        let h = rng.random_range(5.0..9.0);
        let shapes = vec![Shape::Cylinder { cx: 0.0, cy: 0.0, r, z0: 0.0, z1: h }];
        (!st.near_intersection(s, 5.0))
            .then(|| Body::new(ObjectKind::Pole, Behaviour::Static, Motion::Static(st.pose(s, d)), shapes))
    });
    b.place_many(sp.trees, (ObjectKind::Tree, Behaviour::Static), |rng, st| {
        let s = rng.random_range(0.0..len);
        let d = side(rng) * rng.random_range(6.3..6.8);
        let r = rng.random_range(0.15..0.3);
        let h = rng.random_range(2.2..3.2);
        let crown = rng.random_range(1.2..2.2);
        let shapes = vec![
            Shape::Cylinder { cx: 0.0, cy: 0.0, r, z0: 0.0, z1: h },
            Shape::Sphere { cx: 0.0, cy: 0.0, cz: h + 0.8 * crown, r: crown },
        ];
        (!st.near_intersection(s, 6.0))
            .then(|| Body::new(ObjectKind::Tree, Behaviour::Static, Motion::Static(st.pose(s, d)), shapes))
    });
    b.place_many(sp.parked_cars, (ObjectKind::ParkedCar, Behaviour::Static), |rng, st| {
        let s = rng.random_range(2.0..len - 2.0);
        let sd = side(rng);
        let d = sd * (4.5 + rng.random_range(-0.15..0.15));
        // Mostly parked in the direction of their lane's traffic.
        let facing_traffic = rng.random_bool(0.8);
        let mut pose = st.pose(s, d);
        if (sd > 0.0) == facing_traffic {
            pose.yaw += PI;
        }
        let shapes = car_shapes(rng);
        (!st.near_intersection(s, 9.5))
            .then(|| Body::new(ObjectKind::ParkedCar, Behaviour::Static, Motion::Static(pose), shapes))
    });
    // The rarest behaviour first, so that it finds room.
    b.place_many(sp.turning_cars, (ObjectKind::MovingCar, Behaviour::Turning), |rng, st| Some(turning_car(rng, st)));
    b.place_many(sp.crossing_cars, (ObjectKind::MovingCar, Behaviour::Crossing), |rng, st| {
        let sd = side(rng);
        let x = st.pose(st.intersection_s_m, 0.0);
        // Right-hand traffic: heading +left uses the lane on the +along side.
        let start = Pose2 { yaw: x.yaw + sd * FRAC_PI_2, ..x.offset(sd * LANE_D_M, 0.0) };
        let path = Path::new(start, vec![Segment { length_m: 1.0, curvature_per_m: 0.0 }]);
        let speed = rng.random_range(5.0..10.0);
        let u0 = rng.random_range(-30.0..0.0);
        let motion = Motion::Path { path, u0_m: u0, speed_mps: speed, yaw_offset_rad: 0.0 };
        Some(Body::new(ObjectKind::MovingCar, Behaviour::Crossing, motion, car_shapes(rng)))
    });
    let ego_u = sp.ego_start_m;
    b.place_many(sp.same_direction_cars, (ObjectKind::MovingCar, Behaviour::SameDirection), |rng, st| {
        let u0 = ego_u + rng.random_range(-50.0..70.0);
        let speed = rng.random_range(5.0..13.0);
        let motion = Motion::Path { path: st.lane(-LANE_D_M), u0_m: u0, speed_mps: speed, yaw_offset_rad: 0.0 };
        Some(Body::new(ObjectKind::MovingCar, Behaviour::SameDirection, motion, car_shapes(rng)))
    });
    b.place_many(sp.oncoming_cars, (ObjectKind::MovingCar, Behaviour::Oncoming), |rng, st| {
        let u0 = ego_u + rng.random_range(-30.0..100.0);
        let speed = -rng.random_range(6.0..13.0);
        let motion = Motion::Path { path: st.lane(LANE_D_M), u0_m: u0, speed_mps: speed, yaw_offset_rad: PI };
        Some(Body::new(ObjectKind::MovingCar, Behaviour::Oncoming, motion, car_shapes(rng)))
    });
    b.place_many(sp.pedestrians, (ObjectKind::Pedestrian, Behaviour::Walking), |rng, st| {
        let d = side(rng) * rng.random_range(6.9..8.4);
        let u0 = ego_u + rng.random_range(-40.0..50.0);
        let forward = rng.random_bool(0.5);
        let speed = rng.random_range(0.9..1.6) * if forward { 1.0 } else { -1.0 };
        let yaw_offset_rad = if forward { 0.0 } else { PI };
        let motion = Motion::Path { path: st.lane(d), u0_m: u0, speed_mps: speed, yaw_offset_rad };
        Some(Body::new(ObjectKind::Pedestrian, Behaviour::Walking, motion, pedestrian_shapes(rng)))
    });
    Scene { bodies: b.bodies, ego, unplaced: b.unplaced }
}

/// Buildings along both sides, from arc length 0 to `len`, with random widths, depths, heights,
/// setbacks and gaps, leaving the side street open. A building that would touch its neighbour
/// (on the inner side of the curve) is shifted along the street until it fits.
fn place_buildings(b: &mut Builder, len: f64) {
    for sd in [-1.0, 1.0] {
        let mut s = 0.0;
        while s < len {
            let mut width = b.rng.random_range(10.0..28.0);
            let gap = b.rng.random_range(1.0..5.0);
            let setback = b.rng.random_range(0.0..1.5);
            let depth = b.rng.random_range(8.0..16.0);
            let height = b.rng.random_range(6.0..22.0);
            let open_lo = b.street.intersection_s_m - 9.0;
            let open_hi = b.street.intersection_s_m + 9.0;
            if s < open_hi && s + width > open_lo {
                if s + 6.0 <= open_lo {
                    width = open_lo - s;
                } else {
                    s = open_hi;
                    continue;
                }
            }
            width = width.min(len - s);
            if width < 6.0 {
                break;
            }
            let d = sd * (FACADE_D_M + setback + 0.5 * depth);
            let pose = b.street.pose(s + 0.5 * width, d);
            let shapes = vec![Shape::Box { cx: 0.0, cy: 0.0, hx: 0.5 * width, hy: 0.5 * depth, z0: 0.0, z1: height }];
            if b.try_add(Body::new(ObjectKind::Building, Behaviour::Static, Motion::Static(pose), shapes)) {
                s += width + gap;
            } else {
                s += 1.0;
            }
        }
    }
}

/// A car that comes along the side street and turns into the opposite lane of the main road:
/// a straight approach, a quarter circle of radius 6-9 m (left turn from the right-hand side
/// street or right turn from the left-hand one), then straight on. It starts just before the
/// arc, so it rotates during the first frames.
fn turning_car(rng: &mut ChaCha8Rng, st: &Street) -> Body {
    let x = st.pose(st.intersection_s_m, 0.0);
    let left_turn = rng.random_bool(0.5);
    let r = rng.random_range(6.0..9.0);
    let speed = rng.random_range(4.0..6.0);
    let approach_m = 25.0;
    // Arc start in the intersection frame (along, left), heading and curvature; the arc ends
    // heading against the main direction in the opposite lane (left = +1.75).
    let (along, left, yaw, k) = if left_turn {
        (LANE_D_M, LANE_D_M - r, x.yaw + FRAC_PI_2, 1.0 / r)
    } else {
        (-LANE_D_M, LANE_D_M + r, x.yaw - FRAC_PI_2, -1.0 / r)
    };
    let arc_start = Pose2 { yaw, ..x.offset(along, left) };
    let start = arc_start.offset(-approach_m, 0.0);
    let path = Path::new(
        start,
        vec![
            Segment { length_m: approach_m, curvature_per_m: 0.0 },
            Segment { length_m: r * FRAC_PI_2, curvature_per_m: k },
            Segment { length_m: 1.0, curvature_per_m: 0.0 },
        ],
    );
    let u0 = approach_m - rng.random_range(0.0..3.0);
    let motion = Motion::Path { path, u0_m: u0, speed_mps: speed, yaw_offset_rad: 0.0 };
    Body::new(ObjectKind::MovingCar, Behaviour::Turning, motion, car_shapes(rng))
}
