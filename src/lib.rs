//! mbnt: long-term per-point 4D trajectories for LiDAR point-cloud sequences.
//!
//! A trajectory network (NTP) is fitted to a sequence by test-time optimisation, regularised by
//! a multi-body rigidity loss (MBNT); pair-wise scene-flow fitting (NSFP, MBNSF) is kept as a
//! baseline. The crate is a library with a thin binary (`src/main.rs`: `serve`, `fit`,
//! `simulate`, `eval`, `bench`, `odometry`).
//!
//! # Layout
//! - [`geometry`]: points, k-d tree queries, DBSCAN, ground removal, rigid transforms.
//! - [`nn`]: dense layers and the MLP, forward and backward by hand over a fast GEMM; Adam.
//! - [`losses`]: truncated Chamfer, cycle consistency, multi-body score, value and gradient.
//! - [`fit`]: the NTP/MBNT and NSFP/MBNSF fitting loops, their parameters and progress.
//! - [`odometry`]: LiDAR odometry, the sensor poses of a sequence recorded without them.
//! - [`trajectory`]: a fitted model answers where a point is at any time.
//! - [`metrics`]: scene-flow and long-term trajectory metrics.
//! - [`io`]: PLY, PCD, KITTI `.bin`, NumPy readers; `.npy`/`.npz` writers.
//! - [`sim`]: synthetic LiDAR sequences with exact ground truth.
//! - [`store`], [`jobs`], [`http`]: the service (SQLite + files, job queue, axum routes).
//!
//! # Dependency direction
//! `geometry`, `nn`, `losses`, `odometry`, `fit`, `trajectory`, `metrics` and `sim` are synchronous and
//! know nothing of tokio, axum, the store or the file system. `io` reads and writes bytes.
//! `jobs` drives `fit` and uses `store`; `http` uses `jobs`, `store` and `trajectory` and never
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
pub mod nn;
pub mod odometry;
pub mod sim;
pub mod store;
pub mod trajectory;
