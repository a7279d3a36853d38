//! Volume files nobody here wrote (issue 45): NIfTI files from nibabel's wheel, DICOM from
//! pydicom's, and volumes written by tifffile, pynrrd, zarr-python and VTK from those voxels
//! (`scripts/volume-fixtures.py`, run here with the checkout's `.venv-volumes`, which
//! `scripts/setup` fills). Each prepares without `--dims`/`--dtype`, with the dims, spacing, origin and value
//! range the Python library reads; `verify --input FILE` passes every voxel (tetwave's reader
//! against the store), and `verify --input` of the library's own voxels passes too (the
//! library's reading against the store, so that a reader wrong in the same way on both sides
//! cannot pass). Files tetwave must refuse give one `error:` line naming the reason.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tetwave-server"))
}

/// The fixtures, written once per test process by the venv's Python.
fn fixtures() -> &'static (tempfile::TempDir, Vec<Value>) {
    static F: std::sync::OnceLock<(tempfile::TempDir, Vec<Value>)> = std::sync::OnceLock::new();
    F.get_or_init(|| {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let python = std::env::var_os("TETWAVE_PYTHON")
            .map(PathBuf::from)
            .unwrap_or_else(|| root.join(".venv-volumes/bin/python"));
        let dir = tempfile::tempdir().unwrap();
        let out = Command::new(&python)
            .arg(root.join("scripts/volume-fixtures.py"))
            .arg(dir.path())
            .output()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot run {} ({e}): run scripts/setup, which installs nibabel, pydicom, \
                     tifffile, pynrrd, zarr and vtk into the checkout's .venv-volumes",
                    python.display()
                )
            });
        assert!(
            out.status.success(),
            "scripts/volume-fixtures.py failed (run scripts/setup for its Python packages):\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let cases: Vec<Value> =
            serde_json::from_slice(&std::fs::read(dir.path().join("cases.json")).unwrap()).unwrap();
        (dir, cases)
    })
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

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-5 * a.abs().max(b.abs()).max(1.0)
}

/// Runs every case whose source (`note`) starts with `library` (all when empty); returns how
/// many ran, so that a test asserts it saw its files.
fn check(library: &str) -> usize {
    let (dir, cases) = fixtures();
    let mut ran = 0;
    for c in cases.iter().filter(|c| {
        c["note"]
            .as_str()
            .or(c["library"].as_str())
            .unwrap_or("")
            .starts_with(library)
    }) {
        ran += 1;
        let name = c["name"].as_str().unwrap();
        let input = dir.path().join(c["path"].as_str().unwrap());
        let input = input.to_str().unwrap();
        let extra: Vec<&str> = c["args"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| a.as_str().unwrap())
            .collect();
        let store = dir.path().join(format!("{name}.store"));
        let store = store.to_str().unwrap();
        let mut args = vec!["prepare", input, "--out", store, "--json"];
        args.extend(&extra);
        let r = run(&args);
        if let Some(error) = c["error"].as_str() {
            assert!(!r.ok, "{name}: should be refused ({error})");
            let lines: Vec<&str> = r
                .stderr
                .lines()
                .filter(|l| l.starts_with("error:"))
                .collect();
            assert_eq!(lines.len(), 1, "{name}: one error line: {}", r.stderr);
            assert!(
                lines[0].contains(error),
                "{name}: {:?} lacks {error:?}",
                lines[0]
            );
            continue;
        }
        assert!(r.ok, "{name}: prepare failed: {}", r.stderr);
        let s: Value = serde_json::from_str(r.stdout.trim()).expect("one JSON object");
        let v = &s["volume"];
        let dims: Vec<u64> = v["dims"]
            .as_array()
            .unwrap_or_else(|| panic!("{name}: no volume in {s}"))
            .iter()
            .map(|x| x.as_u64().unwrap())
            .collect();
        let want_dims: Vec<u64> = c["dims"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap())
            .collect();
        assert_eq!(dims, want_dims, "{name}: dims");
        for (got, want) in f64s(&v["spacing"]).into_iter().zip(f64s(&c["spacing"])) {
            assert!(
                close(got, want),
                "{name}: spacing {} vs {}",
                v["spacing"],
                c["spacing"]
            );
        }
        if !c["origin"].is_null() {
            for (got, want) in f64s(&v["origin"]).into_iter().zip(f64s(&c["origin"])) {
                assert!(
                    (got - want).abs() < 1e-3,
                    "{name}: origin {} vs {}",
                    v["origin"],
                    c["origin"]
                );
            }
        }
        // the store keeps the file's world: its origin, frame and units as the summary reports
        // them (DICOM's world is LPS; NIfTI's RAS where the file has an sform or qform)
        let manifest: Value =
            serde_json::from_slice(&std::fs::read(Path::new(store).join("manifest.json")).unwrap())
                .unwrap();
        let physical = &manifest["physical"];
        let want_frame = match v["format"].as_str() {
            Some("NIfTI") => Some("RAS"),
            Some("DICOM") => Some("LPS"),
            _ => None,
        };
        match want_frame {
            Some("LPS") => assert_eq!(physical["frame"].as_str(), Some("LPS"), "{name}"),
            Some(f) => assert!(
                v["frame"].is_null() || v["frame"].as_str() == Some(f),
                "{name}: frame {}",
                v["frame"]
            ),
            None => {}
        }
        if !physical.is_null() {
            for k in ["origin", "frame", "length_unit", "value_unit"] {
                assert_eq!(physical[k], v[k], "{name}: manifest's {k}");
            }
        }
        let range = f64s(&s["source_value_range"]);
        let want = f64s(&c["range"]);
        assert!(
            close(range[0], want[0]) && close(range[1], want[1]),
            "{name}: value range {range:?} vs {want:?}"
        );
        // tetwave's reader against the store, every voxel
        let mut args = vec!["verify", store, "--input", input, "--json"];
        args.extend(&extra);
        let r = run(&args);
        assert!(
            r.ok,
            "{name}: verify --input failed: {}{}",
            r.stdout, r.stderr
        );
        let rep: Value = serde_json::from_str(r.stdout.trim()).unwrap();
        let points = rep["input"]["points"].as_u64().unwrap();
        assert_eq!(
            points,
            want_dims.iter().product::<u64>(),
            "{name}: every voxel"
        );
        // the library's voxels against the store
        let expect = dir.path().join(c["expect"].as_str().unwrap());
        let d = format!("{},{},{}", want_dims[0], want_dims[1], want_dims[2]);
        let sp = f64s(&c["spacing"]);
        let sp = format!("{},{},{}", sp[0], sp[1], sp[2]);
        let r = run(&[
            "verify",
            store,
            "--input",
            expect.to_str().unwrap(),
            "--dims",
            &d,
            "--dtype",
            "f64",
            "--spacing",
            &sp,
            "--json",
        ]);
        assert!(
            r.ok,
            "{name}: the store differs from the library's voxels: {}{}",
            r.stdout, r.stderr
        );
        let rep: Value = serde_json::from_str(r.stdout.trim()).unwrap();
        assert_eq!(rep["input"]["points"].as_u64().unwrap(), points, "{name}");
        by_parts_is_whole(dir.path(), name, input, &extra);
        // lossless: bit-exact wherever the library's f64 is the stored f32
        assert!(
            rep["input"]["max_abs_error"].as_f64().unwrap()
                <= 1e-6 * want[0].abs().max(want[1].abs()),
            "{name}: {rep}"
        );
    }
    ran
}

/// Prepared by parts (`--parts 2`, each part reading its block of the file alone, as out of core),
/// the store is the one-process store byte for byte, manifest included.
fn by_parts_is_whole(dir: &Path, name: &str, input: &str, extra: &[&str]) {
    let one = dir.join(format!("{name}.one"));
    let many = dir.join(format!("{name}.many"));
    let (one, many) = (one.to_str().unwrap(), many.to_str().unwrap());
    let go = |more: &[&str], out: &str| {
        let mut args = vec!["prepare", input, "--levels", "2", "--out", out];
        args.extend(extra);
        args.extend(more);
        let r = run(&args);
        assert!(r.ok, "{name}: prepare {more:?} failed: {}", r.stderr);
    };
    go(&[], one);
    go(&["--parts", "2", "--part", "0"], many);
    go(&["--parts", "2", "--part", "1"], many);
    go(&["--parts", "2", "--finish"], many);
    let mut files: Vec<_> = std::fs::read_dir(one)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    files.sort();
    assert!(!files.is_empty());
    for f in files {
        let (a, b) = (
            std::fs::read(Path::new(one).join(&f)).unwrap(),
            std::fs::read(Path::new(many).join(&f)),
        );
        assert!(
            b.as_ref().is_ok_and(|b| *b == a),
            "{name}: {f:?} differs between the one-process and the by-parts store"
        );
    }
}

#[test]
fn nifti_files_from_nibabel() {
    assert!(check("nibabel") >= 5, "nibabel's files ran");
}

#[test]
fn zarr_arrays_and_ome_zarr_from_zarr_python() {
    assert!(check("zarr-python") >= 10, "zarr-python's files ran");
}

#[test]
fn nrrd_files_from_pynrrd() {
    assert!(check("pynrrd") >= 8, "pynrrd's files ran");
}

#[test]
fn vtk_image_data_from_vtk() {
    assert!(check("vtk") >= 10, "VTK's files ran");
}

#[test]
fn tiff_stacks_from_tifffile() {
    assert!(check("tifffile") >= 11, "tifffile's files ran");
}

#[test]
fn dicom_series_from_pydicom() {
    assert!(check("pydicom") >= 11, "pydicom's files ran");
}
