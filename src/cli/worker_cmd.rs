//! `mbnt worker`: a process that fits queued jobs of a shared store (PostgreSQL and an object
//! store) and serves no HTTP, until SIGTERM or Ctrl-C. Any number of them, on any machines,
//! beside any number of `mbnt serve --workers 0`.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;

use super::serve_cmd::{FleetArgs, stop_signal};
use crate::jobs::{CoreFitter, JobQueue, WorkerPool};

/// Arguments of `mbnt worker`.
#[derive(Debug, Clone, clap::Args)]
pub struct WorkerArgs {
    /// Fits this process runs at the same time (each claims its own job).
    #[arg(long, env = "MBNT_WORKERS", default_value_t = 1)]
    pub workers: usize,
    /// Threads of each fit (default: all cores divided among the workers).
    #[arg(long, env = "MBNT_THREADS_PER_JOB")]
    pub threads_per_job: Option<usize>,
    /// Local scratch directory (nothing in it outlives the process's work).
    #[arg(long, env = "MBNT_DATA_DIR", default_value = "./mbnt-data")]
    pub data_dir: PathBuf,
    /// The shared store and how jobs are held.
    #[command(flatten)]
    pub fleet: FleetArgs,
}

/// Runs the workers until SIGTERM or Ctrl-C; a running fit stops at its next iteration and its
/// job goes back to the queue (with its checkpoint, for any worker to go on from).
pub fn run(args: WorkerArgs) -> anyhow::Result<()> {
    if args.fleet.database_url.is_none() {
        anyhow::bail!(
            "mbnt worker needs a shared store: set MBNT_DATABASE_URL (postgres://...) and MBNT_OBJECT_STORE_URL \
             (file:///DIR or s3://BUCKET/PREFIX); on one machine, `mbnt serve` runs its own workers"
        );
    }
    let workers = args.workers.max(1);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads_per_job = args.threads_per_job.unwrap_or((cores / workers).max(1)).max(1);
    let (store, _scratch) = args.fleet.open_store(&args.data_dir)?;
    let queue = JobQueue::with_settings(store, args.fleet.worker_settings()?);
    let pool = WorkerPool::start(queue, Arc::new(CoreFitter), workers, threads_per_job)?;
    tracing::info!(workers, threads_per_job, "mbnt worker ready");
    let runtime =
        tokio::runtime::Builder::new_current_thread().enable_all().build().context("starting the signal listener")?;
    runtime.block_on(stop_signal());
    pool.shutdown();
    tracing::info!("mbnt worker stopped");
    Ok(())
}
