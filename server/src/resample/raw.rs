//! Raw scalar grids (`--dims X,Y,Z --dtype u8|u16|i16|f32 [--spacing sx,sy,sz]`), x fastest,
//! little-endian (`i16`: two's complement, as CT scanners write Hounsfield units),
//! sampled by trilinear interpolation.
//!
//! **Voxel-exact placement** ([`VoxelLattice`], `prepare`'s default for a grid): the base mesh is
//! a box of Kuhn cells whose finest lattice step is the voxel spacing, so every voxel is a vertex
//! and its sample is the voxel's value (no interpolation); where the cells reach past the grid
//! (the padding, less than one cell per axis) the samples repeat the nearest voxel and the
//! domain's level set (the box of the voxels) clips them out of every image.

use std::path::{Path, PathBuf};

/// A raw grid's sample type: one of the volume readers' ([`tetwave_import::volume::DType`]).
pub use tetwave_import::volume::DType as RawType;
use tetwave_import::volume::{Endian, Samples};

#[derive(Debug, thiserror::Error)]
pub enum RawError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("raw grid needs --dims X,Y,Z and --dtype u8|i8|u16|i16|u32|i32|f32|f64")]
    MissingDims,
    #[error("voxel rows {y:?} of planes {z:?} asked of a grid of {dims:?} rows and planes")]
    BadBlock {
        y: std::ops::Range<usize>,
        z: std::ops::Range<usize>,
        dims: [usize; 2],
    },
    #[error("{bytes} bytes of voxels do not fit in this machine's memory")]
    NoMemory { bytes: u64 },
    #[error(
        "{path}: size {actual} bytes does not match --dims {dims:?} × {dtype:?} = {expected} bytes"
    )]
    SizeMismatch {
        path: PathBuf,
        dims: [usize; 3],
        dtype: RawType,
        /// Exact (the product of the dims can exceed u64).
        expected: String,
        actual: u64,
    },
    #[error("--dims must be at least 2 along every axis, got {0:?}")]
    TooSmall([usize; 3]),
    #[error("--spacing must be positive and finite, got {0:?}")]
    BadSpacing([f64; 3]),
}

/// A scalar grid held in memory in its own type (a u8 volume stays 1 byte per sample).
pub struct RawGrid {
    pub dims: [usize; 3],
    pub spacing: [f64; 3],
    data: Samples,
}

impl RawGrid {
    pub fn read(
        path: &Path,
        dims: [usize; 3],
        dtype: RawType,
        spacing: [f64; 3],
    ) -> Result<Self, RawError> {
        Self::read_block(path, dims, dtype, spacing, 0..dims[1], 0..dims[2])
    }

    /// The voxel rows `y` of the planes `z` (a block) of the grid of `dims` at `path`, as a grid
    /// of their own (`[x, y.len(), z.len()]` voxels, its first voxel at the origin): one seek and
    /// one read a plane (one in all for whole planes), so that a part of a store (`prepare
    /// --part`) holds its block alone.
    pub fn read_block(
        path: &Path,
        dims: [usize; 3],
        dtype: RawType,
        spacing: [f64; 3],
        y: std::ops::Range<usize>,
        z: std::ops::Range<usize>,
    ) -> Result<Self, RawError> {
        use std::io::{Read, Seek, SeekFrom};
        if dims.iter().any(|&d| d < 2) {
            return Err(RawError::TooSmall(dims));
        }
        if spacing.iter().any(|&s| !(s.is_finite() && s > 0.0)) {
            return Err(RawError::BadSpacing(spacing));
        }
        let io = |source| RawError::Io {
            path: path.to_path_buf(),
            source,
        };
        let actual = std::fs::metadata(path).map_err(io)?.len();
        let expected = dims
            .iter()
            .try_fold(dtype.bytes() as u128, |a, &d| a.checked_mul(d as u128));
        if expected != Some(actual as u128) {
            return Err(RawError::SizeMismatch {
                path: path.to_path_buf(),
                dims,
                dtype,
                expected: expected.map_or_else(|| "more than 2^128".into(), |e| e.to_string()),
                actual,
            });
        }
        if z.start >= z.end || z.end > dims[2] || y.start >= y.end || y.end > dims[1] {
            return Err(RawError::BadBlock {
                y,
                z,
                dims: [dims[1], dims[2]],
            });
        }
        // within the file's size, which fits u64
        let row = (dims[0] * dtype.bytes()) as u64;
        let plane = row * dims[1] as u64;
        let rows = row * y.len() as u64;
        let len = rows * z.len() as u64;
        let mut bytes = Vec::new();
        bytes
            .try_reserve_exact(len as usize)
            .map_err(|_| RawError::NoMemory { bytes: len })?;
        let mut f = std::fs::File::open(path).map_err(io)?;
        // whole planes are one read; rows of planes one a plane
        let whole_planes = y.len() == dims[1];
        let reads = if whole_planes {
            z.start..z.start + 1
        } else {
            z.clone()
        };
        for k in reads {
            f.seek(SeekFrom::Start(plane * k as u64 + row * y.start as u64))
                .map_err(io)?;
            let take = if whole_planes { len } else { rows };
            (&mut f).take(take).read_to_end(&mut bytes).map_err(io)?;
        }
        if bytes.len() as u64 != len {
            return Err(io(std::io::Error::from(std::io::ErrorKind::UnexpectedEof)));
        }
        let data = Samples::decode(dtype, &bytes, Endian::Little);
        Ok(RawGrid {
            dims: [dims[0], y.len(), z.len()],
            spacing,
            data,
        })
    }

    /// A grid of `dims` voxels (x fastest) from their samples (as many as the dims hold).
    pub fn from_samples(dims: [usize; 3], spacing: [f64; 3], data: Samples) -> Self {
        debug_assert_eq!(data.len(), dims.iter().product::<usize>());
        RawGrid {
            dims,
            spacing,
            data,
        }
    }

    /// `(min, max)` of the finite samples (`None` when there is none).
    pub fn value_range(&self) -> Option<(f32, f32)> {
        self.data
            .value_range()
            .map(|(lo, hi)| (lo as f32, hi as f32))
    }

    /// Index of the first non-finite sample, if any (only float grids can have one).
    pub fn first_non_finite(&self) -> Option<usize> {
        self.data.first_non_finite()
    }

    /// Replaces non-finite samples by `value`; returns how many.
    pub fn replace_non_finite(&mut self, value: f32) -> usize {
        self.data.replace_non_finite(value as f64)
    }

    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let hi = [0, 1, 2].map(|a| (self.dims[a] - 1) as f64 * self.spacing[a]);
        ([0.0; 3], hi)
    }

    #[inline]
    fn at(&self, i: usize, j: usize, k: usize) -> f64 {
        self.data.get(i + self.dims[0] * (j + self.dims[1] * k))
    }

    /// The voxel at index `[i, j, k]`.
    pub fn voxel(&self, [i, j, k]: [usize; 3]) -> f64 {
        self.at(i, j, k)
    }

    /// Trilinear interpolation at `p` (clamped to the grid). A coordinate within 1e-9 steps of a
    /// voxel plane is snapped to it, so that a voxel's position reads exactly its value.
    pub fn sample(&self, p: [f64; 3]) -> f64 {
        let mut i0 = [0usize; 3];
        let mut t = [0.0f64; 3];
        for a in 0..3 {
            let x = p[a] / self.spacing[a];
            let x = if (x - x.round()).abs() <= 1e-9 * x.abs().max(1.0) {
                x.round()
            } else {
                x
            };
            let x = x.clamp(0.0, (self.dims[a] - 1) as f64);
            let f = (x.floor() as usize).min(self.dims[a] - 2);
            i0[a] = f;
            t[a] = x - f as f64;
        }
        let [i, j, k] = i0;
        let c = |di, dj, dk| self.at(i + di, j + dj, k + dk);
        let lerp = |a: f64, b: f64, s: f64| a + (b - a) * s;
        let x00 = lerp(c(0, 0, 0), c(1, 0, 0), t[0]);
        let x10 = lerp(c(0, 1, 0), c(1, 1, 0), t[0]);
        let x01 = lerp(c(0, 0, 1), c(1, 0, 1), t[0]);
        let x11 = lerp(c(0, 1, 1), c(1, 1, 1), t[0]);
        lerp(lerp(x00, x10, t[1]), lerp(x01, x11, t[1]), t[2])
    }
}

/// The largest padding, as a share of the grid's own points, [`VoxelLattice::fit`] accepts when it
/// chooses the levels.
const MOST_PADDING: f64 = 0.5;
/// The most Kuhn cells [`VoxelLattice::fit`] gives a base mesh when it chooses the levels (6 tets
/// each: a base mesh a client receives first, in one message).
pub const MOST_AUTO_CELLS: usize = 4096;
/// The most base tets an explicit `--levels` may ask for.
pub const MOST_BASE_TETS: usize = 1 << 22;

/// Where a raw grid's voxels sit in a semi-regular mesh of Kuhn cells refined `levels` times: a
/// cell spans `2^levels` voxel steps per axis, `cells[a] · 2^levels ≥ dims[a] − 1`, so voxel
/// `(i, j, k)` is the lattice point at `(i, j, k) · spacing`. The lattice reaches past the grid by
/// less than a cell per axis; a non-cubic grid gets cells along its long axes, not a cube.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelLattice {
    pub levels: u8,
    pub cells: [usize; 3],
    /// The lattice's far corner (its near one is the origin, voxel 0).
    pub hi: [f64; 3],
    /// Lattice points per axis: `cells · 2^levels + 1`.
    pub points: [usize; 3],
}

#[derive(Debug, thiserror::Error)]
pub enum LatticeError {
    #[error(
        "--levels {levels} cuts a {x}×{y}×{z} grid into {tets} base tets (at most {MOST_BASE_TETS}); \
         give more levels, or omit --levels to have them chosen"
    )]
    TooManyCells {
        levels: u8,
        x: usize,
        y: usize,
        z: usize,
        tets: usize,
    },
    #[error("a {x}×{y}×{z} grid has more voxels than a hierarchy can index at any level")]
    TooLarge { x: usize, y: usize, z: usize },
}

impl VoxelLattice {
    /// The lattice of a grid of `dims` voxels at `levels`.
    pub fn at(dims: [usize; 3], spacing: [f64; 3], levels: u8) -> Self {
        let side = 1usize << levels;
        let cells = dims.map(|n| (n.max(2) - 1).div_ceil(side));
        VoxelLattice {
            levels,
            cells,
            hi: [0, 1, 2].map(|a| (cells[a] * side) as f64 * spacing[a]),
            points: cells.map(|c| c * side + 1),
        }
    }

    /// `levels` when given (refused when it would make an oversized base mesh); otherwise the most
    /// levels (coarsest base, most progressive stream) whose padding adds at most half the grid's
    /// points with at most 4,096 cells, or failing that the least padding, within what the
    /// hierarchy can index (`fits`: whether `levels` levels over `tets` base tets can).
    pub fn fit(
        dims: [usize; 3],
        spacing: [f64; 3],
        levels: Option<u8>,
        fits: impl Fn(u64, u8) -> bool,
    ) -> Result<Self, LatticeError> {
        let [x, y, z] = dims;
        if let Some(levels) = levels {
            let l = Self::at(dims, spacing, levels);
            let tets = 6usize.saturating_mul(l.cells.iter().product());
            if tets > MOST_BASE_TETS {
                return Err(LatticeError::TooManyCells {
                    levels,
                    x,
                    y,
                    z,
                    tets,
                });
            }
            return Ok(l);
        }
        let voxels = dims.iter().map(|&n| n as f64).product::<f64>();
        let longest = dims.iter().max().copied().unwrap_or(2).max(2) - 1;
        let top = (usize::BITS - (longest - 1).leading_zeros()) as u8;
        let candidates: Vec<(Self, f64)> = (0..=top.min(super::MAX_LEVELS))
            .rev()
            .map(|l| Self::at(dims, spacing, l))
            .filter(|l| {
                let cells: usize = l.cells.iter().product();
                cells <= MOST_AUTO_CELLS && fits(6 * cells as u64, l.levels)
            })
            .map(|l| {
                let points = l.points.iter().map(|&n| n as f64).product::<f64>();
                (l, points / voxels - 1.0)
            })
            .collect();
        candidates
            .iter()
            .find(|(_, pad)| *pad <= MOST_PADDING)
            .or_else(|| {
                candidates
                    .iter()
                    .min_by(|a, b| a.1.total_cmp(&b.1).then(b.0.levels.cmp(&a.0.levels)))
            })
            .map(|(l, _)| *l)
            .ok_or(LatticeError::TooLarge { x, y, z })
    }

    /// Whether the lattice reaches past the grid (then the grid's box is clipped out of it).
    pub fn pads(&self, dims: [usize; 3]) -> bool {
        (0..3).any(|a| self.points[a] > dims[a])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattices_hold_every_voxel_with_little_padding() {
        let any = |_: u64, _: u8| true;
        // 128³: one cell at 7 levels, one padding layer
        let l = VoxelLattice::fit([128; 3], [1.0; 3], None, any).unwrap();
        assert_eq!((l.levels, l.cells, l.points), (7, [1; 3], [129; 3]));
        assert!(l.pads([128; 3]) && !l.pads([129; 3]));
        // 129³ fits 7 levels exactly
        let l = VoxelLattice::fit([129; 3], [1.0; 3], None, any).unwrap();
        assert_eq!((l.levels, l.cells), (7, [1; 3]));
        assert!(!l.pads([129; 3]));
        // non-cubic: cells along the long axes, not a cube
        let l = VoxelLattice::fit([512, 512, 100], [0.5, 0.5, 2.0], None, any).unwrap();
        assert_eq!(
            (l.levels, l.cells, l.points),
            (7, [4, 4, 1], [513, 513, 129])
        );
        assert_eq!(l.hi, [256.0, 256.0, 256.0]);
        // explicit levels: as many cells as needed
        let l = VoxelLattice::fit([128; 3], [1.0; 3], Some(5), any).unwrap();
        assert_eq!(l.cells, [4; 3]);
        assert!(VoxelLattice::fit([4097, 4097, 2], [1.0; 3], Some(0), any).is_err());
        // levels the hierarchy cannot index are skipped
        let l = VoxelLattice::fit([1025; 3], [1.0; 3], None, |_, l| l <= 9).unwrap();
        assert_eq!((l.levels, l.cells), (9, [2; 3]));
        // every grid from 2 to 70 points per axis is covered, each voxel on a lattice point
        for n in 2..70 {
            for dims in [[n, 2, 3], [n, n, 7], [3, n, n]] {
                let l = VoxelLattice::fit(dims, [1.0; 3], None, any).unwrap();
                for a in 0..3 {
                    assert!(l.points[a] >= dims[a], "{dims:?}: {l:?}");
                    assert_eq!(l.hi[a], (l.points[a] - 1) as f64);
                }
            }
        }
    }

    #[test]
    fn samples_at_voxels_are_the_voxels() {
        let dims = [5, 4, 3];
        let path = std::env::temp_dir().join(format!("tetwave-raw-{}.raw", std::process::id()));
        let values: Vec<f32> = (0..60).map(|i| (i as f32 * 0.37).sin() * 1e3).collect();
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(&path, bytes).unwrap();
        let s = [0.7, 0.1, 3.3];
        let g = RawGrid::read(&path, dims, RawType::F32, s).unwrap();
        std::fs::remove_file(&path).ok();
        for k in 0..3 {
            for j in 0..4 {
                for i in 0..5 {
                    // a position as the base mesh computes it: a lattice corner times a fraction
                    let p = [i, j, k].map(|n| n as f64);
                    let p = [0, 1, 2].map(|a| (8.0 * s[a]) * (p[a] / 8.0));
                    assert_eq!(g.sample(p), values[i + 5 * (j + 4 * k)] as f64);
                }
            }
        }
        // past the grid: the nearest voxel
        assert_eq!(g.sample([100.0, 0.0, 0.0]), values[4] as f64);
    }
}
