//! Mid-fit checkpoints of a trajectory fit: the network, the optimiser's moments, the random
//! generator's position, the best-validation network and the early-stopping counters, at the
//! start of a validation iteration. A fit that goes on from one gives the same bits as a fit
//! that never stopped (tested in [`super::ntp`]), so a job whose worker died loses only the
//! iterations since the last checkpoint.
//!
//! File layout (little-endian): `MBNTCKP1`, a `u64` length and that many bytes of JSON (the
//! scalars and the loss curve), then three length-prefixed blocks (the network in
//! [`Mlp::to_bytes`]'s format, Adam's first and second moments as `f32`s), a fourth for the
//! best network (empty when there is none yet), and an FNV-1a checksum of all that precedes it.

use serde::{Deserialize, Serialize};

use crate::model::LossCurve;
use crate::nn::{Adam, Mlp};

const MAGIC: &[u8; 8] = b"MBNTCKP1";

/// Where a fit keeps its checkpoints, for a later run of the same fit (same frames, method and
/// parameters) to go on from.
pub trait Checkpoints {
    /// Whether a checkpoint should be taken now (called at each validation iteration); a
    /// store over the network says yes at most every so many seconds.
    fn due(&mut self) -> bool;
    /// The latest checkpoint kept by an earlier run, if any.
    fn latest(&mut self) -> Option<Vec<u8>>;
    /// Keeps `bytes` as the latest checkpoint, replacing the previous one (atomically: a
    /// failure or a crash while keeping it leaves the previous one usable).
    fn keep(&mut self, bytes: &[u8]);
    /// Told once when the fit goes on from the latest checkpoint, at iteration `iteration`.
    fn resumed(&mut self, iteration: usize);
}

/// Takes no checkpoints and has none.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoCheckpoints;

impl Checkpoints for NoCheckpoints {
    fn due(&mut self) -> bool {
        false
    }
    fn latest(&mut self) -> Option<Vec<u8>> {
        None
    }
    fn keep(&mut self, _bytes: &[u8]) {}
    fn resumed(&mut self, _iteration: usize) {}
}

/// The scalar part of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Scalars {
    /// Identifies the fit (parameters, frames, method): a checkpoint of another fit is ignored.
    pub fingerprint: u64,
    /// The iteration the fit goes on with.
    pub next_iteration: usize,
    /// Adam's step count and learning rate.
    pub adam_steps: u64,
    pub adam_lr: f32,
    /// The random generator's word position (its seed and stream are the fit's), as a decimal
    /// string: JSON numbers cannot hold a `u128`.
    pub rng_word_pos: String,
    /// Best validation loss and its iteration, when a validation has run.
    pub best: Option<(f64, usize)>,
    pub validations_since_best: usize,
    pub restarts: usize,
    pub lr_scale: f32,
    /// The loss curve so far.
    pub losses: LossCurve,
}

/// Everything a trajectory fit needs to go on.
pub(crate) struct TrajectoryState {
    pub scalars: Scalars,
    pub mlp: Mlp<f32>,
    pub adam: Adam<f32>,
    pub best_mlp: Option<Mlp<f32>>,
}

fn fnv1a64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// A fingerprint of `parts` (FNV-1a over their bytes, each length-prefixed).
pub(crate) fn fingerprint(parts: &[&[u8]]) -> u64 {
    let mut bytes = Vec::new();
    for p in parts {
        bytes.extend_from_slice(&(p.len() as u64).to_le_bytes());
        bytes.extend_from_slice(p);
    }
    fnv1a64(&bytes)
}

fn push_block(out: &mut Vec<u8>, block: &[u8]) {
    out.extend_from_slice(&(block.len() as u64).to_le_bytes());
    out.extend_from_slice(block);
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

impl TrajectoryState {
    /// The checkpoint's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        push_block(&mut out, &serde_json::to_vec(&self.scalars).expect("plain data always serialises"));
        push_block(&mut out, &self.mlp.to_bytes());
        let (m, v) = self.adam.moments();
        push_block(&mut out, &f32_bytes(m));
        push_block(&mut out, &f32_bytes(v));
        push_block(&mut out, &self.best_mlp.as_ref().map(Mlp::to_bytes).unwrap_or_default());
        let checksum = fnv1a64(&out);
        out.extend_from_slice(&checksum.to_le_bytes());
        out
    }

    /// Reads a checkpoint written by [`TrajectoryState::to_bytes`]; says what is wrong with a
    /// damaged one.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        let body = bytes.len().checked_sub(8).filter(|&n| n >= MAGIC.len()).ok_or("too short")?;
        if &bytes[..MAGIC.len()] != MAGIC {
            return Err("not a checkpoint (bad magic)".into());
        }
        let stored = u64::from_le_bytes(bytes[body..].try_into().expect("8 bytes"));
        if fnv1a64(&bytes[..body]) != stored {
            return Err("checksum mismatch".into());
        }
        let mut rest = &bytes[MAGIC.len()..body];
        let mut block = || -> Result<&[u8], String> {
            let (len, tail) = rest.split_first_chunk::<8>().ok_or("truncated block length")?;
            let len = usize::try_from(u64::from_le_bytes(*len)).map_err(|e| e.to_string())?;
            if len > tail.len() {
                return Err("truncated block".into());
            }
            let (head, tail) = tail.split_at(len);
            rest = tail;
            Ok(head)
        };
        let scalars: Scalars = serde_json::from_slice(block()?).map_err(|e| format!("scalars: {e}"))?;
        let mlp = Mlp::<f32>::from_bytes(block()?).map_err(|e| format!("network: {e}"))?;
        let floats = |b: &[u8]| -> Result<Vec<f32>, String> {
            if !b.len().is_multiple_of(4) {
                return Err("moments are not whole f32s".into());
            }
            Ok(b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect())
        };
        let m = floats(block()?)?;
        let v = floats(block()?)?;
        let best = block()?;
        let best_mlp =
            if best.is_empty() { None } else { Some(Mlp::<f32>::from_bytes(best).map_err(|e| format!("best: {e}"))?) };
        if !rest.is_empty() {
            return Err(format!("{} unexpected bytes", rest.len()));
        }
        if m.len() != mlp.parameters().len() || best_mlp.as_ref().is_some_and(|b| b.dims() != mlp.dims()) {
            return Err("the parts belong to different networks".into());
        }
        let adam = Adam::from_moments(scalars.adam_lr, m, v, scalars.adam_steps)
            .ok_or("the moments have different lengths")?;
        Ok(Self { scalars, mlp, adam, best_mlp })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn state() -> TrajectoryState {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mlp = Mlp::<f32>::new(&[5, 8, 6], &mut rng);
        let n = mlp.parameters().len();
        let m: Vec<f32> = (0..n).map(|i| i as f32 * 0.5 - 3.0).collect();
        let v: Vec<f32> = (0..n).map(|i| (i as f32).sqrt()).collect();
        let mut losses = LossCurve::default();
        losses.push(1, crate::fit::LossTerms { chamfer: 0.25, cycle: 0.5, rigidity: 0.125, total: 0.875 }, None);
        TrajectoryState {
            scalars: Scalars {
                fingerprint: 42,
                next_iteration: 30,
                adam_steps: 30,
                adam_lr: 1e-3,
                rng_word_pos: u128::MAX.to_string(),
                best: Some((0.1 + 0.2, 20)),
                validations_since_best: 1,
                restarts: 0,
                lr_scale: 0.5,
                losses,
            },
            adam: Adam::from_moments(1e-3, m, v, 30).unwrap(),
            best_mlp: Some(Mlp::<f32>::new(&[5, 8, 6], &mut rng)),
            mlp,
        }
    }

    #[test]
    fn a_checkpoint_reads_back_bit_for_bit() {
        let s = state();
        let bytes = s.to_bytes();
        let back = TrajectoryState::from_bytes(&bytes).unwrap();
        assert_eq!(back.scalars, s.scalars);
        assert_eq!(back.to_bytes(), bytes);
        assert_eq!(back.adam.steps(), 30);
        assert_eq!(back.scalars.rng_word_pos.parse::<u128>().unwrap(), u128::MAX);
    }

    #[test]
    fn a_damaged_checkpoint_is_an_error() {
        let bytes = state().to_bytes();
        for cut in [0, 7, 8, 20, bytes.len() - 1] {
            assert!(TrajectoryState::from_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut flipped = bytes.clone();
        flipped[40] ^= 1;
        assert_eq!(TrajectoryState::from_bytes(&flipped).err().unwrap(), "checksum mismatch");
    }
}
