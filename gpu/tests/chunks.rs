//! A mesh larger than one storage binding is drawn in chunks (`TetDrawData`): forced here on a
//! small mesh (`upload_in_chunks`), the chunked image matches the one-buffer image and the CPU
//! reference, from outside the mesh and from inside it, with the CPU's sort and the GPU's
//! (`VisibilityOrder::Gpu`), which draws the CPU's image. Needs a GPU adapter (`scripts/setup` installs Mesa's lavapipe); without one it
//! fails with the renderer's "no GPU adapter" message rather than skip.

use tetwave_gpu::pt::{PtRenderer, VisibilityOrder};
use tetwave_gpu::GpuContext;
use tetwave_protocol::view::Orbit;
use tetwave_render::image_metrics::psnr;
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;

#[test]
fn a_mesh_in_chunks_draws_the_image_of_one_buffer() {
    let ctx = GpuContext::new().unwrap_or_else(|e| panic!("GPU tests cannot run: {e}"));
    let r = PtRenderer::new(&ctx);
    assert!(
        PtRenderer::chunk_tets(&ctx) > 1_000,
        "one chunk holds a small mesh"
    );
    // 16³ Kuhn cells: 24,576 tets, a field with structure in every direction
    let mesh = RenderMesh::kuhn_cube(16, 1.0, |p| {
        (p[0] * 5.0).sin() * (p[1] * 3.0).cos() + 0.7 * p[2] * p[2]
    });
    let tf = TransferFunction::preset("default").unwrap();
    let whole = r.upload(&ctx, &mesh).unwrap();
    let cam = |distance: f64, azimuth: f64| {
        Orbit {
            target: mesh.center(),
            distance,
            azimuth,
            elevation: 25.0,
            fov: 40.0,
        }
        .camera(128, 128)
    };
    let d = mesh.diagonal();
    // outside at two angles, and inside the mesh (the near plane cuts chunks)
    for (cam, what) in [
        (cam(1.6 * d, 35.0), "outside"),
        (cam(1.6 * d, 210.0), "outside, behind"),
        (cam(0.3 * d, 35.0), "inside"),
    ] {
        let (one, _) = r
            .render_ordered(&ctx, &whole, &cam, &tf, VisibilityOrder::Centroid)
            .unwrap();
        let reference = render_reference(&mesh, &cam, &tf);
        // the GPU's sort draws the CPU's order (but for ties, which neither orders)
        let (gpu, _) = r
            .render_ordered(&ctx, &whole, &cam, &tf, VisibilityOrder::Gpu)
            .unwrap();
        let gpu_one = psnr(&gpu, &one);
        eprintln!("{what}: the GPU's sort: {gpu_one:.1} dB against the CPU's");
        assert!(gpu_one >= 60.0, "{what}: GPU sort {gpu_one:.1} dB");
        for (most, order) in [
            (5_000, VisibilityOrder::Centroid),
            (700, VisibilityOrder::Centroid),
            (700, VisibilityOrder::Gpu),
        ] {
            let chunked = r.upload_in_chunks(&ctx, &mesh, false, most).unwrap();
            let (img, _) = r.render_ordered(&ctx, &chunked, &cam, &tf, order).unwrap();
            let (vs_one, vs_ref, one_ref) = (
                psnr(&img, &one),
                psnr(&img, &reference),
                psnr(&one, &reference),
            );
            eprintln!(
                "{what}: chunks of {most}, {order:?}: {vs_one:.1} dB against one buffer, \
                 {vs_ref:.1} dB against the CPU reference (one buffer: {one_ref:.1} dB)"
            );
            assert!(img.coverage() > 0.05, "{what}: drawn");
            assert!(vs_one >= 50.0, "{what}, chunks of {most}: {vs_one:.1} dB");
            assert!(
                vs_ref >= one_ref - 1.0,
                "{what}, chunks of {most}: {vs_ref:.1} dB"
            );
        }
    }
}
