//! `prepare --parts N --part K` then `--finish` writes the store that one process writes, byte for
//! byte (lossless and to a bound, f32 and u16 grids, padded lattices, uneven layer splits); the
//! finish refuses a missing part (naming it), a part whose file changed, and parts prepared with
//! other options; a part re-run alone completes the store; too many parts for the lattice's layers
//! are refused with what works.

mod ct_common;

use ct_common::ct_field as field;
use std::path::Path;
use tetwave_server::analysis::ErrorBound;
use tetwave_server::prepare::{parts, prepare, GridArgs, PartsArgs, PrepareError, PrepareOptions};
use tetwave_store::STORE_FILES;

fn write_grid(path: &Path, v: &[f32], dtype: &str) {
    let bytes: Vec<u8> = match dtype {
        "f32" => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        "u16" => v.iter().flat_map(|x| (*x as u16).to_le_bytes()).collect(),
        _ => unreachable!(),
    };
    std::fs::write(path, bytes).unwrap();
}

fn options(raw: &Path, out: &Path, dims: [usize; 3], dtype: &str, levels: u8) -> PrepareOptions {
    let mut o = PrepareOptions::new(raw.to_str().unwrap(), out);
    o.read.grid = GridArgs {
        dims: Some(dims),
        dtype: dtype.into(),
        spacing: [1.0, 1.0, 2.0],
        volume: None,
    };
    o.levels = Some(levels);
    o
}

fn by_parts(o: &PrepareOptions, n: u32, part: Option<u32>) -> PrepareOptions {
    PrepareOptions {
        by_parts: PartsArgs {
            parts: Some(n),
            part,
            finish: part.is_none(),
        },
        ..o.clone()
    }
}

fn run_parts(o: &PrepareOptions, n: u32) {
    for k in 0..n {
        parts::prepare_part(&by_parts(o, n, Some(k)), n, k).unwrap();
    }
}

/// Every file of store `a` equals `b`'s, and `b` holds no other.
fn assert_same_store(a: &Path, b: &Path) {
    let names = |d: &Path| {
        let mut v: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .collect();
        v.sort();
        v
    };
    assert_eq!(names(a), names(b), "the stores hold different files");
    for name in names(a) {
        let (x, y) = (
            std::fs::read(a.join(&name)).unwrap(),
            std::fs::read(b.join(&name)).unwrap(),
        );
        assert!(x == y, "{name} differs ({} and {} bytes)", x.len(), y.len());
    }
    for f in STORE_FILES {
        assert!(a.join(f).exists(), "{f} missing");
    }
}

#[test]
fn parts_write_the_one_process_store_byte_for_byte() {
    let tmp = tempfile::tempdir().unwrap();
    // 37×29×65 at 3 levels: 5×4×8 boxes (x and y padded)
    let dims = [37, 29, 65];
    let v = field(dims);
    for dtype in ["f32", "u16"] {
        let raw = tmp.path().join(format!("ct-{dtype}.raw"));
        write_grid(&raw, &v, dtype);
        for max_error in [None, Some("0.5%")] {
            // 1, 3, 8: whole layers; 16, 32: 2 and 4 row ranges of each layer
            for n in [1, 3, 8, 16, 32] {
                let one = tmp.path().join("one");
                let many = tmp.path().join("many");
                let _ = std::fs::remove_dir_all(&one);
                let _ = std::fs::remove_dir_all(&many);
                let mut o = options(&raw, &one, dims, dtype, 3);
                o.max_error = max_error.map(|e| ErrorBound::parse(e).unwrap());
                let whole = prepare(&o).unwrap();
                assert_eq!(whole.base, "kuhn-boxes 5x4x8");
                let o = PrepareOptions {
                    out: many.clone(),
                    ..o
                };
                run_parts(&o, n);
                let finished = prepare(&by_parts(&o, n, None)).unwrap();
                assert_same_store(&one, &many);
                assert!(!many.join("parts").exists(), "the finish leaves parts/");
                assert_eq!(finished.bytes, whole.bytes);
                assert_eq!(finished.coefficients, whole.coefficients);
            }
        }
    }
}

#[test]
fn finish_refuses_missing_and_changed_parts_and_a_rerun_part_completes_the_store() {
    let tmp = tempfile::tempdir().unwrap();
    let dims = [17, 17, 33];
    let raw = tmp.path().join("g.raw");
    write_grid(&raw, &field(dims), "f32");
    let one = tmp.path().join("one");
    let many = tmp.path().join("many");
    let mut o = options(&raw, &one, dims, "f32", 2);
    o.max_error = Some(ErrorBound::parse("1%").unwrap());
    prepare(&o).unwrap();
    let o = PrepareOptions {
        out: many.clone(),
        ..o
    };
    let n = 4;
    run_parts(&o, n);
    let summary = many.join("parts/part-2-of-4/part.json");
    std::fs::remove_file(&summary).unwrap();
    std::fs::remove_file(many.join("parts/part-3-of-4/part.json")).unwrap();
    let e = prepare(&by_parts(&o, n, None)).unwrap_err().to_string();
    assert!(e.contains("part 2, part 3"), "{e}");
    assert!(
        !many.join("manifest.json").exists(),
        "a store without its parts looks whole"
    );
    // re-run the missing parts alone
    for k in [2, 3] {
        parts::prepare_part(&by_parts(&o, n, Some(k)), n, k).unwrap();
    }
    // a part's nodes changed after it was written: refused, naming it
    let nodes = many.join("parts/part-1-of-4/nodes.bin");
    let mut b = std::fs::read(&nodes).unwrap();
    let mid = b.len() / 2;
    b[mid] ^= 0x10;
    std::fs::write(&nodes, &b).unwrap();
    let e = prepare(&by_parts(&o, n, None)).unwrap_err().to_string();
    assert!(
        e.contains("part-1-of-4") && e.contains("run the part again"),
        "{e}"
    );
    assert!(!many.join("manifest.json").exists());
    parts::prepare_part(&by_parts(&o, n, Some(1)), n, 1).unwrap();
    prepare(&by_parts(&o, n, None)).unwrap();
    assert_same_store(&one, &many);

    // a part prepared with another bound is refused
    run_parts(&o, n);
    let mut other = by_parts(&o, n, Some(0));
    other.max_error = Some(ErrorBound::parse("2%").unwrap());
    parts::prepare_part(&other, n, 0).unwrap();
    let e = prepare(&by_parts(&o, n, None)).unwrap_err().to_string();
    assert!(e.contains("part 0") && e.contains("other options"), "{e}");
}

#[test]
fn parts_refuse_what_they_cannot_split() {
    let tmp = tempfile::tempdir().unwrap();
    let dims = [17, 17, 17];
    let raw = tmp.path().join("g.raw");
    write_grid(&raw, &field(dims), "f32");
    let out = tmp.path().join("s");
    let o = options(&raw, &out, dims, "f32", 3);
    // 16 voxel steps at 3 levels: 2 layers of boxes
    let e = parts::prepare_part(&by_parts(&o, 3, Some(0)), 3, 0)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("2 layer(s)") && e.contains("fewer --levels"),
        "{e}"
    );
    let e = parts::prepare_part(&by_parts(&o, 2, Some(2)), 2, 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("0 to 1"), "{e}");
    let mut bits = by_parts(&o, 2, Some(0));
    bits.bits = Some(12);
    assert!(matches!(
        parts::prepare_part(&bits, 2, 0),
        Err(PrepareError::Usage(_))
    ));
    let mut mesh = by_parts(&o, 2, Some(0));
    mesh.read.grid.dims = None;
    mesh.input = "synthetic:harmonic".into();
    let e = parts::prepare_part(&mesh, 2, 0).unwrap_err().to_string();
    assert!(e.contains("raw grid"), "{e}");
    let mut neither = by_parts(&o, 2, None);
    neither.by_parts.finish = false;
    let e = prepare(&neither).unwrap_err().to_string();
    assert!(e.contains("--part K"), "{e}");
}

#[test]
fn out_of_core_keeps_the_parts_an_earlier_run_finished() {
    let tmp = tempfile::tempdir().unwrap();
    let dims = [37, 29, 65];
    let raw = tmp.path().join("g.raw");
    write_grid(&raw, &field(dims), "u16");
    let one = tmp.path().join("one");
    let ooc = tmp.path().join("ooc");
    // 65 MiB: 64 for the process, 1 for a part (the whole hierarchy needs about 3 MiB)
    let memory = 65u64 << 20;
    let mut o = options(&raw, &ooc, dims, "u16", 3);
    o.levels = None;
    o.memory = Some(memory);
    o.max_error = Some(ErrorBound::parse("0.5%").unwrap());
    let plan = parts::out_of_core_plan(&o, memory).unwrap();
    assert!(plan.parts > 2, "{plan:?}");
    assert!(plan.part_bytes <= memory, "{plan:?}");
    // an earlier run cut short: part 0 done, part 1 begun (no summary)
    let at = PrepareOptions {
        levels: Some(plan.levels),
        ..o.clone()
    };
    parts::prepare_part(&by_parts(&at, plan.parts, Some(0)), plan.parts, 0).unwrap();
    parts::prepare_part(&by_parts(&at, plan.parts, Some(1)), plan.parts, 1).unwrap();
    let dir = |k: u32| ooc.join(format!("parts/part-{k}-of-{}", plan.parts));
    std::fs::remove_file(dir(1).join("part.json")).unwrap();
    let written = |k: u32| {
        std::fs::metadata(dir(k).join("part.json"))
            .unwrap()
            .modified()
            .unwrap()
    };
    let kept = written(0);
    // a run that stops at part 2 (its directory's place is taken by a file)
    std::fs::write(dir(2), b"in the way").unwrap();
    std::thread::sleep(std::time::Duration::from_millis(20));
    assert!(prepare(&o).is_err());
    assert_eq!(written(0), kept, "part 0 was prepared again");
    assert!(dir(1).join("part.json").exists(), "part 1 was not resumed");
    // and a run that completes: the store the in-memory one of those levels
    std::fs::remove_file(dir(2)).unwrap();
    let s = prepare(&o).unwrap();
    assert_eq!(s.levels, plan.levels);
    assert!(!ooc.join("parts").exists());
    let whole = PrepareOptions {
        out: one.clone(),
        memory: None,
        ..at
    };
    prepare(&whole).unwrap();
    assert_same_store(&one, &ooc);
}

/// A full disk (writes into `/dev/full`, through a symlink where a file goes): one error naming
/// the file and the cause, and nothing that looks like a finished part or store.
#[test]
fn a_full_disk_is_an_error_naming_the_file_and_leaves_nothing_that_looks_done() {
    let full = Path::new("/dev/full");
    assert!(full.exists(), "/dev/full is missing: this test needs Linux");
    let tmp = tempfile::tempdir().unwrap();
    let dims = [17, 17, 33];
    let raw = tmp.path().join("g.raw");
    write_grid(&raw, &field(dims), "f32");
    let out = tmp.path().join("s");
    let o = options(&raw, &out, dims, "f32", 2);
    // a part's node file
    let dir = out.join("parts/part-0-of-2");
    std::fs::create_dir_all(&dir).unwrap();
    std::os::unix::fs::symlink(full, dir.join("nodes.bin")).unwrap();
    let e = parts::prepare_part(&by_parts(&o, 2, Some(0)), 2, 0)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("nodes.bin") && e.contains("No space left"),
        "{e}"
    );
    assert!(
        !dir.join("part.json").exists(),
        "a part that failed looks done"
    );
    // the store's blocks, at the finish
    std::fs::remove_file(dir.join("nodes.bin")).unwrap();
    for k in 0..2 {
        parts::prepare_part(&by_parts(&o, 2, Some(k)), 2, k).unwrap();
    }
    std::os::unix::fs::symlink(full, out.join("blocks.bin.partial")).unwrap();
    let e = prepare(&by_parts(&o, 2, None)).unwrap_err().to_string();
    assert!(
        e.contains("blocks.bin") && e.contains("No space left"),
        "{e}"
    );
    assert!(
        !out.join("manifest.json").exists(),
        "a store that failed looks whole"
    );
    // and in one process
    let one = tmp.path().join("one");
    std::fs::create_dir_all(&one).unwrap();
    std::os::unix::fs::symlink(full, one.join("blocks.bin.partial")).unwrap();
    let e = prepare(&PrepareOptions {
        out: one.clone(),
        ..o.clone()
    })
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("blocks.bin") && e.contains("No space left"),
        "{e}"
    );
    assert!(!one.join("manifest.json").exists());
}
