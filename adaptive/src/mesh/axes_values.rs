//! Vertex values of a [`Predictor::Axes`] hierarchy: a vertex's prediction reads grid points
//! the mesh may not hold (3 steps along an axis, and its own level's points), so values are
//! synthesized by grid point, apart from the mesh, with the same rule as for the parent
//! predictor: `synthesize(d, P)` with `d` the coefficient held, or 0 while it has not arrived.
//! A value is exact (the server's) once every coefficient its stencils read, transitively, has
//! arrived.
//!
//! Values are memoized by key, in pages allocated when first written, so memory follows the
//! points a session touches (its mesh and the stencils around it), not the hierarchy's size. An
//! arriving node's coefficients can change only the points within [`DEPENDENCY_REACH`] of its
//! level's step around its edges' midpoints, so arrivals mark the bricks (cubes of [`BRICK`]³ grid
//! points) that box overlaps: a memoized value is valid while it is newer than its brick's last
//! mark, and a refresh recomputes the present vertices of marked bricks only.
//!
//! [`Predictor::Axes`]: tetwave_protocol::wavelet::Predictor::Axes

use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::axes::{along_axis, AxesError, Grid, Point, DEPENDENCY_REACH};
use tetwave_protocol::hierarchy::Bary;
use tetwave_protocol::wavelet::synthesize;
use tetwave_protocol::{BaseMesh, Forest, LatticeTet, TetId, VertexKeys};

/// Grid points per brick edge.
const BRICK: u32 = 8;
/// Keys per memo page.
const PAGE: usize = 1024;

type Page = Box<[(f32, u32); PAGE]>;

#[derive(Debug, Clone)]
pub(super) struct AxesValues {
    grid: Grid,
    forest: Forest,
    base: Vec<f32>,
    /// Per key: the memoized value and the generation it was computed in (0: never), by page.
    pages: Vec<Option<Page>>,
    /// Bricks per axis, and per brick the generation of its last mark (0: never).
    bricks: u32,
    marked: Vec<u32>,
    /// Arrived nodes not marked yet.
    pending: Vec<TetId>,
    /// The current generation: one per marking of arrivals.
    now: u32,
    /// The generation the mesh's values were last refreshed at.
    refreshed: u32,
}

impl AxesValues {
    pub(super) fn new(base: &BaseMesh, keys: &VertexKeys) -> Result<Self, AxesError> {
        let grid = Grid::of(base, keys)?;
        let bricks = (grid.m() + 1).div_ceil(BRICK);
        Ok(AxesValues {
            grid,
            forest: base.forest(),
            base: base.values.clone(),
            pages: vec![None; (keys.vertex_count() as usize).div_ceil(PAGE)],
            bricks,
            marked: vec![0; (bricks as usize).pow(3)],
            pending: Vec::new(),
            now: 1,
            refreshed: 1,
        })
    }

    /// The grid point of lattice point `w` of base tet `tet`.
    pub(super) fn point(&self, tet: u32, w: &Bary) -> Point {
        self.grid.point(tet, w)
    }

    #[inline]
    fn brick(&self, p: Point) -> usize {
        let b = self.bricks as usize;
        let q = p.map(|c| (c / BRICK) as usize);
        q[0] + b * (q[1] + b * q[2])
    }

    /// Nodes `ids` have arrived: [`Self::mark_arrived`] will mark what they can change (the
    /// network side only queues them; the frame loop marks and recomputes).
    pub(super) fn arrived(&mut self, ids: &[TetId]) {
        self.pending.extend_from_slice(ids);
    }

    /// Marks stale every value that the coefficients of the queued arrivals can change.
    pub(super) fn mark_arrived(&mut self) {
        if self.pending.is_empty() {
            return;
        }
        let ids = std::mem::take(&mut self.pending);
        if self.now == u32::MAX {
            // (after 2^32 batches) start the generations again
            self.pages
                .iter_mut()
                .flatten()
                .for_each(|p| p.fill((0.0, 0)));
            self.marked.fill(0);
            self.now = 1;
            self.refreshed = 0;
        }
        self.now += 1;
        let (m, b) = (self.grid.m(), self.bricks);
        let mut everything = false;
        for &id in &ids {
            // the node's coefficients are at its edges' midpoints, inside its tet, made with
            // step m / 2^(level+1): one box, the tet's bounds and the reach around them
            let s = m >> (self.forest.level(id) + 1);
            let r = DEPENDENCY_REACH.saturating_mul(s);
            let lt = LatticeTet::from_id(&self.forest, id);
            let corners = lt.v.map(|w| self.grid.point(lt.base, &w));
            let bound = |a: usize, f: fn(u32, u32) -> u32| corners.iter().map(|p| p[a]).reduce(f);
            let lo: [u32; 3] =
                std::array::from_fn(|a| bound(a, u32::min).unwrap_or(0).saturating_sub(r) / BRICK);
            let hi: [u32; 3] = std::array::from_fn(|a| {
                bound(a, u32::max).unwrap_or(0).saturating_add(r).min(m) / BRICK
            });
            if lo == [0; 3] && hi == [b - 1; 3] {
                // (a coarse node reaches every brick: mark them once, below)
                everything = true;
                continue;
            }
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        self.marked[(x + b * (y + b * z)) as usize] = self.now;
                    }
                }
            }
        }
        if everything {
            self.marked.fill(self.now);
        }
        self.pending = ids;
        self.pending.clear();
    }

    /// Whether the value at point `p` may have changed since the last [`Self::refreshed`].
    #[inline]
    pub(super) fn stale(&self, p: Point) -> bool {
        self.marked[self.brick(p)] > self.refreshed
    }

    /// Whether any value may have changed since the last [`Self::refreshed`] (after
    /// [`Self::mark_arrived`]).
    pub(super) fn any_stale(&self) -> bool {
        self.now > self.refreshed
    }

    /// Whether arrivals wait to be marked, or marked values to be recomputed.
    pub(super) fn behind(&self) -> bool {
        !self.pending.is_empty() || self.any_stale()
    }

    /// The mesh's values are current again.
    pub(super) fn refreshed(&mut self) {
        self.refreshed = self.now;
    }

    /// The value of vertex `key` at grid point `p` from the coefficients `buf` holds.
    pub(super) fn value(&mut self, key: usize, p: Point, buf: &DetailBuffer) -> f32 {
        if key < self.base.len() {
            return self.base[key];
        }
        let (page, slot) = (key / PAGE, key % PAGE);
        if let Some(pg) = &self.pages[page] {
            let (v, t) = pg[slot];
            if t != 0 && t >= self.marked[self.brick(p)] {
                return v;
            }
        }
        let st = self.grid.stencil(p).expect("a non-base key has a stencil");
        // the stencil's points come earlier in the order, so the recursion ends (its depth is
        // at most 3 passes per level)
        let mut at = |q: Point| self.value(self.grid.key(q), q, buf);
        let a = st[0].map(&mut at);
        let b = at(st[1].expect("inside"));
        let c = at(st[2].expect("inside"));
        let d = st[3].map(&mut at);
        let v = synthesize(buf.coeff(key as u64).unwrap_or(0.0), along_axis(a, b, c, d));
        let now = self.now;
        self.pages[page].get_or_insert_with(|| Box::new([(0.0, 0); PAGE]))[slot] = (v, now);
        v
    }

    /// Bytes held.
    pub(super) fn bytes(&self) -> usize {
        self.pages.len() * 8
            + self.pages.iter().flatten().count() * PAGE * 8
            + self.marked.len() * 4
            + self.pending.capacity() * 8
    }
}
