//! The axes predictor ([`Predictor::Axes`]): SZ3's interpolation, on hierarchies whose vertices
//! are a grid.
//!
//! Refined `L` times, a `box6` base (an axis-aligned box in the 6 Kuhn tets around one diagonal)
//! has as level-`k` vertices exactly the points of the `(2^k + 1)³` grid. A new level-`k + 1`
//! vertex is odd (in steps `s = 2^(L−k−1)` of the finest grid) along one, two or three axes, and is
//! predicted along the last of them, level by level and within a level in three passes: first the
//! points odd along x only, from their x-neighbours; then those odd along y (x either, z even),
//! from their y-neighbours, some of which the first pass made; then those odd along z, from their
//! z-neighbours. Along the axis the prediction reads the points 1 and 3 steps away on each side:
//! the cubic `(−a + 9b + 9c − d)/16` with all four, the one-sided quadratic `(3b + 6c − d)/8`
//! (mirrored) with one outer point past the box, the midpoint `(b + c)/2` with neither.
//!
//! Unlike [`Predictor::Parent`] this reads vertices outside the tets around the new one (3 steps
//! along an axis, and this level's points), so a client must hold values of vertices its mesh
//! does not; `docs/decisions.md` ("A local predictor") says what that asks of a client.
//! Analysis and synthesis both run [`Grid::predict_all`], so both evaluate the same f32
//! expressions in the same order.
//!
//! [`Predictor::Axes`]: crate::wavelet::Predictor::Axes
//! [`Predictor::Parent`]: crate::wavelet::Predictor::Parent

use crate::base::BaseMesh;
use crate::hierarchy::Bary;
use crate::vertex::VertexKeys;
use crate::wavelet::predict;

/// Why a base mesh cannot carry the axes predictor.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AxesError {
    #[error(
        "the axes predictor needs a box6 base (an axis-aligned box in the 6 Kuhn tets around one \
         diagonal, whose refined vertices are a grid); this base mesh is not one: {0}"
    )]
    NotKuhnBox(&'static str),
    #[error("{0} grid points are more than the axes predictor indexes (2^32)")]
    TooLarge(u64),
}

/// The vertex key of every grid point of a `box6` hierarchy (x fastest), and the grid point of
/// every key.
#[derive(Debug, Clone)]
pub struct Grid {
    /// Finest-grid steps per axis: `2^levels`.
    m: u32,
    keys: Vec<u32>,
    /// Per key, its grid point's index into `keys`.
    points: Vec<u32>,
}

/// How far (in multiples of its level's step, along every axis) the vertices whose values read
/// a vertex can lie from it ([`Grid::stencil`]).
pub const DEPENDENCY_REACH: u32 = 6;

/// The points a new vertex's prediction reads along its axis, by key: 3 and 1 steps before it, 1
/// and 3 steps after it (the outer ones `None` past the box).
pub type Stencil = [Option<usize>; 4];

impl Grid {
    /// The grid of `base`'s hierarchy, or why it has none.
    pub fn of(base: &BaseMesh, keys: &VertexKeys) -> Result<Self, AxesError> {
        let corners = kuhn_corners(base)?;
        let m = base.lattice().m();
        let n = m as u64 + 1;
        if n * n * n > u32::MAX as u64 || keys.vertex_count() > u32::MAX as u64 {
            return Err(AxesError::TooLarge(n * n * n));
        }
        let n = n as usize;
        let mut grid = vec![u32::MAX; n * n * n];
        for (t, tet) in base.tets.iter().enumerate() {
            let bits = tet.map(|v| corners[v as usize]);
            // every lattice point w of the tet: its grid point is Σ w_i · corner_i
            for w0 in 0..=m {
                for w1 in 0..=m - w0 {
                    for w2 in 0..=m - w0 - w1 {
                        let w: Bary = [w0, w1, w2, m - w0 - w1 - w2];
                        let c = |axis: u32| -> usize {
                            (0..4)
                                .filter(|&i| bits[i] >> axis & 1 == 1)
                                .map(|i| w[i] as usize)
                                .sum()
                        };
                        grid[c(0) + n * (c(1) + n * c(2))] = keys.key(t as u32, &w) as u32;
                    }
                }
            }
        }
        if grid.contains(&u32::MAX) {
            return Err(AxesError::NotKuhnBox(
                "its tets leave grid points uncovered",
            ));
        }
        let mut points = vec![u32::MAX; keys.vertex_count() as usize];
        for (i, &k) in grid.iter().enumerate() {
            points[k as usize] = i as u32;
        }
        Ok(Grid {
            m,
            keys: grid,
            points,
        })
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        (self.keys.len() + self.points.len()) * 4
    }

    /// Finest-grid steps per axis (`2^levels`): grid points run over `0..=m()` on each axis.
    pub fn m(&self) -> u32 {
        self.m
    }

    /// The grid point of vertex `key`.
    #[inline]
    pub fn point(&self, key: usize) -> [u32; 3] {
        let n = self.m + 1;
        let i = self.points[key];
        [i % n, i / n % n, i / (n * n)]
    }

    /// The step `s` (in finest steps) of the level that makes vertex `key` and the axis it is
    /// predicted along; `None` for a base vertex (a corner of the box).
    #[inline]
    pub fn step_and_axis(&self, key: usize) -> Option<(u32, usize)> {
        let p = self.point(key);
        // its level's step: the largest power of two dividing every coordinate; the axis: the
        // last one odd in that step (the pass that makes the point)
        let tz = p.map(|c| if c == 0 { u32::MAX } else { c.trailing_zeros() });
        let t = tz.into_iter().min().expect("3 axes");
        if t >= self.m.trailing_zeros() {
            return None;
        }
        let axis = (0..3).rev().find(|&a| tz[a] == t).expect("an odd axis");
        Some((1 << t, axis))
    }

    /// What vertex `key`'s prediction reads; `None` for a base vertex.
    ///
    /// Following stencils from a vertex made with step `s` moves at most `3σ` along each axis
    /// per level of step `σ ≤ s` (one pass per axis), so every vertex whose value reads it,
    /// transitively, lies within `6s` of it along every axis ([`DEPENDENCY_REACH`]).
    pub fn stencil(&self, key: usize) -> Option<Stencil> {
        let (s, axis) = self.step_and_axis(key)?;
        Some(self.stencil_at(self.point(key), axis, s))
    }

    #[inline]
    fn stencil_at(&self, p: [u32; 3], axis: usize, s: u32) -> Stencil {
        let at = |o: i64| -> Option<usize> {
            let c = p[axis] as i64 + o * s as i64;
            (0..=self.m as i64).contains(&c).then(|| {
                let mut q = p;
                q[axis] = c as u32;
                self.key(q)
            })
        };
        [at(-3), at(-1), at(1), at(3)]
    }

    /// The key of grid point `p` (finest steps).
    #[inline]
    fn key(&self, p: [u32; 3]) -> usize {
        let n = self.m as usize + 1;
        self.keys[p[0] as usize + n * (p[1] as usize + n * p[2] as usize)] as usize
    }

    /// Visits every vertex above the base level in the predictor's order (coarse to fine, then
    /// x, y, z passes) with its key and its prediction from `values` (by vertex key); `value`
    /// returns the vertex's value, which `values` takes before any later prediction reads it.
    pub fn predict_all(&self, values: &mut [f32], mut value: impl FnMut(usize, f32) -> f32) {
        let m = self.m;
        let mut s = m / 2;
        while s >= 1 {
            for axis in 0..3 {
                // points odd along `axis`; even along the later axes; any along the earlier ones
                let step = |d: usize| if d < axis { s } else { 2 * s };
                let first = |d: usize| if d == axis { s } else { 0 };
                let mut p = [0u32; 3];
                p[2] = first(2);
                while p[2] <= m {
                    p[1] = first(1);
                    while p[1] <= m {
                        p[0] = first(0);
                        while p[0] <= m {
                            let st = self.stencil_at(p, axis, s);
                            let prediction = predict_from(st, |k| values[k]);
                            let k = self.key(p);
                            values[k] = value(k, prediction);
                            p[0] += step(0);
                        }
                        p[1] += step(1);
                    }
                    p[2] += step(2);
                }
            }
            s /= 2;
        }
    }
}

/// The prediction from a stencil's points, `value` giving their values.
#[inline]
pub fn predict_from(st: Stencil, value: impl Fn(usize) -> f32) -> f32 {
    let (b, c) = (st[1].expect("inside"), st[2].expect("inside"));
    along_axis(st[0].map(&value), value(b), value(c), st[3].map(&value))
}

/// The prediction at the midpoint between `b` and `c` from the points `a` before `b` and `d` after
/// `c`, where they exist (see the module documentation).
#[inline]
pub fn along_axis(a: Option<f32>, b: f32, c: f32, d: Option<f32>) -> f32 {
    match (a, d) {
        (Some(a), Some(d)) => (9.0 * (b + c) - (a + d)) * 0.0625,
        (None, Some(d)) => (3.0 * b + 6.0 * c - d) * 0.125,
        (Some(a), None) => (3.0 * c + 6.0 * b - a) * 0.125,
        (None, None) => predict(b, c),
    }
}

/// Whether `base` can carry the axes predictor (a `box6` mesh), without building its grid.
pub fn check_base(base: &BaseMesh) -> Result<(), AxesError> {
    kuhn_corners(base).map(|_| ())
}

/// Per base vertex its corner of the box as 3 bits (bit `a` set at the box's maximum along axis
/// `a`), when `base` is a box6 mesh.
fn kuhn_corners(base: &BaseMesh) -> Result<Vec<u8>, AxesError> {
    if base.positions.len() != 8 || base.tets.len() != 6 {
        return Err(AxesError::NotKuhnBox("it is not 8 vertices and 6 tets"));
    }
    let (lo, hi) = base.bounds();
    if (0..3).any(|a| lo[a] >= hi[a]) {
        return Err(AxesError::NotKuhnBox("its box is flat"));
    }
    let mut corners = Vec::with_capacity(8);
    for p in &base.positions {
        let mut c = 0u8;
        for a in 0..3 {
            if p[a] == hi[a] {
                c |= 1 << a;
            } else if p[a] != lo[a] {
                return Err(AxesError::NotKuhnBox("a vertex is no corner of its box"));
            }
        }
        corners.push(c);
    }
    let mut seen = 0u8;
    for &c in &corners {
        seen |= 1 << c;
    }
    if seen != 0xff {
        return Err(AxesError::NotKuhnBox("two vertices share a corner"));
    }
    // each tet a monotone path 000 → 111 (one axis added per vertex), all 6 paths once
    let mut paths = 0u64;
    for t in &base.tets {
        let mut c = t.map(|v| corners[v as usize]);
        c.sort_by_key(|x| x.count_ones());
        let monotone = c[0] == 0 && c[3] == 7 && (0..3).all(|i| c[i] & c[i + 1] == c[i]);
        if !monotone || c[1].count_ones() != 1 || c[2].count_ones() != 2 {
            return Err(AxesError::NotKuhnBox(
                "a tet is not a Kuhn path along the diagonal",
            ));
        }
        paths |= 1 << (c[1] * 8 + c[2]);
    }
    if paths.count_ones() != 6 {
        return Err(AxesError::NotKuhnBox("a Kuhn tet is repeated"));
    }
    Ok(corners)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shapes::{box5, box6};
    use crate::testing::unsampled_base;
    use crate::wavelet::Predictor;

    fn base(levels: u8, (positions, tets): crate::shapes::PointsAndTets) -> BaseMesh {
        let mut b = unsampled_base(levels, (positions, tets));
        b.predictor = Predictor::Axes;
        b
    }

    #[test]
    fn box6_grid_keys_are_every_vertex_once() {
        for levels in 0..4 {
            let b = base(levels, box6([0.0; 3], [2.0, 1.0, 0.5]));
            let keys = b.vertex_keys();
            let g = Grid::of(&b, &keys).unwrap();
            let mut seen = vec![false; keys.vertex_count() as usize];
            for &k in &g.keys {
                assert!(!seen[k as usize], "key {k} twice");
                seen[k as usize] = true;
            }
            assert!(seen.iter().all(|&s| s));
            assert_eq!(g.keys.len(), ((1usize << levels) + 1).pow(3));
        }
    }

    #[test]
    fn other_bases_are_refused() {
        let b = base(2, box5([0.0; 3], [1.0; 3]));
        assert!(matches!(
            Grid::of(&b, &b.vertex_keys()),
            Err(AxesError::NotKuhnBox(_))
        ));
        let mut b = base(2, box6([0.0; 3], [1.0; 3]));
        b.positions[3][0] = 0.5;
        assert!(Grid::of(&b, &b.vertex_keys()).is_err());
        let mut b = base(2, box6([0.0; 3], [1.0; 3]));
        b.tets[1] = b.tets[0];
        assert!(Grid::of(&b, &b.vertex_keys()).is_err());
    }

    /// Every vertex is visited once, after the points its prediction reads; a field cubic along
    /// every axis line is predicted exactly wherever the 4-point rule applies, and a quadratic one
    /// wherever the one-sided rule does too (everywhere but the first level's midpoints).
    #[test]
    fn predictions_read_only_earlier_points_and_are_exact_for_their_degree() {
        let levels = 4;
        let b = base(levels, box6([0.0; 3], [1.0; 3]));
        let keys = b.vertex_keys();
        let g = Grid::of(&b, &keys).unwrap();
        let n = keys.vertex_count() as usize;
        let m = g.m;
        let mut pos = vec![[0u32; 3]; n];
        for z in 0..=m {
            for y in 0..=m {
                for x in 0..=m {
                    pos[g.key([x, y, z])] = [x, y, z];
                }
            }
        }
        // the step s of the level that makes point p, the axis it is predicted along, and
        // whether both outer points (3 steps away) are inside
        let rule = |p: [u32; 3]| {
            let tz = p.map(|c| if c == 0 { 32 } else { c.trailing_zeros() });
            let t = *tz.iter().min().unwrap();
            let axis = (0..3).rev().find(|&a| tz[a] == t).unwrap();
            let s = 1u32 << t;
            (s, p[axis] >= 3 * s && p[axis] + 3 * s <= m)
        };
        let cubic = |p: [u32; 3]| {
            let [x, y, z] = p.map(|c| c as f32 / m as f32);
            1.0 + x * x * x - 2.0 * y * y * y + 0.5 * z * z * z + x * y * z
        };
        let quadratic = |p: [u32; 3]| {
            let [x, y, z] = p.map(|c| c as f32 / m as f32);
            1.0 + x * x - 2.0 * y * y + 0.5 * z * z + x * y - y * z
        };
        for (f, exact_when) in [
            (&cubic as &dyn Fn([u32; 3]) -> f32, 0),
            (&quadratic as &dyn Fn([u32; 3]) -> f32, 1),
        ] {
            let mut values = vec![f32::NAN; n];
            for v in 0..8 {
                values[v] = f(pos[v]);
            }
            let (mut visits, mut checked) = (0, 0);
            let mut seen = vec![false; n];
            seen[..8].fill(true);
            g.predict_all(&mut values, |k, p| {
                visits += 1;
                // the stencil a client reads by key is the one the pass used, and its points
                // were visited before
                let st = g.stencil(k).expect("not a corner");
                assert!(st.iter().flatten().all(|&q| seen[q]), "{:?}", pos[k]);
                assert_eq!(p.to_bits(), predict_from(st, |q| f(pos[q])).to_bits());
                seen[k] = true;
                assert!(p.is_finite(), "vertex {k} read an unset point");
                let (s, four) = rule(pos[k]);
                let applies = if exact_when == 0 { four } else { s < m / 2 };
                if applies {
                    checked += 1;
                    assert!(
                        (p - f(pos[k])).abs() < 1e-5,
                        "{:?}: {p} vs {}",
                        pos[k],
                        f(pos[k])
                    );
                }
                f(pos[k])
            });
            assert_eq!(visits, n - 8);
            assert!((0..8).all(|k| g.stencil(k).is_none()));
            assert!(checked > n / 4, "{checked} of {n}");
        }
        // the test could fail: the linear midpoint is not exact on the quadratic
        assert!(
            (predict(quadratic([0, 0, 0]), quadratic([m, 0, 0])) - quadratic([m / 2, 0, 0])).abs()
                > 1e-3
        );
    }

    /// Every vertex whose value reads a vertex made with step `s`, transitively, lies within
    /// `DEPENDENCY_REACH · s` of it along every axis (what the client's stale marking relies on),
    /// and the bound is reached by some pair less than 2× over (it is not loose by much).
    #[test]
    fn dependencies_stay_within_their_reach() {
        let b = base(4, box6([0.0; 3], [1.0; 3]));
        let keys = b.vertex_keys();
        let g = Grid::of(&b, &keys).unwrap();
        let n = keys.vertex_count() as usize;
        let mut worst = 0f64;
        for q in 0..n {
            let pq = g.point(q);
            let mut stack = vec![q];
            let mut seen = vec![false; n];
            while let Some(v) = stack.pop() {
                for r in g.stencil(v).into_iter().flatten().flatten() {
                    if !std::mem::replace(&mut seen[r], true) {
                        stack.push(r);
                        let Some((s, _)) = g.step_and_axis(r) else {
                            continue;
                        };
                        let pr = g.point(r);
                        for a in 0..3 {
                            let d = pq[a].abs_diff(pr[a]);
                            assert!(d <= DEPENDENCY_REACH * s, "{pq:?} reads {pr:?} (step {s})");
                            worst = worst.max(d as f64 / (DEPENDENCY_REACH * s) as f64);
                        }
                    }
                }
            }
        }
        assert!(worst > 0.5, "{worst}");
    }
}
