//! Typed voxel buffers: the sample types volumes are stored in, their decoding from bytes in
//! either byte order, reorientation, rescale and the choice of one component of several.

use super::{AxisMap, ScalarChoice};

/// A voxel's stored type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl DType {
    pub const ALL: [DType; 8] = [
        DType::U8,
        DType::I8,
        DType::U16,
        DType::I16,
        DType::U32,
        DType::I32,
        DType::F32,
        DType::F64,
    ];

    /// `u8`, `i8`, `u16`, `i16`, `u32`, `i32`, `f32`, `f64`.
    pub fn parse(s: &str) -> Option<DType> {
        DType::ALL.into_iter().find(|t| t.name() == s)
    }

    pub fn name(&self) -> &'static str {
        match self {
            DType::U8 => "u8",
            DType::I8 => "i8",
            DType::U16 => "u16",
            DType::I16 => "i16",
            DType::U32 => "u32",
            DType::I32 => "i32",
            DType::F32 => "f32",
            DType::F64 => "f64",
        }
    }

    pub fn bytes(&self) -> usize {
        match self {
            DType::U8 | DType::I8 => 1,
            DType::U16 | DType::I16 => 2,
            DType::U32 | DType::I32 | DType::F32 => 4,
            DType::F64 => 8,
        }
    }
}

impl std::fmt::Display for DType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Byte order of stored samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Endian {
    Little,
    Big,
}

/// Voxels in their own type (a u8 volume stays 1 byte a voxel).
#[derive(Debug, Clone, PartialEq)]
pub enum Samples {
    U8(Vec<u8>),
    I8(Vec<i8>),
    U16(Vec<u16>),
    I16(Vec<i16>),
    U32(Vec<u32>),
    I32(Vec<i32>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

/// Applies `$body` to the vector inside any variant, rebuilding the same variant from its value.
macro_rules! each {
    ($s:expr, $v:ident => $body:expr) => {
        match $s {
            Samples::U8($v) => Samples::U8($body),
            Samples::I8($v) => Samples::I8($body),
            Samples::U16($v) => Samples::U16($body),
            Samples::I16($v) => Samples::I16($body),
            Samples::U32($v) => Samples::U32($body),
            Samples::I32($v) => Samples::I32($body),
            Samples::F32($v) => Samples::F32($body),
            Samples::F64($v) => Samples::F64($body),
        }
    };
}

/// Evaluates `$body` on the vector inside any variant.
macro_rules! with {
    ($s:expr, $v:ident => $body:expr) => {
        match $s {
            Samples::U8($v) => $body,
            Samples::I8($v) => $body,
            Samples::U16($v) => $body,
            Samples::I16($v) => $body,
            Samples::U32($v) => $body,
            Samples::I32($v) => $body,
            Samples::F32($v) => $body,
            Samples::F64($v) => $body,
        }
    };
}

impl Samples {
    /// Decodes `bytes` (a whole number of samples) stored as `dtype` in byte order `endian`.
    pub fn decode(dtype: DType, bytes: &[u8], endian: Endian) -> Samples {
        macro_rules! dec {
            ($t:ty, $n:literal, $variant:ident) => {
                Samples::$variant(
                    bytes
                        .chunks_exact($n)
                        .map(|c| {
                            let a: [u8; $n] = c.try_into().expect("chunks of the type's size");
                            match endian {
                                Endian::Little => <$t>::from_le_bytes(a),
                                Endian::Big => <$t>::from_be_bytes(a),
                            }
                        })
                        .collect(),
                )
            };
        }
        match dtype {
            DType::U8 => Samples::U8(bytes.to_vec()),
            DType::I8 => Samples::I8(bytes.iter().map(|&b| b as i8).collect()),
            DType::U16 => dec!(u16, 2, U16),
            DType::I16 => dec!(i16, 2, I16),
            DType::U32 => dec!(u32, 4, U32),
            DType::I32 => dec!(i32, 4, I32),
            DType::F32 => dec!(f32, 4, F32),
            DType::F64 => dec!(f64, 8, F64),
        }
    }

    /// An empty buffer of `dtype` with room for `n` samples.
    pub fn with_capacity(dtype: DType, n: usize) -> Samples {
        match dtype {
            DType::U8 => Samples::U8(Vec::with_capacity(n)),
            DType::I8 => Samples::I8(Vec::with_capacity(n)),
            DType::U16 => Samples::U16(Vec::with_capacity(n)),
            DType::I16 => Samples::I16(Vec::with_capacity(n)),
            DType::U32 => Samples::U32(Vec::with_capacity(n)),
            DType::I32 => Samples::I32(Vec::with_capacity(n)),
            DType::F32 => Samples::F32(Vec::with_capacity(n)),
            DType::F64 => Samples::F64(Vec::with_capacity(n)),
        }
    }

    /// Appends `other` (of the same type; `false` and nothing appended otherwise).
    pub fn extend(&mut self, other: &Samples) -> bool {
        match (self, other) {
            (Samples::U8(a), Samples::U8(b)) => a.extend_from_slice(b),
            (Samples::I8(a), Samples::I8(b)) => a.extend_from_slice(b),
            (Samples::U16(a), Samples::U16(b)) => a.extend_from_slice(b),
            (Samples::I16(a), Samples::I16(b)) => a.extend_from_slice(b),
            (Samples::U32(a), Samples::U32(b)) => a.extend_from_slice(b),
            (Samples::I32(a), Samples::I32(b)) => a.extend_from_slice(b),
            (Samples::F32(a), Samples::F32(b)) => a.extend_from_slice(b),
            (Samples::F64(a), Samples::F64(b)) => a.extend_from_slice(b),
            _ => return false,
        }
        true
    }

    pub fn dtype(&self) -> DType {
        match self {
            Samples::U8(_) => DType::U8,
            Samples::I8(_) => DType::I8,
            Samples::U16(_) => DType::U16,
            Samples::I16(_) => DType::I16,
            Samples::U32(_) => DType::U32,
            Samples::I32(_) => DType::I32,
            Samples::F32(_) => DType::F32,
            Samples::F64(_) => DType::F64,
        }
    }

    pub fn len(&self) -> usize {
        with!(self, v => v.len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sample `i` as f64 (exact for every type).
    #[inline]
    pub fn get(&self, i: usize) -> f64 {
        match self {
            Samples::U8(v) => v[i] as f64,
            Samples::I8(v) => v[i] as f64,
            Samples::U16(v) => v[i] as f64,
            Samples::I16(v) => v[i] as f64,
            Samples::U32(v) => v[i] as f64,
            Samples::I32(v) => v[i] as f64,
            Samples::F32(v) => v[i] as f64,
            Samples::F64(v) => v[i],
        }
    }

    /// `(min, max)` of the finite samples (`None` when there is none).
    pub fn value_range(&self) -> Option<(f64, f64)> {
        (0..self.len())
            .map(|i| self.get(i))
            .filter(|x| x.is_finite())
            .fold(None, |r, x| {
                Some(r.map_or((x, x), |(lo, hi): (f64, f64)| (lo.min(x), hi.max(x))))
            })
    }

    /// Index of the first non-finite sample (only float types can have one).
    pub fn first_non_finite(&self) -> Option<usize> {
        match self {
            Samples::F32(v) => v.iter().position(|x| !x.is_finite()),
            Samples::F64(v) => v.iter().position(|x| !x.is_finite()),
            _ => None,
        }
    }

    /// Replaces non-finite samples by `value`; returns how many.
    pub fn replace_non_finite(&mut self, value: f64) -> usize {
        let mut n = 0;
        match self {
            Samples::F32(v) => {
                for x in v.iter_mut().filter(|x| !x.is_finite()) {
                    *x = value as f32;
                    n += 1;
                }
            }
            Samples::F64(v) => {
                for x in v.iter_mut().filter(|x| !x.is_finite()) {
                    *x = value;
                    n += 1;
                }
            }
            _ => {}
        }
        n
    }

    /// The samples of a box of `fdims` (file order, fastest first) laid out along the world axes
    /// `axes` say (file axis `a` along world axis `axes[a].axis`, reversed where `flip`).
    pub fn reorient(self, fdims: [usize; 3], axes: [AxisMap; 3]) -> Samples {
        let mut wdims = [0; 3];
        for a in 0..3 {
            wdims[axes[a].axis] = fdims[a];
        }
        // file stride of each world axis, and where the world index 0 starts in the file
        let fstride = [1, fdims[0], fdims[0] * fdims[1]];
        let mut step = [0isize; 3];
        let mut start = 0isize;
        for a in 0..3 {
            let w = axes[a].axis;
            if axes[a].flip {
                step[w] = -(fstride[a] as isize);
                start += ((fdims[a] - 1) * fstride[a]) as isize;
            } else {
                step[w] = fstride[a] as isize;
            }
        }
        fn go<T: Copy>(src: &[T], wdims: [usize; 3], step: [isize; 3], start: isize) -> Vec<T> {
            let mut out = Vec::with_capacity(src.len());
            for k in 0..wdims[2] {
                for j in 0..wdims[1] {
                    let mut at = start + k as isize * step[2] + j as isize * step[1];
                    for _ in 0..wdims[0] {
                        out.push(src[at as usize]);
                        at += step[0];
                    }
                }
            }
            out
        }
        each!(self, v => go(&v, wdims, step, start))
    }

    /// `slope · v + intercept` of every sample, as f32 (f64 for an f64 buffer): exact for the
    /// integer results of integer slopes and intercepts up to 2^24.
    pub fn rescaled(self, slope: f64, intercept: f64) -> Samples {
        match self {
            Samples::F64(v) => Samples::F64(v.into_iter().map(|x| slope * x + intercept).collect()),
            s => Samples::F32(
                (0..s.len())
                    .map(|i| (slope * s.get(i) + intercept) as f32)
                    .collect(),
            ),
        }
    }

    /// Component `k` of `n` interleaved components a voxel.
    pub fn component(&self, n: usize, k: usize) -> Samples {
        each!(self, v => v.iter().skip(k).step_by(n.max(1)).copied().collect())
    }

    /// The Euclidean norm of each voxel's `n` interleaved components, as f32 (f64 for f64).
    pub fn magnitude(&self, n: usize) -> Samples {
        let n = n.max(1);
        let voxels = self.len() / n;
        let norm = |i: usize| {
            (0..n)
                .map(|c| self.get(i * n + c).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        match self {
            Samples::F64(_) => Samples::F64((0..voxels).map(norm).collect()),
            _ => Samples::F32((0..voxels).map(|i| norm(i) as f32).collect()),
        }
    }
}

/// Which component `choice` names among `names` (`n` components; names may be empty), with the
/// error message listing them when it names none. `Ok(None)`: the magnitude.
pub fn choose_component(
    choice: Option<&ScalarChoice>,
    n: usize,
    names: &[String],
) -> Result<Option<usize>, String> {
    let list = || {
        if names.len() == n && n > 0 {
            names
                .iter()
                .enumerate()
                .map(|(k, s)| format!("{k} ({s})"))
                .collect::<Vec<_>>()
                .join(", ")
        } else {
            format!("0 to {}", n.saturating_sub(1))
        }
    };
    match choice {
        None if n <= 1 => Ok(Some(0)),
        None => Err(format!(
            "{n} components a voxel: choose one with --scalar K or NAME, or --scalar mag (their \
             norm); components: {}",
            list()
        )),
        Some(ScalarChoice::Magnitude) => Ok(None),
        Some(ScalarChoice::Index(k)) if *k < n.max(1) => Ok(Some(*k)),
        Some(ScalarChoice::Index(k)) => Err(format!(
            "--scalar {k}: the volume has {} component(s): {}",
            n.max(1),
            list()
        )),
        Some(ScalarChoice::Name(s)) => {
            names.iter().position(|x| x == s).map(Some).ok_or_else(|| {
                format!(
                    "--scalar {s}: no component of that name; components: {}",
                    list()
                )
            })
        }
    }
}

/// The scalar of a voxel from its `n` interleaved components: `Some(k)` the component `k`,
/// `None` the magnitude.
pub fn select(samples: Samples, n: usize, which: Option<usize>) -> Samples {
    match (n, which) {
        (0 | 1, _) => samples,
        (_, Some(k)) => samples.component(n, k),
        (_, None) => samples.magnitude(n),
    }
}
