//! Predict-only lifting (thesis §4.3): the one place where the prediction and its inverse are defined.
//!
//! For a new vertex `m`, midpoint of the edge `(u, v)` of a coarser tet:
//! analysis `d_m = f(m) − (f(u) + f(v))/2`, synthesis `f(m) = d_m + (f(u) + f(v))/2`.
//! Both sides evaluate exactly these f32 expressions in this order, so a detail chosen by [`analyze`]
//! reproduces the sampled value bit for bit whenever one f32 detail can (always when `f(m)` and the
//! prediction are within a factor 2 of each other, by Sterbenz' lemma; otherwise [`analyze`] picks the
//! closest reachable value, within one ulp of the prediction).

/// Linear prediction of the midpoint value from the edge's end values.
#[inline]
pub fn predict(fu: f32, fv: f32) -> f32 {
    0.5 * (fu + fv)
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
