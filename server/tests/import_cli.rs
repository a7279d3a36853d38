//! `tetwave-server prepare` on real-world mesh files (issue 7): what `--json` reports about the
//! import, `--scalar` on cell and vector arrays, `--field distance`, `--format`, and broken files
//! refused with one line naming the file, the section and the reason.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn fixture(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
        .display()
        .to_string()
}

fn run(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_tetwave-server"))
        .args(args)
        .output()
        .expect("runs");
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "panic: {stderr}");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr,
    )
}

fn out_dir(d: &tempfile::TempDir, name: &str) -> String {
    let p: PathBuf = d.path().join(name);
    p.display().to_string()
}

fn prepare(input: &str, extra: &[&str]) -> Value {
    let d = tempfile::tempdir().unwrap();
    let out = out_dir(&d, "o");
    let mut args = vec!["prepare", input, "--levels", "2", "--json", "--out", &out];
    args.extend_from_slice(extra);
    let (ok, stdout, stderr) = run(&args);
    assert!(ok, "prepare {input} failed: {stderr}");
    serde_json::from_str(stdout.trim()).expect("one JSON object")
}

fn expect_error(input: &str, extra: &[&str], needles: &[&str]) {
    let d = tempfile::tempdir().unwrap();
    let out = out_dir(&d, "o");
    let mut args = vec!["prepare", input, "--levels", "2", "--out", &out];
    args.extend_from_slice(extra);
    let (ok, _, stderr) = run(&args);
    assert!(!ok, "should fail: {args:?}");
    let lines: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error")).collect();
    assert_eq!(lines.len(), 1, "one error line expected: {stderr}");
    for n in needles {
        assert!(lines[0].contains(n), "{:?} lacks {n:?}", lines[0]);
    }
}

#[test]
fn json_reports_split_cells() {
    for name in ["volcells.vtu", "volcells_51.vtk", "volcells_22.msh"] {
        let j = prepare(&fixture(name), &[]);
        let i = &j["import"];
        let points = tetwave_import::read_mesh(Path::new(&fixture(name)), None)
            .unwrap()
            .mesh
            .points
            .len();
        assert!(points >= 8, "{name}: {points} points");
        assert_eq!(i["points_read"], points, "{name}");
        assert_eq!(i["cells_read"], 5, "{name}");
        assert_eq!(i["tets_read"], 17, "{name}");
        assert_eq!(i["tets_kept"], 17, "{name}");
        assert_eq!(i["tets_reoriented"], 0, "{name}");
        assert_eq!(i["tets_dropped"], 0, "{name}");
        assert_eq!(i["cells_ignored"], 1, "{name}");
        assert_eq!(i["cells_split"], 4, "{name}");
        assert_eq!(i["scalar"], "height", "{name}");
        assert_eq!(i["scalar_source"], "point", "{name}");
        assert_eq!(i["slivers"], 0, "{name}");
        // height = z on a domain from z = 0 to 1.5
        assert_eq!(j["value_range"][0].as_f64(), Some(0.0));
        assert_eq!(j["value_range"][1].as_f64(), Some(1.5));
    }
}

#[test]
fn json_reports_cell_scalar_and_quadratic_tets() {
    let j = prepare(&fixture("volcells.vtu"), &["--scalar", "density"]);
    assert_eq!(j["import"]["scalar"], "density");
    assert_eq!(j["import"]["scalar_source"], "cell");
    let lo = j["value_range"][0].as_f64().unwrap();
    let hi = j["value_range"][1].as_f64().unwrap();
    // (0,0,0) is in hex A only (density 1), (2,0,0) in hex B only (2): both are corners of
    // the bounding box, hence lattice vertices; no point value is above the pyramid's 4.
    assert_eq!(lo, 1.0);
    assert!((2.0..=4.0).contains(&hi), "{hi}");

    let j = prepare(&fixture("quadratic_22.msh"), &[]);
    assert_eq!(j["import"]["cells_read"], 7);
    assert_eq!(j["import"]["tets_kept"], 7);
    assert_eq!(j["import"]["tets_reoriented"], 3);
    assert_eq!(j["import"]["cells_split"], 0);
    assert!(j["import"]["notes"]
        .as_array()
        .unwrap()
        .iter()
        .any(|n| n.as_str().unwrap().contains("7 higher-order tets")));
}

#[test]
fn vector_component_from_the_cli() {
    // velocity = (x, y, z): component 0 ranges over x in [0.1, 0.8].
    let j = prepare(&fixture("cube_binary.vtu"), &["--scalar", "velocity:0"]);
    assert_eq!(j["import"]["scalar"], "velocity:0");
    assert!((j["value_range"][0].as_f64().unwrap() - 0.1).abs() < 1e-6);
    assert!((j["value_range"][1].as_f64().unwrap() - 0.8).abs() < 1e-6);
    expect_error(
        &fixture("cube_binary.vtu"),
        &["--scalar", "velocity:7"],
        &["velocity", "3 components", "velocity:mag"],
    );
}

#[test]
fn bare_mesh_gets_the_distance_field() {
    // no flag needed: a geometry-only mesh prepares with the distance field, and says so
    let j = prepare(&fixture("bare_42.vtk"), &[]);
    assert_eq!(j["import"]["scalar"], "distance");
    assert_eq!(j["import"]["scalar_source"], "geometric");
    assert!(j["import"]["notes"]
        .as_array()
        .unwrap()
        .iter()
        .any(|n| n.as_str().unwrap().contains("no point or cell arrays")));
    let j = prepare(&fixture("cube_10.msh"), &["--field", "distance"]);
    assert_eq!(j["import"]["scalar"], "distance");
    assert_eq!(j["import"]["scalar_source"], "geometric");
    assert_eq!(j["import"]["cells_ignored"], 1);
    assert_eq!(j["value_range"][0].as_f64(), Some(0.0));
    expect_error(
        &fixture("cube_10.msh"),
        &["--field", "distance", "--scalar", "x"],
        &["exclude"],
    );
}

#[test]
fn format_flag_overrides_detection() {
    let d = tempfile::tempdir().unwrap();
    let renamed = d.path().join("cube.data");
    std::fs::copy(fixture("cube.mesh"), &renamed).unwrap();
    let j = prepare(renamed.to_str().unwrap(), &["--format", "mesh"]);
    assert_eq!(j["import"]["tets_kept"], 7);
    assert_eq!(j["import"]["scalar"], "ref");
    assert_eq!(j["import"]["scalar_source"], "cell");
    expect_error(
        &fixture("cube_binary.vtu"),
        &["--format", "msh"],
        &["cube_binary.vtu", "not a gmsh file"],
    );
    let (ok, _, stderr) = run(&[
        "prepare",
        &fixture("cube_binary.vtu"),
        "--format",
        "stl",
        "--out",
        &out_dir(&d, "o"),
    ]);
    assert!(!ok && stderr.contains("stl"), "{stderr}");
}

#[test]
fn broken_files_exit_non_zero_with_one_line() {
    for (name, needles) in [
        (
            "wrong_type.vtu",
            &[
                "wrong_type.vtu",
                "Piece 0 Cells",
                "connectivity has 56 values",
            ][..],
        ),
        ("wrong_type.vtk", &["wrong_type.vtk", "binary data"][..]),
        (
            "corrupt_zlib.vtu",
            &["corrupt_zlib.vtu", "zlib block 0 of 4 is corrupt"][..],
        ),
        (
            "surface_only.msh",
            &["surface_only.msh", "surface-only"][..],
        ),
        (
            "bad_cell_data_count.vtk",
            &["CELL_DATA 5 but the file has 7 cells"][..],
        ),
        ("bad_node_count_10.msh", &["$ELM", "announces 4 nodes"][..]),
        ("truncated_binary.msh", &["truncated"][..]),
        ("node_out_of_range.vtu", &["refers to point 99"][..]),
    ] {
        expect_error(&fixture(name), &[], needles);
    }
}

/// Every array constant (a Medit `ref` of zeros): the store is written with a warning on stderr
/// and in the summary that names the arrays; `--json` lists them.
#[test]
fn all_constant_arrays_warn() {
    let d = tempfile::tempdir().unwrap();
    let input = d.path().join("zeros.mesh");
    std::fs::write(
        &input,
        "MeshVersionFormatted 2\nDimension 3\nVertices\n5\n0 0 0 0\n1 0 0 0\n0 1 0 0\n0 0 1 0\n1 1 1 0\n\
         Tetrahedra\n2\n1 2 3 4 0\n2 3 4 5 0\nEnd\n",
    )
    .unwrap();
    let input = input.to_str().unwrap();
    let out = out_dir(&d, "o");
    let (ok, stdout, stderr) = run(&["prepare", input, "--levels", "1", "--out", &out]);
    assert!(ok, "{stderr}");
    assert!(
        stderr.contains("every array of the mesh is constant")
            && stderr.contains("ref (cell, constant)"),
        "{stderr}"
    );
    assert!(
        stdout.contains("warning: every array is constant (ref (cell, constant))"),
        "{stdout}"
    );
    let j = prepare(input, &[]);
    assert_eq!(j["import"]["scalar"], "ref");
    assert_eq!(j["import"]["arrays"][0]["name"], "ref");
    assert_eq!(j["import"]["arrays"][0]["source"], "cell");
    assert_eq!(j["import"]["arrays"][0]["constant"], true);
}

/// A gmsh 2.2 mesh with two physical groups: `prepare --json` lists `gmsh:physical` and
/// `gmsh:geometrical`, and `--scalar gmsh:physical` gives the groups' numbers (1 and 2).
#[test]
fn gmsh_physical_groups_are_arrays() {
    let d = tempfile::tempdir().unwrap();
    let input = d.path().join("two.msh");
    std::fs::write(
        &input,
        "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n5\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 1 1 1\n$EndNodes\n\
         $Elements\n3\n1 2 2 3 30 2 3 4\n2 4 2 1 10 1 2 3 4\n3 4 2 2 20 2 3 4 5\n$EndElements\n",
    )
    .unwrap();
    let input = input.to_str().unwrap();
    let j = prepare(input, &["--scalar", "gmsh:physical"]);
    assert_eq!(j["import"]["scalar"], "gmsh:physical");
    assert_eq!(j["import"]["scalar_source"], "cell");
    let names: Vec<&str> = j["import"]["arrays"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["gmsh:physical", "gmsh:geometrical"]);
    let (lo, hi) = (
        j["value_range"][0].as_f64().unwrap(),
        j["value_range"][1].as_f64().unwrap(),
    );
    assert!(
        (lo - 1.0).abs() < 1e-3 && (hi - 2.0).abs() < 1e-3,
        "{lo} {hi}"
    );
    let j = prepare(input, &["--scalar", "gmsh:geometrical"]);
    assert_eq!(j["import"]["scalar"], "gmsh:geometrical");
}
