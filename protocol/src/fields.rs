//! Analytic scalar fields: the named synthetic datasets (`synthetic:<name>` in the server's `prepare`)
//! and the smooth field the tests and benchmarks on both sides share.
//!
//! `synthetic:harmonic` — [`harmonic`], the default dataset, standing in for the thesis' HARMONIC
//! (30×30×30 units): on the box [`HARMONIC_BOUNDS`] `= [0,30]^3`, with `u = (p − 15)/15 ∈ [−1,1]^3`
//! and `r = |u|`,
//!
//! `f(p) = exp(−2 r²) · cos(4π r) + 0.25 · sin(2π u_x) · sin(2π u_y) · sin(2π u_z)`
//!
//! a radial standing wave (nested shells) plus a product of harmonics; values lie in about [−1, 1].
//!
//! `synthetic:linear` — [`linear`], `f = x + 2y + 3z` on [`LINEAR_BOUNDS`] `= [0,1]^3` (exactly
//! representable by any linear interpolant).

use std::f64::consts::PI;

/// The box `synthetic:harmonic` is defined on.
pub const HARMONIC_BOUNDS: ([f64; 3], [f64; 3]) = ([0.0; 3], [30.0; 3]);

/// The box `synthetic:linear` is defined on.
pub const LINEAR_BOUNDS: ([f64; 3], [f64; 3]) = ([0.0; 3], [1.0; 3]);

/// The `synthetic:harmonic` field at `p` (see the module doc), in the units of [`HARMONIC_BOUNDS`].
pub fn harmonic(p: [f64; 3]) -> f64 {
    let u = [
        (p[0] - 15.0) / 15.0,
        (p[1] - 15.0) / 15.0,
        (p[2] - 15.0) / 15.0,
    ];
    let r2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
    let r = r2.sqrt();
    (-2.0 * r2).exp() * (4.0 * PI * r).cos()
        + 0.25 * (2.0 * PI * u[0]).sin() * (2.0 * PI * u[1]).sin() * (2.0 * PI * u[2]).sin()
}

/// [`harmonic`] scaled onto the unit cube: `harmonic(30 p)`, for meshes on `[0,1]^3`.
pub fn harmonic_unit(p: [f64; 3]) -> f64 {
    harmonic(p.map(|x| x * 30.0))
}

/// The `synthetic:linear` field at `p`.
pub fn linear(p: [f64; 3]) -> f64 {
    p[0] + 2.0 * p[1] + 3.0 * p[2]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn harmonic_shape() {
        // the centre is the crest of the radial wave; the product term vanishes on the mid-planes
        assert_eq!(harmonic([15.0; 3]), 1.0);
        assert_eq!(harmonic_unit([0.5; 3]), 1.0);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for i in 0..=30 {
            for j in 0..=30 {
                for k in 0..=30 {
                    let v = harmonic([i as f64, j as f64, k as f64]);
                    lo = lo.min(v);
                    hi = hi.max(v);
                }
            }
        }
        assert!(lo > -1.01 && lo < -0.95 && hi == 1.0, "{lo} {hi}");
    }
}
