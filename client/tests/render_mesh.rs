//! `tetwave render <mesh> --compare` for every mesh format read (VTK XML `.vtu`, legacy `.vtk`,
//! gmsh `.msh`, Medit `.mesh`): the GPU image against the CPU reference, on the reader fixtures of
//! `server/tests/fixtures` (a 9-point, 7-tet non-convex cube piece). Needs a GPU adapter (lavapipe
//! in CI), like `render_gpu`.

use std::path::PathBuf;
use std::process::Command;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../server/tests/fixtures")
        .join(name)
}

fn render(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_tetwave"))
        .arg("render")
        .args(args)
        .output()
        .expect("tetwave runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn render_mesh_compare_every_format() {
    let d = tempfile::tempdir().unwrap();
    for name in [
        "cube_ascii.vtu",
        "cube_binary_zlib.vtu",
        "cube_51_ascii.vtk",
        "cube_42_binary.vtk",
        "cube_41_ascii.msh",
        "cube_22_binary.msh",
        "cube.mesh",
    ] {
        let png = d.path().join(format!("{name}.png"));
        let (ok, out, err) = render(&[
            fixture(name).to_str().unwrap(),
            "--compare",
            "--size",
            "64x64",
            "--json",
            "-o",
            png.to_str().unwrap(),
        ]);
        assert!(ok, "{name}: {err}");
        let v: serde_json::Value = serde_json::from_str(out.trim()).expect(&out);
        assert_eq!(v["input"], "mesh", "{name}");
        assert_eq!(v["tets"], 7, "{name}");
        let psnr = v["psnr_db"].as_f64().expect("compare reports a PSNR");
        eprintln!(
            "{name}: scalar {}, GPU vs reference {psnr:.2} dB",
            v["scalar"]
        );
        assert!(psnr >= 45.0, "{name}: {psnr:.2} dB");
        assert!(png.exists());
    }
}

#[test]
fn render_mesh_bad_options_fail_clearly() {
    let vtu = fixture("cube_ascii.vtu");
    let vtu = vtu.to_str().unwrap();
    let (ok, _, err) = render(&[vtu, "--levels", "2", "--reference"]);
    assert!(!ok && err.contains("--levels applies to stores"), "{err}");
    let (ok, _, err) = render(&[vtu, "--scalar", "nope", "--reference"]);
    assert!(
        !ok && err.contains("no point or cell array named \"nope\""),
        "{err}"
    );
    let (ok, _, err) = render(&["/nonexistent/x.vtu", "--reference"]);
    assert!(!ok && err.contains("/nonexistent/x.vtu"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// A mesh with no arrays renders without flags: the distance to its boundary, with one line
/// saying so (the CPU reference, so no adapter is needed for this one).
#[test]
fn render_a_geometry_only_mesh_without_flags() {
    let d = tempfile::tempdir().unwrap();
    let png = d.path().join("bare.png");
    let (ok, out, err) = render(&[
        fixture("bare_42.vtk").to_str().unwrap(),
        "--reference",
        "--size",
        "48x48",
        "--json",
        "-o",
        png.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).expect(&out);
    assert_eq!(v["scalar"], "distance", "{v}");
    let said: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("no point or cell arrays"))
        .collect();
    assert_eq!(said.len(), 1, "{err}");
    assert!(said[0].contains("distance to its boundary"), "{err}");
    assert!(png.exists());
}
