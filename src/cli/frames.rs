//! Frame files read when a fit needs them: `mbnt fit` of a long log holds one window's frames at
//! a time, and writes its labels one frame at a time, instead of holding the whole log.

use std::path::{Path, PathBuf};

use anyhow::{Context, ensure};

use crate::fit::{FitError, FrameSource};
use crate::geometry::Point;
use crate::io::read_points_file;

/// A sequence of frame files, with its timestamps and poses: a [`FrameSource`] reading each
/// frame from its file when the fit asks for it.
#[derive(Debug, Clone)]
pub struct FileFrames {
    paths: Vec<PathBuf>,
    timestamps_s: Option<Vec<f64>>,
    poses: Option<Vec<[f64; 16]>>,
}

impl FileFrames {
    /// The frames in `paths` (time order), with one timestamp (s) and one sensor-to-world pose
    /// (row-major 4 x 4) per frame when given.
    pub fn new(
        paths: Vec<PathBuf>,
        timestamps_s: Option<Vec<f64>>,
        poses: Option<Vec<[f64; 16]>>,
    ) -> anyhow::Result<Self> {
        let frames = paths.len();
        if let Some(ts) = &timestamps_s {
            ensure!(ts.len() == frames, "{} timestamps for {frames} frames", ts.len());
        }
        if let Some(poses) = &poses {
            ensure!(poses.len() == frames, "{} poses for {frames} frames", poses.len());
        }
        Ok(Self { paths, timestamps_s, poses })
    }

    /// Reads every frame once and returns its point count: a file that does not read, or a frame
    /// without points, fails here rather than after the windows before it were fitted. Holds one
    /// frame at a time.
    pub fn check(&self) -> anyhow::Result<Vec<usize>> {
        let bar = super::progress::bar(self.paths.len(), "reading frames");
        let counts = self
            .paths
            .iter()
            .map(|path| {
                let points = read(path)?;
                ensure!(!points.is_empty(), "frame {} has no points", path.display());
                bar.inc(1);
                Ok(points.len())
            })
            .collect();
        bar.finish_and_clear();
        counts
    }

    /// Frame `k`'s points (sensor coordinates of sweep k).
    pub fn frame(&self, k: usize) -> anyhow::Result<Vec<Point>> {
        read(&self.paths[k])
    }
}

fn read(path: &Path) -> anyhow::Result<Vec<Point>> {
    read_points_file(path).with_context(|| format!("reading frame {}", path.display()))
}

impl FrameSource for FileFrames {
    fn frame_count(&self) -> usize {
        self.paths.len()
    }

    fn timestamps_s(&self) -> Option<&[f64]> {
        self.timestamps_s.as_deref()
    }

    fn poses(&self) -> Option<&[[f64; 16]]> {
        self.poses.as_deref()
    }

    fn read_frames(&self, range: std::ops::Range<usize>) -> Result<Vec<Vec<Point>>, FitError> {
        range.map(|k| self.frame(k).map_err(|e| FitError::FrameRead(format!("{e:#}")))).collect()
    }
}

/// The peak resident memory of this process so far (bytes; Linux `VmHWM`), when the system
/// reports it: printed by long commands so that a user sees what a fit needed.
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_read_from_their_files_when_asked_and_a_bad_file_fails_the_check() {
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, points: &[Point]| {
            let path = dir.path().join(name);
            let bytes: Vec<u8> =
                points.iter().flat_map(|p| [p[0], p[1], p[2], 0.0]).flat_map(f32::to_le_bytes).collect();
            std::fs::write(&path, bytes).unwrap();
            path
        };
        let a = write("000.bin", &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        let b = write("001.bin", &[[7.0, 8.0, 9.0]]);
        let frames = FileFrames::new(vec![a.clone(), b.clone()], Some(vec![0.0, 0.1]), None).unwrap();
        assert_eq!(frames.check().unwrap(), vec![2, 1]);
        assert_eq!(frames.frame_count(), 2);
        assert_eq!(frames.read_frames(1..2).unwrap(), vec![vec![[7.0, 8.0, 9.0]]]);
        assert_eq!(*frames.read_frame(0).unwrap(), [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        // A frame without points, and a file that is not there, fail the check with the file's name.
        let empty = write("002.bin", &[]);
        let err = FileFrames::new(vec![a.clone(), empty], None, None).unwrap().check().unwrap_err();
        assert!(err.to_string().contains("002.bin"), "{err}");
        let missing = dir.path().join("003.bin");
        let frames = FileFrames::new(vec![a.clone(), missing], None, None).unwrap();
        assert!(format!("{:#}", frames.check().unwrap_err()).contains("003.bin"));
        assert!(matches!(frames.read_frames(0..2), Err(FitError::FrameRead(_))));
        // Timestamps and poses must match the frames.
        assert!(FileFrames::new(vec![a, b], Some(vec![0.0]), None).is_err());
    }

    #[test]
    fn the_peak_memory_is_read_on_linux() {
        if cfg!(target_os = "linux") {
            let peak = peak_rss_bytes().expect("VmHWM on Linux");
            assert!(peak > 1 << 20, "{peak}");
        }
    }
}
