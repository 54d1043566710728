//! The HTTP API over a real bound port: every route, bad inputs, auth, the OpenAPI document,
//! restart recovery, a full round trip, and the examples in `api/`.

mod common;

use std::collections::BTreeSet;
use std::io::Read;
use std::sync::Arc;
use std::time::Duration;

use common::{Options, SlowFitter, TestServer, frames, npy_bytes, ply_bytes, read_events};
use mbnt::http::{Limits, ROUTES};
use reqwest::Method;
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};

fn slow(steps: usize, step_ms: u64) -> Options {
    Options { fitter: Arc::new(SlowFitter { steps, step: Duration::from_millis(step_ms) }), ..Options::default() }
}

fn zip_names(bytes: &[u8]) -> Vec<String> {
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(bytes)).expect("a zip archive");
    let mut names: Vec<String> = (0..archive.len()).map(|i| archive.by_index(i).unwrap().name().to_string()).collect();
    names.sort();
    names
}

#[tokio::test]
async fn the_open_routes_answer_without_a_token_and_serve_the_committed_document() {
    let s = TestServer::start_with(Options { token: Some("secret".into()), ..Options::default() }).await;
    let (status, body) = s.send("GET", "/healthz", s.client.get(s.url("/healthz"))).await;
    assert_eq!((status, body), (200, json!({ "status": "ok" })));
    let response = s.client.get(s.url("/openapi.yaml")).send().await.unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(response.headers()["content-type"], "application/yaml");
    let text = response.text().await.unwrap();
    assert_eq!(text, std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/openapi.yaml")).unwrap());
    let response = s.client.get(s.url("/metrics")).send().await.unwrap();
    assert_eq!(response.status(), 200);
    let text = response.text().await.unwrap();
    for needle in [
        "mbnt_jobs{status=\"queued\"} 0",
        "mbnt_fit_iterations_total 0",
        "mbnt_fit_iterations_per_second 0",
        "mbnt_http_request_duration_seconds_bucket{method=\"GET\",route=\"/healthz\",le=\"+Inf\"} 1",
        "mbnt_http_requests_total{method=\"GET\",route=\"/openapi.yaml\",status=\"200\"} 1",
    ] {
        assert!(text.contains(needle), "missing {needle:?} in\n{text}");
    }
}

#[tokio::test]
async fn the_viewer_page_and_its_files_are_served_without_a_token() {
    let s = TestServer::start_with(Options { token: Some("secret".into()), ..Options::default() }).await;
    for asset in mbnt::http::viewer::ASSETS {
        let response = s.client.get(s.url(asset.path)).send().await.unwrap();
        assert_eq!(response.status(), 200, "{}", asset.path);
        assert_eq!(response.headers()["content-type"], asset.content_type, "{}", asset.path);
        assert!(response.headers()["content-security-policy"].to_str().unwrap().contains("script-src 'self'"));
        assert_eq!(response.text().await.unwrap(), asset.body, "{}", asset.path);
    }
    // `/?job=ID` is the same page (the script reads the id); it loads its script and style.
    let response = s.client.get(s.url("/?job=3f1c0a52-0000-4000-8000-000000000000")).send().await.unwrap();
    assert_eq!(response.status(), 200);
    assert!(response.headers()["content-type"].to_str().unwrap().starts_with("text/html"));
    let page = response.text().await.unwrap();
    for needle in ["<canvas id=\"scene\"", "<canvas id=\"loss\"", "/viewer/viewer.js", "/viewer/viewer.css"] {
        assert!(page.contains(needle), "the page lacks {needle}");
    }
    // Beside the files, the same strict answers as everywhere: problems for unknown files and
    // other methods.
    let response = s.client.get(s.url("/viewer/nothing.js")).send().await.unwrap();
    assert_eq!(
        (response.status().as_u16(), response.headers()["content-type"].to_str().unwrap()),
        (404, "application/problem+json")
    );
    let response = s.client.post(s.url("/")).body("x").send().await.unwrap();
    assert_eq!(
        (response.status().as_u16(), response.headers()["content-type"].to_str().unwrap()),
        (405, "application/problem+json")
    );
}

#[tokio::test]
async fn v1_routes_need_the_right_bearer_token_when_one_is_configured() {
    let mut s = TestServer::start_with(Options { token: Some("secret".into()), ..Options::default() }).await;
    let (status, body) = s.get("/v1/sequences", "/v1/sequences").await;
    assert_eq!(status, 200, "{body}");
    s.token = None;
    let response = s.client.get(s.url("/v1/sequences")).send().await.unwrap();
    assert_eq!(response.headers()["www-authenticate"], "Bearer");
    let (status, body) = s.get("/v1/sequences", "/v1/sequences").await;
    assert_eq!((status, body["type"].as_str()), (401, Some("urn:mbnt:problem:unauthorized")));
    s.token = Some("secreT".into());
    assert_eq!(s.get("/v1/jobs", "/v1/jobs").await.0, 401);
    s.token = Some("secret-and-more".into());
    assert_eq!(s.post_json("/v1/jobs", "/v1/jobs", &json!({})).await.0, 401);
}

#[tokio::test]
async fn the_router_and_openapi_yaml_describe_the_same_routes() {
    let s = TestServer::start().await;
    let documented: BTreeSet<(String, String)> = s.spec.operations().into_iter().collect();
    let routed: BTreeSet<(String, String)> =
        ROUTES.iter().map(|r| (r.method.to_string(), r.path.to_string())).collect();
    assert_eq!(documented, routed, "openapi.yaml and mbnt::http::ROUTES differ");
    // Every table entry is really served: no routing 404 or 405 for its method.
    let id = uuid::Uuid::new_v4().to_string();
    for route in ROUTES {
        let path = route.path.replace("{id}", &id);
        let method = Method::from_bytes(route.method.as_bytes()).unwrap();
        let response = s.request(method, &path).send().await.unwrap();
        let status = response.status().as_u16();
        let body: Value = response.json().await.unwrap_or(Value::Null);
        assert_ne!(status, 405, "{route:?}");
        assert!(!(status == 404 && body["detail"] == "no such route"), "{route:?} is not routed: {body}");
    }
    // Unknown routes and methods are problems too.
    let response = s.client.get(s.url("/v2/nothing")).send().await.unwrap();
    assert_eq!(response.status(), 404);
    assert_eq!(response.headers()["content-type"], "application/problem+json");
    let response = s.client.put(s.url("/v1/jobs")).send().await.unwrap();
    assert_eq!(response.status(), 405);
    assert_eq!(response.headers()["content-type"], "application/problem+json");
    let problem: Value = response.json().await.unwrap();
    assert_eq!(problem["type"], "urn:mbnt:problem:method-not-allowed");
}

#[tokio::test]
async fn a_sequence_round_trips_through_fit_query_and_both_label_formats() {
    let s = TestServer::start().await;
    let f = frames(3, 300);
    let (status, seq) = s
        .post_json(
            "/v1/sequences",
            "/v1/sequences",
            &json!({ "name": "demo", "frames": f, "timestamps": [10.0, 10.1, 10.2] }),
        )
        .await;
    assert_eq!(status, 201, "{seq}");
    assert_eq!(seq["frames"], 3);
    assert_eq!(seq["points_per_frame"], json!([300, 300, 300]));
    assert_eq!(seq["time_unit"], "s");
    let id = seq["id"].as_str().unwrap();
    let (status, got) = s.get("/v1/sequences/{id}", &format!("/v1/sequences/{id}")).await;
    assert_eq!((status, &got), (200, &seq));
    let (_, list) = s.get("/v1/sequences", "/v1/sequences").await;
    assert_eq!(list["sequences"][0]["id"], id);

    let job = s.submit(id, "mbnt").await;
    let done = s.wait_status(&job, "succeeded").await;
    assert_eq!(done["progress"]["fraction"], 1.0);
    assert_eq!(done["method"], "mbnt");
    assert_eq!(done["params"]["iterations"], 5);
    let (_, jobs) = s.get("/v1/jobs", &format!("/v1/jobs?status=succeeded&sequence_id={id}")).await;
    assert_eq!(jobs["jobs"].as_array().unwrap().len(), 1);

    // The loss curve: one record per iteration, in order, every term finite.
    let (status, curve) = s.get("/v1/jobs/{id}/losses", &format!("/v1/jobs/{job}/losses")).await;
    assert_eq!(status, 200, "{curve}");
    assert_eq!((curve["job_id"].as_str(), curve["iterations"].as_u64()), (Some(job.as_str()), Some(5)));
    let records = curve["losses"].as_array().unwrap();
    let iterations: Vec<u64> = records.iter().map(|r| r["iteration"].as_u64().unwrap()).collect();
    assert_eq!(iterations, [1, 2, 3, 4, 5]);
    for r in records {
        for term in ["chamfer", "cycle", "rigidity", "total"] {
            assert!(r["loss"][term].as_f64().is_some_and(f64::is_finite), "{r}");
        }
    }
    // The first iteration validates, and the checkpoint's record carries its validation loss.
    assert!(records[0]["validation"]["total"].is_f64(), "{curve}");
    let best = records.iter().find(|r| r["iteration"] == curve["best_iteration"]).expect("the checkpoint's record");
    assert_eq!(best["validation"]["total"], curve["best_validation_loss"], "{curve}");

    // Frame form: the frame's points at its own time are the points themselves.
    let (status, answer) = s
        .post_json(
            "/v1/jobs/{id}/query",
            &format!("/v1/jobs/{job}/query"),
            &json!({ "frame": 1, "indices": [0, 5, 299], "times": [10.1, 10.0, 10.2] }),
        )
        .await;
    assert_eq!(status, 200, "{answer}");
    let positions = answer["positions"].as_array().unwrap();
    assert_eq!(positions.len(), 3);
    for (row, i) in positions.iter().zip([0usize, 5, 299]) {
        assert_eq!(row.as_array().unwrap().len(), 3);
        for c in 0..3 {
            // f32 coordinates survive the JSON round trip exactly; 1e-5 m allows for a model
            // whose displacement at the observation time is a rounding-level non-zero.
            let got = row[0][c].as_f64().unwrap();
            assert!((got - f[1][i][c] as f64).abs() < 1e-5, "point {i}: {got} vs {}", f[1][i][c]);
        }
    }
    // Points form.
    let (status, answer) = s
        .post_json(
            "/v1/jobs/{id}/query",
            &format!("/v1/jobs/{job}/query"),
            &json!({ "points": [[3.0, -1.5, 0.5], [10.0, 0.0, 0.2]], "t": 10.05, "times": [10.0, 10.2] }),
        )
        .await;
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["positions"].as_array().unwrap().len(), 2);
    assert_eq!(answer["positions"][1].as_array().unwrap().len(), 2);

    // Labels: npz with one flow per pair plus the time axis; av2 with one feather per pair.
    let response = s.request(Method::GET, &format!("/v1/jobs/{job}/labels?format=npz")).send().await.unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(response.headers()["content-type"], "application/octet-stream");
    let npz = response.bytes().await.unwrap();
    // No poses: no scene model, so every point's object id is -1, but the arrays are there.
    assert_eq!(
        zip_names(&npz),
        vec!["flow_000.npy", "flow_001.npy", "object_000.npy", "object_001.npy", "object_002.npy", "timestamps.npy"]
    );
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(&npz[..])).unwrap();
    let mut flow = Vec::new();
    archive.by_name("flow_001.npy").unwrap().read_to_end(&mut flow).unwrap();
    assert!(flow.starts_with(b"\x93NUMPY"));
    assert!(String::from_utf8_lossy(&flow[..128]).contains("(300, 3)"));
    let response = s.request(Method::GET, &format!("/v1/jobs/{job}/labels?format=av2")).send().await.unwrap();
    if cfg!(feature = "av2") {
        assert_eq!(response.status(), 200);
        assert_eq!(response.headers()["content-type"], "application/zip");
        let av2 = response.bytes().await.unwrap();
        assert_eq!(zip_names(&av2), vec!["000000.feather", "000001.feather"]);
        let mut archive = zip::ZipArchive::new(std::io::Cursor::new(&av2[..])).unwrap();
        let mut feather = Vec::new();
        archive.by_name("000001.feather").unwrap().read_to_end(&mut feather).unwrap();
        // Arrow IPC files start and end with the magic "ARROW1".
        assert!(feather.starts_with(b"ARROW1") && feather.ends_with(b"ARROW1"));
        let text = String::from_utf8_lossy(&feather);
        for column in ["flow_tx_m", "flow_ty_m", "flow_tz_m", "is_valid", "object_id"] {
            assert!(text.contains(column), "{column} missing from the feather schema");
        }
        // Written a frame at a time: entry k is frame k's Feather file of the npz labels' flow
        // and object ids of that frame.
        #[cfg(feature = "av2")]
        {
            use mbnt::io::npy::NpyData;
            let arrays = mbnt::io::npz::read_npz(&npz).unwrap();
            for k in 0..2 {
                let (NpyData::F32(flat), NpyData::I32(ids)) =
                    (&arrays[&format!("flow_{k:03}")].data, &arrays[&format!("object_{k:03}")].data)
                else {
                    panic!("frame {k}: float32 flows and int32 object ids expected");
                };
                let flow: Vec<[f32; 3]> = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
                let want = mbnt::io::labels::write_flow_feather(Vec::new(), &flow, None, Some(ids)).unwrap();
                let mut entry = Vec::new();
                archive.by_name(&format!("{k:06}.feather")).unwrap().read_to_end(&mut entry).unwrap();
                assert!(entry == want, "frame {k}'s feather entry differs from the npz labels");
            }
        }
    } else {
        assert_eq!(response.status(), 501);
    }
    let (status, problem) = s.get("/v1/jobs/{id}/labels", &format!("/v1/jobs/{job}/labels?format=csv")).await;
    assert_eq!((status, problem["parameter"].as_str()), (422, Some("format")));

    // Cancelling a finished job is a conflict; deleting the sequence removes its jobs.
    let (status, _) = s.post_json("/v1/jobs/{id}/cancel", &format!("/v1/jobs/{job}/cancel"), &json!({})).await;
    assert_eq!(status, 409);
    let (status, _) =
        s.send("DELETE", "/v1/sequences/{id}", s.request(Method::DELETE, &format!("/v1/sequences/{id}"))).await;
    assert_eq!(status, 204);
    assert_eq!(s.get("/v1/sequences/{id}", &format!("/v1/sequences/{id}")).await.0, 404);
    assert_eq!(s.get("/v1/jobs/{id}", &format!("/v1/jobs/{job}")).await.0, 404);
}

#[tokio::test]
async fn a_sequence_with_poses_lists_its_moving_box_as_one_object_and_labels_carry_its_id() {
    let s = TestServer::start().await;
    let t = 6;
    let f = frames(t, 300);
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
    let timestamps: Vec<f64> = (0..t).map(|k| 0.1 * k as f64).collect();
    let (status, seq) = s
        .post_json(
            "/v1/sequences",
            "/v1/sequences",
            &json!({ "frames": f, "timestamps": timestamps, "poses": vec![identity; t] }),
        )
        .await;
    assert_eq!(status, 201, "{seq}");
    let (status, job) = s
        .post_json(
            "/v1/jobs",
            "/v1/jobs",
            &json!({ "sequence_id": seq["id"], "method": "mbnt", "params": common::tiny_params() }),
        )
        .await;
    assert_eq!(status, 202, "{job}");
    let job = job["id"].as_str().unwrap().to_string();
    s.wait_status(&job, "succeeded").await;
    let (status, objects) = s.get("/v1/jobs/{id}/objects", &format!("/v1/jobs/{job}/objects")).await;
    assert_eq!(status, 200, "{objects}");
    assert_eq!(objects["moving_bodies"], true);
    let list = objects["objects"].as_array().unwrap();
    // The box (odd points) is one object over all six frames; the wall is none.
    assert_eq!(list.len(), 1, "{objects}");
    let body = &list[0];
    assert_eq!(body["frames_seen"], json!([0, 1, 2, 3, 4, 5]));
    assert_eq!(body["points_per_frame"], json!([150, 150, 150, 150, 150, 150]));
    // Its pose moves 0.5 m along y per frame, to within 0.1 m: the box is a flat sheet 0.45 m
    // wide whose motion lies in its own plane (only its edges fix it), registered to a model
    // thinned to 0.1 m cubes. The unit tests of fit::bodies hold real boxes to 0.1 m.
    let y = |k: usize| body["poses"][k][7].as_f64().unwrap();
    for k in 1..t {
        assert!((y(k) - y(k - 1) - 0.5).abs() < 0.1, "frame {k}: {} m", y(k) - y(k - 1));
    }
    assert!((y(t - 1) - y(0) - 2.5).abs() < 0.1, "{} m over the sequence", y(t - 1) - y(0));
    // Labels: one object array per frame, the box's points with its id, the wall's -1.
    let response = s.request(Method::GET, &format!("/v1/jobs/{job}/labels?format=npz")).send().await.unwrap();
    assert_eq!(response.status(), 200);
    let npz = response.bytes().await.unwrap();
    let names = zip_names(&npz);
    assert!(names.contains(&"object_005.npy".to_string()), "{names:?}");
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(&npz[..])).unwrap();
    let mut ids = Vec::new();
    archive.by_name("object_003.npy").unwrap().read_to_end(&mut ids).unwrap();
    let header_len = u16::from_le_bytes([ids[8], ids[9]]) as usize;
    let values: Vec<i32> =
        ids[10 + header_len..].chunks_exact(4).map(|b| i32::from_le_bytes(b.try_into().unwrap())).collect();
    assert_eq!(values.len(), 300);
    let id = body["id"].as_i64().unwrap() as i32;
    for (i, v) in values.iter().enumerate() {
        assert_eq!(*v, if i % 2 == 1 { id } else { -1 }, "point {i}");
    }
}

#[tokio::test]
async fn multipart_uploads_read_every_frame_format_with_meta() {
    let s = TestServer::start().await;
    let f = frames(3, 200);
    let mut kitti = Vec::new();
    for p in &f[2] {
        for c in p.iter().chain(&[0.5f32]) {
            kitti.extend(c.to_le_bytes());
        }
    }
    let form = Form::new()
        .part(
            "meta",
            Part::text(r#"{"name": "files", "timestamps": [0.0, 0.1, 0.25]}"#).mime_str("application/json").unwrap(),
        )
        .part("frame", Part::bytes(npy_bytes(&f[0])).file_name("000.npy"))
        .part("frame", Part::bytes(ply_bytes(&f[1])).file_name("001.ply"))
        .part("frame", Part::bytes(kitti).file_name("002.bin"));
    let (status, seq) = s.send("POST", "/v1/sequences", s.request(Method::POST, "/v1/sequences").multipart(form)).await;
    assert_eq!(status, 201, "{seq}");
    assert_eq!(seq["points_per_frame"], json!([200, 200, 200]));
    assert_eq!(seq["timestamps"], json!([0.0, 0.1, 0.25]));
    assert_eq!(seq["name"], "files");
    // The frames are stored exactly: a fitted job's frame query at the frame's time gives them back.
    let job = s.submit(seq["id"].as_str().unwrap(), "ntp").await;
    s.wait_status(&job, "succeeded").await;
    let (_, answer) = s
        .post_json(
            "/v1/jobs/{id}/query",
            &format!("/v1/jobs/{job}/query"),
            &json!({ "frame": 2, "indices": [7], "times": [0.25] }),
        )
        .await;
    assert!((answer["positions"][0][0][1].as_f64().unwrap() - f[2][7][1] as f64).abs() < 1e-5, "{answer}");
}

async fn upload_problem(s: &TestServer, request: reqwest::RequestBuilder) -> (u16, Value) {
    s.send("POST", "/v1/sequences", request).await
}

#[tokio::test]
async fn bad_uploads_are_problems_that_say_what_is_wrong() {
    let s = TestServer::start_with(Options {
        limits: Limits { max_frames: 4, max_points_per_frame: 500, ..Limits::default() },
        ..Options::default()
    })
    .await;
    let post = || s.request(Method::POST, "/v1/sequences");
    let f = frames(2, 50);
    // Malformed frame file.
    let form = Form::new().part("frame", Part::bytes(npy_bytes(&f[0])).file_name("a.npy")).part(
        "frame",
        Part::bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n".to_vec()).file_name("b.ply"),
    );
    let (status, p) = upload_problem(&s, post().multipart(form)).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("frame")), "{p}");
    assert!(p["detail"].as_str().unwrap().contains("frame 1"), "{p}");
    // Unknown format.
    let form = Form::new().part("frame", Part::bytes(vec![1, 2, 3]).file_name("a.xyz"));
    assert_eq!(upload_problem(&s, post().multipart(form)).await.0, 422);
    // Unknown part.
    let form = Form::new().part("frames", Part::bytes(npy_bytes(&f[0])));
    let (status, p) = upload_problem(&s, post().multipart(form)).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("frames")));
    // NaN in a JSON frame (as Python's json.dumps writes it), and a number beyond f32.
    let body = r#"{"frames": [[[0, 0, 0]], [[1, NaN, 0]]]}"#;
    let (status, p) = upload_problem(&s, post().header("content-type", "application/json").body(body)).await;
    assert_eq!(status, 422, "{p}");
    assert!(p["detail"].as_str().unwrap().contains("non-finite"), "{p}");
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": [[[0, 0, 0]], [[1e39, 0, 0]]] }))).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("frames")), "{p}");
    // NaN in a frame file.
    let mut bad = f[1].clone();
    bad[3][2] = f32::NAN;
    let form = Form::new()
        .part("frame", Part::bytes(npy_bytes(&f[0])).file_name("a.npy"))
        .part("frame", Part::bytes(npy_bytes(&bad)).file_name("b.npy"));
    assert_eq!(upload_problem(&s, post().multipart(form)).await.0, 422);
    // Empty frame; a single frame; no frames key.
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": [[[0, 0, 0]], []] }))).await;
    assert_eq!(status, 422);
    assert!(p["detail"].as_str().unwrap().contains("frame 1 has no points"), "{p}");
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": [[[0, 0, 0]]] }))).await;
    assert!(status == 422 && p["detail"].as_str().unwrap().contains("at least 2 frames"), "{p}");
    let (status, p) = upload_problem(&s, post().json(&json!({ "name": "x" }))).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("frames")), "{p}");
    // Unknown field, malformed JSON, bad timestamps, bad poses.
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": f, "colour": 1 }))).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("colour")));
    let (status, p) =
        upload_problem(&s, post().header("content-type", "application/json").body("{\"frames\": [")).await;
    assert_eq!((status, p["type"].as_str()), (400, Some("urn:mbnt:problem:bad-request")));
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": f, "timestamps": [0.0] }))).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("timestamps")));
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": f, "timestamps": [1.0, 1.0] }))).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("timestamps")));
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": f, "poses": vec![vec![1.0f64; 16]] }))).await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("poses")));
    // Wrong or missing content type.
    let (status, p) = upload_problem(&s, post().header("content-type", "text/csv").body("1,2,3")).await;
    assert_eq!((status, p["type"].as_str()), (415, Some("urn:mbnt:problem:unsupported-media-type")));
    assert_eq!(upload_problem(&s, post().body("{}")).await.0, 415);
    // Limits: frames and points per frame.
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": frames(5, 10) }))).await;
    assert_eq!((status, p["limit"].as_str()), (422, Some("max_frames")), "{p}");
    let (status, p) = upload_problem(&s, post().json(&json!({ "frames": frames(2, 501) }))).await;
    assert_eq!((status, p["limit"].as_str()), (422, Some("max_points_per_frame")), "{p}");
    let form = Form::new().part("frame", Part::bytes(npy_bytes(&frames(1, 501)[0])).file_name("a.npy"));
    let (status, p) = upload_problem(&s, post().multipart(form)).await;
    assert_eq!((status, p["limit"].as_str()), (422, Some("max_points_per_frame")), "{p}");
    // Nothing of the failed uploads was kept.
    let (_, list) = s.get("/v1/sequences", "/v1/sequences").await;
    assert_eq!(list["sequences"], json!([]));
    for sub in ["staging", "tmp", "sequences"] {
        assert_eq!(std::fs::read_dir(s.dir().join(sub)).unwrap().count(), 0, "{sub} is not empty");
    }
}

#[tokio::test]
async fn bodies_over_the_configured_limit_are_413_whether_sized_or_streamed() {
    let s = TestServer::start_with(Options {
        limits: Limits { max_body_bytes: 2_000, max_json_bytes: 1_000, ..Limits::default() },
        ..Options::default()
    })
    .await;
    let f = frames(2, 200);
    // Content-Length known up front.
    let (status, p) = s.post_json("/v1/sequences", "/v1/sequences", &json!({ "frames": f })).await;
    assert_eq!((status, p["type"].as_str()), (413, Some("urn:mbnt:problem:body-too-large")), "{p}");
    // Streamed without a length (chunked): the limit applies while reading.
    let chunks: Vec<Result<Vec<u8>, std::io::Error>> =
        serde_json::to_vec(&json!({ "frames": f })).unwrap().chunks(500).map(|c| Ok(c.to_vec())).collect();
    let body = reqwest::Body::wrap_stream(futures_util::stream::iter(chunks));
    let request = s.request(Method::POST, "/v1/sequences").header("content-type", "application/json").body(body);
    let (status, _) = s.send("POST", "/v1/sequences", request).await;
    assert_eq!(status, 413);
    let form = Form::new()
        .part("frame", Part::stream(npy_bytes(&f[0])).file_name("a.npy"))
        .part("frame", Part::stream(npy_bytes(&f[1])).file_name("b.npy"));
    let (status, _) = s.send("POST", "/v1/sequences", s.request(Method::POST, "/v1/sequences").multipart(form)).await;
    assert_eq!(status, 413);
    // The smaller JSON limit of the job routes.
    let big = json!({ "sequence_id": "x".repeat(1_500) });
    let (status, _) = s.post_json("/v1/jobs", "/v1/jobs", &big).await;
    assert_eq!(status, 413);
}

/// Sends `head` (request line and headers), waits, then `body_bytes` bytes of body, and reads
/// the whole answer, over a raw connection: what a client uploading a large file sees.
async fn raw_exchange(base: &str, head: &str, body_bytes: usize) -> std::io::Result<String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(base.trim_start_matches("http://")).await?;
    stream.write_all(head.as_bytes()).await?;
    // The server may answer from the headers alone; the body follows as a slow client's would.
    tokio::time::sleep(Duration::from_millis(300)).await;
    for chunk in vec![b' '; body_bytes].chunks(64 * 1024) {
        stream.write_all(chunk).await?;
    }
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer).await?;
    Ok(String::from_utf8_lossy(&answer).into_owned())
}

#[tokio::test]
async fn a_client_still_sending_an_oversized_body_reads_the_413_instead_of_a_reset() {
    let s = TestServer::start_with(Options {
        limits: Limits { max_body_bytes: 2_000, max_json_bytes: 1_000, ..Limits::default() },
        ..Options::default()
    })
    .await;
    // Over the upload limit by its Content-Length, and over a job route's JSON limit while read.
    for (path, length) in [("/v1/sequences", 4 << 20), ("/v1/jobs", 2 << 20)] {
        let head = format!(
            "POST {path} HTTP/1.1\r\nhost: test\r\ncontent-type: application/json\r\n\
             content-length: {length}\r\nconnection: close\r\n\r\n"
        );
        let answer = raw_exchange(&s.base, &head, length).await.unwrap_or_else(|e| panic!("{path}: {e}"));
        assert!(answer.starts_with("HTTP/1.1 413"), "{path}: {answer}");
        assert!(answer.contains("urn:mbnt:problem:body-too-large"), "{path}: {answer}");
    }
}

#[tokio::test]
async fn bad_job_requests_name_the_parameter() {
    let s = TestServer::start_with(Options {
        limits: Limits { max_iterations: 50, ..Limits::default() },
        ..Options::default()
    })
    .await;
    let seq = s.upload(&frames(2, 50), None).await;
    let few = json!({ "iterations": 5 });
    let cases = [
        (json!({ "sequence_id": uuid::Uuid::new_v4(), "params": few }), "sequence_id"),
        (json!({ "sequence_id": "not-a-uuid", "params": few }), "sequence_id"),
        (json!({ "sequence_id": seq, "method": "magic" }), "method"),
        (json!({ "sequence_id": seq, "params": { "learning_rate": -1.0 } }), "params.learning_rate"),
        (json!({ "sequence_id": seq, "params": { "hidden_layers": 0 } }), "params.hidden_layers"),
        (json!({ "sequence_id": seq, "params": { "bogus": 1 } }), "params.bogus"),
        (json!({ "sequence_id": seq, "params": { "iterations": "many" } }), "params"),
        (json!({ "sequence_id": seq, "colour": "red" }), "colour"),
        (json!({ "method": "ntp" }), "sequence_id"),
        // null is no value of a parameter (openapi.yaml has none nullable): leave it out instead.
        (json!({ "sequence_id": seq, "params": { "iterations": 5, "moving_bodies": null } }), "params.moving_bodies"),
        (json!({ "sequence_id": seq, "params": null }), "params"),
    ];
    for (body, parameter) in cases {
        let (status, p) = s.post_json("/v1/jobs", "/v1/jobs", &body).await;
        assert_eq!((status, p["parameter"].as_str()), (422, Some(parameter)), "{body} -> {p}");
    }
    let (status, p) = s.post_json("/v1/jobs", "/v1/jobs", &json!({ "sequence_id": seq, "method": null })).await;
    assert_eq!(status, 422, "{p}");
    // An integer written with a zero fraction is an integer, as in JSON Schema.
    let (status, job) = s
        .post_json("/v1/jobs", "/v1/jobs", &json!({ "sequence_id": seq, "params": { "iterations": 5.0, "seed": 2.0 } }))
        .await;
    assert_eq!((status, &job["params"]["iterations"], &job["params"]["seed"]), (202, &json!(5), &json!(2)), "{job}");
    // The list routes' limit is 1 to 1000, as documented, not clamped.
    for path in ["/v1/jobs?limit=0", "/v1/jobs?limit=1001", "/v1/sequences?limit=0", "/v1/sequences?limit=5000"] {
        let (status, p) = s.get(path.split('?').next().unwrap(), path).await;
        assert_eq!((status, p["parameter"].as_str()), (422, Some("limit")), "{path} -> {p}");
    }
    assert_eq!(s.get("/v1/sequences", "/v1/sequences?limit=1000").await.0, 200);
    let (status, p) =
        s.post_json("/v1/jobs", "/v1/jobs", &json!({ "sequence_id": seq, "params": { "iterations": 51 } })).await;
    assert_eq!((status, p["limit"].as_str()), (422, Some("max_iterations")), "{p}");
    let request = s.request(Method::POST, "/v1/jobs").header("content-type", "text/plain").body("{}");
    assert_eq!(s.send("POST", "/v1/jobs", request).await.0, 415);
    let request =
        s.request(Method::POST, "/v1/jobs").header("content-type", "application/json").body("{\"sequence_id\": ");
    assert_eq!(s.send("POST", "/v1/jobs", request).await.0, 400);
    let (status, p) = s.get("/v1/jobs", "/v1/jobs?status=done").await;
    assert_eq!((status, p["parameter"].as_str()), (422, Some("status")));
}

#[tokio::test]
async fn unknown_ids_are_404_on_every_route_with_an_id() {
    let s = TestServer::start().await;
    for id in [uuid::Uuid::new_v4().to_string(), "not-a-uuid".to_string()] {
        for route in ROUTES.iter().filter(|r| r.path.contains("{id}")) {
            let path = route.path.replace("{id}", &id);
            let method = Method::from_bytes(route.method.as_bytes()).unwrap();
            let mut request = s.request(method, &path);
            if route.method == "POST" {
                request = request.json(&json!({ "times": [0.0], "frame": 0 }));
            }
            let (status, p) = s.send(route.method, route.path, request).await;
            assert_eq!((status, p["type"].as_str()), (404, Some("urn:mbnt:problem:not-found")), "{route:?}");
        }
    }
}

#[tokio::test]
async fn queries_need_a_succeeded_job_and_valid_points_and_times() {
    let s = TestServer::start_with(Options {
        limits: Limits { max_query_points: 10, max_query_times: 3, ..Limits::default() },
        ..slow(2_000, 5)
    })
    .await;
    let seq = s.upload(&frames(3, 40), None).await;
    let running = s.submit(&seq, "ntp").await;
    let queued = s.submit(&seq, "ntp").await;
    s.wait_status(&running, "running").await;
    for job in [&running, &queued] {
        let (status, p) = s
            .post_json("/v1/jobs/{id}/query", &format!("/v1/jobs/{job}/query"), &json!({ "frame": 0, "times": [0.0] }))
            .await;
        assert_eq!(status, 409, "{p}");
        let (status, _) = s.get("/v1/jobs/{id}/labels", &format!("/v1/jobs/{job}/labels")).await;
        assert_eq!(status, 409);
        let (status, p) = s.get("/v1/jobs/{id}/poses", &format!("/v1/jobs/{job}/poses")).await;
        assert_eq!((status, p["type"].as_str()), (409, Some("urn:mbnt:problem:conflict")), "{p}");
        let (status, p) = s.get("/v1/jobs/{id}/losses", &format!("/v1/jobs/{job}/losses")).await;
        assert_eq!((status, p["type"].as_str()), (409, Some("urn:mbnt:problem:conflict")), "{p}");
    }
    // Cancel both: the queued one at once, the running one at its next iteration.
    let (status, j) = s.post_json("/v1/jobs/{id}/cancel", &format!("/v1/jobs/{queued}/cancel"), &json!({})).await;
    assert_eq!((status, j["status"].as_str()), (202, Some("cancelled")));
    let (status, j) = s.post_json("/v1/jobs/{id}/cancel", &format!("/v1/jobs/{running}/cancel"), &json!({})).await;
    assert_eq!((status, j["cancel_requested"].as_bool()), (202, Some(true)));
    let cancelled = s.wait_status(&running, "cancelled").await;
    assert!(cancelled["finished_at"].is_string());
    assert_eq!(s.post_json("/v1/jobs/{id}/cancel", &format!("/v1/jobs/{running}/cancel"), &json!({})).await.0, 202);

    // A job that succeeds quickly: the slow fitter's steps are the worker's; use a fresh
    // server with the real fitter on the same data.
    let dir = s.stop().await;
    let s = TestServer::start_with(Options {
        limits: Limits { max_query_points: 10, max_query_times: 3, ..Limits::default() },
        dir: Some(dir.clone()),
        ..Options::default()
    })
    .await;
    let job = s.submit(&seq, "ntp").await;
    s.wait_status(&job, "succeeded").await;
    let q = |body: Value| {
        let path = format!("/v1/jobs/{job}/query");
        let s = &s;
        async move { s.post_json("/v1/jobs/{id}/query", &path, &body).await }
    };
    let cases = [
        (json!({ "frame": 0, "indices": [0], "times": [5.0] }), "times"),
        (json!({ "frame": 0, "indices": [0], "times": [] }), "times"),
        (json!({ "frame": 3, "indices": [0], "times": [0.0] }), "frame"),
        (json!({ "frame": 0, "indices": [40], "times": [0.0] }), "indices"),
        (json!({ "frame": 0, "indices": [0], "t": 0.0, "times": [0.0] }), "t"),
        (json!({ "points": [[0, 0, 0]], "times": [0.0] }), "t"),
        (json!({ "points": [[0, 0, 0]], "t": -1.0, "times": [0.0] }), "t"),
        (json!({ "points": [[1e39, 0, 0]], "t": 0.0, "times": [0.0] }), "points"),
        (json!({ "times": [0.0] }), "frame"),
        (json!({ "frame": 0 }), "times"),
        (json!({ "frame": 0, "times": [0.0], "speed": 1 }), "speed"),
    ];
    for (body, parameter) in cases {
        let (status, p) = q(body.clone()).await;
        assert_eq!((status, p["parameter"].as_str()), (422, Some(parameter)), "{body} -> {p}");
    }
    let request = s
        .request(Method::POST, &format!("/v1/jobs/{job}/query"))
        .header("content-type", "application/json")
        .body(r#"{"points": [[0, NaN, 0]], "t": 0, "times": [0]}"#);
    let (status, p) = s.send("POST", "/v1/jobs/{id}/query", request).await;
    assert_eq!(status, 422, "{p}");
    for (body, limit) in [
        (json!({ "frame": 0, "times": [0.0] }), "max_query_points"),
        (json!({ "points": vec![[0.0, 0.0, 0.0]; 11], "t": 0.0, "times": [0.0] }), "max_query_points"),
        (json!({ "frame": 0, "indices": [0], "times": [0.0, 0.5, 1.0, 2.0] }), "max_query_times"),
    ] {
        let (status, p) = q(body.clone()).await;
        assert_eq!((status, p["limit"].as_str()), (422, Some(limit)), "{body} -> {p}");
    }
    let (status, a) = q(json!({ "frame": 0, "indices": [1, 2], "times": [0.0, 0.5, 2.0] })).await;
    assert_eq!(status, 200, "{a}");
    // As in openapi.yaml: whole numbers may carry a zero fraction, and a field is never null.
    let (status, b) = q(json!({ "frame": 0.0, "indices": [1.0, 2], "times": [0.0, 0.5, 2.0] })).await;
    assert_eq!((status, &b), (200, &a));
    for body in [
        json!({ "frame": 0, "t": null, "times": [0.0] }),
        json!({ "frame": 0, "indices": null, "times": [0.0] }),
        json!({ "frame": null, "points": [[0, 0, 0]], "t": 0.0, "times": [0.0] }),
        json!({ "frame": 0.5, "times": [0.0] }),
    ] {
        let (status, p) = q(body.clone()).await;
        assert_eq!((status, p["type"].as_str()), (422, Some("urn:mbnt:problem:invalid-input")), "{body} -> {p}");
    }
    drop(s);
    let _ = std::fs::remove_dir_all(dir);
}

/// Asks for `job`'s answers on route `route` (0: a query of frame 1, 1: labels, 2: objects), all
/// of which need its stored result.
async fn result_answer(s: &TestServer, job: &str, route: usize) -> (u16, Value) {
    match route {
        0 => {
            let body = json!({ "frame": 1, "times": [0.0] });
            s.post_json("/v1/jobs/{id}/query", &format!("/v1/jobs/{job}/query"), &body).await
        }
        1 => s.get("/v1/jobs/{id}/labels", &format!("/v1/jobs/{job}/labels")).await,
        _ => s.get("/v1/jobs/{id}/objects", &format!("/v1/jobs/{job}/objects")).await,
    }
}

#[tokio::test]
async fn an_unreadable_stored_result_is_a_problem_naming_the_job_and_the_job_fails_with_the_cause() {
    let s = TestServer::start().await;
    let seq = s.upload(&frames(3, 40), None).await;
    let (truncated, old_version) = (s.submit(&seq, "ntp").await, s.submit(&seq, "ntp").await);
    let other_seq = s.upload(&frames(3, 40), None).await;
    let (by_frame, by_labels) = (s.submit(&other_seq, "ntp").await, s.submit(&other_seq, "ntp").await);
    for job in [&truncated, &old_version, &by_frame, &by_labels] {
        s.wait_status(job, "succeeded").await;
    }
    // Damage the files before any query reads them (queries cache models).
    let model = |job: &str| s.dir().join("models").join(format!("{job}.mbnt"));
    let bytes = std::fs::read(model(&truncated)).unwrap();
    std::fs::write(model(&truncated), &bytes[..bytes.len() / 2]).unwrap();
    let mut bytes = std::fs::read(model(&old_version)).unwrap();
    bytes[7] = b'0'; // MBNTMDL1 -> MBNTMDL0: a format this server does not know
    std::fs::write(model(&old_version), &bytes).unwrap();
    let frame_1 = s.dir().join("sequences").join(&other_seq).join("frame_00001.f32");
    let bytes = std::fs::read(&frame_1).unwrap();
    std::fs::write(&frame_1, &bytes[..bytes.len() - 5]).unwrap();

    for (job, route, cause) in [
        (&truncated, 0, "the model file cannot be read: model file truncated"),
        (&old_version, 1, "the model file cannot be read: not an mbnt model file (bad magic or version)"),
        (&by_frame, 0, "the sequence's frames: corrupt stored data: frame 1 of sequence"),
        (&by_labels, 1, "the sequence's frames: corrupt stored data: frame 1 of sequence"),
    ] {
        // The first request that needs the file says what is wrong, naming the job.
        let (status, p) = result_answer(&s, job, route).await;
        assert_eq!((status, p["type"].as_str()), (409, Some("urn:mbnt:problem:result-unreadable")), "{p}");
        assert_eq!(p["job_id"].as_str(), Some(job.as_str()), "{p}");
        let detail = p["detail"].as_str().unwrap();
        assert!(detail.starts_with(&format!("job {job}: the stored result cannot be read: ")), "{detail}");
        assert!(detail.contains(cause) && detail.ends_with("the job is now marked failed"), "{detail}");
        assert!(!detail.contains(s.dir().to_str().unwrap()), "no server path in a problem: {detail}");
        // The job is failed with the cause, and every route now says so.
        let (_, view) = s.get("/v1/jobs/{id}", &format!("/v1/jobs/{job}")).await;
        assert_eq!(view["status"], "failed", "{view}");
        let error = view["error"].as_str().unwrap();
        assert!(error.starts_with("the stored result cannot be read: ") && error.contains(cause), "{error}");
        for route in 0..3 {
            let (status, p) = result_answer(&s, job, route).await;
            assert_eq!((status, p["type"].as_str()), (409, Some("urn:mbnt:problem:conflict")), "{p}");
            assert!(p["detail"].as_str().unwrap().contains(error), "{p}");
        }
    }
    // Only the damaged results failed: a new job on the undamaged sequence succeeds and answers.
    let fine = s.submit(&seq, "ntp").await;
    s.wait_status(&fine, "succeeded").await;
    let (status, a) = result_answer(&s, &fine, 0).await;
    assert_eq!(status, 200, "{a}");
}

/// Three sweeps of a room-sized corner (floor and three walls, 0.5 m grid) from a sensor that
/// does not move: enough structure for the odometry.
fn corner_frames() -> Vec<Vec<[f32; 3]>> {
    let mut points = Vec::new();
    for i in 0..60 {
        for j in 0..60 {
            let (u, v) = (-15.0 + 0.5 * i as f32, 0.25 * j as f32);
            points.push([u, -15.0 + 0.5 * j as f32, -1.5]);
            points.push([12.0, u, -1.5 + v]);
            points.push([u, 9.0, -1.5 + v]);
            points.push([u, -10.0, -1.5 + v]);
        }
    }
    vec![points; 3]
}

#[tokio::test]
async fn poses_are_the_estimate_or_the_uploaded_ones_and_a_fit_without_any_is_a_conflict() {
    let s = TestServer::start().await;
    let f = corner_frames();
    let seq = s.upload(&f, Some(vec![0.0, 0.1, 0.2])).await;
    // The odometry is off by default (docs/benchmarks.md section 8): asked for here.
    let mut auto = common::tiny_params();
    auto["odometry"] = json!("auto");
    let (status, queued) =
        s.post_json("/v1/jobs", "/v1/jobs", &json!({ "sequence_id": seq, "method": "ntp", "params": auto })).await;
    assert_eq!(status, 202, "{queued}");
    let job = queued["id"].as_str().unwrap().to_string();
    s.wait_status(&job, "succeeded").await;
    let (status, body) = s.get("/v1/jobs/{id}/poses", &format!("/v1/jobs/{job}/poses")).await;
    assert_eq!((status, body["estimated"].as_bool()), (200, Some(true)), "{body}");
    let poses = body["poses"].as_array().unwrap();
    assert_eq!(poses.len(), 3);
    // The sensor stood still: every estimate is the identity, to well under a millimetre.
    for pose in poses {
        for (i, v) in pose.as_array().unwrap().iter().enumerate() {
            let identity = if i % 5 == 0 { 1.0 } else { 0.0 };
            assert!((v.as_f64().unwrap() - identity).abs() < 1e-4, "{pose}");
        }
    }

    // Uploaded poses come back as given, not estimated.
    let shifted = |x: f64| vec![1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
    let given = vec![shifted(0.0), shifted(0.5), shifted(1.0)];
    let (status, with_poses) =
        s.post_json("/v1/sequences", "/v1/sequences", &json!({ "frames": f, "poses": given })).await;
    assert_eq!(status, 201, "{with_poses}");
    let job = s.submit(with_poses["id"].as_str().unwrap(), "ntp").await;
    s.wait_status(&job, "succeeded").await;
    let (status, body) = s.get("/v1/jobs/{id}/poses", &format!("/v1/jobs/{job}/poses")).await;
    assert_eq!((status, &body["estimated"], &body["poses"]), (200, &json!(false), &json!(given)), "{body}");

    // Odometry off and no poses uploaded: the fit worked in sensor coordinates.
    let mut params = common::tiny_params();
    params["odometry"] = json!("off");
    let (status, queued) =
        s.post_json("/v1/jobs", "/v1/jobs", &json!({ "sequence_id": seq, "method": "ntp", "params": params })).await;
    assert_eq!(status, 202, "{queued}");
    let job = queued["id"].as_str().unwrap();
    s.wait_status(job, "succeeded").await;
    let (status, p) = s.get("/v1/jobs/{id}/poses", &format!("/v1/jobs/{job}/poses")).await;
    assert_eq!(status, 409, "{p}");
    assert!(p["detail"].as_str().unwrap().contains("without poses"), "{p}");
}

#[tokio::test]
async fn a_sequence_with_an_active_job_cannot_be_deleted() {
    let s = TestServer::start_with(slow(100_000, 5)).await;
    let seq = s.upload(&frames(2, 30), None).await;
    let job = s.submit(&seq, "ntp").await;
    let path = format!("/v1/sequences/{seq}");
    let (status, p) = s.send("DELETE", "/v1/sequences/{id}", s.request(Method::DELETE, &path)).await;
    assert_eq!((status, p["type"].as_str()), (409, Some("urn:mbnt:problem:conflict")));
    s.post_json("/v1/jobs/{id}/cancel", &format!("/v1/jobs/{job}/cancel"), &json!({})).await;
    s.wait_status(&job, "cancelled").await;
    assert_eq!(s.send("DELETE", "/v1/sequences/{id}", s.request(Method::DELETE, &path)).await.0, 204);
}

#[tokio::test]
async fn the_event_stream_reports_progress_and_ends_with_the_final_state() {
    let s = TestServer::start_with(slow(50, 20)).await;
    let seq = s.upload(&frames(2, 30), None).await;
    let job = s.submit(&seq, "ntp").await;
    let response = s.request(Method::GET, &format!("/v1/jobs/{job}/events")).send().await.unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(response.headers()["content-type"], "text/event-stream");
    let events = read_events(response, Duration::from_secs(60)).await;
    let (last_name, last) = events.last().unwrap();
    assert_eq!((last_name.as_str(), last["status"].as_str()), ("end", Some("succeeded")));
    assert!(
        events
            .iter()
            .any(|(n, j)| n == "progress" && j["status"] == "running" && j["progress"]["iteration"].as_u64() > Some(0))
    );
    for (_, j) in &events {
        let mut errors = Vec::new();
        s.spec.validate(&json!({ "$ref": "#/components/schemas/Job" }), j, "$", &mut errors);
        assert!(errors.is_empty(), "{errors:?}");
    }
    // A finished job's stream is its final state, then the end.
    let response = s.request(Method::GET, &format!("/v1/jobs/{job}/events")).send().await.unwrap();
    let events = read_events(response, Duration::from_secs(10)).await;
    assert_eq!(events.len(), 1);
    assert_eq!(events[0].0, "end");
}

#[tokio::test]
async fn a_job_interrupted_by_a_restart_runs_again_and_the_sequence_is_intact() {
    let s = TestServer::start_with(slow(100_000, 5)).await;
    let f = frames(3, 100);
    let seq = s.upload(&f, Some(vec![0.0, 0.1, 0.2])).await;
    let (_, before) = s.get("/v1/sequences/{id}", &format!("/v1/sequences/{seq}")).await;
    let job = s.submit(&seq, "ntp").await;
    // Wait for persisted progress (written about once a second), then stop mid-fit.
    let running = s.wait_job(&job, Duration::from_secs(30), |j| j["progress"]["iteration"].as_u64() > Some(0)).await;
    assert_eq!(running["status"], "running");
    let dir = s.stop().await;
    // The stop put the job back in the queue; make the database look as after a crash
    // (kill -9 mid-fit: the row still says running), which the next start must recover.
    let db = rusqlite::Connection::open(dir.join("mbnt.sqlite3")).unwrap();
    let status: String = db.query_row("SELECT status FROM jobs WHERE id = ?1", [&job], |r| r.get(0)).unwrap();
    assert_eq!(status, "queued");
    assert_eq!(db.execute("UPDATE jobs SET status = 'running', attempts = 1 WHERE id = ?1", [&job]).unwrap(), 1);
    drop(db);

    let s = TestServer::start_with(Options { dir: Some(dir.clone()), ..Options::default() }).await;
    let done = s.wait_status(&job, "succeeded").await;
    assert_eq!(done["attempts"], 2);
    let (_, after) = s.get("/v1/sequences/{id}", &format!("/v1/sequences/{seq}")).await;
    assert_eq!(before, after);
    let (status, a) = s
        .post_json(
            "/v1/jobs/{id}/query",
            &format!("/v1/jobs/{job}/query"),
            &json!({ "frame": 2, "indices": [99], "times": [0.2] }),
        )
        .await;
    assert_eq!(status, 200, "{a}");
    for c in 0..3 {
        assert!((a["positions"][0][0][c].as_f64().unwrap() - f[2][99][c] as f64).abs() < 1e-5, "{a}");
    }
    drop(s);
    let _ = std::fs::remove_dir_all(dir);
}

#[tokio::test]
async fn metrics_count_jobs_by_status_and_fit_iterations() {
    let s = TestServer::start().await;
    let seq = s.upload(&frames(2, 30), None).await;
    let job = s.submit(&seq, "nsfp").await;
    s.wait_status(&job, "succeeded").await;
    let text = s.client.get(s.url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(text.contains("mbnt_jobs{status=\"succeeded\"} 1"), "{text}");
    let iterations: u64 =
        text.lines().find_map(|l| l.strip_prefix("mbnt_fit_iterations_total ")).and_then(|v| v.parse().ok()).unwrap();
    assert!(iterations > 0);
    assert!(text.contains("route=\"/v1/jobs/{id}\""), "latency is keyed by route template: {text}");
}

/// Replaces `{{name}}` with captured values in every string of `v`.
fn substitute(v: &Value, vars: &std::collections::HashMap<String, String>) -> Value {
    match v {
        Value::String(s) => {
            let mut s = s.clone();
            for (k, val) in vars {
                s = s.replace(&format!("{{{{{k}}}}}"), val);
            }
            Value::String(s)
        }
        Value::Array(a) => Value::Array(a.iter().map(|x| substitute(x, vars)).collect()),
        Value::Object(o) => Value::Object(o.iter().map(|(k, x)| (k.clone(), substitute(x, vars))).collect()),
        other => other.clone(),
    }
}

/// Whether `actual` has every field of `expected` with the same value (`"*"` matches anything
/// present; arrays compare element-wise).
fn contains(actual: &Value, expected: &Value) -> bool {
    match (actual, expected) {
        (_, Value::String(s)) if s == "*" => !actual.is_null(),
        (Value::Object(a), Value::Object(e)) => e.iter().all(|(k, ev)| a.get(k).is_some_and(|av| contains(av, ev))),
        (Value::Array(a), Value::Array(e)) => a.len() == e.len() && a.iter().zip(e).all(|(x, y)| contains(x, y)),
        _ => actual == expected,
    }
}

#[tokio::test]
async fn the_api_examples_replay() {
    let s = TestServer::start().await;
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("api");
    let mut files: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.retain(|p| p.extension().is_some_and(|e| e == "json"));
    files.sort();
    assert!(files.len() >= 10, "api/ holds the examples");
    let mut vars = std::collections::HashMap::new();
    for file in files {
        let name = file.file_name().unwrap().to_string_lossy().to_string();
        let example: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
        let example = substitute(&example, &vars);
        let req = &example["request"];
        let method = req["method"].as_str().unwrap();
        let path = req["path"].as_str().unwrap();
        let template = req["route"].as_str().unwrap();
        let mut request = s.request(Method::from_bytes(method.as_bytes()).unwrap(), path);
        if let Some(body) = req.get("body") {
            request = request.json(body);
        }
        if let Some(raw) = req.get("raw_body").and_then(Value::as_str) {
            request = request.body(raw.to_string());
        }
        for (k, v) in req.get("headers").and_then(Value::as_object).into_iter().flatten() {
            request = request.header(k.as_str(), v.as_str().unwrap());
        }
        let expected = &example["response"];
        let (status, body) = if let Some(until) = example.get("wait_until") {
            let (field, value) = (until["field"].as_str().unwrap(), &until["equals"]);
            let id = path.rsplit('/').next().unwrap();
            let job = s.wait_job(id, Duration::from_secs(60), |j| j.pointer(field) == Some(value)).await;
            (200, job)
        } else {
            s.send(method, template, request).await
        };
        assert_eq!(status, expected["status"].as_u64().unwrap() as u16, "{name}: {body}");
        if let Some(e) = expected.get("body") {
            assert!(contains(&body, e), "{name}: {body} does not contain {e}");
        }
        for (var, pointer) in expected.get("capture").and_then(Value::as_object).into_iter().flatten() {
            let value = body.pointer(pointer.as_str().unwrap()).and_then(Value::as_str).unwrap();
            vars.insert(var.clone(), value.to_string());
        }
    }
}

#[tokio::test]
async fn shutdown_ends_open_event_streams_and_requeues_the_running_job() {
    let s = TestServer::start_with(slow(100_000, 5)).await;
    let seq = s.upload(&frames(2, 30), None).await;
    let job = s.submit(&seq, "ntp").await;
    s.wait_status(&job, "running").await;
    let events = s.request(Method::GET, &format!("/v1/jobs/{job}/events")).send().await.unwrap();
    assert_eq!(events.status(), 200);
    // A graceful shutdown must not wait for the stream's client to hang up.
    let dir = tokio::time::timeout(Duration::from_secs(20), s.stop()).await.expect("shutdown completes");
    let s = TestServer::start_with(Options {
        dir: Some(dir.clone()),
        fitter: Arc::new(SlowFitter { steps: 100_000, step: Duration::from_millis(5) }),
        workers: 1,
        ..Options::default()
    })
    .await;
    let (_, j) = s.get("/v1/jobs/{id}", &format!("/v1/jobs/{job}")).await;
    assert!(j["status"] == "queued" || j["status"] == "running", "{j}");
    drop(events);
    s.stop().await;
    let _ = std::fs::remove_dir_all(dir);
}
