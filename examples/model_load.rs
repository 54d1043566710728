//! What loading a stitched model costs, lazily and eagerly (issue 21): the time to load a model
//! file and to answer one query, and how many windows that decodes.
//!
//! ```text
//! cargo run --release --example model_load -- resave MODEL_FILE OUT_FILE
//! cargo run --release --example model_load -- lazy|eager MODEL_FILE [REPEATS]
//! ```
//!
//! `resave` writes the model back with the current writer (its header then names each window's
//! frames). `lazy` loads the file as the service does (windows decoded on first use); `eager`
//! also decodes every window at load, as loading did before windows loaded lazily. Each load
//! is repeated `REPEATS` times (default 5) and the median is printed; then one query (frame
//! `T/2`'s first 1,000 points to the next frame's time) is answered. Run each mode in its own
//! process under `/usr/bin/time -v` for its peak resident memory.

use std::time::Instant;

use mbnt::model::FittedModel;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let usage = "usage: model_load resave MODEL_FILE OUT_FILE | model_load lazy|eager MODEL_FILE [REPEATS]";
    let (mode, path) = match (args.get(1), args.get(2)) {
        (Some(mode), Some(path)) => (mode.as_str(), path),
        _ => anyhow::bail!(usage),
    };
    if mode == "resave" {
        let out = args.get(3).ok_or_else(|| anyhow::anyhow!(usage))?;
        let model = FittedModel::from_vec(std::fs::read(path)?).map_err(anyhow::Error::msg)?;
        std::fs::write(out, model.to_bytes()?)?;
        return Ok(());
    }
    let eager = match mode {
        "lazy" => false,
        "eager" => true,
        _ => anyhow::bail!(usage),
    };
    let repeats: usize = args.get(3).map_or(Ok(5), |r| r.parse())?;
    let mut load_s = Vec::with_capacity(repeats);
    let mut model = None;
    for _ in 0..repeats.max(1) {
        // The file is read outside the timing: the service's store hands the bytes over.
        let bytes = std::fs::read(path)?;
        let start = Instant::now();
        let loaded = FittedModel::from_vec(bytes).map_err(anyhow::Error::msg)?;
        if eager {
            loaded.windows()?;
        }
        load_s.push(start.elapsed().as_secs_f64());
        model = Some(loaded);
    }
    let model = model.expect("loaded at least once");
    let rss_loaded_mib = rss_mib();
    load_s.sort_by(f64::total_cmp);
    let median_s = load_s[load_s.len() / 2];
    let decoded_at_load = model.decoded_windows();
    let axis = model.time_axis();
    let k = axis.frames() / 2;
    // A query point grid around the sensor: what a frame's points look like to the model.
    let points: Vec<[f32; 3]> =
        (0..1000).map(|i| [(i % 40) as f32 * 1.5 - 30.0, (i / 40) as f32 * 2.0 - 25.0, 0.5]).collect();
    let start = Instant::now();
    let answers = model.positions(&points, axis.frame_time(k), &[axis.frame_time(k + 1)])?;
    let query_s = start.elapsed().as_secs_f64();
    println!(
        "{mode}: {} frames, {} windows; load {:.2} ms (median of {}), {decoded_at_load} windows decoded at load; \
         one query at frame {k} ({} points) {:.2} ms, {} windows decoded after it",
        axis.frames(),
        model.window_starts().len(),
        median_s * 1e3,
        load_s.len(),
        answers.len(),
        query_s * 1e3,
        model.decoded_windows(),
    );
    // What every window decoded adds (resident memory; the file's bytes are freed once every window is decoded).
    model.windows()?;
    let rss_all_decoded_mib = rss_mib();
    let file_mib = std::fs::metadata(path)?.len() as f64 / (1024.0 * 1024.0);
    println!(
        "{mode}: resident {rss_loaded_mib:.1} MiB once loaded ({file_mib:.1} MiB file), \
         {rss_all_decoded_mib:.1} MiB with every window decoded"
    );
    Ok(())
}

/// The process's resident memory (MiB), from `/proc/self/status` (0 where there is none).
fn rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kib = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .unwrap_or(0.0);
    kib / 1024.0
}
