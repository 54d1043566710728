//! Accuracy metrics of method.md section 5: scene flow of one frame pair, and long-term
//! trajectories from frame 0 to frame T-1, with the research code's bugs fixed (its relative
//! clause is computed on the true label norm, not an element-wise square).

use serde::{Deserialize, Serialize};

use crate::geometry::Point;

/// Scene-flow metrics of one frame pair (or their average over pairs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneFlowMetrics {
    /// Mean end-point error (m).
    pub epe_m: f64,
    /// Share of points with error < 0.05 m or relative error < 5 %.
    pub acc_strict: f64,
    /// Share of points with error < 0.10 m or relative error < 10 %.
    pub acc_relaxed: f64,
    /// Share of points with error > 0.3 m or relative error > 10 %.
    pub outliers: f64,
    /// Mean angle between predicted and true flow (rad); a zero vector counts pi/2.
    pub angle_rad: f64,
    /// Number of points evaluated.
    pub points: usize,
}

/// Long-term trajectory metrics (positions of frame 0's points at frame T-1).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryMetrics {
    /// Mean end-point error (m).
    pub epe_m: f64,
    /// Share of points with error < 0.5 m.
    pub acc_0_5: f64,
    /// Share of points with error < 1.0 m.
    pub acc_1_0: f64,
    /// Number of points evaluated.
    pub points: usize,
}

fn norm(v: &Point) -> f64 {
    let [x, y, z] = v.map(f64::from);
    (x * x + y * y + z * z).sqrt()
}

fn sub(a: &Point, b: &Point) -> Point {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Angle between two vectors (rad); pi/2 when either is zero, as the method defines.
fn angle_between(a: &Point, b: &Point) -> f64 {
    let (na, nb) = (norm(a), norm(b));
    if na == 0.0 || nb == 0.0 {
        return std::f64::consts::FRAC_PI_2;
    }
    let dot: f64 = a.iter().zip(b).map(|(x, y)| f64::from(*x) * f64::from(*y)).sum();
    (dot / (na * nb)).clamp(-1.0, 1.0).acos()
}

/// Scene-flow metrics of predicted vs true flow vectors (m) of one frame's points, restricted
/// to `mask` when given. An empty selection yields all-zero metrics with `points == 0`.
pub fn scene_flow_metrics(pred: &[Point], truth: &[Point], mask: Option<&[bool]>) -> SceneFlowMetrics {
    assert_eq!(pred.len(), truth.len(), "one prediction per labelled point");
    let mut m = SceneFlowMetrics::default();
    for (i, (p, g)) in pred.iter().zip(truth).enumerate() {
        if mask.is_some_and(|mk| !mk[i]) {
            continue;
        }
        let err = norm(&sub(p, g));
        let gt_norm = norm(g);
        // A zero label has no scale: an exact answer has relative error 0, any other infinity.
        let rel = if gt_norm > 0.0 {
            err / gt_norm
        } else if err == 0.0 {
            0.0
        } else {
            f64::INFINITY
        };
        m.epe_m += err;
        m.acc_strict += f64::from(u8::from(err < 0.05 || rel < 0.05));
        m.acc_relaxed += f64::from(u8::from(err < 0.10 || rel < 0.10));
        m.outliers += f64::from(u8::from(err > 0.3 || rel > 0.10));
        m.angle_rad += angle_between(p, g);
        m.points += 1;
    }
    if m.points > 0 {
        let n = m.points as f64;
        m.epe_m /= n;
        m.acc_strict /= n;
        m.acc_relaxed /= n;
        m.outliers /= n;
        m.angle_rad /= n;
    }
    m
}

/// Averages per-pair metrics over pairs (each pair counts once, whatever its size), skipping
/// pairs that evaluated no point.
pub fn average_over_pairs(pairs: &[SceneFlowMetrics]) -> SceneFlowMetrics {
    let used: Vec<_> = pairs.iter().filter(|m| m.points > 0).collect();
    let mut avg = SceneFlowMetrics::default();
    if used.is_empty() {
        return avg;
    }
    let n = used.len() as f64;
    for m in &used {
        avg.epe_m += m.epe_m / n;
        avg.acc_strict += m.acc_strict / n;
        avg.acc_relaxed += m.acc_relaxed / n;
        avg.outliers += m.outliers / n;
        avg.angle_rad += m.angle_rad / n;
        avg.points += m.points;
    }
    avg
}

/// Long-term metrics of predicted vs true end positions (m), restricted to `mask` when given.
pub fn trajectory_metrics(pred: &[Point], truth: &[Point], mask: Option<&[bool]>) -> TrajectoryMetrics {
    assert_eq!(pred.len(), truth.len(), "one prediction per labelled point");
    let mut m = TrajectoryMetrics::default();
    for (i, (p, g)) in pred.iter().zip(truth).enumerate() {
        if mask.is_some_and(|mk| !mk[i]) {
            continue;
        }
        let err = norm(&sub(p, g));
        m.epe_m += err;
        m.acc_0_5 += f64::from(u8::from(err < 0.5));
        m.acc_1_0 += f64::from(u8::from(err < 1.0));
        m.points += 1;
    }
    if m.points > 0 {
        let n = m.points as f64;
        m.epe_m /= n;
        m.acc_0_5 /= n;
        m.acc_1_0 /= n;
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_flow_metrics_match_a_hand_computed_example() {
        let truth = [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0]];
        let pred = [
            [1.04, 0.0, 0.0], // err 0.04: strict and relaxed
            [0.0, 2.15, 0.0], // err 0.15, rel 7.5 %: relaxed only, not an outlier
            [0.0, 0.0, 0.0],  // err 0 on a zero label: accurate, angle pi/2
            [10.0, 0.5, 0.0], // err 0.5, rel 5 % (not < 5 %): relaxed by rel, outlier by err
        ];
        let m = scene_flow_metrics(&pred, &truth, None);
        assert_eq!(m.points, 4);
        assert!((m.epe_m - (0.04 + 0.15 + 0.0 + 0.5) / 4.0).abs() < 1e-6);
        assert!((m.acc_strict - 0.5).abs() < 1e-12);
        assert!((m.acc_relaxed - 1.0).abs() < 1e-12);
        assert!((m.outliers - 0.25).abs() < 1e-12);
        let angle4 = (0.5f64 / 10.0).atan();
        let expected_angle = (0.0 + 0.0 + std::f64::consts::FRAC_PI_2 + angle4) / 4.0;
        assert!((m.angle_rad - expected_angle).abs() < 1e-5, "{} vs {expected_angle}", m.angle_rad);
    }

    #[test]
    fn the_relative_clause_uses_the_true_label_norm() {
        // err 0.3 on a 4 m flow: rel 7.5 % < 10 %, so accurate under Acc.10 although err > 0.1 m.
        // The research code's element-wise square would compare against 16 and also pass; on a
        // 0.5 m flow with err 0.04 both agree. The discriminating case: flow (2, 2, 0), err 0.25:
        // rel = 0.25 / 2.83 = 8.8 % < 10 %; the buggy norm sqrt(2^4 + 2^4) = 5.66 would give 4.4 %
        // and also count it under Acc.05.
        let m = scene_flow_metrics(&[[2.25, 2.0, 0.0]], &[[2.0, 2.0, 0.0]], None);
        assert_eq!(m.acc_relaxed, 1.0);
        assert_eq!(m.acc_strict, 0.0);
    }

    #[test]
    fn trajectory_metrics_respect_the_mask_and_thresholds() {
        let truth = [[0.0; 3]; 3];
        let pred = [[0.4, 0.0, 0.0], [0.0, 0.7, 0.0], [0.0, 0.0, 3.0]];
        let all = trajectory_metrics(&pred, &truth, None);
        assert!((all.acc_0_5 - 1.0 / 3.0).abs() < 1e-12);
        assert!((all.acc_1_0 - 2.0 / 3.0).abs() < 1e-12);
        assert!((all.epe_m - 4.1 / 3.0).abs() < 1e-6);
        let masked = trajectory_metrics(&pred, &truth, Some(&[false, true, false]));
        assert_eq!(masked.points, 1);
        assert_eq!(masked.acc_0_5, 0.0);
        assert_eq!(masked.acc_1_0, 1.0);
    }

    #[test]
    fn pairs_are_averaged_with_equal_weight() {
        let a = SceneFlowMetrics { epe_m: 1.0, points: 10, ..Default::default() };
        let b = SceneFlowMetrics { epe_m: 3.0, points: 1000, ..Default::default() };
        let empty = SceneFlowMetrics::default();
        let avg = average_over_pairs(&[a, b, empty]);
        assert!((avg.epe_m - 2.0).abs() < 1e-12);
        assert_eq!(avg.points, 1010);
    }
}
