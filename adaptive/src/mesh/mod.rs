//! The adaptive mesh: red/green refinement over the semi-regular hierarchy, always conforming.
//!
//! # State
//! The state is the set `R` of red-refined hierarchy tets, closed under parent. Hierarchy *leaves* are
//! the base tets not in `R` and the children of tets in `R` that are not in `R`. Each leaf is drawn
//! either as itself or, when some of its edges carry a present midpoint, as its *green closure*.
//!
//! Storage is arrays + u32 indices + free lists, no pointer graph:
//! - **nodes**: one `Node` per tet of `R` ∪ leaves. Base tets occupy slots `0..n`; the 8 children
//!   of a refined tet occupy one contiguous block of 8 slots (`children` = first slot), recycled
//!   through a free list of blocks. A node (12 bytes) keeps its id, its first child slot, flags,
//!   and for a leaf its green pattern (the marked-edge mask; the midpoints are looked up when the
//!   greens are listed). Vertex slots are kept per block: the parent's 4 corners and 6 edge
//!   midpoints (40 bytes for 8 children; a child's 4 vertices are 4 of these,
//!   [`BEY_CHILDREN`](tetwave_protocol::hierarchy::BEY_CHILDREN)),
//!   and a base tet's are its base mesh's.
//! - **vertices**: slot arrays (key, position, value, edge endpoints, reference count, level, number of
//!   dependants). Base vertices are slots `0..nv` (slot = key) and never go away. A non-base vertex, the
//!   midpoint of an edge of a level-`k` tet, is present iff some refined level-`k` tet contains that
//!   edge; its reference count is the number of such refined tets. One array, dense over the key space
//!   and allocated once, finds a vertex's slot by key: for arriving coefficients, and for the
//!   closure, which computes the keys of a tet's edge midpoints and level-`k+2` points from its
//!   lattice tet (integer barycentric weights, [`AdaptiveMesh::lattice_of`]).
//! - The node and vertex arrays (except positions and values, which renderers read as slices) are
//!   `SegVec`s: they grow by segments and never copy what they hold, so no operation pays for
//!   moving a large array (a frame budget could not absorb it).
//!
//! # Values
//! A midpoint's value is `synthesize(d, P)` with `d` its coefficient from the
//! [`DetailBuffer`](crate::detail_buffer::DetailBuffer), or 0 (the prediction itself) while it has
//! not arrived, and `P` the contract's prediction ([`tetwave_protocol::wavelet`]): linear on a base
//! edge, else the quadratic interpolant of the refined tet's parent, which reads the edge's ends
//! and up to 4 more of the parent's points ([`VertexPrediction`]); all of them are present while
//! the vertex is (a refined tet's parent is refined). When coefficients arrive
//! ([`AdaptiveMesh::apply_arrivals`]) the present vertices that own them are recomputed in place;
//! if any of those has dependants (present vertices predicted from it), the present vertices are
//! re-synthesized level by level from the lowest changed level up, each one whose prediction read
//! a changed vertex being recomputed (one pass over the present vertices per batch).
//!
//! # Files
//! One concern per file: `node` (the packed node and its flags), `lattice` (Bey's children as
//! barycentric arithmetic), `keys` (the key → slot table), `green` (green patterns and splits),
//! `closure` (the closure's worklist), `vertices`, `red_tree` (slots, lookups, the selector's
//! view), `leaves` (the leaf mesh), `refine`, `coarsen`, `coarsen_batch` (batches and refusal
//! witnesses), `arrivals`, `changes` (the change log) and `conformity` (the invariant check).

mod arrivals;
mod axes_values;
mod changes;
mod closure;
mod coarsen;
mod coarsen_batch;
mod conformity;
mod error;
mod green;
mod keys;
mod lattice;
mod leaves;
mod node;
mod red_tree;
mod refine;
mod vertices;

/// Re-exported for the selector's per-slot arrays (its home is `crate::seg_vec`).
pub use changes::SlotChange;
pub use conformity::ConformityError;
pub use error::MeshError;
pub use green::{green_pattern_ok, green_piece_count, green_split};
pub use leaves::LeafTet;
pub use node::MAX_TETS;
pub use red_tree::RedNode;
pub use vertices::VertexPrediction;

use crate::seg_vec::SegVec;
use changes::MeshUid;
use coarsen_batch::Refusal;
use keys::KeySlots;
use node::{Node, NodeFlags};
use rustc_hash::FxHashMap;
use tetwave_protocol::base::signed_volume;
use tetwave_protocol::hierarchy::FACES;
use tetwave_protocol::{BaseMesh, Forest, TetId, VertexKeys};

const NONE: u32 = u32::MAX;

/// Owners remembered per vertex ([`AdaptiveMesh::vowner`]).
const OWNERS: usize = 2;

/// Red/green adaptive mesh (see the module docs).
#[derive(Debug, Clone)]
pub struct AdaptiveMesh {
    forest: Forest,
    keys: VertexKeys,
    base_positions: Vec<[f64; 3]>,
    base_tets: Vec<[u32; 4]>,
    /// Per base vertex: the base tets that use it.
    vertex_tets: Vec<Vec<u32>>,
    /// Per base tet and local face: lies on the domain boundary.
    boundary: Vec<[bool; 4]>,
    domain_volume: f64,

    nodes: SegVec<Node>,
    /// Per block of 8 children (block `b` = slots `n + 8b..n + 8b + 8`, `n` base tets): the
    /// parent's 4 corners and 6 edge midpoints (`BEY_CHILDREN`'s points), from which
    /// [`Self::node_verts`] reads a child's vertices (5 bytes per node instead of 16).
    bverts: SegVec<[u32; 10]>,
    free_blocks: Vec<u32>,
    n_leaves: usize,

    vkey: SegVec<u64>,
    vpos: Vec<[f32; 3]>,
    vval: Vec<f32>,
    vends: SegVec<[u32; 2]>,
    vref: SegVec<u32>,
    vlevel: SegVec<u8>,
    vdeps: SegVec<u32>,
    /// Per vertex: the points its quadratic prediction reads beyond its edge's ends (see
    /// [`VertexPrediction`]): a face mid-segment's opposite midpoint, or the other 4 midpoints of
    /// the parent whose centre it is; `NONE` elsewhere. They are present while the vertex is.
    vsrc: SegVec<[u32; 4]>,
    /// Per vertex: up to [`OWNERS`] of the refined tets that have it as an edge midpoint (`NONE`: not
    /// known), kept while they stay refined. A refusal witness whose every vertex has such an
    /// owner outside a merge batch is present whatever the batch releases, which settles its
    /// candidate before it is gathered.
    vowner: SegVec<[u32; OWNERS]>,
    free_vertices: Vec<u32>,
    n_vertices: usize,
    /// Slot by vertex key; base keys map to themselves.
    by_key: KeySlots,

    work: Vec<(u32, TetId)>,
    /// The candidates the last merge batch settled by their witness alone, each with the owners
    /// (one per witness vertex, `NONE` padding) outside the batch that keep the witness present:
    /// while those owners stay refined and out of a batch, so does the candidate.
    held: Vec<(u32, [u32; 4])>,
    /// Refined tets (by slot) whose last merge attempt in a batch was refused, and why.
    refused: FxHashMap<u32, Refusal>,
    /// Red splits and merges done so far (closure refinements included).
    n_splits: u64,
    n_merges: u64,

    /// Identity of this mesh (a clone gets a new one), for incremental consumers of [`Self::changes`].
    uid: MeshUid,
    /// Structural changes since [`Self::changes_start`] (see [`SlotChange`]); bounded, see
    /// [`Self::trim_changes`].
    changes: Vec<SlotChange>,
    changes_start: u64,
    /// Values by grid point for a hierarchy with the axes predictor, and each vertex's point.
    axes: Option<axes_values::AxesValues>,
    vpoint: SegVec<[u32; 3]>,
}

impl AdaptiveMesh {
    /// The coarsest mesh: the base tets as leaves. `base` must pass [`BaseMesh::validate`]; a
    /// hierarchy with [`MAX_TETS`] tets or more is refused (the mesh packs ids in 40 bits), and
    /// so is one whose vertex keys a `usize` cannot count (the key table's directory is indexed
    /// by key; on a 64-bit target every hierarchy under [`MAX_TETS`] tets passes). Vertex keys are
    /// kept whole (64 bits); the key table's directory takes 0.25 B per key of the hierarchy.
    pub fn new(base: &BaseMesh) -> Result<Self, MeshError> {
        let forest = base.forest();
        let keys = base.vertex_keys();
        let nkeys = keys.vertex_count();
        Self::check_size(forest.total_tets(), nkeys)?;
        let nv = base.positions.len();
        let mut vertex_tets = vec![Vec::new(); nv];
        let mut face_count: FxHashMap<[u32; 3], u32> = FxHashMap::default();
        for (t, tv) in base.tets.iter().enumerate() {
            for &g in tv {
                vertex_tets[g as usize].push(t as u32);
            }
            for f in &FACES {
                let mut k = [tv[f[0]], tv[f[1]], tv[f[2]]];
                k.sort_unstable();
                *face_count.entry(k).or_insert(0) += 1;
            }
        }
        let boundary = base
            .tets
            .iter()
            .map(|tv| {
                std::array::from_fn(|d| {
                    let f = FACES[d];
                    let mut k = [tv[f[0]], tv[f[1]], tv[f[2]]];
                    k.sort_unstable();
                    face_count[&k] == 1
                })
            })
            .collect();
        let mut nodes = SegVec::new();
        let mut domain_volume = 0.0;
        for (t, tv) in base.tets.iter().enumerate() {
            let p = tv.map(|g| base.positions[g as usize]);
            let vol = signed_volume(p[0], p[1], p[2], p[3]);
            domain_volume += vol.abs();
            let mut flags = NodeFlags::ALIVE;
            if vol < 0.0 {
                flags |= NodeFlags::FLIP;
            }
            if base.empty[t] {
                flags |= NodeFlags::EMPTY;
            }
            nodes.push(Node::new(t as TetId, NONE, 0, flags));
        }
        let mut m = AdaptiveMesh {
            forest,
            keys,
            base_positions: base.positions.clone(),
            base_tets: base.tets.clone(),
            vertex_tets,
            boundary,
            domain_volume,
            nodes,
            bverts: SegVec::new(),
            free_blocks: Vec::new(),
            n_leaves: base.tets.len(),
            vkey: SegVec::new(),
            vpos: Vec::new(),
            vval: Vec::new(),
            vends: SegVec::new(),
            vref: SegVec::new(),
            vlevel: SegVec::new(),
            vdeps: SegVec::new(),
            vsrc: SegVec::new(),
            vowner: SegVec::new(),
            free_vertices: Vec::new(),
            n_vertices: 0,
            by_key: KeySlots::new(0),
            work: Vec::new(),
            held: Vec::new(),
            refused: FxHashMap::default(),
            n_splits: 0,
            n_merges: 0,
            uid: MeshUid::new(),
            changes: Vec::new(),
            changes_start: 0,
            axes: None,
            vpoint: SegVec::new(),
        };
        if base.predictor == tetwave_protocol::wavelet::Predictor::Axes {
            let axes = axes_values::AxesValues::new(base, &m.keys)?;
            let lm = m.keys.lattice().m();
            for g in 0..nv {
                // a base vertex is the lattice point with all of a tet's weight on it
                let t = m.vertex_tets[g][0];
                let i = base.tets[t as usize].iter().position(|&v| v as usize == g);
                let mut w = [0u32; 4];
                w[i.expect("the tet has the vertex")] = lm;
                m.vpoint.push(axes.point(t, &w));
            }
            m.axes = Some(axes);
        }
        for g in 0..nv {
            let p = base.positions[g];
            m.vkey.push(g as u64);
            m.vpos.push([p[0] as f32, p[1] as f32, p[2] as f32]);
            m.vval.push(base.values[g]);
            m.vends.push([NONE; 2]);
            m.vref.push(u32::MAX);
            m.vlevel.push(0);
            m.vdeps.push(0);
            m.vsrc.push([NONE; 4]);
            m.vowner.push([NONE; OWNERS]);
        }
        m.n_vertices = nv;
        m.by_key = KeySlots::new(nkeys as usize);
        for g in 0..nv {
            m.by_key.insert(g as u64, g as u32);
        }
        Ok(m)
    }

    /// [`Self::new`]'s size limits: [`MAX_TETS`] tets, and keys a `usize` can count.
    fn check_size(total_tets: u64, nkeys: u64) -> Result<(), MeshError> {
        if total_tets >= MAX_TETS {
            return Err(MeshError::TooManyTets(total_tets));
        }
        if usize::try_from(nkeys).is_err() {
            return Err(MeshError::TooManyKeys(nkeys));
        }
        Ok(())
    }

    pub fn forest(&self) -> Forest {
        self.forest
    }

    pub fn vertex_keys(&self) -> &VertexKeys {
        &self.keys
    }

    /// Sum of the base tets' volumes.
    pub fn domain_volume(&self) -> f64 {
        self.domain_volume
    }

    /// Red splits and merges done so far, closure refinements included. Each split removes one leaf
    /// and creates 8; each merge the reverse.
    pub fn op_counts(&self) -> (u64, u64) {
        (self.n_splits, self.n_merges)
    }

    /// Bytes held by the node, vertex and map storage (capacities).
    pub fn bytes_held(&self) -> usize {
        self.bytes_parts().iter().map(|p| p.1).sum()
    }

    /// [`Self::bytes_held`] by part: nodes, vertices, key table, refusal records, the rest.
    pub fn bytes_parts(&self) -> [(&'static str, usize); 5] {
        use std::mem::size_of;
        [
            (
                "nodes",
                self.nodes.bytes() + self.bverts.bytes() + self.free_blocks.capacity() * 4,
            ),
            (
                "vertices",
                self.vkey.bytes()
                    + self.vpos.capacity() * 12
                    + self.vval.capacity() * 4
                    + self.vends.bytes()
                    + self.vref.bytes()
                    + self.vlevel.bytes()
                    + self.vdeps.bytes()
                    + self.vsrc.bytes()
                    + self.vowner.bytes()
                    + self.vpoint.bytes()
                    + self.free_vertices.capacity() * 4,
            ),
            (
                "keys",
                self.by_key.bytes() + self.axes.as_ref().map_or(0, |a| a.bytes()),
            ),
            (
                "refusals",
                self.refused.capacity() * (size_of::<(u32, Refusal)>() + 1)
                    + self.held.capacity() * size_of::<(u32, [u32; 4])>(),
            ),
            (
                "work",
                self.work.capacity() * size_of::<(u32, TetId)>()
                    + self.changes.capacity() * size_of::<SlotChange>(),
            ),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Vertex keys past 2^32 are no longer refused (keys are kept whole): one tet at 12 levels
    /// (1.1e10 keys, 7.9e10 tets) and the 2049³ box (8.6e9 keys) pass; 2^40 tets or more do not.
    /// The sizes are checked without making those meshes (the key table alone would take GBs).
    #[test]
    fn sizes_past_32_bit_keys_pass() {
        use tetwave_protocol::{shapes, testing::unsampled_base};
        let (p, _) = shapes::box6([0.0; 3], [1.0; 3]);
        let tet = unsampled_base(12, (vec![p[0], p[1], p[2], p[4]], vec![[0, 1, 2, 3]]));
        let boxed = unsampled_base(11, shapes::box6([0.0; 3], [1.0; 3]));
        assert_eq!(boxed.vertex_keys().vertex_count(), 2049u64.pow(3));
        for b in [&tet, &boxed] {
            let nkeys = b.vertex_keys().vertex_count();
            assert!(nkeys > u32::MAX as u64);
            assert_eq!(
                AdaptiveMesh::check_size(b.forest().total_tets(), nkeys),
                Ok(())
            );
        }
        assert_eq!(
            AdaptiveMesh::check_size(MAX_TETS, 1 << 36),
            Err(MeshError::TooManyTets(MAX_TETS))
        );
        assert_eq!(AdaptiveMesh::check_size(MAX_TETS - 1, 1 << 36), Ok(()));
    }
}
