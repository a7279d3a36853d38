//! Analysis ↔ synthesis round trips, ownership, resampling accuracy and the outside rule.

use proptest::prelude::*;
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_protocol::testing::unsampled_base;
use tetwave_protocol::wavelet::Predictor;
use tetwave_protocol::LatticeTet;
use tetwave_server::analysis::{analyze_hierarchy, Precision};
use tetwave_server::resample::synthetic::kuhn_cube_mesh;
use tetwave_server::resample::unstructured::{clean, Locator};
use tetwave_server::resample::{base, resample, BaseSpec, Resampled, Source};

fn resampled_with(levels: u8, box6: bool, field: impl Fn(u64) -> f32) -> Resampled {
    let shape = if box6 {
        base::box6([0.0; 3], [1.0; 3])
    } else {
        base::box5([0.0; 3], [1.0; 3])
    };
    let mut b = unsampled_base(levels, shape);
    let keys = b.vertex_keys();
    let samples: Vec<f32> = (0..keys.vertex_count()).map(field).collect();
    b.values = samples[..b.positions.len()].to_vec();
    Resampled {
        base: b,
        keys,
        samples,
        outside: 0,
    }
}

/// Like [`resampled_with`], the field given at the vertices' positions.
fn resampled_with_positions(levels: u8, box6: bool, field: impl Fn([f64; 3]) -> f32) -> Resampled {
    let mut r = resampled_with(levels, box6, |_| 0.0);
    for (e, _) in r.keys.entities() {
        r.keys.for_each_in(e, |k, t, w| {
            r.samples[k as usize] = field(r.base.position(t, &w))
        });
    }
    r.base.values = r.samples[..r.base.positions.len()].to_vec();
    r
}

fn hash(seed: u64, k: u64) -> f64 {
    // splitmix64 → [0, 1)
    let mut z = seed.wrapping_add(k.wrapping_mul(0x9E3779B97F4A7C15));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// synthesis ∘ analysis = identity, bit for bit, for smooth fields whose predictions stay within
    /// a factor 2 of the values (the f32 lifting step is then exact by Sterbenz' lemma), at any
    /// level 0–6, on box5 and box6, and with the axes predictor.
    #[test]
    fn round_trip_bit_exact(levels in 0u8..=6, seed in any::<u64>(), kind in 0u8..3) {
        let (a0, a1) = (hash(seed, 1), hash(seed, 2));
        let mut r = resampled_with_positions(levels, kind > 0, |p| {
            (1.2 + 0.3 * (3.0 * p[0] + a0).sin() * (2.0 * p[1] - a1).cos() + 0.2 * p[2] * p[2]) as f32
        });
        if kind == 2 {
            r.base.predictor = Predictor::Axes;
        }
        let reference = r.samples.clone();
        let a = analyze_hierarchy(r, Precision::Lossless, false).unwrap();
        let keys = a.base.vertex_keys();
        let values = synthesize_all(&a.base, &keys, a.nodes()).unwrap();
        prop_assert_eq!(values, reference);
        prop_assert_eq!(a.max_abs_error, 0.0);
    }

    /// Noise within a factor 2: a quadratic prediction may leave the factor 2 (its weights reach
    /// ±2), so the round trip is within a few ulps, and the analysis reports what it is.
    #[test]
    fn round_trip_of_noise_within_ulps(levels in 0u8..=5, seed in any::<u64>(), box6 in any::<bool>()) {
        let r = resampled_with(levels, box6, |k| (1.0 + hash(seed, k)) as f32);
        let reference = r.samples.clone();
        let a = analyze_hierarchy(r, Precision::Lossless, false).unwrap();
        let keys = a.base.vertex_keys();
        let values = synthesize_all(&a.base, &keys, a.nodes()).unwrap();
        let err = values.iter().zip(&reference).map(|(x, y)| (*x as f64 - *y as f64).abs()).fold(0.0, f64::max);
        prop_assert!(err <= 4.0 * 2.0 * f32::EPSILON as f64, "err {}", err);
        prop_assert_eq!(err, a.max_abs_error);
    }

    /// For arbitrary fields (signs, zeros, several orders of magnitude) the round trip stays within
    /// 1e-6 × the value range.
    #[test]
    fn round_trip_any_field(levels in 0u8..=5, seed in any::<u64>(), scale in 1e-3f64..1e6) {
        let r = resampled_with(levels, false, |k| ((hash(seed, k) - 0.5) * scale) as f32);
        let reference = r.samples.clone();
        let a = analyze_hierarchy(r, Precision::Lossless, false).unwrap();
        let keys = a.base.vertex_keys();
        let values = synthesize_all(&a.base, &keys, a.nodes()).unwrap();
        let range = (a.value_range.1 - a.value_range.0) as f64;
        let err = values.iter().zip(&reference).map(|(x, y)| (*x as f64 - *y as f64).abs()).fold(0.0, f64::max);
        prop_assert!(err <= 1e-6 * range, "err {} range {}", err, range);
        prop_assert!(err <= a.error_bound);
    }

    /// Quantized: every vertex within the manifest bound (q/2), whatever the level and predictor
    /// (white noise is where the axes predictor's cubic overshoots the codes' width most).
    #[test]
    fn quantized_error_within_bound(levels in 1u8..=5, seed in any::<u64>(), bits in 8u8..=16, axes in any::<bool>()) {
        let mut r = resampled_with(levels, axes, |k| (hash(seed, k) * 100.0) as f32);
        if axes {
            r.base.predictor = Predictor::Axes;
        }
        let reference = r.samples.clone();
        let a = analyze_hierarchy(r, Precision::Bits(bits), false).unwrap();
        let keys = a.base.vertex_keys();
        let values = synthesize_all(&a.base, &keys, a.nodes()).unwrap();
        let err = values.iter().zip(&reference).map(|(x, y)| (*x as f64 - *y as f64).abs()).fold(0.0, f64::max);
        prop_assert!(err <= a.error_bound, "err {} bound {}", err, a.error_bound);
        prop_assert!((err - a.max_abs_error).abs() < 1e-12);
    }
}

/// Every new vertex has exactly one owning tet; it is the lowest-id tet of its level containing the
/// vertex's edge.
#[test]
fn every_new_vertex_has_exactly_one_owner() {
    let levels = 4;
    let r = resampled_with(levels, false, |k| k as f32);
    let a = analyze_hierarchy(r, Precision::Lossless, false).unwrap();
    let keys = a.base.vertex_keys();
    let forest = a.base.forest();
    let mut owner = vec![None; keys.vertex_count() as usize];
    let mut lowest = vec![u64::MAX; keys.vertex_count() as usize];
    for id in 0..forest.nodes() {
        let t = LatticeTet::from_id(&forest, id);
        for e in 0..6 {
            let k = keys.key(t.base, &t.edge_midpoint(e)) as usize;
            lowest[k] = lowest[k].min(id);
            if a.owned[id as usize] & (1 << e) != 0 {
                assert!(owner[k].is_none(), "vertex {k} owned twice");
                owner[k] = Some(id);
            }
        }
    }
    let nv = a.base.positions.len();
    for k in 0..owner.len() {
        if k < nv {
            assert!(owner[k].is_none());
        } else {
            assert_eq!(owner[k], Some(lowest[k]), "vertex {k}");
        }
    }
    assert_eq!(a.coeffs.len(), owner.len() - nv);
}

/// An unstructured mesh carrying a linear field is reproduced to 1e-5 relative at every vertex.
#[test]
fn unstructured_linear_field_is_reproduced() {
    let lin = |p: [f64; 3]| 1.0 + p[0] + 2.0 * p[1] + 3.0 * p[2];
    let mesh = kuhn_cube_mesh(6, 0.3, |_, _, _| true, lin);
    let (m, report) = clean(mesh, None, None).unwrap();
    assert_eq!(report.tets_kept, 6 * 216);
    let source = Source::Mesh(Box::new(Locator::new(&m)), ([0.0; 3], [1.0; 3]));
    for spec in [BaseSpec::Box5, BaseSpec::Box6] {
        let r = resample(&source, &spec, 4).unwrap();
        assert_eq!(r.outside, 0);
        for (e, range) in r.keys.entities() {
            r.keys.for_each_in(e, |k, t, w| {
                let want = lin(r.base.position(t, &w));
                let got = r.samples[k as usize] as f64;
                assert!((got - want).abs() <= 1e-5 * want.abs(), "{got} vs {want}");
            });
            let _ = range;
        }
    }
}

/// A non-convex (L-shaped) input: vertices in the missing quadrant are outside; tets entirely there
/// are flagged empty; no tet touching the domain is.
#[test]
fn non_convex_input_leaves_outside_tets_empty() {
    let n = 4;
    // L shape: drop the cells with x > 0.5 and y > 0.5
    let mesh = kuhn_cube_mesh(
        n,
        0.0,
        |i, j, _| !(i >= n / 2 && j >= n / 2),
        |p| p[0] + p[1] + p[2],
    );
    let (m, _) = clean(mesh, None, None).unwrap();
    let source = Source::Mesh(Box::new(Locator::new(&m)), ([0.0; 3], [1.0; 3]));
    let levels = 4;
    let r = resample(&source, &BaseSpec::Box6, levels).unwrap();
    assert!(r.outside > 0);
    let outside: Vec<bool> = r.samples.iter().map(|x| x.is_nan()).collect();
    let a = analyze_hierarchy(r, Precision::Lossless, false).unwrap();
    let keys = a.base.vertex_keys();
    let forest = a.base.forest();
    let (mut empty_leaves, mut leaves_fully_out) = (0, 0);
    for id in forest.level_start(levels)..forest.total_tets() {
        let t = LatticeTet::from_id(&forest, id);
        let parent = forest.parent(id).unwrap() as usize;
        let flagged = a.empty_children[parent] & (1 << forest.child_index(id).unwrap()) != 0;
        let all_out = t.v.iter().all(|w| outside[keys.key(t.base, w) as usize]);
        let pos = t.v.map(|w| a.base.position(t.base, &w));
        let centroid = [0, 1, 2].map(|ax| pos.iter().map(|p| p[ax]).sum::<f64>() / 4.0);
        if all_out {
            leaves_fully_out += 1;
        }
        assert_eq!(flagged, all_out, "leaf {id} at {centroid:?}");
        if flagged {
            empty_leaves += 1;
            // an empty leaf lies in the missing quadrant
            assert!(centroid[0] > 0.5 && centroid[1] > 0.5, "{centroid:?}");
        }
    }
    assert!(empty_leaves > 0 && empty_leaves == leaves_fully_out);
    // outside vertices carry a zero detail: their synthesized value is the linear prediction, and the
    // subtree max |detail| of empty subtrees is 0
    for id in 0..forest.nodes() as usize {
        if a.empty_children[id] == 0xff {
            assert_eq!(a.subtree_max_abs[id], 0.0, "node {id}");
        }
    }
}
