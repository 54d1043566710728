//! `mbnt bench`: where a fit's time goes, on a simulated sequence, for the faithful and the
//! fast mode side by side: time per iteration split by phase, achieved MLP GFLOP/s against
//! the GEMM throughput measured in the same run, full-fit wall time, peak memory, accuracy.

use std::ops::ControlFlow;
use std::time::Instant;

use anyhow::Context;
use serde::Serialize;

use crate::fit::{FitParams, Method, Mode, PhaseTimes, Sequence, ValidFitParams, fit_sequence};
use crate::geometry::Point;
use crate::metrics::{TrajectoryMetrics, trajectory_metrics};
use crate::nn::matmul::{MatMut, MatRef, Threads, matmul};
use crate::sim::{SimParams, SimSequence, simulate};

/// Arguments of `mbnt bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Simulator seed of the sequence.
    #[arg(long, default_value_t = 100)]
    pub seed: u64,
    /// Frames of the sequence.
    #[arg(long, default_value_t = 25)]
    pub frames: usize,
    /// Method to time (a trajectory method: mbnt or ntp).
    #[arg(long, default_value = "mbnt")]
    pub method: Method,
    /// Iterations timed per mode when not running full fits.
    #[arg(long, default_value_t = 30)]
    pub iterations: usize,
    /// Run complete fits (all iterations, early stopping as configured) and score them.
    #[arg(long)]
    pub full: bool,
    /// Modes to run, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "fast,faithful")]
    pub modes: Vec<Mode>,
    /// Also time each mode at about 10k/30k/100k points per frame and T = 10/25/50.
    #[arg(long)]
    pub scaling: bool,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
    /// Also write the sequence as the faithful fit sees it (after ground removal, range and
    /// height filters and ego-motion removal) into this directory, for the PyTorch reference
    /// timing (`benches/pytorch/`): `points_KKK.npy` (N x 3 float32, metres, frame 0's
    /// coordinates) and `clusters_KKK.npy` (N int32 DBSCAN labels, -1 for noise) per frame.
    #[arg(long)]
    pub export_prepared: Option<std::path::PathBuf>,
}

/// Throughput of one GEMM shape.
#[derive(Debug, Clone, Serialize)]
pub struct GemmResult {
    /// Shape m x k times k x n.
    pub shape: [usize; 3],
    /// Best of several runs, GFLOP/s.
    pub gflops: f64,
}

/// One mode's measurements.
#[derive(Debug, Clone, Serialize)]
pub struct ModeResult {
    /// The mode.
    pub mode: Mode,
    /// Iterations run.
    pub iterations: usize,
    /// Phase times summed over the run (s).
    pub times: PhaseTimes,
    /// Mean wall time of an ordinary (non-validation) iteration (s).
    pub seconds_per_iteration: f64,
    /// Median wall time of an ordinary iteration (s): robust to a short disturbance of the
    /// machine during a long run, where the mean is not.
    pub median_seconds_per_iteration: f64,
    /// Mean wall time of a validation iteration (s), if one ran after the first.
    pub seconds_per_validation: Option<f64>,
    /// MLP GFLOP/s achieved (flops of all passes over their time).
    pub mlp_gflops: f64,
    /// Wall time of the whole fit as run, preparation included (s).
    pub wall_s: f64,
    /// Full-fit wall time: measured with --full, else estimated from the iteration times.
    pub full_fit_s: f64,
    /// Whether `full_fit_s` was measured (true) or estimated.
    pub full_fit_measured: bool,
    /// Peak resident memory during this mode's fit (MiB), from /proc/self/status; the peak is
    /// reset before each mode where the kernel allows it (else it is the process's peak so far).
    pub peak_rss_mib: Option<f64>,
    /// Whether `peak_rss_mib` is this mode's own peak (true) or the process's peak so far.
    pub peak_rss_own: bool,
    /// Rigid tracks the fit found and the time they took (s, inside `wall_s`).
    pub rigid_tracks: usize,
    /// Time spent building the rigid tracks (s).
    pub rigid_tracks_s: f64,
    /// Long-term accuracy (frame 0 to T-1, non-ground points), with --full.
    pub long_term: Option<TrajectoryMetrics>,
    /// The same, dynamic points only.
    pub long_term_dynamic: Option<TrajectoryMetrics>,
    /// Long-term accuracy of the same fit's network alone (its rigid tracks dropped), with --full.
    pub long_term_network: Option<TrajectoryMetrics>,
    /// The same, dynamic points only.
    pub long_term_network_dynamic: Option<TrajectoryMetrics>,
}

/// Scaling measurement: one mode's timings at one sequence size.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingResult {
    /// Frames.
    pub frames: usize,
    /// Mean points per frame fitted (after ground removal and the range and height limits).
    pub points_per_frame: usize,
    /// Wall time of preparation: ground removal, trees, clusters (s).
    pub prepare_s: f64,
    /// The timings (no accuracy: thinned and dense sequences have no ground truth at hand).
    pub timing: ModeResult,
}

/// Everything `mbnt bench` measured.
#[derive(Debug, Clone, Serialize)]
pub struct BenchResult {
    /// Logical CPUs the process may use.
    pub cpus: usize,
    /// GEMM throughput on the MLP's shape and a large square one.
    pub gemm: Vec<GemmResult>,
    /// The measured peak: the best GEMM throughput.
    pub gemm_peak_gflops: f64,
    /// Per mode.
    pub modes: Vec<ModeResult>,
    /// Scaling runs (with --scaling).
    pub scaling: Vec<ScalingResult>,
}

/// Best-of-`reps` throughput of an m x k by k x n product on the rayon pool.
fn gemm_gflops(m: usize, k: usize, n: usize, reps: usize) -> f64 {
    let a: Vec<f32> = (0..m * k).map(|i| ((i % 97) as f32 - 48.0) * 0.01).collect();
    let b: Vec<f32> = (0..k * n).map(|i| ((i % 89) as f32 - 44.0) * 0.01).collect();
    let mut c = vec![0f32; m * n];
    let mut best = f64::INFINITY;
    for _ in 0..reps {
        let clock = Instant::now();
        matmul(
            MatMut::row_major(&mut c, m, n),
            MatRef::row_major(&a, m, k),
            MatRef::row_major(&b, k, n),
            false,
            Threads::Pool,
        );
        best = best.min(clock.elapsed().as_secs_f64());
    }
    std::hint::black_box(&c);
    2.0 * (m * n * k) as f64 / best * 1e-9
}

/// Resets this process's peak resident set size to its current one (Linux `clear_refs` 5), so
/// the next reading is the peak of what runs in between; false where that is not possible.
fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// Peak resident set size (VmHWM) of this process, MiB; None off Linux.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Fits `sequence` in `mode` (`iterations` of them, or a full fit) and times it; scores the
/// result against `sim`'s ground truth when given and the fit is full.
fn run_mode(
    sequence: &Sequence,
    sim: Option<&SimSequence>,
    method: Method,
    mode: Mode,
    iterations: Option<usize>,
) -> anyhow::Result<(ModeResult, crate::model::FitReport)> {
    let params = FitParams { mode: Some(mode), iterations, ..FitParams::default() }.check(method)?;
    let peak_rss_own = reset_peak_rss();
    let mut regular = Vec::new();
    let mut validation = Vec::new();
    let started = Instant::now();
    let mut last = None::<Instant>;
    let mut last_print = Instant::now();
    let model = fit_sequence(sequence, method, &params, &mut |p| {
        if p.rigid_tracks.is_some() {
            // Steps of the rigid-track search after the last iteration, timed in rigid_tracks_s.
            return ControlFlow::Continue(());
        }
        let now = Instant::now();
        // The first iteration's interval would include preparation: skip it.
        if let Some(prev) = last {
            let dt = now.duration_since(prev).as_secs_f64();
            if (p.iteration - 1) % params.validate_every == 0 { validation.push(dt) } else { regular.push(dt) }
        }
        last = Some(now);
        if last_print.elapsed().as_secs_f64() > 15.0 {
            last_print = now;
            eprintln!("  {} iteration {}/{} loss {:.5}", mode.name(), p.iteration, p.iterations, p.loss.total);
        }
        ControlFlow::Continue(())
    })?;
    let wall_s = started.elapsed().as_secs_f64();
    let report = model.report();
    let mean = |v: &[f64]| if v.is_empty() { None } else { Some(v.iter().sum::<f64>() / v.len() as f64) };
    let seconds_per_iteration = mean(&regular).unwrap_or(0.0);
    let median_seconds_per_iteration = median(&mut regular);
    let seconds_per_validation = mean(&validation);
    let times = report.phase_times;
    let full = iterations.is_none();
    let full_fit_s = if full {
        wall_s
    } else {
        // Default iteration count, no early stop assumed: an upper estimate.
        let planned = FitParams { mode: Some(mode), ..FitParams::default() }.check(method)?.iterations;
        let validations = planned.div_ceil(params.validate_every);
        let prep = wall_s - times.total_s;
        prep + seconds_per_iteration * (planned - validations) as f64
            + seconds_per_validation.unwrap_or(seconds_per_iteration) * validations as f64
    };
    let peak_rss_mib = peak_rss_mib();
    let (long_term, long_term_dynamic, long_term_network, long_term_network_dynamic) =
        if let (true, Some(sim)) = (full, sim) {
            let (all, dynamic) = accuracy(sim, sequence, &model, &params)?;
            let (net_all, net_dynamic) = accuracy(sim, sequence, &model.without_tracks()?, &params)?;
            (Some(all), Some(dynamic), Some(net_all), Some(net_dynamic))
        } else {
            (None, None, None, None)
        };
    let result = ModeResult {
        mode,
        iterations: report.iterations,
        mlp_gflops: times.mlp_gflop / (times.mlp_forward_s + times.mlp_backward_s).max(1e-12),
        times,
        seconds_per_iteration,
        median_seconds_per_iteration,
        seconds_per_validation,
        wall_s,
        full_fit_s,
        full_fit_measured: full,
        peak_rss_mib,
        peak_rss_own,
        rigid_tracks: report.rigid_tracks,
        rigid_tracks_s: report.rigid_tracks_seconds,
        long_term,
        long_term_dynamic,
        long_term_network,
        long_term_network_dynamic,
    };
    Ok((result, report.clone()))
}

/// The median of `values` (0 when empty); sorts them.
fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => 0.0,
        n if n % 2 == 1 => values[n / 2],
        n => 0.5 * (values[n / 2 - 1] + values[n / 2]),
    }
}

/// Long-term metrics of frame 0's points at the last frame, on the points `mbnt eval` scores
/// (non-ground, inside the fit's range and height limits): all, and dynamic only.
fn accuracy(
    sim: &SimSequence,
    sequence: &Sequence,
    model: &crate::model::FittedModel,
    params: &ValidFitParams,
) -> anyhow::Result<(TrajectoryMetrics, TrajectoryMetrics)> {
    let t = sim.frames.len();
    let axis = model.time_axis();
    let predicted = model.positions(&sequence.frames[0], axis.frame_time(0), &[axis.frame_time(t - 1)])?;
    let truth = sim.positions_at(0, t - 1)?;
    let dynamic = sim.is_dynamic(0)?;
    let ground: Vec<bool> = sim.truth[0].iter().map(|p| p.is_ground).collect();
    let all = super::eval_cmd::evaluated_in_frame(&sim.frames[0], &ground, params)?;
    let dyn_mask: Vec<bool> = all.iter().zip(&dynamic).map(|(a, d)| *a && *d).collect();
    Ok((trajectory_metrics(&predicted, &truth, Some(&all)), trajectory_metrics(&predicted, &truth, Some(&dyn_mask))))
}

/// Keeps about `fraction` of each frame's points (deterministic stride), for the scaling runs.
fn thin(sim: &SimSequence, fraction: f64) -> Vec<Vec<Point>> {
    let stride = (1.0 / fraction).round().max(1.0) as usize;
    sim.frames.iter().map(|f| f.iter().step_by(stride).copied().collect()).collect()
}

/// Runs `mbnt bench`.
pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.method.is_trajectory(), "mbnt bench times the trajectory methods (mbnt, ntp)");
    let cpus = rayon::current_num_threads();
    eprintln!("measuring GEMM throughput ({cpus} threads)");
    let gemm: Vec<GemmResult> = [[30_000, 128, 128], [1024, 1024, 1024]]
        .into_iter()
        .map(|[m, k, n]| GemmResult { shape: [m, k, n], gflops: gemm_gflops(m, k, n, 7) })
        .collect();
    let gemm_peak_gflops = gemm.iter().map(|g| g.gflops).fold(0.0, f64::max);

    let sim = simulate(&SimParams { seed: args.seed, frames: args.frames, ..SimParams::default() })?;
    eprintln!("simulated seed {}: {} frames, {} points in frame 0", args.seed, sim.frames.len(), sim.frames[0].len());
    if let Some(dir) = &args.export_prepared {
        export_prepared(&sim.to_fit_sequence(), args.method, dir)?;
        eprintln!("wrote the prepared frames to {}", dir.display());
    }
    let mut modes = Vec::new();
    for &mode in &args.modes {
        eprintln!("timing {} in {} mode", args.method.name(), mode.name());
        let iterations = if args.full { None } else { Some(args.iterations) };
        modes.push(run_mode(&sim.to_fit_sequence(), Some(&sim), args.method, mode, iterations)?.0);
    }

    let mut scaling = Vec::new();
    if args.scaling {
        let mut sequences = Vec::new();
        for (frames, fraction) in [(25, 1.0 / 3.0), (25, 1.0), (10, 1.0), (50, 1.0)] {
            let sim = simulate(&SimParams { seed: args.seed, frames, ..SimParams::default() })?;
            sequences.push(Sequence { frames: thin(&sim, fraction), ..sim.to_fit_sequence() });
        }
        sequences.push(simulate(&dense_params(args.seed))?.to_fit_sequence());
        for &mode in &args.modes {
            for sequence in &sequences {
                scaling.push(time_scaling(sequence, args.method, mode, args.iterations)?);
            }
        }
    }

    let result = BenchResult { cpus, gemm, gemm_peak_gflops, modes, scaling };
    print_report(&result);
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_vec_pretty(&result)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Writes the frames of `sequence` as faithful mode prepares them for `method` (see
/// [`BenchArgs::export_prepared`]).
fn export_prepared(sequence: &Sequence, method: Method, dir: &std::path::Path) -> anyhow::Result<()> {
    let params = FitParams { mode: Some(Mode::Faithful), ..FitParams::default() }.check(method)?;
    let poses = crate::fit::fit_frame_poses(sequence, &params)?;
    let (frames, _) = crate::fit::prepare::prepare_frames(sequence, &params, true, false, poses.as_deref())?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    for (k, frame) in frames.iter().enumerate() {
        let n = frame.full.points.len();
        let mut labels = vec![-1i32; n];
        for (c, members) in frame.full.clusters.iter().enumerate() {
            for &i in members {
                labels[i as usize] = c as i32;
            }
        }
        let coords: Vec<f32> = frame.full.points.iter().flatten().copied().collect();
        let (mut points_npy, mut labels_npy) = (Vec::new(), Vec::new());
        crate::io::npy::write_npy_f32(&mut points_npy, &[n, 3], &coords)?;
        crate::io::npy::write_npy_i32(&mut labels_npy, &[n], &labels)?;
        for (name, bytes) in [("points", points_npy), ("clusters", labels_npy)] {
            let path = dir.join(format!("{name}_{k:03}.npy"));
            std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
        }
    }
    Ok(())
}

/// A sequence at about 100k points per frame after ground removal: the default scene seen by
/// a denser sensor (twice the beams, half the azimuth step).
fn dense_params(seed: u64) -> SimParams {
    let mut params = SimParams { seed, frames: 25, ..SimParams::default() };
    params.lidar.beams *= 2;
    params.lidar.azimuth_step_deg /= 2.0;
    params
}

fn time_scaling(sequence: &Sequence, method: Method, mode: Mode, iterations: usize) -> anyhow::Result<ScalingResult> {
    let (timing, report) = run_mode(sequence, None, method, mode, Some(iterations))?;
    let fitted: usize = report.frames.iter().map(|f| f.fitted_points).sum();
    let result = ScalingResult {
        frames: sequence.frames.len(),
        points_per_frame: fitted / sequence.frames.len(),
        prepare_s: timing.wall_s - timing.times.total_s,
        timing,
    };
    eprintln!(
        "  {} T = {}, {} points/frame: {:.3} s/iteration, full fit (est.) {:.0} s",
        mode.name(),
        result.frames,
        result.points_per_frame,
        result.timing.seconds_per_iteration,
        result.timing.full_fit_s
    );
    Ok(result)
}

fn print_report(r: &BenchResult) {
    println!("GEMM ({} threads):", r.cpus);
    for g in &r.gemm {
        println!("  {} x {} x {}: {:.1} GFLOP/s", g.shape[0], g.shape[1], g.shape[2], g.gflops);
    }
    println!("  measured peak: {:.1} GFLOP/s", r.gemm_peak_gflops);
    println!();
    println!(
        "{:<9} {:>6} {:>9} {:>9} | {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} | {:>8} {:>6} | {:>9} {:>8} | {:>6} {:>6} {:>9} {:>9}",
        "mode",
        "iters",
        "s/iter",
        "s/valid",
        "fwd",
        "bwd",
        "nn",
        "multib",
        "cycle",
        "adam",
        "other",
        "GFLOP/s",
        "%peak",
        "full fit",
        "peak MiB",
        "Acc.5",
        "Dyn.5",
        "net Acc.5",
        "net Dyn.5"
    );
    for m in &r.modes {
        let t = &m.times;
        let per = |v: f64| 1000.0 * v / m.iterations.max(1) as f64;
        let other =
            t.total_s - t.mlp_forward_s - t.mlp_backward_s - t.nearest_s - t.multibody_s - t.cycle_s - t.optimiser_s;
        println!(
            "{:<9} {:>6} {:>9.3} {:>9} | {:>7.1} {:>7.1} {:>7.1} {:>7.1} {:>7.1} {:>7.1} {:>7.1} | {:>8.1} {:>5.0}% | {:>8.0}{} {:>8.0} | {:>6} {:>6} {:>9} {:>9}",
            m.mode.name(),
            m.iterations,
            m.seconds_per_iteration,
            m.seconds_per_validation.map_or("-".to_string(), |v| format!("{v:.3}")),
            per(t.mlp_forward_s),
            per(t.mlp_backward_s),
            per(t.nearest_s),
            per(t.multibody_s),
            per(t.cycle_s),
            per(t.optimiser_s),
            per(other),
            m.mlp_gflops,
            100.0 * m.mlp_gflops / r.gemm_peak_gflops,
            m.full_fit_s,
            if m.full_fit_measured { "s" } else { "s*" },
            m.peak_rss_mib.unwrap_or(f64::NAN),
            m.long_term.as_ref().map_or("-".to_string(), |a| format!("{:.2}", 100.0 * a.acc_0_5)),
            m.long_term_dynamic.as_ref().map_or("-".to_string(), |a| format!("{:.2}", 100.0 * a.acc_0_5)),
            m.long_term_network.as_ref().map_or("-".to_string(), |a| format!("{:.2}", 100.0 * a.acc_0_5)),
            m.long_term_network_dynamic.as_ref().map_or("-".to_string(), |a| format!("{:.2}", 100.0 * a.acc_0_5)),
        );
    }
    println!("(phase columns: ms per iteration, averaged over all iterations run, validations included;");
    println!(" s* = full-fit time estimated from the timed iterations; Acc.5 needs --full;");
    println!(" net = the same fit's network alone, its rigid tracks dropped)");
    for m in &r.modes {
        println!(
            "{}: median s/iteration {:.3}; {} rigid tracks in {:.1} s (inside the full fit); peak memory {}",
            m.mode.name(),
            m.median_seconds_per_iteration,
            m.rigid_tracks,
            m.rigid_tracks_s,
            if m.peak_rss_own { "of this mode alone" } else { "of the process so far" }
        );
    }
    if !r.scaling.is_empty() {
        println!();
        println!("scaling: mode, frames, points/frame, preparation s, s/iteration, s/validation, full fit s (est.)");
        for s in &r.scaling {
            let t = &s.timing;
            println!(
                "  {:<9} {:>3} {:>7} {:>8.2} {:>8.3} {:>8.2} {:>8.0}",
                t.mode.name(),
                s.frames,
                s.points_per_frame,
                s.prepare_s,
                t.seconds_per_iteration,
                t.seconds_per_validation.unwrap_or(f64::NAN),
                t.full_fit_s
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::npy::{NpyData, read_npy};

    #[test]
    fn exported_frames_are_the_faithful_fits_points_and_clusters() {
        let sim = simulate(&SimParams { seed: 5, frames: 2, ..SimParams::default() }).unwrap();
        let sequence = sim.to_fit_sequence();
        let dir = tempfile::tempdir().unwrap();
        export_prepared(&sequence, Method::Mbnt, dir.path()).unwrap();

        let params = FitParams { mode: Some(Mode::Faithful), ..FitParams::default() }.check(Method::Mbnt).unwrap();
        let poses = crate::fit::fit_frame_poses(&sequence, &params).unwrap();
        assert!(poses.is_some(), "the simulator gives poses and faithful mode uses them");
        let (frames, _) =
            crate::fit::prepare::prepare_frames(&sequence, &params, true, false, poses.as_deref()).unwrap();
        for (k, frame) in frames.iter().enumerate() {
            let read =
                |name: &str| read_npy(&std::fs::read(dir.path().join(format!("{name}_{k:03}.npy"))).unwrap()).unwrap();
            let (points, labels) = (read("points"), read("clusters"));
            let n = frame.full.points.len();
            assert_eq!((points.shape.clone(), labels.shape.clone()), (vec![n, 3], vec![n]));
            let (NpyData::F32(coords), NpyData::I32(labels)) = (points.data, labels.data) else {
                panic!("points must be float32 and labels int32");
            };
            assert!(coords.chunks_exact(3).zip(&frame.full.points).all(|(a, b)| a == b.as_slice()));
            // Every cluster comes back whole under its own label; the rest is noise (-1).
            assert!(!frame.full.clusters.is_empty());
            for (c, members) in frame.full.clusters.iter().enumerate() {
                assert!(members.iter().all(|&i| labels[i as usize] == c as i32));
                assert_eq!(labels.iter().filter(|&&l| l == c as i32).count(), members.len());
            }
            let clustered: usize = frame.full.clusters.iter().map(Vec::len).sum();
            assert_eq!(labels.iter().filter(|&&l| l == -1).count(), n - clustered);
        }
    }
}
