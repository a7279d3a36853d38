//! Mesh readers against the fixtures written by `scripts/gen-fixtures.py` (meshio, plus
//! hand-written variants): every variant of the same small mesh reads back to the same points,
//! tets and point arrays; mixed cells are counted; broken files fail with a telling error and
//! never panic.

use std::path::{Path, PathBuf};
use tetwave_protocol::shapes::kuhn_grid;

mod fixture_mesh;
use fixture_mesh::{cube_points, fixture, temperature, tets, Corruptor};

use tetwave_import::{
    format_of_content, parse_tet_mesh, read_tet_mesh, read_tet_mesh_as, ImportError, MeshFormat,
    TetMesh,
};

fn read(name: &str) -> TetMesh {
    match read_tet_mesh(&fixture(name)) {
        Ok(m) => m,
        Err(e) => panic!("{name}: {e}"),
    }
}

fn pressure(p: [f64; 3]) -> f64 {
    101.325 * (1.0 + p[0] - p[2])
}

/// How close read values must be to the f64 originals.
#[derive(Debug, Clone, Copy)]
enum Tol {
    /// Binary f64 or shortest-round-trip ascii.
    Exact,
    /// Relative: f32 data (1e-6), meshio's 12-digit .vtu ascii (1e-11).
    Rel(f64),
}

fn close(a: f64, b: f64, tol: Tol) -> bool {
    match tol {
        Tol::Exact => a.to_bits() == b.to_bits(),
        Tol::Rel(r) => (a - b).abs() <= r * b.abs().max(1e-30),
    }
}

fn array<'m>(mesh: &'m TetMesh, name: &str) -> Option<&'m [f64]> {
    mesh.point_data
        .iter()
        .find(|a| a.name == name)
        .map(|a| a.values.as_slice())
}

/// The mesh has the cube's points, tets and both fields (and nothing else as point data).
fn assert_cube(name: &str, mesh: &TetMesh, tol: Tol, ignored: usize) {
    let pts = cube_points();
    assert_eq!(mesh.points.len(), pts.len(), "{name}: point count");
    for (i, (a, b)) in mesh.points.iter().zip(&pts).enumerate() {
        for k in 0..3 {
            assert!(
                close(a[k], b[k], tol),
                "{name}: point {i} is {a:?}, expected {b:?}"
            );
        }
    }
    assert_eq!(mesh.tets, tets(), "{name}: tets");
    assert_eq!(mesh.cells_ignored, ignored, "{name}: cells_ignored");
    let mut names: Vec<&str> = mesh.point_data.iter().map(|a| a.name.as_str()).collect();
    names.sort_unstable();
    assert_eq!(
        names,
        ["pressure", "temperature"],
        "{name}: point arrays (velocity has 3 components)"
    );
    for (field, f) in [
        ("temperature", temperature as fn([f64; 3]) -> f64),
        ("pressure", pressure),
    ] {
        let values = array(mesh, field).unwrap_or_default();
        assert_eq!(values.len(), pts.len(), "{name}: {field} length");
        for (i, (&v, &p)) in values.iter().zip(&pts).enumerate() {
            assert!(
                close(v, f(p), tol),
                "{name}: {field}[{i}] = {v}, expected {}",
                f(p)
            );
        }
    }
}

fn check_all(cases: &[(&str, Tol)]) {
    for &(name, tol) in cases {
        assert_cube(name, &read(name), tol, 0);
    }
}

#[test]
fn vtu_every_encoding_reads_the_same_mesh() {
    check_all(&[
        ("cube_ascii.vtu", Tol::Rel(1e-11)),
        ("cube_binary.vtu", Tol::Exact),
        ("cube_binary_zlib.vtu", Tol::Exact),
        ("cube_f32_i32_zlib_h64.vtu", Tol::Rel(1e-6)),
        ("cube_appended_raw.vtu", Tol::Exact),
        ("cube_appended_raw_zlib.vtu", Tol::Exact),
        ("cube_appended_raw_be_h64.vtu", Tol::Exact),
        ("cube_appended_base64.vtu", Tol::Exact),
        ("cube_appended_base64_zlib.vtu", Tol::Exact),
    ]);
}

#[test]
fn legacy_vtk_every_variant_reads_the_same_mesh() {
    check_all(&[
        ("cube_42_ascii.vtk", Tol::Exact),
        ("cube_42_binary.vtk", Tol::Exact),
        ("cube_42_f32_binary.vtk", Tol::Rel(1e-6)),
        ("cube_51_ascii.vtk", Tol::Exact),
        ("cube_51_binary.vtk", Tol::Exact),
        ("cube_51_metadata.vtk", Tol::Exact),
        ("cube_scalars_ascii.vtk", Tol::Exact),
        ("cube_scalars_binary.vtk", Tol::Rel(1e-6)),
    ]);
}

#[test]
fn legacy_binary_f64_field_is_exact_next_to_f32_scalars() {
    // cube_scalars_binary.vtk: float points and SCALARS, a double FIELD array.
    let mesh = read("cube_scalars_binary.vtk");
    let expected: Vec<f64> = cube_points().into_iter().map(pressure).collect();
    assert_eq!(array(&mesh, "pressure"), Some(expected.as_slice()));
    let t = array(&mesh, "temperature").unwrap_or_default();
    assert!(t
        .iter()
        .zip(cube_points())
        .all(|(&v, p)| v == f64::from(temperature(p) as f32)));
}

#[test]
fn msh_every_variant_reads_the_same_mesh() {
    check_all(&[
        ("cube_22_ascii.msh", Tol::Exact),
        ("cube_22_binary.msh", Tol::Exact),
        ("cube_41_ascii.msh", Tol::Exact),
        ("cube_41_binary.msh", Tol::Exact),
        ("cube_22_tags_ascii.msh", Tol::Exact),
        ("cube_22_tags_binary.msh", Tol::Exact),
    ]);
    // 4.1 with unsorted, non-contiguous tags, a parametric node block and a triangle.
    for name in ["cube_41_tags_ascii.msh", "cube_41_tags_binary.msh"] {
        let mesh = read(name);
        assert_cube(name, &mesh, Tol::Exact, 1);
        // File order of the $NodeData blocks: pressure first.
        assert_eq!(mesh.point_data[0].name, "pressure", "{name}");
    }
}

#[test]
fn mixed_cells_keep_tets_and_count_the_rest() {
    for name in [
        "mixed.vtu",
        "mixed_51.vtk",
        "mixed_42_ascii.vtk",
        "mixed_22_ascii.msh",
        "mixed_22_binary.msh",
        "mixed_41_ascii.msh",
        "mixed_41_binary.msh",
    ] {
        // 2 triangles, 3 lines and 1 vertex around the 7 tets.
        assert_cube(name, &read(name), Tol::Exact, 6);
    }
}

#[test]
fn vtu_pieces_are_concatenated_with_shifted_indices() {
    let mesh = read("two_pieces.vtu");
    let mut pts = vec![[2.0, 2.0, 2.0], [3.0, 3.0, 3.0]];
    pts.extend(cube_points());
    assert_eq!(mesh.points, pts);
    let shifted: Vec<[u32; 4]> = tets().iter().map(|t| t.map(|v| v + 2)).collect();
    assert_eq!(mesh.tets, shifted);
    assert_eq!(mesh.cells_ignored, 1, "the line of the first piece");
    let t: Vec<f64> = pts.iter().map(|&p| temperature(p)).collect();
    assert_eq!(array(&mesh, "temperature"), Some(t.as_slice()));
    assert_eq!(array(&mesh, "pressure").map(<[f64]>::len), Some(11));
}

#[test]
fn vtu_multi_block_zlib_grid() {
    // 9^3 grid points, 6 tets per cell (as kuhn_grid lists them): connectivity spans several
    // 32 KiB zlib blocks.
    let mesh = read("grid_zlib.vtu");
    let (pts, grid_tets) = kuhn_grid(8, |_, _, _| true);
    assert_eq!(mesh.points, pts);
    assert_eq!(mesh.tets.len(), 3072);
    assert_eq!(mesh.tets, grid_tets);
    let t: Vec<f64> = pts.iter().map(|&p| temperature(p)).collect();
    assert_eq!(array(&mesh, "temperature"), Some(t.as_slice()));
}

/// The error for a broken fixture: Malformed (or Io) and its text names the problem.
fn assert_fails(name: &str, needle: &str) {
    let err = match read_tet_mesh(&fixture(name)) {
        Ok(m) => panic!(
            "{name}: read a mesh of {} points from a broken file",
            m.points.len()
        ),
        Err(e) => e,
    };
    let text = err.to_string();
    let ImportError::Malformed {
        section, reason, ..
    } = err
    else {
        panic!("{name}: {text}")
    };
    assert!(
        text.contains(name),
        "{name}: the error does not name the file: {text}"
    );
    // The needle is looked for in the section and reason only, not in the file name.
    let problem = format!("{section}: {reason}");
    assert!(
        problem.contains(needle),
        "{name}: expected \"{needle}\" in: {text}"
    );
}

#[test]
fn broken_files_fail_with_a_telling_error() {
    for (name, needle) in [
        ("truncated.vtu", "truncated"),
        ("truncated_appended.vtu", "truncated"),
        ("garbage.vtu", "not a VTK XML file"),
        ("truncated_ascii.msh", "truncated"),
        ("truncated_binary.msh", "truncated"),
        ("truncated_41_binary.msh", "truncated"),
        (
            "node_out_of_range.msh",
            "refers to node 99, which $Nodes does not define",
        ),
        (
            "node_out_of_range.vtu",
            "refers to point 99, but the piece has 9 points",
        ),
        (
            "bad_point_count.vtk",
            "POINTS: expected 36 values, found 27",
        ),
        (
            "bad_cell_types.vtk",
            "CELL_TYPES: expected 9 values, found 7",
        ),
        (
            "bad_point_data_count.vtk",
            "POINT_DATA 4 but the file has 9 points",
        ),
        ("huge_count.vtk", "file is truncated: 12000000000 values"),
        ("huge_count.msh", "file is truncated: 2000000000 nodes"),
        ("empty.vtu", "empty file"),
        ("empty.vtk", "empty file"),
        ("empty.msh", "empty file"),
    ] {
        assert_fails(name, needle);
    }
}

fn temp_copy(dir: &Path, src: &str, name: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::copy(fixture(src), &path).expect("copy fixture");
    path
}

#[test]
fn format_comes_from_content_before_extension() {
    let dir = tempfile::tempdir().expect("temp dir");
    for (src, name) in [
        ("cube_binary_zlib.vtu", "no_extension"),
        ("cube_binary_zlib.vtu", "wrong.msh"),
        ("cube_51_binary.vtk", "mesh.dat"),
        ("cube_41_binary.msh", "wrong.vtu"),
        ("cube_22_ascii.msh", "MESH.VTK"),
    ] {
        let mesh = read_tet_mesh(&temp_copy(dir.path(), src, name))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_cube(name, &mesh, Tol::Exact, 0);
    }
    let bytes = std::fs::read(fixture("cube_appended_raw.vtu")).expect("fixture");
    assert_eq!(format_of_content(&bytes), Some(MeshFormat::Vtu));
    assert_eq!(
        format_of_content(b"  # vtk DataFile Version 2.0\n"),
        Some(MeshFormat::LegacyVtk)
    );
    assert_eq!(
        format_of_content(b"$MeshFormat\n2.2 0 8\n"),
        Some(MeshFormat::Msh)
    );
    assert_eq!(format_of_content(b"solid cube\n"), None);

    let garbage = temp_copy(dir.path(), "garbage.vtu", "garbage.bin");
    assert!(matches!(
        read_tet_mesh(&garbage),
        Err(ImportError::UnknownFormat { .. })
    ));
    let missing = dir.path().join("missing.vtu");
    assert!(matches!(
        read_tet_mesh(&missing),
        Err(ImportError::Io { .. })
    ));
    let forced = read_tet_mesh_as(&fixture("cube_binary.vtu"), MeshFormat::Msh);
    assert!(forced.is_err_and(|e| e.to_string().contains("not a gmsh file")));
}

const VALID: [&str; 31] = [
    "cube_ascii.vtu",
    "cube_binary.vtu",
    "cube_binary_zlib.vtu",
    "cube_f32_i32_zlib_h64.vtu",
    "cube_appended_raw.vtu",
    "cube_appended_raw_zlib.vtu",
    "cube_appended_raw_be_h64.vtu",
    "cube_appended_base64.vtu",
    "cube_appended_base64_zlib.vtu",
    "two_pieces.vtu",
    "mixed.vtu",
    "cube_42_ascii.vtk",
    "cube_42_binary.vtk",
    "cube_42_f32_binary.vtk",
    "cube_51_ascii.vtk",
    "cube_51_binary.vtk",
    "cube_51_metadata.vtk",
    "cube_scalars_ascii.vtk",
    "cube_scalars_binary.vtk",
    "mixed_51.vtk",
    "cube_22_ascii.msh",
    "cube_22_binary.msh",
    "cube_41_ascii.msh",
    "cube_41_binary.msh",
    "cube_22_tags_ascii.msh",
    "cube_22_tags_binary.msh",
    "cube_41_tags_ascii.msh",
    "cube_41_tags_binary.msh",
    "mixed_22_binary.msh",
    "mixed_41_ascii.msh",
    "mixed_41_binary.msh",
];

fn format(name: &str) -> MeshFormat {
    match Path::new(name).extension().and_then(|e| e.to_str()) {
        Some("vtu") => MeshFormat::Vtu,
        Some("vtk") => MeshFormat::LegacyVtk,
        _ => MeshFormat::Msh,
    }
}

/// What every returned mesh satisfies.
fn assert_consistent(what: &str, m: &TetMesh) {
    let n = m.points.len();
    assert!(
        m.tets.iter().flatten().all(|&v| (v as usize) < n),
        "{what}: index out of range"
    );
    assert!(
        m.point_data.iter().all(|a| a.values.len() == n),
        "{what}: array length"
    );
}

#[test]
fn every_truncation_fails_or_reads_the_whole_mesh() {
    for name in VALID {
        let bytes = std::fs::read(fixture(name)).expect("fixture");
        let fmt = format(name);
        let full = parse_tet_mesh(Path::new(name), &bytes, fmt).expect("full file");
        for len in 0..bytes.len() {
            let what = format!("{name}[..{len}]");
            match parse_tet_mesh(Path::new(name), &bytes[..len], fmt) {
                Err(ImportError::Malformed { .. }) => {}
                Err(e) => panic!("{what}: unexpected error kind {e:?}"),
                Ok(m) => {
                    assert_consistent(&what, &m);
                    // Legacy VTK has no end marker: a cut in the last section can still parse.
                    if fmt != MeshFormat::LegacyVtk {
                        assert_eq!(m.points, full.points, "{what}: partial points");
                        assert_eq!(m.tets, full.tets, "{what}: partial tets");
                        for a in &m.point_data {
                            assert!(
                                full.point_data.contains(a),
                                "{what}: partial array {}",
                                a.name
                            );
                        }
                    }
                }
            }
        }
    }
}

/// Random byte changes, deletions and duplications: an error or a consistent mesh, never a
/// panic. `MESH_IO_FUZZ_ROUNDS` (default 300 per fixture) runs more.
#[test]
fn corrupted_bytes_never_panic() {
    let rounds: usize = std::env::var("MESH_IO_FUZZ_ROUNDS")
        .ok()
        .and_then(|r| r.parse().ok())
        .unwrap_or(300);
    let mut rng = Corruptor::new(0x2545_f491_4f6c_dd1d);
    for name in VALID {
        let bytes = std::fs::read(fixture(name)).expect("fixture");
        let fmt = format(name);
        for round in 0..rounds {
            let b = rng.corrupt(&bytes, round);
            let what = format!("{name} round {round}");
            match parse_tet_mesh(Path::new(name), &b, fmt) {
                Ok(m) => assert_consistent(&what, &m),
                Err(e) => assert!(matches!(e, ImportError::Malformed { .. }), "{what}: {e:?}"),
            }
        }
    }
}

/// A device or a pipe is not read (`/dev/zero` would be read until memory runs out): the error
/// says why.
#[test]
fn devices_are_not_read() {
    for format in [None, Some(MeshFormat::LegacyVtk)] {
        let e = tetwave_import::read_mesh(Path::new("/dev/zero"), format).expect_err("refused");
        assert!(e.to_string().contains("not a regular file"), "{e}");
    }
}
