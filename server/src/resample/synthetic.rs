//! Analytic fields, for the embedded default dataset and for tests: the named synthetic datasets
//! (`synthetic:harmonic`, `synthetic:linear`), defined in [`tetwave_protocol::fields`] so the client's
//! tests and the renderer's use the same function, and the jittered Kuhn-cube test mesh.

use tetwave_protocol::fields;

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
            Synthetic::Harmonic => fields::HARMONIC_BOUNDS,
            Synthetic::Linear => fields::LINEAR_BOUNDS,
        }
    }

    pub fn eval(&self, p: [f64; 3]) -> f64 {
        match self {
            Synthetic::Harmonic => fields::harmonic(p),
            Synthetic::Linear => fields::linear(p),
        }
    }
}

/// splitmix64 of `(seed, k)` mapped to `[0, 1)`: a reproducible jitter.
fn unit_hash(seed: u64, k: u64) -> f64 {
    let mut z = seed.wrapping_add(k.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

/// An unstructured test mesh: `[0,1]^3` cut into `n^3` cubes of 6 Kuhn tets each (as
/// [`tetwave_protocol::shapes::kuhn_grid`] orders them, not reoriented), interior points moved by up
/// to `jitter/2` of a cell, cells kept where `keep(i, j, k)`, with the point scalar `f` named `"f"`.
/// Unused points are kept (they are in no tet).
pub fn kuhn_cube_mesh(
    n: usize,
    jitter: f64,
    keep: impl Fn(usize, usize, usize) -> bool,
    f: impl Fn([f64; 3]) -> f64,
) -> tetwave_import::TetMesh {
    let (mut points, tets) = tetwave_protocol::shapes::kuhn_grid(n, keep);
    for (idx, p) in points.iter_mut().enumerate() {
        let c = [
            idx % (n + 1),
            (idx / (n + 1)) % (n + 1),
            idx / ((n + 1) * (n + 1)),
        ];
        if c.iter().all(|&x| x > 0 && x < n) {
            for (a, x) in p.iter_mut().enumerate() {
                *x += (unit_hash(a as u64 + 1, idx as u64) - 0.5) * jitter / n as f64;
            }
        }
    }
    let values = points.iter().map(|&p| f(p)).collect();
    tetwave_import::TetMesh {
        points,
        tets,
        point_data: vec![tetwave_import::ScalarArray {
            name: "f".into(),
            values,
        }],
        cells_ignored: 0,
    }
}
