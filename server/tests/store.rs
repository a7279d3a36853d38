//! The store: random access by node id range agrees with a sequential read and with the analysis,
//! quantized codes round-trip, and `verify` fails when the error exceeds the manifest's bound.

use proptest::prelude::*;
use tetwave_server::prepare::{prepare, verify, PrepareError, PrepareOptions};
use tetwave_store::{FormatError, Store, StoreError, BLOCK};

fn make_store(dir: &std::path::Path, levels: u8, bits: Option<u8>) -> Store {
    let mut o = PrepareOptions::new("synthetic:harmonic", dir);
    o.levels = Some(levels);
    o.bits = bits;
    o.keep_reference = true;
    prepare(&o).unwrap();
    Store::open(dir).unwrap()
}

#[test]
fn ranges_agree_with_a_full_read() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), 5, None);
    let n = store.manifest.counts.nodes;
    assert!(n > 2 * BLOCK);
    let all = store.read_nodes(0, n).unwrap();
    assert_eq!(all.len() as u64, n);
    assert_eq!(
        all.iter().map(|x| x.coeffs.len() as u64).sum::<u64>(),
        store.manifest.counts.coefficients
    );
    for (i, node) in all.iter().enumerate() {
        assert_eq!(node.id, i as u64);
    }
    let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig::with_cases(200));
    runner
        .run(&(0..n, 0..n), |(a, b)| {
            let (a, b) = (a.min(b), a.max(b));
            let part = store.read_nodes(a, b).unwrap();
            prop_assert_eq!(&part[..], &all[a as usize..b as usize]);
            Ok(())
        })
        .unwrap();
    assert!(matches!(
        store.read_nodes(5, n + 1),
        Err(StoreError::Format {
            source: FormatError::RangeOutOfBounds { .. },
            ..
        })
    ));
    assert!(matches!(
        store.read_nodes(7, 3),
        Err(StoreError::Format {
            source: FormatError::RangeOutOfBounds { .. },
            ..
        })
    ));
    assert!(store.read_nodes(9, 9).unwrap().is_empty());
}

#[test]
fn quantized_widths_round_trip() {
    for bits in [8u8, 12, 16, 20, 24] {
        let d = tempfile::tempdir().unwrap();
        let store = make_store(d.path(), 3, Some(bits));
        // coded: up to 16 bits, below the fixed-width codes alone of store format 1 (at 20 and 24
        // bits the low bits of each code are noise, which no entropy coder shrinks)
        let width = (bits as u64).div_ceil(8);
        let fixed = store.manifest.counts.coefficients * width;
        let coded = store.manifest.files["blocks.bin"].bytes;
        assert!(
            bits > 16 || coded < fixed,
            "bits {bits}: {coded} vs {fixed}"
        );
        let r = verify(d.path()).unwrap();
        assert!(r.max_abs_error.unwrap() <= r.max_error_bound, "bits {bits}");
        // more bits, smaller bound
        assert!(
            r.max_error_bound < 1.0 / (1u64 << (bits - 8)) as f64,
            "bits {bits}: {}",
            r.max_error_bound
        );
    }
}

#[test]
fn verify_fails_beyond_the_bound() {
    let d = tempfile::tempdir().unwrap();
    make_store(d.path(), 3, Some(8));
    let mpath = d.path().join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["max_error_bound"] = serde_json::json!(1e-12);
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    match verify(d.path()) {
        Err(PrepareError::VerifyFailed { error, bound, .. }) => assert!(error > bound),
        other => panic!("expected a failure, got {other:?}"),
    }
}

#[test]
fn truncated_store_files_are_refused() {
    let d = tempfile::tempdir().unwrap();
    make_store(d.path(), 3, None);
    for file in ["blocks.bin", "block_index.bin"] {
        let p = d.path().join(file);
        let b = std::fs::read(&p).unwrap();
        std::fs::write(&p, &b[..b.len() - 6]).unwrap();
        let e = Store::open(d.path()).err().expect("refused");
        assert!(e.to_string().contains(file), "{e}");
        std::fs::write(&p, &b).unwrap();
        Store::open(d.path()).unwrap();
    }
}

/// A manifest whose quantized encoding the decoders cannot read (0 or more than 24 bits, a step
/// that is not a positive number, level steps that would grow toward coarse levels) is refused when the store opens, with the reason, instead of
/// panicking later in a read (0 bits made a zero-width chunk, 40 bits a 5-byte code).
#[test]
fn unreadable_encodings_are_refused() {
    let d = tempfile::tempdir().unwrap();
    make_store(d.path(), 2, Some(12));
    let mpath = d.path().join("manifest.json");
    let text = std::fs::read_to_string(&mpath).unwrap();
    for (encoding, why) in [
        (
            serde_json::json!({"quantized": {"bits": 0, "step": 0.001}}),
            "bits 0 outside 8..=24",
        ),
        (
            serde_json::json!({"quantized": {"bits": 40, "step": 0.001}}),
            "bits 40 outside 8..=24",
        ),
        (
            serde_json::json!({"quantized": {"bits": 12, "step": -1.0}}),
            "step -1 is not",
        ),
        (
            serde_json::json!({"quantized": {"bits": 12, "step": 0.001, "levels": {"ratio": 0.5, "cap": 2.0}}}),
            "ratio 0.5 and cap 2 must lie in 1..=16",
        ),
    ] {
        let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
        m["encoding"] = encoding;
        std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
        let e = Store::open(d.path()).err().expect("refused");
        assert!(e.to_string().contains(why), "{e}");
        let e = verify(d.path()).expect_err("refused");
        assert!(e.to_string().contains(why), "{e}");
    }
}

/// Hierarchies beyond this machine's memory (4097³ and 8193³ vertices: terabytes) are refused
/// before any sample is allocated (not by an allocation failure, nor after resampling), and
/// levels past what the hierarchy supports are refused as such.
#[test]
fn too_many_levels_fail_before_resampling() {
    let d = tempfile::tempdir().unwrap();
    for levels in [12u8, 13] {
        let mut o = PrepareOptions::new("synthetic:harmonic", d.path());
        o.levels = Some(levels);
        let e = prepare(&o).expect_err("refused");
        let msg = e.to_string();
        assert!(
            msg.contains(&format!("at {levels} levels")) && msg.contains("fewer --levels"),
            "{msg}"
        );
    }
    let mut o = PrepareOptions::new("synthetic:harmonic", d.path());
    o.levels = Some(40);
    let msg = prepare(&o).expect_err("refused").to_string();
    assert!(msg.contains("--levels 40"), "{msg}");
    assert!(!d.path().join("manifest.json").exists());
}

/// `verify` needs a checksum for every store file: a manifest whose `files` map was emptied (or
/// lost an entry) is refused instead of passing unchecked.
#[test]
fn verify_needs_every_checksum() {
    let d = tempfile::tempdir().unwrap();
    make_store(d.path(), 2, None);
    let mpath = d.path().join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["files"].as_object_mut().unwrap().remove("blocks.bin");
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    let e = verify(d.path()).expect_err("refused");
    assert!(e.to_string().contains("no checksum for blocks.bin"), "{e}");
}

/// Prepares a level-2 store in `dir`, puts a directory at `blocked` (in place of the file there,
/// if any), and prepares level 3 over it: the error.
fn rewrite_over_a_directory(
    dir: &std::path::Path,
    blocked: &std::path::Path,
) -> tetwave_server::prepare::PrepareError {
    make_store(dir, 2, None);
    if blocked.exists() {
        std::fs::remove_file(blocked).unwrap();
    }
    std::fs::create_dir(blocked).unwrap();
    let mut o = PrepareOptions::new("synthetic:harmonic", dir);
    o.levels = Some(3);
    prepare(&o).expect_err("a directory where a file must go")
}

/// Preparing over an existing store that fails while its files are written (here
/// `block_index.bin.partial` cannot be created) leaves the old store as it was, and no partial
/// files.
#[test]
fn a_failed_rewrite_keeps_the_old_store() {
    let d = tempfile::tempdir().unwrap();
    let blocked = d.path().join("block_index.bin.partial");
    let e = rewrite_over_a_directory(d.path(), &blocked);
    assert!(e.to_string().contains("block_index.bin"), "{e}");
    let old = Store::open(d.path()).expect("the old store is still there");
    assert_eq!(old.manifest.levels, 2);
    verify(d.path()).unwrap();
    for name in ["base.bin", "blocks.bin"] {
        assert!(!d.path().join(format!("{name}.partial")).exists(), "{name}");
    }
    std::fs::remove_dir(&blocked).unwrap();
    assert_eq!(make_store(d.path(), 3, None).manifest.levels, 3);
}

/// Preparing over an existing store that fails while replacing it (here `blocks.bin` is a
/// directory the new file cannot be renamed over) leaves a directory that does not open as a
/// store, instead of the old manifest over a mix of new and old files; a prepare that succeeds
/// replaces the store whole.
#[test]
fn a_failed_rewrite_leaves_no_store() {
    let d = tempfile::tempdir().unwrap();
    let coeffs = d.path().join("blocks.bin");
    let e = rewrite_over_a_directory(d.path(), &coeffs);
    assert!(e.to_string().contains("blocks.bin"), "{e}");
    let e = Store::open(d.path()).err().expect("no store");
    assert!(e.to_string().contains("manifest.json"), "{e}");
    std::fs::remove_dir(&coeffs).unwrap();
    let store = make_store(d.path(), 3, None);
    assert_eq!(store.manifest.levels, 3);
    assert!(!d.path().join("manifest.json.partial").exists());
    verify(d.path()).unwrap();
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// `--max-error E`: over random fields (a raw f32 grid: a smooth wave plus noise of random
    /// amplitude, offset and scale) and random bounds (absolute or a percentage of the range), every
    /// synthesized vertex is within `E` of its sample, the manifest's bound is at most `E`, and
    /// `verify` passes; with either predictor (box6 grids get the axes predictor).
    #[test]
    fn every_vertex_within_max_error(
        seed in any::<u64>(),
        noise in 0.0f64..1.0,
        offset in -1e3f64..1e3,
        scale in 1e-3f64..1e3,
        exp in -5.0f64..-1.0,
        pct in any::<bool>(),
        levels in 2u8..4,
        box6 in any::<bool>(),
    ) {
        use tetwave_server::analysis::ErrorBound;
        let d = tempfile::tempdir().unwrap();
        let n = 9usize;
        let mut state = seed | 1;
        let mut rnd = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut bytes = Vec::with_capacity(n * n * n * 4);
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    let (x, y, z) = (i as f64 / 8.0, j as f64 / 8.0, k as f64 / 8.0);
                    let v = offset + scale * ((3.0 * x).sin() * (2.0 * y + z).cos() + noise * rnd());
                    bytes.extend_from_slice(&(v as f32).to_le_bytes());
                }
            }
        }
        let raw = d.path().join("field.raw");
        std::fs::write(&raw, bytes).unwrap();
        let out = d.path().join("store");
        let mut o = PrepareOptions::new(raw.to_str().unwrap(), &out);
        o.read.grid.dims = Some([n, n, n]);
        o.read.grid.dtype = "f32".into();
        o.keep_reference = true;
        o.levels = Some(levels);
        // the axes predictor (`--predictor auto` on a box6 grid), or the parent's on box5
        o.base = if box6 {
            tetwave_server::resample::BaseSpec::Box6
        } else {
            tetwave_server::resample::BaseSpec::Box5
        };
        let frac = 10f64.powf(exp);
        let bound = if pct { ErrorBound::OfRange(frac) } else { ErrorBound::Absolute(frac * scale) };
        o.max_error = Some(bound);
        if let Err(err) = prepare(&o) {
            // only a bound f32 cannot hold at these magnitudes, or one that would need codes over
            // 24 bits, may be refused
            let magnitude = offset.abs() + 2.0 * scale;
            let e = match bound {
                ErrorBound::Absolute(e) => e,
                ErrorBound::OfRange(f) => f * 2.0 * scale * (1.0 + noise),
            };
            prop_assert!(e < 2e-6 * magnitude, "refused a reachable bound {e}: {err}");
            prop_assert!(err.to_string().contains("lossless"), "{err}");
            return Ok(());
        }
        let store = Store::open(&out).unwrap();
        let values = store.synthesize_all().unwrap();
        let reference = store.read_reference().unwrap().expect("kept");
        let (lo, hi) = (store.manifest.value_range[0] as f64, store.manifest.value_range[1] as f64);
        let e = match bound {
            ErrorBound::Absolute(e) => e,
            ErrorBound::OfRange(f) => f * (hi - lo),
        };
        let worst = values
            .iter()
            .zip(&reference)
            .map(|(a, b)| (*a as f64 - *b as f64).abs())
            .fold(0.0, f64::max);
        prop_assert!(worst <= e, "max error {worst} > bound {e}");
        prop_assert!(store.manifest.max_error_bound <= e);
        prop_assert!(worst <= store.manifest.max_error_bound);
        prop_assert!(verify(&out).is_ok());
        let axes = store.base.predictor == tetwave_protocol::wavelet::Predictor::Axes;
        prop_assert_eq!(axes, box6);
    }
}

/// `--max-error` below what f32 can hold is refused with a message, and `--bits` with it too.
#[test]
fn max_error_refuses_what_it_cannot_keep() {
    use tetwave_server::analysis::ErrorBound;
    let d = tempfile::tempdir().unwrap();
    let mut o = PrepareOptions::new("synthetic:harmonic", &d.path().join("a"));
    o.levels = Some(2);
    o.max_error = Some(ErrorBound::Absolute(1e-12));
    let e = prepare(&o).unwrap_err().to_string();
    assert!(e.contains("--max-error") && e.contains("lossless"), "{e}");
    o.max_error = Some(ErrorBound::OfRange(1e-3));
    o.bits = Some(12);
    let e = prepare(&o).unwrap_err().to_string();
    assert!(e.contains("not both"), "{e}");
    assert!(ErrorBound::parse("0.1%").is_ok_and(|b| b == ErrorBound::OfRange(0.001)));
    assert!(ErrorBound::parse("2.5").is_ok_and(|b| b == ErrorBound::Absolute(2.5)));
    for bad in ["", "-1", "0", "inf", "abc%", "nan"] {
        assert!(ErrorBound::parse(bad).is_err(), "{bad:?}");
    }
}

/// A store holds what it streams and little else: no copy of the samples unless asked
/// (`--keep-reference`), so a grid store's directory is at most 1.2× its streamable bytes; with
/// the copy, 4 bytes a vertex more, which `verify` then compares with.
#[test]
fn a_store_keeps_no_copy_of_its_samples_unless_asked() {
    use tetwave_server::analysis::ErrorBound;
    let d = tempfile::tempdir().unwrap();
    let dir_bytes = |p: &std::path::Path| -> u64 {
        std::fs::read_dir(p)
            .unwrap()
            .map(|e| e.unwrap().metadata().unwrap().len())
            .sum()
    };
    let mut o = PrepareOptions::new("synthetic:harmonic", &d.path().join("s"));
    o.levels = Some(6);
    o.base = "box6".parse().unwrap();
    o.max_error = Some(ErrorBound::parse("0.1%").unwrap());
    let s = prepare(&o).unwrap();
    let on_disk = dir_bytes(&o.out);
    eprintln!(
        "harmonic box6 level 6 at 0.1%: {} vertices, {} streamable bytes, {on_disk} on disk",
        s.vertices, s.bytes
    );
    assert_eq!(s.reference_bytes, 0);
    assert!(!o.out.join("reference.f32").exists());
    assert!(
        on_disk as f64 <= 1.2 * s.bytes as f64,
        "{on_disk} bytes on disk for {} streamable",
        s.bytes
    );
    assert_eq!(verify(&o.out).unwrap().against, "bound");
    // asked: the copy is there, and verify compares with it
    o.keep_reference = true;
    let k = prepare(&o).unwrap();
    assert_eq!(k.reference_bytes, 4 * k.vertices);
    // (and the manifest's line for it)
    let more = dir_bytes(&o.out) - on_disk;
    assert!(
        (k.reference_bytes..k.reference_bytes + 200).contains(&more),
        "{more}"
    );
    let r = verify(&o.out).unwrap();
    assert_eq!(r.against, "reference");
    assert!(r.max_abs_error.unwrap() <= r.max_error_bound);
    // prepared again without it, the old copy goes: it is not this store's
    o.keep_reference = false;
    prepare(&o).unwrap();
    assert!(!o.out.join("reference.f32").exists());
    assert_eq!(dir_bytes(&o.out), on_disk);
}
