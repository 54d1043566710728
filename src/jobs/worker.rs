//! Workers: threads that claim queued jobs and run their fits, each on its own rayon pool,
//! reporting progress (persisted at most about once a second) and honouring cancellation.

use std::ops::ControlFlow;
use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context;

use super::{Fitter, JobQueue};
use crate::fit::windows::FinishedWindows;
use crate::fit::{FitError, FrameSource, Progress};
use crate::geometry::Point;
use crate::model::FittedModel;
use crate::store::{Claim, JobOutcome, JobProgress, JobRecord, LeaseStatus, StoreError};

/// How often a running job's progress is written to the store.
const PERSIST_EVERY: Duration = Duration::from_secs(1);
/// How often watchers (server-sent events) get a new state at most.
const PUBLISH_EVERY: Duration = Duration::from_millis(100);
/// How long an idle worker sleeps before looking at the queue again without being woken.
const IDLE_POLL: Duration = Duration::from_millis(500);

/// A name for the next worker of this process, unique among live workers of a fleet:
/// `host:pid:n`.
pub fn worker_name() -> String {
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "localhost".into());
    format!("{host}:{}:{}", std::process::id(), NEXT.fetch_add(1, Ordering::Relaxed))
}

/// Runs jobs one at a time. [`WorkerPool`] drives several on threads; tests call
/// [`Worker::try_execute_next`] directly.
pub struct Worker {
    name: String,
    queue: Arc<JobQueue>,
    fitter: Arc<dyn Fitter>,
    pool: rayon::ThreadPool,
    shutdown: Arc<AtomicBool>,
}

impl std::fmt::Debug for Worker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Worker").field("threads", &self.pool.current_num_threads()).finish_non_exhaustive()
    }
}

impl Worker {
    /// A worker whose fits use `threads` threads; it stops between iterations once
    /// `shutdown` is set, putting its job back in the queue.
    pub fn new(
        queue: Arc<JobQueue>,
        fitter: Arc<dyn Fitter>,
        threads: usize,
        shutdown: Arc<AtomicBool>,
    ) -> anyhow::Result<Self> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .thread_name(|i| format!("mbnt-fit-{i}"))
            .build()
            .context("creating a fit thread pool")?;
        Ok(Self { name: worker_name(), queue, fitter, pool, shutdown })
    }

    /// The name the worker claims jobs under.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Claims the oldest queued job (or one whose worker died) and runs it to its end; returns
    /// its final state, or `None` when the queue was empty. Blocking (for as long as the fit
    /// takes).
    pub fn try_execute_next(&self) -> Result<Option<JobRecord>, StoreError> {
        let settings = &self.queue.settings;
        let claim = Claim { worker: self.name.clone(), lease: settings.lease, max_attempts: settings.max_attempts };
        let Some(job) = self.queue.store.claim_next_job(&claim)? else {
            return Ok(None);
        };
        let id = job.id;
        let cancel = self.queue.register_running(id);
        let result = self.execute(job, &cancel);
        self.queue.unregister_running(id);
        let done = result?;
        self.queue.publish(&done);
        Ok(Some(done))
    }

    #[tracing::instrument(skip_all, fields(job_id = %job.id, method = job.method.name(), worker = %self.name))]
    fn execute(&self, job: JobRecord, cancel: &AtomicBool) -> Result<JobRecord, StoreError> {
        // The lease is renewed beside the fit, so that a long step without progress reports
        // (odometry, body search, a slow store) does not lose it.
        let lost = AtomicBool::new(false);
        let done = AtomicBool::new(false);
        let claimed = std::sync::Mutex::new(None::<String>);
        let store = &*self.queue.store;
        let lease = self.queue.settings.lease;
        std::thread::scope(|scope| {
            let heartbeat = scope.spawn(|| {
                renew_until(lease, &done, || {
                    match store.renew_lease(job.id, &self.name, lease) {
                        Ok(LeaseStatus::Held { cancel_requested }) => {
                            if cancel_requested {
                                cancel.store(true, Ordering::Relaxed);
                            }
                        }
                        Ok(LeaseStatus::Lost) => {
                            lost.store(true, Ordering::Relaxed);
                            return false;
                        }
                        // The lease may still hold; the next renewal tells.
                        Err(e) => tracing::warn!(error = %e, "could not renew the job's lease"),
                    }
                    let window = claimed.lock().unwrap_or_else(|p| p.into_inner()).clone();
                    if let Some(key) = window
                        && let Err(e) = store.claim_window(job.id, &key, &self.name, lease)
                    {
                        tracing::warn!(error = %e, "could not renew a window claim");
                    }
                    true
                });
            });
            let result = self.run(job.clone(), cancel, &lost, &claimed);
            done.store(true, Ordering::Relaxed);
            heartbeat.thread().unpark();
            result
        })
        .or_else(|e| match e {
            StoreError::LeaseLost(why) => {
                tracing::warn!(%why, "the job's lease was lost (this worker was too slow to renew it); another worker may hold it, and this run records nothing");
                Ok(store.get_job(job.id)?.unwrap_or(job))
            }
            e => Err(e),
        })
    }

    /// One run of a claimed job; [`StoreError::LeaseLost`] once the lease is gone.
    fn run(
        &self,
        mut job: JobRecord,
        cancel: &AtomicBool,
        lost: &AtomicBool,
        claimed: &std::sync::Mutex<Option<String>>,
    ) -> Result<JobRecord, StoreError> {
        tracing::info!(attempt = job.attempts, "fit started");
        let store = self.queue.store.clone();
        let worker = self.name.as_str();
        let job_id = job.id;
        let lease_lost = || StoreError::LeaseLost(format!("job {job_id} is no longer held by {worker}"));
        job.progress = JobProgress { iterations: job.params.iterations, ..JobProgress::default() };
        if store.update_progress(job.id, worker, &job.progress)? == LeaseStatus::Lost {
            return Err(lease_lost());
        }
        self.queue.publish(&job);
        let sequence = match StoredFrames::open(&*store, &job) {
            Ok(s) => s,
            Err(e) => {
                tracing::error!(error = %e, "could not load the job's sequence");
                return store.finish_job(
                    job.id,
                    worker,
                    JobOutcome::Failed { error: format!("could not load the sequence: {e}") },
                );
            }
        };
        let (method, params) = (job.method, job.params.clone());
        // usize::MAX until the fit goes on from a checkpoint (an atomic: the fit runs on the pool).
        let resumed_from = AtomicUsize::new(usize::MAX);
        let resumed = || Some(resumed_from.load(Ordering::Relaxed)).filter(|&i| i != usize::MAX);
        let mut finished = StoredWindows {
            store: &*store,
            job: job.id,
            worker,
            lease: self.queue.settings.lease,
            claimed,
            checkpoint_every: self.queue.settings.checkpoint_every,
            last_checkpoint: Instant::now(),
            resumed_from: &resumed_from,
        };
        let started = Instant::now();
        let mut last_persist = started;
        let mut last_publish = started;
        // The window being fitted (0 without windows) and when its first iteration was reported.
        let mut window_clock = (0usize, started);
        let mut store_error = None;
        let mut on_progress = |p: &Progress| -> ControlFlow<()> {
            // A windowed fit's rate is the current window's (its clock starts at its first
            // iteration); the iterations left are the window's and every later window's plan.
            let window = p.window.map_or(0, |w| w.window);
            if window != window_clock.0 {
                window_clock = (window, Instant::now());
            }
            let elapsed_s = window_clock.1.elapsed().as_secs_f64();
            // A run that went on from a checkpoint did only the iterations since.
            let done_here = p.iteration.saturating_sub(resumed().unwrap_or(0));
            let rate = if elapsed_s > 0.0 { done_here as f64 / elapsed_s } else { 0.0 };
            self.queue.stats.record(job.id, rate);
            let window_fraction =
                if p.iterations > 0 { (p.iteration as f64 / p.iterations as f64).min(1.0) } else { 0.0 };
            let mut remaining = p.iterations.saturating_sub(p.iteration) as f64;
            let mut fraction = window_fraction;
            if let Some(w) = p.window {
                remaining += (w.windows.saturating_sub(w.window + 1) * p.iterations) as f64;
                fraction = ((w.windows_done as f64 + window_fraction) / w.windows.max(1) as f64).min(1.0);
            }
            let eta_s = (rate > 0.0 && p.rigid_tracks.is_none()).then(|| remaining / rate);
            job.progress = JobProgress {
                fraction,
                iteration: p.iteration,
                iterations: p.iterations,
                loss: Some(p.loss),
                eta_s,
                rigid_tracks: p.rigid_tracks,
                window: p.window,
                resumed_from_iteration: resumed(),
            };
            let now = Instant::now();
            // The last iteration is stored at once; the rigid-track steps after it (which repeat its
            // iteration count) only every PERSIST_EVERY.
            let last_iteration = p.iteration >= p.iterations && p.rigid_tracks.is_none();
            // A window's first iteration is stored at once too, so the windows done show.
            let new_window = p.window.is_some_and(|w| w.window > 0) && p.iteration == 1;
            if now - last_persist >= PERSIST_EVERY || last_iteration || new_window {
                last_persist = now;
                match store.update_progress(job.id, worker, &job.progress) {
                    Ok(LeaseStatus::Held { cancel_requested: true }) => cancel.store(true, Ordering::Relaxed),
                    Ok(LeaseStatus::Held { cancel_requested: false }) => {}
                    Ok(LeaseStatus::Lost) => lost.store(true, Ordering::Relaxed),
                    // Keep fitting: progress is advisory, and the outcome is retried below.
                    Err(e) => store_error = Some(e),
                }
            }
            if now - last_publish >= PUBLISH_EVERY {
                last_publish = now;
                self.queue.publish(&job);
            }
            if cancel.load(Ordering::Relaxed) || lost.load(Ordering::Relaxed) || self.shutdown.load(Ordering::Relaxed) {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        };
        let fitter = &*self.fitter;

        let result = std::panic::catch_unwind(AssertUnwindSafe(|| {
            self.pool.install(|| fitter.fit_resuming(&sequence, method, &params, &mut finished, &mut on_progress))
        }));
        if let Some(e) = store_error {
            tracing::warn!(error = %e, "progress could not be stored during the fit");
        }
        if lost.load(Ordering::Relaxed) {
            return Err(lease_lost());
        }
        let outcome = match result {
            // Only a model that loads and answers makes a job succeed: one holding a non-finite
            // number fails it, naming the part, instead of failing every later query.
            Ok(Ok(model)) => match model.to_bytes() {
                Ok(bytes) => {
                    tracing::info!(seconds = started.elapsed().as_secs_f64(), "fit succeeded");
                    return store.finish_job(job.id, worker, JobOutcome::Succeeded { model: &bytes });
                }
                Err(e) => {
                    tracing::error!(error = %e, "the fitted model holds a non-finite number");
                    JobOutcome::Failed { error: format!("model not saved: {e}") }
                }
            },
            Ok(Err(FitError::Cancelled { iteration })) if !cancel.load(Ordering::Relaxed) => {
                tracing::info!(iteration, "fit interrupted by shutdown; the job goes back to the queue");
                return store.requeue_job(job.id, worker);
            }
            Ok(Err(FitError::Cancelled { iteration })) => {
                tracing::info!(iteration, "fit cancelled");
                JobOutcome::Cancelled
            }
            Ok(Err(e)) => {
                tracing::warn!(error = %e, "fit failed");
                JobOutcome::Failed { error: e.to_string() }
            }
            Err(panic) => {
                let what = panic
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| panic.downcast_ref::<String>().cloned())
                    .unwrap_or_default();
                tracing::error!(panic = %what, "fit panicked");
                JobOutcome::Failed { error: "internal error: the fit stopped unexpectedly".into() }
            }
        };
        store.finish_job(job.id, worker, outcome)
    }
}

impl Worker {
    /// With no job to claim: fits one window of a running job's long log that no worker has
    /// claimed or finished (the job's own worker takes it from the store), so that the windows
    /// of one log spread over idle workers. Returns whether it did any work. Blocking.
    pub fn try_help(&self) -> Result<bool, StoreError> {
        let store = &*self.queue.store;
        let filter =
            crate::store::JobFilter { status: Some(crate::store::JobStatus::Running), sequence_id: None, limit: 100 };
        let mut running = store.list_jobs(&filter)?;
        // Oldest first: help the job that has waited longest.
        running.reverse();
        for job in running {
            if job.worker.as_deref() == Some(self.name.as_str()) {
                continue;
            }
            let Ok(sequence) = StoredFrames::open(store, &job) else { continue };
            if !crate::fit::windows::windows_can_be_shared(&sequence, &job.params) {
                continue;
            }
            let frames = job.params.window_frames;
            let starts =
                crate::fit::windows::window_starts(sequence.frame_count(), frames, job.params.window_overlap_frames);
            // One listing per job, not a read of every kept model at every idle poll.
            let kept = store.window_keys(job.id)?;
            for (w, &start) in starts.iter().enumerate() {
                if kept.contains(&StoredWindows::key(start, frames)) {
                    continue;
                }
                let key = StoredWindows::claim_key(start, frames);
                if !store.claim_window(job.id, &key, &self.name, self.queue.settings.lease)? {
                    continue;
                }
                // Kept between the listing and the claim: nothing to do.
                if store.window_keys(job.id)?.contains(&StoredWindows::key(start, frames)) {
                    store.release_window(job.id, &key, &self.name)?;
                    continue;
                }
                self.help_with(&job, &sequence, w, start, &key);
                if let Err(e) = store.release_window(job.id, &key, &self.name) {
                    tracing::warn!(error = %e, "could not release a window claim (it expires on its own)");
                }
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// Fits window `window` of `job` (claimed under `key`) and keeps its model for the job's
    /// worker, renewing the claim beside the fit; stops when the claim is lost (the job ended
    /// or was cancelled) or the worker shuts down.
    #[tracing::instrument(skip_all, fields(job_id = %job.id, window, worker = %self.name))]
    fn help_with(&self, job: &JobRecord, sequence: &StoredFrames<'_>, window: usize, start: usize, key: &str) {
        let store = &*self.queue.store;
        let lease = self.queue.settings.lease;
        let lost = AtomicBool::new(false);
        let done = AtomicBool::new(false);
        tracing::info!(first_frame = start, "helping: fitting a window of another worker's job");
        let started = Instant::now();
        std::thread::scope(|scope| {
            let heartbeat = scope.spawn(|| {
                renew_until(lease, &done, || match store.claim_window(job.id, key, &self.name, lease) {
                    Ok(held) => {
                        lost.store(!held, Ordering::Relaxed);
                        held
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "could not renew a window claim");
                        true
                    }
                });
            });
            let resumed = AtomicUsize::new(usize::MAX);
            let claimed = std::sync::Mutex::new(None);
            let mut checkpoints = StoredWindows {
                store,
                job: job.id,
                worker: &self.name,
                lease,
                claimed: &claimed,
                checkpoint_every: self.queue.settings.checkpoint_every,
                last_checkpoint: Instant::now(),
                resumed_from: &resumed,
            };
            let mut on_progress = |_: &Progress| {
                if lost.load(Ordering::Relaxed) || self.shutdown.load(Ordering::Relaxed) {
                    ControlFlow::Break(())
                } else {
                    ControlFlow::Continue(())
                }
            };
            let fitted = std::panic::catch_unwind(AssertUnwindSafe(|| {
                self.pool.install(|| {
                    // Built here: the fit runs on the pool's threads.
                    let frames = job.params.window_frames;
                    let mut window_checkpoints =
                        crate::fit::windows::KeptCheckpoints::new(&mut checkpoints, start, frames);
                    crate::fit::windows::fit_window(
                        sequence,
                        job.method,
                        &job.params,
                        window,
                        &mut window_checkpoints,
                        &mut on_progress,
                    )
                })
            }));
            done.store(true, Ordering::Relaxed);
            heartbeat.thread().unpark();
            match fitted {
                Ok(Ok(model)) => match model.to_bytes() {
                    Ok(bytes) => match store.put_window_model(
                        job.id,
                        &StoredWindows::key(start, job.params.window_frames),
                        &bytes,
                    ) {
                        Ok(()) => tracing::info!(seconds = started.elapsed().as_secs_f64(), "helping: window kept"),
                        Err(e) => tracing::warn!(error = %e, "helping: could not keep the window"),
                    },
                    // The job's worker fits it again and fails the job with the reason.
                    Err(e) => tracing::warn!(error = %e, "helping: the window holds a non-finite number"),
                },
                Ok(Err(e)) => tracing::info!(error = %e, "helping: the window's fit stopped"),
                Err(_) => tracing::error!("helping: the window's fit panicked"),
            }
        });
    }
}

/// The finished windows and the latest mid-fit checkpoint of one job, kept in the store
/// (`windows/{job}/` of the data directory, or of the object store) until the job finishes, so
/// that a job run again after a shutdown or a crash, on this worker or another, skips them. A
/// kept window or checkpoint that cannot be read or written is fitted again: keeping them
/// saves time only.
struct StoredWindows<'a> {
    store: &'a dyn crate::store::Store,
    job: uuid::Uuid,
    /// The worker fitting, and the lease of its window claims.
    worker: &'a str,
    lease: Duration,
    /// The window claim this worker holds now (renewed by its heartbeat).
    claimed: &'a std::sync::Mutex<Option<String>>,
    checkpoint_every: Duration,
    last_checkpoint: Instant,
    /// Set when a window's fit goes on from a checkpoint: the iteration it went on from.
    resumed_from: &'a AtomicUsize,
}

impl StoredWindows<'_> {
    fn key(first_frame: usize, frames: usize) -> String {
        format!("{first_frame}-{frames}")
    }

    fn checkpoint_key(first_frame: usize, frames: usize) -> String {
        format!("checkpoint-{first_frame}-{frames}")
    }

    fn claim_key(first_frame: usize, frames: usize) -> String {
        format!("w-{first_frame}-{frames}")
    }
}

impl FinishedWindows for StoredWindows<'_> {
    fn take(&mut self, first_frame: usize, frames: usize) -> Option<FittedModel> {
        let bytes = match self.store.read_window_model(self.job, &Self::key(first_frame, frames)) {
            Ok(bytes) => bytes?,
            Err(e) => {
                tracing::warn!(error = %e, first_frame, "could not read a kept window; fitting it again");
                return None;
            }
        };
        match FittedModel::from_bytes(&bytes) {
            Ok(model) if model.time_axis().frames() == frames => Some(model),
            Ok(_) => None,
            Err(e) => {
                tracing::warn!(error = %e, first_frame, "a kept window does not load; fitting it again");
                None
            }
        }
    }

    fn keep(&mut self, first_frame: usize, frames: usize, model: &FittedModel) {
        // A window with a non-finite number is not kept; the whole model's check fails the job.
        let Ok(bytes) = model.to_bytes() else { return };
        if let Err(e) = self.store.put_window_model(self.job, &Self::key(first_frame, frames), &bytes) {
            tracing::warn!(error = %e, first_frame, "could not keep a finished window");
        }
    }

    fn checkpoint_due(&mut self) -> bool {
        self.last_checkpoint.elapsed() >= self.checkpoint_every
    }

    fn checkpoint(&mut self, first_frame: usize, frames: usize) -> Option<Vec<u8>> {
        self.store.read_window_model(self.job, &Self::checkpoint_key(first_frame, frames)).unwrap_or_else(|e| {
            tracing::warn!(error = %e, first_frame, "could not read a checkpoint; fitting from the start");
            None
        })
    }

    fn keep_checkpoint(&mut self, first_frame: usize, frames: usize, bytes: &[u8]) {
        self.last_checkpoint = Instant::now();
        if let Err(e) = self.store.put_window_model(self.job, &Self::checkpoint_key(first_frame, frames), bytes) {
            tracing::warn!(error = %e, first_frame, "could not keep a checkpoint");
        }
    }

    fn resumed(&mut self, _first_frame: usize, _frames: usize, iteration: usize) {
        self.resumed_from.store(iteration, Ordering::Relaxed);
    }

    fn claim(&mut self, first_frame: usize, frames: usize) -> bool {
        let key = Self::claim_key(first_frame, frames);
        match self.store.claim_window(self.job, &key, self.worker, self.lease) {
            Ok(true) => {
                *self.claimed.lock().unwrap_or_else(|p| p.into_inner()) = Some(key);
                true
            }
            Ok(false) => false,
            // Without the claim table the window is fitted here: at worst twice, never lost.
            Err(e) => {
                tracing::warn!(error = %e, first_frame, "could not claim a window; fitting it here");
                true
            }
        }
    }

    fn release(&mut self, first_frame: usize, frames: usize) {
        let key = Self::claim_key(first_frame, frames);
        self.claimed.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let Err(e) = self.store.release_window(self.job, &key, self.worker) {
            tracing::warn!(error = %e, first_frame, "could not release a window claim (it expires on its own)");
        }
    }
}

/// A job's sequence in the store, whose frames the fit reads when it needs them (a whole log
/// one window at a time).
struct StoredFrames<'a> {
    store: &'a dyn crate::store::Store,
    record: crate::store::SequenceRecord,
}

impl<'a> StoredFrames<'a> {
    /// The job's sequence; its frames are not read yet.
    fn open(store: &'a dyn crate::store::Store, job: &JobRecord) -> Result<Self, StoreError> {
        let record = store
            .get_sequence(job.sequence_id)?
            .ok_or_else(|| StoreError::Missing(format!("sequence {}", job.sequence_id)))?;
        Ok(Self { store, record })
    }
}

impl FrameSource for StoredFrames<'_> {
    fn frame_count(&self) -> usize {
        self.record.frames()
    }

    fn timestamps_s(&self) -> Option<&[f64]> {
        self.record.timestamps_s.as_deref()
    }

    fn poses(&self) -> Option<&[[f64; 16]]> {
        self.record.poses.as_deref()
    }

    fn read_frames(&self, range: std::ops::Range<usize>) -> Result<Vec<Vec<Point>>, FitError> {
        range
            .map(|k| {
                self.store.read_frame(self.record.id, k).map_err(|e| FitError::FrameRead(format!("frame {k}: {e}")))
            })
            .collect()
    }
}

/// Calls `renew` every third of `lease` (so that two renewals may fail before it ends) until
/// `done` is set or `renew` says the lease is gone; `done`'s setter unparks the thread.
fn renew_until(lease: Duration, done: &AtomicBool, mut renew: impl FnMut() -> bool) {
    while !done.load(Ordering::Relaxed) {
        std::thread::park_timeout(lease / 3);
        if done.load(Ordering::Relaxed) || !renew() {
            break;
        }
    }
}

/// A fixed number of worker threads, so that at most that many fits run at once.
pub struct WorkerPool {
    queue: Arc<JobQueue>,
    shutdown: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for WorkerPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerPool").field("workers", &self.threads.len()).finish_non_exhaustive()
    }
}

impl WorkerPool {
    /// Starts `workers` threads, each running fits on `threads_per_job` threads.
    pub fn start(
        queue: Arc<JobQueue>,
        fitter: Arc<dyn Fitter>,
        workers: usize,
        threads_per_job: usize,
    ) -> anyhow::Result<Self> {
        let shutdown = Arc::new(AtomicBool::new(false));
        let mut threads = Vec::with_capacity(workers);
        for i in 0..workers {
            let worker = Worker::new(queue.clone(), fitter.clone(), threads_per_job, shutdown.clone())?;
            let handle = std::thread::Builder::new()
                .name(format!("mbnt-worker-{i}"))
                .spawn(move || worker_loop(&worker))
                .context("starting a worker thread")?;
            threads.push(handle);
        }
        Ok(Self { queue, shutdown, threads })
    }

    /// Stops the workers: running fits stop at their next iteration and go back to the
    /// queue (they run again on the next start). Blocks until every worker has stopped.
    pub fn shutdown(self) {
        self.shutdown.store(true, Ordering::Relaxed);
        self.queue.wake.notify();
        for t in self.threads {
            if t.join().is_err() {
                tracing::error!("a worker thread panicked");
            }
        }
    }
}

fn worker_loop(worker: &Worker) {
    while !worker.shutdown.load(Ordering::Relaxed) {
        match worker.try_execute_next() {
            Ok(Some(_)) => {}
            Ok(None) => match worker.try_help() {
                Ok(true) => {}
                Ok(false) => worker.queue.wake.wait(IDLE_POLL),
                Err(e) => {
                    tracing::error!(error = %e, "worker could not look for windows to help with; retrying");
                    worker.queue.wake.wait(IDLE_POLL);
                }
            },
            Err(e) => {
                tracing::error!(error = %e, "worker could not use the store; retrying");
                std::thread::sleep(IDLE_POLL);
            }
        }
    }
}
