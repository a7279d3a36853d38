//! `tetwave render <mesh>` with no `--tf` draws with the `auto` transfer function (the `default`
//! preset fitted to the data's value histogram, `TransferFunction::fitted`): on a FEM-like field
//! concentrated at low values, at least a quarter of the pixels whose ray hits the mesh are
//! bright (Rec. 709 luma ≥ 0.2), where the `default` preset leaves most of them dark. A store of
//! the mesh fits to nearly the same function. Needs a GPU adapter (lavapipe in CI), like
//! `render_mesh`.

use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;
use tetwave_render::image_metrics::Rgba8Image;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TransferFunction, AUTO};
use tetwave_server::prepare::{prepare, PrepareOptions};

/// A 12³-cube Kuhn mesh of `[0, 1]³` (10,368 tets) with the field of a point source at
/// `(0.3, 0.35, 0.6)`, `1 / (1 + (r / 0.08)²)`: a potential that decays away from its source, so
/// that most of the volume has values in the lowest tenth of the range, as an ASCII `.vtu`.
fn write_skewed_vtu(path: &Path) {
    let m = RenderMesh::kuhn_cube(12, 1.0, |p| {
        let r2 = (p[0] - 0.3).powi(2) + (p[1] - 0.35).powi(2) + (p[2] - 0.6).powi(2);
        1.0 / (1.0 + r2 / 0.08f64.powi(2))
    });
    let mut s = String::new();
    writeln!(s, "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\">\n<UnstructuredGrid>").unwrap();
    writeln!(
        s,
        "<Piece NumberOfPoints=\"{}\" NumberOfCells=\"{}\">",
        m.positions.len(),
        m.tets.len()
    )
    .unwrap();
    s += "<PointData Scalars=\"u\">\n<DataArray type=\"Float64\" Name=\"u\" format=\"ascii\">\n";
    for v in &m.values {
        writeln!(s, "{v}").unwrap();
    }
    s += "</DataArray>\n</PointData>\n<Points>\n<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n";
    for p in &m.positions {
        writeln!(s, "{} {} {}", p[0], p[1], p[2]).unwrap();
    }
    s += "</DataArray>\n</Points>\n<Cells>\n<DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">\n";
    for t in &m.tets {
        writeln!(s, "{} {} {} {}", t[0], t[1], t[2], t[3]).unwrap();
    }
    s += "</DataArray>\n<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">\n";
    for i in 0..m.tets.len() {
        writeln!(s, "{}", 4 * (i + 1)).unwrap();
    }
    s += "</DataArray>\n<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n";
    for _ in 0..m.tets.len() {
        s += "10\n";
    }
    s += "</DataArray>\n</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>\n";
    std::fs::write(path, s).unwrap();
}

/// `tetwave render input --size 128x128 --json -o out` with `extra`: the image and the report.
fn render(input: &Path, out: &Path, extra: &[&str]) -> (Rgba8Image, serde_json::Value) {
    let o = Command::new(env!("CARGO_BIN_EXE_tetwave"))
        .arg("render")
        .arg(input)
        .args(["--size", "128x128", "--json", "-o"])
        .arg(out)
        .args(extra)
        .output()
        .expect("tetwave runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report = serde_json::from_slice(&o.stdout).expect("one JSON object");
    (Rgba8Image::load_png(out).unwrap(), report)
}

fn luma(p: &[u8; 4]) -> f64 {
    (0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64) / 255.0
}

/// The share of `domain`'s pixels whose luma is ≥ 0.2.
fn bright_share(img: &Rgba8Image, domain: &[bool]) -> f64 {
    let n = domain.iter().filter(|&&d| d).count();
    let bright = img
        .pixels
        .iter()
        .zip(domain)
        .filter(|(p, &d)| d && luma(p) >= 0.2)
        .count();
    bright as f64 / n as f64
}

#[test]
fn auto_is_the_default_and_shows_skewed_data() {
    let d = tempfile::tempdir().unwrap();
    let vtu = d.path().join("source.vtu");
    write_skewed_vtu(&vtu);
    // the domain: pixels an opaque white medium covers
    let mask_tf = d.path().join("mask.json");
    std::fs::write(
        &mask_tf,
        r#"{"name":"mask","points":[{"s":0,"rgb":[1,1,1],"extinction":100000}]}"#,
    )
    .unwrap();
    let (mask, _) = render(
        &vtu,
        &d.path().join("mask.png"),
        &["--tf", mask_tf.to_str().unwrap()],
    );
    let domain: Vec<bool> = mask.pixels.iter().map(|p| p[0] > 0).collect();
    let n = domain.iter().filter(|&&x| x).count();
    assert!(n > 128 * 128 / 8, "{n} domain pixels");

    let (auto, report) = render(&vtu, &d.path().join("auto.png"), &[]);
    let (preset, _) = render(&vtu, &d.path().join("default.png"), &["--tf", "default"]);
    let (a, p) = (bright_share(&auto, &domain), bright_share(&preset, &domain));
    eprintln!("luma ≥ 0.2 on {a:.3} of {n} domain pixels with auto, {p:.3} with default");
    assert!(a >= 0.25, "auto: {a:.3}");
    assert!(p < 0.25, "the default preset is not faint here: {p:.3}");
    let tf: TransferFunction = serde_json::from_value(report["tf"].clone()).unwrap();
    assert_eq!(tf.name, AUTO);
    tf.validate().unwrap();
    // the report's function is the one drawn: given back as a file, it draws the same image
    let saved = d.path().join("auto.json");
    std::fs::write(&saved, serde_json::to_string(&tf).unwrap()).unwrap();
    let (again, _) = render(
        &vtu,
        &d.path().join("again.png"),
        &["--tf", saved.to_str().unwrap()],
    );
    assert!(again.pixels == auto.pixels);
    // `--tf auto` is the default
    let (explicit, _) = render(&vtu, &d.path().join("explicit.png"), &["--tf", "auto"]);
    assert!(explicit.pixels == auto.pixels);

    // a store of the mesh fits to its finest level, at every level drawn: nearly the mesh's
    // function, and the same at each level
    let store = d.path().join("store");
    let mut o = PrepareOptions::new(vtu.to_str().unwrap(), &store);
    o.levels = Some(3);
    prepare(&o).unwrap();
    let fit = |level: &str| -> TransferFunction {
        let (_, r) = render(&store, &d.path().join("store.png"), &["--levels", level]);
        serde_json::from_value(r["tf"].clone()).unwrap()
    };
    let (fine, coarse) = (fit("3"), fit("1"));
    assert_eq!(fine, coarse);
    for (a, b) in tf.points.iter().zip(&fine.points) {
        assert!((a.s - b.s).abs() < 0.02, "mesh {a:?}, store {b:?}");
        assert!(
            (a.extinction / b.extinction - 1.0).abs() < 0.05,
            "mesh {a:?}, store {b:?}"
        );
    }
}
