//! The load driver of `mbnt bench-load` at small scale against a real bound port: uploads and
//! queries while a fit runs, every answer checked. No wall-clock limit is asserted: the
//! figures are for `docs/benchmarks.md`, not for a test on a shared machine.

mod common;

use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::Duration;

use common::{Options, SlowFitter, TestServer};
use mbnt::cli::load_cmd::{LoadConfig, drive};
use mbnt::fit::{FitError, Method, Progress, Sequence, ValidFitParams};
use mbnt::jobs::{CoreFitter, Fitter};
use mbnt::model::FittedModel;

/// Runs small fits for real; a fit asking for more than `long_from` iterations reports an
/// iteration every 10 ms until it is cancelled (`slow`, an hour of them), so that the long
/// fit surely outlasts the load whatever the machine's speed.
struct UntilCancelled {
    long_from: usize,
    slow: SlowFitter,
}

impl Fitter for UntilCancelled {
    fn fit(
        &self,
        sequence: &Sequence,
        method: Method,
        params: &ValidFitParams,
        on_progress: &mut dyn FnMut(&Progress) -> ControlFlow<()>,
    ) -> Result<FittedModel, FitError> {
        let fitter: &dyn Fitter = if params.iterations <= self.long_from { &CoreFitter } else { &self.slow };
        fitter.fit(sequence, method, params, on_progress)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_and_queries_during_a_fit_all_succeed_with_the_right_answers() {
    let fitter = Arc::new(UntilCancelled {
        long_from: 100,
        slow: SlowFitter { steps: 360_000, step: Duration::from_millis(10) },
    });
    let s = TestServer::start_with(Options { fitter, ..Options::default() }).await;
    let config = LoadConfig::small(5, 50);
    let report = drive(&s.base, None, &config).await.expect("the load runs");

    assert_eq!(report.errors, 0, "{:#?}", report.error_samples);
    assert_eq!((report.uploads.count, report.uploads.errors), (5, 0));
    assert_eq!((report.queries.count, report.queries.errors), (50, 0));
    assert!(report.fit_running_throughout, "{:?}", report.fit_not_running_seen);
    assert!(report.fit_iterations[1] >= report.fit_iterations[0] && report.fit_iterations[0] >= 1);
    assert!(report.uploads.p50_ms > 0.0 && report.uploads.p50_ms <= report.uploads.p99_ms);
    assert!(report.queries.p50_ms > 0.0 && report.queries.p50_ms <= report.queries.p99_ms);
    assert!(report.query_points >= 1 && report.upload_points_per_frame.len() == 3);

    // The store holds what the driver saw: the query sequence, the long fit's and the 5 uploads;
    // the small fit succeeded and the long one was cancelled after the load.
    let (status, list) = s.get("/v1/sequences", "/v1/sequences").await;
    assert_eq!(status, 200);
    let names: Vec<&str> = list["sequences"].as_array().unwrap().iter().filter_map(|q| q["name"].as_str()).collect();
    assert_eq!(names.iter().filter(|n| n.starts_with("load-") && n[5..].parse::<usize>().is_ok()).count(), 5);
    assert_eq!(names.len(), 7, "{names:?}");
    let job = s.wait_status(&report.fit_job, "cancelled").await;
    assert_eq!(job["status"], "cancelled");
    let (_, jobs) = s.get("/v1/jobs", "/v1/jobs?status=succeeded").await;
    assert_eq!(jobs["jobs"].as_array().unwrap().len(), 1);
}
