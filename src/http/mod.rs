//! The HTTP service: axum routes over the store and the job queue, problem+json errors,
//! bearer-token auth on `/v1`, body limits, server-sent progress, Prometheus metrics, the
//! OpenAPI document and the viewer page ([`viewer`]).
//!
//! [`Service::start`] opens the store, re-queues jobs a dead process left running, starts
//! the workers and binds the listener; [`Service::shutdown`] stops accepting, ends progress
//! streams, lets requests finish and stops the workers (their jobs go back to the queue).

mod drain;
pub mod error;
mod jobs;
pub mod metrics;
mod sequences;
pub mod strict;
pub mod viewer;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use anyhow::Context;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{HeaderValue, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{MethodRouter, delete, get, post};
use axum::{Json, Router};
use tokio::sync::watch;
use uuid::Uuid;

use crate::jobs::{Fitter, JobQueue, WorkerPool, WorkerSettings};
use crate::model::FittedModel;
use crate::store::{Store, StoreConfig, StoreError};
pub use error::ApiError;
pub use sequences::parse_meta_part;

/// The OpenAPI 3.1 document, served at `/openapi.yaml`.
pub const OPENAPI_YAML: &str = include_str!("../../openapi.yaml");

/// Configurable limits; every one answers with a problem naming it when exceeded.
#[derive(Debug, Clone, PartialEq)]
pub struct Limits {
    /// Largest request body, bytes (413 beyond; uploads included).
    pub max_body_bytes: u64,
    /// Largest JSON body of the non-upload routes (jobs, queries), bytes (413 beyond).
    pub max_json_bytes: usize,
    /// Most frames per sequence.
    pub max_frames: usize,
    /// Most points per frame.
    pub max_points_per_frame: usize,
    /// Most fit iterations a job may ask for.
    pub max_iterations: usize,
    /// Most points per query.
    pub max_query_points: usize,
    /// Most times per query.
    pub max_query_times: usize,
    /// Most positions (points x times) per query answer.
    pub max_query_positions: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_body_bytes: 1 << 30,
            max_json_bytes: 64 << 20,
            max_frames: 300,
            max_points_per_frame: 1_000_000,
            max_iterations: crate::fit::MAX_ITERATIONS,
            max_query_points: 100_000,
            max_query_times: 1_000,
            // ~30 bytes of JSON per position: answers stay below ~300 MB.
            max_query_positions: 10_000_000,
        }
    }
}

/// Everything the service needs to start.
#[derive(Debug, Clone)]
pub struct ServiceConfig {
    /// Address to listen on (port 0 picks a free one).
    pub bind: SocketAddr,
    /// Data directory (database, frames, models); created when absent. With a shared store,
    /// only its `tmp/` is used (upload parts).
    pub data_dir: PathBuf,
    /// The embedded store (default) or a fleet's shared one.
    pub store: StoreConfig,
    /// How the workers hold jobs and keep checkpoints.
    pub worker: WorkerSettings,
    /// Fits that may run at once in this process (0: none, the API alone).
    pub workers: usize,
    /// Threads of each fit.
    pub threads_per_job: usize,
    /// When set, every `/v1` route needs `Authorization: Bearer <token>`.
    pub api_token: Option<String>,
    /// Request limits.
    pub limits: Limits,
}

/// One route: its method and path (as in `openapi.yaml`) and its handler.
#[derive(Clone, Copy)]
pub struct Route {
    /// HTTP method, upper case.
    pub method: &'static str,
    /// Path template with `{param}` segments.
    pub path: &'static str,
    handler: fn() -> MethodRouter<AppState>,
}

impl std::fmt::Debug for Route {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}", self.method, self.path)
    }
}

/// Every route of the service. The router is built from this table, and a test checks it
/// against `openapi.yaml` in both directions.
pub const ROUTES: &[Route] = &[
    Route { method: "GET", path: "/healthz", handler: || get(healthz) },
    Route { method: "GET", path: "/metrics", handler: || get(metrics::render) },
    Route { method: "GET", path: "/openapi.yaml", handler: || get(openapi) },
    Route { method: "POST", path: "/v1/sequences", handler: || post(sequences::create) },
    Route { method: "GET", path: "/v1/sequences", handler: || get(sequences::list) },
    Route { method: "GET", path: "/v1/sequences/{id}", handler: || get(sequences::show) },
    Route { method: "DELETE", path: "/v1/sequences/{id}", handler: || delete(sequences::remove) },
    Route { method: "POST", path: "/v1/jobs", handler: || post(jobs::create) },
    Route { method: "GET", path: "/v1/jobs", handler: || get(jobs::list) },
    Route { method: "GET", path: "/v1/jobs/{id}", handler: || get(jobs::show) },
    Route { method: "POST", path: "/v1/jobs/{id}/cancel", handler: || post(jobs::cancel) },
    Route { method: "GET", path: "/v1/jobs/{id}/events", handler: || get(jobs::events) },
    Route { method: "POST", path: "/v1/jobs/{id}/query", handler: || post(jobs::query) },
    Route { method: "GET", path: "/v1/jobs/{id}/labels", handler: || get(jobs::labels) },
    Route { method: "GET", path: "/v1/jobs/{id}/objects", handler: || get(jobs::objects) },
    Route { method: "GET", path: "/v1/jobs/{id}/poses", handler: || get(jobs::poses) },
    Route { method: "GET", path: "/v1/jobs/{id}/losses", handler: || get(jobs::losses) },
];

/// Shared state of the handlers.
#[derive(Clone)]
pub struct AppState {
    inner: Arc<StateInner>,
}

struct StateInner {
    store: Arc<dyn Store>,
    queue: Arc<JobQueue>,
    limits: Limits,
    api_token: Option<String>,
    tmp_dir: PathBuf,
    metrics: metrics::RequestMetrics,
    /// Recently used models, most recent last (loading one parses the whole file).
    models: Mutex<Vec<(Uuid, Arc<FittedModel>)>>,
    /// Becomes true when the service stops: progress streams end.
    shutdown: watch::Receiver<bool>,
}

/// Models kept in memory for queries.
const MODEL_CACHE: usize = 4;

impl AppState {
    fn store(&self) -> Arc<dyn Store> {
        self.inner.store.clone()
    }

    fn limits(&self) -> &Limits {
        &self.inner.limits
    }

    /// Runs a blocking storage call off the executor.
    async fn blocking<T: Send + 'static>(
        &self,
        f: impl FnOnce(&dyn Store) -> Result<T, ApiError> + Send + 'static,
    ) -> Result<T, ApiError> {
        let store = self.store();
        tokio::task::spawn_blocking(move || f(&*store)).await?
    }

    /// The model of a succeeded job, from the cache or the store. A model file that is missing
    /// or cannot be read fails the job ([`result_unreadable`]).
    async fn model(&self, job: Uuid) -> Result<Arc<FittedModel>, ApiError> {
        if let Some(m) = self.cached_model(job) {
            return Ok(m);
        }
        let model = self
            .blocking(move |s| {
                let bytes = s.read_model(job).map_err(|e| stored_read_error(s, job, "the model file", e))?;
                FittedModel::from_bytes(&bytes)
                    .map_err(|e| result_unreadable(s, job, format!("the model file cannot be read: {e}")))
            })
            .await?;
        let model = Arc::new(model);
        let mut cache = self.inner.models.lock().unwrap_or_else(|p| p.into_inner());
        cache.retain(|(id, _)| *id != job);
        if cache.len() >= MODEL_CACHE {
            cache.remove(0);
        }
        cache.push((job, model.clone()));
        Ok(model)
    }

    fn cached_model(&self, job: Uuid) -> Option<Arc<FittedModel>> {
        let mut cache = self.inner.models.lock().unwrap_or_else(|p| p.into_inner());
        let at = cache.iter().position(|(id, _)| *id == job)?;
        let entry = cache.remove(at);
        let model = entry.1.clone();
        cache.push(entry);
        Some(model)
    }
}

/// Marks the succeeded job `job` failed because a stored file its answers need cannot be read
/// (`what`: which file, and why), and returns the problem that says so. Every later request
/// then sees a failed job with that reason, instead of an internal error on every query.
/// Blocking.
fn result_unreadable(store: &dyn Store, job: Uuid, what: String) -> ApiError {
    let error = format!("the stored result cannot be read: {what}");
    tracing::error!(job_id = %job, error, "a succeeded job's stored result is unreadable; the job is failed");
    if let Err(e) = store.fail_succeeded_job(job, &error) {
        tracing::error!(job_id = %job, error = %e, "could not mark the job failed");
    }
    ApiError::ResultUnreadable { job, detail: error }
}

/// Maps an error reading `file` (a stored file of the succeeded job `job`): a damaged or
/// missing file fails the job ([`result_unreadable`]); other failures (I/O, the database) may
/// pass, and stay internal errors. Blocking.
fn stored_read_error(store: &dyn Store, job: Uuid, file: &str, e: StoreError) -> ApiError {
    use std::io::ErrorKind;
    match &e {
        StoreError::Corrupt(_) | StoreError::Missing(_) => result_unreadable(store, job, format!("{file}: {e}")),
        StoreError::Io(io) if matches!(io.kind(), ErrorKind::InvalidData | ErrorKind::UnexpectedEof) => {
            result_unreadable(store, job, format!("{file}: {e}"))
        }
        _ => e.into(),
    }
}

/// Default and largest `limit` of the list routes.
const LIST_LIMIT_DEFAULT: usize = 100;
const LIST_LIMIT_MAX: usize = 1000;

/// The `limit` query parameter of the list routes: 1 to 1000, 100 when absent. A value out of
/// range is a 422 rather than silently clamped, as `openapi.yaml` declares the range.
fn list_limit(limit: Option<usize>) -> Result<usize, ApiError> {
    match limit {
        None => Ok(LIST_LIMIT_DEFAULT),
        Some(n) if (1..=LIST_LIMIT_MAX).contains(&n) => Ok(n),
        Some(n) => Err(ApiError::invalid("limit", format!("must be in [1, {LIST_LIMIT_MAX}], got {n}"))),
    }
}

/// Parses an id from the path; anything that is not a UUID names no resource (404).
fn parse_id(what: &'static str, id: &str) -> Result<Uuid, ApiError> {
    Uuid::parse_str(id).map_err(|_| ApiError::NotFound { what, id: id.to_string() })
}

async fn healthz(State(state): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    state.blocking(|s| s.ping().map_err(|e| ApiError::Unavailable(format!("storage does not answer: {e}")))).await?;
    Ok(Json(serde_json::json!({ "status": "ok" })))
}

async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, HeaderValue::from_static("application/yaml"))], OPENAPI_YAML).into_response()
}

/// Compares without an early exit, so response timing does not reveal a token's prefix.
fn tokens_match(given: &[u8], expected: &[u8]) -> bool {
    given.len() == expected.len() && given.iter().zip(expected).fold(0u8, |acc, (a, b)| acc | (a ^ b)) == 0
}

async fn require_token(State(state): State<AppState>, request: Request, next: Next) -> Result<Response, ApiError> {
    if let Some(expected) = &state.inner.api_token {
        let given = request
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim);
        if !given.is_some_and(|g| tokens_match(g.as_bytes(), expected.as_bytes())) {
            return Err(ApiError::Unauthorized);
        }
    }
    Ok(next.run(request).await)
}

/// Unknown paths: a plain 404 that [`error::problem_json`] turns into a problem.
async fn fallback() -> (axum::http::StatusCode, &'static str) {
    (axum::http::StatusCode::NOT_FOUND, "no such route")
}

/// The router over `state`: every route of [`ROUTES`], `/v1` behind the token, the viewer's
/// files ([`viewer::ASSETS`]), the body limit, request metrics and problem+json for every error.
pub fn router(state: AppState) -> Router {
    let mut open = Router::new();
    let mut v1 = Router::new();
    for route in ROUTES {
        if route.path.starts_with("/v1/") {
            v1 = v1.route(route.path, (route.handler)());
        } else {
            open = open.route(route.path, (route.handler)());
        }
    }
    let v1 = v1.route_layer(middleware::from_fn_with_state(state.clone(), require_token));
    let limit = usize::try_from(state.limits().max_body_bytes).unwrap_or(usize::MAX);
    open.merge(v1)
        .merge(viewer::routes())
        .fallback(fallback)
        .layer(DefaultBodyLimit::disable())
        .layer(tower_http::limit::RequestBodyLimitLayer::new(limit))
        .layer(middleware::from_fn(drain::drain_unread_body))
        .layer(middleware::from_fn_with_state(state.clone(), metrics::track))
        .layer(tower_http::catch_panic::CatchPanicLayer::new())
        .layer(middleware::from_fn(error::problem_json))
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(state)
}

/// A running service.
pub struct Service {
    addr: SocketAddr,
    stop: watch::Sender<bool>,
    server: tokio::task::JoinHandle<std::io::Result<()>>,
    workers: WorkerPool,
}

impl std::fmt::Debug for Service {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Service").field("addr", &self.addr).finish_non_exhaustive()
    }
}

impl Service {
    /// Opens the store, re-queues jobs left running by a dead process, starts the workers
    /// (fitting with `fitter`) and starts serving on `config.bind`.
    pub async fn start(config: ServiceConfig, fitter: Arc<dyn Fitter>) -> anyhow::Result<Self> {
        let (data_dir, store_config) = (config.data_dir.clone(), config.store.clone());
        let (store, tmp_dir) = tokio::task::spawn_blocking(move || crate::store::open(&data_dir, &store_config))
            .await?
            .context("opening the store")?;
        if config.workers == 0 {
            if config.store.database_url.is_none() {
                tracing::warn!(
                    "no workers and the embedded store: queued jobs wait until this service starts with workers \
                     (only a shared store, MBNT_DATABASE_URL, has `mbnt worker` processes)"
                );
            } else {
                tracing::info!("no workers here: `mbnt worker` processes of the shared store fit the jobs");
            }
        }
        let queue = JobQueue::with_settings(store.clone(), config.worker.clone());
        let workers = WorkerPool::start(queue.clone(), fitter, config.workers, config.threads_per_job.max(1))?;
        let (stop, stopped) = watch::channel(false);
        let state = AppState {
            inner: Arc::new(StateInner {
                store,
                queue,
                limits: config.limits.clone(),
                api_token: config.api_token.clone().filter(|t| !t.is_empty()),
                tmp_dir,
                metrics: metrics::RequestMetrics::default(),
                models: Mutex::default(),
                shutdown: stopped.clone(),
            }),
        };
        let listener = match tokio::net::TcpListener::bind(config.bind).await {
            Ok(l) => l,
            Err(e) => {
                tokio::task::spawn_blocking(move || workers.shutdown()).await?;
                return Err(e).with_context(|| format!("binding {}", config.bind));
            }
        };
        let addr = listener.local_addr()?;
        let app = router(state);
        let mut signal = stopped;
        let server = tokio::spawn(async move {
            axum::serve(listener, app)
                .with_graceful_shutdown(async move {
                    let _ = signal.wait_for(|s| *s).await;
                })
                .await
        });
        tracing::info!(%addr, "mbnt service listening");
        Ok(Self { addr, stop, server, workers })
    }

    /// The address the service listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Stops the service: no new connections, progress streams end, requests in flight
    /// finish, then running fits stop at their next iteration and go back to the queue.
    pub async fn shutdown(self) -> anyhow::Result<()> {
        let _ = self.stop.send(true);
        let served = self.server.await;
        let workers = self.workers;
        tokio::task::spawn_blocking(move || workers.shutdown()).await?;
        served?.context("serving")?;
        tracing::info!("mbnt service stopped");
        Ok(())
    }

    /// Serves until `signal` completes (or the server fails), then shuts down.
    pub async fn run_until(mut self, signal: impl std::future::Future<Output = ()>) -> anyhow::Result<()> {
        tokio::select! {
            () = signal => self.shutdown().await,
            served = &mut self.server => {
                let workers = self.workers;
                tokio::task::spawn_blocking(move || workers.shutdown()).await?;
                served?.context("serving")?;
                anyhow::bail!("the server stopped on its own")
            }
        }
    }
}
