//! Visibility order on the GPU ([`super::pt::VisibilityOrder::Gpu`]): each chunk's tets keyed by
//! their centroid's squared distance from the eye and radix-sorted back to front by compute passes
//! (`shaders/sort.wgsl`), so that a frame's order never leaves the GPU: the draw reads it from the
//! sorted buffer and rasterizes every face of each tet, the entry faces culled.
//!
//! The sort is stable (equal keys keep their tet order) and exact: the order is the CPU's centroid
//! order but for ties, which [`super::order::centroid_order`] breaks arbitrarily.

use wgpu::util::DeviceExt;

const SHADER: &str = include_str!("../../shaders/sort.wgsl");

/// Pairs one invocation of `count` and `scatter` walks.
const BLOCK: u32 = 512;

/// The uniform of one pass (`Params` in the shader).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    counts: [u32; 4],
    eye: [f32; 4],
}

/// The sort's pipelines: create once per device.
pub(crate) struct GpuSort {
    layout: wgpu::BindGroupLayout,
    keys: wgpu::ComputePipeline,
    count: wgpu::ComputePipeline,
    scan_rows: wgpu::ComputePipeline,
    scan_totals: wgpu::ComputePipeline,
    scatter: wgpu::ComputePipeline,
}

/// One chunk's sort state: its centroids, the (key, tet) pairs in two copies the passes move
/// between, the histogram, and a uniform and bind group per pass. After [`GpuSort::encode`] the
/// order is in [`Self::order`].
pub(crate) struct SortBuffers {
    n: u32,
    params: [wgpu::Buffer; 4],
    binds: [wgpu::BindGroup; 4],
    vals: wgpu::Buffer,
}

impl SortBuffers {
    /// The tets (chunk-local indices) back to front, once a sort is encoded.
    pub(crate) fn order(&self) -> &wgpu::Buffer {
        &self.vals
    }
}

/// Workgroups of 64 for `n` invocations, as a 2D grid within the per-dimension limit.
fn groups(n: u32) -> (u32, u32) {
    let w = n.div_ceil(64).max(1);
    let x = w.min(65_535);
    (x, w.div_ceil(x))
}

impl GpuSort {
    pub(crate) fn new(device: &wgpu::Device) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("sort.wgsl"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let storage = |binding: u32, read_only: bool| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("sort"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                storage(1, true),
                storage(2, false),
                storage(3, false),
                storage(4, false),
                storage(5, false),
                storage(6, false),
            ],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("sort"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pl),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        GpuSort {
            keys: pipeline("keys"),
            count: pipeline("count"),
            scan_rows: pipeline("scan_rows"),
            scan_totals: pipeline("scan_totals"),
            scatter: pipeline("scatter"),
            layout,
        }
    }

    /// The buffers to sort `centroids` (a chunk's, `[x, y, z, 1]` each) with.
    pub(crate) fn buffers(&self, device: &wgpu::Device, centroids: &[[f32; 4]]) -> SortBuffers {
        let n = centroids.len() as u32;
        let nblocks = n.div_ceil(BLOCK).max(1);
        let storage = |label: &str, bytes: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes.max(16),
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        };
        let pairs = 4 * n as u64;
        let centroid_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("sort centroids"),
            contents: if centroids.is_empty() {
                &[0u8; 16]
            } else {
                bytemuck::cast_slice(centroids)
            },
            usage: wgpu::BufferUsages::STORAGE,
        });
        let keys = [storage("keys a", pairs), storage("keys b", pairs)];
        let vals = [storage("vals a", pairs), storage("vals b", pairs)];
        let hist = storage("hist", 4 * (256 * nblocks as u64 + 256));
        let params: [wgpu::Buffer; 4] = std::array::from_fn(|_| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("sort params"),
                size: std::mem::size_of::<Params>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        });
        // pass p moves the pairs from copy p % 2 to the other: after 4 passes they are in copy 0
        let binds = std::array::from_fn(|p| {
            let (s, d) = (p % 2, 1 - p % 2);
            let entries = [
                params[p].as_entire_binding(),
                centroid_buf.as_entire_binding(),
                keys[s].as_entire_binding(),
                vals[s].as_entire_binding(),
                keys[d].as_entire_binding(),
                vals[d].as_entire_binding(),
                hist.as_entire_binding(),
            ];
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("sort"),
                layout: &self.layout,
                entries: &entries
                    .into_iter()
                    .enumerate()
                    .map(|(i, resource)| wgpu::BindGroupEntry {
                        binding: i as u32,
                        resource,
                    })
                    .collect::<Vec<_>>(),
            })
        });
        let [vals_a, _] = vals;
        SortBuffers {
            n,
            params,
            binds,
            vals: vals_a,
        }
    }

    /// Encodes the sort of `b`'s centroids back to front from `eye` (writing the passes'
    /// uniforms now: submit before the next `encode` of the same buffers).
    pub(crate) fn encode(
        &self,
        queue: &wgpu::Queue,
        enc: &mut wgpu::CommandEncoder,
        b: &SortBuffers,
        eye: [f32; 3],
    ) {
        let nblocks = b.n.div_ceil(BLOCK).max(1);
        for (p, buf) in b.params.iter().enumerate() {
            let params = Params {
                counts: [b.n, BLOCK, nblocks, 8 * p as u32],
                eye: [eye[0], eye[1], eye[2], 1.0],
            };
            queue.write_buffer(buf, 0, bytemuck::bytes_of(&params));
        }
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("sort"),
            timestamp_writes: None,
        });
        let (tx, ty) = groups(b.n);
        let (bx, by) = groups(nblocks);
        pass.set_pipeline(&self.keys);
        pass.set_bind_group(0, &b.binds[0], &[]);
        pass.dispatch_workgroups(tx, ty, 1);
        for bind in &b.binds {
            pass.set_bind_group(0, bind, &[]);
            pass.set_pipeline(&self.count);
            pass.dispatch_workgroups(bx, by, 1);
            pass.set_pipeline(&self.scan_rows);
            pass.dispatch_workgroups(4, 1, 1);
            pass.set_pipeline(&self.scan_totals);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(&self.scatter);
            pass.dispatch_workgroups(bx, by, 1);
        }
    }
}
