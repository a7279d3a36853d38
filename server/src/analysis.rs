//! Wavelet analysis: predict-only lifting over the semi-regular hierarchy (thesis §4.3, design.md).
//!
//! For every new vertex `m` (midpoint of an edge `(u,v)` of a level-`k−1` tet) one detail
//! `d_m = f(m) − (f(u)+f(v))/2`, owned by the lowest-id level-`k−1` tet containing the edge.
//! The details are computed against the values *synthesis will reconstruct* (closed loop, coarse to
//! fine): in exact arithmetic this is the same as lifting from the finest level up, and in f32 it makes
//! the lossless round trip bit-exact (see [`tetwave_protocol::wavelet::analyze`]) and keeps quantization
//! error from accumulating across levels: with step `q` every vertex is within `q/2` of its sample.
//!
//! Per node the analysis also records the max |detail| of every vertex created in its subtree and which
//! children are empty (outside the input's domain, see [`crate::resample`]).

use crate::resample::Resampled;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, Ordering};
use tetwave_protocol::hierarchy::{bey_split_edges, midpoint, LevelWalker, BEY_CHILDREN, EDGES};
use tetwave_protocol::vertex::VertexKeys;
use tetwave_protocol::wavelet::{analyze, predict, synthesize, Quantizer};
use tetwave_protocol::LatticeTet;
use tetwave_protocol::{BaseMesh, Forest};

/// Everything the store needs, in node-id order.
pub struct Analysis {
    /// Base mesh with reconstructed base values and empty flags.
    pub base: BaseMesh,
    /// Per node: owned-edge mask.
    pub owned: Vec<u8>,
    /// Per node: bit `i` set when child `i` is empty.
    pub empty_children: Vec<u8>,
    /// Per node: max |detail| of all vertices created by refining it and its descendants.
    pub subtree_max_abs: Vec<f32>,
    /// Owned details in node order, then edge order (dequantized when quantized).
    pub coeffs: Vec<f32>,
    pub quantizer: Option<Quantizer>,
    /// The sampled value of every vertex (outside vertices filled by the outside rule): what
    /// synthesis is compared against.
    pub reference: Vec<f32>,
    /// Inside samples' range.
    pub value_range: (f32, f32),
    /// Measured max |synthesis − sample|.
    pub max_abs_error: f64,
    /// The bound the store promises (`q/2` plus f32 rounding when quantized, `1e-6 × range` lossless).
    pub error_bound: f64,
}

impl Analysis {
    /// The detail nodes in id order, as the store holds them.
    pub fn nodes(&self) -> Vec<tetwave_protocol::DetailNode> {
        let mut at = 0;
        (0..self.owned.len())
            .map(|i| {
                let n = self.owned[i].count_ones() as usize;
                let node = tetwave_protocol::DetailNode {
                    id: i as u64,
                    owned: self.owned[i],
                    empty_children: self.empty_children[i],
                    subtree_max_abs: self.subtree_max_abs[i],
                    coeffs: self.coeffs[at..at + n].to_vec(),
                };
                at += n;
                node
            })
            .collect()
    }
}

#[derive(Debug, thiserror::Error)]
pub enum AnalysisError {
    #[error("--bits must be in 8..=24, got {0}")]
    BadBits(u8),
    #[error("{0} tets in one level is more than this build can index")]
    TooLarge(u64),
}

fn bar(len: u64, msg: &str, show: bool) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} ({eta})")
            .unwrap_or(ProgressStyle::default_bar()),
    );
    pb.set_message(msg.to_string());
    pb
}

/// Keys of the 10 split points of a tet: its 4 vertices, then its 6 edge midpoints.
#[inline]
fn split_keys(keys: &VertexKeys, t: &LatticeTet) -> [usize; 10] {
    let p = t.split_points();
    std::array::from_fn(|i| keys.key(t.base, &p[i]) as usize)
}

/// The ids of level `k` cut into chunks for parallel walks.
fn level_chunks(forest: Forest, k: u8, chunk: u64) -> Vec<std::ops::Range<u64>> {
    let (lo, hi) = (forest.level_start(k), forest.level_start(k + 1));
    (lo..hi)
        .step_by(chunk as usize)
        .map(|s| s..(s + chunk).min(hi))
        .collect()
}

const CHUNK: u64 = 4096;

/// One chunk's output: owned masks, coefficients, max error, own max |d|, empty-children masks.
type ChunkOut = (Vec<u8>, Vec<f32>, f64, Vec<f32>, Vec<u8>);

/// Calls `f(id, keys)` for every tet of level `k` whose parent lies in `parents` (level `k − 1`;
/// for `k = 0`, `parents` are base tet ids and the base tets themselves are visited), with `keys` the
/// keys of its 4 vertices then its 6 edge midpoints. Children's vertex keys come from the parent's
/// split, and the 25 midpoints of the split's edges are keyed once per parent.
fn for_each_tet_keys(
    forest: Forest,
    keys: &VertexKeys,
    k: u8,
    parents: std::ops::Range<u64>,
    mut f: impl FnMut(u64, &[usize; 10]),
) {
    if k == 0 {
        for (id, tet) in LevelWalker::new(forest, 0, parents) {
            f(id, &split_keys(keys, &tet));
        }
        return;
    }
    let split = bey_split_edges();
    let mut mid = [0usize; 25];
    for (pid, parent) in LevelWalker::new(forest, k - 1, parents) {
        let pk = split_keys(keys, &parent);
        let pp = parent.split_points();
        for (j, &(a, b)) in split.edges.iter().enumerate() {
            mid[j] = keys.key(parent.base, &midpoint(&pp[a], &pp[b])) as usize;
        }
        for (i, c) in BEY_CHILDREN.iter().enumerate() {
            let ce = &split.child_edges[i];
            let ck = [
                pk[c[0]], pk[c[1]], pk[c[2]], pk[c[3]], mid[ce[0]], mid[ce[1]], mid[ce[2]],
                mid[ce[3]], mid[ce[4]], mid[ce[5]],
            ];
            f(forest.child(pid, i), &ck);
        }
    }
}

/// Parent-id chunks whose children make up level `k` (base tet ids for `k = 0`).
fn parent_chunks(forest: Forest, k: u8) -> Vec<std::ops::Range<u64>> {
    if k == 0 {
        level_chunks(forest, 0, CHUNK)
    } else {
        level_chunks(forest, k - 1, CHUNK / 8)
    }
}

/// Max |open-loop detail| over all new vertices (sizes the quantizer).
fn max_open_detail(forest: Forest, r: &Resampled) -> f64 {
    (0..forest.levels)
        .map(|k| {
            level_chunks(forest, k, CHUNK)
                .into_par_iter()
                .map(|range| {
                    let mut m = 0f64;
                    for (_, tet) in LevelWalker::new(forest, k, range) {
                        let sk = split_keys(&r.keys, &tet);
                        for (e, &(a, b)) in EDGES.iter().enumerate() {
                            let f = |i: usize| r.samples[sk[i]] as f64;
                            let d = f(4 + e) - 0.5 * (f(a) + f(b));
                            if d.is_finite() {
                                m = m.max(d.abs());
                            }
                        }
                    }
                    m
                })
                .reduce(|| 0.0, f64::max)
        })
        .fold(0.0, f64::max)
}

#[inline]
fn load(a: &[AtomicU32], i: usize) -> f32 {
    f32::from_bits(a[i].load(Ordering::Relaxed))
}

#[inline]
fn store(a: &[AtomicU32], i: usize, x: f32) {
    a[i].store(x.to_bits(), Ordering::Relaxed)
}

/// Runs the analysis. `bits`: uniform quantization of the details (8..=24), or lossless f32.
pub fn analyze_hierarchy(
    r: Resampled,
    bits: Option<u8>,
    progress: bool,
) -> Result<Analysis, AnalysisError> {
    if let Some(b) = bits {
        if !(8..=24).contains(&b) {
            return Err(AnalysisError::BadBits(b));
        }
    }
    let forest = r.base.forest();
    let levels = forest.levels;
    if levels > 0 && forest.level_len(levels - 1) >= u32::MAX as u64 {
        return Err(AnalysisError::TooLarge(forest.level_len(levels - 1)));
    }
    let nodes = forest.nodes() as usize;
    let nv = r.base.positions.len();
    let outside: Vec<bool> = r.samples.iter().map(|x| x.is_nan()).collect();
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for &x in r.samples.iter().filter(|x| !x.is_nan()) {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    let range = (hi - lo) as f64;
    let quantizer = bits.map(|b| {
        let m = max_open_detail(forest, &r);
        // closed-loop details are at most m + q/2: the codes ±(2^(b−1)−1) cover them with q = m/(max−1)
        let step = if m > 0.0 {
            (m / (Quantizer::max_code(b) - 1) as f64) as f32
        } else {
            1.0
        };
        Quantizer { bits: b, step }
    });

    let Resampled {
        mut base,
        keys,
        samples,
        ..
    } = r;
    // outside base vertices take the mean of the inside samples
    let inside_mean = {
        let (s, c) = samples
            .iter()
            .filter(|x| !x.is_nan())
            .fold((0f64, 0u64), |(s, c), &x| (s + x as f64, c + 1));
        (s / c.max(1) as f64) as f32
    };
    // in place (same layout): no second copy of the samples
    let reference: Vec<AtomicU32> = samples
        .into_iter()
        .map(|x| AtomicU32::new(x.to_bits()))
        .collect();
    for v in 0..nv {
        if load(&reference, v).is_nan() {
            store(&reference, v, inside_mean);
        }
    }
    let rec: Vec<AtomicU32> = reference
        .iter()
        .map(|a| AtomicU32::new(a.load(Ordering::Relaxed)))
        .collect();
    // per vertex: level-local index of the lowest-id tet containing its edge (the owner)
    let owner: Vec<AtomicU32> = (0..rec.len()).map(|_| AtomicU32::new(u32::MAX)).collect();
    let mut owned = vec![0u8; nodes];
    let mut empty_children = vec![0u8; nodes];
    let mut subtree_max_abs = vec![0f32; nodes];
    let mut coeffs = Vec::with_capacity(rec.len() - nv);
    let mut max_err = 0f64;

    // top-down, closed loop: level k tets create the level-(k+1) vertices
    let pb = bar(nodes as u64, "analysis", progress);
    for k in 0..levels {
        let start = forest.level_start(k);
        let chunks = parent_chunks(forest, k);
        // 1. owners: the lowest id wins
        chunks.par_iter().for_each(|range| {
            for_each_tet_keys(forest, &keys, k, range.clone(), |id, sk| {
                let li = (id - start) as u32;
                for e in 0..6 {
                    owner[sk[4 + e]].fetch_min(li, Ordering::Relaxed);
                }
            });
        });
        // 2. details, each vertex by its owner (distinct writers), reading only coarser vertices
        let leaf_parents = k + 1 == levels;
        let parts: Vec<ChunkOut> = chunks
            .par_iter()
            .map(|range| {
                let len = (range.end - range.start) as usize * if k == 0 { 1 } else { 8 };
                let mut masks = Vec::with_capacity(len);
                let mut own_max = Vec::with_capacity(len);
                let mut empties = Vec::with_capacity(if leaf_parents { len } else { 0 });
                let mut cs = Vec::new();
                let mut err = 0f64;
                for_each_tet_keys(forest, &keys, k, range.clone(), |id, sk| {
                    let li = (id - start) as u32;
                    let mut mask = 0u8;
                    let mut mx = 0f32;
                    for (e, &(a, b)) in EDGES.iter().enumerate() {
                        let m = sk[4 + e];
                        let (u, v) = (sk[a], sk[b]);
                        if !outside[m] {
                            // open-loop |d| of every edge (inside samples are never written: no race)
                            let f = load(&reference, m);
                            mx = mx
                                .max((f - predict(load(&reference, u), load(&reference, v))).abs());
                        }
                        if owner[m].load(Ordering::Relaxed) != li {
                            continue;
                        }
                        mask |= 1 << e;
                        if outside[m] {
                            store(
                                &reference,
                                m,
                                predict(load(&reference, u), load(&reference, v)),
                            );
                        }
                        let f = load(&reference, m);
                        let p = predict(load(&rec, u), load(&rec, v));
                        let d = match &quantizer {
                            None => analyze(f, p),
                            Some(q) => q.decode(q.encode(f - p)),
                        };
                        let x = synthesize(d, p);
                        store(&rec, m, x);
                        err = err.max((x as f64 - f as f64).abs());
                        cs.push(d);
                    }
                    masks.push(mask);
                    own_max.push(mx);
                    if leaf_parents {
                        let mut empty = 0u8;
                        for (i, child) in BEY_CHILDREN.iter().enumerate() {
                            if child.iter().all(|&p| outside[sk[p]]) {
                                empty |= 1 << i;
                            }
                        }
                        empties.push(empty);
                    }
                });
                cs.shrink_to_fit();
                (masks, cs, err, own_max, empties)
            })
            .collect();
        let mut at = start as usize;
        for (masks, cs, err, own_max, empties) in parts {
            owned[at..at + masks.len()].copy_from_slice(&masks);
            subtree_max_abs[at..at + masks.len()].copy_from_slice(&own_max);
            if leaf_parents {
                empty_children[at..at + masks.len()].copy_from_slice(&empties);
            }
            at += masks.len();
            coeffs.extend_from_slice(&cs);
            max_err = max_err.max(err);
        }
        pb.set_position(forest.level_start(k + 1));
    }
    pb.finish_and_clear();
    drop(owner);
    let from_atomic = |v: Vec<AtomicU32>| -> Vec<f32> {
        v.into_iter()
            .map(|a| f32::from_bits(a.into_inner()))
            .collect()
    };
    let rec = from_atomic(rec);
    let reference = from_atomic(reference);

    // bottom-up: subtree max |detail| and empty children, by id arithmetic only
    for k in (0..levels.saturating_sub(1)).rev() {
        let (s, e) = (
            forest.level_start(k) as usize,
            forest.level_start(k + 1) as usize,
        );
        let (this_empty, below_empty) = empty_children.split_at_mut(e);
        let (this_max, below_max) = subtree_max_abs.split_at_mut(e);
        this_empty[s..e]
            .par_iter_mut()
            .zip(this_max[s..e].par_iter_mut())
            .enumerate()
            .for_each(|(j, (em, mx))| {
                let id = (s + j) as u64;
                let first = forest.child(id, 0) as usize - e;
                let mut empty = 0u8;
                for i in 0..8 {
                    *mx = mx.max(below_max[first + i]);
                    if below_empty[first + i] == 0xff {
                        empty |= 1 << i;
                    }
                }
                *em = empty;
            });
    }
    base.empty = (0..base.tets.len())
        .map(|b| {
            if levels == 0 {
                base.tets[b].iter().all(|&v| outside[v as usize])
            } else {
                empty_children[b] == 0xff
            }
        })
        .collect();
    base.values = rec[..nv].to_vec();
    let error_bound = match &quantizer {
        Some(q) => {
            q.step as f64 / 2.0 * (1.0 + 1e-6)
                + 4.0 * f32::EPSILON as f64 * (lo.abs().max(hi.abs()) as f64 + q.step as f64)
        }
        None => 1e-6 * range.max(f32::MIN_POSITIVE as f64),
    };
    Ok(Analysis {
        base,
        owned,
        empty_children,
        subtree_max_abs,
        coeffs,
        quantizer,
        reference,
        value_range: (lo, hi),
        max_abs_error: max_err,
        error_bound,
    })
}
