//! # tetwave-gpu
//!
//! GPU rendering (wgpu) of what `tetwave-render` describes. [`GpuContext`] is the shared set-up (instance, adapter, device, queue);
//! [`pt::PtRenderer`] draws leaf tets by projected tetrahedra (WGSL in `shaders/pt.wgsl`).
//! The adaptive mesh never touches wgpu: renderers take a [`tetwave_render::render_mesh::RenderMesh`].

pub mod order;
pub mod pt;
mod sort;

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("no GPU adapter found (wgpu saw none for Vulkan or GL; on Debian, `apt-get install mesa-vulkan-drivers` gives the lavapipe CPU driver); the CPU reference renderer (--reference) still works")]
    NoAdapter,
    #[error("GPU device request failed: {0}")]
    Device(String),
    #[error("GPU readback failed: {0}")]
    Readback(String),
    #[error("the mesh needs {needed} bytes in one GPU buffer; this adapter allows {limit}")]
    TooLarge { needed: u64, limit: u64 },
    #[error("a {width}x{height} image: each side must be 1..={limit} on this adapter")]
    ImageSize { width: u32, height: u32, limit: u32 },
}

/// Keeps Mesa's Vulkan device-selection layer (`VK_LAYER_MESA_device_select`, an implicit layer
/// on most Linux installs) from probing for a Wayland compositor when there is no display at all:
/// its probe calls `wl_display_connect`, which prints "error: XDG_RUNTIME_DIR is invalid or not
/// set in the environment." on every headless run, and without a display the layer has nothing
/// to select by (the adapters keep the driver's order). Sets `NODEVICE_SELECT=1` (the layer's
/// documented off switch) when neither `WAYLAND_DISPLAY` nor `DISPLAY` is set and the user has
/// not set it. Call at the start of `main`, before any thread exists (it sets an environment
/// variable); a process with a display is left as it is.
pub fn quiet_headless_vulkan_layers() {
    let set = |k: &str| std::env::var_os(k).is_some_and(|v| !v.is_empty());
    if !set("WAYLAND_DISPLAY") && !set("DISPLAY") && std::env::var_os("NODEVICE_SELECT").is_none() {
        std::env::set_var("NODEVICE_SELECT", "1");
    }
}

/// Instance, adapter, device and queue, created once and shared.
pub struct GpuContext {
    /// The instance the adapter came from: a window's surface must be created from it to be
    /// presentable with this device (the viewer shares the device with its window).
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// Whether 32-bit float render targets can be blended (used for accumulation precision).
    pub float32_blend: bool,
}

impl GpuContext {
    /// Picks a Vulkan adapter when there is one (wgpu lists llvmpipe for both Vulkan and GL), else GL.
    pub fn new() -> Result<Self, RenderError> {
        // Vulkan first (wgpu lists llvmpipe for both Vulkan and GL; GL's EGL probing is noisy and
        // slower), then GL, unless WGPU_BACKEND chooses.
        let from_env = std::env::var_os("WGPU_BACKEND").is_some();
        let tries: &[wgpu::Backends] = if from_env {
            &[wgpu::Backends::all()]
        } else {
            &[wgpu::Backends::VULKAN, wgpu::Backends::GL]
        };
        let mut found = None;
        for &backends in tries {
            let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
            if !from_env {
                desc.backends = backends;
            }
            let instance = wgpu::Instance::new(desc);
            let adapters = pollster::block_on(instance.enumerate_adapters(backends));
            if let Some(a) = adapters.into_iter().next() {
                found = Some((instance, a));
                break;
            }
        }
        let (instance, adapter) = found.ok_or(RenderError::NoAdapter)?;
        // the transfer-function table is one 64 KiB uniform binding (see `pt::TF_TABLE_INTERVALS`)
        let uniform = adapter.limits().max_uniform_buffer_binding_size;
        if uniform < pt::TF_TABLE_BYTES {
            return Err(RenderError::Device(format!(
                "{} allows {uniform} bytes per uniform binding; the renderer's transfer-function \
                 table needs {}",
                adapter.get_info().name,
                pt::TF_TABLE_BYTES
            )));
        }
        let float32_blend = adapter
            .features()
            .contains(wgpu::Features::FLOAT32_BLENDABLE);
        let mut required_features = wgpu::Features::empty();
        if float32_blend {
            required_features |= wgpu::Features::FLOAT32_BLENDABLE;
        }
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("tetwave"),
            required_features,
            required_limits: adapter.limits(),
            experimental_features: wgpu::ExperimentalFeatures::default(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| RenderError::Device(e.to_string()))?;
        tracing::info!(adapter = %adapter.get_info().name, backend = ?adapter.get_info().backend, "GPU adapter");
        Ok(GpuContext {
            instance,
            adapter,
            device,
            queue,
            float32_blend,
        })
    }

    /// `name (backend)` of the adapter.
    pub fn describe(&self) -> String {
        let i = self.adapter.get_info();
        format!("{} ({:?})", i.name, i.backend)
    }
}
