//! Vertex values of a [`Predictor::Axes`] hierarchy: a vertex's prediction reads grid points
//! the mesh may not hold (3 steps along an axis, and its own level's points), so values are
//! synthesized by vertex key, apart from the mesh, with the same rule as for the parent
//! predictor: `synthesize(d, P)` with `d` the coefficient held, or 0 while it has not arrived.
//! A value is exact (the server's) once every coefficient its stencils read, transitively, has
//! arrived.
//!
//! Values are memoized by key. An arriving coefficient can change only the vertices within
//! [`DEPENDENCY_REACH`] of its level's step around it, so arrivals mark the bricks (cubes of
//! [`BRICK`]³ grid points) that box overlaps: a memoized value is valid while it is newer than
//! its brick's last mark, and a refresh recomputes the present vertices of marked bricks only.
//!
//! [`Predictor::Axes`]: tetwave_protocol::wavelet::Predictor::Axes

use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::axes::{along_axis, AxesError, Grid, DEPENDENCY_REACH};
use tetwave_protocol::wavelet::synthesize;
use tetwave_protocol::{BaseMesh, VertexKeys};

/// Grid points per brick edge.
const BRICK: u32 = 8;

#[derive(Debug, Clone)]
pub(super) struct AxesValues {
    grid: Grid,
    base: Vec<f32>,
    /// Per key: the memoized value and when it was computed (0: never).
    memo: Vec<f32>,
    stamp: Vec<u32>,
    /// Bricks per axis, and per brick the generation of its last mark (0: never).
    bricks: u32,
    marked: Vec<u32>,
    /// The current generation: one per batch of arrivals.
    now: u32,
    /// The generation the mesh's values were last refreshed at.
    refreshed: u32,
}

impl AxesValues {
    pub(super) fn new(base: &BaseMesh, keys: &VertexKeys) -> Result<Self, AxesError> {
        let n = keys.vertex_count() as usize;
        let grid = Grid::of(base, keys)?;
        let bricks = (grid.m() + 1).div_ceil(BRICK);
        Ok(AxesValues {
            grid,
            base: base.values.clone(),
            memo: vec![0.0; n],
            stamp: vec![0; n],
            bricks,
            marked: vec![0; (bricks as usize).pow(3)],
            now: 1,
            refreshed: 1,
        })
    }

    #[inline]
    fn brick(&self, key: usize) -> usize {
        let p = self.grid.point(key).map(|c| (c / BRICK) as usize);
        let b = self.bricks as usize;
        p[0] + b * (p[1] + b * p[2])
    }

    /// Coefficients of `keys` have arrived: every value that can read them is marked stale.
    pub(super) fn arrived(&mut self, keys: &[u64]) {
        if keys.is_empty() {
            return;
        }
        if self.now == u32::MAX {
            // (after 2^32 batches) start the generations again
            self.stamp.fill(0);
            self.marked.fill(0);
            self.now = 1;
            self.refreshed = 0;
        }
        self.now += 1;
        let (m, b) = (self.grid.m(), self.bricks);
        for &k in keys {
            let Some((s, _)) = self.grid.step_and_axis(k as usize) else {
                continue;
            };
            let p = self.grid.point(k as usize);
            let r = DEPENDENCY_REACH.saturating_mul(s);
            let lo = p.map(|c| c.saturating_sub(r) / BRICK);
            let hi = p.map(|c| c.saturating_add(r).min(m) / BRICK);
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        self.marked[(x + b * (y + b * z)) as usize] = self.now;
                    }
                }
            }
        }
    }

    /// Whether vertex `key`'s value may have changed since the last [`Self::refreshed`].
    #[inline]
    pub(super) fn stale(&self, key: usize) -> bool {
        key >= self.base.len() && self.marked[self.brick(key)] > self.refreshed
    }

    /// Whether any value may have changed since the last [`Self::refreshed`].
    pub(super) fn any_stale(&self) -> bool {
        self.now > self.refreshed
    }

    /// The mesh's values are current again.
    pub(super) fn refreshed(&mut self) {
        self.refreshed = self.now;
    }

    /// The value of vertex `key` from the coefficients `buf` holds.
    pub(super) fn value(&mut self, key: usize, buf: &DetailBuffer) -> f32 {
        if key < self.base.len() {
            return self.base[key];
        }
        let t = self.stamp[key];
        if t != 0 && t >= self.marked[self.brick(key)] {
            return self.memo[key];
        }
        let st = self
            .grid
            .stencil(key)
            .expect("a non-base key has a stencil");
        // the stencil's points come earlier in the order, so the recursion ends (its depth is
        // at most 3 passes per level)
        let (b, c) = (st[1].expect("inside"), st[2].expect("inside"));
        let a = st[0].map(|k| self.value(k, buf));
        let (b, c) = (self.value(b, buf), self.value(c, buf));
        let d = st[3].map(|k| self.value(k, buf));
        let v = synthesize(buf.coeff(key as u64).unwrap_or(0.0), along_axis(a, b, c, d));
        self.memo[key] = v;
        self.stamp[key] = self.now;
        v
    }

    /// Bytes held.
    pub(super) fn bytes(&self) -> usize {
        self.memo.len() * 8 + self.marked.len() * 4 + self.grid.bytes()
    }
}
