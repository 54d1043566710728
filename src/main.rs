//! The `mbnt` binary: a thin dispatcher over the library's command front ends.

use clap::{Parser, Subcommand};
use mbnt::cli::{bench_cmd, eval_cmd, fit_cmd, label_cmd, load_cmd, odometry_cmd, serve_cmd, simulate_cmd, worker_cmd};

/// Long-term per-point 4D trajectories for LiDAR point-cloud sequences.
#[derive(Debug, Parser)]
#[command(name = "mbnt", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the HTTP service (uploads, fit jobs, queries, label export).
    Serve(serve_cmd::ServeArgs),
    /// Fit jobs of a shared store (PostgreSQL + object store) without serving HTTP: a fleet's worker.
    Worker(worker_cmd::WorkerArgs),
    /// Fit a method to frame files and write trajectories and scene-flow labels (.npz).
    Fit(fit_cmd::FitArgs),
    /// Label a log in a dataset's layout (Argoverse 2, KITTI): one scene-flow file per frame.
    Label(label_cmd::LabelArgs),
    /// Write a synthetic LiDAR sequence with exact ground truth.
    Simulate(simulate_cmd::SimulateArgs),
    /// Compare methods and baselines on simulated sequences (or directories with ground truth).
    Eval(eval_cmd::EvalArgs),
    /// Time a fit phase by phase, faithful and fast modes side by side.
    Bench(bench_cmd::BenchArgs),
    /// Load the HTTP service on loopback: concurrent uploads and queries while a fit runs.
    BenchLoad(load_cmd::LoadArgs),
    /// Estimate the sensor poses of frame files (LiDAR odometry), printed as KITTI poses.txt.
    Odometry(odometry_cmd::OdometryArgs),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info,tower_http=info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Serve(args) => serve_cmd::run(args),
        Command::Worker(args) => worker_cmd::run(args),
        Command::Fit(args) => fit_cmd::run(args),
        Command::Label(args) => label_cmd::run(args),
        Command::Simulate(args) => simulate_cmd::run(args),
        Command::Eval(args) => eval_cmd::run(args),
        Command::Bench(args) => bench_cmd::run(args),
        Command::BenchLoad(args) => load_cmd::run(args),
        Command::Odometry(args) => odometry_cmd::run(args),
    }
}
