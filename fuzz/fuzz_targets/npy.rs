//! `read_npy` and `read_npy_points` on arbitrary bytes: never panic; an array has as many
//! elements as its shape declares and survives a write and a second read unchanged; points are
//! finite, one per row.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::npy::{read_npy, read_npy_points};
use mbnt_fuzz::{assert_cloud, npy_bytes, shape_len};

fuzz_target!(|data: &[u8]| {
    let Ok(array) = read_npy(data) else {
        assert!(read_npy_points(data).is_err(), "points from bytes that are not an array");
        return;
    };
    assert_eq!(array.data.len(), shape_len(&array.shape), "shape {:?}", array.shape);
    let written = npy_bytes(&array);
    let again = read_npy(&written).expect("an array written by write_npy reads back");
    assert_eq!(npy_bytes(&again), written, "the round trip changed the array");
    if let Ok(points) = read_npy_points(data) {
        assert_cloud(&points, data.len());
        assert_eq!(points.len(), array.shape[0]);
    }
});
