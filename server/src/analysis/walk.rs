//! The top-down level walks: every level-`k` tet claims the midpoints of its edges for the lowest
//! id, computes their details against the values synthesis will reconstruct, and records its own
//! max |d| (and, on the last level, folds its children into it).

use super::keys::{for_each_split_keys, for_each_tet_keys};
use super::par::par_max;
use super::{bar, BASE_PER_TASK, PARALLEL_WALK_FROM, PARENTS_PER_TASK};
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use tetwave_protocol::hierarchy::{BEY_CHILDREN, BEY_SPLIT, EDGES};
use tetwave_protocol::vertex::VertexKeys;
use tetwave_protocol::wavelet::{analyze, predict, predict_split, synthesize, Quantizer};
use tetwave_protocol::Forest;

/// One walk task's node outputs: its parents' subtree max and empty masks, then its children's.
type LevelTask<'a> = ((&'a mut [f32], &'a mut [u8]), (&'a mut [f32], &'a mut [u8]));

/// A vertex's owner code, `8 × (lowest id of a tet containing its edge) + local edge`, in an
/// atomic of the width the hierarchy needs: `u32` while every code fits below its [`Self::UNOWNED`]
/// (2^29 nodes), `u64` past that (8 more bytes a vertex, so only where needed).
pub(super) trait Owner: Send + Sync {
    /// A code as a plain number.
    type Code: Copy + Ord + Send + Sync + std::fmt::Debug;
    /// No visitor yet.
    const UNOWNED: Self::Code;
    /// The most nodes whose codes fit.
    const MAX_NODES: u64;
    fn new(code: Self::Code) -> Self;
    fn load(&self) -> Self::Code;
    /// Lowers the code to `code`; returns the one before.
    fn fetch_min(&self, code: Self::Code) -> Self::Code;
    /// The code of `8 × id + edge`.
    fn code(id: u64, edge: u64) -> Self::Code;
    /// `8 × id + edge` of a code.
    fn wide(code: Self::Code) -> u64;
}

impl Owner for AtomicU32 {
    type Code = u32;
    const UNOWNED: u32 = u32::MAX;
    const MAX_NODES: u64 = (u32::MAX >> 3) as u64;
    fn new(code: u32) -> Self {
        AtomicU32::new(code)
    }
    #[inline]
    fn load(&self) -> u32 {
        AtomicU32::load(self, Ordering::Relaxed)
    }
    #[inline]
    fn fetch_min(&self, code: u32) -> u32 {
        AtomicU32::fetch_min(self, code, Ordering::Relaxed)
    }
    #[inline]
    fn code(id: u64, edge: u64) -> u32 {
        debug_assert!(id < Self::MAX_NODES);
        (8 * id + edge) as u32
    }
    #[inline]
    fn wide(code: u32) -> u64 {
        code as u64
    }
}

impl Owner for AtomicU64 {
    type Code = u64;
    const UNOWNED: u64 = u64::MAX;
    const MAX_NODES: u64 = u64::MAX >> 3;
    fn new(code: u64) -> Self {
        AtomicU64::new(code)
    }
    #[inline]
    fn load(&self) -> u64 {
        AtomicU64::load(self, Ordering::Relaxed)
    }
    #[inline]
    fn fetch_min(&self, code: u64) -> u64 {
        AtomicU64::fetch_min(self, code, Ordering::Relaxed)
    }
    #[inline]
    fn code(id: u64, edge: u64) -> u64 {
        8 * id + edge
    }
    #[inline]
    fn wide(code: u64) -> u64 {
        code
    }
}

/// Per vertex, in one cache line: the reconstruction and its owner code ([`Owner::UNOWNED`]
/// before the first visit).
pub(super) struct Cell<O> {
    pub(super) rec: AtomicU32,
    pub(super) owner: O,
}

#[inline]
pub(super) fn load(a: &AtomicU32) -> f32 {
    f32::from_bits(a.load(Ordering::Relaxed))
}

#[inline]
pub(super) fn store(a: &AtomicU32, x: f32) {
    a.store(x.to_bits(), Ordering::Relaxed)
}

/// The per-vertex state the level walks share.
pub(super) struct Walk<'a, O> {
    /// Sampled values (the samples' own memory); outside vertices are filled by prediction when
    /// first reached.
    pub(super) reference: &'a [AtomicU32],
    pub(super) cells: &'a [Cell<O>],
    /// Per new vertex: its detail.
    pub(super) detail: &'a [AtomicU32],
    /// Bitset of the vertices outside the input's domain; `None` when there are none.
    pub(super) outside: Option<&'a [u64]>,
    pub(super) quantizer: Option<Quantizer>,
    /// Whether the walk computes the parent predictor's details; with the axes predictor it
    /// only settles ownership, bounds and empty children, and `axes` computes the details.
    pub(super) details: bool,
}

impl<O: Owner> Walk<'_, O> {
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
        let mut mx = 0f32;
        let r = |i: usize| load(&self.reference[sk[i]]);
        for (e, &(a, b)) in EDGES.iter().enumerate() {
            let m = sk[4 + e];
            let out = self.is_outside(m);
            if !out {
                // open-loop |d| of every edge (inside samples are never written: no race)
                mx = mx.max((r(4 + e) - predict(r(a), r(b))).abs());
            }
            self.claim(m, O::code(id, e as u64), out, err, || {
                predict(load(&self.cells[sk[a]].rec), load(&self.cells[sk[b]].rec))
            });
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
        // gather first: independent loads overlap their cache misses
        let (mut fm, mut owner, mut fp) = ([0f32; 25], [O::UNOWNED; 25], [0f32; 10]);
        for j in 0..25 {
            fm[j] = load(&self.reference[mid[j]]);
            owner[j] = self.cells[mid[j]].owner.load();
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
            let code = O::code(c0 + i as u64, e as u64);
            if code < owner[j] {
                self.claim(m, code, out, err, || {
                    let rec: [f32; 10] = std::array::from_fn(|p| load(&self.cells[pk[p]].rec));
                    predict_split(&rec, a, b)
                });
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

    /// Lowers the owner of new vertex `m` to `code`; the first visitor computes its detail against
    /// `prediction` (of the coarser reconstructions, [`tetwave_protocol::wavelet`]) and its
    /// reconstruction. An outside vertex takes the prediction as its value: its detail is 0, and
    /// the field is extended smoothly (quadratically) past the domain.
    #[inline]
    fn claim(
        &self,
        m: usize,
        code: O::Code,
        out: bool,
        err: &mut f64,
        prediction: impl FnOnce() -> f32,
    ) {
        let cell = &self.cells[m];
        // within a task ids increase: mostly only a task's first reach of a vertex takes the atomic
        if code >= cell.owner.load() || cell.owner.fetch_min(code) != O::UNOWNED || !self.details {
            return;
        }
        let p = prediction();
        if out {
            store(&self.reference[m], p);
        }
        let f = load(&self.reference[m]);
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

impl<O: Owner> Walk<'_, O> {
    /// Walks every level top-down (closed loop: each level reads only coarser reconstructions),
    /// filling each node's own max |d| and, for the last node level, its subtree max and empty
    /// children; returns the max |synthesis − sample| over the new vertices.
    pub(super) fn levels(
        &self,
        forest: Forest,
        keys: &VertexKeys,
        subtree_max_abs: &mut [f32],
        empty_children: &mut [u8],
        progress: bool,
    ) -> f64 {
        let levels = forest.levels;
        // top-down, closed loop: level k tets create the level-(k+1) vertices, one walk per level that
        // claims owners, computes details and records each tet's own max |d| (and, on the last level, folds
        // the children into their parents)
        let pb = bar(forest.nodes(), "analysis", progress);
        let mut max_err = 0f64;
        for k in 0..levels {
            let leaf_parent = k + 1 == levels;
            let start = forest.level_start(k) as usize;
            let end = forest.level_start(k + 1) as usize;
            let err = if k == 0 {
                let task = |(ti, (mx, em)): (usize, (&mut [f32], &mut [u8]))| {
                    let p0 = (ti * BASE_PER_TASK) as u64;
                    let mut err = 0f64;
                    for_each_tet_keys(forest, keys, 0, p0..p0 + mx.len() as u64, |id, sk| {
                        let j = (id - p0) as usize;
                        (mx[j], em[j]) = self.visit(id, sk, leaf_parent, &mut err);
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
                        keys,
                        k - 1,
                        p0..p0 + pm.len() as u64,
                        |pid, pk, mid| {
                            let c = forest.child(pid, 0);
                            let j = (c - c0) as usize;
                            self.visit_parent(
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
        max_err
    }
}

/// Folds 8 children's subtree max and empty flags into their parent's.
#[inline]
pub(super) fn fold_children(own: &mut f32, empty: &mut u8, child_max: &[f32], child_empty: &[u8]) {
    let mut e = 0u8;
    for i in 0..8 {
        *own = own.max(child_max[i]);
        if child_empty[i] == 0xff {
            e |= 1 << i;
        }
    }
    *empty = e;
}
