//! The part of a domain's level set a streaming client needs (`GET /v1/levelset`).
//!
//! A store of a mesh with an outside holds the signed distance `φ` to the domain's boundary at
//! every vertex, clamped to `±cap` (the largest diameter of a tet the vertex is a corner or an
//! edge midpoint of; see the server's `resample::levelset`). A client draws hierarchy tets and
//! green pieces, whose corners are a tet's corners and edge midpoints. A vertex at the clamp is
//! never interpolated across a drawn tet that straddles the boundary: `φ` is 1-Lipschitz, so
//! every such tet lies on one side, and any value of that side's sign draws it as the exact one
//! does (whole inside, nothing outside). And a tet whose corners are all ≥ 0 is drawn whole
//! whatever they hold. So the band lists the corners and edge midpoints of the tets (of any
//! level) with one of them outside: near ones (`|φ| < cap`) with their value, far-outside ones
//! flagged ([`FAR_OUTSIDE`]: only the sign matters); a client gives every vertex not listed
//! (inside, in no such tet) a positive value (e.g. the domain's diameter).
//!
//! Near values are kept as integer multiples of a `step` (the server takes 1/32 of the smallest
//! clamp, about two finest tets' diameter, so the clipped boundary moves by less than 1/32 of a
//! finest tet), rounded
//! so that the sign survives: a value `< 0` becomes a code `≤ −1`.
//!
//! Coded as `count: u64 LE`, `step: f32 LE`, then one [`crate::entropy`] stream: per entry its
//! key's gap to the previous (adaptive integer, context: the previous gap's bit length), an
//! adaptive flag "far outside" (context: the previous entry's), and otherwise its code (zigzag
//! adaptive integer, context: the previous code's bit length); runs of far-outside vertices cost
//! a fraction of a bit each. Decoding is total: a malformed, truncated or oversized body is an
//! error.
//!
//! **A box domain** (a raw grid's voxels inside a lattice that reaches past them) needs no band:
//! its body is the count `u64::MAX`, then the box's `lo` and `hi` (6 × f64 LE, 56 bytes in all),
//! and a client gives each vertex the exact signed distance to the box at its position
//! ([`NearLevelSet::value_at`]). On the finest level the box's faces are lattice planes, so the
//! clip is exact there; coarser tets straddling a face are clipped by the linear interpolant, as
//! with a band.

use crate::entropy::{unzigzag, zigzag, Bit, Decoder, Encoder, EntropyError, UInt};

/// The value [`NearLevelSet::get`] gives a far-outside vertex: only its sign matters.
pub const FAR_OUTSIDE: f32 = f32::NEG_INFINITY;

/// The code of a far-outside vertex.
const FAR: i32 = i32::MIN;
/// Gap contexts: the previous gap's bit length, capped.
const GAP_CONTEXTS: usize = 24;
/// Code contexts: the previous code's bit length, capped.
const CODE_CONTEXTS: usize = 24;
/// Largest code magnitude (a near value is below its cap, a few thousand steps at most in any
/// sensible hierarchy; this bounds what a decoder accepts).
const MAX_CODE: u64 = 1 << 30;

/// The near band of a level set: per listed vertex key (increasing), its value as a code of
/// `step`, or far outside.
#[derive(Debug, Clone, PartialEq)]
pub struct NearLevelSet {
    step: f32,
    keys: Vec<u64>,
    codes: Vec<i32>,
    /// A box domain ([`NearLevelSet::of_box`]): no entries, `φ` computed from positions.
    domain_box: Option<[[f64; 3]; 2]>,
}

/// The count that marks a box domain's body: `u64::MAX`, then `lo` and `hi` as 6 f64 LE.
const BOX_MARK: u64 = u64::MAX;

/// The exact signed distance from `p` to the boundary of the box `[lo, hi]`, positive inside.
pub fn box_signed_distance(lo: [f64; 3], hi: [f64; 3], p: [f64; 3]) -> f64 {
    let inside = (0..3).all(|a| lo[a] <= p[a] && p[a] <= hi[a]);
    if inside {
        (0..3)
            .map(|a| (p[a] - lo[a]).min(hi[a] - p[a]))
            .fold(f64::INFINITY, f64::min)
    } else {
        -(0..3)
            .map(|a| (lo[a] - p[a]).max(p[a] - hi[a]).max(0.0).powi(2))
            .sum::<f64>()
            .sqrt()
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LevelSetError {
    #[error("level set: {0} bytes is too short for its header")]
    Truncated(usize),
    #[error("level set: {count} entries for a hierarchy of {keys} vertices")]
    TooMany { count: u64, keys: u64 },
    #[error("level set: key {key} is beyond the hierarchy's {keys} vertices")]
    KeyOutOfRange { key: u64, keys: u64 },
    #[error("level set: step {0} is not positive and finite")]
    BadStep(f32),
    #[error("level set: the value {value} of key {key} is not finite or beyond 2^30 steps")]
    BadValue { key: u64, value: f32 },
    #[error("level set: a box domain's corners {lo:?} .. {hi:?} are not finite and ordered")]
    BadBox { lo: [f64; 3], hi: [f64; 3] },
    #[error("level set: a box domain's body is {0} bytes, not 56")]
    BoxLength(usize),
    #[error("level set: {0}")]
    Coding(#[from] EntropyError),
}

fn context(v: u64, n: usize) -> usize {
    ((u64::BITS - v.leading_zeros()) as usize).min(n - 1)
}

impl NearLevelSet {
    /// The entries `(key, φ)` in any order (φ = [`FAR_OUTSIDE`] for a far-outside vertex; a
    /// repeated key keeps its last value), values rounded to codes of `step`, signs kept.
    pub fn new(
        step: f32,
        entries: impl IntoIterator<Item = (u64, f32)>,
    ) -> Result<Self, LevelSetError> {
        if !(step.is_finite() && step > 0.0) {
            return Err(LevelSetError::BadStep(step));
        }
        let mut e: Vec<(u64, f32)> = entries.into_iter().collect();
        e.sort_by_key(|x| x.0);
        let mut out = NearLevelSet {
            step,
            keys: Vec::with_capacity(e.len()),
            codes: Vec::with_capacity(e.len()),
            domain_box: None,
        };
        for (key, value) in e {
            let code = if value == FAR_OUTSIDE {
                FAR
            } else {
                let q = (value as f64 / step as f64).round();
                // a negative value stays negative
                let q = if value < 0.0 { q.min(-1.0) } else { q };
                if !(q.is_finite() && q.abs() <= MAX_CODE as f64 && (q as f32 * step).is_finite()) {
                    return Err(LevelSetError::BadValue { key, value });
                }
                q as i32
            };
            if out.keys.last() == Some(&key) {
                *out.codes.last_mut().expect("a code per key") = code;
            } else {
                out.keys.push(key);
                out.codes.push(code);
            }
        }
        Ok(out)
    }

    /// The level set of the box domain `[lo, hi]` (a raw grid's voxels inside a lattice that
    /// reaches past them): no entries, 56 bytes coded; [`Self::value_at`] gives each vertex the
    /// exact signed distance to the box at its position.
    pub fn of_box(lo: [f64; 3], hi: [f64; 3]) -> Result<Self, LevelSetError> {
        if !(0..3).all(|a| lo[a].is_finite() && hi[a].is_finite() && lo[a] <= hi[a]) {
            return Err(LevelSetError::BadBox { lo, hi });
        }
        Ok(NearLevelSet {
            step: 1.0,
            keys: Vec::new(),
            codes: Vec::new(),
            domain_box: Some([lo, hi]),
        })
    }

    /// The box of a box domain.
    pub fn domain_box(&self) -> Option<[[f64; 3]; 2]> {
        self.domain_box
    }

    /// `φ` as a client draws it at vertex `key`, at `pos`, with `far` beyond any tet's diameter:
    /// a box domain's exact signed distance (clamped to `±far`); otherwise a listed value as
    /// listed, a far-outside one `−far`, an unlisted one (no tet beside the outside has it) `+far`.
    pub fn value_at(&self, key: u64, pos: [f64; 3], far: f32) -> f32 {
        if let Some([lo, hi]) = self.domain_box {
            return (box_signed_distance(lo, hi, pos) as f32).clamp(-far, far);
        }
        match self.get(key) {
            Some(FAR_OUTSIDE) => -far,
            Some(v) => v,
            None => far,
        }
    }

    pub fn len(&self) -> usize {
        self.keys.len()
    }

    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    pub fn step(&self) -> f32 {
        self.step
    }

    fn value(&self, code: i32) -> f32 {
        match code {
            FAR => FAR_OUTSIDE,
            c => c as f32 * self.step,
        }
    }

    /// `φ` (to within half a step, sign kept) at vertex `key` when it is near the boundary,
    /// [`FAR_OUTSIDE`] when it is far outside, `None` when it is not listed (far inside).
    pub fn get(&self, key: u64) -> Option<f32> {
        self.keys
            .binary_search(&key)
            .ok()
            .map(|i| self.value(self.codes[i]))
    }

    /// The entries in key order.
    pub fn iter(&self) -> impl Iterator<Item = (u64, f32)> + '_ {
        self.keys
            .iter()
            .zip(&self.codes)
            .map(|(&k, &c)| (k, self.value(c)))
    }

    /// The coded form (see the module documentation).
    pub fn encode(&self) -> Result<Vec<u8>, LevelSetError> {
        if let Some(corners) = self.domain_box {
            let mut out = BOX_MARK.to_le_bytes().to_vec();
            out.extend(corners.iter().flatten().flat_map(|x| x.to_le_bytes()));
            return Ok(out);
        }
        let mut e = Encoder::default();
        let mut m = Models::default();
        let (mut prev, mut gap_ctx, mut code_ctx, mut prev_far) = (None::<u64>, 0, 0, false);
        for (&k, &c) in self.keys.iter().zip(&self.codes) {
            let gap = prev.map_or(k, |p| k - p - 1);
            e.uint(&mut m.gaps[gap_ctx], gap)?;
            gap_ctx = context(gap, GAP_CONTEXTS);
            prev = Some(k);
            let far = c == FAR;
            e.bit(&mut m.far[prev_far as usize], far);
            prev_far = far;
            if !far {
                let z = zigzag(c as i64);
                e.uint(&mut m.codes[code_ctx], z)?;
                code_ctx = context(z, CODE_CONTEXTS);
            }
        }
        let mut out = (self.keys.len() as u64).to_le_bytes().to_vec();
        out.extend(self.step.to_le_bytes());
        out.extend(e.finish());
        Ok(out)
    }

    /// Decodes a body of a hierarchy with `n_keys` vertices: keys increasing and below `n_keys`,
    /// the step positive and finite, codes within 2^30 and finite values. The count is bounded by
    /// `n_keys` only (runs of far-outside entries cost a fraction of a bit), so pass a vertex
    /// count the caller has accepted.
    pub fn decode(bytes: &[u8], n_keys: u64) -> Result<Self, LevelSetError> {
        if bytes.len() < 12 {
            return Err(LevelSetError::Truncated(bytes.len()));
        }
        let count = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes"));
        if count == BOX_MARK {
            if bytes.len() != 56 {
                return Err(LevelSetError::BoxLength(bytes.len()));
            }
            let x: Vec<f64> = bytes[8..]
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect();
            return Self::of_box([x[0], x[1], x[2]], [x[3], x[4], x[5]]);
        }
        let step = f32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
        if count > n_keys {
            return Err(LevelSetError::TooMany {
                count,
                keys: n_keys,
            });
        }
        let mut out = NearLevelSet::new(step, [])?;
        if count == 0 {
            return Ok(out);
        }
        let mut d = Decoder::new(&bytes[12..])?;
        let mut m = Models::default();
        let (mut prev, mut gap_ctx, mut code_ctx, mut prev_far) = (None::<u64>, 0, 0, false);
        for _ in 0..count {
            let gap = d.uint(&mut m.gaps[gap_ctx])?;
            gap_ctx = context(gap, GAP_CONTEXTS);
            let key = match prev {
                None => Some(gap),
                Some(p) => p.checked_add(gap).and_then(|k| k.checked_add(1)),
            }
            .filter(|&k| k < n_keys)
            .ok_or(LevelSetError::KeyOutOfRange {
                key: prev.map_or(gap, |p| p.saturating_add(gap).saturating_add(1)),
                keys: n_keys,
            })?;
            prev = Some(key);
            let far = d.bit(&mut m.far[prev_far as usize])?;
            prev_far = far;
            let code = if far {
                FAR
            } else {
                let z = d.uint(&mut m.codes[code_ctx])?;
                code_ctx = context(z, CODE_CONTEXTS);
                let c = unzigzag(z);
                if c.unsigned_abs() > MAX_CODE || !(c as f32 * step).is_finite() {
                    return Err(LevelSetError::BadValue {
                        key,
                        value: c as f32 * step,
                    });
                }
                c as i32
            };
            out.keys.push(key);
            out.codes.push(code);
        }
        Ok(out)
    }
}

/// The adaptive models of one body.
struct Models {
    gaps: Vec<UInt>,
    far: [Bit; 2],
    codes: Vec<UInt>,
}

impl Default for Models {
    fn default() -> Self {
        Models {
            gaps: vec![UInt::default(); GAP_CONTEXTS],
            far: [Bit::default(); 2],
            codes: vec![UInt::default(); CODE_CONTEXTS],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_box_domain_round_trips_in_56_bytes_and_gives_the_exact_distance() {
        let (lo, hi) = ([0.0, -1.0, 2.0], [4.0, 1.0, 2.5]);
        let set = NearLevelSet::of_box(lo, hi).unwrap();
        let bytes = set.encode().unwrap();
        assert_eq!(bytes.len(), 56);
        let back = NearLevelSet::decode(&bytes, 10).unwrap();
        assert_eq!(back, set);
        assert_eq!(back.domain_box(), Some([lo, hi]));
        assert!(back.is_empty() && back.get(3).is_none());
        let far = 100.0;
        // inside: the nearest face; on a face: 0; outside: the distance to the box
        assert_eq!(back.value_at(0, [1.0, 0.0, 2.25], far), 0.25);
        assert_eq!(back.value_at(0, [4.0, 0.0, 2.25], far), 0.0);
        assert_eq!(back.value_at(0, [5.0, 0.0, 2.25], far), -1.0);
        assert_eq!(back.value_at(0, [7.0, 5.0, 2.25], far), -5.0);
        assert_eq!(back.value_at(0, [1e9, 0.0, 2.25], far), -far);
        // refused: other lengths, disordered or infinite corners
        assert_eq!(
            NearLevelSet::decode(&bytes[..55], 10),
            Err(LevelSetError::BoxLength(55))
        );
        let mut bad = bytes.clone();
        bad[8..16].copy_from_slice(&9.0f64.to_le_bytes());
        assert!(matches!(
            NearLevelSet::decode(&bad, 10),
            Err(LevelSetError::BadBox { .. })
        ));
        assert!(NearLevelSet::of_box([0.0; 3], [f64::INFINITY, 1.0, 1.0]).is_err());
    }

    #[test]
    fn a_band_round_trips_and_answers_lookups() {
        let step = 1e-3;
        let set = NearLevelSet::new(
            step,
            (0..2000u64)
                .map(|i| (i * 7 + 3, (i as f32 * 0.01).sin() * 0.1))
                .chain((20_000..30_000).map(|k| (k, FAR_OUTSIDE))),
        )
        .unwrap();
        let bytes = set.encode().unwrap();
        let back = NearLevelSet::decode(&bytes, 30_000).unwrap();
        assert_eq!(back, set);
        assert_eq!(back.get(3), Some(0.0));
        assert_eq!(back.get(4), None);
        assert_eq!(back.get(25_000), Some(FAR_OUTSIDE));
        let v = (1999f32 * 0.01).sin() * 0.1;
        let got = back.get(7 * 1999 + 3).unwrap();
        assert!((got - v).abs() <= step / 2.0 + 1e-7 && got.signum() == v.signum());
        // a tiny negative value stays negative
        let tiny = NearLevelSet::new(step, [(1, -1e-9), (2, 1e-9)]).unwrap();
        assert!(tiny.get(1).unwrap() < 0.0 && tiny.get(2).unwrap() >= 0.0);
        // about a byte a near entry (codes up to 100 steps); a run of far ones almost free
        assert!(bytes.len() < 2000 * 2 + 200, "{} bytes", bytes.len());
        // refused: keys or a count beyond the hierarchy, a short header, a bad step or value
        assert!(matches!(
            NearLevelSet::decode(&bytes, 100),
            Err(LevelSetError::TooMany { .. } | LevelSetError::KeyOutOfRange { .. })
        ));
        assert_eq!(
            NearLevelSet::decode(&[1, 2, 3], 10),
            Err(LevelSetError::Truncated(3))
        );
        assert_eq!(
            NearLevelSet::new(0.0, []).err(),
            Some(LevelSetError::BadStep(0.0))
        );
        assert!(matches!(
            NearLevelSet::new(1.0, [(5, f32::NAN)]),
            Err(LevelSetError::BadValue { key: 5, .. })
        ));
    }

    proptest! {
        #[test]
        fn any_entries_round_trip(entries in proptest::collection::vec((0u64..1 << 40, -1e6f32..1e6, any::<bool>()), 0..200), step in 1e-3f32..10.0) {
            let set = NearLevelSet::new(
                step,
                entries.into_iter().map(|(k, v, far)| (k, if far { FAR_OUTSIDE } else { v })),
            )
            .unwrap();
            let back = NearLevelSet::decode(&set.encode().unwrap(), 1 << 40).unwrap();
            prop_assert_eq!(back, set);
        }

        #[test]
        fn decoding_any_body_is_total(bytes in proptest::collection::vec(any::<u8>(), 0..200), n_keys in 0u64..1000) {
            if let Ok(set) = NearLevelSet::decode(&bytes, n_keys) {
                let keys: Vec<u64> = set.iter().map(|e| e.0).collect();
                prop_assert!(keys.windows(2).all(|w| w[0] < w[1]));
                prop_assert!(keys.iter().all(|&k| k < n_keys));
                prop_assert!(set.iter().all(|e| !e.1.is_nan()));
            }
        }
    }
}
