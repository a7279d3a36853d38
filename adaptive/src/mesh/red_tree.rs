//! The red tree's nodes: slots, lookup by hierarchy id, and the view of a node the selector reads
//! ([`RedNode`]).

use super::node::{Node, NodeFlags};
use super::AdaptiveMesh;
use tetwave_protocol::hierarchy::{Lattice, BEY_CHILDREN};
use tetwave_protocol::{LatticeTet, TetId};

/// One node of the red tree as selection sees it ([`AdaptiveMesh::red_node`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RedNode {
    pub id: TetId,
    /// Its node slot ([`AdaptiveMesh::node_verts`] gives its vertices).
    pub slot: u32,
    pub leaf: bool,
    /// Lies outside the input domain.
    pub empty: bool,
    /// A refined node whose 8 children are all leaves (a merge candidate); false for leaves.
    pub children_leaves: bool,
}

impl AdaptiveMesh {
    /// Length of the node slot array (live and dead slots); see [`Self::red_node`].
    pub fn node_slot_len(&self) -> usize {
        self.nodes.len()
    }

    /// The live node in slot `slot`, `None` for a dead (free) slot.
    #[inline]
    pub fn red_node(&self, slot: usize) -> Option<RedNode> {
        let n = self.nodes.get(slot)?;
        if !n.alive() {
            return None;
        }
        Some(self.red_view(slot as u32, n))
    }

    /// Asks the CPU to bring the node in slot `slot` into the cache (see [`SegVec::prefetch`]).
    #[inline(always)]
    pub(crate) fn prefetch_node(&self, slot: usize) {
        self.nodes.prefetch(slot);
    }

    /// Vertex slots of the live node in slot `slot`, hierarchy vertex order: a base tet's own, a
    /// child's from its block's 10 points (the parent's corners and edge midpoints, see
    /// [`BEY_CHILDREN`]).
    #[inline]
    pub fn node_verts(&self, slot: usize) -> [u32; 4] {
        if slot < self.base_tets.len() {
            return self.base_tets[slot];
        }
        let p = &self.bverts[self.block_of(slot)];
        BEY_CHILDREN[(slot - self.base_tets.len()) & 7].map(|q| p[q])
    }

    /// Index in [`Self::bverts`] of the block holding non-base slot `slot`.
    #[inline]
    pub(super) fn block_of(&self, slot: usize) -> usize {
        (slot - self.base_tets.len()) >> 3
    }

    /// The 10 points of the block whose first slot is `block`.
    #[inline]
    pub(super) fn block_points(&self, block: u32) -> &[u32; 10] {
        &self.bverts[self.block_of(block as usize)]
    }

    #[inline]
    fn red_view(&self, slot: u32, n: &Node) -> RedNode {
        let leaf = n.is_leaf();
        RedNode {
            id: n.id(),
            slot,
            leaf,
            empty: n.flags.contains(NodeFlags::EMPTY),
            children_leaves: !leaf && n.nref == 0,
        }
    }

    /// Appends the slots of the subtree of the red tree rooted at `slot` (itself included) to `out`.
    pub fn subtree_slots(&self, slot: usize, out: &mut Vec<u32>) {
        let start = out.len();
        out.push(slot as u32);
        let mut i = start;
        while i < out.len() {
            let n = &self.nodes[out[i] as usize];
            if !n.is_leaf() {
                out.extend(n.children..n.children + 8);
            }
            i += 1;
        }
    }

    /// Whether `slot` holds the live node of hierarchy tet `id`.
    #[inline]
    pub fn slot_holds(&self, slot: usize, id: TetId) -> bool {
        self.nodes
            .get(slot)
            .is_some_and(|n| n.alive() && n.id() == id)
    }

    /// Node slot of hierarchy tet `id`, if it is in the red tree (see [`Self::red_node`]).
    #[inline]
    pub fn slot_of(&self, id: TetId) -> Option<usize> {
        self.find(id).map(|s| s as usize)
    }

    /// The node of hierarchy tet `id`, if it is in the red tree.
    pub fn red_node_of(&self, id: TetId) -> Option<RedNode> {
        self.find(id)
            .map(|s| self.red_view(s, &self.nodes[s as usize]))
    }

    /// The lattice tet of `id`, without allocating.
    pub fn lattice_of(&self, id: TetId) -> LatticeTet {
        let k = self.forest.level(id);
        let local = id - self.forest.level_start(k);
        let base = (local >> (3 * k as u32)) as u32;
        let mut t = LatticeTet::base_tet(
            Lattice {
                levels: self.forest.levels,
            },
            base,
        );
        for j in 0..k {
            let d = (local >> (3 * (k - 1 - j) as u32)) & 7;
            t = t.child(d as usize);
        }
        t
    }

    /// Node slot of hierarchy tet `id`, if it is in the red tree (refined or leaf).
    pub(super) fn find(&self, id: TetId) -> Option<u32> {
        if id >= self.forest.total_tets() {
            return None;
        }
        let k = self.forest.level(id);
        let local = id - self.forest.level_start(k);
        let mut slot = (local >> (3 * k as u32)) as u32;
        for j in 0..k {
            let n = &self.nodes[slot as usize];
            if n.is_leaf() {
                return None;
            }
            slot = n.children + ((local >> (3 * (k - 1 - j) as u32)) & 7) as u32;
        }
        Some(slot)
    }

    /// Whether hierarchy tet `id` is a leaf of the red tree.
    pub fn is_leaf(&self, id: TetId) -> bool {
        self.find(id)
            .is_some_and(|s| self.nodes[s as usize].is_leaf())
    }

    /// Whether hierarchy tet `id` is red-refined.
    pub fn is_refined(&self, id: TetId) -> bool {
        self.find(id)
            .is_some_and(|s| !self.nodes[s as usize].is_leaf())
    }

    /// Whether hierarchy tet `id` is known to be empty (outside the input domain).
    pub fn is_empty_tet(&self, id: TetId) -> bool {
        self.find(id)
            .is_some_and(|s| self.nodes[s as usize].flags.contains(NodeFlags::EMPTY))
    }

    /// Ids of the hierarchy leaves.
    pub fn leaf_ids(&self) -> Vec<TetId> {
        self.nodes
            .iter()
            .filter(|n| n.alive() && n.is_leaf())
            .map(|n| n.id())
            .collect()
    }

    /// Ids of the red-refined tets.
    pub fn refined_ids(&self) -> Vec<TetId> {
        self.nodes
            .iter()
            .filter(|n| n.alive() && !n.is_leaf())
            .map(|n| n.id())
            .collect()
    }

    /// Ids of the refined tets whose 8 children are all leaves (candidates for [`Self::coarsen`]).
    pub fn coarsenable_ids(&self) -> Vec<TetId> {
        self.nodes
            .iter()
            .filter(|n| n.alive() && !n.is_leaf() && self.children_leaves(n))
            .map(|n| n.id())
            .collect()
    }

    /// Number of hierarchy leaves.
    pub fn leaf_count(&self) -> usize {
        self.n_leaves
    }

    /// Whether the 8 children of refined node `n` are leaves.
    #[inline]
    pub(super) fn children_leaves(&self, n: &Node) -> bool {
        debug_assert_eq!(
            n.nref as usize,
            (0..8)
                .filter(|&i| !self.nodes[(n.children + i) as usize].is_leaf())
                .count()
        );
        n.nref == 0
    }

    /// Adds `d` to the refined-children count of the parent of `id` (if not a base tet).
    #[inline]
    pub(super) fn count_in_parent(&mut self, id: TetId, d: i8) {
        if let Some(p) = self.forest.parent(id) {
            let ps = self.find(p).expect("a node's parent is in the tree") as usize;
            let n = &mut self.nodes[ps];
            n.nref = n.nref.wrapping_add_signed(d);
        }
    }
}
