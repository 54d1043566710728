//! The embedded store: one SQLite database (WAL mode) for metadata, the queue and progress,
//! and the data directory for frames and models ([`super::files`]).
//!
//! One connection behind a mutex: statements are short (the heavy bytes live in files), so
//! a pool would buy little; callers run every method off the async executor.

use std::fs;
use std::sync::{Arc, Mutex, MutexGuard};

use rusqlite::{Connection, OptionalExtension, Row, params};
use uuid::Uuid;

use super::files::{self, DataDir};
use super::{
    CancelOutcome, Claim, DeleteOutcome, FrameSink, JobFilter, JobOutcome, JobProgress, JobRecord, JobStatus,
    LeaseStatus, SequenceMeta, SequenceRecord, Store, StoreError, now_ms,
};
use crate::fit::Method;
use crate::geometry::Point;

/// Schema version stored in `PRAGMA user_version` (2: a running job's worker and lease, and
/// the claims of windows fitted by other workers).
const SCHEMA_VERSION: i64 = 2;

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS sequences (
    id TEXT PRIMARY KEY,
    name TEXT,
    points_per_frame TEXT NOT NULL,
    timestamps TEXT,
    poses TEXT,
    created_at INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    sequence_id TEXT NOT NULL,
    method TEXT NOT NULL,
    params TEXT NOT NULL,
    status TEXT NOT NULL,
    progress TEXT NOT NULL,
    error TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    attempts INTEGER NOT NULL DEFAULT 0,
    created_at INTEGER NOT NULL,
    started_at INTEGER,
    finished_at INTEGER,
    worker TEXT,
    lease_expires_at INTEGER
);
CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs (status);
CREATE TABLE IF NOT EXISTS window_claims (
    job_id TEXT NOT NULL,
    key TEXT NOT NULL,
    worker TEXT NOT NULL,
    lease_expires_at INTEGER NOT NULL,
    PRIMARY KEY (job_id, key)
);
CREATE INDEX IF NOT EXISTS jobs_by_sequence ON jobs (sequence_id);
";

/// What version 1 (no leases) needs to become version 2.
const MIGRATE_1_TO_2: &str = "
ALTER TABLE jobs ADD COLUMN worker TEXT;
ALTER TABLE jobs ADD COLUMN lease_expires_at INTEGER;
";

const JOB_COLUMNS: &str = "id, sequence_id, method, params, status, progress, error, cancel_requested, attempts, \
                           created_at, started_at, finished_at, worker, lease_expires_at";

struct Inner {
    conn: Mutex<Connection>,
    dir: DataDir,
    /// The data directory's lock, held for as long as the store is open (the kernel releases
    /// it when the process dies, however it dies).
    _lock: fs::File,
}

impl Inner {
    fn conn(&self) -> MutexGuard<'_, Connection> {
        // A panic while holding the lock cannot leave SQLite inconsistent (statements are
        // atomic), so a poisoned lock is still usable.
        self.conn.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// SQLite + data-directory implementation of [`Store`]. Cheap to clone (shared state).
#[derive(Clone)]
pub struct SqliteStore {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for SqliteStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SqliteStore").field("dir", &self.inner.dir.root()).finish()
    }
}

impl SqliteStore {
    /// Opens (creating when absent) the store in `data_dir`, and removes what a crash may
    /// have left behind: staged uploads, upload parts, and files no record refers to.
    ///
    /// Fails with [`StoreError::InUse`] while another open store (in this or another process)
    /// holds the directory: the clean-up here and [`Store::requeue_running_jobs`] assume that
    /// no one else is uploading or fitting in it.
    pub fn open(data_dir: &std::path::Path) -> Result<Self, StoreError> {
        let dir = DataDir::create(data_dir)?;
        let lock = lock_data_dir(&dir)?;
        let conn = Connection::open(dir.database())?;
        conn.busy_timeout(std::time::Duration::from_secs(10))?;
        let mode: String = conn.query_row("PRAGMA journal_mode = WAL", [], |r| r.get(0))?;
        if !mode.eq_ignore_ascii_case("wal") {
            return Err(StoreError::Corrupt(format!("could not switch the database to WAL mode (got {mode})")));
        }
        // FULL: a committed job or sequence survives a power loss, not just a process crash.
        conn.execute_batch("PRAGMA synchronous = FULL;")?;
        let version: i64 = conn.query_row("PRAGMA user_version", [], |r| r.get(0))?;
        if version > SCHEMA_VERSION {
            return Err(StoreError::Corrupt(format!(
                "database schema version {version} is newer than this program's ({SCHEMA_VERSION})"
            )));
        }
        if version == 1 {
            conn.execute_batch(MIGRATE_1_TO_2)?;
        }
        conn.execute_batch(SCHEMA)?;
        conn.execute_batch(&format!("PRAGMA user_version = {SCHEMA_VERSION};"))?;
        let store = Self { inner: Arc::new(Inner { conn: Mutex::new(conn), dir, _lock: lock }) };
        store.sweep()?;
        Ok(store)
    }

    /// The data directory.
    pub fn data_dir(&self) -> &DataDir {
        &self.inner.dir
    }

    /// Removes files no committed record refers to (left by a crash mid-upload or mid-delete).
    fn sweep(&self) -> Result<(), StoreError> {
        let dir = &self.inner.dir;
        for parent in [dir.staging_dir(), dir.tmp_dir()] {
            for entry in fs::read_dir(&parent)? {
                let path = entry?.path();
                let removed = if path.is_dir() { fs::remove_dir_all(&path) } else { fs::remove_file(&path) };
                if let Err(e) = removed {
                    tracing::warn!(path = %path.display(), error = %e, "could not remove a leftover upload");
                }
            }
        }
        let (sequences, models) = {
            let conn = self.inner.conn();
            let sequences: Vec<String> =
                conn.prepare("SELECT id FROM sequences")?.query_map([], |r| r.get(0))?.collect::<Result<_, _>>()?;
            let models: Vec<String> = conn
                .prepare("SELECT id FROM jobs WHERE status = 'succeeded'")?
                .query_map([], |r| r.get(0))?
                .collect::<Result<_, _>>()?;
            (sequences, models)
        };
        for entry in fs::read_dir(dir.sequences_dir())? {
            let entry = entry?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if !sequences.contains(&name) {
                tracing::info!(sequence = %name, "removing frames of a sequence that was never committed or was deleted");
                fs::remove_dir_all(entry.path())?;
            }
        }
        // Kept windows of jobs that will not run again (finished or deleted while the process
        // was down).
        let unfinished: Vec<String> = self
            .inner
            .conn()
            .prepare("SELECT id FROM jobs WHERE status IN ('queued', 'running')")?
            .query_map([], |r| r.get(0))?
            .collect::<Result<_, _>>()?;
        for entry in fs::read_dir(dir.windows_dir())? {
            let entry = entry?;
            if !unfinished.contains(&entry.file_name().to_string_lossy().into_owned()) {
                fs::remove_dir_all(entry.path())?;
            }
        }
        for entry in fs::read_dir(dir.models_dir())? {
            let entry = entry?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let job = name.strip_suffix(".mbnt").unwrap_or("");
            if !models.iter().any(|m| m == job) {
                fs::remove_file(entry.path())?;
            }
        }
        Ok(())
    }
}

/// A window key names a file: letters, digits and `-` only, so it cannot leave its directory.
fn check_window_key(key: &str) -> Result<(), StoreError> {
    if key.is_empty() || !key.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
        return Err(StoreError::Io(std::io::Error::other(format!("invalid window key {key:?}"))));
    }
    Ok(())
}

/// Takes the exclusive lock of the data directory, without waiting.
fn lock_data_dir(dir: &DataDir) -> Result<fs::File, StoreError> {
    let path = dir.lock_file();
    let file = fs::OpenOptions::new().create(true).truncate(false).write(true).open(&path)?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(fs::TryLockError::WouldBlock) => Err(StoreError::InUse(format!(
            "the data directory {} is in use by another mbnt process (its lock file {} is held)",
            dir.root().display(),
            path.display()
        ))),
        Err(fs::TryLockError::Error(e)) => Err(e.into()),
    }
}

/// A sequence being uploaded into `staging/{id}/`.
struct SqliteFrameSink {
    inner: Arc<Inner>,
    id: Uuid,
    staging: std::path::PathBuf,
    points_per_frame: Vec<usize>,
    committed: bool,
}

impl FrameSink for SqliteFrameSink {
    fn put_frame(&mut self, points: &[Point]) -> Result<(), StoreError> {
        let k = self.points_per_frame.len();
        files::write_frame_file(&self.staging.join(files::frame_file_name(k)), points)?;
        self.points_per_frame.push(points.len());
        Ok(())
    }

    fn frames_written(&self) -> usize {
        self.points_per_frame.len()
    }

    fn commit(mut self: Box<Self>, meta: SequenceMeta) -> Result<SequenceRecord, StoreError> {
        let record = SequenceRecord {
            id: self.id,
            name: meta.name,
            points_per_frame: std::mem::take(&mut self.points_per_frame),
            timestamps_s: meta.timestamps_s,
            poses: meta.poses,
            created_at_ms: now_ms(),
        };
        // Frames are fsynced; make their directory entries durable, then publish the
        // directory with one rename, then the row. A crash before the row leaves an orphan
        // directory that the next start removes.
        files::sync_dir(&self.staging)?;
        let target = self.inner.dir.sequence_dir(&self.id.to_string());
        fs::rename(&self.staging, &target)?;
        self.committed = true;
        files::sync_dir(&self.inner.dir.sequences_dir())?;
        let inserted = self.inner.conn().execute(
            "INSERT INTO sequences (id, name, points_per_frame, timestamps, poses, created_at) \
             VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            params![
                record.id.to_string(),
                record.name,
                json(&record.points_per_frame),
                record.timestamps_s.as_ref().map(json),
                record.poses.as_ref().map(json),
                record.created_at_ms
            ],
        );
        if let Err(e) = inserted {
            let _ = fs::remove_dir_all(&target);
            return Err(e.into());
        }
        Ok(record)
    }
}

impl Drop for SqliteFrameSink {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_dir_all(&self.staging);
        }
    }
}

fn json<T: serde::Serialize>(value: &T) -> String {
    serde_json::to_string(value).expect("plain data always serialises")
}

fn parse<T: serde::de::DeserializeOwned>(what: &str, text: &str) -> Result<T, StoreError> {
    serde_json::from_str(text).map_err(|e| StoreError::Corrupt(format!("{what}: {e}")))
}

fn parse_uuid(text: &str) -> Result<Uuid, StoreError> {
    Uuid::parse_str(text).map_err(|e| StoreError::Corrupt(format!("id {text:?}: {e}")))
}

/// A `sequences` row as stored.
struct RawSequence {
    id: String,
    name: Option<String>,
    points_per_frame: String,
    timestamps: Option<String>,
    poses: Option<String>,
    created_at: i64,
}

impl RawSequence {
    const COLUMNS: &str = "id, name, points_per_frame, timestamps, poses, created_at";

    fn from_row(r: &Row<'_>) -> rusqlite::Result<Self> {
        Ok(Self {
            id: r.get(0)?,
            name: r.get(1)?,
            points_per_frame: r.get(2)?,
            timestamps: r.get(3)?,
            poses: r.get(4)?,
            created_at: r.get(5)?,
        })
    }

    fn decode(self) -> Result<SequenceRecord, StoreError> {
        Ok(SequenceRecord {
            id: parse_uuid(&self.id)?,
            name: self.name,
            points_per_frame: parse("points_per_frame", &self.points_per_frame)?,
            timestamps_s: self.timestamps.as_deref().map(|t| parse("timestamps", t)).transpose()?,
            poses: self.poses.as_deref().map(|p| parse("poses", p)).transpose()?,
            created_at_ms: self.created_at,
        })
    }
}

/// A `jobs` row as stored.
struct RawJob {
    id: String,
    sequence_id: String,
    method: String,
    params: String,
    status: String,
    progress: String,
    error: Option<String>,
    cancel_requested: bool,
    attempts: u32,
    created_at: i64,
    started_at: Option<i64>,
    finished_at: Option<i64>,
    worker: Option<String>,
    lease_expires_at: Option<i64>,
}

impl RawJob {
    fn from_row(r: &Row<'_>) -> rusqlite::Result<Self> {
        Ok(Self {
            id: r.get(0)?,
            sequence_id: r.get(1)?,
            method: r.get(2)?,
            params: r.get(3)?,
            status: r.get(4)?,
            progress: r.get(5)?,
            error: r.get(6)?,
            cancel_requested: r.get(7)?,
            attempts: r.get(8)?,
            created_at: r.get(9)?,
            started_at: r.get(10)?,
            finished_at: r.get(11)?,
            worker: r.get(12)?,
            lease_expires_at: r.get(13)?,
        })
    }

    fn decode(self) -> Result<JobRecord, StoreError> {
        Ok(JobRecord {
            id: parse_uuid(&self.id)?,
            sequence_id: parse_uuid(&self.sequence_id)?,
            method: self.method.parse::<Method>().map_err(StoreError::Corrupt)?,
            params: parse("params", &self.params)?,
            status: self.status.parse::<JobStatus>().map_err(StoreError::Corrupt)?,
            progress: parse("progress", &self.progress)?,
            error: self.error,
            cancel_requested: self.cancel_requested,
            attempts: self.attempts,
            created_at_ms: self.created_at,
            started_at_ms: self.started_at,
            finished_at_ms: self.finished_at,
            worker: self.worker,
            lease_expires_at_ms: self.lease_expires_at,
        })
    }
}

/// Milliseconds of a lease, saturated.
fn lease_ms(lease: std::time::Duration) -> i64 {
    i64::try_from(lease.as_millis()).unwrap_or(i64::MAX / 2)
}

fn get_job(conn: &Connection, id: Uuid) -> Result<Option<JobRecord>, StoreError> {
    conn.query_row(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?1"), [id.to_string()], RawJob::from_row)
        .optional()?
        .map(RawJob::decode)
        .transpose()
}

fn require_job(conn: &Connection, id: Uuid) -> Result<JobRecord, StoreError> {
    get_job(conn, id)?.ok_or_else(|| StoreError::Missing(format!("job {id}")))
}

impl Store for SqliteStore {
    fn begin_sequence(&self) -> Result<Box<dyn FrameSink>, StoreError> {
        let id = Uuid::new_v4();
        let staging = self.inner.dir.staging_dir().join(id.to_string());
        fs::create_dir(&staging)?;
        Ok(Box::new(SqliteFrameSink {
            inner: self.inner.clone(),
            id,
            staging,
            points_per_frame: Vec::new(),
            committed: false,
        }))
    }

    fn get_sequence(&self, id: Uuid) -> Result<Option<SequenceRecord>, StoreError> {
        let conn = self.inner.conn();
        conn.query_row(
            &format!("SELECT {} FROM sequences WHERE id = ?1", RawSequence::COLUMNS),
            [id.to_string()],
            RawSequence::from_row,
        )
        .optional()?
        .map(RawSequence::decode)
        .transpose()
    }

    fn list_sequences(&self, limit: usize) -> Result<Vec<SequenceRecord>, StoreError> {
        let conn = self.inner.conn();
        let mut stmt = conn.prepare(&format!(
            "SELECT {} FROM sequences ORDER BY created_at DESC, rowid DESC LIMIT ?1",
            RawSequence::COLUMNS
        ))?;
        let raw = stmt
            .query_map([i64::try_from(limit).unwrap_or(i64::MAX)], RawSequence::from_row)?
            .collect::<Result<Vec<_>, _>>()?;
        raw.into_iter().map(RawSequence::decode).collect()
    }

    fn delete_sequence(&self, id: Uuid) -> Result<DeleteOutcome, StoreError> {
        let key = id.to_string();
        let jobs: Vec<String> = {
            let mut conn = self.inner.conn();
            let tx = conn.transaction()?;
            let exists = tx.query_row("SELECT 1 FROM sequences WHERE id = ?1", [&key], |_| Ok(())).optional()?;
            if exists.is_none() {
                return Ok(DeleteOutcome::NotFound);
            }
            let active: i64 = tx.query_row(
                "SELECT COUNT(*) FROM jobs WHERE sequence_id = ?1 AND status IN ('queued', 'running')",
                [&key],
                |r| r.get(0),
            )?;
            if active > 0 {
                return Ok(DeleteOutcome::HasActiveJobs);
            }
            let jobs = tx
                .prepare("SELECT id FROM jobs WHERE sequence_id = ?1")?
                .query_map([&key], |r| r.get(0))?
                .collect::<Result<Vec<String>, _>>()?;
            tx.execute(
                "DELETE FROM window_claims WHERE job_id IN (SELECT id FROM jobs WHERE sequence_id = ?1)",
                [&key],
            )?;
            tx.execute("DELETE FROM jobs WHERE sequence_id = ?1", [&key])?;
            tx.execute("DELETE FROM sequences WHERE id = ?1", [&key])?;
            tx.commit()?;
            jobs
        };
        // The rows are gone, so nothing refers to these files any more; if removing them
        // fails, the next start's sweep does it.
        for job in jobs {
            let path = self.inner.dir.model_path(&job);
            if let Err(e) = fs::remove_file(&path)
                && e.kind() != std::io::ErrorKind::NotFound
            {
                tracing::warn!(path = %path.display(), error = %e, "could not remove a deleted job's model");
            }
        }
        if let Err(e) = fs::remove_dir_all(self.inner.dir.sequence_dir(&key)) {
            tracing::warn!(sequence = %key, error = %e, "could not remove a deleted sequence's frames");
        }
        Ok(DeleteOutcome::Deleted)
    }

    fn read_frame(&self, id: Uuid, k: usize) -> Result<Vec<Point>, StoreError> {
        let path = self.inner.dir.sequence_dir(&id.to_string()).join(files::frame_file_name(k));
        files::read_frame(&path).map_err(|e| {
            match e.kind() {
                std::io::ErrorKind::NotFound => StoreError::Missing(format!("frame {k} of sequence {id}")),
                // A bad magic, a wrong length, a file cut short: the file is damaged, not busy.
                // Users see this, so the data directory's path is left out.
                std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof => {
                    let what = e.to_string().replace(&format!("{} ", path.display()), "");
                    StoreError::Corrupt(format!("frame {k} of sequence {id}: {what}"))
                }
                _ => StoreError::Io(e),
            }
        })
    }

    fn insert_job(&self, job: &JobRecord) -> Result<(), StoreError> {
        let conn = self.inner.conn();
        let inserted = conn.execute(
            &format!(
                "INSERT INTO jobs ({JOB_COLUMNS}) SELECT ?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14 \
                 WHERE EXISTS (SELECT 1 FROM sequences WHERE id = ?2)"
            ),
            params![
                job.id.to_string(),
                job.sequence_id.to_string(),
                job.method.name(),
                json(&job.params),
                job.status.as_str(),
                json(&job.progress),
                job.error,
                job.cancel_requested,
                job.attempts,
                job.created_at_ms,
                job.started_at_ms,
                job.finished_at_ms,
                job.worker,
                job.lease_expires_at_ms
            ],
        )?;
        if inserted == 0 {
            return Err(StoreError::Missing(format!("sequence {}", job.sequence_id)));
        }
        Ok(())
    }

    fn get_job(&self, id: Uuid) -> Result<Option<JobRecord>, StoreError> {
        get_job(&self.inner.conn(), id)
    }

    fn list_jobs(&self, filter: &JobFilter) -> Result<Vec<JobRecord>, StoreError> {
        let conn = self.inner.conn();
        let mut stmt = conn.prepare(&format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE (?1 IS NULL OR status = ?1) AND (?2 IS NULL OR sequence_id = ?2) \
             ORDER BY created_at DESC, rowid DESC LIMIT ?3"
        ))?;
        let raw = stmt
            .query_map(
                params![
                    filter.status.map(JobStatus::as_str),
                    filter.sequence_id.map(|s| s.to_string()),
                    i64::try_from(filter.limit).unwrap_or(i64::MAX)
                ],
                RawJob::from_row,
            )?
            .collect::<Result<Vec<_>, _>>()?;
        raw.into_iter().map(RawJob::decode).collect()
    }

    fn claim_next_job(&self, claim: &Claim) -> Result<Option<JobRecord>, StoreError> {
        let mut conn = self.inner.conn();
        let tx = conn.transaction()?;
        let now = now_ms();
        // A job whose worker died after a user asked to cancel it ends cancelled, as asked.
        tx.execute(
            "UPDATE jobs SET status = 'cancelled', finished_at = ?1, worker = NULL, lease_expires_at = NULL \
             WHERE status = 'running' AND lease_expires_at < ?1 AND cancel_requested = 1",
            [now],
        )?;
        // Orderly hand-backs give their attempt back, so `attempts` counts runs that died:
        // a job that used them all fails rather than killing another worker.
        tx.execute(
            "UPDATE jobs SET status = 'failed', finished_at = ?1, worker = NULL, lease_expires_at = NULL, \
             error = 'its worker stopped without finishing ' || attempts || ' times (the process died or \
             lost the database); max_attempts is ' || ?2 \
             WHERE (status = 'queued' OR (status = 'running' AND lease_expires_at < ?1)) AND attempts >= ?2",
            params![now, claim.max_attempts],
        )?;
        let job = tx
            .query_row(
                &format!(
                    "UPDATE jobs SET status = 'running', started_at = ?1, attempts = attempts + 1, worker = ?2, \
                     lease_expires_at = ?1 + ?3 \
                     WHERE id = (SELECT id FROM jobs WHERE status = 'queued' \
                                 OR (status = 'running' AND lease_expires_at < ?1) \
                                 ORDER BY created_at, rowid LIMIT 1) \
                     RETURNING {JOB_COLUMNS}"
                ),
                params![now, claim.worker, lease_ms(claim.lease)],
                RawJob::from_row,
            )
            .optional()?;
        tx.commit()?;
        job.map(RawJob::decode).transpose()
    }

    fn renew_lease(&self, id: Uuid, worker: &str, lease: std::time::Duration) -> Result<LeaseStatus, StoreError> {
        let conn = self.inner.conn();
        let cancel: Option<bool> = conn
            .query_row(
                "UPDATE jobs SET lease_expires_at = ?3 WHERE id = ?1 AND status = 'running' AND worker = ?2 \
                 RETURNING cancel_requested",
                params![id.to_string(), worker, now_ms().saturating_add(lease_ms(lease))],
                |r| r.get(0),
            )
            .optional()?;
        Ok(cancel.map_or(LeaseStatus::Lost, |cancel_requested| LeaseStatus::Held { cancel_requested }))
    }

    fn update_progress(&self, id: Uuid, worker: &str, progress: &JobProgress) -> Result<LeaseStatus, StoreError> {
        let conn = self.inner.conn();
        let cancel: Option<bool> = conn
            .query_row(
                "UPDATE jobs SET progress = ?3 WHERE id = ?1 AND status = 'running' AND worker = ?2 \
                 RETURNING cancel_requested",
                params![id.to_string(), worker, json(progress)],
                |r| r.get(0),
            )
            .optional()?;
        Ok(cancel.map_or(LeaseStatus::Lost, |cancel_requested| LeaseStatus::Held { cancel_requested }))
    }

    fn finish_job(&self, id: Uuid, worker: &str, outcome: JobOutcome<'_>) -> Result<JobRecord, StoreError> {
        let key = id.to_string();
        let held = |conn: &Connection| -> Result<JobRecord, StoreError> {
            let job = require_job(conn, id)?;
            if job.status != JobStatus::Running || job.worker.as_deref() != Some(worker) {
                return Err(StoreError::LeaseLost(format!("job {id} is no longer held by {worker}")));
            }
            Ok(job)
        };
        held(&self.inner.conn())?;
        let (status, error) = match &outcome {
            JobOutcome::Succeeded { model } => {
                files::write_atomic(&self.inner.dir.model_path(&key), |w| std::io::Write::write_all(w, model))?;
                (JobStatus::Succeeded, None)
            }
            JobOutcome::Failed { error } => (JobStatus::Failed, Some(error.clone())),
            JobOutcome::Cancelled => (JobStatus::Cancelled, None),
        };
        let conn = self.inner.conn();
        let mut job = held(&conn)?;
        if status == JobStatus::Succeeded {
            job.progress.fraction = 1.0;
            job.progress.eta_s = Some(0.0);
        }
        conn.execute(
            "UPDATE jobs SET status = ?2, error = ?3, progress = ?4, finished_at = ?5, worker = NULL, \
             lease_expires_at = NULL WHERE id = ?1",
            params![key, status.as_str(), error, json(&job.progress), now_ms()],
        )?;
        conn.execute("DELETE FROM window_claims WHERE job_id = ?1", [&key])?;
        let job = require_job(&conn, id)?;
        drop(conn);
        // The job will not run again: its kept windows and checkpoints are of no more use. If
        // removing them fails, the next start's sweep does it.
        let windows = self.inner.dir.windows_dir().join(&key);
        if let Err(e) = fs::remove_dir_all(&windows)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            tracing::warn!(path = %windows.display(), error = %e, "could not remove a finished job's windows");
        }
        Ok(job)
    }

    fn fail_succeeded_job(&self, id: Uuid, error: &str) -> Result<Option<JobRecord>, StoreError> {
        let conn = self.inner.conn();
        // The model file stays, for an operator to look at; deleting the sequence removes it.
        conn.execute(
            "UPDATE jobs SET status = 'failed', error = ?2 WHERE id = ?1 AND status = 'succeeded'",
            params![id.to_string(), error],
        )?;
        get_job(&conn, id)
    }

    fn requeue_job(&self, id: Uuid, worker: &str) -> Result<JobRecord, StoreError> {
        let conn = self.inner.conn();
        let n = conn.execute(
            "UPDATE jobs SET status = 'queued', attempts = MAX(attempts - 1, 0), worker = NULL, \
             lease_expires_at = NULL WHERE id = ?1 AND status = 'running' AND worker = ?2",
            params![id.to_string(), worker],
        )?;
        if n == 0 {
            return Err(StoreError::LeaseLost(format!("job {id} is no longer held by {worker}")));
        }
        require_job(&conn, id)
    }

    fn request_cancel(&self, id: Uuid) -> Result<CancelOutcome, StoreError> {
        let mut conn = self.inner.conn();
        let tx = conn.transaction()?;
        let Some(job) = get_job(&tx, id)? else {
            return Ok(CancelOutcome::NotFound);
        };
        let key = id.to_string();
        match job.status {
            JobStatus::Queued => {
                tx.execute(
                    "UPDATE jobs SET status = 'cancelled', finished_at = ?2 WHERE id = ?1",
                    params![key, now_ms()],
                )?;
            }
            JobStatus::Running => {
                tx.execute("UPDATE jobs SET cancel_requested = 1 WHERE id = ?1", [&key])?;
            }
            JobStatus::Cancelled => {}
            JobStatus::Succeeded | JobStatus::Failed => return Ok(CancelOutcome::AlreadyFinished(job)),
        }
        let job = require_job(&tx, id)?;
        tx.commit()?;
        Ok(CancelOutcome::Accepted(job))
    }

    fn requeue_running_jobs(&self) -> Result<usize, StoreError> {
        let mut conn = self.inner.conn();
        let tx = conn.transaction()?;
        // A job whose cancellation was requested before the crash ends cancelled, as asked.
        tx.execute(
            "UPDATE jobs SET status = 'cancelled', finished_at = ?1, worker = NULL, lease_expires_at = NULL \
             WHERE status = 'running' AND cancel_requested = 1",
            [now_ms()],
        )?;
        let n = tx.execute(
            "UPDATE jobs SET status = 'queued', worker = NULL, lease_expires_at = NULL WHERE status = 'running'",
            [],
        )?;
        tx.commit()?;
        Ok(n)
    }

    fn put_window_model(&self, job_id: Uuid, key: &str, model: &[u8]) -> Result<(), StoreError> {
        check_window_key(key)?;
        let path = self.inner.dir.window_model_path(&job_id.to_string(), key);
        fs::create_dir_all(path.parent().expect("a window model has a directory"))?;
        files::write_atomic(&path, |w| std::io::Write::write_all(w, model))?;
        Ok(())
    }

    fn claim_window(&self, id: Uuid, key: &str, worker: &str, lease: std::time::Duration) -> Result<bool, StoreError> {
        let mut conn = self.inner.conn();
        let tx = conn.transaction()?;
        let running = tx
            .query_row("SELECT 1 FROM jobs WHERE id = ?1 AND status = 'running'", [id.to_string()], |_| Ok(()))
            .optional()?
            .is_some();
        if !running {
            return Ok(false);
        }
        let now = now_ms();
        let n = tx.execute(
            "INSERT INTO window_claims (job_id, key, worker, lease_expires_at) VALUES (?1, ?2, ?3, ?4) \
             ON CONFLICT (job_id, key) DO UPDATE SET worker = excluded.worker, \
             lease_expires_at = excluded.lease_expires_at \
             WHERE window_claims.worker = excluded.worker OR window_claims.lease_expires_at < ?5",
            params![id.to_string(), key, worker, now.saturating_add(lease_ms(lease)), now],
        )?;
        tx.commit()?;
        Ok(n == 1)
    }

    fn release_window(&self, id: Uuid, key: &str, worker: &str) -> Result<(), StoreError> {
        self.inner.conn().execute(
            "DELETE FROM window_claims WHERE job_id = ?1 AND key = ?2 AND worker = ?3",
            params![id.to_string(), key, worker],
        )?;
        Ok(())
    }

    fn window_keys(&self, job_id: Uuid) -> Result<Vec<String>, StoreError> {
        let dir = self.inner.dir.windows_dir().join(job_id.to_string());
        let entries = match fs::read_dir(&dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(e.into()),
        };
        let mut keys = Vec::new();
        for entry in entries {
            let name = entry?.file_name().to_string_lossy().into_owned();
            // Temporaries of an atomic write in progress start with a dot.
            if let Some(key) = name.strip_suffix(".mbnt").filter(|_| !name.starts_with('.')) {
                keys.push(key.to_string());
            }
        }
        Ok(keys)
    }

    fn read_window_model(&self, job_id: Uuid, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        check_window_key(key)?;
        match fs::read(self.inner.dir.window_model_path(&job_id.to_string(), key)) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn read_model(&self, job_id: Uuid) -> Result<Vec<u8>, StoreError> {
        fs::read(self.inner.dir.model_path(&job_id.to_string())).map_err(|e| {
            if e.kind() == std::io::ErrorKind::NotFound {
                StoreError::Missing(format!("model of job {job_id}"))
            } else {
                StoreError::Io(e)
            }
        })
    }

    fn count_jobs_by_status(&self) -> Result<Vec<(JobStatus, u64)>, StoreError> {
        let conn = self.inner.conn();
        let mut stmt = conn.prepare("SELECT status, COUNT(*) FROM jobs GROUP BY status")?;
        let rows = stmt.query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))?;
        let mut out = Vec::new();
        for row in rows {
            let (status, n) = row?;
            out.push((status.parse::<JobStatus>().map_err(StoreError::Corrupt)?, u64::try_from(n).unwrap_or(0)));
        }
        Ok(out)
    }

    fn ping(&self) -> Result<(), StoreError> {
        self.inner.conn().query_row("SELECT 1", [], |_| Ok(()))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::FitParams;

    fn temp_dir() -> std::path::PathBuf {
        std::env::temp_dir().join(format!("mbnt-store-{}", Uuid::new_v4()))
    }

    fn sequence(store: &SqliteStore) -> SequenceRecord {
        let mut sink = store.begin_sequence().unwrap();
        sink.put_frame(&[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]).unwrap();
        sink.put_frame(&[[0.0, 1.0, 0.0]]).unwrap();
        sink.commit(SequenceMeta { name: Some("s".into()), timestamps_s: Some(vec![0.0, 0.1]), poses: None }).unwrap()
    }

    fn job(sequence_id: Uuid) -> JobRecord {
        JobRecord::queued(sequence_id, Method::Ntp, FitParams::default().check(Method::Ntp).unwrap())
    }

    const WORKER: &str = "test:1:0";

    fn claim_as(worker: &str, lease_ms: u64, max_attempts: u32) -> Claim {
        Claim { worker: worker.into(), lease: std::time::Duration::from_millis(lease_ms), max_attempts }
    }

    /// A claim by [`WORKER`] with a lease no test outlives.
    fn claim() -> Claim {
        claim_as(WORKER, 600_000, 3)
    }

    #[test]
    fn a_committed_sequence_and_its_frames_survive_reopening() {
        let dir = temp_dir();
        let id = {
            let store = SqliteStore::open(&dir).unwrap();
            sequence(&store).id
        };
        let store = SqliteStore::open(&dir).unwrap();
        let seq = store.get_sequence(id).unwrap().unwrap();
        assert_eq!(seq.points_per_frame, vec![2, 1]);
        assert_eq!(seq.timestamps_s, Some(vec![0.0, 0.1]));
        assert_eq!(store.read_frame(id, 1).unwrap(), vec![[0.0, 1.0, 0.0]]);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_abandoned_upload_leaves_nothing_behind() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let mut sink = store.begin_sequence().unwrap();
        sink.put_frame(&[[1.0, 2.0, 3.0]]).unwrap();
        drop(sink);
        assert_eq!(fs::read_dir(store.data_dir().staging_dir()).unwrap().count(), 0);
        assert!(store.list_sequences(10).unwrap().is_empty());
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn jobs_are_claimed_oldest_first_and_only_once() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        let (a, b) = (job(seq.id), job(seq.id));
        store.insert_job(&a).unwrap();
        store.insert_job(&b).unwrap();
        let first = store.claim_next_job(&claim()).unwrap().unwrap();
        assert_eq!((first.id, first.status, first.attempts), (a.id, JobStatus::Running, 1));
        assert_eq!(store.claim_next_job(&claim()).unwrap().unwrap().id, b.id);
        assert!(store.claim_next_job(&claim()).unwrap().is_none());
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_job_for_a_missing_sequence_is_refused() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        assert!(matches!(store.insert_job(&job(Uuid::new_v4())), Err(StoreError::Missing(_))));
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn running_jobs_go_back_to_the_queue_on_restart_unless_cancelled() {
        let dir = temp_dir();
        let (a, b) = {
            let store = SqliteStore::open(&dir).unwrap();
            let seq = sequence(&store);
            let (a, b) = (job(seq.id), job(seq.id));
            store.insert_job(&a).unwrap();
            store.insert_job(&b).unwrap();
            store.claim_next_job(&claim()).unwrap();
            store.claim_next_job(&claim()).unwrap();
            assert!(matches!(store.request_cancel(b.id).unwrap(), CancelOutcome::Accepted(_)));
            (a.id, b.id)
        };
        let store = SqliteStore::open(&dir).unwrap();
        assert_eq!(store.requeue_running_jobs().unwrap(), 1);
        assert_eq!(store.get_job(a).unwrap().unwrap().status, JobStatus::Queued);
        assert_eq!(store.get_job(b).unwrap().unwrap().status, JobStatus::Cancelled);
        let again = store.claim_next_job(&claim()).unwrap().unwrap();
        assert_eq!((again.id, again.attempts), (a, 2));
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn cancelling_a_queued_job_is_immediate_and_a_running_one_is_flagged() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        let (a, b) = (job(seq.id), job(seq.id));
        store.insert_job(&a).unwrap();
        store.claim_next_job(&claim()).unwrap();
        store.insert_job(&b).unwrap();
        let CancelOutcome::Accepted(queued) = store.request_cancel(b.id).unwrap() else { panic!() };
        assert_eq!(queued.status, JobStatus::Cancelled);
        let held = |cancel_requested| LeaseStatus::Held { cancel_requested };
        assert_eq!(store.update_progress(a.id, WORKER, &JobProgress::default()).unwrap(), held(false));
        let CancelOutcome::Accepted(running) = store.request_cancel(a.id).unwrap() else { panic!() };
        assert_eq!((running.status, running.cancel_requested), (JobStatus::Running, true));
        assert_eq!(store.update_progress(a.id, WORKER, &JobProgress::default()).unwrap(), held(true));
        let done = store.finish_job(a.id, WORKER, JobOutcome::Cancelled).unwrap();
        assert_eq!(done.status, JobStatus::Cancelled);
        assert!(done.finished_at_ms.is_some());
        assert_eq!(store.request_cancel(Uuid::new_v4()).unwrap(), CancelOutcome::NotFound);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_sequence_with_active_jobs_is_kept_and_deleting_removes_models() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        let a = job(seq.id);
        store.insert_job(&a).unwrap();
        assert_eq!(store.delete_sequence(seq.id).unwrap(), DeleteOutcome::HasActiveJobs);
        store.claim_next_job(&claim()).unwrap();
        let done = store.finish_job(a.id, WORKER, JobOutcome::Succeeded { model: b"model" }).unwrap();
        assert_eq!((done.status, done.progress.fraction), (JobStatus::Succeeded, 1.0));
        assert_eq!(store.read_model(a.id).unwrap(), b"model");
        assert_eq!(store.delete_sequence(seq.id).unwrap(), DeleteOutcome::Deleted);
        assert!(store.get_job(a.id).unwrap().is_none());
        assert!(matches!(store.read_model(a.id), Err(StoreError::Missing(_))));
        assert!(!store.data_dir().sequence_dir(&seq.id.to_string()).exists());
        assert_eq!(store.delete_sequence(seq.id).unwrap(), DeleteOutcome::NotFound);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_data_directory_is_opened_by_one_store_at_a_time() {
        let dir = temp_dir();
        let first = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&first);
        let a = job(seq.id);
        first.insert_job(&a).unwrap();
        first.claim_next_job(&claim()).unwrap();
        // A second opening would sweep the first one's uploads and re-queue its running job.
        assert!(matches!(SqliteStore::open(&dir), Err(StoreError::InUse(_))));
        assert_eq!(first.get_job(a.id).unwrap().unwrap().status, JobStatus::Running);
        drop(first);
        let second = SqliteStore::open(&dir).unwrap();
        assert_eq!(second.requeue_running_jobs().unwrap(), 1);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn orphan_files_are_swept_at_startup() {
        let dir = temp_dir();
        {
            let store = SqliteStore::open(&dir).unwrap();
            let d = store.data_dir();
            fs::create_dir_all(d.sequence_dir("not-a-committed-sequence")).unwrap();
            fs::write(d.model_path("no-such-job"), b"x").unwrap();
            fs::write(d.tmp_dir().join("part"), b"x").unwrap();
            fs::create_dir_all(d.staging_dir().join("half")).unwrap();
            fs::create_dir_all(d.windows_dir().join("no-such-job")).unwrap();
        }
        let store = SqliteStore::open(&dir).unwrap();
        let d = store.data_dir();
        for sub in [d.sequences_dir(), d.models_dir(), d.tmp_dir(), d.staging_dir(), d.windows_dir()] {
            assert_eq!(fs::read_dir(&sub).unwrap().count(), 0, "{}", sub.display());
        }
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn jobs_are_listed_by_status_and_counted() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        for _ in 0..3 {
            store.insert_job(&job(seq.id)).unwrap();
        }
        store.claim_next_job(&claim()).unwrap();
        let queued = store
            .list_jobs(&JobFilter { status: Some(JobStatus::Queued), sequence_id: Some(seq.id), limit: 10 })
            .unwrap();
        assert_eq!(queued.len(), 2);
        let mut counts = store.count_jobs_by_status().unwrap();
        counts.sort_by_key(|(s, _)| s.as_str());
        assert_eq!(counts, vec![(JobStatus::Queued, 2), (JobStatus::Running, 1)]);
        assert_eq!(store.list_jobs(&JobFilter { limit: 1, ..Default::default() }).unwrap().len(), 1);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_expired_lease_lets_another_worker_claim_the_job_and_the_first_records_nothing() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        let a = job(seq.id);
        store.insert_job(&a).unwrap();
        let first = store.claim_next_job(&claim_as("w1", 200, 3)).unwrap().unwrap();
        assert_eq!((first.worker.as_deref(), first.attempts), (Some("w1"), 1));
        // A live lease keeps the job from everyone else.
        assert!(store.claim_next_job(&claim_as("w0", 600_000, 3)).unwrap().is_none());
        std::thread::sleep(std::time::Duration::from_millis(250));
        let second = store.claim_next_job(&claim_as("w2", 600_000, 3)).unwrap().unwrap();
        assert_eq!((second.id, second.worker.as_deref(), second.attempts), (a.id, Some("w2"), 2));
        assert!(store.claim_next_job(&claim_as("w3", 600_000, 3)).unwrap().is_none());
        let progress = JobProgress::default();
        assert_eq!(store.update_progress(a.id, "w1", &progress).unwrap(), LeaseStatus::Lost);
        let lost = std::time::Duration::from_secs(60);
        assert_eq!(store.renew_lease(a.id, "w1", lost).unwrap(), LeaseStatus::Lost);
        let late = store.finish_job(a.id, "w1", JobOutcome::Succeeded { model: b"stale" });
        assert!(matches!(late, Err(StoreError::LeaseLost(_))), "{late:?}");
        assert!(matches!(store.requeue_job(a.id, "w1"), Err(StoreError::LeaseLost(_))));
        assert!(matches!(store.read_model(a.id), Err(StoreError::Missing(_))));
        let held = LeaseStatus::Held { cancel_requested: false };
        assert_eq!(store.renew_lease(a.id, "w2", lost).unwrap(), held);
        let done = store.finish_job(a.id, "w2", JobOutcome::Succeeded { model: b"model" }).unwrap();
        assert_eq!((done.status, done.worker, done.lease_expires_at_ms), (JobStatus::Succeeded, None, None));
        assert_eq!(store.read_model(a.id).unwrap(), b"model");
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_renewed_lease_outlives_its_first_term() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        store.insert_job(&job(seq.id)).unwrap();
        let a = store.claim_next_job(&claim_as("w1", 300, 3)).unwrap().unwrap();
        for _ in 0..4 {
            std::thread::sleep(std::time::Duration::from_millis(100));
            let renewed = store.renew_lease(a.id, "w1", std::time::Duration::from_millis(300)).unwrap();
            assert_eq!(renewed, LeaseStatus::Held { cancel_requested: false });
        }
        // 400 ms after a 300 ms claim: without the renewals the job would be up for grabs.
        assert!(store.claim_next_job(&claim_as("w2", 300, 3)).unwrap().is_none());
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_job_whose_workers_keep_dying_fails_after_max_attempts_and_a_handed_back_run_is_free() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        let a = job(seq.id);
        store.insert_job(&a).unwrap();
        // Orderly hand-backs (shutdowns) do not use attempts up.
        for _ in 0..5 {
            let run = store.claim_next_job(&claim_as("w", 600_000, 2)).unwrap().unwrap();
            assert_eq!(run.attempts, 1);
            assert_eq!(store.requeue_job(a.id, "w").unwrap().attempts, 0);
        }
        for attempt in 1..=2 {
            let run = store.claim_next_job(&claim_as(&format!("w{attempt}"), 1, 2)).unwrap().unwrap();
            assert_eq!(run.attempts, attempt);
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        assert!(store.claim_next_job(&claim_as("w3", 600_000, 2)).unwrap().is_none());
        let failed = store.get_job(a.id).unwrap().unwrap();
        assert_eq!((failed.status, failed.worker), (JobStatus::Failed, None));
        let error = failed.error.unwrap();
        assert!(error.contains("2 times") && error.contains("max_attempts is 2"), "{error}");
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_version_1_database_gains_the_lease_columns_and_keeps_its_jobs() {
        let dir = temp_dir();
        let id = {
            let store = SqliteStore::open(&dir).unwrap();
            let seq = sequence(&store);
            let a = job(seq.id);
            store.insert_job(&a).unwrap();
            a.id
        };
        {
            // Back to version 1's table: the same columns without the lease.
            let conn = Connection::open(DataDir::create(&dir).unwrap().database()).unwrap();
            conn.execute_batch(
                "ALTER TABLE jobs DROP COLUMN worker; ALTER TABLE jobs DROP COLUMN lease_expires_at; \
                 PRAGMA user_version = 1;",
            )
            .unwrap();
        }
        let store = SqliteStore::open(&dir).unwrap();
        assert_eq!(store.get_job(id).unwrap().unwrap().status, JobStatus::Queued);
        let run = store.claim_next_job(&claim()).unwrap().unwrap();
        assert_eq!((run.id, run.worker.as_deref()), (id, Some(WORKER)));
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_window_is_claimed_by_one_worker_until_its_lease_expires_or_it_is_released() {
        let dir = temp_dir();
        let store = SqliteStore::open(&dir).unwrap();
        let seq = sequence(&store);
        crate::store::conformance::window_claims(&store, job(seq.id));
        let claims: i64 = store.inner.conn().query_row("SELECT COUNT(*) FROM window_claims", [], |r| r.get(0)).unwrap();
        assert_eq!(claims, 0, "the job's end ends its claims");
        fs::remove_dir_all(&dir).unwrap();
    }
}
