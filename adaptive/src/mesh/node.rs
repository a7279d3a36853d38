//! One node of the red tree, packed in 12 bytes, and its flags.

use super::NONE;
use tetwave_protocol::TetId;

bitflags::bitflags! {
    /// The state bits of a [`Node`] (one byte of its 12).
    #[repr(transparent)]
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub(super) struct NodeFlags: u8 {
        /// The slot holds a node (a free slot holds [`Node::DEAD`]).
        const ALIVE = 1;
        /// Lies outside the input domain.
        const EMPTY = 2;
        /// Its hierarchy vertex order is negatively oriented: its pieces are listed with their last
        /// two vertices swapped.
        const FLIP = 4;
        /// On the closure's worklist (see `AdaptiveMesh::queue`).
        const QUEUED = 8;
        /// Seen while a merge batch gathers its candidates (cleared before it returns).
        const BATCHED = 16;
    }
}

const _: () = assert!(std::mem::size_of::<NodeFlags>() == 1);

/// One node of the red tree (see the module docs): 12 bytes. Its id is split in a low word and a
/// high byte ([`MAX_TETS`]): with a 64-bit id the node took 16 bytes, and the mesh 4 more per
/// slot.
#[derive(Debug, Clone, Copy)]
pub(super) struct Node {
    pub(super) id_lo: u32,
    pub(super) children: u32,
    pub(super) id_hi: u8,
    /// Marked edges of a leaf (its green pattern); 0 for refined nodes.
    pub(super) mask: u8,
    pub(super) flags: NodeFlags,
    /// Refined children (0 for a leaf): a refined node with none has 8 leaf children.
    pub(super) nref: u8,
}

const _: () = assert!(std::mem::size_of::<Node>() == 12);

/// Tets a hierarchy may have (all levels) for
/// [`AdaptiveMesh::new`](super::AdaptiveMesh::new): a node keeps 40 bits of id.
pub const MAX_TETS: u64 = 1 << 40;

impl Node {
    pub(super) const DEAD: Node = Node::new(0, NONE, 0, NodeFlags::empty());

    #[inline(always)]
    pub(super) const fn new(id: TetId, children: u32, mask: u8, flags: NodeFlags) -> Node {
        Node {
            id_lo: id as u32,
            children,
            id_hi: (id >> 32) as u8,
            mask,
            flags,
            nref: 0,
        }
    }

    #[inline(always)]
    pub(super) fn id(&self) -> TetId {
        self.id_lo as TetId | (self.id_hi as TetId) << 32
    }

    #[inline]
    pub(super) fn is_leaf(&self) -> bool {
        self.children == NONE
    }
    #[inline]
    pub(super) fn alive(&self) -> bool {
        self.flags.contains(NodeFlags::ALIVE)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_ids_keep_40_bits() {
        for id in [0, 1, u32::MAX as TetId, 1 << 32, MAX_TETS - 1] {
            let n = Node::new(id, 7, 3, NodeFlags::ALIVE);
            assert_eq!(
                (n.id(), n.children, n.mask, n.flags, n.nref),
                (id, 7, 3, NodeFlags::ALIVE, 0)
            );
        }
    }
}
