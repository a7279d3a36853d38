//! The semi-regular hierarchy: tet ids, levels, Bey child order and local edge order.
//!
//! A semi-regular mesh is a coarse conforming base mesh of `n` tets refined `L` times by Bey's regular
//! refinement. Every tet of every level has an id; the hierarchy is *implicit*: ids, children, parents,
//! levels and vertex positions are computed, never stored per tet.
//!
//! - Level-0 (base) tets have ids `0..n`.
//! - The children of tet `t` (any level) are `n + 8t + i`, `i = 0..8` (a complete 8-ary forest).
//! - Level `k` occupies the id range `[n(8^k − 1)/7, n(8^{k+1} − 1)/7)`.
//!
//! Vertices of a tet are kept as *lattice coordinates*: integer barycentric weights with respect to the
//! tet's base tet, scaled so that they sum to `m = 2^L` (see [`Lattice`]). Midpoints are then exact integer
//! averages, and a vertex's global key ([`crate::vertex`]) follows from its weights alone.

use serde::{Deserialize, Serialize};

/// Tet id in the complete 8-ary forest numbering.
pub type TetId = u64;

/// Local edge order of a tet: `(0,1) (0,2) (0,3) (1,2) (1,3) (2,3)`.
pub const EDGES: [(usize, usize); 6] = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];

/// Local face order: face `i` is the face opposite vertex `i`, listed by its other three vertices.
pub const FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];

/// Index into the 10 points of a Bey split: `0..4` are the tet's vertices, `4..10` the midpoints of
/// [`EDGES`] in order (`x01 x02 x03 x12 x13 x23`).
const X01: usize = 4;
const X02: usize = 5;
const X03: usize = 6;
const X12: usize = 7;
const X13: usize = 8;
const X23: usize = 9;

/// Bey's regular refinement of `T = [x0,x1,x2,x3]`, children in the contract's order (docs/protocol.md):
/// `T0=[x0,x01,x02,x03] T1=[x01,x1,x12,x13] T2=[x02,x12,x2,x23] T3=[x03,x13,x23,x3]`
/// `T4=[x01,x02,x03,x13] T5=[x01,x02,x12,x13] T6=[x02,x03,x13,x23] T7=[x02,x12,x13,x23]`.
/// Entries index the 10 split points (see the constants above). The vertex order is part of the
/// contract: it keeps all descendants in at most three similarity classes.
pub const BEY_CHILDREN: [[usize; 4]; 8] = [
    [0, X01, X02, X03],
    [X01, 1, X12, X13],
    [X02, X12, 2, X23],
    [X03, X13, X23, 3],
    [X01, X02, X03, X13],
    [X01, X02, X12, X13],
    [X02, X03, X13, X23],
    [X02, X12, X13, X23],
];

/// The edges of a Bey split: the 25 distinct edges of the 8 children, as pairs of split points
/// (`0..4` vertices, `4..10` midpoints), and for each child its 6 local edges ([`EDGES`] order) as
/// indices into that list. A walk over parents computes the 25 child-edge midpoints once instead of
/// 48 times.
#[derive(Debug, Clone)]
pub struct BeySplitEdges {
    pub edges: Vec<(usize, usize)>,
    pub child_edges: [[usize; 6]; 8],
}

/// The (lazily built) [`BeySplitEdges`].
pub fn bey_split_edges() -> &'static BeySplitEdges {
    static CELL: std::sync::OnceLock<BeySplitEdges> = std::sync::OnceLock::new();
    CELL.get_or_init(|| BeySplitEdges {
        edges: BEY_SPLIT.edges.to_vec(),
        child_edges: BEY_SPLIT.child_edges,
    })
}

/// [`BeySplitEdges`] as constant tables (fixed sizes, usable in unrolled loops), plus for each split
/// edge the first child (in Bey order) that has it and its local edge index there.
#[derive(Debug, Clone, Copy)]
pub struct BeySplit {
    pub edges: [(usize, usize); 25],
    pub child_edges: [[usize; 6]; 8],
    pub first_child: [(usize, usize); 25],
}

/// The edges of a Bey split (see [`BeySplitEdges`]), in the same order.
pub const BEY_SPLIT: BeySplit = {
    let mut edges = [(0usize, 0usize); 25];
    let mut child_edges = [[0usize; 6]; 8];
    let mut first_child = [(0usize, 0usize); 25];
    let mut len = 0;
    let mut i = 0;
    while i < 8 {
        let c = BEY_CHILDREN[i];
        let mut e = 0;
        while e < 6 {
            let (a, b) = EDGES[e];
            let (x, y) = (c[a], c[b]);
            let pair = if x < y { (x, y) } else { (y, x) };
            let mut idx = 0;
            while idx < len && (edges[idx].0 != pair.0 || edges[idx].1 != pair.1) {
                idx += 1;
            }
            if idx == len {
                edges[len] = pair;
                first_child[len] = (i, e);
                len += 1;
            }
            child_edges[i][e] = idx;
            e += 1;
        }
        i += 1;
    }
    assert!(len == 25);
    BeySplit {
        edges,
        child_edges,
        first_child,
    }
};

/// Id arithmetic of a forest with `n_base` roots and `levels` levels of refinement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Forest {
    pub n_base: u64,
    pub levels: u8,
}

/// The largest number of levels the id and lattice arithmetic supports (`8^k` fits in u64 for every
/// level with room for `n_base` up to 2^20; lattice weights fit in u32).
pub const MAX_LEVELS: u8 = 16;

impl Forest {
    pub fn new(n_base: u64, levels: u8) -> Self {
        assert!(levels <= MAX_LEVELS, "levels {levels} > {MAX_LEVELS}");
        Forest { n_base, levels }
    }

    /// First id of level `k` (`k` may be `levels + 1`, giving the total count).
    pub fn level_start(&self, k: u8) -> u64 {
        // 7 divides 8^k − 1 (8 ≡ 1 mod 7): dividing first, the only product is the count itself,
        // which cannot overflow where the count fits
        self.n_base * (((1u64 << (3 * k as u32)) - 1) / 7)
    }

    /// Number of tets at level `k`.
    pub fn level_len(&self, k: u8) -> u64 {
        self.n_base << (3 * k as u32)
    }

    /// Tets in all levels `0..=L`.
    pub fn total_tets(&self) -> u64 {
        self.level_start(self.levels + 1)
    }

    /// Leaves of the uniform finest level.
    pub fn leaves(&self) -> u64 {
        self.level_len(self.levels)
    }

    /// Detail nodes: tets that have children (levels `0..L`).
    pub fn nodes(&self) -> u64 {
        self.level_start(self.levels)
    }

    /// [`Self::level_start`] without overflow: `None` when the count does not fit in a u64 (a base
    /// mesh of many tets with many levels, e.g. one read from an untrusted source).
    pub fn checked_level_start(&self, k: u8) -> Option<u64> {
        let p = 1u128.checked_shl(3 * k as u32)?;
        (self.n_base as u128)
            .checked_mul(p - 1)
            .map(|x| x / 7)
            .and_then(|x| u64::try_from(x).ok())
    }

    /// [`Self::nodes`] without overflow: `None` when it does not fit in a u64.
    pub fn checked_nodes(&self) -> Option<u64> {
        self.checked_level_start(self.levels)
    }

    /// The first id of the finest node level (`levels − 1`: nodes whose children are the
    /// hierarchy's leaves), when that level has parents (at least 2 levels; a base tet has no
    /// parent whose bound could stand in for its own); `None` otherwise or when it does not fit
    /// in a u64.
    pub fn checked_finest_nodes_start(&self) -> Option<u64> {
        if self.levels < 2 {
            return None;
        }
        self.checked_level_start(self.levels - 1)
    }

    /// [`Self::total_tets`] without overflow: `None` when it does not fit in a u64.
    pub fn checked_total_tets(&self) -> Option<u64> {
        self.checked_level_start(self.levels + 1)
    }

    /// Whether `id` names a tet of this forest.
    pub fn contains(&self, id: TetId) -> bool {
        id < self.total_tets()
    }

    /// Level of a tet id (ids beyond the forest still get the level of their range).
    pub fn level(&self, id: TetId) -> u8 {
        // id ≥ level_start(k) ⇔ 7·id + n ≥ n·8^k (n·(8^k − 1) is a multiple of 7): shifts, no
        // division (this is on the client's hot paths)
        let n = self.n_base as u128;
        let q = 7 * id as u128 + n;
        let mut k = 0u8;
        while k < 21 && q >= n << (3 * (k as u32 + 1)) {
            k += 1;
        }
        k
    }

    /// Parent of `id`, `None` for a base tet.
    pub fn parent(&self, id: TetId) -> Option<TetId> {
        (id >= self.n_base).then(|| (id - self.n_base) / 8)
    }

    /// Position `i` of `id` among its parent's children, `None` for a base tet.
    pub fn child_index(&self, id: TetId) -> Option<usize> {
        (id >= self.n_base).then(|| ((id - self.n_base) % 8) as usize)
    }

    /// Id of child `i` of `id`.
    pub fn child(&self, id: TetId, i: usize) -> TetId {
        debug_assert!(i < 8);
        self.n_base + 8 * id + i as u64
    }

    /// The base tet `id` descends from and the child indices from it down to `id`, root first.
    pub fn path(&self, id: TetId) -> (u32, Vec<u8>) {
        let k = self.level(id);
        let local = id - self.level_start(k);
        let base = (local >> (3 * k as u32)) as u32;
        let digits = (0..k)
            .map(|j| ((local >> (3 * (k - 1 - j) as u32)) & 7) as u8)
            .collect();
        (base, digits)
    }
}

/// Barycentric lattice weights of a point with respect to a base tet, summing to `m = 2^L`.
pub type Bary = [u32; 4];

/// Per Bey child and vertex: the two parent vertices it is the midpoint of (the same twice for a
/// corner), from [`BEY_CHILDREN`] and [`EDGES`].
const CHILD_PAIRS: [[(u8, u8); 4]; 8] = child_pairs();

const fn child_pairs() -> [[(u8, u8); 4]; 8] {
    let mut out = [[(0u8, 0u8); 4]; 8];
    let mut i = 0;
    while i < 8 {
        let mut j = 0;
        while j < 4 {
            let p = BEY_CHILDREN[i][j];
            out[i][j] = if p < 4 {
                (p as u8, p as u8)
            } else {
                (EDGES[p - 4].0 as u8, EDGES[p - 4].1 as u8)
            };
            j += 1;
        }
        i += 1;
    }
    out
}

/// Lattice of a forest's finest level: `m = 2^levels` steps along every base edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lattice {
    pub levels: u8,
}

impl Lattice {
    pub fn m(&self) -> u32 {
        1u32 << self.levels
    }

    /// Weights of the 4 vertices of a base tet.
    pub fn base_corners(&self) -> [Bary; 4] {
        let m = self.m();
        [[m, 0, 0, 0], [0, m, 0, 0], [0, 0, m, 0], [0, 0, 0, m]]
    }

    /// Level at which a lattice point first appears (0 for base vertices).
    pub fn vertex_level(&self, w: &Bary) -> u8 {
        let tz = w
            .iter()
            .map(|&x| if x == 0 { 32 } else { x.trailing_zeros() })
            .min()
            .unwrap();
        self.levels - tz.min(self.levels as u32) as u8
    }
}

/// A tet of the hierarchy: its base tet and the lattice weights of its 4 vertices, in contract order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct LatticeTet {
    pub base: u32,
    pub v: [Bary; 4],
}

/// Exact midpoint of two lattice points of a level `< L`.
#[inline]
pub fn midpoint(a: &Bary, b: &Bary) -> Bary {
    [
        (a[0] + b[0]) / 2,
        (a[1] + b[1]) / 2,
        (a[2] + b[2]) / 2,
        (a[3] + b[3]) / 2,
    ]
}

impl LatticeTet {
    pub fn base_tet(lattice: Lattice, base: u32) -> Self {
        LatticeTet {
            base,
            v: lattice.base_corners(),
        }
    }

    /// The tet with id `id` of `forest` (O(level)).
    pub fn from_id(forest: &Forest, id: TetId) -> Self {
        let (base, digits) = forest.path(id);
        let mut t = LatticeTet::base_tet(
            Lattice {
                levels: forest.levels,
            },
            base,
        );
        for d in digits {
            t = t.child(d as usize);
        }
        t
    }

    /// Midpoint of local edge `e` (see [`EDGES`]).
    #[inline]
    pub fn edge_midpoint(&self, e: usize) -> Bary {
        let (a, b) = EDGES[e];
        midpoint(&self.v[a], &self.v[b])
    }

    /// The 10 points of the Bey split: 4 vertices then the 6 edge midpoints.
    #[inline]
    pub fn split_points(&self) -> [Bary; 10] {
        let mut p = [[0u32; 4]; 10];
        p[..4].copy_from_slice(&self.v);
        for e in 0..6 {
            p[4 + e] = self.edge_midpoint(e);
        }
        p
    }

    /// Child `i` in Bey order: each vertex is `(v[a] + v[b]) / 2` for a pair of parent vertices
    /// (`a = b` at a corner), branch-free (the mesh's closure computes one per queued leaf).
    #[inline]
    pub fn child(&self, i: usize) -> Self {
        let pairs = &CHILD_PAIRS[i];
        LatticeTet {
            base: self.base,
            v: std::array::from_fn(|j| {
                let (a, b) = pairs[j];
                midpoint(&self.v[a as usize], &self.v[b as usize])
            }),
        }
    }

    /// All 8 children in Bey order.
    pub fn children(&self) -> [Self; 8] {
        let p = self.split_points();
        std::array::from_fn(|i| {
            let c = BEY_CHILDREN[i];
            LatticeTet {
                base: self.base,
                v: [p[c[0]], p[c[1]], p[c[2]], p[c[3]]],
            }
        })
    }
}

/// Walks the tets of one level in increasing id order, in amortized O(1) per tet (it keeps the path
/// from the base tet and recomputes only the levels whose child index changed).
#[derive(Debug, Clone)]
pub struct LevelWalker {
    forest: Forest,
    level: u8,
    next: TetId,
    end: TetId,
    /// `stack[j]` is the ancestor at level `j` of the current tet; `digits[j]` its child index.
    stack: Vec<LatticeTet>,
    digits: Vec<u8>,
}

impl LevelWalker {
    /// Ids `range` of level `level` (clamped to the level's range).
    pub fn new(forest: Forest, level: u8, range: std::ops::Range<TetId>) -> Self {
        let lo = forest.level_start(level);
        let hi = forest.level_start(level + 1);
        let start = range.start.clamp(lo, hi);
        let end = range.end.clamp(start, hi);
        LevelWalker {
            forest,
            level,
            next: start,
            end,
            stack: Vec::new(),
            digits: Vec::new(),
        }
    }

    /// The whole level.
    pub fn level(forest: Forest, level: u8) -> Self {
        Self::new(
            forest,
            level,
            forest.level_start(level)..forest.level_start(level + 1),
        )
    }
}

impl Iterator for LevelWalker {
    type Item = (TetId, LatticeTet);

    fn next(&mut self) -> Option<Self::Item> {
        if self.next >= self.end {
            return None;
        }
        let id = self.next;
        self.next += 1;
        let k = self.level as usize;
        if self.stack.len() != k + 1 {
            // first call: build the path from the id
            let (base, digits) = self.forest.path(id);
            let lattice = Lattice {
                levels: self.forest.levels,
            };
            self.stack.clear();
            self.stack.push(LatticeTet::base_tet(lattice, base));
            for (j, &d) in digits.iter().enumerate() {
                let c = self.stack[j].child(d as usize);
                self.stack.push(c);
            }
            self.digits = digits;
        } else {
            // odometer: the deepest digit below 7 increments, the ones after it restart at 0
            let mut j = k;
            while j > 0 && self.digits[j - 1] == 7 {
                j -= 1;
            }
            if j == 0 {
                let lattice = Lattice {
                    levels: self.forest.levels,
                };
                let base = self.stack[0].base + 1;
                self.stack[0] = LatticeTet::base_tet(lattice, base);
            } else {
                self.digits[j - 1] += 1;
                self.stack[j] = self.stack[j - 1].child(self.digits[j - 1] as usize);
            }
            for i in j..k {
                self.digits[i] = 0;
                self.stack[i + 1] = self.stack[i].child(0);
            }
        }
        debug_assert_eq!(self.stack.len(), k + 1);
        Some((id, self.stack[k]))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let n = (self.end - self.next) as usize;
        (n, Some(n))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn thesis_table_counts() {
        let f = Forest::new(5, 5);
        assert_eq!(f.total_tets(), 187_245);
        assert_eq!(f.leaves(), 163_840);
        assert_eq!(f.nodes(), 23_405);
        let f6 = Forest::new(5, 6);
        assert_eq!(f6.total_tets(), 1_497_965);
        assert_eq!(f6.leaves(), 1_310_720);
        assert_eq!(f6.nodes(), 187_245);
        assert_eq!(Forest::new(6, 5).total_tets(), 224_694);
    }

    /// The checked counts agree with the plain ones where those fit, and say `None` where they
    /// would wrap (2^20 roots at 16 levels: 2^20 · 8^16 / 7 ≈ 2^65.8).
    #[test]
    fn checked_counts() {
        for (n, l) in [(5u64, 5u8), (6, 6), (5, 10), (1 << 16, 15)] {
            let f = Forest::new(n, l);
            assert_eq!(f.checked_nodes(), Some(f.nodes()));
            assert_eq!(f.checked_total_tets(), Some(f.total_tets()));
        }
        assert_eq!(Forest::new(5, 10).checked_nodes(), Some(766_958_445));
        let huge = Forest::new(1 << 20, MAX_LEVELS);
        assert_eq!(huge.checked_nodes(), None);
        assert_eq!(huge.checked_total_tets(), None);
        let edge = Forest::new(1 << 16, MAX_LEVELS);
        assert_eq!(edge.checked_nodes(), Some(edge.nodes()));
        assert_eq!(edge.checked_total_tets(), None);
        assert_eq!(Forest::new(u64::MAX, 1).checked_total_tets(), None);
    }

    /// `level_start` is exact wherever the count fits in a u64, also where `n · (8^k − 1)` alone
    /// would not (2^20 base tets at 15 levels; 2^21 at 15 and 3 · 2^20 at 15 just below 2^64).
    #[test]
    fn level_start_is_exact_wherever_it_fits() {
        for (n, k) in [
            (1u64 << 20, 15u8),
            (1 << 21, 15),
            (3 << 20, 15),
            (1 << 16, 16),
            (6 << 12, 16),
            (u32::MAX as u64, 10),
        ] {
            let f = Forest::new(n, MAX_LEVELS);
            let exact = n as u128 * ((1u128 << (3 * k as u32)) - 1) / 7;
            assert_eq!(f.checked_level_start(k).map(u128::from), Some(exact));
            assert_eq!(f.level_start(k) as u128, exact, "n {n} k {k}");
        }
    }

    #[test]
    fn level_ranges() {
        let f = Forest::new(5, 4);
        for k in 0..=4u8 {
            assert_eq!(f.level(f.level_start(k)), k);
            assert_eq!(f.level(f.level_start(k + 1) - 1), k);
        }
    }

    /// `level` (shifts) agrees with the definition through `level_start` at every level boundary
    /// of forests from 1 to 2^20 roots, up to the largest level ids can name.
    #[test]
    fn level_matches_level_start() {
        // `level_start` in u128 (no overflow)
        let start = |n: u64, k: u8| n as u128 * ((1u128 << (3 * k as u32)) - 1) / 7;
        let by_start = |n: u64, id: TetId| {
            let mut k = 0u8;
            while k < 21 && id as u128 >= start(n, k + 1) {
                k += 1;
            }
            k
        };
        for n in [1u64, 2, 5, 6, 7, 48, 1000, 1 << 20] {
            let f = Forest::new(n, MAX_LEVELS);
            for k in 0..=21u8 {
                let Ok(s) = u64::try_from(start(n, k)) else {
                    break;
                };
                for id in [
                    s.saturating_sub(1),
                    s,
                    s.saturating_add(1),
                    s.saturating_add(n / 2),
                ] {
                    assert_eq!(f.level(id), by_start(n, id), "n {n} id {id}");
                }
            }
        }
    }

    #[test]
    fn bey_split_has_25_edges() {
        let b = bey_split_edges();
        assert_eq!(b.edges.len(), 25);
        let t = LatticeTet::base_tet(Lattice { levels: 2 }, 0);
        let p = t.split_points();
        for (i, c) in t.children().iter().enumerate() {
            for e in 0..6 {
                let (x, y) = b.edges[b.child_edges[i][e]];
                assert_eq!(c.edge_midpoint(e), midpoint(&p[x], &p[y]));
            }
        }
    }

    #[test]
    fn child_matches_split_points() {
        // `child` (pair table) against `children` (the 10 split points), levels 1 to 3
        let lat = Lattice { levels: 4 };
        let mut todo = vec![(LatticeTet::base_tet(lat, 2), 0)];
        let mut seen = 0;
        while let Some((t, depth)) = todo.pop() {
            for (i, c) in t.children().iter().enumerate() {
                assert_eq!(t.child(i), *c);
                seen += 1;
                if depth + 1 < 3 {
                    todo.push((*c, depth + 1));
                }
            }
        }
        assert_eq!(seen, 8 + 64 + 512);
    }

    #[test]
    fn walker_matches_from_id() {
        let f = Forest::new(5, 4);
        for k in 0..=4u8 {
            for (id, t) in LevelWalker::level(f, k) {
                assert_eq!(t, LatticeTet::from_id(&f, id));
            }
        }
        let mid = f.level_start(3) + 77;
        let w: Vec<_> = LevelWalker::new(f, 3, mid..mid + 100).collect();
        assert_eq!(w.len(), 100);
        assert_eq!(w[0].1, LatticeTet::from_id(&f, mid));
        assert_eq!(w[99].1, LatticeTet::from_id(&f, mid + 99));
    }

    proptest! {
        #[test]
        fn parent_child_bijective(n in 1u64..50, levels in 1u8..8, pick in any::<u64>(), i in 0usize..8) {
            let f = Forest::new(n, levels);
            let t = pick % f.nodes();
            let c = f.child(t, i);
            prop_assert!(f.contains(c));
            prop_assert_eq!(f.parent(c), Some(t));
            prop_assert_eq!(f.child_index(c), Some(i));
            prop_assert_eq!(f.level(c), f.level(t) + 1);
            // path of the child extends the parent's path by i
            let (b0, mut p0) = f.path(t);
            let (b1, p1) = f.path(c);
            p0.push(i as u8);
            prop_assert_eq!(b0, b1);
            prop_assert_eq!(p0, p1);
        }

        #[test]
        fn every_id_has_a_unique_path(n in 1u64..20, levels in 1u8..5, pick in any::<u64>()) {
            let f = Forest::new(n, levels);
            let id = pick % f.total_tets();
            let (b, digits) = f.path(id);
            // rebuild the id from the path
            let mut r = b as u64;
            for d in digits { r = f.child(r, d as usize); }
            prop_assert_eq!(r, id);
        }
    }
}
