//! Vertex values of a [`Predictor::Axes`] hierarchy: a vertex's prediction reads grid points
//! the mesh may not hold (3 steps along an axis, and its own level's points), so values are
//! synthesized by vertex key, apart from the mesh, with the same rule as for the parent
//! predictor: `synthesize(d, P)` with `d` the coefficient held, or 0 while it has not arrived.
//! A value is memoized until the next arrivals ([`AxesValues::invalidate`]); it is exact (the
//! server's) once every coefficient its stencils read, transitively, has arrived.
//!
//! [`Predictor::Axes`]: tetwave_protocol::wavelet::Predictor::Axes

use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::axes::{along_axis, AxesError, Grid};
use tetwave_protocol::wavelet::synthesize;
use tetwave_protocol::{BaseMesh, VertexKeys};

#[derive(Debug, Clone)]
pub(super) struct AxesValues {
    grid: Grid,
    base: Vec<f32>,
    /// Per key: the memoized value, valid while `stamp` is `now`.
    memo: Vec<f32>,
    stamp: Vec<u32>,
    now: u32,
}

impl AxesValues {
    pub(super) fn new(base: &BaseMesh, keys: &VertexKeys) -> Result<Self, AxesError> {
        let n = keys.vertex_count() as usize;
        Ok(AxesValues {
            grid: Grid::of(base, keys)?,
            base: base.values.clone(),
            memo: vec![0.0; n],
            stamp: vec![0; n],
            now: 1,
        })
    }

    /// Forgets every memoized value (coefficients have arrived).
    pub(super) fn invalidate(&mut self) {
        self.now = self.now.wrapping_add(1);
        if self.now == 0 {
            self.stamp.fill(0);
            self.now = 1;
        }
    }

    /// The value of vertex `key` from the coefficients `buf` holds.
    pub(super) fn value(&mut self, key: usize, buf: &DetailBuffer) -> f32 {
        if key < self.base.len() {
            return self.base[key];
        }
        if self.stamp[key] == self.now {
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
        self.memo.len() * 8 + self.grid.bytes()
    }
}
