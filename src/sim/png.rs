//! A top-down picture of one frame, so that a person can see the scene: points coloured by the
//! kind of body they hit, the ego as a white triangle, encoded as PNG bytes.

use super::{ObjectKind, SimError, SimSequence};

/// Half the side of the square shown (m), centred on the sensor.
pub const TOP_DOWN_HALF_EXTENT_M: f64 = 50.0;

const BACKGROUND: [u8; 3] = [16, 16, 16];

fn colour(kind: ObjectKind, dynamic: bool) -> [u8; 3] {
    match kind {
        ObjectKind::Ground => [85, 85, 85],
        ObjectKind::Building => [70, 130, 220],
        ObjectKind::Pole => [240, 230, 80],
        ObjectKind::Tree => [60, 190, 60],
        ObjectKind::ParkedCar => [230, 150, 40],
        ObjectKind::MovingCar if dynamic => [235, 40, 40],
        ObjectKind::MovingCar => [230, 150, 40],
        ObjectKind::Pedestrian => [230, 60, 230],
    }
}

/// Renders frame `k` seen from above as an RGB PNG of `size_px` x `size_px` (16 to 8192).
///
/// The view is the sensor frame of sweep k: forward (+x) points up, left (+y) points left, and
/// the square spans +-50 m around the sensor. Ground points are grey and drawn first; buildings
/// blue, poles yellow, trees green, parked cars orange, moving cars red, pedestrians magenta.
pub fn render_top_down_png(seq: &SimSequence, k: usize, size_px: u32) -> Result<Vec<u8>, SimError> {
    if !(16..=8192).contains(&size_px) {
        return Err(SimError::InvalidParams(format!("size_px = {size_px} must be in 16..=8192")));
    }
    seq.check_frame(k)?;
    let n = size_px as usize;
    let mut rgb = vec![0u8; n * n * 3];
    for px in rgb.chunks_exact_mut(3) {
        px.copy_from_slice(&BACKGROUND);
    }
    let px_per_m = n as f64 / (2.0 * TOP_DOWN_HALF_EXTENT_M);
    let centre = n as f64 / 2.0;
    let to_pixel = |x: f64, y: f64| -> Option<(usize, usize)> {
        let col = (centre - y * px_per_m).floor();
        let row = (centre - x * px_per_m).floor();
        (col >= 0.0 && row >= 0.0 && col < n as f64 && row < n as f64).then_some((row as usize, col as usize))
    };
    let put = |rgb: &mut [u8], row: usize, col: usize, c: [u8; 3]| {
        let i = 3 * (row * n + col);
        rgb[i..i + 3].copy_from_slice(&c);
    };
    // Ground first, so that objects are drawn over it.
    for ground_pass in [true, false] {
        for (p, t) in seq.frames[k].iter().zip(&seq.truth[k]) {
            if t.is_ground != ground_pass {
                continue;
            }
            let o = &seq.objects[t.object_id as usize];
            if let Some((row, col)) = to_pixel(p[0] as f64, p[1] as f64) {
                put(&mut rgb, row, col, colour(o.kind, o.dynamic));
            }
        }
    }
    // The ego: a white triangle 4.5 m long, 2 m wide, nose forward.
    let (len_m, half_w_m) = (4.5, 1.0);
    let steps = (len_m * px_per_m * 2.0).ceil().max(2.0) as usize;
    for i in 0..=steps {
        let x = len_m * (0.5 - i as f64 / steps as f64);
        let half = half_w_m * i as f64 / steps as f64;
        let w_steps = (2.0 * half * px_per_m * 2.0).ceil().max(1.0) as usize;
        for j in 0..=w_steps {
            let y = -half + 2.0 * half * j as f64 / w_steps as f64;
            if let Some((row, col)) = to_pixel(x, y) {
                put(&mut rgb, row, col, [255, 255, 255]);
            }
        }
    }
    let mut bytes = Vec::new();
    let mut encoder = ::png::Encoder::new(&mut bytes, size_px, size_px);
    encoder.set_color(::png::ColorType::Rgb);
    encoder.set_depth(::png::BitDepth::Eight);
    let encode = |e: ::png::EncodingError| SimError::Encode(e.to_string());
    let mut writer = encoder.write_header().map_err(encode)?;
    writer.write_image_data(&rgb).map_err(encode)?;
    writer.finish().map_err(encode)?;
    Ok(bytes)
}
