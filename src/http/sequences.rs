//! `/v1/sequences`: uploads (multipart frame files or JSON), streamed to disk and parsed one
//! frame at a time; listing, reading and deleting.

use std::cell::RefCell;
use std::fmt;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};

use axum::Json;
use axum::extract::{FromRequest, Multipart, Path as UrlPath, Query, Request, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use futures_util::StreamExt;
use serde::de::{self, DeserializeSeed, MapAccess, SeqAccess, Visitor};
use serde::{Deserialize, Serialize};
use tokio::io::AsyncWriteExt;

use super::error::{json_error, parse_body_with, parse_json};
use super::{ApiError, AppState, Limits, list_limit, parse_id};
use crate::geometry::Point;
use crate::store::{DeleteOutcome, FrameSink, SequenceMeta, SequenceRecord, rfc3339};

/// Longest accepted sequence name, characters.
const MAX_NAME_CHARS: usize = 256;
/// Largest `meta` part of a multipart upload (300 poses of 16 numbers fit easily).
const MAX_META_BYTES: usize = 16 << 20;

/// A sequence as the API shows it.
#[derive(Debug, Serialize)]
pub struct SequenceView {
    id: String,
    name: Option<String>,
    frames: usize,
    points_per_frame: Vec<usize>,
    /// The time axis: the uploaded timestamps (s), or the frame indices.
    timestamps: Vec<f64>,
    /// `"s"` when timestamps were uploaded, `"frame"` when the axis is frame indices.
    time_unit: &'static str,
    has_poses: bool,
    created_at: String,
}

impl From<&SequenceRecord> for SequenceView {
    fn from(r: &SequenceRecord) -> Self {
        Self {
            id: r.id.to_string(),
            name: r.name.clone(),
            frames: r.frames(),
            points_per_frame: r.points_per_frame.clone(),
            timestamps: match &r.timestamps_s {
                Some(ts) => ts.clone(),
                None => (0..r.frames()).map(|k| k as f64).collect(),
            },
            time_unit: if r.timestamps_s.is_some() { "s" } else { "frame" },
            has_poses: r.poses.is_some(),
            created_at: rfc3339(r.created_at_ms),
        }
    }
}

/// A file in the temporary directory, removed when dropped.
struct TempFile(PathBuf);

impl TempFile {
    fn new(dir: &Path) -> Self {
        Self(dir.join(format!("{}.part", uuid::Uuid::new_v4().simple())))
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// Whether an error (or one of its causes) is the body limit being hit.
fn is_length_limit(e: &(dyn std::error::Error + 'static)) -> bool {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(err) = cur {
        if err.is::<http_body_util::LengthLimitError>() {
            return true;
        }
        cur = err.source();
    }
    false
}

fn too_large(limits: &Limits) -> ApiError {
    ApiError::TooLarge(format!(
        "the request body exceeds the limit of {} bytes (server option --max-body-bytes)",
        limits.max_body_bytes
    ))
}

fn body_error(e: axum::Error, limits: &Limits) -> ApiError {
    if is_length_limit(&e) { too_large(limits) } else { ApiError::BadRequest(format!("could not read the body: {e}")) }
}

/// `POST /v1/sequences`: multipart (frame files) or JSON (points), by content type.
pub async fn create(State(state): State<AppState>, request: Request) -> Result<Response, ApiError> {
    let content_type =
        request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    let record = if content_type.starts_with("multipart/form-data") {
        let multipart = Multipart::from_request(request, &state)
            .await
            .map_err(|e| ApiError::BadRequest(format!("malformed multipart request: {}", e.body_text())))?;
        create_multipart(&state, multipart).await?
    } else if is_json(&content_type) {
        create_json(&state, request).await?
    } else {
        return Err(ApiError::UnsupportedMediaType(format!(
            "content type {:?}: send multipart/form-data (frame files) or application/json (points)",
            if content_type.is_empty() { "(none)" } else { &content_type }
        )));
    };
    let location = format!("/v1/sequences/{}", record.id);
    Ok((StatusCode::CREATED, [(header::LOCATION, location)], Json(SequenceView::from(&record))).into_response())
}

/// Whether a content type is JSON (`application/json` or any `+json`).
pub fn is_json(content_type: &str) -> bool {
    let essence = content_type.split(';').next().unwrap_or("").trim();
    essence == "application/json" || (essence.starts_with("application/") && essence.ends_with("+json"))
}

/// Checks a frame before it is stored: not empty, not too many points, not too many frames.
fn check_frame(k: usize, points: &[Point], limits: &Limits) -> Result<(), ApiError> {
    if k >= limits.max_frames {
        return Err(ApiError::LimitExceeded {
            limit: "max_frames",
            detail: format!("a sequence may have at most {} frames", limits.max_frames),
        });
    }
    if points.is_empty() {
        return Err(ApiError::invalid("frames", format!("frame {k} has no points")));
    }
    if points.len() > limits.max_points_per_frame {
        return Err(ApiError::LimitExceeded {
            limit: "max_points_per_frame",
            detail: format!(
                "frame {k} has {} points; at most {} are allowed",
                points.len(),
                limits.max_points_per_frame
            ),
        });
    }
    if let Some(i) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        return Err(ApiError::invalid("frames", format!("frame {k}, point {i} has a non-finite coordinate")));
    }
    Ok(())
}

/// Checks the metadata against the frames and commits the sequence.
fn commit(sink: Box<dyn FrameSink>, meta: SequenceMeta) -> Result<SequenceRecord, ApiError> {
    let frames = sink.frames_written();
    if frames < 2 {
        return Err(ApiError::invalid("frames", format!("a sequence needs at least 2 frames, got {frames}")));
    }
    if let Some(name) = &meta.name
        && name.chars().count() > MAX_NAME_CHARS
    {
        return Err(ApiError::invalid("name", format!("at most {MAX_NAME_CHARS} characters")));
    }
    if let Some(ts) = &meta.timestamps_s {
        if ts.len() != frames {
            return Err(ApiError::invalid("timestamps", format!("{} timestamps for {frames} frames", ts.len())));
        }
        if ts.iter().any(|t| !t.is_finite()) || ts.windows(2).any(|w| w[1] <= w[0]) {
            return Err(ApiError::invalid("timestamps", "timestamps must be finite and strictly increasing"));
        }
    }
    if let Some(poses) = &meta.poses {
        if poses.len() != frames {
            return Err(ApiError::invalid("poses", format!("{} poses for {frames} frames", poses.len())));
        }
        if let Some(k) = poses.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
            return Err(ApiError::invalid("poses", format!("pose {k} has a non-finite entry")));
        }
    }
    Ok(sink.commit(meta)?)
}

/// The `meta` part of a multipart upload.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct MetaPart {
    name: Option<String>,
    timestamps: Option<Vec<f64>>,
    poses: Option<Vec<[f64; 16]>>,
}

/// Parses the JSON `meta` part of a multipart upload, `{"name"?, "timestamps"?, "poses"?}`
/// (poses as 16 numbers, row-major 4 x 4), into the sequence's metadata. Errors are the
/// upload's answers: a 422 naming `meta` (or the offending field) for wrong JSON, unknown
/// fields or wrong types. Checks against the frames (counts, finite and increasing times) come
/// when the sequence is committed, once the frames are known. Cost: O(len).
pub fn parse_meta_part(bytes: &[u8]) -> Result<SequenceMeta, ApiError> {
    let meta: MetaPart = parse_json(bytes).map_err(|e| match e {
        ApiError::Invalid { parameter, detail } => {
            ApiError::Invalid { parameter: parameter.or(Some("meta".into())), detail }
        }
        ApiError::BadRequest(d) => ApiError::Invalid { parameter: Some("meta".into()), detail: d },
        other => other,
    })?;
    Ok(SequenceMeta { name: meta.name, timestamps_s: meta.timestamps, poses: meta.poses })
}

async fn create_multipart(state: &AppState, mut multipart: Multipart) -> Result<SequenceRecord, ApiError> {
    let limits = state.limits().clone();
    let store = state.store();
    let mut sink = tokio::task::spawn_blocking(move || store.begin_sequence()).await??;
    let mut meta: Option<SequenceMeta> = None;
    let multipart_error = |e: axum::extract::multipart::MultipartError, limits: &Limits| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            too_large(limits)
        } else {
            ApiError::BadRequest(format!("malformed multipart body: {}", e.body_text()))
        }
    };
    while let Some(mut field) = multipart.next_field().await.map_err(|e| multipart_error(e, &limits))? {
        match field.name().unwrap_or("") {
            "meta" => {
                if meta.is_some() {
                    return Err(ApiError::invalid("meta", "the meta part may appear only once"));
                }
                let mut bytes = Vec::new();
                while let Some(chunk) = field.chunk().await.map_err(|e| multipart_error(e, &limits))? {
                    if bytes.len() + chunk.len() > MAX_META_BYTES {
                        return Err(ApiError::invalid("meta", format!("the meta part exceeds {MAX_META_BYTES} bytes")));
                    }
                    bytes.extend_from_slice(&chunk);
                }
                meta = Some(parse_body_with(bytes, parse_meta_part).await?);
            }
            "frame" => {
                let k = sink.frames_written();
                if k >= limits.max_frames {
                    return Err(ApiError::LimitExceeded {
                        limit: "max_frames",
                        detail: format!("a sequence may have at most {} frames", limits.max_frames),
                    });
                }
                let file_name = field.file_name().map(str::to_string);
                // Stream the part to disk; parse it once complete.
                let part = TempFile::new(&state.inner.tmp_dir);
                let mut file = tokio::fs::File::create(&part.0)
                    .await
                    .map_err(|e| ApiError::Internal(anyhow::anyhow!("creating an upload file: {e}")))?;
                while let Some(chunk) = field.chunk().await.map_err(|e| multipart_error(e, &limits))? {
                    file.write_all(&chunk)
                        .await
                        .map_err(|e| ApiError::Internal(anyhow::anyhow!("writing an upload file: {e}")))?;
                }
                file.flush().await.map_err(|e| ApiError::Internal(anyhow::anyhow!("writing an upload file: {e}")))?;
                drop(file);
                let limits = limits.clone();
                let (back, stored) = tokio::task::spawn_blocking(move || {
                    let stored = (|| {
                        let bytes = std::fs::read(&part.0)
                            .map_err(|e| ApiError::Internal(anyhow::anyhow!("reading an upload file: {e}")))?;
                        drop(part);
                        let points = crate::io::read_points(&bytes, file_name.as_deref()).map_err(|e| {
                            ApiError::invalid(
                                "frame",
                                format!("frame {k}{}: {e}", file_name.map(|n| format!(" ({n})")).unwrap_or_default()),
                            )
                        })?;
                        drop(bytes);
                        check_frame(k, &points, &limits)?;
                        sink.put_frame(&points)?;
                        Ok::<_, ApiError>(())
                    })();
                    (sink, stored)
                })
                .await?;
                sink = back;
                stored?;
            }
            other => {
                return Err(ApiError::invalid(
                    other.to_string(),
                    format!("unknown part {other:?}: expected `meta` and `frame` parts"),
                ));
            }
        }
    }
    let meta = meta.unwrap_or_default();
    tokio::task::spawn_blocking(move || commit(sink, meta)).await?
}

async fn create_json(state: &AppState, request: Request) -> Result<SequenceRecord, ApiError> {
    let limits = state.limits().clone();
    // Stream the body to disk, then parse it from there frame by frame.
    let upload = TempFile::new(&state.inner.tmp_dir);
    let mut file = tokio::fs::File::create(&upload.0)
        .await
        .map_err(|e| ApiError::Internal(anyhow::anyhow!("creating an upload file: {e}")))?;
    let mut body = request.into_body().into_data_stream();
    while let Some(chunk) = body.next().await {
        let chunk = chunk.map_err(|e| body_error(e, &limits))?;
        file.write_all(&chunk).await.map_err(|e| ApiError::Internal(anyhow::anyhow!("writing an upload: {e}")))?;
    }
    file.flush().await.map_err(|e| ApiError::Internal(anyhow::anyhow!("writing an upload: {e}")))?;
    drop(file);
    let store = state.store();
    tokio::task::spawn_blocking(move || {
        let mut sink = store.begin_sequence()?;
        let failure = RefCell::new(None);
        let reader = BufReader::new(
            std::fs::File::open(&upload.0)
                .map_err(|e| ApiError::Internal(anyhow::anyhow!("reading an upload: {e}")))?,
        );
        let mut de = serde_json::Deserializer::from_reader(reader);
        let parsed = UploadSeed { sink: &mut *sink, limits: &limits, failure: &failure }
            .deserialize(&mut de)
            .and_then(|meta| de.end().map(|()| meta));
        let meta = match parsed {
            Ok(meta) => meta,
            Err(e) => {
                return Err(failure
                    .into_inner()
                    .unwrap_or_else(|| json_error(&e, |l, c| file_text_near(&upload.0, l, c))));
            }
        };
        commit(sink, meta)
    })
    .await?
}

/// The text around (line, column) of a file, for [`json_error`].
fn file_text_near(path: &Path, line: usize, column: usize) -> String {
    let Ok(file) = std::fs::File::open(path) else { return String::new() };
    let mut reader = BufReader::new(file);
    let mut buf = Vec::new();
    for _ in 0..line {
        buf.clear();
        if reader.read_until(b'\n', &mut buf).unwrap_or(0) == 0 {
            return String::new();
        }
    }
    super::error::text_near(&buf, 1, column)
}

/// Deserialises a JSON upload `{"name"?, "timestamps"?, "poses"?, "frames": [...]}`, storing
/// each frame as soon as it is parsed so that only one frame is in memory at a time. Limit and
/// validation failures are put in `failure` (serde errors cannot carry them).
struct UploadSeed<'a> {
    sink: &'a mut dyn FrameSink,
    limits: &'a Limits,
    failure: &'a RefCell<Option<ApiError>>,
}

impl<'de> DeserializeSeed<'de> for UploadSeed<'_> {
    type Value = SequenceMeta;
    fn deserialize<D: de::Deserializer<'de>>(self, d: D) -> Result<SequenceMeta, D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de> Visitor<'de> for UploadSeed<'_> {
    type Value = SequenceMeta;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("an object with `frames` and optional `name`, `timestamps`, `poses`")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<SequenceMeta, A::Error> {
        const FIELDS: &[&str] = &["name", "timestamps", "poses", "frames"];
        let mut meta = SequenceMeta::default();
        let mut seen_frames = false;
        while let Some(key) = map.next_key::<String>()? {
            match key.as_str() {
                "name" => meta.name = map.next_value()?,
                "timestamps" => meta.timestamps_s = map.next_value()?,
                "poses" => meta.poses = map.next_value()?,
                "frames" => {
                    if seen_frames {
                        return Err(de::Error::duplicate_field("frames"));
                    }
                    seen_frames = true;
                    map.next_value_seed(FramesSeed {
                        sink: &mut *self.sink,
                        limits: self.limits,
                        failure: self.failure,
                    })?;
                }
                other => return Err(de::Error::unknown_field(other, FIELDS)),
            }
        }
        if !seen_frames {
            return Err(de::Error::missing_field("frames"));
        }
        Ok(meta)
    }
}

struct FramesSeed<'a> {
    sink: &'a mut dyn FrameSink,
    limits: &'a Limits,
    failure: &'a RefCell<Option<ApiError>>,
}

impl<'de> DeserializeSeed<'de> for FramesSeed<'_> {
    type Value = ();
    fn deserialize<D: de::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for FramesSeed<'_> {
    type Value = ();

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("an array of frames, each an array of [x, y, z] points")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        loop {
            let k = self.sink.frames_written();
            let Some(points) = seq.next_element_seed(PointsSeed {
                limit: self.limits.max_points_per_frame,
                frame: k,
                failure: self.failure,
            })?
            else {
                return Ok(());
            };
            let stored = check_frame(k, &points, self.limits).and_then(|()| Ok(self.sink.put_frame(&points)?));
            if let Err(e) = stored {
                let detail = format!("{e:?}");
                *self.failure.borrow_mut() = Some(e);
                return Err(de::Error::custom(detail));
            }
        }
    }
}

/// One frame's points, stopping as soon as the per-frame limit is passed.
struct PointsSeed<'a> {
    limit: usize,
    frame: usize,
    failure: &'a RefCell<Option<ApiError>>,
}

impl<'de> DeserializeSeed<'de> for PointsSeed<'_> {
    type Value = Vec<Point>;
    fn deserialize<D: de::Deserializer<'de>>(self, d: D) -> Result<Vec<Point>, D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for PointsSeed<'_> {
    type Value = Vec<Point>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("an array of [x, y, z] points")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<Point>, A::Error> {
        let mut points = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(self.limit));
        while let Some([x, y, z]) = seq.next_element::<[f64; 3]>()? {
            if points.len() >= self.limit {
                *self.failure.borrow_mut() = Some(ApiError::LimitExceeded {
                    limit: "max_points_per_frame",
                    detail: format!("frame {} has more than {} points", self.frame, self.limit),
                });
                return Err(de::Error::custom("too many points"));
            }
            // A finite f64 beyond f32's range becomes infinite: check_frame rejects it.
            points.push([x as f32, y as f32, z as f32]);
        }
        Ok(points)
    }
}

/// Query string of `GET /v1/sequences`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    limit: Option<usize>,
}

/// `GET /v1/sequences`.
pub async fn list(
    State(state): State<AppState>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let Query(query) = query.map_err(|e| ApiError::Invalid { parameter: None, detail: e.body_text() })?;
    let limit = list_limit(query.limit)?;
    let records = state.blocking(move |s| Ok(s.list_sequences(limit)?)).await?;
    let views: Vec<SequenceView> = records.iter().map(SequenceView::from).collect();
    Ok(Json(serde_json::json!({ "sequences": views })))
}

/// `GET /v1/sequences/{id}`.
pub async fn show(State(state): State<AppState>, UrlPath(id): UrlPath<String>) -> Result<Json<SequenceView>, ApiError> {
    let uuid = parse_id("sequence", &id)?;
    let record = state.blocking(move |s| Ok(s.get_sequence(uuid)?)).await?;
    let record = record.ok_or(ApiError::NotFound { what: "sequence", id })?;
    Ok(Json(SequenceView::from(&record)))
}

/// `DELETE /v1/sequences/{id}`: 204; 409 while jobs of it are queued or running.
pub async fn remove(State(state): State<AppState>, UrlPath(id): UrlPath<String>) -> Result<StatusCode, ApiError> {
    let uuid = parse_id("sequence", &id)?;
    match state.blocking(move |s| Ok(s.delete_sequence(uuid)?)).await? {
        DeleteOutcome::Deleted => Ok(StatusCode::NO_CONTENT),
        DeleteOutcome::NotFound => Err(ApiError::NotFound { what: "sequence", id }),
        DeleteOutcome::HasActiveJobs => {
            Err(ApiError::Conflict("jobs of this sequence are queued or running; cancel them first".into()))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parameter_of(meta: &str) -> Option<String> {
        match parse_meta_part(meta.as_bytes()) {
            Err(ApiError::Invalid { parameter, .. }) => parameter,
            other => panic!("{meta}: expected a 422, got {other:?}"),
        }
    }

    #[test]
    fn meta_part_reads_name_timestamps_and_poses() {
        let pose = "[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]";
        let meta = parse_meta_part(format!(r#"{{"name": "a", "timestamps": [0, 0.5], "poses": [{pose}]}}"#).as_bytes())
            .unwrap();
        assert_eq!(meta.name.as_deref(), Some("a"));
        assert_eq!(meta.timestamps_s, Some(vec![0.0, 0.5]));
        assert_eq!(meta.poses.unwrap()[0][15], 1.0);
        assert_eq!(parse_meta_part(b"{}").unwrap(), SequenceMeta::default());
    }

    #[test]
    fn meta_part_refusals_name_meta_or_the_field() {
        assert_eq!(parameter_of(r#"{"timestamps": [0, "#).as_deref(), Some("meta"));
        assert_eq!(parameter_of(r#"{"timestamps": [NaN]}"#).as_deref(), Some("meta"));
        assert_eq!(parameter_of(r#"{"frames": []}"#).as_deref(), Some("frames"));
        assert_eq!(parameter_of(r#"{"poses": [[1, 2, 3]]}"#).as_deref(), Some("meta"));
    }
}
