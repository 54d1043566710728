//! One error type for every route, rendered as RFC 9457 `application/problem+json`, and a
//! middleware that turns every other error response (axum's own rejections, 404/405 from
//! routing, 413 from the body limit) into the same form.

use axum::body::Body;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

/// Media type of error bodies.
pub const PROBLEM_JSON: &str = "application/problem+json";

/// Prefix of every problem `type` URI; the suffix is a short slug listed in `openapi.yaml`.
pub const PROBLEM_TYPE_PREFIX: &str = "urn:mbnt:problem:";

/// An error a handler returns. Each variant's doc names its HTTP status.
#[derive(Debug)]
pub enum ApiError {
    /// 400: the request cannot be read (malformed JSON or multipart, bad query string).
    BadRequest(String),
    /// 401: missing or wrong bearer token.
    Unauthorized,
    /// 404: no such resource (`what` and the id as given).
    NotFound {
        /// Kind of resource: "sequence", "job".
        what: &'static str,
        /// The id as given in the path.
        id: String,
    },
    /// 409: the resource is not in a state that allows the request.
    Conflict(String),
    /// 409: a succeeded job's stored result (its model, its sequence's frames) cannot be read;
    /// the job has been marked failed with the cause, so later requests see a failed job.
    ResultUnreadable {
        /// The job.
        job: uuid::Uuid,
        /// What cannot be read and why (the job's error).
        detail: String,
    },
    /// 413: the body is larger than the configured limit.
    TooLarge(String),
    /// 415: the body's content type is not one the route accepts.
    UnsupportedMediaType(String),
    /// 422: the request is well-formed but a value is not acceptable; `parameter` names it.
    Invalid {
        /// The offending field or hyper-parameter, when there is one.
        parameter: Option<String>,
        /// What is wrong.
        detail: String,
    },
    /// 422: a configured limit (frames, points, iterations, query size) is exceeded.
    LimitExceeded {
        /// Name of the limit, as in the server options (e.g. "max_frames").
        limit: &'static str,
        /// What exceeded it.
        detail: String,
    },
    /// 501: the server was built without the feature the request needs.
    NotImplemented(String),
    /// 503: the service cannot answer now (storage unreachable, shutting down).
    Unavailable(String),
    /// 500: anything else; logged, and opaque to the client.
    Internal(anyhow::Error),
}

impl ApiError {
    /// A 422 naming `parameter`.
    pub fn invalid(parameter: impl Into<String>, detail: impl Into<String>) -> Self {
        ApiError::Invalid { parameter: Some(parameter.into()), detail: detail.into() }
    }

    /// The HTTP status.
    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::BadRequest(_) => StatusCode::BAD_REQUEST,
            ApiError::Unauthorized => StatusCode::UNAUTHORIZED,
            ApiError::NotFound { .. } => StatusCode::NOT_FOUND,
            ApiError::Conflict(_) | ApiError::ResultUnreadable { .. } => StatusCode::CONFLICT,
            ApiError::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ApiError::Invalid { .. } | ApiError::LimitExceeded { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::NotImplemented(_) => StatusCode::NOT_IMPLEMENTED,
            ApiError::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    fn problem(&self) -> Problem {
        let status = self.status();
        let job_id = match self {
            ApiError::ResultUnreadable { job, .. } => Some(job.to_string()),
            _ => None,
        };
        let (slug, title, detail, parameter, limit) = match self {
            ApiError::BadRequest(d) => ("bad-request", "Malformed request", d.clone(), None, None),
            ApiError::Unauthorized => (
                "unauthorized",
                "Authentication required",
                "send the API token as `Authorization: Bearer <token>`".to_string(),
                None,
                None,
            ),
            ApiError::NotFound { what, id } => {
                ("not-found", "Not found", format!("no {what} with id {id:?}"), None, None)
            }
            ApiError::Conflict(d) => ("conflict", "Conflict with the resource's state", d.clone(), None, None),
            ApiError::ResultUnreadable { job, detail } => (
                "result-unreadable",
                "The job's stored result cannot be read",
                format!("job {job}: {detail}; the job is now marked failed"),
                None,
                None,
            ),
            ApiError::TooLarge(d) => ("body-too-large", "Request body too large", d.clone(), None, None),
            ApiError::UnsupportedMediaType(d) => {
                ("unsupported-media-type", "Unsupported media type", d.clone(), None, None)
            }
            ApiError::Invalid { parameter, detail } => {
                ("invalid-input", "Invalid input", detail.clone(), parameter.clone(), None)
            }
            ApiError::LimitExceeded { limit, detail } => {
                ("limit-exceeded", "A configured limit is exceeded", detail.clone(), None, Some(*limit))
            }
            ApiError::NotImplemented(d) => ("not-implemented", "Not implemented by this build", d.clone(), None, None),
            ApiError::Unavailable(d) => ("unavailable", "Service unavailable", d.clone(), None, None),
            ApiError::Internal(_) => (
                "internal",
                "Internal server error",
                "the server failed to handle the request; it has been logged".to_string(),
                None,
                None,
            ),
        };
        Problem {
            r#type: format!("{PROBLEM_TYPE_PREFIX}{slug}"),
            title: title.to_string(),
            status: status.as_u16(),
            detail,
            parameter,
            limit: limit.map(str::to_string),
            job_id,
        }
    }
}

impl From<crate::store::StoreError> for ApiError {
    fn from(e: crate::store::StoreError) -> Self {
        ApiError::Internal(e.into())
    }
}

impl From<tokio::task::JoinError> for ApiError {
    fn from(e: tokio::task::JoinError) -> Self {
        ApiError::Internal(anyhow::anyhow!("a blocking task failed: {e}"))
    }
}

/// The RFC 9457 body.
#[derive(Debug, Serialize)]
struct Problem {
    r#type: String,
    title: String,
    status: u16,
    detail: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    parameter: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    limit: Option<String>,
    /// The job a `result-unreadable` problem is about.
    #[serde(skip_serializing_if = "Option::is_none")]
    job_id: Option<String>,
}

impl Problem {
    fn into_response(self, status: StatusCode) -> Response {
        let body = serde_json::to_vec(&self).expect("a problem always serialises");
        let mut response = (status, body).into_response();
        response.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        response
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        if let ApiError::Internal(e) = &self {
            tracing::error!(error = format!("{e:#}"), "internal error");
        }
        let status = self.status();
        let mut response = self.problem().into_response(status);
        if status == StatusCode::UNAUTHORIZED {
            response.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        response
    }
}

/// Error bodies longer than this are not copied into `detail`.
const MAX_DETAIL_BYTES: usize = 16 * 1024;

/// Middleware: rewrites any 4xx/5xx response that is not already problem+json (axum's
/// extractor rejections, routing 404/405, the body limit's 413, panics caught as 500) into a
/// problem, keeping its status and headers and its text as the detail.
pub async fn problem_json(request: axum::extract::Request, next: axum::middleware::Next) -> Response {
    let response = next.run(request).await;
    let status = response.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return response;
    }
    let is_problem = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with(PROBLEM_JSON));
    if is_problem {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = match axum::body::to_bytes(body, MAX_DETAIL_BYTES).await {
        Ok(bytes) => String::from_utf8_lossy(&bytes).trim().to_string(),
        Err(_) => String::new(),
    };
    let reason = status.canonical_reason().unwrap_or("Error");
    let slug = match status {
        StatusCode::BAD_REQUEST => "bad-request",
        StatusCode::NOT_FOUND => "not-found",
        StatusCode::METHOD_NOT_ALLOWED => "method-not-allowed",
        StatusCode::PAYLOAD_TOO_LARGE => "body-too-large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported-media-type",
        StatusCode::UNPROCESSABLE_ENTITY => "invalid-input",
        StatusCode::INTERNAL_SERVER_ERROR => "internal",
        _ if status.is_server_error() => "unavailable",
        _ => "bad-request",
    };
    let detail = if status == StatusCode::INTERNAL_SERVER_ERROR {
        // A caught panic's text is not for clients.
        "the server failed to handle the request; it has been logged".to_string()
    } else if status == StatusCode::NOT_FOUND && text.is_empty() {
        "no such route".to_string()
    } else if status == StatusCode::METHOD_NOT_ALLOWED && text.is_empty() {
        let allow = parts.headers.get(header::ALLOW).and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
        format!("method not allowed on this route (allowed: {allow})")
    } else if text.is_empty() {
        reason.to_string()
    } else {
        text
    };
    let problem = Problem {
        r#type: format!("{PROBLEM_TYPE_PREFIX}{slug}"),
        title: reason.to_string(),
        status: status.as_u16(),
        detail,
        parameter: None,
        limit: None,
        job_id: None,
    };
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
    let body = serde_json::to_vec(&problem).expect("a problem always serialises");
    Response::from_parts(parts, Body::from(body))
}

/// Maps a JSON decoding error to a problem. `text_near` returns the input around a line and
/// column (1-based), so that a `NaN` or `Infinity` token (JSON has neither, but Python's
/// `json.dumps` writes them) is reported as a 422 on the value rather than as a syntax error.
pub fn json_error(e: &serde_json::Error, text_near: impl FnOnce(usize, usize) -> String) -> ApiError {
    use serde_json::error::Category;
    match e.classify() {
        Category::Syntax | Category::Eof => {
            let near = text_near(e.line(), e.column());
            if ["NaN", "Infinity", "inf", "nan"].iter().any(|t| near.contains(t)) {
                ApiError::Invalid {
                    parameter: None,
                    detail: format!(
                        "non-finite number at line {} column {}: coordinates and times must be finite \
                         (JSON has no NaN or Infinity)",
                        e.line(),
                        e.column()
                    ),
                }
            } else {
                ApiError::BadRequest(format!("malformed JSON: {e}"))
            }
        }
        Category::Data => {
            let message = e.to_string();
            // serde names unknown and missing fields between backticks.
            let parameter = ["unknown field `", "missing field `"].iter().find_map(|prefix| {
                let rest = message.split(prefix).nth(1)?;
                Some(rest.split('`').next()?.to_string())
            });
            ApiError::Invalid { parameter, detail: message }
        }
        Category::Io => ApiError::BadRequest(format!("could not read the body: {e}")),
    }
}

/// The bytes around (line, column) of `input`, for [`json_error`].
pub fn text_near(input: &[u8], line: usize, column: usize) -> String {
    let Some(line_text) = input.split(|&b| b == b'\n').nth(line.saturating_sub(1)) else {
        return String::new();
    };
    let at = column.saturating_sub(1).min(line_text.len());
    let from = at.saturating_sub(2);
    let to = (at + 10).min(line_text.len());
    String::from_utf8_lossy(&line_text[from..to]).into_owned()
}

/// Parses a JSON body, mapping errors with [`json_error`].
pub fn parse_json<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    serde_json::from_slice(bytes).map_err(|e| json_error(&e, |l, c| text_near(bytes, l, c)))
}

/// Bodies up to this size are parsed on the executor: below it, handing the work to the
/// blocking pool costs more than the parse itself.
const INLINE_PARSE_BYTES: usize = 64 << 10;

/// [`parse_json`] for a body of any size, off the async executor when it is large. Parsing is
/// CPU work in proportion to the body (queries may carry 100,000 points), and on an executor
/// thread it would stall every other request that thread serves.
pub async fn parse_json_body<T, B>(bytes: B) -> Result<T, ApiError>
where
    T: serde::de::DeserializeOwned + Send + 'static,
    B: AsRef<[u8]> + Send + 'static,
{
    parse_body_with(bytes, parse_json::<T>).await
}

/// Runs the pure parser `parse` on a body, off the async executor when the body is large (as
/// [`parse_json_body`] does for plain JSON), so that a parser with its own error mapping can
/// stay a plain function that tests and fuzz targets call directly.
pub async fn parse_body_with<T, B>(bytes: B, parse: fn(&[u8]) -> Result<T, ApiError>) -> Result<T, ApiError>
where
    T: Send + 'static,
    B: AsRef<[u8]> + Send + 'static,
{
    if bytes.as_ref().len() <= INLINE_PARSE_BYTES {
        parse(bytes.as_ref())
    } else {
        tokio::task::spawn_blocking(move || parse(bytes.as_ref())).await?
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Body {
        points: Vec<[f64; 3]>,
    }

    fn problem_of(input: &str) -> (StatusCode, Option<String>) {
        let e = parse_json::<Body>(input.as_bytes()).unwrap_err();
        let p = e.problem();
        (e.status(), p.parameter)
    }

    #[test]
    fn nan_tokens_are_a_422_and_other_syntax_errors_a_400() {
        assert_eq!(problem_of(r#"{"points": [[1, NaN, 2]]}"#).0, StatusCode::UNPROCESSABLE_ENTITY);
        assert_eq!(problem_of("{\"points\":\n [[1, 2, -Infinity]]}").0, StatusCode::UNPROCESSABLE_ENTITY);
        assert_eq!(problem_of(r#"{"points": [[1, 2, 3]"#).0, StatusCode::BAD_REQUEST);
        assert_eq!(problem_of(r#"{"points": [[1, 2, 3]], }"#).0, StatusCode::BAD_REQUEST);
    }

    #[test]
    fn unknown_and_missing_fields_are_named() {
        assert_eq!(
            problem_of(r#"{"points": [], "bogus": 1}"#),
            (StatusCode::UNPROCESSABLE_ENTITY, Some("bogus".into()))
        );
        assert_eq!(problem_of(r#"{}"#), (StatusCode::UNPROCESSABLE_ENTITY, Some("points".into())));
    }
}
