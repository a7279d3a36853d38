//! View order from the top down: a session's walk of the hierarchy in the order its client will
//! split it, holding only the nodes it has reached (not arrays over every node).
//!
//! The walk is a best-first search from the base tets. A node in its frontier is one the client
//! will read: the child of a tet it splits under the view (the base tets: always) that it cannot
//! settle with its parent's subtree bound (a child that would stay unsplit even with that bound
//! is left unsplit without its node, as the client's selection does). Popping the
//! best sends it; if the client will split it too (inside the frustum, weighted screen-space
//! error over the tolerance, the criterion both sides share: [`tetwave_protocol::view`]), its 8
//! children join the frontier. What the walk never reaches is sent last, by increasing id.
//!
//! The image weight of a node needs its corner values and curvature. They are exact for nodes
//! of the first [`Coarse::level`] levels, whose vertex values the server synthesizes once (at
//! most [`COARSE_NODES`] nodes). Below, a node's values are enclosed instead: the tet at that
//! level holds its subtree's field within `(L − l) · smax` of its corners' range (each finer level
//! moves a value by at most its subtree bound from the linear midpoint, and the bound covers the
//! subtree), and a node's curvature is at most its parent's bound. The enclosure only widens the
//! range the transfer function's sensitivity is taken over, so the weight is never below the
//! exact one: a client's node is never ranked below where the exact weight puts it, only some
//! nodes it does not read are sent earlier.

use super::state::Shared;
use glam::DVec3;
use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::sync::Arc;
use tetwave_protocol::hierarchy::{Bary, LatticeTet, BEY_CHILDREN, EDGES};
use tetwave_protocol::vertex::VertexKeys;
use tetwave_protocol::view::{
    data_weight, image_bound, screen_error, tet_sphere, Camera, ImageCriterion, Tolerance, View,
};
use tetwave_protocol::wire::ViewParams;
use tetwave_protocol::{Forest, TetId};
use tetwave_store::{Store, StoreError};

/// Most nodes whose vertex values the server synthesizes for exact image weights ([`Coarse`]):
/// about 50 MB while they are decoded at start, a few MB kept.
pub const COARSE_NODES: u64 = 1 << 21;

/// Levels below a split node's children whose blocks are read ahead: a store in object storage
/// answers after a round trip, and the walk reaches those blocks soon after.
const READ_AHEAD_LEVELS: usize = 1;

/// Detail magnitude (relative to the value range) from which a node's data weight is full.
pub const DATA_DELTA: f32 = 0.01;

/// Factor on the priority of a node outside the view frustum, and floor of a weight: subtrees
/// that cannot change the image or are hidden go last among what the client reads.
const HIDDEN: f64 = 1e-6;
const WEIGHT_FLOOR: f64 = 1e-3;

/// The vertex values of the hierarchy's first `level` levels, synthesized from the store's
/// nodes of those levels (the predictors read only coarser values, so they are exact).
pub(super) struct Coarse {
    level: u8,
    /// `L − level`: a finest-lattice weight of a level-`level` point, shifted right by this, is
    /// its weight in this table's lattice.
    shift: u32,
    keys: VertexKeys,
    values: Vec<f32>,
}

impl Coarse {
    /// The deepest level whose nodes number at most `limit` ([`COARSE_NODES`] by default),
    /// synthesized.
    pub(super) fn build(store: &Store, limit: u64) -> Result<Coarse, StoreError> {
        let forest = store.forest();
        let mut level = 0u8;
        while level < forest.levels && forest.level_start(level + 1) <= limit {
            level += 1;
        }
        let mut base = store.base.clone();
        base.levels = level;
        let keys = base.vertex_keys();
        let nodes = store.read_nodes(0, forest.level_start(level))?;
        let values =
            tetwave_protocol::synthesis::synthesize_all(&base, &keys, nodes).map_err(|e| {
                StoreError::Corrupt {
                    path: store.dir.join("blocks.bin"),
                    reason: format!("its first {level} levels do not synthesize: {e}"),
                }
            })?;
        Ok(Coarse {
            level,
            shift: (forest.levels - level) as u32,
            keys,
            values,
        })
    }

    /// Only the base mesh's own values (level 0).
    pub(super) fn base_only(store: &Store) -> Coarse {
        let mut base = store.base.clone();
        base.levels = 0;
        Coarse {
            level: 0,
            shift: store.forest().levels as u32,
            keys: base.vertex_keys(),
            values: store.base.values.clone(),
        }
    }

    /// Levels whose vertices the table holds.
    pub(super) fn level(&self) -> u8 {
        self.level
    }

    /// The value of a point of level at most [`Self::level`].
    #[inline]
    fn value(&self, base: u32, w: &Bary) -> f32 {
        let w = w.map(|x| x >> self.shift);
        self.values[self.keys.key(base, &w) as usize]
    }
}

/// What ranks a node: its corner values' range (exact, or an enclosure), its curvature (the
/// largest deviation of its corners created at its level from the midpoint of the parent edge
/// each halves; infinite for a base tet) and its subtree bound (resolved).
#[derive(Debug, Clone, Copy)]
pub(super) struct Prior {
    lo: f32,
    hi: f32,
    curvature: f32,
    smax: f32,
}

/// How a session ranks nodes: its view, and the image criterion of its transfer function (`None`:
/// the data weight).
pub(super) struct Ranker {
    view: View,
    value_range: [f32; 2],
    image: Option<ImageCriterion>,
    coarse: Arc<Coarse>,
    forest: Forest,
}

impl Ranker {
    pub(super) fn new(s: &Shared, v: &ViewParams, image: Option<ImageCriterion>) -> Self {
        Ranker {
            view: View::new(&Camera::from_view_params(v), Tolerance::Pixels(v.tol_px)),
            value_range: s.store.manifest.value_range,
            image,
            coarse: s.coarse(),
            forest: s.forest(),
        }
    }

    /// The node's weight: its image weight (as `ImageCriterion::node_weight` computes it from
    /// exact corners), else its data weight.
    #[inline]
    fn weight(&self, p: &Prior, level: u8, diam: f64) -> f64 {
        match &self.image {
            Some(img) => {
                let bound = image_bound(self.forest.levels.saturating_sub(level), p.smax, {
                    if level == 0 {
                        f64::INFINITY
                    } else {
                        p.curvature as f64
                    }
                });
                img.weight(p.lo, p.hi, bound, diam) as f32 as f64
            }
            None => data_weight(p.smax, self.value_range, DATA_DELTA),
        }
    }

    /// Whether the client splits a tet with this sphere and prior: inside the frustum, with its
    /// weighted screen-space error (unfloored, as the client computes it) over the tolerance.
    #[inline]
    fn splits(&self, sphere: (DVec3, f64), p: &Prior, level: u8) -> bool {
        let (c, r) = sphere;
        self.view.sphere_visible(c, r)
            && screen_error(&self.view, c, r, self.weight(p, level, 2.0 * r)) > self.view.tol_px
    }

    /// The view-order priority: the screen-space error with the weight floored at
    /// [`WEIGHT_FLOOR`], × [`HIDDEN`] outside the frustum (larger goes first).
    #[inline]
    fn priority(&self, sphere: (DVec3, f64), p: &Prior, level: u8) -> f32 {
        let (c, r) = sphere;
        let w = self.weight(p, level, 2.0 * r).max(WEIGHT_FLOOR);
        let mut e = screen_error(&self.view, c, r, w);
        if !self.view.sphere_visible(c, r) {
            e *= HIDDEN;
        }
        if e.is_finite() {
            (e as f32).max(0.0)
        } else {
            f32::MAX
        }
    }

    /// The priors of the 8 children of tet `t` (level `level`, prior `p`), whose own subtree
    /// bounds are `smax` (resolved).
    fn children(&self, t: &LatticeTet, level: u8, p: &Prior, smax: [f32; 8]) -> [Prior; 8] {
        let exact = level < self.coarse.level;
        if exact {
            let pts = t.split_points();
            let v: [f32; 10] = std::array::from_fn(|i| self.coarse.value(t.base, &pts[i]));
            std::array::from_fn(|i| {
                let corners = BEY_CHILDREN[i];
                let mut curvature = 0.0f64;
                for &c in &corners {
                    if c >= 4 {
                        let (e0, e1) = EDGES[c - 4];
                        let mid = 0.5 * (v[e0] as f64 + v[e1] as f64);
                        curvature = curvature.max((v[c] as f64 - mid).abs());
                    }
                }
                let vals = corners.map(|c| v[c]);
                Prior {
                    lo: vals.iter().copied().fold(f32::INFINITY, f32::min),
                    hi: vals.iter().copied().fold(f32::NEG_INFINITY, f32::max),
                    curvature: curvature as f32,
                    smax: smax[i],
                }
            })
        } else {
            // below the table: the children's values lie in this tet's range widened by what
            // the levels below can move them (once, where the enclosure starts)
            let widen = if level == self.coarse.level {
                self.forest.levels.saturating_sub(level) as f32 * p.smax
            } else {
                0.0
            };
            std::array::from_fn(|i| Prior {
                lo: p.lo - widen,
                hi: p.hi + widen,
                curvature: p.smax,
                smax: smax[i],
            })
        }
    }

    /// The prior of base tet `b` (its subtree bound `smax`).
    fn base_prior(&self, base: &tetwave_protocol::BaseMesh, b: usize, smax: f32) -> Prior {
        let vals = base.tets[b].map(|v| base.values[v as usize]);
        Prior {
            lo: vals.iter().copied().fold(f32::INFINITY, f32::min),
            hi: vals.iter().copied().fold(f32::NEG_INFINITY, f32::max),
            curvature: f32::INFINITY,
            smax,
        }
    }
}

/// A tet's bounding sphere in world units, `f64` (as the client caches it: [`tet_sphere`]).
fn sphere(s: &Shared, t: &LatticeTet) -> (DVec3, f64) {
    let base = &s.store.base;
    let (c, r) = tet_sphere(t.v.map(|w| DVec3::from_array(base.position(t.base, &w))));
    (c.as_dvec3(), r as f64)
}

/// A priority as a frontier key: its `f32` bits (ordered as the non-negative floats) without
/// the low 19 of the mantissa's 23, so 16 steps an octave. Within a step the walk goes by
/// increasing id: nodes of about the same error leave together in store order, so a decoded
/// block serves all of its nodes the client reads, not the few of one region at a time (a
/// store in object storage pays a round trip a block).
#[inline]
fn bucket(priority: f32) -> u32 {
    priority.to_bits() >> 19
}

/// A frontier node: its priority bucket ([`bucket`]), id and prior.
struct Entry {
    key: u32,
    id: TetId,
    prior: Prior,
}

impl PartialEq for Entry {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o) == Ordering::Equal
    }
}
impl Eq for Entry {}
impl PartialOrd for Entry {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Entry {
    /// Larger priority first; ties: the smaller id first.
    fn cmp(&self, o: &Self) -> Ordering {
        self.key.cmp(&o.key).then(o.id.cmp(&self.id))
    }
}

/// One walk for one view (a new `View` starts a new walk).
pub(super) struct Walk {
    ranker: Ranker,
    frontier: BinaryHeap<Entry>,
    /// Nodes taken from the frontier, in its order, not yet handed out.
    ready: std::collections::VecDeque<TetId>,
}

/// Nodes a walk takes from its frontier at a time.
const GROUP: usize = 64;

impl Walk {
    /// A walk whose frontier is the base tets.
    pub(super) fn new(s: &Shared, ranker: Ranker) -> Result<Self, StoreError> {
        let base = &s.store.base;
        let n = base.tets.len() as TetId;
        let bounds = s.bounds(0, n, f32::INFINITY)?;
        let lattice = tetwave_protocol::hierarchy::Lattice {
            levels: ranker.forest.levels,
        };
        let mut frontier = BinaryHeap::with_capacity(n as usize);
        for (b, &smax) in bounds.iter().enumerate() {
            let prior = ranker.base_prior(base, b, smax);
            let t = LatticeTet::base_tet(lattice, b as u32);
            let key = bucket(ranker.priority(sphere(s, &t), &prior, 0));
            frontier.push(Entry {
                key,
                id: b as TetId,
                prior,
            });
        }
        Ok(Walk {
            ranker,
            frontier,
            ready: Default::default(),
        })
    }

    /// The best node of the frontier, its children added when the client will split it; `None`
    /// when the walk is over. Nodes leave the frontier [`GROUP`] at a time: the blocks their
    /// children lie in are asked for together (one round trip for the group from object
    /// storage), and a child joins the frontier at most a group late.
    pub(super) fn next(&mut self, s: &Shared) -> Result<Option<TetId>, StoreError> {
        if self.ready.is_empty() {
            self.pop_group(s)?;
        }
        Ok(self.ready.pop_front())
    }

    fn pop_group(&mut self, s: &Shared) -> Result<(), StoreError> {
        let forest = self.ranker.forest;
        let mut split = Vec::new();
        while self.ready.len() < GROUP {
            let Some(Entry { id, prior, .. }) = self.frontier.pop() else {
                break;
            };
            self.ready.push_back(id);
            let level = forest.level(id);
            // the finest node level's children are leaves: nothing to read below them
            if level + 1 < forest.levels {
                let t = LatticeTet::from_id(&forest, id);
                if self.ranker.splits(sphere(s, &t), &prior, level) {
                    let first = forest.child(id, 0);
                    s.prefetch(first, first + 8);
                    split.push((id, t, level, prior));
                }
            }
        }
        for (id, t, level, prior) in split {
            let first = forest.child(id, 0);
            let b = s.bounds(first, first + 8, prior.smax)?;
            // the blocks the next levels below will want, read meanwhile
            let (mut a, mut z) = (first, first + 8);
            for _ in 0..READ_AHEAD_LEVELS {
                (a, z) = (forest.child(a, 0), forest.child(z - 1, 7) + 1);
                if a >= s.nodes() {
                    break;
                }
                s.prefetch(a, z);
            }
            let priors = self
                .ranker
                .children(&t, level, &prior, std::array::from_fn(|i| b[i]));
            for (i, c) in t.children().iter().enumerate() {
                let sp = sphere(s, c);
                // a child that would stay unsplit even with its parent's bound is settled by the
                // client without its node (`Selector::stays_unsplit_without_node`): it is not
                // read, and waits for the tail
                let settled = Prior {
                    smax: prior.smax,
                    ..priors[i]
                };
                if !self.ranker.splits(sp, &settled, level + 1) {
                    continue;
                }
                let key = bucket(self.ranker.priority(sp, &priors[i], level + 1));
                self.frontier.push(Entry {
                    key,
                    id: first + i as TetId,
                    prior: priors[i],
                });
            }
        }
        Ok(())
    }
}

impl Shared {
    /// The nodes a view-order session's walk hands out for `view` and a client drawing with `tf`,
    /// in its order, until it ends (before the tail): what that client reads, for tests.
    pub fn view_walk(
        &self,
        view: &ViewParams,
        tf: super::ViewTf,
    ) -> Result<Vec<TetId>, StoreError> {
        let mut walk = Walk::new(self, Ranker::new(self, view, self.criterion(tf)))?;
        let mut out = Vec::new();
        while let Some(id) = walk.next(self)? {
            out.push(id);
        }
        Ok(out)
    }

    /// The view-order priority of each node `ids` for `view` and the image criterion `image`
    /// (`None`: data weights), each from its own path down the hierarchy: what a walk ranks it
    /// by when it reaches it (larger is sent first).
    pub(super) fn priorities_of(
        &self,
        view: &ViewParams,
        image: Option<ImageCriterion>,
        ids: std::ops::Range<TetId>,
    ) -> Result<Vec<f32>, StoreError> {
        let r = Ranker::new(self, view, image);
        let forest = r.forest;
        let mut out = Vec::with_capacity((ids.end - ids.start) as usize);
        for id in ids {
            let (b, digits) = forest.path(id);
            let mut t = LatticeTet::base_tet(
                tetwave_protocol::hierarchy::Lattice {
                    levels: forest.levels,
                },
                b,
            );
            let mut node = b as TetId;
            let mut p = r.base_prior(
                &self.store.base,
                b as usize,
                self.bounds(node, node + 1, f32::INFINITY)?[0],
            );
            for (level, &d) in digits.iter().enumerate() {
                let first = forest.child(node, 0);
                let bounds = self.bounds(first, first + 8, p.smax)?;
                p = r.children(&t, level as u8, &p, std::array::from_fn(|i| bounds[i]))[d as usize];
                t = t.child(d as usize);
                node = first + d as TetId;
            }
            out.push(r.priority(sphere(self, &t), &p, digits.len() as u8));
        }
        Ok(out)
    }
}
