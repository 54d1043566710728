//! The fleet as processes: one `mbnt serve --workers 0` (the API alone) and two `mbnt worker`
//! processes on one PostgreSQL database and one object store (a local directory through the
//! object-store layer). Four jobs are queued; one worker is killed with SIGKILL mid-fit, after a
//! checkpoint; the API is restarted while the other works. Every job must succeed, the killed
//! one on the other worker from its checkpoint, and no job may be run to its end by two
//! workers.
//!
//! Needs the PostgreSQL server of the project's machines (127.0.0.1:5432, trust auth, or
//! `MBNT_TEST_DATABASE_URL`); without one the test says it skipped.

mod common;

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, mpsc};
use std::time::Duration;

use common::{frames, temp_dir};
use serde_json::{Value, json};
use sqlx::Connection;

/// How long any awaited state may take on a loaded 2-core CI machine.
const TIMEOUT: Duration = Duration::from_secs(240);

fn admin_url() -> String {
    std::env::var("MBNT_TEST_DATABASE_URL").unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".into())
}

/// A fresh database on the test server, dropped with the guard; `None` (the test skips) when
/// no server answers.
struct Database {
    admin: String,
    name: String,
    url: String,
}

impl Database {
    async fn create() -> Option<Self> {
        let admin = admin_url();
        let connect = sqlx::PgConnection::connect(&admin);
        let mut conn = match tokio::time::timeout(Duration::from_secs(3), connect).await {
            Ok(Ok(conn)) => conn,
            _ => {
                eprintln!("skipped: no PostgreSQL at {admin}");
                return None;
            }
        };
        let name = format!("mbnt_fleet_{}", uuid::Uuid::new_v4().simple());
        sqlx::query(sqlx::AssertSqlSafe(format!("CREATE DATABASE {name}")))
            .execute(&mut conn)
            .await
            .expect("database created");
        let base = admin.rsplit_once('/').expect("a database URL has a path").0;
        Some(Self { url: format!("{base}/{name}"), admin, name })
    }
}

impl Drop for Database {
    fn drop(&mut self) {
        let (admin, name) = (self.admin.clone(), self.name.clone());
        // Drop runs inside the test's runtime: use a thread with its own.
        let _ = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
            rt.block_on(async {
                if let Ok(mut conn) = sqlx::PgConnection::connect(&admin).await {
                    let _ = sqlx::query(sqlx::AssertSqlSafe(format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)")))
                        .execute(&mut conn)
                        .await;
                }
            });
        })
        .join();
    }
}

/// A child process of the `mbnt` binary whose log is collected.
struct Proc {
    child: Child,
    log: Arc<Mutex<Vec<String>>>,
}

impl Proc {
    /// Starts `mbnt ARGS` with `env`; returns it and a channel that receives the first log
    /// line containing `ready` (its address for `serve`).
    fn start(args: &[&str], env: &[(&str, String)], ready: &'static str) -> (Self, mpsc::Receiver<String>) {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_mbnt"));
        cmd.args(args)
            .env("RUST_LOG", "info")
            .env("NO_COLOR", "1")
            .env_remove("MBNT_API_TOKEN")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().expect("mbnt starts");
        let stderr = child.stderr.take().expect("piped stderr");
        let log = Arc::new(Mutex::new(Vec::new()));
        let (tx, rx) = mpsc::channel();
        let sink = log.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                if line.contains(ready) {
                    let addr = line.split_whitespace().find_map(|w| w.strip_prefix("addr=")).unwrap_or("");
                    let _ = tx.send(addr.to_string());
                }
                sink.lock().unwrap().push(line);
            }
        });
        (Self { child, log }, rx)
    }

    fn log(&self) -> String {
        self.log.lock().unwrap().join("\n")
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM, then wait for the orderly stop (nothing when it has exited already).
    fn stop(&mut self) {
        if matches!(self.child.try_wait(), Ok(Some(_))) {
            return;
        }
        let _ = Command::new("kill").arg("-TERM").arg(self.child.id().to_string()).status();
        let _ = self.child.wait();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

async fn wait_ready(rx: mpsc::Receiver<String>, what: &str, proc: &Proc) -> String {
    match tokio::task::spawn_blocking(move || rx.recv_timeout(TIMEOUT)).await.unwrap() {
        Ok(addr) => addr,
        Err(_) => panic!("{what} did not start; log:\n{}", proc.log()),
    }
}

struct Api {
    proc: Proc,
    base: String,
    client: reqwest::Client,
}

impl Api {
    async fn start(env: &[(&str, String)], dir: &std::path::Path) -> Self {
        let dir = dir.to_string_lossy().into_owned();
        let args = ["serve", "--workers", "0", "--bind", "127.0.0.1:0", "--data-dir", &dir];
        let (proc, rx) = Proc::start(&args, env, "mbnt service listening");
        let addr = wait_ready(rx, "mbnt serve", &proc).await;
        Self { proc, base: format!("http://{addr}"), client: reqwest::Client::new() }
    }

    async fn get(&self, path: &str) -> Value {
        let r = self.client.get(format!("{}{path}", self.base)).send().await.expect("request sent");
        assert_eq!(r.status(), 200, "GET {path}");
        r.json().await.expect("JSON answer")
    }

    async fn post(&self, path: &str, body: &Value) -> (u16, Value) {
        let r = self.client.post(format!("{}{path}", self.base)).json(body).send().await.expect("request sent");
        (r.status().as_u16(), r.json().await.unwrap_or(Value::Null))
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_worker_loses_nothing_and_no_job_is_run_twice() {
    let Some(db) = Database::create().await else { return };
    let root = temp_dir();
    let objects = root.join("objects");
    std::fs::create_dir_all(&objects).unwrap();
    let env = vec![
        ("MBNT_DATABASE_URL", db.url.clone()),
        ("MBNT_OBJECT_STORE_URL", format!("file://{}", objects.display())),
        // A dead worker's job is taken over after 2 s; checkpoints at every validation.
        ("MBNT_LEASE_S", "2".to_string()),
        ("MBNT_CHECKPOINT_EVERY_S", "0".to_string()),
    ];
    let mut api = Api::start(&env, &root.join("api")).await;
    let mut workers = Vec::new();
    for w in 0..2 {
        let dir = root.join(format!("worker{w}")).to_string_lossy().into_owned();
        let args = ["worker", "--threads-per-job", "1", "--data-dir", &dir];
        let (proc, rx) = Proc::start(&args, &env, "mbnt worker ready");
        wait_ready(rx, "mbnt worker", &proc).await;
        workers.push(proc);
    }

    let (status, seq) = api.post("/v1/sequences", &json!({ "name": "fleet", "frames": frames(3, 300) })).await;
    assert_eq!(status, 201, "{seq}");
    let seq = seq["id"].as_str().unwrap().to_string();
    // Long enough to be caught mid-fit on a fast machine; validations (and checkpoints) every 10.
    let params = json!({ "iterations": 300, "validate_every": 10, "validation_patience": 0, "hidden_width": 64,
                         "remove_ground": false });
    let mut jobs = Vec::new();
    for _ in 0..4 {
        let (status, job) =
            api.post("/v1/jobs", &json!({ "sequence_id": seq, "method": "ntp", "params": params })).await;
        assert_eq!(status, 202, "{job}");
        jobs.push(job["id"].as_str().unwrap().to_string());
    }

    // Find a job past its first checkpoints, and kill the worker process holding it.
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    let (victim, victim_worker) = loop {
        let mut found = None;
        for id in &jobs {
            let job = api.get(&format!("/v1/jobs/{id}")).await;
            if job["status"] == "running" && job["progress"]["iteration"].as_u64() >= Some(35) {
                found = Some((id.clone(), job["worker"].as_str().unwrap().to_string()));
                break;
            }
        }
        if let Some(found) = found {
            break found;
        }
        assert!(tokio::time::Instant::now() < deadline, "no job got far enough");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    // Worker names are `host:pid:n`.
    let pid: u32 = victim_worker.split(':').nth(1).unwrap().parse().unwrap();
    let killed = workers.iter().position(|w| w.child.id() == pid).expect("the holder is one of our workers");
    workers[killed].kill();

    // The API restarts while the other worker works: nothing is lost or re-queued by it.
    api.proc.stop();
    api = Api::start(&env, &root.join("api")).await;

    let deadline = tokio::time::Instant::now() + TIMEOUT;
    let mut done = BTreeMap::new();
    while done.len() < jobs.len() {
        for id in &jobs {
            let job = api.get(&format!("/v1/jobs/{id}")).await;
            assert_ne!(job["status"], "failed", "{job}\nworkers' logs:\n{}", workers[1 - killed].log());
            if job["status"] == "succeeded" {
                done.insert(id.clone(), job);
            }
        }
        assert!(tokio::time::Instant::now() < deadline, "jobs did not all succeed: {done:?}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let taken_over = &done[&victim];
    assert_eq!(taken_over["attempts"], 2, "{taken_over}");
    let resumed = taken_over["resumed_from_iteration"].as_u64().expect("went on from a checkpoint");
    assert!(resumed >= 30, "resumed from {resumed}: a checkpoint is taken at every validation");
    for (id, job) in &done {
        if *id != victim {
            assert_eq!(job["attempts"], 1, "{job}");
        }
        assert_eq!(job["worker"], Value::Null, "{job}");
        // The model answers through the restarted API.
        let (status, answer) =
            api.post(&format!("/v1/jobs/{id}/query"), &json!({ "frame": 1, "indices": [0, 1], "times": [0, 2] })).await;
        assert_eq!(status, 200, "{answer}");
    }
    // Each job was fitted to its end exactly once across the two workers' logs.
    let logs = [workers[0].log(), workers[1].log()];
    for id in &jobs {
        let ends: usize =
            logs.iter().map(|l| l.lines().filter(|x| x.contains(id) && x.contains("fit succeeded")).count()).sum();
        assert_eq!(ends, 1, "job {id} succeeded {ends} times; logs:\n{}\n---\n{}", logs[0], logs[1]);
    }
    for w in &mut workers {
        w.stop();
    }
    api.proc.stop();
    let _ = std::fs::remove_dir_all(&root);
}
