//! Raw scalar grids (`--dims X,Y,Z --dtype u8|u16|f32 [--spacing sx,sy,sz]`), x fastest, little-endian,
//! sampled by trilinear interpolation.

use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RawType {
    U8,
    U16,
    F32,
}

impl RawType {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "u8" => Some(RawType::U8),
            "u16" => Some(RawType::U16),
            "f32" => Some(RawType::F32),
            _ => None,
        }
    }
    pub fn bytes(&self) -> usize {
        match self {
            RawType::U8 => 1,
            RawType::U16 => 2,
            RawType::F32 => 4,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RawError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("raw grid needs --dims X,Y,Z and --dtype u8|u16|f32")]
    MissingDims,
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
    data: RawData,
}

enum RawData {
    U8(Vec<u8>),
    U16(Vec<u16>),
    F32(Vec<f32>),
}

impl RawGrid {
    pub fn read(
        path: &Path,
        dims: [usize; 3],
        dtype: RawType,
        spacing: [f64; 3],
    ) -> Result<Self, RawError> {
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
        let bytes = std::fs::read(path).map_err(io)?;
        let data = match dtype {
            RawType::U8 => RawData::U8(bytes),
            RawType::U16 => RawData::U16(
                bytes
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]]))
                    .collect(),
            ),
            RawType::F32 => RawData::F32(
                bytes
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect(),
            ),
        };
        Ok(RawGrid {
            dims,
            spacing,
            data,
        })
    }

    /// `(min, max)` of the finite samples (`None` when there is none).
    pub fn value_range(&self) -> Option<(f32, f32)> {
        let fold = |it: &mut dyn Iterator<Item = f32>| {
            it.filter(|x| x.is_finite())
                .fold(None, |r: Option<(f32, f32)>, x| {
                    Some(r.map_or((x, x), |(lo, hi)| (lo.min(x), hi.max(x))))
                })
        };
        match &self.data {
            RawData::U8(v) => fold(&mut v.iter().map(|&x| x as f32)),
            RawData::U16(v) => fold(&mut v.iter().map(|&x| x as f32)),
            RawData::F32(v) => fold(&mut v.iter().copied()),
        }
    }

    /// Index of the first non-finite sample, if any (only f32 grids can have one).
    pub fn first_non_finite(&self) -> Option<usize> {
        match &self.data {
            RawData::F32(v) => v.iter().position(|x| !x.is_finite()),
            _ => None,
        }
    }

    /// Replaces non-finite samples by `value`; returns how many.
    pub fn replace_non_finite(&mut self, value: f32) -> usize {
        match &mut self.data {
            RawData::F32(v) => {
                let mut n = 0;
                for x in v.iter_mut().filter(|x| !x.is_finite()) {
                    *x = value;
                    n += 1;
                }
                n
            }
            _ => 0,
        }
    }

    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let hi = [0, 1, 2].map(|a| (self.dims[a] - 1) as f64 * self.spacing[a]);
        ([0.0; 3], hi)
    }

    #[inline]
    fn at(&self, i: usize, j: usize, k: usize) -> f64 {
        let idx = i + self.dims[0] * (j + self.dims[1] * k);
        match &self.data {
            RawData::U8(v) => v[idx] as f64,
            RawData::U16(v) => v[idx] as f64,
            RawData::F32(v) => v[idx] as f64,
        }
    }

    /// Trilinear interpolation at `p` (clamped to the grid).
    pub fn sample(&self, p: [f64; 3]) -> f64 {
        let mut i0 = [0usize; 3];
        let mut t = [0.0f64; 3];
        for a in 0..3 {
            let x = (p[a] / self.spacing[a]).clamp(0.0, (self.dims[a] - 1) as f64);
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
