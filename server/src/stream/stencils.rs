//! For stores with the axes predictor ([`tetwave_protocol::axes`]): which nodes own the vertices
//! a node's stencils read, so that every order sends them no later than the node itself, in the
//! same batch at the latest. A client then holds, with each node, every coefficient its new
//! vertices' predictions read (transitively, since each of those owners came with its own), and
//! draws those vertices exactly as soon as they arrive, whatever the order or the view.

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

    /// The nodes owning the vertices node `id`'s new vertices' stencils read (not `id` itself;
    /// with repeats).
    pub(super) fn reads(&self, id: TetId, out: &mut Vec<TetId>) {
        self.for_each_owned_key(id, |k| {
            for r in self.grid.stencil(k).into_iter().flatten().flatten() {
                let o = self.owner[r];
                if o != u32::MAX && o as TetId != id {
                    out.push(o as TetId);
                }
            }
        });
    }
}
