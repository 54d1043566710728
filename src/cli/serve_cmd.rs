//! `mbnt serve`: the HTTP service with its workers, until SIGTERM or Ctrl-C.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;

use crate::http::{Limits, Service, ServiceConfig};
use crate::jobs::{CoreFitter, WorkerSettings};
use crate::store::{Store, StoreConfig};

/// Where the data lives and how workers hold jobs: shared by `mbnt serve` and `mbnt worker`.
#[derive(Debug, Clone, clap::Args)]
pub struct FleetArgs {
    /// PostgreSQL database of a fleet (`postgres://user@host/db`): sequences, jobs, the queue and
    /// progress, shared by any number of `mbnt serve` and `mbnt worker` processes. Unset: the
    /// embedded SQLite database of the data directory (one process).
    #[arg(long, env = "MBNT_DATABASE_URL", hide_env_values = true)]
    pub database_url: Option<String>,
    /// Object store of a fleet for frames, models and checkpoints: `file:///DIR` or
    /// `s3://BUCKET/PREFIX` (endpoint and credentials from the AWS_* variables). Default with a
    /// database: `objects/` of the data directory (one machine).
    #[arg(long, env = "MBNT_OBJECT_STORE_URL")]
    pub object_store_url: Option<String>,
    /// Seconds a worker holds a job without renewing; a worker that died loses its job to
    /// another this long after (renewed every third of it).
    #[arg(long, env = "MBNT_LEASE_S", default_value_t = 30.0)]
    pub lease_s: f64,
    /// A job whose worker died this many times fails instead of running again.
    #[arg(long, env = "MBNT_MAX_ATTEMPTS", default_value_t = 3)]
    pub max_attempts: u32,
    /// Least seconds between two mid-fit checkpoints of a job (taken at validations).
    #[arg(long, env = "MBNT_CHECKPOINT_EVERY_S", default_value_t = 30.0)]
    pub checkpoint_every_s: f64,
}

impl FleetArgs {
    /// The store settings.
    pub fn store_config(&self) -> StoreConfig {
        StoreConfig { database_url: self.database_url.clone(), object_store_url: self.object_store_url.clone() }
    }

    /// The lease and checkpoint settings, checked.
    pub fn worker_settings(&self) -> anyhow::Result<WorkerSettings> {
        let seconds = |name: &str, s: f64, min: f64| {
            if s.is_finite() && (min..=86_400.0).contains(&s) {
                Ok(std::time::Duration::from_secs_f64(s))
            } else {
                Err(anyhow::anyhow!("{name} must be between {min} and 86400 seconds, got {s}"))
            }
        };
        if self.max_attempts == 0 {
            anyhow::bail!("max_attempts must be at least 1");
        }
        Ok(WorkerSettings {
            lease: seconds("lease_s", self.lease_s, 0.3)?,
            max_attempts: self.max_attempts,
            checkpoint_every: seconds("checkpoint_every_s", self.checkpoint_every_s, 0.0)?,
        })
    }

    /// Opens the store (see [`crate::store::open`]); returns it and the local scratch directory.
    pub fn open_store(&self, data_dir: &std::path::Path) -> anyhow::Result<(Arc<dyn Store>, PathBuf)> {
        crate::store::open(data_dir, &self.store_config()).context("opening the store")
    }
}

/// Arguments of `mbnt serve`.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Address to listen on.
    #[arg(long, env = "MBNT_BIND", default_value = "127.0.0.1:8080")]
    pub bind: SocketAddr,
    /// Data directory (SQLite database, frames, models); created when absent.
    #[arg(long, env = "MBNT_DATA_DIR", default_value = "./mbnt-data")]
    pub data_dir: PathBuf,
    /// Fits that may run at the same time in this process (0: the API alone, for a fleet whose
    /// `mbnt worker` processes fit).
    #[arg(long, env = "MBNT_WORKERS", default_value_t = 1)]
    pub workers: usize,
    /// Threads of each fit (default: all cores divided among the workers).
    #[arg(long, env = "MBNT_THREADS_PER_JOB")]
    pub threads_per_job: Option<usize>,
    /// Largest request body, bytes (uploads included).
    #[arg(long, env = "MBNT_MAX_BODY_BYTES", default_value_t = Limits::default().max_body_bytes)]
    pub max_body_bytes: u64,
    /// Largest JSON body of the job and query routes, bytes.
    #[arg(long, env = "MBNT_MAX_JSON_BYTES", default_value_t = Limits::default().max_json_bytes)]
    pub max_json_bytes: usize,
    /// Most frames per sequence.
    #[arg(long, env = "MBNT_MAX_FRAMES", default_value_t = Limits::default().max_frames)]
    pub max_frames: usize,
    /// Most points per frame.
    #[arg(long, env = "MBNT_MAX_POINTS_PER_FRAME", default_value_t = Limits::default().max_points_per_frame)]
    pub max_points_per_frame: usize,
    /// Most fit iterations a job may ask for.
    #[arg(long, env = "MBNT_MAX_ITERATIONS", default_value_t = Limits::default().max_iterations)]
    pub max_iterations: usize,
    /// Most points per query.
    #[arg(long, env = "MBNT_MAX_QUERY_POINTS", default_value_t = Limits::default().max_query_points)]
    pub max_query_points: usize,
    /// Most times per query.
    #[arg(long, env = "MBNT_MAX_QUERY_TIMES", default_value_t = Limits::default().max_query_times)]
    pub max_query_times: usize,
    /// Most positions (points x times) per query answer.
    #[arg(long, env = "MBNT_MAX_QUERY_POSITIONS", default_value_t = Limits::default().max_query_positions)]
    pub max_query_positions: usize,
    /// The store and how workers hold jobs.
    #[command(flatten)]
    pub fleet: FleetArgs,
}

impl ServeArgs {
    /// The service configuration; the API token comes from the environment (`MBNT_API_TOKEN`)
    /// only, so that it never shows in a process listing.
    pub fn config(&self, api_token: Option<String>) -> anyhow::Result<ServiceConfig> {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let workers = self.workers;
        Ok(ServiceConfig {
            bind: self.bind,
            data_dir: self.data_dir.clone(),
            store: self.fleet.store_config(),
            worker: self.fleet.worker_settings()?,
            workers,
            threads_per_job: self.threads_per_job.unwrap_or((cores / workers.max(1)).max(1)),
            api_token,
            limits: Limits {
                max_body_bytes: self.max_body_bytes,
                max_json_bytes: self.max_json_bytes,
                max_frames: self.max_frames,
                max_points_per_frame: self.max_points_per_frame,
                max_iterations: self.max_iterations,
                max_query_points: self.max_query_points,
                max_query_times: self.max_query_times,
                max_query_positions: self.max_query_positions,
            },
        })
    }
}

/// Resolves on SIGTERM or Ctrl-C.
pub(crate) async fn stop_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!(error = %e, "cannot listen for Ctrl-C");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => tracing::info!("Ctrl-C: shutting down"),
        () = term => tracing::info!("SIGTERM: shutting down"),
    }
}

/// Runs the service until SIGTERM or Ctrl-C; running fits go back to the queue and run again
/// on the next start.
pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let token = std::env::var("MBNT_API_TOKEN").ok().filter(|t| !t.is_empty());
    let config = args.config(token)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("mbnt-http")
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async move {
        let service = Service::start(config, Arc::new(CoreFitter)).await?;
        service.run_until(stop_signal()).await
    })
}
