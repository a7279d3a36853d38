//! The renderer draws into a texture of the caller's (as a window would give it) the same image it
//! renders offscreen. Needs a GPU adapter (`scripts/setup` installs Mesa's lavapipe); without one
//! it fails with the renderer's "no GPU adapter" message rather than skip.

use tetwave_gpu::pt::{Accumulation, PtRenderer, TetDrawData, VisibilityOrder};
use tetwave_gpu::GpuContext;
use tetwave_protocol::view::Orbit;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;

/// In one buffer, and in chunks of 100 tets (a frame's ranges then cross chunks), with the CPU's
/// sort and the GPU's.
#[test]
fn drawing_into_a_callers_texture_gives_the_offscreen_image() {
    let ctx = GpuContext::new().unwrap_or_else(|e| panic!("GPU tests cannot run: {e}"));
    let r = PtRenderer::with_accumulation(&ctx, Accumulation::U8);
    let mesh = RenderMesh::kuhn_cube(6, 1.0, |p| (p[0] * 3.0).sin() * p[1] + p[2]);
    for order in [VisibilityOrder::Centroid, VisibilityOrder::Gpu] {
        check(&ctx, &r, &mesh, r.upload(&ctx, &mesh).unwrap(), order);
        let chunked = r.upload_in_chunks(&ctx, &mesh, false, 100).unwrap();
        check(&ctx, &r, &mesh, chunked, order);
    }
}

fn check(
    ctx: &GpuContext,
    r: &PtRenderer,
    mesh: &RenderMesh,
    data: TetDrawData,
    order: VisibilityOrder,
) {
    let tf = TransferFunction::preset("default").unwrap();
    let (w, h) = (96, 72);
    let cam = Orbit {
        target: mesh.center(),
        distance: 2.0 * mesh.diagonal(),
        azimuth: 30.0,
        elevation: 20.0,
        fov: 40.0,
    }
    .camera(w, h);
    let (offscreen, _) = r.render_ordered(ctx, &data, &cam, &tf, order).unwrap();
    assert!(offscreen.coverage() > 0.05, "the cube is drawn");

    let texture = ctx.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("caller's target"),
        size: wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: r.format(),
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    let view = texture.create_view(&Default::default());
    let draw = |clear| {
        r.draw_into(ctx, &data, &cam, &tf, order, &view, clear);
        r.read_texture(ctx, &texture).unwrap()
    };
    let drawn = draw(true);
    assert!(
        drawn == offscreen,
        "the caller's texture differs from the offscreen image"
    );

    // drawn without clearing over what the caller had: the same frame blends over it
    let twice = draw(false);
    assert!(
        twice != drawn,
        "a second frame without clear blends over the first"
    );

    // one frame spread over uneven ranges of its triangles, one submission each (as the viewer
    // spreads a slow draw over several window frames): the same image
    let frame = r.prepare(ctx, &data, &cam, &tf, order);
    let n = frame.triangles();
    assert!(n > 1000, "{n} triangles");
    let cuts = [0, 1, n / 7, n / 3, n / 3, n / 2 + 5, n - 1, n + 50];
    for (i, w) in cuts.windows(2).enumerate() {
        r.draw_range_into(ctx, &frame, w[0]..w[1], &view, i == 0);
    }
    let ranged = r.read_texture(ctx, &texture).unwrap();
    assert!(
        ranged == offscreen,
        "a frame drawn in ranges differs from the frame drawn at once"
    );
    // a range short of the end leaves part of the image undrawn
    r.draw_range_into(ctx, &frame, 0..n / 2, &view, true);
    assert!(r.read_texture(ctx, &texture).unwrap() != offscreen);
}
