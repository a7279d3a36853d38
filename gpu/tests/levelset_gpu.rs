//! Domain clipping on the GPU: projected tetrahedra cut each tet's chord to where its linear level
//! set is ≥ 0, as the CPU reference does exactly. Needs a GPU adapter (`scripts/setup` installs
//! Mesa's lavapipe); without one it fails with the renderer's "no GPU adapter" message.

use glam::DVec3;
use tetwave_gpu::pt::PtRenderer;
use tetwave_gpu::GpuContext;
use tetwave_protocol::view::Orbit;
use tetwave_render::image_metrics::psnr;
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;

fn ctx() -> GpuContext {
    GpuContext::new().unwrap_or_else(|e| panic!("GPU tests cannot run: {e}"))
}

/// One tet cut by the plane `x = 0.3` (level set `x − 0.3` at its corners) and an 8³ Kuhn cube
/// clipped to a ball of radius 0.45 (level set `0.45 − |x − c|`, linear per tet, so the drawn
/// domain is the piecewise-linear ball): the GPU image is within a 40 dB floor of the exact CPU
/// reference (measured on lavapipe, 128×128: 70.4 and 73.4 dB for the tet, 67.8 and 70.3 dB for
/// the ball), every pixel the reference leaves background is background on the GPU too, and the
/// clip removes pixels that the unclipped mesh covers (about half of the tet's, 60% of the cube's).
#[test]
fn gpu_clips_to_the_level_set_like_the_reference() {
    let ctx = ctx();
    let r = PtRenderer::new(&ctx);
    let tf = TransferFunction::preset("default").unwrap();
    let corners = vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    let mut tet = RenderMesh::new(
        corners.clone(),
        vec![[0, 1, 2, 3]],
        vec![0.0, 1.0, 0.3, 0.7],
    );
    tet.levelset = Some(corners.iter().map(|p| (p[0] - 0.3) as f32).collect());
    let mut ball = RenderMesh::kuhn_cube(8, 1.0, |p| p[0] + 0.5 * p[1] * p[2]);
    let c = DVec3::splat(0.5);
    ball.levelset = Some(
        ball.positions
            .iter()
            .map(|&p| (0.45 - (DVec3::from_array(p) - c).length()) as f32)
            .collect(),
    );
    for (name, mesh) in [("tet", &tet), ("ball", &ball)] {
        let mut whole = mesh.clone();
        whole.levelset = None;
        for (az, el) in [(30.0, 25.0), (200.0, -35.0)] {
            let cam = Orbit {
                target: mesh.center(),
                distance: 2.2 * mesh.diagonal(),
                azimuth: az,
                elevation: el,
                fov: 35.0,
            }
            .camera(128, 128);
            let data = r.upload(&ctx, mesh).unwrap();
            let (gpu, _) = r.render(&ctx, &data, &cam, &tf).unwrap();
            let reference = render_reference(mesh, &cam, &tf);
            let unclipped = render_reference(&whole, &cam, &tf);
            let p = psnr(&gpu, &reference);
            let bg = [0u8; 4];
            let leaks = gpu
                .pixels
                .iter()
                .zip(&reference.pixels)
                .filter(|(g, r)| **r == bg && **g != bg)
                .count();
            let covered = |px: &[[u8; 4]]| px.iter().filter(|p| **p != bg).count();
            eprintln!(
                "{name} az {az}: PSNR {p:.1} dB, {leaks} GPU pixels outside, covered {} (clipped) \
                 vs {} (whole)",
                covered(&reference.pixels),
                covered(&unclipped.pixels)
            );
            assert!(p >= 40.0, "{name} az {az}: PSNR {p:.1} dB");
            assert_eq!(
                leaks, 0,
                "{name} az {az}: GPU draws where the domain is not"
            );
            assert!(covered(&reference.pixels) > 100, "{name}: in view");
            assert!(
                covered(&unclipped.pixels) > covered(&reference.pixels) + 20,
                "{name}: the clip removes pixels"
            );
        }
    }
}
