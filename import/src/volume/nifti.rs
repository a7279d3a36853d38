//! NIfTI-1 and NIfTI-2 (`.nii`, `.nii.gz`, `.hdr`/`.img` pairs, either byte order).
//!
//! Written here rather than with the `nifti` crate: the header is two fixed records (348 and 540
//! bytes), and the box reader needs the samples' offset and layout for random access into an
//! uncompressed file, which is all this reader takes from the header besides the geometry.
//!
//! Geometry: the sform when its code is set, else the qform, else the pixdims (NIfTI's "method
//! 1"); the world frame is RAS. A direction matrix that is not a signed permutation (within
//! 1e-6 of the largest entry of its column) is refused as oblique. Axes 4 (time) and 5 (vector
//! components) are `--frame` and `--scalar`; axes 6 and 7 are refused.

use super::raw::{read_box, ByteSource, Layout};
use super::samples::{choose_component, select};
use super::{
    AxisMap, DType, Endian, FileHeader, Samples, VolumeError, VolumeFormat, VolumeOptions,
    VolumeReader,
};
use std::io::Read;
use std::path::{Path, PathBuf};

/// Whether `head` (at least 348 bytes) holds a NIfTI-1 or -2 magic.
pub(crate) fn has_magic(head: &[u8]) -> bool {
    (head.len() >= 348 && matches!(&head[344..348], b"n+1\0" | b"ni1\0"))
        || (head.len() >= 12 && matches!(&head[4..12], b"n+2\0\r\n\x1a\n" | b"ni2\0\r\n\x1a\n"))
}

pub(crate) struct NiftiReader {
    data_path: PathBuf,
    gzip: bool,
    header: FileHeader,
    /// Layout of one 3D volume of all its RGB components (interleaved), starting at the chosen
    /// frame and vector component.
    layout: Layout,
    /// Which interleaved component (RGB files), `None`: magnitude.
    which: Option<usize>,
}

/// Field reader over a header record in its byte order.
struct Fields<'a> {
    b: &'a [u8],
    endian: Endian,
}

impl Fields<'_> {
    fn arr<const N: usize>(&self, at: usize) -> [u8; N] {
        self.b[at..at + N].try_into().expect("within the header")
    }
    fn i16(&self, at: usize) -> i16 {
        match self.endian {
            Endian::Little => i16::from_le_bytes(self.arr(at)),
            Endian::Big => i16::from_be_bytes(self.arr(at)),
        }
    }
    fn i32(&self, at: usize) -> i32 {
        match self.endian {
            Endian::Little => i32::from_le_bytes(self.arr(at)),
            Endian::Big => i32::from_be_bytes(self.arr(at)),
        }
    }
    fn i64(&self, at: usize) -> i64 {
        match self.endian {
            Endian::Little => i64::from_le_bytes(self.arr(at)),
            Endian::Big => i64::from_be_bytes(self.arr(at)),
        }
    }
    fn f32(&self, at: usize) -> f64 {
        (match self.endian {
            Endian::Little => f32::from_le_bytes(self.arr(at)),
            Endian::Big => f32::from_be_bytes(self.arr(at)),
        }) as f64
    }
    fn f64(&self, at: usize) -> f64 {
        match self.endian {
            Endian::Little => f64::from_le_bytes(self.arr(at)),
            Endian::Big => f64::from_be_bytes(self.arr(at)),
        }
    }
}

/// What both versions' headers give, in one form.
struct Raw {
    dim: [i64; 8],
    datatype: i32,
    pixdim: [f64; 8],
    vox_offset: f64,
    scl: (f64, f64),
    xyzt_units: i32,
    qform_code: i32,
    sform_code: i32,
    quatern: [f64; 6],
    srow: [[f64; 4]; 3],
    single_file: bool,
    /// Bytes of the header and its 4 extension bytes: 352 (NIfTI-1) or 544 (NIfTI-2).
    header_bytes: u64,
}

fn parse(path: &Path, b: &[u8]) -> Result<(Raw, Endian), VolumeError> {
    let bad = |m: String| VolumeError::bad(path, "header", m);
    if b.len() < 348 {
        return Err(bad(format!(
            "{} bytes: a NIfTI header has 348 (NIfTI-1) or 540 (NIfTI-2)",
            b.len()
        )));
    }
    let size_le = i32::from_le_bytes(b[0..4].try_into().expect("4 bytes"));
    let size_be = i32::from_be_bytes(b[0..4].try_into().expect("4 bytes"));
    let (version, endian) = match (size_le, size_be) {
        (348, _) => (1, Endian::Little),
        (_, 348) => (1, Endian::Big),
        (540, _) => (2, Endian::Little),
        (_, 540) => (2, Endian::Big),
        _ => {
            return Err(bad(format!(
                "sizeof_hdr is {size_le} (or {size_be} big-endian): not 348 (NIfTI-1) or 540 \
                 (NIfTI-2)"
            )))
        }
    };
    let f = Fields { b, endian };
    if version == 1 {
        let magic = &b[344..348];
        let single_file = match magic {
            b"n+1\0" => true,
            b"ni1\0" => false,
            _ => {
                return Err(bad(format!(
                    "magic {magic:?}: not NIfTI-1 (n+1 or ni1; an ANALYZE 7.5 header is not read)"
                )))
            }
        };
        Ok((
            Raw {
                dim: std::array::from_fn(|k| f.i16(40 + 2 * k) as i64),
                datatype: f.i16(70) as i32,
                pixdim: std::array::from_fn(|k| f.f32(76 + 4 * k)),
                vox_offset: f.f32(108),
                scl: (f.f32(112), f.f32(116)),
                xyzt_units: b[123] as i32,
                qform_code: f.i16(252) as i32,
                sform_code: f.i16(254) as i32,
                quatern: std::array::from_fn(|k| f.f32(256 + 4 * k)),
                srow: std::array::from_fn(|r| std::array::from_fn(|c| f.f32(280 + 16 * r + 4 * c))),
                single_file,
                header_bytes: 352,
            },
            endian,
        ))
    } else {
        if b.len() < 540 {
            return Err(bad(format!("{} bytes: a NIfTI-2 header has 540", b.len())));
        }
        let single_file = match &b[4..12] {
            b"n+2\0\r\n\x1a\n" => true,
            b"ni2\0\r\n\x1a\n" => false,
            m => return Err(bad(format!("magic {m:?}: not NIfTI-2"))),
        };
        Ok((
            Raw {
                dim: std::array::from_fn(|k| f.i64(16 + 8 * k)),
                datatype: f.i16(12) as i32,
                pixdim: std::array::from_fn(|k| f.f64(104 + 8 * k)),
                vox_offset: f.i64(168) as f64,
                scl: (f.f64(176), f.f64(184)),
                xyzt_units: f.i32(500),
                qform_code: f.i32(344),
                sform_code: f.i32(348),
                quatern: std::array::from_fn(|k| f.f64(352 + 8 * k)),
                srow: std::array::from_fn(|r| std::array::from_fn(|c| f.f64(400 + 32 * r + 8 * c))),
                single_file,
                header_bytes: 544,
            },
            endian,
        ))
    }
}

/// The 3×4 voxel-to-world matrix the header states (sform, else qform, else pixdims).
fn affine(r: &Raw) -> ([[f64; 4]; 3], Option<&'static str>) {
    if r.sform_code > 0 {
        return (r.srow, Some("sform"));
    }
    let dx = r.pixdim[1..4].to_vec();
    if r.qform_code > 0 {
        let [b, c, d, x, y, z] = r.quatern;
        let a = (1.0 - (b * b + c * c + d * d)).max(0.0).sqrt();
        let rot = [
            [
                a * a + b * b - c * c - d * d,
                2.0 * (b * c - a * d),
                2.0 * (b * d + a * c),
            ],
            [
                2.0 * (b * c + a * d),
                a * a + c * c - b * b - d * d,
                2.0 * (c * d - a * b),
            ],
            [
                2.0 * (b * d - a * c),
                2.0 * (c * d + a * b),
                a * a + d * d - c * c - b * b,
            ],
        ];
        let qfac = if r.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let scale = [dx[0], dx[1], qfac * dx[2]];
        let t = [x, y, z];
        let m = std::array::from_fn(|i| {
            let mut row = [0.0; 4];
            for j in 0..3 {
                row[j] = rot[i][j] * scale[j];
            }
            row[3] = t[i];
            row
        });
        return (m, Some("qform"));
    }
    let m = std::array::from_fn(|i| {
        let mut row = [0.0; 4];
        row[i] = dx[i];
        row
    });
    (m, None)
}

fn dtype_of(code: i32) -> Option<(DType, usize)> {
    Some(match code {
        2 => (DType::U8, 1),
        4 => (DType::I16, 1),
        8 => (DType::I32, 1),
        16 => (DType::F32, 1),
        64 => (DType::F64, 1),
        256 => (DType::I8, 1),
        512 => (DType::U16, 1),
        768 => (DType::U32, 1),
        128 => (DType::U8, 3),
        2304 => (DType::U8, 4),
        _ => return None,
    })
}

fn is_gzip(path: &Path) -> Result<bool, VolumeError> {
    let mut m = [0u8; 2];
    let mut f = std::fs::File::open(path).map_err(VolumeError::io(path))?;
    let n = f.read(&mut m).map_err(VolumeError::io(path))?;
    Ok(n == 2 && m == [0x1f, 0x8b])
}

fn open_stream(path: &Path, gzip: bool) -> Result<Box<dyn Read>, VolumeError> {
    let f = std::fs::File::open(path).map_err(VolumeError::io(path))?;
    let f = std::io::BufReader::with_capacity(1 << 16, f);
    Ok(if gzip {
        Box::new(flate2::read::MultiGzDecoder::new(f))
    } else {
        Box::new(f)
    })
}

impl NiftiReader {
    pub fn open(path: &Path, options: &VolumeOptions) -> Result<Self, VolumeError> {
        let gzip = is_gzip(path)?;
        let mut head = Vec::with_capacity(540);
        open_stream(path, gzip)?
            .take(540)
            .read_to_end(&mut head)
            .map_err(|e| VolumeError::bad(path, "header", format!("cannot decode: {e}")))?;
        let (r, endian) = parse(path, &head)?;
        let bad = |section: &str, m: String| VolumeError::bad(path, section, m);
        let ndim = r.dim[0];
        if !(1..=7).contains(&ndim) {
            return Err(bad(
                "dim",
                format!("dim[0] = {ndim}: give 1 to 7 dimensions"),
            ));
        }
        let dim = |k: usize| if (k as i64) <= ndim { r.dim[k] } else { 1 };
        for k in 1..=ndim as usize {
            if r.dim[k] < 1 {
                return Err(bad(
                    "dim",
                    format!("dim[{k}] = {}: must be at least 1", r.dim[k]),
                ));
            }
        }
        if dim(6) > 1 || dim(7) > 1 {
            return Err(VolumeError::unsupported(
                path,
                "dim",
                format!(
                    "dims {:?}: a 6th or 7th dimension",
                    &r.dim[1..=ndim as usize]
                ),
            ));
        }
        let as_usize =
            |v: i64| usize::try_from(v).map_err(|_| bad("dim", format!("{v}: too large")));
        let dims = [as_usize(dim(1))?, as_usize(dim(2))?, as_usize(dim(3))?];
        let frames = as_usize(dim(4))?;
        let vectors = as_usize(dim(5))?;
        let (dtype, rgb) = dtype_of(r.datatype).ok_or_else(|| {
            VolumeError::unsupported(
                path,
                "datatype",
                format!(
                    "datatype {}: read are u8, i8, u16, i16, u32, i32, f32, f64 and RGB(A) u8 \
                     (not complex, 64-bit integers or float128)",
                    r.datatype
                ),
            )
        })?;
        let components = rgb.max(vectors);
        let names: Vec<String> = if rgb == 3 {
            ["r", "g", "b"].map(String::from).to_vec()
        } else if rgb == 4 {
            ["r", "g", "b", "a"].map(String::from).to_vec()
        } else {
            Vec::new()
        };
        // a one-component file takes its component whatever the choice (`mag` included)
        let which = choose_component(options.scalar.as_ref(), components, &names)
            .map_err(|m| VolumeError::usage(path, m))?
            .or(if components <= 1 { Some(0) } else { None });
        if vectors > 1 && which.is_none() {
            return Err(VolumeError::unsupported(
                path,
                "dim",
                "--scalar mag of a NIfTI vector (dim[5]) volume: choose one component with \
                 --scalar K",
            ));
        }
        let frame = match (options.frame, frames) {
            (Some(t), n) if t < n => t,
            (Some(t), n) => {
                return Err(VolumeError::usage(
                    path,
                    format!("--frame {t}: the volume has {n} frame(s) (0 to {})", n - 1),
                ))
            }
            (None, 1) => 0,
            (None, n) => {
                return Err(VolumeError::usage(
                    path,
                    format!(
                        "{n} frames (a 4D volume): choose one with --frame T (0 to {})",
                        n - 1
                    ),
                ))
            }
        };
        // where the chosen frame and vector component start
        // a single file's vox_offset 0 is read as "just after the header", as nibabel and
        // niftilib do (files written by ANALYZE-era tools)
        let vox_offset = if r.single_file && r.vox_offset == 0.0 {
            r.header_bytes as f64
        } else {
            r.vox_offset
        };
        if !(vox_offset.is_finite() && vox_offset >= 0.0) {
            return Err(bad(
                "vox_offset",
                format!("{vox_offset}: must be a byte offset"),
            ));
        }
        let data_path = if r.single_file {
            if (vox_offset as u64) < r.header_bytes - 4 {
                return Err(bad(
                    "vox_offset",
                    format!("{vox_offset}: a .nii's samples start after its header"),
                ));
            }
            path.to_path_buf()
        } else {
            img_path(path)?
        };
        let volume_bytes = dims
            .iter()
            .try_fold((rgb * dtype.bytes()) as u64, |a, &d| {
                a.checked_mul(d as u64)
            })
            .ok_or_else(|| bad("dim", format!("{dims:?}: too many voxels")))?;
        let vector = if vectors > 1 { which.unwrap_or(0) } else { 0 };
        let offset = (vox_offset as u64)
            .checked_add(
                volume_bytes
                    .checked_mul((vector * frames + frame) as u64)
                    .ok_or_else(|| bad("dim", "too many voxels".into()))?,
            )
            .ok_or_else(|| bad("dim", "too many voxels".into()))?;
        let gzip_data = if r.single_file {
            gzip
        } else {
            is_gzip(&data_path)?
        };
        // an uncompressed file must hold every voxel of every frame
        if !gzip_data {
            let len = std::fs::metadata(&data_path)
                .map_err(VolumeError::io(&data_path))?
                .len();
            let need = (vox_offset as u64)
                .checked_add(volume_bytes.saturating_mul((frames * vectors) as u64));
            if need.is_none_or(|n| n > len) {
                return Err(VolumeError::bad(
                    &data_path,
                    "data",
                    format!(
                        "truncated: {len} bytes, the header's {dims:?} × {frames} frame(s) × \
                         {vectors} component(s) of {} from byte {vox_offset} need {}",
                        dtype,
                        need.map_or("more than 2^64".into(), |n| n.to_string())
                    ),
                ));
            }
        }
        let (m, form) = affine(&r);
        let mut axes = [AxisMap {
            axis: 0,
            flip: false,
        }; 3];
        let mut spacing = [0.0; 3];
        for a in 0..3 {
            let col = [m[0][a], m[1][a], m[2][a]];
            let big = col.iter().map(|x| x.abs()).fold(0.0, f64::max);
            let rows: Vec<usize> = (0..3).filter(|&i| col[i].abs() > 1e-6 * big).collect();
            if big == 0.0 || !big.is_finite() {
                return Err(bad(
                    form.unwrap_or("pixdim"),
                    format!("axis {a} has no extent ({col:?})"),
                ));
            }
            if rows.len() != 1 {
                return Err(VolumeError::unsupported(
                    path,
                    form.unwrap_or("pixdim"),
                    format!(
                        "an oblique orientation (voxel axis {a} runs along {col:?} in RAS): \
                         resample it to the scanner's axes first (e.g. 3D Slicer's or ANTs' \
                         resampling to an axis-aligned grid)"
                    ),
                ));
            }
            axes[a] = AxisMap {
                axis: rows[0],
                flip: col[rows[0]] < 0.0,
            };
            spacing[a] = col[rows[0]].abs();
        }
        let origin = [m[0][3], m[1][3], m[2][3]];
        let out_dtype = match which {
            None => {
                if dtype == DType::F64 {
                    DType::F64
                } else {
                    DType::F32
                }
            }
            Some(_) => dtype,
        };
        let mut header = FileHeader::new(VolumeFormat::Nifti, dims, out_dtype, spacing);
        header.axes = axes;
        header.origin = if form.is_some() { origin } else { [0.0; 3] };
        header.frame = form.map(|_| "RAS".to_string());
        header.length_unit = match r.xyzt_units & 7 {
            1 => Some("m".into()),
            2 => Some("mm".into()),
            3 => Some("um".into()),
            _ => None,
        };
        let (slope, inter) = r.scl;
        if slope.is_finite() && slope != 0.0 && inter.is_finite() && (slope, inter) != (1.0, 0.0) {
            header.rescale = Some((slope, inter));
        }
        if frames > 1 {
            header.notes.push(format!("frame {frame} of {frames}"));
        }
        if components > 1 {
            header.notes.push(match which {
                Some(k) => format!("component {k} of {components}"),
                None => format!("magnitude of {components} components"),
            });
        }
        Ok(NiftiReader {
            data_path,
            gzip: gzip_data,
            header,
            layout: Layout {
                offset,
                dims,
                components: rgb,
                dtype,
                endian,
            },
            which: if rgb > 1 { which } else { Some(0) },
        })
    }
}

/// The `.img` (or `.img.gz`) beside a `.hdr`.
fn img_path(hdr: &Path) -> Result<PathBuf, VolumeError> {
    let name = hdr.to_string_lossy();
    let stem = name
        .strip_suffix(".hdr.gz")
        .or_else(|| name.strip_suffix(".hdr"))
        .unwrap_or(&name);
    for cand in [format!("{stem}.img"), format!("{stem}.img.gz")] {
        if Path::new(&cand).exists() {
            return Ok(PathBuf::from(cand));
        }
    }
    Err(VolumeError::bad(
        hdr,
        "header",
        format!("a two-file NIfTI (magic ni1/ni2) needs its samples in {stem}.img: not found"),
    ))
}

impl VolumeReader for NiftiReader {
    fn header(&self) -> &FileHeader {
        &self.header
    }
    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
        let s = if self.gzip {
            let mut r = open_stream(&self.data_path, true)?;
            read_box(
                &self.data_path,
                &mut ByteSource::Stream(&mut r, 0),
                &self.layout,
                lo,
                hi,
            )?
        } else {
            let mut f =
                std::fs::File::open(&self.data_path).map_err(VolumeError::io(&self.data_path))?;
            read_box(
                &self.data_path,
                &mut ByteSource::Seek(&mut f),
                &self.layout,
                lo,
                hi,
            )?
        };
        Ok(select(s, self.layout.components, self.which))
    }
}
