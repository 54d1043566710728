//! The bytes of the fleet's store (frames, models, window checkpoints) live in an object
//! store behind [`Blobs`]; [`MemoryBlobs`] keeps them in memory, for tests.

use std::collections::BTreeMap;
use std::sync::{Mutex, MutexGuard};

use super::StoreError;

/// A flat key space of immutable byte objects (`sequences/{id}/frame_00000.f32`, ...).
/// Methods block; keys use `/` to group objects under prefixes.
pub trait Blobs: Send + Sync + 'static {
    /// Stores `bytes` under `key`, atomically, replacing any object there.
    fn put(&self, key: &str, bytes: Vec<u8>) -> Result<(), StoreError>;
    /// The object under `key`, `None` when absent.
    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError>;
    /// Removes the object under `key`; an absent object is not an error.
    fn delete(&self, key: &str) -> Result<(), StoreError>;
    /// Keys of the objects under `prefix` (e.g. `"sequences/"`).
    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError>;
    /// Removes every object under `prefix`; returns how many were removed.
    fn delete_prefix(&self, prefix: &str) -> Result<usize, StoreError>;
}

/// [`Blobs`] in memory (lost with the process): for tests.
#[derive(Debug, Default)]
pub struct MemoryBlobs {
    objects: Mutex<BTreeMap<String, Vec<u8>>>,
}

impl MemoryBlobs {
    /// An empty store.
    pub fn new() -> Self {
        Self::default()
    }

    fn objects(&self) -> MutexGuard<'_, BTreeMap<String, Vec<u8>>> {
        // Every operation leaves the map whole, so a panic elsewhere cannot corrupt it.
        self.objects.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl Blobs for MemoryBlobs {
    fn put(&self, key: &str, bytes: Vec<u8>) -> Result<(), StoreError> {
        self.objects().insert(key.to_string(), bytes);
        Ok(())
    }

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.objects().get(key).cloned())
    }

    fn delete(&self, key: &str) -> Result<(), StoreError> {
        self.objects().remove(key);
        Ok(())
    }

    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        Ok(self
            .objects()
            .range(prefix.to_string()..)
            .map(|(k, _)| k)
            .take_while(|k| k.starts_with(prefix))
            .cloned()
            .collect())
    }

    fn delete_prefix(&self, prefix: &str) -> Result<usize, StoreError> {
        let mut objects = self.objects();
        let before = objects.len();
        objects.retain(|k, _| !k.starts_with(prefix));
        Ok(before - objects.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_blobs_list_and_delete_only_under_their_prefix() {
        let blobs = MemoryBlobs::new();
        for key in ["a/1", "a/2", "ab/1", "b/1"] {
            blobs.put(key, key.as_bytes().to_vec()).unwrap();
        }
        blobs.put("a/1", b"new".to_vec()).unwrap();
        assert_eq!(blobs.get("a/1").unwrap().as_deref(), Some(&b"new"[..]));
        assert_eq!(blobs.list("a/").unwrap(), vec!["a/1", "a/2"]);
        assert_eq!(blobs.delete_prefix("a/").unwrap(), 2);
        assert_eq!(blobs.list("").unwrap(), vec!["ab/1", "b/1"]);
        blobs.delete("missing").unwrap();
        assert_eq!(blobs.get("a/2").unwrap(), None);
    }
}
