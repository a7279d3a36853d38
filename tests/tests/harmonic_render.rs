//! Server → store → client → GPU: the harmonic dataset at level 3, rendered by projected tetrahedra,
//! against the CPU reference (PSNR ≥ 45 dB), for an opaque-ish and a very transparent transfer
//! function, camera outside, inside and grazing. Needs a GPU adapter (lavapipe in CI).

use glam::DVec3;
use tetwave_gpu::pt::PtRenderer;
use tetwave_gpu::GpuContext;
use tetwave_protocol::view::Orbit;
use tetwave_render::image_metrics::psnr;
use tetwave_render::reference::render_reference;
use tetwave_render::transfer::TransferFunction;
use tetwave_server::prepare::{prepare, PrepareOptions};
use tetwave_source::load::store_mesh;
use tetwave_store::Store;

#[test]
fn client_reads_the_servers_store_identically() {
    let d = tempfile::tempdir().unwrap();
    let mut o = PrepareOptions::new("synthetic:harmonic", d.path());
    o.levels = Some(4);
    o.bits = Some(12);
    o.keep_reference = true;
    prepare(&o).unwrap();
    let server = Store::open(d.path()).unwrap();
    let client = Store::open(d.path()).unwrap();
    let n = server.manifest.counts.nodes;
    assert_eq!(
        server.read_nodes(0, n).unwrap(),
        client.read_nodes(0, n).unwrap()
    );
    assert_eq!(&server.base, &client.base);
    // the client's synthesis equals the stored samples within the manifest's bound
    let values = client.synthesize_all().unwrap();
    let reference = server.read_reference().unwrap().expect("kept");
    let err = values
        .iter()
        .zip(&reference)
        .map(|(a, b)| (a - b).abs() as f64)
        .fold(0.0, f64::max);
    assert!(err <= server.manifest.max_error_bound, "{err}");
}

#[test]
fn harmonic_level3_gpu_matches_reference() {
    let d = tempfile::tempdir().unwrap();
    let mut o = PrepareOptions::new("synthetic:harmonic", d.path());
    o.levels = Some(3);
    prepare(&o).unwrap();
    let store = Store::open(d.path()).unwrap();
    let (mesh, level) = store_mesh(&store, None).unwrap();
    assert_eq!((level, mesh.tets.len()), (3, 2560));
    let ctx = GpuContext::new().unwrap_or_else(|e| panic!("GPU test cannot run: {e}"));
    let r = PtRenderer::new(&ctx);
    let data = r.upload(&ctx, &mesh).unwrap();
    let c = mesh.center();
    let diag = mesh.diagonal();
    let cams = [
        ("outside", Orbit::around(c, 1.6 * diag).camera(256, 256)),
        (
            "inside",
            Orbit {
                target: c + DVec3::new(2.0, 1.0, 0.5),
                distance: 3.0,
                azimuth: 35.0,
                elevation: 25.0,
                fov: 70.0,
            }
            .camera(256, 256),
        ),
        (
            "grazing",
            Orbit {
                target: c,
                distance: 1.6 * diag,
                azimuth: 0.0,
                elevation: 0.3,
                fov: 40.0,
            }
            .camera(256, 256),
        ),
    ];
    let mut worst = f64::INFINITY;
    for (name, cam) in &cams {
        for tf in ["default", "transparent"] {
            let tf = TransferFunction::preset(tf).unwrap();
            let (gpu, _) = r.render(&ctx, &data, cam, &tf).unwrap();
            let reference = render_reference(&mesh, cam, &tf);
            let p = psnr(&gpu, &reference);
            eprintln!("harmonic L3 {name} {}: {p:.2} dB", tf.name);
            assert!(gpu.coverage() > 0.05, "{name}: blank");
            assert!(p >= 45.0, "{name} {}: {p:.2} dB", tf.name);
            worst = worst.min(p);
        }
    }
    eprintln!("worst {worst:.2} dB");
}
