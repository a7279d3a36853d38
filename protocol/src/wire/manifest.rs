//! The manifest as a session sends it (in [`super::ServerMsg::Start`]): what a client needs, in
//! fewer bytes than the store's whole manifest. Left out, because a client can derive or does not
//! need them: the format and version (the protocol version implies the store's), the counts that
//! follow from the base tets and levels (all tets, leaves, nodes), the source file's name and every
//! file's sum but the level-set band's (`GET /v1/manifest` serves those); bounds as f32 where that
//! is exact. The decoded manifest has the store's format and version, the derived counts, an empty
//! source and only the level-set band among its files.

use crate::base::Points;
use crate::hierarchy::{Forest, MAX_LEVELS};
use crate::store_format::{
    Counts, Encoding, FileSum, Manifest, Physical, Preview, HISTOGRAM_BINS, LEVELSET_BAND_FILE,
    STORE_FORMAT, STORE_VERSION,
};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// The input's value range against the samples'.
#[derive(Serialize, Deserialize)]
enum SourceRange {
    Unknown,
    /// The samples' own ([`Manifest::value_range`]).
    Same,
    Range([f32; 2]),
}

#[derive(Serialize, Deserialize)]
struct Wire {
    dataset: String,
    bounds: Points,
    base: String,
    base_tets: u64,
    base_vertices: u64,
    levels: u8,
    value_range: [f32; 2],
    source_value_range: SourceRange,
    vertices: u64,
    coefficients: u64,
    outside_vertices: u64,
    empty_base_tets: u64,
    encoding: Encoding,
    max_error_bound: f64,
    max_abs_error: f64,
    levelset_band: Option<FileSum>,
    preview: Option<Preview>,
    value_histogram: Option<Vec<u64>>,
    physical: Option<Physical>,
}

pub fn serialize<S: Serializer>(m: &Manifest, s: S) -> Result<S::Ok, S::Error> {
    let same = |r: [f32; 2]| r.map(f32::to_bits) == m.value_range.map(f32::to_bits);
    Wire {
        dataset: m.dataset.clone(),
        bounds: Points::new(&m.bounds),
        base: m.base.clone(),
        base_tets: m.base_tets,
        base_vertices: m.base_vertices,
        levels: m.levels,
        value_range: m.value_range,
        source_value_range: match m.source_value_range {
            None => SourceRange::Unknown,
            Some(r) if same(r) => SourceRange::Same,
            Some(r) => SourceRange::Range(r),
        },
        vertices: m.counts.vertices,
        coefficients: m.counts.coefficients,
        outside_vertices: m.counts.outside_vertices,
        empty_base_tets: m.counts.empty_base_tets,
        encoding: m.encoding.clone(),
        max_error_bound: m.max_error_bound,
        max_abs_error: m.max_abs_error,
        levelset_band: m.files.get(LEVELSET_BAND_FILE).cloned(),
        preview: m.preview.clone(),
        value_histogram: m.value_histogram.clone(),
        physical: m.physical.clone(),
    }
    .serialize(s)
}

pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Box<Manifest>, D::Error> {
    use serde::de::Error;
    let w = Wire::deserialize(d)?;
    if w.levels > MAX_LEVELS {
        return Err(D::Error::custom(format!(
            "manifest: {} levels exceeds the maximum {MAX_LEVELS}",
            w.levels
        )));
    }
    let forest = Forest {
        n_base: w.base_tets,
        levels: w.levels,
    };
    let count = |k: u8| {
        forest.checked_level_start(k).ok_or_else(|| {
            D::Error::custom(format!(
                "manifest: {} base tets over {} levels overflow the tet ids",
                w.base_tets, w.levels
            ))
        })
    };
    let (nodes, tets_total) = (count(w.levels)?, count(w.levels + 1)?);
    if let Some(p) = &w.preview {
        p.check(w.levels)
            .map_err(|e| D::Error::custom(format!("manifest: {e}")))?;
    }
    if let Some(h) = &w.value_histogram {
        if h.len() != HISTOGRAM_BINS {
            return Err(D::Error::custom(format!(
                "manifest: a value histogram of {} bins, not {HISTOGRAM_BINS}",
                h.len()
            )));
        }
    }
    let bounds = match Points::into_f64(w.bounds)[..] {
        [lo, hi] => [lo, hi],
        _ => return Err(D::Error::custom("manifest: bounds need two corners")),
    };
    Ok(Box::new(Manifest {
        format: STORE_FORMAT.to_string(),
        version: STORE_VERSION,
        dataset: w.dataset,
        source: String::new(),
        bounds,
        base: w.base,
        base_tets: w.base_tets,
        base_vertices: w.base_vertices,
        levels: w.levels,
        value_range: w.value_range,
        source_value_range: match w.source_value_range {
            SourceRange::Unknown => None,
            SourceRange::Same => Some(w.value_range),
            SourceRange::Range(r) => Some(r),
        },
        counts: Counts {
            tets_total,
            leaves: tets_total - nodes,
            nodes,
            vertices: w.vertices,
            coefficients: w.coefficients,
            outside_vertices: w.outside_vertices,
            empty_base_tets: w.empty_base_tets,
        },
        encoding: w.encoding,
        max_error_bound: w.max_error_bound,
        max_abs_error: w.max_abs_error,
        files: w
            .levelset_band
            .map(|f| (LEVELSET_BAND_FILE.to_string(), f))
            .into_iter()
            .collect(),
        preview: w.preview,
        value_histogram: w.value_histogram,
        physical: w.physical,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wavelet::LevelSteps;

    fn store_manifest() -> Manifest {
        let f = Forest {
            n_base: 6,
            levels: 5,
        };
        Manifest {
            format: STORE_FORMAT.into(),
            version: STORE_VERSION,
            dataset: "harmonic-l5".into(),
            source: "harmonic-l5.raw".into(),
            bounds: [[0.0; 3], [30.0; 3]],
            base: "box6".into(),
            base_tets: 6,
            base_vertices: 8,
            levels: 5,
            value_range: [-0.98702455, 1.0],
            source_value_range: Some([-0.98702455, 1.0]),
            counts: Counts {
                tets_total: f.total_tets(),
                leaves: f.leaves(),
                nodes: f.nodes(),
                vertices: 35_937,
                coefficients: 35_929,
                outside_vertices: 0,
                empty_base_tets: 0,
            },
            encoding: Encoding::Quantized {
                bits: 11,
                step: 0.003_973_087_3,
                levels: LevelSteps::AXES,
            },
            max_error_bound: 0.001_987_024_366_162_433_7,
            max_abs_error: 0.001_986_101_269_721_985,
            files: [
                ("base.bin", 165, 1),
                ("blocks.bin", 12_892, 2),
                (LEVELSET_BAND_FILE, 4_321, 3),
            ]
            .into_iter()
            .map(|(n, bytes, crc32)| (n.to_string(), FileSum { bytes, crc32 }))
            .collect(),
            preview: Some(Preview {
                encoding: Encoding::uniform(9, 0.25),
                levels: 4,
                max_error_bound: 0.1,
            }),
            value_histogram: Some((0..HISTOGRAM_BINS as u64).map(|k| k * k).collect()),
            physical: Some(Physical {
                origin: [-90.0, 126.0, -72.0],
                frame: Some("RAS".into()),
                length_unit: Some("mm".into()),
                value_unit: None,
            }),
        }
    }

    #[derive(Serialize, Deserialize, PartialEq, Debug)]
    struct Sent(#[serde(with = "super")] Box<Manifest>);

    fn round_trip(m: &Manifest) -> (Result<Manifest, String>, usize) {
        let cfg = bincode::config::standard();
        let bytes = bincode::serde::encode_to_vec(Sent(Box::new(m.clone())), cfg).unwrap();
        let back = bincode::serde::decode_from_slice::<Sent, _>(&bytes, cfg)
            .map(|(s, _)| *s.0)
            .map_err(|e| e.to_string());
        (back, bytes.len())
    }

    #[test]
    fn a_session_receives_what_a_client_needs_in_fewer_bytes() {
        let m = store_manifest();
        let (back, _) = round_trip(&m);
        let mut want = m.clone();
        want.source.clear();
        want.files.retain(|n, _| n == LEVELSET_BAND_FILE);
        assert_eq!(back.unwrap(), want);
        // without a preview, a histogram and a volume's world: under half the whole
        // manifest's bincode
        let mut m = store_manifest();
        m.preview = None;
        m.value_histogram = None;
        m.physical = None;
        let (_, len) = round_trip(&m);
        let whole = bincode::serde::encode_to_vec(&m, bincode::config::standard())
            .unwrap()
            .len();
        assert!(len <= 101 && 2 * len < whole, "{len} bytes, whole {whole}");

        // an input range of its own, none at all, bounds that are no f32, no level set
        for (range, lo) in [(Some([-3.0, 2.5]), 0.1), (None, 1e-300)] {
            let mut m = store_manifest();
            m.source_value_range = range;
            m.bounds[0] = [lo, -lo, 0.0];
            m.files.clear();
            m.preview = None;
            let (back, _) = round_trip(&m);
            m.source.clear();
            assert_eq!(back.unwrap(), m);
        }
    }

    #[test]
    fn counts_that_overflow_the_ids_are_errors() {
        for (base_tets, levels) in [(u64::MAX, 16), (1 << 20, 17), (6, u8::MAX)] {
            let mut m = store_manifest();
            m.base_tets = base_tets;
            m.levels = levels;
            let (back, _) = round_trip(&m);
            let err = back.expect_err("refused");
            assert!(err.contains("levels") || err.contains("overflow"), "{err}");
        }
    }

    #[test]
    fn a_histogram_of_another_bin_count_is_refused() {
        let mut m = store_manifest();
        m.value_histogram = Some(vec![1; HISTOGRAM_BINS + 1]);
        let err = round_trip(&m).0.expect_err("refused");
        assert!(err.contains("bins"), "{err}");
    }
}
