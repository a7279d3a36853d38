//! Wavelet analysis: predict-only lifting over the semi-regular hierarchy (thesis §4.3, design.md).
//!
//! For every new vertex `m` (midpoint of an edge `(u,v)` of a level-`k−1` tet) one detail
//! `d_m = f(m) − (f(u)+f(v))/2`, owned by the lowest-id level-`k−1` tet containing the edge.
//! The details are computed against the values *synthesis will reconstruct* (closed loop, coarse to
//! fine): in exact arithmetic this is the same as lifting from the finest level up, and in f32 it makes
//! the lossless round trip bit-exact (see [`tetwave_protocol::wavelet::analyze`]) and keeps quantization
//! error from accumulating across levels: with step `q` every vertex is within `q/2` of its sample.
//!
//! Per node the analysis also records the max |detail| of every vertex created in its subtree and which
//! children are empty (outside the input's domain, see [`crate::resample`]).

use crate::resample::Resampled;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use tetwave_protocol::hierarchy::{LevelWalker, EDGES};
use tetwave_protocol::wavelet::{analyze, predict, synthesize, Quantizer};
use tetwave_protocol::{BaseMesh, Forest};

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
    pub quantizer: Option<Quantizer>,
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

#[derive(Debug, thiserror::Error)]
pub enum AnalysisError {
    #[error("--bits must be in 8..=24, got {0}")]
    BadBits(u8),
}

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

/// Max |open-loop detail| over all new vertices (sizes the quantizer).
fn max_open_detail(forest: Forest, r: &Resampled) -> f64 {
    (0..forest.levels)
        .map(|k| {
            let (lo, hi) = (forest.level_start(k), forest.level_start(k + 1));
            let chunk = 8192u64;
            let ranges: Vec<_> = (lo..hi)
                .step_by(chunk as usize)
                .map(|s| s..(s + chunk).min(hi))
                .collect();
            ranges
                .into_par_iter()
                .map(|range| {
                    let mut m = 0f64;
                    for (_, tet) in LevelWalker::new(forest, k, range) {
                        for (e, &(a, b)) in EDGES.iter().enumerate() {
                            let fm =
                                r.samples[r.keys.key(tet.base, &tet.edge_midpoint(e)) as usize];
                            let fu = r.samples[r.keys.key(tet.base, &tet.v[a]) as usize];
                            let fv = r.samples[r.keys.key(tet.base, &tet.v[b]) as usize];
                            let d = fm as f64 - 0.5 * (fu as f64 + fv as f64);
                            if d.is_finite() {
                                m = m.max(d.abs());
                            }
                        }
                    }
                    m
                })
                .reduce(|| 0.0, f64::max)
        })
        .fold(0.0, f64::max)
}

/// Runs the analysis. `bits`: uniform quantization of the details (8..=24), or lossless f32.
pub fn analyze_hierarchy(
    r: Resampled,
    bits: Option<u8>,
    progress: bool,
) -> Result<Analysis, AnalysisError> {
    if let Some(b) = bits {
        if !(8..=24).contains(&b) {
            return Err(AnalysisError::BadBits(b));
        }
    }
    let forest = r.base.forest();
    let levels = forest.levels;
    let nodes = forest.nodes() as usize;
    let nv = r.base.positions.len();
    let outside: Vec<bool> = r.samples.iter().map(|x| x.is_nan()).collect();
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for &x in r.samples.iter().filter(|x| !x.is_nan()) {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    let range = (hi - lo) as f64;
    let quantizer = bits.map(|b| {
        let m = max_open_detail(forest, &r);
        // closed-loop details are at most m + q/2: the codes ±(2^(b−1)−1) cover them with q = m/(max−1)
        let step = if m > 0.0 {
            (m / (Quantizer::max_code(b) - 1) as f64) as f32
        } else {
            1.0
        };
        Quantizer { bits: b, step }
    });

    let Resampled {
        mut base,
        keys,
        samples,
        ..
    } = r;
    let mut reference = samples;
    // outside base vertices take the mean of the inside samples
    let inside_mean = {
        let (s, c) = reference
            .iter()
            .filter(|x| !x.is_nan())
            .fold((0f64, 0u64), |(s, c), &x| (s + x as f64, c + 1));
        (s / c.max(1) as f64) as f32
    };
    for v in reference[..nv].iter_mut() {
        if v.is_nan() {
            *v = inside_mean;
        }
    }
    let mut rec = reference.clone();
    let mut claimed = vec![false; rec.len()];
    claimed[..nv].fill(true);
    let mut owned = vec![0u8; nodes];
    let mut coeffs = Vec::with_capacity(rec.len() - nv);
    let mut max_err = 0f64;

    // top-down, closed loop: level k−1 tets create the level-k vertices
    let pb = bar(nodes as u64, "analysis", progress);
    for k in 0..levels {
        for (id, tet) in LevelWalker::level(forest, k) {
            let mut mask = 0u8;
            for (e, &(a, b)) in EDGES.iter().enumerate() {
                let m = keys.key(tet.base, &tet.edge_midpoint(e)) as usize;
                if claimed[m] {
                    continue;
                }
                claimed[m] = true;
                mask |= 1 << e;
                let u = keys.key(tet.base, &tet.v[a]) as usize;
                let v = keys.key(tet.base, &tet.v[b]) as usize;
                if outside[m] {
                    reference[m] = predict(reference[u], reference[v]);
                }
                let p = predict(rec[u], rec[v]);
                let d = match &quantizer {
                    None => analyze(reference[m], p),
                    Some(q) => q.decode(q.encode(reference[m] - p)),
                };
                rec[m] = synthesize(d, p);
                max_err = max_err.max((rec[m] as f64 - reference[m] as f64).abs());
                coeffs.push(d);
            }
            owned[id as usize] = mask;
            if id & 0xffff == 0 {
                pb.set_position(id);
            }
        }
    }
    pb.finish_and_clear();
    drop(claimed);

    // bottom-up: subtree max |detail| and empty children
    let mut empty_children = vec![0u8; nodes];
    let mut subtree_max_abs = vec![0f32; nodes];
    for k in (0..levels).rev() {
        let (s, e) = (
            forest.level_start(k) as usize,
            forest.level_start(k + 1) as usize,
        );
        let below_start = e;
        let (this_empty, below_empty) = empty_children.split_at_mut(below_start);
        let (this_max, below_max) = subtree_max_abs.split_at_mut(below_start);
        let chunk = 4096usize;
        this_empty[s..e]
            .par_chunks_mut(chunk)
            .zip(this_max[s..e].par_chunks_mut(chunk))
            .enumerate()
            .for_each(|(ci, (ec, mc))| {
                let first = (s + ci * chunk) as u64;
                let walker = LevelWalker::new(forest, k, first..first + ec.len() as u64);
                for (j, (id, tet)) in walker.enumerate() {
                    let mut mx = 0f32;
                    for (e, &(a, b)) in EDGES.iter().enumerate() {
                        let m = keys.key(tet.base, &tet.edge_midpoint(e)) as usize;
                        let u = keys.key(tet.base, &tet.v[a]) as usize;
                        let v = keys.key(tet.base, &tet.v[b]) as usize;
                        mx = mx.max((rec[m] - predict(rec[u], rec[v])).abs());
                    }
                    let mut empty = 0u8;
                    for i in 0..8 {
                        let is_empty = if k + 1 == levels {
                            let c = tet.child(i);
                            c.v.iter().all(|w| outside[keys.key(tet.base, w) as usize])
                        } else {
                            let c = (forest.child(id, i) as usize) - below_start;
                            mx = mx.max(below_max[c]);
                            below_empty[c] == 0xff
                        };
                        if is_empty {
                            empty |= 1 << i;
                        }
                    }
                    ec[j] = empty;
                    mc[j] = mx;
                }
            });
    }
    base.empty = (0..base.tets.len())
        .map(|b| {
            if levels == 0 {
                base.tets[b].iter().all(|&v| outside[v as usize])
            } else {
                empty_children[b] == 0xff
            }
        })
        .collect();
    base.values = rec[..nv].to_vec();
    let error_bound = match &quantizer {
        Some(q) => {
            q.step as f64 / 2.0 * (1.0 + 1e-6)
                + 4.0 * f32::EPSILON as f64 * (lo.abs().max(hi.abs()) as f64 + q.step as f64)
        }
        None => 1e-6 * range.max(f32::MIN_POSITIVE as f64),
    };
    Ok(Analysis {
        base,
        owned,
        empty_children,
        subtree_max_abs,
        coeffs,
        quantizer,
        reference,
        value_range: (lo, hi),
        max_abs_error: max_err,
        error_bound,
    })
}
