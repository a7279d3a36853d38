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

/// How far (in multiples of its level's step, along every axis) the vertices whose values read
/// a vertex can lie from it ([`Grid::stencil`]).
pub const DEPENDENCY_REACH: u32 = 6;

/// A grid point, in finest steps (`0..=m` on each axis).
pub type Point = [u32; 3];

/// The points a new vertex's prediction reads along its axis: 3 and 1 steps before it, 1 and 3
/// steps after it (the outer ones `None` past the box).
pub type Stencil = [Option<Point>; 4];

/// The grid of a `box6` hierarchy: vertex keys of grid points and grid points of lattice points,
/// by arithmetic (no table per vertex: a client holding a small part of a large hierarchy pays
/// for what it touches only).
#[derive(Debug, Clone)]
pub struct Grid {
    /// Finest-grid steps per axis: `2^levels`.
    m: u32,
    /// Per base vertex, its corner of the box (bit `a` set at the maximum along axis `a`).
    corners: Vec<u8>,
    /// Per Kuhn path (index `3a + b` for first axis `a`, second `b`): the base tet whose
    /// vertices are `000, e_a, e_a + e_b, 111`, and the local index of each.
    paths: [(u32, [u8; 4]); 9],
    keys: VertexKeys,
}

impl Grid {
    /// The grid of `base`'s hierarchy (`keys` its numbering), or why it has none.
    pub fn of(base: &BaseMesh, keys: &VertexKeys) -> Result<Self, AxesError> {
        let corners = checked_corners(base)?;
        let m = base.lattice().m();
        let mut paths = [(u32::MAX, [0u8; 4]); 9];
        for (t, tet) in base.tets.iter().enumerate() {
            let mut local: [u8; 4] = [0, 1, 2, 3];
            local.sort_by_key(|&i| corners[tet[i as usize] as usize].count_ones());
            let c = local.map(|i| corners[tet[i as usize] as usize]);
            let (a, b) = (c[1].trailing_zeros(), (c[2] ^ c[1]).trailing_zeros());
            paths[(3 * a + b) as usize] = (t as u32, local);
        }
        Ok(Grid {
            m,
            corners,
            paths,
            keys: keys.clone(),
        })
    }

    /// Finest-grid steps per axis (`2^levels`): grid points run over `0..=m()` on each axis.
    pub fn m(&self) -> u32 {
        self.m
    }

    /// The vertex key of grid point `p`.
    #[inline]
    pub fn key(&self, p: Point) -> usize {
        // the Kuhn tet {p_a ≥ p_b ≥ p_c} holds p (on a shared face either does: keys are global)
        let (mut a, mut b, mut c) = (0, 1, 2);
        if p[b] > p[a] {
            std::mem::swap(&mut a, &mut b);
        }
        if p[c] > p[b] {
            std::mem::swap(&mut b, &mut c);
            if p[b] > p[a] {
                std::mem::swap(&mut a, &mut b);
            }
        }
        let (t, local) = self.paths[3 * a + b];
        let mut w = [0u32; 4];
        w[local[0] as usize] = self.m - p[a];
        w[local[1] as usize] = p[a] - p[b];
        w[local[2] as usize] = p[b] - p[c];
        w[local[3] as usize] = p[c];
        self.keys.key(t, &w) as usize
    }

    /// The grid point of lattice point `w` of base tet `tet`.
    #[inline]
    pub fn point(&self, tet: u32, w: &Bary) -> Point {
        let t = &self.keys.base_tets()[tet as usize];
        let mut p = [0u32; 3];
        for i in 0..4 {
            let c = self.corners[t[i] as usize];
            for (a, pa) in p.iter_mut().enumerate() {
                if c >> a & 1 == 1 {
                    *pa += w[i];
                }
            }
        }
        p
    }

    /// The step `s` (in finest steps) of the level that makes point `p` and the axis it is
    /// predicted along; `None` for a base vertex (a corner of the box).
    #[inline]
    pub fn step_and_axis(&self, p: Point) -> Option<(u32, usize)> {
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

    /// What point `p`'s prediction reads; `None` for a base vertex.
    ///
    /// Following stencils from a point made with step `s` moves at most `3σ` along each axis
    /// per level of step `σ ≤ s` (one pass per axis), so every point whose value reads it,
    /// transitively, lies within `6s` of it along every axis ([`DEPENDENCY_REACH`]).
    #[inline]
    pub fn stencil(&self, p: Point) -> Option<Stencil> {
        let (s, axis) = self.step_and_axis(p)?;
        Some(self.stencil_at(p, axis, s))
    }

    #[inline]
    fn stencil_at(&self, p: Point, axis: usize, s: u32) -> Stencil {
        let at = |o: i64| -> Option<Point> {
            let c = p[axis] as i64 + o * s as i64;
            (0..=self.m as i64).contains(&c).then(|| {
                let mut q = p;
                q[axis] = c as u32;
                q
            })
        };
        [at(-3), at(-1), at(1), at(3)]
    }

    /// Visits every vertex above the base level in the predictor's order (coarse to fine, then
    /// x, y, z passes) with its key and its prediction from `values` (by vertex key); `value`
    /// returns the vertex's value, which `values` takes before any later prediction reads it;
    /// its third argument is how many levels above the finest the vertex lies (0: the finest).
    /// Holds a key per grid point while it runs.
    pub fn predict_all(&self, values: &mut [f32], mut value: impl FnMut(usize, f32, u32) -> f32) {
        let m = self.m;
        let n = m as usize + 1;
        let mut keys = vec![0u32; n * n * n];
        for z in 0..=m {
            for y in 0..=m {
                for x in 0..=m {
                    keys[x as usize + n * (y as usize + n * z as usize)] =
                        self.key([x, y, z]) as u32;
                }
            }
        }
        let key = |q: Point| keys[q[0] as usize + n * (q[1] as usize + n * q[2] as usize)] as usize;
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
                            let prediction = predict_from(st, |q| values[key(q)]);
                            let k = key(p);
                            values[k] = value(k, prediction, s.trailing_zeros());
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
pub fn predict_from(st: Stencil, value: impl Fn(Point) -> f32) -> f32 {
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

/// Whether `base` can carry the axes predictor: a `box6` mesh whose grid points a `u32` counts.
pub fn check_base(base: &BaseMesh) -> Result<(), AxesError> {
    checked_corners(base).map(|_| ())
}

/// [`kuhn_corners`] of a base that passes [`check_base`].
fn checked_corners(base: &BaseMesh) -> Result<Vec<u8>, AxesError> {
    let corners = kuhn_corners(base)?;
    let n = base.lattice().m() as u64 + 1;
    if n * n * n > u32::MAX as u64 {
        return Err(AxesError::TooLarge(n * n * n));
    }
    Ok(corners)
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

    fn points(m: u32) -> impl Iterator<Item = Point> {
        (0..=m).flat_map(move |z| (0..=m).flat_map(move |y| (0..=m).map(move |x| [x, y, z])))
    }

    /// Grid points and vertex keys are one-to-one, and a lattice point of any base tet is the
    /// grid point whose key it has (base tets in any vertex order).
    #[test]
    fn box6_grid_keys_are_every_vertex_once() {
        for levels in 0..4 {
            let mut b = base(levels, box6([0.0; 3], [2.0, 1.0, 0.5]));
            for t in b.tets.iter_mut().skip(1).step_by(2) {
                t.swap(0, 2);
                t.swap(1, 3);
            }
            let keys = b.vertex_keys();
            let g = Grid::of(&b, &keys).unwrap();
            let mut seen = vec![false; keys.vertex_count() as usize];
            for p in points(g.m()) {
                let k = g.key(p);
                assert!(!std::mem::replace(&mut seen[k], true), "key {k} twice");
            }
            assert!(seen.iter().all(|&s| s));
            let m = b.lattice().m();
            for t in 0..6u32 {
                for w0 in 0..=m {
                    for w1 in 0..=m - w0 {
                        for w2 in 0..=m - w0 - w1 {
                            let w = [w0, w1, w2, m - w0 - w1 - w2];
                            assert_eq!(g.key(g.point(t, &w)), keys.key(t, &w) as usize);
                        }
                    }
                }
            }
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
        // a grid of more points than a u32 counts is refused by validation, before any table
        let b = base(11, box6([0.0; 3], [1.0; 3]));
        assert!(matches!(check_base(&b), Err(AxesError::TooLarge(_))));
        assert!(b.validate().is_err());
        assert!(check_base(&base(10, box6([0.0; 3], [1.0; 3]))).is_ok());
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
        let m = g.m();
        let mut pos = vec![[0u32; 3]; n];
        for p in points(m) {
            pos[g.key(p)] = p;
        }
        let cubic = |p: Point| {
            let [x, y, z] = p.map(|c| c as f32 / m as f32);
            1.0 + x * x * x - 2.0 * y * y * y + 0.5 * z * z * z + x * y * z
        };
        let quadratic = |p: Point| {
            let [x, y, z] = p.map(|c| c as f32 / m as f32);
            1.0 + x * x - 2.0 * y * y + 0.5 * z * z + x * y - y * z
        };
        for (f, exact_when) in [
            (&cubic as &dyn Fn(Point) -> f32, 0),
            (&quadratic as &dyn Fn(Point) -> f32, 1),
        ] {
            let mut values = vec![f32::NAN; n];
            for v in 0..8 {
                values[v] = f(pos[v]);
            }
            let (mut visits, mut checked) = (0, 0);
            let mut seen = vec![false; n];
            seen[..8].fill(true);
            g.predict_all(&mut values, |k, p, _| {
                visits += 1;
                assert!(p.is_finite(), "vertex {k} read an unset point");
                // the stencil a client reads by point is the one the pass used, and its points
                // were visited before
                let st = g.stencil(pos[k]).expect("not a corner");
                assert!(st.iter().flatten().all(|&q| seen[g.key(q)]), "{:?}", pos[k]);
                assert_eq!(p.to_bits(), predict_from(st, f).to_bits());
                seen[k] = true;
                let (s, axis) = g.step_and_axis(pos[k]).unwrap();
                let four = pos[k][axis] >= 3 * s && pos[k][axis] + 3 * s <= m;
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
            assert!((0..8).all(|k| g.stencil(pos[k]).is_none()));
            assert!(checked > n / 4, "{checked} of {n}");
        }
        // the test could fail: the linear midpoint is not exact on the quadratic
        let mid = predict(quadratic([0, 0, 0]), quadratic([m, 0, 0]));
        assert!((mid - quadratic([m / 2, 0, 0])).abs() > 1e-3);
    }

    /// Every point whose value reads a point made with step `s`, transitively, lies within
    /// `DEPENDENCY_REACH · s` of it along every axis (what the client's stale marking relies on),
    /// and the bound is reached by some pair less than 2× over (it is not loose by much).
    #[test]
    fn dependencies_stay_within_their_reach() {
        let b = base(4, box6([0.0; 3], [1.0; 3]));
        let keys = b.vertex_keys();
        let g = Grid::of(&b, &keys).unwrap();
        let mut worst = 0f64;
        for q in points(g.m()) {
            let mut stack = vec![q];
            let mut seen = std::collections::HashSet::new();
            while let Some(v) = stack.pop() {
                for r in g.stencil(v).into_iter().flatten().flatten() {
                    if seen.insert(r) {
                        stack.push(r);
                        let Some((s, _)) = g.step_and_axis(r) else {
                            continue;
                        };
                        for a in 0..3 {
                            let d = q[a].abs_diff(r[a]);
                            assert!(d <= DEPENDENCY_REACH * s, "{q:?} reads {r:?} (step {s})");
                            worst = worst.max(d as f64 / (DEPENDENCY_REACH * s) as f64);
                        }
                    }
                }
            }
        }
        assert!(worst > 0.5, "{worst}");
    }
}
