//! What the walks need from the samples before they start: the inside range, which vertices lie
//! outside the input's domain, the quantizer's step, and the reference values (outside base
//! vertices filled).

use super::keys::{for_each_split_keys, for_each_tet_keys, parent_chunks};
use super::PARALLEL_PASS_FROM;
use super::{AnalysisError, ErrorBound, Precision};
use crate::resample::Resampled;
use rayon::prelude::*;
use std::sync::atomic::AtomicU32;
use tetwave_protocol::hierarchy::{BEY_SPLIT, EDGES};
use tetwave_protocol::store_format::QUANTIZED_BITS;
use tetwave_protocol::wavelet::{predict_split, LevelSteps, Predictor, Quantizer};
use tetwave_protocol::Forest;

/// The inside samples' range and the outside vertices (NaN samples).
pub(super) struct SampleStats {
    pub(super) lo: f32,
    pub(super) hi: f32,
    /// Bitset of the outside vertices; empty when there are none.
    pub(super) outside_bits: Vec<u64>,
}

impl SampleStats {
    pub(super) fn of(samples: &[f32]) -> Self {
        let big = samples.len() >= PARALLEL_PASS_FROM;
        // range of the inside samples (`min`/`max` skip NaN) and the outside (NaN) count
        let block = 1 << 16; // a multiple of 64: blocks' bitsets concatenate
        let range_of = |xs: &[f32]| {
            // 8 independent lanes (vectorizable); a comparison with NaN is false, so NaN never wins
            const L: usize = 8;
            let (mut lo, mut hi, mut nan) = ([f32::INFINITY; L], [f32::NEG_INFINITY; L], [0u32; L]);
            let mut chunks = xs.chunks_exact(L);
            for c in &mut chunks {
                for l in 0..L {
                    let x = c[l];
                    lo[l] = if x < lo[l] { x } else { lo[l] };
                    hi[l] = if x > hi[l] { x } else { hi[l] };
                    nan[l] += x.is_nan() as u32;
                }
            }
            let tail = chunks.remainder().iter().fold(
                (f32::INFINITY, f32::NEG_INFINITY, 0usize),
                |(lo, hi, c), &x| (lo.min(x), hi.max(x), c + x.is_nan() as usize),
            );
            (0..L).fold(tail, |(a, b, c), l| {
                (a.min(lo[l]), b.max(hi[l]), c + nan[l] as usize)
            })
        };
        let merge =
            |a: (f32, f32, usize), b: (f32, f32, usize)| (a.0.min(b.0), a.1.max(b.1), a.2 + b.2);
        let (lo, hi, n_outside) = if big {
            samples
                .par_chunks(block)
                .map(range_of)
                .reduce(|| (f32::INFINITY, f32::NEG_INFINITY, 0), merge)
        } else {
            range_of(samples)
        };
        let any_outside = n_outside > 0;
        let outside_bits: Vec<u64> = if any_outside {
            let bits_of = |xs: &[f32]| {
                let mut bits = vec![0u64; xs.len().div_ceil(64)];
                for (j, x) in xs.iter().enumerate() {
                    bits[j >> 6] |= (x.is_nan() as u64) << (j & 63);
                }
                bits
            };
            if big {
                samples.par_chunks(block).flat_map_iter(bits_of).collect()
            } else {
                bits_of(samples)
            }
        } else {
            Vec::new()
        };
        SampleStats {
            lo,
            hi,
            outside_bits,
        }
    }

    #[inline]
    pub(super) fn any_outside(&self) -> bool {
        !self.outside_bits.is_empty()
    }

    pub(super) fn outside_count(&self) -> u64 {
        self.outside_bits
            .iter()
            .map(|w| w.count_ones() as u64)
            .sum()
    }

    #[inline]
    pub(super) fn is_outside(&self, v: usize) -> bool {
        self.any_outside() && (self.outside_bits[v >> 6] >> (v & 63)) & 1 != 0
    }
}

/// The finest level's quantizer for `precision` and how coarser levels' steps shrink (none:
/// lossless).
///
/// With `Bits(b)` the step is sized so that the codes cover every closed-loop detail, one step for
/// every level (the width the user chose must hold every code). With `MaxError(E)` the step is
/// chosen first: closed-loop quantization leaves each vertex with its own detail's rounding error
/// only (the prediction uses reconstructed values), at most `step / 2`, so `step = 2 E` less the
/// f32 rounding the analysis allows for ([`error_bound`]); with the axes predictor the coarser
/// levels take [`LevelSteps::AXES`] (one step when their codes would need more than 24 bits; the
/// parent predictor's walk quantizes every level alike); the code width is then the narrowest in
/// 8..=24 bits that covers every detail.
pub(super) fn size_quantizer(
    precision: Precision,
    r: &Resampled,
    stats: &SampleStats,
) -> Result<Option<(Quantizer, LevelSteps)>, AnalysisError> {
    let forest = r.base.forest();
    match precision {
        Precision::Lossless => Ok(None),
        Precision::Bits(b) => {
            let m = max_open_detail(forest, r);
            // closed-loop details are at most m + q (a prediction's weights sum to at most 2 in
            // absolute value, each read value is within q/2): the codes ±(2^(b−1)−1) cover them
            // with q = m/(max−2)
            let step = if m > 0.0 {
                let wanted = m / (Quantizer::max_code(b) - 2) as f64;
                if wanted < f32::MIN_POSITIVE as f64 {
                    tracing::warn!(
                        max_detail = m,
                        "--bits {b}: details this small need a step below f32's normal range; \
                         the step is {:e} instead, coarser than {b} bits (use --max-error, or \
                         rescale the input)",
                        f32::MIN_POSITIVE
                    );
                }
                (wanted as f32).max(f32::MIN_POSITIVE)
            } else {
                1.0
            };
            Ok(Some((Quantizer { bits: b, step }, LevelSteps::UNIFORM)))
        }
        Precision::MaxError(bound) => {
            let e = match bound {
                ErrorBound::Absolute(e) => e,
                ErrorBound::OfRange(f) if stats.hi > stats.lo => {
                    f * (stats.hi as f64 - stats.lo as f64)
                }
                ErrorBound::OfRange(f) if f.is_finite() && f > 0.0 => {
                    return Err(AnalysisError::ZeroRange { percent: f * 100.0 })
                }
                ErrorBound::OfRange(f) => f * (stats.hi as f64 - stats.lo as f64),
            };
            if !(e.is_finite() && e > 0.0) {
                return Err(AnalysisError::BadMaxError(e));
            }
            let range = stats.hi as f64 - stats.lo as f64;
            if range > 0.0 && e >= 0.5 * range {
                tracing::warn!(
                    max_error = e,
                    value_range = range,
                    "--max-error is at least half the value range: a constant at mid-range would \
                     meet it, and most details quantize to 0"
                );
            }
            // the largest step whose bound (error_bound) is at most e
            let magnitude = stats.lo.abs().max(stats.hi.abs()) as f64;
            let slack = 4.0 * f32::EPSILON as f64;
            // (1 − 1e-9): room for the rounding of error_bound's own arithmetic
            let step = (e - slack * magnitude) / (0.5 * (1.0 + 1e-6) + slack) * (1.0 - 1e-9);
            // f32 rounding of the step itself: never round it up
            let mut q = step as f32;
            if q as f64 > step {
                q = f32::from_bits(q.to_bits() - 1);
            }
            if !(step > 0.0 && q > 0.0) {
                return Err(AnalysisError::MaxErrorTooSmall {
                    bound: e,
                    magnitude,
                });
            }
            let m = max_open_detail(forest, r);
            // codes must reach the largest closed-loop detail, m + q (see `Bits`), on the coarse
            // levels in steps up to the cap times finer
            let need = ((m + q as f64) / q as f64).ceil() + 1.0;
            let width = |steps: LevelSteps| {
                let need = need * steps.cap as f64;
                QUANTIZED_BITS
                    .clone()
                    .find(|&b| Quantizer::max_code(b) as f64 >= need)
                    .map(|bits| (Quantizer { bits, step: q }, steps))
            };
            let finer = (r.base.predictor == Predictor::Axes).then_some(LevelSteps::AXES);
            finer
                .and_then(width)
                .or_else(|| width(LevelSteps::UNIFORM))
                .map(Some)
                .ok_or(AnalysisError::MaxErrorNeedsTooManyBits {
                    bound: e,
                    detail: m,
                })
        }
    }
}

/// The bound on `|synthesized − sample|` that a store with `quantizer` guarantees (what the
/// manifest records and `verify` checks): half a step plus f32 rounding, or f32 rounding alone.
pub(super) fn error_bound(quantizer: Option<&Quantizer>, lo: f32, hi: f32) -> f64 {
    match quantizer {
        Some(q) => {
            q.step as f64 / 2.0 * (1.0 + 1e-6)
                + 4.0 * f32::EPSILON as f64 * (lo.abs().max(hi.abs()) as f64 + q.step as f64)
        }
        None => 1e-6 * ((hi - lo) as f64).max(f32::MIN_POSITIVE as f64),
    }
}

/// The reference values (the samples' own memory, in place), outside base vertices set to the
/// mean of the inside samples.
pub(super) fn reference_values(
    samples: Vec<f32>,
    stats: &SampleStats,
    nv: usize,
) -> Vec<AtomicU32> {
    // outside base vertices take the mean of the inside samples
    let inside_mean = if (0..nv).any(|v| stats.is_outside(v)) {
        let (s, c) = samples
            .iter()
            .filter(|x| !x.is_nan())
            .fold((0f64, 0u64), |(s, c), &x| (s + x as f64, c + 1));
        (s / c.max(1) as f64) as f32
    } else {
        0.0
    };
    // in place (same layout): the samples' memory holds the reference values
    let reference: Vec<AtomicU32> = samples
        .into_iter()
        .map(|x| AtomicU32::new(x.to_bits()))
        .collect();
    for v in (0..nv).filter(|&v| stats.is_outside(v)) {
        super::walk::store(&reference[v], inside_mean);
    }
    reference
}

/// Max |open-loop detail| over all new vertices (sizes the quantizer).
/// The largest |open-loop detail| (the prediction evaluated on the samples) of any new vertex.
fn max_open_detail(forest: Forest, r: &Resampled) -> f64 {
    let f = |i: usize| r.samples[i];
    (0..forest.levels)
        .map(|k| {
            let chunks = parent_chunks(forest, k);
            chunks
                .into_par_iter()
                .map(|range| {
                    let mut m = 0f64;
                    let mut see = |d: f64| {
                        if d.is_finite() {
                            m = m.max(d.abs());
                        }
                    };
                    if k == 0 {
                        // base edges: the linear midpoint
                        for_each_tet_keys(forest, &r.keys, 0, range, |_, sk| {
                            for (e, &(a, b)) in EDGES.iter().enumerate() {
                                let lin = 0.5 * (f(sk[a]) as f64 + f(sk[b]) as f64);
                                see(f(sk[4 + e]) as f64 - lin);
                            }
                        });
                    } else {
                        // children of level-(k−1) tets: their parent's quadratic interpolant
                        for_each_split_keys(forest, &r.keys, k - 1, range, |_, pk, mid| {
                            let v: [f32; 10] = std::array::from_fn(|p| f(pk[p]));
                            for (j, &(a, b)) in BEY_SPLIT.edges.iter().enumerate() {
                                see(f(mid[j]) as f64 - predict_split(&v, a, b) as f64);
                            }
                        });
                    }
                    m
                })
                .reduce(|| 0.0, f64::max)
        })
        .fold(0.0, f64::max)
}
