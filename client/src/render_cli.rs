//! `tetwave render`: one image of a store's uniform level, on the GPU (projected tetrahedra) or with
//! the CPU reference integrator, with its time and, on request, its PSNR against the reference.

use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;
use tetwave_protocol::view::Camera;
use tetwave_render::gpu::pt::{Accumulation, PtRenderer, VisibilityOrder};
use tetwave_render::gpu::{GpuContext, RenderError};
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TfError, TransferFunction};
use tetwave_store::{OpenOptions, Store, StoreError};

/// What to render and how.
#[derive(Debug, Clone, clap::Args)]
pub struct RenderArgs {
    /// Store directory (written by `tetwave-server prepare`).
    pub store: PathBuf,
    /// Uniform level to draw (default: the store's finest).
    #[arg(long)]
    pub levels: Option<u8>,
    #[arg(long, default_value_t = 35.0, value_parser = crate::camera_arg::angle)]
    pub azimuth: f64,
    #[arg(long, default_value_t = 25.0, value_parser = crate::camera_arg::elevation)]
    pub elevation: f64,
    /// Eye distance from the volume's centre (default: 1.6 × the bounding-box diagonal).
    #[arg(long, value_parser = crate::camera_arg::distance)]
    pub distance: Option<f64>,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 40.0, value_parser = crate::camera_arg::fov)]
    pub fov: f64,
    /// Image size `WxH`.
    #[arg(long, default_value = "512x512", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Transfer function: a preset (default, transparent, opaque, shells) or a .json file.
    #[arg(long, default_value = "default")]
    pub tf: String,
    /// Render with the CPU reference integrator instead of the GPU.
    #[arg(long)]
    pub reference: bool,
    /// Also render the reference and report the PSNR of the image against it.
    #[arg(long)]
    pub compare: bool,
    /// Visibility order: centroid (approximate) or mpvo (exact for convex acyclic meshes).
    #[arg(long, value_enum, default_value_t = VisibilityOrder::Centroid)]
    pub order: VisibilityOrder,
    /// Precision of the blending target: best (32-bit float where blendable, else 16-bit), f16, or
    /// u8 (fastest on CPU rasterizers, least accurate).
    #[arg(long, value_enum, default_value_t = Accumulation::Best)]
    pub accumulation: Accumulation,
    /// Output PNG.
    #[arg(short = 'o', long, default_value = "out.png")]
    pub output: PathBuf,
    /// Print one JSON object (`tets, ms, psnr_db`, …).
    #[arg(long)]
    pub json: bool,
    /// Recompute every store file's CRC-32 when opening it (reads the whole store; `base.bin`'s
    /// and the structure are always checked).
    #[arg(long)]
    pub verify: bool,
}

/// Image widths and heights the CLIs accept, in pixels.
pub const IMAGE_SIDES: std::ops::RangeInclusive<u32> = 1..=8192;

/// One image side in pixels (`--width`, `--height`), within [`IMAGE_SIDES`].
pub fn parse_side(s: &str) -> Result<u32, String> {
    let v: u32 = s
        .parse()
        .map_err(|_| format!("expected a whole number of pixels, got {s:?}"))?;
    if IMAGE_SIDES.contains(&v) {
        Ok(v)
    } else {
        Err(format!(
            "{v} pixels is outside {}..={}",
            IMAGE_SIDES.start(),
            IMAGE_SIDES.end()
        ))
    }
}

pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("expected WxH, got {s:?}"))?;
    let w: u32 = w
        .trim()
        .parse()
        .map_err(|_| format!("bad width in {s:?}"))?;
    let h: u32 = h
        .trim()
        .parse()
        .map_err(|_| format!("bad height in {s:?}"))?;
    if !IMAGE_SIDES.contains(&w) || !IMAGE_SIDES.contains(&h) {
        return Err(format!("size {w}x{h} outside 1..={}", IMAGE_SIDES.end()));
    }
    Ok((w, h))
}

#[derive(Debug, thiserror::Error)]
pub enum RenderCliError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Tf(#[from] TfError),
    #[error(transparent)]
    Gpu(#[from] RenderError),
    #[error("--levels {asked} exceeds the store's {levels} levels")]
    Level { asked: u8, levels: u8 },
    #[error("{path}: cannot write PNG: {reason}")]
    Png { path: PathBuf, reason: String },
}

#[derive(Debug, Clone, Serialize)]
pub struct RenderReport {
    pub tets: u64,
    pub level: u8,
    pub width: u32,
    pub height: u32,
    pub renderer: String,
    /// Time of the image itself (GPU: sort + draw + readback; CPU: the reference integration).
    pub ms: f64,
    pub psnr_db: Option<f64>,
    pub reference_ms: Option<f64>,
    pub output: String,
}

/// The level-`level` mesh of a store (finest when `None`).
pub fn store_mesh(store: &Store, level: Option<u8>) -> Result<(RenderMesh, u8), RenderCliError> {
    let levels = store.base.levels;
    let level = level.unwrap_or(levels);
    if level > levels {
        return Err(RenderCliError::Level {
            asked: level,
            levels,
        });
    }
    let values = store.synthesize_all()?;
    let empty = store.empty_children()?;
    Ok((
        RenderMesh::uniform_level(&store.base, &values, &empty, level),
        level,
    ))
}

pub fn run(a: &RenderArgs) -> Result<RenderReport, RenderCliError> {
    let tf = TransferFunction::load(&a.tf)?;
    let store = Store::open_with(
        &a.store,
        OpenOptions {
            verify_checksums: a.verify,
        },
    )?;
    let (mesh, level) = store_mesh(&store, a.levels)?;
    let distance = a.distance.unwrap_or(1.6 * mesh.diagonal());
    let cam = Camera::orbit(
        mesh.center(),
        distance,
        a.azimuth,
        a.elevation,
        a.fov,
        a.size.0,
        a.size.1,
    );
    let reference = |mesh: &RenderMesh| {
        let t = Instant::now();
        let img = render_reference(mesh, &cam, &tf);
        (img, t.elapsed().as_secs_f64() * 1e3)
    };
    let (img, ms, renderer, refimg): (Rgba8Image, f64, String, Option<(Rgba8Image, f64)>) =
        if a.reference {
            let (img, ms) = reference(&mesh);
            (img, ms, "cpu-reference".into(), None)
        } else {
            let ctx = GpuContext::new()?;
            let r = PtRenderer::with_accumulation(&ctx, a.accumulation);
            let data = r.upload_with(&ctx, &mesh, a.order == VisibilityOrder::Mpvo)?;
            // first frame warms the pipeline up; time the second
            r.render_ordered(&ctx, &data, &cam, &tf, a.order)?;
            let (img, times) = r.render_ordered(&ctx, &data, &cam, &tf, a.order)?;
            let refimg = a.compare.then(|| reference(&mesh));
            (
                img,
                times.total_ms,
                format!("gpu-pt {}", ctx.describe()),
                refimg,
            )
        };
    img.save_png(&a.output).map_err(|e| RenderCliError::Png {
        path: a.output.clone(),
        reason: e.to_string(),
    })?;
    Ok(RenderReport {
        tets: mesh.tets.len() as u64,
        level,
        width: a.size.0,
        height: a.size.1,
        renderer,
        ms,
        psnr_db: refimg.as_ref().map(|(r, _)| psnr(&img, r).min(99.0)),
        reference_ms: refimg.as_ref().map(|(_, ms)| *ms),
        output: a.output.display().to_string(),
    })
}
