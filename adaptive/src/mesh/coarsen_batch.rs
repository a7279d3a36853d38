//! Coarsening in batches: the candidates the closure would refine again are filtered out before
//! anything is unrefined, and refusal witnesses settle repeated attempts cheaply.

use super::green::{green_pattern_ok, FACE_MASK};
use super::node::NodeFlags;
use super::{AdaptiveMesh, MeshError, NONE};
use crate::detail_buffer::DetailBuffer;
use rustc_hash::FxHashMap;
use tetwave_protocol::hierarchy::{midpoint, Bary, EDGES};
use tetwave_protocol::{LatticeTet, TetId};

/// A candidate of [`AdaptiveMesh::coarsen_batch_at`].
struct BatchCand {
    slot: u32,
    id: TetId,
    mids: [u32; 6],
    keep: bool,
    /// What forced it when last refused (from the mesh's refusal records), if anything.
    wit: Option<Witness>,
    /// `wit` was found in this batch (not read from a record).
    fresh: bool,
    /// Its entry in the batch's [`BatchAux`] list once the closure's test needed one (`NONE`).
    aux: u32,
}

/// What the closure's test of one batch candidate looks up (kept apart: most candidates are
/// settled by a witness and never need it).
struct BatchAux {
    /// Its lattice tet; `None`: too fine to have level-k+2 points.
    lt: Option<LatticeTet>,
    /// Slots of the level-k+2 points on its boundary, looked up when first needed (`UNKNOWN`):
    /// the halves of edge `e` at `2e`, `2e + 1`; the segments of face `d` at `12 + 3d ..`.
    pts: [u32; 24],
}

/// Vertices whose presence forces a refined tet to be refined again if its split is undone (see
/// [`AdaptiveMesh::coarsen_batch_at`]): up to 4 (slot, key) pairs, unused ones `(NONE, 0)`. Any
/// present superset forces it too (the closure's test is monotone in the present vertices).
/// The keys are whole (a slot may be reused by another vertex; hierarchies of 2049³ points have
/// keys past 2^32): 48 bytes, slots and keys apart so that neither pads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Witness {
    slots: [u32; 4],
    keys: [u64; 4],
}

const _: () = assert!(std::mem::size_of::<Witness>() == 48);

/// Why the last merge attempt of a refined tet was refused, kept by its slot. Only
/// `AdaptiveMesh::unrefine` makes a refined tet a leaf or frees a slot, and it drops the record:
/// a record's slot holds the tet it was made for (the conformity check verifies it).
#[derive(Debug, Clone, Copy)]
pub(super) struct Refusal {
    wit: Witness,
}

const UNKNOWN: u32 = u32::MAX - 1;

impl AdaptiveMesh {
    /// Coarsens every tet of `ts` whose children are all leaves at that point (in the given order;
    /// others are skipped), without the per-tet refusal of [`Self::coarsen`], then restores the
    /// closure, which may refine some of them again. This is how a region refined uniformly is
    /// coarsened: no single tet of it can be coarsened alone, since its neighbours keep its edges
    /// split. Returns how many of `ts` are leaves afterwards.
    ///
    /// The tets the closure would refine again are filtered out first (without touching the mesh):
    /// every candidate's midpoints are released virtually (reference counts), then candidates that
    /// would be forced under that are dropped and their midpoints restored, until none is; only the
    /// rest are unrefined. The result is the same, without the wasted unrefine + refine pairs.
    ///
    /// A refused candidate is remembered with a *witness*: up to 4 vertices whose presence alone
    /// forces it (monotone test). When it comes back in a later batch while it stayed refined, a
    /// witness still present with the whole batch released settles it without the closure's test
    /// and without reading its children (repeatedly refused merges are the bulk of a
    /// view-dependent run's attempts); otherwise it is tested again. The records are bounded and
    /// only save work ([`Self::clear_refusal_records`]). Before any of that, a recorded candidate
    /// whose witness vertices each have a remembered owner (a refined tet splitting that vertex's
    /// edge) outside the batch is left out: forced whatever the batch releases, and leaving out a
    /// candidate that is forced anyway changes no other outcome. The selector reads
    /// those, with their owners, through `batch_held`.
    pub fn coarsen_batch(&mut self, ts: &[TetId], buf: &DetailBuffer) -> Result<usize, MeshError> {
        self.coarsen_batch_at(ts, &[], buf)
    }

    /// [`Self::coarsen_batch`] with `hints[i]`: the node slot `ts[i]` probably is in (checked).
    pub(crate) fn coarsen_batch_at(
        &mut self,
        ts: &[TetId],
        hints: &[u32],
        buf: &DetailBuffer,
    ) -> Result<usize, MeshError> {
        let mut slots: Vec<u32> = Vec::with_capacity(ts.len());
        let mut gathered: Vec<u32> = Vec::with_capacity(ts.len());
        // in the given order, each tet once (flagged while gathering)
        for (i, &t) in ts.iter().enumerate() {
            let slot = match hints.get(i) {
                Some(&h) if self.slot_holds(h as usize, t) => h,
                _ => self.find(t).unwrap_or(NONE),
            };
            slots.push(slot);
            if slot == NONE || self.nodes[slot as usize].flags.contains(NodeFlags::BATCHED) {
                continue;
            }
            self.nodes[slot as usize].flags.insert(NodeFlags::BATCHED);
            let n = &self.nodes[slot as usize];
            if !n.is_leaf() && self.children_leaves(n) {
                gathered.push(slot);
            }
        }
        // With every candidate flagged: a refused one whose witness vertices all have an owner
        // outside the batch stays forced whatever the batch releases, and leaving out a candidate
        // that is forced anyway changes nothing (forcing only grows with the vertices present).
        let mut cand: Vec<BatchCand> = Vec::with_capacity(gathered.len());
        self.held.clear();
        for &slot in &gathered {
            let n = &self.nodes[slot as usize];
            let rec = self.refused.get(&slot);
            if let Some(owners) = rec.and_then(|r| self.witness_held(&r.wit)) {
                self.held.push((slot, owners));
                continue;
            }
            cand.push(BatchCand {
                slot,
                id: n.id(),
                mids: self.child_mids(n),
                keep: true,
                wit: rec.map(|r| r.wit),
                fresh: false,
                aux: NONE,
            });
        }
        for &s in &slots {
            if s != NONE {
                self.nodes[s as usize].flags.remove(NodeFlags::BATCHED);
            }
        }
        for c in &cand {
            for &m in &c.mids {
                self.vref[m as usize] -= 1;
            }
        }
        // With every candidate released, those forced anyway are forced whatever else holds:
        // their witnesses are kept for the next batches, where a witness still present settles
        // the candidate without the closure's test.
        let mut aux: Vec<BatchAux> = Vec::new();
        let mut first: Vec<(usize, Option<Witness>)> = Vec::new();
        for (i, c) in cand.iter_mut().enumerate() {
            if let Some(w) = c.wit {
                if self.witness_present(&w) {
                    first.push((i, None));
                    continue;
                }
            }
            if let Some(w) = self.forced_witness(c, &mut aux) {
                first.push((i, Some(w)));
            }
        }
        for &(i, w) in &first {
            let c = &mut cand[i];
            c.keep = false;
            if w.is_some() {
                c.wit = w;
                c.fresh = true;
            }
            for &m in &c.mids {
                self.vref[m as usize] += 1;
            }
        }
        let mut dropped = !first.is_empty();
        while dropped {
            dropped = false;
            for c in cand.iter_mut() {
                if !c.keep {
                    continue;
                }
                if let Some(w) = self.forced_witness(c, &mut aux) {
                    c.keep = false;
                    c.wit = Some(w);
                    c.fresh = true;
                    for &m in &c.mids {
                        self.vref[m as usize] += 1;
                    }
                    dropped = true;
                }
            }
        }
        for c in &cand {
            if c.keep {
                for &m in &c.mids {
                    self.vref[m as usize] += 1;
                }
            } else if let (true, Some(wit)) = (c.fresh, c.wit) {
                // bounded: records of tets no longer candidates are dropped wholesale (and the
                // table shrunk when the mesh did)
                let bound = (self.n_leaves / 16).max(1024);
                if self.refused.len() >= bound {
                    if self.refused.capacity() > 2 * bound {
                        self.refused = FxHashMap::default();
                    } else {
                        self.refused.clear();
                    }
                }
                self.refused.insert(c.slot, Refusal { wit });
            }
        }
        for c in &cand {
            if c.keep {
                self.unrefine(c.slot);
            }
        }
        let closed = self.close(buf);
        // a tet of `ts` keeps its slot (coarsening frees children only, the closure refines)
        let held = ts
            .iter()
            .zip(&slots)
            .filter(|&(&t, &s)| {
                s != NONE && {
                    let n = &self.nodes[s as usize];
                    n.alive() && n.id() == t && n.is_leaf()
                }
            })
            .count();
        closed?;
        Ok(held)
    }

    /// Whether slot `s` holds a present vertex of key `k` (a witness entry's test).
    #[inline(always)]
    fn holds_vertex(&self, s: u32, k: u64) -> bool {
        self.vref[s as usize] > 0 && self.vkey[s as usize] == k
    }

    /// The witness made of the vertices in slots `ss` (at most 4), with their keys as they are.
    fn witness(&self, ss: &[u32]) -> Witness {
        let mut w = Witness {
            slots: [NONE; 4],
            keys: [0; 4],
        };
        for (i, &s) in ss.iter().enumerate() {
            w.slots[i] = s;
            w.keys[i] = self.vkey[s as usize];
        }
        w
    }

    /// Whether the vertices of witness `w` are all present (positive count, same key).
    #[inline]
    fn witness_present(&self, w: &Witness) -> bool {
        let present = |i: usize| w.slots[i] == NONE || self.holds_vertex(w.slots[i], w.keys[i]);
        present(0) && present(1) && present(2) && present(3)
    }

    /// When every vertex of witness `w` is present with an owner ([`Self::vowner`]) that is not a
    /// candidate of the batch being gathered (not flagged [`NodeFlags::BATCHED`]): those owners.
    #[inline]
    fn witness_held(&self, w: &Witness) -> Option<[u32; 4]> {
        let mut owners = [NONE; 4];
        for (o, (&s, &k)) in owners.iter_mut().zip(w.slots.iter().zip(&w.keys)) {
            if s == NONE {
                continue;
            }
            if !self.holds_vertex(s, k) {
                return None;
            }
            *o = *self.vowner[s as usize].iter().find(|&&o| {
                o != NONE && !self.nodes[o as usize].flags.contains(NodeFlags::BATCHED)
            })?;
        }
        Some(owners)
    }

    /// The candidates the last [`Self::coarsen_batch_at`] settled by their refusal witness, each
    /// with the refined tets outside the batch whose midpoints make the witness (slots, `NONE`
    /// padding). Such a candidate stays refused in any batch that leaves all of them out, until
    /// one of them changes.
    pub(crate) fn batch_held(&self) -> &[(u32, [u32; 4])] {
        &self.held
    }

    /// Whether batch candidate `c` would be forced with the reference counts as they stand (the
    /// candidates still kept released): [`Self::classify`] with a vertex present iff its count is
    /// positive, returning a witness when forced; the level-k+2 points' slots are looked up once
    /// and kept in `c`'s entry of `aux`.
    fn forced_witness(&self, c: &mut BatchCand, aux: &mut Vec<BatchAux>) -> Option<Witness> {
        let mut mask = 0u8;
        for (e, &m) in c.mids.iter().enumerate() {
            if self.vref[m as usize] > 0 {
                mask |= 1 << e;
            }
        }
        if !green_pattern_ok(mask) {
            // 3 edges off a face, or 4 edges: present midpoints that alone are a bad pattern
            let mut ss = [NONE; 4];
            let mut j = 0;
            for e in 0..6 {
                if mask & (1 << e) != 0 && j < 4 {
                    ss[j] = c.mids[e];
                    j += 1;
                }
            }
            let n = if mask.count_ones() == 3 { 3 } else { 4 };
            return Some(self.witness(&ss[..n]));
        }
        if mask == 0 {
            return None;
        }
        if c.aux == NONE {
            c.aux = aux.len() as u32;
            let fits = self.forest.level(c.id) + 2 <= self.forest.levels;
            aux.push(BatchAux {
                lt: fits.then(|| self.lattice_of(c.id)),
                pts: [UNKNOWN; 24],
            });
        }
        let a = &mut aux[c.aux as usize];
        let lt = a.lt?;
        let pt = |a: &mut BatchAux, i: usize, w: &dyn Fn() -> Bary| -> Option<u32> {
            if a.pts[i] == UNKNOWN {
                a.pts[i] = self.slot_at(lt.base, &w());
            }
            let s = a.pts[i];
            (s != NONE && self.vref[s as usize] > 0).then_some(s)
        };
        for (e, &(x, y)) in EDGES.iter().enumerate() {
            if mask & (1 << e) != 0 {
                let m = || lt.edge_midpoint(e);
                if let Some(s) = pt(a, 2 * e, &|| midpoint(&lt.v[x], &m()))
                    .or_else(|| pt(a, 2 * e + 1, &|| midpoint(&m(), &lt.v[y])))
                {
                    return Some(self.witness(&[c.mids[e], s]));
                }
            }
        }
        if mask.count_ones() >= 2 {
            for (d, &fm) in FACE_MASK.iter().enumerate() {
                let m = mask & fm;
                if m.count_ones() < 2 {
                    continue;
                }
                // the face's edges in increasing order; pair (0,1), (0,2), (1,2)
                let e0 = fm.trailing_zeros() as usize;
                let r = fm & (fm - 1);
                let e1 = r.trailing_zeros() as usize;
                let e2 = (r & (r - 1)).trailing_zeros() as usize;
                for (p, (x, y)) in [(e0, e1), (e0, e2), (e1, e2)].into_iter().enumerate() {
                    if m & (1 << x) != 0 && m & (1 << y) != 0 {
                        if let Some(s) = pt(a, 12 + 3 * d + p, &|| {
                            midpoint(&lt.edge_midpoint(x), &lt.edge_midpoint(y))
                        }) {
                            return Some(self.witness(&[c.mids[x], c.mids[y], s]));
                        }
                    }
                }
            }
        }
        None
    }

    /// Forgets why earlier merges were refused (see [`Self::coarsen_batch`]). The records only
    /// save work: every operation gives the same result with or without them.
    pub fn clear_refusal_records(&mut self) {
        self.refused.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_protocol::shapes;
    use tetwave_protocol::testing::unsampled_base;

    /// A witness keeps its vertices' keys whole: a key past 2^32 still matches its vertex, and a
    /// slot reused by the vertex whose key is that key's low 32 bits does not. The mesh is one tet
    /// refined once; its midpoint's key is set past 2^32 by hand (no hierarchy that large is made).
    #[test]
    fn witness_keys_past_32_bits() {
        let (p, _) = shapes::box6([0.0; 3], [1.0; 3]);
        let base = unsampled_base(3, (vec![p[0], p[1], p[2], p[4]], vec![[0, 1, 2, 3]]));
        let buf = DetailBuffer::new(base.forest(), base.vertex_keys());
        let mut m = AdaptiveMesh::new(&base).unwrap();
        m.refine(0, &buf).unwrap();
        let s = m.child_mids(&m.nodes[0])[0];
        assert!(s >= 4 && m.vref[s as usize] > 0, "a present midpoint");
        let low = m.vkey[s as usize];
        let wide = low + (1 << 32);
        m.vkey[s as usize] = wide;
        let w = m.witness(&[s]);
        assert!(
            m.witness_present(&w),
            "the vertex the witness names is present"
        );
        assert_eq!(m.witness_held(&w), Some([0, NONE, NONE, NONE]));
        // the slot now holds another vertex, whose key is the first one's low 32 bits
        m.vkey[s as usize] = low;
        assert!(!m.witness_present(&w), "another vertex is in the slot");
        assert_eq!(m.witness_held(&w), None);
        assert_eq!((w.slots, w.keys), ([s, NONE, NONE, NONE], [wide, 0, 0, 0]));
    }
}
