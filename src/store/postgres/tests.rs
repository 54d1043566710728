//! Tests of [`PgStore`] against a real PostgreSQL: `MBNT_TEST_DATABASE_URL`, or the local
//! server with trust authentication. Each test creates its own database and drops it at the
//! end, also when it panics; without a reachable server each test says it skipped and passes.

use std::sync::Arc;
use std::time::Duration;

use sqlx::Connection;

use super::*;
use crate::fit::FitParams;
use crate::store::blobs::ObjectBlobs;
use crate::store::now_ms;

const DEFAULT_TEST_URL: &str = "postgres://postgres@127.0.0.1:5432/postgres";

/// How long the admin connection may take before the tests take PostgreSQL as absent.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);

fn admin_url() -> String {
    std::env::var("MBNT_TEST_DATABASE_URL").unwrap_or_else(|_| DEFAULT_TEST_URL.to_string())
}

/// `url` with its database replaced by `database` (query parameters kept).
fn with_database(url: &str, database: &str) -> String {
    let (base, query) = url.split_once('?').map_or((url, None), |(b, q)| (b, Some(q)));
    let authority_start = base.find("://").map_or(0, |i| i + 3);
    let host_end = base[authority_start..].find('/').map_or(base.len(), |i| authority_start + i);
    let mut out = format!("{}/{database}", &base[..host_end]);
    if let Some(query) = query {
        out.push('?');
        out.push_str(query);
    }
    out
}

/// Runs `sql` (one plain statement or several) on the database at `url`. `Err(None)` when no
/// connection could be made within [`CONNECT_TIMEOUT`], `Err(Some(message))` when the SQL failed.
fn execute(url: &str, sql: &str) -> Result<(), Option<String>> {
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let mut conn = match tokio::time::timeout(CONNECT_TIMEOUT, sqlx::PgConnection::connect(url)).await {
            Ok(Ok(conn)) => conn,
            _ => return Err(None),
        };
        sqlx::raw_sql(sqlx::AssertSqlSafe(sql)).execute(&mut conn).await.map_err(|e| Some(e.to_string()))?;
        let _ = conn.close().await;
        Ok(())
    })
}

/// A database of its own for one test, dropped with the guard.
struct TestDb {
    name: String,
    url: String,
}

impl TestDb {
    /// `None` (after saying so on stderr) when there is no PostgreSQL to test against.
    fn create() -> Option<Self> {
        let admin = admin_url();
        let name = format!("mbnt_test_{}", Uuid::new_v4().simple());
        match execute(&admin, &format!("CREATE DATABASE {name}")) {
            Ok(()) => Some(Self { url: with_database(&admin, &name), name }),
            Err(None) => {
                eprintln!("skipped: no PostgreSQL at {}", redact_url(&admin));
                None
            }
            Err(Some(e)) => panic!("could not create the test database {name}: {e}"),
        }
    }

    fn connect(&self, blobs: &Arc<ObjectBlobs>) -> PgStore {
        PgStore::connect(&self.url, blobs.clone()).unwrap()
    }

    /// Runs SQL in the test's database, outside any store.
    fn sql(&self, sql: &str) {
        execute(&self.url, sql).unwrap_or_else(|e| panic!("{sql}: {e:?}"));
    }
}

impl Drop for TestDb {
    fn drop(&mut self) {
        // FORCE: a store still connected (a test that panicked) must not keep the database.
        if let Err(e) = execute(&admin_url(), &format!("DROP DATABASE IF EXISTS {} WITH (FORCE)", self.name)) {
            eprintln!("could not drop the test database {}: {e:?}", self.name);
        }
    }
}

/// A test database and a store connected to it with fresh in-memory objects; returns from the
/// test when PostgreSQL is absent.
macro_rules! setup {
    () => {{
        let Some(db) = TestDb::create() else { return };
        let blobs = Arc::new(ObjectBlobs::from_url("memory://").unwrap());
        let store = db.connect(&blobs);
        (db, blobs, store)
    }};
}

fn sequence(store: &PgStore) -> SequenceRecord {
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
    Claim { worker: worker.into(), lease: Duration::from_millis(lease_ms), max_attempts }
}

/// A claim by [`WORKER`] with a lease no test outlives.
fn claim() -> Claim {
    claim_as(WORKER, 600_000, 3)
}

/// The database's clock, ms since the Unix epoch.
fn db_now_ms(store: &PgStore) -> i64 {
    store.inner.run(async { sqlx::query_scalar("SELECT mbnt_now_ms()").fetch_one(&store.inner.pool).await }).unwrap()
}

#[test]
fn urls_lose_their_password_in_messages() {
    assert_eq!(redact_url("postgres://u:hunter2@h:5432/db?x=1"), "postgres://u:***@h:5432/db?x=1");
    assert_eq!(redact_url("postgres://u@h/db"), "postgres://u@h/db");
    assert_eq!(url_password("postgres://u:p:q@h/db"), Some("p:q"));
    assert_eq!(redact_password("bad password p@ss%zz for u", "postgres://u:p%40ss%zz@h/db"), "bad password *** for u");
    assert_eq!(percent_decode("a%2Fb%%41%4"), "a/b%A%4");
    assert_eq!(with_database("postgres://u@h:1/postgres?sslmode=disable", "x"), "postgres://u@h:1/x?sslmode=disable");
    assert_eq!(with_database("postgres://u@h:1", "x"), "postgres://u@h:1/x");
}

#[test]
fn a_failed_connection_does_not_show_the_password() {
    let blobs: Arc<dyn Blobs> = Arc::new(ObjectBlobs::from_url("memory://").unwrap());
    // Port 1: nothing listens, the connection is refused at once.
    for url in ["postgres://mbnt:s3cret-pw@127.0.0.1:1/mbnt", "postgres://mbnt:s3cret-pw@127.0.0.1:notaport/mbnt"] {
        let e = PgStore::connect(url, blobs.clone()).unwrap_err();
        assert!(matches!(e, StoreError::Postgres(_)), "{e:?}");
        assert!(!e.to_string().contains("s3cret-pw") && !format!("{e:?}").contains("s3cret-pw"), "{e}");
    }
}

#[test]
fn a_committed_sequence_and_its_frames_survive_reconnecting() {
    let (db, blobs, store) = setup!();
    let poses = vec![[
        0.1 + 0.2,
        1.0 / 3.0,
        f64::MIN_POSITIVE,
        1e-300,
        -0.0,
        5e-324,
        2.0f64.sqrt(),
        1e300,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0,
    ]];
    let timestamps = vec![1_700_000_000.123_456_7];
    let mut sink = store.begin_sequence().unwrap();
    sink.put_frame(&[[0.5, f32::MIN_POSITIVE, -1e30]]).unwrap();
    assert_eq!(sink.frames_written(), 1);
    let committed = sink
        .commit(SequenceMeta {
            name: Some("drive".into()),
            timestamps_s: Some(timestamps.clone()),
            poses: Some(poses.clone()),
        })
        .unwrap();
    drop(store);
    let store = db.connect(&blobs);
    let seq = store.get_sequence(committed.id).unwrap().unwrap();
    assert_eq!(seq, committed);
    assert_eq!(seq.name.as_deref(), Some("drive"));
    assert_eq!(seq.points_per_frame, vec![1]);
    // Bit for bit: the JSON is kept as text, not as jsonb's rewritten numbers.
    let bits = |p: &[[f64; 16]]| p.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(seq.poses.as_deref().unwrap()), bits(&poses));
    assert_eq!(seq.timestamps_s.unwrap()[0].to_bits(), timestamps[0].to_bits());
    let frame = store.read_frame(committed.id, 0).unwrap();
    assert_eq!(frame[0].map(f32::to_bits), [0.5, f32::MIN_POSITIVE, -1e30].map(f32::to_bits));
    assert!(matches!(store.read_frame(committed.id, 1), Err(StoreError::Missing(_))));
    blobs.put(&frame_key(committed.id, 0), b"MBNTFRM1 cut short".to_vec()).unwrap();
    assert!(matches!(store.read_frame(committed.id, 0), Err(StoreError::Corrupt(_))));
    assert_eq!(store.list_sequences(10).unwrap(), vec![committed]);
}

#[test]
fn an_abandoned_upload_leaves_nothing_behind() {
    let (_db, blobs, store) = setup!();
    let mut sink = store.begin_sequence().unwrap();
    sink.put_frame(&[[1.0, 2.0, 3.0]]).unwrap();
    assert_eq!(blobs.list("sequences/").unwrap().len(), 1);
    // Not visible before its commit.
    assert!(store.list_sequences(10).unwrap().is_empty());
    drop(sink);
    assert!(blobs.list("").unwrap().is_empty());
    assert!(store.list_sequences(10).unwrap().is_empty());
    let uploads: i64 = store
        .inner
        .run(async { sqlx::query_scalar("SELECT COUNT(*) FROM uploads").fetch_one(&store.inner.pool).await })
        .unwrap();
    assert_eq!(uploads, 0);
}

#[test]
fn jobs_are_claimed_oldest_first_and_only_once() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let (a, b) = (job(seq.id), job(seq.id));
    store.insert_job(&a).unwrap();
    store.insert_job(&b).unwrap();
    let first = store.claim_next_job(&claim()).unwrap().unwrap();
    assert_eq!((first.id, first.status, first.attempts), (a.id, JobStatus::Running, 1));
    assert_eq!(first.worker.as_deref(), Some(WORKER));
    assert_eq!(store.claim_next_job(&claim()).unwrap().unwrap().id, b.id);
    assert!(store.claim_next_job(&claim()).unwrap().is_none());
}

#[test]
fn a_job_for_a_missing_sequence_is_refused() {
    let (_db, _blobs, store) = setup!();
    assert!(matches!(store.insert_job(&job(Uuid::new_v4())), Err(StoreError::Missing(_))));
    assert!(store.list_jobs(&JobFilter { limit: 10, ..Default::default() }).unwrap().is_empty());
}

#[test]
fn only_jobs_whose_lease_expired_go_back_to_the_queue_unless_cancelled() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let (a, b, c) = (job(seq.id), job(seq.id), job(seq.id));
    for j in [&a, &b, &c] {
        store.insert_job(j).unwrap();
    }
    store.claim_next_job(&claim_as("dead-1", 100, 3)).unwrap();
    store.claim_next_job(&claim_as("dead-2", 100, 3)).unwrap();
    store.claim_next_job(&claim_as("alive", 600_000, 3)).unwrap();
    assert!(matches!(store.request_cancel(b.id).unwrap(), CancelOutcome::Accepted(_)));
    std::thread::sleep(Duration::from_millis(150));
    assert_eq!(store.requeue_running_jobs().unwrap(), 1);
    let status = |id| store.get_job(id).unwrap().unwrap();
    assert_eq!((status(a.id).status, status(a.id).worker), (JobStatus::Queued, None));
    assert_eq!(status(b.id).status, JobStatus::Cancelled);
    // Another process's live worker keeps its job.
    assert_eq!((status(c.id).status, status(c.id).worker.as_deref()), (JobStatus::Running, Some("alive")));
    let again = store.claim_next_job(&claim()).unwrap().unwrap();
    assert_eq!((again.id, again.attempts), (a.id, 2));
}

#[test]
fn cancelling_a_queued_job_is_immediate_and_a_running_one_is_flagged() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let (a, b) = (job(seq.id), job(seq.id));
    store.insert_job(&a).unwrap();
    store.claim_next_job(&claim()).unwrap();
    store.insert_job(&b).unwrap();
    let CancelOutcome::Accepted(queued) = store.request_cancel(b.id).unwrap() else { panic!() };
    assert_eq!(queued.status, JobStatus::Cancelled);
    assert!(queued.finished_at_ms.is_some());
    let held = |cancel_requested| LeaseStatus::Held { cancel_requested };
    let progress = JobProgress { fraction: 0.25, iteration: 5, iterations: 20, ..Default::default() };
    assert_eq!(store.update_progress(a.id, WORKER, &progress).unwrap(), held(false));
    assert_eq!(store.get_job(a.id).unwrap().unwrap().progress, progress);
    let CancelOutcome::Accepted(running) = store.request_cancel(a.id).unwrap() else { panic!() };
    assert_eq!((running.status, running.cancel_requested), (JobStatus::Running, true));
    assert_eq!(store.update_progress(a.id, WORKER, &JobProgress::default()).unwrap(), held(true));
    assert_eq!(store.renew_lease(a.id, WORKER, Duration::from_secs(60)).unwrap(), held(true));
    let done = store.finish_job(a.id, WORKER, JobOutcome::Cancelled).unwrap();
    assert_eq!((done.status, done.worker, done.lease_expires_at_ms), (JobStatus::Cancelled, None, None));
    assert!(done.finished_at_ms.is_some());
    assert_eq!(store.request_cancel(Uuid::new_v4()).unwrap(), CancelOutcome::NotFound);
}

#[test]
fn a_sequence_with_active_jobs_is_kept_and_deleting_removes_models() {
    let (_db, blobs, store) = setup!();
    let seq = sequence(&store);
    let other = sequence(&store);
    let a = job(seq.id);
    store.insert_job(&a).unwrap();
    assert_eq!(store.delete_sequence(seq.id).unwrap(), DeleteOutcome::HasActiveJobs);
    store.claim_next_job(&claim()).unwrap();
    assert_eq!(store.delete_sequence(seq.id).unwrap(), DeleteOutcome::HasActiveJobs);
    store.put_window_model(a.id, "w-0", b"window").unwrap();
    assert_eq!(store.read_window_model(a.id, "w-0").unwrap().as_deref(), Some(&b"window"[..]));
    assert!(store.read_window_model(a.id, "../x").is_err());
    let done = store.finish_job(a.id, WORKER, JobOutcome::Succeeded { model: b"model" }).unwrap();
    assert_eq!((done.status, done.progress.fraction), (JobStatus::Succeeded, 1.0));
    assert_eq!(store.read_model(a.id).unwrap(), b"model");
    // Finished: its kept windows are gone.
    assert_eq!(store.read_window_model(a.id, "w-0").unwrap(), None);
    assert_eq!(store.delete_sequence(seq.id).unwrap(), DeleteOutcome::Deleted);
    assert!(store.get_job(a.id).unwrap().is_none());
    assert!(store.get_sequence(seq.id).unwrap().is_none());
    assert!(matches!(store.read_model(a.id), Err(StoreError::Missing(_))));
    assert!(matches!(store.read_frame(seq.id, 0), Err(StoreError::Missing(_))));
    // Only the other sequence's objects remain.
    let left = blobs.list("").unwrap();
    assert_eq!(left.len(), 2);
    assert!(left.iter().all(|k| k.starts_with(&sequence_prefix(other.id))), "{left:?}");
    assert_eq!(store.delete_sequence(seq.id).unwrap(), DeleteOutcome::NotFound);
}

#[test]
fn a_succeeded_job_whose_files_are_unreadable_can_be_failed() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let a = job(seq.id);
    store.insert_job(&a).unwrap();
    assert_eq!(store.fail_succeeded_job(a.id, "gone").unwrap().unwrap().status, JobStatus::Queued);
    store.claim_next_job(&claim()).unwrap();
    store.finish_job(a.id, WORKER, JobOutcome::Succeeded { model: b"m" }).unwrap();
    let failed = store.fail_succeeded_job(a.id, "model unreadable").unwrap().unwrap();
    assert_eq!((failed.status, failed.error.as_deref()), (JobStatus::Failed, Some("model unreadable")));
    assert!(store.fail_succeeded_job(Uuid::new_v4(), "x").unwrap().is_none());
    let CancelOutcome::AlreadyFinished(_) = store.request_cancel(a.id).unwrap() else { panic!() };
}

#[test]
fn orphan_objects_are_swept_at_connect_but_live_uploads_are_not() {
    let (db, blobs, store) = setup!();
    let seq = sequence(&store);
    let a = job(seq.id);
    store.insert_job(&a).unwrap();
    store.put_window_model(a.id, "w-1", b"kept").unwrap();
    let uploads = |blobs: &ObjectBlobs| -> Vec<String> {
        blobs.list("sequences/").unwrap().into_iter().filter(|k| !k.starts_with(&sequence_prefix(seq.id))).collect()
    };
    // An upload whose process stopped touching it two hours ago, then a live one.
    let mut dead = store.begin_sequence().unwrap();
    dead.put_frame(&[[2.0, 2.0, 2.0]]).unwrap();
    db.sql("UPDATE uploads SET touched_at = touched_at - 7200000");
    let dead_keys = uploads(&blobs);
    let mut live = store.begin_sequence().unwrap();
    live.put_frame(&[[1.0, 1.0, 1.0]]).unwrap();
    let live_keys: Vec<String> = uploads(&blobs).into_iter().filter(|k| !dead_keys.contains(k)).collect();
    assert_eq!((dead_keys.len(), live_keys.len()), (1, 1));
    let orphan_job = Uuid::new_v4();
    for key in [
        frame_key(Uuid::new_v4(), 0),
        "sequences/not-a-uuid/frame_00000.f32".to_string(),
        model_key(orphan_job),
        "models/junk".to_string(),
        format!("{}w-1.mbnt", windows_prefix(orphan_job)),
    ] {
        blobs.put(&key, b"x".to_vec()).unwrap();
    }
    let second = db.connect(&blobs);
    let mut expected: Vec<String> = (0..2).map(|k| frame_key(seq.id, k)).collect();
    expected.push(format!("{}w-1.mbnt", windows_prefix(a.id)));
    expected.extend(live_keys);
    expected.sort();
    assert_eq!(blobs.list("").unwrap(), expected);
    // The live upload goes on and commits; the swept one cannot, and takes its late frame along.
    live.put_frame(&[[3.0, 3.0, 3.0]]).unwrap();
    let kept = live.commit(SequenceMeta::default()).unwrap();
    assert_eq!(second.get_sequence(kept.id).unwrap().unwrap().points_per_frame, vec![1, 1]);
    dead.put_frame(&[[4.0, 4.0, 4.0]]).unwrap();
    assert!(matches!(dead.commit(SequenceMeta::default()), Err(StoreError::Missing(_))));
    assert_eq!(second.sweep_orphans(STALE_UPLOAD).unwrap(), 0);
    assert_eq!(blobs.list("").unwrap().len(), expected.len() + 1);
}

#[test]
fn jobs_are_listed_by_status_and_counted() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let mut ids = Vec::new();
    for _ in 0..3 {
        let j = job(seq.id);
        ids.push(j.id);
        store.insert_job(&j).unwrap();
    }
    store.claim_next_job(&claim()).unwrap();
    let queued =
        store.list_jobs(&JobFilter { status: Some(JobStatus::Queued), sequence_id: Some(seq.id), limit: 10 }).unwrap();
    assert_eq!(queued.iter().map(|j| j.id).collect::<Vec<_>>(), vec![ids[2], ids[1]], "newest first");
    let mut counts = store.count_jobs_by_status().unwrap();
    counts.sort_by_key(|(s, _)| s.as_str());
    assert_eq!(counts, vec![(JobStatus::Queued, 2), (JobStatus::Running, 1)]);
    assert_eq!(store.list_jobs(&JobFilter { limit: 1, ..Default::default() }).unwrap().len(), 1);
    let elsewhere = JobFilter { sequence_id: Some(Uuid::new_v4()), limit: 10, ..Default::default() };
    assert!(store.list_jobs(&elsewhere).unwrap().is_empty());
    let second = sequence(&store);
    assert_eq!(store.list_sequences(10).unwrap().iter().map(|s| s.id).collect::<Vec<_>>(), vec![second.id, seq.id]);
    assert_eq!(store.list_sequences(1).unwrap().len(), 1);
}

#[test]
fn an_expired_lease_lets_another_worker_claim_the_job_and_the_first_records_nothing() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let a = job(seq.id);
    store.insert_job(&a).unwrap();
    let first = store.claim_next_job(&claim_as("w1", 200, 3)).unwrap().unwrap();
    assert_eq!((first.worker.as_deref(), first.attempts), (Some("w1"), 1));
    // A live lease keeps the job from everyone else.
    assert!(store.claim_next_job(&claim_as("w0", 600_000, 3)).unwrap().is_none());
    std::thread::sleep(Duration::from_millis(250));
    let second = store.claim_next_job(&claim_as("w2", 600_000, 3)).unwrap().unwrap();
    assert_eq!((second.id, second.worker.as_deref(), second.attempts), (a.id, Some("w2"), 2));
    assert!(store.claim_next_job(&claim_as("w3", 600_000, 3)).unwrap().is_none());
    let progress = JobProgress::default();
    assert_eq!(store.update_progress(a.id, "w1", &progress).unwrap(), LeaseStatus::Lost);
    let lost = Duration::from_secs(60);
    assert_eq!(store.renew_lease(a.id, "w1", lost).unwrap(), LeaseStatus::Lost);
    let late = store.finish_job(a.id, "w1", JobOutcome::Succeeded { model: b"stale" });
    assert!(matches!(late, Err(StoreError::LeaseLost(_))), "{late:?}");
    assert!(matches!(store.finish_job(a.id, "w1", JobOutcome::Cancelled), Err(StoreError::LeaseLost(_))));
    assert!(matches!(store.requeue_job(a.id, "w1"), Err(StoreError::LeaseLost(_))));
    assert!(matches!(store.read_model(a.id), Err(StoreError::Missing(_))));
    let job_now = store.get_job(a.id).unwrap().unwrap();
    assert_eq!((job_now.status, job_now.worker.as_deref(), job_now.attempts), (JobStatus::Running, Some("w2"), 2));
    let held = LeaseStatus::Held { cancel_requested: false };
    assert_eq!(store.renew_lease(a.id, "w2", lost).unwrap(), held);
    let done = store.finish_job(a.id, "w2", JobOutcome::Succeeded { model: b"model" }).unwrap();
    assert_eq!((done.status, done.worker, done.lease_expires_at_ms), (JobStatus::Succeeded, None, None));
    assert_eq!(store.read_model(a.id).unwrap(), b"model");
    assert!(matches!(store.finish_job(a.id, "w2", JobOutcome::Cancelled), Err(StoreError::LeaseLost(_))));
}

#[test]
fn a_renewed_lease_outlives_its_first_term() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    store.insert_job(&job(seq.id)).unwrap();
    let a = store.claim_next_job(&claim_as("w1", 300, 3)).unwrap().unwrap();
    for _ in 0..4 {
        std::thread::sleep(Duration::from_millis(100));
        let renewed = store.renew_lease(a.id, "w1", Duration::from_millis(300)).unwrap();
        assert_eq!(renewed, LeaseStatus::Held { cancel_requested: false });
    }
    // 400 ms after a 300 ms claim: without the renewals the job would be up for grabs.
    assert!(store.claim_next_job(&claim_as("w2", 300, 3)).unwrap().is_none());
}

#[test]
fn a_job_whose_workers_keep_dying_fails_after_max_attempts_and_a_handed_back_run_is_free() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let a = job(seq.id);
    store.insert_job(&a).unwrap();
    // Orderly hand-backs (shutdowns) do not use attempts up.
    for _ in 0..5 {
        let run = store.claim_next_job(&claim_as("w", 600_000, 2)).unwrap().unwrap();
        assert_eq!(run.attempts, 1);
        let back = store.requeue_job(a.id, "w").unwrap();
        assert_eq!((back.status, back.attempts, back.worker), (JobStatus::Queued, 0, None));
    }
    for attempt in 1..=2 {
        let run = store.claim_next_job(&claim_as(&format!("w{attempt}"), 1, 2)).unwrap().unwrap();
        assert_eq!(run.attempts, attempt);
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(store.claim_next_job(&claim_as("w3", 600_000, 2)).unwrap().is_none());
    let failed = store.get_job(a.id).unwrap().unwrap();
    assert_eq!((failed.status, failed.worker), (JobStatus::Failed, None));
    let error = failed.error.unwrap();
    assert!(error.contains("2 times") && error.contains("max_attempts is 2"), "{error}");
}

#[test]
fn a_job_cancelled_while_its_worker_died_ends_cancelled_at_the_next_claim() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let (a, b) = (job(seq.id), job(seq.id));
    store.insert_job(&a).unwrap();
    store.insert_job(&b).unwrap();
    store.claim_next_job(&claim_as("dies", 1, 3)).unwrap();
    store.request_cancel(a.id).unwrap();
    std::thread::sleep(Duration::from_millis(20));
    // The expired, cancelled job is not run again: the claim moves on to the next one.
    assert_eq!(store.claim_next_job(&claim()).unwrap().unwrap().id, b.id);
    let a_now = store.get_job(a.id).unwrap().unwrap();
    assert_eq!((a_now.status, a_now.worker), (JobStatus::Cancelled, None));
}

#[test]
fn racing_workers_claim_every_job_exactly_once() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let jobs: Vec<Uuid> = (0..20)
        .map(|_| {
            let j = job(seq.id);
            store.insert_job(&j).unwrap();
            j.id
        })
        .collect();
    let claimed: Vec<Vec<Uuid>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..8)
            .map(|w| {
                let store = &store;
                s.spawn(move || {
                    let mut mine = Vec::new();
                    while let Some(j) = store.claim_next_job(&claim_as(&format!("racer-{w}"), 600_000, 3)).unwrap() {
                        assert_eq!(j.worker, Some(format!("racer-{w}")));
                        mine.push(j.id);
                    }
                    mine
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let mut counts = std::collections::HashMap::new();
    for id in claimed.iter().flatten() {
        *counts.entry(*id).or_insert(0) += 1;
    }
    assert_eq!(counts.len(), jobs.len());
    assert!(jobs.iter().all(|j| counts[j] == 1), "{counts:?}");
    // Each record names the worker that got it.
    for (w, mine) in claimed.iter().enumerate() {
        for id in mine {
            let j = store.get_job(*id).unwrap().unwrap();
            assert_eq!((j.worker, j.attempts), (Some(format!("racer-{w}")), 1));
        }
    }
}

#[test]
fn leases_are_timed_by_the_database_clock() {
    let (db, _blobs, store) = setup!();
    let seq = sequence(&store);
    let a = job(seq.id);
    store.insert_job(&a).unwrap();
    // The database's clock runs an hour ahead of this machine's.
    db.sql(
        "CREATE OR REPLACE FUNCTION mbnt_now_ms() RETURNS bigint LANGUAGE sql VOLATILE \
         AS $$ SELECT floor(extract(epoch FROM clock_timestamp()) * 1000)::bigint + 3600000 $$",
    );
    let before = db_now_ms(&store);
    let run = store.claim_next_job(&claim_as("w1", 60_000, 3)).unwrap().unwrap();
    let after = db_now_ms(&store);
    let expires = run.lease_expires_at_ms.unwrap();
    assert!((before + 60_000..=after + 60_000).contains(&expires), "{before} {expires} {after}");
    assert!(expires > now_ms() + 3_000_000, "the lease is on the database's clock, not this machine's");
    // The database's clock jumps two minutes on: the lease is over for every worker, whatever
    // their own clocks say.
    db.sql(
        "CREATE OR REPLACE FUNCTION mbnt_now_ms() RETURNS bigint LANGUAGE sql VOLATILE \
         AS $$ SELECT floor(extract(epoch FROM clock_timestamp()) * 1000)::bigint + 3720000 $$",
    );
    let taken = store.claim_next_job(&claim_as("w2", 60_000, 3)).unwrap().unwrap();
    assert_eq!((taken.id, taken.worker.as_deref(), taken.attempts), (a.id, Some("w2"), 2));
    assert_eq!(store.renew_lease(a.id, "w1", Duration::from_secs(60)).unwrap(), LeaseStatus::Lost);
}

#[test]
fn an_api_restart_leaves_live_workers_their_jobs() {
    let (db, blobs, api) = setup!();
    let worker = db.connect(&blobs);
    let seq = sequence(&api);
    let a = job(seq.id);
    api.insert_job(&a).unwrap();
    let run = worker.claim_next_job(&claim_as("host-b:42:0", 600_000, 3)).unwrap().unwrap();
    // The API process stops and starts again, and re-queues what it takes as interrupted.
    drop(api);
    let api = db.connect(&blobs);
    assert_eq!(api.requeue_running_jobs().unwrap(), 0);
    let now = api.get_job(a.id).unwrap().unwrap();
    assert_eq!((now.status, now.worker.as_deref(), now.attempts), (JobStatus::Running, Some("host-b:42:0"), 1));
    assert!(api.claim_next_job(&claim()).unwrap().is_none());
    assert_eq!(
        worker.renew_lease(run.id, "host-b:42:0", Duration::from_secs(60)).unwrap(),
        LeaseStatus::Held { cancel_requested: false }
    );
    let done = worker.finish_job(run.id, "host-b:42:0", JobOutcome::Succeeded { model: b"m" }).unwrap();
    assert_eq!(done.status, JobStatus::Succeeded);
    assert_eq!(api.read_model(a.id).unwrap(), b"m");
}

#[test]
fn migrations_applied_twice_change_nothing() {
    let (db, blobs, store) = setup!();
    let seq = sequence(&store);
    store.insert_job(&job(seq.id)).unwrap();
    let again = db.connect(&blobs);
    let third = db.connect(&blobs);
    assert_eq!(again.get_sequence(seq.id).unwrap().unwrap(), seq);
    assert_eq!(third.count_jobs_by_status().unwrap(), vec![(JobStatus::Queued, 1)]);
    let applied: i64 = store
        .inner
        .run(async { sqlx::query_scalar("SELECT COUNT(*) FROM _sqlx_migrations").fetch_one(&store.inner.pool).await })
        .unwrap();
    assert_eq!(applied, i64::try_from(MIGRATOR.iter().count()).unwrap());
}

#[test]
fn the_store_answers_from_plain_threads_blocking_tasks_and_async_tasks_of_another_runtime() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    // Plain threads, at once.
    std::thread::scope(|s| {
        for _ in 0..4 {
            s.spawn(|| assert_eq!(store.get_sequence(seq.id).unwrap().unwrap().id, seq.id));
        }
    });
    // spawn_blocking of a multi-thread runtime (how the HTTP handlers call it).
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let shared = store.clone();
    let frames = runtime
        .block_on(async move { tokio::task::spawn_blocking(move || shared.read_frame(seq.id, 0)).await })
        .unwrap()
        .unwrap();
    assert_eq!(frames.len(), 2);
    // Directly in async tasks (blocking them, as any Store call does), on both kinds of runtime,
    // many calls in a row: tokio's task budget must not starve the store's I/O.
    let current = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    for runtime in [&runtime, &current] {
        let shared = store.clone();
        let n = runtime.block_on(async move {
            let mut n = 0;
            for _ in 0..300 {
                shared.ping().unwrap();
                n += shared.list_sequences(5).unwrap().len();
            }
            n
        });
        assert_eq!(n, 300);
    }
    // The last handle dropped on another runtime's worker shuts the store's runtime down
    // without blocking or panicking.
    runtime.block_on(async move { tokio::spawn(async move { drop(store) }).await }).unwrap();
}

#[test]
fn a_window_is_claimed_by_one_worker_until_its_lease_expires_or_it_is_released() {
    let (_db, _blobs, store) = setup!();
    let seq = sequence(&store);
    crate::store::conformance::window_claims(&store, job(seq.id));
}
