//! Readers of scalar volumes on a regular grid: headerless raw files, NIfTI-1/-2, NRRD, VTK image
//! data (`.vti`, legacy `STRUCTURED_POINTS`), TIFF stacks, DICOM series and Zarr (v2, v3,
//! OME-Zarr). `docs/formats.md` has the user-facing table.
//!
//! Every format is a [`VolumeReader`]: a [`FileHeader`] (dims, sample type, spacing, origin, the
//! file axes' directions, a rescale) and [`VolumeReader::read_box`], which returns the voxels of
//! one box of the file's own index space, never the whole array unless asked for it. [`Volume`]
//! puts a reader in the world frame: axis-aligned flips and permutations applied (an oblique
//! direction matrix is refused by the reader that finds it), the rescale applied, and
//! [`Volume::read_block`] giving voxel rows and planes of that frame, x fastest, as `prepare` reads
//! a raw grid by parts.
//!
//! The format comes from the content where it is recognizable (NIfTI's and NRRD's magic, a VTK
//! header, TIFF's byte order mark, DICOM's `DICM`, a folder holding `.zarray`/`zarr.json` or
//! DICOM/TIFF slices) and otherwise from the extension ([`sniff`]).
//!
//! Files: this one has the shared types, the orientation and the dispatch; `raw.rs` headerless
//! grids; `samples.rs` typed voxel buffers and their decoding; one file a format.

mod dicom;
mod nifti;
mod nrrd;
mod raw;
mod samples;
mod tiff_stack;
mod vtk_image;
mod zarr;

pub use raw::RawSpec;
pub use samples::{DType, Endian, Samples};

use std::ops::Range;
use std::path::{Path, PathBuf};

/// Volume file formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum VolumeFormat {
    /// Headerless samples, dims and type given by the user.
    Raw,
    Nifti,
    Nrrd,
    /// VTK XML `ImageData` (`.vti`).
    Vti,
    /// Legacy `.vtk` `DATASET STRUCTURED_POINTS`.
    VtkStructuredPoints,
    Tiff,
    Dicom,
    Zarr,
}

impl VolumeFormat {
    pub fn name(&self) -> &'static str {
        match self {
            VolumeFormat::Raw => "raw",
            VolumeFormat::Nifti => "NIfTI",
            VolumeFormat::Nrrd => "NRRD",
            VolumeFormat::Vti => "VTK image data (.vti)",
            VolumeFormat::VtkStructuredPoints => "legacy VTK STRUCTURED_POINTS",
            VolumeFormat::Tiff => "TIFF",
            VolumeFormat::Dicom => "DICOM",
            VolumeFormat::Zarr => "Zarr",
        }
    }
}

/// Errors of the volume readers: each names the file (or folder, or object) and what in it is
/// wrong. No reader panics on a malformed file.
#[derive(Debug, thiserror::Error)]
pub enum VolumeError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The file is malformed: truncated, an inconsistent header, a bad value.
    #[error("{path}: {section}: {message}")]
    Bad {
        path: PathBuf,
        section: String,
        message: String,
    },
    /// The file is well formed but uses what is not read (a compression, a type, an oblique
    /// orientation); `message` says which and, where there is one, what to do.
    #[error("{path}: {section}: not supported: {message}")]
    Unsupported {
        path: PathBuf,
        section: String,
        message: String,
    },
    /// A choice the user made does not fit the file (`--scalar`, `--frame`, a box past the dims).
    #[error("{path}: {message}")]
    Usage { path: PathBuf, message: String },
    #[error("{path}: {bytes} bytes of voxels do not fit in this machine's memory")]
    NoMemory { path: PathBuf, bytes: u64 },
}

impl VolumeError {
    pub(crate) fn bad(path: &Path, section: &str, message: impl Into<String>) -> Self {
        VolumeError::Bad {
            path: path.to_path_buf(),
            section: section.into(),
            message: message.into(),
        }
    }
    pub(crate) fn unsupported(path: &Path, section: &str, message: impl Into<String>) -> Self {
        VolumeError::Unsupported {
            path: path.to_path_buf(),
            section: section.into(),
            message: message.into(),
        }
    }
    pub(crate) fn usage(path: &Path, message: impl Into<String>) -> Self {
        VolumeError::Usage {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
    pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Self + '_ {
        move |source| VolumeError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// Which scalar of a voxel with several components (`--scalar`): a component by index or by
/// name, or the Euclidean norm of all of them. One-component files take `None` or index 0.
#[derive(Debug, Clone, PartialEq)]
pub enum ScalarChoice {
    Index(usize),
    Name(String),
    Magnitude,
}

impl ScalarChoice {
    /// `--scalar NAME|K|mag`.
    pub fn parse(s: &str) -> ScalarChoice {
        match s {
            "mag" | "magnitude" => ScalarChoice::Magnitude,
            _ => match s.parse::<usize>() {
                Ok(k) => ScalarChoice::Index(k),
                Err(_) => ScalarChoice::Name(s.to_string()),
            },
        }
    }
}

/// How to open a volume: what the user chose on the command line.
#[derive(Debug, Clone, Default)]
pub struct VolumeOptions {
    /// For a headerless raw file: its dims, type and spacing (`--dims`, `--dtype`, `--spacing`).
    pub raw: Option<RawSpec>,
    /// `--scalar`: the component of a multi-component volume (default: the only one; several
    /// are refused without a choice, with their list).
    pub scalar: Option<ScalarChoice>,
    /// `--frame T`: the time point of a 4D volume (default 0 when there is one frame; several
    /// are refused without a choice).
    pub frame: Option<usize>,
}

/// Where a file axis points in the world frame: world axis `axis` (0 = x, 1 = y, 2 = z), with
/// the file's index increasing along it (`flip == false`) or against it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct AxisMap {
    pub axis: usize,
    pub flip: bool,
}

/// What a reader knows of a volume before reading its voxels.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FileHeader {
    pub format: VolumeFormat,
    /// Voxels along the file's axes, fastest first.
    pub dims: [usize; 3],
    /// The type [`VolumeReader::read_box`] returns (after the component choice).
    pub dtype: DType,
    /// Distance between voxel centres along each file axis (positive).
    pub spacing: [f64; 3],
    /// World position of voxel `[0, 0, 0]`.
    pub origin: [f64; 3],
    /// Each file axis's world axis and direction (identity when the file states none).
    pub axes: [AxisMap; 3],
    /// `value = slope · stored + intercept` (DICOM's rescale, NIfTI's `scl_slope`), when not the
    /// identity.
    pub rescale: Option<(f64, f64)>,
    /// The world frame's name when the file states one (`RAS`: NIfTI; `LPS`: DICOM, NRRD's
    /// `left-posterior-superior`), for orientation labels.
    pub frame: Option<String>,
    /// Unit of the spacing (`mm`, `um`, ...), when the file states one.
    pub length_unit: Option<String>,
    /// Unit of the values (`HU`, ...), when the file states one.
    pub value_unit: Option<String>,
    /// Notes for the user: what was chosen (a component, a frame, a series), what was ignored.
    pub notes: Vec<String>,
}

impl FileHeader {
    /// A header with the identity orientation and no units, for readers to fill in.
    pub fn new(format: VolumeFormat, dims: [usize; 3], dtype: DType, spacing: [f64; 3]) -> Self {
        FileHeader {
            format,
            dims,
            dtype,
            spacing,
            origin: [0.0; 3],
            axes: [0, 1, 2].map(|axis| AxisMap { axis, flip: false }),
            rescale: None,
            frame: None,
            length_unit: None,
            value_unit: None,
            notes: Vec::new(),
        }
    }

    /// The checks every reader's header passes before it is used: dims at least 2 along every
    /// axis and their product within `usize`, spacing positive and finite, the axes a
    /// permutation.
    pub fn check(&self, path: &Path) -> Result<(), VolumeError> {
        if self.dims.iter().any(|&d| d < 2) {
            return Err(VolumeError::unsupported(
                path,
                "dims",
                format!(
                    "{:?} voxels: a volume needs at least 2 voxels along every axis",
                    self.dims
                ),
            ));
        }
        let bytes = self
            .dims
            .iter()
            .try_fold(self.dtype.bytes() as u64, |a, &d| a.checked_mul(d as u64));
        if bytes.is_none_or(|b| b > isize::MAX as u64) {
            return Err(VolumeError::bad(
                path,
                "dims",
                format!("{:?} voxels are more than can be indexed", self.dims),
            ));
        }
        if self.spacing.iter().any(|&s| !(s.is_finite() && s > 0.0)) {
            return Err(VolumeError::bad(
                path,
                "spacing",
                format!("{:?}: spacing must be positive and finite", self.spacing),
            ));
        }
        if self.origin.iter().any(|o| !o.is_finite()) {
            return Err(VolumeError::bad(
                path,
                "origin",
                format!("{:?}: origin must be finite", self.origin),
            ));
        }
        let mut seen = [false; 3];
        for m in &self.axes {
            if m.axis > 2 || std::mem::replace(&mut seen[m.axis], true) {
                return Err(VolumeError::bad(
                    path,
                    "orientation",
                    format!("{:?} is not a permutation of the axes", self.axes),
                ));
            }
        }
        if let Some((s, i)) = self.rescale {
            if !(s.is_finite() && i.is_finite() && s != 0.0) {
                return Err(VolumeError::bad(
                    path,
                    "rescale",
                    format!("slope {s}, intercept {i}: give a finite non-zero slope"),
                ));
            }
        }
        Ok(())
    }
}

/// A format's reader: its header, and the voxels of any box of its index space.
pub trait VolumeReader: Send {
    fn header(&self) -> &FileHeader;
    /// The voxels of the box `lo..hi` of the file's index space (`lo[a] < hi[a] <= dims[a]`),
    /// fastest axis first, in [`FileHeader::dtype`], of the chosen component and frame, before
    /// the rescale. Reads no more of the file than the box's chunks, strips or slices need
    /// (formats whose compression runs through the whole file, such as gzip, decode up to the
    /// box's end).
    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError>;
}

/// Whether `path` is a URL (`s3://`, `http://`, `https://`) rather than a local path.
pub fn is_url(path: &Path) -> bool {
    let s = path.to_string_lossy();
    ["s3://", "http://", "https://"]
        .iter()
        .any(|p| s.starts_with(p))
}

/// Recognizes a volume: the format of `path` (a file, or a folder of slices or a Zarr), from its
/// content and, failing that, its extension. `None`: not a volume this crate reads.
pub fn sniff(path: &Path) -> Option<VolumeFormat> {
    if path.is_dir() {
        if zarr::is_zarr_dir(path) {
            return Some(VolumeFormat::Zarr);
        }
        // a folder of slices: the first DICOM or TIFF file in name order decides (a README
        // before the slices does not hide them); no more than 64 files are looked at
        return slice_files(path)
            .ok()?
            .iter()
            .take(64)
            .find_map(|f| match sniff(f) {
                Some(fm @ (VolumeFormat::Dicom | VolumeFormat::Tiff)) => Some(fm),
                _ => None,
            });
    }
    let mut head = [0u8; 1024];
    let n = std::fs::File::open(path)
        .and_then(|mut f| {
            use std::io::Read;
            let mut n = 0;
            while n < head.len() {
                match f.read(&mut head[n..])? {
                    0 => break,
                    k => n += k,
                }
            }
            Ok(n)
        })
        .unwrap_or(0);
    let head = &head[..n];
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if let Some(f) = sniff_bytes(head) {
        return Some(f);
    }
    if name.ends_with(".nii") || name.ends_with(".nii.gz") || name.ends_with(".hdr") {
        return Some(VolumeFormat::Nifti);
    }
    if name.ends_with(".nrrd") || name.ends_with(".nhdr") {
        return Some(VolumeFormat::Nrrd);
    }
    if name.ends_with(".vti") {
        return Some(VolumeFormat::Vti);
    }
    if name.ends_with(".tif") || name.ends_with(".tiff") {
        return Some(VolumeFormat::Tiff);
    }
    if name.ends_with(".dcm") {
        return Some(VolumeFormat::Dicom);
    }
    if name.ends_with(".raw") {
        return Some(VolumeFormat::Raw);
    }
    None
}

/// The format its first bytes name, when they do.
fn sniff_bytes(head: &[u8]) -> Option<VolumeFormat> {
    let starts = |m: &[u8]| head.starts_with(m);
    if head.len() >= 348 && nifti::has_magic(head) {
        return Some(VolumeFormat::Nifti);
    }
    if starts(b"\x1f\x8b") {
        // gzip: a .nii.gz is the only gzipped volume read; its header is checked by the reader
        return Some(VolumeFormat::Nifti);
    }
    if starts(b"NRRD0") {
        return Some(VolumeFormat::Nrrd);
    }
    // before TIFF: a DICOM preamble may hold a TIFF header (dual-format files, PS3.10 7.5)
    if head.len() >= 132 && &head[128..132] == b"DICM" {
        return Some(VolumeFormat::Dicom);
    }
    if starts(b"II*\0") || starts(b"MM\0*") || starts(b"II+\0") || starts(b"MM\0+") {
        return Some(VolumeFormat::Tiff);
    }
    let text = String::from_utf8_lossy(head);
    if text.starts_with("# vtk DataFile") && text.contains("STRUCTURED_POINTS") {
        return Some(VolumeFormat::VtkStructuredPoints);
    }
    if (text.starts_with("<?xml") || text.starts_with("<VTKFile")) && text.contains("ImageData") {
        return Some(VolumeFormat::Vti);
    }
    None
}

/// The regular files of a folder in name order (hidden files skipped): a slice series.
pub(crate) fn slice_files(dir: &Path) -> Result<Vec<PathBuf>, VolumeError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(VolumeError::io(dir))?
        .filter_map(|e| e.ok())
        .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
        .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
        .map(|e| e.path())
        .collect();
    files.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
    Ok(files)
}

/// Name order with digit runs compared as numbers (`slice2` before `slice10`).
pub(crate) fn natural_cmp(a: &str, b: &str) -> std::cmp::Ordering {
    let (mut a, mut b) = (a.as_bytes(), b.as_bytes());
    loop {
        match (a.first(), b.first()) {
            (None, None) => return std::cmp::Ordering::Equal,
            (None, _) => return std::cmp::Ordering::Less,
            (_, None) => return std::cmp::Ordering::Greater,
            (Some(x), Some(y)) if x.is_ascii_digit() && y.is_ascii_digit() => {
                let da = a.iter().take_while(|c| c.is_ascii_digit()).count();
                let db = b.iter().take_while(|c| c.is_ascii_digit()).count();
                let (na, nb) = (&a[..da], &b[..db]);
                let strip = |s: &[u8]| {
                    let z = s.iter().take_while(|&&c| c == b'0').count();
                    s[z..].to_vec()
                };
                let (sa, sb) = (strip(na), strip(nb));
                let o = sa.len().cmp(&sb.len()).then(sa.cmp(&sb));
                if o != std::cmp::Ordering::Equal {
                    return o;
                }
                a = &a[da..];
                b = &b[db..];
            }
            (Some(x), Some(y)) => {
                if x != y {
                    return x.cmp(y);
                }
                a = &a[1..];
                b = &b[1..];
            }
        }
    }
}

/// Whether `lo..hi` is a non-empty box within `dims` (what every [`VolumeReader::read_box`]
/// accepts); the error names the file.
pub(crate) fn check_box(
    path: &Path,
    lo: [usize; 3],
    hi: [usize; 3],
    dims: [usize; 3],
) -> Result<(), VolumeError> {
    if (0..3).any(|a| lo[a] >= hi[a] || hi[a] > dims[a]) {
        return Err(VolumeError::usage(
            path,
            format!("box {lo:?}..{hi:?} asked of a volume of {dims:?} voxels"),
        ));
    }
    Ok(())
}

/// Opens the volume at `path` (`format`: what [`sniff`] found, or the user's override).
pub fn open_reader(
    path: &Path,
    format: VolumeFormat,
    options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    let reader: Box<dyn VolumeReader> = match format {
        VolumeFormat::Raw => {
            let spec = options.raw.ok_or_else(|| {
                VolumeError::usage(
                    path,
                    "a headerless raw grid needs --dims X,Y,Z and --dtype (u8, i8, u16, i16, \
                     u32, i32, f32, f64)",
                )
            })?;
            Box::new(raw::RawReader::open(path, spec)?)
        }
        VolumeFormat::Nifti => Box::new(nifti::NiftiReader::open(path, options)?),
        VolumeFormat::Nrrd => nrrd::open(path, options)?,
        VolumeFormat::Vti | VolumeFormat::VtkStructuredPoints => {
            vtk_image::open(path, format, options)?
        }
        VolumeFormat::Tiff => tiff_stack::open(path, options)?,
        VolumeFormat::Dicom => dicom::open(path, options)?,
        VolumeFormat::Zarr => zarr::open(path, options)?,
    };
    reader.header().check(path)?;
    Ok(reader)
}

/// A volume in the world frame: the reader's axes permuted and flipped as its header says, its
/// rescale applied.
pub struct Volume {
    path: PathBuf,
    reader: Box<dyn VolumeReader>,
    /// Voxels along the world axes.
    pub dims: [usize; 3],
    /// Spacing along the world axes.
    pub spacing: [f64; 3],
    /// World position of the world-frame voxel `[0, 0, 0]` (the box's lowest corner).
    pub origin: [f64; 3],
    /// The type [`Self::read_block`] returns: the file's, or `f32` (`f64` for an `f64` file)
    /// when a rescale applies.
    pub dtype: DType,
}

impl Volume {
    /// Opens `path` as a volume of format `format` (default: [`sniff`]'s).
    pub fn open(
        path: &Path,
        format: Option<VolumeFormat>,
        options: &VolumeOptions,
    ) -> Result<Volume, VolumeError> {
        if is_url(path) {
            // only Zarr is read from a bucket or a web server (chunk by chunk)
            return Self::from_reader(path, open_reader(path, VolumeFormat::Zarr, options)?);
        }
        let format = match format.or_else(|| sniff(path)) {
            Some(f) => f,
            None if options.raw.is_some() => VolumeFormat::Raw,
            None => {
                return Err(VolumeError::unsupported(
                    path,
                    "format",
                    "not a volume this reader recognizes (NIfTI, NRRD, VTK image data, TIFF, \
                     DICOM, Zarr; a headerless raw file needs --dims and --dtype)",
                ))
            }
        };
        std::fs::metadata(path).map_err(VolumeError::io(path))?;
        Self::from_reader(path, open_reader(path, format, options)?)
    }

    /// A volume from an open reader (whose header passed [`FileHeader::check`]).
    pub fn from_reader(path: &Path, reader: Box<dyn VolumeReader>) -> Result<Volume, VolumeError> {
        let h = reader.header();
        let mut dims = [0; 3];
        let mut spacing = [0.0; 3];
        let mut origin = h.origin;
        for a in 0..3 {
            let m = h.axes[a];
            dims[m.axis] = h.dims[a];
            spacing[m.axis] = h.spacing[a];
            if m.flip {
                // the file's last voxel along `a` is the world box's low corner
                origin[m.axis] -= (h.dims[a] - 1) as f64 * h.spacing[a];
            }
        }
        let dtype = match (h.rescale, h.dtype) {
            (None, t) => t,
            (Some(_), DType::F64) => DType::F64,
            (Some(_), _) => DType::F32,
        };
        Ok(Volume {
            path: path.to_path_buf(),
            dims,
            spacing,
            origin,
            dtype,
            reader,
        })
    }

    pub fn header(&self) -> &FileHeader {
        self.reader.header()
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The world voxel rows `y` of the planes `z`, every voxel along x, x fastest: a block of
    /// `dims[0] · y.len() · z.len()` samples in [`Self::dtype`].
    pub fn read_block(&mut self, y: Range<usize>, z: Range<usize>) -> Result<Samples, VolumeError> {
        if y.start >= y.end || y.end > self.dims[1] || z.start >= z.end || z.end > self.dims[2] {
            return Err(VolumeError::usage(
                &self.path,
                format!(
                    "voxel rows {y:?} of planes {z:?} asked of a volume of {} rows and {} planes",
                    self.dims[1], self.dims[2]
                ),
            ));
        }
        let world = [0..self.dims[0], y, z];
        let h = self.reader.header().clone();
        // the file box that holds the world block
        let mut lo = [0; 3];
        let mut hi = [0; 3];
        for a in 0..3 {
            let m = h.axes[a];
            let r = &world[m.axis];
            let n = h.dims[a];
            (lo[a], hi[a]) = if m.flip {
                (n - r.end, n - r.start)
            } else {
                (r.start, r.end)
            };
        }
        let file = self.reader.read_box(lo, hi)?;
        let fdims = [0, 1, 2].map(|a| hi[a] - lo[a]);
        if file.len() != fdims.iter().product::<usize>() {
            return Err(VolumeError::bad(
                &self.path,
                "voxels",
                format!(
                    "the reader returned {} voxels for a box of {fdims:?}",
                    file.len()
                ),
            ));
        }
        if file.dtype() != h.dtype {
            return Err(VolumeError::bad(
                &self.path,
                "voxels",
                format!(
                    "the reader returned {} samples for a header of {}",
                    file.dtype(),
                    h.dtype
                ),
            ));
        }
        let identity = (0..3).all(|a| {
            h.axes[a]
                == AxisMap {
                    axis: a,
                    flip: false,
                }
        });
        let oriented = if identity {
            file
        } else {
            file.reorient(fdims, h.axes)
        };
        Ok(match h.rescale {
            Some((slope, intercept)) => oriented.rescaled(slope, intercept),
            None => oriented,
        })
    }
}

#[cfg(test)]
mod tests;
