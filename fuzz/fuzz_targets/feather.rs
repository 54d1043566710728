//! `read_feather` (Argoverse 2 sweeps, Arrow IPC) on arbitrary bytes: never panics (a panic of
//! arrow-ipc's decoder that the reader's checks let through aborts here, though the reader turns
//! it into an error in production); a cloud is finite and reads the same through `read_points`,
//! whose detection finds the format from the content alone.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::feather::read_feather;
use mbnt::io::read_points;
use mbnt_fuzz::assert_finite;

fuzz_target!(|data: &[u8]| {
    if let Ok(points) = read_feather(data) {
        assert_finite(&points);
        assert_eq!(read_points(data, None).ok().as_ref(), Some(&points), "read_points disagrees");
    }
});
