//! `detect_format` and `read_points`, the upload path's dispatch, on arbitrary bytes with a file
//! name chosen by the first byte. Never panics; a cloud is finite and no larger than the input;
//! content decides over the name (a format found without a name is found with every name).
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::{detect_format, read_points};
use mbnt_fuzz::assert_cloud;

/// File names an upload may carry: none, each format's extension, a misleading and an odd one.
const HINTS: [Option<&str>; 9] = [
    None,
    Some("a.ply"),
    Some("a.pcd"),
    Some("a.bin"),
    Some("a.npy"),
    Some("a.feather"),
    Some("frame.BIN"),
    Some("a.txt"),
    Some(".ply"),
];

fuzz_target!(|input: &[u8]| {
    let Some((&selector, data)) = input.split_first() else { return };
    let hint = HINTS[selector as usize % HINTS.len()];
    if let Ok(points) = read_points(data, hint) {
        assert_cloud(&points, data.len());
    }
    if let Ok(format) = detect_format(data, None) {
        for h in HINTS {
            assert_eq!(detect_format(data, h).ok(), Some(format), "name {h:?} overrode the content");
        }
    }
});
