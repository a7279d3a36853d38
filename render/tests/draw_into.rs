//! The renderer draws into a texture of the caller's (as a window would give it) the same image it
//! renders offscreen. Needs a GPU adapter (`scripts/setup` installs Mesa's lavapipe); without one
//! it fails with the renderer's "no GPU adapter" message rather than skip.

use tetwave_protocol::view::Camera;
use tetwave_render::gpu::pt::{Accumulation, PtRenderer, VisibilityOrder};
use tetwave_render::gpu::GpuContext;
use tetwave_render::image_metrics::Rgba8Image;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;

/// Reads an `Rgba8Unorm` texture back into an image.
fn read_rgba8(ctx: &GpuContext, texture: &wgpu::Texture, w: u32, h: u32) -> Rgba8Image {
    let bpr = (w * 4).div_ceil(256) * 256;
    let buf = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("test readback"),
        size: (bpr * h) as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut enc = ctx.device.create_command_encoder(&Default::default());
    enc.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buf,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(bpr),
                rows_per_image: Some(h),
            },
        },
        wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        },
    );
    ctx.queue.submit([enc.finish()]);
    let slice = buf.slice(..);
    slice.map_async(wgpu::MapMode::Read, |_| {});
    ctx.device
        .poll(wgpu::PollType::wait_indefinitely())
        .unwrap();
    let bytes = slice.get_mapped_range().unwrap();
    let pixels = (0..h as usize)
        .flat_map(|y| {
            bytes[y * bpr as usize..][..(w * 4) as usize]
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect::<Vec<_>>()
        })
        .collect();
    Rgba8Image {
        width: w,
        height: h,
        pixels,
    }
}

#[test]
fn drawing_into_a_callers_texture_gives_the_offscreen_image() {
    let ctx = GpuContext::new().unwrap_or_else(|e| panic!("GPU tests cannot run: {e}"));
    let r = PtRenderer::with_accumulation(&ctx, Accumulation::U8);
    assert_eq!(r.format(), wgpu::TextureFormat::Rgba8Unorm);
    let mesh = RenderMesh::kuhn_cube(6, 1.0, |p| (p[0] * 3.0).sin() * p[1] + p[2]);
    let data = r.upload(&ctx, &mesh).unwrap();
    let tf = TransferFunction::preset("default").unwrap();
    let (w, h) = (96, 72);
    let cam = Camera::orbit(mesh.center(), 2.0 * mesh.diagonal(), 30.0, 20.0, 40.0, w, h);
    let (offscreen, _) = r
        .render_ordered(&ctx, &data, &cam, &tf, VisibilityOrder::Centroid)
        .unwrap();
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
    r.draw_into(
        &ctx,
        &data,
        &cam,
        &tf,
        VisibilityOrder::Centroid,
        &view,
        true,
    );
    let drawn = read_rgba8(&ctx, &texture, w, h);
    assert!(
        drawn == offscreen,
        "the caller's texture differs from the offscreen image"
    );

    // drawn without clearing over what the caller had: the same frame blends over it
    r.draw_into(
        &ctx,
        &data,
        &cam,
        &tf,
        VisibilityOrder::Centroid,
        &view,
        false,
    );
    let twice = read_rgba8(&ctx, &texture, w, h);
    assert!(
        twice != drawn,
        "a second frame without clear blends over the first"
    );
}
