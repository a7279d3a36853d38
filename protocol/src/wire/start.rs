//! A session's first message ([`super::ServerMsg::Start`]): the manifest in its session form
//! ([`super::manifest`]) and the base mesh, in one frame. Where the base mesh is exactly the
//! named box of the manifest (`box5` or `box6` of its bounds, bit for bit, at its levels), its
//! geometry and levels are left out: they follow from the manifest (a box's corners would
//! otherwise be sent twice, 24 bytes or more).

use crate::base::BaseMesh;
use crate::shapes::{box5, box6, PointsAndTets};
use crate::store_format::Manifest;
use crate::wavelet::Predictor;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// What a session starts with.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionStart {
    pub manifest: Manifest,
    pub base: BaseMesh,
}

#[derive(Serialize, Deserialize)]
enum BaseForm {
    /// The manifest's named box at the manifest's levels: only what is not geometry.
    OfManifest {
        values: Vec<f32>,
        empty: Vec<bool>,
        predictor: Predictor,
    },
    Whole(BaseMesh),
}

#[derive(Serialize, Deserialize)]
struct Wire {
    #[serde(with = "super::manifest")]
    manifest: Box<Manifest>,
    base: BaseForm,
}

/// The base mesh a manifest names when it names a box: `box5` or `box6` of its bounds.
fn named_box(m: &Manifest) -> Option<PointsAndTets> {
    let [lo, hi] = m.bounds;
    match m.base.as_str() {
        "box5" => Some(box5(lo, hi)),
        "box6" => Some(box6(lo, hi)),
        _ => None,
    }
}

/// Whether `b` is exactly `m`'s named box at `m`'s levels (bit for bit: a box of zeros with other
/// signs would decode differently).
fn is_named_box(m: &Manifest, b: &BaseMesh) -> bool {
    let bits = |a: &[[f64; 3]]| a.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    b.levels == m.levels
        && named_box(m).is_some_and(|(p, t)| t == b.tets && bits(&p) == bits(&b.positions))
}

pub fn serialize<S: Serializer>(st: &SessionStart, s: S) -> Result<S::Ok, S::Error> {
    let base = if is_named_box(&st.manifest, &st.base) {
        BaseForm::OfManifest {
            values: st.base.values.clone(),
            empty: st.base.empty.clone(),
            predictor: st.base.predictor,
        }
    } else {
        BaseForm::Whole(st.base.clone())
    };
    Wire {
        manifest: Box::new(st.manifest.clone()),
        base,
    }
    .serialize(s)
}

pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Box<SessionStart>, D::Error> {
    use serde::de::Error;
    let w = Wire::deserialize(d)?;
    let base = match w.base {
        BaseForm::Whole(b) => b,
        BaseForm::OfManifest {
            values,
            empty,
            predictor,
        } => {
            let (positions, tets) = named_box(&w.manifest).ok_or_else(|| {
                D::Error::custom(format!(
                    "start: the base mesh is the manifest's box, but the manifest names {:?}",
                    w.manifest.base
                ))
            })?;
            BaseMesh {
                levels: w.manifest.levels,
                positions,
                tets,
                values,
                empty,
                predictor,
            }
        }
    };
    Ok(Box::new(SessionStart {
        manifest: *w.manifest,
        base,
    }))
}

#[cfg(test)]
mod tests {
    use super::super::{decode_server, encode, ServerMsg};
    use super::*;
    use crate::hierarchy::Forest;
    use crate::store_format::{Counts, Encoding, STORE_FORMAT, STORE_VERSION};

    fn manifest(base: &str, n_base: u64, levels: u8) -> Manifest {
        let f = Forest { n_base, levels };
        Manifest {
            format: STORE_FORMAT.into(),
            version: STORE_VERSION,
            dataset: "d".into(),
            source: String::new(),
            bounds: [[0.0; 3], [30.0, 20.0, 10.0]],
            base: base.into(),
            base_tets: n_base,
            base_vertices: 8,
            levels,
            value_range: [-1.0, 1.0],
            source_value_range: Some([-1.0, 1.0]),
            counts: Counts {
                tets_total: f.total_tets(),
                leaves: f.leaves(),
                nodes: f.nodes(),
                vertices: 0,
                coefficients: 0,
                outside_vertices: 0,
                empty_base_tets: 0,
            },
            encoding: Encoding::uniform(12, 0.01),
            max_error_bound: 0.005,
            max_abs_error: 0.004,
            files: Default::default(),
            preview: None,
            value_histogram: None,
            physical: None,
        }
    }

    fn base_of((positions, tets): PointsAndTets, levels: u8) -> BaseMesh {
        BaseMesh {
            levels,
            values: (0..positions.len()).map(|i| i as f32 * 0.25).collect(),
            empty: vec![false; tets.len()],
            positions,
            tets,
            predictor: Predictor::Parent,
        }
    }

    fn round_trip(st: &SessionStart) -> usize {
        let msg = ServerMsg::Start(Box::new(st.clone()));
        let frame = encode(&msg).unwrap();
        assert_eq!(decode_server(&frame).unwrap(), msg);
        frame.len()
    }

    #[test]
    fn a_named_box_of_the_manifest_is_sent_once() {
        for (name, shape, n) in [("box6", box6 as fn(_, _) -> _, 6), ("box5", box5, 5)] {
            let manifest = manifest(name, n, 3);
            let [lo, hi] = manifest.bounds;
            let st = SessionStart {
                base: base_of(shape(lo, hi), 3),
                manifest,
            };
            let short = round_trip(&st);
            // the same box at other bounds, levels or with a moved point: sent whole, and longer
            let mut other = st.clone();
            other.base = base_of(shape(lo, [30.0, 20.0, 11.0]), 3);
            assert!(round_trip(&other) > short + 20, "{name}");
            let mut other = st.clone();
            other.base.levels = 2;
            assert!(round_trip(&other) > short + 20, "{name}");
            let mut other = st.clone();
            other.base.positions[0][0] = -0.0;
            assert!(round_trip(&other) > short + 20, "{name}");
            // a base that is not the manifest's named box, whatever the name says
            let mut other = st.clone();
            other.manifest.base = "mesh.vtu".into();
            assert!(round_trip(&other) > short + 20, "{name}");
        }
    }

    #[test]
    fn a_short_form_without_a_named_box_is_an_error() {
        let manifest = manifest("box6", 6, 3);
        let [lo, hi] = manifest.bounds;
        let st = SessionStart {
            base: base_of(box6(lo, hi), 3),
            manifest,
        };
        let mut frame = encode(&ServerMsg::Start(Box::new(st))).unwrap();
        // rename "box6" to "bo_6" in place: the frame still parses, and names no box
        let at = frame.windows(4).position(|w| w == b"box6").unwrap();
        frame[at + 2] = b'_';
        assert!(decode_server(&frame).is_err());
    }
}
