//! The base mesh: the coarse conforming tet mesh the hierarchy refines, with the scalar at its vertices.

use crate::hierarchy::{Bary, Forest, Lattice, MAX_LEVELS};
use crate::vertex::VertexKeys;
use crate::wavelet::Predictor;
use serde::{Deserialize, Serialize};

/// Base mesh as stored and sent: positions, tets (vertex order is part of the contract), the scalar at
/// the base vertices, and which base tets lie entirely outside the input domain.
///
/// Serialized (`geometry`) with its geometry as a named box when it is exactly one
/// ([`crate::shapes::box5`] or [`crate::shapes::box6`] of its first and last corners: two points
/// instead of eight and the tets), else as its points and tets; points as f32 when every
/// coordinate is one exactly (a box's corners, a grid's bounds), else as f64. Never a rounded
/// position.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(into = "geometry::Wire", try_from = "geometry::Wire")]
pub struct BaseMesh {
    pub levels: u8,
    pub positions: Vec<[f64; 3]>,
    pub tets: Vec<[u32; 4]>,
    pub values: Vec<f32>,
    pub empty: Vec<bool>,
    /// How new vertices are predicted ([`Predictor::Axes`] only on a `box6` base).
    pub predictor: Predictor,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BaseError {
    #[error("base mesh has no tets")]
    NoTets,
    #[error("base mesh: {levels} levels exceeds the maximum {MAX_LEVELS}")]
    TooManyLevels { levels: u8 },
    #[error("base mesh: tet {tet} names vertex {vertex} but there are {count} vertices")]
    VertexOutOfRange {
        tet: usize,
        vertex: u32,
        count: usize,
    },
    #[error("base mesh: {values} values for {count} vertices")]
    ValueCount { values: usize, count: usize },
    #[error("base mesh: {flags} empty flags for {count} tets")]
    EmptyCount { flags: usize, count: usize },
    #[error("base mesh: non-finite position or value")]
    NonFinite,
    #[error("base mesh: tet {tet} repeats a vertex")]
    DegenerateTet { tet: usize },
    #[error("base mesh: {0}")]
    Predictor(#[from] crate::axes::AxesError),
}

impl BaseMesh {
    /// Structural checks a receiver applies before building anything from the mesh.
    pub fn validate(&self) -> Result<(), BaseError> {
        if self.tets.is_empty() {
            return Err(BaseError::NoTets);
        }
        if self.levels > MAX_LEVELS {
            return Err(BaseError::TooManyLevels {
                levels: self.levels,
            });
        }
        let count = self.positions.len();
        for (i, t) in self.tets.iter().enumerate() {
            for &v in t {
                if v as usize >= count {
                    return Err(BaseError::VertexOutOfRange {
                        tet: i,
                        vertex: v,
                        count,
                    });
                }
            }
            for a in 0..4 {
                for b in a + 1..4 {
                    if t[a] == t[b] {
                        return Err(BaseError::DegenerateTet { tet: i });
                    }
                }
            }
        }
        if self.values.len() != count {
            return Err(BaseError::ValueCount {
                values: self.values.len(),
                count,
            });
        }
        if self.empty.len() != self.tets.len() {
            return Err(BaseError::EmptyCount {
                flags: self.empty.len(),
                count: self.tets.len(),
            });
        }
        if self.positions.iter().flatten().any(|x| !x.is_finite())
            || self.values.iter().any(|x| !x.is_finite())
        {
            return Err(BaseError::NonFinite);
        }
        if self.predictor == Predictor::Axes {
            crate::axes::check_base(self)?;
        }
        Ok(())
    }

    pub fn forest(&self) -> Forest {
        Forest::new(self.tets.len() as u64, self.levels)
    }

    pub fn lattice(&self) -> Lattice {
        Lattice {
            levels: self.levels,
        }
    }

    /// The global vertex numbering of this mesh's hierarchy.
    pub fn vertex_keys(&self) -> VertexKeys {
        VertexKeys::new(self.positions.len() as u32, &self.tets, self.lattice())
    }

    /// Position of lattice point `w` of base tet `tet`.
    #[inline]
    pub fn position(&self, tet: u32, w: &Bary) -> [f64; 3] {
        lattice_position(
            &self.positions,
            &self.tets[tet as usize],
            self.lattice().m(),
            w,
        )
    }

    /// Axis-aligned bounds `(min, max)` of the base vertices.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.positions {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        (lo, hi)
    }
}

/// Position of lattice point `w` (weights summing to `m`) of the tet with corners `tet`.
#[inline]
pub fn lattice_position(positions: &[[f64; 3]], tet: &[u32; 4], m: u32, w: &Bary) -> [f64; 3] {
    let mut p = [0.0f64; 3];
    let inv = 1.0 / m as f64;
    for i in 0..4 {
        if w[i] != 0 {
            let x = positions[tet[i] as usize];
            let s = w[i] as f64 * inv;
            p[0] += s * x[0];
            p[1] += s * x[1];
            p[2] += s * x[2];
        }
    }
    p
}

/// Signed volume of a tet (positive for the right-handed orientation).
pub fn signed_volume(a: [f64; 3], b: [f64; 3], c: [f64; 3], d: [f64; 3]) -> f64 {
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let w = [d[0] - a[0], d[1] - a[1], d[2] - a[2]];
    (u[0] * (v[1] * w[2] - v[2] * w[1]) - u[1] * (v[0] * w[2] - v[2] * w[0])
        + u[2] * (v[0] * w[1] - v[1] * w[0]))
        / 6.0
}

/// Volume of the tets `tets` of `points` (each counted positive, whatever its orientation).
pub fn total_volume(points: &[[f64; 3]], tets: &[[u32; 4]]) -> f64 {
    tets.iter()
        .map(|t| {
            let p = |k: usize| points[t[k] as usize];
            signed_volume(p(0), p(1), p(2), p(3)).abs()
        })
        .sum()
}

/// Points as serialized (base meshes, the session's manifest): as f32 when every coordinate is
/// one exactly, else as f64, so never rounded.
#[derive(Serialize, Deserialize)]
pub(crate) enum Points {
    F32(Vec<[f32; 3]>),
    F64(Vec<[f64; 3]>),
}

impl Points {
    pub(crate) fn new(p: &[[f64; 3]]) -> Points {
        // NaN (which validation refuses) round-trips as f32 too
        let exact = p
            .iter()
            .flatten()
            .all(|&x| x as f32 as f64 == x || x.is_nan());
        if exact {
            Points::F32(p.iter().map(|c| c.map(|x| x as f32)).collect())
        } else {
            Points::F64(p.to_vec())
        }
    }

    pub(crate) fn into_f64(self) -> Vec<[f64; 3]> {
        match self {
            Points::F32(v) => v.into_iter().map(|c| c.map(f64::from)).collect(),
            Points::F64(v) => v,
        }
    }

    /// Two points as a box's `lo` and `hi`; `None` for any other count.
    pub(crate) fn into_box(self) -> Option<([f64; 3], [f64; 3])> {
        match self.into_f64()[..] {
            [lo, hi] => Some((lo, hi)),
            _ => None,
        }
    }
}

/// The serialized form of a [`BaseMesh`].
mod geometry {
    use super::{BaseMesh, Points};
    use crate::shapes::{box5, box6, PointsAndTets};
    use crate::wavelet::Predictor;
    use serde::{Deserialize, Serialize};

    #[derive(Serialize, Deserialize)]
    enum Geometry {
        /// [`box5`] of the two corners.
        Box5(Points),
        /// [`box6`] of the two corners.
        Box6(Points),
        Mesh {
            points: Points,
            tets: Vec<[u32; 4]>,
        },
    }

    #[derive(Serialize, Deserialize)]
    pub struct Wire {
        levels: u8,
        geometry: Geometry,
        values: Vec<f32>,
        empty: Vec<bool>,
        predictor: Predictor,
    }

    impl From<BaseMesh> for Wire {
        fn from(b: BaseMesh) -> Wire {
            let named = |shape: fn([f64; 3], [f64; 3]) -> PointsAndTets| {
                let (lo, hi) = (*b.positions.first()?, *b.positions.last()?);
                let (p, t) = shape(lo, hi);
                // bit for bit: -0.0 == 0.0, but a box of zeros would decode other signs
                let bits =
                    |a: &[[f64; 3]]| a.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
                (bits(&p) == bits(&b.positions) && t == b.tets).then(|| Points::new(&[lo, hi]))
            };
            let geometry = if let Some(corners) = named(box6) {
                Geometry::Box6(corners)
            } else if let Some(corners) = named(box5) {
                Geometry::Box5(corners)
            } else {
                Geometry::Mesh {
                    points: Points::new(&b.positions),
                    tets: b.tets,
                }
            };
            Wire {
                levels: b.levels,
                geometry,
                values: b.values,
                empty: b.empty,
                predictor: b.predictor,
            }
        }
    }

    impl TryFrom<Wire> for BaseMesh {
        type Error = String;

        fn try_from(w: Wire) -> Result<BaseMesh, String> {
            let corners = |c: Points| {
                c.into_box()
                    .ok_or_else(|| "a named box needs two corners".to_string())
            };
            let (positions, tets) = match w.geometry {
                Geometry::Box5(c) => corners(c).map(|(lo, hi)| box5(lo, hi))?,
                Geometry::Box6(c) => corners(c).map(|(lo, hi)| box6(lo, hi))?,
                Geometry::Mesh { points, tets } => (points.into_f64(), tets),
            };
            Ok(BaseMesh {
                levels: w.levels,
                positions,
                tets,
                values: w.values,
                empty: w.empty,
                predictor: w.predictor,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(b: &BaseMesh) -> (BaseMesh, usize) {
        let bytes = bincode::serde::encode_to_vec(b, bincode::config::standard()).unwrap();
        let (back, _) =
            bincode::serde::decode_from_slice(&bytes, bincode::config::standard()).unwrap();
        (back, bytes.len())
    }

    fn mesh(positions: Vec<[f64; 3]>, tets: Vec<[u32; 4]>) -> BaseMesh {
        BaseMesh {
            levels: 2,
            values: vec![0.5; positions.len()],
            empty: vec![false; tets.len()],
            predictor: Default::default(),
            positions,
            tets,
        }
    }

    #[test]
    fn positions_go_as_f32_only_when_that_is_exact() {
        // a box6 with one corner moved is no named box: its points and tets are written
        let (mut positions, tets) = crate::shapes::box6([0.0; 3], [2.5, 1.0, 0.75]);
        positions[3] = [2.0, 1.0, 0.0];
        let exact = mesh(positions, tets);
        let (back, small) = round_trip(&exact);
        assert_eq!(back, exact);
        // 0.1 is no f32: every coordinate must come back bit for bit, in f64
        let mut inexact = exact.clone();
        inexact.positions[3][1] = 0.1;
        inexact.positions[5][2] = 1.0 + f64::EPSILON;
        let (back, large) = round_trip(&inexact);
        assert_eq!(back, inexact);
        assert_eq!(
            large - small,
            8 * 3 * 4,
            "f64 costs 4 more bytes per coordinate"
        );
    }

    #[test]
    fn a_named_box_goes_as_its_two_corners() {
        type Shape = fn([f64; 3], [f64; 3]) -> crate::shapes::PointsAndTets;
        for shape in [crate::shapes::box5 as Shape, crate::shapes::box6] {
            for (lo, hi) in [
                ([0.0; 3], [30.0; 3]),
                ([-0.1, 0.0, 1e-300], [0.7, 2.0, 3.0]),
            ] {
                let (positions, tets) = shape(lo, hi);
                let b = mesh(positions, tets);
                let (back, len) = round_trip(&b);
                assert_eq!(back, b, "every position and tet bit for bit");
                // levels, 2 tags, 2 corners (f32 or f64), 8 values, the empty flags, predictor
                assert!(
                    len <= 1 + 2 + 1 + 2 * 24 + 1 + 32 + 1 + 6 + 1,
                    "{len} bytes"
                );
                // the same points with the tets in another order are another mesh
                let mut other = b.clone();
                other.tets.swap(0, 1);
                let (back, longer) = round_trip(&other);
                assert_eq!(back, other);
                assert!(longer > len + 90, "{longer} against {len}");
            }
        }
    }

    /// A box whose corners differ from the named box's only in the sign of a zero is no named box:
    /// every coordinate comes back bit for bit.
    #[test]
    fn signed_zeros_keep_their_sign() {
        let (mut positions, tets) = crate::shapes::box6([0.0; 3], [1.0; 3]);
        positions[2][2] = -0.0;
        let b = mesh(positions, tets);
        let (back, _) = round_trip(&b);
        let bits = |m: &BaseMesh| -> Vec<u64> {
            m.positions.iter().flatten().map(|x| x.to_bits()).collect()
        };
        assert_eq!(bits(&back), bits(&b));
    }

    #[test]
    fn a_named_box_of_other_than_two_corners_is_an_error() {
        for corners in [1u8, 3] {
            // levels 1, geometry Box6 (variant 1), points F32 (variant 0) of `corners` points
            let mut bytes = vec![1u8, 1, 0, corners];
            bytes.extend(std::iter::repeat_n(0u8, 12 * corners as usize));
            // 8 values, 6 empty flags, the predictor
            bytes.push(8);
            bytes.extend([0u8; 32]);
            bytes.push(6);
            bytes.extend([0u8; 6]);
            bytes.push(0);
            let got: Result<(BaseMesh, usize), _> =
                bincode::serde::decode_from_slice(&bytes, bincode::config::standard());
            let err = got.expect_err("refused").to_string();
            assert!(err.contains("two corners"), "{err}");
        }
    }
}
