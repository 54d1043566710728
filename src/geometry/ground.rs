//! Map-free ground removal and the range/height pre-filter of method.md section 7.
//!
//! The research code subtracts a map raster (|z − h| ≤ 0.3 m); mbnt has no map, so the ground
//! height h is estimated from the points of the frame itself:
//! 1. an x-y grid (`cell_m`) collects the points; each occupied cell's candidate height is a low
//!    quantile of its z (robust to a few stray returns below the road, and picks the road rather
//!    than a car side when a cell holds both);
//! 2. candidates far below their neighbourhood are dropped (pits: stray returns under the road,
//!    mirror images; see `reject_pits`): below three quarters of a 5 x 5 window, or below a neighbour
//!    with fewer than three cells of a 9 x 9 window at their own height;
//! 3. the remaining candidates are replaced by their lower slope envelope
//!    h(c) = min over cells c' of h0(c') + `max_slope` · dist(c, c'),
//!    computed exactly for the 8-neighbour chamfer metric by two raster sweeps. A cell holding
//!    only a car roof, a wall or a trunk therefore gets the height of the ground next to it plus at
//!    most the allowed slope, while a road rising slower than `max_slope` keeps its own height;
//! 4. a point is ground when z − h(cell) ≤ `tolerance_m` (points below the estimate, i.e. stray
//!    returns under the road, count as ground too).
//!
//! Cost: O(n) for the grid plus O(cells) for the pit test (81 reads per occupied cell) and the
//! sweeps; 5-15 ms per 124k-point KITTI frame (test profile, busy 2-core host). Coordinates are
//! the sensor frame of the sweep, z up.

use serde::{Deserialize, Serialize};

use super::Point;

/// Largest grid the estimate may allocate (cells); 2^22 f32 cells are 16 MiB.
pub const MAX_GRID_CELLS: usize = 1 << 22;

/// The default [`GroundParams::tolerance_m`] (m): 0.3 m as the research code. Nothing of a
/// fitted frame lies this close above the ground, which the scene model's bodies allow for.
pub const GROUND_TOLERANCE_M: f32 = 0.3;

/// Parameters of the local ground estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GroundParams {
    /// Side of a grid cell (m). 0.5 m resolves curbs and car sides while a near-range cell still
    /// holds dozens of returns.
    pub cell_m: f32,
    /// A point at most this far above the local ground is ground (m); [`GROUND_TOLERANCE_M`] by default.
    pub tolerance_m: f32,
    /// Largest ground slope followed by the estimate (rise per run, m/m). 0.2 (11°) covers steep
    /// streets and ramps; walls and vehicles are far steeper.
    pub max_slope: f32,
    /// Quantile of z in a cell taken as its candidate ground height, in [0, 1]. 0.1 ignores
    /// one stray low return among ten.
    pub cell_quantile: f32,
    /// A cell whose candidate lies more than this below most of its 5 x 5 neighbourhood is a
    /// pit (stray returns under the road, mirror images) and is ignored (m). 0.5 m: well above
    /// curbs and road camber within 2.5 m.
    pub pit_depth_m: f32,
    /// Ground is estimated only within this x-y half-width around the sensor (m); points beyond
    /// it are never ground. Bounds the grid whatever far outliers a frame holds.
    pub grid_half_extent_m: f32,
}

impl Default for GroundParams {
    fn default() -> Self {
        Self {
            cell_m: 0.5,
            tolerance_m: GROUND_TOLERANCE_M,
            max_slope: 0.2,
            cell_quantile: 0.1,
            pit_depth_m: 0.5,
            grid_half_extent_m: 100.0,
        }
    }
}

/// Parameters of the pre-processing filter applied before fitting (method.md section 7).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PreprocessParams {
    /// Remove ground points (default true).
    pub remove_ground: bool,
    /// The ground estimate (also used for `max_height_m`).
    pub ground: GroundParams,
    /// Points farther than this from the sensor origin (3-D distance, m) are dropped. 80 m.
    pub max_range_m: f32,
    /// Points higher than this above the local ground (m) are dropped. 4 m.
    ///
    /// Measured from the estimated local ground rather than the sensor: the research code's
    /// z ≤ 4 m is in a frame whose origin sits on the ground (Argoverse ego frame), while KITTI's
    /// sensor is 1.73 m up; height over local ground means the same thing for every sensor.
    pub max_height_m: f32,
}

impl Default for PreprocessParams {
    fn default() -> Self {
        Self { remove_ground: true, ground: GroundParams::default(), max_range_m: 80.0, max_height_m: 4.0 }
    }
}

/// What [`preprocess`] did to a frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FilterReport {
    /// Points in the input.
    pub input: usize,
    /// Points removed as ground.
    pub ground: usize,
    /// Points removed for range, height or a non-finite coordinate.
    pub out_of_range: usize,
    /// Points kept (`input − ground − out_of_range`).
    pub kept: usize,
}

/// Invalid ground or pre-processing parameters.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GroundParamsError {
    /// A parameter is NaN or outside its range.
    #[error("ground parameter {name} = {value} is outside {range}")]
    OutOfRange {
        /// Parameter name.
        name: &'static str,
        /// The rejected value.
        value: f32,
        /// The accepted range, for the message.
        range: &'static str,
    },
    /// `grid_half_extent_m / cell_m` asks for more than [`MAX_GRID_CELLS`] cells.
    #[error("ground grid of {cells} cells exceeds {max}: raise cell_m or lower grid_half_extent_m")]
    GridTooLarge {
        /// Cells requested.
        cells: f64,
        /// The limit.
        max: usize,
    },
}

fn check(name: &'static str, value: f32, ok: bool, range: &'static str) -> Result<(), GroundParamsError> {
    if ok { Ok(()) } else { Err(GroundParamsError::OutOfRange { name, value, range }) }
}

impl GroundParams {
    /// Validates the parameters (NaN fails every check).
    pub fn validate(&self) -> Result<(), GroundParamsError> {
        check("cell_m", self.cell_m, self.cell_m > 0.0 && self.cell_m.is_finite(), "(0, inf)")?;
        check("tolerance_m", self.tolerance_m, self.tolerance_m >= 0.0 && self.tolerance_m.is_finite(), "[0, inf)")?;
        check("max_slope", self.max_slope, self.max_slope >= 0.0 && self.max_slope.is_finite(), "[0, inf)")?;
        check("cell_quantile", self.cell_quantile, (0.0..=1.0).contains(&self.cell_quantile), "[0, 1]")?;
        check("pit_depth_m", self.pit_depth_m, self.pit_depth_m >= 0.0, "[0, inf]")?;
        let h = self.grid_half_extent_m;
        check("grid_half_extent_m", h, h > 0.0 && h.is_finite(), "(0, inf)")?;
        let side = (2.0 * h as f64 / self.cell_m as f64).ceil() + 1.0;
        if side * side > MAX_GRID_CELLS as f64 {
            return Err(GroundParamsError::GridTooLarge { cells: side * side, max: MAX_GRID_CELLS });
        }
        Ok(())
    }
}

impl PreprocessParams {
    /// Validates the parameters; infinite `max_range_m` / `max_height_m` disable those limits.
    pub fn validate(&self) -> Result<(), GroundParamsError> {
        self.ground.validate()?;
        check("max_range_m", self.max_range_m, self.max_range_m > 0.0, "(0, inf]")?;
        check("max_height_m", self.max_height_m, self.max_height_m > 0.0, "(0, inf]")
    }
}

/// The local ground of one sweep: the height h(cell) of every cell of its x-y grid (see the
/// module doc), to be asked at any point of the sweep's coordinates.
#[derive(Debug, Clone)]
pub struct GroundEstimate {
    grid: Grid,
    /// Per cell (row-major, x fastest): the ground height (m); +inf where nothing says.
    height_m: Vec<f32>,
}

impl GroundEstimate {
    /// The ground estimated from `points` (sensor coordinates, z up); `None` when no point is
    /// finite. O(n + cells).
    pub fn new(points: &[Point], params: &GroundParams) -> Result<Option<Self>, GroundParamsError> {
        params.validate()?;
        let Some(grid) = Grid::new(points, params) else {
            return Ok(None);
        };
        let n_cells = grid.nx * grid.ny;
        // Counting sort of z by cell: offsets, then the z values cell after cell.
        let cell_of: Vec<u32> = points.iter().map(|p| grid.cell(p).map_or(u32::MAX, |c| c as u32)).collect();
        let mut start = vec![0u32; n_cells + 1];
        for &c in &cell_of {
            if c != u32::MAX {
                start[c as usize + 1] += 1;
            }
        }
        for c in 0..n_cells {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut z_sorted = vec![0.0f32; start[n_cells] as usize];
        for (p, &c) in points.iter().zip(&cell_of) {
            if c != u32::MAX {
                z_sorted[fill[c as usize] as usize] = p[2];
                fill[c as usize] += 1;
            }
        }
        drop(fill);
        let mut h = vec![f32::INFINITY; n_cells];
        for c in 0..n_cells {
            let zs = &mut z_sorted[start[c] as usize..start[c + 1] as usize];
            if zs.is_empty() {
                continue;
            }
            let k = ((zs.len() - 1) as f32 * params.cell_quantile).floor() as usize;
            let (_, z, _) = zs.select_nth_unstable_by(k, f32::total_cmp);
            h[c] = *z;
        }
        reject_pits(&mut h, grid.nx, grid.ny, params.pit_depth_m);
        slope_envelope(&mut h, grid.nx, grid.ny, params.max_slope * params.cell_m);
        Ok(Some(Self { grid, height_m: h }))
    }

    /// Height (m) of `p` above the ground under it: z − h(cell). `None` outside the grid, for a
    /// non-finite point, or where the sweep saw no ground at all.
    pub fn height_above(&self, p: &Point) -> Option<f32> {
        let h = self.height_m[self.grid.cell(p)?];
        h.is_finite().then(|| p[2] - h)
    }
}

/// Height of every point above the estimated local ground (m): z − h(cell). NaN for points with
/// a non-finite coordinate or outside the grid (`grid_half_extent_m`). See the module doc.
pub fn height_above_ground(points: &[Point], params: &GroundParams) -> Result<Vec<f32>, GroundParamsError> {
    let Some(ground) = GroundEstimate::new(points, params)? else {
        return Ok(vec![f32::NAN; points.len()]);
    };
    Ok(points.iter().map(|p| ground.grid.cell(p).map_or(f32::NAN, |c| p[2] - ground.height_m[c])).collect())
}

/// Ground flags: true where a point lies at most `tolerance_m` above the local ground estimate
/// (or below it). Points outside the grid or non-finite are not ground. O(n + cells).
pub fn ground_mask(points: &[Point], params: &GroundParams) -> Result<Vec<bool>, GroundParamsError> {
    let heights = height_above_ground(points, params)?;
    Ok(heights.iter().map(|&dz| dz <= params.tolerance_m).collect())
}

/// Pre-filters a frame before fitting: drops non-finite points and points beyond `max_range_m`
/// (counted as out of range), then ground points when `remove_ground` is set, then points higher
/// than `max_height_m` above the local ground (out of range). Returns the kept indices in
/// increasing order and the counts. O(n + cells).
pub fn preprocess(points: &[Point], params: &PreprocessParams) -> Result<(Vec<u32>, FilterReport), GroundParamsError> {
    params.validate()?;
    let heights = height_above_ground(points, &params.ground)?;
    let max_r2 = params.max_range_m as f64 * params.max_range_m as f64;
    let mut report = FilterReport { input: points.len(), ..FilterReport::default() };
    let mut kept = Vec::with_capacity(points.len());
    for (i, (p, &dz)) in points.iter().zip(&heights).enumerate() {
        let r2: f64 = p.iter().map(|&c| c as f64 * c as f64).sum();
        let in_range = r2 <= max_r2 && p.iter().all(|c| c.is_finite());
        if !in_range {
            report.out_of_range += 1;
        } else if params.remove_ground && dz <= params.ground.tolerance_m {
            report.ground += 1;
        } else if dz > params.max_height_m {
            report.out_of_range += 1;
        } else {
            kept.push(i as u32);
        }
    }
    report.kept = kept.len();
    Ok((kept, report))
}

/// The occupied part of the x-y grid: the bounding box of the finite points clipped to the
/// half-extent square around the sensor.
#[derive(Debug, Clone)]
struct Grid {
    x0: f32,
    y0: f32,
    inv_cell: f32,
    nx: usize,
    ny: usize,
}

impl Grid {
    fn new(points: &[Point], params: &GroundParams) -> Option<Grid> {
        let r = params.grid_half_extent_m;
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for p in points.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
            for k in 0..2 {
                let v = p[k].clamp(-r, r);
                lo[k] = lo[k].min(v);
                hi[k] = hi[k].max(v);
            }
        }
        if lo[0] > hi[0] {
            return None;
        }
        let inv_cell = 1.0 / params.cell_m;
        // validate() bounds these by the full square's side.
        let nx = ((hi[0] - lo[0]) * inv_cell).floor() as usize + 1;
        let ny = ((hi[1] - lo[1]) * inv_cell).floor() as usize + 1;
        Some(Grid { x0: lo[0], y0: lo[1], inv_cell, nx, ny })
    }

    /// Row-major cell index (x fastest) of a point, `None` outside the grid or non-finite.
    fn cell(&self, p: &Point) -> Option<usize> {
        let fx = (p[0] - self.x0) * self.inv_cell;
        let fy = (p[1] - self.y0) * self.inv_cell;
        // Negated comparisons reject NaN as well.
        if !(fx >= 0.0 && fy >= 0.0) {
            return None;
        }
        let (ix, iy) = (fx as usize, fy as usize);
        (ix < self.nx && iy < self.ny).then_some(iy * self.nx + ix)
    }
}

/// Window radius (cells) of the majority test: 5 x 5 cells, 2.5 m at the default cell size.
const PIT_WINDOW: usize = 2;

/// Window radius (cells) of the support test: 9 x 9 cells, 4.5 m at the default cell size, so
/// that a stray return between two scan rings (about 2.5 m apart at 25 m for an HDL-64E) still
/// sees the road on both sides.
const SUPPORT_WINDOW: usize = 4;

/// Fewest cells (itself included) of its window at a cell's own height (within `depth_m`) that
/// a candidate lying below a neighbour needs to seed the envelope. Stray returns come one to
/// three at a spot (KITTI 00 frames 0-5: 1-3 returns 5-11 m down, in one or two cells), while
/// the road is seen by many cells along each scan ring.
const MIN_SUPPORT_CELLS: usize = 3;

/// Clears (sets to +inf) the candidate of every cell that lies more than `depth_m` below its
/// neighbourhood, by either of two tests (windows include the cell itself):
/// - the majority test: fewer than a quarter of the occupied cells of its 5 x 5 window are at
///   most `depth_m` above it;
/// - the support test: some occupied cell of its 9 x 9 window is more than `depth_m` above it,
///   and fewer than [`MIN_SUPPORT_CELLS`] cells of that window are within `depth_m` of its height.
///
/// The envelope spreads every low value over a cone, so one stray return under the road (KITTI
/// frame 0 has one 10 m down) would otherwise pull the ground down for tens of metres. The
/// majority test alone misses stray returns where the window is sparse: at 25 m an HDL-64E's
/// ground rings are about 2.5 m apart, so a window may hold only 5-8 occupied cells, and two
/// adjacent stray cells (KITTI frame 3) are then a quarter of them; the support test catches
/// those, since a real patch of ground is seen by more than two cells. A genuine ground cell has
/// ground neighbours at its own height; if it is hemmed in by objects, clearing it only lets the
/// envelope of the cells beyond take over. A cell alone in its window is kept: nothing says it
/// is low.
fn reject_pits(h: &mut [f32], nx: usize, ny: usize, depth_m: f32) {
    let h0 = h.to_vec();
    for y in 0..ny {
        for x in 0..nx {
            let here = h0[y * nx + x];
            if here == f32::INFINITY {
                continue;
            }
            // Majority counts over the inner window; support counts over the outer one.
            let (mut occupied, mut level) = (0usize, 0usize);
            let (mut higher, mut similar) = (0usize, 0usize);
            for wy in y.saturating_sub(SUPPORT_WINDOW)..(y + SUPPORT_WINDOW + 1).min(ny) {
                let (x_lo, x_hi) = (x.saturating_sub(SUPPORT_WINDOW), (x + SUPPORT_WINDOW + 1).min(nx));
                for (wx, &v) in (x_lo..x_hi).zip(&h0[wy * nx + x_lo..wy * nx + x_hi]) {
                    if v == f32::INFINITY {
                        continue;
                    }
                    let is_level = v <= here + depth_m;
                    higher += usize::from(!is_level);
                    similar += usize::from(is_level && v >= here - depth_m);
                    if wx.abs_diff(x) <= PIT_WINDOW && wy.abs_diff(y) <= PIT_WINDOW {
                        occupied += 1;
                        level += usize::from(is_level);
                    }
                }
            }
            if 4 * level < occupied || (higher > 0 && similar < MIN_SUPPORT_CELLS) {
                h[y * nx + x] = f32::INFINITY;
            }
        }
    }
}

/// In place: h(c) ← min over c' of h(c') + step · d(c, c'), with d the 8-neighbour chamfer
/// distance in cells (1 axis-aligned, √2 diagonal). Two sweeps suffice for this metric (the
/// classic two-pass distance transform, here with arbitrary initial values). Empty cells are +inf
/// and only carry the envelope across gaps.
fn slope_envelope(h: &mut [f32], nx: usize, ny: usize, step: f32) {
    let diag = step * std::f32::consts::SQRT_2;
    for y in 0..ny {
        for x in 0..nx {
            let i = y * nx + x;
            let mut v = h[i];
            if x > 0 {
                v = v.min(h[i - 1] + step);
            }
            if y > 0 {
                let up = i - nx;
                v = v.min(h[up] + step);
                if x > 0 {
                    v = v.min(h[up - 1] + diag);
                }
                if x + 1 < nx {
                    v = v.min(h[up + 1] + diag);
                }
            }
            h[i] = v;
        }
    }
    for y in (0..ny).rev() {
        for x in (0..nx).rev() {
            let i = y * nx + x;
            let mut v = h[i];
            if x + 1 < nx {
                v = v.min(h[i + 1] + step);
            }
            if y + 1 < ny {
                let down = i + nx;
                v = v.min(h[down] + step);
                if x + 1 < nx {
                    v = v.min(h[down + 1] + diag);
                }
                if x > 0 {
                    v = v.min(h[down - 1] + diag);
                }
            }
            h[i] = v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Axis-aligned box: min and max corners (m).
    struct Boxx {
        lo: Point,
        hi: Point,
    }

    impl Boxx {
        /// Whether the segment from the sensor (origin) to `p` passes through the box (slab test):
        /// the ground behind a box is in its shadow.
        #[allow(clippy::needless_range_loop)] // the slab test reads three arrays per axis
        fn occludes(&self, p: &Point) -> bool {
            let (mut t0, mut t1) = (0.0f32, 0.999f32);
            for k in 0..3 {
                if p[k].abs() < 1e-9 {
                    if 0.0 < self.lo[k] || 0.0 > self.hi[k] {
                        return false;
                    }
                    continue;
                }
                let (a, b) = (self.lo[k] / p[k], self.hi[k] / p[k]);
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
            t0 <= t1
        }

        /// Random points on the box faces visible from the origin (a crude LiDAR view).
        fn surface(&self, n: usize, rng: &mut ChaCha8Rng) -> Vec<Point> {
            let mut pts = Vec::new();
            while pts.len() < n {
                let face = rng.random_range(0..5);
                let mut p: Point = std::array::from_fn(|k| rng.random_range(self.lo[k]..self.hi[k]));
                match face {
                    0 => p[0] = self.lo[0],
                    1 => p[0] = self.hi[0],
                    2 => p[1] = self.lo[1],
                    3 => p[1] = self.hi[1],
                    _ => p[2] = self.hi[2],
                }
                let pull = [p[0] * 0.999, p[1] * 0.999, p[2] * 0.999];
                if !self.occludes(&pull) {
                    pts.push(p);
                }
            }
            pts
        }
    }

    /// A ground surface z = f(x, y) sampled on LiDAR-like rings out to 40 m, minus the shadows of
    /// `boxes`, plus points on the boxes. Returns the points and, per point, whether it is ground.
    fn scene(ground: impl Fn(f32, f32) -> f32, boxes: &[Boxx], seed: u64) -> (Vec<Point>, Vec<bool>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut pts = Vec::new();
        let mut truth = Vec::new();
        let mut r = 3.0f32;
        while r < 40.0 {
            for k in 0..1000 {
                let a = k as f32 / 1000.0 * std::f32::consts::TAU + rng.random_range(0.0..0.006);
                let (x, y) = (r * a.cos(), r * a.sin());
                // ±2 cm range noise on the ground, as a real sensor.
                let p = [x, y, ground(x, y) + rng.random_range(-0.02..0.02)];
                if !boxes.iter().any(|b| b.occludes(&p)) {
                    pts.push(p);
                    truth.push(true);
                }
            }
            r *= 1.04;
        }
        for b in boxes {
            for p in b.surface(800, &mut rng) {
                pts.push(p);
                truth.push(false);
            }
        }
        (pts, truth)
    }

    fn car(x: f32, y: f32, z: f32) -> Boxx {
        Boxx { lo: [x, y, z + 0.2], hi: [x + 4.2, y + 1.8, z + 1.5] }
    }

    /// Every true ground point is found, and every object point well above the true ground is kept.
    fn check_scene(pts: &[Point], truth: &[bool], ground: impl Fn(f32, f32) -> f32) {
        let params = GroundParams::default();
        let mask = ground_mask(pts, &params).unwrap();
        let missed = pts.iter().zip(truth).zip(&mask).filter(|&((_, &t), &m)| t && !m).count();
        let n_ground = truth.iter().filter(|&&t| t).count();
        // All ground points: the envelope is exact on a surface that rises slower than max_slope.
        assert_eq!(missed, 0, "{missed} of {n_ground} ground points kept");
        // Object points 0.55 m above the true ground are kept: under a box the estimate may sit one
        // diagonal slope step (0.2 · 0.5 · √2 ≈ 0.14 m) above a neighbouring ground cell, whose own
        // estimate is off by at most the ground's rise across a cell (≤ 0.05 m) and the 2 cm noise:
        // 0.3 + 0.14 + 0.05 + 0.02 ≈ 0.51 m, rounded up.
        for ((p, &t), &m) in pts.iter().zip(truth).zip(&mask) {
            if !t && p[2] - ground(p[0], p[1]) > 0.55 {
                assert!(!m, "object point {p:?} taken as ground");
            }
        }
    }

    #[test]
    fn a_flat_plane_with_boxes_loses_its_plane_and_keeps_its_boxes() {
        let z = |_: f32, _: f32| -1.73;
        // The wall stands where no car shadows the ground in front of it: behind a car the ground
        // is unobserved and no map-free estimate can tell the wall's foot from the road.
        let wall = Boxx { lo: [-10.0, 15.0, -1.73], hi: [10.0, 15.5, 3.0] };
        let boxes = [car(6.0, 2.0, -1.73), car(-12.0, -4.0, -1.73), wall];
        let (mut pts, mut truth) = scene(z, &boxes, 1);
        // A stray return 10 m under the road (KITTI frame 0 has one) must not drag the ground
        // estimate down around it, or the road within ~50 m would stop being ground.
        pts.push([-20.0, 20.0, -11.73]);
        truth.push(true);
        check_scene(&pts, &truth, z);
    }

    /// A flat road z = -1.73 seen as an HDL-64E sees it: rings whose spacing grows with range
    /// (2.5 m at 25 m), 2000 returns per ring, out to 45 m.
    fn sparse_ring_road(seed: u64) -> Vec<Point> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut pts = Vec::new();
        let mut r = 4.0f32;
        while r < 45.0 {
            for k in 0..2000 {
                let a = k as f32 / 2000.0 * std::f32::consts::TAU + rng.random_range(0.0..0.003);
                pts.push([r * a.cos(), r * a.sin(), -1.73 + rng.random_range(-0.02..0.02)]);
            }
            r *= 1.1;
        }
        pts
    }

    #[test]
    fn a_few_returns_ten_metres_under_the_road_do_not_move_the_ground_estimate() {
        let road = sparse_ring_road(3);
        let params = GroundParams::default();
        let before = height_above_ground(&road, &params).unwrap();
        // As in KITTI 00 frames 0-5: pairs and triples of returns at one spot about 10 m down,
        // here between two rings (the rings near 24 m are 2.3 m apart), in adjacent cells.
        let strays: [Point; 7] = [
            [23.8, 0.1, -11.7],
            [23.8, 0.6, -11.7],
            [-13.6, 4.4, -7.0],
            [-13.6, 4.4, -7.0],
            [-13.6, 4.4, -7.0],
            [2.0, -31.5, -12.0],
            [2.3, -31.5, -12.1],
        ];
        let mut with_strays = road.clone();
        with_strays.extend(strays);
        let after = height_above_ground(&with_strays, &params).unwrap();
        // Every road point keeps its height above the estimate: the strays seed nothing.
        let moved = before.iter().zip(&after).filter(|(a, b)| (*a - *b).abs() > 1e-6).count();
        assert_eq!(moved, 0, "{moved} of {} road points moved", road.len());
        // And the road is ground, within the 2 cm noise of its own estimate.
        assert!(before.iter().all(|h| h.abs() <= 0.05), "{:?}", before.iter().map(|h| h.abs()).fold(0.0, f32::max));
    }

    #[test]
    fn a_sloped_road_is_ground_and_a_car_on_it_is_not() {
        // An 8 % grade along x and a 2 % camber along y.
        let z = |x: f32, y: f32| -1.73 + 0.08 * x + 0.02 * y;
        // Each car's flat bottom clears the highest ground under its footprint (the far corner).
        let boxes = [car(8.0, -3.0, z(12.2, -1.2)), car(-15.0, 3.0, z(-10.8, 4.8))];
        let (pts, truth) = scene(z, &boxes, 2);
        check_scene(&pts, &truth, z);
    }

    #[test]
    fn the_estimate_asked_anywhere_agrees_with_the_heights_of_the_points_it_came_from() {
        let z = |x: f32, y: f32| -1.73 + 0.08 * x + 0.02 * y;
        let boxes = [car(8.0, -3.0, z(12.2, -1.2))];
        let (pts, _) = scene(z, &boxes, 4);
        let params = GroundParams::default();
        let heights = height_above_ground(&pts, &params).unwrap();
        let ground = GroundEstimate::new(&pts, &params).unwrap().expect("finite points");
        for (p, &h) in pts.iter().zip(&heights) {
            assert_eq!(ground.height_above(p), Some(h), "{p:?}");
        }
        // Between the returns, over the road: the road's own height, within the 2 cm noise and
        // a cell's rise (0.08 * 0.5 + 0.02 * 0.5 m).
        for &(x, y) in &[(5.3f32, 7.1f32), (-20.2, 3.3), (14.0, -15.5)] {
            let h = ground.height_above(&[x, y, z(x, y) + 1.0]).expect("inside the grid");
            assert!((h - 1.0).abs() < 0.08, "({x}, {y}): {h:.3} m up, 1 m expected");
        }
        // Outside the grid and non-finite: no answer.
        assert_eq!(ground.height_above(&[500.0, 0.0, 0.0]), None);
        assert_eq!(ground.height_above(&[f32::NAN, 0.0, 0.0]), None);
        assert!(GroundEstimate::new(&[], &params).unwrap().is_none());
    }

    #[test]
    fn invalid_parameters_are_errors() {
        let pts = [[0.0f32, 0.0, 0.0]];
        for bad in [
            GroundParams { cell_m: 0.0, ..Default::default() },
            GroundParams { cell_m: f32::NAN, ..Default::default() },
            GroundParams { tolerance_m: -0.1, ..Default::default() },
            GroundParams { max_slope: f32::INFINITY, ..Default::default() },
            GroundParams { cell_quantile: 1.5, ..Default::default() },
            GroundParams { grid_half_extent_m: 1e6, ..Default::default() },
        ] {
            assert!(ground_mask(&pts, &bad).is_err(), "{bad:?}");
        }
        for bad in [
            PreprocessParams { max_range_m: f32::NAN, ..Default::default() },
            PreprocessParams { max_height_m: 0.0, ..Default::default() },
        ] {
            assert!(preprocess(&pts, &bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn edge_cases_are_handled() {
        let p = GroundParams::default();
        assert!(ground_mask(&[], &p).unwrap().is_empty());
        // A single point is its own ground.
        assert_eq!(ground_mask(&[[1.0, 1.0, 5.0]], &p).unwrap(), vec![true]);
        let pts = [[0.0, 0.0, -1.7], [f32::NAN, 0.0, 0.0], [500.0, 0.0, -1.7], [0.2, 0.1, 1.0], [90.0, 0.0, 0.0]];
        assert_eq!(ground_mask(&pts, &p).unwrap(), vec![true, false, false, false, true]);
        let (kept, report) = preprocess(&pts, &PreprocessParams::default()).unwrap();
        assert_eq!(kept, vec![3]);
        assert_eq!(report, FilterReport { input: 5, ground: 1, out_of_range: 3, kept: 1 });
        let keep_ground = PreprocessParams { remove_ground: false, ..Default::default() };
        let (kept, report) = preprocess(&pts, &keep_ground).unwrap();
        assert_eq!(kept, vec![0, 3]);
        assert_eq!(report.ground, 0);
        // Without a range limit, far points stay but non-finite ones still go.
        let unlimited = PreprocessParams { max_range_m: f32::INFINITY, ..Default::default() };
        let with_inf = [[0.0, 0.0, -1.7], [f32::INFINITY, 0.0, 0.0], [0.2, 0.1, 1.0], [90.0, 0.0, 0.5]];
        let (kept, report) = preprocess(&with_inf, &unlimited).unwrap();
        assert_eq!(kept, vec![2]);
        assert_eq!(report, FilterReport { input: 4, ground: 2, out_of_range: 1, kept: 1 });
    }

    #[test]
    fn points_high_above_the_ground_are_dropped() {
        let mut pts: Vec<Point> = (0..400).map(|i| [(i % 20) as f32 * 0.5, (i / 20) as f32 * 0.5, -1.7]).collect();
        pts.push([5.0, 5.0, -1.7 + 3.9]);
        pts.push([5.0, 5.2, -1.7 + 4.2]);
        let (kept, report) = preprocess(&pts, &PreprocessParams::default()).unwrap();
        assert_eq!(kept, vec![400]);
        assert_eq!(report, FilterReport { input: 402, ground: 400, out_of_range: 1, kept: 1 });
    }

    pub(crate) fn read_kitti(path: &std::path::Path) -> Option<Vec<Point>> {
        let bytes = std::fs::read(path).ok()?;
        let floats: Vec<f32> = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        Some(floats.chunks_exact(4).map(|c| [c[0], c[1], c[2]]).collect())
    }

    /// Precision and recall of our ground flags against labelled ones.
    fn precision_recall(ours: &[bool], labelled: &[bool]) -> (f64, f64) {
        let both = ours.iter().zip(labelled).filter(|&(&o, &l)| o && l).count() as f64;
        let n_ours = ours.iter().filter(|&&o| o).count() as f64;
        let n_labelled = labelled.iter().filter(|&&l| l).count() as f64;
        (both / n_ours, both / n_labelled)
    }

    #[test]
    fn ground_share_is_steady_over_the_six_real_kitti_frames() {
        let dir = std::path::Path::new("../shared/data/kitti-odometry-00");
        let frames: Vec<Vec<Point>> = (0..6).filter_map(|k| read_kitti(&dir.join(format!("{k:06}.bin")))).collect();
        if frames.len() < 6 {
            eprintln!("skipped: the six frames of {} not found", dir.display());
            return;
        }
        let params = PreprocessParams::default();
        let mut shares = Vec::new();
        for (k, pts) in frames.iter().enumerate() {
            let started = std::time::Instant::now();
            let (_, report) = preprocess(pts, &params).unwrap();
            let ms = started.elapsed().as_secs_f64() * 1e3;
            let share = report.ground as f64 / report.input as f64;
            eprintln!("KITTI frame {k}: {report:?}, ground share {share:.4}, {ms:.1} ms");
            shares.push(share);
        }
        // Consecutive sweeps 0.1 s apart see the same street: the ground share may not jump.
        for k in 1..shares.len() {
            assert!((shares[k] - shares[k - 1]).abs() <= 0.05, "frames {} and {k}: shares {shares:?}", k - 1);
        }
        // An HDL-64E street frame has 40-65 % of its returns on the road and sidewalks.
        assert!(shares.iter().all(|s| (0.4..0.65).contains(s)), "{shares:?}");
    }

    /// The real pair of `../shared/data/real-pair-icpflow`: the two sweeps, 0.1 s apart, get the
    /// same share of ground. Precision and recall against the file's `ground1`/`ground2` are
    /// printed, not asserted: those flags are independent of the points (they flag 16 % of the
    /// all-NaN padding rows too, and 16 % of the points in every height band), so no geometric
    /// estimate can match them; docs/benchmarks.md section 9 has the figures.
    #[test]
    fn ground_share_is_steady_over_the_real_pair() {
        let path = std::path::Path::new("../shared/data/real-pair-icpflow/demo.npz");
        if !path.exists() {
            eprintln!("skipped: {} not found", path.display());
            return;
        }
        let pair = crate::io::flow_pair::FlowPair::load(path).unwrap();
        let params = GroundParams::default();
        let ours1 = ground_mask(&pair.pc1, &params).unwrap();
        let ours2 = ground_mask(&pair.pc2, &params).unwrap();
        let share = |m: &[bool]| m.iter().filter(|&&g| g).count() as f64 / m.len() as f64;
        let ours: Vec<bool> = ours1.iter().chain(&ours2).copied().collect();
        let labelled: Vec<bool> = pair.ground1.iter().chain(&pair.ground2).copied().collect();
        let (precision, recall) = precision_recall(&ours, &labelled);
        eprintln!(
            "real pair: ground share {:.4} / {:.4}; against the file's flags ({} of {} points): precision {precision:.4}, \
             recall {recall:.4}",
            share(&ours1),
            share(&ours2),
            labelled.iter().filter(|&&l| l).count(),
            labelled.len()
        );
        assert!((share(&ours1) - share(&ours2)).abs() <= 0.05, "{} vs {}", share(&ours1), share(&ours2));
    }

    #[test]
    fn ground_removal_on_kitti_frame_0_is_sane() {
        let path = std::path::Path::new("../shared/data/kitti-odometry-00/000000.bin");
        let Some(pts) = read_kitti(path) else {
            println!("skipped: {} not found", path.display());
            return;
        };
        let params = PreprocessParams::default();
        let heights = height_above_ground(&pts, &params.ground).unwrap();
        let mask = ground_mask(&pts, &params.ground).unwrap();
        let (kept, report) = preprocess(&pts, &params).unwrap();
        let removed = mask.iter().filter(|&&g| g).count() as f32 / pts.len() as f32;
        println!("KITTI frame 0: {report:?}, ground share {removed:.3}");
        let near = |p: &Point| p[0].hypot(p[1]) < 15.0;
        let low: Vec<bool> = pts.iter().zip(&mask).filter(|(p, _)| near(p) && p[2] < -1.4).map(|(_, &g)| g).collect();
        let low_ground = low.iter().filter(|&&g| g).count() as f32 / low.len() as f32;
        let high: Vec<bool> = pts.iter().zip(&mask).filter(|(p, _)| near(p) && p[2] > -0.9).map(|(_, &g)| g).collect();
        let high_kept = high.iter().filter(|&&g| !g).count() as f32 / high.len() as f32;
        println!(
            "near low points ground {low_ground:.3} of {}, near high points kept {high_kept:.3} of {}",
            low.len(),
            high.len()
        );
        let spread: Vec<f32> = heights.iter().copied().filter(|h| h.is_finite()).collect();
        assert_eq!(spread.len(), pts.len());
        assert_eq!(report.kept, kept.len());
        assert_eq!(report.input, report.ground + report.out_of_range + report.kept);
        // In an HDL-64E urban frame 40-65 % of the returns hit the road and sidewalks.
        assert!((0.35..0.7).contains(&removed), "ground share {removed}");
        // Near the car, the road is at z ≈ −1.73: almost all points below −1.4 m are ground.
        assert!(low_ground > 0.95, "{low_ground}");
        // Points 0.8 m above the nearby road (cars, walls, poles) are kept.
        assert!(high_kept > 0.98, "{high_kept}");
    }
}
