//! The `params` of `POST /v1/jobs` on arbitrary bytes, as the handler reads them: JSON, then
//! `strict::fit_params_object` (JSON Schema's reading), then `FitParams` and its `check` for a
//! method chosen by the first byte. Never panics; an accepted object has no `null` and no whole
//! number left as a float; checked parameters stay within the iteration cap and survive a JSON
//! round trip (as the store keeps them).
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::fit::{FitParams, MAX_ITERATIONS, Method, ValidFitParams};
use mbnt::http::strict::fit_params_object;
use serde_json::Value;

fuzz_target!(|input: &[u8]| {
    let Some((&selector, data)) = input.split_first() else { return };
    let Ok(value) = serde_json::from_slice::<Value>(data) else { return };
    let Ok(object) = fit_params_object(value) else { return };
    for (name, v) in &object {
        assert!(!v.is_null(), "params.{name} is null but accepted");
        if let Value::Number(n) = v {
            let whole = n.as_f64().is_some_and(|f| f >= 0.0 && f < 18_446_744_073_709_551_616.0 && f.fract() == 0.0);
            assert!(!whole || n.is_u64() || n.is_i64(), "params.{name} = {n} left as a float");
        }
    }
    let Ok(params) = serde_json::from_value::<FitParams>(object.into()) else { return };
    let method = Method::ALL[selector as usize % Method::ALL.len()];
    let Ok(valid) = params.check(method) else { return };
    assert!((1..=MAX_ITERATIONS).contains(&valid.iterations), "iterations {}", valid.iterations);
    // Windows overlap and each keeps a frame of its own.
    assert!((1..valid.window_frames).contains(&valid.window_overlap_frames), "window overlap");
    // The store keeps checked parameters as JSON. Unchecked ones need not survive: a finite
    // JSON number beyond f32's range reads as infinity and is written back as `null` (found by
    // this target; `check` refuses it).
    let text = serde_json::to_vec(&valid).expect("checked parameters serialise");
    assert_eq!(serde_json::from_slice::<ValidFitParams>(&text).expect("their JSON reads back"), valid);
});
