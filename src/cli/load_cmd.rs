//! `mbnt bench-load`: a load benchmark of the HTTP service on loopback.
//!
//! The driver fits a small job first (so there is a succeeded job to query), starts a long fit
//! of a simulated sequence and waits until it iterates, then sends uploads (multipart KITTI
//! frames with timestamps and poses, all at once) and queries of the finished job (a bounded
//! number in flight) at the same time. Every answer is checked: an upload must be a 201
//! describing exactly the frames sent, and a query must return byte for byte the answer the
//! same query got before the load started. The report gives the error count, p50 / p99 latency
//! of each kind and whether the long fit was running from the first request to the last; the
//! long fit is cancelled at the end.
//!
//! Without `--target` the service runs in this process, on its own runtime, over a temporary
//! data directory that is removed afterwards.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail, ensure};
use axum::body::Bytes;
use serde::Serialize;
use serde_json::{Value, json};

use crate::http::{Limits, Service, ServiceConfig};
use crate::jobs::CoreFitter;
use crate::sim::{LidarParams, SimParams, SimSequence, simulate};

/// Arguments of `mbnt bench-load`.
#[derive(Debug, Clone, clap::Args)]
pub struct LoadArgs {
    /// Base URL of a running service (e.g. http://127.0.0.1:8080); the token, if it needs one,
    /// comes from MBNT_API_TOKEN. Without it, a service is started in this process over a
    /// temporary data directory.
    #[arg(long)]
    pub target: Option<String>,
    /// Uploads, all sent at once.
    #[arg(long, default_value_t = 50)]
    pub uploads: usize,
    /// Frames of each uploaded sequence (simulated, default 32-beam sensor).
    #[arg(long, default_value_t = 3)]
    pub upload_frames: usize,
    /// Queries of the finished job.
    #[arg(long, default_value_t = 2000)]
    pub queries: usize,
    /// Queries in flight at once.
    #[arg(long, default_value_t = 32)]
    pub query_concurrency: usize,
    /// Points per query.
    #[arg(long, default_value_t = 500)]
    pub query_points: usize,
    /// Times per query.
    #[arg(long, default_value_t = 5)]
    pub query_times: usize,
    /// Frames of the sequence whose fit runs during the load.
    #[arg(long, default_value_t = 10)]
    pub fit_frames: usize,
    /// Iterations of that fit (it never stops early; it is cancelled after the load).
    #[arg(long, default_value_t = 5000)]
    pub fit_iterations: usize,
    /// Seed of the simulated sequences.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Threads of the fit of the in-process service (default: all cores).
    #[arg(long)]
    pub threads_per_job: Option<usize>,
    /// Also write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// What the driver sends; [`LoadConfig::default`] is the benchmark of `docs/benchmarks.md`.
#[derive(Debug, Clone)]
pub struct LoadConfig {
    /// Uploads, all sent at once.
    pub uploads: usize,
    /// The simulated sequence every upload sends (and the finished job is fitted to).
    pub upload_sequence: SimParams,
    /// Queries of the finished job.
    pub queries: usize,
    /// Queries in flight at once.
    pub query_concurrency: usize,
    /// Points per query (at most a frame's points).
    pub query_points: usize,
    /// Times per query.
    pub query_times: usize,
    /// Distinct query bodies, sent in turn (each one's quiet answer is fetched first).
    pub query_bodies: usize,
    /// Parameters of the small fit whose result is queried.
    pub query_fit_params: Value,
    /// The simulated sequence of the fit that runs during the load.
    pub fit_sequence: SimParams,
    /// Parameters of that fit: it must outlast the load (it is cancelled afterwards).
    pub fit_params: Value,
    /// Longest wait for the small fit to succeed and for the long one to start iterating.
    pub setup_timeout: Duration,
    /// Longest wait for one request of the load; a request that takes longer is an error.
    pub request_timeout: Duration,
}

impl Default for LoadConfig {
    fn default() -> Self {
        Self {
            uploads: 50,
            upload_sequence: SimParams { seed: 1, frames: 3, ..SimParams::default() },
            queries: 2000,
            query_concurrency: 32,
            query_points: 500,
            query_times: 5,
            query_bodies: 8,
            query_fit_params: json!({ "iterations": 5, "seed": 7, "hidden_width": 16, "hidden_layers": 2,
                                      "validate_every": 2 }),
            fit_sequence: SimParams { seed: 1, frames: 10, ..SimParams::default() },
            fit_params: json!({ "seed": 1, "iterations": 5000, "validation_patience": 0 }),
            setup_timeout: Duration::from_secs(600),
            request_timeout: Duration::from_secs(300),
        }
    }
}

impl LoadConfig {
    /// A configuration small enough for a test: a sparse 8-beam sensor, few points per query.
    pub fn small(uploads: usize, queries: usize) -> Self {
        let lidar = LidarParams { beams: 8, azimuth_step_deg: 2.0, ..LidarParams::default() };
        Self {
            uploads,
            upload_sequence: SimParams { seed: 1, frames: 3, lidar: lidar.clone(), ..SimParams::default() },
            queries,
            query_concurrency: 8,
            query_points: 40,
            query_times: 3,
            query_bodies: 4,
            fit_sequence: SimParams { seed: 2, frames: 4, lidar, ..SimParams::default() },
            ..Self::default()
        }
    }
}

/// Latency of one kind of request, milliseconds (nearest-rank percentiles).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Latency {
    /// Requests sent.
    pub count: usize,
    /// Requests that failed (transport error, unexpected status, wrong answer).
    pub errors: usize,
    /// Median.
    pub p50_ms: f64,
    /// 99th percentile.
    pub p99_ms: f64,
    /// Slowest.
    pub max_ms: f64,
}

impl Latency {
    fn of(outcomes: &[Outcome]) -> Self {
        let mut ms: Vec<f64> = outcomes.iter().map(|o| o.seconds * 1e3).collect();
        ms.sort_by(f64::total_cmp);
        let rank = |p: f64| -> f64 {
            if ms.is_empty() {
                return 0.0;
            }
            let k = ((p * ms.len() as f64).ceil() as usize).clamp(1, ms.len());
            ms[k - 1]
        };
        Self {
            count: outcomes.len(),
            errors: outcomes.iter().filter(|o| o.error.is_some()).count(),
            p50_ms: rank(0.50),
            p99_ms: rank(0.99),
            max_ms: ms.last().copied().unwrap_or(0.0),
        }
    }
}

/// What the load showed.
#[derive(Debug, Clone, Serialize)]
pub struct LoadReport {
    /// The uploads.
    pub uploads: Latency,
    /// Bytes of one upload's frame files.
    pub upload_bytes: usize,
    /// Points per frame of the uploaded sequence.
    pub upload_points_per_frame: Vec<usize>,
    /// The queries.
    pub queries: Latency,
    /// Points and times of each query.
    pub query_points: usize,
    /// Times of each query.
    pub query_times: usize,
    /// Queries in flight at once.
    pub query_concurrency: usize,
    /// Failed requests of the load, both kinds (uploads that were stored but then read back
    /// wrong included).
    pub errors: usize,
    /// The first few failures, for the log.
    pub error_samples: Vec<String>,
    /// The job that fitted during the load.
    pub fit_job: String,
    /// Whether it was `running` when the load began, at every check during it, and at its end.
    pub fit_running_throughout: bool,
    /// Its status checks during the load that found it not running.
    pub fit_not_running_seen: Vec<String>,
    /// Its iterations done when the load began and when it ended.
    pub fit_iterations: [usize; 2],
    /// Seconds from the first request of the load to the last answer.
    pub wall_s: f64,
}

impl LoadReport {
    /// True when every request succeeded with the right answer and the fit ran throughout.
    pub fn passed(&self) -> bool {
        self.errors == 0 && self.fit_running_throughout
    }
}

/// One request of the load.
#[derive(Debug)]
struct Outcome {
    seconds: f64,
    error: Option<String>,
}

/// A client of the service under test.
struct Api {
    client: reqwest::Client,
    base: String,
    token: Option<String>,
}

impl Api {
    fn request(&self, method: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let r = self.client.request(method, format!("{}{path}", self.base));
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    /// Sends a setup request and returns its JSON answer, which must have status `expected`.
    async fn json(&self, request: reqwest::RequestBuilder, expected: u16, what: &str) -> anyhow::Result<Value> {
        let response = request.send().await.with_context(|| format!("{what}: sending"))?;
        let status = response.status().as_u16();
        let text = response.text().await.with_context(|| format!("{what}: reading the answer"))?;
        ensure!(status == expected, "{what}: status {status} (expected {expected}): {text}");
        serde_json::from_str(&text).with_context(|| format!("{what}: the answer is not JSON: {text}"))
    }

    async fn job(&self, id: &str) -> anyhow::Result<Value> {
        self.json(self.request(reqwest::Method::GET, &format!("/v1/jobs/{id}")), 200, "reading the job").await
    }

    /// Polls the job until `done` holds; fails when it ends (succeeded, failed, cancelled)
    /// without `done` holding, or after `timeout`.
    async fn wait_job(&self, id: &str, timeout: Duration, done: impl Fn(&Value) -> bool) -> anyhow::Result<Value> {
        let deadline = Instant::now() + timeout;
        loop {
            let job = self.job(id).await?;
            if done(&job) {
                return Ok(job);
            }
            let status = job["status"].as_str().unwrap_or("");
            if matches!(status, "succeeded" | "failed" | "cancelled") {
                bail!("job {id} ended {status} before it reached the state the load needs: {job}");
            }
            ensure!(Instant::now() < deadline, "job {id} did not reach the state the load needs in time: {job}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    async fn submit(&self, sequence: &str, params: &Value) -> anyhow::Result<String> {
        let body = json!({ "sequence_id": sequence, "params": params });
        let job =
            self.json(self.request(reqwest::Method::POST, "/v1/jobs").json(&body), 202, "submitting a fit").await?;
        Ok(job["id"].as_str().context("the job has no id")?.to_string())
    }
}

/// An upload: the multipart parts of one simulated sequence, built once and shared (the frame
/// files are reference-counted, so 50 uploads do not copy them 50 times).
struct Upload {
    frames: Vec<Bytes>,
    points_per_frame: Vec<usize>,
    timestamps: Vec<f64>,
    poses: Vec<[f64; 16]>,
}

impl Upload {
    fn new(sim: &SimSequence) -> Self {
        Self {
            frames: sim.frames.iter().map(|f| Bytes::from(kitti_bytes(f))).collect(),
            points_per_frame: sim.frames.iter().map(Vec::len).collect(),
            timestamps: sim.timestamps_s.clone(),
            poses: sim.ego_poses.clone(),
        }
    }

    fn bytes(&self) -> usize {
        self.frames.iter().map(Bytes::len).sum()
    }

    fn form(&self, name: &str) -> reqwest::multipart::Form {
        let meta = json!({ "name": name, "timestamps": self.timestamps, "poses": self.poses }).to_string();
        let meta = reqwest::multipart::Part::text(meta).mime_str("application/json").expect("a valid media type");
        let mut form = reqwest::multipart::Form::new().part("meta", meta);
        for (k, frame) in self.frames.iter().enumerate() {
            let part = reqwest::multipart::Part::stream_with_length(frame.clone(), frame.len() as u64)
                .file_name(format!("{k:06}.bin"));
            form = form.part("frame", part);
        }
        form
    }

    /// Why an upload's answer does not describe this sequence under `name`, if it does not.
    fn mismatch(&self, name: &str, answer: &Value) -> Option<String> {
        let expected = json!({
            "name": name,
            "frames": self.frames.len(),
            "points_per_frame": self.points_per_frame,
            "timestamps": self.timestamps,
            "time_unit": "s",
            "has_poses": true,
        });
        let differs: Vec<&str> = expected
            .as_object()
            .into_iter()
            .flatten()
            .filter(|(k, v)| answer.get(k.as_str()) != Some(v))
            .map(|(k, _)| k.as_str())
            .collect();
        let has_id = answer["id"].as_str().is_some_and(|id| uuid::Uuid::parse_str(id).is_ok());
        if differs.is_empty() && has_id {
            None
        } else {
            Some(format!("the upload answer differs in {differs:?} (id present: {has_id}): {answer}"))
        }
    }
}

/// KITTI velodyne layout: float32 x, y, z, intensity (0: not simulated) per point.
fn kitti_bytes(points: &[[f32; 3]]) -> Vec<u8> {
    let mut out = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in [p[0], p[1], p[2], 0.0] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// The query bodies: even ones take a frame's points by index, odd ones send points (a frame's,
/// moved 5 cm) with their time; times spread over the sequence.
fn query_bodies(sim: &SimSequence, config: &LoadConfig) -> Vec<Value> {
    let (t0, t1) = (sim.timestamps_s[0], *sim.timestamps_s.last().unwrap_or(&sim.timestamps_s[0]));
    let times: Vec<f64> =
        (0..config.query_times.max(1)).map(|j| t0 + (t1 - t0) * j as f64 / config.query_times.max(2) as f64).collect();
    (0..config.query_bodies.max(1))
        .map(|b| {
            let k = b % sim.frames.len();
            let frame = &sim.frames[k];
            let n = config.query_points.clamp(1, frame.len());
            // Spread the picked points over the frame, shifted per body so the bodies differ.
            let indices: Vec<usize> = (0..n).map(|j| (j * frame.len() / n + b) % frame.len()).collect();
            if b % 2 == 0 {
                json!({ "frame": k, "indices": indices, "times": times })
            } else {
                let points: Vec<[f32; 3]> =
                    indices.iter().map(|&i| [frame[i][0] + 0.05, frame[i][1], frame[i][2]]).collect();
                json!({ "points": points, "t": sim.timestamps_s[k], "times": times })
            }
        })
        .collect()
}

/// Checks a quiet answer: `points` rows of `times` finite positions.
fn check_positions(answer: &[u8], points: usize, times: usize) -> anyhow::Result<()> {
    let v: Value = serde_json::from_slice(answer).context("a query answer is not JSON")?;
    let rows = v["positions"].as_array().context("a query answer has no positions")?;
    ensure!(rows.len() == points, "{} rows for {points} points", rows.len());
    for row in rows {
        let row = row.as_array().context("a positions row is not an array")?;
        ensure!(row.len() == times, "{} positions for {times} times", row.len());
        for p in row {
            let p = p.as_array().context("a position is not an array")?;
            ensure!(p.len() == 3 && p.iter().all(|c| c.as_f64().is_some_and(f64::is_finite)), "a bad position {p:?}");
        }
    }
    Ok(())
}

/// Watches the long fit during the load: every status check that does not find it running.
async fn watch_fit(api: Arc<Api>, job: String, stop: tokio::sync::watch::Receiver<bool>) -> Vec<String> {
    let mut seen = Vec::new();
    let mut stop = stop;
    loop {
        match api.job(&job).await {
            Ok(j) if j["status"] == "running" => {}
            Ok(j) => seen.push(format!("status {}", j["status"])),
            Err(e) => seen.push(format!("{e:#}")),
        }
        tokio::select! {
            _ = stop.wait_for(|s| *s) => return seen,
            () = tokio::time::sleep(Duration::from_millis(250)) => {}
        }
    }
}

/// Runs the load against the service at `base` (e.g. `http://127.0.0.1:8080`), with `token`
/// when it needs one. Errors are setup failures (the small fit failed, the long fit never
/// started); failed requests of the load itself are counted in the report.
pub async fn drive(base: &str, token: Option<&str>, config: &LoadConfig) -> anyhow::Result<LoadReport> {
    let client = reqwest::Client::builder().timeout(config.request_timeout).build().context("building a client")?;
    let api = Arc::new(Api { client, base: base.trim_end_matches('/').to_string(), token: token.map(str::to_string) });

    // Simulating is CPU work of a second or so: keep it off the executor.
    let (upload_params, fit_params) = (config.upload_sequence.clone(), config.fit_sequence.clone());
    let (upload_sim, fit_sim) = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
        Ok((simulate(&upload_params)?, simulate(&fit_params)?))
    })
    .await??;
    let upload = Arc::new(Upload::new(&upload_sim));
    let fit_upload = Upload::new(&fit_sim);

    // A finished job to query: the upload sequence, fitted small.
    let seq = api
        .json(
            api.request(reqwest::Method::POST, "/v1/sequences").multipart(upload.form("load-query")),
            201,
            "uploading",
        )
        .await?;
    let seq = seq["id"].as_str().context("the sequence has no id")?.to_string();
    let queried = api.submit(&seq, &config.query_fit_params).await?;
    api.wait_job(&queried, config.setup_timeout, |j| j["status"] == "succeeded").await?;

    // The quiet answer of each query body, against which every answer under load is checked.
    let bodies = query_bodies(&upload_sim, config);
    let mut quiet = Vec::with_capacity(bodies.len());
    let mut query_points = 0;
    for body in &bodies {
        let response =
            api.request(reqwest::Method::POST, &format!("/v1/jobs/{queried}/query")).json(body).send().await?;
        let status = response.status().as_u16();
        let bytes = response.bytes().await?;
        ensure!(status == 200, "a quiet query: status {status}: {}", String::from_utf8_lossy(&bytes));
        let points = body["indices"].as_array().or(body["points"].as_array()).map_or(0, Vec::len);
        check_positions(&bytes, points, config.query_times.max(1))?;
        query_points = query_points.max(points);
        quiet.push(bytes);
    }
    let bodies: Arc<Vec<(Bytes, Bytes)>> =
        Arc::new(bodies.iter().map(|b| Bytes::from(b.to_string())).zip(quiet).collect());

    // The long fit, iterating before the load begins.
    let seq = api
        .json(
            api.request(reqwest::Method::POST, "/v1/sequences").multipart(fit_upload.form("load-fit")),
            201,
            "uploading the long fit's sequence",
        )
        .await?;
    let seq = seq["id"].as_str().context("the sequence has no id")?.to_string();
    let fit_job = api.submit(&seq, &config.fit_params).await?;
    let started = api
        .wait_job(&fit_job, config.setup_timeout, |j| {
            j["status"] == "running" && j["progress"]["iteration"].as_u64().is_some_and(|i| i >= 1)
        })
        .await?;
    let first_iteration = started["progress"]["iteration"].as_u64().unwrap_or(0) as usize;

    let (stop, stopped) = tokio::sync::watch::channel(false);
    let watcher = tokio::spawn(watch_fit(api.clone(), fit_job.clone(), stopped));
    let load_started = Instant::now();

    let uploads: Vec<_> = (0..config.uploads)
        .map(|i| {
            let (api, upload) = (api.clone(), upload.clone());
            tokio::spawn(async move {
                let name = format!("load-{i}");
                let form = upload.form(&name);
                let t = Instant::now();
                let result = async {
                    let response = api.request(reqwest::Method::POST, "/v1/sequences").multipart(form).send().await?;
                    let status = response.status().as_u16();
                    let bytes = response.bytes().await?;
                    Ok::<_, reqwest::Error>((status, bytes))
                }
                .await;
                let seconds = t.elapsed().as_secs_f64();
                let (error, stored) = match result {
                    Err(e) => (Some(format!("upload {i}: {e}")), None),
                    Ok((status, bytes)) => match serde_json::from_slice::<Value>(&bytes) {
                        Ok(v) if status == 201 => {
                            let stored = v["id"].as_str().map(|id| (id.to_string(), name.clone()));
                            (upload.mismatch(&name, &v).map(|m| format!("upload {i}: {m}")), stored)
                        }
                        _ => (Some(format!("upload {i}: status {status}: {}", String::from_utf8_lossy(&bytes))), None),
                    },
                };
                (Outcome { seconds, error }, stored)
            })
        })
        .collect();

    let permits = Arc::new(tokio::sync::Semaphore::new(config.query_concurrency.max(1)));
    let queries: Vec<_> = (0..config.queries)
        .map(|i| {
            let (api, bodies, permits) = (api.clone(), bodies.clone(), permits.clone());
            let path = format!("/v1/jobs/{queried}/query");
            tokio::spawn(async move {
                let _permit = permits.acquire_owned().await.expect("the semaphore is never closed");
                let (body, expected) = &bodies[i % bodies.len()];
                let t = Instant::now();
                let result = async {
                    let response = api
                        .request(reqwest::Method::POST, &path)
                        .header(reqwest::header::CONTENT_TYPE, "application/json")
                        .body(body.clone())
                        .send()
                        .await?;
                    let status = response.status().as_u16();
                    Ok::<_, reqwest::Error>((status, response.bytes().await?))
                }
                .await;
                let seconds = t.elapsed().as_secs_f64();
                let error = match result {
                    Err(e) => Some(format!("query {i}: {e}")),
                    Ok((200, bytes)) if bytes == *expected => None,
                    Ok((200, _)) => Some(format!("query {i}: the answer differs from the same query's quiet answer")),
                    Ok((status, bytes)) => {
                        Some(format!("query {i}: status {status}: {}", String::from_utf8_lossy(&bytes)))
                    }
                };
                Outcome { seconds, error }
            })
        })
        .collect();

    let mut upload_outcomes = Vec::with_capacity(uploads.len());
    let mut uploaded = Vec::new();
    for task in uploads {
        let (outcome, stored) = task.await.context("an upload task failed")?;
        upload_outcomes.push(outcome);
        uploaded.extend(stored);
    }
    let mut query_outcomes = Vec::with_capacity(queries.len());
    for task in queries {
        query_outcomes.push(task.await.context("a query task failed")?);
    }
    let wall_s = load_started.elapsed().as_secs_f64();
    let _ = stop.send(true);
    let mut not_running = watcher.await.context("the fit watcher failed")?;
    let end = api.job(&fit_job).await?;
    if end["status"] != "running" {
        not_running.push(format!("status {} after the load", end["status"]));
    }
    let last_iteration = end["progress"]["iteration"].as_u64().unwrap_or(0) as usize;

    // The stored sequences read back as uploaded (not timed: after the load).
    let mut errors: Vec<String> =
        upload_outcomes.iter().chain(&query_outcomes).filter_map(|o| o.error.clone()).collect();
    for (id, name) in &uploaded {
        let path = format!("/v1/sequences/{id}");
        match api.json(api.request(reqwest::Method::GET, &path), 200, "reading an upload back").await {
            Ok(v) => errors.extend(upload.mismatch(name, &v).map(|m| format!("sequence {id} read back: {m}"))),
            Err(e) => errors.push(format!("sequence {id}: {e:#}")),
        }
    }

    // The long fit has served its purpose.
    let cancel = api.request(reqwest::Method::POST, &format!("/v1/jobs/{fit_job}/cancel")).send().await?;
    if cancel.status().as_u16() == 202 {
        api.wait_job(&fit_job, config.setup_timeout, |j| j["status"] == "cancelled").await.ok();
    }

    Ok(LoadReport {
        uploads: Latency::of(&upload_outcomes),
        upload_bytes: upload.bytes(),
        upload_points_per_frame: upload.points_per_frame.clone(),
        queries: Latency::of(&query_outcomes),
        query_points,
        query_times: config.query_times.max(1),
        query_concurrency: config.query_concurrency.max(1),
        errors: errors.len(),
        error_samples: errors.into_iter().take(10).collect(),
        fit_job,
        fit_running_throughout: not_running.is_empty(),
        fit_not_running_seen: not_running,
        fit_iterations: [first_iteration, last_iteration],
        wall_s,
    })
}

/// Starts the service on a free loopback port over `dir`, on its own runtime so that the
/// driver's tasks do not share its executor threads (as if it were another process).
fn start_local(dir: PathBuf, threads_per_job: usize) -> anyhow::Result<(tokio::runtime::Runtime, Service)> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("mbnt-http")
        .build()
        .context("starting the service's runtime")?;
    let config = ServiceConfig {
        bind: "127.0.0.1:0".parse().expect("a valid address"),
        data_dir: dir,
        store: Default::default(),
        worker: Default::default(),
        workers: 1,
        threads_per_job,
        api_token: None,
        limits: Limits::default(),
    };
    let service = runtime.block_on(Service::start(config, Arc::new(CoreFitter)))?;
    Ok((runtime, service))
}

/// Prints the report.
fn print(report: &LoadReport) {
    let line = |what: &str, l: &Latency| {
        println!(
            "{what:<8} {:>5} sent  {:>3} errors  p50 {:>8.1} ms  p99 {:>8.1} ms  max {:>8.1} ms",
            l.count, l.errors, l.p50_ms, l.p99_ms, l.max_ms
        );
    };
    line("uploads", &report.uploads);
    line("queries", &report.queries);
    println!(
        "upload: {} frames, {:?} points, {:.1} MB; query: {} points x {} times, {} in flight",
        report.upload_points_per_frame.len(),
        report.upload_points_per_frame,
        report.upload_bytes as f64 / 1e6,
        report.query_points,
        report.query_times,
        report.query_concurrency
    );
    println!(
        "errors {}; load {:.1} s; fit {} running throughout: {} (iterations {} -> {})",
        report.errors,
        report.wall_s,
        report.fit_job,
        report.fit_running_throughout,
        report.fit_iterations[0],
        report.fit_iterations[1]
    );
    for e in &report.error_samples {
        println!("  error: {e}");
    }
    for s in &report.fit_not_running_seen {
        println!("  fit not running: {s}");
    }
}

/// Runs `mbnt bench-load`: fails when a request failed or the fit did not run throughout.
pub fn run(args: LoadArgs) -> anyhow::Result<()> {
    let defaults = LoadConfig::default();
    let config = LoadConfig {
        uploads: args.uploads,
        upload_sequence: SimParams { seed: args.seed, frames: args.upload_frames, ..defaults.upload_sequence.clone() },
        queries: args.queries,
        query_concurrency: args.query_concurrency,
        query_points: args.query_points,
        query_times: args.query_times,
        fit_sequence: SimParams { seed: args.seed, frames: args.fit_frames, ..defaults.fit_sequence.clone() },
        fit_params: json!({ "seed": args.seed, "iterations": args.fit_iterations, "validation_patience": 0 }),
        ..defaults
    };
    ensure!(config.upload_sequence.frames >= 2 && config.fit_sequence.frames >= 2, "sequences need 2 frames or more");
    let local = match &args.target {
        Some(_) => None,
        None => {
            let dir = std::env::temp_dir().join(format!("mbnt-load-{}", uuid::Uuid::new_v4().simple()));
            let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
            let (runtime, service) = start_local(dir.clone(), args.threads_per_job.unwrap_or(cores).max(1))?;
            Some((runtime, service, dir))
        }
    };
    let base = match (&args.target, &local) {
        (Some(t), _) => t.clone(),
        (None, Some((_, service, _))) => format!("http://{}", service.addr()),
        (None, None) => unreachable!("a local service is started when there is no target"),
    };
    let token = std::env::var("MBNT_API_TOKEN").ok().filter(|t| !t.is_empty() && args.target.is_some());
    eprintln!("load against {base}");
    let client = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("mbnt-load")
        .build()
        .context("starting the driver's runtime")?;
    let report = client.block_on(drive(&base, token.as_deref(), &config));
    drop(client);
    if let Some((runtime, service, dir)) = local {
        runtime.block_on(service.shutdown())?;
        drop(runtime);
        let _ = std::fs::remove_dir_all(&dir);
    }
    let report = report?;
    print(&report);
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_vec_pretty(&report)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    ensure!(report.errors == 0, "{} requests failed", report.errors);
    ensure!(
        report.fit_running_throughout,
        "the fit did not run throughout the load: {:?}",
        report.fit_not_running_seen
    );
    Ok(())
}
