//! Queue and worker behaviour, driven step by step with `Worker::try_execute_next`.

use std::ops::ControlFlow;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use super::*;
use crate::fit::{FitParams, LossTerms};
use crate::store::{JobFilter, JobStatus, SequenceMeta, SqliteStore};

/// Reports `steps` slow iterations of its own (stopping on `Break`), then runs the real fit:
/// a fit long enough to be cancelled or interrupted.
struct SlowFitter {
    steps: usize,
    step: Duration,
}

impl Fitter for SlowFitter {
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        for iteration in 1..=self.steps {
            std::thread::sleep(self.step);
            let p = Progress {
                iteration,
                iterations: self.steps,
                loss: LossTerms::default(),
                best_validation_loss: None,
                validation_loss: None,
                fewest_live_units: None,
                rigid_tracks: None,
                window: None,
            };
            if on_progress(&p).is_break() {
                return Err(FitError::Cancelled { iteration });
            }
        }
        CoreFitter.fit(sequence, method, params, on_progress)
    }
}

struct PanickingFitter;

impl Fitter for PanickingFitter {
    fn fit(
        &self,
        _: &Sequence,
        _: Method,
        _: &ValidFitParams,
        _: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        panic!("a bug in the fit")
    }
}

/// Runs the real fit, then gives the model a moving body whose pose at frame 1 is NaN: what a
/// runaway extrapolation produced before models were checked (issue 21).
struct PoisoningFitter;

impl Fitter for PoisoningFitter {
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        let model = CoreFitter.fit(sequence, method, params, on_progress)?;
        let mut runaway = crate::geometry::rigid::Rigid::identity();
        runaway.rotation[0][0] = f64::NAN;
        let body = crate::model::MovingBody {
            id: 3,
            poses: vec![crate::geometry::rigid::Rigid::identity(), runaway],
            observed: vec![true, false],
            members: vec![vec![[0.0; 3]], vec![]],
            member_counts: vec![1, 0],
            extent_min_m: [-1.0; 3],
            extent_max_m: [1.0; 3],
        };
        Ok(model.with_bodies(vec![body]))
    }
}

struct Fixture {
    dir: std::path::PathBuf,
    queue: Arc<JobQueue>,
    sequence: Uuid,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// A store with one small sequence: two frames of a 10 x 10 x 2 grid, the second shifted.
fn fixture() -> Fixture {
    let dir = std::env::temp_dir().join(format!("mbnt-jobs-{}", Uuid::new_v4()));
    let store = SqliteStore::open(&dir).unwrap();
    let grid: Vec<[f32; 3]> =
        (0..200).map(|i| [(i % 10) as f32 * 0.3, ((i / 10) % 10) as f32 * 0.3, (i / 100) as f32 * 0.5 + 1.0]).collect();
    let mut sink = store.begin_sequence().unwrap();
    sink.put_frame(&grid).unwrap();
    sink.put_frame(&grid.iter().map(|p| [p[0] + 0.1, p[1], p[2]]).collect::<Vec<_>>()).unwrap();
    let sequence = sink.commit(SequenceMeta::default()).unwrap().id;
    Fixture { dir, queue: JobQueue::new(Arc::new(store)), sequence }
}

fn tiny_params(method: Method) -> ValidFitParams {
    FitParams { iterations: Some(3), hidden_width: Some(16), hidden_layers: Some(2), ..FitParams::default() }
        .check(method)
        .unwrap()
}

fn worker(f: &Fixture, fitter: impl Fitter) -> (Worker, Arc<AtomicBool>) {
    let shutdown = Arc::new(AtomicBool::new(false));
    (Worker::new(f.queue.clone(), Arc::new(fitter), 1, shutdown.clone()).unwrap(), shutdown)
}

fn wait_until_running(queue: &JobQueue, id: Uuid) {
    for _ in 0..1000 {
        if queue.store().get_job(id).unwrap().unwrap().status == JobStatus::Running {
            return;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    panic!("job {id} never started");
}

#[test]
fn a_submitted_job_runs_to_success_and_stores_a_loadable_model() {
    let f = fixture();
    let (w, _) = worker(&f, CoreFitter);
    let job = JobQueue::new_job(f.sequence, Method::Ntp, tiny_params(Method::Ntp));
    f.queue.submit(&job).unwrap();
    let done = w.try_execute_next().unwrap().unwrap();
    assert_eq!(done.id, job.id);
    assert_eq!(done.status, JobStatus::Succeeded, "{:?}", done.error);
    assert_eq!((done.progress.fraction, done.attempts), (1.0, 1));
    assert!(done.started_at_ms.is_some() && done.finished_at_ms.is_some());
    let model = FittedModel::from_bytes(&f.queue.store().read_model(job.id).unwrap()).unwrap();
    assert_eq!(model.time_axis().frames(), 2);
    assert!(f.queue.stats().iterations_total() > 0);
    assert!(w.try_execute_next().unwrap().is_none(), "the queue is empty");
}

#[test]
fn a_panicking_fit_fails_the_job_and_the_worker_goes_on() {
    let f = fixture();
    let (w, _) = worker(&f, PanickingFitter);
    for _ in 0..2 {
        f.queue.submit(&JobQueue::new_job(f.sequence, Method::Mbnt, tiny_params(Method::Mbnt))).unwrap();
    }
    for _ in 0..2 {
        let done = w.try_execute_next().unwrap().unwrap();
        assert_eq!(done.status, JobStatus::Failed);
        assert!(done.error.unwrap().contains("internal error"));
    }
}

#[test]
fn a_fit_whose_model_holds_a_nan_fails_the_job_naming_the_part_and_stores_no_model() {
    let f = fixture();
    let (w, _) = worker(&f, PoisoningFitter);
    let job = JobQueue::new_job(f.sequence, Method::Ntp, tiny_params(Method::Ntp));
    f.queue.submit(&job).unwrap();
    let done = w.try_execute_next().unwrap().unwrap();
    assert_eq!(done.status, JobStatus::Failed);
    assert_eq!(done.error.as_deref(), Some("model not saved: moving body 3, pose at frame 1 is not finite"));
    assert!(matches!(f.queue.store().read_model(job.id), Err(crate::store::StoreError::Missing(_))));
}

#[test]
fn cancelling_a_running_job_stops_its_fit() {
    let f = fixture();
    let (w, _) = worker(&f, SlowFitter { steps: 100_000, step: Duration::from_millis(1) });
    let job = JobQueue::new_job(f.sequence, Method::Ntp, tiny_params(Method::Ntp));
    f.queue.submit(&job).unwrap();
    let mut events = f.queue.subscribe(job.id);
    std::thread::scope(|s| {
        let run = s.spawn(|| w.try_execute_next());
        wait_until_running(&f.queue, job.id);
        let CancelOutcome::Accepted(flagged) = f.queue.cancel(job.id).unwrap() else { panic!("not accepted") };
        assert!(flagged.cancel_requested);
        let done = run.join().unwrap().unwrap().unwrap();
        assert_eq!(done.status, JobStatus::Cancelled);
        assert!(done.progress.iteration < 100_000);
    });
    // The watcher's last state is the terminal one.
    assert!(events.has_changed().unwrap_or(true));
    assert_eq!(events.borrow_and_update().as_ref().unwrap().status, JobStatus::Cancelled);
}

#[test]
fn a_shutdown_puts_the_running_job_back_in_the_queue_and_it_runs_again() {
    let f = fixture();
    let (w, shutdown) = worker(&f, SlowFitter { steps: 100_000, step: Duration::from_millis(1) });
    let job = JobQueue::new_job(f.sequence, Method::Ntp, tiny_params(Method::Ntp));
    f.queue.submit(&job).unwrap();
    std::thread::scope(|s| {
        let run = s.spawn(|| w.try_execute_next());
        wait_until_running(&f.queue, job.id);
        shutdown.store(true, Ordering::Relaxed);
        let stopped = run.join().unwrap().unwrap().unwrap();
        assert_eq!(stopped.status, JobStatus::Queued);
    });
    let (w2, _) = worker(&f, SlowFitter { steps: 3, step: Duration::from_millis(1) });
    let done = w2.try_execute_next().unwrap().unwrap();
    // The orderly hand-back gave its attempt back: attempts count runs that died or ended.
    assert_eq!((done.id, done.status, done.attempts), (job.id, JobStatus::Succeeded, 1));
}

/// Runs the real fit, but the first time stops it (as a killed worker would stop) once
/// `stop_at` iterations are done.
struct StopOnce {
    stop_at: usize,
    stopped: AtomicBool,
}

impl Fitter for StopOnce {
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        CoreFitter.fit(sequence, method, params, on_progress)
    }

    fn fit_resuming(
        &self,
        sequence: &dyn crate::fit::FrameSource,
        method: Method,
        params: &ValidFitParams,
        finished: &mut dyn crate::fit::windows::FinishedWindows,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        CoreFitter.fit_resuming(sequence, method, params, finished, &mut |p| {
            if p.iteration >= self.stop_at && !self.stopped.swap(true, Ordering::Relaxed) {
                return ControlFlow::Break(());
            }
            on_progress(p)
        })
    }
}

fn fixture_with(settings: WorkerSettings) -> Fixture {
    let mut f = fixture();
    f.queue = JobQueue::with_settings(f.queue.store().clone(), settings);
    f
}

#[test]
fn a_job_stopped_after_a_checkpoint_goes_on_from_it_and_ends_with_the_same_network() {
    let settings = WorkerSettings { checkpoint_every: Duration::ZERO, ..WorkerSettings::default() };
    let f = fixture_with(settings);
    let params = FitParams {
        iterations: Some(30),
        validate_every: Some(5),
        validation_patience: Some(0),
        hidden_width: Some(16),
        hidden_layers: Some(2),
        ..FitParams::default()
    }
    .check(Method::Ntp)
    .unwrap();
    let whole = JobQueue::new_job(f.sequence, Method::Ntp, params.clone());
    f.queue.submit(&whole).unwrap();
    let (w, _) = worker(&f, CoreFitter);
    let whole = w.try_execute_next().unwrap().unwrap();
    assert_eq!((whole.status, whole.progress.resumed_from_iteration), (JobStatus::Succeeded, None));

    let job = JobQueue::new_job(f.sequence, Method::Ntp, params);
    f.queue.submit(&job).unwrap();
    let (w, _) = worker(&f, StopOnce { stop_at: 23, stopped: AtomicBool::new(false) });
    let stopped = w.try_execute_next().unwrap().unwrap();
    assert_eq!(stopped.status, JobStatus::Queued);
    let resumed = w.try_execute_next().unwrap().unwrap();
    // The checkpoint before iteration 23 was taken at the start of validation iteration 20.
    assert_eq!((resumed.status, resumed.progress.resumed_from_iteration), (JobStatus::Succeeded, Some(20)));

    let load = |id| FittedModel::from_bytes(&f.queue.store().read_model(id).unwrap()).unwrap();
    let (a, b) = (load(whole.id), load(job.id));
    let points: Vec<[f32; 3]> = (0..50).map(|i| [i as f32 * 0.05, 0.3, 1.0]).collect();
    let bits = |m: &FittedModel| -> Vec<u32> {
        m.network_positions(&points, 0.0, &[1.0]).iter().flatten().map(|c| c.to_bits()).collect()
    };
    assert_eq!(bits(&a), bits(&b), "a resumed fit must end with the uninterrupted fit's network");
    assert_eq!(a.report().losses, b.report().losses);
    assert_eq!(a.report().best_iteration, b.report().best_iteration);
}

#[test]
fn a_job_whose_worker_stopped_renewing_is_run_by_another_worker_and_the_first_records_nothing() {
    let settings = WorkerSettings { lease: Duration::from_millis(300), ..WorkerSettings::default() };
    let f = fixture_with(settings);
    let job = JobQueue::new_job(f.sequence, Method::Ntp, tiny_params(Method::Ntp));
    f.queue.submit(&job).unwrap();
    let store = f.queue.store();
    // A worker that claims the job and then dies (never renews).
    let dead = crate::store::Claim { worker: "dead:1:0".into(), lease: Duration::from_millis(300), max_attempts: 3 };
    assert_eq!(store.claim_next_job(&dead).unwrap().unwrap().id, job.id);
    let (w, _) = worker(&f, CoreFitter);
    assert!(w.try_execute_next().unwrap().is_none(), "a live lease is nobody else's to take");
    std::thread::sleep(Duration::from_millis(400));
    let done = w.try_execute_next().unwrap().unwrap();
    assert_eq!((done.id, done.status, done.attempts), (job.id, JobStatus::Succeeded, 2));
    let late = store.finish_job(job.id, "dead:1:0", crate::store::JobOutcome::Failed { error: "late".into() });
    assert!(matches!(late, Err(StoreError::LeaseLost(_))));
    assert_eq!(store.get_job(job.id).unwrap().unwrap().status, JobStatus::Succeeded);
}

#[test]
fn progress_is_persisted_while_the_fit_runs() {
    let f = fixture();
    let (w, shutdown) = worker(&f, SlowFitter { steps: 100_000, step: Duration::from_millis(2) });
    let job = JobQueue::new_job(f.sequence, Method::Ntp, tiny_params(Method::Ntp));
    f.queue.submit(&job).unwrap();
    std::thread::scope(|s| {
        let run = s.spawn(|| w.try_execute_next());
        wait_until_running(&f.queue, job.id);
        // PERSIST_EVERY is 1 s: after 1.5 s at least one mid-fit write must have happened.
        std::thread::sleep(Duration::from_millis(1500));
        let seen = f.queue.store().get_job(job.id).unwrap().unwrap();
        shutdown.store(true, Ordering::Relaxed);
        run.join().unwrap().unwrap();
        assert!(seen.progress.iteration > 0, "{:?}", seen.progress);
        assert!(seen.progress.fraction > 0.0 && seen.progress.fraction < 1.0);
        assert!(seen.progress.eta_s.is_some() && seen.progress.loss.is_some());
    });
}

#[test]
fn a_pool_runs_every_submitted_job_and_stops_cleanly() {
    let f = fixture();
    let pool = WorkerPool::start(f.queue.clone(), Arc::new(CoreFitter), 2, 1).unwrap();
    let ids: Vec<Uuid> = (0..3)
        .map(|_| {
            let job = JobQueue::new_job(f.sequence, Method::Nsfp, tiny_params(Method::Nsfp));
            f.queue.submit(&job).unwrap();
            job.id
        })
        .collect();
    for _ in 0..2000 {
        let done = f
            .queue
            .store()
            .list_jobs(&JobFilter { status: Some(JobStatus::Succeeded), limit: 10, ..Default::default() })
            .unwrap();
        if done.len() == ids.len() {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    pool.shutdown();
    for id in ids {
        let job = f.queue.store().get_job(id).unwrap().unwrap();
        assert_eq!(job.status, JobStatus::Succeeded, "{:?}", job.error);
    }
}

/// A store holding simulated log `seed` of `frames` frames, with timestamps and poses; and the
/// log.
fn log_fixture(seed: u64, frames: usize) -> (Fixture, crate::sim::SimSequence) {
    let sim = crate::fit::windows::tests::small_log(seed, frames);
    let dir = std::env::temp_dir().join(format!("mbnt-jobs-{}", Uuid::new_v4()));
    let store = SqliteStore::open(&dir).unwrap();
    let mut sink = store.begin_sequence().unwrap();
    for frame in &sim.frames {
        sink.put_frame(frame).unwrap();
    }
    let meta =
        SequenceMeta { name: None, timestamps_s: Some(sim.timestamps_s.clone()), poses: Some(sim.ego_poses.clone()) };
    let sequence = sink.commit(meta).unwrap().id;
    (Fixture { dir, queue: JobQueue::new(Arc::new(store)), sequence }, sim)
}

/// The real fit, stopped (as a shutdown stops it) once it reaches window `stop_at` in its first
/// run; records which windows each run fitted (reported an iteration 1: a window taken from
/// the store reports its last iteration only).
struct InterruptedOnce {
    stop_at: usize,
    fitted: std::sync::Mutex<Vec<Vec<usize>>>,
}

impl Fitter for InterruptedOnce {
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        CoreFitter.fit(sequence, method, params, on_progress)
    }

    fn fit_resuming(
        &self,
        sequence: &dyn crate::fit::FrameSource,
        method: Method,
        params: &ValidFitParams,
        finished: &mut dyn crate::fit::windows::FinishedWindows,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        let run = {
            let mut fitted = self.fitted.lock().unwrap();
            fitted.push(Vec::new());
            fitted.len() - 1
        };
        CoreFitter.fit_resuming(sequence, method, params, finished, &mut |p| {
            let window = p.window.expect("a windowed fit").window;
            if p.iteration == 1 {
                self.fitted.lock().unwrap()[run].push(window);
            }
            if run == 0 && window == self.stop_at { ControlFlow::Break(()) } else { on_progress(p) }
        })
    }
}

#[test]
fn a_restarted_job_keeps_its_finished_windows() {
    let (f, _) = log_fixture(5, 12);
    let fitter = Arc::new(InterruptedOnce { stop_at: 2, fitted: std::sync::Mutex::new(Vec::new()) });
    let shutdown = Arc::new(AtomicBool::new(false));
    let w = Worker::new(f.queue.clone(), fitter.clone(), 1, shutdown).unwrap();
    // 12 frames in windows of 6 overlapping by at least 2: windows from frames 0, 3 and 6.
    let params = crate::fit::windows::tests::quick_params(6, 2);
    let job = JobQueue::new_job(f.sequence, Method::Mbnt, params);
    f.queue.submit(&job).unwrap();
    // The first run stops in window 2 as a shutdown would: the job goes back to the queue with
    // windows 0 and 1 kept.
    let first = w.try_execute_next().unwrap().unwrap();
    assert_eq!(first.status, JobStatus::Queued, "{:?}", first.error);
    let store = f.queue.store();
    for key in ["0-6", "3-6"] {
        assert!(store.read_window_model(job.id, key).unwrap().is_some(), "window {key} kept");
    }
    assert!(store.read_window_model(job.id, "6-6").unwrap().is_none(), "the stopped window is not kept");
    // The second run fits window 2 only, and the job succeeds with a model of the whole log.
    let second = w.try_execute_next().unwrap().unwrap();
    assert_eq!(second.status, JobStatus::Succeeded, "{:?}", second.error);
    assert_eq!(*fitter.fitted.lock().unwrap(), vec![vec![0, 1, 2], vec![2]]);
    let model = FittedModel::from_bytes(&store.read_model(job.id).unwrap()).unwrap();
    assert_eq!(model.window_starts(), vec![0, 3, 6]);
    // A finished job keeps no windows.
    assert!(store.read_window_model(job.id, "0-6").unwrap().is_none());
}

/// Issue 21's case, at a scale a test affords: a 100-frame log with poses, one default MBNT job
/// (iterations and network cut down, 25-frame windows). The job succeeds with one model of the
/// whole log, its progress has counted the windows, and every frame's points answer at every
/// frame time, finite; labels exist for every frame.
#[test]
fn a_hundred_frame_log_is_one_job_whose_every_query_answers() {
    let (f, sim) = log_fixture(21, 100);
    let (w, _) = worker(&f, CoreFitter);
    // The default windows.
    use crate::model::params::{DEFAULT_WINDOW_FRAMES, DEFAULT_WINDOW_OVERLAP_FRAMES};
    let params = crate::fit::windows::tests::quick_params(DEFAULT_WINDOW_FRAMES, DEFAULT_WINDOW_OVERLAP_FRAMES);
    let job = JobQueue::new_job(f.sequence, Method::Mbnt, params);
    f.queue.submit(&job).unwrap();
    let done = w.try_execute_next().unwrap().unwrap();
    assert_eq!(done.status, JobStatus::Succeeded, "{:?}", done.error);
    let window = done.progress.window.expect("the progress of a windowed fit names its window");
    assert_eq!((window.window, window.windows), (4, 5), "100 frames: 5 windows of 25");
    let model = FittedModel::from_bytes(&f.queue.store().read_model(job.id).unwrap()).unwrap();
    assert_eq!(model.time_axis().frames(), 100);
    assert_eq!(model.window_starts().len(), 5);
    let times = &sim.timestamps_s;
    for (k, frame) in sim.frames.iter().enumerate() {
        let some: Vec<[f32; 3]> = frame.iter().step_by(200).copied().collect();
        let answers = model.positions(&some, times[k], times).unwrap();
        assert_eq!(answers.len(), some.len() * 100);
        assert!(answers.iter().flatten().all(|c| c.is_finite()), "frame {k}");
    }
    let flows = model.scene_flow(&sim.frames).unwrap();
    let ids = model.object_ids(&sim.frames).unwrap();
    assert_eq!((flows.len(), ids.len()), (99, 100));
    assert!((0..100).all(|k| ids[k].len() == sim.frames[k].len()));
    assert!(flows.iter().flatten().flatten().all(|c| c.is_finite()));
    // The objects (GET /v1/jobs/{id}/objects) each cover the whole log.
    assert!(model.bodies().iter().all(|b| b.fits(100)));
}

/// Runs the real fit but holds the first report of window 0 for `hold`: a job's worker busy
/// with its first window while another worker looks for work.
struct HoldFirstWindow {
    hold: Duration,
}

impl Fitter for HoldFirstWindow {
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        CoreFitter.fit(sequence, method, params, on_progress)
    }

    fn fit_resuming(
        &self,
        sequence: &dyn crate::fit::FrameSource,
        method: Method,
        params: &ValidFitParams,
        finished: &mut dyn crate::fit::windows::FinishedWindows,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        let mut held = false;
        CoreFitter.fit_resuming(sequence, method, params, finished, &mut |p| {
            if !held && p.window.is_some_and(|w| w.window == 0) {
                held = true;
                std::thread::sleep(self.hold);
            }
            on_progress(p)
        })
    }
}

#[test]
fn an_idle_worker_fits_windows_of_a_running_log_and_the_model_is_the_one_worker_model() {
    let f = fixture();
    let store = f.queue.store().clone();
    // An 8-frame log of the moving grid, fitted as windows of 4 frames overlapping by 2 (3 windows).
    let grid: Vec<[f32; 3]> =
        (0..200).map(|i| [(i % 10) as f32 * 0.3, ((i / 10) % 10) as f32 * 0.3, (i / 100) as f32 * 0.5 + 1.0]).collect();
    let mut sink = store.begin_sequence().unwrap();
    for k in 0..8 {
        sink.put_frame(&grid.iter().map(|p| [p[0] + 0.1 * k as f32, p[1], p[2]]).collect::<Vec<_>>()).unwrap();
    }
    // With poses (the sensor still): a log without them needs an odometry run over every frame,
    // which helpers would each repeat, so its windows are not shared.
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
    let log = sink.commit(SequenceMeta { poses: Some(vec![identity; 8]), ..SequenceMeta::default() }).unwrap().id;
    let params = FitParams {
        window_frames: Some(4),
        window_overlap_frames: Some(2),
        window_iterations: Some(20),
        hidden_width: Some(16),
        hidden_layers: Some(2),
        ..FitParams::default()
    }
    .check(Method::Ntp)
    .unwrap();
    let alone = JobQueue::new_job(log, Method::Ntp, params.clone());
    f.queue.submit(&alone).unwrap();
    let (w, _) = worker(&f, CoreFitter);
    let alone = w.try_execute_next().unwrap().unwrap();
    assert_eq!(alone.status, JobStatus::Succeeded);

    let shared = JobQueue::new_job(log, Method::Ntp, params);
    f.queue.submit(&shared).unwrap();
    let (owner, _) = worker(&f, HoldFirstWindow { hold: Duration::from_secs(3) });
    let (helper, _) = worker(&f, CoreFitter);
    let helped = std::thread::scope(|s| {
        let run = s.spawn(|| owner.try_execute_next());
        wait_until_running(&f.queue, shared.id);
        let mut helped = 0;
        while !run.is_finished() {
            if helper.try_help().unwrap() {
                helped += 1;
            } else {
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        let done = run.join().unwrap().unwrap().unwrap();
        assert_eq!(done.status, JobStatus::Succeeded, "{:?}", done.error);
        helped
    });
    // The owner held window 0 for 3 s: the helper had time for windows 1 and 2.
    assert!(helped >= 1, "the idle worker fitted no window");
    let load = |id| FittedModel::from_bytes(&store.read_model(id).unwrap()).unwrap();
    let (a, b) = (load(alone.id), load(shared.id));
    for k in [0usize, 3, 5, 7] {
        let points: Vec<[f32; 3]> = grid.iter().take(30).map(|p| [p[0] + 0.1 * k as f32, p[1], p[2]]).collect();
        let times: Vec<f64> = (0..8).map(|t| t as f64).collect();
        let answer = |m: &FittedModel| -> Vec<u32> {
            m.positions(&points, k as f64, &times).unwrap().iter().flatten().map(|c| c.to_bits()).collect()
        };
        assert_eq!(answer(&a), answer(&b), "frame {k}: windows fitted by two workers must stitch to the same model");
    }
}

#[test]
fn a_torn_checkpoint_is_ignored_and_the_previous_one_survives_a_failed_write() {
    let settings = WorkerSettings { checkpoint_every: Duration::ZERO, ..WorkerSettings::default() };
    let f = fixture_with(settings);
    let params = FitParams {
        iterations: Some(30),
        validate_every: Some(5),
        validation_patience: Some(0),
        hidden_width: Some(16),
        hidden_layers: Some(2),
        ..FitParams::default()
    }
    .check(Method::Ntp)
    .unwrap();
    let job = JobQueue::new_job(f.sequence, Method::Ntp, params);
    f.queue.submit(&job).unwrap();
    let (w, _) = worker(&f, StopOnce { stop_at: 12, stopped: AtomicBool::new(false) });
    assert_eq!(w.try_execute_next().unwrap().unwrap().status, JobStatus::Queued);
    let store = f.queue.store();
    let key = "checkpoint-0-2";
    let kept = store.read_window_model(job.id, key).unwrap().expect("a checkpoint was kept at iteration 10");
    // A write that dies half-way (the kill of issue 22) never replaces the kept file: the store
    // writes a temporary and renames it.
    let dir = std::env::temp_dir().join(format!("mbnt-torn-{}", Uuid::new_v4()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("checkpoint.mbnt");
    crate::store::files::write_atomic(&path, |w| std::io::Write::write_all(w, &kept)).unwrap();
    let torn = crate::store::files::write_atomic(&path, |w| {
        std::io::Write::write_all(w, &kept[..kept.len() / 2])?;
        Err(std::io::Error::other("killed mid-write"))
    });
    assert!(torn.is_err());
    assert_eq!(std::fs::read(&path).unwrap(), kept);
    std::fs::remove_dir_all(&dir).unwrap();
    // A checkpoint torn by other means (a store without atomic writes) is refused by its checksum:
    // the job starts over from iteration 0 and still succeeds.
    store.put_window_model(job.id, key, &kept[..kept.len() / 2]).unwrap();
    let done = w.try_execute_next().unwrap().unwrap();
    assert_eq!((done.status, done.progress.resumed_from_iteration), (JobStatus::Succeeded, None));
}
