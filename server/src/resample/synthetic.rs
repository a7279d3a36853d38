//! Analytic fields, for the embedded default dataset and for tests.
//!
//! `harmonic` — the default, standing in for the thesis' HARMONIC (30×30×30 units): on the box
//! `[0,30]^3`, with `u = (p − 15)/15 ∈ [−1,1]^3` and `r = |u|`,
//!
//! `f(p) = exp(−2 r²) · cos(4π r) + 0.25 · sin(2π u_x) · sin(2π u_y) · sin(2π u_z)`
//!
//! a radial standing wave (nested shells) plus a product of harmonics; values lie in about [−0.8, 1].
//! `linear` is `f = x + 2y + 3z` on `[0,1]^3` (exactly representable by any linear interpolant).

use std::f64::consts::PI;

/// A named analytic field on a box.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Synthetic {
    Harmonic,
    Linear,
}

impl Synthetic {
    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "harmonic" => Some(Synthetic::Harmonic),
            "linear" => Some(Synthetic::Linear),
            _ => None,
        }
    }

    pub fn name(&self) -> &'static str {
        match self {
            Synthetic::Harmonic => "harmonic",
            Synthetic::Linear => "linear",
        }
    }

    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        match self {
            Synthetic::Harmonic => ([0.0; 3], [30.0; 3]),
            Synthetic::Linear => ([0.0; 3], [1.0; 3]),
        }
    }

    pub fn eval(&self, p: [f64; 3]) -> f64 {
        match self {
            Synthetic::Harmonic => {
                let u = [
                    (p[0] - 15.0) / 15.0,
                    (p[1] - 15.0) / 15.0,
                    (p[2] - 15.0) / 15.0,
                ];
                let r2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
                let r = r2.sqrt();
                (-2.0 * r2).exp() * (4.0 * PI * r).cos()
                    + 0.25
                        * (2.0 * PI * u[0]).sin()
                        * (2.0 * PI * u[1]).sin()
                        * (2.0 * PI * u[2]).sin()
            }
            Synthetic::Linear => p[0] + 2.0 * p[1] + 3.0 * p[2],
        }
    }
}
