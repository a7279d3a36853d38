//! `tetwave-server prepare` / `verify` end to end: the thesis' counts, the error bounds, and one test
//! per kind of bad input (clear one-line error, non-zero exit, never a panic).

use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use tetwave_protocol::shapes::box6;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tetwave-server"))
}

struct Run {
    ok: bool,
    stdout: String,
    stderr: String,
}

fn run(args: &[&str]) -> Run {
    let out = bin().args(args).output().expect("runs");
    let r = Run {
        ok: out.status.success(),
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    };
    assert!(!r.stderr.contains("panicked"), "panic: {}", r.stderr);
    r
}

fn prepare_json(args: &[&str]) -> Value {
    let r = run(args);
    assert!(r.ok, "prepare failed: {}", r.stderr);
    serde_json::from_str(r.stdout.trim()).expect("one JSON object")
}

/// Fails with exactly one `error:` line on stderr that contains every `needle`.
fn expect_error(args: &[&str], needles: &[&str]) {
    let r = run(args);
    assert!(!r.ok, "should fail: {args:?}\n{}", r.stdout);
    let lines: Vec<&str> = r
        .stderr
        .lines()
        .filter(|l| l.starts_with("error:"))
        .collect();
    assert_eq!(lines.len(), 1, "one error line expected: {}", r.stderr);
    assert_eq!(lines[0].lines().count(), 1);
    for n in needles {
        assert!(lines[0].contains(n), "{:?} lacks {n:?}", lines[0]);
    }
}

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn harmonic_level5_matches_thesis_table_and_verifies() {
    let d = tmp();
    let store = d.path().join("h5");
    let j = prepare_json(&[
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "5",
        "--out",
        s(&store),
        "--json",
    ]);
    assert_eq!(j["base_tets"], 5);
    assert_eq!(j["levels"], 5);
    assert_eq!(j["tets_total"], 187_245);
    assert_eq!(j["leaves"], 163_840);
    assert_eq!(j["nodes"], 23_405);
    assert_eq!(j["vertices"], 30_481);
    assert_eq!(j["coefficients"], 30_473);
    for k in ["bytes", "max_abs_error", "seconds"] {
        assert!(j[k].is_number(), "{k}");
    }
    let range = j["value_range"][1].as_f64().unwrap() - j["value_range"][0].as_f64().unwrap();
    assert!(j["max_abs_error"].as_f64().unwrap() <= 1e-6 * range);
    // the store keeps no copy of its samples: `verify` checks its bound, `--input` the field
    let r = run(&["verify", s(&store), "--json"]);
    assert!(r.ok, "{}", r.stderr);
    let v: Value = serde_json::from_str(r.stdout.trim()).unwrap();
    assert_eq!(
        (&v["against"], &v["max_abs_error"]),
        (&json!("bound"), &Value::Null)
    );
    assert!(!store.join("reference.f32").exists());
    let r = run(&[
        "verify",
        s(&store),
        "--input",
        "synthetic:harmonic",
        "--json",
    ]);
    assert!(r.ok, "{}", r.stderr);
    let v: Value = serde_json::from_str(r.stdout.trim()).unwrap();
    assert_eq!(v["input"]["points_are"], "vertices");
    assert_eq!(v["input"]["points"], 30_481);
    assert!(v["input"]["max_abs_error"].as_f64().unwrap() <= 1e-6 * range);
}

#[test]
fn quantized_12_bits_within_manifest_bound() {
    let d = tmp();
    let store = d.path().join("q");
    let j = prepare_json(&[
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "5",
        "--bits",
        "12",
        "--out",
        s(&store),
        "--json",
    ]);
    let err = j["max_abs_error"].as_f64().unwrap();
    let bound = j["max_error_bound"].as_f64().unwrap();
    assert!(err > 0.0 && err <= bound, "err {err} bound {bound}");
    let r = run(&[
        "verify",
        s(&store),
        "--input",
        "synthetic:harmonic",
        "--json",
    ]);
    assert!(r.ok, "{}", r.stderr);
    let v: Value = serde_json::from_str(r.stdout.trim()).unwrap();
    let c = &v["input"];
    assert!(c["max_abs_error"].as_f64().unwrap() <= bound);
    // the RMS error (PSNR's) is positive for a quantized store and at most the largest error
    let rms = c["rms_error"].as_f64().unwrap();
    assert!(
        rms > 0.0 && rms <= c["max_abs_error"].as_f64().unwrap(),
        "{v}"
    );
    // another field than the store's is refused past the bound
    let r = run(&["verify", s(&store), "--input", "synthetic:linear"]);
    assert!(
        !r.ok && r.stderr.contains("exceeds the manifest's bound"),
        "{}",
        r.stderr
    );
    // coded 12-bit codes: the whole of blocks.bin (masks, bounds and codes) is smaller than the
    // 30,473 codes alone took at a fixed 2 bytes each in store format 1
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(store.join("manifest.json")).unwrap())
            .unwrap();
    assert_eq!(m["counts"]["coefficients"], 30_473);
    let blocks = m["files"]["blocks.bin"]["bytes"].as_u64().unwrap();
    assert!(blocks < 2 * 30_473, "blocks.bin: {blocks} bytes");
}

#[test]
fn level6_and_box6_counts() {
    let d = tmp();
    let j = prepare_json(&[
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "6",
        "--out",
        s(&d.path().join("h6")),
        "--json",
    ]);
    assert_eq!(j["tets_total"], 1_497_965);
    assert_eq!(j["leaves"], 1_310_720);
    assert_eq!(j["nodes"], 187_245);
    assert_eq!(j["vertices"], 230_945);
    let j = prepare_json(&[
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "5",
        "--base",
        "box6",
        "--out",
        s(&d.path().join("b6")),
        "--json",
    ]);
    assert_eq!(j["tets_total"], 224_694);
    assert_eq!(j["vertices"], 35_937);
}

#[test]
fn verify_fails_on_a_corrupted_store() {
    let d = tmp();
    let store = d.path().join("c");
    prepare_json(&[
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "3",
        "--keep-reference",
        "--out",
        s(&store),
        "--json",
    ]);
    // a flipped byte inside blocks.bin: block 0 no longer decodes, which every open finds
    let p = store.join("blocks.bin");
    let original = std::fs::read(&p).unwrap();
    let mut b = original.clone();
    let mid = b.len() / 2;
    b[mid] ^= 0x55;
    std::fs::write(&p, &b).unwrap();
    expect_error(&["verify", s(&store)], &["blocks.bin", "block 0"]);
    expect_error(
        &["serve", s(&store), "--addr", "127.0.0.1:0"],
        &["blocks.bin", "block 0"],
    );
    std::fs::write(&p, &original).unwrap();
    // a flip that keeps the structure (the reference values are not streamed): `verify` finds it
    // by its checksum, and `serve` checks the checksums only with --verify (and then refuses before
    // it binds)
    let p = store.join("reference.f32");
    let mut b = std::fs::read(&p).unwrap();
    b[10] ^= 0x55;
    std::fs::write(&p, b).unwrap();
    expect_error(&["verify", s(&store)], &["reference.f32", "checksum"]);
    expect_error(
        &["serve", s(&store), "--verify", "--addr", "127.0.0.1:0"],
        &["reference.f32", "checksum"],
    );
}

// ---- bad input ----

fn write_raw(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

/// A legacy-VTK ascii unstructured grid written by hand (not by the reader's code).
fn write_vtk(
    dir: &Path,
    name: &str,
    points: &[[f64; 3]],
    cells: &[(u8, Vec<u32>)],
    scalars: &[(&str, Vec<f64>)],
) -> PathBuf {
    let mut t =
        String::from("# vtk DataFile Version 3.0\ntest\nASCII\nDATASET UNSTRUCTURED_GRID\n");
    t += &format!("POINTS {} double\n", points.len());
    for p in points {
        t += &format!("{} {} {}\n", p[0], p[1], p[2]);
    }
    let size: usize = cells.iter().map(|c| c.1.len() + 1).sum();
    t += &format!("CELLS {} {}\n", cells.len(), size);
    for (_, c) in cells {
        t += &format!(
            "{} {}\n",
            c.len(),
            c.iter()
                .map(|x| x.to_string())
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    t += &format!("CELL_TYPES {}\n", cells.len());
    for (k, _) in cells {
        t += &format!("{k}\n");
    }
    if !scalars.is_empty() {
        t += &format!("POINT_DATA {}\n", points.len());
        for (n, v) in scalars {
            t += &format!("SCALARS {n} double 1\nLOOKUP_TABLE default\n");
            for x in v {
                t += &format!("{x}\n");
            }
        }
    }
    let p = dir.join(name);
    std::fs::write(&p, t).unwrap();
    p
}

/// The unit cube's corners and its 6 Kuhn tets (VTK cell type 10), positively oriented: `box6`.
fn cube_points() -> Vec<[f64; 3]> {
    box6([0.0; 3], [1.0; 3]).0
}

fn cube_tets() -> Vec<(u8, Vec<u32>)> {
    let (_, tets) = box6([0.0; 3], [1.0; 3]);
    tets.iter().map(|t| (10, t.to_vec())).collect()
}

fn lin(p: &[f64; 3]) -> f64 {
    p[0] + 2.0 * p[1] + 3.0 * p[2]
}

#[test]
fn missing_file() {
    let d = tmp();
    let missing = d.path().join("nope.vtu");
    expect_error(
        &["prepare", s(&missing), "--out", s(&d.path().join("o"))],
        &["nope.vtu"],
    );
}

/// Garbage and truncated mesh files: an error naming the file, never a panic.
#[test]
fn garbage_and_truncated_meshes_name_the_file() {
    let cases: [(&str, &[u8]); 3] = [
        ("garbage.vtu", b"\x00\x01this is not xml at all\xff\xfe"),
        (
            "cut.msh",
            b"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n8\n1 0 0 0\n2 1 0 0\n3 0 1",
        ),
        (
            "cut.vtu",
            b"<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"0.1\"><UnstructuredGrid><Piece NumberOfPoints=\"8\" NumberOfCells=\"6\"><Points><DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">0 0 0 1 0",
        ),
    ];
    for (name, bytes) in cases {
        let d = tmp();
        let p = write_raw(d.path(), name, bytes);
        expect_error(
            &["prepare", s(&p), "--out", s(&d.path().join("o"))],
            &[name],
        );
    }
}

#[test]
fn raw_size_disagrees_with_dims() {
    let d = tmp();
    let p = write_raw(d.path(), "v.raw", &vec![7u8; 1000]);
    expect_error(
        &[
            "prepare",
            s(&p),
            "--dims",
            "10,10,11",
            "--out",
            s(&d.path().join("o")),
        ],
        &["v.raw", "does not match", "1100"],
    );
    // dims whose product overflows u64 show the exact size asked for
    expect_error(
        &[
            "prepare",
            s(&p),
            "--dims",
            "4294967295,4294967295,4294967295",
            "--dtype",
            "f32",
            "--out",
            s(&d.path().join("o")),
        ],
        &["316912649835696421541200789500 bytes"],
    );
}

#[test]
fn truncated_raw() {
    let d = tmp();
    let p = write_raw(d.path(), "t.raw", &vec![7u8; 2 * 999]);
    expect_error(
        &[
            "prepare",
            s(&p),
            "--dims",
            "10,10,10",
            "--dtype",
            "u16",
            "--out",
            s(&d.path().join("o")),
        ],
        &["t.raw", "1998 bytes"],
    );
}

#[test]
fn raw_ok_and_u16() {
    let d = tmp();
    let dims = 9usize;
    let mut b = Vec::new();
    for k in 0..dims {
        for j in 0..dims {
            for i in 0..dims {
                b.extend_from_slice(&((i + 2 * j + 3 * k) as u16 * 10).to_le_bytes());
            }
        }
    }
    let p = write_raw(d.path(), "lin.raw", &b);
    let j = prepare_json(&[
        "prepare",
        s(&p),
        "--dims",
        "9,9,9",
        "--dtype",
        "u16",
        "--levels",
        "3",
        "--base",
        "box6",
        "--out",
        s(&d.path().join("o")),
        "--json",
    ]);
    // trilinear interpolation of a linear field is exact: values span 0..=10*(8+16+24)
    assert_eq!(j["value_range"][0].as_f64().unwrap(), 0.0);
    assert_eq!(j["value_range"][1].as_f64().unwrap(), 480.0);
    assert_eq!(j["max_abs_error"].as_f64().unwrap(), 0.0);
}

/// A signed 16-bit grid (CT Hounsfield units, air at -1024): prepared voxel-exact without loss,
/// with the signed value range, and `verify --input` checks every voxel against the store.
#[test]
fn raw_i16_ct_grid_is_exact() {
    let d = tmp();
    let dims = [9usize, 8, 7];
    let mut b = Vec::new();
    let mut v = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                // air outside a ball of "tissue", a bright "bone" core and noise
                let r2 = [i as f64 - 4.0, j as f64 - 3.5, k as f64 - 3.0]
                    .iter()
                    .map(|x| x * x)
                    .sum::<f64>();
                let noise = ((i * 7 + j * 13 + k * 29) % 11) as i16 - 5;
                let hu: i16 = if r2 > 9.0 {
                    -1024
                } else if r2 > 2.0 {
                    40 + noise
                } else {
                    1200 + noise
                };
                v.push(hu);
                b.extend_from_slice(&hu.to_le_bytes());
            }
        }
    }
    let p = write_raw(d.path(), "ct.raw", &b);
    let o = d.path().join("o");
    let grid = ["--dims", "9,8,7", "--dtype", "i16"];
    let j = prepare_json(&then(
        &then(&["prepare", s(&p)], &grid),
        &["--out", s(&o), "--json"],
    ));
    let (lo, hi) = (*v.iter().min().unwrap(), *v.iter().max().unwrap());
    assert_eq!(lo, -1024);
    assert_eq!(j["value_range"][0].as_f64().unwrap(), lo as f64);
    assert_eq!(j["value_range"][1].as_f64().unwrap(), hi as f64);
    assert_eq!(j["max_abs_error"].as_f64().unwrap(), 0.0);
    let r = run(&then(
        &then(&["verify", s(&o), "--input", s(&p)], &grid),
        &["--json"],
    ));
    assert!(r.ok, "verify --input: {}", r.stderr);
    // a grid of another type is refused with the types that exist
    expect_error(
        &[
            "prepare",
            s(&p),
            "--dims",
            "9,8,7",
            "--dtype",
            "i12",
            "--out",
            s(&o),
        ],
        &["i12", "i16"],
    );
}

#[test]
fn nan_in_raw_is_refused_or_replaced() {
    let d = tmp();
    let mut b = Vec::new();
    for i in 0..27 {
        let v: f32 = if i == 13 { f32::NAN } else { i as f32 };
        b.extend_from_slice(&v.to_le_bytes());
    }
    let p = write_raw(d.path(), "nan.raw", &b);
    let raw = ["prepare", s(&p), "--dims", "3,3,3", "--dtype", "f32"];
    let (o, o2, o3) = (d.path().join("o"), d.path().join("o2"), d.path().join("o3"));
    expect_error(&then(&raw, &["--out", s(&o)]), &["NaN", "--nan-as"]);
    let j = prepare_json(&then(
        &raw,
        &["--nan-as", "0", "--levels", "2", "--out", s(&o2), "--json"],
    ));
    assert!(j["max_abs_error"].as_f64().unwrap() <= j["max_error_bound"].as_f64().unwrap());
    // a negative replacement needs no `=`
    let j = prepare_json(&then(
        &raw,
        &["--nan-as", "-5", "--levels", "2", "--out", s(&o2), "--json"],
    ));
    assert_eq!(j["value_range"][0].as_f64(), Some(-5.0));
    // a replacement that is itself no finite f32 is refused up front, naming the option
    for bad in ["1e39", "inf", "NaN"] {
        expect_error(
            &then(&raw, &["--nan-as", bad, "--out", s(&o3)]),
            &["--nan-as", "finite"],
        );
    }
}

/// The arguments `head` then `tail`.
fn then<'a>(head: &[&'a str], tail: &[&'a str]) -> Vec<&'a str> {
    head.iter().chain(tail).copied().collect()
}

/// Options that only a mesh file has are refused for a grid instead of being ignored, and a
/// bound in percent of a constant field's range (0) says so.
#[test]
fn grid_inputs_refuse_mesh_options_and_a_percent_of_no_range() {
    let d = tmp();
    let p = write_raw(d.path(), "c.raw", &[9u8; 27]);
    let grid = ["prepare", s(&p), "--dims", "3,3,3", "--levels", "2"];
    for (flag, value) in [
        ("--scalar", "u"),
        ("--field", "distance"),
        ("--format", "vtu"),
    ] {
        let out = d.path().join("o");
        expect_error(
            &then(&grid, &[flag, value, "--out", s(&out)]),
            &[flag, "mesh files"],
        );
        let synthetic = ["prepare", "synthetic:linear", flag, value, "--out", s(&out)];
        expect_error(&synthetic, &[flag, "mesh files"]);
    }
    let out = d.path().join("c");
    expect_error(
        &then(&grid, &["--max-error", "0.1%", "--out", s(&out)]),
        &["0.1%", "constant", "absolute bound"],
    );
    // an absolute bound on the same constant grid is fine
    let j = prepare_json(&then(
        &grid,
        &["--max-error", "0.5", "--out", s(&out), "--json"],
    ));
    assert_eq!(j["max_abs_error"].as_f64(), Some(0.0));
}

/// A mesh that the coarse lattice misses entirely (an octahedron: no corner of its bounding box
/// is inside it) asks for more levels, and is prepared with them.
#[test]
fn a_lattice_too_coarse_for_the_mesh_asks_for_more_levels() {
    let d = tmp();
    let mut pts = vec![[0.0; 3]];
    for axis in 0..3 {
        for sign in [1.0, -1.0] {
            let mut p = [0.0; 3];
            p[axis] = sign;
            pts.push(p);
        }
    }
    // one tet per octant: the centre and the three half-axes bounding it
    let mut tets = Vec::new();
    for o in 0..8u32 {
        let [x, y, z] = [1 + (o & 1), 3 + (o >> 1 & 1), 5 + (o >> 2 & 1)];
        tets.push((10u8, vec![0, x, y, z]));
    }
    let p = write_vtk(
        d.path(),
        "octahedron.vtk",
        &pts,
        &tets,
        &[("f", pts.iter().map(lin).collect())],
    );
    expect_error(
        &[
            "prepare",
            s(&p),
            "--levels",
            "0",
            "--out",
            s(&d.path().join("o")),
        ],
        &["0 levels", "raise --levels"],
    );
    let o2 = d.path().join("o2");
    let j = prepare_json(&["prepare", s(&p), "--levels", "2", "--out", s(&o2), "--json"]);
    // `verify --input` samples the mesh again on the store's base mesh: the vertices inside it
    // (the others are outside, with no sample to compare) are within the bound
    let r = run(&["verify", s(&o2), "--input", s(&p), "--json"]);
    assert!(r.ok, "{}", r.stderr);
    let v: Value = serde_json::from_str(r.stdout.trim()).unwrap();
    let inside = j["vertices"].as_u64().unwrap() - j["outside_vertices"].as_u64().unwrap();
    assert_eq!(v["input"]["points"].as_u64(), Some(inside));
    assert!(
        v["input"]["max_abs_error"].as_f64().unwrap() <= j["max_error_bound"].as_f64().unwrap()
    );
    assert_eq!(v["input"]["input_range"], j["source_value_range"]);
    // the axes predictor needs data at every vertex: refused on this mesh, and `auto` takes the
    // parent predictor instead
    let o3 = d.path().join("o3");
    let box6 = [
        "prepare",
        s(&p),
        "--base",
        "box6",
        "--levels",
        "2",
        "--out",
        s(&o3),
    ];
    expect_error(
        &then(&box6, &["--predictor", "axes"]),
        &["--predictor axes", "outside", "parent"],
    );
    let j = prepare_json(&then(&box6, &["--json"]));
    assert_eq!(j["predictor"], "parent");
}

/// A `--max-error` of half the value range or more is kept, with a warning that it asks for
/// almost nothing.
#[test]
fn a_bound_of_the_whole_range_warns() {
    let d = tmp();
    for (bound, warns) in [("200%", true), ("1%", false)] {
        let out = d.path().join(bound);
        let head = ["prepare", "synthetic:harmonic", "--levels", "2"];
        let r = run(&then(&head, &["--max-error", bound, "--out", s(&out)]));
        assert!(r.ok, "{}", r.stderr);
        assert_eq!(
            r.stderr.contains("half the value range"),
            warns,
            "{}",
            r.stderr
        );
    }
}

/// `--bits` on a field so small that its step would leave f32's normal range says that it keeps
/// fewer bits than asked.
#[test]
fn bits_on_a_tiny_field_warn() {
    let d = tmp();
    let tiny: Vec<u8> = (0..27u32)
        .flat_map(|i| ((i % 7) as f32 * 1e-35).to_le_bytes())
        .collect();
    let raw = write_raw(d.path(), "tiny.raw", &tiny);
    let head = [
        "prepare",
        s(&raw),
        "--dims",
        "3,3,3",
        "--dtype",
        "f32",
        "--levels",
        "2",
    ];
    for (bits, warns) in [("24", true), ("8", false)] {
        let out = d.path().join(bits);
        let r = run(&then(&head, &["--bits", bits, "--out", s(&out)]));
        assert!(r.ok, "{}", r.stderr);
        assert_eq!(r.stderr.contains("coarser than"), warns, "{}", r.stderr);
    }
}

/// `--predictor`: `auto` takes the axes predictor on a box6 grid, `parent` on the default box5;
/// `axes` without box6 is refused; both predictors' stores verify.
#[test]
fn predictor_choice() {
    let d = tmp();
    let out = |name: &str| d.path().join(name).to_str().unwrap().to_string();
    let (a, b, c) = (out("a"), out("b"), out("c"));
    let grid = [
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "3",
        "--max-error",
        "0.1%",
    ];
    let j = prepare_json(&then(&grid, &["--base", "box6", "--out", &a, "--json"]));
    assert_eq!(j["predictor"], "axes");
    let j = prepare_json(&then(&grid, &["--out", &b, "--json"]));
    assert_eq!(j["predictor"], "parent");
    let j = prepare_json(&then(
        &grid,
        &[
            "--base",
            "box6",
            "--predictor",
            "parent",
            "--out",
            &c,
            "--json",
        ],
    ));
    assert_eq!(j["predictor"], "parent");
    for store in [&a, &b, &c] {
        let r = run(&["verify", store]);
        assert!(r.ok, "verify {store}: {}", r.stderr);
    }
    // a bound with the axes predictor takes finer steps on the coarse levels; the parent
    // predictor and a chosen code width keep one step
    let levels = |store: &str| {
        let m: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(std::path::Path::new(store).join("manifest.json")).unwrap(),
        )
        .unwrap();
        let l = &m["encoding"]["quantized"]["levels"];
        (l["ratio"].as_f64().unwrap(), l["cap"].as_f64().unwrap())
    };
    assert_eq!(levels(&a), (1.25, 2.0));
    assert_eq!(levels(&b), (1.0, 1.0));
    assert_eq!(levels(&c), (1.0, 1.0));
    let e = out("e");
    let bits = [
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "3",
        "--bits",
        "12",
    ];
    prepare_json(&then(&bits, &["--base", "box6", "--out", &e, "--json"]));
    assert_eq!(levels(&e), (1.0, 1.0));
    // one and two levels: every level's step agrees between analysis and the block coder
    for l in ["1", "2"] {
        let s = out(&format!("levels{l}"));
        let j = prepare_json(&[
            "prepare",
            "synthetic:harmonic",
            "--levels",
            l,
            "--base",
            "box6",
            "--max-error",
            "0.1%",
            "--out",
            &s,
            "--json",
        ]);
        assert_eq!(j["predictor"], "axes");
        assert_eq!(levels(&s), (1.25, 2.0));
        let r = run(&["verify", &s]);
        assert!(r.ok, "verify {s}: {}", r.stderr);
    }
    expect_error(
        &then(&grid, &["--predictor", "axes", "--out", &out("d")]),
        &["--predictor axes needs one box of 6 Kuhn tets"],
    );
    // samples whose cubic predictions would overflow f32 (5e36 at most: the parent's sums of 6
    // values stay finite, the cubic's 18 do not): auto takes the parent predictor, and axes is
    // refused rather than writing infinite details; beyond 1e37 both are, before writing
    let grid = |name: &str, top: f32| {
        let v: Vec<u8> = (0..729u32)
            .flat_map(|i| ((i % 5) as f32 * 0.25 * top).to_le_bytes())
            .collect();
        write_raw(d.path(), name, &v)
    };
    let raw = grid("huge.raw", 5e36);
    let head = [
        "prepare",
        s(&raw),
        "--dims",
        "9,9,9",
        "--dtype",
        "f32",
        "--base",
        "box6",
        "--levels",
        "3",
    ];
    let j = prepare_json(&then(&head, &["--out", &out("e"), "--json"]));
    assert_eq!(j["predictor"], "parent");
    expect_error(
        &then(&head, &["--predictor", "axes", "--out", &out("f")]),
        &["overflow", "--predictor parent"],
    );
    let raw = grid("huger.raw", 3e38);
    let mut head = head;
    head[1] = s(&raw);
    expect_error(
        &then(&head, &["--out", &out("g")]),
        &["3.00e38", "overflow", "rescale"],
    );
}

#[test]
fn nan_in_mesh_scalar_is_refused_or_replaced() {
    let d = tmp();
    let pts = cube_points();
    let mut v: Vec<f64> = pts.iter().map(lin).collect();
    v[3] = f64::NAN;
    let p = write_vtk(d.path(), "nan.vtk", &pts, &cube_tets(), &[("f", v)]);
    expect_error(
        &[
            "prepare",
            s(&p),
            "--levels",
            "2",
            "--out",
            s(&d.path().join("o")),
        ],
        &["nan.vtk", "NaN", "--nan-as"],
    );
    let j = prepare_json(&[
        "prepare",
        s(&p),
        "--levels",
        "2",
        "--nan-as",
        "1.5",
        "--out",
        s(&d.path().join("o2")),
        "--json",
    ]);
    assert_eq!(j["import"]["non_finite_replaced"], 1);
}

#[test]
fn mesh_without_tets() {
    let d = tmp();
    let pts = cube_points();
    let tris = vec![(5u8, vec![0, 1, 2]), (5u8, vec![1, 2, 3])];
    let p = write_vtk(
        d.path(),
        "tris.vtk",
        &pts,
        &tris,
        &[("f", pts.iter().map(lin).collect())],
    );
    expect_error(
        &["prepare", s(&p), "--out", s(&d.path().join("o"))],
        &["tris.vtk", "no tetrahedra"],
    );
}

#[test]
fn unknown_scalar_name_lists_available() {
    let d = tmp();
    let pts = cube_points();
    let p = write_vtk(
        d.path(),
        "two.vtk",
        &pts,
        &cube_tets(),
        &[
            ("temperature", pts.iter().map(lin).collect()),
            ("pressure", vec![1.0; 8]),
        ],
    );
    expect_error(
        &[
            "prepare",
            s(&p),
            "--scalar",
            "density",
            "--out",
            s(&d.path().join("o")),
        ],
        &["density", "temperature", "pressure"],
    );
    let j = prepare_json(&[
        "prepare",
        s(&p),
        "--scalar",
        "pressure",
        "--levels",
        "2",
        "--out",
        s(&d.path().join("o2")),
        "--json",
    ]);
    assert_eq!(j["import"]["scalar"], "pressure");
    assert_eq!(j["value_range"][0].as_f64().unwrap(), 1.0);
}

#[test]
fn zero_volume_and_inverted_tets_are_fixed_and_counted() {
    let d = tmp();
    let mut pts = cube_points();
    pts.push([0.5, 0.5, 0.0]); // 8: on the bottom face, for a flat tet
    let mut cells = cube_tets();
    // invert two tets
    cells[1].1.swap(2, 3);
    cells[4].1.swap(0, 1);
    // a zero-volume tet: four coplanar points of the bottom face
    cells.push((10, vec![0, 1, 2, 8]));
    let v: Vec<f64> = pts.iter().map(lin).collect();
    let p = write_vtk(d.path(), "bad.vtk", &pts, &cells, &[("f", v)]);
    let j = prepare_json(&[
        "prepare",
        s(&p),
        "--levels",
        "3",
        "--out",
        s(&d.path().join("o")),
        "--json",
    ]);
    assert_eq!(j["import"]["tets_read"], 7);
    assert_eq!(j["import"]["tets_kept"], 6);
    assert_eq!(j["import"]["tets_reoriented"], 2);
    assert_eq!(j["import"]["tets_dropped_degenerate"], 1);
    // the fixed mesh covers the cube: nothing outside, the linear field exact
    assert_eq!(j["outside_vertices"], 0);
    assert_eq!(j["value_range"][0].as_f64().unwrap(), 0.0);
    assert_eq!(j["value_range"][1].as_f64().unwrap(), 6.0);
}

#[test]
fn bad_options_are_refused() {
    let d = tmp();
    expect_error(
        &["prepare", "synthetic:nope", "--out", s(&d.path().join("o"))],
        &["nope"],
    );
    expect_error(
        &[
            "prepare",
            "synthetic:harmonic",
            "--bits",
            "30",
            "--out",
            s(&d.path().join("o")),
        ],
        &["--bits"],
    );
    expect_error(
        &[
            "prepare",
            "synthetic:harmonic",
            "--levels",
            "40",
            "--out",
            s(&d.path().join("o")),
        ],
        &["levels"],
    );
    // beyond this machine's memory (4097³ vertices): the message says what it needs and how to
    // ask for less
    expect_error(
        &[
            "prepare",
            "synthetic:harmonic",
            "--levels",
            "12",
            "--out",
            s(&d.path().join("o")),
        ],
        &["at 12 levels", "GiB", "fewer --levels"],
    );
    expect_error(&["verify", s(&d.path().join("absent"))], &["manifest.json"]);
    // an empty token (an unset variable in `--token "$T"`) would serve without authentication
    expect_error(
        &["serve", s(&d.path().join("absent")), "--token", ""],
        &["--token is empty"],
    );
}

/// `--preview E`: a second analysis of the coarse levels within `E`, written as `preview.bin` and
/// described in the manifest (every node level but the finest); `verify` still checks the
/// store's own bound. Without enough levels, or with a bad bound, an error says why.
#[test]
fn a_preview_is_written_beside_the_store() {
    let d = tmp();
    let out = d.path().join("p");
    let j = prepare_json(&[
        "prepare",
        "synthetic:harmonic",
        "--levels",
        "3",
        "--base",
        "box6",
        "--max-error",
        "0.1%",
        "--preview",
        "10%",
        "--out",
        s(&out),
        "--json",
    ]);
    let bytes = j["preview_bytes"].as_u64().unwrap();
    assert!(bytes > 0 && bytes < j["bytes"].as_u64().unwrap(), "{j}");
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["preview"]["levels"], 2, "{m}");
    assert_eq!(m["files"]["preview.bin"]["bytes"].as_u64(), Some(bytes));
    let bound = m["preview"]["max_error_bound"].as_f64().unwrap();
    let range = j["value_range"][1].as_f64().unwrap() - j["value_range"][0].as_f64().unwrap();
    assert!(
        bound > 0.09 * range && bound < 0.11 * range,
        "{bound} of {range}"
    );
    let r = run(&["verify", s(&out)]);
    assert!(r.ok, "{}", r.stderr);

    let one = d.path().join("one");
    expect_error(
        &[
            "prepare",
            "synthetic:harmonic",
            "--levels",
            "1",
            "--preview",
            "10%",
            "--out",
            s(&one),
        ],
        &["--preview", "2 levels"],
    );
    expect_error(
        &[
            "prepare",
            "synthetic:harmonic",
            "--preview",
            "0%",
            "--out",
            s(&one),
        ],
        &["--preview"],
    );
    // a preview no coarser than the store is refused, and no store is written
    let fine = d.path().join("fine");
    expect_error(
        &[
            "prepare",
            "synthetic:harmonic",
            "--levels",
            "3",
            "--max-error",
            "1%",
            "--preview",
            "0.5%",
            "--out",
            s(&fine),
        ],
        &["--preview", "no coarser"],
    );
    assert!(!fine.join("manifest.json").exists());
}

/// Without --levels, a mesh gets the fewest levels whose leaves are on average no larger than its
/// tets: 1 for a cube of 6 tets, 4 for one of 12³ Kuhn cells (10,368 tets: box5 at 4 levels has
/// 20,480 leaves, at 3 levels 2,560), and fewer when --memory cannot hold them, with a warning.
#[test]
fn a_meshs_default_levels_follow_its_resolution() {
    let d = tmp();
    let mesh = |name: &str, n: usize| {
        let (pts, tets) = tetwave_protocol::shapes::kuhn_boxes([0.0; 3], [1.0; 3], [n; 3]);
        let cells: Vec<(u8, Vec<u32>)> = tets.iter().map(|t| (10, t.to_vec())).collect();
        write_vtk(
            d.path(),
            name,
            &pts,
            &cells,
            &[("f", pts.iter().map(lin).collect())],
        )
    };
    let levels_of = |p: &Path, extra: &[&str]| {
        let out = d.path().join(format!(
            "{}-{}",
            p.file_name().unwrap().to_string_lossy(),
            extra.len()
        ));
        let j = prepare_json(&then(&["prepare", s(p), "--out", s(&out), "--json"], extra));
        j["levels"].as_u64().unwrap()
    };
    let coarse = mesh("coarse.vtk", 1);
    assert_eq!(levels_of(&coarse, &[]), 1);
    let fine = mesh("fine.vtk", 12);
    assert_eq!(levels_of(&fine, &[]), 4);
    // box5 at 3 levels has 9³ vertices (729 × 40 bytes), at 4 levels 17³ (4,913 × 40)
    let r = run(&then(
        &["prepare", s(&fine), "--memory", "100K", "--json"],
        &["--out", s(&d.path().join("capped"))],
    ));
    assert!(r.ok, "{}", r.stderr);
    let j: Value = serde_json::from_str(r.stdout.trim()).unwrap();
    assert_eq!(j["levels"], 3);
    assert!(r.stderr.contains("--memory"), "{}", r.stderr);
    expect_error(
        &[
            "prepare",
            s(&fine),
            "--memory",
            "lots",
            "--out",
            s(&d.path().join("x")),
        ],
        &["--memory", "4G"],
    );
}

/// A hierarchy larger than this machine's memory is refused at once with what it needs and what
/// there is, never by the system stopping the process: a 2049³ u8 grid (a sparse file: nothing is
/// read; about 320 GiB in memory, and even its smallest part over `--memory 1G`) and
/// synthetic:harmonic at 12 levels of box6 (4097³ vertices).
/// Past 2^29 nodes the node count itself is no limit (the analysis' owner codes widen to 64 bits).
#[test]
fn a_hierarchy_beyond_memory_is_refused_before_it_is_read() {
    let d = tmp();
    let raw = d.path().join("ct.raw");
    let f = std::fs::File::create(&raw).unwrap();
    f.set_len(2049 * 2049 * 2049).unwrap();
    let out = d.path().join("o");
    let t = std::time::Instant::now();
    let r = run(&[
        "prepare",
        s(&raw),
        "--dims",
        "2049,2049,2049",
        "--memory",
        "1G",
        "--out",
        s(&out),
    ]);
    assert!(!r.ok);
    // 2049³ voxels at 40 bytes do not fit --memory: prepared by parts, the smallest part at the
    // coarsest base a client accepts (one row of 16³ boxes, 7 levels: 2049 × 129 × 129 vertices)
    // needs about 1.3 GiB
    assert!(
        r.stderr.contains("smallest part") && r.stderr.contains("give --memory 1"),
        "{}",
        r.stderr
    );
    assert!(
        !r.stderr.contains("more voxels than a hierarchy can index"),
        "{}",
        r.stderr
    );
    assert!(
        t.elapsed().as_secs() < 30,
        "refused without reading the grid"
    );
    assert!(!out.join("manifest.json").exists());
    let r = run(&[
        "prepare",
        "synthetic:harmonic",
        "--base",
        "box6",
        "--levels",
        "12",
        "--out",
        s(&out),
    ]);
    assert!(!r.ok);
    assert!(
        r.stderr.contains("68769820673 vertices at 12 levels"),
        "{}",
        r.stderr
    );
}
