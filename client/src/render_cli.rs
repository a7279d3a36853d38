//! `tetwave render`: one image of a store's uniform level, of the unstructured mesh a store is
//! prepared from (`.vtu`, legacy `.vtk`, `.msh`, `.mesh`) as it is, or of a volume file (NIfTI,
//! NRRD, VTK image data, TIFF, DICOM, Zarr) as it is (each cell of voxels cut into 6 tets), on
//! the GPU (projected tetrahedra) or with the CPU reference integrator, with its time and, on
//! request, its PSNR against the reference.
//!
//! A store and the mesh file it was prepared from frame the same default view: the store's base
//! mesh is the box around the mesh's points (`prepare`'s box5/box6), so both have the same bounds,
//! hence the same camera and extinction unit; the mesh's value range is its chosen scalar's
//! min/max over its points, and `prepare` records that range in the store's manifest
//! (`source_value_range`), which the store's image maps (stores without it map their samples'
//! range, which lies within). A store with a level set (`levelset.f32`) is drawn clipped to it:
//! tets that straddle the input's boundary draw only their inside part. A volume file's mesh has
//! the coordinates a store prepared from it has (its lowest-corner voxel at 0), so both frame the
//! same view too. With `--legend`, where the file or the store states its world frame (RAS,
//! LPS), the image's edges carry the anatomical directions they face (`R`, `A`, `SL`, ...), and
//! the legend names the values' unit.

use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;
use tetwave_gpu::order::{face_neighbors, is_convex};
use tetwave_gpu::pt::{Accumulation, PtRenderer, VisibilityOrder};
use tetwave_gpu::{GpuContext, RenderError};
use tetwave_import::clean::ImportOptions;
use tetwave_import::volume::{ScalarChoice, VolumeOptions};
use tetwave_import::MeshFormat;
use tetwave_protocol::view::Camera;
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TfError, TransferFunction, ValueHistogram, AUTO};
use tetwave_source::load::{
    file_mesh, is_mesh_input, is_volume_input, store_histogram, store_mesh, volume_mesh, LoadError,
};
use tetwave_store::{OpenOptions, Physical, Store, StoreError};

/// What to render and how.
#[derive(Debug, Clone, clap::Args)]
pub struct RenderArgs {
    /// Store directory (written by `tetwave-server prepare`), a mesh file (`.vtu`, `.vtk`,
    /// `.msh`, `.mesh`) drawn as it is, or a volume file or folder (NIfTI, NRRD, `.vti`, legacy
    /// `.vtk` image, TIFF stack, DICOM series, Zarr) drawn as it is.
    #[arg(value_name = "STORE|MESH|VOLUME")]
    pub store: PathBuf,
    /// Uniform level to draw (default: the store's finest; stores only).
    #[arg(long)]
    pub levels: Option<u8>,
    /// Mesh input: the scalar, `NAME`, `NAME:mag` or `NAME:K` among point and cell arrays (as
    /// `prepare --scalar`; default: the first point array, else the first cell array). Volume
    /// input: the component of a multi-component volume, `NAME`, `K` or `mag`.
    #[arg(long)]
    pub scalar: Option<String>,
    /// Volume input: the time point of a 4D volume.
    #[arg(long)]
    pub frame: Option<usize>,
    /// Mesh input: a geometric scalar instead of an array (`distance`: to the mesh's boundary).
    #[arg(long)]
    pub field: Option<String>,
    /// Mesh or volume input: replace NaN/Inf values of the scalar by this (refused otherwise).
    #[arg(long, allow_hyphen_values = true)]
    pub nan_as: Option<f64>,
    /// Mesh input: the format (vtu, vtk, msh, mesh), whatever the content and extension say; also
    /// makes the input a mesh file.
    #[arg(long)]
    pub format: Option<MeshFormat>,
    #[command(flatten)]
    pub camera: tetwave_source::options::CameraArgs,
    /// Image size `WxH`.
    #[arg(long, default_value = "512x512", value_parser = tetwave_source::options::parse_size)]
    pub size: (u32, u32),
    /// Transfer function: `auto` (the `default` preset fitted to the data: its control points moved
    /// to the data's value quantiles over its volume, so that each colour band covers the share of
    /// the volume it covers of the range, and its extinctions square-rooted and scaled to a volume mean of 10 per
    /// diagonal; a store fits to its finest level), a preset (default, transparent, opaque, shells)
    /// or a .json file. `--json` reports the function drawn with.
    #[arg(long, default_value = "auto")]
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
    /// Add a colour legend under the image: the transfer function's colours across the value
    /// range, the scalar's name (a store's dataset) and that range.
    #[arg(long)]
    pub legend: bool,
    /// Print one JSON object (`tets, ms, psnr_db`, …).
    #[arg(long)]
    pub json: bool,
    /// Recompute every store file's CRC-32 when opening it (reads the whole store; `base.bin`'s
    /// and the structure are always checked).
    #[arg(long)]
    pub verify: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum RenderCliError {
    #[error(transparent)]
    Load(#[from] LoadError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Tf(#[from] TfError),
    #[error(transparent)]
    Gpu(#[from] RenderError),
    #[error("{0}")]
    Usage(String),
    #[error("{path}: cannot write PNG: {reason}")]
    Png { path: PathBuf, reason: String },
}

#[derive(Debug, Clone, Serialize)]
pub struct RenderReport {
    /// `store`, `mesh` or `volume`.
    pub input: String,
    pub tets: u64,
    /// The store's level drawn (0 for a mesh file).
    pub level: u8,
    /// The mesh's scalar (`name`, `name:mag`, `name:K`, `distance`); none for a store.
    pub scalar: Option<String>,
    pub value_range: (f32, f32),
    pub width: u32,
    pub height: u32,
    pub renderer: String,
    /// Time of the image itself (GPU: sort + draw + readback; CPU: the reference integration).
    pub ms: f64,
    pub psnr_db: Option<f64>,
    pub reference_ms: Option<f64>,
    /// GPU: the time to upload the mesh, and the chunks it is drawn in (1 when it fits one
    /// storage binding of the adapter).
    pub upload_ms: Option<f64>,
    pub gpu_chunks: Option<usize>,
    /// GPU: the CPU's visibility sort within `ms` (near 0 for `--order gpu`, whose sort runs on
    /// the GPU), and the CPU's whole share of the frame (the sort, the exit faces, the
    /// submission: `ms` less the GPU's work and the readback).
    pub sort_ms: Option<f64>,
    pub cpu_ms: Option<f64>,
    pub output: String,
    /// The transfer function drawn with (for `auto`, the fitted one: save it as a `.json` file to
    /// draw another input with the same colours).
    pub tf: TransferFunction,
    /// A volume file's format, voxels along the world axes, and world frame and units.
    pub volume: Option<VolumeReport>,
    /// With `--legend`: the anatomical direction each image edge faces (`[left, right, top,
    /// bottom]`), where the input states its world frame.
    pub orientation: Option<[String; 4]>,
}

#[derive(Debug, Clone, Serialize)]
pub struct VolumeReport {
    pub format: String,
    pub dims: [usize; 3],
    /// The file's world: `origin`, `frame`, `length_unit`, `value_unit`.
    #[serde(flatten)]
    pub physical: Physical,
}

/// `--order mpvo` is exact only on convex meshes: says so (a tracing warning) when the drawn domain
/// is not convex: a boundary with a reflex edge, several parts, or a level set that clips tets.
fn warn_if_not_convex(mesh: &RenderMesh) {
    let clipped = mesh.levelset.is_some();
    let convex = !clipped && is_convex(&mesh.positions, &mesh.tets, &face_neighbors(&mesh.tets));
    if !convex {
        tracing::warn!(
            clipped,
            "--order mpvo on a non-convex mesh: tets on either side of a gap or concavity are \
             ordered arbitrarily (see docs/formats.md); prefer --order centroid or compare with \
             --compare"
        );
    }
}

pub fn run(a: &RenderArgs) -> Result<RenderReport, RenderCliError> {
    // checked before reading the input; `auto` is fitted below, once the data is read
    let mut tf = TransferFunction::load(&a.tf)?;
    let auto = a.tf == AUTO;
    let is_volume = a.format.is_none() && is_volume_input(&a.store);
    let is_mesh = !is_volume && is_mesh_input(&a.store, a.format);
    if !is_volume && a.frame.is_some() {
        return Err(RenderCliError::Usage(
            "--frame applies to 4D volume files".into(),
        ));
    }
    // the legend's name: a mesh's scalar, or a store's dataset
    let mut legend_name = String::new();
    // the input's world, where it states one
    let mut physical: Option<Physical> = None;
    let mut volume = None;
    let (mesh, level, scalar) = if is_volume {
        if a.levels.is_some() || a.field.is_some() {
            return Err(RenderCliError::Usage(
                "--levels applies to stores and --field to mesh files, not volume files".into(),
            ));
        }
        let options = VolumeOptions {
            raw: None,
            scalar: a.scalar.as_deref().map(ScalarChoice::parse),
            frame: a.frame,
        };
        let (mesh, drawn) = volume_mesh(&a.store, &options, a.nan_as)?;
        if auto {
            tf = tf.fitted(&ValueHistogram::of_mesh(&mesh));
        }
        legend_name = drawn.legend_name(&a.store);
        physical = Some(drawn.physical.clone());
        volume = Some(VolumeReport {
            format: drawn.format.into(),
            dims: drawn.dims,
            physical: drawn.physical,
        });
        (mesh, 0, None)
    } else if is_mesh {
        if a.levels.is_some() {
            return Err(RenderCliError::Usage(
                "--levels applies to stores, not mesh files".into(),
            ));
        }
        let options = ImportOptions {
            scalar: a.scalar.as_deref(),
            field: a.field.as_deref(),
            nan_as: a.nan_as,
        };
        let (mesh, scalar) = file_mesh(&a.store, a.format, &options)?;
        if auto {
            tf = tf.fitted(&ValueHistogram::of_mesh(&mesh));
        }
        (mesh, 0, Some(scalar))
    } else {
        if a.scalar.is_some() || a.field.is_some() || a.nan_as.is_some() {
            return Err(RenderCliError::Usage(
                "--scalar, --field and --nan-as apply to mesh files; a store has one scalar".into(),
            ));
        }
        let store = Store::open_with(
            &a.store,
            OpenOptions {
                verify_checksums: a.verify,
                ..Default::default()
            },
        )?;
        let (mesh, level) = store_mesh(&store, a.levels)?;
        if auto {
            tf = tf.fitted(&store_histogram(&store, Some((&mesh, level)))?);
        }
        legend_name = store.manifest.legend_name();
        physical = store.manifest.physical.clone();
        (mesh, level, None)
    };
    let (lo, hi) = mesh.bounds();
    let cam = a
        .camera
        .orbit(Camera::framing(lo.to_array(), hi.to_array()))
        .camera(a.size.0, a.size.1);
    let reference = |mesh: &RenderMesh| {
        let t = Instant::now();
        let img = render_reference(mesh, &cam, &tf);
        (img, t.elapsed().as_secs_f64() * 1e3)
    };
    // the GPU's upload: its time and the chunks the mesh is drawn in
    let mut upload: Option<(f64, usize)> = None;
    let mut frame_times = None;
    let (img, ms, renderer, refimg): (Rgba8Image, f64, String, Option<(Rgba8Image, f64)>) =
        if a.reference {
            let (img, ms) = reference(&mesh);
            (img, ms, "cpu-reference".into(), None)
        } else {
            if a.order == VisibilityOrder::Mpvo {
                warn_if_not_convex(&mesh);
            }
            let ctx = GpuContext::new()?;
            let r = PtRenderer::with_accumulation(&ctx, a.accumulation);
            let t = Instant::now();
            let data = r.upload_with(&ctx, &mesh, a.order == VisibilityOrder::Mpvo)?;
            upload = Some((t.elapsed().as_secs_f64() * 1e3, data.chunks()));
            // first frame warms the pipeline up; time the second
            r.render_ordered(&ctx, &data, &cam, &tf, a.order)?;
            let (img, times) = r.render_ordered(&ctx, &data, &cam, &tf, a.order)?;
            frame_times = Some(times);
            let refimg = a.compare.then(|| reference(&mesh));
            (
                img,
                times.total_ms,
                format!("gpu-pt {}", ctx.describe()),
                refimg,
            )
        };
    let psnr_db = refimg.as_ref().map(|(r, _)| psnr(&img, r).min(99.0));
    let range = [mesh.value_range.0, mesh.value_range.1];
    let name = scalar.as_deref().unwrap_or(&legend_name);
    let orientation = physical
        .as_ref()
        .filter(|_| a.legend)
        .and_then(|p| crate::legend::edge_labels(p, &cam));
    let png = if a.legend {
        let mut img = img;
        if let Some(labels) = &orientation {
            crate::legend::draw_edge_labels(&mut img, labels);
        }
        crate::legend::with_legend(&img, &tf, name, range)
    } else {
        img
    };
    png.save_png(&a.output).map_err(|e| RenderCliError::Png {
        path: a.output.clone(),
        reason: e.to_string(),
    })?;
    Ok(RenderReport {
        input: if is_volume {
            "volume"
        } else if is_mesh {
            "mesh"
        } else {
            "store"
        }
        .into(),
        tets: mesh.tets.len() as u64,
        level,
        scalar,
        value_range: mesh.value_range,
        width: a.size.0,
        height: a.size.1,
        renderer,
        ms,
        psnr_db,
        reference_ms: refimg.as_ref().map(|(_, ms)| *ms),
        upload_ms: upload.map(|(ms, _)| ms),
        gpu_chunks: upload.map(|(_, c)| c),
        sort_ms: frame_times.map(|t| t.sort_ms),
        cpu_ms: frame_times.map(|t| t.total_ms - t.gpu_ms - t.readback_ms),
        output: a.output.display().to_string(),
        tf,
        volume,
        orientation,
    })
}
