//! Wavelet analysis: predict-only lifting over the semi-regular hierarchy (thesis §4.3; docs/protocol.md).
//!
//! For every new vertex `m` (midpoint of an edge `(u,v)` of a level-`k−1` tet) one detail
//! `d_m = f(m) − P(m)`, `P` the prediction of [`tetwave_protocol::wavelet`] (linear on base edges,
//! the parent's quadratic interpolant below), owned by the lowest-id level-`k−1` tet containing the
//! edge.
//! The details are computed against the values *synthesis will reconstruct* (closed loop, coarse to
//! fine): in exact arithmetic this is the same as lifting from the finest level up, and in f32 it makes
//! the lossless round trip bit-exact (see [`tetwave_protocol::wavelet::analyze`]) and keeps quantization
//! error from accumulating across levels: with step `q` every vertex is within `q/2` of its sample.
//!
//! Per node the analysis also records the max linear detail `|f(m) − (f(u)+f(v))/2|` of the sampled
//! values over its edges and its subtree's, raised to its sibling group's largest (the selection's
//! error estimate: what drawing the tet without its subtree costs, whatever the predictor; one
//! value per group codes as one), and which children are empty (outside the input's domain, see [`crate::resample`]).

mod axes;
mod gather;

pub use axes::AXES_MAX_MAGNITUDE;
mod keys;
mod par;
mod samples;
mod walk;

use crate::resample::{Resampled, MAX_NODES};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use samples::SampleStats;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use tetwave_protocol::store_format::QUANTIZED_BITS;
use tetwave_protocol::vertex::VertexKeys;
use tetwave_protocol::wavelet::{LevelSteps, Predictor, Quantizer};
use tetwave_protocol::BaseMesh;
use walk::{load, Cell, Owner, Walk};

/// Everything the store needs, in node-id order.
pub struct Analysis {
    /// Base mesh with reconstructed base values and empty flags.
    pub base: BaseMesh,
    /// Per node: owned-edge mask.
    pub owned: Vec<u8>,
    /// Per node: bit `i` set when child `i` is empty.
    pub empty_children: Vec<u8>,
    /// Per node: max |detail| of all vertices created by refining it and its descendants.
    pub subtree_max_abs: Vec<f32>,
    /// Owned details in node order, then edge order (dequantized when quantized).
    pub coeffs: Vec<f32>,
    /// The finest level's quantizer (its step makes the bound).
    pub quantizer: Option<Quantizer>,
    /// How coarser levels' steps shrink ([`LevelSteps::UNIFORM`] unless quantized to a bound with
    /// the axes predictor).
    pub level_steps: LevelSteps,
    /// The sampled value of every vertex (outside vertices filled by the outside rule): what
    /// synthesis is compared against.
    pub reference: Vec<f32>,
    /// Inside samples' range.
    pub value_range: (f32, f32),
    /// Measured max |synthesis − sample|.
    pub max_abs_error: f64,
    /// The bound the store promises (`q/2` plus f32 rounding when quantized, `1e-6 × range` lossless).
    pub error_bound: f64,
}

impl Analysis {
    /// What the store writes.
    pub fn content(&self) -> tetwave_store::StoreContent<'_> {
        tetwave_store::StoreContent {
            base: &self.base,
            owned: &self.owned,
            empty_children: &self.empty_children,
            subtree_max_abs: &self.subtree_max_abs,
            coeffs: &self.coeffs,
            quantizer: self.quantizer.map(|q| (q, self.level_steps)),
            reference: &self.reference,
            value_range: self.value_range,
            max_abs_error: self.max_abs_error,
            error_bound: self.error_bound,
        }
    }

    /// The detail nodes in id order, as the store holds them.
    pub fn nodes(&self) -> Vec<tetwave_protocol::DetailNode> {
        let mut at = 0;
        (0..self.owned.len())
            .map(|i| {
                let n = self.owned[i].count_ones() as usize;
                let node = tetwave_protocol::DetailNode {
                    id: i as u64,
                    owned: self.owned[i],
                    empty_children: self.empty_children[i],
                    subtree_max_abs: self.subtree_max_abs[i],
                    coeffs: self.coeffs[at..at + n].to_vec(),
                };
                at += n;
                node
            })
            .collect()
    }
}

#[derive(Debug, thiserror::Error)]
pub enum AnalysisError {
    #[error("--bits must be in 8..=24, got {0}")]
    BadBits(u8),
    #[error("--max-error {0}: give a positive, finite bound")]
    BadMaxError(f64),
    #[error(
        "--max-error {percent}%: the samples' value range is 0 (a constant field), so the bound \
         would be 0; give an absolute bound, or leave it out for a lossless store"
    )]
    ZeroRange { percent: f64 },
    #[error(
        "--max-error {bound}: below what f32 values of magnitude {magnitude} can hold; \
         leave it out for a lossless store"
    )]
    MaxErrorTooSmall { bound: f64, magnitude: f64 },
    #[error(
        "--max-error {bound}: details up to {detail} would need codes wider than 24 bits; \
         leave it out for a lossless store"
    )]
    MaxErrorNeedsTooManyBits { bound: f64, detail: f64 },
    #[error("{0} tets in one level is more than this build can index")]
    TooLarge(u64),
    #[error("--predictor axes: {0}")]
    Axes(#[from] tetwave_protocol::axes::AxesError),
    #[error(
        "--predictor axes needs data at every vertex (a grid or synthetic input), and {0} \
         vertices lie outside the input's domain; use the parent predictor for meshes"
    )]
    AxesOutside(u64),
    #[error(
        "--predictor axes: the samples reach {0:.2e}, and its cubic predictions overflow f32 \
         beyond ±{AXES_MAX_MAGNITUDE:e}; use --predictor parent (up to ±{MAX_MAGNITUDE:e}) or \
         rescale the input"
    )]
    AxesOverflow(f64),
    #[error(
        "the samples reach {0:.2e}: wavelet details of values beyond ±{MAX_MAGNITUDE:e} overflow \
         f32; rescale the input"
    )]
    Magnitude(f64),
}

/// Largest sample magnitude the analysis takes: the parent predictor sums up to 6 values and a
/// detail is a difference of two, which must stay finite f32s.
pub const MAX_MAGNITUDE: f32 = 1e37;

fn bar(len: u64, msg: &str, show: bool) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} ({eta})")
            .unwrap_or(ProgressStyle::default_bar()),
    );
    pb.set_message(msg.to_string());
    pb
}

/// Level-`k−1` parents per parallel task (their 8 children each are the level-`k` tets it visits).
const PARENTS_PER_TASK: usize = 64;
/// Base tets per parallel task at level 0.
const BASE_PER_TASK: usize = 4096;
/// Below this many items a pass runs on the calling thread (waking the pool costs more).
const SEQUENTIAL_BELOW: usize = 1 << 13;
/// From this many vertices the per-vertex setup passes run in parallel (below, waking the pool
/// costs more than it saves).
const PARALLEL_PASS_FROM: usize = 1 << 19;
/// From this many vertices the owned masks and coefficients are gathered in parallel.
const SCATTER_PARALLEL_FROM: usize = 1 << 16;
/// Levels of at least this many tets are walked in parallel.
const PARALLEL_WALK_FROM: usize = 1 << 11;

/// How precisely the details are kept.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Precision {
    /// f32 details: synthesis reproduces the samples to f32 rounding.
    Lossless,
    /// Uniform quantization to this many bits (8..=24), the step sized to cover every detail.
    Bits(u8),
    /// The step chosen so that every reconstructed vertex is within this of its sample, the code
    /// width so that the codes cover every detail.
    MaxError(ErrorBound),
}

/// A bound on the reconstruction error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ErrorBound {
    /// In the field's units.
    Absolute(f64),
    /// This fraction of the sampled value range (`--max-error 0.1%` is `OfRange(0.001)`).
    OfRange(f64),
}

impl ErrorBound {
    /// Parses `E` (absolute) or `E%` (of the value range).
    pub fn parse(s: &str) -> Result<Self, String> {
        let t = s.trim();
        let (num, pct) = match t.strip_suffix('%') {
            Some(n) => (n.trim(), true),
            None => (t, false),
        };
        let x: f64 = num
            .parse()
            .map_err(|_| format!("not a number or a percentage: {s:?}"))?;
        if !(x.is_finite() && x > 0.0) {
            return Err(format!("must be positive and finite: {s:?}"));
        }
        Ok(if pct {
            ErrorBound::OfRange(x / 100.0)
        } else {
            ErrorBound::Absolute(x)
        })
    }
}

/// Runs the analysis with details kept to `precision`.
pub fn analyze_hierarchy(
    r: Resampled,
    precision: Precision,
    progress: bool,
) -> Result<Analysis, AnalysisError> {
    analyze_hierarchy_in_range(r, precision, progress, None)
}

/// [`analyze_hierarchy`] of a part of a store (`prepare --part`): `range`, when given, is the
/// inside samples' range over the whole input rather than over `r`'s samples, so that every
/// part sizes the quantizer and the bound as one analysis of the whole would.
pub fn analyze_hierarchy_in_range(
    r: Resampled,
    precision: Precision,
    progress: bool,
    range: Option<(f32, f32)>,
) -> Result<Analysis, AnalysisError> {
    if let Precision::Bits(b) = precision {
        if !tetwave_protocol::store_format::QUANTIZED_BITS.contains(&b) {
            return Err(AnalysisError::BadBits(b));
        }
    }
    let forest = r.base.forest();
    let levels = forest.levels;
    if levels > 0 && forest.nodes() > MAX_NODES {
        return Err(AnalysisError::TooLarge(forest.level_len(levels - 1)));
    }
    let mut stats = SampleStats::of(&r.samples);
    if let Some((lo, hi)) = range {
        (stats.lo, stats.hi) = (lo, hi);
    }
    let magnitude = stats.lo.abs().max(stats.hi.abs());
    if magnitude > MAX_MAGNITUDE {
        return Err(AnalysisError::Magnitude(magnitude as f64));
    }
    if r.base.predictor == Predictor::Axes && magnitude > AXES_MAX_MAGNITUDE {
        return Err(AnalysisError::AxesOverflow(magnitude as f64));
    }
    let (mut quantizer, level_steps) = match samples::size_quantizer(precision, &r, &stats)? {
        Some((q, steps)) => (Some(q), steps),
        None => (None, LevelSteps::UNIFORM),
    };
    let Resampled {
        base,
        keys,
        samples,
        ..
    } = r;
    let axes = base.predictor == Predictor::Axes;
    if axes && stats.any_outside() {
        return Err(AnalysisError::AxesOutside(stats.outside_count()));
    }
    // The code width covers the details the samples show; with an outside, the inside vertices
    // beside it are predicted from the field extended past the domain (see `walk`), which the
    // samples do not show, and the axes predictor's cubic can overshoot the details they show:
    // either way a code may be clamped. Then the walk is run again, wider.
    let spare = (quantizer.is_some() && (stats.any_outside() || axes))
        .then(|| (base.clone(), samples.clone()));
    let mut a = walk_all(
        base,
        &keys,
        samples,
        &stats,
        quantizer,
        level_steps,
        progress,
    )?;
    let Some((base, samples)) = spare else {
        return Ok(a);
    };
    while a.max_abs_error > a.error_bound {
        let q = quantizer.expect("a quantized walk");
        let wider = match precision {
            // the same step (it makes the bound), one more bit
            Precision::MaxError(_) if q.bits < *QUANTIZED_BITS.end() => Quantizer {
                bits: q.bits + 1,
                ..q
            },
            Precision::MaxError(_) => {
                return Err(AnalysisError::MaxErrorNeedsTooManyBits {
                    bound: a.error_bound,
                    detail: a.max_abs_error,
                })
            }
            // the width the user chose, a coarser step (finite details: a bounded number of
            // doublings covers them)
            _ if (q.step * 2.0).is_finite() => Quantizer {
                step: q.step * 2.0,
                ..q
            },
            _ => {
                return Err(AnalysisError::MaxErrorNeedsTooManyBits {
                    bound: a.error_bound,
                    detail: a.max_abs_error,
                })
            }
        };
        tracing::info!(
            bits = wider.bits,
            step = wider.step,
            clamped_error = a.max_abs_error,
            "details exceed the codes; analysing again"
        );
        quantizer = Some(wider);
        a = walk_all(
            base.clone(),
            &keys,
            samples.clone(),
            &stats,
            quantizer,
            level_steps,
            progress,
        )?;
    }
    Ok(a)
}

/// One analysis of `samples` (outside vertices NaN) with details kept by `quantizer`, with owner
/// codes as narrow as the hierarchy allows ([`Owner`]).
fn walk_all(
    base: BaseMesh,
    keys: &VertexKeys,
    samples: Vec<f32>,
    stats: &SampleStats,
    quantizer: Option<Quantizer>,
    level_steps: LevelSteps,
    progress: bool,
) -> Result<Analysis, AnalysisError> {
    if base.forest().nodes() <= <AtomicU32 as Owner>::MAX_NODES {
        walk_all_with::<AtomicU32>(base, keys, samples, stats, quantizer, level_steps, progress)
    } else {
        walk_all_with::<AtomicU64>(base, keys, samples, stats, quantizer, level_steps, progress)
    }
}

/// [`walk_all`] with owner codes in `O`.
fn walk_all_with<O: Owner>(
    mut base: BaseMesh,
    keys: &VertexKeys,
    samples: Vec<f32>,
    stats: &SampleStats,
    quantizer: Option<Quantizer>,
    level_steps: LevelSteps,
    progress: bool,
) -> Result<Analysis, AnalysisError> {
    let forest = base.forest();
    let levels = forest.levels;
    let nodes = forest.nodes() as usize;
    let nv = base.positions.len();
    let n = samples.len();
    let (lo, hi) = (stats.lo, stats.hi);
    let reference = samples::reference_values(samples, stats, nv);
    let cell = |r: &AtomicU32| Cell {
        rec: AtomicU32::new(r.load(Ordering::Relaxed)),
        owner: O::new(O::UNOWNED),
    };
    let zero = |_| AtomicU32::new(0);
    let (cells, detail): (Vec<Cell<O>>, Vec<AtomicU32>) = if n >= PARALLEL_PASS_FROM {
        (
            reference.par_iter().map(cell).collect(),
            (0..n).into_par_iter().map(zero).collect(),
        )
    } else {
        (
            reference.iter().map(cell).collect(),
            (0..n).map(zero).collect(),
        )
    };
    let mut empty_children = vec![0u8; nodes];
    let mut subtree_max_abs = vec![0f32; nodes];
    let walk = Walk {
        reference: &reference,
        cells: &cells,
        detail: &detail,
        outside: stats.any_outside().then_some(&stats.outside_bits[..]),
        // the parent predictor's walk quantizes every level alike (`analyze` gives it uniform
        // steps)
        quantizer,
        details: base.predictor == Predictor::Parent,
    };
    debug_assert!(base.predictor == Predictor::Axes || level_steps == LevelSteps::UNIFORM);
    let mut max_err = walk.levels(
        forest,
        keys,
        &mut subtree_max_abs,
        &mut empty_children,
        progress,
    );
    if base.predictor == Predictor::Axes {
        let q = quantizer.map(|q| (q, level_steps));
        max_err = axes::details(&base, keys, &reference, &cells, &detail, q)?;
    }
    let (owned, coeffs) = gather::owned_coefficients(&cells, &detail, nodes, nv);
    drop(detail);
    gather::fold_subtrees(forest, &mut empty_children, &mut subtree_max_abs);
    tetwave_protocol::node::group_siblings(forest.n_base as usize, &mut subtree_max_abs);
    base.empty = (0..base.tets.len())
        .map(|b| {
            if levels == 0 {
                base.tets[b].iter().all(|&v| stats.is_outside(v as usize))
            } else {
                empty_children[b] == 0xff
            }
        })
        .collect();
    base.values = cells[..nv].iter().map(|c| load(&c.rec)).collect();
    drop(cells);
    // in place again
    let reference: Vec<f32> = reference
        .into_iter()
        .map(|a| f32::from_bits(a.into_inner()))
        .collect();
    let error_bound = samples::error_bound(quantizer.as_ref(), lo, hi);
    Ok(Analysis {
        base,
        owned,
        empty_children,
        subtree_max_abs,
        coeffs,
        quantizer,
        level_steps,
        reference,
        value_range: (lo, hi),
        max_abs_error: max_err,
        error_bound,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resample::synthetic::Synthetic;
    use crate::resample::{resample, BaseSpec, Source};

    /// The walk with 64-bit owner codes (what a hierarchy past 2^29 nodes takes) gives what the
    /// 32-bit one gives, byte for byte: both predictors, lossless and quantized, a box5 and a
    /// box6 base.
    #[test]
    fn wide_owner_codes_analyse_alike() {
        let field = Synthetic::parse("harmonic").unwrap();
        for (spec, predictor, levels) in [
            (BaseSpec::Box5, Predictor::Parent, 4),
            (BaseSpec::Box6, Predictor::Axes, 4),
        ] {
            let mut r = resample(&Source::Synthetic(field), &spec, levels).unwrap();
            r.base.predictor = predictor;
            let stats = SampleStats::of(&r.samples);
            for precision in [Precision::Lossless, Precision::Bits(12)] {
                let (q, steps) = match samples::size_quantizer(precision, &r, &stats).unwrap() {
                    Some((q, steps)) => (Some(q), steps),
                    None => (None, LevelSteps::UNIFORM),
                };
                let run = |wide: bool| {
                    let (base, samples) = (r.base.clone(), r.samples.clone());
                    let a = if wide {
                        walk_all_with::<AtomicU64>(base, &r.keys, samples, &stats, q, steps, false)
                    } else {
                        walk_all_with::<AtomicU32>(base, &r.keys, samples, &stats, q, steps, false)
                    };
                    a.unwrap()
                };
                let (narrow, wide) = (run(false), run(true));
                let what = format!("{spec:?} {predictor:?} {precision:?}");
                assert_eq!(narrow.owned, wide.owned, "{what}");
                assert_eq!(narrow.empty_children, wide.empty_children, "{what}");
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&narrow.coeffs), bits(&wide.coeffs), "{what}");
                assert_eq!(
                    bits(&narrow.subtree_max_abs),
                    bits(&wide.subtree_max_abs),
                    "{what}"
                );
                assert_eq!(bits(&narrow.base.values), bits(&wide.base.values), "{what}");
                assert_eq!(narrow.max_abs_error, wide.max_abs_error, "{what}");
                assert!(narrow.coeffs.len() > 1000, "{what}");
            }
        }
    }
}
