//! `/metrics` in the Prometheus text format, written by hand: jobs by status, fit throughput,
//! and a request-latency histogram per route.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::Mutex;
use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::http::{HeaderValue, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::{ApiError, AppState};
use crate::store::JobStatus;

/// Upper bounds (s) of the latency histogram buckets.
const BUCKETS_S: [f64; 12] = [0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0, 60.0];

#[derive(Debug, Default, Clone)]
struct Histogram {
    counts: [u64; BUCKETS_S.len()],
    count: u64,
    sum_s: f64,
}

/// Request counts and latencies, keyed by method, route template and status.
#[derive(Debug, Default)]
pub struct RequestMetrics {
    latency: Mutex<BTreeMap<(String, String), Histogram>>,
    statuses: Mutex<BTreeMap<(String, String, u16), u64>>,
}

impl RequestMetrics {
    fn record(&self, method: &str, route: &str, status: u16, seconds: f64) {
        {
            let mut latency = self.latency.lock().unwrap_or_else(|p| p.into_inner());
            let h = latency.entry((method.to_string(), route.to_string())).or_default();
            for (count, bound) in h.counts.iter_mut().zip(BUCKETS_S) {
                if seconds <= bound {
                    *count += 1;
                }
            }
            h.count += 1;
            h.sum_s += seconds;
        }
        let mut statuses = self.statuses.lock().unwrap_or_else(|p| p.into_inner());
        *statuses.entry((method.to_string(), route.to_string(), status)).or_default() += 1;
    }
}

/// Middleware: times every request and counts it by route template (not raw path, so ids do
/// not multiply the series). Streaming responses count until their headers are sent.
pub async fn track(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = request.method().as_str().to_string();
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_string())
        .unwrap_or_else(|| "unmatched".to_string());
    let response = next.run(request).await;
    state.inner.metrics.record(&method, &route, response.status().as_u16(), started.elapsed().as_secs_f64());
    response
}

/// Escapes a label value (backslash, quote, newline).
fn label(value: &str) -> String {
    value.replace('\\', "\\\\").replace('"', "\\\"").replace('\n', "\\n")
}

/// `GET /metrics`.
pub async fn render(State(state): State<AppState>) -> Result<Response, ApiError> {
    let counts = state.blocking(|s| Ok(s.count_jobs_by_status()?)).await?;
    let mut out = String::new();
    let _ = writeln!(out, "# HELP mbnt_jobs Jobs in the store by status.");
    let _ = writeln!(out, "# TYPE mbnt_jobs gauge");
    for status in JobStatus::ALL {
        let n = counts.iter().find(|(s, _)| *s == status).map_or(0, |(_, n)| *n);
        let _ = writeln!(out, "mbnt_jobs{{status=\"{}\"}} {n}", status.as_str());
    }
    let stats = state.inner.queue.stats();
    let _ = writeln!(out, "# HELP mbnt_fit_iterations_total Fit iterations completed by this process.");
    let _ = writeln!(out, "# TYPE mbnt_fit_iterations_total counter");
    let _ = writeln!(out, "mbnt_fit_iterations_total {}", stats.iterations_total());
    let _ = writeln!(out, "# HELP mbnt_fit_iterations_per_second Iterations per second of the fits running now.");
    let _ = writeln!(out, "# TYPE mbnt_fit_iterations_per_second gauge");
    let _ = writeln!(out, "mbnt_fit_iterations_per_second {}", stats.iterations_per_second());
    let metrics = &state.inner.metrics;
    let _ = writeln!(out, "# HELP mbnt_http_requests_total HTTP requests by method, route and status.");
    let _ = writeln!(out, "# TYPE mbnt_http_requests_total counter");
    for ((method, route, status), n) in metrics.statuses.lock().unwrap_or_else(|p| p.into_inner()).iter() {
        let _ = writeln!(
            out,
            "mbnt_http_requests_total{{method=\"{}\",route=\"{}\",status=\"{status}\"}} {n}",
            label(method),
            label(route)
        );
    }
    let _ = writeln!(out, "# HELP mbnt_http_request_duration_seconds Time to the response headers.");
    let _ = writeln!(out, "# TYPE mbnt_http_request_duration_seconds histogram");
    for ((method, route), h) in metrics.latency.lock().unwrap_or_else(|p| p.into_inner()).iter() {
        let labels = format!("method=\"{}\",route=\"{}\"", label(method), label(route));
        for (count, bound) in h.counts.iter().zip(BUCKETS_S) {
            let _ = writeln!(out, "mbnt_http_request_duration_seconds_bucket{{{labels},le=\"{bound}\"}} {count}");
        }
        let _ = writeln!(out, "mbnt_http_request_duration_seconds_bucket{{{labels},le=\"+Inf\"}} {}", h.count);
        let _ = writeln!(out, "mbnt_http_request_duration_seconds_sum{{{labels}}} {}", h.sum_s);
        let _ = writeln!(out, "mbnt_http_request_duration_seconds_count{{{labels}}} {}", h.count);
    }
    Ok(([(header::CONTENT_TYPE, HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"))], out)
        .into_response())
}
