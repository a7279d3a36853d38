//! The closure: after vertices appear or disappear, the leaves around them are red-refined when
//! forced, or get their green pattern.
//!
//! # Closure
//! A leaf `T` of level `k` is *forced* (must be red-refined) if its marked edges (edges whose midpoint
//! is present) do not form one of the green patterns (0 edges; 1; 2 on a face; 2 opposite; 3 of one
//! face) or if any of the 24 level-`k+2` lattice points on its boundary is present (1-irregularity:
//! otherwise a vertex would hang on its faces). Those 24 points are the midpoints of the half edges of
//! marked edges (12) and of the segments joining two marked midpoints of one face (12), so the test
//! is a handful of key lookups. The closure is a worklist (a leaf is on it at most once): every vertex
//! that appears or disappears puts the leaves whose closure contains it (point location down the tree
//! with integer barycentric coordinates) on the list; forced leaves are red-refined (domino). The
//! result does not depend on the order (refining only adds vertices, and the test is monotone in
//! them). The number of
//! closure refinements per operation is bounded by the number of hierarchy nodes (an error, never an
//! endless loop). The closure may red-refine an *empty* tet (one outside the input domain) when its
//! neighbours need it; explicit [`AdaptiveMesh::refine`] of an empty tet is refused, and empty leaves
//! are not listed by [`AdaptiveMesh::drawable_leaf_tets`].

use super::green::{green_pattern_ok, FACE_MASK};
use super::lattice::child_weights;
use super::node::NodeFlags;
use super::{AdaptiveMesh, MeshError, NONE};
use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::hierarchy::{midpoint, Bary, EDGES};
use tetwave_protocol::{LatticeTet, TetId};

impl AdaptiveMesh {
    /// Slot of the present vertex at lattice point `w` of base tet `b` (`NONE`: absent).
    #[inline]
    pub(super) fn slot_at(&self, b: u32, w: &Bary) -> u32 {
        self.by_key.get(self.keys.key(b, w))
    }

    /// Slots of the present midpoints of the 6 edges of lattice tet `lt` of level `k` (`NONE`:
    /// absent).
    #[inline]
    pub(super) fn lattice_mids(&self, lt: &LatticeTet, k: u8) -> [u32; 6] {
        if k >= self.forest.levels {
            return [NONE; 6];
        }
        std::array::from_fn(|e| self.slot_at(lt.base, &lt.edge_midpoint(e)))
    }

    /// Green pattern of lattice tet `lt` of level `k` with midpoints `mid` (`NONE` = absent): the
    /// mask and whether the tet is forced (bad pattern, or a present level-k+2 point on its boundary:
    /// the midpoint of a half of a marked edge, or of the segment joining two marked midpoints of one
    /// face). `present(s)` tells whether the vertex in slot `s` counts as present.
    #[inline]
    pub(super) fn classify(
        &self,
        lt: &LatticeTet,
        k: u8,
        mid: &[u32; 6],
        present: impl Fn(u32) -> bool,
    ) -> (u8, bool) {
        let mut mask = 0u8;
        for (e, &m) in mid.iter().enumerate() {
            if m != NONE {
                mask |= 1 << e;
            }
        }
        if !green_pattern_ok(mask) {
            return (mask, true);
        }
        if mask == 0 || k + 2 > self.forest.levels {
            return (mask, false);
        }
        let b = lt.base;
        let at = |w: &Bary| {
            let s = self.slot_at(b, w);
            s != NONE && present(s)
        };
        let mut mw = [[0u32; 4]; 6];
        for (e, &(x, y)) in EDGES.iter().enumerate() {
            if mask & (1 << e) != 0 {
                let m = lt.edge_midpoint(e);
                if at(&midpoint(&lt.v[x], &m)) || at(&midpoint(&m, &lt.v[y])) {
                    return (mask, true);
                }
                mw[e] = m;
            }
        }
        if mask.count_ones() >= 2 {
            for fm in FACE_MASK {
                let m = mask & fm;
                if m.count_ones() >= 2 {
                    let x = m.trailing_zeros() as usize;
                    let rest = m & (m - 1);
                    let y = rest.trailing_zeros() as usize;
                    if at(&midpoint(&mw[x], &mw[y])) {
                        return (mask, true);
                    }
                    let z = rest & (rest - 1);
                    if z != 0 {
                        let z = z.trailing_zeros() as usize;
                        if at(&midpoint(&mw[x], &mw[z])) || at(&midpoint(&mw[y], &mw[z])) {
                            return (mask, true);
                        }
                    }
                }
            }
        }
        (mask, false)
    }

    /// Puts the node in `slot` on the worklist unless it is there already.
    #[inline]
    pub(super) fn queue(&mut self, slot: u32) {
        let n = &mut self.nodes[slot as usize];
        if !n.flags.contains(NodeFlags::QUEUED) {
            n.flags.insert(NodeFlags::QUEUED);
            let id = n.id();
            self.work.push((slot, id));
        }
    }

    /// Empties the worklist (clearing the queued flags).
    fn clear_work(&mut self) {
        while let Some((slot, id)) = self.work.pop() {
            let n = &mut self.nodes[slot as usize];
            if n.alive() && n.id() == id {
                n.flags.remove(NodeFlags::QUEUED);
            }
        }
    }

    /// Pushes every leaf of level `≤ max_level` whose closure contains lattice point `w` of base tet
    /// `b` onto the worklist. For the midpoint of a level-`k` edge, the leaves whose closure can
    /// change are those of level `≤ k`: a finer leaf holding the point has it as a vertex (a lattice
    /// tet holds no other point of its lattice), not as the midpoint of one of its edges.
    pub(super) fn locate(&mut self, b: u32, w: &Bary, max_level: u8) {
        let mut work = std::mem::take(&mut self.work);
        let tv = self.base_tets[b as usize];
        let first = (0..4).find(|&i| w[i] != 0).expect("zero weights");
        for &c in &self.vertex_tets[tv[first] as usize] {
            let cv = self.base_tets[c as usize];
            let mut lam = [0i64; 4];
            let mut ok = true;
            for i in 0..4 {
                if w[i] != 0 {
                    match cv.iter().position(|&g| g == tv[i]) {
                        Some(j) => lam[j] = w[i] as i64,
                        None => {
                            ok = false;
                            break;
                        }
                    }
                }
            }
            if ok {
                let from = work.len();
                self.descend(c, lam, max_level, &mut work);
                // leaves already on the list are not queued twice
                let mut j = from;
                for i in from..work.len() {
                    let (s, _) = work[i];
                    let f = &mut self.nodes[s as usize].flags;
                    if !f.contains(NodeFlags::QUEUED) {
                        f.insert(NodeFlags::QUEUED);
                        work[j] = work[i];
                        j += 1;
                    }
                }
                work.truncate(j);
            }
        }
        self.work = work;
    }

    fn descend(&self, slot: u32, lam: [i64; 4], levels_left: u8, out: &mut Vec<(u32, TetId)>) {
        let n = &self.nodes[slot as usize];
        if n.is_leaf() {
            out.push((slot, n.id()));
            return;
        }
        if levels_left == 0 {
            return;
        }
        let (mu, mut holds) = child_weights(lam);
        while holds != 0 {
            let i = holds.trailing_zeros() as usize;
            holds &= holds - 1;
            self.descend(n.children + i as u32, mu[i], levels_left - 1, out);
        }
    }

    /// Settles the worklist: red-refines forced leaves, records the green pattern of the others.
    pub(super) fn close(&mut self, buf: &DetailBuffer) -> Result<(), MeshError> {
        let bound = self.forest.nodes() as usize + 8;
        let mut refines = 0usize;
        let levels = self.forest.levels;
        while let Some((slot, id)) = self.work.pop() {
            let n = self.nodes[slot as usize];
            if !n.alive() || n.id() != id || !n.flags.contains(NodeFlags::QUEUED) {
                continue;
            }
            self.nodes[slot as usize].flags.remove(NodeFlags::QUEUED);
            if !n.is_leaf() {
                continue;
            }
            let k = self.forest.level(id);
            if k >= levels {
                // no midpoints at the finest level
                continue;
            }
            let lt = self.lattice_of(id);
            let mid = self.lattice_mids(&lt, k);
            let (mask, forced) = self.classify(&lt, k, &mid, |_| true);
            if forced {
                refines += 1;
                if refines > bound {
                    self.clear_work();
                    return Err(MeshError::ClosureBound(bound));
                }
                if let Err(e) = self.refine_slot(slot, &lt, buf) {
                    self.clear_work();
                    return Err(e);
                }
            } else {
                self.nodes[slot as usize].mask = mask;
            }
        }
        Ok(())
    }
}
