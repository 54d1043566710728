//! `read_pcd` on arbitrary bytes: never panics; a cloud it returns is finite, no larger than the
//! input, and is what the generic reader gets from the same bytes (PCD is detected by content).
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::pcd::read_pcd;
use mbnt::io::{Format, detect_format, read_points};
use mbnt_fuzz::assert_cloud;

fuzz_target!(|data: &[u8]| {
    if let Ok(points) = read_pcd(data) {
        assert_cloud(&points, data.len());
        // A file the PCD reader accepts but the dispatcher does not send to it could not be
        // uploaded; the check is only meaningful when no other format's magic comes first.
        if detect_format(data, None).ok() == Some(Format::Pcd) {
            assert_eq!(read_points(data, None).expect("the same bytes through read_points"), points);
        }
    }
});
