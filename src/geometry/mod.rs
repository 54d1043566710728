//! Point clouds and the geometry on them: nearest neighbours, clustering, ground removal,
//! rigid transforms. Synchronous and free of I/O.

pub mod dbscan;
pub mod ground;
pub mod knn;
pub mod rigid;

/// One point: metric x, y, z (m) in the sensor frame of the sweep it belongs to.
///
/// A cloud is a `[Point]`: contiguous f32 N x 3, so `cloud.as_flattened()` is the row-major
/// N x 3 matrix the network consumes.
pub type Point = [f32; 3];
