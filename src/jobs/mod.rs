//! The job queue: submitting and cancelling fits, live progress for subscribers, and the
//! worker threads that run fits off the async executor ([`worker`]).
//!
//! The queue itself lives in the [`Store`] (a job is a row; workers claim rows atomically),
//! so accepted jobs survive restarts and another store can spread them over machines. This
//! module adds what is local to one process: waking idle workers, cancel flags of the fits
//! running here, and a watch channel per observed job for server-sent events.

pub mod worker;

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use tokio::sync::watch;
use uuid::Uuid;

use crate::fit::windows::{FinishedWindows, fit_log};
use crate::fit::{FitError, FrameSource, Method, Progress, Sequence, ValidFitParams, fit_sequence};
use crate::model::FittedModel;
use crate::store::{CancelOutcome, JobRecord, Store, StoreError};

pub use worker::{Worker, WorkerPool, worker_name};

/// Runs one fit. The default is the numerical core ([`CoreFitter`]); the seam lets a worker
/// run fits elsewhere (another process or machine) and lets tests slow a fit down.
pub trait Fitter: Send + Sync + 'static {
    /// Fits `method` to `sequence`, calling `on_progress` after every iteration; a `Break`
    /// from it cancels the fit ([`FitError::Cancelled`]). Blocking.
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError>;

    /// [`Fitter::fit`] of a job that may have run before, whose frames are read when needed:
    /// a sequence fitted as windows takes the windows an earlier run finished from `finished`
    /// and keeps there each one it finishes. The default reads every frame and fits every
    /// window again.
    fn fit_resuming(
        &self,
        sequence: &dyn FrameSource,
        method: Method,
        params: &ValidFitParams,
        finished: &mut dyn FinishedWindows,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        let _ = finished;
        match sequence.in_memory() {
            Some(all) => self.fit(all, method, params, on_progress),
            None => self.fit(&sequence.part(0..sequence.frame_count())?, method, params, on_progress),
        }
    }
}

/// [`Fitter`] that calls [`fit_sequence`] on the calling thread (and its rayon pool).
#[derive(Debug, Clone, Copy, Default)]
pub struct CoreFitter;

impl Fitter for CoreFitter {
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        fit_sequence(sequence, method, params, on_progress)
    }

    fn fit_resuming(
        &self,
        sequence: &dyn FrameSource,
        method: Method,
        params: &ValidFitParams,
        finished: &mut dyn FinishedWindows,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        fit_log(sequence, method, params, finished, on_progress)
    }
}

/// Wakes idle workers when a job is submitted (they also poll, for jobs submitted by other
/// processes sharing the store).
#[derive(Debug, Default)]
struct Wake {
    pending: Mutex<bool>,
    cond: Condvar,
}

impl Wake {
    fn notify(&self) {
        *self.pending.lock().unwrap_or_else(|p| p.into_inner()) = true;
        self.cond.notify_all();
    }

    fn wait(&self, timeout: Duration) {
        let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
        if !*pending {
            pending = self.cond.wait_timeout(pending, timeout).unwrap_or_else(|p| p.into_inner()).0;
        }
        *pending = false;
    }
}

/// Fit throughput counters for `/metrics`.
#[derive(Debug, Default)]
pub struct FitStats {
    iterations_total: AtomicU64,
    rates: Mutex<HashMap<Uuid, f64>>,
}

impl FitStats {
    /// Fit iterations completed by this process since it started.
    pub fn iterations_total(&self) -> u64 {
        self.iterations_total.load(Ordering::Relaxed)
    }

    /// Iterations per second summed over the fits running now (0 when idle).
    pub fn iterations_per_second(&self) -> f64 {
        // fold from +0.0: `sum` of no floats is -0.0, which Prometheus would show as "-0".
        self.rates.lock().unwrap_or_else(|p| p.into_inner()).values().fold(0.0, |a, b| a + b)
    }

    fn record(&self, job: Uuid, rate: f64) {
        self.iterations_total.fetch_add(1, Ordering::Relaxed);
        self.rates.lock().unwrap_or_else(|p| p.into_inner()).insert(job, rate);
    }

    fn forget(&self, job: Uuid) {
        self.rates.lock().unwrap_or_else(|p| p.into_inner()).remove(&job);
    }
}

/// How workers hold their jobs and keep checkpoints.
#[derive(Debug, Clone, PartialEq)]
pub struct WorkerSettings {
    /// How long a claim holds without a renewal; a worker renews it every third of that
    /// (`MBNT_LEASE_S`). A worker that dies loses its job to the queue this long after.
    pub lease: Duration,
    /// A job whose worker died this many times fails instead of running again.
    pub max_attempts: u32,
    /// Least time between two mid-fit checkpoints (taken at validation iterations).
    pub checkpoint_every: Duration,
}

impl Default for WorkerSettings {
    fn default() -> Self {
        Self { lease: Duration::from_secs(30), max_attempts: 3, checkpoint_every: Duration::from_secs(30) }
    }
}

/// Submits, cancels and observes jobs; shared by the HTTP handlers and the workers.
pub struct JobQueue {
    store: Arc<dyn Store>,
    settings: WorkerSettings,
    wake: Wake,
    /// Cancel flags of the fits running in this process.
    running: Mutex<HashMap<Uuid, Arc<AtomicBool>>>,
    /// Latest state of each job someone is watching.
    watchers: Mutex<HashMap<Uuid, watch::Sender<Option<JobRecord>>>>,
    stats: FitStats,
}

impl std::fmt::Debug for JobQueue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("JobQueue").finish_non_exhaustive()
    }
}

impl JobQueue {
    /// A queue over `store`, with the default [`WorkerSettings`].
    pub fn new(store: Arc<dyn Store>) -> Arc<Self> {
        Self::with_settings(store, WorkerSettings::default())
    }

    /// A queue over `store` whose workers hold jobs as `settings` say.
    pub fn with_settings(store: Arc<dyn Store>, settings: WorkerSettings) -> Arc<Self> {
        Arc::new(Self {
            store,
            settings,
            wake: Wake::default(),
            running: Mutex::default(),
            watchers: Mutex::default(),
            stats: FitStats::default(),
        })
    }

    /// The store behind the queue.
    pub fn store(&self) -> &Arc<dyn Store> {
        &self.store
    }

    /// How the queue's workers hold jobs.
    pub fn settings(&self) -> &WorkerSettings {
        &self.settings
    }

    /// Fit throughput counters.
    pub fn stats(&self) -> &FitStats {
        &self.stats
    }

    /// A new queued job record (not yet stored).
    pub fn new_job(sequence_id: Uuid, method: Method, params: ValidFitParams) -> JobRecord {
        JobRecord::queued(sequence_id, method, params)
    }

    /// Stores a queued job and wakes a worker. Blocking.
    pub fn submit(&self, job: &JobRecord) -> Result<(), StoreError> {
        self.store.insert_job(job)?;
        self.wake.notify();
        Ok(())
    }

    /// Cancels a queued job at once, or tells the worker of a running one to stop at its next
    /// iteration. Blocking.
    pub fn cancel(&self, id: Uuid) -> Result<CancelOutcome, StoreError> {
        let outcome = self.store.request_cancel(id)?;
        if let CancelOutcome::Accepted(job) = &outcome {
            if let Some(flag) = self.running.lock().unwrap_or_else(|p| p.into_inner()).get(&id) {
                flag.store(true, Ordering::Relaxed);
            }
            self.publish(job);
        }
        Ok(outcome)
    }

    /// A channel that receives the job's state whenever a worker of this process reports it
    /// (`None` until the first report after subscribing). Subscribe first, then read the
    /// store: a report made in between is not missed.
    pub fn subscribe(&self, id: Uuid) -> watch::Receiver<Option<JobRecord>> {
        let mut watchers = self.watchers.lock().unwrap_or_else(|p| p.into_inner());
        watchers.retain(|_, tx| tx.receiver_count() > 0);
        watchers.entry(id).or_insert_with(|| watch::channel(None).0).subscribe()
    }

    /// Tells watchers of `job` its new state; a terminal state is the last.
    fn publish(&self, job: &JobRecord) {
        let mut watchers = self.watchers.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(tx) = watchers.get(&job.id) {
            tx.send_replace(Some(job.clone()));
            if job.status.is_terminal() {
                watchers.remove(&job.id);
            }
        }
    }

    fn register_running(&self, id: Uuid) -> Arc<AtomicBool> {
        let flag = Arc::new(AtomicBool::new(false));
        self.running.lock().unwrap_or_else(|p| p.into_inner()).insert(id, flag.clone());
        flag
    }

    fn unregister_running(&self, id: Uuid) {
        self.running.lock().unwrap_or_else(|p| p.into_inner()).remove(&id);
        self.stats.forget(id);
    }
}

#[cfg(test)]
mod tests;
