//! Crash consistency of the real `mbnt serve` process: it is killed with SIGKILL (no shutdown
//! code runs) during an upload, during a fit and during a label export, restarted on the same
//! data directory, and then must show no half-written sequence, keep every finished result, and
//! run the interrupted job again.
//!
//! The kill points are found by observing the service (its data directory and its persisted
//! job state), never by sleeping for a guessed time; every wait has a generous timeout.

mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, mpsc};
use std::time::Duration;

use common::{frames, npy_bytes, temp_dir, tiny_params};
use mbnt::store::files::{frame_file_name, read_frame};
use serde_json::{Value, json};

/// How long any awaited state may take on a loaded 2-core CI machine.
const TIMEOUT: Duration = Duration::from_secs(120);

/// A `mbnt serve` child process on a free port over a given data directory.
struct Server {
    child: Child,
    base: String,
    client: reqwest::Client,
    /// Everything the process wrote to stderr (its log), for failure messages.
    log: Arc<Mutex<Vec<String>>>,
}

/// Removes ANSI colour sequences (`ESC [ ... letter`) from a log line.
fn strip_ansi(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut chars = line.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for d in chars.by_ref() {
                if d.is_ascii_alphabetic() {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

impl Server {
    /// Starts `mbnt serve` on port 0 (the kernel picks a free one) and waits for the log line
    /// that names the bound address.
    async fn start(dir: &Path) -> Self {
        match Self::try_start(dir).await {
            Ok(server) => server,
            Err(log) => panic!("mbnt serve exited at startup; log:\n{log}"),
        }
    }

    /// As [`Server::start`], or the log of a process that exited before it listened.
    async fn try_start(dir: &Path) -> Result<Self, String> {
        let mut child = Command::new(env!("CARGO_BIN_EXE_mbnt"))
            .arg("serve")
            .args(["--bind", "127.0.0.1:0", "--workers", "1", "--threads-per-job", "1"])
            .arg("--data-dir")
            .arg(dir)
            .env("RUST_LOG", "info")
            .env("NO_COLOR", "1")
            .env_remove("MBNT_API_TOKEN")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("mbnt serve starts");
        let stderr = child.stderr.take().expect("piped stderr");
        let log = Arc::new(Mutex::new(Vec::new()));
        let (addr_tx, addr_rx) = mpsc::channel();
        // Reads the log to its end, also after the address is known: a full pipe would block
        // the server's logging. The sender drops at the end of the log, i.e. when it exits.
        let sink = log.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                let line = strip_ansi(&line);
                if line.contains("mbnt service listening")
                    && let Some(addr) = line.split_whitespace().find_map(|w| w.strip_prefix("addr="))
                {
                    let _ = addr_tx.send(addr.to_string());
                }
                sink.lock().unwrap().push(line);
            }
        });
        let addr = tokio::task::spawn_blocking(move || addr_rx.recv_timeout(TIMEOUT)).await.unwrap();
        let text = || log.lock().unwrap().join("\n");
        match addr {
            Ok(addr) => Ok(Self { child, base: format!("http://{addr}"), client: reqwest::Client::new(), log }),
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                let status = child.wait().expect("exited process reaped");
                Err(format!("{status}\n{}", text()))
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {
                let _ = child.kill();
                let _ = child.wait();
                panic!("mbnt serve did not report its address; log:\n{}", text());
            }
        }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    fn log(&self) -> String {
        self.log.lock().unwrap().join("\n")
    }

    /// Sends SIGKILL and reaps the process: no destructor, no shutdown hook, no flush runs.
    fn kill(mut self) {
        self.child.kill().expect("SIGKILL sent");
        self.child.wait().expect("killed process reaped");
    }

    async fn get(&self, path: &str) -> (u16, Value) {
        let response = self.client.get(self.url(path)).send().await.expect("request sent");
        let status = response.status().as_u16();
        let bytes = response.bytes().await.expect("body read");
        (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
    }

    async fn post(&self, path: &str, body: &Value) -> (u16, Value) {
        let response = self.client.post(self.url(path)).json(body).send().await.expect("request sent");
        let status = response.status().as_u16();
        (status, response.json().await.unwrap_or(Value::Null))
    }

    /// Uploads `frames` as JSON under `name`; returns the sequence id.
    async fn upload(&self, name: &str, frames: &[Vec<[f32; 3]>]) -> String {
        let (status, body) = self.post("/v1/sequences", &json!({ "name": name, "frames": frames })).await;
        assert_eq!(status, 201, "{body}");
        body["id"].as_str().unwrap().to_string()
    }

    /// Queues a fit; returns the job id.
    async fn submit(&self, sequence: &str, method: &str, params: Value) -> String {
        let (status, body) =
            self.post("/v1/jobs", &json!({ "sequence_id": sequence, "method": method, "params": params })).await;
        assert_eq!(status, 202, "{body}");
        body["id"].as_str().unwrap().to_string()
    }

    async fn job(&self, id: &str) -> Value {
        let (status, job) = self.get(&format!("/v1/jobs/{id}")).await;
        assert_eq!(status, 200, "{job}");
        job
    }

    /// Polls the job until `done(job)` holds; fails on a failed job or after [`TIMEOUT`].
    async fn wait_job(&self, id: &str, done: impl Fn(&Value) -> bool) -> Value {
        let deadline = tokio::time::Instant::now() + TIMEOUT;
        loop {
            let job = self.job(id).await;
            if done(&job) {
                return job;
            }
            assert_ne!(job["status"], "failed", "{job}\nlog:\n{}", self.log());
            assert!(tokio::time::Instant::now() < deadline, "job never reached the expected state: {job}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Reads the job's server-sent events until a `progress` event whose job satisfies
    /// `wanted`, and returns that job; fails when the job ends first or after [`TIMEOUT`].
    async fn wait_event(&self, id: &str, wanted: impl Fn(&Value) -> bool) -> Value {
        let mut response = self.client.get(self.url(&format!("/v1/jobs/{id}/events"))).send().await.unwrap();
        assert_eq!(response.status(), 200);
        let deadline = tokio::time::Instant::now() + TIMEOUT;
        let mut buffer = String::new();
        loop {
            let chunk = tokio::time::timeout_at(deadline, response.chunk())
                .await
                .unwrap_or_else(|_| panic!("no wanted event in time; log:\n{}", self.log()))
                .expect("event stream read")
                .expect("the event stream ended early");
            buffer.push_str(&String::from_utf8_lossy(&chunk));
            while let Some(end) = buffer.find("\n\n") {
                let block: String = buffer.drain(..end + 2).collect();
                let field = |name: &str| block.lines().find_map(|l| l.strip_prefix(name)).map(str::trim);
                let Some(data) = field("data:") else { continue };
                let job: Value = serde_json::from_str(data).expect("event data is JSON");
                assert_ne!(field("event:"), Some("end"), "the job ended before the wanted event: {job}");
                if wanted(&job) {
                    return job;
                }
            }
        }
    }

    async fn wait_status(&self, id: &str, status: &str) -> Value {
        self.wait_job(id, |j| j["status"] == status).await
    }

    /// The names and ids of every listed sequence.
    async fn sequences(&self) -> BTreeMap<String, Value> {
        let (status, list) = self.get("/v1/sequences?limit=1000").await;
        assert_eq!(status, 200, "{list}");
        list["sequences"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| (s["id"].as_str().unwrap().to_string(), s.clone()))
            .collect()
    }

    /// A query of a succeeded job: frame 1's first points at every frame time.
    async fn query(&self, job: &str) -> Value {
        let (status, answer) = self
            .post(&format!("/v1/jobs/{job}/query"), &json!({ "frame": 1, "indices": [0, 1, 2, 3], "times": [0, 1, 2] }))
            .await;
        assert_eq!(status, 200, "{answer}");
        answer
    }

    async fn labels(&self, job: &str) -> Vec<u8> {
        let response =
            self.client.get(self.url(&format!("/v1/jobs/{job}/labels?format=npz"))).send().await.expect("sent");
        assert_eq!(response.status(), 200);
        response.bytes().await.expect("labels read").to_vec()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        // A failed assertion must not leave a server running.
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Names of the entries of `dir` (sorted).
fn entries(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect()
}

/// Polls `check` every 10 ms until it holds; panics with `what` after [`TIMEOUT`].
async fn wait_until(what: &str, mut check: impl FnMut() -> bool) {
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while !check() {
        assert!(tokio::time::Instant::now() < deadline, "timed out waiting until {what}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Asserts that the stored frames of sequence `id` are exactly `expected`, read with the
/// store's own frame reader (which refuses a truncated or foreign file).
fn assert_frames(dir: &Path, id: &str, expected: &[Vec<[f32; 3]>]) {
    let seq_dir = dir.join("sequences").join(id);
    let stored: BTreeSet<String> = entries(&seq_dir);
    let wanted: BTreeSet<String> = (0..expected.len()).map(frame_file_name).collect();
    assert_eq!(stored, wanted, "files of sequence {id}");
    for (k, frame) in expected.iter().enumerate() {
        let points = read_frame(&seq_dir.join(frame_file_name(k))).unwrap_or_else(|e| panic!("{id} frame {k}: {e}"));
        assert_eq!(&points, frame, "sequence {id} frame {k}");
    }
}

/// After a restart: the crash's scratch files are gone and only listed sequences have frames.
fn assert_no_leftovers(dir: &Path, listed: &BTreeMap<String, Value>) {
    assert_eq!(entries(&dir.join("staging")), BTreeSet::new(), "staged uploads survived a restart");
    assert_eq!(entries(&dir.join("tmp")), BTreeSet::new(), "upload scratch files survived a restart");
    let on_disk = entries(&dir.join("sequences"));
    let listed: BTreeSet<String> = listed.keys().cloned().collect();
    assert_eq!(on_disk, listed, "sequence directories on disk vs sequences listed");
}

const BOUNDARY: &str = "crash-test-boundary";

/// The start of one multipart part (its boundary line and headers).
fn part_head(name: &str, file_name: Option<&str>, content_type: &str) -> Vec<u8> {
    let file = file_name.map(|f| format!("; filename=\"{f}\"")).unwrap_or_default();
    format!(
        "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{name}\"{file}\r\nContent-Type: {content_type}\r\n\r\n"
    )
    .into_bytes()
}

/// Starts a POST of a body that arrives in the chunks sent on the returned channel (and ends
/// when it is dropped); the handle resolves to the answer's status, or an error.
fn streamed_post(
    s: &Server,
    path: &str,
    content_type: &str,
) -> (tokio::sync::mpsc::Sender<Vec<u8>>, tokio::task::JoinHandle<Result<u16, reqwest::Error>>) {
    let (tx, rx) = tokio::sync::mpsc::channel::<Vec<u8>>(16);
    let body = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|chunk| (Ok::<_, std::io::Error>(chunk), rx))
    });
    let request =
        s.client.post(s.url(path)).header("content-type", content_type).body(reqwest::Body::wrap_stream(body));
    let handle = tokio::spawn(async move { request.send().await.map(|r| r.status().as_u16()) });
    (tx, handle)
}

/// SIGKILL while two uploads are half received (a multipart one with three of its frames
/// already stored and a fourth streaming, and a JSON one streaming to its scratch file): after
/// the restart only the sequence completed before the crash exists, with its frames intact,
/// and nothing of the two interrupted uploads is left, listed or readable.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_upload_killed_midway_leaves_no_sequence_and_completed_ones_survive() {
    let dir = temp_dir();
    let s = Server::start(&dir).await;
    let kept_frames = frames(3, 200);
    let kept = s.upload("kept", &kept_frames).await;
    let (_, kept_before) = s.get(&format!("/v1/sequences/{kept}")).await;

    // Multipart: meta, three whole frames, then the first half of a fourth, and no end.
    let (multipart, multipart_done) =
        streamed_post(&s, "/v1/sequences", &format!("multipart/form-data; boundary={BOUNDARY}"));
    let mut head = part_head("meta", None, "application/json");
    head.extend_from_slice(br#"{"name":"interrupted-multipart","timestamps":[0,1,2,3]}"#);
    head.extend_from_slice(b"\r\n");
    let upload_frames = frames(4, 200);
    for (k, frame) in upload_frames.iter().take(3).enumerate() {
        head.extend(part_head("frame", Some(&format!("{k:06}.npy")), "application/octet-stream"));
        head.extend(npy_bytes(frame));
        head.extend_from_slice(b"\r\n");
    }
    head.extend(part_head("frame", Some("000003.npy"), "application/octet-stream"));
    let last = npy_bytes(&upload_frames[3]);
    head.extend_from_slice(&last[..last.len() / 2]);
    multipart.send(head).await.unwrap();

    // JSON: the first part of a body, and no end.
    let (json_upload, json_done) = streamed_post(&s, "/v1/sequences", "application/json");
    let text = json!({ "name": "interrupted-json", "frames": frames(3, 200) }).to_string();
    json_upload.send(text.as_bytes()[..text.len() / 2].to_vec()).await.unwrap();

    // The critical moment: frames of the multipart upload are on disk under staging/, and both
    // uploads have a scratch file under tmp/ (the fourth frame's part, the JSON body).
    let staging = dir.join("staging");
    wait_until("three frames are staged and both uploads are streaming", || {
        let staged: Vec<String> = entries(&staging).into_iter().collect();
        staged.len() == 1
            && staging.join(&staged[0]).join(frame_file_name(2)).exists()
            && entries(&dir.join("tmp")).len() == 2
    })
    .await;
    let staged_id = entries(&staging).into_iter().next().unwrap();
    // While uploading, the sequence is not visible.
    assert_eq!(s.sequences().await.keys().cloned().collect::<Vec<_>>(), vec![kept.clone()]);
    assert_eq!(s.get(&format!("/v1/sequences/{staged_id}")).await.0, 404);
    s.kill();
    drop((multipart, json_upload));
    for done in [multipart_done, json_done] {
        let answer = tokio::time::timeout(TIMEOUT, done).await.expect("client gives up").unwrap();
        assert!(answer.is_err(), "an interrupted upload was answered: {answer:?}");
    }
    // The crash did leave half-written state behind: the restart has something to recover.
    assert!(dir.join("staging").join(&staged_id).join(frame_file_name(2)).exists());

    let s = Server::start(&dir).await;
    let listed = s.sequences().await;
    assert_eq!(listed.keys().cloned().collect::<Vec<_>>(), vec![kept.clone()]);
    assert_eq!(s.get(&format!("/v1/sequences/{kept}")).await, (200, kept_before));
    assert_eq!(s.get(&format!("/v1/sequences/{staged_id}")).await.0, 404);
    assert_frames(&dir, &kept, &kept_frames);
    assert_no_leftovers(&dir, &listed);
    // The restarted service takes the same upload whole.
    let again = s.upload("after-restart", &upload_frames).await;
    assert_frames(&dir, &again, &upload_frames);
    s.kill();
    let _ = std::fs::remove_dir_all(&dir);
}

/// The frames of burst upload `n` (distinct per upload, so a mix-up shows).
fn burst_frames(n: usize) -> Vec<Vec<[f32; 3]>> {
    let mut f = frames(3, 40);
    for frame in &mut f {
        for p in frame.iter_mut() {
            p[2] += n as f32;
        }
    }
    f
}

/// SIGKILL at an arbitrary moment of a burst of concurrent uploads: whatever instant it hits
/// (mid-body, mid-frame, mid-commit), every sequence acknowledged before is there after the
/// restart, and every sequence listed is complete and holds exactly the frames sent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_of_uploads_killed_at_any_moment_keeps_every_sequence_whole_or_absent() {
    let dir = temp_dir();
    let s = Server::start(&dir).await;
    let acked = Arc::new(Mutex::new(BTreeMap::<String, usize>::new()));
    let client = s.client.clone();
    let url = s.url("/v1/sequences");
    let mut tasks = Vec::new();
    const CLIENTS: usize = 6;
    for c in 0..CLIENTS {
        let (client, url, acked) = (client.clone(), url.clone(), acked.clone());
        tasks.push(tokio::spawn(async move {
            for i in 0.. {
                let n = i * CLIENTS + c;
                // Alternate the two upload paths: multipart frame files and JSON.
                let request = if n.is_multiple_of(2) {
                    let mut form = reqwest::multipart::Form::new().part(
                        "meta",
                        reqwest::multipart::Part::text(json!({ "name": format!("burst-{n}") }).to_string())
                            .mime_str("application/json")
                            .unwrap(),
                    );
                    for frame in burst_frames(n) {
                        form =
                            form.part("frame", reqwest::multipart::Part::bytes(npy_bytes(&frame)).file_name("f.npy"));
                    }
                    client.post(&url).multipart(form)
                } else {
                    client.post(&url).json(&json!({ "name": format!("burst-{n}"), "frames": burst_frames(n) }))
                };
                let Ok(response) = request.send().await else { return };
                if response.status() != 201 {
                    return;
                }
                let Ok(body) = response.json::<Value>().await else { return };
                acked.lock().unwrap().insert(body["id"].as_str().unwrap().to_string(), n);
            }
        }));
    }
    wait_until("a dozen uploads are acknowledged", || acked.lock().unwrap().len() >= 12).await;
    s.kill();
    for task in tasks {
        tokio::time::timeout(TIMEOUT, task).await.expect("uploaders stop").unwrap();
    }
    let acked = acked.lock().unwrap().clone();

    let s = Server::start(&dir).await;
    let listed = s.sequences().await;
    for (id, n) in &acked {
        let seq = listed.get(id).unwrap_or_else(|| panic!("acknowledged upload {n} ({id}) was lost"));
        assert_eq!(seq["name"], format!("burst-{n}"));
    }
    for (id, seq) in &listed {
        // Listed but unacknowledged: committed just before the kill. Whole either way.
        let n: usize = seq["name"].as_str().unwrap().strip_prefix("burst-").unwrap().parse().unwrap();
        assert_eq!(seq["points_per_frame"], json!([40, 40, 40]), "{seq}");
        assert_frames(&dir, id, &burst_frames(n));
    }
    assert_no_leftovers(&dir, &listed);
    s.kill();
    let _ = std::fs::remove_dir_all(&dir);
}

/// Parameters of a fit that lasts about a second or more on small frames: a few hundred
/// iterations of a wider network, validated only at the end (so no early stop).
fn slow_params() -> Value {
    json!({ "iterations": 300, "validate_every": 300, "seed": 3, "hidden_width": 64, "hidden_layers": 3,
            "remove_ground": false, "dbscan_min_points": 5 })
}

/// SIGKILL while a fit runs (iterations done, a job queued behind it, a finished job beside
/// it): after the restart the interrupted job runs again and succeeds on its second attempt,
/// the queued one runs once, and the finished job keeps its model, its answers and its labels
/// byte for byte.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fit_killed_midway_runs_again_and_finished_results_are_kept() {
    let dir = temp_dir();
    let s = Server::start(&dir).await;
    let f = frames(3, 300);
    let seq = s.upload("fit", &f).await;
    let finished = s.submit(&seq, "ntp", tiny_params()).await;
    let finished_before = s.wait_status(&finished, "succeeded").await;
    let answer_before = s.query(&finished).await;
    let labels_before = s.labels(&finished).await;

    let interrupted = s.submit(&seq, "ntp", slow_params()).await;
    let queued = s.submit(&seq, "ntp", tiny_params()).await;
    // Mid-fit: the live progress stream (about every 100 ms) reports iterations done.
    let running =
        s.wait_event(&interrupted, |j| j["status"] == "running" && j["progress"]["iteration"].as_u64() > Some(0)).await;
    assert_eq!(running["attempts"], 1);
    assert_eq!(s.job(&queued).await["status"], "queued");
    s.kill();

    let s = Server::start(&dir).await;
    let again = s.wait_status(&interrupted, "succeeded").await;
    assert_eq!(again["attempts"], 2, "{again}");
    assert_eq!(again["progress"]["iteration"], again["progress"]["iterations"], "{again}");
    let later = s.wait_status(&queued, "succeeded").await;
    assert_eq!(later["attempts"], 1, "{later}");
    // The finished job is untouched: same record, same answers, same labels.
    assert_eq!(s.job(&finished).await, finished_before);
    assert_eq!(s.query(&finished).await, answer_before);
    assert_eq!(s.labels(&finished).await, labels_before);
    s.query(&interrupted).await;
    // Exactly the three models, no temporary file of an interrupted write.
    let models: BTreeSet<String> = [&finished, &interrupted, &queued].iter().map(|j| format!("{j}.mbnt")).collect();
    assert_eq!(entries(&dir.join("models")), models);
    s.kill();
    let _ = std::fs::remove_dir_all(&dir);
}

/// A second server started on a data directory in use is refused and changes nothing: its
/// start-up would otherwise re-queue the first one's running job (which that worker then
/// records as cancelled, or both run) and delete its uploads in progress.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_server_on_a_data_directory_in_use_is_refused() {
    let dir = temp_dir();
    let s = Server::start(&dir).await;
    let seq = s.upload("shared", &frames(3, 300)).await;
    // Long enough never to end during the test; the kill below stops it.
    let params = json!({ "iterations": 20_000, "validate_every": 20_000, "hidden_width": 64, "remove_ground": false });
    let job = s.submit(&seq, "ntp", params).await;
    s.wait_event(&job, |j| j["status"] == "running" && j["progress"]["iteration"].as_u64() > Some(0)).await;
    let (upload, upload_done) = streamed_post(&s, "/v1/sequences", "application/json");
    upload.send(br#"{"frames": [[[1, 2, 3]]"#.to_vec()).await.unwrap();
    wait_until("the upload streams to its scratch file", || entries(&dir.join("tmp")).len() == 1).await;

    let refused = Server::try_start(&dir).await.err().expect("a second server on the same data directory is refused");
    assert!(refused.contains("in use by another mbnt process"), "{refused}");
    let running = s.job(&job).await;
    assert_eq!((&running["status"], &running["attempts"]), (&json!("running"), &json!(1)), "{running}");
    assert_eq!(entries(&dir.join("tmp")).len(), 1, "the refused server removed an upload in progress");
    // The first server still works: the upload completes.
    upload.send(br#", [[4, 5, 6]]]}"#.to_vec()).await.unwrap();
    drop(upload);
    assert_eq!(upload_done.await.unwrap().unwrap(), 201);
    s.kill();
    let _ = std::fs::remove_dir_all(&dir);
}

/// SIGKILL while labels are being exported (one download partly received, another just asked
/// for): after the restart the job is still succeeded and exports the same labels, and no
/// export scratch file is left.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_label_export_killed_midway_loses_nothing() {
    let dir = temp_dir();
    let s = Server::start(&dir).await;
    // Large enough for the archive to take several reads (the server streams 64 KiB chunks).
    let seq = s.upload("labels", &frames(3, 20_000)).await;
    let job = s.submit(&seq, "ntp", tiny_params()).await;
    let before = s.wait_status(&job, "succeeded").await;
    let labels = s.labels(&job).await;
    assert_eq!(s.labels(&job).await, labels, "the export is not deterministic; the comparison below would be void");

    let url = s.url(&format!("/v1/jobs/{job}/labels?format=npz"));
    let mut response = s.client.get(&url).send().await.unwrap();
    assert_eq!(response.status(), 200);
    let total = response.content_length().expect("labels have a length");
    assert_eq!(total, labels.len() as u64);
    let first = response.chunk().await.unwrap().expect("a first chunk");
    assert!((first.len() as u64) < total, "the whole archive came in one chunk");
    let pending = tokio::spawn(s.client.get(&url).send());
    s.kill();
    // What the kernel had buffered may still arrive; the rest cannot.
    while let Ok(Some(_)) = response.chunk().await {}
    let _ = tokio::time::timeout(TIMEOUT, pending).await.expect("client gives up");

    let s = Server::start(&dir).await;
    assert_eq!(s.job(&job).await, before);
    assert_eq!(s.labels(&job).await, labels);
    assert_eq!(entries(&dir.join("tmp")), BTreeSet::new());
    assert_eq!(entries(&dir.join("models")), BTreeSet::from([format!("{job}.mbnt")]));
    s.kill();
    let _ = std::fs::remove_dir_all(&dir);
}

/// The helpers' own check: ANSI colour codes do not hide the address in a log line.
#[test]
fn the_listening_address_is_found_in_a_coloured_log_line() {
    let line = "\u{1b}[2m2026-01-01T00:00:00Z\u{1b}[0m \u{1b}[32m INFO\u{1b}[0m \u{1b}[2mmbnt::http\u{1b}[0m\u{1b}[2m:\u{1b}[0m mbnt service listening \u{1b}[3maddr\u{1b}[0m\u{1b}[2m=\u{1b}[0m127.0.0.1:4242";
    let plain = strip_ansi(line);
    assert_eq!(plain.split_whitespace().find_map(|w| w.strip_prefix("addr=")), Some("127.0.0.1:4242"));
}
