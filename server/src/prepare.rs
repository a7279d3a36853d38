//! `prepare` and `verify`: resample → analysis → store, and the store's round-trip check.

use crate::analysis::Analysis;
use crate::analysis::{
    analyze_hierarchy, AnalysisError, ErrorBound, Precision, AXES_MAX_MAGNITUDE,
};
use crate::resample::levelset::signed_distance;
use crate::resample::raw::{LatticeError, RawError, RawGrid, RawType, VoxelLattice};
use crate::resample::synthetic::Synthetic;
use crate::resample::unstructured::{
    self, BoundaryDistance, CleanError, CleanReport, ImportOptions, Locator,
};
use crate::resample::{indexable, resample, BaseSpec, ResampleError, Source, MAX_NODES};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tetwave_import::volume::{
    self, FileHeader, ScalarChoice, Volume, VolumeError, VolumeFormat, VolumeOptions,
};
use tetwave_import::{self as import, ImportError, MeshFormat};
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::store_format::MAX_PREVIEW_NODES;
use tetwave_protocol::wavelet::Predictor;
pub mod parts;
mod remote;

pub use parts::PartsArgs;
use tetwave_store::{
    self as store, Preview, PreviewNodes, Store, StoreError, StoreMeta, PREVIEW_FILE,
    REFERENCE_FILE,
};

#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    #[error("{0}")]
    Usage(String),
    #[error("unknown input {0:?}: give synthetic:harmonic|linear, a raw grid (.raw, or any file with --dims), or a .vtu/.vtk/.msh mesh")]
    UnknownInput(String),
    #[error("unknown synthetic field {0:?} (known: harmonic, linear)")]
    UnknownSynthetic(String),
    #[error("unknown --dtype {0:?} (u8, i8, u16, i16, u32, i32, f32, f64)")]
    UnknownDtype(String),
    #[error("{path}: {count} NaN/Inf samples (first at index {first}); pass --nan-as VALUE to replace them")]
    NonFiniteRaw {
        path: PathBuf,
        count: usize,
        first: usize,
    },
    #[error(transparent)]
    Raw(#[from] RawError),
    #[error(transparent)]
    Volume(#[from] VolumeError),
    #[error(transparent)]
    Lattice(#[from] LatticeError),
    #[error(transparent)]
    Import(#[from] ImportError),
    #[error("{path}: {source}")]
    Clean { path: PathBuf, source: CleanError },
    #[error(transparent)]
    Resample(#[from] ResampleError),
    #[error(transparent)]
    Analysis(#[from] AnalysisError),
    #[error("the domain's level set: {0}")]
    LevelSet(#[from] tetwave_protocol::levelset::LevelSetError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(
        "{vertices} vertices at {levels} levels: prepare holds the whole hierarchy in memory, \
         about {need_gib:.1} GiB here, and this machine has {have_gib:.1} GiB (a raw grid is \
         prepared by parts within --memory; meshes and synthetic fields are not yet): give fewer \
         --levels, or prepare on a machine with more memory"
    )]
    TooLargeForMemory {
        vertices: u64,
        levels: u8,
        need_gib: f64,
        have_gib: f64,
    },
    #[error(
        "--memory {memory}: the smallest part of this grid (one row of boxes, at the fewest \
         levels that keep its base mesh small enough) needs about {least} bytes (its block of \
         voxels and {per_vertex} bytes a vertex, and {overhead} for the process): give --memory \
         {least_mib}M or more"
    )]
    MemoryTooSmall {
        memory: u64,
        least: u64,
        least_mib: u64,
        per_vertex: u64,
        overhead: u64,
    },
    #[error("{what}: max abs error {error:e} exceeds the manifest's bound {bound:e}")]
    VerifyFailed {
        what: String,
        error: f64,
        bound: f64,
    },
}

/// How to read a raw grid (`prepare`, `verify --input`).
#[derive(Debug, Clone, clap::Args)]
pub struct GridArgs {
    /// Raw grid dimensions `X,Y,Z` (x fastest). Volume files (NIfTI, NRRD, ...) state their own.
    #[arg(long, value_parser = parse_dims)]
    pub dims: Option<[usize; 3]>,
    /// Raw sample type: u8, i8, u16, i16 (CT Hounsfield units), u32, i32, f32 or f64,
    /// little-endian.
    #[arg(long, default_value = "u8")]
    pub dtype: String,
    /// Raw grid spacing `sx,sy,sz`.
    #[arg(long, value_parser = parse_spacing, default_value = "1,1,1")]
    pub spacing: [f64; 3],
    /// A volume file's format and header, when the grid is one (`dims`, `dtype` and `spacing`
    /// are then its world frame's, [`ReadArgs::resolve_volume`]).
    #[arg(skip)]
    pub volume: Option<VolumeInput>,
}

/// A volume file read as a grid: what [`Volume::open`] needs again for each block, and what its
/// header said.
#[derive(Debug, Clone)]
pub struct VolumeInput {
    pub format: VolumeFormat,
    pub options: VolumeOptions,
    pub header: FileHeader,
    /// World position of the grid's voxel `[0, 0, 0]` (the store's lattice starts at 0).
    pub origin: [f64; 3],
}

impl VolumeInput {
    /// What the store's manifest keeps of the file's world (`physical`): `None` when the file
    /// states no frame and no unit (a raw grid's origin is its own lattice's).
    pub fn physical(&self) -> Option<store::Physical> {
        let h = &self.header;
        let stated = h.frame.is_some() || h.length_unit.is_some() || h.value_unit.is_some();
        (stated || self.origin != [0.0; 3]).then(|| store::Physical {
            origin: self.origin,
            frame: h.frame.clone(),
            length_unit: h.length_unit.clone(),
            value_unit: h.value_unit.clone(),
        })
    }
}

impl Default for GridArgs {
    fn default() -> Self {
        GridArgs {
            dims: None,
            dtype: "u8".into(),
            spacing: [1.0; 3],
            volume: None,
        }
    }
}

impl GridArgs {
    /// Reads the grid at `path`; NaN/Inf samples are refused, or replaced by `nan_as`.
    pub fn read(&self, path: &Path, nan_as: Option<f64>) -> Result<RawGrid, PrepareError> {
        let dims = self.dims.ok_or(RawError::MissingDims)?;
        self.read_slab(path, nan_as, 0..dims[2])
    }

    /// [`Self::read`] of the voxel planes `z` alone ([`RawGrid::read_block`]); a NaN's index is
    /// the whole grid's.
    pub fn read_slab(
        &self,
        path: &Path,
        nan_as: Option<f64>,
        z: std::ops::Range<usize>,
    ) -> Result<RawGrid, PrepareError> {
        let dims = self.dims.ok_or(RawError::MissingDims)?;
        self.read_block(path, nan_as, 0..dims[1], z)
    }

    /// [`Self::read`] of the voxel rows `y` of the planes `z` alone ([`RawGrid::read_block`]); a
    /// NaN's index is the block's first plane's in the whole grid plus its index in the block.
    pub fn read_block(
        &self,
        path: &Path,
        nan_as: Option<f64>,
        y: std::ops::Range<usize>,
        z: std::ops::Range<usize>,
    ) -> Result<RawGrid, PrepareError> {
        let dims = self.dims.ok_or(RawError::MissingDims)?;
        let before = (z.start * dims[1] + y.start) * dims[0];
        let mut grid = match &self.volume {
            Some(v) => {
                let mut vol = Volume::open(path, Some(v.format), &v.options)?;
                if vol.dims != dims {
                    return Err(PrepareError::Usage(format!(
                        "{}: the volume's dims changed while it was read ({:?}, were {dims:?})",
                        path.display(),
                        vol.dims
                    )));
                }
                let block = [dims[0], y.len(), z.len()];
                RawGrid::from_samples(block, self.spacing, vol.read_block(y, z)?)
            }
            None => {
                let dtype = RawType::parse(&self.dtype)
                    .ok_or_else(|| PrepareError::UnknownDtype(self.dtype.clone()))?;
                RawGrid::read_block(path, dims, dtype, self.spacing, y, z)?
            }
        };
        if let Some(first) = grid.first_non_finite() {
            match nan_as {
                Some(v) => {
                    let n = grid.replace_non_finite(v as f32);
                    tracing::warn!(replaced = n, value = v, "replaced NaN/Inf samples");
                }
                None => {
                    let count = grid.replace_non_finite(0.0);
                    return Err(PrepareError::NonFiniteRaw {
                        path: path.to_path_buf(),
                        count,
                        first: before + first,
                    });
                }
            }
        }
        Ok(grid)
    }
}

/// How to read an input (`prepare`, and `verify --input`, which reads it as `prepare` did).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ReadArgs {
    #[command(flatten)]
    pub grid: GridArgs,
    /// Array to use from a mesh file: a point or cell array `NAME`; for a vector array its
    /// magnitude `NAME:mag` (the default for vectors; the Frobenius norm of a tensor, a
    /// 6-component one read as symmetric xx yy zz xy yz xz) or a component `NAME:0`. Cell arrays are
    /// averaged to the points, weighted by volume. Default: the first point scalar.
    #[arg(long)]
    pub scalar: Option<String>,
    /// A geometric scalar instead of an array, for a bare mesh: `distance` (to the boundary).
    #[arg(long)]
    pub field: Option<String>,
    /// Mesh format, whatever the content and the extension say: vtu, vtk, msh or mesh.
    #[arg(long)]
    pub format: Option<MeshFormat>,
    /// Replace NaN/Inf input values by this value instead of refusing the input.
    #[arg(long, allow_negative_numbers = true)]
    pub nan_as: Option<f64>,
    /// A 4D volume file: the time point to read (from 0).
    #[arg(long)]
    pub frame: Option<usize>,
}

impl ReadArgs {
    /// When `input` is a volume file (NIfTI, NRRD, VTK image data, TIFF, DICOM, Zarr: found by
    /// [`volume::sniff`], or any `s3://`/`http(s)://` location, read as Zarr), these arguments
    /// with its header's world dims, type and spacing as the grid's; `None` for raw grids,
    /// meshes and synthetic fields.
    pub fn resolve_volume(&self, input: &str) -> Result<Option<ReadArgs>, PrepareError> {
        let path = Path::new(input);
        let raw = self.grid.dims.is_some()
            || path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("raw"));
        if input.starts_with("synthetic:") || raw || self.format.is_some() {
            return Ok(None);
        }
        let format = match volume::sniff(path) {
            Some(VolumeFormat::Raw) => return Ok(None),
            Some(f) => f,
            None if volume::is_url(path) => VolumeFormat::Zarr,
            None => return Ok(None),
        };
        if let Some(flag) = self.field.as_ref().map(|_| "--field") {
            return Err(PrepareError::Usage(format!(
                "{flag} applies to mesh files (.vtu, .vtk, .msh); {input} is a {} volume",
                format.name()
            )));
        }
        let options = VolumeOptions {
            raw: None,
            scalar: self.scalar.as_deref().map(ScalarChoice::parse),
            frame: self.frame,
        };
        let vol = Volume::open(path, Some(format), &options)?;
        let h = vol.header().clone();
        tracing::info!(
            format = format.name(),
            dims = ?vol.dims,
            dtype = %vol.dtype,
            spacing = ?vol.spacing,
            origin = ?vol.origin,
            frame = h.frame.as_deref().unwrap_or("-"),
            unit = h.length_unit.as_deref().unwrap_or("-"),
            rescale = ?h.rescale,
            "volume"
        );
        for note in &h.notes {
            tracing::info!("{input}: {note}");
        }
        let mut r = self.clone();
        r.grid = GridArgs {
            dims: Some(vol.dims),
            dtype: vol.dtype.name().to_string(),
            spacing: vol.spacing,
            volume: Some(VolumeInput {
                format,
                options,
                header: h,
                origin: vol.origin,
            }),
        };
        Ok(Some(r))
    }
}

/// What `tetwave-server prepare` is asked to do (its command-line arguments, which are also the
/// library's options).
#[derive(Debug, Clone, clap::Args)]
pub struct PrepareOptions {
    /// `synthetic:harmonic` (the embedded default), `synthetic:linear`, a raw grid (.raw or with
    /// --dims), or an unstructured tet mesh (.vtu, .vtk, .msh).
    pub input: String,
    /// Where to write the store: a directory, or `s3://BUCKET/PREFIX` (any S3-compatible
    /// service; endpoint and credentials from AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID,
    /// AWS_SECRET_ACCESS_KEY, AWS_REGION, AWS_ALLOW_HTTP), written through a local staging
    /// folder (--stage) and copied up, the manifest last.
    #[arg(long)]
    pub out: PathBuf,
    /// Staging folder for a store written to object storage (it needs the store's size free).
    /// Default: the system's temporary folder.
    #[arg(long)]
    pub stage: Option<PathBuf>,
    /// Levels of Bey refinement. Default: for a mesh, the fewest whose finest leaves are on
    /// average no larger than its tets, within --memory; for a raw grid, the most levels whose
    /// voxel lattice pads the grid by at most half its points (see --base); 5 for a synthetic
    /// field.
    #[arg(long)]
    pub levels: Option<u8>,
    /// Base mesh: `auto`, `box5` (bounding box in 5 tets), `box6` (6 Kuhn tets) or a coarse tet
    /// mesh file. `auto` is box5, except for a raw grid: Kuhn boxes whose finest vertices are the
    /// voxels (no resampling; the lattice's padding, under one box per axis, is clipped away), so
    /// --max-error bounds every voxel of the input; a non-cubic grid gets boxes along its long
    /// axes. An explicit box5/box6/file resamples a grid by trilinear interpolation.
    #[arg(long, default_value = "auto")]
    pub base: BaseSpec,
    /// Quantize details uniformly to this many bits (8..=24); lossless f32 when absent.
    #[arg(long, conflicts_with = "max_error")]
    pub bits: Option<u8>,
    /// Keep every reconstructed vertex within this of its sample: `E` in the field's units, or
    /// `E%` of the value range (e.g. `0.1%`). The quantizer's step and code width follow from
    /// it; the manifest records the bound and the measured error, and `verify` checks them.
    /// Lossless f32 when absent.
    #[arg(long, value_parser = parse_max_error)]
    pub max_error: Option<ErrorBound>,
    /// Also write a preview: the coarse levels analysed a second time within this error (`E`, or
    /// `E%` of the value range, e.g. `10%`), which `serve` sends a new session first, so that a
    /// thin link shows the whole volume coarsely after a few hundred bytes (docs/benchmarks.md).
    /// Costs a second analysis. Needs at least 2 levels and a bound coarser than the store's.
    #[arg(long, value_parser = parse_max_error)]
    pub preview: Option<ErrorBound>,
    /// How new vertices are predicted: `axes` (SZ3's cubic interpolation along the grid's axes,
    /// level by level: fewer bytes on smooth fields, see docs/benchmarks.md; needs `--base box6`
    /// and data at every vertex), `parent` (the refined tet's parent's
    /// quadratic: any base, meshes with an outside), or `auto`: `axes` where it applies.
    #[arg(long, value_enum, default_value_t = PredictorChoice::Auto)]
    pub predictor: PredictorChoice,
    #[command(flatten)]
    pub read: ReadArgs,
    /// Memory `prepare` may use, e.g. `4G`, `512M` (default: a sixth of this machine's memory).
    /// Bounds the default levels of a mesh: the most whose samples and analysis fit (at
    /// [`PREPARE_BYTES_PER_VERTEX`] a vertex).
    #[arg(long, value_parser = parse_bytes)]
    pub memory: Option<u64>,
    /// Also write `reference.f32`: the sampled value of every vertex, 4 bytes each, as large as
    /// the input and never streamed. Without it, `verify --input` checks the store against its
    /// input.
    #[arg(long)]
    pub keep_reference: bool,
    #[command(flatten)]
    pub by_parts: PartsArgs,
    /// Show progress bars (on a terminal, without --json).
    #[arg(skip)]
    pub progress: bool,
}

impl PrepareOptions {
    pub fn new(input: &str, out: &Path) -> Self {
        PrepareOptions {
            input: input.to_string(),
            out: out.to_path_buf(),
            stage: None,
            levels: None,
            base: BaseSpec::Auto,
            bits: None,
            max_error: None,
            preview: None,
            predictor: PredictorChoice::Auto,
            read: ReadArgs::default(),
            memory: None,
            keep_reference: false,
            by_parts: PartsArgs::default(),
            progress: false,
        }
    }
}

/// The summary `prepare --json` prints.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub dataset: String,
    pub store: String,
    pub base: String,
    pub base_tets: u64,
    pub levels: u8,
    pub tets_total: u64,
    pub leaves: u64,
    pub nodes: u64,
    pub vertices: u64,
    pub coefficients: u64,
    /// Bytes of what is streamed: base mesh, node records, coefficients and index.
    pub bytes: u64,
    /// Bytes of the verification reference (`reference.f32`, `--keep-reference`; not streamed).
    pub reference_bytes: u64,
    /// Bytes of the preview (`preview.bin`, `--preview`; a server sends part of it to new
    /// sessions; not counted in `bytes`).
    pub preview_bytes: u64,
    /// Bytes of the domain's level set (`levelset.f32`, not streamed; 0 when the input has no
    /// outside).
    pub levelset_bytes: u64,
    /// Bytes of its near band (`levelset_near.bin`, what `/v1/levelset` sends streaming clients;
    /// counted in `bytes`).
    pub levelset_near_bytes: u64,
    pub encoding: String,
    /// `parent` or `axes` (`--predictor`).
    pub predictor: &'static str,
    pub max_abs_error: f64,
    pub max_error_bound: f64,
    pub value_range: [f32; 2],
    /// The input's scalar range (the manifest's `source_value_range`), when known.
    pub source_value_range: Option<[f32; 2]>,
    pub outside_vertices: u64,
    pub empty_base_tets: u64,
    pub seconds: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub import: Option<CleanReport>,
    /// A volume file's header, as read (world frame: axes ascending, x fastest).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub volume: Option<VolumeSummary>,
}

/// What `prepare` read of a volume file's header.
#[derive(Debug, Clone, Serialize)]
pub struct VolumeSummary {
    pub format: &'static str,
    /// Voxels along the world axes (the file's axes permuted as its orientation says).
    pub dims: [usize; 3],
    /// The type read (the file's; f32 when a rescale applies).
    pub dtype: String,
    pub spacing: [f64; 3],
    /// World position of the lowest corner voxel (the store's lattice starts at 0 there).
    pub origin: [f64; 3],
    /// The world frame (`RAS`, `LPS`) when the file states one.
    pub frame: Option<String>,
    pub length_unit: Option<String>,
    pub value_unit: Option<String>,
    /// `(slope, intercept)` applied to the stored values.
    pub rescale: Option<(f64, f64)>,
    pub notes: Vec<String>,
}

impl VolumeSummary {
    pub fn of(grid: &GridArgs) -> Option<Self> {
        let v = grid.volume.as_ref()?;
        Some(VolumeSummary {
            format: v.format.name(),
            dims: grid.dims?,
            dtype: grid.dtype.clone(),
            spacing: grid.spacing,
            origin: v.origin,
            frame: v.header.frame.clone(),
            length_unit: v.header.length_unit.clone(),
            value_unit: v.header.value_unit.clone(),
            rescale: v.header.rescale,
            notes: v.header.notes.clone(),
        })
    }
}

/// The input's domain, where it is smaller than the semi-regular mesh.
enum Domain {
    /// An unstructured mesh's boundary surface (inside where a sample exists).
    Mesh(BoundaryDistance),
    /// A raw grid's box of voxels, inside a lattice that reaches past it (padding, whose samples
    /// repeat the nearest voxel).
    Box { lo: [f64; 3], hi: [f64; 3] },
}

/// What `prepare` reads from its input besides the samples.
struct Loaded {
    source: Source,
    dataset: String,
    import: Option<CleanReport>,
    /// The input's scalar range as the importer read it (a mesh's point values, a raw grid's
    /// samples); `None` for synthetic fields and `--field distance`, whose samples are computed at
    /// each resampled point rather than interpolated from the input's values.
    source_range: Option<(f32, f32)>,
    /// A mesh's boundary surface, for the level set (`None`: the input has no outside).
    boundary: Option<BoundaryDistance>,
    /// A mesh's tet count and volume (`None` for grids and synthetic fields): what its default
    /// levels follow ([`mesh_levels`]).
    resolution: Option<(u64, f64)>,
}

fn load_source(input: &str, o: &ReadArgs) -> Result<Loaded, PrepareError> {
    if let Some(v) = o.nan_as {
        if !(v.is_finite() && (v as f32).is_finite()) {
            return Err(PrepareError::Usage(format!(
                "--nan-as {v}: give a finite value that fits in f32"
            )));
        }
    }
    let path = PathBuf::from(input);
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let grid = input.starts_with("synthetic:") || o.grid.dims.is_some() || ext == "raw";
    if o.frame.is_some() && o.grid.volume.is_none() {
        return Err(PrepareError::Usage(format!(
            "--frame applies to 4D volume files (NIfTI, NRRD, Zarr, ...); {input} is not one"
        )));
    }
    let mesh_only = [
        ("--scalar", o.scalar.is_some() && o.grid.volume.is_none()),
        ("--field", o.field.is_some()),
        ("--format", o.format.is_some()),
    ];
    if let (true, Some((flag, _))) = (grid, mesh_only.iter().find(|(_, given)| *given)) {
        return Err(PrepareError::Usage(format!(
            "{flag} applies to mesh files (.vtu, .vtk, .msh); {} is a grid",
            input
        )));
    }
    if let Some(name) = input.strip_prefix("synthetic:") {
        let s = Synthetic::parse(name)
            .ok_or_else(|| PrepareError::UnknownSynthetic(name.to_string()))?;
        return Ok(Loaded {
            source: Source::Synthetic(s),
            dataset: s.name().to_string(),
            import: None,
            source_range: None,
            boundary: None,
            resolution: None,
        });
    }
    let stem = dataset_name(&path, input);
    if o.grid.dims.is_some() || ext == "raw" {
        let grid = o.grid.read(&path, o.nan_as)?;
        return Ok(Loaded {
            source_range: grid.value_range(),
            source: Source::Raw(grid),
            dataset: stem,
            import: None,
            boundary: None,
            resolution: None,
        });
    }
    if o.format.is_some() || import::format_of(&path).is_some() || path.exists() {
        let mesh = import::read_mesh(&path, o.format)?;
        let options = ImportOptions {
            scalar: o.scalar.as_deref(),
            field: o.field.as_deref(),
            nan_as: o.nan_as,
        };
        let (clean, report) =
            unstructured::clean_import(mesh, &options).map_err(|source| PrepareError::Clean {
                path: path.clone(),
                source,
            })?;
        if report.tets_reoriented > 0 || report.tets_dropped > 0 {
            tracing::warn!(
                reoriented = report.tets_reoriented,
                dropped_degenerate = report.tets_dropped_degenerate,
                dropped_duplicate = report.tets_dropped_duplicate,
                "fixed inverted tets and dropped zero-volume and duplicate tets"
            );
        }
        let bounds = unstructured::bbox(&clean.points);
        let loc = Locator::new(&clean);
        let source_range = (!clean.distance)
            .then(|| {
                clean.values.iter().fold(None, |r: Option<(f32, f32)>, &v| {
                    let v = v as f32;
                    Some(r.map_or((v, v), |(lo, hi)| (lo.min(v), hi.max(v))))
                })
            })
            .flatten();
        let boundary = BoundaryDistance::new(&clean.points, &clean.tets);
        let volume = tetwave_protocol::base::total_volume(&clean.points, &clean.tets);
        let resolution = Some((clean.tets.len() as u64, volume));
        return Ok(Loaded {
            source: Source::Mesh(Box::new(loc), bounds),
            dataset: stem,
            import: Some(report),
            source_range,
            boundary: Some(boundary),
            resolution,
        });
    }
    Err(PrepareError::UnknownInput(input.to_string()))
}

/// A store's dataset name: the input file's name without its extensions (`brain.nii.gz`:
/// `brain`), or `input` when it has none.
pub(crate) fn dataset_name(path: &Path, input: &str) -> String {
    path.file_name()
        .map(|s| s.to_string_lossy().to_string())
        .and_then(|s| {
            let s = s.strip_suffix(".gz").unwrap_or(&s);
            let s = s.rsplit_once('.').map_or(s, |(stem, _)| stem);
            (!s.is_empty()).then(|| s.to_string())
        })
        .unwrap_or_else(|| input.to_string())
}

/// What `prepare` holds a vertex of the semi-regular mesh with: measured 31 bytes at 513³
/// (`prepare` of a grid: samples, reference values, the analysis' cells, details and
/// coefficients); a mesh adds its level set, 4 more.
pub const PREPARE_BYTES_PER_VERTEX: u64 = 40;

/// `--memory`'s default: a sixth of this machine's memory (4 GiB on 24 GiB).
pub fn default_memory() -> u64 {
    store::machine_memory() / 6
}

/// A mesh's default levels: the fewest whose finest leaves are, on average, no larger than the
/// input's tets (the mean leaf volume of `spec`'s base over `bounds` at most the mesh's `volume`
/// over its `tets`), so that the store is as fine as the mesh is, on the whole, and no finer;
/// at least 1, and at most what `memory` holds at [`PREPARE_BYTES_PER_VERTEX`] a vertex (and
/// the analysis can index), with a warning when that caps it.
pub fn mesh_levels(
    spec: &BaseSpec,
    bounds: ([f64; 3], [f64; 3]),
    tets: u64,
    volume: f64,
    memory: u64,
) -> Result<u8, PrepareError> {
    let mut base = bare_base(spec, bounds)?;
    let base_volume = tetwave_protocol::base::total_volume(&base.positions, &base.tets);
    let n_base = base.tets.len() as f64;
    let input_tet = volume / tets.max(1) as f64;
    let fits = |base: &mut tetwave_protocol::BaseMesh, l: u8| {
        base.levels = l;
        base.forest()
            .checked_nodes()
            .is_some_and(|n| n <= MAX_NODES)
            && base.vertex_keys().vertex_count() * PREPARE_BYTES_PER_VERTEX <= memory
    };
    let mut levels = 1;
    while levels < tetwave_protocol::hierarchy::MAX_LEVELS
        && base_volume / (n_base * 8f64.powi(levels as i32)) > input_tet
    {
        if !fits(&mut base, levels + 1) {
            tracing::warn!(
                levels,
                memory,
                "the mesh's {tets} tets ask for more levels than --memory holds (at \
                 {PREPARE_BYTES_PER_VERTEX} bytes a vertex): its store is coarser than the mesh"
            );
            return Ok(levels);
        }
        levels += 1;
    }
    tracing::info!(
        levels,
        input_tets = tets,
        leaves = (n_base * 8f64.powi(levels as i32)) as u64,
        "levels for the mesh: the fewest whose leaves are on average no larger than its tets \
         (--levels to choose)"
    );
    Ok(levels)
}

/// `spec`'s base mesh over `bounds`, without values: what sizes a hierarchy before it is sampled.
fn bare_base(
    spec: &BaseSpec,
    bounds: ([f64; 3], [f64; 3]),
) -> Result<tetwave_protocol::BaseMesh, PrepareError> {
    let (positions, tets) = crate::resample::base_mesh(spec, bounds)?;
    Ok(tetwave_protocol::BaseMesh {
        levels: 0,
        positions,
        tets,
        values: Vec::new(),
        empty: Vec::new(),
        predictor: Default::default(),
    })
}

/// Refuses, before anything is allocated, a hierarchy whose in-memory preparation needs more than
/// this machine's memory (at [`PREPARE_BYTES_PER_VERTEX`] a vertex): one error line instead of
/// the system stopping the process half way.
fn check_fits_memory(
    spec: &BaseSpec,
    bounds: ([f64; 3], [f64; 3]),
    levels: u8,
) -> Result<(), PrepareError> {
    if levels > tetwave_protocol::hierarchy::MAX_LEVELS {
        return Err(ResampleError::TooManyLevels(levels).into());
    }
    let mut base = bare_base(spec, bounds)?;
    base.levels = levels;
    let vertices = base.vertex_keys().vertex_count();
    let need = vertices.saturating_mul(PREPARE_BYTES_PER_VERTEX);
    let have = store::machine_memory();
    if need > have {
        return Err(PrepareError::TooLargeForMemory {
            vertices,
            levels,
            need_gib: need as f64 / (1u64 << 30) as f64,
            have_gib: have as f64 / (1u64 << 30) as f64,
        });
    }
    Ok(())
}

/// A byte count: `N`, or `N` with `K`, `M`, `G`, `T` (powers of 1024; `KiB`, `GB` … read alike).
fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let x: f64 = num
        .parse()
        .map_err(|_| format!("{s:?}: give a size such as 4G, 512M or 1073741824"))?;
    let shift = match unit
        .trim()
        .to_ascii_uppercase()
        .trim_end_matches(['B', 'I'])
    {
        "" => 0,
        "K" => 10,
        "M" => 20,
        "G" => 30,
        "T" => 40,
        _ => return Err(format!("{s:?}: unknown unit (K, M, G or T)")),
    };
    let bytes = x * (1u64 << shift) as f64;
    if !(bytes >= 1.0 && bytes < u64::MAX as f64) {
        return Err(format!("{s:?}: give a positive size"));
    }
    Ok(bytes as u64)
}

/// `--base auto` for a raw grid: the Kuhn boxes whose finest vertices are its voxels
/// ([`VoxelLattice`]), their levels, and the voxels' box as the domain when the lattice pads.
fn voxel_base(
    g: &RawGrid,
    levels: Option<u8>,
) -> Result<(BaseSpec, u8, Option<Domain>), PrepareError> {
    let l = VoxelLattice::fit(g.dims, g.spacing, levels, indexable)?;
    let ([x, y, z], [px, py, pz], [cx, cy, cz]) = (g.dims, l.points, l.cells);
    let pads = l.pads(g.dims);
    tracing::info!(
        "voxel-exact: the {x}×{y}×{z} voxels are vertices of {cx}×{cy}×{cz} Kuhn boxes refined \
         {} times ({px}×{py}×{pz} points{})",
        l.levels,
        if pads { "; the padding is clipped" } else { "" }
    );
    let spec = BaseSpec::KuhnBoxes {
        lo: [0.0; 3],
        hi: l.hi,
        cells: l.cells,
    };
    let (lo, hi) = g.bounds();
    Ok((spec, l.levels, pads.then_some(Domain::Box { lo, hi })))
}

/// Resamples, analyses and writes a store.
pub fn prepare(o: &PrepareOptions) -> Result<Summary, PrepareError> {
    let resolved;
    let o = match o.read.resolve_volume(&o.input)? {
        Some(read) => {
            resolved = PrepareOptions { read, ..o.clone() };
            &resolved
        }
        None => o,
    };
    if let Some(to) = remote::remote_out(o)? {
        return remote::prepare_to(o, &to);
    }
    match (o.by_parts.parts, o.by_parts.part, o.by_parts.finish) {
        (Some(n), None, true) => return parts::finish(o, n),
        (Some(_), Some(_), _) => {
            return Err(PrepareError::Usage(
                "prepare one part with parts::prepare_part (`prepare --parts N --part K`)".into(),
            ))
        }
        (Some(n), None, false) => {
            return Err(PrepareError::Usage(format!(
                "--parts {n} needs --part K (0 to {}) to prepare one part, or --finish to write \
                 the store from all of them",
                n.saturating_sub(1)
            )))
        }
        (None, _, _) => {}
    }
    let t0 = Instant::now();
    // a raw grid's voxel lattice is known from its dims: refuse one too large before reading it
    // (a file of another size than its dims is left to the reader, which says so)
    let dims_match_file = |dims: [usize; 3]| {
        let dtype = RawType::parse(&o.read.grid.dtype);
        let voxels = dims.iter().try_fold(1u64, |a, &n| a.checked_mul(n as u64));
        let len = std::fs::metadata(&o.input).map(|m| m.len()).ok();
        matches!((dtype, voxels, len), (Some(t), Some(v), Some(l))
            if v.checked_mul(t.bytes() as u64) == Some(l))
    };
    if let (Some(dims), BaseSpec::Auto, true) = (
        o.read.grid.dims,
        &o.base,
        o.read
            .grid
            .dims
            .is_some_and(|d| o.read.grid.volume.is_some() || dims_match_file(d)),
    ) {
        let l = VoxelLattice::fit(dims, o.read.grid.spacing, o.levels, indexable)?;
        let memory = o.memory.unwrap_or_else(default_memory);
        let dtype = RawType::parse(&o.read.grid.dtype).expect("checked with the file's size");
        let whole = parts::part_bytes(&l, dims, dtype.bytes(), l.cells[1], l.cells[2])
            + parts::PROCESS_OVERHEAD;
        if whole > memory {
            match parts::out_of_core_refusal(o) {
                None => {
                    tracing::info!(
                        need = whole,
                        memory,
                        "the grid's hierarchy does not fit --memory: preparing it by parts"
                    );
                    return parts::prepare_out_of_core(o, memory);
                }
                Some(why) => tracing::info!(
                    need = whole,
                    memory,
                    "the grid's hierarchy does not fit --memory, and cannot be prepared by parts \
                     ({why}): preparing it whole"
                ),
            }
        }
        let spec = BaseSpec::KuhnBoxes {
            lo: [0.0; 3],
            hi: l.hi,
            cells: l.cells,
        };
        check_fits_memory(&spec, ([0.0; 3], l.hi), l.levels)?;
    }
    let Loaded {
        source,
        dataset,
        import,
        source_range,
        boundary,
        resolution,
    } = load_source(&o.input, &o.read)?;
    let (base, levels, domain) = match (&o.base, &source) {
        (BaseSpec::Auto, Source::Raw(g)) => voxel_base(g, o.levels)?,
        (spec, source) => {
            if let Source::Raw(_) = source {
                tracing::info!(
                    "--base {}: the grid is resampled by trilinear interpolation (omit --base \
                     to keep every voxel)",
                    spec.name()
                );
            }
            let domain = boundary.map(Domain::Mesh);
            let levels = match (o.levels, resolution) {
                (Some(l), _) => l,
                (None, Some((tets, volume))) => {
                    let memory = o.memory.unwrap_or_else(default_memory);
                    mesh_levels(spec, source.bounds(), tets, volume, memory)?
                }
                (None, None) => 5,
            };
            (spec.clone(), levels, domain)
        }
    };
    check_fits_memory(&base, source.bounds(), levels)?;
    tracing::info!(input = %o.input, levels, "resampling");
    let mut r = resample(&source, &base, levels)?;
    let box6 = tetwave_protocol::axes::check_base(&r.base).is_ok();
    if o.predictor == PredictorChoice::Axes && !box6 {
        return Err(PrepareError::Usage(
            "--predictor axes needs one box of 6 Kuhn tets (--base box6, or a raw grid whose \
             voxel lattice is one box): its refined vertices are a grid"
                .into(),
        ));
    }
    r.base.predictor = match o.predictor {
        PredictorChoice::Parent => Predictor::Parent,
        PredictorChoice::Axes => Predictor::Axes,
        PredictorChoice::Auto
            if box6
                && r.outside == 0
                && r.samples.iter().all(|v| v.abs() <= AXES_MAX_MAGNITUDE) =>
        {
            Predictor::Axes
        }
        PredictorChoice::Auto => Predictor::Parent,
    };
    let predictor = r.base.predictor;
    drop(source);
    let outside = r.outside;
    // only an input with an outside needs clipping (inside, every vertex's level set is ≥ 0): a
    // mesh's, whose level set is stored whole and as a near band; a grid's padding, whose level
    // set is the voxels' box, which every reader computes from positions
    let (levelset, levelset_near) = match domain {
        Some(Domain::Mesh(b)) if outside > 0 => {
            tracing::info!(vertices = r.samples.len(), "level set of the domain");
            let l = signed_distance(&r, &b)?;
            (Some(l.values), Some(l.near))
        }
        Some(Domain::Box { lo, hi }) => (None, Some(NearLevelSet::of_box(lo, hi)?)),
        _ => (None, None),
    };
    tracing::info!(vertices = r.samples.len(), outside, "analysing");
    let precision = match (o.bits, o.max_error) {
        (None, None) => Precision::Lossless,
        (Some(b), None) => Precision::Bits(b),
        (None, Some(e)) => Precision::MaxError(e),
        (Some(_), Some(_)) => {
            return Err(PrepareError::Usage(
                "give --bits or --max-error, not both".into(),
            ))
        }
    };
    if o.preview.is_some() && levels < 2 {
        return Err(PrepareError::Usage(
            "--preview needs at least 2 levels (it covers the coarse ones)".into(),
        ));
    }
    let preview_input = o.preview.map(|_| r.clone());
    let a = analyze_hierarchy(r, precision, o.progress)?;
    let preview = match (o.preview, preview_input) {
        (Some(e), Some(r)) => {
            tracing::info!("analysing the preview");
            let p = analyze_hierarchy(r, Precision::MaxError(e), o.progress)?;
            Some(preview_nodes(&a, &p)?)
        }
        _ => None,
    };
    let base_name = base.name();
    let meta = StoreMeta {
        dataset: dataset.clone(),
        source: o.input.clone(),
        base: base_name.clone(),
        outside_vertices: outside,
        source_value_range: source_range,
        levelset,
        levelset_near,
        preview,
        keep_reference: o.keep_reference,
        physical: o.read.grid.volume.as_ref().and_then(VolumeInput::physical),
    };
    let m = store::write(&o.out, &a.content(), meta)?;
    let mut summary = Summary::of(&m, o, predictor, import, t0);
    summary.volume = VolumeSummary::of(&o.read.grid);
    Ok(summary)
}

impl Summary {
    /// What `prepare` wrote, from the manifest it wrote.
    fn of(
        m: &store::Manifest,
        o: &PrepareOptions,
        predictor: Predictor,
        import: Option<CleanReport>,
        t0: Instant,
    ) -> Summary {
        let file = |name: &str| m.files.get(name).map(|f| f.bytes).unwrap_or(0);
        let bytes = m
            .files
            .iter()
            .filter(|(k, _)| !matches!(k.as_str(), REFERENCE_FILE | "levelset.f32" | PREVIEW_FILE))
            .map(|(_, f)| f.bytes)
            .sum();
        Summary {
            dataset: m.dataset.clone(),
            store: o.out.display().to_string(),
            base: m.base.clone(),
            base_tets: m.base_tets,
            levels: m.levels,
            tets_total: m.counts.tets_total,
            leaves: m.counts.leaves,
            nodes: m.counts.nodes,
            vertices: m.counts.vertices,
            coefficients: m.counts.coefficients,
            bytes,
            reference_bytes: file(REFERENCE_FILE),
            preview_bytes: file(PREVIEW_FILE),
            levelset_bytes: file("levelset.f32"),
            levelset_near_bytes: file("levelset_near.bin"),
            encoding: match m.encoding {
                store::Encoding::F32 => "f32".into(),
                store::Encoding::Quantized { bits, .. } => format!("quantized{bits}"),
            },
            predictor: predictor.name(),
            max_abs_error: m.max_abs_error,
            max_error_bound: m.max_error_bound,
            value_range: m.value_range,
            source_value_range: m.source_value_range,
            outside_vertices: m.counts.outside_vertices,
            empty_base_tets: m.counts.empty_base_tets,
            seconds: t0.elapsed().as_secs_f64(),
            import,
            volume: None,
        }
    }
}

/// What `verify` measured.
#[derive(Debug, Clone, Serialize)]
pub struct VerifyReport {
    pub store: String,
    pub vertices: u64,
    pub nodes: u64,
    /// What synthesis was compared with: `reference` (the samples the store keeps,
    /// `--keep-reference`), `input` (the input read and sampled again as `prepare` did), or
    /// `bound` (neither: every vertex synthesizes to a finite value, and where the input has
    /// data everywhere, within the value range widened by the bound).
    pub against: &'static str,
    /// Max |synthesis − sample| over the vertices compared; `None` against `bound`.
    pub max_abs_error: Option<f64>,
    pub max_error_bound: f64,
    /// Root-mean-square of synthesis − sample over the vertices compared (for PSNR against the
    /// samples); `None` against `bound`.
    pub rms_error: Option<f64>,
    /// Vertices whose synthesis equals their sample bit for bit; `None` against `bound`.
    pub exact_vertices: Option<u64>,
    /// The check against the input (`verify --input`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub input: Option<InputCheck>,
    pub seconds: f64,
}

/// `verify --input`: the store's reconstruction against the input it was prepared from: at every
/// voxel of a raw grid whose voxels are the store's vertices, or at every vertex where the input
/// (a synthetic field, a mesh) has data, sampled again on the store's base mesh as `prepare` did.
#[derive(Debug, Clone, Serialize)]
pub struct InputCheck {
    /// `voxels` (of the raw grid) or `vertices` (of the store, inside the input's domain).
    pub points_are: &'static str,
    /// How many were compared.
    pub points: u64,
    pub max_abs_error: f64,
    pub rms_error: f64,
    /// Points whose reconstruction is bit-exact.
    pub exact_points: u64,
    /// The input's value range, and the store's (`value_range` of its manifest).
    pub input_range: [f32; 2],
    pub store_range: [f32; 2],
}

/// Max, sum of squares and bit-exact count of synthesis − sample over the points compared.
#[derive(Default)]
struct Errors {
    points: u64,
    max: f64,
    sum_sq: f64,
    exact: u64,
}

impl Errors {
    fn add(&mut self, got: f32, want: f64) {
        self.points += 1;
        if got as f64 == want {
            self.exact += 1;
        }
        let d = got as f64 - want;
        // NaN (a synthesis that is not finite) poisons the max
        self.max = if d.is_nan() {
            f64::NAN
        } else {
            self.max.max(d.abs())
        };
        self.sum_sq += d * d;
    }

    fn rms(&self) -> f64 {
        (self.sum_sq / self.points.max(1) as f64).sqrt()
    }

    /// Fails when the max exceeds `bound` (or is NaN).
    fn within(&self, bound: f64, what: impl FnOnce() -> String) -> Result<(), PrepareError> {
        if self.max > bound || self.max.is_nan() {
            return Err(PrepareError::VerifyFailed {
                what: what(),
                error: self.max,
                bound,
            });
        }
        Ok(())
    }

    fn input_check(
        &self,
        points_are: &'static str,
        input: [f32; 2],
        store: [f32; 2],
    ) -> InputCheck {
        InputCheck {
            points_are,
            points: self.points,
            max_abs_error: self.max,
            rms_error: self.rms(),
            exact_points: self.exact,
            input_range: input,
            store_range: store,
        }
    }
}

/// A store whose checksums hold, with every vertex synthesized from its nodes.
struct Synthesized {
    store: Store,
    values: Vec<f32>,
    t0: Instant,
}

impl Synthesized {
    fn of(dir: &Path) -> Result<Self, PrepareError> {
        let t0 = Instant::now();
        let store = Store::open(dir)?;
        store.check_sums()?;
        let values = store.synthesize_all()?;
        Ok(Synthesized { store, values, t0 })
    }

    fn what(&self) -> String {
        self.store.dir.display().to_string()
    }

    /// Compares with the kept samples, or checks the values against the manifest's range and
    /// bound when the store keeps none.
    fn report(&self) -> Result<VerifyReport, PrepareError> {
        let m = &self.store.manifest;
        let bound = m.max_error_bound;
        let mut report = VerifyReport {
            store: self.what(),
            vertices: self.values.len() as u64,
            nodes: m.counts.nodes,
            against: "bound",
            max_abs_error: None,
            max_error_bound: bound,
            rms_error: None,
            exact_vertices: None,
            input: None,
            seconds: 0.0,
        };
        match self.store.read_reference()? {
            Some(reference) => {
                let mut e = Errors::default();
                for (&a, &b) in self.values.iter().zip(&reference) {
                    e.add(a, b as f64);
                }
                e.within(bound, || self.what())?;
                report.against = "reference";
                report.max_abs_error = Some(e.max);
                report.rms_error = Some(e.rms());
                report.exact_vertices = Some(e.exact);
            }
            None => {
                // inside samples lie in the value range, so their synthesis lies within the bound
                // of it; outside vertices (a mesh's) carry predictions, which may lie beyond
                let [lo, hi] = m.value_range.map(|v| v as f64);
                let everywhere = m.counts.outside_vertices == 0;
                let bad = self.values.iter().position(|&v| {
                    let v = v as f64;
                    !v.is_finite() || (everywhere && (v < lo - bound || v > hi + bound))
                });
                if let Some(k) = bad {
                    // its sample lies in the range: the error is at least the distance to it
                    let v = self.values[k] as f64;
                    return Err(PrepareError::VerifyFailed {
                        what: format!(
                            "{}: vertex key {k} synthesizes to {v}, outside the value range \
                             [{lo}, {hi}] (so at least this far from its sample)",
                            self.what(),
                        ),
                        error: if v.is_finite() {
                            (lo - v).max(v - hi)
                        } else {
                            v
                        },
                        bound,
                    });
                }
            }
        }
        Ok(report)
    }

    fn finish(&self, mut report: VerifyReport) -> VerifyReport {
        report.seconds = self.t0.elapsed().as_secs_f64();
        report
    }
}

/// Re-runs synthesis from the store's base mesh and nodes and compares every vertex with the
/// samples it keeps (`--keep-reference`); a store without them is checked against its bound
/// ([`VerifyReport::against`]). Fails if a checksum is wrong, a node is malformed, or the error
/// exceeds the manifest's bound.
pub fn verify(dir: &Path) -> Result<VerifyReport, PrepareError> {
    let s = Synthesized::of(dir)?;
    let report = s.report()?;
    Ok(s.finish(report))
}

/// [`verify`], and then every voxel of `grid` (the raw grid the store was prepared from, as
/// `prepare` read it) against the store's reconstruction at its vertex: fails when a voxel is not
/// a vertex (a store resampled with an explicit `--base`), when the store holds values at
/// points between voxels, or when a voxel's error exceeds the manifest's bound.
pub fn verify_input(dir: &Path, grid: &RawGrid) -> Result<VerifyReport, PrepareError> {
    let s = Synthesized::of(dir)?;
    let mut report = s.report()?;
    let (store, values) = (&s.store, &s.values);
    let keys = store.base.vertex_keys();
    let [nx, ny, nz] = grid.dims;
    let total = nx * ny * nz;
    let not_exact = |why: String| {
        PrepareError::Usage(format!(
            "{}: the store's vertices are not the voxels of this grid ({why}); a store prepared \
             with an explicit --base resamples the grid, and only `--base auto` keeps every voxel",
            dir.display()
        ))
    };
    // per voxel: seen (the base mesh's shared vertices have one key, so twice is an error)
    let mut seen = vec![false; total];
    let mut stray: Option<[f64; 3]> = None;
    let mut e = Errors::default();
    for (entity, _) in keys.entities() {
        keys.for_each_in(entity, |key, tet, w| {
            let p = store.base.position(tet, &w);
            let mut idx = [0usize; 3];
            let mut in_grid = true;
            let mut on_voxel = true;
            for a in 0..3 {
                let x = p[a] / grid.spacing[a];
                let r = x.round();
                on_voxel &= (x - r).abs() <= 1e-6 * x.abs().max(1.0);
                in_grid &= r >= 0.0 && (r as usize) < grid.dims[a] && x > -0.5;
                idx[a] = r.max(0.0) as usize;
            }
            if !in_grid {
                return; // padding
            }
            if !on_voxel {
                stray.get_or_insert(p);
                return;
            }
            seen[idx[0] + nx * (idx[1] + ny * idx[2])] = true;
            e.add(values[key as usize], grid.voxel(idx));
        });
    }
    if let Some(p) = stray {
        return Err(not_exact(format!("a vertex lies between voxels at {p:?}")));
    }
    if let Some(i) = seen.iter().position(|s| !s) {
        let (x, y, z) = (i % nx, i / nx % ny, i / (nx * ny));
        return Err(not_exact(format!("voxel ({x}, {y}, {z}) is no vertex")));
    }
    e.within(store.manifest.max_error_bound, || {
        format!("{} against the input's voxels", dir.display())
    })?;
    let (lo, hi) = grid.value_range().unwrap_or((f32::NAN, f32::NAN));
    report.input = Some(e.input_check("voxels", [lo, hi], store.manifest.value_range));
    Ok(s.finish(report))
}

/// [`verify`], and then the input (`input` read with `read`, as `prepare` took it): a raw grid
/// voxel by voxel ([`verify_input`]); anything else (a synthetic field, a mesh) sampled again on
/// the store's base mesh, every vertex where it has data against the store's reconstruction.
pub fn verify_source(
    dir: &Path,
    input: &str,
    read: &ReadArgs,
) -> Result<VerifyReport, PrepareError> {
    let resolved = read.resolve_volume(input)?;
    let loaded = load_source(input, resolved.as_ref().unwrap_or(read))?;
    if let Source::Raw(grid) = &loaded.source {
        return verify_input(dir, grid);
    }
    let s = Synthesized::of(dir)?;
    let mut report = s.report()?;
    let base = &s.store.base;
    tracing::info!(input, "sampling the input again on the store's base mesh");
    let r = crate::resample::resample_onto(
        &loaded.source,
        (base.positions.clone(), base.tets.clone()),
        base.levels,
    )?;
    let mut e = Errors::default();
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for (&got, &want) in s.values.iter().zip(&r.samples) {
        if !want.is_nan() {
            e.add(got, want as f64);
            lo = lo.min(want);
            hi = hi.max(want);
        }
    }
    e.within(s.store.manifest.max_error_bound, || {
        format!("{} against its input {input}", dir.display())
    })?;
    let range = loaded.source_range.map_or([lo, hi], |(a, b)| [a, b]);
    report.input = Some(e.input_check("vertices", range, s.store.manifest.value_range));
    Ok(s.finish(report))
}

fn parse_triple<T: std::str::FromStr>(s: &str) -> Result<[T; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("expected three comma-separated numbers, got {s:?}"));
    }
    let mut out = Vec::with_capacity(3);
    for p in parts {
        out.push(
            p.trim()
                .parse::<T>()
                .map_err(|_| format!("not a number: {p:?}"))?,
        );
    }
    out.try_into()
        .map_err(|_| "expected three numbers".to_string())
}

/// The preview of store analysis `a` from the coarse analysis `p` of the same samples: the
/// nodes of every node level but the finest (fewer while they would exceed
/// [`MAX_PREVIEW_NODES`]), with `p`'s coefficients, checked to have `a`'s masks (the preview's
/// coder sends no subtree bounds: the store's own nodes bring theirs).
fn preview_nodes(a: &Analysis, p: &Analysis) -> Result<PreviewNodes, PrepareError> {
    if p.error_bound <= a.error_bound {
        return Err(PrepareError::Usage(format!(
            "--preview: its bound {:e} is no coarser than the store's {:e}; a preview is a coarse \
             copy sent before the store's own nodes (give a larger bound, e.g. 10%)",
            p.error_bound, a.error_bound
        )));
    }
    let forest = a.base.forest();
    if a.base
        .values
        .iter()
        .map(|v| v.to_bits())
        .ne(p.base.values.iter().map(|v| v.to_bits()))
    {
        return Err(PrepareError::Usage(
            "the preview's analysis reconstructs other base values than the store's".into(),
        ));
    }
    let levels = (1..forest.levels)
        .rev()
        .find(|&k| forest.level_start(k) <= MAX_PREVIEW_NODES)
        .ok_or_else(|| {
            PrepareError::Usage(format!(
                "--preview: the base mesh's {} tets alone exceed a preview's {MAX_PREVIEW_NODES} nodes",
                forest.n_base
            ))
        })?;
    let count = forest.level_start(levels) as usize;
    let nodes = p.content().nodes(count).map_err(PrepareError::Usage)?;
    for (i, n) in nodes.iter().enumerate() {
        if n.owned != a.owned[i] || n.empty_children != a.empty_children[i] {
            return Err(PrepareError::Usage(format!(
                "the preview's node {i} owns other vertices than the store's"
            )));
        }
    }
    Ok(PreviewNodes {
        preview: Preview {
            encoding: store::Encoding::of(p.content().quantizer),
            levels,
            max_error_bound: p.error_bound,
        },
        nodes,
    })
}

fn parse_max_error(s: &str) -> Result<ErrorBound, String> {
    ErrorBound::parse(s)
}

/// `prepare --predictor`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PredictorChoice {
    /// `axes` where it applies (a box6 base with data at every vertex), else `parent`.
    Auto,
    /// The refined tet's parent's quadratic.
    Parent,
    /// SZ3's cubic interpolation along the grid's axes.
    Axes,
}

fn parse_dims(s: &str) -> Result<[usize; 3], String> {
    parse_triple(s)
}

fn parse_spacing(s: &str) -> Result<[f64; 3], String> {
    parse_triple(s)
}
