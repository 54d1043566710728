//! `read_kitti_bin` on arbitrary bytes: never panics, and succeeds exactly when the length is a
//! whole number of 16-byte records with finite x, y, z, returning each record's first three floats.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::kitti::read_kitti_bin;
use mbnt_fuzz::assert_cloud;

fuzz_target!(|data: &[u8]| {
    let records: Vec<[f32; 4]> = data
        .chunks_exact(16)
        .map(|r| std::array::from_fn(|k| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap())))
        .collect();
    let valid = data.len() % 16 == 0 && records.iter().all(|r| r[..3].iter().all(|c| c.is_finite()));
    match read_kitti_bin(data) {
        Ok(points) => {
            assert!(valid, "accepted {} bytes that are not whole finite records", data.len());
            assert_cloud(&points, data.len());
            let expected: Vec<[f32; 3]> = records.iter().map(|r| [r[0], r[1], r[2]]).collect();
            assert_eq!(points, expected);
        }
        Err(e) => assert!(!valid, "refused valid records: {e}"),
    }
});
