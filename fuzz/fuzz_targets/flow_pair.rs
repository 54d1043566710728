//! `FlowPair::from_npz` on arbitrary bytes: never panics, and a pair it returns keeps its
//! documented layout: finite points, every per-point array aligned with its cloud, ground-truth
//! flow finite exactly on the scoring set, the peer's estimate exactly there.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::io::flow_pair::FlowPair;
use mbnt_fuzz::assert_finite;

fuzz_target!(|data: &[u8]| {
    let Ok(pair) = FlowPair::from_npz(data) else { return };
    assert_finite(&pair.pc1);
    assert_finite(&pair.pc2);
    let n1 = pair.pc1.len();
    assert_eq!(pair.ground1.len(), n1);
    assert_eq!(pair.classes1.len(), n1);
    assert_eq!(pair.gt_flow.len(), n1);
    assert_eq!(pair.valid1.len(), n1);
    assert_eq!(pair.ground2.len(), pair.pc2.len());
    for (i, (flow, &valid)) in pair.gt_flow.iter().zip(&pair.valid1).enumerate() {
        if valid {
            assert!(flow.iter().all(|c| c.is_finite()), "point {i}: scored but flow {flow:?}");
        } else {
            assert!(flow.iter().all(|c| c.is_nan()), "point {i}: not scored but flow {flow:?}");
        }
    }
    if let Some(est) = &pair.est_flow {
        assert_eq!(est.len(), n1);
        for (i, (e, &valid)) in est.iter().zip(&pair.valid1).enumerate() {
            assert_eq!(e.is_some(), valid, "point {i}: an estimate exactly on the scoring set");
        }
    }
});
