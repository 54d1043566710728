//! `read_feather` (Argoverse 2 sweeps, Arrow IPC) on arbitrary bytes: no panic escapes it (the
//! reader turns a panic of arrow-ipc's decoder that its own checks let through into an error, by
//! design); a cloud is finite and reads the same through `read_points`, whose detection finds the
//! format from the content alone.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::feather::read_feather;
use mbnt::io::read_points;
use mbnt_fuzz::assert_finite;

/// libFuzzer's panic hook aborts on every panic, even one the reader catches; with this quiet hook
/// a caught panic is the error the reader returns, and an escaping one still aborts (libfuzzer-sys
/// catches it around the target and aborts).
static QUIET_PANICS: std::sync::Once = std::sync::Once::new();

fuzz_target!(|data: &[u8]| {
    QUIET_PANICS.call_once(|| std::panic::set_hook(Box::new(|_| {})));
    if let Ok(points) = read_feather(data) {
        assert_finite(&points);
        assert_eq!(read_points(data, None).ok().as_ref(), Some(&points), "read_points disagrees");
    }
});
