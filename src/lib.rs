//! mbnt: long-term per-point 4D trajectories for LiDAR point-cloud sequences.
//!
//! A trajectory network (NTP) is fitted to a sequence by test-time optimisation, regularised by
//! a multi-body rigidity loss (MBNT); pair-wise scene-flow fitting (NSFP, MBNSF) is kept as a
//! baseline. The crate is a library with a thin binary (`src/main.rs`: `serve`, `fit`,
//! `simulate`, `eval`, `bench`, `bench-load`, `odometry`).
//!
//! # Layout
//! - [`geometry`]: points, k-d tree queries, DBSCAN, ground removal, rigid transforms.
//! - [`nn`]: dense layers and the MLP, forward and backward by hand over a fast GEMM; Adam.
//! - [`losses`]: truncated Chamfer, cycle consistency, multi-body score, value and gradient.
//! - [`fit`]: the NTP/MBNT and NSFP/MBNSF fitting loops, their parameters and progress.
//! - [`odometry`]: LiDAR odometry, the sensor poses of a sequence recorded without them.
//! - [`model`]: a fitted model answers where a point is at any time; its versioned file format
//!   and every type a model file holds (fit report, parameters, moving bodies, rigid tracks).
//! - [`metrics`]: scene-flow and long-term trajectory metrics.
//! - [`io`]: PLY, PCD, KITTI `.bin`, NumPy readers; `.npy`/`.npz` writers.
//! - [`sim`]: synthetic LiDAR sequences with exact ground truth.
//! - [`store`], [`jobs`], [`http`]: the service (SQLite + files, job queue, axum routes).
//!
//! # Dependency direction
//! `geometry`, `nn`, `losses`, `odometry`, `fit`, `model`, `metrics` and `sim` are synchronous and
//! know nothing of tokio, axum, the store or the file system. `io` reads and writes bytes.
//! `fit` builds a `model` and imports its types; `model` imports nothing from `fit`.
//! `jobs` drives `fit` and uses `store`; `http` uses `jobs`, `store` and `model` and never
//! runs a fit itself.
#![warn(missing_docs)]

pub mod cli;
pub mod fit;
pub mod geometry;
pub mod http;
pub mod io;
pub mod jobs;
pub mod losses;
pub mod metrics;
pub mod model;
pub mod nn;
pub mod odometry;
pub mod sim;
pub mod store;
