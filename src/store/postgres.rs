//! The fleet's store: PostgreSQL for metadata, the queue and progress, an object store
//! ([`Blobs`]) for the bytes, so that an API process and workers on many machines share one
//! queue.
//!
//! Objects: `sequences/{id}/frame_{k:05}.f32` ([`files::write_frame`] format),
//! `models/{job}.mbnt`, `windows/{job}/{key}.mbnt`. A row says which objects are committed:
//! an upload writes its frames straight to their final keys under an `uploads` row, and its
//! commit swaps that row for the sequence's in one transaction.
//!
//! Leases are timed by the database's clock (`mbnt_now_ms()`, see the migrations in
//! `migrations/postgres/`), never a worker's, because workers on different machines have
//! different clocks.
//!
//! The [`Store`] trait is blocking and sqlx is async: a [`PgStore`] owns a small tokio runtime
//! whose worker drives the connections' I/O and timers while the calling thread (a plain
//! thread, a `spawn_blocking` thread of another runtime, even an async task of one) waits.

use std::collections::{BTreeSet, HashSet};
use std::future::Future;
use std::str::FromStr;
use std::sync::Arc;
use std::task::{Context, Poll, Wake, Waker};
use std::time::{Duration, Instant};

use sqlx::postgres::{PgConnectOptions, PgPoolOptions, PgRow};
// `AssertSqlSafe`: the only formatted SQL splices in the column-list constants, never input.
use sqlx::{AssertSqlSafe, PgPool, Postgres, Row, Transaction};
use uuid::Uuid;

use super::blobs::Blobs;
use super::files;
use super::{
    CancelOutcome, Claim, DeleteOutcome, FrameSink, JobFilter, JobOutcome, JobProgress, JobRecord, JobStatus,
    LeaseStatus, SequenceMeta, SequenceRecord, Store, StoreError,
};
use crate::fit::Method;
use crate::geometry::Point;

/// The schema, embedded at build time and applied at connect (idempotent; sqlx takes an
/// advisory lock so that processes starting together apply it once).
static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("./migrations/postgres");

/// Connections per store: a handful of concurrent statements per process is plenty (the heavy
/// bytes go to the object store), and a fleet of processes must fit PostgreSQL's limit.
const POOL_CONNECTIONS: u32 = 4;

/// How long a statement waits for a free (or new) connection before failing.
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(10);

/// An upload whose row was not touched for this long is taken as dead (its process crashed)
/// by the janitor that [`PgStore::connect`] runs.
pub const STALE_UPLOAD: Duration = Duration::from_secs(3600);

/// How often a live upload refreshes its row, far more often than [`STALE_UPLOAD`].
const UPLOAD_TOUCH_INTERVAL: Duration = Duration::from_secs(60);

const JOB_COLUMNS: &str = "id, sequence_id, method, params, status, progress, error, cancel_requested, attempts, \
                           created_at, started_at, finished_at, worker, lease_expires_at";

const SEQUENCE_COLUMNS: &str = "id, name, points_per_frame, timestamps, poses, created_at";

impl From<sqlx::Error> for StoreError {
    fn from(e: sqlx::Error) -> Self {
        StoreError::Postgres(e.to_string())
    }
}

struct Inner {
    /// `Some` until dropped; taken in `Drop` to shut it down without waiting.
    runtime: Option<tokio::runtime::Runtime>,
    pool: PgPool,
    blobs: Arc<dyn Blobs>,
}

impl Inner {
    /// Runs `fut` to completion on the calling thread, with the store's runtime driving I/O.
    ///
    /// Not `Runtime::block_on`: it panics when the caller is itself inside a runtime's async
    /// context, and the `Store` contract is "blocking, callable from anywhere". The future only
    /// needs the runtime entered (so sqlx can reach tokio's reactor and spawn its tasks); the
    /// multi-thread runtime's worker, not this thread, drives the reactor and timers.
    fn run<F: Future>(&self, fut: F) -> F::Output {
        let _entered = self.runtime.as_ref().expect("the runtime lives as long as the store").enter();
        // Unconstrained: on another runtime's worker thread, tokio's per-task budget would be
        // spent after a few polls and then every resource would answer "pending" forever.
        block_on(tokio::task::unconstrained(fut))
    }

    fn blobs(&self) -> &dyn Blobs {
        self.blobs.as_ref()
    }
}

impl Drop for Inner {
    fn drop(&mut self) {
        // Closing tells the server the sessions ended (instead of leaving them to time out);
        // bounded, so a dead server cannot hang a drop.
        let pool = self.pool.clone();
        self.run(async move {
            let _ = tokio::time::timeout(Duration::from_secs(2), pool.close()).await;
        });
        if let Some(runtime) = self.runtime.take() {
            // Not a blocking shutdown: a drop may happen on another runtime's thread.
            runtime.shutdown_background();
        }
    }
}

/// Wakes a parked thread.
struct ThreadWaker(std::thread::Thread);

impl Wake for ThreadWaker {
    fn wake(self: Arc<Self>) {
        self.0.unpark();
    }
    fn wake_by_ref(self: &Arc<Self>) {
        self.0.unpark();
    }
}

/// Polls `fut` on this thread, parking between wake-ups.
fn block_on<F: Future>(fut: F) -> F::Output {
    let mut fut = std::pin::pin!(fut);
    let waker = Waker::from(Arc::new(ThreadWaker(std::thread::current())));
    let mut cx = Context::from_waker(&waker);
    loop {
        if let Poll::Ready(out) = fut.as_mut().poll(&mut cx) {
            return out;
        }
        // A stray unpark only costs one more poll.
        std::thread::park();
    }
}

/// PostgreSQL + object store implementation of [`Store`]. Cheap to clone (shared state); many
/// processes may open the same database and object store at once.
#[derive(Clone)]
pub struct PgStore {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for PgStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PgStore").field("connections", &self.inner.pool.size()).finish()
    }
}

/// `url` with its password (if any) replaced by `***`, for messages.
pub fn redact_url(url: &str) -> String {
    redact_password(url, url)
}

/// The password of `url` (between `user:` and `@` of the authority), if any.
fn url_password(url: &str) -> Option<&str> {
    let rest = &url[url.find("://")? + 3..];
    let authority = &rest[..rest.find(['/', '?']).unwrap_or(rest.len())];
    let userinfo = &authority[..authority.rfind('@')?];
    let password = &userinfo[userinfo.find(':')? + 1..];
    (!password.is_empty()).then_some(password)
}

/// `text` with every occurrence of `url`'s password, as written or percent-decoded, replaced by
/// `***`.
fn redact_password(text: &str, url: &str) -> String {
    match url_password(url) {
        Some(password) => text.replace(password, "***").replace(&percent_decode(password), "***"),
        None => text.to_string(),
    }
}

/// `%XX` escapes decoded (invalid ones kept as they are), as URL parsers read a password.
fn percent_decode(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = bytes.get(i + 1..i + 3).and_then(|h| std::str::from_utf8(h).ok());
        match hex.filter(|_| bytes[i] == b'%').and_then(|h| u8::from_str_radix(h, 16).ok()) {
            Some(byte) => {
                out.push(byte);
                i += 3;
            }
            None => {
                out.push(bytes[i]);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

impl PgStore {
    /// Connects to the database at `database_url` (`postgres://user:password@host:port/db`),
    /// applies the migrations it lacks, and removes objects that a crash left behind (see
    /// [`PgStore::sweep_orphans`]; a failing sweep is logged, not fatal). `blobs` holds the
    /// frames and models. Error messages never contain the URL's password.
    pub fn connect(database_url: &str, blobs: Arc<dyn Blobs>) -> Result<Self, StoreError> {
        let redacted = |e: &dyn std::fmt::Display| StoreError::Postgres(redact_password(&e.to_string(), database_url));
        let options = PgConnectOptions::from_str(database_url).map_err(|e| redacted(&e))?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("mbnt-postgres")
            .enable_all()
            .build()?;
        // The pool is created inside the runtime so that its connections and its maintenance
        // tasks belong to it.
        let pool = {
            let _entered = runtime.enter();
            PgPoolOptions::new()
                .max_connections(POOL_CONNECTIONS)
                .acquire_timeout(ACQUIRE_TIMEOUT)
                .connect_lazy_with(options)
        };
        let store = Self { inner: Arc::new(Inner { runtime: Some(runtime), pool, blobs }) };
        store.inner.run(async { MIGRATOR.run(&store.inner.pool).await }).map_err(|e| redacted(&e))?;
        match store.sweep_orphans(STALE_UPLOAD) {
            Ok(0) => {}
            Ok(n) => tracing::info!(objects = n, "removed objects that no row refers to"),
            Err(e) => tracing::warn!(error = %e, "could not sweep orphan objects"),
        }
        Ok(store)
    }

    /// Removes objects that no row refers to and that no live upload is writing:
    /// - the frames of uploads whose row was not touched for `stale_after` (a live upload
    ///   touches its row every minute while frames come in; its commit fails once swept),
    /// - frames under `sequences/` that neither a sequence nor an upload row claims (an upload
    ///   whose process died after its row went, a delete whose object removal failed),
    /// - models of jobs that no longer exist, and kept windows of jobs that will not run again.
    ///
    /// Safe beside live uploads and workers: objects are listed before the rows are read, and
    /// an upload's row exists before its first object and is replaced by its sequence's row in
    /// one transaction, so a listed object of a live upload always finds a row. The object
    /// store's timestamps are not used (the [`Blobs`] interface has none). Returns how many
    /// objects were removed.
    pub fn sweep_orphans(&self, stale_after: Duration) -> Result<usize, StoreError> {
        let inner = &self.inner;
        let stale_ms = lease_ms(stale_after);
        let stale: Vec<Uuid> = inner.run(async {
            sqlx::query_scalar("DELETE FROM uploads WHERE touched_at < mbnt_now_ms() - $1 RETURNING id")
                .bind(stale_ms)
                .fetch_all(&inner.pool)
                .await
        })?;
        let mut removed = 0;
        for id in stale {
            tracing::info!(upload = %id, "removing the frames of an upload abandoned by its process");
            removed += inner.blobs().delete_prefix(&sequence_prefix(id))?;
        }

        let frame_keys = inner.blobs().list("sequences/")?;
        let ids = folder_ids(&frame_keys, "sequences/");
        let claimed: HashSet<Uuid> = inner
            .run(async {
                sqlx::query_scalar(
                    "SELECT id FROM sequences WHERE id = ANY($1) UNION SELECT id FROM uploads WHERE id = ANY($1)",
                )
                .bind(&ids)
                .fetch_all(&inner.pool)
                .await
            })?
            .into_iter()
            .collect();
        for key in &frame_keys {
            if !folder_id(key, "sequences/").is_some_and(|id| claimed.contains(&id)) {
                inner.blobs().delete(key)?;
                removed += 1;
            }
        }

        let model_keys = inner.blobs().list("models/")?;
        let model_jobs: Vec<Uuid> = model_keys.iter().filter_map(|k| model_job(k)).collect();
        let jobs: HashSet<Uuid> = inner
            .run(async {
                sqlx::query_scalar("SELECT id FROM jobs WHERE id = ANY($1)")
                    .bind(&model_jobs)
                    .fetch_all(&inner.pool)
                    .await
            })?
            .into_iter()
            .collect();
        for key in &model_keys {
            if !model_job(key).is_some_and(|id| jobs.contains(&id)) {
                inner.blobs().delete(key)?;
                removed += 1;
            }
        }

        let window_keys = inner.blobs().list("windows/")?;
        let window_jobs = folder_ids(&window_keys, "windows/");
        let unfinished: HashSet<Uuid> = inner
            .run(async {
                sqlx::query_scalar("SELECT id FROM jobs WHERE id = ANY($1) AND status IN ('queued', 'running')")
                    .bind(&window_jobs)
                    .fetch_all(&inner.pool)
                    .await
            })?
            .into_iter()
            .collect();
        for key in &window_keys {
            if !folder_id(key, "windows/").is_some_and(|id| unfinished.contains(&id)) {
                inner.blobs().delete(key)?;
                removed += 1;
            }
        }
        Ok(removed)
    }

    /// The job if `worker` holds it, else [`StoreError::LeaseLost`].
    fn held_job(&self, id: Uuid, worker: &str) -> Result<JobRecord, StoreError> {
        match self.get_job(id)? {
            Some(job) if job.status == JobStatus::Running && job.worker.as_deref() == Some(worker) => Ok(job),
            _ => Err(lease_lost(id, worker)),
        }
    }
}

fn lease_lost(id: Uuid, worker: &str) -> StoreError {
    StoreError::LeaseLost(format!("job {id} is no longer held by {worker}"))
}

fn sequence_prefix(id: Uuid) -> String {
    format!("sequences/{id}/")
}

fn frame_key(id: Uuid, k: usize) -> String {
    format!("sequences/{id}/{}", files::frame_file_name(k))
}

fn model_key(job: Uuid) -> String {
    format!("models/{job}.mbnt")
}

fn windows_prefix(job: Uuid) -> String {
    format!("windows/{job}/")
}

/// The id naming the folder of `key` under `parent` (`sequences/{id}/...`), if it is one.
fn folder_id(key: &str, parent: &str) -> Option<Uuid> {
    let rest = key.strip_prefix(parent)?;
    Uuid::parse_str(&rest[..rest.find('/')?]).ok()
}

/// The distinct folder ids of `keys` under `parent`.
fn folder_ids(keys: &[String], parent: &str) -> Vec<Uuid> {
    keys.iter().filter_map(|k| folder_id(k, parent)).collect::<BTreeSet<_>>().into_iter().collect()
}

/// The job of a `models/{job}.mbnt` key.
fn model_job(key: &str) -> Option<Uuid> {
    Uuid::parse_str(key.strip_prefix("models/")?.strip_suffix(".mbnt")?).ok()
}

/// A window key names an object: letters, digits and `-` only, so it cannot leave its folder.
fn check_window_key(key: &str) -> Result<(), StoreError> {
    if key.is_empty() || !key.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
        return Err(StoreError::Io(std::io::Error::other(format!("invalid window key {key:?}"))));
    }
    Ok(())
}

/// Milliseconds of a duration, saturated (far below `i64::MAX` so that adding it to a time
/// cannot overflow the bigint).
fn lease_ms(lease: Duration) -> i64 {
    i64::try_from(lease.as_millis()).unwrap_or(i64::MAX / 4).min(i64::MAX / 4)
}

fn json<T: serde::Serialize>(value: &T) -> String {
    serde_json::to_string(value).expect("plain data always serialises")
}

fn parse<T: serde::de::DeserializeOwned>(what: &str, text: &str) -> Result<T, StoreError> {
    serde_json::from_str(text).map_err(|e| StoreError::Corrupt(format!("{what}: {e}")))
}

fn sequence_from_row(r: &PgRow) -> Result<SequenceRecord, StoreError> {
    let timestamps: Option<String> = r.try_get("timestamps")?;
    let poses: Option<String> = r.try_get("poses")?;
    Ok(SequenceRecord {
        id: r.try_get("id")?,
        name: r.try_get("name")?,
        points_per_frame: parse("points_per_frame", &r.try_get::<String, _>("points_per_frame")?)?,
        timestamps_s: timestamps.as_deref().map(|t| parse("timestamps", t)).transpose()?,
        poses: poses.as_deref().map(|p| parse("poses", p)).transpose()?,
        created_at_ms: r.try_get("created_at")?,
    })
}

fn job_from_row(r: &PgRow) -> Result<JobRecord, StoreError> {
    let attempts: i32 = r.try_get("attempts")?;
    Ok(JobRecord {
        id: r.try_get("id")?,
        sequence_id: r.try_get("sequence_id")?,
        method: r.try_get::<String, _>("method")?.parse::<Method>().map_err(StoreError::Corrupt)?,
        params: parse("params", &r.try_get::<String, _>("params")?)?,
        status: r.try_get::<String, _>("status")?.parse::<JobStatus>().map_err(StoreError::Corrupt)?,
        progress: parse("progress", &r.try_get::<String, _>("progress")?)?,
        error: r.try_get("error")?,
        cancel_requested: r.try_get("cancel_requested")?,
        attempts: u32::try_from(attempts).map_err(|_| StoreError::Corrupt(format!("attempts {attempts}")))?,
        created_at_ms: r.try_get("created_at")?,
        started_at_ms: r.try_get("started_at")?,
        finished_at_ms: r.try_get("finished_at")?,
        worker: r.try_get("worker")?,
        lease_expires_at_ms: r.try_get("lease_expires_at")?,
    })
}

async fn fetch_job(tx: &mut Transaction<'_, Postgres>, id: Uuid) -> Result<Option<JobRecord>, StoreError> {
    sqlx::query(AssertSqlSafe(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1")))
        .bind(id)
        .fetch_optional(&mut **tx)
        .await?
        .as_ref()
        .map(job_from_row)
        .transpose()
}

/// A sequence being uploaded: frames go straight to their final keys, under an `uploads` row
/// that keeps the janitor away.
struct PgFrameSink {
    inner: Arc<Inner>,
    id: Uuid,
    points_per_frame: Vec<usize>,
    last_touch: Instant,
    committed: bool,
}

impl FrameSink for PgFrameSink {
    fn put_frame(&mut self, points: &[Point]) -> Result<(), StoreError> {
        if self.last_touch.elapsed() >= UPLOAD_TOUCH_INTERVAL {
            let touched = self.inner.run(async {
                sqlx::query("UPDATE uploads SET touched_at = mbnt_now_ms() WHERE id = $1")
                    .bind(self.id)
                    .execute(&self.inner.pool)
                    .await
            })?;
            if touched.rows_affected() == 0 {
                return Err(StoreError::Missing(format!("upload {} (idle for too long, it was discarded)", self.id)));
            }
            self.last_touch = Instant::now();
        }
        let k = self.points_per_frame.len();
        let mut bytes = Vec::with_capacity(16 + 12 * points.len());
        files::write_frame(&mut bytes, points)?;
        self.inner.blobs().put(&frame_key(self.id, k), bytes)?;
        self.points_per_frame.push(points.len());
        Ok(())
    }

    fn frames_written(&self) -> usize {
        self.points_per_frame.len()
    }

    fn commit(mut self: Box<Self>, meta: SequenceMeta) -> Result<SequenceRecord, StoreError> {
        let points_per_frame = std::mem::take(&mut self.points_per_frame);
        let inner = self.inner.clone();
        let id = self.id;
        let committed = inner.run(async {
            let mut tx = inner.pool.begin().await?;
            // The upload row goes in the same transaction as the sequence's: at no moment do
            // the frames lack a row, and an upload the janitor discarded cannot commit.
            let upload = sqlx::query("DELETE FROM uploads WHERE id = $1").bind(id).execute(&mut *tx).await?;
            if upload.rows_affected() == 0 {
                return Err(StoreError::Missing(format!("upload {id} (idle for too long, it was discarded)")));
            }
            let row = sqlx::query(AssertSqlSafe(format!(
                "INSERT INTO sequences (id, name, points_per_frame, timestamps, poses, created_at) \
                 VALUES ($1, $2, $3, $4, $5, mbnt_now_ms()) RETURNING {SEQUENCE_COLUMNS}"
            )))
            .bind(id)
            .bind(&meta.name)
            .bind(json(&points_per_frame))
            .bind(meta.timestamps_s.as_ref().map(json))
            .bind(meta.poses.as_ref().map(json))
            .fetch_one(&mut *tx)
            .await?;
            tx.commit().await?;
            sequence_from_row(&row)
        });
        // On failure `Drop` removes the frames and the upload row (if still there).
        self.committed = committed.is_ok();
        committed
    }
}

impl Drop for PgFrameSink {
    fn drop(&mut self) {
        if self.committed {
            return;
        }
        // A commit whose answer was lost (the connection broke after COMMIT) may have
        // succeeded: the row decides. Unknown (no database) leaves it all to the janitor.
        let committed = self.inner.run(async {
            sqlx::query_scalar::<_, bool>("SELECT EXISTS (SELECT 1 FROM sequences WHERE id = $1)")
                .bind(self.id)
                .fetch_one(&self.inner.pool)
                .await
        });
        match committed {
            Ok(false) => {}
            Ok(true) => return,
            Err(e) => {
                tracing::warn!(upload = %self.id, error = %e, "could not tell whether an abandoned upload committed");
                return;
            }
        }
        // Objects first, then the row: if this fails half-way, the row (or, once the row is
        // gone, the orphan rule) lets the janitor finish the job.
        if let Err(e) = self.inner.blobs().delete_prefix(&sequence_prefix(self.id)) {
            tracing::warn!(upload = %self.id, error = %e, "could not remove the frames of an abandoned upload");
            return;
        }
        let deleted = self.inner.run(async {
            sqlx::query("DELETE FROM uploads WHERE id = $1").bind(self.id).execute(&self.inner.pool).await
        });
        if let Err(e) = deleted {
            tracing::warn!(upload = %self.id, error = %e, "could not remove the row of an abandoned upload");
        }
    }
}

impl Store for PgStore {
    fn begin_sequence(&self) -> Result<Box<dyn FrameSink>, StoreError> {
        let id = Uuid::new_v4();
        // The row before any object, so that the janitor never takes a live upload's frames
        // for orphans.
        self.inner.run(async {
            sqlx::query("INSERT INTO uploads (id, touched_at) VALUES ($1, mbnt_now_ms())")
                .bind(id)
                .execute(&self.inner.pool)
                .await
        })?;
        Ok(Box::new(PgFrameSink {
            inner: self.inner.clone(),
            id,
            points_per_frame: Vec::new(),
            last_touch: Instant::now(),
            committed: false,
        }))
    }

    fn get_sequence(&self, id: Uuid) -> Result<Option<SequenceRecord>, StoreError> {
        let row = self.inner.run(async {
            sqlx::query(AssertSqlSafe(format!("SELECT {SEQUENCE_COLUMNS} FROM sequences WHERE id = $1")))
                .bind(id)
                .fetch_optional(&self.inner.pool)
                .await
        })?;
        row.as_ref().map(sequence_from_row).transpose()
    }

    fn list_sequences(&self, limit: usize) -> Result<Vec<SequenceRecord>, StoreError> {
        let rows = self.inner.run(async {
            sqlx::query(AssertSqlSafe(format!(
                "SELECT {SEQUENCE_COLUMNS} FROM sequences ORDER BY created_at DESC, ord DESC LIMIT $1"
            )))
            .bind(i64::try_from(limit).unwrap_or(i64::MAX))
            .fetch_all(&self.inner.pool)
            .await
        })?;
        rows.iter().map(sequence_from_row).collect()
    }

    fn delete_sequence(&self, id: Uuid) -> Result<DeleteOutcome, StoreError> {
        let deleted = self.inner.run(async {
            let mut tx = self.inner.pool.begin().await?;
            // The row lock makes a concurrent insert_job (its foreign key takes a share lock on
            // this row) wait for the outcome, so no job can slip in between check and delete.
            let exists = sqlx::query("SELECT 1 FROM sequences WHERE id = $1 FOR UPDATE")
                .bind(id)
                .fetch_optional(&mut *tx)
                .await?;
            if exists.is_none() {
                return Ok::<_, StoreError>(Err(DeleteOutcome::NotFound));
            }
            let active: i64 = sqlx::query_scalar(
                "SELECT COUNT(*) FROM jobs WHERE sequence_id = $1 AND status IN ('queued', 'running')",
            )
            .bind(id)
            .fetch_one(&mut *tx)
            .await?;
            if active > 0 {
                return Ok(Err(DeleteOutcome::HasActiveJobs));
            }
            let jobs: Vec<Uuid> = sqlx::query_scalar("DELETE FROM jobs WHERE sequence_id = $1 RETURNING id")
                .bind(id)
                .fetch_all(&mut *tx)
                .await?;
            sqlx::query("DELETE FROM sequences WHERE id = $1").bind(id).execute(&mut *tx).await?;
            tx.commit().await?;
            Ok(Ok(jobs))
        })?;
        let jobs = match deleted {
            Ok(jobs) => jobs,
            Err(outcome) => return Ok(outcome),
        };
        // The rows are gone, so nothing refers to these objects any more; if removing them
        // fails, the janitor's orphan rules remove them at a later connect.
        let blobs = self.inner.blobs();
        for job in jobs {
            let removed = blobs.delete(&model_key(job)).and_then(|()| blobs.delete_prefix(&windows_prefix(job)));
            if let Err(e) = removed {
                tracing::warn!(job = %job, error = %e, "could not remove a deleted job's model");
            }
        }
        if let Err(e) = blobs.delete_prefix(&sequence_prefix(id)) {
            tracing::warn!(sequence = %id, error = %e, "could not remove a deleted sequence's frames");
        }
        Ok(DeleteOutcome::Deleted)
    }

    fn read_frame(&self, id: Uuid, k: usize) -> Result<Vec<Point>, StoreError> {
        let bytes = self
            .inner
            .blobs()
            .get(&frame_key(id, k))?
            .ok_or_else(|| StoreError::Missing(format!("frame {k} of sequence {id}")))?;
        files::parse_frame(&bytes).map_err(|e| StoreError::Corrupt(format!("frame {k} of sequence {id}: {e}")))
    }

    fn insert_job(&self, job: &JobRecord) -> Result<(), StoreError> {
        let inserted = self.inner.run(async {
            sqlx::query(AssertSqlSafe(format!(
                "INSERT INTO jobs ({JOB_COLUMNS}) \
                 SELECT $1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14 \
                 WHERE EXISTS (SELECT 1 FROM sequences WHERE id = $2)"
            )))
            .bind(job.id)
            .bind(job.sequence_id)
            .bind(job.method.name())
            .bind(json(&job.params))
            .bind(job.status.as_str())
            .bind(json(&job.progress))
            .bind(&job.error)
            .bind(job.cancel_requested)
            .bind(i32::try_from(job.attempts).unwrap_or(i32::MAX))
            .bind(job.created_at_ms)
            .bind(job.started_at_ms)
            .bind(job.finished_at_ms)
            .bind(&job.worker)
            .bind(job.lease_expires_at_ms)
            .execute(&self.inner.pool)
            .await
        });
        let missing = || StoreError::Missing(format!("sequence {}", job.sequence_id));
        match inserted {
            Ok(done) if done.rows_affected() == 0 => Err(missing()),
            Ok(_) => Ok(()),
            // The sequence was deleted between the check and the insert.
            Err(sqlx::Error::Database(e)) if e.is_foreign_key_violation() => Err(missing()),
            Err(e) => Err(e.into()),
        }
    }

    fn get_job(&self, id: Uuid) -> Result<Option<JobRecord>, StoreError> {
        let row = self.inner.run(async {
            sqlx::query(AssertSqlSafe(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1")))
                .bind(id)
                .fetch_optional(&self.inner.pool)
                .await
        })?;
        row.as_ref().map(job_from_row).transpose()
    }

    fn list_jobs(&self, filter: &JobFilter) -> Result<Vec<JobRecord>, StoreError> {
        let rows = self.inner.run(async {
            sqlx::query(AssertSqlSafe(format!(
                "SELECT {JOB_COLUMNS} FROM jobs \
                 WHERE ($1::text IS NULL OR status = $1) AND ($2::uuid IS NULL OR sequence_id = $2) \
                 ORDER BY created_at DESC, ord DESC LIMIT $3"
            )))
            .bind(filter.status.map(JobStatus::as_str))
            .bind(filter.sequence_id)
            .bind(i64::try_from(filter.limit).unwrap_or(i64::MAX))
            .fetch_all(&self.inner.pool)
            .await
        })?;
        rows.iter().map(job_from_row).collect()
    }

    fn claim_next_job(&self, claim: &Claim) -> Result<Option<JobRecord>, StoreError> {
        let max_attempts = i32::try_from(claim.max_attempts).unwrap_or(i32::MAX);
        self.inner.run(async {
            let mut tx = self.inner.pool.begin().await?;
            // One candidate at a time, locked, skipping rows other claimers hold: two workers
            // never get the same job and never wait on each other. A candidate that ends
            // (cancelled, out of attempts) instead of running lets the loop look further.
            loop {
                let candidate = sqlx::query(
                    "SELECT id, status, cancel_requested, attempts FROM jobs \
                     WHERE status = 'queued' OR (status = 'running' AND lease_expires_at < mbnt_now_ms()) \
                     ORDER BY created_at, ord LIMIT 1 FOR UPDATE SKIP LOCKED",
                )
                .fetch_optional(&mut *tx)
                .await?;
                let Some(candidate) = candidate else {
                    tx.commit().await?;
                    return Ok(None);
                };
                let id: Uuid = candidate.try_get("id")?;
                let expired = candidate.try_get::<String, _>("status")? == "running";
                let attempts: i32 = candidate.try_get("attempts")?;
                if expired && candidate.try_get::<bool, _>("cancel_requested")? {
                    // Its worker died after a user asked to cancel it: it ends cancelled, as asked.
                    sqlx::query(
                        "UPDATE jobs SET status = 'cancelled', finished_at = mbnt_now_ms(), worker = NULL, \
                         lease_expires_at = NULL WHERE id = $1",
                    )
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
                    continue;
                }
                if attempts >= max_attempts {
                    // Orderly hand-backs give their attempt back, so `attempts` counts runs
                    // that died: a job that used them all fails rather than kill another worker.
                    sqlx::query(
                        "UPDATE jobs SET status = 'failed', finished_at = mbnt_now_ms(), worker = NULL, \
                         lease_expires_at = NULL, error = $2 WHERE id = $1",
                    )
                    .bind(id)
                    .bind(format!(
                        "its worker stopped without finishing {attempts} times (the process died or lost the \
                         database); max_attempts is {}",
                        claim.max_attempts
                    ))
                    .execute(&mut *tx)
                    .await?;
                    continue;
                }
                let row = sqlx::query(AssertSqlSafe(format!(
                    "UPDATE jobs SET status = 'running', started_at = mbnt_now_ms(), attempts = attempts + 1, \
                     worker = $2, lease_expires_at = mbnt_now_ms() + $3 WHERE id = $1 RETURNING {JOB_COLUMNS}"
                )))
                .bind(id)
                .bind(&claim.worker)
                .bind(lease_ms(claim.lease))
                .fetch_one(&mut *tx)
                .await?;
                tx.commit().await?;
                return job_from_row(&row).map(Some);
            }
        })
    }

    fn renew_lease(&self, id: Uuid, worker: &str, lease: Duration) -> Result<LeaseStatus, StoreError> {
        let cancel: Option<bool> = self.inner.run(async {
            sqlx::query_scalar(
                "UPDATE jobs SET lease_expires_at = mbnt_now_ms() + $3 \
                 WHERE id = $1 AND status = 'running' AND worker = $2 RETURNING cancel_requested",
            )
            .bind(id)
            .bind(worker)
            .bind(lease_ms(lease))
            .fetch_optional(&self.inner.pool)
            .await
        })?;
        Ok(cancel.map_or(LeaseStatus::Lost, |cancel_requested| LeaseStatus::Held { cancel_requested }))
    }

    fn update_progress(&self, id: Uuid, worker: &str, progress: &JobProgress) -> Result<LeaseStatus, StoreError> {
        let cancel: Option<bool> = self.inner.run(async {
            sqlx::query_scalar(
                "UPDATE jobs SET progress = $3 WHERE id = $1 AND status = 'running' AND worker = $2 \
                 RETURNING cancel_requested",
            )
            .bind(id)
            .bind(worker)
            .bind(json(progress))
            .fetch_optional(&self.inner.pool)
            .await
        })?;
        Ok(cancel.map_or(LeaseStatus::Lost, |cancel_requested| LeaseStatus::Held { cancel_requested }))
    }

    fn finish_job(&self, id: Uuid, worker: &str, outcome: JobOutcome<'_>) -> Result<JobRecord, StoreError> {
        // Checked before the model is written, so that a worker that lost its job does not
        // overwrite the model of the worker now holding it.
        let mut job = self.held_job(id, worker)?;
        let (status, error) = match &outcome {
            JobOutcome::Succeeded { model } => {
                self.inner.blobs().put(&model_key(id), model.to_vec())?;
                job.progress.fraction = 1.0;
                job.progress.eta_s = Some(0.0);
                (JobStatus::Succeeded, None)
            }
            JobOutcome::Failed { error } => (JobStatus::Failed, Some(error.clone())),
            JobOutcome::Cancelled => (JobStatus::Cancelled, None),
        };
        // Conditional on the lease still being held: if it was lost since the check, nothing
        // is recorded (a model written meanwhile is the next holder's to overwrite).
        let row = self.inner.run(async {
            sqlx::query(AssertSqlSafe(format!(
                "UPDATE jobs SET status = $3, error = $4, progress = $5, finished_at = mbnt_now_ms(), worker = NULL, \
                 lease_expires_at = NULL WHERE id = $1 AND worker = $2 AND status = 'running' \
                 RETURNING {JOB_COLUMNS}"
            )))
            .bind(id)
            .bind(worker)
            .bind(status.as_str())
            .bind(error)
            .bind(json(&job.progress))
            .fetch_optional(&self.inner.pool)
            .await
        })?;
        let job = job_from_row(&row.ok_or_else(|| lease_lost(id, worker))?)?;
        // Claims of a job that is not running are refused anyway; removing them keeps the table
        // small (a failure here is harmless).
        if let Err(e) = self.inner.run(async {
            sqlx::query("DELETE FROM window_claims WHERE job_id = $1").bind(id).execute(&self.inner.pool).await
        }) {
            tracing::warn!(job = %id, error = %e, "could not remove a finished job's window claims");
        }
        // The job will not run again: its kept windows and checkpoints are of no more use. If
        // removing them fails, the janitor does it at a later connect.
        if let Err(e) = self.inner.blobs().delete_prefix(&windows_prefix(id)) {
            tracing::warn!(job = %id, error = %e, "could not remove a finished job's windows");
        }
        Ok(job)
    }

    fn fail_succeeded_job(&self, id: Uuid, error: &str) -> Result<Option<JobRecord>, StoreError> {
        // The model object stays, for an operator to look at; deleting the sequence removes it.
        self.inner.run(async {
            let mut tx = self.inner.pool.begin().await?;
            sqlx::query("UPDATE jobs SET status = 'failed', error = $2 WHERE id = $1 AND status = 'succeeded'")
                .bind(id)
                .bind(error)
                .execute(&mut *tx)
                .await?;
            let job = fetch_job(&mut tx, id).await?;
            tx.commit().await?;
            Ok(job)
        })
    }

    fn requeue_job(&self, id: Uuid, worker: &str) -> Result<JobRecord, StoreError> {
        let row = self.inner.run(async {
            sqlx::query(AssertSqlSafe(format!(
                "UPDATE jobs SET status = 'queued', attempts = GREATEST(attempts - 1, 0), worker = NULL, \
                 lease_expires_at = NULL WHERE id = $1 AND status = 'running' AND worker = $2 \
                 RETURNING {JOB_COLUMNS}"
            )))
            .bind(id)
            .bind(worker)
            .fetch_optional(&self.inner.pool)
            .await
        })?;
        job_from_row(&row.ok_or_else(|| lease_lost(id, worker))?)
    }

    fn request_cancel(&self, id: Uuid) -> Result<CancelOutcome, StoreError> {
        self.inner.run(async {
            let mut tx = self.inner.pool.begin().await?;
            // Locked so that a claim or a finish cannot change the status under the decision.
            let row = sqlx::query(AssertSqlSafe(format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1 FOR UPDATE")))
                .bind(id)
                .fetch_optional(&mut *tx)
                .await?;
            let Some(job) = row.as_ref().map(job_from_row).transpose()? else {
                return Ok(CancelOutcome::NotFound);
            };
            match job.status {
                JobStatus::Queued => {
                    sqlx::query("UPDATE jobs SET status = 'cancelled', finished_at = mbnt_now_ms() WHERE id = $1")
                        .bind(id)
                        .execute(&mut *tx)
                        .await?;
                }
                JobStatus::Running => {
                    sqlx::query("UPDATE jobs SET cancel_requested = true WHERE id = $1")
                        .bind(id)
                        .execute(&mut *tx)
                        .await?;
                }
                JobStatus::Cancelled => {}
                JobStatus::Succeeded | JobStatus::Failed => return Ok(CancelOutcome::AlreadyFinished(job)),
            }
            let job = fetch_job(&mut tx, id).await?.ok_or_else(|| StoreError::Missing(format!("job {id}")))?;
            tx.commit().await?;
            Ok(CancelOutcome::Accepted(job))
        })
    }

    fn requeue_running_jobs(&self) -> Result<usize, StoreError> {
        // Other processes' workers may be alive: only jobs whose lease ran out are theirs no
        // more. Rows a claimer holds locked are skipped (it is taking them anyway).
        self.inner.run(async {
            let mut tx = self.inner.pool.begin().await?;
            sqlx::query(
                "UPDATE jobs SET status = 'cancelled', finished_at = mbnt_now_ms(), worker = NULL, \
                 lease_expires_at = NULL WHERE id IN (SELECT id FROM jobs WHERE status = 'running' \
                 AND lease_expires_at < mbnt_now_ms() AND cancel_requested FOR UPDATE SKIP LOCKED)",
            )
            .execute(&mut *tx)
            .await?;
            let requeued = sqlx::query(
                "UPDATE jobs SET status = 'queued', worker = NULL, lease_expires_at = NULL \
                 WHERE id IN (SELECT id FROM jobs WHERE status = 'running' AND lease_expires_at < mbnt_now_ms() \
                 FOR UPDATE SKIP LOCKED)",
            )
            .execute(&mut *tx)
            .await?;
            tx.commit().await?;
            Ok(usize::try_from(requeued.rows_affected()).unwrap_or(usize::MAX))
        })
    }

    fn read_model(&self, job_id: Uuid) -> Result<Vec<u8>, StoreError> {
        self.inner.blobs().get(&model_key(job_id))?.ok_or_else(|| StoreError::Missing(format!("model of job {job_id}")))
    }

    fn put_window_model(&self, job_id: Uuid, key: &str, model: &[u8]) -> Result<(), StoreError> {
        check_window_key(key)?;
        self.inner.blobs().put(&format!("{}{key}.mbnt", windows_prefix(job_id)), model.to_vec())
    }

    fn claim_window(&self, id: Uuid, key: &str, worker: &str, lease: std::time::Duration) -> Result<bool, StoreError> {
        self.inner.run(async {
            // Only while the job runs; a live claim of another worker is left alone.
            let claimed = sqlx::query(
                "INSERT INTO window_claims (job_id, key, worker, lease_expires_at) \
                 SELECT $1, $2, $3, mbnt_now_ms() + $4 WHERE EXISTS \
                 (SELECT 1 FROM jobs WHERE id = $1 AND status = 'running') \
                 ON CONFLICT (job_id, key) DO UPDATE SET worker = EXCLUDED.worker, \
                 lease_expires_at = EXCLUDED.lease_expires_at \
                 WHERE window_claims.worker = EXCLUDED.worker OR window_claims.lease_expires_at < mbnt_now_ms()",
            )
            .bind(id)
            .bind(key)
            .bind(worker)
            .bind(lease_ms(lease))
            .execute(&self.inner.pool)
            .await?;
            Ok(claimed.rows_affected() == 1)
        })
    }

    fn release_window(&self, id: Uuid, key: &str, worker: &str) -> Result<(), StoreError> {
        self.inner.run(async {
            sqlx::query("DELETE FROM window_claims WHERE job_id = $1 AND key = $2 AND worker = $3")
                .bind(id)
                .bind(key)
                .bind(worker)
                .execute(&self.inner.pool)
                .await?;
            Ok(())
        })
    }

    fn window_keys(&self, job_id: Uuid) -> Result<Vec<String>, StoreError> {
        let prefix = windows_prefix(job_id);
        Ok(self
            .inner
            .blobs()
            .list(&prefix)?
            .into_iter()
            .filter_map(|k| k.strip_prefix(&prefix).and_then(|k| k.strip_suffix(".mbnt")).map(str::to_string))
            .collect())
    }

    fn read_window_model(&self, job_id: Uuid, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        check_window_key(key)?;
        self.inner.blobs().get(&format!("{}{key}.mbnt", windows_prefix(job_id)))
    }

    fn count_jobs_by_status(&self) -> Result<Vec<(JobStatus, u64)>, StoreError> {
        let rows: Vec<(String, i64)> = self.inner.run(async {
            sqlx::query_as("SELECT status, COUNT(*) FROM jobs GROUP BY status").fetch_all(&self.inner.pool).await
        })?;
        rows.into_iter()
            .map(|(status, n)| {
                Ok((status.parse::<JobStatus>().map_err(StoreError::Corrupt)?, u64::try_from(n).unwrap_or(0)))
            })
            .collect()
    }

    fn ping(&self) -> Result<(), StoreError> {
        self.inner.run(async { sqlx::query("SELECT 1").execute(&self.inner.pool).await })?;
        Ok(())
    }
}

#[cfg(test)]
mod tests;
