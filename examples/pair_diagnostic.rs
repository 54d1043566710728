//! Where the scene model loses accuracy on a real pair with ground-truth flow (the protocol of
//! `mbnt eval --real-pair`): per moving object (the dynamic scored points of `pc1`, grouped by
//! DBSCAN at 1 m), its size, true and predicted mean flow, EPE, and the fitted bodies that hold
//! it; then the static scored points that move 5 cm or more, grouped the same way, with the
//! body or free points responsible, and for those a body holds their distance to the second
//! sweep left still and carried by the body (points labelled static that the data shows moving
//! with a car). Free moving points (on no body) are described: how many the fit's
//! pre-processing kept, their distance to the nearest body member, and with
//! `PAIR_DIAG_BOX=1` where they lie in each body's coordinates against its box.
//!
//! ```text
//! cargo run --release --example pair_diagnostic -- ../shared/data/real-pair-icpflow ['{"iterations": 1}']
//! ```

use std::collections::BTreeMap;

use mbnt::cli::real_pair::{PAIR_DT_S, ScoredSet};
use mbnt::fit::{FitParams, Method, Sequence, fit_sequence};
use mbnt::geometry::Point;
use mbnt::geometry::dbscan::{clusters, dbscan};
use mbnt::geometry::rigid::Rigid;
use mbnt::io::flow_pair::FlowPair;

fn mean(points: impl Iterator<Item = Point>) -> [f32; 3] {
    let (mut sum, mut n) = ([0.0f64; 3], 0usize);
    for p in points {
        for c in 0..3 {
            sum[c] += f64::from(p[c]);
        }
        n += 1;
    }
    std::array::from_fn(|c| (sum[c] / n.max(1) as f64) as f32)
}

fn norm(v: [f32; 3]) -> f32 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = args.get(1).map_or("../shared/data/real-pair-icpflow", String::as_str);
    let params: FitParams = serde_json::from_str(args.get(2).map_or(r#"{"iterations": 1}"#, String::as_str))?;
    let params = params.check(Method::Mbnt)?;
    let pair = FlowPair::load(std::path::Path::new(path))?;
    let set = ScoredSet::of(&pair);
    let non_ground =
        |pts: &[Point], ground: &[bool]| pts.iter().zip(ground).filter(|(_, g)| !**g).map(|(p, _)| *p).collect();
    let sequence = Sequence {
        frames: vec![non_ground(&pair.pc1, &pair.ground1), non_ground(&pair.pc2, &pair.ground2)],
        timestamps_s: Some(vec![0.0, PAIR_DT_S]),
        poses: Some(vec![Rigid::identity().to_row_major(); 2]),
    };
    let started = std::time::Instant::now();
    let model = fit_sequence(&sequence, Method::Mbnt, &params, &mut |_| std::ops::ControlFlow::Continue(()))?;
    println!(
        "{} bodies, fit {:.1} s (bodies {:.1} s)",
        model.bodies().len(),
        started.elapsed().as_secs_f64(),
        model.report().rigid_tracks_seconds
    );
    let points: Vec<Point> = set.indices.iter().map(|&i| pair.pc1[i]).collect();
    let moved = model.positions(&points, 0.0, &[PAIR_DT_S])?;
    let flow: Vec<Point> = points.iter().zip(&moved).map(|(p, q)| std::array::from_fn(|c| q[c] - p[c])).collect();
    let owners = model.object_ids(std::slice::from_ref(&points))?[0].clone();
    let truth: Vec<Point> = set.indices.iter().map(|&i| pair.gt_flow[i]).collect();
    let error = |k: usize| norm(std::array::from_fn(|c| flow[k][c] - truth[k][c]));

    // Which scored points the fit's own pre-processing kept (frame 0: the non-ground pc1 points).
    let pre = mbnt::geometry::ground::PreprocessParams::default();
    let (kept, _) = mbnt::geometry::ground::preprocess(&sequence.frames[0], &pre)?;
    let kept_set: std::collections::HashSet<[u32; 3]> =
        kept.iter().map(|&i| sequence.frames[0][i as usize].map(f32::to_bits)).collect();
    let all_members: Vec<Point> = model.bodies().iter().flat_map(|b| b.members[0].iter().copied()).collect();
    let members_tree = mbnt::geometry::knn::KdTree::new(&all_members);
    let report = |title: &str, members: &[usize]| {
        println!("{title}: {} points", members.len());
        let pts: Vec<Point> = members.iter().map(|&k| points[k]).collect();
        let labels = dbscan(&pts, 1.0, 5);
        let mut groups = clusters(&labels);
        groups.sort_by_key(|g| std::cmp::Reverse(g.len()));
        let unclustered = labels.iter().filter(|l| **l < 0).count();
        for group in groups.iter().take(25) {
            let ks: Vec<usize> = group.iter().map(|&g| members[g as usize]).collect();
            let centre = mean(ks.iter().map(|&k| points[k]));
            let t = mean(ks.iter().map(|&k| truth[k]));
            let f = mean(ks.iter().map(|&k| flow[k]));
            let epe = ks.iter().map(|&k| f64::from(error(k))).sum::<f64>() / ks.len() as f64;
            let mut held: BTreeMap<i32, usize> = BTreeMap::new();
            for &k in &ks {
                *held.entry(owners[k]).or_default() += 1;
            }
            let held: Vec<String> = held.iter().map(|(b, n)| format!("{b}:{n}")).collect();
            println!(
                "  ({:>6.1},{:>6.1},{:>5.1}) {:>5} pts  true ({:+.3},{:+.3},{:+.3})  ours ({:+.3},{:+.3},{:+.3})  EPE {:.3}  bodies {}",
                centre[0],
                centre[1],
                centre[2],
                ks.len(),
                t[0],
                t[1],
                t[2],
                f[0],
                f[1],
                f[2],
                epe,
                held.join(",")
            );
            let free: Vec<usize> = ks.iter().copied().filter(|&k| owners[k] < 0).collect();
            if !free.is_empty() {
                let zs: Vec<f32> = free.iter().map(|&k| points[k][2]).collect();
                let held_z =
                    ks.iter().filter(|&&k| owners[k] >= 0).map(|&k| points[k][2]).fold(f32::INFINITY, f32::min);
                let centre_free = mean(free.iter().map(|&k| points[k]));
                if std::env::var("PAIR_DIAG_BOX").is_ok() {
                    for b in model.bodies() {
                        let qs: Vec<Point> = free.iter().map(|&k| b.poses[0].inverse().apply(&points[k])).collect();
                        let lo: Vec<f32> =
                            (0..3).map(|c| qs.iter().map(|q| q[c]).fold(f32::INFINITY, f32::min)).collect();
                        let hi: Vec<f32> =
                            (0..3).map(|c| qs.iter().map(|q| q[c]).fold(f32::NEG_INFINITY, f32::max)).collect();
                        println!(
                            "    body {} box {:?}..{:?}; free in body coords {:?}..{:?}",
                            b.id, b.extent_min_m, b.extent_max_m, lo, hi
                        );
                    }
                }
                let fitted = free.iter().filter(|&&k| kept_set.contains(&points[k].map(f32::to_bits))).count();
                println!("    free: {fitted} of them kept by the fit's pre-processing");
                // Distance to the nearest body member of frame 0, and whether inside a body's box.
                let mut d: Vec<f32> =
                    free.iter().filter_map(|&k| members_tree.nearest(&points[k]).map(|h| h.dist2.sqrt())).collect();
                d.sort_by(f32::total_cmp);
                let inside = free
                    .iter()
                    .filter(|&&k| {
                        model.bodies().iter().any(|b| {
                            let q = b.poses[0].inverse().apply(&points[k]);
                            (0..3).all(|c| q[c] >= b.extent_min_m[c] - 0.1 && q[c] <= b.extent_max_m[c] + 0.1)
                        })
                    })
                    .count();
                println!(
                    "    free: nearest member {:.2} / {:.2} / {:.2} m (min/median/max), {inside} inside a box (+0.1 m)",
                    d[0],
                    d[d.len() / 2],
                    d[d.len() - 1]
                );
                println!(
                    "    free: {} pts, z {:.2}..{:.2} (held from {:.2}), centre ({:.1},{:.1})",
                    free.len(),
                    zs.iter().copied().fold(f32::INFINITY, f32::min),
                    zs.iter().copied().fold(f32::NEG_INFINITY, f32::max),
                    held_z,
                    centre_free[0],
                    centre_free[1]
                );
            }
        }
        println!("  ({unclustered} points in no group)");
    };
    let dynamic: Vec<usize> = (0..points.len()).filter(|&k| set.dynamic[k]).collect();
    report("dynamic", &dynamic);
    let epe = |ks: &[usize]| ks.iter().map(|&k| f64::from(error(k))).sum::<f64>() / ks.len().max(1) as f64;
    let statics: Vec<usize> = (0..points.len()).filter(|&k| !set.dynamic[k]).collect();
    println!("dynamic EPE {:.4} m, static EPE {:.4} m", epe(&dynamic), epe(&statics));
    let static_off: Vec<usize> = (0..points.len()).filter(|&k| !set.dynamic[k] && error(k) >= 0.05).collect();
    let static_all = (0..points.len()).filter(|&k| !set.dynamic[k]).count();
    let on_body = static_off.iter().filter(|&&k| owners[k] >= 0).count();
    println!("static points 5 cm or more off: {} of {static_all} ({on_body} on a body)", static_off.len());
    report("static, off", &static_off);
    {
        // The still test of the bodies for the static points a body holds: distance to the other
        // sweep's fitted points left still and carried by the body.
        let (kept1, _) = mbnt::geometry::ground::preprocess(&sequence.frames[1], &pre)?;
        let f1: Vec<Point> = kept1.iter().map(|&i| sequence.frames[1][i as usize]).collect();
        let tree1 = mbnt::geometry::knn::KdTree::new(&f1);
        let mut rows: Vec<(f32, f32)> = Vec::new();
        for &k in static_off.iter().filter(|&&k| owners[k] >= 0) {
            let b = model.bodies().iter().find(|b| b.id as i32 == owners[k]).unwrap();
            let step = b.poses[1].compose(&b.poses[0].inverse());
            let still = tree1.nearest(&points[k]).map_or(9.0, |h| h.dist2.sqrt());
            let moved = tree1.nearest(&step.apply(&points[k])).map_or(9.0, |h| h.dist2.sqrt());
            rows.push((still, moved));
        }
        rows.sort_by(|a, b| a.0.total_cmp(&b.0));
        let s: Vec<String> = rows.iter().step_by(4).map(|(a, b)| format!("{a:.2}/{b:.2}")).collect();
        println!("  still/moved distances to sweep 1 (every 4th): {}", s.join(" "));
    }
    for body in model.bodies() {
        let step = body.poses[1].compose(&body.poses[0].inverse());
        let c = mean(body.members[0].iter().copied());
        let moved = step.apply(&c);
        println!(
            "body {}: {} + {} members, centre ({:.1},{:.1},{:.1}), step ({:+.3},{:+.3},{:+.3}), turn {:.4} rad",
            body.id,
            body.member_counts[0],
            body.member_counts[1],
            c[0],
            c[1],
            c[2],
            moved[0] - c[0],
            moved[1] - c[1],
            moved[2] - c[2],
            step.angle_rad()
        );
    }
    Ok(())
}
