//! The `mbnt` command line: parses arguments and calls into the library (`mbnt::cli`).

use clap::{Parser, Subcommand};

/// Long-term per-point 4D trajectories for LiDAR sequences.
#[derive(Debug, Parser)]
#[command(name = "mbnt", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the HTTP service (uploads, fit jobs, queries, label export).
    Serve(mbnt::cli::serve_cmd::ServeArgs),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info,tower_http=info".into()),
        )
        .init();
    match Cli::parse().command {
        Command::Serve(args) => mbnt::cli::serve_cmd::run(args),
    }
}
