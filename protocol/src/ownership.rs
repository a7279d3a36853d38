//! Which edges a tet owns, derived from the hierarchy alone.
//!
//! The contract (docs/protocol.md) gives each new vertex one owner: the lowest id among the tets of its
//! level that contain the vertex's edge. Because the children of tet `t` are `n + 8t + i`, a lower
//! parent always has lower children, and ownership follows down the forest from two facts about
//! each tet `P`:
//! - `owned` (6 bits): `P` is the lowest tet of its level around its local edge `e`;
//! - `faces` (4 bits): `P` is lower than the tet across its local face `f` (or has none).
//!
//! A child edge that halves a parent edge `e` is contained only in children of tets around `e`: the
//! children of `P` own it iff `P` owns `e`. A child edge inside a parent face `f` is shared with the
//! children of the tet across `f`: `P`'s children own it iff `P` wins face `f`. A child edge inside
//! `P` is `P`'s children's alone. In each case the owner among `P`'s children is the lowest child
//! index that has the edge. Child faces on a parent face inherit the parent's face bit; a face
//! between two siblings is won by the lower index.
//!
//! So the owned masks of every node follow from the base mesh's adjacency, and the stream need not
//! carry them (a coded block sends only where a store disagrees, see [`crate::block`]).

use crate::hierarchy::{Forest, TetId, BEY_CHILDREN, BEY_SPLIT, EDGES, FACES};
use crate::BaseMesh;
use std::collections::HashMap;

/// Where a split edge or a child face lies in its parent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Site {
    /// On the parent's local edge.
    Edge(u8),
    /// On the parent's local face (opposite the given vertex).
    Face(u8),
    /// Strictly inside the parent; for a face, the sibling on its other side.
    Inside(u8),
}

/// Parent vertices a split point (`0..4` corners, `4..10` edge midpoints) lies on.
const fn support(p: usize) -> u8 {
    if p < 4 {
        1 << p
    } else {
        (1 << EDGES[p - 4].0) | (1 << EDGES[p - 4].1)
    }
}

const fn site_of(sup: u8) -> Site {
    match sup.count_ones() {
        2 => {
            let mut e = 0;
            while e < 6 {
                if (1 << EDGES[e].0) | (1 << EDGES[e].1) == sup {
                    return Site::Edge(e as u8);
                }
                e += 1;
            }
            panic!("an edge's support is one of the 6 edges")
        }
        3 => Site::Face((!sup & 0xf).trailing_zeros() as u8),
        _ => Site::Inside(0),
    }
}

/// Per child and local edge: whether the child owns the edge when its parent's condition holds
/// (it is the lowest child with the edge), and that condition's site.
const CHILD_EDGES: [[(bool, Site); 6]; 8] = {
    let mut out = [[(false, Site::Inside(0)); 6]; 8];
    let mut c = 0;
    while c < 8 {
        let mut e = 0;
        while e < 6 {
            let s = BEY_SPLIT.child_edges[c][e];
            let (a, b) = BEY_SPLIT.edges[s];
            out[c][e] = (
                BEY_SPLIT.first_child[s].0 == c,
                site_of(support(a) | support(b)),
            );
            e += 1;
        }
        c += 1;
    }
    out
};

/// Per child and local face: the parent face it lies on, or the sibling across it.
const CHILD_FACES: [[Site; 4]; 8] = {
    let mut out = [[Site::Inside(0); 4]; 8];
    let mut c = 0;
    while c < 8 {
        let mut f = 0;
        while f < 4 {
            let pts = [
                BEY_CHILDREN[c][FACES[f][0]],
                BEY_CHILDREN[c][FACES[f][1]],
                BEY_CHILDREN[c][FACES[f][2]],
            ];
            let sup = support(pts[0]) | support(pts[1]) | support(pts[2]);
            out[c][f] = match site_of(sup) {
                Site::Face(pf) => Site::Face(pf),
                _ => Site::Inside(sibling_with(c, pts) as u8),
            };
            f += 1;
        }
        c += 1;
    }
    out
};

/// The other child that has the three split points `pts` as a face.
const fn sibling_with(c: usize, pts: [usize; 3]) -> usize {
    let mut s = 0;
    while s < 8 {
        if s != c {
            let mut hits = 0;
            let mut j = 0;
            while j < 4 {
                let p = BEY_CHILDREN[s][j];
                if p == pts[0] || p == pts[1] || p == pts[2] {
                    hits += 1;
                }
                j += 1;
            }
            if hits == 3 {
                return s;
            }
        }
        s += 1;
    }
    panic!("an interior child face is shared by two children")
}

/// A tet's ownership state: owned-edge mask (6 bits) and won faces (4 bits).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TetOwnership {
    pub owned: u8,
    pub faces: u8,
}

impl TetOwnership {
    /// Child `c`'s state.
    pub fn child(self, c: usize) -> TetOwnership {
        let mut owned = 0;
        for (e, &(first, site)) in CHILD_EDGES[c].iter().enumerate() {
            let cond = match site {
                Site::Edge(pe) => self.owned >> pe & 1 == 1,
                Site::Face(pf) => self.faces >> pf & 1 == 1,
                Site::Inside(_) => true,
            };
            if first && cond {
                owned |= 1 << e;
            }
        }
        let mut faces = 0;
        for (f, &site) in CHILD_FACES[c].iter().enumerate() {
            let win = match site {
                Site::Face(pf) => self.faces >> pf & 1 == 1,
                Site::Inside(s) => c < s as usize,
                Site::Edge(_) => unreachable!("a face is never on an edge"),
            };
            if win {
                faces |= 1 << f;
            }
        }
        TetOwnership { owned, faces }
    }
}

/// [`TetOwnership::child`] as a table: per child index and parent state (`owned | faces << 6`),
/// the child's state in the same packing.
fn child_table() -> &'static [[u16; 1024]; 8] {
    static T: std::sync::OnceLock<Box<[[u16; 1024]; 8]>> = std::sync::OnceLock::new();
    T.get_or_init(|| {
        let mut t = Box::new([[0u16; 1024]; 8]);
        for (c, row) in t.iter_mut().enumerate() {
            for (p, out) in row.iter_mut().enumerate() {
                let parent = TetOwnership {
                    owned: (p & 0x3f) as u8,
                    faces: (p >> 6) as u8,
                };
                let s = parent.child(c);
                *out = s.owned as u16 | (s.faces as u16) << 6;
            }
        }
        t
    })
}

/// Ownership of every node of a forest, from its base mesh.
#[derive(Debug, Clone)]
pub struct Ownership {
    forest: Forest,
    base: Vec<TetOwnership>,
}

impl Ownership {
    /// Base tets' states from the base mesh's adjacency (by vertex index).
    pub fn new(base: &BaseMesh) -> Self {
        let mut edge_min: HashMap<(u32, u32), usize> = HashMap::new();
        let mut face_tets: HashMap<[u32; 3], (usize, usize)> = HashMap::new();
        for (t, v) in base.tets.iter().enumerate() {
            for (a, b) in EDGES {
                let k = (v[a].min(v[b]), v[a].max(v[b]));
                edge_min.entry(k).or_insert(t);
            }
            for f in FACES {
                let mut k = [v[f[0]], v[f[1]], v[f[2]]];
                k.sort_unstable();
                face_tets
                    .entry(k)
                    .and_modify(|e| e.1 = e.1.min(t))
                    .or_insert((t, usize::MAX));
            }
        }
        let forest = base.forest();
        let states = base
            .tets
            .iter()
            .enumerate()
            .map(|(t, v)| {
                let mut s = TetOwnership::default();
                for (e, (a, b)) in EDGES.into_iter().enumerate() {
                    if edge_min[&(v[a].min(v[b]), v[a].max(v[b]))] == t {
                        s.owned |= 1 << e;
                    }
                }
                for (f, fv) in FACES.into_iter().enumerate() {
                    let mut k = [v[fv[0]], v[fv[1]], v[fv[2]]];
                    k.sort_unstable();
                    let (first, second) = face_tets[&k];
                    // the two tets sharing the face, in id order (second is MAX on the boundary)
                    let other = if first == t { second } else { first };
                    if other > t {
                        s.faces |= 1 << f;
                    }
                }
                s
            })
            .collect();
        Ownership {
            forest,
            base: states,
        }
    }

    /// The state of tet `id` (which must be in the forest): one table lookup per level.
    pub fn of(&self, id: TetId) -> TetOwnership {
        let k = self.forest.level(id);
        let local = id - self.forest.level_start(k);
        let s = self.base[(local >> (3 * k as u32)) as usize];
        let table = child_table();
        let mut state = s.owned as usize | (s.faces as usize) << 6;
        for j in 0..k {
            let c = ((local >> (3 * (k - 1 - j) as u32)) & 7) as usize;
            state = table[c][state] as usize;
        }
        TetOwnership {
            owned: (state & 0x3f) as u8,
            faces: (state >> 6) as u8,
        }
    }

    /// The owned-edge mask of node `id`.
    pub fn owned(&self, id: TetId) -> u8 {
        self.of(id).owned
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shapes::{box5, box6, kuhn_grid};
    use crate::testing::{detail_nodes, unsampled_base};

    fn check(shape: crate::shapes::PointsAndTets, levels: u8) {
        let (base, nodes) = detail_nodes(unsampled_base(levels, shape), |p| p[0] as f32);
        let own = Ownership::new(&base);
        for n in &nodes {
            assert_eq!(own.owned(n.id), n.owned, "node {}", n.id);
        }
    }

    #[test]
    fn derived_masks_are_the_reference_analysis_masks() {
        check(box6([0.0; 3], [1.0; 3]), 3);
        check(box5([0.0; 3], [1.0, 2.0, 3.0]), 3);
        // a non-convex base with vertex indices in an irregular order
        check(kuhn_grid(2, |i, j, k| i + j + k != 3), 2);
    }

    #[test]
    fn every_child_face_on_a_parent_face_or_a_sibling() {
        for (c, faces) in CHILD_FACES.iter().enumerate() {
            for site in faces {
                if let Site::Inside(s) = *site {
                    // the sibling sees the same face, with this child across it
                    assert!(CHILD_FACES[s as usize].contains(&Site::Inside(c as u8)));
                }
            }
        }
    }
}
