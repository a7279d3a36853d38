//! GPU projected tetrahedra against the exact CPU reference (PSNR floor), on lavapipe in CI.
//! These tests need a GPU adapter; `scripts/setup` installs Mesa's lavapipe. Without one they fail
//! with the renderer's "no GPU adapter" message rather than skip.

mod common;

use glam::DVec3;
use tetwave_gpu::pt::{PtRenderer, VisibilityOrder};
use tetwave_gpu::GpuContext;
use tetwave_protocol::fields::harmonic_unit;
use tetwave_protocol::view::{Camera, Orbit};
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;

fn ctx() -> GpuContext {
    GpuContext::new().unwrap_or_else(|e| panic!("GPU tests cannot run: {e}"))
}

fn compare(
    ctx: &GpuContext,
    r: &PtRenderer,
    mesh: &RenderMesh,
    cam: &Camera,
    tf: &str,
) -> (f64, Rgba8Image, Rgba8Image) {
    let tf = TransferFunction::preset(tf).unwrap();
    let data = r.upload(ctx, mesh).unwrap();
    let (gpu, _) = r.render(ctx, &data, cam, &tf).unwrap();
    let reference = render_reference(mesh, cam, &tf);
    (psnr(&gpu, &reference), gpu, reference)
}

/// PSNR ≥ 45 dB against the reference at 256×256: single tet, 6-tet cube, 8³ Kuhn cube; an opaque-ish
/// and a very transparent transfer function; camera outside, inside the volume, and grazing.
#[test]
fn gpu_matches_reference_45db() {
    let ctx = ctx();
    eprintln!("adapter: {}", ctx.describe());
    let r = PtRenderer::new(&ctx);
    let mut failures = Vec::new();
    let single = RenderMesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        vec![[0, 1, 2, 3]],
        vec![0.0, 1.0, 0.3, 0.7],
    );
    let cube6 = RenderMesh::kuhn_cube(1, 1.0, harmonic_unit);
    let cube8 = RenderMesh::kuhn_cube(8, 1.0, harmonic_unit);
    for (name, mesh) in [("single", &single), ("cube6", &cube6), ("kuhn8", &cube8)] {
        let c = mesh.center();
        let d = mesh.diagonal();
        let cams = [
            ("outside", Orbit::around(c, 2.0 * d).camera(256, 256)),
            (
                "inside",
                Orbit {
                    target: c + DVec3::new(0.05, 0.02, 0.01) * d,
                    distance: 0.1 * d,
                    azimuth: 35.0,
                    elevation: 25.0,
                    fov: 60.0,
                }
                .camera(256, 256),
            ),
            (
                "grazing",
                Orbit {
                    target: c,
                    distance: 2.0 * d,
                    azimuth: 0.0,
                    elevation: 0.5,
                    fov: 40.0,
                }
                .camera(256, 256),
            ),
        ];
        for (cname, cam) in &cams {
            for tf in ["default", "transparent"] {
                let (p, gpu, _) = compare(&ctx, &r, mesh, cam, tf);
                eprintln!(
                    "{name:8} {cname:8} {tf:12} psnr {p:.2} coverage {:.3}",
                    gpu.coverage()
                );
                assert!(gpu.coverage() > 0.05, "{name} {cname} {tf}: blank image");
                if p < 45.0 {
                    failures.push(format!("{name} {cname} {tf}: {p:.2} dB"));
                }
            }
        }
    }
    assert!(failures.is_empty(), "below 45 dB: {failures:?}");
}

/// MPVO order on a convex mesh: a valid order that matches the reference as well as centroid order.
#[test]
fn mpvo_order_matches_reference() {
    let ctx = ctx();
    let r = PtRenderer::new(&ctx);
    let tf = TransferFunction::preset("default").unwrap();
    let mesh = RenderMesh::kuhn_cube(8, 1.0, harmonic_unit);
    let data = r.upload_with(&ctx, &mesh, true).unwrap();
    let c = mesh.center();
    let d = mesh.diagonal();
    for cam in [
        Orbit::around(c, 2.0 * d).camera(192, 192),
        Orbit {
            target: c + DVec3::new(0.05, 0.02, 0.01) * d,
            distance: 0.1 * d,
            azimuth: 35.0,
            elevation: 25.0,
            fov: 60.0,
        }
        .camera(192, 192),
    ] {
        let reference = render_reference(&mesh, &cam, &tf);
        let (m, _) = r
            .render_ordered(&ctx, &data, &cam, &tf, VisibilityOrder::Mpvo)
            .unwrap();
        let (ce, _) = r
            .render_ordered(&ctx, &data, &cam, &tf, VisibilityOrder::Centroid)
            .unwrap();
        let (pm, pc) = (psnr(&m, &reference), psnr(&ce, &reference));
        eprintln!("mpvo {pm:.2} dB, centroid {pc:.2} dB");
        assert!(
            pm >= 45.0 && pm >= pc - 0.5,
            "mpvo {pm:.2} centroid {pc:.2}"
        );
    }
}

/// No NaN or blank output from degenerate input: slivers (aspect 1e-4), zero-volume tets,
/// coordinates offset by 1e6, a constant field; and each still matches the reference.
#[test]
fn degenerate_input() {
    let ctx = ctx();
    let r = PtRenderer::new(&ctx);
    let mut cases: Vec<(&str, RenderMesh)> = Vec::new();
    // sliver: a tet flattened to 1e-4 of its size, inside a normal cube mesh
    let mut sliver = RenderMesh::kuhn_cube(2, 1.0, harmonic_unit);
    let base = sliver.positions.len() as u32;
    sliver.positions.extend([
        [0.2, 0.2, 0.5],
        [0.8, 0.2, 0.5],
        [0.5, 0.8, 0.5],
        [0.5, 0.4, 0.5 + 1e-4],
    ]);
    sliver.values.extend([0.0, 1.0, 0.5, 0.2]);
    sliver.tets.push([base, base + 1, base + 2, base + 3]);
    sliver.orient_positive();
    cases.push(("sliver", sliver));
    // zero-volume tets: four coplanar points, and a repeated vertex
    let mut flat = RenderMesh::kuhn_cube(2, 1.0, harmonic_unit);
    let b = flat.positions.len() as u32;
    flat.positions.extend([
        [0.1, 0.1, 0.3],
        [0.9, 0.1, 0.3],
        [0.1, 0.9, 0.3],
        [0.9, 0.9, 0.3],
    ]);
    flat.values.extend([0.0, 1.0, 0.5, 0.2]);
    flat.tets.push([b, b + 1, b + 2, b + 3]);
    flat.tets.push([b, b, b + 1, b + 2]);
    cases.push(("zero-volume", flat));
    // far from the origin
    let mut far = RenderMesh::kuhn_cube(4, 1.0, harmonic_unit);
    for p in &mut far.positions {
        for c in p.iter_mut() {
            *c += 1e6;
        }
    }
    cases.push(("offset 1e6", far));
    cases.push(("constant", RenderMesh::kuhn_cube(3, 1.0, |_| 0.4)));
    let tf = TransferFunction::preset("default").unwrap();
    for (name, mesh) in &cases {
        let cam = Orbit {
            target: mesh.center(),
            distance: 2.0 * mesh.diagonal(),
            azimuth: 30.0,
            elevation: 20.0,
            fov: 40.0,
        }
        .camera(128, 128);
        let data = r.upload(&ctx, mesh).unwrap();
        let (gpu, _) = r.render(&ctx, &data, &cam, &tf).unwrap();
        assert!(gpu.coverage() > 0.05, "{name}: blank");
        let reference = render_reference(mesh, &cam, &tf);
        let p = psnr(&gpu, &reference);
        eprintln!("{name}: {p:.2} dB");
        assert!(p >= 45.0, "{name}: {p:.2} dB");
        // the f64 frame had no NaN: from_f64 maps NaN to 0 in every channel; compare raw floats too
        let (_, times) = r.render(&ctx, &data, &cam, &tf).unwrap();
        assert!(times.total_ms.is_finite());
    }
}

/// Consistency: rendering the same smooth field on meshes refined uniformly (8× the tets each step)
/// converges to the reference of the finest mesh: the error falls at every refinement.
#[test]
fn refinement_converges() {
    let ctx = ctx();
    let r = PtRenderer::new(&ctx);
    let tf = TransferFunction::preset("default").unwrap();
    let smooth = |p: [f64; 3]| (p[0] * 2.0).sin() + (p[1] * 3.0).cos() * p[2];
    let finest = RenderMesh::kuhn_cube(32, 1.0, smooth);
    let cam = Orbit::around(finest.center(), 2.0 * finest.diagonal()).camera(128, 128);
    let reference = render_reference(&finest, &cam, &tf);
    let mut psnrs = Vec::new();
    for n in [2usize, 4, 8, 16] {
        let mut mesh = RenderMesh::kuhn_cube(n, 1.0, smooth);
        mesh.value_range = finest.value_range;
        let data = r.upload(&ctx, &mesh).unwrap();
        let (img, _) = r.render(&ctx, &data, &cam, &tf).unwrap();
        psnrs.push(psnr(&img, &reference));
    }
    eprintln!("PSNR vs the 32^3 reference at n = 2, 4, 8, 16: {psnrs:?}");
    for w in psnrs.windows(2) {
        assert!(w[1] > w[0], "{psnrs:?}");
    }
}

/// Lower-precision accumulation targets trade accuracy for blending speed: 16-bit floats and 8-bit
/// unorm still land far above an 8-bit renderer's typical error on a 32³ Kuhn cube (196,608 tets,
/// ~100 layers per ray), and never below the 32-bit target.
#[test]
fn accumulation_precisions_are_ordered_and_bounded() {
    use tetwave_gpu::pt::Accumulation;
    let ctx = ctx();
    let mesh = RenderMesh::kuhn_cube(32, 1.0, harmonic_unit);
    let cam = Orbit::around(mesh.center(), 1.6 * mesh.diagonal()).camera(192, 192);
    let tf = TransferFunction::preset("default").unwrap();
    let reference = render_reference(&mesh, &cam, &tf);
    let mut out = Vec::new();
    for acc in [Accumulation::Best, Accumulation::F16, Accumulation::U8] {
        let r = PtRenderer::with_accumulation(&ctx, acc);
        let data = r.upload(&ctx, &mesh).unwrap();
        let (img, _) = r.render(&ctx, &data, &cam, &tf).unwrap();
        let p = psnr(&img, &reference);
        eprintln!("{acc:?}: {p:.2} dB");
        out.push(p);
    }
    assert!(
        out[0] >= 45.0,
        "32-bit (or best) accumulation: {:.2} dB",
        out[0]
    );
    assert!(
        out[1] >= 40.0,
        "16-bit float accumulation: {:.2} dB",
        out[1]
    );
    assert!(out[2] >= 30.0, "8-bit accumulation: {:.2} dB", out[2]);
    assert!(
        out[0] + 0.5 >= out[1] && out[1] + 0.5 >= out[2],
        "precisions out of order: {out:?}"
    );
}

/// `tetwave-bench progressive --render-every` on the GPU: the simple run's last frame (every detail
/// arrived) agrees with the CPU reference of the full-resolution mesh.
#[test]
fn render_probe_on_the_gpu() {
    use tetwave_client::progressive::RunConfig;
    let cfg = RunConfig {
        steps: 20,
        per_step: 40,
        width: 96,
        height: 96,
        tol: None,
        ..RunConfig::default()
    };
    let (_, s) = common::probed_run(3, &cfg, 10, false);
    assert!(s.renderer.starts_with("gpu-pt"), "{}", s.renderer);
    assert_eq!(
        s.frames.iter().map(|f| f.step).collect::<Vec<_>>(),
        [0, 10, 19]
    );
    let last = s.frames.last().unwrap();
    assert!(last.psnr_db >= 40.0, "{last:?}");
    assert!(s.frames[0].psnr_db < last.psnr_db, "{:?}", s.frames);
}

/// An image side of 0 or beyond the adapter's limit is an error from the renderer itself (wgpu
/// panicked creating such a target); the CPU reference draws an empty image.
#[test]
fn image_sizes_outside_the_limit_are_errors() {
    let ctx = ctx();
    let r = PtRenderer::new(&ctx);
    let mesh = RenderMesh::kuhn_cube(2, 1.0, harmonic_unit);
    let data = r.upload(&ctx, &mesh).unwrap();
    let tf = TransferFunction::preset("default").unwrap();
    let limit = ctx.device.limits().max_texture_dimension_2d;
    for (w, h) in [(0, 16), (16, 0), (limit + 1, 1)] {
        let cam = Orbit {
            target: mesh.center(),
            distance: 3.0,
            azimuth: 30.0,
            elevation: 20.0,
            fov: 40.0,
        }
        .camera(w, h);
        let e = r.render(&ctx, &data, &cam, &tf).expect_err("refused");
        assert!(
            e.to_string().contains("each side must be 1..="),
            "{w}x{h}: {e}"
        );
    }
    let cam = Orbit {
        target: mesh.center(),
        distance: 3.0,
        azimuth: 30.0,
        elevation: 20.0,
        fov: 40.0,
    }
    .camera(0, 16);
    let img = render_reference(&mesh, &cam, &tf);
    assert_eq!((img.width, img.height, img.pixels.len()), (0, 16, 0));
}
