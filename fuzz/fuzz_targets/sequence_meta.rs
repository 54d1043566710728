//! `parse_meta_part`, the JSON `meta` part of a multipart upload, on arbitrary bytes: never
//! panics; every refusal is a 422 naming a parameter; accepted metadata has finite numbers (JSON
//! has no NaN or infinity, and the commit checks rely on it) and reads back identically from
//! its own JSON.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbnt::http::ApiError;
use mbnt::http::parse_meta_part;

fuzz_target!(|data: &[u8]| {
    let meta = match parse_meta_part(data) {
        Ok(meta) => meta,
        Err(ApiError::Invalid { parameter: Some(_), .. }) => return,
        Err(e) => panic!("refused without naming a parameter: {e:?}"),
    };
    let numbers = meta.timestamps_s.iter().flatten().chain(meta.poses.iter().flatten().flatten());
    assert!(numbers.clone().all(|v| v.is_finite()), "non-finite number in {meta:?}");
    let mut json = serde_json::Map::new();
    if let Some(name) = &meta.name {
        json.insert("name".into(), name.clone().into());
    }
    if let Some(ts) = &meta.timestamps_s {
        json.insert("timestamps".into(), serde_json::json!(ts));
    }
    if let Some(poses) = &meta.poses {
        json.insert("poses".into(), serde_json::json!(poses));
    }
    let text = serde_json::to_vec(&json).expect("finite metadata serialises");
    assert_eq!(parse_meta_part(&text).expect("its own JSON parses"), meta);
});
