//! Projected tetrahedra: [`PtRenderer`] holds the pipeline (long-lived); [`TetDrawData`] holds one
//! mesh's GPU buffers (valid until the mesh changes); each frame sorts the tets back to front and
//! draws each tet's exit faces (indexed, 4 vertices per tet), with no per-frame CPU geometry.
//!
//! **Visibility order.** Tets are sorted by the distance from the eye to their centroid. This is
//! exact for a ray only if no two tets it crosses are mis-ordered; centroid order can fail for tets of
//! very different sizes next to each other or long slivers (a small tet whose centroid is farther
//! than a large neighbour's but which lies in front of it along some rays), and no order exists when
//! the "in front of" relation has a cycle. Errors show as small blending differences on the affected
//! pixels; the image tests bound them against the exact reference.

use super::order::{centroid_order, face_neighbors, mpvo_order};
use super::sort::{GpuSort, SortBuffers};
use super::{GpuContext, RenderError};
use bytemuck::{Pod, Zeroable};
use glam::DVec3;
use rayon::prelude::*;
use tetwave_protocol::view::{Camera, Orbit};
use tetwave_render::image_metrics::Rgba8Image;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;
use wgpu::util::DeviceExt;

/// How tets are ordered back to front each frame (see [`super::order`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum VisibilityOrder {
    /// Sort by eye-to-centroid distance (approximate).
    #[default]
    Centroid,
    /// Williams' MPVO over face adjacency (exact for convex, acyclic meshes).
    Mpvo,
    /// Centroid order computed on the GPU (`shaders/sort.wgsl`: a compute pass of depth keys and
    /// a radix sort); the CPU only orders the chunks.
    Gpu,
}

const SHADER: &str = include_str!("../../shaders/pt.wgsl");

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
    /// The level set `φ(x) = xyz·x + w` (`(0, 0, 0, 1)` without one: nothing is clipped).
    lset: [f32; 4],
}

/// Intervals of the transfer-function table the fragment stage interpolates (a table lookup costs
/// one interpolation instead of a search over the points; the table differs from the piecewise-linear
/// function only inside the intervals that contain a breakpoint). `TF_TABLE_INTERVALS + 1` entries of
/// 16 bytes fill the 64 KiB uniform binding every adapter allows (`shaders/pt.wgsl` declares that
/// size).
pub const TF_TABLE_INTERVALS: u32 = 4095;

/// Bytes of the transfer-function table (one uniform binding).
pub const TF_TABLE_BYTES: u64 = 16 * (TF_TABLE_INTERVALS as u64 + 1);

/// Tets whose normalized scalar range is at most this many sub-step resolutions (a quarter of the
/// transfer function's narrowest piece) are drawn with the loop-free two-sub-step fragment shader
/// (`fs_main`), others with the adaptive `fs_steps`. 4 keeps every tet of a fine mesh on the fast
/// path, where two exact sub-steps are at least as close to the reference as the adaptive count.
const FAST_MAX_STEPS: f32 = 4.0;

/// At most this many pipeline switches per frame; beyond, every tet is drawn with `fs_steps`.
const MAX_RUNS: usize = 256;

/// Corner indices of the 4 faces of a positively oriented tet, each wound counter-clockwise seen from
/// outside (face `i` is opposite corner `i`).
const FACES_POS: [u32; 12] = [1, 2, 3, 0, 3, 2, 0, 1, 3, 0, 2, 1];
/// The same for a negatively oriented tet (every face reversed).
const FACES_NEG: [u32; 12] = [1, 3, 2, 0, 2, 3, 0, 3, 1, 0, 1, 2];

/// Precision of the colour accumulation target (blending happens in this format).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
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

/// Pipelines and layouts: create once per device and format.
pub struct PtRenderer {
    /// Two sub-steps per tet, loop-free (`fs_main`).
    pipeline: wgpu::RenderPipeline,
    /// Adaptive sub-steps (`fs_steps`), for tets with a large scalar range.
    pipeline_steps: wgpu::RenderPipeline,
    /// The same two drawing every face of each tet in the GPU's order (`vs_sorted`).
    sorted: wgpu::RenderPipeline,
    sorted_steps: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    /// Group 1 of the sorted pipelines: the order and the orientation bits.
    order_layout: wgpu::BindGroupLayout,
    gpu_sort: GpuSort,
    format: wgpu::TextureFormat,
    /// The uniform buffers: per-frame globals and the transfer-function table (written while the
    /// frame holds `cache`).
    globals: wgpu::Buffer,
    tf_table: wgpu::Buffer,
    /// Per-frame objects kept between frames (held for the whole frame).
    cache: std::sync::Mutex<FrameCache>,
}

/// Objects a frame needs that outlive it: the target and readback for the last image size; the
/// transfer-function table is rewritten only when the function changes.
#[derive(Default)]
struct FrameCache {
    tf_points: Option<Vec<tetwave_render::transfer::TfPoint>>,
    target: Option<(u32, u32, wgpu::Texture, wgpu::TextureView, wgpu::Buffer)>,
}

/// One mesh on the GPU. Valid for the mesh it was built from; positions are relative to `origin`.
///
/// **Chunks.** A mesh whose per-tet data exceeds one storage binding of the adapter is split into
/// chunks that each fit (`ChunkTree`: a k-d tree of the tets' centroids, split at the median of
/// the longest axis until every leaf fits), each with its own buffers of the vertices it uses.
/// A frame draws the chunks far to near (the k-d tree's order for the eye, exact between the
/// cells of the tree) and each chunk's tets in the chosen order within it: one visibility order
/// across chunks, drawn with one bind group per chunk. The only size limit is memory. The tets are
/// held in chunk order (a permutation of the mesh's), which every per-tet array below follows.
pub struct TetDrawData {
    /// Face adjacency, present when uploaded for MPVO ordering (one chunk only: across chunks the
    /// order is the tree's).
    neighbors: Option<Vec<[u32; 4]>>,
    /// CPU copies of the outward face planes (`n·x = w`, relative to `origin`): each frame draws
    /// only the faces the eye sees from inside (the exit faces), and MPVO orders by them.
    planes: Vec<[[f32; 4]; 4]>,
    /// Per tet: positively oriented (decides the winding of its faces).
    positive: Vec<bool>,
    /// Per tet: range (max − min) of the normalized scalar over its corners.
    s_range: Vec<f32>,
    /// The largest of `s_range`.
    max_s_range: f32,
    chunks: Vec<Chunk>,
    tree: ChunkTree,
    centroids: Vec<[f32; 3]>,
    origin: DVec3,
    diagonal: f64,
    far: f64,
    pub tet_count: u32,
}

/// Tets `range` of a [`TetDrawData`] (in its chunk order) on the GPU, with the vertices they use:
/// `tets` holds indices into this chunk's `positions`.
struct Chunk {
    range: std::ops::Range<u32>,
    positions: wgpu::Buffer,
    tets: wgpu::Buffer,
    geo: wgpu::Buffer,
    /// A bit per tet, set when it is negatively oriented ([`VisibilityOrder::Gpu`]'s draw).
    negative: wgpu::Buffer,
    /// [`VisibilityOrder::Gpu`]'s buffers, made when first drawn in that order.
    sort: std::sync::OnceLock<SortBuffers>,
}

/// The k-d tree whose leaves are the chunks: node 0 is the root; a split sends centroids below
/// `at` on `axis` to `below`, the others to `above`.
#[derive(Debug, Clone)]
enum KdNode {
    Leaf(u32),
    Split {
        axis: usize,
        at: f32,
        below: u32,
        above: u32,
    },
}

/// The chunks' k-d tree ([`TetDrawData`]).
#[derive(Debug, Clone)]
struct ChunkTree(Vec<KdNode>);

impl ChunkTree {
    /// Splits `ids` (tets, by centroid) at the median of the longest axis until each part holds at
    /// most `most`; `ids` is left in leaf order, and the leaves' ranges of it are returned in order.
    fn build(
        ids: &mut [u32],
        centroids: &[[f32; 3]],
        most: usize,
    ) -> (Self, Vec<std::ops::Range<u32>>) {
        let mut tree = ChunkTree(Vec::new());
        let mut leaves = Vec::new();
        tree.split(ids, 0, centroids, most.max(1), &mut leaves);
        (tree, leaves)
    }

    fn split(
        &mut self,
        ids: &mut [u32],
        offset: u32,
        centroids: &[[f32; 3]],
        most: usize,
        leaves: &mut Vec<std::ops::Range<u32>>,
    ) -> u32 {
        let me = self.0.len() as u32;
        if ids.len() <= most {
            self.0.push(KdNode::Leaf(leaves.len() as u32));
            leaves.push(offset..offset + ids.len() as u32);
            return me;
        }
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for &t in ids.iter() {
            let c = centroids[t as usize];
            for a in 0..3 {
                lo[a] = lo[a].min(c[a]);
                hi[a] = hi[a].max(c[a]);
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
            .unwrap_or(0);
        let mid = ids.len() / 2;
        let key = |t: &u32| centroids[*t as usize][axis];
        ids.select_nth_unstable_by(mid, |a, b| key(a).total_cmp(&key(b)));
        let at = key(&ids[mid]);
        self.0.push(KdNode::Leaf(u32::MAX)); // placeholder, set below
        let (first, second) = ids.split_at_mut(mid);
        let below = self.split(first, offset, centroids, most, leaves);
        let above = self.split(second, offset + mid as u32, centroids, most, leaves);
        self.0[me as usize] = KdNode::Split {
            axis,
            at,
            below,
            above,
        };
        me
    }

    /// The chunks far to near from `eye`: at each split the side without the eye first.
    fn far_to_near(&self, eye: [f32; 3]) -> Vec<u32> {
        let mut out = Vec::new();
        let mut stack = vec![0u32];
        while let Some(n) = stack.pop() {
            match self.0[n as usize] {
                KdNode::Leaf(c) => out.push(c),
                KdNode::Split {
                    axis,
                    at,
                    below,
                    above,
                } => {
                    // pushed near first: popped (drawn) far first
                    let (near, far) = if eye[axis] < at {
                        (below, above)
                    } else {
                        (above, below)
                    };
                    stack.push(near);
                    stack.push(far);
                }
            }
        }
        out
    }
}

/// The exit faces of one chunk's tets in drawing order ([`FramePlan`]), with runs of (adaptive
/// shader, triangle count).
struct PartPlan {
    chunk: u32,
    draw: PartPlanDraw,
}

/// How a chunk is drawn.
enum PartPlanDraw {
    /// The exit faces listed, with runs of (adaptive shader, triangle count).
    Indexed {
        indices: Vec<[u32; 3]>,
        runs: Vec<(bool, u32)>,
    },
    /// Every face in the GPU's order, all with the adaptive shader or none.
    Sorted { slow: bool },
}

impl TetDrawData {
    /// How many chunks the mesh is drawn in (1 when it fits one storage binding).
    pub fn chunks(&self) -> usize {
        self.chunks.len()
    }
}

/// The CPU half of a frame's draw data ([`PtRenderer::plan`]): the exit faces in visibility
/// order, chunk by chunk, the shader runs and the uniforms, for [`PtRenderer::finish`].
pub struct FramePlan {
    parts: Vec<PartPlan>,
    globals: Globals,
    sort_ms: f64,
}

/// One chunk's share of a [`FrameDraw`].
struct FramePart {
    chunk: u32,
    triangles: u32,
    draw: FramePartDraw,
}

enum FramePartDraw {
    /// Exit faces by index, with runs of (adaptive shader, triangle count) in drawing order.
    Indexed {
        indices: wgpu::Buffer,
        runs: Vec<(bool, u32)>,
    },
    /// Every face (4 triangles a tet) in the order the GPU sorted, bound as group 1.
    Sorted { order: wgpu::BindGroup, slow: bool },
}

/// One frame's draw data ([`PtRenderer::prepare`]): the exit faces of the tets in visibility
/// order and the bindings to draw them with. Valid for the frame it was prepared for, until the
/// renderer prepares another.
pub struct FrameDraw {
    parts: Vec<FramePart>,
    triangles: u32,
    /// One bind group per chunk of the data.
    binds: Vec<wgpu::BindGroup>,
    sort_ms: f64,
}

impl FrameDraw {
    /// Triangles the frame draws (exit faces; a tet has one to three).
    pub fn triangles(&self) -> u32 {
        self.triangles
    }

    /// Milliseconds its visibility sort took.
    pub fn sort_ms(&self) -> f64 {
        self.sort_ms
    }
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
        let format = match acc {
            Accumulation::Best if ctx.float32_blend => wgpu::TextureFormat::Rgba32Float,
            Accumulation::U8 => wgpu::TextureFormat::Rgba8Unorm,
            _ => wgpu::TextureFormat::Rgba16Float,
        };
        Self::with_format(ctx, format)
    }

    /// The renderer for colour targets of `format` (a blendable colour format, e.g. a window
    /// surface's): what [`Self::draw_into`] and [`Self::draw`] need their target to be.
    pub fn with_format(ctx: &GpuContext, format: wgpu::TextureFormat) -> Self {
        let device = &ctx.device;
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
                wgpu::BindGroupLayoutEntry {
                    binding: 5,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
            ],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("pt"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let order_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("pt order"),
            entries: &[
                storage(0, wgpu::ShaderStages::VERTEX),
                storage(1, wgpu::ShaderStages::VERTEX),
            ],
        });
        let pl_sorted = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("pt sorted"),
            bind_group_layouts: &[Some(&layout), Some(&order_layout)],
            immediate_size: 0,
        });
        let blend = wgpu::BlendComponent {
            src_factor: wgpu::BlendFactor::One,
            dst_factor: wgpu::BlendFactor::OneMinusSrcAlpha,
            operation: wgpu::BlendOperation::Add,
        };
        let make_pipeline = |vs: &str, pl: &wgpu::PipelineLayout, fs: &str| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("pt"),
                layout: Some(pl),
                vertex: wgpu::VertexState {
                    module: &module,
                    entry_point: Some(vs),
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
                    entry_point: Some(fs),
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
            })
        };
        let uniform = |label: &str, size: usize| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        PtRenderer {
            pipeline: make_pipeline("vs_main", &pl, "fs_main"),
            pipeline_steps: make_pipeline("vs_main", &pl, "fs_steps"),
            sorted: make_pipeline("vs_sorted", &pl_sorted, "fs_main"),
            sorted_steps: make_pipeline("vs_sorted", &pl_sorted, "fs_steps"),
            order_layout,
            gpu_sort: GpuSort::new(device),
            globals: uniform("globals", std::mem::size_of::<Globals>()),
            tf_table: uniform("tf", TF_TABLE_BYTES as usize),
            cache: Default::default(),
            layout,
            format,
        }
    }

    /// The most tets one chunk of this context holds: one storage binding (and one buffer) of
    /// per-tet geometry. A larger mesh is drawn in several chunks ([`TetDrawData`]).
    pub fn chunk_tets(ctx: &GpuContext) -> u64 {
        let l = ctx.device.limits();
        l.max_storage_buffer_binding_size.min(l.max_buffer_size)
            / std::mem::size_of::<TetGeo>() as u64
    }

    /// Uploads a mesh (centroid ordering only).
    pub fn upload(&self, ctx: &GpuContext, mesh: &RenderMesh) -> Result<TetDrawData, RenderError> {
        self.upload_with(ctx, mesh, false)
    }

    /// Uploads a mesh; with `mpvo`, also keeps its face adjacency for [`VisibilityOrder::Mpvo`].
    /// A mesh of more than [`Self::chunk_tets`] tets goes up in chunks.
    pub fn upload_with(
        &self,
        ctx: &GpuContext,
        mesh: &RenderMesh,
        mpvo: bool,
    ) -> Result<TetDrawData, RenderError> {
        self.upload_in_chunks(ctx, mesh, mpvo, Self::chunk_tets(ctx))
    }

    /// [`Self::upload_with`] in chunks of at most `most` tets (at most [`Self::chunk_tets`]; a
    /// smaller bound draws a small mesh the way a large one is drawn).
    pub fn upload_in_chunks(
        &self,
        ctx: &GpuContext,
        mesh: &RenderMesh,
        mpvo: bool,
        most: u64,
    ) -> Result<TetDrawData, RenderError> {
        let origin = mesh.center();
        let n = mesh.tets.len();
        if n as u64 >= u32::MAX as u64 / 4 {
            // vertex indices of the draw are 4 × tet + corner within a chunk, but tets are
            // counted in u32 across the mesh
            return Err(RenderError::TooLarge {
                needed: n as u64,
                limit: u32::MAX as u64 / 4,
            });
        }
        let most = most.clamp(1, Self::chunk_tets(ctx).max(1)) as usize;
        let rel: Vec<[f32; 3]> = mesh
            .positions
            .par_iter()
            .map(|p| {
                let r = DVec3::from_array(*p) - origin;
                [r.x as f32, r.y as f32, r.z as f32]
            })
            .collect();
        let centroid = |t: &[u32; 4]| {
            let mut c = [0f32; 3];
            for &v in t {
                for k in 0..3 {
                    c[k] += rel[v as usize][k] * 0.25;
                }
            }
            c
        };
        // chunk order: the mesh's own order when it fits in one chunk
        let mut ids: Vec<u32> = (0..n as u32).collect();
        let (tree, ranges) = if n <= most {
            let whole = std::iter::once(0..n as u32).collect();
            (ChunkTree(vec![KdNode::Leaf(0)]), whole)
        } else {
            let c: Vec<[f32; 3]> = mesh.tets.par_iter().map(centroid).collect();
            ChunkTree::build(&mut ids, &c, most)
        };
        let tets: Vec<[u32; 4]> = ids.iter().map(|&t| mesh.tets[t as usize]).collect();
        // per-tet geometry is made a chunk at a time and dropped once uploaded; the CPU keeps the
        // face planes (exit faces, MPVO)
        let geo_of = |ids: &[u32]| -> Vec<TetGeo> {
            ids.par_iter()
                .map(|&t| {
                    let t = t as usize;
                    let (planes, g, c) = mesh.tet_geometry(t, origin);
                    let (lg, lc) = mesh.tet_levelset(t, origin);
                    TetGeo {
                        planes: planes.map(|(n, d)| [n.x as f32, n.y as f32, n.z as f32, d as f32]),
                        grad: [g.x as f32, g.y as f32, g.z as f32, c as f32],
                        lset: [lg.x as f32, lg.y as f32, lg.z as f32, lc as f32],
                    }
                })
                .collect()
        };
        let mut planes: Vec<[[f32; 4]; 4]> = Vec::with_capacity(n);
        let centroids: Vec<[f32; 3]> = tets.par_iter().map(centroid).collect();
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
        // each chunk with the vertices its tets use, renumbered in first-use order
        let mut local = vec![u32::MAX; mesh.positions.len()];
        let chunks = ranges
            .into_iter()
            .map(|range| {
                let mine = &tets[range.start as usize..range.end as usize];
                let mut used: Vec<u32> = Vec::new();
                let tets_local: Vec<[u32; 4]> = mine
                    .iter()
                    .map(|t| {
                        t.map(|v| {
                            let l = &mut local[v as usize];
                            if *l == u32::MAX {
                                *l = used.len() as u32;
                                used.push(v);
                            }
                            *l
                        })
                    })
                    .collect();
                let positions: Vec<[f32; 4]> = used
                    .iter()
                    .map(|&v| {
                        local[v as usize] = u32::MAX;
                        let [x, y, z] = rel[v as usize];
                        [x, y, z, 1.0]
                    })
                    .collect();
                let g = geo_of(&ids[range.start as usize..range.end as usize]);
                planes.extend(g.iter().map(|g| g.planes));
                let mut negative = vec![0u32; mine.len().div_ceil(32)];
                for (i, t) in mine.iter().enumerate() {
                    let p = |k: usize| mesh.positions[t[k] as usize];
                    if tetwave_protocol::base::signed_volume(p(0), p(1), p(2), p(3)) < 0.0 {
                        negative[i / 32] |= 1 << (i % 32);
                    }
                }
                Chunk {
                    positions: make("positions", bytemuck::cast_slice(&positions)),
                    tets: make("tets", bytemuck::cast_slice(&tets_local)),
                    geo: make("geo", bytemuck::cast_slice(&g)),
                    negative: make("negative", bytemuck::cast_slice(&negative)),
                    sort: std::sync::OnceLock::new(),
                    range,
                }
            })
            .collect::<Vec<_>>();
        if chunks.len() > 1 {
            tracing::info!(
                tets = n,
                chunks = chunks.len(),
                "the mesh is drawn in chunks of at most {most} tets"
            );
            if mpvo {
                tracing::warn!(
                    "MPVO orders the tets of one chunk: across {} chunks the order is the chunks' \
                     (far to near), each chunk's tets by centroid",
                    chunks.len()
                );
            }
        }
        let neighbors = (mpvo && chunks.len() == 1).then(|| face_neighbors(&tets));
        let s_range: Vec<f32> = tets
            .par_iter()
            .map(|t| {
                let s = t.map(|v| mesh.normalize(mesh.values[v as usize] as f64));
                let (lo, hi) = s
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
                        (lo.min(x), hi.max(x))
                    });
                (hi - lo) as f32
            })
            .collect();
        let max_s_range = s_range.iter().copied().fold(0.0, f32::max);
        let positive = tets
            .par_iter()
            .map(|t| {
                let p = |k: usize| mesh.positions[t[k] as usize];
                tetwave_protocol::base::signed_volume(p(0), p(1), p(2), p(3)) >= 0.0
            })
            .collect();
        Ok(TetDrawData {
            neighbors,
            planes,
            positive,
            s_range,
            max_s_range,
            chunks,
            tree,
            centroids,
            origin,
            diagonal: mesh.diagonal(),
            far: 0.0,
            tet_count: n as u32,
        })
    }

    /// Draws two one-tet meshes (one through each fragment pipeline), so that the driver compiles
    /// its shader variants now rather than during the first real frame.
    pub fn warm_up(&self, ctx: &GpuContext, tf: &TransferFunction) -> Result<(), RenderError> {
        let corners = vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let cam = Orbit {
            target: DVec3::splat(0.25),
            distance: 3.0,
            azimuth: 30.0,
            elevation: 20.0,
            fov: 40.0,
        }
        .camera(16, 16);
        // a constant field takes the two-sub-step shader, a full-range one the adaptive shader
        for values in [vec![0.5; 4], vec![0.0, 1.0, 0.5, 0.25]] {
            let tet = RenderMesh::new(corners.clone(), vec![[0, 1, 2, 3]], values);
            let data = self.upload(ctx, &tet)?;
            self.render(ctx, &data, &cam, tf)?;
        }
        Ok(())
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

    /// The colour format every target of this renderer must have.
    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }

    /// Builds one frame's draw data: the tets sorted for `cam`'s eye ([`VisibilityOrder::Mpvo`]
    /// needs data uploaded with adjacency, else centroid order is used), their exit faces, and the
    /// camera and transfer function written to the renderer's uniforms. Valid until the next
    /// `prepare` on this renderer: draw it before preparing another frame. [`Self::plan`] then
    /// [`Self::finish`], which a caller may run apart (the plan on another thread).
    pub fn prepare(
        &self,
        ctx: &GpuContext,
        data: &TetDrawData,
        cam: &Camera,
        tf: &TransferFunction,
        visibility: VisibilityOrder,
    ) -> FrameDraw {
        self.finish(ctx, data, tf, Self::plan(data, cam, tf, visibility))
    }

    /// The CPU half of [`Self::prepare`] (no GPU access, any thread): the visibility order, the
    /// exit faces in that order, the shader runs and the frame's uniforms.
    pub fn plan(
        data: &TetDrawData,
        cam: &Camera,
        tf: &TransferFunction,
        visibility: VisibilityOrder,
    ) -> FramePlan {
        let t0 = std::time::Instant::now();
        let eye = cam.eye - data.origin;
        let eye32 = [eye.x as f32, eye.y as f32, eye.z as f32];
        // per chunk far to near, its tets (indices into the data's chunk order) back to front
        // (the GPU's order: the chunks alone, their tets left to the GPU)
        let ordered: Vec<(u32, Vec<u32>)> = match (&data.neighbors, visibility) {
            (Some(nb), VisibilityOrder::Mpvo) => {
                vec![(0, mpvo_order(&data.planes, nb, &data.centroids, eye32).0)]
            }
            (_, VisibilityOrder::Gpu) => data
                .tree
                .far_to_near(eye32)
                .into_iter()
                .map(|c| (c, Vec::new()))
                .collect(),
            _ => data
                .tree
                .far_to_near(eye32)
                .into_iter()
                .map(|c| {
                    let r = &data.chunks[c as usize].range;
                    let within =
                        centroid_order(&data.centroids[r.start as usize..r.end as usize], eye32);
                    (c, within.into_iter().map(|t| t + r.start).collect())
                })
                .collect(),
        };
        let sort_ms = t0.elapsed().as_secs_f64() * 1e3;
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
        // only the exit faces (the eye on the inner side of the face plane; none for a zero-volume
        // tet), outward winding counter-clockwise (reversed for negatively oriented tets); the
        // rasterizer still culls front faces, so a face misjudged at a grazing angle draws nothing.
        // A face's vertices are 4 × (the tet's index in its chunk) + corner.
        let exit_faces = |t: u32, first: u32| {
            let b = (t - first) * 4;
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
        };
        // tets whose scalar range needs more than FAST_MAX_STEPS sub-steps are drawn with the
        // adaptive shader: runs of (adaptive, triangle count) in drawing order
        let fast_limit = FAST_MAX_STEPS * s_res as f32;
        let part = |(chunk, order): (u32, Vec<u32>)| {
            let first = data.chunks[chunk as usize].range.start;
            if visibility == VisibilityOrder::Gpu {
                let slow = data.max_s_range > fast_limit;
                return PartPlan {
                    chunk,
                    draw: PartPlanDraw::Sorted { slow },
                };
            }
            if data.max_s_range <= fast_limit {
                let indices: Vec<[u32; 3]> = order
                    .par_iter()
                    .flat_map_iter(|&t| exit_faces(t, first))
                    .collect();
                let n = indices.len() as u32;
                return PartPlan {
                    chunk,
                    draw: PartPlanDraw::Indexed {
                        indices,
                        runs: vec![(false, n)],
                    },
                };
            }
            let mut indices = Vec::with_capacity(order.len() * 2);
            let mut runs: Vec<(bool, u32)> = Vec::new();
            for &t in &order {
                let before = indices.len();
                indices.extend(exit_faces(t, first));
                let added = (indices.len() - before) as u32;
                // (past MAX_RUNS the part is drawn as one adaptive run: no more runs to track)
                if added == 0 || runs.len() > MAX_RUNS {
                    continue;
                }
                let slow = data.s_range[t as usize] > fast_limit;
                match runs.last_mut() {
                    Some((k, n)) if *k == slow => *n += added,
                    _ => runs.push((slow, added)),
                }
            }
            if runs.len() > MAX_RUNS {
                let n = indices.len() as u32;
                runs = vec![(true, n)];
            }
            PartPlan {
                chunk,
                draw: PartPlanDraw::Indexed { indices, runs },
            }
        };
        FramePlan {
            parts: ordered.into_iter().map(part).collect(),
            globals,
            sort_ms,
        }
    }

    /// The GPU half of [`Self::prepare`]: writes `plan`'s uniforms and `tf`'s table (the one the
    /// plan was made with) to the renderer, uploads its faces. `data` must be the plan's.
    pub fn finish(
        &self,
        ctx: &GpuContext,
        data: &TetDrawData,
        tf: &TransferFunction,
        plan: FramePlan,
    ) -> FrameDraw {
        let FramePlan {
            parts,
            globals,
            sort_ms,
        } = plan;
        let device = &ctx.device;
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        let (gbuf, tfbuf) = (&self.globals, &self.tf_table);
        ctx.queue
            .write_buffer(gbuf, 0, bytemuck::bytes_of(&globals));
        if cache.tf_points.as_ref() != Some(&tf.points) {
            let tf_gpu: Vec<[f32; 4]> = (0..=TF_TABLE_INTERVALS)
                .map(|k| {
                    let (rgb, ext) = tf.eval(k as f64 / TF_TABLE_INTERVALS as f64);
                    [rgb[0] as f32, rgb[1] as f32, rgb[2] as f32, ext as f32]
                })
                .collect();
            ctx.queue
                .write_buffer(tfbuf, 0, bytemuck::cast_slice(&tf_gpu));
            cache.tf_points = Some(tf.points.clone());
        }
        // the GPU's order: every sorted chunk's sort, submitted before any draw of the frame
        let eye = globals.eye;
        let mut sorts: Option<wgpu::CommandEncoder> = None;
        let parts: Vec<FramePart> = parts
            .into_iter()
            .map(|p| {
                let chunk = &data.chunks[p.chunk as usize];
                match p.draw {
                    PartPlanDraw::Indexed { indices, runs } => FramePart {
                        chunk: p.chunk,
                        triangles: indices.len() as u32,
                        draw: FramePartDraw::Indexed {
                            indices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                                label: Some("faces"),
                                contents: if indices.is_empty() {
                                    &[0u8; 12]
                                } else {
                                    bytemuck::cast_slice(&indices)
                                },
                                usage: wgpu::BufferUsages::INDEX,
                            }),
                            runs,
                        },
                    },
                    PartPlanDraw::Sorted { slow } => {
                        let r = chunk.range.start as usize..chunk.range.end as usize;
                        let b = chunk.sort.get_or_init(|| {
                            let c: Vec<[f32; 4]> = data.centroids[r]
                                .iter()
                                .map(|c| [c[0], c[1], c[2], 1.0])
                                .collect();
                            self.gpu_sort.buffers(device, &c)
                        });
                        let enc = sorts.get_or_insert_with(|| {
                            device.create_command_encoder(&Default::default())
                        });
                        self.gpu_sort
                            .encode(&ctx.queue, enc, b, [eye[0], eye[1], eye[2]]);
                        let order = device.create_bind_group(&wgpu::BindGroupDescriptor {
                            label: Some("pt order"),
                            layout: &self.order_layout,
                            entries: &[
                                wgpu::BindGroupEntry {
                                    binding: 0,
                                    resource: b.order().as_entire_binding(),
                                },
                                wgpu::BindGroupEntry {
                                    binding: 1,
                                    resource: chunk.negative.as_entire_binding(),
                                },
                            ],
                        });
                        FramePart {
                            chunk: p.chunk,
                            triangles: 4 * (chunk.range.end - chunk.range.start),
                            draw: FramePartDraw::Sorted { order, slow },
                        }
                    }
                }
            })
            .collect();
        if let Some(enc) = sorts {
            ctx.queue.submit([enc.finish()]);
        }
        let binds = data
            .chunks
            .iter()
            .map(|c| {
                device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("pt"),
                    layout: &self.layout,
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: gbuf.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 1,
                            resource: c.positions.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: c.tets.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 3,
                            resource: c.geo.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 5,
                            resource: tfbuf.as_entire_binding(),
                        },
                    ],
                })
            })
            .collect();
        FrameDraw {
            triangles: parts.iter().map(|p| p.triangles).sum(),
            parts,
            binds,
            sort_ms,
        }
    }

    /// Records `frame` into a render pass of the caller's (e.g. a window's), whose colour target
    /// has [`Self::format`] and holds premultiplied colour: the tets blend over what is there.
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>, frame: &FrameDraw) {
        self.draw_range(pass, frame, 0..frame.triangles);
    }

    /// Records triangles `tris` of `frame` (in drawing order) into a render pass: drawing a frame's
    /// triangles in consecutive ranges, in order, into one target makes the image one
    /// [`Self::draw`] makes (blending is applied in the same order), so a slow frame can be
    /// spread over several submissions.
    pub fn draw_range(
        &self,
        pass: &mut wgpu::RenderPass<'_>,
        frame: &FrameDraw,
        tris: std::ops::Range<u32>,
    ) {
        let end = tris.end.min(frame.triangles);
        if tris.start >= end {
            return;
        }
        // `first`: the frame's triangles before the current run
        let mut first = 0;
        for part in &frame.parts {
            let part_end = first + part.triangles;
            if part_end <= tris.start || first >= end {
                first = part_end;
                continue;
            }
            pass.set_bind_group(0, &frame.binds[part.chunk as usize], &[]);
            let base = first;
            let runs = match &part.draw {
                FramePartDraw::Indexed { indices, runs } => {
                    pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
                    runs
                }
                FramePartDraw::Sorted { order, slow } => {
                    pass.set_bind_group(1, order, &[]);
                    pass.set_pipeline(if *slow {
                        &self.sorted_steps
                    } else {
                        &self.sorted
                    });
                    let (a, b) = (first.max(tris.start), part_end.min(end));
                    pass.draw(3 * (a - base)..3 * (b - base), 0..1);
                    first = part_end;
                    continue;
                }
            };
            for &(slow, n) in runs {
                let (a, b) = (first.max(tris.start), (first + n).min(end));
                first += n;
                if a >= b {
                    continue;
                }
                pass.set_pipeline(if slow {
                    &self.pipeline_steps
                } else {
                    &self.pipeline
                });
                pass.draw_indexed(3 * (a - base)..3 * (b - base), 0, 0..1);
            }
            first = part_end;
        }
    }

    /// Draws triangles `tris` of `frame` into a texture view of the caller's (of
    /// [`Self::format`]), cleared to transparent black first when `clear`, and submits it; see
    /// [`Self::draw_range`]. `frame` must be the last one this renderer prepared.
    pub fn draw_range_into(
        &self,
        ctx: &GpuContext,
        frame: &FrameDraw,
        tris: std::ops::Range<u32>,
        target: &wgpu::TextureView,
        clear: bool,
    ) {
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = begin_pass(&mut enc, target, clear);
            self.draw_range(&mut pass, frame, tris);
        }
        ctx.queue.submit([enc.finish()]);
    }

    /// Draws one frame into a texture view of the caller's (of [`Self::format`]), cleared to
    /// transparent black first when `clear`, and submits it. The image is the one
    /// [`Self::render_ordered`] reads back for the same arguments.
    #[allow(clippy::too_many_arguments)]
    pub fn draw_into(
        &self,
        ctx: &GpuContext,
        data: &TetDrawData,
        cam: &Camera,
        tf: &TransferFunction,
        visibility: VisibilityOrder,
        target: &wgpu::TextureView,
        clear: bool,
    ) -> FrameTimes {
        let t0 = std::time::Instant::now();
        let frame = self.prepare(ctx, data, cam, tf, visibility);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        self.encode_pass(&mut enc, target, clear, &frame);
        let t1 = std::time::Instant::now();
        ctx.queue.submit([enc.finish()]);
        FrameTimes {
            sort_ms: frame.sort_ms,
            gpu_ms: t1.elapsed().as_secs_f64() * 1e3,
            readback_ms: 0.0,
            total_ms: t0.elapsed().as_secs_f64() * 1e3,
        }
    }

    fn encode_pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        view: &wgpu::TextureView,
        clear: bool,
        frame: &FrameDraw,
    ) {
        let mut pass = begin_pass(enc, view, clear);
        self.draw(&mut pass, frame);
    }

    /// Renders one frame to an image (premultiplied colour over black) with the given visibility
    /// order, in a target the renderer keeps for the image size. An image side of 0 or beyond
    /// the adapter's texture limit is an error.
    pub fn render_ordered(
        &self,
        ctx: &GpuContext,
        data: &TetDrawData,
        cam: &Camera,
        tf: &TransferFunction,
        visibility: VisibilityOrder,
    ) -> Result<(Rgba8Image, FrameTimes), RenderError> {
        let limit = ctx.device.limits().max_texture_dimension_2d;
        if !(1..=limit).contains(&cam.width) || !(1..=limit).contains(&cam.height) {
            return Err(RenderError::ImageSize {
                width: cam.width,
                height: cam.height,
                limit,
            });
        }
        let t0 = std::time::Instant::now();
        let frame = self.prepare(ctx, data, cam, tf, visibility);
        let device = &ctx.device;
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        let (w, h) = (cam.width, cam.height);
        let texel = texel_bytes(self.format);
        let bpr = (w * texel).div_ceil(256) * 256;
        // taken out for the frame and put back only when it succeeds (a failed readback may leave
        // the buffer mapped or pending)
        let target = cache
            .target
            .take()
            .filter(|(cw, ch, ..)| (*cw, *ch) == (w, h));
        let target = target.unwrap_or_else(|| {
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
            let readback = readback_buffer(device, bpr, h);
            (w, h, texture, view, readback)
        });
        let (_, _, texture, view, readback) = &target;
        let mut enc = device.create_command_encoder(&Default::default());
        self.encode_pass(&mut enc, view, true, &frame);
        encode_copy(&mut enc, texture, readback, bpr);
        let t1 = std::time::Instant::now();
        ctx.queue.submit([enc.finish()]);
        wait_mapped(ctx, readback)?;
        let gpu_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = std::time::Instant::now();
        let pixels = decode_mapped(readback, w, h, bpr, texel)?;
        readback.unmap();
        cache.target = Some(target);
        let img = Rgba8Image {
            width: w,
            height: h,
            pixels,
        };
        let readback_ms = t2.elapsed().as_secs_f64() * 1e3;
        Ok((
            img,
            FrameTimes {
                sort_ms: frame.sort_ms,
                gpu_ms,
                readback_ms,
                total_ms: t0.elapsed().as_secs_f64() * 1e3,
            },
        ))
    }

    /// Reads a texture of [`Self::format`] (with `COPY_SRC` usage, e.g. one [`Self::draw_into`]
    /// drew) back into an 8-bit image, as [`Self::render_ordered`] reads its own target.
    pub fn read_texture(
        &self,
        ctx: &GpuContext,
        texture: &wgpu::Texture,
    ) -> Result<Rgba8Image, RenderError> {
        let (w, h) = (texture.width(), texture.height());
        let texel = texel_bytes(self.format);
        let bpr = (w * texel).div_ceil(256) * 256;
        let buffer = readback_buffer(&ctx.device, bpr, h);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        encode_copy(&mut enc, texture, &buffer, bpr);
        ctx.queue.submit([enc.finish()]);
        wait_mapped(ctx, &buffer)?;
        let pixels = decode_mapped(&buffer, w, h, bpr, texel)?;
        buffer.unmap();
        Ok(Rgba8Image {
            width: w,
            height: h,
            pixels,
        })
    }
}

/// Bytes per texel of the renderer's colour formats.
fn texel_bytes(format: wgpu::TextureFormat) -> u32 {
    match format {
        wgpu::TextureFormat::Rgba32Float => 16,
        wgpu::TextureFormat::Rgba16Float => 8,
        _ => 4,
    }
}

/// A mappable buffer for `h` rows of `bpr` bytes.
fn readback_buffer(device: &wgpu::Device, bpr: u32, h: u32) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: (bpr * h) as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    })
}

/// Copies the whole of `texture` into `buffer`, rows `bpr` bytes apart.
fn encode_copy(
    enc: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
    buffer: &wgpu::Buffer,
    bpr: u32,
) {
    let (w, h) = (texture.width(), texture.height());
    enc.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer,
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
}

/// Maps `buffer` for reading and waits for the GPU.
fn wait_mapped(ctx: &GpuContext, buffer: &wgpu::Buffer) -> Result<(), RenderError> {
    buffer.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    ctx.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map(|_| ())
        .map_err(|e| RenderError::Readback(e.to_string()))
}

/// The mapped rows of `buffer` as 8-bit pixels (straight to 8 bits per channel, as
/// `Rgba8Image::from_f64` rounds; non-finite → 0). The caller unmaps.
fn decode_mapped(
    buffer: &wgpu::Buffer,
    w: u32,
    h: u32,
    bpr: u32,
    texel: u32,
) -> Result<Vec<[u8; 4]>, RenderError> {
    let bytes = buffer
        .slice(..)
        .get_mapped_range()
        .map_err(|e| RenderError::Readback(e.to_string()))?;
    let q = |x: f32| {
        if x.is_finite() {
            tetwave_render::image_metrics::unit_to_u8(x as f64)
        } else {
            0
        }
    };
    let mut pixels = vec![[0u8; 4]; (w * h) as usize];
    pixels
        .par_chunks_mut(w.max(1) as usize)
        .enumerate()
        .for_each(|(y, out)| {
            let row = &bytes[y * bpr as usize..][..(w * texel) as usize];
            match texel {
                16 => {
                    for (o, c) in out.iter_mut().zip(row.chunks_exact(16)) {
                        let f: [f32; 4] = bytemuck::pod_read_unaligned(c);
                        *o = f.map(q);
                    }
                }
                8 => {
                    for (o, c) in out.iter_mut().zip(row.chunks_exact(8)) {
                        let f: [u16; 4] = bytemuck::pod_read_unaligned(c);
                        *o = f.map(|h| q(half_to_f32(h)));
                    }
                }
                _ => {
                    for (o, c) in out.iter_mut().zip(row.chunks_exact(4)) {
                        o.copy_from_slice(c);
                    }
                }
            }
        });
    Ok(pixels)
}

/// IEEE half → f32 (exact).
fn half_to_f32(h: u16) -> f32 {
    let s = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let e = ((h >> 10) & 0x1f) as i32;
    let m = (h & 0x3ff) as f32;
    match e {
        0 => s * m * (2f32).powi(-24),
        31 => {
            if m == 0.0 {
                s * f32::INFINITY
            } else {
                f32::NAN
            }
        }
        _ => s * (1.0 + m / 1024.0) * (2f32).powi(e - 15),
    }
}

/// A render pass onto `view`, cleared to transparent black first when `clear`.
fn begin_pass<'a>(
    enc: &'a mut wgpu::CommandEncoder,
    view: &wgpu::TextureView,
    clear: bool,
) -> wgpu::RenderPass<'a> {
    enc.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("pt"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations {
                load: if clear {
                    wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT)
                } else {
                    wgpu::LoadOp::Load
                },
                store: wgpu::StoreOp::Store,
            },
        })],
        depth_stencil_attachment: None,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    })
}
