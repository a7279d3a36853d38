//! Headerless raw grids (`--dims X,Y,Z --dtype T [--spacing sx,sy,sz]`), x fastest,
//! little-endian, and the box reader every format with uncompressed or stream-compressed samples
//! at a known offset shares ([`Layout`], [`read_box`]).

use super::{DType, Endian, FileHeader, Samples, VolumeError, VolumeFormat, VolumeReader};
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// What the user says of a headerless file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RawSpec {
    pub dims: [usize; 3],
    pub dtype: DType,
    pub spacing: [f64; 3],
}

/// How samples are laid out from a byte offset: `dims` voxels x fastest, `components` interleaved
/// values a voxel, each `dtype` in byte order `endian`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Layout {
    pub offset: u64,
    pub dims: [usize; 3],
    pub components: usize,
    pub dtype: DType,
    pub endian: Endian,
}

impl Layout {
    pub fn voxel_bytes(&self) -> u64 {
        (self.components * self.dtype.bytes()) as u64
    }
    /// Bytes of all the samples (`None` past u64).
    pub fn bytes(&self) -> Option<u64> {
        self.dims
            .iter()
            .try_fold(self.voxel_bytes(), |a, &d| a.checked_mul(d as u64))
    }
}

/// Where samples are read from: a file that seeks, or a stream (a gzip body) read forward.
pub(crate) enum ByteSource<'a> {
    Seek(&'a mut dyn SeekRead),
    /// A stream and how many bytes of it have been consumed.
    Stream(&'a mut dyn Read, u64),
}

pub(crate) trait SeekRead: Read + Seek {}
impl<T: Read + Seek> SeekRead for T {}

impl ByteSource<'_> {
    fn read_at(&mut self, at: u64, buf: &mut Vec<u8>, len: u64) -> std::io::Result<()> {
        let start = buf.len();
        match self {
            ByteSource::Seek(f) => {
                f.seek(SeekFrom::Start(at))?;
                f.take(len).read_to_end(buf)?;
            }
            ByteSource::Stream(r, pos) => {
                if at < *pos {
                    return Err(std::io::Error::other("a stream cannot read backwards"));
                }
                let skipped = std::io::copy(&mut (&mut **r).take(at - *pos), &mut std::io::sink())?;
                *pos += skipped;
                (&mut **r).take(len).read_to_end(buf)?;
                *pos += (buf.len() - start) as u64;
            }
        }
        if (buf.len() - start) as u64 != len {
            return Err(std::io::Error::from(std::io::ErrorKind::UnexpectedEof));
        }
        Ok(())
    }
}

/// The voxels of the box `lo..hi` (all components, interleaved) of samples laid out as `layout`
/// says: one read a row of the box (a plane, or the whole box, where the box spans whole rows or
/// planes).
pub(crate) fn read_box(
    path: &Path,
    src: &mut ByteSource,
    layout: &Layout,
    lo: [usize; 3],
    hi: [usize; 3],
) -> Result<Samples, VolumeError> {
    let [nx, ny, _] = layout.dims;
    let vb = layout.voxel_bytes();
    let row = (hi[0] - lo[0]) as u64 * vb;
    let rows = (hi[1] - lo[1]) as u64;
    let planes = (hi[2] - lo[2]) as u64;
    let len = row * rows * planes;
    let mut bytes = Vec::new();
    bytes
        .try_reserve_exact(len as usize)
        .map_err(|_| VolumeError::NoMemory {
            path: path.to_path_buf(),
            bytes: len,
        })?;
    let at = |x: usize, y: usize, z: usize| {
        layout.offset + ((z as u64 * ny as u64 + y as u64) * nx as u64 + x as u64) * vb
    };
    let whole_rows = lo[0] == 0 && hi[0] == nx;
    let whole_planes = whole_rows && lo[1] == 0 && hi[1] == ny;
    let truncated = |e: std::io::Error| {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            VolumeError::bad(
                path,
                "data",
                format!(
                    "truncated: the samples ({} voxels of {} component(s) of {}) end past the \
                     file's end",
                    layout.dims.iter().product::<usize>(),
                    layout.components,
                    layout.dtype
                ),
            )
        } else if e.kind() == std::io::ErrorKind::InvalidData {
            VolumeError::bad(path, "data", e.to_string())
        } else {
            VolumeError::Io {
                path: path.to_path_buf(),
                source: e,
            }
        }
    };
    if whole_planes {
        src.read_at(at(0, 0, lo[2]), &mut bytes, len)
            .map_err(truncated)?;
    } else if whole_rows {
        for z in lo[2]..hi[2] {
            src.read_at(at(0, lo[1], z), &mut bytes, row * rows)
                .map_err(truncated)?;
        }
    } else {
        for z in lo[2]..hi[2] {
            for y in lo[1]..hi[1] {
                src.read_at(at(lo[0], y, z), &mut bytes, row)
                    .map_err(truncated)?;
            }
        }
    }
    Ok(Samples::decode(layout.dtype, &bytes, layout.endian))
}

/// A headerless raw file.
pub(crate) struct RawReader {
    path: PathBuf,
    header: FileHeader,
    layout: Layout,
}

impl RawReader {
    pub fn open(path: &Path, spec: RawSpec) -> Result<Self, VolumeError> {
        let header = FileHeader::new(VolumeFormat::Raw, spec.dims, spec.dtype, spec.spacing);
        header.check(path)?;
        let layout = Layout {
            offset: 0,
            dims: spec.dims,
            components: 1,
            dtype: spec.dtype,
            endian: Endian::Little,
        };
        let actual = std::fs::metadata(path)
            .map_err(VolumeError::io(path))?
            .len();
        let expected = layout.bytes();
        if expected != Some(actual) {
            return Err(VolumeError::usage(
                path,
                format!(
                    "size {actual} bytes does not match --dims {:?} × {} = {} bytes",
                    spec.dims,
                    spec.dtype,
                    expected.map_or_else(|| "more than 2^64".into(), |e| e.to_string())
                ),
            ));
        }
        Ok(RawReader {
            path: path.to_path_buf(),
            header,
            layout,
        })
    }
}

impl VolumeReader for RawReader {
    fn header(&self) -> &FileHeader {
        &self.header
    }
    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
        let mut f = std::fs::File::open(&self.path).map_err(VolumeError::io(&self.path))?;
        read_box(
            &self.path,
            &mut ByteSource::Seek(&mut f),
            &self.layout,
            lo,
            hi,
        )
    }
}
