//! The viewer's GPU side, on the one device the window and the renderer share.
//!
//! The volume is drawn by [`tetwave_gpu::pt::PtRenderer::draw_into`] into an offscreen texture of the renderer's
//! accumulation format (32-bit float where blendable, else 16-bit): blending many layers in the
//! window's 8-bit surface would lose precision at every layer (≈ 30 dB against the reference
//! instead of ≥ 45). An egui paint callback then copies that texture, texel for texel, into the
//! view's rectangle of the surface ([`Blit`]); the server's image is shown the same way from an
//! 8-bit texture. Colours are premultiplied over black, as `tetwave render` writes them, so a
//! screenshot of the view is the offscreen image quantized once to 8 bits.

use eframe::egui_wgpu;
use tetwave_gpu::GpuContext;
use tetwave_render::image_metrics::Rgba8Image;

const BLIT: &str = r#"
@group(0) @binding(0) var src: texture_2d<f32>;

struct Out {
    @builtin(position) pos: vec4<f32>,
    @location(0) uv: vec2<f32>,
};

// one triangle covering the viewport; uv is 0..1 across it (top-left origin)
@vertex
fn vs(@builtin(vertex_index) i: u32) -> Out {
    let x = f32((i << 1u) & 2u);
    let y = f32(i & 2u);
    var o: Out;
    o.pos = vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
    o.uv = vec2<f32>(x, y);
    return o;
}

// texel for texel (the viewport has the texture's size): premultiplied colour over black
@fragment
fn fs(v: Out) -> @location(0) vec4<f32> {
    let dims = textureDimensions(src);
    let p = min(vec2<u32>(v.uv * vec2<f32>(dims)), dims - vec2<u32>(1u, 1u));
    let c = textureLoad(src, p, 0);
    return vec4<f32>(clamp(c.rgb, vec3<f32>(0.0), vec3<f32>(1.0)), 1.0);
}
"#;

/// The copy pipeline (for the window's surface format) and its layout.
#[derive(Clone)]
pub struct Blit {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
}

impl Blit {
    pub fn new(device: &wgpu::Device, target: wgpu::TextureFormat) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("viewer blit"),
            source: wgpu::ShaderSource::Wgsl(BLIT.into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("viewer blit"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Float { filterable: false },
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: false,
                },
                count: None,
            }],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("viewer blit"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("viewer blit"),
            layout: Some(&pl),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs"),
                buffers: &[],
                compilation_options: Default::default(),
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: None,
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs"),
                targets: &[Some(wgpu::ColorTargetState {
                    format: target,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
                compilation_options: Default::default(),
            }),
            multiview_mask: None,
            cache: None,
        });
        Blit { pipeline, layout }
    }

    /// A bind group showing `view`.
    pub fn bind(&self, device: &wgpu::Device, view: &wgpu::TextureView) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("viewer blit"),
            layout: &self.layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::TextureView(view),
            }],
        })
    }
}

/// The paint callback: copies one texture into the callback's rectangle.
pub struct BlitCallback {
    pub blit: Blit,
    pub bind: wgpu::BindGroup,
}

impl egui_wgpu::CallbackTrait for BlitCallback {
    fn paint(
        &self,
        _info: eframe::egui::PaintCallbackInfo,
        pass: &mut wgpu::RenderPass<'static>,
        _resources: &egui_wgpu::CallbackResources,
    ) {
        pass.set_pipeline(&self.blit.pipeline);
        pass.set_bind_group(0, &self.bind, &[]);
        pass.draw(0..3, 0..1);
    }
}

/// An offscreen colour target of the view's size.
pub struct Target {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pub bind: wgpu::BindGroup,
}

impl Target {
    pub fn new(
        ctx: &GpuContext,
        blit: &Blit,
        format: wgpu::TextureFormat,
        width: u32,
        height: u32,
    ) -> Self {
        let texture = ctx.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("viewer target"),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&Default::default());
        let bind = blit.bind(&ctx.device, &view);
        Target {
            texture,
            view,
            bind,
        }
    }

    /// A texture holding an 8-bit image (the server's), to show with [`Blit`].
    pub fn from_image(ctx: &GpuContext, blit: &Blit, img: &Rgba8Image) -> Self {
        let t = Self::new(
            ctx,
            blit,
            wgpu::TextureFormat::Rgba8Unorm,
            img.width,
            img.height,
        );
        ctx.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &t.texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(&img.pixels),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(4 * img.width),
                rows_per_image: Some(img.height),
            },
            wgpu::Extent3d {
                width: img.width,
                height: img.height,
                depth_or_array_layers: 1,
            },
        );
        t
    }

    pub fn size(&self) -> (u32, u32) {
        (self.texture.width(), self.texture.height())
    }
}

/// The wgpu set-up eframe uses: this context's instance, adapter, device and queue, so the window
/// and the renderer share one device.
pub fn shared_setup(ctx: &GpuContext) -> egui_wgpu::WgpuSetup {
    egui_wgpu::WgpuSetup::Existing(egui_wgpu::WgpuSetupExisting {
        instance: ctx.instance.clone(),
        adapter: ctx.adapter.clone(),
        device: ctx.device.clone(),
        queue: ctx.queue.clone(),
    })
}
