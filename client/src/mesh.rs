//! The adaptive mesh: red/green refinement over the semi-regular hierarchy, always conforming.
//!
//! # State
//! The state is the set `R` of red-refined hierarchy tets, closed under parent. Hierarchy *leaves* are
//! the base tets not in `R` and the children of tets in `R` that are not in `R`. Each leaf is drawn
//! either as itself or, when some of its edges carry a present midpoint, as its *green closure*.
//!
//! Storage is arrays + u32 indices + free lists, no pointer graph:
//! - **nodes**: one [`Node`] per tet of `R` ∪ leaves. Base tets occupy slots `0..n`; the 8 children
//!   of a refined tet occupy one contiguous block of 8 slots (`children` = first slot), recycled
//!   through a free list of blocks. A node (12 bytes) keeps its id, its first child slot, flags,
//!   and for a leaf its green pattern (the marked-edge mask; the midpoints are looked up when the
//!   greens are listed). Vertex slots are kept per block: the parent's 4 corners and 6 edge
//!   midpoints (40 bytes for 8 children; a child's 4 vertices are 4 of these, [`BEY_CHILDREN`]),
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
//! A midpoint's value is `synthesize(d, predict(f(u), f(v)))` with `d` its coefficient from the
//! [`DetailBuffer`], or 0 (linear prediction, the thesis' fallback) while it has not arrived. When
//! coefficients arrive ([`AdaptiveMesh::apply_arrivals`]) the present vertices that own them are
//! recomputed in place; if any of those has dependants (present vertices predicted from it), the
//! present vertices are re-synthesized level by level from the lowest changed level up, each one whose
//! edge endpoint changed being recomputed (one pass over the present vertices per batch).
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
//!
//! # Green splits
//! Built so that the split of every face depends only on that face: a face with 3 marked edges is cut
//! into Bey's 4 triangles (the pattern "3 edges of one face" cones them to the opposite vertex);
//! otherwise the tet is bisected at its marked edge whose midpoint has the smallest key, and each half
//! recursively at its remaining marked edge. On a face with two marked edges this draws the segment
//! from the smaller-key midpoint to the opposite corner and joins the two midpoints. All pieces are
//! made by replacing vertices of the (positively oriented) tet by points of the same edges, which keeps
//! the orientation.

use crate::detail_buffer::{Arrivals, DetailBuffer};
/// Re-exported for the selector's per-slot arrays (its home is [`crate::seg_vec`]).
pub(crate) use crate::seg_vec::SegVec;
use rustc_hash::FxHashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::OnceLock;
use tetwave_protocol::base::signed_volume;
use tetwave_protocol::hierarchy::{midpoint, Bary, Lattice, BEY_CHILDREN, EDGES, FACES};
use tetwave_protocol::wavelet::{predict, synthesize};
use tetwave_protocol::{BaseMesh, Forest, LatticeTet, TetId, VertexKeys};

const NONE: u32 = u32::MAX;
const ALIVE: u8 = 1;
const EMPTY: u8 = 2;
const FLIP: u8 = 4;
/// On the closure's worklist (see `AdaptiveMesh::queue`).
const QUEUED: u8 = 8;
/// Seen while a merge batch gathers its candidates (cleared before it returns).
const BATCHED: u8 = 16;
/// Owners remembered per vertex ([`AdaptiveMesh::vowner`]).
const OWNERS: usize = 2;

/// Edges of the face opposite vertex `d` (the edges not touching `d`), as a mask over [`EDGES`].
const FACE_MASK: [u8; 4] = face_masks();
/// Edges touching vertex `v`, as a mask over [`EDGES`].
const VERTEX_MASK: [u8; 4] = vertex_masks();

const fn face_masks() -> [u8; 4] {
    let mut out = [0u8; 4];
    let mut d = 0;
    while d < 4 {
        let mut e = 0;
        while e < 6 {
            if EDGES[e].0 != d && EDGES[e].1 != d {
                out[d] |= 1 << e;
            }
            e += 1;
        }
        d += 1;
    }
    out
}

const fn vertex_masks() -> [u8; 4] {
    let mut out = [0u8; 4];
    let mut e = 0;
    while e < 6 {
        out[EDGES[e].0] |= 1 << e;
        out[EDGES[e].1] |= 1 << e;
        e += 1;
    }
    out
}

#[inline]
fn edge_index(a: usize, b: usize) -> usize {
    let (a, b) = if a < b { (a, b) } else { (b, a) };
    match (a, b) {
        (0, 1) => 0,
        (0, 2) => 1,
        (0, 3) => 2,
        (1, 2) => 3,
        (1, 3) => 4,
        _ => 5,
    }
}

/// Whether a marked-edge mask has a green closure.
#[inline]
pub fn green_pattern_ok(mask: u8) -> bool {
    match mask.count_ones() {
        0..=2 => true,
        3 => FACE_MASK.contains(&mask),
        _ => false,
    }
}

/// Per Bey child: the matrix whose column `j` holds the parent barycentrics of child vertex `j`.
fn child_matrix(c: &[usize; 4]) -> [[f64; 4]; 4] {
    let mut m = [[0f64; 4]; 4];
    for (j, &p) in c.iter().enumerate() {
        if p < 4 {
            m[p][j] = 1.0;
        } else {
            let (a, b) = EDGES[p - 4];
            m[a][j] = 0.5;
            m[b][j] = 0.5;
        }
    }
    m
}

/// Per Bey child: whether it is mirrored w.r.t. its parent.
fn child_flips() -> &'static [bool; 8] {
    static CELL: OnceLock<[bool; 8]> = OnceLock::new();
    CELL.get_or_init(|| std::array::from_fn(|i| det4(&child_matrix(&BEY_CHILDREN[i])) < 0.0))
}

/// Per Bey child: the integer matrix taking barycentric coordinates w.r.t. the parent to those
/// w.r.t. the child (both scaled to the same sum); [`child_weights`] is its closed form.
#[cfg(test)]
fn to_child_maps() -> [[[i64; 4]; 4]; 8] {
    std::array::from_fn(|i| {
        let inv = invert4(&child_matrix(&BEY_CHILDREN[i]));
        inv.map(|row| {
            row.map(|x| {
                assert!((x - x.round()).abs() < 1e-9, "Bey child map not integral");
                x.round() as i64
            })
        })
    })
}

/// Barycentric weights of a point w.r.t. each Bey child, from its nonnegative weights `lam`
/// w.r.t. the parent (`to_child_maps` applied, in closed form: every row is one of
/// `2λ_j`, `a_j = 2λ_j − Σλ`, `b = λ0 + λ1 − λ2 − λ3`, `c = λ0 − λ1 − λ2 + λ3` or a negation),
/// and the mask of the children that hold the point (all weights ≥ 0). Point location's inner
/// loop: 6 sums instead of up to 128 products.
#[inline]
fn child_weights(lam: [i64; 4]) -> ([[i64; 4]; 8], u8) {
    let [l0, l1, l2, l3] = lam;
    let s = l0 + l1 + l2 + l3;
    let (d0, d1, d2, d3) = (2 * l0, 2 * l1, 2 * l2, 2 * l3);
    let (a0, a1, a2, a3) = (d0 - s, d1 - s, d2 - s, d3 - s);
    let b = l0 + l1 - l2 - l3;
    let c = l0 - l1 - l2 + l3;
    let mu = [
        [a0, d1, d2, d3],
        [d0, a1, d2, d3],
        [d0, d1, a2, d3],
        [d0, d1, d2, a3],
        [b, d2, c, -a0],
        [b, -a1, -c, d3],
        [-a3, c, d1, -b],
        [d0, -c, -a2, -b],
    ];
    // with `lam ≥ 0` every `2λ_j` is too, so only the other weights decide
    debug_assert!(lam.iter().all(|&l| l >= 0), "{lam:?}");
    let holds = (a0 >= 0) as u8
        | ((a1 >= 0) as u8) << 1
        | ((a2 >= 0) as u8) << 2
        | ((a3 >= 0) as u8) << 3
        | ((b >= 0 && c >= 0 && a0 <= 0) as u8) << 4
        | ((b >= 0 && a1 <= 0 && c <= 0) as u8) << 5
        | ((a3 <= 0 && c >= 0 && b <= 0) as u8) << 6
        | ((c <= 0 && a2 <= 0 && b <= 0) as u8) << 7;
    (mu, holds)
}

#[allow(clippy::needless_range_loop)] // small dense linear algebra reads best indexed
fn det4(m: &[[f64; 4]; 4]) -> f64 {
    let mut a = *m;
    let mut det = 1.0;
    for c in 0..4 {
        let p = (c..4)
            .max_by(|&x, &y| a[x][c].abs().total_cmp(&a[y][c].abs()))
            .unwrap();
        if a[p][c] == 0.0 {
            return 0.0;
        }
        if p != c {
            a.swap(p, c);
            det = -det;
        }
        det *= a[c][c];
        for r in c + 1..4 {
            let f = a[r][c] / a[c][c];
            for k in c..4 {
                a[r][k] -= f * a[c][k];
            }
        }
    }
    det
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
fn invert4(m: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    let mut a = *m;
    let mut inv = [[0f64; 4]; 4];
    for (i, row) in inv.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for c in 0..4 {
        let p = (c..4)
            .max_by(|&x, &y| a[x][c].abs().total_cmp(&a[y][c].abs()))
            .unwrap();
        a.swap(p, c);
        inv.swap(p, c);
        let d = a[c][c];
        for k in 0..4 {
            a[c][k] /= d;
            inv[c][k] /= d;
        }
        for r in 0..4 {
            if r != c {
                let f = a[r][c];
                for k in 0..4 {
                    a[r][k] -= f * a[c][k];
                    inv[r][k] -= f * inv[c][k];
                }
            }
        }
    }
    inv
}

/// Makes room for `extra` more items growing by 1/8 (not doubling): the mesh's arrays are its
/// memory, and doubling would leave up to half of them unused.
#[inline]
fn grow<T>(v: &mut Vec<T>, extra: usize) {
    if v.len() + extra > v.capacity() {
        v.reserve_exact((v.capacity() / 8).max(extra).max(64));
    }
}

/// Keys per page of [`KeySlots`].
const KEY_PAGE_BITS: u32 = 4;
const KEY_PAGE: usize = 1 << KEY_PAGE_BITS;

/// Vertex slot by vertex key (`NONE`: absent), in pages of [`KEY_PAGE`] keys made on first use and
/// recycled when emptied. A view-dependent mesh holds a few of the hierarchy's keys, scattered:
/// a dense table sized for every key took 27.6 B per leaf on a level-6 run at 20% (0.92 MB), pages
/// of 16 about 4 B plus 0.25 B per key for the directory. No operation moves the table (pages sit
/// in a [`SegVec`]), so it never stalls a frame the way a growing hash map's rehash would.
#[derive(Clone, Debug)]
struct KeySlots {
    /// Page index by key / [`KEY_PAGE`] (`NONE`: no page); sized once for every key.
    dir: Vec<u32>,
    pages: SegVec<[u32; KEY_PAGE]>,
    /// Present keys per page.
    fill: SegVec<u8>,
    free: Vec<u32>,
}

impl KeySlots {
    fn new(nkeys: usize) -> Self {
        KeySlots {
            dir: vec![NONE; nkeys.div_ceil(KEY_PAGE)],
            pages: SegVec::new(),
            fill: SegVec::new(),
            free: Vec::new(),
        }
    }

    #[inline]
    fn get(&self, key: u64) -> u32 {
        match self.dir[(key >> KEY_PAGE_BITS) as usize] {
            NONE => NONE,
            p => self.pages[p as usize][key as usize & (KEY_PAGE - 1)],
        }
    }

    /// Maps absent key `key` to `slot`.
    fn insert(&mut self, key: u64, slot: u32) {
        let d = (key >> KEY_PAGE_BITS) as usize;
        let p = match self.dir[d] {
            NONE => {
                let p = match self.free.pop() {
                    Some(p) => p,
                    None => {
                        self.pages.push([NONE; KEY_PAGE]);
                        self.fill.push(0);
                        (self.pages.len() - 1) as u32
                    }
                };
                self.dir[d] = p;
                p
            }
            p => p,
        } as usize;
        let e = &mut self.pages[p][key as usize & (KEY_PAGE - 1)];
        debug_assert_eq!(*e, NONE, "key {key} mapped twice");
        *e = slot;
        self.fill[p] += 1;
    }

    /// Unmaps present key `key`.
    fn remove(&mut self, key: u64) {
        let d = (key >> KEY_PAGE_BITS) as usize;
        let p = self.dir[d] as usize;
        let e = &mut self.pages[p][key as usize & (KEY_PAGE - 1)];
        debug_assert_ne!(*e, NONE, "key {key} not mapped");
        *e = NONE;
        self.fill[p] -= 1;
        if self.fill[p] == 0 {
            self.dir[d] = NONE;
            self.free.push(p as u32);
        }
    }

    /// Keys mapped.
    fn count(&self) -> usize {
        self.fill.iter().map(|&f| f as usize).sum()
    }

    fn bytes(&self) -> usize {
        self.dir.capacity() * 4 + self.pages.bytes() + self.fill.bytes() + self.free.capacity() * 4
    }
}

/// The green closure of a tet `v` (in an orientation-consistent vertex order) with marked-edge mask
/// `mask`: calls `out` with each piece, all in the orientation of `v`. `mid[e]` is the midpoint of
/// local edge `e` (read only for marked edges), `mkey[e]` its vertex key.
pub fn green_split<P: Copy>(
    v: [P; 4],
    mask: u8,
    mid: &[P; 6],
    mkey: &[u64; 6],
    out: &mut impl FnMut([P; 4]),
) {
    if mask == 0 {
        out(v);
        return;
    }
    if mask.count_ones() == 3 {
        let d = FACE_MASK
            .iter()
            .position(|&m| m == mask)
            .expect("3 marked edges not on one face: not a green pattern");
        let [a, b, c] = FACES[d];
        let (mab, mac, mbc) = (
            mid[edge_index(a, b)],
            mid[edge_index(a, c)],
            mid[edge_index(b, c)],
        );
        let mut t = v;
        t[b] = mab;
        t[c] = mac;
        out(t);
        let mut t = v;
        t[a] = mab;
        t[c] = mbc;
        out(t);
        let mut t = v;
        t[a] = mac;
        t[b] = mbc;
        out(t);
        let mut t = v;
        t[a] = mbc;
        t[b] = mac;
        t[c] = mab;
        out(t);
        return;
    }
    debug_assert!(mask.count_ones() <= 2);
    let mut e = 6;
    for i in 0..6 {
        if mask & (1 << i) != 0 && (e == 6 || mkey[i] < mkey[e]) {
            e = i;
        }
    }
    let (a, b) = EDGES[e];
    let rest = mask & !(1 << e);
    let mut t = v;
    t[a] = mid[e];
    green_split(t, rest & !VERTEX_MASK[a], mid, mkey, out);
    let mut t = v;
    t[b] = mid[e];
    green_split(t, rest & !VERTEX_MASK[b], mid, mkey, out);
}

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
type Witness = [(u32, u32); 4];

/// Why the last merge attempt of a refined tet was refused, kept by its slot. Only
/// `AdaptiveMesh::unrefine` makes a refined tet a leaf or frees a slot, and it drops the record:
/// a record's slot holds the tet it was made for (the conformity check verifies it).
#[derive(Debug, Clone, Copy)]
struct Refusal {
    wit: Witness,
}

const UNKNOWN: u32 = u32::MAX - 1;

/// One node of the red tree (see the module docs): 12 bytes. Its id is split in a low word and a
/// high byte ([`MAX_TETS`]): with a 64-bit id the node took 16 bytes, and the mesh 4 more per
/// slot.
#[derive(Debug, Clone, Copy)]
struct Node {
    id_lo: u32,
    children: u32,
    id_hi: u8,
    /// Marked edges of a leaf (its green pattern); 0 for refined nodes.
    mask: u8,
    flags: u8,
    /// Refined children (0 for a leaf): a refined node with none has 8 leaf children.
    nref: u8,
}

const _: () = assert!(std::mem::size_of::<Node>() == 12);

/// Tets a hierarchy may have (all levels) for [`AdaptiveMesh::new`]: a node keeps 40 bits of id.
pub const MAX_TETS: u64 = 1 << 40;

impl Node {
    const DEAD: Node = Node::new(0, NONE, 0, 0);

    #[inline(always)]
    const fn new(id: TetId, children: u32, mask: u8, flags: u8) -> Node {
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
    fn id(&self) -> TetId {
        self.id_lo as TetId | (self.id_hi as TetId) << 32
    }

    #[inline]
    fn is_leaf(&self) -> bool {
        self.children == NONE
    }
    #[inline]
    fn alive(&self) -> bool {
        self.flags & ALIVE != 0
    }
}

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

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MeshError {
    #[error("tet {0} is not in the mesh (an ancestor is a leaf)")]
    NotInMesh(TetId),
    #[error("tet {0} is already refined")]
    NotLeaf(TetId),
    #[error("tet {0} is at the finest level")]
    Finest(TetId),
    #[error("tet {0} is empty (outside the domain) and is not refined on request")]
    Empty(TetId),
    #[error("tet {0} is not refined")]
    NotRefined(TetId),
    #[error("tet {0}: some children are refined")]
    ChildrenRefined(TetId),
    #[error("coarsening tet {0} refused: the closure would refine it again")]
    Forced(TetId),
    #[error("green closure did not settle within {0} refinements")]
    ClosureBound(usize),
    #[error("the hierarchy has {0} vertex keys: the adaptive mesh holds at most 2^32 - 1")]
    TooManyKeys(u64),
    #[error("the hierarchy has {0} tets: the adaptive mesh holds at most 2^40")]
    TooManyTets(u64),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConformityError {
    #[error("node {id}: vertex {local} has slot {slot} with key {have:?}, lattice key {want}")]
    VertexMismatch {
        id: TetId,
        local: usize,
        slot: u32,
        have: Option<u64>,
        want: u64,
    },
    #[error("leaf {id}: green pattern {mask:#04x} stored, {want:#04x} computed")]
    StaleGreen { id: TetId, mask: u8, want: u8 },
    #[error("leaf {id} is forced (pattern {mask:#04x}) but not refined")]
    NotClosed { id: TetId, mask: u8 },
    #[error("leaf {id}: piece of volume {volume} ≤ 0")]
    NonPositive { id: TetId, volume: f64 },
    #[error("face {face:?} used {count} times (boundary: {boundary})")]
    Face {
        face: [u64; 3],
        count: u32,
        boundary: bool,
    },
    #[error("vertex {key} (slot {slot}) is present but no leaf uses it")]
    Unused { key: u64, slot: u32 },
    #[error("vertex {key}: reference count {have}, {want} refined tets create it")]
    RefCount { key: u64, have: u32, want: u32 },
    #[error("leaf volumes sum to {sum}, the domain's volume is {domain}")]
    Volume { sum: f64, domain: f64 },
    #[error("{0}")]
    Other(String),
}

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
    /// parent's 4 corners and 6 edge midpoints ([`BEY_CHILDREN`]'s points), from which
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
}

/// A node slot whose structure changed: split (`block` = its new children), merged (`block` = its
/// former children, now free), or whose `empty` flag flipped (`block` = its children or `u32::MAX`).
/// The slots whose selection status may have changed are `slot`, the 8 slots of `block` and the
/// slot of the parent of the node in `slot` (if the node that changed has gone since, so has its
/// parent's split, which is recorded too).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SlotChange {
    pub slot: u32,
    pub block: u32,
}

/// Most [`SlotChange`]s kept unread (beyond, the log restarts and a reader rescans).
const MAX_CHANGES: usize = 1 << 16;

static NEXT_UID: AtomicU64 = AtomicU64::new(1);

#[derive(Debug)]
struct MeshUid(u64);

impl MeshUid {
    fn new() -> Self {
        MeshUid(NEXT_UID.fetch_add(1, Ordering::Relaxed))
    }
}

impl Clone for MeshUid {
    fn clone(&self) -> Self {
        MeshUid::new()
    }
}

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

/// Number of leaf-mesh pieces a leaf with green pattern `mask` is drawn as.
#[inline]
pub fn green_piece_count(mask: u8) -> usize {
    match mask.count_ones() {
        0 => 1,
        1 => 2,
        2 => {
            if mask == 0b100001 || mask == 0b010010 || mask == 0b001100 {
                4
            } else {
                3
            }
        }
        _ => 4,
    }
}

impl AdaptiveMesh {
    /// The coarsest mesh: the base tets as leaves. `base` must pass [`BaseMesh::validate`]; a
    /// hierarchy with 2^32 vertex keys or more, or [`MAX_TETS`] tets or more, is refused (the mesh
    /// packs keys in 32 bits and ids in 40).
    pub fn new(base: &BaseMesh) -> Result<Self, MeshError> {
        let forest = base.forest();
        if forest.total_tets() >= MAX_TETS {
            return Err(MeshError::TooManyTets(forest.total_tets()));
        }
        let keys = base.vertex_keys();
        let nkeys = keys.vertex_count();
        if nkeys >= NONE as u64 {
            return Err(MeshError::TooManyKeys(nkeys));
        }
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
            let mut flags = ALIVE;
            if vol < 0.0 {
                flags |= FLIP;
            }
            if base.empty[t] {
                flags |= EMPTY;
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
        };
        for g in 0..nv {
            let p = base.positions[g];
            m.vkey.push(g as u64);
            m.vpos.push([p[0] as f32, p[1] as f32, p[2] as f32]);
            m.vval.push(base.values[g]);
            m.vends.push([NONE; 2]);
            m.vref.push(u32::MAX);
            m.vlevel.push(0);
            m.vdeps.push(0);
            m.vowner.push([NONE; OWNERS]);
        }
        m.n_vertices = nv;
        m.by_key = KeySlots::new(nkeys as usize);
        for g in 0..nv {
            m.by_key.insert(g as u64, g as u32);
        }
        Ok(m)
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

    // ---------------------------------------------------------------- selection view

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
    pub fn prefetch_node(&self, slot: usize) {
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
    fn block_of(&self, slot: usize) -> usize {
        (slot - self.base_tets.len()) >> 3
    }

    /// The 10 points of the block whose first slot is `block`.
    #[inline]
    fn block_points(&self, block: u32) -> &[u32; 10] {
        &self.bverts[self.block_of(block as usize)]
    }

    #[inline]
    fn red_view(&self, slot: u32, n: &Node) -> RedNode {
        let leaf = n.is_leaf();
        RedNode {
            id: n.id(),
            slot,
            leaf,
            empty: n.flags & EMPTY != 0,
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

    /// Identity of this mesh object: unique per process, a clone gets a new one.
    pub fn uid(&self) -> u64 {
        self.uid.0
    }

    /// Sequence number after the last recorded [`SlotChange`].
    pub fn change_seq(&self) -> u64 {
        self.changes_start + self.changes.len() as u64
    }

    /// The structural changes since sequence number `seq` (from [`Self::change_seq`]); `None` when
    /// some of them were dropped (the log is bounded: read and [`Self::trim_changes`] it often).
    pub fn changes_since(&self, seq: u64) -> Option<&[SlotChange]> {
        let i = seq.checked_sub(self.changes_start)? as usize;
        self.changes.get(i..)
    }

    /// Forgets the changes before sequence number `seq`.
    pub fn trim_changes(&mut self, seq: u64) {
        if seq >= self.change_seq() {
            self.changes_start = self.change_seq();
            self.changes.clear();
        } else if seq > self.changes_start {
            self.changes.drain(..(seq - self.changes_start) as usize);
            self.changes_start = seq;
        }
    }

    #[inline]
    fn log_change(&mut self, slot: u32, block: u32) {
        if self.changes.len() >= MAX_CHANGES {
            self.changes_start += self.changes.len() as u64;
            self.changes.clear();
        }
        self.changes.push(SlotChange { slot, block });
    }

    /// The node of hierarchy tet `id`, if it is in the red tree.
    pub fn red_node_of(&self, id: TetId) -> Option<RedNode> {
        self.find(id)
            .map(|s| self.red_view(s, &self.nodes[s as usize]))
    }

    /// Red splits and merges done so far, closure refinements included. Each split removes one leaf
    /// and creates 8; each merge the reverse.
    pub fn op_counts(&self) -> (u64, u64) {
        (self.n_splits, self.n_merges)
    }

    /// Pieces of the leaf mesh (red leaves and green pieces): `(all, drawable)`; the counts
    /// [`Self::for_each_leaf_tet`] would list, without listing them.
    pub fn piece_counts(&self) -> (usize, usize) {
        let (mut all, mut drawable) = (0, 0);
        for n in self.nodes.iter() {
            if n.alive() && n.is_leaf() {
                let k = green_piece_count(n.mask);
                all += k;
                if n.flags & EMPTY == 0 {
                    drawable += k;
                }
            }
        }
        (all, drawable)
    }

    // ---------------------------------------------------------------- lookups

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
    fn find(&self, id: TetId) -> Option<u32> {
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
            .is_some_and(|s| self.nodes[s as usize].flags & EMPTY != 0)
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

    /// Number of present vertices.
    pub fn vertex_count(&self) -> usize {
        self.n_vertices
    }

    /// Length of the vertex slot arrays (present and free slots).
    pub fn vertex_slot_len(&self) -> usize {
        self.vkey.len()
    }

    /// Slots of the present vertices.
    pub fn vertex_slots(&self) -> impl Iterator<Item = u32> + '_ {
        (0..self.vkey.len() as u32).filter(|&s| self.vref[s as usize] != 0)
    }

    /// Slot of the present vertex with key `key`.
    pub fn slot_of_key(&self, key: u64) -> Option<u32> {
        if key < self.keys.base_vertex_count() {
            return Some(key as u32);
        }
        (key < self.keys.vertex_count())
            .then(|| self.by_key.get(key))
            .filter(|&s| s != NONE)
    }

    pub fn vertex_key(&self, slot: u32) -> u64 {
        self.vkey[slot as usize]
    }
    pub fn vertex_value(&self, slot: u32) -> f32 {
        self.vval[slot as usize]
    }
    pub fn vertex_position(&self, slot: u32) -> [f32; 3] {
        self.vpos[slot as usize]
    }
    /// The edge endpoints a midpoint vertex is predicted from; `None` for base vertices.
    pub fn vertex_ends(&self, slot: u32) -> Option<[u32; 2]> {
        let e = self.vends[slot as usize];
        (e[0] != NONE).then_some(e)
    }
    /// Level at which a vertex appears (0 for base vertices).
    pub fn vertex_level(&self, slot: u32) -> u8 {
        self.vlevel[slot as usize]
    }
    /// Position array by slot (free slots hold stale data).
    pub fn positions(&self) -> &[[f32; 3]] {
        &self.vpos
    }
    /// Value array by slot (free slots hold stale data).
    pub fn values(&self) -> &[f32] {
        &self.vval
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
                    + self.vowner.bytes()
                    + self.free_vertices.capacity() * 4,
            ),
            ("keys", self.by_key.bytes()),
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

    // ---------------------------------------------------------------- leaf mesh

    /// Calls `f` with every tet of the leaf mesh (red leaves and green pieces), positively oriented.
    pub fn for_each_leaf_tet(&self, mut f: impl FnMut(LeafTet)) {
        for (slot, n) in self.nodes.iter().enumerate() {
            if !n.alive() || !n.is_leaf() {
                continue;
            }
            let nv = self.node_verts(slot);
            let empty = n.flags & EMPTY != 0;
            let flip = n.flags & FLIP != 0;
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

    // ---------------------------------------------------------------- closure

    /// Slot of the present vertex at lattice point `w` of base tet `b` (`NONE`: absent).
    #[inline]
    fn slot_at(&self, b: u32, w: &Bary) -> u32 {
        self.by_key.get(self.keys.key(b, w))
    }

    /// Slots of the present midpoints of the 6 edges of lattice tet `lt` of level `k` (`NONE`:
    /// absent).
    #[inline]
    fn lattice_mids(&self, lt: &LatticeTet, k: u8) -> [u32; 6] {
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
    fn classify(
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
    fn queue(&mut self, slot: u32) {
        let n = &mut self.nodes[slot as usize];
        if n.flags & QUEUED == 0 {
            n.flags |= QUEUED;
            let id = n.id();
            self.work.push((slot, id));
        }
    }

    /// Empties the worklist (clearing the queued flags).
    fn clear_work(&mut self) {
        while let Some((slot, id)) = self.work.pop() {
            let n = &mut self.nodes[slot as usize];
            if n.alive() && n.id() == id {
                n.flags &= !QUEUED;
            }
        }
    }

    /// Pushes every leaf of level `≤ max_level` whose closure contains lattice point `w` of base tet
    /// `b` onto the worklist. For the midpoint of a level-`k` edge, the leaves whose closure can
    /// change are those of level `≤ k`: a finer leaf holding the point has it as a vertex (a lattice
    /// tet holds no other point of its lattice), not as the midpoint of one of its edges.
    fn locate(&mut self, b: u32, w: &Bary, max_level: u8) {
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
                    if *f & QUEUED == 0 {
                        *f |= QUEUED;
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
    fn close(&mut self, buf: &DetailBuffer) -> Result<(), MeshError> {
        let bound = self.forest.nodes() as usize + 8;
        let mut refines = 0usize;
        let levels = self.forest.levels;
        while let Some((slot, id)) = self.work.pop() {
            let n = self.nodes[slot as usize];
            if !n.alive() || n.id() != id || n.flags & QUEUED == 0 {
                continue;
            }
            self.nodes[slot as usize].flags &= !QUEUED;
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

    // ---------------------------------------------------------------- vertices

    fn new_vertex(&mut self, key: u64, pos: [f32; 3], level: u8, ends: [u32; 2], val: f32) -> u32 {
        let s = match self.free_vertices.pop() {
            Some(s) => {
                let i = s as usize;
                self.vkey[i] = key;
                self.vpos[i] = pos;
                self.vval[i] = val;
                self.vends[i] = ends;
                self.vref[i] = 1;
                self.vlevel[i] = level;
                self.vdeps[i] = 0;
                self.vowner[i] = [NONE; OWNERS];
                s
            }
            None => {
                grow(&mut self.vpos, 1);
                grow(&mut self.vval, 1);
                self.vkey.push(key);
                self.vpos.push(pos);
                self.vval.push(val);
                self.vends.push(ends);
                self.vref.push(1);
                self.vlevel.push(level);
                self.vdeps.push(0);
                self.vowner.push([NONE; OWNERS]);
                (self.vkey.len() - 1) as u32
            }
        };
        self.vdeps[ends[0] as usize] += 1;
        self.vdeps[ends[1] as usize] += 1;
        self.n_vertices += 1;
        s
    }

    fn lattice_position(&self, b: u32, w: &Bary) -> [f64; 3] {
        tetwave_protocol::base::lattice_position(
            &self.base_positions,
            &self.base_tets[b as usize],
            self.keys.lattice().m(),
            w,
        )
    }

    #[inline]
    fn synth_value(&self, buf: &DetailBuffer, key: u64, ends: [u32; 2]) -> f32 {
        let d = buf.coeff(key).unwrap_or(0.0);
        synthesize(
            d,
            predict(self.vval[ends[0] as usize], self.vval[ends[1] as usize]),
        )
    }

    // ---------------------------------------------------------------- refine / coarsen

    fn alloc_block(&mut self) -> u32 {
        match self.free_blocks.pop() {
            Some(b) => b,
            None => {
                let b = self.nodes.len() as u32;
                for _ in 0..8 {
                    self.nodes.push(Node::DEAD);
                }
                self.bverts.push([NONE; 10]);
                b
            }
        }
    }

    /// Red-splits leaf `slot` (lattice tet `lt`): creates or references its 6 midpoints and its 8
    /// children, and queues the children and the leaves around new vertices.
    fn refine_slot(
        &mut self,
        slot: u32,
        lt: &LatticeTet,
        buf: &DetailBuffer,
    ) -> Result<(), MeshError> {
        let n = self.nodes[slot as usize];
        debug_assert!(n.is_leaf());
        let level = self.forest.level(n.id());
        if level >= self.forest.levels {
            return Err(MeshError::Finest(n.id()));
        }
        let nv = self.node_verts(slot as usize);
        let mut pts = [0u32; 10];
        pts[..4].copy_from_slice(&nv);
        let mut created = [false; 6];
        for (e, &(a, b)) in EDGES.iter().enumerate() {
            let (sa, sb) = (nv[a], nv[b]);
            let w = lt.edge_midpoint(e);
            let key = self.keys.key(lt.base, &w);
            let s = match self.by_key.get(key) {
                s if s != NONE => {
                    self.vref[s as usize] += 1;
                    s
                }
                _ => {
                    let p = self.lattice_position(lt.base, &w);
                    let val = self.synth_value(buf, key, [sa, sb]);
                    let s = self.new_vertex(
                        key,
                        [p[0] as f32, p[1] as f32, p[2] as f32],
                        level + 1,
                        [sa, sb],
                        val,
                    );
                    self.by_key.insert(key, s);
                    created[e] = true;
                    s
                }
            };
            pts[4 + e] = s;
            if let Some(o) = self.vowner[s as usize].iter_mut().find(|o| **o == NONE) {
                *o = slot;
            }
        }
        let block = self.alloc_block();
        let bi = self.block_of(block as usize);
        self.bverts[bi] = pts;
        for (i, &flip) in child_flips().iter().enumerate() {
            let mut flags = ALIVE | (n.flags & (EMPTY | FLIP));
            if flip {
                flags ^= FLIP;
            }
            if buf.child_empty(n.id(), i) {
                flags |= EMPTY;
            }
            let id = self.forest.child(n.id(), i);
            self.nodes[(block + i as u32) as usize] = Node::new(id, NONE, 0, flags | QUEUED);
            self.work.push((block + i as u32, id));
        }
        let node = &mut self.nodes[slot as usize];
        node.children = block;
        node.mask = 0;
        self.n_leaves += 7;
        self.n_splits += 1;
        self.log_change(slot, block);
        self.count_in_parent(n.id(), 1);
        for (e, &c) in created.iter().enumerate() {
            if c {
                self.locate(lt.base, &lt.edge_midpoint(e), level);
            }
        }
        Ok(())
    }

    /// Red-refines leaf `t` and restores conformity (green closure, domino refinements). Missing
    /// coefficients are predicted (d = 0) and corrected by [`Self::apply_arrivals`] later.
    pub fn refine(&mut self, t: TetId, buf: &DetailBuffer) -> Result<(), MeshError> {
        let slot = self.find(t).ok_or(MeshError::NotInMesh(t))?;
        let n = self.nodes[slot as usize];
        if !n.is_leaf() {
            return Err(MeshError::NotLeaf(t));
        }
        if n.flags & EMPTY != 0 {
            return Err(MeshError::Empty(t));
        }
        if self.forest.level(t) >= self.forest.levels {
            return Err(MeshError::Finest(t));
        }
        let lt = self.lattice_of(t);
        self.refine_slot(slot, &lt, buf)?;
        self.close(buf)
    }

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
    /// candidate that is forced anyway changes no other outcome. [`Self::batch_held`] lists those
    /// with their owners.
    pub fn coarsen_batch(&mut self, ts: &[TetId], buf: &DetailBuffer) -> Result<usize, MeshError> {
        self.coarsen_batch_at(ts, &[], buf)
    }

    /// [`Self::coarsen_batch`] with `hints[i]`: the node slot `ts[i]` probably is in (checked).
    pub fn coarsen_batch_at(
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
            if slot == NONE || self.nodes[slot as usize].flags & BATCHED != 0 {
                continue;
            }
            self.nodes[slot as usize].flags |= BATCHED;
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
                self.nodes[s as usize].flags &= !BATCHED;
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
    fn holds_vertex(&self, s: u32, k: u32) -> bool {
        self.vref[s as usize] > 0 && self.vkey[s as usize] == k as u64
    }

    /// Whether the vertices of witness `w` are all present (positive count, same key).
    #[inline]
    fn witness_present(&self, w: &Witness) -> bool {
        let present = |(s, k): (u32, u32)| s == NONE || self.holds_vertex(s, k);
        present(w[0]) && present(w[1]) && present(w[2]) && present(w[3])
    }

    /// When every vertex of witness `w` is present with an owner ([`Self::vowner`]) that is not a
    /// candidate of the batch being gathered (not flagged [`BATCHED`]): those owners.
    #[inline]
    fn witness_held(&self, w: &Witness) -> Option<[u32; 4]> {
        let mut owners = [NONE; 4];
        for (o, &(s, k)) in owners.iter_mut().zip(w) {
            if s == NONE {
                continue;
            }
            if !self.holds_vertex(s, k) {
                return None;
            }
            *o = *self.vowner[s as usize]
                .iter()
                .find(|&&o| o != NONE && self.nodes[o as usize].flags & BATCHED == 0)?;
        }
        Some(owners)
    }

    /// The candidates the last [`Self::coarsen_batch_at`] settled by their refusal witness, each
    /// with the refined tets outside the batch whose midpoints make the witness (slots, `NONE`
    /// padding). Such a candidate stays refused in any batch that leaves all of them out, until
    /// one of them changes.
    pub fn batch_held(&self) -> &[(u32, [u32; 4])] {
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
        let wit = |ss: &[u32]| -> Witness {
            let mut w = [(NONE, 0u32); 4];
            for (i, &s) in ss.iter().enumerate() {
                w[i] = (s, self.vkey[s as usize] as u32);
            }
            w
        };
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
            return Some(wit(&ss[..n]));
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
                    return Some(wit(&[c.mids[e], s]));
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
                            return Some(wit(&[c.mids[x], c.mids[y], s]));
                        }
                    }
                }
            }
        }
        None
    }

    /// Forgets why earlier merges were refused (see [`Self::coarsen_batch_at`]). The records only
    /// save work: every operation gives the same result with or without them.
    pub fn clear_refusal_records(&mut self) {
        self.refused.clear();
    }

    /// Whether the 8 children of refined node `n` are leaves.
    #[inline]
    fn children_leaves(&self, n: &Node) -> bool {
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
    fn count_in_parent(&mut self, id: TetId, d: i8) {
        if let Some(p) = self.forest.parent(id) {
            let ps = self.find(p).expect("a node's parent is in the tree") as usize;
            let n = &mut self.nodes[ps];
            n.nref = n.nref.wrapping_add_signed(d);
        }
    }

    /// Midpoint slots of the 6 edges of refined node `n`, read off its children ([`BEY_CHILDREN`]:
    /// `T0 = [x0, x01, x02, x03]`, `T1 = [x01, x1, x12, x13]`, `T2 = [x02, x12, x2, x23]`).
    #[inline]
    fn child_mids(&self, n: &Node) -> [u32; 6] {
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
    fn unrefine(&mut self, slot: u32) {
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
                let ends = self.vends[s];
                debug_assert_eq!(self.vdeps[s], 0);
                self.by_key.remove(self.vkey[s]);
                self.vdeps[ends[0] as usize] -= 1;
                self.vdeps[ends[1] as usize] -= 1;
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

    // ---------------------------------------------------------------- arrivals

    /// Applies coefficients and node metadata that arrived in `buf` (as recorded in `arrivals`):
    /// present vertices owning a new coefficient are recomputed in place, then every present vertex
    /// predicted from a changed one (level by level); children of arrived nodes get their `empty`
    /// flags. Returns the number of vertex values recomputed.
    pub fn apply_arrivals(&mut self, buf: &DetailBuffer, arrivals: &Arrivals) -> usize {
        let mut dirty: Vec<u32> = Vec::new();
        let nbase = self.keys.base_vertex_count();
        for &key in &arrivals.keys {
            if let Some(s) = self.slot_of_key(key).filter(|&s| s as u64 >= nbase) {
                let v = self.synth_value(buf, key, self.vends[s as usize]);
                self.vval[s as usize] = v;
                dirty.push(s);
            }
        }
        let mut count = dirty.len();
        if dirty.iter().any(|&s| self.vdeps[s as usize] > 0) {
            let lo = dirty
                .iter()
                .map(|&s| self.vlevel[s as usize])
                .min()
                .unwrap_or(0);
            let mut mark = vec![false; self.vkey.len()];
            for &s in &dirty {
                mark[s as usize] = true;
            }
            let mut by_level: Vec<Vec<u32>> = vec![Vec::new(); self.forest.levels as usize + 1];
            for s in 0..self.vkey.len() {
                if self.vref[s] != 0 && self.vlevel[s] > lo {
                    by_level[self.vlevel[s] as usize].push(s as u32);
                }
            }
            for lv in by_level {
                for s in lv {
                    let ends = self.vends[s as usize];
                    if mark[ends[0] as usize] || mark[ends[1] as usize] {
                        self.vval[s as usize] = self.synth_value(buf, self.vkey[s as usize], ends);
                        if !mark[s as usize] {
                            mark[s as usize] = true;
                            count += 1;
                        }
                    }
                }
            }
        }
        for &id in &arrivals.nodes {
            if let Some(slot) = self.find(id) {
                if !self.nodes[slot as usize].is_leaf() {
                    self.refresh_empty(slot, buf);
                }
            }
        }
        count
    }

    fn refresh_empty(&mut self, slot: u32, buf: &DetailBuffer) {
        let n = self.nodes[slot as usize];
        if n.is_leaf() {
            return;
        }
        for i in 0..8u32 {
            let c = (n.children + i) as usize;
            let empty = n.flags & EMPTY != 0 || buf.child_empty(n.id(), i as usize);
            let old = self.nodes[c].flags & EMPTY != 0;
            if empty != old {
                self.nodes[c].flags ^= EMPTY;
                let block = self.nodes[c].children;
                self.log_change(c as u32, block);
                self.refresh_empty(c as u32, buf);
            }
        }
    }

    // ---------------------------------------------------------------- checks

    /// Checks every invariant of the leaf mesh (see [`ConformityError`]): node vertices agree with the
    /// lattice, the closure is settled and stored green patterns are current, every piece has
    /// positive volume, every face is shared by exactly two pieces or lies on the domain boundary,
    /// every present vertex is used by a piece, reference counts match the refined tets, and the
    /// volumes sum to the domain's (relative 1e-9).
    pub fn check_conformity(&self) -> Result<(), ConformityError> {
        let mut faces: FxHashMap<[u64; 3], (u32, bool)> = FxHashMap::default();
        let mut used = vec![false; self.vkey.len()];
        let mut want_ref = vec![0u32; self.vkey.len()];
        let mut total = 0.0f64;
        let lattice = Lattice {
            levels: self.forest.levels,
        };
        let mut stack: Vec<(u32, LatticeTet)> = (0..self.base_tets.len() as u32)
            .map(|b| (b, LatticeTet::base_tet(lattice, b)))
            .collect();
        let mut alive_nodes = 0usize;
        while let Some((slot, lt)) = stack.pop() {
            let n = self.nodes[slot as usize];
            if !n.alive() {
                return Err(ConformityError::Other(format!(
                    "dead node in tree: slot {slot}"
                )));
            }
            alive_nodes += 1;
            for i in 0..4 {
                let want = self.keys.key(lt.base, &lt.v[i]);
                let s = self.node_verts(slot as usize)[i];
                let have = (s != NONE && self.vref[s as usize] != 0).then(|| self.vkey[s as usize]);
                if have != Some(want) {
                    return Err(ConformityError::VertexMismatch {
                        id: n.id(),
                        local: i,
                        slot: s,
                        have,
                        want,
                    });
                }
            }
            let level = self.forest.level(n.id());
            if !n.is_leaf() {
                let mids = self.lattice_mids(&lt, level);
                for &m in &mids {
                    if m == NONE {
                        return Err(ConformityError::Other(format!(
                            "refined tet {} misses a midpoint",
                            n.id()
                        )));
                    }
                    want_ref[m as usize] += 1;
                }
                let nref = (0..8)
                    .filter(|&i| !self.nodes[(n.children + i) as usize].is_leaf())
                    .count();
                if nref != n.nref as usize {
                    return Err(ConformityError::Other(format!(
                        "refined tet {} counts {} refined children, has {nref}",
                        n.id(),
                        n.nref
                    )));
                }
                for (i, c) in lt.children().into_iter().enumerate() {
                    let cs = n.children + i as u32;
                    let cn = &self.nodes[cs as usize];
                    if cn.id() != self.forest.child(n.id(), i) {
                        return Err(ConformityError::Other(format!(
                            "child {i} of {} has id {}",
                            n.id(),
                            cn.id()
                        )));
                    }
                    stack.push((cs, c));
                }
                continue;
            }
            let mid = self.lattice_mids(&lt, level);
            let (mask, forced) = self.classify(&lt, level, &mid, |_| true);
            if forced {
                return Err(ConformityError::NotClosed { id: n.id(), mask });
            }
            if mask != n.mask {
                return Err(ConformityError::StaleGreen {
                    id: n.id(),
                    mask: n.mask,
                    want: mask,
                });
            }
            // pieces over (slot, lattice point)
            let nv = self.node_verts(slot as usize);
            let v: [(u32, Bary); 4] = std::array::from_fn(|i| (nv[i], lt.v[i]));
            let midp: [(u32, Bary); 6] = std::array::from_fn(|e| (mid[e], lt.edge_midpoint(e)));
            let mkey: [u64; 6] = std::array::from_fn(|e| {
                if mid[e] != NONE {
                    self.vkey[mid[e] as usize]
                } else {
                    u64::MAX
                }
            });
            let flip = n.flags & FLIP != 0;
            let mut err = None;
            green_split(v, mask, &midp, &mkey, &mut |p: [(u32, Bary); 4]| {
                if err.is_some() {
                    return;
                }
                let p = if flip { [p[0], p[1], p[3], p[2]] } else { p };
                let x = p.map(|q| self.lattice_position(lt.base, &q.1));
                let vol = signed_volume(x[0], x[1], x[2], x[3]);
                if vol <= 0.0 {
                    err = Some(ConformityError::NonPositive {
                        id: n.id(),
                        volume: vol,
                    });
                    return;
                }
                total += vol;
                for q in &p {
                    used[q.0 as usize] = true;
                }
                for f in &FACES {
                    let mut k = [
                        self.vkey[p[f[0]].0 as usize],
                        self.vkey[p[f[1]].0 as usize],
                        self.vkey[p[f[2]].0 as usize],
                    ];
                    k.sort_unstable();
                    let on_boundary = (0..4).any(|z| {
                        self.boundary[lt.base as usize][z] && f.iter().all(|&j| p[j].1[z] == 0)
                    });
                    let entry = faces.entry(k).or_insert((0, on_boundary));
                    entry.0 += 1;
                    entry.1 |= on_boundary;
                }
            });
            if let Some(e) = err {
                return Err(e);
            }
        }
        let alive_total = self.nodes.iter().filter(|n| n.alive()).count();
        if alive_total != alive_nodes {
            return Err(ConformityError::Other(format!(
                "{alive_total} live nodes, {alive_nodes} reachable"
            )));
        }
        for (face, &(count, boundary)) in &faces {
            let ok = if boundary { count == 1 } else { count == 2 };
            if !ok {
                return Err(ConformityError::Face {
                    face: *face,
                    count,
                    boundary,
                });
            }
        }
        let nv = self.keys.base_vertex_count() as usize;
        let mut present = 0usize;
        for s in 0..self.vkey.len() {
            if self.vref[s] == 0 {
                continue;
            }
            present += 1;
            if !used[s] {
                return Err(ConformityError::Unused {
                    key: self.vkey[s],
                    slot: s as u32,
                });
            }
            if s >= nv && self.vref[s] != want_ref[s] {
                return Err(ConformityError::RefCount {
                    key: self.vkey[s],
                    have: self.vref[s],
                    want: want_ref[s],
                });
            }
        }
        for s in 0..self.vkey.len() {
            for &o in &self.vowner[s] {
                if o == NONE {
                    continue;
                }
                let n = &self.nodes[o as usize];
                if self.vref[s] == 0
                    || !n.alive()
                    || n.is_leaf()
                    || !self.child_mids(n).contains(&(s as u32))
                {
                    return Err(ConformityError::Other(format!(
                        "vertex {} names slot {o} as an owner, which does not refine its edge",
                        self.vkey[s]
                    )));
                }
            }
        }
        for &slot in self.refused.keys() {
            let n = self.nodes.get(slot as usize);
            if !n.is_some_and(|n| n.alive() && !n.is_leaf()) {
                return Err(ConformityError::Other(format!(
                    "a refusal record for slot {slot}, which holds no refined tet"
                )));
            }
        }
        let keyed = self.by_key.count();
        if present != self.n_vertices || keyed != present {
            return Err(ConformityError::Other(format!(
                "{present} present vertices, counter {}, key map {}",
                self.n_vertices, keyed
            )));
        }
        if (total - self.domain_volume).abs() > 1e-9 * self.domain_volume {
            return Err(ConformityError::Volume {
                sum: total,
                domain: self.domain_volume,
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progressive::splitmix;

    /// The paged key table against a map, with pages emptied, recycled and refilled.
    #[test]
    fn key_slots_match_a_map() {
        let nkeys = 1000u64;
        let mut t = KeySlots::new(nkeys as usize);
        let mut want = std::collections::BTreeMap::new();
        for step in 0..20_000u32 {
            let x = splitmix(step as u64);
            // keys clustered in a window that drifts, so pages empty and come back
            let key = ((x >> 33) % 96 + (step as u64 / 50) % (nkeys - 96)) % nkeys;
            if want.remove(&key).is_some() {
                t.remove(key);
            } else {
                want.insert(key, step);
                t.insert(key, step);
            }
            if step % 997 == 0 {
                for k in 0..nkeys {
                    assert_eq!(t.get(k), want.get(&k).copied().unwrap_or(NONE), "key {k}");
                }
            }
        }
        assert_eq!(t.count(), want.len());
        // the pages in use are exactly those of the present keys (emptied ones are recycled)
        let used = t.pages.len() - t.free.len();
        let mut pages: Vec<u64> = want.keys().map(|k| k >> KEY_PAGE_BITS).collect();
        pages.dedup();
        assert_eq!(used, pages.len());
    }

    #[test]
    fn child_maps_invert_bey() {
        let to_child = to_child_maps();
        let flips = child_flips();
        let lat = Lattice { levels: 3 };
        let t = LatticeTet::base_tet(lat, 0);
        for (i, c) in t.children().iter().enumerate() {
            // the child's own vertices map to its unit corners (scaled by m)
            for j in 0..4 {
                let lam = c.v[j].map(|x| x as i64);
                let a = &to_child[i];
                let mu: [i64; 4] = std::array::from_fn(|r| (0..4).map(|s| a[r][s] * lam[s]).sum());
                let mut want = [0i64; 4];
                want[j] = 8;
                assert_eq!(mu, want, "child {i} vertex {j}");
            }
        }
        // corner children keep the orientation
        assert!(!flips[0] && !flips[1] && !flips[2] && !flips[3]);
    }

    #[test]
    fn child_weights_match_child_maps() {
        // the closed form against the inverted Bey matrices, on lattice-like weights with zeros
        let to_child = to_child_maps();
        let mut x = 0u64;
        for n in 0..20_000u64 {
            let mut lam = [0i64; 4];
            for (k, l) in lam.iter_mut().enumerate() {
                x = splitmix(n * 4 + k as u64);
                // every 4th weight 0 (points on faces and edges), others up to 64
                *l = if x & 3 == 0 { 0 } else { (x >> 8) as i64 % 65 };
            }
            if n % 7 == 0 {
                lam[(x % 4) as usize] = 0;
            }
            let (mu, holds) = child_weights(lam);
            for (i, (m, a)) in mu.iter().zip(&to_child).enumerate() {
                let want: [i64; 4] =
                    std::array::from_fn(|r| (0..4).map(|c| a[r][c] * lam[c]).sum());
                assert_eq!(*m, want, "child {i} of {lam:?}");
                assert_eq!(holds & (1 << i) != 0, want.iter().all(|&w| w >= 0));
            }
        }
    }

    #[test]
    fn node_ids_keep_40_bits() {
        for id in [0, 1, u32::MAX as TetId, 1 << 32, MAX_TETS - 1] {
            let n = Node::new(id, 7, 3, ALIVE);
            assert_eq!(
                (n.id(), n.children, n.mask, n.flags, n.nref),
                (id, 7, 3, ALIVE, 0)
            );
        }
    }

    #[test]
    fn green_patterns() {
        assert!(green_pattern_ok(0));
        for e in 0..6 {
            assert!(green_pattern_ok(1 << e));
        }
        let mut n3 = 0;
        for m in 0u8..64 {
            if m.count_ones() == 3 && green_pattern_ok(m) {
                n3 += 1;
            }
        }
        assert_eq!(n3, 4);
        assert!(!green_pattern_ok(0b111111));
    }

    #[test]
    fn green_split_piece_counts() {
        let v = [0u32, 1, 2, 3];
        let mid = [4u32, 5, 6, 7, 8, 9];
        let mkey = [14u64, 15, 16, 17, 18, 19];
        let count = |mask: u8| {
            let mut n = 0;
            green_split(v, mask, &mid, &mkey, &mut |_| n += 1);
            n
        };
        assert_eq!(count(0), 1);
        assert_eq!(count(1), 2);
        assert_eq!(count(0b000011), 3); // (0,1),(0,2) share face 3
        assert_eq!(count(0b100001), 4); // (0,1),(2,3) opposite
        assert_eq!(count(FACE_MASK[0]), 4);
    }
}
