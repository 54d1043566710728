//! `/v1/jobs`: submitting fits, their state and live progress, cancelling, querying a
//! fitted model, and exporting scene-flow labels.

use std::convert::Infallible;
use std::time::Duration;

use axum::Json;
use axum::body::{Body, Bytes};
use axum::extract::{Path as UrlPath, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures_util::Stream;
use serde::{Deserialize, Serialize};
use uuid::Uuid;

use super::error::parse_json_body;
use super::sequences::is_json;
use super::strict::{Index, fit_params_object, present};
use super::{ApiError, AppState, list_limit, parse_id, result_unreadable, stored_read_error};
use crate::fit::{FitParams, Method};
use crate::geometry::Point;
use crate::geometry::rigid::Rigid;
use crate::io::labels::LabelsWriter;
use crate::jobs::JobQueue;
use crate::model::{LossRecord, QueryError};
use crate::store::{CancelOutcome, JobFilter, JobProgress, JobRecord, JobStatus, rfc3339};

/// A job as the API shows it.
#[derive(Debug, Serialize, PartialEq)]
pub struct JobView {
    id: String,
    sequence_id: String,
    method: &'static str,
    params: crate::fit::ValidFitParams,
    status: JobStatus,
    progress: JobProgress,
    error: Option<String>,
    cancel_requested: bool,
    attempts: u32,
    worker: Option<String>,
    lease_expires_at: Option<String>,
    resumed_from_iteration: Option<usize>,
    created_at: String,
    started_at: Option<String>,
    finished_at: Option<String>,
}

impl From<&JobRecord> for JobView {
    fn from(j: &JobRecord) -> Self {
        Self {
            id: j.id.to_string(),
            sequence_id: j.sequence_id.to_string(),
            method: j.method.name(),
            params: j.params.clone(),
            status: j.status,
            progress: j.progress.clone(),
            error: j.error.clone(),
            cancel_requested: j.cancel_requested,
            attempts: j.attempts,
            worker: j.worker.clone(),
            lease_expires_at: j.lease_expires_at_ms.map(rfc3339),
            resumed_from_iteration: j.progress.resumed_from_iteration,
            created_at: rfc3339(j.created_at_ms),
            started_at: j.started_at_ms.map(rfc3339),
            finished_at: j.finished_at_ms.map(rfc3339),
        }
    }
}

/// Reads a JSON body of a non-upload route (content type checked, size capped).
async fn json_body<T: serde::de::DeserializeOwned + Send + 'static>(
    state: &AppState,
    request: Request,
) -> Result<T, ApiError> {
    let content_type = request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    if !is_json(&content_type.to_ascii_lowercase()) {
        return Err(ApiError::UnsupportedMediaType(format!(
            "content type {:?}: send application/json",
            if content_type.is_empty() { "(none)" } else { content_type }
        )));
    }
    let limit = state.limits().max_json_bytes;
    let bytes = axum::body::to_bytes(request.into_body(), limit).await.map_err(|e| {
        let limited = std::error::Error::source(&e).is_some_and(|s| s.is::<http_body_util::LengthLimitError>());
        if limited || e.to_string().contains("length limit") {
            ApiError::TooLarge(format!("the JSON body exceeds {limit} bytes (server option --max-json-bytes)"))
        } else {
            ApiError::BadRequest(format!("could not read the body: {e}"))
        }
    })?;
    parse_json_body(bytes).await
}

/// Body of `POST /v1/jobs`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CreateJob {
    sequence_id: String,
    #[serde(default, deserialize_with = "present")]
    method: Option<String>,
    #[serde(default, deserialize_with = "present")]
    params: Option<serde_json::Value>,
}

/// `POST /v1/jobs`: 202 with the queued job and its `Location`.
pub async fn create(State(state): State<AppState>, request: Request) -> Result<Response, ApiError> {
    let body: CreateJob = json_body(&state, request).await?;
    let method = match body.method.as_deref() {
        None => Method::default(),
        Some(m) => m.parse::<Method>().map_err(|e| ApiError::invalid("method", e))?,
    };
    let params: FitParams = match body.params {
        None => FitParams::default(),
        Some(value) => serde_json::from_value(fit_params_object(value)?.into()).map_err(|e| {
            let message = e.to_string();
            let name = message
                .split("unknown field `")
                .nth(1)
                .and_then(|r| r.split('`').next())
                .map(|n| format!("params.{n}"))
                .unwrap_or_else(|| "params".to_string());
            ApiError::invalid(name, format!("params: {message}"))
        })?,
    };
    let params = params.check(method).map_err(|e| ApiError::invalid(format!("params.{}", e.name), e.to_string()))?;
    let max = state.limits().max_iterations;
    if params.iterations > max {
        return Err(ApiError::LimitExceeded {
            limit: "max_iterations",
            detail: format!("params.iterations is {}; this server allows at most {max}", params.iterations),
        });
    }
    let sequence_id = Uuid::parse_str(&body.sequence_id)
        .map_err(|_| ApiError::invalid("sequence_id", format!("no sequence with id {:?}", body.sequence_id)))?;
    let job = JobQueue::new_job(sequence_id, method, params);
    let queue = state.inner.queue.clone();
    let stored = job.clone();
    tokio::task::spawn_blocking(move || queue.submit(&stored)).await?.map_err(|e| match e {
        crate::store::StoreError::Missing(_) => {
            ApiError::invalid("sequence_id", format!("no sequence with id {:?}", body.sequence_id))
        }
        other => other.into(),
    })?;
    let location = format!("/v1/jobs/{}", job.id);
    Ok((StatusCode::ACCEPTED, [(header::LOCATION, location)], Json(JobView::from(&job))).into_response())
}

/// Query string of `GET /v1/jobs`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    status: Option<String>,
    sequence_id: Option<String>,
    limit: Option<usize>,
}

/// `GET /v1/jobs?status=&sequence_id=&limit=`.
pub async fn list(
    State(state): State<AppState>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let Query(query) = query.map_err(|e| ApiError::Invalid { parameter: None, detail: e.body_text() })?;
    let status =
        query.status.map(|s| s.parse::<JobStatus>()).transpose().map_err(|e| ApiError::invalid("status", e))?;
    let sequence_id = query
        .sequence_id
        .map(|s| Uuid::parse_str(&s))
        .transpose()
        .map_err(|e| ApiError::invalid("sequence_id", format!("not a sequence id: {e}")))?;
    let filter = JobFilter { status, sequence_id, limit: list_limit(query.limit)? };
    let jobs = state.blocking(move |s| Ok(s.list_jobs(&filter)?)).await?;
    let views: Vec<JobView> = jobs.iter().map(JobView::from).collect();
    Ok(Json(serde_json::json!({ "jobs": views })))
}

async fn load_job(state: &AppState, id: &str) -> Result<JobRecord, ApiError> {
    let uuid = parse_id("job", id)?;
    state
        .blocking(move |s| Ok(s.get_job(uuid)?))
        .await?
        .ok_or_else(|| ApiError::NotFound { what: "job", id: id.to_string() })
}

/// `GET /v1/jobs/{id}`.
pub async fn show(State(state): State<AppState>, UrlPath(id): UrlPath<String>) -> Result<Json<JobView>, ApiError> {
    Ok(Json(JobView::from(&load_job(&state, &id).await?)))
}

/// `POST /v1/jobs/{id}/cancel`: 202 with the job (cancelled, or flagged while its fit stops).
pub async fn cancel(State(state): State<AppState>, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let uuid = parse_id("job", &id)?;
    let queue = state.inner.queue.clone();
    match tokio::task::spawn_blocking(move || queue.cancel(uuid)).await?? {
        CancelOutcome::Accepted(job) => Ok((StatusCode::ACCEPTED, Json(JobView::from(&job))).into_response()),
        CancelOutcome::NotFound => Err(ApiError::NotFound { what: "job", id }),
        CancelOutcome::AlreadyFinished(job) => {
            Err(ApiError::Conflict(format!("the job has already {}", job.status.as_str())))
        }
    }
}

/// How often a progress stream re-reads the store (for fits run by another process).
const EVENTS_POLL: Duration = Duration::from_secs(2);

/// `GET /v1/jobs/{id}/events`: server-sent events, `progress` with the job on every change,
/// then `end` with the job once it is succeeded, failed or cancelled.
pub async fn events(
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let uuid = parse_id("job", &id)?;
    // Subscribe before reading, so that no report in between is missed.
    let rx = state.inner.queue.subscribe(uuid);
    let first = load_job(&state, &id).await?;
    struct Feed {
        state: AppState,
        id: Uuid,
        rx: tokio::sync::watch::Receiver<Option<JobRecord>>,
        shutdown: tokio::sync::watch::Receiver<bool>,
        next: Option<JobRecord>,
        last: Option<JobView>,
        done: bool,
    }
    let shutdown = state.inner.shutdown.clone();
    let feed = Feed { state, id: uuid, rx, shutdown, next: Some(first), last: None, done: false };
    let stream = futures_util::stream::unfold(feed, |mut feed| async move {
        loop {
            if feed.done {
                return None;
            }
            if let Some(job) = feed.next.take() {
                let view = JobView::from(&job);
                if feed.last.as_ref() == Some(&view) {
                    continue;
                }
                let terminal = job.status.is_terminal();
                let event = Event::default()
                    .event(if terminal { "end" } else { "progress" })
                    .json_data(&view)
                    .unwrap_or_else(|_| Event::default().event("error"));
                feed.last = Some(view);
                feed.done = terminal;
                return Some((Ok(event), feed));
            }
            let reread = tokio::select! {
                changed = feed.rx.changed() => match changed {
                    Ok(()) => {
                        feed.next = feed.rx.borrow_and_update().clone();
                        false
                    }
                    // The watcher ended (its job reached a terminal state): the store has it.
                    Err(_) => {
                        feed.rx = feed.state.inner.queue.subscribe(feed.id);
                        true
                    }
                },
                // Fits run by another process sharing the store only show in the store.
                () = tokio::time::sleep(EVENTS_POLL) => true,
                _ = feed.shutdown.wait_for(|s| *s) => return None,
            };
            if reread {
                let id = feed.id;
                match feed.state.blocking(move |s| Ok(s.get_job(id)?)).await {
                    Ok(Some(job)) => feed.next = Some(job),
                    // Deleted with its sequence, or the store failed: end the stream.
                    _ => return None,
                }
            }
        }
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// Body of `POST /v1/jobs/{id}/query`: either a frame's points or arbitrary points.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct QueryBody {
    #[serde(default, deserialize_with = "present")]
    frame: Option<Index>,
    #[serde(default, deserialize_with = "present")]
    indices: Option<Vec<Index>>,
    #[serde(default, deserialize_with = "present")]
    points: Option<Vec<[f64; 3]>>,
    #[serde(default, deserialize_with = "present")]
    t: Option<f64>,
    times: Vec<f64>,
}

/// `{"positions": [[[x, y, z] per time] per point]}` written straight from the flat answer.
struct Positions<'a> {
    flat: &'a [Point],
    times: usize,
}

impl Serialize for Positions<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        struct Rows<'a>(&'a [Point], usize);
        impl Serialize for Rows<'_> {
            fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.collect_seq(self.0.chunks(self.1.max(1)))
            }
        }
        let mut map = s.serialize_map(Some(1))?;
        map.serialize_entry("positions", &Rows(self.flat, self.times))?;
        map.end()
    }
}

/// `POST /v1/jobs/{id}/query`: positions of points at the given times (succeeded jobs only).
pub async fn query(
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    request: Request,
) -> Result<Response, ApiError> {
    let job = load_job(&state, &id).await?;
    let body: QueryBody = json_body(&state, request).await?;
    if job.status != JobStatus::Succeeded {
        return Err(not_succeeded(&job, "only a succeeded job can be queried"));
    }
    let limits = state.limits().clone();
    if body.times.is_empty() {
        return Err(ApiError::invalid("times", "give at least one time"));
    }
    if body.times.len() > limits.max_query_times {
        return Err(ApiError::LimitExceeded {
            limit: "max_query_times",
            detail: format!("{} times; at most {} per query", body.times.len(), limits.max_query_times),
        });
    }
    let check_points = |n: usize| -> Result<(), ApiError> {
        if n > limits.max_query_points {
            return Err(ApiError::LimitExceeded {
                limit: "max_query_points",
                detail: format!("{n} points; at most {} per query", limits.max_query_points),
            });
        }
        if n.saturating_mul(body.times.len()) > limits.max_query_positions {
            return Err(ApiError::LimitExceeded {
                limit: "max_query_positions",
                detail: format!(
                    "{n} points x {} times; at most {} positions per query",
                    body.times.len(),
                    limits.max_query_positions
                ),
            });
        }
        Ok(())
    };
    let model = state.model(job.id).await?;
    let (points, t_obs) = match (body.frame, body.points) {
        (Some(Index(k)), None) => {
            if body.t.is_some() {
                return Err(ApiError::invalid(
                    "t",
                    "`t` goes with `points`; a frame's points are observed at its time",
                ));
            }
            let frames = model.time_axis().frames();
            if k >= frames {
                return Err(ApiError::invalid(
                    "frame",
                    format!("frame {k} does not exist (the sequence has {frames})"),
                ));
            }
            if let Some(indices) = &body.indices {
                check_points(indices.len())?;
            }
            let (sequence, job_id) = (job.sequence_id, job.id);
            let frame = state
                .blocking(move |s| {
                    s.read_frame(sequence, k).map_err(|e| stored_read_error(s, job_id, "the sequence's frames", e))
                })
                .await?;
            let points = match body.indices {
                None => {
                    check_points(frame.len())?;
                    frame
                }
                Some(indices) => {
                    if let Some(Index(bad)) = indices.iter().find(|i| i.0 >= frame.len()) {
                        return Err(ApiError::invalid(
                            "indices",
                            format!("index {bad} is out of range (frame {k} has {} points)", frame.len()),
                        ));
                    }
                    indices.iter().map(|i| frame[i.0]).collect()
                }
            };
            (points, model.time_axis().frame_time(k))
        }
        (None, Some(points)) => {
            if body.indices.is_some() {
                return Err(ApiError::invalid("indices", "`indices` goes with `frame`"));
            }
            let t =
                body.t.ok_or_else(|| ApiError::invalid("t", "give the time `t` at which the points were observed"))?;
            check_points(points.len())?;
            let points: Vec<Point> = points.iter().map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]).collect();
            (points, t)
        }
        _ => {
            return Err(ApiError::invalid("frame", "give either `frame` (and optional `indices`) or `points` and `t`"));
        }
    };
    let times = body.times;
    let store = state.store();
    let json = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
        let flat = model.positions(&points, t_obs, &times).map_err(|e| match e {
            QueryError::CorruptWindow { .. } => unreadable_window(&*store, job.id, &e),
            QueryError::NonFinitePoint { .. } => ApiError::invalid("points", e.to_string()),
            QueryError::TimeOutOfRange { time, .. } if time == t_obs && !times.contains(&time) => {
                ApiError::invalid("t", e.to_string())
            }
            QueryError::TimeOutOfRange { .. } => ApiError::invalid("times", e.to_string()),
        })?;
        serde_json::to_vec(&Positions { flat: &flat, times: times.len() })
            .map_err(|e| ApiError::Internal(anyhow::anyhow!("serialising positions: {e}")))
    })
    .await??;
    Ok(([(header::CONTENT_TYPE, HeaderValue::from_static("application/json"))], json).into_response())
}

/// A window of the succeeded job `job`'s stitched model that cannot be read (found when a query
/// first decodes it, `e`): the stored result is unreadable, the job is failed
/// ([`result_unreadable`]). Blocking.
fn unreadable_window(store: &dyn crate::store::Store, job: Uuid, e: &QueryError) -> ApiError {
    result_unreadable(store, job, format!("the model file cannot be read: {e}"))
}

/// The 409 for a job that has not succeeded: its status, its error when it failed (e.g. a
/// stored result found unreadable), then `rule`.
fn not_succeeded(job: &JobRecord, rule: &str) -> ApiError {
    match &job.error {
        Some(error) if job.status == JobStatus::Failed => {
            ApiError::Conflict(format!("the job is failed ({error}); {rule}"))
        }
        _ => ApiError::Conflict(format!("the job is {}; {rule}", job.status.as_str())),
    }
}

/// The job `id` when it has succeeded; 409 naming `what` exists only then otherwise.
async fn succeeded_job(state: &AppState, id: &str, what: &str) -> Result<JobRecord, ApiError> {
    let job = load_job(state, id).await?;
    if job.status != JobStatus::Succeeded {
        return Err(not_succeeded(&job, &format!("{what} exist only for a succeeded job")));
    }
    Ok(job)
}

/// One moving body as `GET /v1/jobs/{id}/objects` lists it.
#[derive(Debug, Serialize)]
struct ObjectView {
    id: u32,
    frames_seen: Vec<usize>,
    points_per_frame: Vec<usize>,
    /// Per frame, body-to-world (row-major 4 x 4; world: frame 0's sensor coordinates).
    poses: Vec<[f64; 16]>,
    /// Per frame, body-to-sensor of that frame's sweep (row-major 4 x 4).
    poses_sensor: Vec<[f64; 16]>,
    extent: ExtentView,
}

/// A body's box in its own coordinates (origin at its centre, x along its travel, z up).
#[derive(Debug, Serialize)]
struct ExtentView {
    min_m: [f32; 3],
    max_m: [f32; 3],
    size_m: [f32; 3],
}

/// The answer of `GET /v1/jobs/{id}/objects`.
#[derive(Debug, Serialize)]
struct ObjectsView {
    job_id: String,
    frames: usize,
    times: Vec<f64>,
    /// Whether the model is a scene model with moving bodies (`moving_bodies` and poses).
    moving_bodies: bool,
    objects: Vec<ObjectView>,
}

/// `GET /v1/jobs/{id}/objects`: the moving bodies of a succeeded job's scene model, each one
/// object over the sequence with its pose at every frame time, its extent and its points per
/// frame.
pub async fn objects(State(state): State<AppState>, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let job = succeeded_job(&state, &id, "objects").await?;
    let model = state.model(job.id).await?;
    let axis = model.time_axis();
    let identity = Rigid::identity();
    let view = ObjectsView {
        job_id: job.id.to_string(),
        frames: axis.frames(),
        times: (0..axis.frames()).map(|k| axis.frame_time(k)).collect(),
        moving_bodies: job.params.moving_bodies && model.frame_poses().is_some(),
        objects: model
            .bodies()
            .iter()
            .map(|b| ObjectView {
                id: b.id,
                frames_seen: b.frames_seen(),
                points_per_frame: b.member_counts.clone(),
                poses: b.poses.iter().map(Rigid::to_row_major).collect(),
                poses_sensor: b
                    .poses
                    .iter()
                    .enumerate()
                    .map(|(k, pose)| {
                        let to_fit = model.frame_poses().map_or(&identity, |p| &p[k]);
                        to_fit.inverse().compose(pose).to_row_major()
                    })
                    .collect(),
                extent: ExtentView {
                    min_m: b.extent_min_m,
                    max_m: b.extent_max_m,
                    size_m: std::array::from_fn(|c| b.extent_max_m[c] - b.extent_min_m[c]),
                },
            })
            .collect(),
    };
    Ok(Json(view).into_response())
}

/// The answer of `GET /v1/jobs/{id}/losses`.
#[derive(Debug, Serialize)]
struct LossesView<'a> {
    job_id: String,
    /// Optimiser iterations run (summed over pairs or windows).
    iterations: usize,
    /// The iteration, numbered as in `losses`, whose validation pass selected the checkpoint.
    best_iteration: Option<usize>,
    best_validation_loss: Option<f64>,
    losses: &'a [LossRecord],
}

/// `GET /v1/jobs/{id}/losses`: the loss curve of a succeeded fit, as its report recorded it
/// (a running fit's latest loss is in its progress and events).
pub async fn losses(State(state): State<AppState>, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let job = succeeded_job(&state, &id, "loss curves").await?;
    let model = state.model(job.id).await?;
    let report = model.report();
    let view = LossesView {
        job_id: job.id.to_string(),
        iterations: report.iterations,
        // The report counts the loop's iterations from 0; the curve counts them done, from 1
        // (the validation of loop iteration k is measured before its update, in record k + 1).
        best_iteration: report.best_iteration.map(|k| k + 1),
        best_validation_loss: report.best_validation_loss,
        losses: &report.losses,
    };
    Ok(Json(view).into_response())
}

/// The sensor poses a fit worked with, as `GET /v1/jobs/{id}/poses` shows them.
#[derive(Debug, Serialize)]
pub struct JobPoses {
    job_id: String,
    /// True when the fit's odometry estimated them, false when they were uploaded.
    estimated: bool,
    /// Sensor-to-world, row-major 4 x 4, one per frame.
    poses: Vec<[f64; 16]>,
}

/// `GET /v1/jobs/{id}/poses`: the sensor-to-world poses of a succeeded fit, estimated by its
/// odometry or uploaded with the sequence; 409 when it worked without poses.
pub async fn poses(State(state): State<AppState>, UrlPath(id): UrlPath<String>) -> Result<Json<JobPoses>, ApiError> {
    let job = succeeded_job(&state, &id, "poses").await?;
    let model = state.model(job.id).await?;
    let job_id = job.id.to_string();
    if let Some(poses) = &model.report().estimated_poses {
        return Ok(Json(JobPoses { job_id, estimated: true, poses: poses.clone() }));
    }
    // Without an estimate, the fit used the uploaded poses exactly when it had them and was
    // allowed to (`fit::fit_coordinates`).
    if job.params.use_poses {
        let sequence_id = job.sequence_id;
        let record = state
            .blocking(move |s| Ok(s.get_sequence(sequence_id)?))
            .await?
            .ok_or_else(|| ApiError::Conflict("the job's sequence has been deleted".into()))?;
        if let Some(poses) = record.poses {
            return Ok(Json(JobPoses { job_id, estimated: false, poses }));
        }
    }
    Err(ApiError::Conflict(
        "the fit worked without poses, each frame in its own sensor coordinates: the sequence has none and \
         odometry did not estimate them (parameter `odometry` off, `use_poses` false, or the odometry could not \
         register the frames)"
            .into(),
    ))
}

/// Query string of `GET /v1/jobs/{id}/labels`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabelsQuery {
    format: Option<String>,
}

/// `GET /v1/jobs/{id}/labels?format=npz|av2`: scene flow of every frame's points to the next.
pub async fn labels(
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    query: Result<Query<LabelsQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(query) = query.map_err(|e| ApiError::Invalid { parameter: None, detail: e.body_text() })?;
    let job = load_job(&state, &id).await?;
    let format = query.format.unwrap_or_else(|| "npz".to_string());
    if format != "npz" && format != "av2" {
        return Err(ApiError::invalid("format", format!("unknown format {format:?} (expected npz or av2)")));
    }
    if format == "av2" && !cfg!(feature = "av2") {
        return Err(ApiError::NotImplemented("this build has no av2 export (cargo feature `av2`)".into()));
    }
    if job.status != JobStatus::Succeeded {
        return Err(not_succeeded(&job, "labels exist only for a succeeded job"));
    }
    let model = state.model(job.id).await?;
    let tmp_dir = state.inner.tmp_dir.clone();
    let as_npz = format == "npz";
    let store = state.store();
    // Build the archive in a temporary file (it can be large), then stream it.
    let file = tokio::task::spawn_blocking(move || -> Result<std::fs::File, ApiError> {
        let record = store
            .get_sequence(job.sequence_id)?
            .ok_or_else(|| ApiError::Conflict("the job's sequence has been deleted".into()))?;
        let read_frame = |k: usize| {
            store.read_frame(record.id, k).map_err(|e| stored_read_error(&*store, job.id, "the sequence's frames", e))
        };
        // The stored frames are finite and their times in range: only a damaged window of a
        // stitched model fails a label query.
        let query_error = |e: QueryError| match e {
            QueryError::CorruptWindow { .. } => unreadable_window(&*store, job.id, &e),
            _ => ApiError::Internal(anyhow::anyhow!("labelling the stored frames: {e}")),
        };
        let path = tmp_dir.join(format!("{}.labels", Uuid::new_v4().simple()));
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| ApiError::Internal(anyhow::anyhow!("creating a labels file: {e}")))?;
        // Unlinked at once: the open handle keeps the data until the response is sent.
        let _ = std::fs::remove_file(&path);
        let w = std::io::BufWriter::new(file);
        let write_error = |e: crate::io::WriteError| ApiError::Internal(anyhow::anyhow!("writing labels: {e}"));
        let frames = record.frames();
        // One frame at a time, in either format: a long log's labels never hold more than a
        // frame (its points, flow and object ids).
        let write_frames = |labels: &mut dyn LabelsWriter| -> Result<(), ApiError> {
            for k in 0..frames {
                let points = read_frame(k)?;
                let flow =
                    (k + 1 < frames).then(|| model.frame_scene_flow(k, &points)).transpose().map_err(query_error)?;
                let object_ids = model.frame_object_ids(k, &points).map_err(query_error)?;
                labels.frame(flow.as_deref(), &object_ids).map_err(write_error)?;
            }
            Ok(())
        };
        let written = if as_npz {
            let mut labels = crate::io::labels::LabelsNpzWriter::new(w);
            write_frames(&mut labels)?;
            let axis = model.time_axis();
            let timestamps: Vec<f64> = (0..axis.frames()).map(|k| axis.frame_time(k)).collect();
            labels.finish(&timestamps)
        } else {
            write_av2(w, write_frames)?
        };
        let mut file = written
            .map_err(write_error)?
            .into_inner()
            .map_err(|e| ApiError::Internal(anyhow::anyhow!("writing labels: {}", e.error())))?;
        std::io::Seek::seek(&mut file, std::io::SeekFrom::Start(0))
            .map_err(|e| ApiError::Internal(anyhow::anyhow!("rewinding labels: {e}")))?;
        Ok(file)
    })
    .await??;
    let len = file.metadata().map(|m| m.len()).ok();
    let stream = futures_util::stream::unfold(tokio::fs::File::from_std(file), |mut f| async move {
        use tokio::io::AsyncReadExt;
        let mut buf = vec![0u8; 1 << 16];
        match f.read(&mut buf).await {
            Ok(0) => None,
            Ok(n) => {
                buf.truncate(n);
                Some((Ok::<_, std::io::Error>(Bytes::from(buf)), f))
            }
            Err(e) => Some((Err(e), f)),
        }
    });
    let (content_type, extension) =
        if as_npz { ("application/octet-stream", "npz") } else { ("application/zip", "zip") };
    let mut headers = HeaderMap::new();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"labels-{id}.{extension}\"")) {
        headers.insert(header::CONTENT_DISPOSITION, v);
    }
    if let Some(len) = len {
        headers.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    }
    Ok((headers, Body::from_stream(stream)).into_response())
}

/// The labels in the Argoverse 2 layout: `write_frames` writes every frame into the archive.
#[cfg(feature = "av2")]
fn write_av2<W: std::io::Write + std::io::Seek>(
    w: W,
    write_frames: impl FnOnce(&mut dyn LabelsWriter) -> Result<(), ApiError>,
) -> Result<Result<W, crate::io::WriteError>, ApiError> {
    let mut labels = crate::io::labels::LabelsAv2Writer::new(w);
    write_frames(&mut labels)?;
    Ok(labels.finish())
}

/// A build without the `av2` feature refuses the format before the labels are written.
#[cfg(not(feature = "av2"))]
fn write_av2<W: std::io::Write + std::io::Seek>(
    _: W,
    _: impl FnOnce(&mut dyn LabelsWriter) -> Result<(), ApiError>,
) -> Result<Result<W, crate::io::WriteError>, ApiError> {
    Err(ApiError::NotImplemented("this build has no av2 export (cargo feature `av2`)".into()))
}
