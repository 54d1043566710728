//! Persistent storage of the service: sequences (metadata and frames), jobs (the queue, their
//! progress and outcome) and fitted models.
//!
//! Everything goes through the [`Store`] trait so that another backend (e.g. PostgreSQL for the
//! queue and an object store for frames and models, with many worker machines) can replace the
//! embedded default, [`SqliteStore`] (an SQLite file plus a local data directory), without
//! touching the routes or the workers. Methods are blocking: async callers run them on
//! `spawn_blocking`.

pub mod blobs;
pub mod files;
pub mod postgres;
pub mod sqlite;

use std::path::PathBuf;
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use uuid::Uuid;

use crate::fit::{LossTerms, Method, TrackingProgress, ValidFitParams, WindowProgress};
use crate::geometry::Point;

pub use blobs::{Blobs, ObjectBlobs};
pub use postgres::PgStore;
pub use sqlite::SqliteStore;

/// A stored sequence's metadata (its frames live beside it, see [`Store::read_frame`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceRecord {
    /// Identifier.
    pub id: Uuid,
    /// Optional user-given name.
    pub name: Option<String>,
    /// Number of points of each frame (its length is the frame count T).
    pub points_per_frame: Vec<usize>,
    /// Timestamps (s, strictly increasing) when given at upload.
    pub timestamps_s: Option<Vec<f64>>,
    /// Sensor-to-world poses (row-major 4 x 4), one per frame, when given at upload.
    pub poses: Option<Vec<[f64; 16]>>,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: i64,
}

impl SequenceRecord {
    /// Number of frames T.
    pub fn frames(&self) -> usize {
        self.points_per_frame.len()
    }
}

/// What an upload supplies besides the frames.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SequenceMeta {
    /// Optional name.
    pub name: Option<String>,
    /// Timestamps (s), one per frame, strictly increasing (checked by the caller).
    pub timestamps_s: Option<Vec<f64>>,
    /// Sensor-to-world poses, one per frame (checked by the caller).
    pub poses: Option<Vec<[f64; 16]>>,
}

/// Life cycle of a job: `queued -> running -> succeeded | failed | cancelled`; a running job
/// goes back to `queued` when its process stops before the fit ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobStatus {
    /// Waiting for a worker.
    Queued,
    /// A worker is fitting it.
    Running,
    /// The model is stored and can be queried.
    Succeeded,
    /// The fit stopped with an error (see the job's `error`).
    Failed,
    /// Cancelled by a user.
    Cancelled,
}

impl JobStatus {
    /// Every status, in life-cycle order.
    pub const ALL: [JobStatus; 5] =
        [JobStatus::Queued, JobStatus::Running, JobStatus::Succeeded, JobStatus::Failed, JobStatus::Cancelled];

    /// The lower-case name used in the API and the database.
    pub fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
        }
    }

    /// Whether the job can no longer change.
    pub fn is_terminal(self) -> bool {
        matches!(self, JobStatus::Succeeded | JobStatus::Failed | JobStatus::Cancelled)
    }
}

impl std::str::FromStr for JobStatus {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        JobStatus::ALL
            .into_iter()
            .find(|j| j.as_str() == s)
            .ok_or_else(|| format!("unknown status {s:?} (expected queued, running, succeeded, failed or cancelled)"))
    }
}

/// How far a job has come.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct JobProgress {
    /// Fraction of the planned iterations done, in [0, 1] (1 once succeeded).
    pub fraction: f64,
    /// Iterations done.
    pub iteration: usize,
    /// Iterations planned (an upper bound for methods that stop early).
    pub iterations: usize,
    /// Loss terms of the latest iteration, once one is done.
    pub loss: Option<LossTerms>,
    /// Estimated seconds until the fit ends, once an iteration is done (none while the rigid
    /// tracks are built).
    pub eta_s: Option<f64>,
    /// Set while the rigid tracks are built, after the last iteration (absent in records
    /// written before the field existed).
    #[serde(default)]
    pub rigid_tracks: Option<TrackingProgress>,
    /// Set while a sequence longer than `window_frames` is fitted window by window: the
    /// window the iteration fields are about and the windows done; `fraction` and `eta_s` are
    /// then the whole log's (absent in records written before the field existed).
    #[serde(default)]
    pub window: Option<WindowProgress>,
    /// The iteration this run of the job went on from: the checkpoint an earlier run (its
    /// worker stopped or died) left of the window being fitted; `None` when it started from
    /// iteration 0.
    #[serde(default)]
    pub resumed_from_iteration: Option<usize>,
}

/// A job: one fit of one method to one sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct JobRecord {
    /// Identifier.
    pub id: Uuid,
    /// The sequence fitted.
    pub sequence_id: Uuid,
    /// The method.
    pub method: Method,
    /// Every hyper-parameter, defaults filled in.
    pub params: ValidFitParams,
    /// Where the job is in its life cycle.
    pub status: JobStatus,
    /// Progress of the current (or last) run.
    pub progress: JobProgress,
    /// Why the job failed, for failed jobs.
    pub error: Option<String>,
    /// A user asked to cancel the running job; its worker stops at the next iteration.
    pub cancel_requested: bool,
    /// How many runs of the job a worker started and did not hand back (a run interrupted by
    /// its worker's orderly shutdown gives its attempt back; one whose worker died does not).
    pub attempts: u32,
    /// The worker process holding the job while it runs (see [`Claim::worker`]).
    pub worker: Option<String>,
    /// When the holder's lease ends unless it is renewed, ms since the Unix epoch (by the
    /// database's clock): after it, any worker may claim the job again.
    pub lease_expires_at_ms: Option<i64>,
    /// Creation time, ms since the Unix epoch.
    pub created_at_ms: i64,
    /// When the current (or last) run started, ms since the Unix epoch.
    pub started_at_ms: Option<i64>,
    /// When the job reached a terminal status, ms since the Unix epoch.
    pub finished_at_ms: Option<i64>,
}

impl JobRecord {
    /// A new queued job of `method` on sequence `sequence_id` (not yet stored).
    pub fn queued(sequence_id: Uuid, method: Method, params: ValidFitParams) -> Self {
        Self {
            id: Uuid::new_v4(),
            sequence_id,
            method,
            progress: JobProgress { iterations: params.iterations, ..JobProgress::default() },
            params,
            status: JobStatus::Queued,
            error: None,
            cancel_requested: false,
            attempts: 0,
            worker: None,
            lease_expires_at_ms: None,
            created_at_ms: now_ms(),
            started_at_ms: None,
            finished_at_ms: None,
        }
    }
}

/// How a run ended, as recorded by [`Store::finish_job`].
#[derive(Debug)]
pub enum JobOutcome<'a> {
    /// The fit produced this serialised model.
    Succeeded {
        /// [`crate::model::FittedModel::to_bytes`] of the model.
        model: &'a [u8],
    },
    /// The fit failed with this message.
    Failed {
        /// What went wrong, for the user.
        error: String,
    },
    /// The fit was cancelled at a user's request.
    Cancelled,
}

/// Which jobs [`Store::list_jobs`] returns (newest first).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct JobFilter {
    /// Only jobs with this status.
    pub status: Option<JobStatus>,
    /// Only jobs of this sequence.
    pub sequence_id: Option<Uuid>,
    /// At most this many.
    pub limit: usize,
}

/// Who claims a job, and on which terms ([`Store::claim_next_job`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Claim {
    /// The claiming worker's name, unique among live workers (`host:pid:thread`).
    pub worker: String,
    /// How long the claim holds without a renewal ([`Store::renew_lease`]).
    pub lease: std::time::Duration,
    /// A job whose lease expired this many times (attempts) fails instead of running again.
    pub max_attempts: u32,
}

/// Whether a worker still holds its job ([`Store::renew_lease`], [`Store::update_progress`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeaseStatus {
    /// The worker holds the job; `cancel_requested` when a user asked to cancel it.
    Held {
        /// A user asked to cancel the job.
        cancel_requested: bool,
    },
    /// The job is no longer this worker's (its lease expired and the job went back to the
    /// queue, or it was deleted): the worker stops at once and records nothing.
    Lost,
}

/// What [`Store::delete_sequence`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeleteOutcome {
    /// The sequence, its finished jobs and their models are gone.
    Deleted,
    /// No such sequence.
    NotFound,
    /// Jobs of the sequence are queued or running; cancel them first.
    HasActiveJobs,
}

/// What [`Store::request_cancel`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum CancelOutcome {
    /// No such job.
    NotFound,
    /// A queued job is now cancelled, or a running one is flagged for its worker to stop.
    Accepted(JobRecord),
    /// The job had already succeeded or failed.
    AlreadyFinished(JobRecord),
}

/// A storage failure (I/O, database, corrupt data). Users see an opaque 500.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database failed.
    #[error("database: {0}")]
    Database(#[from] rusqlite::Error),
    /// A file operation failed.
    #[error("file: {0}")]
    Io(#[from] std::io::Error),
    /// Stored data could not be decoded.
    #[error("corrupt stored data: {0}")]
    Corrupt(String),
    /// A record the operation needs does not exist.
    #[error("{0} not found")]
    Missing(String),
    /// Another process is using the data directory.
    #[error("{0}")]
    InUse(String),
    /// The PostgreSQL database failed (the fleet's store, [`PgStore`](self)).
    #[error("postgres: {0}")]
    Postgres(String),
    /// The object store (local directory or S3) failed.
    #[error("object store: {0}")]
    Object(String),
    /// The worker no longer holds the job: its lease expired and the job went back to the
    /// queue (another worker may be running it now). The worker stops without recording.
    #[error("lease lost: {0}")]
    LeaseLost(String),
}

/// Receives the frames of a sequence being uploaded, in order. Dropping it without
/// [`FrameSink::commit`] discards everything written.
pub trait FrameSink: Send {
    /// Stores the next frame.
    fn put_frame(&mut self, points: &[Point]) -> Result<(), StoreError>;
    /// Frames stored so far.
    fn frames_written(&self) -> usize;
    /// Makes the sequence visible, atomically, with `meta`.
    fn commit(self: Box<Self>, meta: SequenceMeta) -> Result<SequenceRecord, StoreError>;
}

/// Storage of sequences, jobs and models. Every method blocks; implementations are shared
/// between the HTTP handlers and the worker threads.
pub trait Store: Send + Sync + 'static {
    /// Starts an upload of a new sequence.
    fn begin_sequence(&self) -> Result<Box<dyn FrameSink>, StoreError>;
    /// A sequence's metadata.
    fn get_sequence(&self, id: Uuid) -> Result<Option<SequenceRecord>, StoreError>;
    /// Sequences, newest first, at most `limit`.
    fn list_sequences(&self, limit: usize) -> Result<Vec<SequenceRecord>, StoreError>;
    /// Deletes a sequence with its finished jobs and their models, unless jobs are active.
    fn delete_sequence(&self, id: Uuid) -> Result<DeleteOutcome, StoreError>;
    /// Frame `k` of sequence `id`.
    fn read_frame(&self, id: Uuid, k: usize) -> Result<Vec<Point>, StoreError>;

    /// Adds a queued job. Errors with [`StoreError::Missing`] when its sequence does not exist.
    fn insert_job(&self, job: &JobRecord) -> Result<(), StoreError>;
    /// A job.
    fn get_job(&self, id: Uuid) -> Result<Option<JobRecord>, StoreError>;
    /// Jobs matching `filter`, newest first.
    fn list_jobs(&self, filter: &JobFilter) -> Result<Vec<JobRecord>, StoreError>;
    /// Atomically gives `claim.worker` the oldest job that is queued, or running under a lease
    /// that has expired (its worker died), as `running` under a lease of `claim.lease`, and
    /// counts an attempt. A job whose lease expired after `claim.max_attempts` attempts is
    /// failed, saying so, instead. Two workers never both hold a job.
    fn claim_next_job(&self, claim: &Claim) -> Result<Option<JobRecord>, StoreError>;
    /// Extends `worker`'s lease on job `id` to `lease` from now, if it still holds it.
    fn renew_lease(&self, id: Uuid, worker: &str, lease: std::time::Duration) -> Result<LeaseStatus, StoreError>;
    /// Records a running job's progress, if `worker` still holds it.
    fn update_progress(&self, id: Uuid, worker: &str, progress: &JobProgress) -> Result<LeaseStatus, StoreError>;
    /// Records how `worker`'s run of a job ended (the model first, durably, then the status).
    /// [`StoreError::LeaseLost`] when the worker no longer holds the job (nothing recorded).
    fn finish_job(&self, id: Uuid, worker: &str, outcome: JobOutcome<'_>) -> Result<JobRecord, StoreError>;
    /// Marks a succeeded job failed with `error`, because a stored file its answers need (its
    /// model, its sequence's frames) cannot be read. A job in another state is left as it is.
    /// Returns the job, `None` when it does not exist.
    fn fail_succeeded_job(&self, id: Uuid, error: &str) -> Result<Option<JobRecord>, StoreError>;
    /// Puts `worker`'s running job back in the queue, giving its attempt back (its process is
    /// stopping in order before the fit ended). [`StoreError::LeaseLost`] when the worker no
    /// longer holds it.
    fn requeue_job(&self, id: Uuid, worker: &str) -> Result<JobRecord, StoreError>;
    /// Cancels a queued job, or asks the worker of a running one to stop.
    fn request_cancel(&self, id: Uuid) -> Result<CancelOutcome, StoreError>;
    /// Puts back in the queue every `running` job whose worker is known to be gone: for the
    /// embedded store (one process owns it) every running job at startup; for a shared store
    /// those whose lease has expired. Returns how many were re-queued.
    fn requeue_running_jobs(&self) -> Result<usize, StoreError>;
    /// The serialised model of a succeeded job.
    fn read_model(&self, job_id: Uuid) -> Result<Vec<u8>, StoreError>;
    /// Keeps the model of a finished window (`key`: letters, digits and `-`) of a running job
    /// fitted as windows, or a mid-fit checkpoint, so that the job, run again after a restart
    /// or on another worker, need not fit it again. Removed when the job finishes.
    fn put_window_model(&self, job_id: Uuid, key: &str, model: &[u8]) -> Result<(), StoreError>;
    /// Claims window `key` of running job `id` for `worker` under a lease of `lease` (renewed
    /// when the worker holds it already), so that several workers fit the windows of one long
    /// log side by side without fitting one twice: `true` when the worker holds it now, `false`
    /// when another worker's live lease holds it or the job is not running. Claims end with the
    /// job.
    fn claim_window(&self, id: Uuid, key: &str, worker: &str, lease: std::time::Duration) -> Result<bool, StoreError>;
    /// Lets go of a window `worker` claimed (its model is kept, or its fit stopped).
    fn release_window(&self, id: Uuid, key: &str, worker: &str) -> Result<(), StoreError>;
    /// The keys of the window models and checkpoints kept for this job (without reading them).
    fn window_keys(&self, job_id: Uuid) -> Result<Vec<String>, StoreError>;
    /// A window model kept by [`Store::put_window_model`] for this job, if any.
    fn read_window_model(&self, job_id: Uuid, key: &str) -> Result<Option<Vec<u8>>, StoreError>;
    /// Number of jobs in each status (statuses without jobs are absent).
    fn count_jobs_by_status(&self) -> Result<Vec<(JobStatus, u64)>, StoreError>;
    /// Checks that the storage answers (for /healthz).
    fn ping(&self) -> Result<(), StoreError>;
}

/// Which store a process uses: the embedded one (SQLite and a local directory, one process) or
/// a fleet's (PostgreSQL and an object store, any number of processes).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StoreConfig {
    /// The fleet's PostgreSQL database (`postgres://...`); `None`: the embedded store.
    pub database_url: Option<String>,
    /// The fleet's object store (`file:///DIR`, `s3://BUCKET/PREFIX`); default with a
    /// database: `objects/` of the data directory.
    pub object_store_url: Option<String>,
}

/// Opens the store `config` names, with `data_dir` as the embedded store's directory (or, for a
/// fleet, the local scratch space and default object store); returns it and the scratch
/// directory for upload parts. The embedded store puts the jobs its last process left running
/// back in the queue (one process owns it, so their worker is gone).
pub fn open(data_dir: &std::path::Path, config: &StoreConfig) -> Result<(Arc<dyn Store>, PathBuf), StoreError> {
    let Some(database_url) = &config.database_url else {
        if config.object_store_url.is_some() {
            return Err(StoreError::InUse(
                "MBNT_OBJECT_STORE_URL needs MBNT_DATABASE_URL: the embedded store keeps its files in the data \
                 directory"
                    .into(),
            ));
        }
        let store = SqliteStore::open(data_dir)?;
        let requeued = store.requeue_running_jobs()?;
        if requeued > 0 {
            tracing::info!(requeued, "jobs interrupted by the last stop are queued again");
        }
        let tmp = store.data_dir().tmp_dir();
        return Ok((Arc::new(store), tmp));
    };
    open_fleet(data_dir, database_url, config.object_store_url.as_deref())
}

fn open_fleet(
    data_dir: &std::path::Path,
    database_url: &str,
    object_store_url: Option<&str>,
) -> Result<(Arc<dyn Store>, PathBuf), StoreError> {
    let default_objects;
    let object_store_url = match object_store_url {
        Some(url) => url,
        None => {
            let dir = std::path::absolute(data_dir.join("objects"))?;
            std::fs::create_dir_all(&dir)?;
            default_objects = format!("file://{}", dir.display());
            &default_objects
        }
    };
    let blobs = ObjectBlobs::from_url(object_store_url)?;
    tracing::info!(objects = blobs.url(), "fleet store: PostgreSQL and an object store");
    let store = PgStore::connect(database_url, Arc::new(blobs))?;
    // Upload parts stream to local scratch space before their frames go to the object store.
    let tmp = data_dir.join("tmp");
    std::fs::create_dir_all(&tmp)?;
    Ok((Arc::new(store), tmp))
}

/// Milliseconds since the Unix epoch, now.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

/// Formats milliseconds since the Unix epoch as RFC 3339 UTC (`2026-11-03T12:34:56.789Z`).
pub fn rfc3339(ms: i64) -> String {
    let secs = ms.div_euclid(1000);
    let millis = ms.rem_euclid(1000);
    let days = secs.div_euclid(86_400);
    let sod = secs.rem_euclid(86_400);
    // Civil date from days since 1970-01-01 (Howard Hinnant's `civil_from_days`).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{millis:03}Z", sod / 3600, (sod / 60) % 60, sod % 60)
}

/// Behaviour every [`Store`] shares, checked against each implementation by its tests.
#[cfg(test)]
pub(crate) mod conformance {
    use super::*;
    use std::time::Duration;

    /// Window claims: `job` (queued, of a stored sequence) is inserted and run; claims hold
    /// only while it runs, one worker at a time, until released or expired; its end ends them.
    pub(crate) fn window_claims(store: &dyn Store, job: JobRecord) {
        let ms = Duration::from_millis;
        store.insert_job(&job).unwrap();
        let id = job.id;
        // Not running yet: nothing to help with.
        assert!(!store.claim_window(id, "w-0-25", "w1", ms(60_000)).unwrap());
        let claim = Claim { worker: "owner".into(), lease: ms(600_000), max_attempts: 3 };
        assert_eq!(store.claim_next_job(&claim).unwrap().unwrap().id, id);
        assert!(store.claim_window(id, "w-0-25", "w1", ms(300)).unwrap());
        assert!(!store.claim_window(id, "w-0-25", "w2", ms(60_000)).unwrap());
        assert!(store.claim_window(id, "w-20-25", "w2", ms(60_000)).unwrap());
        // Renewed by its holder; taken over once expired.
        assert!(store.claim_window(id, "w-0-25", "w1", ms(300)).unwrap());
        std::thread::sleep(ms(400));
        assert!(store.claim_window(id, "w-0-25", "w2", ms(60_000)).unwrap());
        assert!(!store.claim_window(id, "w-0-25", "w1", ms(300)).unwrap());
        // Released by its holder only, then free for anyone.
        store.release_window(id, "w-20-25", "w1").unwrap();
        assert!(!store.claim_window(id, "w-20-25", "w3", ms(60_000)).unwrap());
        store.release_window(id, "w-20-25", "w2").unwrap();
        assert!(store.claim_window(id, "w-20-25", "w3", ms(60_000)).unwrap());
        // Kept windows are listed by key without being read.
        assert!(store.window_keys(id).unwrap().is_empty());
        store.put_window_model(id, "0-25", b"model").unwrap();
        store.put_window_model(id, "checkpoint-20-25", b"state").unwrap();
        let mut keys = store.window_keys(id).unwrap();
        keys.sort();
        assert_eq!(keys, ["0-25", "checkpoint-20-25"]);
        store.finish_job(id, "owner", JobOutcome::Cancelled).unwrap();
        assert!(!store.claim_window(id, "w-20-25", "w3", ms(60_000)).unwrap());
        assert!(store.window_keys(id).unwrap().is_empty(), "a finished job's windows are removed");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rfc3339_matches_known_instants() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00.000Z");
        // 2000-02-29T23:59:59.999Z, a leap day in a year divisible by 400.
        assert_eq!(rfc3339(951_868_799_999), "2000-02-29T23:59:59.999Z");
        // 2026-11-03T12:00:00Z.
        assert_eq!(rfc3339(1_793_707_200_000), "2026-11-03T12:00:00.000Z");
        assert_eq!(rfc3339(-1), "1969-12-31T23:59:59.999Z");
    }

    #[test]
    fn statuses_round_trip_through_their_names() {
        for s in JobStatus::ALL {
            assert_eq!(s.as_str().parse::<JobStatus>().unwrap(), s);
        }
        assert!("done".parse::<JobStatus>().is_err());
    }
}
