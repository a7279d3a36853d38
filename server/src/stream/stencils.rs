//! For stores with the axes predictor ([`tetwave_protocol::axes`]): which nodes own the vertices
//! a node's stencils read, transitively, so that an order sends them no later than the node it
//! chose (in the same batch at the latest). A client then draws the chosen node's new vertices
//! exactly as soon as they arrive, whatever the order or the view. The nodes pulled in this way
//! bring other vertices too, whose own stencils are not followed (that would pull in a whole level
//! node by node, each owning vertices of several passes): those are exact once the order reaches
//! them, and everything is once the stream is complete.

use tetwave_protocol::axes::Grid;
use tetwave_protocol::ownership::Ownership;
use tetwave_protocol::synthesis::NodeAt;
use tetwave_protocol::{BaseMesh, Forest, TetId, VertexKeys};

pub(super) struct StencilDeps {
    forest: Forest,
    keys: VertexKeys,
    ownership: Ownership,
    grid: Grid,
    /// Per vertex key, the node owning its coefficient (`u32::MAX` for base vertices).
    owner: Vec<u32>,
}

impl StencilDeps {
    /// `None` for a store with the parent predictor (its stencils read only what the node's own
    /// ancestors hold) or one whose grid cannot be built.
    pub(super) fn new(base: &BaseMesh) -> Option<Self> {
        if base.predictor != tetwave_protocol::wavelet::Predictor::Axes {
            return None;
        }
        let keys = base.vertex_keys();
        let grid = Grid::of(base, &keys).ok()?;
        let forest = base.forest();
        let ownership = Ownership::new(base);
        let mut owner = vec![u32::MAX; keys.vertex_count() as usize];
        let mut deps = StencilDeps {
            forest,
            keys,
            ownership,
            grid,
            owner: Vec::new(),
        };
        for id in 0..forest.nodes() {
            deps.for_each_owned_key(id, |k| owner[k] = id as u32);
        }
        deps.owner = owner;
        Some(deps)
    }

    fn for_each_owned_key(&self, id: TetId, mut f: impl FnMut(usize)) {
        let mask = self.ownership.owned(id);
        if mask == 0 {
            return;
        }
        let tet = NodeAt::from_id(&self.forest, id).tet();
        for e in 0..6 {
            if mask >> e & 1 == 1 {
                f(self.keys.key(tet.base, &tet.edge_midpoint(e)) as usize);
            }
        }
    }

    /// Calls `need` with the owner of every vertex that the stencils of node `id`'s own vertices
    /// read, transitively, deepest first (`id` itself among them), skipping the vertices already
    /// set in `closed` (per key: its closure has been handed out) and setting those it visits.
    pub(super) fn closure(&self, id: TetId, closed: &mut [u64], need: &mut impl FnMut(TetId)) {
        self.for_each_owned_key(id, |k| self.close(k, closed, need));
    }

    /// The recursion of [`Self::closure`]: its depth is at most three passes a level.
    fn close(&self, k: usize, closed: &mut [u64], need: &mut impl FnMut(TetId)) {
        let (w, bit) = (k / 64, 1u64 << (k % 64));
        if closed[w] & bit != 0 {
            return;
        }
        closed[w] |= bit;
        for r in self.grid.stencil(k).into_iter().flatten().flatten() {
            self.close(r, closed, need);
        }
        if self.owner[k] != u32::MAX {
            need(self.owner[k] as TetId);
        }
    }

    /// Words of a [`Self::closure`] bitset.
    pub(super) fn closed_words(&self) -> usize {
        self.owner.len().div_ceil(64)
    }

    /// The owner of vertex `key` (`None` for a base vertex).
    #[cfg(test)]
    pub(super) fn owner(&self, key: usize) -> Option<TetId> {
        (self.owner[key] != u32::MAX).then_some(self.owner[key] as TetId)
    }

    /// The stencil of vertex `key`.
    #[cfg(test)]
    pub(super) fn stencil(&self, key: usize) -> Option<tetwave_protocol::axes::Stencil> {
        self.grid.stencil(key)
    }

    /// The vertices node `id` owns.
    #[cfg(test)]
    pub(super) fn owned_keys(&self, id: TetId) -> Vec<usize> {
        let mut v = Vec::new();
        self.for_each_owned_key(id, |k| v.push(k));
        v
    }
}
