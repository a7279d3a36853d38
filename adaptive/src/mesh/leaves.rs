//! The leaf mesh: red leaves and green pieces, listed or counted.

use super::green::{green_piece_count, green_split};
use super::node::{Node, NodeFlags};
use super::{AdaptiveMesh, NONE};
use tetwave_protocol::TetId;

/// A tet of the leaf mesh: 4 vertex slots, positively oriented.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LeafTet {
    pub v: [u32; 4],
    /// The hierarchy tet it belongs to (itself, or the red tet whose green closure it is part of).
    pub hier: TetId,
    pub green: bool,
    /// Lies outside the input domain (never drawn).
    pub empty: bool,
}

impl AdaptiveMesh {
    /// Pieces of the leaf mesh (red leaves and green pieces): `(all, drawable)`; the counts
    /// [`Self::for_each_leaf_tet`] would list, without listing them.
    pub fn piece_counts(&self) -> (usize, usize) {
        let (mut all, mut drawable) = (0, 0);
        for n in self.nodes.iter() {
            if n.alive() && n.is_leaf() {
                let k = green_piece_count(n.mask);
                all += k;
                if !n.flags.contains(NodeFlags::EMPTY) {
                    drawable += k;
                }
            }
        }
        (all, drawable)
    }

    /// Calls `f` with the id of every red leaf that is not empty and not at the finest level (a
    /// leaf the selector could still split).
    pub fn for_each_splittable_leaf(&self, mut f: impl FnMut(TetId)) {
        let levels = self.forest.levels;
        for n in self.nodes.iter() {
            if n.alive() && n.is_leaf() && !n.flags.contains(NodeFlags::EMPTY) {
                let id = n.id();
                if self.forest.level(id) < levels {
                    f(id);
                }
            }
        }
    }

    /// Calls `f` with every tet of the leaf mesh (red leaves and green pieces), positively oriented.
    pub fn for_each_leaf_tet(&self, mut f: impl FnMut(LeafTet)) {
        for (slot, n) in self.nodes.iter().enumerate() {
            if !n.alive() || !n.is_leaf() {
                continue;
            }
            let nv = self.node_verts(slot);
            let empty = n.flags.contains(NodeFlags::EMPTY);
            let flip = n.flags.contains(NodeFlags::FLIP);
            let mut emit = |v: [u32; 4]| {
                let v = if flip { [v[0], v[1], v[3], v[2]] } else { v };
                f(LeafTet {
                    v,
                    hier: n.id(),
                    green: n.mask != 0,
                    empty,
                })
            };
            if n.mask == 0 {
                emit(nv);
            } else {
                let (mid, mkey) = self.green_mids(n);
                green_split(nv, n.mask, &mid, &mkey, &mut emit);
            }
        }
    }

    /// All tets of the leaf mesh, empty ones included.
    pub fn leaf_tets(&self) -> Vec<LeafTet> {
        let mut out = Vec::with_capacity(self.n_leaves * 2);
        self.for_each_leaf_tet(|t| out.push(t));
        out
    }

    /// The tets of the leaf mesh that lie inside the input domain.
    pub fn drawable_leaf_tets(&self) -> Vec<LeafTet> {
        let mut out = Vec::with_capacity(self.n_leaves * 2);
        self.for_each_leaf_tet(|t| {
            if !t.empty {
                out.push(t)
            }
        });
        out
    }

    /// The drawable leaf mesh with its deepest level merged into their parents, level after level,
    /// until it has at most `most` tets or only base tets are left: what the viewer draws while the
    /// camera moves and whole draws are slow. A merged tet is its ancestor with the ancestor's own
    /// corners (all vertices of the mesh: a refined tet's corners are its children's), so where it
    /// meets a finer tet the mesh has hanging vertices; drawn in motion only, never at rest.
    pub fn coarse_leaf_tets(&self, most: usize) -> Vec<LeafTet> {
        self.coarsened(self.drawable_leaf_tets(), most)
    }

    /// [`Self::coarse_leaf_tets`] from the drawable leaf tets `tets` ([`Self::drawable_leaf_tets`],
    /// already listed for the leaf mesh).
    pub fn coarsened(&self, mut tets: Vec<LeafTet>, most: usize) -> Vec<LeafTet> {
        let level = |id: TetId| self.forest.level(id);
        let mut deepest = tets.iter().map(|t| level(t.hier)).max().unwrap_or(0);
        while tets.len() > most {
            // the deepest level goes to its parents, and the green pieces of the level above
            // (whose marked edges were those children's) to their whole tets; last, the base
            // tets' own green pieces
            let mut whole = Vec::new();
            tets.retain(|t| {
                let l = level(t.hier);
                let into = if deepest > 0 && l >= deepest {
                    self.forest.parent(t.hier)
                } else if t.green && l + 1 >= deepest {
                    Some(t.hier)
                } else {
                    return true;
                };
                whole.extend(into);
                false
            });
            whole.sort_unstable();
            whole.dedup();
            for id in whole {
                let Some(slot) = self.slot_of(id) else {
                    continue;
                };
                let Some(n) = self.nodes.get(slot) else {
                    continue;
                };
                if n.flags.contains(NodeFlags::EMPTY) {
                    continue;
                }
                let v = self.node_verts(slot);
                let v = if n.flags.contains(NodeFlags::FLIP) {
                    [v[0], v[1], v[3], v[2]]
                } else {
                    v
                };
                tets.push(LeafTet {
                    v,
                    hier: id,
                    green: false,
                    empty: false,
                });
            }
            if deepest == 0 {
                break;
            }
            deepest -= 1;
        }
        tets
    }

    /// Midpoint slots and keys of the marked edges of leaf `n` (greens are few).
    fn green_mids(&self, n: &Node) -> ([u32; 6], [u64; 6]) {
        let mut mid = [NONE; 6];
        let mut mkey = [u64::MAX; 6];
        let lt = self.lattice_of(n.id());
        for e in 0..6 {
            if n.mask & (1 << e) != 0 {
                let m = self.slot_at(lt.base, &lt.edge_midpoint(e));
                assert!(m != NONE, "marked edge without midpoint");
                mid[e] = m;
                mkey[e] = self.vkey[m as usize];
            }
        }
        (mid, mkey)
    }
}
