//! Per-sequence preparation done once before any iteration: ground removal and range
//! filtering, a k-d tree per frame, DBSCAN clusters per frame (for the multi-body loss).

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use super::{FitError, Sequence, ValidFitParams};
use crate::geometry::Point;
use crate::geometry::dbscan::{clusters, dbscan};
use crate::geometry::ground::{FilterReport, GroundParamsError, PreprocessParams, preprocess};
use crate::geometry::knn::KdTree;
use crate::geometry::rigid::Rigid;
use crate::model::FrameReport;

/// A point set with its tree and clusters: a whole frame, or one random part of it.
pub struct PointSet {
    /// The points (metric, sensor frame of this sweep).
    pub points: Vec<Point>,
    /// Tree over `points`, built once, queried by the Chamfer terms of neighbouring frames.
    pub tree: KdTree,
    /// DBSCAN clusters (indices into `points`), empty without a rigidity term. Clusters of a
    /// part are the frame's clusters restricted to it (those with more than 2 points left).
    pub clusters: Vec<Vec<u32>>,
}

/// One frame ready for fitting.
pub struct PreparedFrame {
    /// All points the fit uses.
    pub full: PointSet,
    /// When subsampling (`sample_points` > 0 and smaller than the frame): a random partition of
    /// the frame into parts of about `sample_points` points, each with its own tree, drawn once.
    /// An iteration uses one random part per frame; validation always uses part 0.
    pub parts: Vec<PointSet>,
}

impl PreparedFrame {
    /// The point set for part `part` (the whole frame when there are no parts).
    pub fn part(&self, part: usize) -> &PointSet {
        self.parts.get(part).unwrap_or(&self.full)
    }

    /// Number of parts an iteration may draw from (1 when the frame is not split).
    pub fn part_count(&self) -> usize {
        self.parts.len().max(1)
    }
}

/// Splits a frame into random parts of about `sample_points` points (none when it is smaller).
fn split_into_parts(full: &PointSet, sample_points: usize, seed: u64) -> Vec<PointSet> {
    let n = full.points.len();
    if sample_points == 0 || n <= sample_points {
        return Vec::new();
    }
    let mut order: Vec<u32> = (0..n as u32).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let part_count = n.div_ceil(sample_points);
    // Cluster id of every point, to restrict clusters to a part without a search.
    let mut cluster_of = vec![u32::MAX; n];
    for (c, members) in full.clusters.iter().enumerate() {
        for &i in members {
            cluster_of[i as usize] = c as u32;
        }
    }
    (0..part_count)
        .map(|p| {
            // Near-equal parts: part p takes every part_count-th point of the shuffled order.
            let members: Vec<u32> = order.iter().skip(p).step_by(part_count).copied().collect();
            let points: Vec<Point> = members.iter().map(|&i| full.points[i as usize]).collect();
            let mut clusters = vec![Vec::new(); full.clusters.len()];
            for (local, &i) in members.iter().enumerate() {
                let c = cluster_of[i as usize];
                if c != u32::MAX {
                    clusters[c as usize].push(local as u32);
                }
            }
            clusters.retain(|c: &Vec<u32>| c.len() > 2);
            PointSet { tree: KdTree::new(&points), points, clusters }
        })
        .collect()
}

/// Prepares every frame (in parallel over frames). `with_parts` splits frames into random
/// parts of `params.sample_points`; `to_fit_frame` (one transform per frame) moves the kept
/// points into a common frame. Fails when a frame has no point left.
pub fn prepare_frames(
    sequence: &Sequence,
    params: &ValidFitParams,
    with_clusters: bool,
    with_parts: bool,
    to_fit_frame: Option<&[Rigid]>,
) -> Result<(Vec<PreparedFrame>, Vec<FrameReport>), FitError> {
    let pre = PreprocessParams {
        remove_ground: params.remove_ground,
        max_range_m: params.max_range_m,
        ..PreprocessParams::default()
    };
    let prepared: Vec<(PreparedFrame, FrameReport)> = sequence
        .frames
        .par_iter()
        .enumerate()
        .map(|(k, frame)| {
            let (kept, filter): (Vec<u32>, FilterReport) = preprocess(frame, &pre)?;
            // Filters work in the sensor's own coordinates (range, height over the local ground);
            // the kept points then move to the fit's frame (frame 0's, ego motion removed).
            let points: Vec<Point> = match to_fit_frame {
                Some(poses) => kept.iter().map(|&i| poses[k].apply(&frame[i as usize])).collect(),
                None => kept.iter().map(|&i| frame[i as usize]).collect(),
            };
            let tree = KdTree::new(&points);
            let clusters = if with_clusters {
                let labels = dbscan(&points, params.dbscan_eps_m, params.dbscan_min_points);
                clusters(&labels).into_iter().filter(|c| c.len() > 2).collect()
            } else {
                Vec::new()
            };
            let report = FrameReport {
                input_points: frame.len(),
                ground_points: filter.ground,
                out_of_range_points: filter.out_of_range,
                fitted_points: points.len(),
                clusters: clusters.len(),
                clustered_points: clusters.iter().map(Vec::len).sum(),
            };
            let full = PointSet { points, tree, clusters };
            let sample = if with_parts { params.sample_points } else { 0 };
            let parts = split_into_parts(&full, sample, params.seed.wrapping_add(k as u64));
            Ok((PreparedFrame { full, parts }, report))
        })
        .collect::<Result<_, GroundParamsError>>()
        .map_err(|e| FitError::InvalidSequence(format!("ground removal: {e}")))?;
    if let Some(k) = prepared.iter().position(|(f, _)| f.full.points.is_empty()) {
        return Err(FitError::InvalidSequence(format!(
            "frame {k} has no point left after ground removal and range filtering"
        )));
    }
    Ok(prepared.into_iter().unzip())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_partition_the_frame_and_restrict_its_clusters() {
        let points: Vec<Point> = (0..1000).map(|i| [i as f32 * 0.01, (i % 7) as f32, 0.0]).collect();
        let clusters = vec![(0..300).collect::<Vec<u32>>(), (500..505).collect()];
        let full = PointSet { tree: KdTree::new(&points), points, clusters };
        let parts = split_into_parts(&full, 256, 3);
        assert_eq!(parts.len(), 4);
        let mut seen: Vec<Point> = parts.iter().flat_map(|p| p.points.iter().copied()).collect();
        seen.sort_by(|a, b| a[0].total_cmp(&b[0]));
        assert_eq!(seen, full.points, "every point in exactly one part");
        for part in &parts {
            assert!((240..=260).contains(&part.points.len()), "{}", part.points.len());
            // The first cluster (x < 3 m) survives in every part with only its own members.
            let first = &part.clusters[0];
            assert!(first.len() > 50);
            assert!(first.iter().all(|&i| part.points[i as usize][0] < 3.0));
            let in_first = part.points.iter().filter(|p| p[0] < 3.0).count();
            assert_eq!(first.len(), in_first);
        }
        assert_eq!(split_into_parts(&full, 256, 3).len(), 4);
        assert!(split_into_parts(&full, 0, 3).is_empty());
        assert!(split_into_parts(&full, 5000, 3).is_empty());
    }
}
