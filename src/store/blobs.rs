//! Object storage of the fleet's bytes (frames, models, window models, checkpoints) by key, over
//! a local directory, S3 (or an S3-compatible server) or memory, through the `object_store` crate.
//!
//! Keys look like paths (`sequences/{id}/frame_00003.f32`, `models/{job}.mbnt`): segments of
//! `[A-Za-z0-9._-]` joined by `/`. Every backend makes a `put` visible whole or not at all: S3
//! publishes an object when its single PUT completes, the local directory writes a staging file
//! (`{path}#N`) and renames it over the target (fsynced), memory swaps the entry.

use std::fmt;
use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use futures_util::{StreamExt, TryStreamExt};
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::local::LocalFileSystem;
use object_store::memory::InMemory;
use object_store::path::Path as ObjectPath;
use object_store::prefix::PrefixStore;
use object_store::{ClientOptions, ObjectStore, ObjectStoreExt, PutPayload, RetryConfig};
use tokio::runtime::{Handle, Runtime};

use super::StoreError;

/// Objects by key (`sequences/{id}/frame_00003.f32`, `models/{job}.mbnt`): each `put` is
/// visible whole or not at all (readers never see a partial object). Blocking; callers run
/// off the async executor (worker threads, `spawn_blocking`).
pub trait Blobs: Send + Sync + 'static {
    /// Writes `bytes` under `key`, replacing any previous object, atomically.
    fn put(&self, key: &str, bytes: Vec<u8>) -> Result<(), StoreError>;
    /// The object under `key`, `None` when there is none.
    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError>;
    /// Removes `key` (no error when absent).
    fn delete(&self, key: &str) -> Result<(), StoreError>;
    /// Keys under `prefix` (a folder-like prefix ending in `/`), in any order.
    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError>;
    /// Removes every object under `prefix`; returns how many.
    fn delete_prefix(&self, prefix: &str) -> Result<usize, StoreError>;
}

/// Whole-request timeout of an S3 request: generous enough for a large model or checkpoint on a
/// slow link, short enough that a hung connection is retried rather than stalling a worker.
const S3_REQUEST_TIMEOUT: Duration = Duration::from_secs(60);
/// Connection timeout of an S3 request (an unreachable endpoint fails fast, then is retried).
const S3_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// [`Blobs`] over the `object_store` crate: `file:///ABSOLUTE/DIR` (a local directory,
/// created when absent), `s3://BUCKET/PREFIX` (endpoint, region and credentials from the
/// usual AWS_* environment variables: AWS_ENDPOINT_URL, AWS_REGION, AWS_ACCESS_KEY_ID,
/// AWS_SECRET_ACCESS_KEY, AWS_ALLOW_HTTP for a plain-HTTP endpoint) and `memory://` (tests).
///
/// Keys are segments of `[A-Za-z0-9._-]` joined by single `/` (no empty, `.` or `..` segment);
/// other keys are errors. A prefix is such a key followed by `/`, or empty for the whole store.
/// S3 requests time out after 60 s (5 s to connect) and are retried with `object_store`'s
/// defaults (up to 10 times within 3 minutes).
pub struct ObjectBlobs {
    store: Arc<dyn ObjectStore>,
    url: String,
    handle: Handle,
    // An `Option` only so that `Drop` can take it out and shut it down without blocking.
    runtime: Option<Runtime>,
}

impl fmt::Debug for ObjectBlobs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ObjectBlobs").field("url", &self.url).finish_non_exhaustive()
    }
}

/// Where a URL points, once parsed and checked.
enum Target {
    Memory,
    File(PathBuf),
    S3 { bucket: String, prefix: Option<ObjectPath> },
}

impl ObjectBlobs {
    /// Opens the store at `url`; a URL with another scheme, or a malformed one, is a clear error.
    pub fn from_url(url: &str) -> Result<Self, StoreError> {
        let options = match parse_target(url)? {
            Target::S3 { .. } => aws_env_options(),
            Target::Memory | Target::File(_) => Vec::new(),
        };
        let options: Vec<(&str, &str)> = options.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
        Self::from_url_with(url, &options)
    }

    /// Opens the store at `url` as [`ObjectBlobs::from_url`], with S3 settings taken from
    /// `options` instead of the environment: `(key, value)` pairs named as the AWS_* variables
    /// (case-insensitive: `aws_endpoint_url`, `aws_region`, `aws_access_key_id`,
    /// `aws_secret_access_key`, `aws_allow_http`, ...; also `timeout`, `connect_timeout`).
    /// An unknown key is an error; options given with a `file://` or `memory://` URL are too.
    pub fn from_url_with(url: &str, options: &[(&str, &str)]) -> Result<Self, StoreError> {
        Self::open(url, options, RetryConfig::default())
    }

    /// The URL it was opened with, credentials never included (for logs and /healthz).
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Opens the store with an explicit retry policy of S3 requests (tests shorten it).
    fn open(url: &str, options: &[(&str, &str)], retry: RetryConfig) -> Result<Self, StoreError> {
        let target = parse_target(url)?;
        if !options.is_empty() && !matches!(target, Target::S3 { .. }) {
            return Err(StoreError::Object(format!("object store {url}: options apply only to s3:// URLs")));
        }
        let store: Arc<dyn ObjectStore> = match target {
            Target::Memory => Arc::new(InMemory::new()),
            Target::File(dir) => {
                std::fs::create_dir_all(&dir).map_err(|e| {
                    StoreError::Object(format!("object store {url}: cannot create {}: {e}", dir.display()))
                })?;
                let local = LocalFileSystem::new_with_prefix(&dir)
                    .map_err(|e| StoreError::Object(format!("object store {url}: {e}")))?
                    // Durable as the rest of the data directory (files::write_atomic), and
                    // without the empty directories a deleted sequence would leave behind.
                    .with_fsync(true)
                    .with_automatic_cleanup(true);
                Arc::new(local)
            }
            Target::S3 { bucket, prefix } => {
                let s3 = s3_builder(&bucket, options, retry)?
                    .build()
                    .map_err(|e| StoreError::Object(format!("object store {url}: {e}")))?;
                match prefix {
                    Some(prefix) => Arc::new(PrefixStore::new(s3, prefix)),
                    None => Arc::new(s3),
                }
            }
        };
        // One worker is plenty: the work is waiting on I/O, and the callers' threads block.
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("mbnt-blobs")
            .enable_all()
            .build()
            .map_err(|e| StoreError::Object(format!("object store {url}: cannot start its runtime: {e}")))?;
        let handle = runtime.handle().clone();
        Ok(Self { store, url: url.to_string(), handle, runtime: Some(runtime) })
    }

    /// Runs `fut` on the private runtime and waits for its answer. The future is spawned rather
    /// than `block_on`-ed on the caller's thread, so that a call from any thread (plain, a
    /// `spawn_blocking` closure, even by mistake an async task of another runtime) neither
    /// panics nor drives the store's I/O on a runtime that may be shutting down.
    fn run<T: Send + 'static>(
        &self,
        what: String,
        fut: impl Future<Output = Result<T, object_store::Error>> + Send + 'static,
    ) -> Result<T, StoreError> {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        self.handle.spawn(async move {
            // The receiver only goes away if the caller's thread is gone; nothing to tell then.
            let _ = tx.send(fut.await);
        });
        match rx.recv() {
            Ok(result) => result.map_err(|e| StoreError::Object(format!("{what} in {}: {e}", self.url))),
            Err(_) => Err(StoreError::Object(format!("{what} in {}: the object store task stopped", self.url))),
        }
    }
}

impl Drop for ObjectBlobs {
    fn drop(&mut self) {
        // Dropping a runtime from inside an async context panics (its drop blocks); shutting it
        // down in the background never blocks, and nothing is waiting on its tasks any more.
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

impl Blobs for ObjectBlobs {
    fn put(&self, key: &str, bytes: Vec<u8>) -> Result<(), StoreError> {
        let path = object_key(key)?;
        let store = Arc::clone(&self.store);
        self.run(format!("put {key}"), async move { store.put(&path, PutPayload::from(bytes)).await.map(|_| ()) })
    }

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let path = object_key(key)?;
        let store = Arc::clone(&self.store);
        self.run(format!("get {key}"), async move {
            match store.get(&path).await {
                Ok(object) => Ok(Some(Vec::from(object.bytes().await?))),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(e),
            }
        })
    }

    fn delete(&self, key: &str) -> Result<(), StoreError> {
        let path = object_key(key)?;
        let store = Arc::clone(&self.store);
        self.run(format!("delete {key}"), async move {
            match store.delete(&path).await {
                // S3 answers a delete of a missing key with success; the local directory does not.
                Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
                Err(e) => Err(e),
            }
        })
    }

    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        let path = object_prefix(prefix)?;
        let store = Arc::clone(&self.store);
        // The list stream follows S3's continuation tokens, so every page is read.
        self.run(format!("list {prefix}"), async move {
            store.list(path.as_ref()).map_ok(|meta| meta.location.to_string()).try_collect().await
        })
    }

    fn delete_prefix(&self, prefix: &str) -> Result<usize, StoreError> {
        let path = object_prefix(prefix)?;
        let store = Arc::clone(&self.store);
        self.run(format!("delete_prefix {prefix}"), async move {
            let locations: Vec<ObjectPath> =
                store.list(path.as_ref()).map_ok(|meta| meta.location).try_collect().await?;
            // S3 deletes in batches of up to 1,000 keys per request.
            let mut deleted = store.delete_stream(futures_util::stream::iter(locations.into_iter().map(Ok)).boxed());
            let mut count = 0;
            while let Some(result) = deleted.next().await {
                match result {
                    Ok(_) => count += 1,
                    // Removed meanwhile by someone else: not ours to count.
                    Err(object_store::Error::NotFound { .. }) => {}
                    Err(e) => return Err(e),
                }
            }
            Ok(count)
        })
    }
}

/// Checks a key (segments of `[A-Za-z0-9._-]` joined by single `/`, none `.` or `..`) and turns
/// it into an object path. Stricter than S3 on purpose: such a key means the same object on every
/// backend (no `..` escaping a local directory, no name the local directory reserves, like `#1`).
fn object_key(key: &str) -> Result<ObjectPath, StoreError> {
    let invalid = |why: &str| StoreError::Object(format!("invalid object key {key:?}: {why}"));
    if key.is_empty() {
        return Err(invalid("empty"));
    }
    if key.starts_with('/') {
        return Err(invalid("starts with '/'"));
    }
    if let Some(c) = key.chars().find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '/' | '-'))) {
        return Err(invalid(&format!("character {c:?} is not one of A-Z a-z 0-9 . _ / -")));
    }
    for segment in key.split('/') {
        match segment {
            "" => return Err(invalid("empty segment (\"//\" or a trailing '/')")),
            "." | ".." => return Err(invalid("'.' and '..' segments are not allowed")),
            _ => {}
        }
    }
    ObjectPath::parse(key).map_err(|e| invalid(&e.to_string()))
}

/// Checks a listing prefix: empty (every object) or a valid key followed by `/`.
fn object_prefix(prefix: &str) -> Result<Option<ObjectPath>, StoreError> {
    if prefix.is_empty() {
        return Ok(None);
    }
    let Some(folder) = prefix.strip_suffix('/') else {
        return Err(StoreError::Object(format!("invalid object prefix {prefix:?}: must end with '/'")));
    };
    object_key(folder).map(Some).map_err(|_| {
        StoreError::Object(format!("invalid object prefix {prefix:?}: must be a valid key followed by '/'"))
    })
}

/// `url` with any `user:password@` part replaced, for error messages.
fn redacted(url: &str) -> String {
    if let Some(start) = url.find("://").map(|i| i + 3) {
        let authority_end = url[start..].find(['/', '?', '#']).map_or(url.len(), |i| start + i);
        if let Some(at) = url[start..authority_end].rfind('@') {
            return format!("{}***@{}", &url[..start], &url[start + at + 1..]);
        }
    }
    url.to_string()
}

/// Parses and checks a store URL.
fn parse_target(url: &str) -> Result<Target, StoreError> {
    let bad = |why: &str| StoreError::Object(format!("object store URL {}: {why}", redacted(url)));
    let parsed = url::Url::parse(url).map_err(|e| bad(&format!("malformed ({e})")))?;
    if !parsed.username().is_empty() || parsed.password().is_some() {
        return Err(bad("must not carry credentials (give them in the AWS_* variables)"));
    }
    if parsed.query().is_some() || parsed.fragment().is_some() {
        return Err(bad("must not have a query or a fragment"));
    }
    let host = parsed.host_str().unwrap_or("");
    match parsed.scheme() {
        "memory" => {
            if !host.is_empty() || !matches!(parsed.path(), "" | "/") {
                return Err(bad("expected exactly memory://"));
            }
            Ok(Target::Memory)
        }
        "file" => {
            if !host.is_empty() {
                return Err(bad("expected file:///ABSOLUTE/DIR (a local absolute path, no host)"));
            }
            let dir = parsed.to_file_path().map_err(|()| bad("expected file:///ABSOLUTE/DIR"))?;
            Ok(Target::File(dir))
        }
        "s3" => {
            if host.is_empty() {
                return Err(bad("expected s3://BUCKET/PREFIX (the bucket is missing)"));
            }
            // The path as written: `Url` resolves `..` segments, which would silently move the
            // store to another prefix instead of being refused.
            let raw_path = url.split_once("://").and_then(|(_, rest)| rest.find('/').map(|i| &rest[i..]));
            let prefix = raw_path.unwrap_or("").trim_matches('/');
            let prefix = if prefix.is_empty() {
                None
            } else {
                Some(object_key(prefix).map_err(|_| bad("the prefix must be a valid object key"))?)
            };
            Ok(Target::S3 { bucket: host.to_string(), prefix })
        }
        other => Err(bad(&format!("unsupported scheme {other:?} (expected file://, s3:// or memory://)"))),
    }
}

/// The AWS_* environment variables that name an S3 setting, lower-cased (as the builder's own
/// `from_env`, others such as AWS_PROFILE being ignored).
fn aws_env_options() -> Vec<(String, String)> {
    std::env::vars_os()
        .filter_map(|(k, v)| Some((k.into_string().ok()?, v.into_string().ok()?)))
        .filter(|(k, _)| k.starts_with("AWS_"))
        .map(|(k, v)| (k.to_ascii_lowercase(), v))
        .filter(|(k, _)| k.parse::<AmazonS3ConfigKey>().is_ok())
        .collect()
}

/// The S3 builder for `bucket`: this module's timeouts, then `options` (which may override
/// them), then the bucket of the URL (which nothing overrides).
fn s3_builder(bucket: &str, options: &[(&str, &str)], retry: RetryConfig) -> Result<AmazonS3Builder, StoreError> {
    let client = ClientOptions::default().with_timeout(S3_REQUEST_TIMEOUT).with_connect_timeout(S3_CONNECT_TIMEOUT);
    let mut builder = AmazonS3Builder::new().with_client_options(client).with_retry(retry);
    for (key, value) in options {
        // The key, never the value, goes into the message: values include secrets.
        let config: AmazonS3ConfigKey = key
            .to_ascii_lowercase()
            .parse()
            .map_err(|_| StoreError::Object(format!("unknown S3 option {key:?} for bucket {bucket:?}")))?;
        builder = builder.with_config(config, *value);
    }
    Ok(builder.with_bucket_name(bucket))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    /// `len` bytes cycling through every byte value, shifted by `seed`.
    fn pattern(len: usize, seed: u8) -> Vec<u8> {
        (0..len).map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed)).collect()
    }

    /// Round trips, overwrites, missing keys and deletes under `base` (a prefix ending in `/`).
    fn exercise_objects(blobs: &dyn Blobs, base: &str) {
        let key = format!("{base}sequences/0f3a/frame_00003.f32");
        assert_eq!(blobs.get(&key).unwrap(), None, "a key never written is absent");

        // Every byte value, and a size that is not a power of two.
        let first = pattern(300_001, 7);
        blobs.put(&key, first.clone()).unwrap();
        assert_eq!(blobs.get(&key).unwrap().as_deref(), Some(first.as_slice()));

        // A shorter object replaces a longer one entirely (no tail of the old one left).
        let second = pattern(1_000, 200);
        blobs.put(&key, second.clone()).unwrap();
        assert_eq!(blobs.get(&key).unwrap().as_deref(), Some(second.as_slice()));

        let empty_key = format!("{base}models/empty.mbnt");
        blobs.put(&empty_key, Vec::new()).unwrap();
        assert_eq!(blobs.get(&empty_key).unwrap(), Some(Vec::new()), "an empty object exists and is empty");

        blobs.delete(&key).unwrap();
        assert_eq!(blobs.get(&key).unwrap(), None);
        blobs.delete(&key).unwrap();
        blobs.delete(&format!("{base}never/written.bin")).unwrap();
        assert_eq!(blobs.get(&empty_key).unwrap(), Some(Vec::new()), "deleting one key leaves the others");
        blobs.delete(&empty_key).unwrap();
    }

    /// Writes `n` small objects `{prefix}obj_{i:05}.bin` from four threads at once.
    fn put_many(blobs: &dyn Blobs, prefix: &str, n: usize) -> Vec<String> {
        let keys: Vec<String> = (0..n).map(|i| format!("{prefix}obj_{i:05}.bin")).collect();
        std::thread::scope(|s| {
            for chunk in keys.chunks(n.div_ceil(4).max(1)) {
                s.spawn(move || {
                    for key in chunk {
                        blobs.put(key, key.as_bytes().to_vec()).unwrap();
                    }
                });
            }
        });
        keys
    }

    /// `list` and `delete_prefix` with 0, 1 and 1,500 objects (more than an S3 page of 1,000),
    /// next to a sibling prefix that shares the folder's name as a string prefix.
    fn exercise_listing(blobs: &dyn Blobs, base: &str) {
        let sibling = put_many(blobs, &format!("{base}jobs-other/"), 3);
        for n in [0, 1, 1_500] {
            let prefix = format!("{base}jobs/n{n}/");
            let mut keys = put_many(blobs, &prefix, n);
            // Nested keys are under the prefix too.
            if n > 0 {
                let nested = format!("{prefix}deeper/window-0.mbnt");
                blobs.put(&nested, vec![1]).unwrap();
                keys.push(nested);
            }
            keys.sort();
            let mut listed = blobs.list(&prefix).unwrap();
            listed.sort();
            assert_eq!(listed, keys, "listing {prefix}");

            assert_eq!(blobs.delete_prefix(&prefix).unwrap(), keys.len(), "deleting {prefix}");
            assert!(blobs.list(&prefix).unwrap().is_empty(), "{prefix} is empty after delete_prefix");
            assert_eq!(blobs.delete_prefix(&prefix).unwrap(), 0, "a second delete_prefix finds nothing");
            if let Some(key) = keys.first() {
                assert_eq!(blobs.get(key).unwrap(), None);
            }
        }
        // `{base}jobs/` is a string prefix of nothing in `jobs-other/`, which is untouched.
        let mut left = blobs.list(&format!("{base}jobs-other/")).unwrap();
        left.sort();
        assert_eq!(left, sibling);
        for key in &sibling {
            assert_eq!(blobs.get(key).unwrap().as_deref(), Some(key.as_bytes()));
        }
        assert_eq!(blobs.delete_prefix(&format!("{base}jobs-other/")).unwrap(), 3);
    }

    fn assert_object_error(result: Result<impl fmt::Debug, StoreError>, needle: &str) {
        match result {
            Err(StoreError::Object(message)) => {
                assert!(message.contains(needle), "{message:?} should mention {needle:?}")
            }
            other => panic!("expected StoreError::Object mentioning {needle:?}, got {other:?}"),
        }
    }

    #[test]
    fn memory_store_round_trips_lists_and_deletes() {
        let blobs = ObjectBlobs::from_url("memory://").unwrap();
        assert_eq!(blobs.url(), "memory://");
        exercise_objects(&blobs, "");
        exercise_listing(&blobs, "");
        assert!(blobs.list("").unwrap().is_empty());
    }

    #[test]
    fn file_store_round_trips_lists_and_deletes_in_its_directory() {
        let tmp = tempfile::tempdir().unwrap();
        // The directory is created when absent, parents included.
        let dir = tmp.path().join("objects/nested");
        let url = format!("file://{}", dir.display());
        let blobs = ObjectBlobs::from_url(&url).unwrap();
        assert!(dir.is_dir());
        assert_eq!(blobs.url(), url);

        exercise_objects(&blobs, "a/");
        exercise_listing(&blobs, "b/");

        // Keys are paths inside the directory, and nothing else is left there once all is
        // deleted (no staging files, no empty folders).
        blobs.put("models/job-1.mbnt", b"model".to_vec()).unwrap();
        assert_eq!(std::fs::read(dir.join("models/job-1.mbnt")).unwrap(), b"model");
        blobs.delete("models/job-1.mbnt").unwrap();
        let left: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
        assert!(left.is_empty(), "left in the directory: {left:?}");

        // A second store over the same directory sees the same objects.
        blobs.put("sequences/s/frame_00000.f32", pattern(10, 1)).unwrap();
        let again = ObjectBlobs::from_url(&url).unwrap();
        assert_eq!(again.get("sequences/s/frame_00000.f32").unwrap(), Some(pattern(10, 1)));
    }

    #[test]
    fn file_store_readers_never_see_a_partial_object() {
        let tmp = tempfile::tempdir().unwrap();
        let blobs = ObjectBlobs::from_url(&format!("file://{}", tmp.path().display())).unwrap();
        let key = "models/job.mbnt";
        let small = vec![0xAA; 256 * 1024];
        let large = vec![0x55; 2 * 1024 * 1024];
        blobs.put(key, small.clone()).unwrap();
        let done = std::sync::atomic::AtomicBool::new(false);
        std::thread::scope(|s| {
            s.spawn(|| {
                for i in 0..40 {
                    blobs.put(key, if i % 2 == 0 { large.clone() } else { small.clone() }).unwrap();
                }
                done.store(true, std::sync::atomic::Ordering::Release);
            });
            let mut reads = 0;
            while !done.load(std::sync::atomic::Ordering::Acquire) || reads == 0 {
                let got = blobs.get(key).unwrap().expect("the object exists throughout");
                assert!(got == small || got == large, "read a mixed or partial object of {} bytes", got.len());
                reads += 1;
            }
        });
    }

    #[test]
    fn bad_keys_and_prefixes_are_errors() {
        let blobs = ObjectBlobs::from_url("memory://").unwrap();
        for key in [
            "",
            "/models/a.mbnt",
            "models/../secret",
            "..",
            "a/./b",
            "a//b",
            "models/",
            "models/a b",
            "models/a#1",
            "models/ü",
            "models\\a",
            "a?b",
        ] {
            assert_object_error(blobs.put(key, vec![1]), "invalid object key");
            assert_object_error(blobs.get(key), "invalid object key");
            assert_object_error(blobs.delete(key), "invalid object key");
        }
        for prefix in ["models", "/models/", "a/../", "a//", "x y/"] {
            assert_object_error(blobs.list(prefix), "invalid object prefix");
            assert_object_error(blobs.delete_prefix(prefix), "invalid object prefix");
        }
        // Dots inside a segment are fine.
        blobs.put("a/..b/c..d/.e", vec![1]).unwrap();
        assert_eq!(blobs.list("a/").unwrap(), vec!["a/..b/c..d/.e".to_string()]);
    }

    #[test]
    fn bad_urls_are_clear_errors() {
        for (url, needle) in [
            ("", "malformed"),
            ("not a url", "malformed"),
            ("ftp://host/dir", "unsupported scheme \"ftp\""),
            ("gs://bucket/p", "unsupported scheme \"gs\""),
            ("memory://somewhere", "expected exactly memory://"),
            ("file://host/dir", "no host"),
            ("s3://", "bucket is missing"),
            ("s3://bucket/a/../b", "prefix must be a valid object key"),
            ("s3://bucket/p?versionId=1", "query"),
        ] {
            assert_object_error(ObjectBlobs::from_url(url), needle);
        }
        // Credentials in the URL are refused without being repeated in the message.
        match ObjectBlobs::from_url("s3://AKIDEXAMPLE:wJalrXUtnFEMIK7MDENG@bucket/p") {
            Err(StoreError::Object(m)) => {
                assert!(m.contains("credentials"), "{m}");
                assert!(!m.contains("wJalrXUtnFEMIK7MDENG") && !m.contains("AKIDEXAMPLE"), "{m}");
            }
            other => panic!("{other:?}"),
        }
        assert_object_error(
            ObjectBlobs::from_url_with("s3://bucket/p", &[("aws_no_such_option", "1")]),
            "unknown S3 option",
        );
        assert_object_error(ObjectBlobs::from_url_with("memory://", &[("aws_region", "x")]), "only to s3://");
    }

    #[test]
    fn works_from_plain_threads_and_spawn_blocking_and_drops_inside_a_runtime() {
        let blobs = Arc::new(ObjectBlobs::from_url("memory://").unwrap());
        std::thread::scope(|s| {
            for t in 0..4 {
                let blobs = &blobs;
                s.spawn(move || blobs.put(&format!("t/{t}"), vec![t]).unwrap());
            }
        });
        let outer = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        outer.block_on(async {
            let b = Arc::clone(&blobs);
            let listed = tokio::task::spawn_blocking(move || {
                b.put("t/from-spawn-blocking", vec![9]).unwrap();
                b.list("t/").unwrap()
            })
            .await
            .unwrap();
            assert_eq!(listed.len(), 5);
            // A store opened and dropped on an async worker thread: its runtime's shutdown
            // must not panic there.
            let local = ObjectBlobs::from_url("memory://").unwrap();
            drop(local);
        });
        // The last reference dropped inside a spawn_blocking closure of another runtime.
        outer.block_on(async move {
            tokio::task::spawn_blocking(move || {
                assert_eq!(blobs.get("t/3").unwrap(), Some(vec![3]));
                drop(blobs);
            })
            .await
            .unwrap();
        });
    }

    #[test]
    fn an_unreachable_s3_endpoint_is_an_object_error_naming_the_key() {
        // A port that was just free: nothing listens there, connections are refused.
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let endpoint = format!("http://127.0.0.1:{port}");
        let retry = RetryConfig {
            backoff: object_store::BackoffConfig {
                init_backoff: Duration::from_millis(10),
                max_backoff: Duration::from_millis(50),
                base: 2.0,
            },
            max_retries: 2,
            retry_timeout: Duration::from_secs(3),
        };
        let options = moto::s3_options(&endpoint);
        let blobs = ObjectBlobs::open("s3://bucket/fleet", &options, retry).unwrap();
        let started = Instant::now();
        assert_object_error(
            blobs.put("models/job-7.mbnt", vec![1, 2, 3]),
            "put models/job-7.mbnt in s3://bucket/fleet",
        );
        assert_object_error(blobs.get("models/job-7.mbnt"), "get models/job-7.mbnt");
        assert_object_error(blobs.list("models/"), "list models/");
        assert_object_error(blobs.delete_prefix("models/"), "delete_prefix models/");
        assert!(started.elapsed() < Duration::from_secs(10), "took {:?}", started.elapsed());
    }

    #[test]
    fn s3_store_against_moto_round_trips_lists_and_deletes() {
        let started = Instant::now();
        let server = match moto::MotoServer::start() {
            Ok(server) => server,
            Err(moto::Unavailable(why)) => {
                eprintln!("skipped: {why}");
                return;
            }
        };
        eprintln!("moto {} ready after {:.1} s", moto::MOTO_VERSION, started.elapsed().as_secs_f64());
        server.create_bucket("mbnt-test");
        let endpoint = server.endpoint();
        let options = moto::s3_options(&endpoint);

        let blobs = ObjectBlobs::from_url_with("s3://mbnt-test/fleet/blobs", &options).unwrap();
        assert_eq!(blobs.url(), "s3://mbnt-test/fleet/blobs");
        let suite = Instant::now();
        exercise_objects(&blobs, "");
        exercise_listing(&blobs, "");

        // The URL's prefix scopes the store: another prefix of the same bucket, and the bucket
        // as a whole, see their own keys.
        blobs.put("models/job.mbnt", vec![1, 2]).unwrap();
        let other = ObjectBlobs::from_url_with("s3://mbnt-test/other", &options).unwrap();
        assert_eq!(other.get("models/job.mbnt").unwrap(), None);
        let whole = ObjectBlobs::from_url_with("s3://mbnt-test", &options).unwrap();
        assert_eq!(whole.list("").unwrap(), vec!["fleet/blobs/models/job.mbnt".to_string()]);

        // As the HTTP handlers call it: from spawn_blocking inside another runtime.
        let blobs = Arc::new(blobs);
        let outer = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let b = Arc::clone(&blobs);
        let got = outer.block_on(async move { tokio::task::spawn_blocking(move || b.get("models/job.mbnt")).await });
        assert_eq!(got.unwrap().unwrap(), Some(vec![1, 2]));
        // A store that has made requests (its HTTP client holds pooled connections) dropped on
        // an async worker thread of another runtime.
        outer.block_on(async move {
            assert_eq!(other.list("").unwrap(), Vec::<String>::new());
            drop(other);
        });
        assert_eq!(blobs.delete_prefix("").unwrap(), 1);
        eprintln!("S3 checks took {:.1} s", suite.elapsed().as_secs_f64());
    }

    /// A moto S3 server for the tests: installed once into a virtual environment under the
    /// target directory, started per test on a free port, killed on drop.
    mod moto {
        use std::fs::{self, File};
        use std::io::{Read, Write};
        use std::net::TcpStream;
        use std::path::{Path, PathBuf};
        use std::process::{Child, Command, Stdio};
        use std::sync::OnceLock;
        use std::time::{Duration, Instant};

        /// The moto release the tests run against.
        pub const MOTO_VERSION: &str = "5.2.6";

        /// Why the S3 tests cannot run here (no python3, no network to PyPI, ...).
        #[derive(Debug, Clone)]
        pub struct Unavailable(pub String);

        /// Options pointing a store at `endpoint` with dummy credentials.
        pub fn s3_options(endpoint: &str) -> Vec<(&str, &str)> {
            vec![
                ("aws_endpoint_url", endpoint),
                ("aws_allow_http", "true"),
                ("aws_region", "us-east-1"),
                ("aws_access_key_id", "testing"),
                ("aws_secret_access_key", "testing"),
            ]
        }

        fn tools_dir() -> PathBuf {
            let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
            let target =
                std::env::var_os("CARGO_TARGET_DIR").map_or_else(|| manifest.join("target"), |t| manifest.join(t));
            target.join("test-tools")
        }

        fn run(command: &mut Command) -> Result<(), Unavailable> {
            let output = command.output().map_err(|e| Unavailable(format!("cannot run {command:?}: {e}")))?;
            if output.status.success() {
                Ok(())
            } else {
                let stderr = String::from_utf8_lossy(&output.stderr);
                let tail: String = stderr.lines().rev().take(5).collect::<Vec<_>>().join(" | ");
                Err(Unavailable(format!("{command:?} failed ({}): {tail}", output.status)))
            }
        }

        /// The virtual environment holding moto, installed when missing. A file lock keeps
        /// two test processes from installing at once; the `OnceLock` keeps this process from
        /// doing it twice. A marker written last tells a complete install from an interrupted one.
        fn venv() -> Result<PathBuf, Unavailable> {
            static VENV: OnceLock<Result<PathBuf, Unavailable>> = OnceLock::new();
            VENV.get_or_init(|| {
                let tools = tools_dir();
                let venv = tools.join(format!("moto-{MOTO_VERSION}"));
                let installed = venv.join(".installed");
                if installed.exists() {
                    return Ok(venv);
                }
                fs::create_dir_all(&tools)
                    .map_err(|e| Unavailable(format!("cannot create {}: {e}", tools.display())))?;
                let lock = File::create(tools.join(format!("moto-{MOTO_VERSION}.lock")))
                    .and_then(|f| f.lock().map(|()| f))
                    .map_err(|e| Unavailable(format!("cannot lock in {}: {e}", tools.display())))?;
                if !installed.exists() {
                    let started = Instant::now();
                    let _ = fs::remove_dir_all(&venv);
                    run(Command::new("python3").arg("-m").arg("venv").arg(&venv))?;
                    run(Command::new(venv.join("bin/python")).args([
                        "-m",
                        "pip",
                        "install",
                        "--quiet",
                        "--disable-pip-version-check",
                        &format!("moto[server]=={MOTO_VERSION}"),
                    ]))?;
                    fs::write(&installed, MOTO_VERSION).map_err(|e| Unavailable(e.to_string()))?;
                    eprintln!("installed moto {MOTO_VERSION} in {:.1} s", started.elapsed().as_secs_f64());
                }
                drop(lock);
                Ok(venv)
            })
            .clone()
        }

        /// Sends one HTTP/1.1 request without a body and returns the status code.
        fn http(port: u16, method: &str, path: &str) -> std::io::Result<u16> {
            let mut stream = TcpStream::connect(("127.0.0.1", port))?;
            stream.set_read_timeout(Some(Duration::from_secs(10)))?;
            write!(
                stream,
                "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
            )?;
            let mut answer = String::new();
            stream.read_to_string(&mut answer)?;
            answer
                .split_whitespace()
                .nth(1)
                .and_then(|code| code.parse().ok())
                .ok_or_else(|| std::io::Error::other(format!("not an HTTP answer: {answer:.80}")))
        }

        /// A running `moto_server`.
        pub struct MotoServer {
            child: Child,
            port: u16,
        }

        impl MotoServer {
            /// Installs moto if needed and starts a server, waiting until it answers.
            pub fn start() -> Result<Self, Unavailable> {
                let venv = venv()?;
                let port = std::net::TcpListener::bind("127.0.0.1:0")
                    .and_then(|l| l.local_addr())
                    .map_err(|e| Unavailable(e.to_string()))?
                    .port();
                let child = Command::new(venv.join("bin/moto_server"))
                    .args(["-H", "127.0.0.1", "-p", &port.to_string()])
                    .stdin(Stdio::null())
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .spawn()
                    .expect("moto_server of a complete install starts");
                let mut server = Self { child, port };
                let deadline = Instant::now() + Duration::from_secs(30);
                loop {
                    if http(port, "GET", "/").is_ok_and(|status| status == 200) {
                        return Ok(server);
                    }
                    if let Some(status) = server.child.try_wait().unwrap() {
                        panic!("moto_server exited with {status} before answering");
                    }
                    assert!(Instant::now() < deadline, "moto_server did not answer on port {port} within 30 s");
                    std::thread::sleep(Duration::from_millis(100));
                }
            }

            /// Its endpoint URL.
            pub fn endpoint(&self) -> String {
                format!("http://127.0.0.1:{}", self.port)
            }

            /// Creates a bucket (moto accepts unsigned requests).
            pub fn create_bucket(&self, name: &str) {
                let status = http(self.port, "PUT", &format!("/{name}")).unwrap();
                assert_eq!(status, 200, "creating bucket {name}");
            }
        }

        impl Drop for MotoServer {
            fn drop(&mut self) {
                let _ = self.child.kill();
                let _ = self.child.wait();
            }
        }
    }
}
