//! Predict-only lifting: the one place where the prediction and its inverse are defined.
//!
//! A new vertex `m` (level `k + 1`) is the midpoint of an edge `(u, v)` of a level-`k` tet `T`.
//! Analysis stores `d_m = f(m) − P(m)`, synthesis computes `f(m) = d_m + P(m)`, where `P(m)` is
//! - on a base tet's edge (`k = 0`): the linear midpoint `(f(u) + f(v))/2` (thesis §4.3);
//! - otherwise the **quadratic (P2) interpolant of `T`'s parent** at `m`: the parent's 4 vertices
//!   and 6 edge midpoints are exactly the 10 nodes of a P2 tet, and every level-`k + 1` vertex
//!   inside it lies at a point where that interpolant depends only on the nodes of the smallest
//!   parent entity holding `m` (an edge, a face or the interior), so any tet whose split creates
//!   `m` predicts the same value ([`predict_split`]): the half of a parent edge `(i, j)` with
//!   midpoint `x` ([`predict_on_edge`]), a mid-segment of a parent face ([`predict_on_face`]), the
//!   parent's centre ([`predict_at_centre`]). Quadratic fields are predicted exactly, so a smooth
//!   field's details fall by 8× per level where the linear midpoint's fall by 4×.
//!
//! Both sides evaluate exactly these f32 expressions (sums whose order could differ are taken in
//! sorted order), so a detail chosen by [`analyze`] reproduces the sampled value bit for bit
//! whenever one f32 detail can (always when `f(m)` and the prediction are within a factor 2 of each
//! other, by Sterbenz' lemma; otherwise [`analyze`] picks the closest reachable value, within one
//! ulp of the prediction).

use crate::hierarchy::EDGES;
use serde::{Deserialize, Serialize};

/// How a hierarchy predicts its new vertices: part of the base mesh, so that both sides read it
/// from the same place.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Predictor {
    /// Linear on base edges, then the refined tet's parent's quadratic interpolant (this module):
    /// reads only the points every tet around the new vertex holds.
    #[default]
    Parent,
    /// SZ3's cubic interpolation along the grid's axes, level by level ([`crate::axes`]): a
    /// higher-order, finer stencil (smaller residuals on smooth fields), but it reads vertices a
    /// selectively refined mesh may not hold, and needs a `box6` base.
    Axes,
}

impl Predictor {
    /// The name `prepare --predictor` takes and the manifest shows.
    pub fn name(self) -> &'static str {
        match self {
            Predictor::Parent => "parent",
            Predictor::Axes => "axes",
        }
    }
}

/// Linear prediction of the midpoint value from the edge's end values.
#[inline]
pub fn predict(fu: f32, fv: f32) -> f32 {
    0.5 * (fu + fv)
}

/// P2 prediction at the quarter point of a parent edge `(near, far)` next to `near`, from the
/// edge's end values and its midpoint's value `mid`.
#[inline]
pub fn predict_on_edge(near: f32, mid: f32, far: f32) -> f32 {
    predict(near, mid) + 0.25 * (mid - predict(near, far))
}

/// P2 prediction at the midpoint of the segment joining the midpoints `a = x_ij` and `b = x_ik` of a
/// parent face `(i, j, k)`, from their values, the midpoint `x_jk`'s value `opp` and the values of
/// `j` and `k`.
#[inline]
pub fn predict_on_face(a: f32, b: f32, opp: f32, j: f32, k: f32) -> f32 {
    predict(a, b) + 0.25 * (opp - predict(j, k))
}

/// P2 prediction at a parent tet's centre (the midpoint of Bey's interior diagonal) from its 6 edge
/// midpoints' and 4 vertices' values, in any order.
#[inline]
pub fn predict_at_centre(mut mids: [f32; 6], mut corners: [f32; 4]) -> f32 {
    mids.sort_unstable_by(f32::total_cmp);
    corners.sort_unstable_by(f32::total_cmp);
    0.25 * mids.iter().sum::<f32>() - 0.125 * corners.iter().sum::<f32>()
}

/// Where an edge between two of a Bey split's 10 points (`0..4` the parent's vertices, `4..10` its
/// edge midpoints in [`EDGES`] order) lies in the parent, with the points its prediction reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SplitEdge {
    /// Half of parent edge `(near, far)` whose midpoint is `mid`: [`predict_on_edge`].
    Edge { near: u8, mid: u8, far: u8 },
    /// Mid-segment of a parent face: [`predict_on_face`] with the ends as `a`, `b`, and the
    /// opposite edge's midpoint `opp` and ends `j`, `k`.
    Face { opp: u8, j: u8, k: u8 },
    /// The interior diagonal: [`predict_at_centre`].
    Centre,
}

const fn edge_index(a: usize, b: usize) -> usize {
    let mut e = 0;
    while e < 6 {
        let (x, y) = EDGES[e];
        if (x == a && y == b) || (x == b && y == a) {
            return e;
        }
        e += 1;
    }
    panic!("not an edge")
}

const fn classify(p: usize, q: usize) -> Option<SplitEdge> {
    if p == q || (p < 4 && q < 4) {
        return None;
    }
    if p < 4 || q < 4 {
        let (c, m) = if p < 4 { (p, q) } else { (q, p) };
        let (x, y) = EDGES[m - 4];
        if x != c && y != c {
            return None;
        }
        let far = if x == c { y } else { x };
        return Some(SplitEdge::Edge {
            near: c as u8,
            mid: m as u8,
            far: far as u8,
        });
    }
    let (a, b) = (EDGES[p - 4], EDGES[q - 4]);
    // the shared parent vertex, if any
    let i = if a.0 == b.0 || a.0 == b.1 {
        a.0
    } else if a.1 == b.0 || a.1 == b.1 {
        a.1
    } else {
        return Some(SplitEdge::Centre);
    };
    let j = if a.0 == i { a.1 } else { a.0 };
    let k = if b.0 == i { b.1 } else { b.0 };
    Some(SplitEdge::Face {
        opp: (4 + edge_index(j, k)) as u8,
        j: j as u8,
        k: k as u8,
    })
}

const fn split_edge_table() -> [[Option<SplitEdge>; 10]; 10] {
    let mut t = [[None; 10]; 10];
    let mut p = 0;
    while p < 10 {
        let mut q = 0;
        while q < 10 {
            t[p][q] = classify(p, q);
            q += 1;
        }
        p += 1;
    }
    t
}

static SPLIT_EDGES: [[Option<SplitEdge>; 10]; 10] = split_edge_table();

/// The kind of the segment between split points `p` and `q`; `None` when it is no child's edge.
#[inline]
pub fn split_edge(p: usize, q: usize) -> Option<SplitEdge> {
    SPLIT_EDGES[p][q]
}

/// Prediction of the midpoint of the child edge between split points `p` and `q` of a parent whose
/// 10 split points hold the values `v` (see the module documentation).
///
/// # Panics
/// When `(p, q)` is no edge of a Bey child (a caller's bug: children's edges come from tables).
#[inline]
pub fn predict_split(v: &[f32; 10], p: usize, q: usize) -> f32 {
    match SPLIT_EDGES[p][q].expect("an edge of a Bey child") {
        SplitEdge::Edge { near, mid, far } => {
            predict_on_edge(v[near as usize], v[mid as usize], v[far as usize])
        }
        SplitEdge::Face { opp, j, k } => {
            predict_on_face(v[p], v[q], v[opp as usize], v[j as usize], v[k as usize])
        }
        SplitEdge::Centre => predict_at_centre(
            [v[4], v[5], v[6], v[7], v[8], v[9]],
            [v[0], v[1], v[2], v[3]],
        ),
    }
}

/// Inverse lifting step: the midpoint value from its detail and prediction.
#[inline]
pub fn synthesize(detail: f32, prediction: f32) -> f32 {
    detail + prediction
}

/// Forward lifting step: the detail `d` such that `synthesize(d, prediction) == value`, or the one whose
/// synthesis is closest to `value` when no f32 detail reaches it exactly.
pub fn analyze(value: f32, prediction: f32) -> f32 {
    let d = value - prediction;
    if synthesize(d, prediction) == value || !d.is_finite() {
        return d;
    }
    let mut best = d;
    let mut best_err = (synthesize(d, prediction) - value).abs();
    let (mut up, mut down) = (d, d);
    for _ in 0..4 {
        up = up.next_up();
        down = down.next_down();
        for c in [up, down] {
            let e = (synthesize(c, prediction) - value).abs();
            if e < best_err {
                best = c;
                best_err = e;
            }
        }
        if best_err == 0.0 {
            break;
        }
    }
    best
}

/// Uniform scalar quantizer of details with step `step`: codes are signed integers, the dequantized
/// detail is `code as f32 * step` on both sides.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Quantizer {
    pub bits: u8,
    pub step: f32,
}

/// How a store's quantization step shrinks toward the coarse levels: the details of vertices
/// `above` levels above the finest are quantized with `step / min(ratio^above, cap)`. Coarse
/// vertices are few, and a finer step there makes every prediction that reads them closer, so the
/// many fine residuals shrink (SZ3's successors, QoZ and HPEZ, tune the same two numbers). The
/// finest level keeps `step`, so the error bound, half of it, holds everywhere.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LevelSteps {
    pub ratio: f32,
    pub cap: f32,
}

impl LevelSteps {
    /// One step for every level.
    pub const UNIFORM: LevelSteps = LevelSteps {
        ratio: 1.0,
        cap: 1.0,
    };
    /// What `prepare --max-error` takes for the axes predictor (docs/benchmarks.md, "Level
    /// steps").
    pub const AXES: LevelSteps = LevelSteps {
        ratio: 1.25,
        cap: 2.0,
    };
    /// Largest `ratio` and `cap` a store may name (codes grow by up to `cap` on coarse levels).
    pub const MAX: f32 = 16.0;

    /// The divisor of the step `above` levels above the finest: `min(ratio^above, cap)`, by
    /// repeated f32 products, so that every reader computes the same bits.
    pub fn divisor(&self, above: u32) -> f32 {
        let mut f = 1f32;
        for _ in 0..above {
            f *= self.ratio;
            if f >= self.cap {
                return self.cap;
            }
        }
        f
    }

    /// `quantizer` for the details `above` levels above the finest.
    pub fn at(&self, quantizer: Quantizer, above: u32) -> Quantizer {
        Quantizer {
            step: quantizer.step / self.divisor(above),
            ..quantizer
        }
    }

    /// [`Self::at`] for every level of a hierarchy of `levels`, indexed by `above` (`0` the
    /// finest): what coders look up per vertex or node.
    pub fn quantizers(&self, quantizer: Quantizer, levels: u8) -> Vec<Quantizer> {
        (0..levels as u32).map(|a| self.at(quantizer, a)).collect()
    }

    /// Whether the two numbers are ones a reader accepts: finite, from 1 to [`Self::MAX`].
    pub fn check(&self) -> Result<(), String> {
        let ok = |x: f32| (1.0..=Self::MAX).contains(&x);
        if ok(self.ratio) && ok(self.cap) {
            Ok(())
        } else {
            Err(format!(
                "level steps: ratio {} and cap {} must lie in 1..={}",
                self.ratio,
                self.cap,
                Self::MAX
            ))
        }
    }
}

impl Default for LevelSteps {
    fn default() -> Self {
        Self::UNIFORM
    }
}

impl Quantizer {
    /// Largest code magnitude for `bits`.
    pub fn max_code(bits: u8) -> i32 {
        (1i32 << (bits - 1)) - 1
    }
    /// Code of a detail (clamped to the code range).
    pub fn encode(&self, d: f32) -> i32 {
        let c = (d as f64 / self.step as f64).round();
        let mc = Self::max_code(self.bits) as f64;
        c.clamp(-mc, mc) as i32
    }
    pub fn decode(&self, code: i32) -> f32 {
        code as f32 * self.step
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn lifting_step_is_exact_for_comparable_values(f in -1e6f32..1e6, u in -1e6f32..1e6, v in -1e6f32..1e6) {
            let p = predict(u, v);
            let d = analyze(f, p);
            let r = synthesize(d, p);
            // exact, or within one ulp of the prediction's magnitude when f32 cannot reach f
            let tol = if r == f { 0.0 } else { p.abs().max(f.abs()) * f32::EPSILON };
            prop_assert!((r - f).abs() <= tol, "f {f} p {p} d {d} r {r}");
        }
    }

    /// A quadratic field at a parent's 10 split points (unit reference tet, weights as positions).
    fn quadratic_at(points: &[[f64; 3]; 10], f: impl Fn([f64; 3]) -> f64) -> [f32; 10] {
        points.map(|p| f(p) as f32)
    }

    fn reference_split_points() -> [[f64; 3]; 10] {
        let v = [
            [0.1, 0.2, 0.0],
            [1.3, 0.1, 0.2],
            [0.2, 1.1, 0.3],
            [0.3, 0.2, 0.9],
        ];
        let mut p = [[0.0; 3]; 10];
        p[..4].copy_from_slice(&v);
        for (e, &(a, b)) in EDGES.iter().enumerate() {
            p[4 + e] = std::array::from_fn(|c| 0.5 * (v[a][c] + v[b][c]));
        }
        p
    }

    #[test]
    fn split_prediction_is_exact_for_quadratics_on_every_child_edge() {
        use crate::hierarchy::BEY_CHILDREN;
        let pts = reference_split_points();
        let f = |x: [f64; 3]| {
            1.0 + 2.0 * x[0] - x[1] + 0.5 * x[2] + 3.0 * x[0] * x[0] - 2.0 * x[0] * x[1]
                + x[1] * x[2]
                + 1.5 * x[2] * x[2]
                - 0.7 * x[0] * x[2]
                + 0.4 * x[1] * x[1]
        };
        let v = quadratic_at(&pts, f);
        let (mut kinds, mut linear_misses) = ([0usize; 3], 0);
        for child in BEY_CHILDREN {
            for (a, b) in EDGES {
                let (p, q) = (child[a], child[b]);
                let m: [f64; 3] = std::array::from_fn(|c| 0.5 * (pts[p][c] + pts[q][c]));
                let got = predict_split(&v, p, q) as f64;
                assert!((got - f(m)).abs() < 1e-5, "edge {p}-{q}: {got} vs {}", f(m));
                if (predict(v[p], v[q]) as f64 - f(m)).abs() > 1e-3 {
                    linear_misses += 1;
                }
                kinds[match split_edge(p, q).unwrap() {
                    SplitEdge::Edge { .. } => 0,
                    SplitEdge::Face { .. } => 1,
                    SplitEdge::Centre => 2,
                }] += 1;
            }
        }
        // 48 child edges: 12 halves of parent edges (3 in each corner child), 32 face
        // mid-segments, and the diagonal in each of the 4 inner children
        assert_eq!(kinds, [12, 32, 4]);
        // the linear midpoint is not exact on this field (the test could fail)
        assert!(linear_misses >= 40, "{linear_misses}");
    }

    #[test]
    fn split_prediction_does_not_depend_on_the_points_order() {
        let v = [0.3, -1.0, 2.5, 7.0, 1.0, 0.125, -3.0, 4.0, 1e-3, 9.0];
        for p in 0..10 {
            for q in 0..10 {
                if split_edge(p, q).is_some() {
                    assert_eq!(predict_split(&v, p, q), predict_split(&v, q, p));
                }
            }
        }
        let mut mids = [1.0, 2.0e7, -3.0, 0.1, 5.0, -2.0e7];
        let corners = [0.5, -0.25, 3.0, 1e-9];
        let a = predict_at_centre(mids, corners);
        mids.reverse();
        assert_eq!(a.to_bits(), predict_at_centre(mids, corners).to_bits());
    }

    /// Steps shrink by the ratio per level up to the cap, the same bits on every reader; a
    /// ratio or cap below 1 (coarser steps above the finest level would break the bound) or
    /// beyond the limit is refused.
    #[test]
    fn level_steps_shrink_toward_coarse_levels() {
        let s = LevelSteps::AXES;
        let d: Vec<f32> = (0..6).map(|k| s.divisor(k)).collect();
        assert_eq!(d, [1.0, 1.25, 1.5625, 1.953125, 2.0, 2.0]);
        assert_eq!(LevelSteps::UNIFORM.divisor(9), 1.0);
        let q = Quantizer {
            bits: 12,
            step: 0.5,
        };
        assert_eq!(s.at(q, 0), q);
        assert_eq!(s.at(q, 4).step, 0.25);
        assert!(s.check().is_ok() && LevelSteps::UNIFORM.check().is_ok());
        for (ratio, cap) in [(0.5, 2.0), (1.25, 0.9), (f32::NAN, 2.0), (1.25, 17.0)] {
            assert!(LevelSteps { ratio, cap }.check().is_err(), "{ratio} {cap}");
        }
    }

    #[test]
    fn quantizer_round_trip_within_half_step() {
        let q = Quantizer {
            bits: 12,
            step: 0.01,
        };
        for i in -1000..1000 {
            let d = i as f32 * 0.0037;
            assert!((q.decode(q.encode(d)) - d).abs() <= 0.005 + 1e-7);
        }
    }
}
