//! The command-line front ends of the binary: each subcommand's arguments and its `run`.

pub mod bench_cmd;
pub mod eval_cmd;
pub mod fit_cmd;
pub mod frames;
pub mod label_cmd;
pub mod load_cmd;
pub mod odometry_cmd;
pub mod progress;
pub mod real_pair;
pub mod serve_cmd;
pub mod simulate_cmd;
pub mod worker_cmd;
