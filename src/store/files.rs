//! The data directory's files: frames and models, written atomically (temporary file, fsync,
//! rename, fsync of the directory) so that a crash never leaves a half-written file visible.
//!
//! Layout under the data directory:
//! - `mbnt.sqlite3` (+ WAL files): the database (see [`super::sqlite`]).
//! - `lock`: held locked (an advisory file lock) by the one process using the directory.
//! - `sequences/{id}/frame_{k:05}.f32`: frame k of a sequence ([`write_frame`] format).
//! - `staging/{uuid}/`: a sequence being uploaded; renamed into `sequences/` when complete.
//! - `models/{job_id}.mbnt`: a fitted model ([`crate::model::FittedModel::to_bytes`]).
//! - `windows/{job_id}/{key}.mbnt`: the finished windows of a job still queued or running (a
//!   long log fitted as windows), so that the job run again after a restart skips them.
//! - `tmp/`: raw upload parts while they stream in.

use std::fs::{self, File};
use std::io::{self, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use crate::geometry::Point;

/// Magic and version of a stored frame file; a little-endian `u64` point count follows, then
/// `3 * count` little-endian `f32` (x, y, z per point).
const FRAME_MAGIC: &[u8; 8] = b"MBNTFRM1";

/// Paths inside one data directory.
#[derive(Debug, Clone)]
pub struct DataDir {
    root: PathBuf,
}

impl DataDir {
    /// Opens (creating when absent) the data directory and its sub-directories.
    pub fn create(root: &Path) -> io::Result<Self> {
        for sub in ["sequences", "staging", "models", "tmp", "windows"] {
            fs::create_dir_all(root.join(sub))?;
        }
        Ok(Self { root: root.to_path_buf() })
    }

    /// The data directory itself.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The database file.
    pub fn database(&self) -> PathBuf {
        self.root.join("mbnt.sqlite3")
    }

    /// The file whose lock marks the directory as in use by a process.
    pub fn lock_file(&self) -> PathBuf {
        self.root.join("lock")
    }

    /// Directory of the committed sequence `id`.
    pub fn sequence_dir(&self, id: &str) -> PathBuf {
        self.root.join("sequences").join(id)
    }

    /// Parent of all committed sequences.
    pub fn sequences_dir(&self) -> PathBuf {
        self.root.join("sequences")
    }

    /// Parent of sequences being uploaded.
    pub fn staging_dir(&self) -> PathBuf {
        self.root.join("staging")
    }

    /// Parent of the model files.
    pub fn models_dir(&self) -> PathBuf {
        self.root.join("models")
    }

    /// Parent of the finished windows of unfinished jobs, one directory per job.
    pub fn windows_dir(&self) -> PathBuf {
        self.root.join("windows")
    }

    /// The model file of window `key` of job `id`.
    pub fn window_model_path(&self, id: &str, key: &str) -> PathBuf {
        self.windows_dir().join(id).join(format!("{key}.mbnt"))
    }

    /// The model file of job `id`.
    pub fn model_path(&self, id: &str) -> PathBuf {
        self.root.join("models").join(format!("{id}.mbnt"))
    }

    /// Scratch space for upload parts (same file system as the rest, so renames are atomic).
    pub fn tmp_dir(&self) -> PathBuf {
        self.root.join("tmp")
    }
}

/// File name of frame `k` inside a sequence directory.
pub fn frame_file_name(k: usize) -> String {
    format!("frame_{k:05}.f32")
}

/// Writes `bytes` to `path` atomically: a sibling temporary file is written and fsynced, then
/// renamed over `path`, then the directory is fsynced so the rename itself is durable.
pub fn write_atomic(path: &Path, write: impl FnOnce(&mut BufWriter<File>) -> io::Result<()>) -> io::Result<()> {
    let dir = path.parent().ok_or_else(|| io::Error::other("atomic write target has no parent directory"))?;
    let name = path.file_name().ok_or_else(|| io::Error::other("atomic write target has no file name"))?;
    let tmp = dir.join(format!(".{}.{}.tmp", name.to_string_lossy(), uuid::Uuid::new_v4().simple()));
    let result = (|| {
        let mut w = BufWriter::new(File::create(&tmp)?);
        write(&mut w)?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        fs::rename(&tmp, path)?;
        sync_dir(dir)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// Fsyncs a directory so that entries created or renamed in it survive a crash.
pub fn sync_dir(dir: &Path) -> io::Result<()> {
    // Only Unix can open a directory to sync it; elsewhere renames are as durable as the
    // platform makes them.
    #[cfg(unix)]
    {
        File::open(dir)?.sync_all()
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        Ok(())
    }
}

/// Writes one frame in the stored frame format (not synced: the caller syncs the directory
/// it renames into place, see [`write_frame_file`]).
pub fn write_frame(w: &mut impl Write, points: &[Point]) -> io::Result<()> {
    w.write_all(FRAME_MAGIC)?;
    w.write_all(&(points.len() as u64).to_le_bytes())?;
    for p in points {
        for c in p {
            w.write_all(&c.to_le_bytes())?;
        }
    }
    Ok(())
}

/// Writes a frame file durably (written, fsynced; the caller renames the directory).
pub fn write_frame_file(path: &Path, points: &[Point]) -> io::Result<()> {
    let mut w = BufWriter::new(File::create(path)?);
    write_frame(&mut w, points)?;
    let file = w.into_inner().map_err(|e| e.into_error())?;
    file.sync_all()
}

/// Reads a frame written by [`write_frame`].
pub fn read_frame(path: &Path) -> io::Result<Vec<Point>> {
    let mut bytes = Vec::new();
    File::open(path)?.read_to_end(&mut bytes)?;
    // The path leads the message, as callers (and their users) expect to see which file it was.
    parse_frame(&bytes).map_err(|e| io::Error::new(e.kind(), format!("{} {e}", path.display())))
}

/// Decodes the bytes of a frame written by [`write_frame`] (a whole frame file, or an object of
/// an object store). A bad magic or a length that disagrees with the point count is
/// [`io::ErrorKind::InvalidData`].
pub fn parse_frame(bytes: &[u8]) -> io::Result<Vec<Point>> {
    let invalid = |what: String| io::Error::new(io::ErrorKind::InvalidData, what);
    if bytes.len() < 16 || &bytes[..8] != FRAME_MAGIC {
        return Err(invalid("is not a frame file".to_string()));
    }
    let count = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes"));
    let len_bytes = bytes.len() as u64;
    if Some(len_bytes) != count.checked_mul(12).and_then(|b| b.checked_add(16)) {
        return Err(invalid(format!("is truncated ({len_bytes} bytes for {count} points)")));
    }
    Ok(bytes[16..]
        .chunks_exact(12)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().expect("4 bytes"));
            [f(0), f(4), f(8)]
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_reads_back_bit_for_bit() {
        let dir = std::env::temp_dir().join(format!("mbnt-files-{}", uuid::Uuid::new_v4()));
        fs::create_dir_all(&dir).unwrap();
        let points = vec![[1.0, -2.5, 3.25], [f32::MIN_POSITIVE, 0.0, -0.0], [1e30, -1e-30, 7.0]];
        let path = dir.join(frame_file_name(3));
        write_frame_file(&path, &points).unwrap();
        let back = read_frame(&path).unwrap();
        assert_eq!(
            back.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>(),
            points.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>()
        );
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_truncated_frame_is_an_error_not_a_short_frame() {
        let dir = std::env::temp_dir().join(format!("mbnt-files-{}", uuid::Uuid::new_v4()));
        fs::create_dir_all(&dir).unwrap();
        let path = dir.join("f");
        write_frame_file(&path, &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]).unwrap();
        let bytes = fs::read(&path).unwrap();
        fs::write(&path, &bytes[..bytes.len() - 4]).unwrap();
        assert_eq!(read_frame(&path).unwrap_err().kind(), io::ErrorKind::InvalidData);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn parse_frame_reads_what_write_frame_wrote_and_refuses_damage() {
        let points = vec![[0.5, -1.0, f32::MAX], [-0.0, 3.0, 1e-40]];
        let mut bytes = Vec::new();
        write_frame(&mut bytes, &points).unwrap();
        let back = parse_frame(&bytes).unwrap();
        assert_eq!(
            back.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>(),
            points.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>()
        );
        let longer = [bytes.as_slice(), &[0]].concat();
        for damaged in [&[][..], &bytes[..bytes.len() - 1], &bytes[..10], &longer[..]] {
            assert_eq!(parse_frame(damaged).unwrap_err().kind(), io::ErrorKind::InvalidData);
        }
        let mut bad_magic = bytes.clone();
        bad_magic[0] = b'X';
        assert_eq!(parse_frame(&bad_magic).unwrap_err().kind(), io::ErrorKind::InvalidData);
    }

    #[test]
    fn an_atomic_write_replaces_the_whole_file_and_leaves_no_temporary() {
        let dir = std::env::temp_dir().join(format!("mbnt-files-{}", uuid::Uuid::new_v4()));
        fs::create_dir_all(&dir).unwrap();
        let path = dir.join("model.mbnt");
        write_atomic(&path, |w| w.write_all(b"first version, longer")).unwrap();
        write_atomic(&path, |w| w.write_all(b"second")).unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"second");
        let failed = write_atomic(&path, |_| Err(io::Error::other("disk full")));
        assert!(failed.is_err());
        assert_eq!(fs::read(&path).unwrap(), b"second");
        assert_eq!(fs::read_dir(&dir).unwrap().count(), 1);
        fs::remove_dir_all(&dir).unwrap();
    }
}
