//! The client's detail buffer: every detail node received so far, in whatever order it came.
//!
//! Nodes may arrive in any order, repeated (duplicates are ignored and counted) and with gaps. A node is
//! validated ([`DetailNode::validate`], id inside the forest, owned vertices not already owned by
//! another node) and then stored twice over:
//!
//! - its coefficients **by vertex key**: owned local edge `e` of tet `t` gives the key of
//!   `t`'s edge midpoint `e` ([`VertexKeys::key`]), so the adaptive mesh asks "coefficient of vertex
//!   `k`" without knowing which (possibly neighbouring) tet owns it;
//! - its **metadata** by tet id (`subtree_max_abs`, `empty_children`, owned mask), for selection.
//!
//! A node whose parent has not arrived yet is *pending*: it is kept, and becomes *usable*
//! ([`DetailBuffer::is_usable`]) once all its ancestors are present.
//!
//! A *preview* node ([`DetailBuffer::insert_preview`]: a coarse copy from the store's preview) is
//! held like any other until the store's own node with its id arrives and replaces it: its
//! coefficients are overwritten (and reported as arrivals, so values are recomputed) and its
//! metadata too. Preview nodes count as present for usability, but not as held:
//! [`DetailBuffer::missing_ranges`] lists them and [`DetailBuffer::nodes_held`] leaves them out,
//! so a session is complete only with every node of the store's own.

use rustc_hash::FxHashMap;
use tetwave_protocol::hierarchy::EDGES;
use tetwave_protocol::node::{resolve_bound, NodeError};
use tetwave_protocol::wire::IdRange;
use tetwave_protocol::{DetailNode, Forest, LatticeTet, TetId, VertexKeys};

/// Per-node metadata kept after the coefficients have been moved to the by-key table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeMeta {
    pub subtree_max_abs: f32,
    pub empty_children: u8,
    pub owned: u8,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BufferError {
    #[error("node {id} is beyond the hierarchy's {nodes} nodes")]
    OutOfRange { id: TetId, nodes: u64 },
    #[error(transparent)]
    Invalid(#[from] NodeError),
    #[error("node {id} claims vertex {key}, which another node already owns")]
    OwnedTwice { id: TetId, key: u64 },
    #[error("node {id} owns edges {got:#08b}, its preview owned {preview:#08b}")]
    NotItsPreview { id: TetId, got: u8, preview: u8 },
}

/// What one [`DetailBuffer::insert`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Inserted {
    /// A node not seen before.
    New,
    /// The id was already held; the node was ignored.
    Duplicate,
    /// The store's node replaced the preview node held for its id.
    Replaced,
}

/// What arrived since the mesh last looked: vertex keys that got a coefficient and node ids that got
/// metadata. [`DetailBuffer::insert`] appends to it; `AdaptiveMesh::apply_arrivals` consumes it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Arrivals {
    pub keys: Vec<u64>,
    pub nodes: Vec<TetId>,
    /// Of `nodes`, those whose preview was replaced: their metadata changed, not only appeared.
    pub replaced: Vec<TetId>,
}

impl Arrivals {
    pub fn clear(&mut self) {
        self.keys.clear();
        self.nodes.clear();
        self.replaced.clear();
    }
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty() && self.nodes.is_empty()
    }
}

impl NodeMeta {
    /// What the buffer keeps of `node` besides its coefficients.
    fn of(node: &DetailNode) -> Self {
        NodeMeta {
            subtree_max_abs: node.subtree_max_abs,
            empty_children: node.empty_children,
            owned: node.owned,
        }
    }
}

/// A value an [`IdTable`] can hold, with a bit pattern that means "absent".
trait Cell: Copy {
    const EMPTY: Self;
    fn is_empty(&self) -> bool;
}

/// Coefficients are finite ([`DetailNode::validate`]): NaN marks an absent one.
impl Cell for f32 {
    const EMPTY: f32 = f32::NAN;
    #[inline]
    fn is_empty(&self) -> bool {
        self.is_nan()
    }
}

/// Subtree maxima are finite or infinite, never NaN ([`DetailNode::validate`]): NaN marks an
/// absent node.
impl Cell for NodeMeta {
    const EMPTY: NodeMeta = NodeMeta {
        subtree_max_abs: f32::NAN,
        empty_children: 0,
        owned: 0,
    };
    #[inline]
    fn is_empty(&self) -> bool {
        self.subtree_max_abs.is_nan()
    }
}

const PAGE_BITS: u32 = 9;
const PAGE: usize = 1 << PAGE_BITS;
const NO_PAGE: u32 = u32::MAX;
/// Keys below this go to [`IdTable`]'s pages (a directory of at most 2^23 entries); the others
/// (forests of more than 2^32 nodes or vertices) to its hash map.
const DENSE_KEYS: u64 = 1 << 32;

/// A map from node ids (or vertex keys) to values, in pages of [`PAGE`] consecutive keys made on
/// first insert: ids and keys are dense (a level's ids are consecutive, and so are a node's
/// children), so a lookup reads one line of one page. The hash maps it replaced read two lines per
/// probe (control bytes, then the bucket), at the selection's and the refinement's hottest spots:
/// a leaf's subtree max and usability, a new vertex's coefficient, a child's emptiness.
#[derive(Debug, Clone)]
struct IdTable<V> {
    /// Page index by key / [`PAGE`] ([`NO_PAGE`]: none), grown to the largest page used.
    dir: Vec<u32>,
    pages: Vec<Box<[V]>>,
    sparse: FxHashMap<u64, V>,
    len: usize,
}

impl<V: Cell> IdTable<V> {
    fn new() -> Self {
        IdTable {
            dir: Vec::new(),
            pages: Vec::new(),
            sparse: FxHashMap::default(),
            len: 0,
        }
    }

    #[inline]
    fn get(&self, k: u64) -> Option<V> {
        if k >= DENSE_KEYS {
            return self.sparse.get(&k).copied();
        }
        match self.dir.get((k >> PAGE_BITS) as usize) {
            Some(&p) if p != NO_PAGE => {
                let v = self.pages[p as usize][k as usize & (PAGE - 1)];
                (!v.is_empty()).then_some(v)
            }
            _ => None,
        }
    }

    #[inline]
    fn contains_key(&self, k: u64) -> bool {
        self.get(k).is_some()
    }

    /// Sets key `k` to `v` (not [`Cell::EMPTY`]), present or not.
    fn insert(&mut self, k: u64, v: V) {
        debug_assert!(!v.is_empty());
        if !self.contains_key(k) {
            self.len += 1;
        }
        if k >= DENSE_KEYS {
            self.sparse.insert(k, v);
            return;
        }
        let d = (k >> PAGE_BITS) as usize;
        if d >= self.dir.len() {
            self.dir.resize(d + 1, NO_PAGE);
        }
        if self.dir[d] == NO_PAGE {
            self.dir[d] = self.pages.len() as u32;
            self.pages.push(vec![V::EMPTY; PAGE].into_boxed_slice());
        }
        self.pages[self.dir[d] as usize][k as usize & (PAGE - 1)] = v;
    }

    fn len(&self) -> usize {
        self.len
    }

    /// The keys present, ascending: the pages in order, then the sparse keys (all above the
    /// pages') sorted.
    fn keys(&self) -> impl Iterator<Item = u64> + '_ {
        let dense = self
            .dir
            .iter()
            .enumerate()
            .filter(|&(_, &p)| p != NO_PAGE)
            .flat_map(move |(d, &p)| {
                let page = &self.pages[p as usize];
                (0..PAGE)
                    .filter(move |&i| !page[i].is_empty())
                    .map(move |i| ((d << PAGE_BITS) + i) as u64)
            });
        let mut sparse: Vec<u64> = self.sparse.keys().copied().collect();
        sparse.sort_unstable();
        dense.chain(sparse)
    }

    fn bytes(&self) -> usize {
        use std::mem::size_of;
        self.dir.capacity() * 4
            + self.pages.capacity() * size_of::<Box<[V]>>()
            + self.pages.len() * PAGE * size_of::<V>()
            + self.sparse.capacity() * (size_of::<(u64, V)>() + 1)
    }
}

/// All detail nodes received so far (see the module docs).
#[derive(Debug, Clone)]
pub struct DetailBuffer {
    forest: Forest,
    keys: VertexKeys,
    coeffs: IdTable<f32>,
    meta: IdTable<NodeMeta>,
    /// Ids held as preview nodes (replaced by the store's own when they arrive).
    previews: rustc_hash::FxHashSet<TetId>,
    /// Nodes inserted or replaced so far: what a cache of presence compares against.
    generation: u64,
    duplicates: u64,
    pending: u64,
}

impl DetailBuffer {
    pub fn new(forest: Forest, keys: VertexKeys) -> Self {
        DetailBuffer {
            forest,
            keys,
            coeffs: IdTable::new(),
            meta: IdTable::new(),
            previews: Default::default(),
            generation: 0,
            duplicates: 0,
            pending: 0,
        }
    }

    pub fn forest(&self) -> Forest {
        self.forest
    }

    pub fn vertex_keys(&self) -> &VertexKeys {
        &self.keys
    }

    /// Validates and stores `node`; appends the vertex keys that newly got a coefficient and the node's
    /// id to `arrivals` (nothing is appended for a duplicate or an error). On error nothing is stored.
    pub fn insert(
        &mut self,
        node: &DetailNode,
        arrivals: &mut Arrivals,
    ) -> Result<Inserted, BufferError> {
        let nodes = self.forest.nodes();
        if node.id >= nodes {
            return Err(BufferError::OutOfRange { id: node.id, nodes });
        }
        node.validate()?;
        if self.previews.contains(&node.id) {
            return self.replace_preview(node, arrivals);
        }
        if self.meta.contains_key(node.id) {
            self.duplicates += 1;
            return Ok(Inserted::Duplicate);
        }
        // keys first, so that a bad node changes nothing
        let mut owned = [(0u64, 0f32); 6];
        let mut n = 0;
        if node.owned != 0 {
            let tet = LatticeTet::from_id(&self.forest, node.id);
            for e in 0..EDGES.len() {
                if let Some(d) = node.coeff(e) {
                    let key = self.keys.key(tet.base, &tet.edge_midpoint(e));
                    if self.coeffs.contains_key(key) || owned[..n].iter().any(|p| p.0 == key) {
                        return Err(BufferError::OwnedTwice { id: node.id, key });
                    }
                    owned[n] = (key, d);
                    n += 1;
                }
            }
        }
        for &(key, d) in &owned[..n] {
            self.coeffs.insert(key, d);
            arrivals.keys.push(key);
        }
        arrivals.nodes.push(node.id);
        self.generation += 1;
        self.meta.insert(node.id, NodeMeta::of(node));
        // pending bookkeeping: this node waits for its parent; its children stop waiting for it
        if let Some(p) = self.forest.parent(node.id) {
            if !self.meta.contains_key(p) {
                self.pending += 1;
            }
        }
        for i in 0..8 {
            let c = self.forest.child(node.id, i);
            if self.meta.contains_key(c) {
                self.pending -= 1;
            }
        }
        Ok(Inserted::New)
    }

    /// Holds preview node `node` until the store's own arrives ([`Self::insert`] replaces it);
    /// ignored (a duplicate) when the id is already held, as a preview or as the store's node.
    pub fn insert_preview(
        &mut self,
        node: &DetailNode,
        arrivals: &mut Arrivals,
    ) -> Result<Inserted, BufferError> {
        // (an id beyond the hierarchy is held by no one: `insert` refuses it)
        if self.meta.contains_key(node.id) {
            self.duplicates += 1;
            return Ok(Inserted::Duplicate);
        }
        let got = self.insert(node, arrivals)?;
        if got == Inserted::New {
            self.previews.insert(node.id);
        }
        Ok(got)
    }

    /// The store's node `node` replaces the preview held for its id: same owned edges, so the
    /// same vertex keys, whose coefficients change.
    fn replace_preview(
        &mut self,
        node: &DetailNode,
        arrivals: &mut Arrivals,
    ) -> Result<Inserted, BufferError> {
        let held = self.meta.get(node.id).expect("a preview is held");
        if held.owned != node.owned {
            return Err(BufferError::NotItsPreview {
                id: node.id,
                got: node.owned,
                preview: held.owned,
            });
        }
        let tet = LatticeTet::from_id(&self.forest, node.id);
        for e in 0..EDGES.len() {
            if let Some(d) = node.coeff(e) {
                let key = self.keys.key(tet.base, &tet.edge_midpoint(e));
                self.coeffs.insert(key, d);
                arrivals.keys.push(key);
            }
        }
        self.meta.insert(node.id, NodeMeta::of(node));
        arrivals.nodes.push(node.id);
        arrivals.replaced.push(node.id);
        self.generation += 1;
        self.previews.remove(&node.id);
        Ok(Inserted::Replaced)
    }

    /// How many nodes were inserted or replaced so far: presence, usability or a node's metadata
    /// may have changed since a reader saw another value.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Preview nodes held (not yet replaced by the store's own).
    pub fn previews_held(&self) -> u64 {
        self.previews.len() as u64
    }

    /// Whether node `t` has arrived (as the store's node or a preview of it).
    #[inline]
    pub fn is_present(&self, t: TetId) -> bool {
        self.meta.contains_key(t)
    }

    /// Whether node `t` is held as a preview (not yet replaced by the store's own).
    #[inline]
    pub fn is_preview(&self, t: TetId) -> bool {
        self.previews.contains(&t)
    }

    /// The ids of the hierarchy's nodes not held, as ascending disjoint ranges. The walk takes time
    /// in the nodes held (and their pages), never in the hierarchy's size: a hierarchy of a
    /// billion nodes with none held is one range.
    pub fn missing_ranges(&self) -> impl Iterator<Item = IdRange> + '_ {
        let nodes = self.forest.nodes();
        let mut next = 0u64;
        // every id held is below `nodes` (insert refuses the others); a preview is missing still
        let mut held = self.meta.keys().filter(|id| !self.previews.contains(id));
        std::iter::from_fn(move || loop {
            if next >= nodes {
                return None;
            }
            let from = next;
            match held.next() {
                Some(id) if id == next => next += 1,
                Some(id) => {
                    next = id + 1;
                    return Some(IdRange { from, to: id });
                }
                None => {
                    next = nodes;
                    return Some(IdRange { from, to: nodes });
                }
            }
        })
    }

    /// Whether `t` and all its ancestors have arrived.
    pub fn is_usable(&self, t: TetId) -> bool {
        let mut cur = Some(t);
        while let Some(c) = cur {
            if !self.meta.contains_key(c) {
                return false;
            }
            cur = self.forest.parent(c);
        }
        true
    }

    /// Metadata of node `t`, if it arrived.
    #[inline]
    pub fn meta(&self, t: TetId) -> Option<NodeMeta> {
        self.meta.get(t)
    }

    /// Max |detail| of `t`'s subtree, if `t` arrived: its own bound, or for a finest-level node
    /// (which arrives without one) its parent's ([`resolve_bound`]; infinite until the parent
    /// has arrived).
    #[inline]
    pub fn subtree_max(&self, t: TetId) -> Option<f32> {
        let own = self.meta.get(t)?.subtree_max_abs;
        Some(resolve_bound(own, || {
            self.forest
                .parent(t)
                .and_then(|p| self.meta.get(p))
                .map(|m| m.subtree_max_abs)
        }))
    }

    /// Whether child `i` of `t` is known to be empty (false while `t` has not arrived).
    #[inline]
    pub fn child_empty(&self, t: TetId, i: usize) -> bool {
        self.meta
            .get(t)
            .is_some_and(|m| m.empty_children & (1 << i) != 0)
    }

    /// Coefficient of vertex `key`, if its owner node arrived.
    #[inline]
    pub fn coeff(&self, key: u64) -> Option<f32> {
        self.coeffs.get(key)
    }

    /// The store's nodes held (pending ones included; previews not).
    pub fn nodes_held(&self) -> u64 {
        (self.meta.len() - self.previews.len()) as u64
    }

    /// Nodes held whose parent has not arrived.
    pub fn nodes_pending(&self) -> u64 {
        self.pending
    }

    /// Coefficients held.
    pub fn coeffs_held(&self) -> u64 {
        self.coeffs.len() as u64
    }

    /// Duplicate nodes ignored so far.
    pub fn duplicates(&self) -> u64 {
        self.duplicates
    }

    /// Bytes held by the two tables (pages, directories and capacities) and the preview ids.
    pub fn bytes_held(&self) -> usize {
        self.coeffs.bytes()
            + self.meta.bytes()
            + self.previews.capacity() * (std::mem::size_of::<TetId>() + 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_protocol::hierarchy::Lattice;

    fn setup() -> DetailBuffer {
        let tets = vec![[0, 1, 2, 3]];
        let keys = VertexKeys::new(4, &tets, Lattice { levels: 2 });
        DetailBuffer::new(Forest::new(1, 2), keys)
    }

    fn node(id: TetId, owned: u8) -> DetailNode {
        DetailNode {
            id,
            owned,
            empty_children: 0,
            subtree_max_abs: 1.0,
            coeffs: (0..owned.count_ones()).map(|i| i as f32 + 0.5).collect(),
        }
    }

    /// The paged table against a hash map, over keys on shared and separate pages, beyond the
    /// directory's end and past the dense range.
    #[test]
    fn id_table_matches_a_map() {
        let mut t: IdTable<f32> = IdTable::new();
        let mut m = std::collections::HashMap::new();
        let keys = [
            0u64,
            1,
            PAGE as u64 - 1,
            PAGE as u64,
            7 * PAGE as u64 + 3,
            DENSE_KEYS - 1,
            DENSE_KEYS,
            u64::MAX,
        ];
        for (i, &k) in keys.iter().enumerate() {
            assert_eq!(t.get(k), None);
            t.insert(k, i as f32 - 3.5);
            m.insert(k, i as f32 - 3.5);
            assert_eq!(t.len(), m.len());
            for probe in keys
                .iter()
                .copied()
                .chain([2, 5 * PAGE as u64, DENSE_KEYS + 1])
            {
                assert_eq!(t.get(probe), m.get(&probe).copied(), "key {probe}");
            }
        }
        assert!(t.bytes() >= 3 * PAGE * 4);
    }

    #[test]
    fn pending_duplicates_usable() {
        let mut b = setup();
        let mut arr = Arrivals::default();
        // child 1 + 8*0 = 1 .. 8 are level 1; node 3's parent is 0
        assert_eq!(b.insert(&node(3, 0b001000), &mut arr), Ok(Inserted::New));
        assert_eq!(b.nodes_pending(), 1);
        assert!(!b.is_usable(3));
        assert_eq!(arr.keys.len(), 1);
        assert_eq!(
            b.insert(&node(3, 0b001000), &mut arr),
            Ok(Inserted::Duplicate)
        );
        assert_eq!(b.duplicates(), 1);
        assert_eq!(arr.keys.len(), 1);
        assert_eq!(b.insert(&node(0, 0b111111), &mut arr), Ok(Inserted::New));
        assert_eq!(b.nodes_pending(), 0);
        assert!(b.is_usable(3));
        assert!(!b.is_usable(4));
        assert_eq!(arr.keys.len(), 7);
        assert_eq!(b.coeffs_held(), 7);
        assert_eq!(b.nodes_held(), 2);
        assert!(b.bytes_held() > 0);
        for &k in &arr.keys {
            assert!(b.coeff(k).is_some());
        }
    }

    /// A finest-level node arrives without a bound of its own: its parent's stands in once the
    /// parent has arrived, and until then an infinite one (full weight, never "flat").
    #[test]
    fn a_finest_node_takes_its_parents_bound() {
        use tetwave_protocol::node::INHERITED_BOUND;
        let mut b = setup();
        let mut arr = Arrivals::default();
        let child = DetailNode {
            subtree_max_abs: INHERITED_BOUND,
            ..node(3, 0b001000)
        };
        b.insert(&child, &mut arr).unwrap();
        assert_eq!(b.subtree_max(3), Some(f32::INFINITY));
        let parent = DetailNode {
            subtree_max_abs: 0.25,
            ..node(0, 0b111111)
        };
        b.insert(&parent, &mut arr).unwrap();
        assert_eq!(b.subtree_max(3), Some(0.25));
        assert_eq!(b.subtree_max(0), Some(0.25));
        assert_eq!(b.subtree_max(4), None);
    }

    /// A preview node is present and usable but not held; the store's node replaces it (its
    /// coefficients and bound change, reported as arrivals), once; a preview after the store's
    /// node is ignored; a store's node owning other edges than its preview is refused.
    #[test]
    fn a_preview_is_held_until_the_stores_node_replaces_it() {
        let mut b = setup();
        let mut arr = Arrivals::default();
        let r = |from, to| IdRange { from, to };
        let coarse = DetailNode {
            coeffs: vec![0.0; 6],
            subtree_max_abs: 2.0,
            ..node(0, 0b111111)
        };
        assert_eq!(b.insert_preview(&coarse, &mut arr), Ok(Inserted::New));
        assert!(b.is_present(0) && b.is_usable(0));
        assert_eq!((b.nodes_held(), b.previews_held()), (0, 1));
        assert_eq!(b.missing_ranges().collect::<Vec<_>>(), [r(0, 9)]);
        assert_eq!(b.subtree_max(0), Some(2.0));
        let key = arr.keys[0];
        assert_eq!(b.coeff(key), Some(0.0));
        // a preview again, and a child's: the same rules as the store's nodes
        assert_eq!(b.insert_preview(&coarse, &mut arr), Ok(Inserted::Duplicate));
        assert_eq!(
            b.insert_preview(&node(3, 0b001000), &mut arr),
            Ok(Inserted::New)
        );
        assert_eq!(b.nodes_pending(), 0);

        // another mask: refused, nothing changes
        let generation = b.generation();
        assert!(matches!(
            b.insert(&node(0, 0b011111), &mut arr),
            Err(BufferError::NotItsPreview { id: 0, .. })
        ));
        assert_eq!((b.generation(), b.coeff(key)), (generation, Some(0.0)));

        arr.clear();
        assert_eq!(
            b.insert(&node(0, 0b111111), &mut arr),
            Ok(Inserted::Replaced)
        );
        assert_eq!((arr.keys.len(), arr.nodes.as_slice()), (6, &[0][..]));
        assert_eq!(arr.replaced, [0]);
        assert_eq!(b.coeff(key), Some(0.5));
        assert_eq!(b.subtree_max(0), Some(1.0));
        assert_eq!(b.coeffs_held(), 7);
        assert_eq!((b.nodes_held(), b.previews_held()), (1, 1));
        assert!(b.generation() > generation);
        assert_eq!(b.missing_ranges().collect::<Vec<_>>(), [r(1, 9)]);
        // held now: the store's node again and a late preview are duplicates
        assert_eq!(
            b.insert(&node(0, 0b111111), &mut arr),
            Ok(Inserted::Duplicate)
        );
        assert_eq!(b.insert_preview(&coarse, &mut arr), Ok(Inserted::Duplicate));
        assert_eq!(b.coeff(key), Some(0.5));
    }

    /// The ids not held, as ranges: all of them at first, then the gaps around what arrived.
    #[test]
    fn missing_ranges_are_the_gaps() {
        let mut b = setup();
        let r = |from, to| IdRange { from, to };
        assert_eq!(b.missing_ranges().collect::<Vec<_>>(), [r(0, 9)]);
        let mut arr = Arrivals::default();
        b.insert(&node(3, 0b001000), &mut arr).unwrap();
        assert_eq!(b.missing_ranges().collect::<Vec<_>>(), [r(0, 3), r(4, 9)]);
        b.insert(&node(0, 0b111111), &mut arr).unwrap();
        b.insert(&node(8, 0), &mut arr).unwrap();
        assert_eq!(b.missing_ranges().collect::<Vec<_>>(), [r(1, 3), r(4, 8)]);
        for id in [1, 2, 4, 5, 6, 7] {
            b.insert(&node(id, 0), &mut arr).unwrap();
        }
        assert_eq!(b.missing_ranges().count(), 0);
    }

    #[test]
    fn rejects_bad_nodes_without_side_effects() {
        let mut b = setup();
        let mut arr = Arrivals::default();
        assert!(matches!(
            b.insert(&node(9, 0), &mut arr),
            Err(BufferError::OutOfRange { .. })
        ));
        let mut bad = node(0, 0b11);
        bad.coeffs.pop();
        assert!(matches!(
            b.insert(&bad, &mut arr),
            Err(BufferError::Invalid(_))
        ));
        b.insert(&node(0, 0b111111), &mut arr).unwrap();
        // child 0 of tet 0 (id 1) shares edge midpoints' parents with none of the base edges'
        // midpoints, but a second node claiming a base-edge midpoint is an error
        let before = (b.coeffs_held(), arr.keys.len());
        // tet 1 = child 0: [x0, x01, x02, x03]; its edge (0,1) midpoint is new (level 2), so fine;
        // claim it twice via two nodes: 1 owns edge 0, then 1 is duplicate → ignored.
        b.insert(&node(1, 0b000001), &mut arr).unwrap();
        assert_eq!(b.coeffs_held(), before.0 + 1);
        // node 5 = child 4 = [x01,x02,x03,x13]: edge (0,1) is x01-x02, whose midpoint is new too;
        // node 2 = child 1 = [x01, x1, x12, x13]; its edge (0,1) = x01-x1; distinct from node 1's.
        // Node 8 = child 7 = [x02,x12,x13,x23]; claim an edge shared with child 5 = [x01,x02,x12,x13]
        // (edge x02-x12 is edge (0,1) of child 7 and edge (1,2) of child 5).
        b.insert(&node(8, 0b000001), &mut arr).unwrap();
        let n = b.coeffs_held();
        assert!(matches!(
            b.insert(&node(6, 0b001000), &mut arr),
            Err(BufferError::OwnedTwice { .. })
        ));
        assert_eq!(b.coeffs_held(), n);
        assert!(!b.is_present(6));
    }
}
