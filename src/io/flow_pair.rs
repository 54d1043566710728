//! A LiDAR pair with ground-truth scene flow in the `.npz` layout of ICP-Flow's demo
//! (`../shared/data/real-pair-icpflow/README.md`): `pc1`, `pc2` (N, 3) float32 in one common
//! frame with all-NaN padding rows, `gt_flow_0_1` (N, 3), `pc1_flows_valid_idx` (indices of the
//! scored `pc1` rows), `pc1_classes` (-1 = background), `ground1`, `ground2` (1 = ground) and,
//! optionally, a peer's estimate `est_flow` (one row per valid index).
//!
//! Padding rows are dropped on loading; every per-point array below is aligned with the kept
//! points of `pc1` (or `pc2`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::npy::{NpyArray, NpyData};
use super::npz::{NpzReadError, read_npz};
use crate::geometry::Point;

/// A frame pair with per-point ground truth for the first frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowPair {
    /// The first sweep's points (padding dropped), metres.
    pub pc1: Vec<Point>,
    /// The second sweep's points (padding dropped), metres, in the same frame as `pc1`.
    pub pc2: Vec<Point>,
    /// Per `pc1` point: labelled ground.
    pub ground1: Vec<bool>,
    /// Per `pc2` point: labelled ground.
    pub ground2: Vec<bool>,
    /// Per `pc1` point: object class, -1 for background.
    pub classes1: Vec<f32>,
    /// Per `pc1` point: true flow to the time of `pc2` (m); NaN where `valid1` is false.
    pub gt_flow: Vec<Point>,
    /// Per `pc1` point: whether its ground truth is valid (the scoring set).
    pub valid1: Vec<bool>,
    /// Per `pc1` point: the peer's estimated flow (`est_flow`), `None` when the file has none
    /// or the point is not in the scoring set.
    pub est_flow: Option<Vec<Option<Point>>>,
}

/// Why a flow pair could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum FlowPairError {
    /// The file could not be read.
    #[error("reading {}: {source}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A directory was given that does not hold exactly one `.npz` file.
    #[error("{}: expected exactly one .npz file in the directory, found {found}", .dir.display())]
    NoSingleNpz {
        /// The directory.
        dir: PathBuf,
        /// How many `.npz` files it holds.
        found: usize,
    },
    /// The archive could not be read.
    #[error(transparent)]
    Npz(#[from] NpzReadError),
    /// A required array is absent.
    #[error("flow pair: no array '{0}'")]
    Missing(&'static str),
    /// An array has the wrong shape or element type.
    #[error("flow pair: array '{name}' is {got}, expected {expected}")]
    Layout {
        /// The array.
        name: &'static str,
        /// What it is.
        got: String,
        /// What it should be.
        expected: String,
    },
    /// An index points outside `pc1` or at a padding row.
    #[error("flow pair: {name}[{position}] = {index} is {why}")]
    BadIndex {
        /// The index array.
        name: &'static str,
        /// Position in the index array.
        position: usize,
        /// The index value.
        index: i64,
        /// Why it is rejected.
        why: &'static str,
    },
}

impl FlowPair {
    /// Loads a pair from an `.npz` file, or from the only `.npz` file of a directory.
    pub fn load(path: &Path) -> Result<FlowPair, FlowPairError> {
        let file = if path.is_dir() {
            let io = |source| FlowPairError::Io { path: path.to_owned(), source };
            let mut found = Vec::new();
            for entry in std::fs::read_dir(path).map_err(io)? {
                let p = entry.map_err(io)?.path();
                if p.extension().is_some_and(|e| e == "npz") {
                    found.push(p);
                }
            }
            if found.len() != 1 {
                return Err(FlowPairError::NoSingleNpz { dir: path.to_owned(), found: found.len() });
            }
            found.remove(0)
        } else {
            path.to_owned()
        };
        let bytes = std::fs::read(&file).map_err(|source| FlowPairError::Io { path: file.clone(), source })?;
        FlowPair::from_npz(&bytes)
    }

    /// Parses the archive's bytes; see the module doc for the layout.
    pub fn from_npz(bytes: &[u8]) -> Result<FlowPair, FlowPairError> {
        let mut arrays = read_npz(bytes)?;
        let pc1_raw = rows3(&mut arrays, "pc1", None)?;
        let pc2_raw = rows3(&mut arrays, "pc2", None)?;
        let (n1, n2) = (pc1_raw.len(), pc2_raw.len());
        let flow_raw = rows3(&mut arrays, "gt_flow_0_1", Some(n1))?;
        let classes_raw = vector_f32(&mut arrays, "pc1_classes", n1)?;
        let ground1_raw = vector_f32(&mut arrays, "ground1", n1)?;
        let ground2_raw = vector_f32(&mut arrays, "ground2", n2)?;
        let valid_idx = index_vector(&mut arrays, "pc1_flows_valid_idx")?;

        // Padding rows are all NaN; any non-finite coordinate makes a row unusable as a point.
        let finite = |p: &Point| p.iter().all(|c| c.is_finite());
        let keep1: Vec<Option<usize>> = {
            let mut next = 0;
            pc1_raw
                .iter()
                .map(|p| {
                    finite(p).then(|| {
                        next += 1;
                        next - 1
                    })
                })
                .collect()
        };
        let mut valid_raw = vec![false; n1];
        for (position, &index) in valid_idx.iter().enumerate() {
            let bad = |why| FlowPairError::BadIndex { name: "pc1_flows_valid_idx", position, index, why };
            let i = usize::try_from(index).ok().filter(|&i| i < n1).ok_or_else(|| bad("outside pc1"))?;
            if keep1[i].is_none() {
                return Err(bad("a padding row of pc1"));
            }
            if !finite(&flow_raw[i]) {
                return Err(bad("a row whose gt_flow_0_1 is not finite"));
            }
            valid_raw[i] = true;
        }
        let est_flow = match arrays.remove("est_flow") {
            None => None,
            Some(a) => {
                let est = rows3_array("est_flow", a, Some(valid_idx.len()))?;
                let mut per_point = vec![None; n1];
                for (&index, e) in valid_idx.iter().zip(est) {
                    // Validated above: a kept row of pc1.
                    per_point[index as usize] = Some(e);
                }
                Some(pick(&keep1, per_point))
            }
        };
        let nan = [f32::NAN; 3];
        let gt_flow = flow_raw.iter().zip(&valid_raw).map(|(f, &v)| if v { *f } else { nan }).collect();
        Ok(FlowPair {
            pc1: pick(&keep1, pc1_raw),
            ground1: pick(&keep1, ground1_raw.iter().map(|&g| g == 1.0).collect()),
            classes1: pick(&keep1, classes_raw),
            gt_flow: pick(&keep1, gt_flow),
            valid1: pick(&keep1, valid_raw),
            est_flow,
            ground2: pc2_raw.iter().zip(&ground2_raw).filter(|(p, _)| finite(p)).map(|(_, &g)| g == 1.0).collect(),
            pc2: pc2_raw.into_iter().filter(finite).collect(),
        })
    }
}

/// The elements of `values` whose row is kept.
fn pick<T>(keep: &[Option<usize>], values: Vec<T>) -> Vec<T> {
    values.into_iter().zip(keep).filter(|(_, k)| k.is_some()).map(|(v, _)| v).collect()
}

fn take(arrays: &mut BTreeMap<String, NpyArray>, name: &'static str) -> Result<NpyArray, FlowPairError> {
    arrays.remove(name).ok_or(FlowPairError::Missing(name))
}

fn describe(a: &NpyArray) -> String {
    format!("{} of shape {:?}", a.data.dtype().descr(), a.shape)
}

fn as_f32(name: &'static str, a: NpyArray, expected: &str) -> Result<Vec<f32>, FlowPairError> {
    match a.data {
        NpyData::F32(v) => Ok(v),
        NpyData::F64(v) => Ok(v.into_iter().map(|x| x as f32).collect()),
        _ => Err(FlowPairError::Layout { name, got: describe(&a), expected: expected.into() }),
    }
}

/// An (N, 3) float array as points; `rows` fixes N when given.
fn rows3_array(name: &'static str, a: NpyArray, rows: Option<usize>) -> Result<Vec<Point>, FlowPairError> {
    let expected = match rows {
        Some(n) => format!("float ({n}, 3)"),
        None => "float (N, 3)".into(),
    };
    match a.shape.as_slice() {
        [n, 3] if rows.is_none_or(|r| r == *n) => {}
        _ => return Err(FlowPairError::Layout { name, got: describe(&a), expected }),
    }
    let v = as_f32(name, a, &expected)?;
    Ok(v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
}

/// The (N, 3) float array `name` as points; `rows` fixes N when given.
fn rows3(
    arrays: &mut BTreeMap<String, NpyArray>,
    name: &'static str,
    rows: Option<usize>,
) -> Result<Vec<Point>, FlowPairError> {
    rows3_array(name, take(arrays, name)?, rows)
}

/// An (n,) float array.
fn vector_f32(
    arrays: &mut BTreeMap<String, NpyArray>,
    name: &'static str,
    n: usize,
) -> Result<Vec<f32>, FlowPairError> {
    let a = take(arrays, name)?;
    let expected = format!("float ({n},)");
    if a.shape != [n] {
        return Err(FlowPairError::Layout { name, got: describe(&a), expected });
    }
    as_f32(name, a, &expected)
}

/// A 1-D integer array.
fn index_vector(arrays: &mut BTreeMap<String, NpyArray>, name: &'static str) -> Result<Vec<i64>, FlowPairError> {
    let a = take(arrays, name)?;
    match (&a.data, a.shape.len()) {
        (NpyData::I64(v), 1) => Ok(v.clone()),
        (NpyData::I32(v), 1) => Ok(v.iter().map(|&i| i64::from(i)).collect()),
        _ => Err(FlowPairError::Layout { name, got: describe(&a), expected: "integer (M,)".into() }),
    }
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;
    use crate::io::npz::NpzWriter;

    /// Four `pc1` rows (row 2 padding), three `pc2` rows (row 0 padding); rows 0 and 3 valid.
    fn archive(valid: &[i64], with_est: bool) -> Vec<u8> {
        let nan = f32::NAN;
        let mut w = NpzWriter::new(Cursor::new(Vec::new()));
        w.add_f32("pc1", &[4, 3], &[0., 0., 0., 1., 0., 0., nan, nan, nan, 3., 0., 0.]).unwrap();
        w.add_f32("pc2", &[3, 3], &[nan, nan, nan, 0., 1., 0., 0., 2., 0.]).unwrap();
        w.add_f32("gt_flow_0_1", &[4, 3], &[0., 0., 0., 9., 9., 9., nan, nan, nan, 1., 0., 0.]).unwrap();
        w.add_i64("pc1_flows_valid_idx", &[valid.len()], valid).unwrap();
        w.add_f32("pc1_classes", &[4], &[-1., -1., -1., 10.]).unwrap();
        w.add_f32("ground1", &[4], &[1., 0., 0., 0.]).unwrap();
        w.add_f32("ground2", &[3], &[0., 1., 0.]).unwrap();
        if with_est {
            let est: Vec<f32> = (0..valid.len() * 3).map(|i| i as f32).collect();
            w.add_f32("est_flow", &[valid.len(), 3], &est).unwrap();
        }
        w.finish().unwrap().into_inner()
    }

    #[test]
    fn padding_is_dropped_and_every_array_stays_aligned() {
        let pair = FlowPair::from_npz(&archive(&[0, 3], true)).unwrap();
        assert_eq!(pair.pc1, vec![[0., 0., 0.], [1., 0., 0.], [3., 0., 0.]]);
        assert_eq!(pair.pc2, vec![[0., 1., 0.], [0., 2., 0.]]);
        assert_eq!(pair.ground1, vec![true, false, false]);
        assert_eq!(pair.ground2, vec![true, false]);
        assert_eq!(pair.classes1, vec![-1., -1., 10.]);
        assert_eq!(pair.valid1, vec![true, false, true]);
        assert_eq!(pair.gt_flow[0], [0., 0., 0.]);
        assert!(pair.gt_flow[1].iter().all(|c| c.is_nan()), "an invalid row's flow is not used");
        assert_eq!(pair.gt_flow[2], [1., 0., 0.]);
        assert_eq!(pair.est_flow, Some(vec![Some([0., 1., 2.]), None, Some([3., 4., 5.])]));
        assert_eq!(FlowPair::from_npz(&archive(&[0, 3], false)).unwrap().est_flow, None);
    }

    #[test]
    fn malformed_pairs_are_clear_errors() {
        let msg = |bytes: &[u8]| FlowPair::from_npz(bytes).unwrap_err().to_string();
        assert_eq!(msg(&archive(&[0, 2], false)), "flow pair: pc1_flows_valid_idx[1] = 2 is a padding row of pc1");
        assert_eq!(msg(&archive(&[7], false)), "flow pair: pc1_flows_valid_idx[0] = 7 is outside pc1");
        assert_eq!(msg(&archive(&[-1], false)), "flow pair: pc1_flows_valid_idx[0] = -1 is outside pc1");
        let mut w = NpzWriter::new(Cursor::new(Vec::new()));
        w.add_f32("pc1", &[2, 2], &[0.; 4]).unwrap();
        assert_eq!(
            msg(&w.finish().unwrap().into_inner()),
            "flow pair: array 'pc1' is <f4 of shape [2, 2], expected float (N, 3)"
        );
        let mut w = NpzWriter::new(Cursor::new(Vec::new()));
        w.add_f32("pc1", &[1, 3], &[0.; 3]).unwrap();
        assert_eq!(msg(&w.finish().unwrap().into_inner()), "flow pair: no array 'pc2'");
        assert!(msg(b"PK garbage").starts_with("not a readable .npz"));
    }
}
