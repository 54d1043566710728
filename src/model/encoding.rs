//! Network inputs: a point and its (fractional) frame time, embedded as NTP does.

use crate::geometry::Point;

/// Number of cosine frequencies of the time embedding for a sequence of `frames` frames:
/// 1 + ceil(log2 T) (6 for T = 25).
pub fn time_frequencies(frames: usize) -> usize {
    1 + (frames.max(1) as f64).log2().ceil() as usize
}

/// Width of one input row: x, y, z and the cosines.
pub fn input_width(frames: usize) -> usize {
    3 + time_frequencies(frames)
}

/// Writes the input rows [x, y, z, cos(2^k pi tau) for k = 0..K-1], tau = (t + 0.5) / T, of
/// every point observed at fractional frame index `t`, into `out` (resized to n x width).
/// Coordinates stay metric, unnormalised (method.md section 1).
pub fn encode_points(points: &[Point], t: f64, frames: usize, out: &mut Vec<f32>) {
    let k_count = time_frequencies(frames);
    let width = 3 + k_count;
    let tau = (t + 0.5) / frames as f64;
    let mut cosines = [0f32; 32];
    for (k, c) in cosines.iter_mut().take(k_count).enumerate() {
        *c = ((1u64 << k) as f64 * std::f64::consts::PI * tau).cos() as f32;
    }
    out.resize(points.len() * width, 0.0);
    for (row, p) in out.chunks_exact_mut(width).zip(points) {
        row[..3].copy_from_slice(p);
        row[3..].copy_from_slice(&cosines[..k_count]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_25_frame_sequence_uses_six_frequencies_and_nine_inputs() {
        assert_eq!(time_frequencies(25), 6);
        assert_eq!(input_width(25), 9);
        assert_eq!(time_frequencies(2), 2);
        assert_eq!(time_frequencies(32), 6);
    }

    #[test]
    fn rows_hold_the_point_then_the_cosines() {
        let mut out = Vec::new();
        encode_points(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], 0.0, 25, &mut out);
        assert_eq!(out.len(), 18);
        assert_eq!(&out[9..12], &[4.0, 5.0, 6.0]);
        let tau = 0.5 / 25.0;
        assert!((out[3] - (std::f64::consts::PI * tau).cos() as f32).abs() < 1e-7);
        assert!((out[8] - (32.0 * std::f64::consts::PI * tau).cos() as f32).abs() < 1e-6);
    }
}
