//! Hierarchies past 2^32: tet ids, counts, vertex keys, coded ids and block offsets of the target
//! sizes — a 1025³ grid (box6 refined 10 times), 2049³ (11 times), 4097³ (12 times) and lattices of
//! 2×2×3 Kuhn boxes at 9 and 10 levels — checked on sampled ids and points at the ends of their
//! ranges and around 2^32 and 2^33, without allocating anything of the hierarchy's size (the
//! largest allocation is a store's block index, 8 bytes per 4096 nodes: 22 MB at most here).
//!
//! Every expected value is computed apart from the code under test: counts and levels in u128
//! from their definitions, vertex keys from the table of `protocol::vertex`'s documentation (global
//! entity numbering by sorted global vertex ids, lexicographic ranks within an entity) in u128.

use std::collections::{BTreeMap, HashMap};
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::hierarchy::{Bary, Forest, LatticeTet, LevelWalker, TetId, EDGES, FACES};
use tetwave_protocol::levelset::{LevelSetError, NearLevelSet, FAR_OUTSIDE};
use tetwave_protocol::node::INHERITED_BOUND;
use tetwave_protocol::order::splitmix;
use tetwave_protocol::ownership::Ownership;
use tetwave_protocol::shapes::kuhn_boxes;
use tetwave_protocol::store_format::{
    Counts, Encoding, FormatError, Manifest, Preview, StoreFiles, StoreHead, BLOCK,
    MAX_BLOCK_BYTES, STORE_FORMAT, STORE_VERSION,
};
use tetwave_protocol::synthesis::NodeAt;
use tetwave_protocol::vertex::{Entity, VertexKeys};
use tetwave_protocol::wavelet::Predictor;
use tetwave_protocol::wire::{decode_server, encode, ServerMsg, SessionStart};
use tetwave_protocol::{BaseMesh, DetailNode};

const P32: u64 = 1 << 32;
const P33: u64 = 1 << 33;

/// `cells` Kuhn boxes (6 base tets each; one cell is box6, bit for bit) refined `levels` times.
/// The box spans `cells · 2^levels` finest steps per axis, so that base positions are grid points
/// in finest steps, exactly.
#[derive(Debug, Clone, Copy)]
struct Case {
    cells: [usize; 3],
    levels: u8,
}

/// box6 at 10, 11 and 12 levels (1025³, 2049³, 4097³ vertices); 2×2×3 Kuhn boxes at 9 and 10.
const CASES: [Case; 5] = [
    Case {
        cells: [1, 1, 1],
        levels: 10,
    },
    Case {
        cells: [1, 1, 1],
        levels: 11,
    },
    Case {
        cells: [1, 1, 1],
        levels: 12,
    },
    Case {
        cells: [2, 2, 3],
        levels: 9,
    },
    Case {
        cells: [2, 2, 3],
        levels: 10,
    },
];

impl Case {
    fn m(&self) -> u32 {
        1 << self.levels
    }

    fn base(&self) -> BaseMesh {
        let m = self.m() as f64;
        let hi = self.cells.map(|c| c as f64 * m);
        let (positions, tets) = kuhn_boxes([0.0; 3], hi, self.cells);
        BaseMesh {
            levels: self.levels,
            values: vec![0.0; positions.len()],
            empty: vec![false; tets.len()],
            predictor: Predictor::Parent,
            positions,
            tets,
        }
    }

    fn forest(&self) -> Forest {
        Forest::new(6 * self.cells.iter().product::<usize>() as u64, self.levels)
    }

    /// Finest-lattice vertices: `(cells · 2^levels + 1)` per axis.
    fn vertices(&self) -> u64 {
        self.cells
            .iter()
            .map(|&c| c as u64 * self.m() as u64 + 1)
            .product()
    }
}

/// `level_start` by its definition, in u128.
fn start128(n: u64, k: u8) -> u128 {
    n as u128 * ((1u128 << (3 * k as u32)) - 1) / 7
}

/// The level of `id` by the definition: the `k` with `start(k) ≤ id < start(k + 1)`.
fn level128(n: u64, id: TetId) -> u8 {
    let mut k = 0;
    while id as u128 >= start128(n, k + 1) {
        k += 1;
    }
    k
}

/// Ids to check: the first two and last two of every level, both sides of every level's first
/// and last base tet boundary, both sides of 2^32 .. 2^35 where the forest has them, and random
/// ids of the last two levels.
fn sample_ids(f: &Forest, seed: u64) -> Vec<TetId> {
    let mut ids = Vec::new();
    for k in 0..=f.levels {
        let (s, e) = (f.level_start(k), f.level_start(k + 1));
        ids.extend([s, s + 1, e - 2, e - 1]);
        let per_base = 1u64 << (3 * k as u32);
        for b in [1, f.n_base - 1] {
            let x = s + b * per_base;
            ids.extend([x - 1, x]);
        }
    }
    for p in [P32, P33, 1 << 34, 1 << 35] {
        if p + 1 < f.total_tets() {
            ids.extend([p - 1, p, p + 1]);
        }
    }
    let mut r = seed;
    for _ in 0..64 {
        r = splitmix(r);
        let k = f.levels - (r & 1) as u8;
        ids.push(f.level_start(k) + (r >> 1) % f.level_len(k));
    }
    ids.sort_unstable();
    ids.dedup();
    ids
}

#[test]
fn counts_of_the_target_sizes() {
    // (nodes, tets of all levels, leaves)
    let want: [(u64, u64, u64); 5] = [
        (920_350_134, 7_362_801_078, 6_442_450_944),
        (7_362_801_078, 58_902_408_630, 51_539_607_552),
        (58_902_408_630, 471_219_269_046, 412_316_860_416),
        (1_380_525_192, 11_044_201_608, 9_663_676_416),
        (11_044_201_608, 88_353_612_936, 77_309_411_328),
    ];
    for (c, (nodes, total, leaves)) in CASES.iter().zip(want) {
        let f = c.forest();
        assert_eq!(
            (f.nodes(), f.total_tets(), f.leaves()),
            (nodes, total, leaves),
            "{c:?}"
        );
        assert_eq!(f.checked_nodes(), Some(nodes));
        assert_eq!(f.checked_total_tets(), Some(total));
        assert_eq!(
            f.checked_finest_nodes_start(),
            Some(f.level_start(c.levels - 1))
        );
        let mut sum = 0u64;
        for k in 0..=c.levels + 1 {
            assert_eq!(
                f.level_start(k) as u128,
                start128(f.n_base, k),
                "{c:?} k {k}"
            );
            assert_eq!(f.checked_level_start(k), Some(f.level_start(k)));
            assert_eq!(sum, f.level_start(k));
            if k <= c.levels {
                assert_eq!(
                    f.level_len(k) as u128,
                    f.n_base as u128 * 8u128.pow(k as u32)
                );
                sum += f.level_len(k);
            }
        }
        assert!(f.contains(total - 1) && !f.contains(total));
    }
}

/// Level, parent, children and path of ids of every level, the last ones past 2^32 and 2^33.
#[test]
fn ids_round_trip_through_parents_children_and_paths() {
    for c in CASES {
        let f = c.forest();
        for id in sample_ids(&f, c.levels as u64) {
            let k = f.level(id);
            assert_eq!(k, level128(f.n_base, id), "{c:?} id {id}");
            assert!(f.contains(id));
            if k > 0 {
                let p = f.parent(id).expect("a parent");
                let i = f.child_index(id).expect("a child index");
                assert_eq!(f.level(p), k - 1);
                assert_eq!(f.child(p, i), id);
            } else {
                assert_eq!((f.parent(id), f.child_index(id)), (None, None));
            }
            if k < c.levels {
                for i in 0..8 {
                    let ch = f.child(id, i);
                    assert!(f.contains(ch));
                    assert_eq!(f.parent(ch), Some(id));
                    assert_eq!(f.child_index(ch), Some(i));
                    assert_eq!(f.level(ch), k + 1);
                }
            }
            // the path: the base tet, then one octal digit per level of the level-local index
            let (b, digits) = f.path(id);
            assert_eq!(digits.len(), k as usize);
            assert!((b as u64) < f.n_base);
            let local = digits.iter().fold(b as u128, |x, &d| 8 * x + d as u128);
            assert_eq!(local + start128(f.n_base, k), id as u128, "{c:?} id {id}");
            let rebuilt = digits.iter().fold(b as u64, |x, &d| f.child(x, d as usize));
            assert_eq!(rebuilt, id);
        }
        // one past the last tet is beyond the forest, and its level is the next one's
        assert_eq!(f.level(f.total_tets()), c.levels + 1);
    }
}

/// Determinant of a 4×4 integer matrix (Laplace over the 24 permutations).
fn det4(a: [[i128; 4]; 4]) -> i128 {
    let mut det = 0;
    for p0 in 0..4 {
        for p1 in 0..4 {
            for p2 in 0..4 {
                for p3 in 0..4 {
                    let p = [p0, p1, p2, p3];
                    if (0..4).any(|i| (i + 1..4).any(|j| p[i] == p[j])) {
                        continue;
                    }
                    let inversions = (0..4)
                        .flat_map(|i| (i + 1..4).map(move |j| (i, j)))
                        .filter(|&(i, j)| p[i] > p[j])
                        .count();
                    let term = a[0][p0] * a[1][p1] * a[2][p2] * a[3][p3];
                    det += if inversions % 2 == 0 { term } else { -term };
                }
            }
        }
    }
    det
}

/// The lattice tets of sampled ids: on their level's lattice, of their level's volume, their
/// parent's child, what a level walk crossing 2^32 (and base-tet boundaries) yields; the
/// position `NodeAt` and the ownership state a block coder derives follow the same path.
#[test]
fn lattice_tets_of_large_ids() {
    for c in CASES {
        let f = c.forest();
        let base = c.base();
        let own = Ownership::new(&base);
        let m = c.m();
        for id in sample_ids(&f, 100 + c.levels as u64) {
            let k = f.level(id);
            let t = LatticeTet::from_id(&f, id);
            assert_eq!(t.base, f.path(id).0);
            let step = 1u32 << (c.levels - k);
            for w in &t.v {
                assert_eq!(w.iter().sum::<u32>(), m, "{c:?} id {id}: {w:?}");
                assert!(w.iter().all(|x| x % step == 0), "{c:?} id {id}: {w:?}");
            }
            // the volume of a level-k tet is 8^-k of its base tet's: |det| of the integer weights
            // (rows summing to m = 2^L) is m^4 / 8^k
            let rows = t.v.map(|w| w.map(|x| x as i128));
            let det = det4(rows).abs();
            assert_eq!(
                det,
                1i128 << (4 * c.levels as u32 - 3 * k as u32),
                "{c:?} id {id}"
            );
            if let Some(p) = f.parent(id) {
                let i = f.child_index(id).unwrap();
                assert_eq!(LatticeTet::from_id(&f, p).child(i), t);
                assert_eq!(own.of(id), own.of(p).child(i), "{c:?} id {id}");
            }
            assert_eq!(NodeAt::from_id(&f, id).tet(), t);
            assert!(own.owned(id) < 64);
        }
        // walks across 2^32, 2^33 and base-tet boundaries agree with the tets built from ids
        let last = c.levels;
        let s = f.level_start(last);
        let mut starts = vec![s, s + (1u64 << (3 * last as u32)), f.total_tets() - 4];
        starts.extend(
            [P32, P33]
                .into_iter()
                .filter(|&p| s + 4 <= p && p + 4 < f.total_tets()),
        );
        for x in starts {
            let lo = x.saturating_sub(4).max(s);
            let hi = (x + 4).min(f.total_tets());
            let walked: Vec<_> = LevelWalker::new(f, last, lo..hi).collect();
            assert_eq!(walked.len() as u64, hi - lo);
            for (i, (id, t)) in walked.into_iter().enumerate() {
                assert_eq!(id, lo + i as u64);
                assert_eq!(t, LatticeTet::from_id(&f, id), "{c:?} id {id}");
            }
        }
    }
}

/// Rank of `(i, j)` among the pairs `≥ 0` with `i + j ≤ s`, lexicographically.
fn tri_rank(i: u128, j: u128, s: u128) -> u128 {
    i * (s + 1) - i * i.saturating_sub(1) / 2 + j
}

/// Triples `≥ 0` with sum `≤ n − 1`.
fn tetrahedral(n: u128) -> u128 {
    n * (n + 1) * (n + 2) / 6
}

/// Rank of `(i, j, k)` among the triples `≥ 0` with `i + j + k ≤ s`, lexicographically: those
/// with a smaller first, then those with this first and a smaller second, then `k`.
fn tet_rank(i: u128, j: u128, k: u128, s: u128) -> u128 {
    tetrahedral(s + 1) - tetrahedral(s + 1 - i) + tri_rank(j, k, s - i)
}

/// The ranks are the positions in a plain lexicographic enumeration.
#[test]
fn ranks_are_lexicographic_positions() {
    for s in 0..12u128 {
        let mut at = 0;
        for i in 0..=s {
            for j in 0..=s - i {
                assert_eq!(tri_rank(i, j, s), at);
                at += 1;
            }
        }
        let mut at = 0;
        for i in 0..=s {
            for j in 0..=s - i {
                for k in 0..=s - i - j {
                    assert_eq!(tet_rank(i, j, k, s), at);
                    at += 1;
                }
            }
        }
    }
}

/// The vertex numbering of `protocol::vertex`'s documentation, in u128: base vertices, then the
/// sorted global edges' interiors, the sorted global faces', the base tets'.
struct Numbering {
    m: u128,
    nv: u128,
    tets: Vec<[u32; 4]>,
    edges: Vec<[u32; 2]>,
    faces: Vec<[u32; 3]>,
}

impl Numbering {
    fn of(base: &BaseMesh) -> Self {
        let mut edges: Vec<[u32; 2]> = Vec::new();
        let mut faces: Vec<[u32; 3]> = Vec::new();
        for t in &base.tets {
            for (a, b) in EDGES {
                let mut e = [t[a], t[b]];
                e.sort_unstable();
                edges.push(e);
            }
            for f in FACES {
                let mut g = [t[f[0]], t[f[1]], t[f[2]]];
                g.sort_unstable();
                faces.push(g);
            }
        }
        edges.sort_unstable();
        edges.dedup();
        faces.sort_unstable();
        faces.dedup();
        Numbering {
            m: 1u128 << base.levels,
            nv: base.positions.len() as u128,
            tets: base.tets.clone(),
            edges,
            faces,
        }
    }

    fn per_edge(&self) -> u128 {
        self.m - 1
    }
    fn per_face(&self) -> u128 {
        (self.m - 1) * (self.m - 2) / 2
    }
    fn per_tet(&self) -> u128 {
        (self.m - 1) * (self.m - 2) * (self.m - 3) / 6
    }
    fn face_offset(&self) -> u128 {
        self.nv + self.edges.len() as u128 * self.per_edge()
    }
    fn tet_offset(&self) -> u128 {
        self.face_offset() + self.faces.len() as u128 * self.per_face()
    }
    fn count(&self) -> u128 {
        self.tet_offset() + self.tets.len() as u128 * self.per_tet()
    }

    /// The key of lattice point `w` of base tet `t`.
    fn key(&self, t: u32, w: &Bary) -> u128 {
        let tv = self.tets[t as usize];
        // the nonzero weights by global vertex id
        let mut nz: Vec<(u32, u128)> = (0..4)
            .filter(|&i| w[i] != 0)
            .map(|i| (tv[i], w[i] as u128))
            .collect();
        nz.sort_unstable();
        match nz.len() {
            1 => nz[0].0 as u128,
            2 => {
                let e = self.edges.binary_search(&[nz[0].0, nz[1].0]).unwrap() as u128;
                self.nv + e * self.per_edge() + nz[1].1 - 1
            }
            3 => {
                let f = self
                    .faces
                    .binary_search(&[nz[0].0, nz[1].0, nz[2].0])
                    .unwrap() as u128;
                self.face_offset()
                    + f * self.per_face()
                    + tri_rank(nz[1].1 - 1, nz[2].1 - 1, self.m - 3)
            }
            _ => {
                let r = |i: usize| w[i] as u128 - 1;
                self.tet_offset()
                    + t as u128 * self.per_tet()
                    + tet_rank(r(1), r(2), r(3), self.m - 4)
            }
        }
    }
}

/// Grid points (in finest steps) and the lattice points of base tets that are them, for a base of
/// Kuhn boxes whose corners are grid points.
struct GridOf<'a> {
    base: &'a BaseMesh,
    m: u32,
}

impl GridOf<'_> {
    fn corner(&self, v: u32) -> [u64; 3] {
        self.base.positions[v as usize].map(|x| {
            assert_eq!(x, x.round());
            x as u64
        })
    }

    /// The grid point of lattice point `w` of base tet `t`.
    fn point(&self, t: u32, w: &Bary) -> [u64; 3] {
        let tv = self.base.tets[t as usize];
        let mut p = [0u64; 3];
        for i in 0..4 {
            let x = self.corner(tv[i]);
            for a in 0..3 {
                p[a] += w[i] as u64 * x[a];
            }
        }
        p.map(|c| {
            assert_eq!(c % self.m as u64, 0);
            c / self.m as u64
        })
    }

    /// Every base tet that holds grid point `p`, with `p`'s weights there. A Kuhn tet's corners,
    /// by coordinate sum, step along its axes `a`, `b`, `c` in turn; it holds the points with
    /// `m ≥ q_a ≥ q_b ≥ q_c ≥ 0`, `q = p − corner 0`, at weights `m − q_a, q_a − q_b, q_b − q_c, q_c`.
    fn holders(&self, p: [u64; 3]) -> Vec<(u32, Bary)> {
        let m = self.m as i64;
        let mut out = Vec::new();
        for (t, tv) in self.base.tets.iter().enumerate() {
            let mut order = [0usize, 1, 2, 3];
            order.sort_by_key(|&i| self.corner(tv[i]).iter().sum::<u64>());
            let x = order.map(|i| self.corner(tv[i]).map(|c| c as i64));
            let axis = |s: usize| (0..3).find(|&a| x[s + 1][a] != x[s][a]).unwrap();
            let (a, b, c) = (axis(0), axis(1), axis(2));
            let q: [i64; 3] = std::array::from_fn(|i| p[i] as i64 - x[0][i]);
            if m >= q[a] && q[a] >= q[b] && q[b] >= q[c] && q[c] >= 0 {
                let ws = [m - q[a], q[a] - q[b], q[b] - q[c], q[c]];
                let mut w = [0u32; 4];
                for (s, &i) in order.iter().enumerate() {
                    w[i] = ws[s] as u32;
                }
                out.push((t as u32, w));
            }
        }
        out
    }
}

/// Vertex counts, the entities' key ranges (tiling `0..count`) and the documented count of each.
#[test]
fn vertex_counts_and_entity_ranges_of_the_target_sizes() {
    for c in CASES {
        let base = c.base();
        let keys = base.vertex_keys();
        let num = Numbering::of(&base);
        let n = keys.vertex_count();
        assert_eq!(n, c.vertices(), "{c:?}");
        assert_eq!(n as u128, num.count());
        assert_eq!(keys.edge_count(), num.edges.len() as u64);
        assert_eq!(keys.face_count(), num.faces.len() as u64);
        let below = Case {
            levels: c.levels - 1,
            ..c
        };
        assert_eq!(keys.vertex_count_at_level(c.levels - 1), below.vertices());
        let ents = keys.entities();
        let mut at = 0u64;
        for (e, r) in &ents {
            assert_eq!(r.start, at, "{c:?} {e:?}");
            let len = match e {
                Entity::Vertex(_) => 1,
                Entity::Edge(_) => num.per_edge(),
                Entity::Face(_) => num.per_face(),
                Entity::Tet(_) => num.per_tet(),
            };
            assert_eq!((r.end - r.start) as u128, len, "{c:?} {e:?}");
            at = r.end;
        }
        assert_eq!(at, n);
        let count = |f: fn(&Entity) -> bool| ents.iter().filter(|(e, _)| f(e)).count() as u64;
        assert_eq!(
            count(|e| matches!(e, Entity::Vertex(_))),
            base.positions.len() as u64
        );
        assert_eq!(
            count(|e| matches!(e, Entity::Tet(_))),
            base.tets.len() as u64
        );
    }
}

/// The largest `x` in `lo..=hi` with `pred(x)`, for `pred` true then false along the range.
fn last_true(lo: u32, hi: u32, pred: impl Fn(u32) -> bool) -> u32 {
    assert!(pred(lo));
    let (mut a, mut b) = (lo, hi);
    while a < b {
        let mid = a + (b - a).div_ceil(2);
        if pred(mid) {
            a = mid
        } else {
            b = mid - 1
        }
    }
    a
}

/// The lattice point of base tet `t` whose key is `x`, a key of the tet's interior: keys run over
/// the interior's points lexicographically in `(w_1, w_2, w_3)`, so a search on `w_1`, then `w_2`,
/// then the remainder in `w_3` (only `key` is used: this inverts the implementation).
fn interior_point(keys: &VertexKeys, t: u32, m: u32, x: u64) -> Bary {
    let key = |i: u32, j: u32, k: u32| keys.key(t, &[m - i - j - k, i, j, k]);
    let i = last_true(1, m - 3, |i| key(i, 1, 1) <= x);
    let j = last_true(1, m - 2 - i, |j| key(i, j, 1) <= x);
    let k = 1 + u32::try_from(x - key(i, j, 1)).expect("within one line");
    assert!(i + j + k < m, "key {x}: past the line ({i}, {j}, {k})");
    [m - i - j - k, i, j, k]
}

/// Keys past 2^32: every sampled point's key (wherever it lies: inside a base tet, on a face
/// or edge shared by tets and cells) is the documented one from every tet that holds it, and
/// below the count; no two sampled points share a key; the keys around 2^32 and 2^33, the last
/// key, the ends of every tet's range and random keys all invert to a point that has them.
#[test]
fn vertex_keys_past_2_32() {
    for c in CASES {
        let base = c.base();
        let keys = base.vertex_keys();
        let num = Numbering::of(&base);
        let n = keys.vertex_count();
        let m = c.m();
        let grid = GridOf { base: &base, m };
        let size = c.cells.map(|x| x as u64 * m as u64);
        // points: the box's corners and centre, points on cell faces and Kuhn faces, random ones
        let mut r = 7 + c.levels as u64;
        let mut rand = |below: u64| {
            r = splitmix(r);
            r % below
        };
        let mut points: Vec<[u64; 3]> = Vec::new();
        for i in 0..8 {
            points.push(std::array::from_fn(|a| (i >> a & 1) as u64 * size[a]));
        }
        points.push(size.map(|s| s / 2));
        for _ in 0..400 {
            let mut p: [u64; 3] = std::array::from_fn(|a| rand(size[a] + 1));
            match rand(4) {
                0 => p[rand(3) as usize] = m as u64 * rand(2),
                1 => p[1] = p[0].min(size[1]),
                2 => {
                    p[1] = p[0].min(size[1]);
                    p[2] = p[0].min(size[2]);
                }
                _ => {}
            }
            points.push(p);
        }
        let mut seen: HashMap<u64, [u64; 3]> = HashMap::new();
        let mut past = 0;
        for p in points {
            let holders = grid.holders(p);
            assert!(!holders.is_empty(), "{c:?}: {p:?} in no tet");
            let k = keys.key(holders[0].0, &holders[0].1);
            assert!(k < n);
            past += (k >= P32) as usize;
            for (t, w) in &holders {
                assert_eq!(grid.point(*t, w), p);
                assert_eq!(keys.key(*t, w), k, "{c:?}: {p:?} from tet {t}");
                assert_eq!(num.key(*t, w), k as u128, "{c:?}: {p:?} from tet {t}");
            }
            if let Some(q) = seen.insert(k, p) {
                assert_eq!(q, p, "{c:?}: key {k} twice");
            }
        }
        if n > 2 * P32 {
            assert!(past > 0, "{c:?}: no sampled key past 2^32");
        }
        // keys to invert
        let mut targets = vec![n - 2, n - 1];
        for p in [P32, P33] {
            if p + 1 < n {
                targets.extend([p - 1, p, p + 1]);
            }
        }
        for (e, range) in keys.entities() {
            if let Entity::Tet(_) = e {
                targets.extend([range.start, range.start + 1, range.end - 1]);
            }
        }
        for _ in 0..64 {
            targets.push(rand(n));
        }
        let ents = keys.entities();
        for x in targets {
            let i = ents.partition_point(|(_, r)| r.end <= x);
            let (e, range) = &ents[i];
            assert!(range.contains(&x));
            let (t, w) = match *e {
                Entity::Tet(t) => (t, interior_point(&keys, t, m, x)),
                _ => {
                    let mut found = None;
                    keys.for_each_in(*e, |k, t, w| {
                        if k == x {
                            found = Some((t, w));
                        }
                    });
                    found.expect("the entity has the key")
                }
            };
            assert_eq!(keys.key(t, &w), x, "{c:?}: key {x}");
            assert_eq!(num.key(t, &w), x as u128, "{c:?}: key {x}");
            // the point's key from every tet that holds it (one, inside a base tet)
            for (t2, w2) in grid.holders(grid.point(t, &w)) {
                assert_eq!(keys.key(t2, &w2), x);
            }
        }
        // the vertices of tets of the last level (ids past 2^32) have their documented keys
        let f = c.forest();
        for id in sample_ids(&f, 3) {
            if f.level(id) != c.levels {
                continue;
            }
            let t = LatticeTet::from_id(&f, id);
            for w in &t.v {
                let k = keys.key(t.base, w);
                assert!(k < n);
                assert_eq!(num.key(t.base, w), k as u128, "{c:?} id {id}: {w:?}");
            }
        }
    }
}

/// A store's `blocks.bin` whose blocks are real only where a test reads them: each read must lie
/// within the real ones (offsets past 2^32 included).
struct SparseBlocks(BTreeMap<u64, Vec<u8>>);

impl StoreFiles for SparseBlocks {
    type Error = FormatError;
    fn read_at(&self, file: &str, offset: u64, buf: &mut [u8]) -> Result<(), FormatError> {
        assert_eq!(file, "blocks.bin");
        let end = offset + buf.len() as u64;
        let mut covered = 0;
        for (&at, bytes) in self.0.range(..end) {
            let until = at + bytes.len() as u64;
            if until <= offset {
                continue;
            }
            let (lo, hi) = (at.max(offset), until.min(end));
            buf[(lo - offset) as usize..(hi - offset) as usize]
                .copy_from_slice(&bytes[(lo - at) as usize..(hi - at) as usize]);
            covered += hi - lo;
        }
        if covered != buf.len() as u64 {
            return Err(FormatError::Inconsistent(format!(
                "bytes {offset}..{end} are not a test block's"
            )));
        }
        Ok(())
    }
}

/// The node a test block holds at `id`: a mask near the derived one, coefficients from the id.
fn test_node(own: &Ownership, id: TetId) -> DetailNode {
    let owned = own.owned(id) ^ id.is_multiple_of(3) as u8;
    DetailNode {
        id,
        owned,
        empty_children: id.is_multiple_of(5) as u8 * 0x81,
        subtree_max_abs: 1.0,
        coeffs: (0..owned.count_ones())
            .map(|e| (id % 997) as f32 - 498.0 + e as f32 * 0.25)
            .collect(),
    }
}

/// The node as decoded: a finest node level's bound is its parent's.
fn decoded(mut n: DetailNode, finest_from: TetId) -> DetailNode {
    if n.id >= finest_from {
        n.subtree_max_abs = INHERITED_BOUND;
    }
    n
}

fn manifest(c: &Case, base: &BaseMesh) -> Manifest {
    let f = base.forest();
    let n = base.vertex_keys().vertex_count();
    let (lo, hi) = base.bounds();
    Manifest {
        format: STORE_FORMAT.into(),
        version: STORE_VERSION,
        dataset: "large".into(),
        source: "large.raw".into(),
        bounds: [lo, hi],
        base: if c.cells == [1, 1, 1] {
            "box6".into()
        } else {
            "kuhn-boxes".into()
        },
        base_tets: base.tets.len() as u64,
        base_vertices: base.positions.len() as u64,
        levels: base.levels,
        value_range: [0.0, 1.0],
        source_value_range: None,
        counts: Counts {
            tets_total: f.total_tets(),
            leaves: f.leaves(),
            nodes: f.nodes(),
            vertices: n,
            coefficients: n - base.positions.len() as u64,
            outside_vertices: 0,
            empty_base_tets: 0,
        },
        encoding: Encoding::F32,
        max_error_bound: 0.0,
        max_abs_error: 0.0,
        files: Default::default(),
        preview: None,
        value_histogram: None,
        physical: None,
    }
}

/// A store of more than 2^32 nodes: its block index (one entry per 4096 nodes, byte offsets past
/// 2^32) decodes and is checked, block ids are exact at 2^32 and at the last, partial block, and
/// reads of id ranges across 2^32 and up to the last node return exactly those nodes.
#[test]
fn store_blocks_past_2_32_nodes() {
    for c in [CASES[1], CASES[4]] {
        let base = c.base();
        let f = base.forest();
        let nodes = f.nodes();
        assert!(nodes > P32);
        let blocks = nodes.div_ceil(BLOCK);
        let finest = f.checked_finest_nodes_start().unwrap();
        let own = Ownership::new(&base);
        let coder = BlockCoder::new(&base, &Encoding::F32);
        let last = blocks - 1;
        let mut real: Vec<u64> = vec![P32 / BLOCK - 1, P32 / BLOCK, last - 1, last];
        if nodes > P33 {
            real.extend([P33 / BLOCK - 1, P33 / BLOCK]);
        }
        real.sort_unstable();
        let coded: BTreeMap<u64, Vec<u8>> = real
            .iter()
            .map(|&b| {
                let ids = b * BLOCK..((b + 1) * BLOCK).min(nodes);
                let ns: Vec<_> = ids.map(|id| test_node(&own, id)).collect();
                (b, coder.encode(&ns).unwrap().bytes)
            })
            .collect();
        // every other block spans the most a block may, so the real ones sit past 2^32 bytes
        let mut index = Vec::with_capacity(8 * (blocks as usize + 1));
        let mut files = BTreeMap::new();
        let mut at = 0u64;
        for b in 0..blocks {
            index.extend(at.to_le_bytes());
            at += match coded.get(&b) {
                Some(bytes) => {
                    files.insert(at, bytes.clone());
                    bytes.len() as u64
                }
                None => MAX_BLOCK_BYTES,
            };
        }
        index.extend(at.to_le_bytes());
        assert!(at > 1 << 40);
        let files = SparseBlocks(files);
        let bytes = bincode::serde::encode_to_vec(&base, bincode::config::standard()).unwrap();
        let m = manifest(&c, &base);
        let short = StoreHead::decode(m.clone(), &bytes, &index[..index.len() - 8]);
        assert!(matches!(short, Err(FormatError::BadIndex(_))));
        let head = StoreHead::decode(m, &bytes, &index).unwrap();
        assert_eq!(head.blocks(), blocks);
        assert_eq!(head.index.len() as u64, blocks + 1);
        assert_eq!(head.index[blocks as usize], at);
        assert_eq!(head.block_ids(0), (0, BLOCK));
        assert_eq!(head.block_ids(P32 / BLOCK), (P32, P32 + BLOCK));
        assert_eq!(head.block_ids(last), (last * BLOCK, nodes));
        assert_eq!(head.block_ids(blocks), (nodes, nodes));
        assert!(nodes - last * BLOCK < BLOCK);
        for &b in &real {
            let (from, to) = head.block_ids(b);
            let start = head.index[b as usize];
            assert!(start > P32, "block {b} at byte {start}");
            let bytes = &files.0[&start];
            let got = head.decode_block(b, bytes).unwrap();
            assert_eq!(got.len() as u64, to - from);
            assert_eq!(got.first().map(|n| n.id), Some(from));
        }
        let mut ranges = vec![
            (P32 - 5, P32 + 5),
            (P32 - BLOCK, P32 + BLOCK),
            (last * BLOCK - 3, nodes),
            (nodes - 1, nodes),
            (P32, P32),
        ];
        if nodes > P33 {
            ranges.push((P33 - 1, P33 + 1));
        }
        for (from, to) in ranges {
            let got = head.read_nodes(&files, from, to).unwrap();
            let want: Vec<_> = (from..to)
                .map(|id| decoded(test_node(&own, id), finest))
                .collect();
            assert_eq!(got, want, "{c:?}: nodes {from}..{to}");
        }
        for (from, to) in [(nodes, nodes + 1), (nodes - 1, P33 * 4), (P32 + 1, P32)] {
            assert!(matches!(
                head.read_nodes(&files, from, to),
                Err(FormatError::RangeOutOfBounds { .. })
            ));
        }
        // a preview is at most 2^20 nodes: the levels below the first with more
        let p = |levels| Preview {
            encoding: Encoding::F32,
            levels,
            max_error_bound: 0.0,
        };
        let most = (1..c.levels)
            .rev()
            .find(|&k| f.level_start(k) <= 1 << 20)
            .unwrap();
        assert_eq!(
            p(most).check_for(f.n_base, c.levels),
            Ok(f.level_start(most))
        );
        assert!(p(most + 1).check_for(f.n_base, c.levels).is_err());
    }
}

/// A coded block's ids (the first in its header, then runs, jumps in sibling groups and gaps)
/// jump across 2^32 and 2^33 and up to the hierarchy's last node.
#[test]
fn coded_ids_jump_past_2_32() {
    for c in [CASES[1], CASES[2], CASES[4]] {
        let base = c.base();
        let f = base.forest();
        let nodes = f.nodes();
        let finest = f.checked_finest_nodes_start().unwrap();
        let own = Ownership::new(&base);
        let coder = BlockCoder::new(&base, &Encoding::F32);
        // a group start past 2^32: the first child of a parent
        let group = f.child((P32 - f.n_base) / 8 + 3, 0);
        let mut ids = vec![
            0,
            5,
            finest - 1,
            finest,
            P32 - 1,
            P32,
            P32 + 1,
            group,
            group + 7,
        ];
        if nodes > P33 + 8 {
            ids.extend([P33, P33 + 8]);
        }
        ids.extend([nodes - 9, nodes - 1]);
        ids.sort_unstable();
        ids.dedup();
        let ns: Vec<_> = ids.iter().map(|&id| test_node(&own, id)).collect();
        let block = coder.encode(&ns).unwrap();
        assert_eq!((block.count as usize, block.first), (ids.len(), 0));
        let got = coder.decode(&block).unwrap();
        let want: Vec<_> = ns.into_iter().map(|n| decoded(n, finest)).collect();
        assert_eq!(got, want, "{c:?}");
        // one past the last node is refused
        let mut over = test_node(&own, nodes - 1);
        over.id = nodes;
        assert!(coder.encode(&[over]).is_err());
    }
}

/// The level set's near band codes keys past 2^32 (a gap to the first key and between keys) and
/// refuses a key at or beyond the vertex count.
#[test]
fn level_set_keys_past_2_32() {
    for c in [CASES[1], CASES[4]] {
        let n = c.vertices();
        let entries = [
            (0, 0.5),
            (P32 - 1, -0.25),
            (P32, FAR_OUTSIDE),
            (P32 + 1, 1.0),
            (P33 + 7, -1.0),
            (n - 1, 0.75),
        ];
        let set = NearLevelSet::new(0.25, entries).unwrap();
        let bytes = set.encode().unwrap();
        let back = NearLevelSet::decode(&bytes, n).unwrap();
        assert_eq!(back.iter().collect::<Vec<_>>(), entries);
        assert_eq!(back.get(P32), Some(FAR_OUTSIDE));
        assert_eq!(back.get(P32 + 2), None);
        assert_eq!(
            NearLevelSet::decode(&bytes, n - 1),
            Err(LevelSetError::KeyOutOfRange {
                key: n - 1,
                keys: n - 1
            })
        );
    }
}

/// A session's first frame for hierarchies past 2^32 nodes: its counts come back as the forest's.
#[test]
fn session_start_of_large_hierarchies() {
    for c in [CASES[0], CASES[1], CASES[2], CASES[4]] {
        let base = c.base();
        let m = manifest(&c, &base);
        let frame = encode(&ServerMsg::Start(Box::new(SessionStart {
            manifest: m.clone(),
            base: base.clone(),
        })))
        .unwrap();
        let ServerMsg::Start(st) = decode_server(&frame).unwrap() else {
            panic!("not a start")
        };
        assert_eq!(st.manifest.counts, m.counts, "{c:?}");
        assert_eq!(st.base, base);
    }
}

/// The axes predictor's grid at the largest box6 it takes (1025³ points, 10 levels): grid points
/// and vertex keys by arithmetic agree with the keys of the lattice points of every tet holding
/// them. (At 11 levels, 2049³ points, `axes::check_base` refuses the base today: a u32 per grid
/// point in `Grid::predict_all`'s key table; `axes.rs`'s own test pins that.)
#[test]
fn axes_grid_at_its_largest() {
    use tetwave_protocol::axes::Grid;
    let c = CASES[0];
    let mut base = c.base();
    base.predictor = Predictor::Axes;
    base.validate().unwrap();
    let keys = base.vertex_keys();
    let g = Grid::of(&base, &keys).unwrap();
    let grid = GridOf {
        base: &base,
        m: c.m(),
    };
    let m = c.m() as u64;
    let mut r = 11u64;
    let mut points: Vec<[u64; 3]> = vec![[0; 3], [m; 3], [m, 0, m], [m - 1, m, 1]];
    for _ in 0..500 {
        points.push(std::array::from_fn(|_| {
            r = splitmix(r);
            r % (m + 1)
        }));
    }
    for p in points {
        let q = p.map(|x| x as u32);
        for (t, w) in grid.holders(p) {
            assert_eq!(g.key(q), keys.key(t, &w) as usize, "{p:?}");
            assert_eq!(g.point(t, &w), q);
        }
    }
}
