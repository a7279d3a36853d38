//! Projected tetrahedra: [`PtRenderer`] holds the pipeline (long-lived); [`TetDrawData`] holds one
//! mesh's GPU buffers (valid until the mesh changes); each frame sorts the tets back to front and
//! draws them instanced, 12 vertices per tet, with no per-frame CPU geometry.
//!
//! **Visibility order.** Tets are sorted by the distance from the eye to their centroid. This is
//! exact for a ray only if no two tets it crosses are mis-ordered; centroid order can fail for tets of
//! very different sizes next to each other or long slivers (a small tet whose centroid is farther
//! than a large neighbour's but which lies in front of it along some rays), and no order exists when
//! the "in front of" relation has a cycle. Errors show as small blending differences on the affected
//! pixels; the image tests bound them against the exact reference.

use super::order::{centroid_order, face_neighbors, mpvo_order};
use super::{GpuContext, RenderError};
use crate::camera::Camera;
use crate::image_metrics::Rgba8Image;
use crate::render_mesh::RenderMesh;
use crate::transfer::TransferFunction;
use bytemuck::{Pod, Zeroable};
use glam::DVec3;
use rayon::prelude::*;
use wgpu::util::DeviceExt;

/// How tets are ordered back to front each frame (see [`super::order`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
pub enum VisibilityOrder {
    /// Sort by eye-to-centroid distance (approximate).
    #[default]
    Centroid,
    /// Williams' MPVO over face adjacency (exact for convex, acyclic meshes).
    Mpvo,
}

const SHADER: &str = include_str!("../../../shaders/pt.wgsl");

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Globals {
    view_proj: [[f32; 4]; 4],
    eye: [f32; 4],
    fwd: [f32; 4],
    tf_info: [u32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct TetGeo {
    planes: [[f32; 4]; 4],
    grad: [f32; 4],
}

/// Intervals of the transfer-function table the fragment stage interpolates (a table lookup costs
/// one interpolation instead of a search over the points; the table differs from the piecewise-linear
/// function only inside the intervals that contain a breakpoint).
pub const TF_TABLE_INTERVALS: u32 = 4096;

/// Corner indices of the 4 faces of a positively oriented tet, each wound counter-clockwise seen from
/// outside (face `i` is opposite corner `i`).
const FACES_POS: [u32; 12] = [1, 2, 3, 0, 3, 2, 0, 1, 3, 0, 2, 1];
/// The same for a negatively oriented tet (every face reversed).
const FACES_NEG: [u32; 12] = [1, 3, 2, 0, 2, 3, 0, 3, 1, 0, 1, 2];

/// Precision of the colour accumulation target (blending happens in this format).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
pub enum Accumulation {
    /// 32-bit float per channel where the adapter can blend it, else 16-bit (the default: exact
    /// enough for the ≥ 45 dB image tests).
    #[default]
    Best,
    /// 16-bit float per channel.
    F16,
    /// 8-bit unorm per channel: fastest blending on CPU rasterizers, ~8-bit rounding per layer.
    U8,
}

/// Pipeline and layouts: create once per device and format.
pub struct PtRenderer {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    format: wgpu::TextureFormat,
}

/// One mesh on the GPU. Valid for the mesh it was built from; positions are relative to `origin`.
pub struct TetDrawData {
    /// Face adjacency, present when uploaded for MPVO ordering.
    neighbors: Option<Vec<[u32; 4]>>,
    /// CPU copies of the outward face planes (`n·x = w`, relative to `origin`): each frame draws
    /// only the faces the eye sees from inside (the exit faces), and MPVO orders by them.
    planes: Vec<[[f32; 4]; 4]>,
    /// Per tet: positively oriented (decides the winding of its faces).
    positive: Vec<bool>,
    positions: wgpu::Buffer,
    tets: wgpu::Buffer,
    geo: wgpu::Buffer,
    centroids: Vec<[f32; 3]>,
    origin: DVec3,
    diagonal: f64,
    far: f64,
    pub tet_count: u32,
}

/// Timings of one frame, in milliseconds.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct FrameTimes {
    pub sort_ms: f64,
    pub gpu_ms: f64,
    pub readback_ms: f64,
    pub total_ms: f64,
}

impl PtRenderer {
    /// The renderer with [`Accumulation::Best`].
    pub fn new(ctx: &GpuContext) -> Self {
        Self::with_accumulation(ctx, Accumulation::Best)
    }

    /// The renderer accumulating in the given precision.
    pub fn with_accumulation(ctx: &GpuContext, acc: Accumulation) -> Self {
        let device = &ctx.device;
        let format = match acc {
            Accumulation::Best if ctx.float32_blend => wgpu::TextureFormat::Rgba32Float,
            Accumulation::U8 => wgpu::TextureFormat::Rgba8Unorm,
            _ => wgpu::TextureFormat::Rgba16Float,
        };
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("pt.wgsl"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let storage = |binding: u32, vis: wgpu::ShaderStages| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: vis,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: true },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let vf = wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT;
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("pt"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: vf,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                storage(1, wgpu::ShaderStages::VERTEX),
                storage(2, wgpu::ShaderStages::VERTEX),
                storage(3, wgpu::ShaderStages::VERTEX),
                storage(5, wgpu::ShaderStages::FRAGMENT),
            ],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("pt"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let blend = wgpu::BlendComponent {
            src_factor: wgpu::BlendFactor::One,
            dst_factor: wgpu::BlendFactor::OneMinusSrcAlpha,
            operation: wgpu::BlendOperation::Add,
        };
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("pt"),
            layout: Some(&pl),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_main"),
                buffers: &[],
                compilation_options: Default::default(),
            },
            // outward faces wind counter-clockwise: culling front faces keeps the exit faces
            primitive: wgpu::PrimitiveState {
                front_face: wgpu::FrontFace::Ccw,
                cull_mode: Some(wgpu::Face::Front),
                ..Default::default()
            },
            depth_stencil: None,
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs_main"),
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: Some(wgpu::BlendState {
                        color: blend,
                        alpha: blend,
                    }),
                    write_mask: wgpu::ColorWrites::ALL,
                })],
                compilation_options: Default::default(),
            }),
            multiview_mask: None,
            cache: None,
        });
        PtRenderer {
            pipeline,
            layout,
            format,
        }
    }

    /// Uploads a mesh (centroid ordering only).
    pub fn upload(&self, ctx: &GpuContext, mesh: &RenderMesh) -> Result<TetDrawData, RenderError> {
        self.upload_with(ctx, mesh, false)
    }

    /// Uploads a mesh; with `mpvo`, also keeps its face adjacency for [`VisibilityOrder::Mpvo`].
    pub fn upload_with(
        &self,
        ctx: &GpuContext,
        mesh: &RenderMesh,
        mpvo: bool,
    ) -> Result<TetDrawData, RenderError> {
        let origin = mesh.center();
        let limit = ctx.device.limits().max_storage_buffer_binding_size;
        let needed = mesh.tets.len() as u64 * std::mem::size_of::<TetGeo>() as u64;
        if needed > limit {
            return Err(RenderError::TooLarge { needed, limit });
        }
        let positions: Vec<[f32; 4]> = mesh
            .positions
            .iter()
            .map(|p| {
                let r = DVec3::from_array(*p) - origin;
                [r.x as f32, r.y as f32, r.z as f32, 1.0]
            })
            .collect();
        let tets: Vec<[u32; 4]> = mesh.tets.clone();
        let geo: Vec<TetGeo> = (0..mesh.tets.len())
            .into_par_iter()
            .map(|t| {
                let (planes, g, c) = mesh.tet_geometry(t, origin);
                TetGeo {
                    planes: planes.map(|(n, d)| [n.x as f32, n.y as f32, n.z as f32, d as f32]),
                    grad: [g.x as f32, g.y as f32, g.z as f32, c as f32],
                }
            })
            .collect();
        let centroids = mesh
            .tets
            .iter()
            .map(|t| {
                let mut c = [0f32; 3];
                for &v in t {
                    for k in 0..3 {
                        c[k] += positions[v as usize][k] * 0.25;
                    }
                }
                c
            })
            .collect();
        let make = |label: &str, contents: &[u8]| {
            ctx.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: if contents.is_empty() {
                        &[0u8; 16]
                    } else {
                        contents
                    },
                    usage: wgpu::BufferUsages::STORAGE,
                })
        };
        let neighbors = mpvo.then(|| face_neighbors(&mesh.tets));
        let planes = geo.iter().map(|g| g.planes).collect();
        let positive = mesh
            .tets
            .iter()
            .map(|t| {
                let p = |k: usize| mesh.positions[t[k] as usize];
                tetwave_protocol::base::signed_volume(p(0), p(1), p(2), p(3)) >= 0.0
            })
            .collect();
        Ok(TetDrawData {
            neighbors,
            planes,
            positive,
            positions: make("positions", bytemuck::cast_slice(&positions)),
            tets: make("tets", bytemuck::cast_slice(&tets)),
            geo: make("geo", bytemuck::cast_slice(&geo)),
            centroids,
            origin,
            diagonal: mesh.diagonal(),
            far: 0.0,
            tet_count: mesh.tets.len() as u32,
        })
    }

    /// Renders one frame to an image (premultiplied colour over black).
    pub fn render(
        &self,
        ctx: &GpuContext,
        data: &TetDrawData,
        cam: &Camera,
        tf: &TransferFunction,
    ) -> Result<(Rgba8Image, FrameTimes), RenderError> {
        self.render_ordered(ctx, data, cam, tf, VisibilityOrder::Centroid)
    }

    /// Renders one frame with the given visibility order ([`VisibilityOrder::Mpvo`] needs data
    /// uploaded with adjacency, else it falls back to centroid order).
    pub fn render_ordered(
        &self,
        ctx: &GpuContext,
        data: &TetDrawData,
        cam: &Camera,
        tf: &TransferFunction,
        visibility: VisibilityOrder,
    ) -> Result<(Rgba8Image, FrameTimes), RenderError> {
        let t0 = std::time::Instant::now();
        let eye = cam.eye - data.origin;
        let eye32 = [eye.x as f32, eye.y as f32, eye.z as f32];
        let order: Vec<u32> = match (&data.neighbors, visibility) {
            (Some(nb), VisibilityOrder::Mpvo) => {
                mpvo_order(&data.planes, nb, &data.centroids, eye32).0
            }
            _ => centroid_order(&data.centroids, eye32),
        };
        let sort_ms = t0.elapsed().as_secs_f64() * 1e3;

        let device = &ctx.device;
        let far = (eye.length() + data.diagonal) * 2.0 + data.far;
        let vp = cam.view_proj(data.origin, far).as_mat4();
        let fwd = cam.forward();
        let s_res = tf
            .points
            .windows(2)
            .map(|w| (w[1].s - w[0].s) as f64)
            .filter(|d| *d > 0.0)
            .fold(1.0f64, f64::min)
            / 4.0;
        let globals = Globals {
            view_proj: vp.to_cols_array_2d(),
            eye: [eye32[0], eye32[1], eye32[2], cam.near as f32],
            fwd: [
                fwd.x as f32,
                fwd.y as f32,
                fwd.z as f32,
                (1.0 / data.diagonal) as f32,
            ],
            tf_info: [
                TF_TABLE_INTERVALS,
                (s_res as f32).to_bits(),
                (tf.max_extinction() as f32).to_bits(),
                0,
            ],
        };
        let tf_gpu: Vec<[f32; 4]> = (0..=TF_TABLE_INTERVALS)
            .map(|k| {
                let (rgb, ext) = tf.eval(k as f64 / TF_TABLE_INTERVALS as f64);
                [rgb[0] as f32, rgb[1] as f32, rgb[2] as f32, ext as f32]
            })
            .collect();
        let gbuf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("globals"),
            contents: bytemuck::bytes_of(&globals),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        // only the exit faces (the eye on the inner side of the face plane; none for a zero-volume
        // tet), outward winding counter-clockwise (reversed for negatively oriented tets); the
        // rasterizer still culls front faces, so a face misjudged at a grazing angle draws nothing
        let indices: Vec<[u32; 3]> = order
            .par_iter()
            .flat_map_iter(|&t| {
                let b = t * 4;
                let f = if data.positive[t as usize] {
                    FACES_POS
                } else {
                    FACES_NEG
                };
                let pl = &data.planes[t as usize];
                (0..4).filter_map(move |i| {
                    let [nx, ny, nz, w] = pl[i];
                    let c = w - (nx * eye32[0] + ny * eye32[1] + nz * eye32[2]);
                    (c > 0.0).then(|| [b + f[3 * i], b + f[3 * i + 1], b + f[3 * i + 2]])
                })
            })
            .collect();
        let ibuf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("faces"),
            contents: if indices.is_empty() {
                &[0u8; 12]
            } else {
                bytemuck::cast_slice(&indices)
            },
            usage: wgpu::BufferUsages::INDEX,
        });
        let tfbuf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("tf"),
            contents: bytemuck::cast_slice(&tf_gpu),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("pt"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: gbuf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: data.positions.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: data.tets.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: data.geo.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: tfbuf.as_entire_binding(),
                },
            ],
        });
        let (w, h) = (cam.width, cam.height);
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("target"),
            size: wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: self.format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&Default::default());
        let texel = match self.format {
            wgpu::TextureFormat::Rgba32Float => 16,
            wgpu::TextureFormat::Rgba16Float => 8,
            _ => 4,
        };
        let bpr = (w * texel).div_ceil(256) * 256;
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: (bpr * h) as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut enc = device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("pt"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            if !indices.is_empty() {
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, &bind, &[]);
                pass.set_index_buffer(ibuf.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..3 * indices.len() as u32, 0, 0..1);
            }
        }
        enc.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &readback,
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
        let t1 = std::time::Instant::now();
        ctx.queue.submit([enc.finish()]);
        let slice = readback.slice(..);
        slice.map_async(wgpu::MapMode::Read, |_| {});
        device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        let gpu_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = std::time::Instant::now();
        let bytes = slice
            .get_mapped_range()
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        let mut px = Vec::with_capacity((w * h) as usize);
        for y in 0..h {
            let row = &bytes[(y * bpr) as usize..];
            for x in 0..w as usize {
                let c: [f64; 4] = match texel {
                    16 => {
                        let f: &[f32] = bytemuck::cast_slice(&row[x * 16..x * 16 + 16]);
                        std::array::from_fn(|k| f[k] as f64)
                    }
                    8 => {
                        let f: &[u16] = bytemuck::cast_slice(&row[x * 8..x * 8 + 8]);
                        std::array::from_fn(|k| half_to_f64(f[k]))
                    }
                    _ => std::array::from_fn(|k| row[x * 4 + k] as f64 / 255.0),
                };
                px.push(c.map(|v| if v.is_finite() { v } else { f64::NAN }));
            }
        }
        drop(bytes);
        readback.unmap();
        let img = Rgba8Image::from_f64(w, h, &px);
        let readback_ms = t2.elapsed().as_secs_f64() * 1e3;
        Ok((
            img,
            FrameTimes {
                sort_ms,
                gpu_ms,
                readback_ms,
                total_ms: t0.elapsed().as_secs_f64() * 1e3,
            },
        ))
    }
}

/// IEEE half → f64.
fn half_to_f64(h: u16) -> f64 {
    let s = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let e = ((h >> 10) & 0x1f) as i32;
    let m = (h & 0x3ff) as f64;
    match e {
        0 => s * m * 2f64.powi(-24),
        31 => {
            if m == 0.0 {
                s * f64::INFINITY
            } else {
                f64::NAN
            }
        }
        _ => s * (1.0 + m / 1024.0) * 2f64.powi(e - 15),
    }
}
