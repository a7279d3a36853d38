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

use crate::resample::{Resampled, MAX_NODES};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, AtomicUsize, Ordering};
use std::sync::Mutex;
use tetwave_protocol::hierarchy::Bary;
use tetwave_protocol::hierarchy::{midpoint, LevelWalker, BEY_CHILDREN, BEY_SPLIT, EDGES};
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
    /// What the store writes.
    pub fn content(&self) -> tetwave_store::StoreContent<'_> {
        tetwave_store::StoreContent {
            base: &self.base,
            owned: &self.owned,
            empty_children: &self.empty_children,
            subtree_max_abs: &self.subtree_max_abs,
            coeffs: &self.coeffs,
            quantizer: self.quantizer,
            reference: &self.reference,
            value_range: self.value_range,
            max_abs_error: self.max_abs_error,
            error_bound: self.error_bound,
        }
    }

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

/// Level-`k−1` parents per parallel task (their 8 children each are the level-`k` tets it visits).
const PARENTS_PER_TASK: usize = 64;
/// Base tets per parallel task at level 0.
const BASE_PER_TASK: usize = 4096;
/// Below this many items a pass runs on the calling thread (waking the pool costs more).
const SEQUENTIAL_BELOW: usize = 1 << 13;
/// From this many vertices the per-vertex setup passes run in parallel (below, waking the pool
/// costs more than it saves).
const PARALLEL_PASS_FROM: usize = 1 << 19;
/// From this many vertices the owned masks and coefficients are gathered in parallel.
const SCATTER_PARALLEL_FROM: usize = 1 << 16;
/// Levels of at least this many tets are walked in parallel.
const PARALLEL_WALK_FROM: usize = 1 << 11;

/// One walk task's node outputs: its parents' subtree max and empty masks, then its children's.
type LevelTask<'a> = ((&'a mut [f32], &'a mut [u8]), (&'a mut [f32], &'a mut [u8]));

/// Calls `f(id, keys, mids)` for every tet of level `k` in `ids`, in increasing id order, with `keys`
/// the keys of its 10 split points (4 vertices, 6 edge midpoints) and `mids` the keys of the midpoints
/// of the 25 edges of its split ([`BEY_SPLIT`]): the new vertices of its children's edges.
fn for_each_split_keys(
    forest: Forest,
    keys: &VertexKeys,
    k: u8,
    ids: std::ops::Range<u64>,
    mut f: impl FnMut(u64, &[usize; 10], &[usize; 25]),
) {
    let split = &BEY_SPLIT;
    let mids = |tet: &LatticeTet, pp: &[Bary; 10]| -> [usize; 25] {
        let mut m = [0usize; 25];
        for (j, &(a, b)) in split.edges.iter().enumerate() {
            m[j] = keys.key(tet.base, &midpoint(&pp[a], &pp[b])) as usize;
        }
        m
    };
    let split_keys = |tet: &LatticeTet, pp: &[Bary; 10]| -> [usize; 10] {
        let mut k = [0usize; 10];
        for (i, p) in pp.iter().enumerate() {
            k[i] = keys.key(tet.base, p) as usize;
        }
        k
    };
    if k == 0 {
        for (id, tet) in LevelWalker::new(forest, k, ids) {
            let pp = tet.split_points();
            f(id, &split_keys(&tet, &pp), &mids(&tet, &pp));
        }
        return;
    }
    if ids.is_empty() {
        return;
    }
    // walk the parents: a tet's split keys are its parent's split keys and split-edge midpoints
    let (Some(first), Some(last)) = (forest.parent(ids.start), forest.parent(ids.end - 1)) else {
        return;
    };
    for (gid, g) in LevelWalker::new(forest, k - 1, first..last + 1) {
        let gp = g.split_points();
        let gk = split_keys(&g, &gp);
        let gm = mids(&g, &gp);
        for (i, c) in BEY_CHILDREN.iter().enumerate() {
            let id = forest.child(gid, i);
            if !ids.contains(&id) {
                continue;
            }
            let tet = LatticeTet {
                base: g.base,
                v: [gp[c[0]], gp[c[1]], gp[c[2]], gp[c[3]]],
            };
            let ce = &split.child_edges[i];
            let pk = [
                gk[c[0]], gk[c[1]], gk[c[2]], gk[c[3]], gm[ce[0]], gm[ce[1]], gm[ce[2]], gm[ce[3]],
                gm[ce[4]], gm[ce[5]],
            ];
            f(id, &pk, &mids(&tet, &tet.split_points()));
        }
    }
}

/// Calls `f(id, keys)` for every tet of level `k` whose parent lies in `parents` (level `k − 1`;
/// for `k = 0`, `parents` are base tet ids and the base tets themselves are visited), in increasing id
/// order, with `keys` the keys of its 4 vertices then its 6 edge midpoints. Children's vertex keys come
/// from the parent's split, and the 25 midpoints of the split's edges are keyed once per parent.
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
    let split = &BEY_SPLIT;
    for_each_split_keys(forest, keys, k - 1, parents, |pid, pk, mid| {
        let first = forest.child(pid, 0);
        for (i, c) in BEY_CHILDREN.iter().enumerate() {
            let ce = &split.child_edges[i];
            let ck = [
                pk[c[0]], pk[c[1]], pk[c[2]], pk[c[3]], mid[ce[0]], mid[ce[1]], mid[ce[2]],
                mid[ce[3]], mid[ce[4]], mid[ce[5]],
            ];
            f(first + i as u64, &ck);
        }
    });
}

/// Parent-id chunks whose children make up level `k` (base tet ids for `k = 0`).
fn parent_chunks(forest: Forest, k: u8) -> Vec<std::ops::Range<u64>> {
    let (lo, hi, step) = if k == 0 {
        (0, forest.n_base, BASE_PER_TASK as u64)
    } else {
        (
            forest.level_start(k - 1),
            forest.level_start(k),
            PARENTS_PER_TASK as u64,
        )
    };
    (lo..hi)
        .step_by(step as usize)
        .map(|s| s..(s + step).min(hi))
        .collect()
}

/// Max |open-loop detail| over all new vertices (sizes the quantizer).
fn max_open_detail(forest: Forest, r: &Resampled) -> f64 {
    (0..forest.levels)
        .map(|k| {
            parent_chunks(forest, k)
                .into_par_iter()
                .map(|range| {
                    let mut m = 0f64;
                    for_each_tet_keys(forest, &r.keys, k, range, |_, sk| {
                        for (e, &(a, b)) in EDGES.iter().enumerate() {
                            let f = |i: usize| r.samples[sk[i]] as f64;
                            let d = f(4 + e) - 0.5 * (f(a) + f(b));
                            if d.is_finite() {
                                m = m.max(d.abs());
                            }
                        }
                    });
                    m
                })
                .reduce(|| 0.0, f64::max)
        })
        .fold(0.0, f64::max)
}

/// Per vertex, in one cache line: the reconstruction and `8 × (lowest id of a tet containing its
/// edge) + local edge` ([`UNOWNED`] before the first visit).
struct Cell {
    rec: AtomicU32,
    owner: AtomicU32,
}

#[inline]
fn load(a: &AtomicU32) -> f32 {
    f32::from_bits(a.load(Ordering::Relaxed))
}

#[inline]
fn store(a: &AtomicU32, x: f32) {
    a.store(x.to_bits(), Ordering::Relaxed)
}

/// No visitor yet (in [`Cell::owner`]).
const UNOWNED: u32 = u32::MAX;

// Owner codes are 8 × node id + edge in a u32 below `UNOWNED`: every hierarchy within
// `MAX_NODES` (the limit resample owns and checks first) must fit.
const _: () = assert!(MAX_NODES <= (UNOWNED >> 3) as u64);

/// The per-vertex state the level walks share.
struct Walk<'a> {
    /// Sampled values (the samples' own memory); outside vertices are filled by prediction when
    /// first reached.
    reference: &'a [AtomicU32],
    cells: &'a [Cell],
    /// Per new vertex: its detail.
    detail: &'a [AtomicU32],
    /// Bitset of the vertices outside the input's domain; `None` when there are none.
    outside: Option<&'a [u64]>,
    quantizer: Option<Quantizer>,
}

impl Walk<'_> {
    #[inline]
    fn is_outside(&self, v: usize) -> bool {
        match self.outside {
            None => false,
            Some(b) => (b[v >> 6] >> (v & 63)) & 1 != 0,
        }
    }

    /// Visits tet `id` (level `k`) with split-point keys `sk`: claims its edges' midpoints for the lowest
    /// id, computes the detail of each midpoint it is the first to reach (the detail depends only on the
    /// edge, not on which tet reaches it, and reads only coarser vertices), and returns the max
    /// |open-loop detail| over its 6 edges and, for `leaf_parent`, its empty-children mask.
    #[inline]
    fn visit(&self, id: u64, sk: &[usize; 10], leaf_parent: bool, err: &mut f64) -> (f32, u8) {
        let code0 = (id as u32) << 3;
        let mut mx = 0f32;
        let r = |i: usize| load(&self.reference[sk[i]]);
        for (e, &(a, b)) in EDGES.iter().enumerate() {
            let m = sk[4 + e];
            let out = self.is_outside(m);
            if !out {
                // open-loop |d| of every edge (inside samples are never written: no race)
                mx = mx.max((r(4 + e) - predict(r(a), r(b))).abs());
            }
            self.claim(m, code0 | e as u32, out, sk[a], sk[b], err);
        }
        let mut empty = 0u8;
        if leaf_parent && self.outside.is_some() {
            for (i, child) in BEY_CHILDREN.iter().enumerate() {
                if child.iter().all(|&p| self.is_outside(sk[p])) {
                    empty |= 1 << i;
                }
            }
        }
        (mx, empty)
    }

    /// Visits the 8 children of the level-`k−1` tet whose first child is `c0`, given its split keys `pk`
    /// and the keys `mid` of its 25 split edges' midpoints: like [`Self::visit`] on every child, but
    /// each of the 25 distinct edges is handled once, claimed for the first child that has it.
    /// Writes the children's own max |open-loop detail| and, for `leaf_parent`, empty masks.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    fn visit_parent(
        &self,
        c0: u64,
        pk: &[usize; 10],
        mid: &[usize; 25],
        leaf_parent: bool,
        err: &mut f64,
        child_max: &mut [f32],
        child_empty: &mut [u8],
    ) {
        let split = &BEY_SPLIT;
        let mut od = [0f32; 25];
        let code0 = (c0 as u32) << 3;
        // gather first: independent loads overlap their cache misses
        let (mut fm, mut owner, mut fp) = ([0f32; 25], [0u32; 25], [0f32; 10]);
        for j in 0..25 {
            fm[j] = load(&self.reference[mid[j]]);
            owner[j] = self.cells[mid[j]].owner.load(Ordering::Relaxed);
        }
        for p in 0..10 {
            fp[p] = load(&self.reference[pk[p]]);
        }
        for (j, &(a, b)) in split.edges.iter().enumerate() {
            let m = mid[j];
            let out = self.is_outside(m);
            if !out {
                // open-loop |d| (inside samples are never written: no race)
                od[j] = (fm[j] - predict(fp[a], fp[b])).abs();
            }
            let (i, e) = split.first_child[j];
            let code = code0 + ((i as u32) << 3) + e as u32;
            if code < owner[j] {
                self.claim(m, code, out, pk[a], pk[b], err);
            }
        }
        for (i, ce) in split.child_edges.iter().enumerate() {
            let mut mx = 0f32;
            for &j in ce {
                mx = mx.max(od[j]);
            }
            child_max[i] = mx;
        }
        if leaf_parent && self.outside.is_some() {
            let split_out: [bool; 10] = std::array::from_fn(|p| self.is_outside(pk[p]));
            for (i, child) in BEY_CHILDREN.iter().enumerate() {
                let mut empty = 0u8;
                let ce = &split.child_edges[i];
                let ck = [
                    child[0], child[1], child[2], child[3], ce[0], ce[1], ce[2], ce[3], ce[4],
                    ce[5],
                ];
                for (ci, grandchild) in BEY_CHILDREN.iter().enumerate() {
                    if grandchild.iter().all(|&p| {
                        if p < 4 {
                            split_out[ck[p]]
                        } else {
                            self.is_outside(mid[ck[p]])
                        }
                    }) {
                        empty |= 1 << ci;
                    }
                }
                child_empty[i] = empty;
            }
        }
    }

    /// Lowers the owner of new vertex `m` (midpoint of `u`–`v`) to `code`; the first visitor computes
    /// its detail and reconstruction (and fills its reference value when it is outside).
    #[inline]
    fn claim(&self, m: usize, code: u32, out: bool, u: usize, v: usize, err: &mut f64) {
        let cell = &self.cells[m];
        // within a task ids increase: mostly only a task's first reach of a vertex takes the atomic
        if code >= cell.owner.load(Ordering::Relaxed)
            || cell.owner.fetch_min(code, Ordering::Relaxed) != UNOWNED
        {
            return;
        }
        if out {
            let p = predict(load(&self.reference[u]), load(&self.reference[v]));
            store(&self.reference[m], p);
        }
        let f = load(&self.reference[m]);
        let p = predict(load(&self.cells[u].rec), load(&self.cells[v].rec));
        let d = match &self.quantizer {
            None => {
                // `analyze`'s common case, inline
                let d = f - p;
                if synthesize(d, p) == f {
                    d
                } else {
                    analyze(f, p)
                }
            }
            Some(q) => q.decode(q.encode(f - p)),
        };
        let x = synthesize(d, p);
        store(&cell.rec, x);
        store(&self.detail[m], d);
        *err = err.max((x as f64 - f as f64).abs());
    }
}

/// Runs `f` on every item on all pool threads, which claim items from a shared counter; returns the
/// results in item order. [`rayon::broadcast`] wakes every worker explicitly: an indexed parallel
/// iterator relies on lazy wake-ups which, right after another parallel pass, often leave the second
/// worker asleep through a whole sub-millisecond level walk.
fn par_map<T: Send, R: Send>(items: Vec<T>, f: impl Fn(T) -> R + Sync) -> Vec<R> {
    let threads = rayon::current_num_threads();
    if items.len() <= 1 || threads == 1 {
        return items.into_iter().map(f).collect();
    }
    // threads claim slots in turn: order the items so that consecutive slots come from far apart
    // (thread-many contiguous runs, interleaved), keeping concurrent tasks off each other's cache lines
    let len = items.len();
    let run = len.div_ceil(threads);
    let mut items: Vec<Option<T>> = items.into_iter().map(Some).collect();
    let slots: Vec<Mutex<Option<(usize, T)>>> = (0..run)
        .flat_map(|r| (0..threads).map(move |t| t * run + r))
        .filter(|&i| i < len)
        .map(|i| Mutex::new(items[i].take().map(|t| (i, t))))
        .collect();
    let next = AtomicUsize::new(0);
    let done = rayon::broadcast(|_| {
        let mut out = Vec::new();
        while let Some(slot) = slots.get(next.fetch_add(1, Ordering::Relaxed)) {
            let item = slot.lock().unwrap_or_else(|e| e.into_inner()).take();
            if let Some((i, t)) = item {
                out.push((i, f(t)));
            }
        }
        out
    });
    let mut results: Vec<Option<R>> = (0..len).map(|_| None).collect();
    for (i, r) in done.into_iter().flatten() {
        results[i] = Some(r);
    }
    results
        .into_iter()
        .map(|r| r.expect("every item ran"))
        .collect()
}

/// [`par_map`], reduced by `max`.
fn par_max<T: Send>(items: Vec<T>, f: impl Fn(T) -> f64 + Sync) -> f64 {
    par_map(items, f).into_iter().fold(0.0, f64::max)
}

/// Folds 8 children's subtree max and empty flags into their parent's.
#[inline]
fn fold_children(own: &mut f32, empty: &mut u8, child_max: &[f32], child_empty: &[u8]) {
    let mut e = 0u8;
    for i in 0..8 {
        *own = own.max(child_max[i]);
        if child_empty[i] == 0xff {
            e |= 1 << i;
        }
    }
    *empty = e;
}

/// Runs the analysis. `bits`: uniform quantization of the details (8..=24), or lossless f32.
pub fn analyze_hierarchy(
    r: Resampled,
    bits: Option<u8>,
    progress: bool,
) -> Result<Analysis, AnalysisError> {
    if let Some(b) = bits {
        if !tetwave_protocol::store_format::QUANTIZED_BITS.contains(&b) {
            return Err(AnalysisError::BadBits(b));
        }
    }
    let forest = r.base.forest();
    let levels = forest.levels;
    if levels > 0 && forest.nodes() > MAX_NODES {
        return Err(AnalysisError::TooLarge(forest.level_len(levels - 1)));
    }
    let nodes = forest.nodes() as usize;
    let nv = r.base.positions.len();
    let n = r.samples.len();
    let big = n >= PARALLEL_PASS_FROM;
    // range of the inside samples (`min`/`max` skip NaN) and the outside (NaN) count
    let block = 1 << 16; // a multiple of 64: blocks' bitsets concatenate
    let range_of = |xs: &[f32]| {
        // 8 independent lanes (vectorizable); a comparison with NaN is false, so NaN never wins
        const L: usize = 8;
        let (mut lo, mut hi, mut nan) = ([f32::INFINITY; L], [f32::NEG_INFINITY; L], [0u32; L]);
        let mut chunks = xs.chunks_exact(L);
        for c in &mut chunks {
            for l in 0..L {
                let x = c[l];
                lo[l] = if x < lo[l] { x } else { lo[l] };
                hi[l] = if x > hi[l] { x } else { hi[l] };
                nan[l] += x.is_nan() as u32;
            }
        }
        let tail = chunks.remainder().iter().fold(
            (f32::INFINITY, f32::NEG_INFINITY, 0usize),
            |(lo, hi, c), &x| (lo.min(x), hi.max(x), c + x.is_nan() as usize),
        );
        (0..L).fold(tail, |(a, b, c), l| {
            (a.min(lo[l]), b.max(hi[l]), c + nan[l] as usize)
        })
    };
    let merge =
        |a: (f32, f32, usize), b: (f32, f32, usize)| (a.0.min(b.0), a.1.max(b.1), a.2 + b.2);
    let (lo, hi, n_outside) = if big {
        r.samples
            .par_chunks(block)
            .map(range_of)
            .reduce(|| (f32::INFINITY, f32::NEG_INFINITY, 0), merge)
    } else {
        range_of(&r.samples)
    };
    let any_outside = n_outside > 0;
    let outside_bits: Vec<u64> = if any_outside {
        let bits_of = |xs: &[f32]| {
            let mut bits = vec![0u64; xs.len().div_ceil(64)];
            for (j, x) in xs.iter().enumerate() {
                bits[j >> 6] |= (x.is_nan() as u64) << (j & 63);
            }
            bits
        };
        if big {
            r.samples.par_chunks(block).flat_map_iter(bits_of).collect()
        } else {
            bits_of(&r.samples)
        }
    } else {
        Vec::new()
    };
    let outside = |v: usize| any_outside && (outside_bits[v >> 6] >> (v & 63)) & 1 != 0;
    let range = (hi - lo) as f64;
    let quantizer = bits.map(|b| {
        let m = max_open_detail(forest, &r);
        // closed-loop details are at most m + q/2: the codes ±(2^(b−1)−1) cover them with q = m/(max−1)
        let step = if m > 0.0 {
            ((m / (Quantizer::max_code(b) - 1) as f64) as f32).max(f32::MIN_POSITIVE)
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
    let inside_mean = if (0..nv).any(outside) {
        let (s, c) = samples
            .iter()
            .filter(|x| !x.is_nan())
            .fold((0f64, 0u64), |(s, c), &x| (s + x as f64, c + 1));
        (s / c.max(1) as f64) as f32
    } else {
        0.0
    };
    // in place (same layout): the samples' memory holds the reference values
    let reference: Vec<AtomicU32> = samples
        .into_iter()
        .map(|x| AtomicU32::new(x.to_bits()))
        .collect();
    for v in (0..nv).filter(|&v| outside(v)) {
        store(&reference[v], inside_mean);
    }
    let cell = |r: &AtomicU32| Cell {
        rec: AtomicU32::new(r.load(Ordering::Relaxed)),
        owner: AtomicU32::new(UNOWNED),
    };
    let zero = |_| AtomicU32::new(0);
    let (cells, detail): (Vec<Cell>, Vec<AtomicU32>) = if big {
        (
            reference.par_iter().map(cell).collect(),
            (0..n).into_par_iter().map(zero).collect(),
        )
    } else {
        (
            reference.iter().map(cell).collect(),
            (0..n).map(zero).collect(),
        )
    };
    let mut empty_children = vec![0u8; nodes];
    let mut subtree_max_abs = vec![0f32; nodes];
    let walk = Walk {
        reference: &reference,
        cells: &cells,
        detail: &detail,
        outside: any_outside.then_some(&outside_bits[..]),
        quantizer,
    };
    let mut max_err = 0f64;

    // top-down, closed loop: level k tets create the level-(k+1) vertices, one walk per level that
    // claims owners, computes details and records each tet's own max |d| (and, on the last level, folds
    // the children into their parents)
    let pb = bar(nodes as u64, "analysis", progress);
    for k in 0..levels {
        let leaf_parent = k + 1 == levels;
        let start = forest.level_start(k) as usize;
        let end = forest.level_start(k + 1) as usize;
        let err = if k == 0 {
            let task = |(ti, (mx, em)): (usize, (&mut [f32], &mut [u8]))| {
                let p0 = (ti * BASE_PER_TASK) as u64;
                let mut err = 0f64;
                for_each_tet_keys(forest, &keys, 0, p0..p0 + mx.len() as u64, |id, sk| {
                    let j = (id - p0) as usize;
                    (mx[j], em[j]) = walk.visit(id, sk, leaf_parent, &mut err);
                });
                err
            };
            let (mx, em) = (&mut subtree_max_abs[..end], &mut empty_children[..end]);
            let tasks = mx
                .chunks_mut(BASE_PER_TASK)
                .zip(em.chunks_mut(BASE_PER_TASK))
                .enumerate()
                .collect();
            par_max(tasks, task)
        } else {
            let pstart = forest.level_start(k - 1) as usize;
            let (pmax, cmax) = subtree_max_abs[pstart..end].split_at_mut(start - pstart);
            let (pem, cem) = empty_children[pstart..end].split_at_mut(start - pstart);
            let task = |(ti, ((pm, pe), (cm, ce))): (usize, LevelTask)| {
                let p0 = (pstart + ti * PARENTS_PER_TASK) as u64;
                let c0 = forest.child(p0, 0);
                let mut err = 0f64;
                for_each_split_keys(
                    forest,
                    &keys,
                    k - 1,
                    p0..p0 + pm.len() as u64,
                    |pid, pk, mid| {
                        let c = forest.child(pid, 0);
                        let j = (c - c0) as usize;
                        walk.visit_parent(
                            c,
                            pk,
                            mid,
                            leaf_parent,
                            &mut err,
                            &mut cm[j..j + 8],
                            &mut ce[j..j + 8],
                        );
                    },
                );
                if leaf_parent {
                    for i in 0..pm.len() {
                        let c = 8 * i..8 * i + 8;
                        fold_children(&mut pm[i], &mut pe[i], &cm[c.clone()], &ce[c]);
                    }
                }
                err
            };
            let tasks: Vec<_> = pmax
                .chunks_mut(PARENTS_PER_TASK)
                .zip(pem.chunks_mut(PARENTS_PER_TASK))
                .zip(
                    cmax.chunks_mut(8 * PARENTS_PER_TASK)
                        .zip(cem.chunks_mut(8 * PARENTS_PER_TASK)),
                )
                .enumerate()
                .collect();
            if end - start >= PARALLEL_WALK_FROM {
                par_max(tasks, task)
            } else {
                tasks.into_iter().map(task).fold(0.0, f64::max)
            }
        };
        max_err = max_err.max(err);
        pb.set_position(forest.level_start(k + 1));
    }
    pb.finish_and_clear();

    // owned masks and coefficients (node order, then edge order) from the per-vertex owners: each
    // part of the node range scans all owners and writes only its own masks and coefficients (no
    // atomics); the masks are padded to whole 8-node words for the rank computation
    let parts = if n >= SCATTER_PARALLEL_FROM {
        rayon::current_num_threads().clamp(1, 4)
    } else {
        1
    };
    let padded = nodes.next_multiple_of(8);
    let part_len = padded.div_ceil(parts).next_multiple_of(8).max(8);
    let mut owned = vec![0u8; padded];
    let owners = &cells[nv..];
    par_map(
        owned.chunks_mut(part_len).enumerate().collect(),
        |(p, masks): (usize, &mut [u8])| {
            let lo = (p * part_len) as u32;
            for c in owners {
                let c = c.owner.load(Ordering::Relaxed);
                debug_assert_ne!(c, UNOWNED);
                let i = (c >> 3).wrapping_sub(lo) as usize;
                if i < masks.len() {
                    masks[i] |= 1 << (c & 7);
                }
            }
        },
    );
    // coefficients before each word of 8 nodes; within a word, the popcount of the bits below
    let words: Vec<u64> = owned
        .chunks_exact(8)
        .map(|w| u64::from_le_bytes(w.try_into().unwrap()))
        .collect();
    let mut word_offsets = Vec::with_capacity(words.len() + 1);
    let mut total = 0u32;
    for w in &words {
        word_offsets.push(total);
        total += w.count_ones();
    }
    word_offsets.push(total);
    owned.truncate(nodes);
    debug_assert_eq!(total as usize, n - nv);
    let mut coeffs = vec![0f32; total as usize];
    {
        // split the coefficients at the parts' node boundaries
        let mut rest: &mut [f32] = &mut coeffs;
        let mut tasks = Vec::with_capacity(parts);
        for p in 0..padded.div_ceil(part_len) {
            let (w0, w1) = (p * part_len / 8, ((p + 1) * part_len / 8).min(words.len()));
            let (head, tail) = rest.split_at_mut((word_offsets[w1] - word_offsets[w0]) as usize);
            tasks.push((w0, w1, head));
            rest = tail;
        }
        let (detail, words, word_offsets) = (&detail, &words, &word_offsets);
        par_map(tasks, |(w0, w1, out): (usize, usize, &mut [f32])| {
            let base = word_offsets[w0];
            for (m, c) in owners.iter().enumerate() {
                let code = c.owner.load(Ordering::Relaxed);
                // bit position of (node, edge) in its word = 8 × (node mod 8) + edge = code mod 64
                let w = (code >> 6) as usize;
                if w < w0 || w >= w1 {
                    continue;
                }
                let at =
                    word_offsets[w] - base + (words[w] & ((1u64 << (code & 63)) - 1)).count_ones();
                out[at as usize] = load(&detail[nv + m]);
            }
        });
    }
    drop((detail, words, word_offsets));

    // bottom-up: subtree max |detail| and empty children, by id arithmetic only (the last node level
    // was folded into its parents by the last walk)
    for k in (0..levels.saturating_sub(2)).rev() {
        let (s, e) = (
            forest.level_start(k) as usize,
            forest.level_start(k + 1) as usize,
        );
        let (this_empty, below_empty) = empty_children.split_at_mut(e);
        let (this_max, below_max) = subtree_max_abs.split_at_mut(e);
        let fold = |(j, (em, mx)): (usize, (&mut u8, &mut f32))| {
            let first = forest.child((s + j) as u64, 0) as usize - e;
            let c = first..first + 8;
            fold_children(mx, em, &below_max[c.clone()], &below_empty[c]);
        };
        if e - s >= SEQUENTIAL_BELOW {
            this_empty[s..e]
                .par_iter_mut()
                .zip(this_max[s..e].par_iter_mut())
                .enumerate()
                .for_each(fold);
        } else {
            this_empty[s..e]
                .iter_mut()
                .zip(this_max[s..e].iter_mut())
                .enumerate()
                .for_each(fold);
        }
    }
    base.empty = (0..base.tets.len())
        .map(|b| {
            if levels == 0 {
                base.tets[b].iter().all(|&v| outside(v as usize))
            } else {
                empty_children[b] == 0xff
            }
        })
        .collect();
    base.values = cells[..nv].iter().map(|c| load(&c.rec)).collect();
    drop(cells);
    // in place again
    let reference: Vec<f32> = reference
        .into_iter()
        .map(|a| f32::from_bits(a.into_inner()))
        .collect();
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
