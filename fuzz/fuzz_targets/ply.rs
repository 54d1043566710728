//! `read_ply` on arbitrary bytes: never panics; a cloud it returns is finite, no larger than the
//! input, and reads back identically from a plain binary PLY of it.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::ply::read_ply;
use mbnt_fuzz::{assert_cloud, ply_binary};

fuzz_target!(|data: &[u8]| {
    if let Ok(points) = read_ply(data) {
        assert_cloud(&points, data.len());
        let again = read_ply(&ply_binary(&points)).expect("a binary PLY of a cloud read back");
        assert_eq!(again, points);
    }
});
