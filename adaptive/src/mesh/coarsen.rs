//! Undoing the red split of a tet whose children are leaves (coarsening, or merging).

use super::node::Node;
use super::{AdaptiveMesh, MeshError, NONE};
use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::TetId;

impl AdaptiveMesh {
    /// Undoes the red split of `t` (whose 8 children must be leaves) and restores the green closure
    /// around it. Refused ([`MeshError::Forced`]) when the closure would refine `t` again at once.
    pub fn coarsen(&mut self, t: TetId, buf: &DetailBuffer) -> Result<(), MeshError> {
        let slot = self.find(t).ok_or(MeshError::NotInMesh(t))?;
        let n = self.nodes[slot as usize];
        if n.is_leaf() {
            return Err(MeshError::NotRefined(t));
        }
        if (0..8).any(|i| !self.nodes[(n.children + i) as usize].is_leaf()) {
            return Err(MeshError::ChildrenRefined(t));
        }
        let all = self.child_mids(&n);
        // midpoints that stay: created by another refined tet too
        let after: [u32; 6] = std::array::from_fn(|e| {
            if self.vref[all[e] as usize] > 1 {
                all[e]
            } else {
                NONE
            }
        });
        let lt = self.lattice_of(t);
        if self.classify(&lt, self.forest.level(t), &after, |_| true).1 {
            return Err(MeshError::Forced(t));
        }
        self.unrefine(slot);
        self.close(buf)
    }

    /// Midpoint slots of the 6 edges of refined node `n`, read off its children ([`BEY_CHILDREN`]:
    /// `T0 = [x0, x01, x02, x03]`, `T1 = [x01, x1, x12, x13]`, `T2 = [x02, x12, x2, x23]`).
    #[inline]
    pub(super) fn child_mids(&self, n: &Node) -> [u32; 6] {
        let p = self.block_points(n.children);
        let m = [p[4], p[5], p[6], p[7], p[8], p[9]];
        debug_assert_eq!(
            m,
            self.lattice_mids(&self.lattice_of(n.id()), self.forest.level(n.id()))
        );
        m
    }

    /// Removes the 8 (leaf) children of `slot` and releases its midpoints; queues `slot` and the
    /// leaves around every vertex that went away.
    pub(super) fn unrefine(&mut self, slot: u32) {
        let n = self.nodes[slot as usize];
        let t = n.id();
        let all = self.child_mids(&n);
        let lt = self.lattice_of(t);
        if !self.refused.is_empty() {
            self.refused.remove(&slot);
        }
        for i in 0..8 {
            self.nodes[(n.children + i) as usize] = Node::DEAD;
        }
        self.free_blocks.push(n.children);
        self.nodes[slot as usize].children = NONE;
        self.n_leaves -= 7;
        self.n_merges += 1;
        self.log_change(slot, n.children);
        self.count_in_parent(t, -1);
        let mut removed = [false; 6];
        for e in 0..6 {
            let s = all[e] as usize;
            let o = &mut self.vowner[s];
            for x in o.iter_mut() {
                if *x == slot {
                    *x = NONE;
                }
            }
            self.vref[s] -= 1;
            if self.vref[s] == 0 {
                debug_assert_eq!(self.vdeps[s], 0);
                self.by_key.remove(self.vkey[s]);
                self.drop_dependencies(s);
                self.free_vertices.push(s as u32);
                self.n_vertices -= 1;
                removed[e] = true;
            }
        }
        self.queue(slot);
        let level = self.forest.level(t);
        for (e, &r) in removed.iter().enumerate() {
            if r {
                self.locate(lt.base, &lt.edge_midpoint(e), level);
            }
        }
    }
}
