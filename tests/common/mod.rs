//! Helpers of the API tests: a service on a real port over a temporary data directory, a
//! client that checks every JSON answer against `openapi.yaml`, synthetic frames and frame
//! files, and a slow fitter for jobs that must still be running when the test acts.

#![allow(dead_code)]

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use mbnt::fit::{FitError, LossTerms, Method, Progress, Sequence, ValidFitParams};
use mbnt::http::{Limits, Service, ServiceConfig};
use mbnt::jobs::{CoreFitter, Fitter};
use mbnt::model::FittedModel;
use serde_json::{Value, json};

/// Reports `steps` iterations of `step` each (stopping on `Break`), then runs the real fit.
pub struct SlowFitter {
    pub steps: usize,
    pub step: Duration,
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
                loss: LossTerms { chamfer: 1.0 / iteration as f64, ..LossTerms::default() },
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

/// A running service and a client for it.
pub struct TestServer {
    pub service: Option<Service>,
    pub base: String,
    pub client: reqwest::Client,
    pub token: Option<String>,
    pub spec: Spec,
    dir: PathBuf,
    owns_dir: bool,
}

/// Options of [`TestServer::start_with`].
pub struct Options {
    pub limits: Limits,
    pub token: Option<String>,
    pub fitter: Arc<dyn Fitter>,
    pub workers: usize,
    pub dir: Option<PathBuf>,
}

impl Default for Options {
    fn default() -> Self {
        Self { limits: Limits::default(), token: None, fitter: Arc::new(CoreFitter), workers: 1, dir: None }
    }
}

pub fn temp_dir() -> PathBuf {
    std::env::temp_dir().join(format!("mbnt-api-{}", uuid::Uuid::new_v4()))
}

impl TestServer {
    pub async fn start() -> Self {
        Self::start_with(Options::default()).await
    }

    pub async fn start_with(options: Options) -> Self {
        let owns_dir = options.dir.is_none();
        let dir = options.dir.unwrap_or_else(temp_dir);
        let config = ServiceConfig {
            bind: "127.0.0.1:0".parse().unwrap(),
            data_dir: dir.clone(),
            store: Default::default(),
            worker: Default::default(),
            workers: options.workers,
            threads_per_job: 1,
            api_token: options.token.clone(),
            limits: options.limits,
        };
        let service = Service::start(config, options.fitter).await.expect("service starts");
        let base = format!("http://{}", service.addr());
        Self {
            service: Some(service),
            base,
            client: reqwest::Client::new(),
            token: options.token,
            spec: Spec::load(),
            dir,
            owns_dir,
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Stops the service, keeping the data directory.
    pub async fn stop(mut self) -> PathBuf {
        self.owns_dir = false;
        self.service.take().unwrap().shutdown().await.expect("clean shutdown");
        self.dir.clone()
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    pub fn request(&self, method: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let r = self.client.request(method, self.url(path));
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    /// Sends `request` for the route `template`, checks the answer against the OpenAPI
    /// document (documented status, media type, schema) and returns status and JSON body
    /// (`Null` for non-JSON bodies).
    pub async fn send(&self, method: &str, template: &str, request: reqwest::RequestBuilder) -> (u16, Value) {
        let response = request.send().await.expect("request sent");
        let status = response.status().as_u16();
        let content_type = response
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .split(';')
            .next()
            .unwrap()
            .to_string();
        let bytes = response.bytes().await.expect("body read");
        let body = if content_type.ends_with("json") {
            serde_json::from_slice(&bytes)
                .unwrap_or_else(|e| panic!("{method} {template}: bad JSON ({e}): {}", String::from_utf8_lossy(&bytes)))
        } else {
            Value::Null
        };
        if status >= 400 {
            assert_eq!(content_type, "application/problem+json", "{method} {template} -> {status}: {body}");
        }
        self.spec.check_response(method, template, status, &content_type, &body);
        (status, body)
    }

    pub async fn get(&self, template: &str, path: &str) -> (u16, Value) {
        self.send("GET", template, self.request(reqwest::Method::GET, path)).await
    }

    pub async fn post_json(&self, template: &str, path: &str, body: &Value) -> (u16, Value) {
        self.send("POST", template, self.request(reqwest::Method::POST, path).json(body)).await
    }

    /// Uploads `frames` as JSON; returns the sequence id.
    pub async fn upload(&self, frames: &[Vec<[f32; 3]>], timestamps: Option<Vec<f64>>) -> String {
        let (status, body) = self
            .post_json("/v1/sequences", "/v1/sequences", &json!({ "frames": frames, "timestamps": timestamps }))
            .await;
        assert_eq!(status, 201, "{body}");
        body["id"].as_str().unwrap().to_string()
    }

    /// Queues a small fit; returns the job id.
    pub async fn submit(&self, sequence: &str, method: &str) -> String {
        let (status, body) = self
            .post_json(
                "/v1/jobs",
                "/v1/jobs",
                &json!({ "sequence_id": sequence, "method": method, "params": tiny_params() }),
            )
            .await;
        assert_eq!(status, 202, "{body}");
        body["id"].as_str().unwrap().to_string()
    }

    /// Polls the job until `done(job)` holds (at most `timeout`).
    pub async fn wait_job(&self, id: &str, timeout: Duration, done: impl Fn(&Value) -> bool) -> Value {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            let (status, job) = self.get("/v1/jobs/{id}", &format!("/v1/jobs/{id}")).await;
            assert_eq!(status, 200, "{job}");
            if done(&job) {
                return job;
            }
            assert!(tokio::time::Instant::now() < deadline, "job never reached the expected state: {job}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    pub async fn wait_status(&self, id: &str, status: &str) -> Value {
        self.wait_job(id, Duration::from_secs(60), |j| j["status"] == status).await
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if self.owns_dir {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// Fit parameters that keep a fit to a fraction of a second.
pub fn tiny_params() -> Value {
    json!({ "iterations": 5, "seed": 7, "hidden_width": 16, "hidden_layers": 2, "remove_ground": false,
            "dbscan_min_points": 5, "validate_every": 2 })
}

/// `t` frames of `n` points: a static wall (x = 10) and a box moving 0.5 m per frame along
/// y, half the points each, deterministic.
pub fn frames(t: usize, n: usize) -> Vec<Vec<[f32; 3]>> {
    (0..t)
        .map(|k| {
            (0..n)
                .map(|i| {
                    let u = (i % 20) as f32 * 0.1;
                    let v = (i / 20) as f32 * 0.1;
                    if i % 2 == 0 {
                        [10.0, u - 1.0, v]
                    } else {
                        [3.0 + u * 0.5, -2.0 + k as f32 * 0.5 + v * 0.3, 0.5 + u * 0.2]
                    }
                })
                .collect()
        })
        .collect()
}

/// A `.npy` float32 (N, 3) file.
pub fn npy_bytes(points: &[[f32; 3]]) -> Vec<u8> {
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, 3), }}", points.len());
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    for p in points {
        for c in p {
            out.extend(c.to_le_bytes());
        }
    }
    out
}

/// An ASCII PLY file.
pub fn ply_bytes(points: &[[f32; 3]]) -> Vec<u8> {
    let mut s = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
        points.len()
    );
    for p in points {
        s.push_str(&format!("{} {} {}\n", p[0], p[1], p[2]));
    }
    s.into_bytes()
}

/// The OpenAPI document as JSON, with a small schema checker (type, required, properties,
/// additionalProperties: false, items, enum, min/max, minItems/maxItems, oneOf, $ref).
pub struct Spec {
    pub doc: Value,
}

impl Spec {
    pub fn load() -> Self {
        let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi.yaml")).unwrap();
        let yaml: serde_yaml::Value = serde_yaml::from_str(&text).expect("openapi.yaml parses");
        Self { doc: serde_json::to_value(yaml).unwrap() }
    }

    fn resolve<'a>(&'a self, v: &'a Value) -> &'a Value {
        match v.get("$ref").and_then(Value::as_str) {
            Some(r) => {
                let pointer = r.strip_prefix('#').expect("local $ref");
                self.resolve(self.doc.pointer(pointer).unwrap_or_else(|| panic!("dangling $ref {r}")))
            }
            None => v,
        }
    }

    /// Every (method, path) the document describes.
    pub fn operations(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        for (path, item) in self.doc["paths"].as_object().unwrap() {
            for method in ["get", "post", "put", "patch", "delete"] {
                if item.get(method).is_some() {
                    out.push((method.to_uppercase(), path.clone()));
                }
            }
        }
        out.sort();
        out
    }

    pub fn check_response(&self, method: &str, template: &str, status: u16, content_type: &str, body: &Value) {
        let op = &self.doc["paths"][template][method.to_lowercase()];
        assert!(op.is_object(), "{method} {template} is not documented");
        let response = op["responses"]
            .get(status.to_string())
            .unwrap_or_else(|| panic!("{method} {template}: status {status} is not documented (body {body})"));
        let response = self.resolve(response);
        if status == 204 {
            return;
        }
        let content = &response["content"];
        let media = content.get(content_type).unwrap_or_else(|| {
            panic!("{method} {template} -> {status}: media type {content_type:?} is not documented")
        });
        if content_type.ends_with("json") {
            let mut errors = Vec::new();
            self.validate(&media["schema"], body, "$", &mut errors);
            assert!(errors.is_empty(), "{method} {template} -> {status}: {errors:?}\nbody: {body}");
        }
    }

    pub fn validate(&self, schema: &Value, v: &Value, at: &str, errors: &mut Vec<String>) {
        let schema = self.resolve(schema);
        if let Some(options) = schema.get("oneOf").and_then(Value::as_array) {
            let matching = options
                .iter()
                .filter(|o| {
                    let mut e = Vec::new();
                    self.validate(o, v, at, &mut e);
                    e.is_empty()
                })
                .count();
            if matching != 1 {
                errors.push(format!("{at}: matches {matching} of the oneOf options"));
            }
            return;
        }
        if let Some(t) = schema.get("type") {
            let types: Vec<&str> = match t {
                Value::String(s) => vec![s.as_str()],
                Value::Array(a) => a.iter().filter_map(Value::as_str).collect(),
                _ => vec![],
            };
            let ok = types.iter().any(|t| match *t {
                "null" => v.is_null(),
                "object" => v.is_object(),
                "array" => v.is_array(),
                "string" => v.is_string(),
                "boolean" => v.is_boolean(),
                "integer" => v.is_i64() || v.is_u64(),
                "number" => v.is_number(),
                _ => false,
            });
            if !ok {
                errors.push(format!("{at}: expected {types:?}, got {v}"));
                return;
            }
        }
        if let Some(e) = schema.get("enum").and_then(Value::as_array)
            && !e.contains(v)
        {
            errors.push(format!("{at}: {v} is not one of {e:?}"));
        }
        if let Some(n) = v.as_f64() {
            if let Some(min) = schema.get("minimum").and_then(Value::as_f64)
                && n < min
            {
                errors.push(format!("{at}: {n} < minimum {min}"));
            }
            if let Some(max) = schema.get("maximum").and_then(Value::as_f64)
                && n > max
            {
                errors.push(format!("{at}: {n} > maximum {max}"));
            }
        }
        if let Some(obj) = v.as_object() {
            for r in schema.get("required").and_then(Value::as_array).into_iter().flatten() {
                if !obj.contains_key(r.as_str().unwrap()) {
                    errors.push(format!("{at}: missing required {r}"));
                }
            }
            let props = schema.get("properties").and_then(Value::as_object);
            for (k, val) in obj {
                match props.and_then(|p| p.get(k)) {
                    Some(s) => self.validate(s, val, &format!("{at}.{k}"), errors),
                    None if schema.get("additionalProperties") == Some(&Value::Bool(false)) => {
                        errors.push(format!("{at}: unexpected property {k}"))
                    }
                    None => {}
                }
            }
        }
        if let Some(arr) = v.as_array() {
            if let Some(min) = schema.get("minItems").and_then(Value::as_u64)
                && (arr.len() as u64) < min
            {
                errors.push(format!("{at}: fewer than {min} items"));
            }
            if let Some(max) = schema.get("maxItems").and_then(Value::as_u64)
                && (arr.len() as u64) > max
            {
                errors.push(format!("{at}: more than {max} items"));
            }
            if let Some(items) = schema.get("items") {
                for (i, item) in arr.iter().enumerate() {
                    self.validate(items, item, &format!("{at}[{i}]"), errors);
                }
            }
        }
    }
}

/// Reads server-sent events until an `end` event (or `timeout`); returns (event, data) pairs.
pub async fn read_events(response: reqwest::Response, timeout: Duration) -> Vec<(String, Value)> {
    use futures_util::StreamExt;
    let mut stream = response.bytes_stream();
    let mut buffer = String::new();
    let mut events = Vec::new();
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let chunk = tokio::time::timeout_at(deadline, stream.next()).await.expect("events arrive in time");
        let Some(chunk) = chunk else { return events };
        buffer.push_str(&String::from_utf8_lossy(&chunk.expect("stream chunk")));
        while let Some(end) = buffer.find("\n\n") {
            let block: String = buffer.drain(..end + 2).collect();
            let mut name = String::from("message");
            let mut data = String::new();
            for line in block.lines() {
                if let Some(n) = line.strip_prefix("event:") {
                    name = n.trim().to_string();
                } else if let Some(d) = line.strip_prefix("data:") {
                    data.push_str(d.trim_start());
                }
            }
            if data.is_empty() {
                continue; // keep-alive comment
            }
            let done = name == "end";
            events.push((name, serde_json::from_str(&data).expect("event data is JSON")));
            if done {
                return events;
            }
        }
    }
}
