//! How many bits each predictor leaves to code, on one (2^L+1)³ grid of f32 samples: the benchmark
//! behind "where the gap to SZ3 is" in docs/benchmarks.md.
//!
//! ```text
//! cargo run --release -p tetwave-protocol --example predictor_bits -- GRID.raw LEVELS [BOUND]
//! ```
//!
//! `GRID.raw`: little-endian f32, x fastest, `(2^LEVELS + 1)³` samples (what `scripts/bench-rd`
//! writes); `BOUND`: the error bound as a fraction of the value range (default 1e-3). On the box6
//! hierarchy whose vertices are the grid points, every predictor runs closed loop with the uniform
//! quantizer of step `2 × BOUND × range` (so every vertex stays within the bound), and the estimate
//! is the zeroth-order entropy of each level's codes (what an ideal static coder per level would
//! spend; tetwave's adaptive block coder lands within a few percent of it):
//!
//! - `p2`: tetwave's predictor (linear on base edges, then the quadratic interpolant of the refined
//!   tet's parent), which reads only vertices every tet around the new vertex holds;
//! - `p4-grandparent`: the quartic interpolant of the grandparent (its 35 level-`k` points), which
//!   needs every grandchild of it refined, so a client refining selectively cannot always use it;
//! - `cubic-edge-line`: the 4-point cubic along the new vertex's own edge `(a, b)` through the
//!   coarser points `2a − b` and `2b − a` (one-sided, then linear, at the border): reads the
//!   coarser level's 1-ring of the edge's ends, outside the tets a selective client holds;
//! - `cubic-tensor`: the tensor-product cubic over the 4, 16 or 64 coarser points around a vertex
//!   odd along 1, 2 or 3 axes: reads the coarser level only, but its 2-ring;
//! - `p2|tensor`: the better of `p2` and `cubic-tensor` on each level (a choice a manifest could
//!   record);
//! - `cubic-axes`: SZ3's interpolation: level by level, cubic splines along x, then y, then z
//!   through the points already reconstructed, including this level's (non-local: a vertex reads
//!   neighbours 3 steps away along an axis, in tets a selective client may never hold).

mod common;

use common::{read_grid, unit_box6};
use std::collections::HashMap;
use tetwave_protocol::hierarchy::{LatticeTet, LevelWalker, BEY_CHILDREN, EDGES};
use tetwave_protocol::wavelet::{predict, predict_split};

struct Grid {
    n: usize,
    f: Vec<f32>,
    step: f32,
}

impl Grid {
    fn at(&self, i: [i64; 3]) -> usize {
        (i[2] as usize * self.n + i[1] as usize) * self.n + i[0] as usize
    }
    fn quantize(&self, i: usize, prediction: f32) -> (i64, f32) {
        let q = ((self.f[i] - prediction) / self.step).round() as i64;
        (q, prediction + q as f32 * self.step)
    }
}

/// Bits of a static per-level code of `codes`: their zeroth-order entropy.
fn entropy_bits(codes: &HashMap<i64, usize>) -> f64 {
    let total: usize = codes.values().sum();
    codes
        .values()
        .map(|&c| -(c as f64) * (c as f64 / total as f64).log2())
        .sum()
}

fn corners(g: &Grid, rec: &mut [f32]) {
    let m = g.n as i64 - 1;
    for c in 0..8 {
        let i = [c & 1, c >> 1 & 1, c >> 2 & 1].map(|x| x * m);
        rec[g.at(i)] = g.f[g.at(i)];
    }
}

/// A grandparent's 35 P4 points (grid index, barycentric weights × 4) and its P8 points (grid
/// index → barycentric weights × 8).
struct Grandparent {
    id: u64,
    p4: Vec<(usize, [u32; 4])>,
    p8: HashMap<usize, [u32; 4]>,
}

/// The tet hierarchy's predictors: `quartic` uses the grandparent's P4 interpolant from level 2 on.
#[derive(Clone, Copy, PartialEq)]
enum Stencil {
    P2,
    Quartic,
    /// Cubic along the edge's own line through the coarse points `2a − b` and `2b − a`.
    EdgeLine,
}

fn hierarchy_bits(g: &Grid, levels: u8, stencil: Stencil) -> Vec<f64> {
    let base = unit_box6(levels);
    let forest = base.forest();
    let m = (g.n - 1) as f64;
    let mut rec = vec![f32::NAN; g.f.len()];
    corners(g, &mut rec);
    let mut out = Vec::new();
    for k in 0..levels {
        let mut codes = HashMap::new();
        let mut done = vec![false; g.f.len()];
        let mut grand: Option<Grandparent> = None;
        for (id, t) in LevelWalker::level(forest, k) {
            let index =
                |w: &[u32; 4]| g.at(base.position(t.base, w).map(|x| (x * m).round() as i64));
            for (e, &(a, b)) in EDGES.iter().enumerate() {
                let mi = index(&t.edge_midpoint(e));
                if std::mem::replace(&mut done[mi], true) {
                    continue;
                }
                let prediction = if stencil == Stencil::EdgeLine {
                    let g3 =
                        |w: &[u32; 4]| base.position(t.base, w).map(|x| (x * m).round() as i64);
                    let (pa, pb) = (g3(&t.v[a]), g3(&t.v[b]));
                    let outer = |p: [i64; 3], q: [i64; 3]| {
                        let r: [i64; 3] = std::array::from_fn(|j| 2 * p[j] - q[j]);
                        r.iter()
                            .all(|&x| (0..=m as i64).contains(&x))
                            .then(|| rec[g.at(r)])
                    };
                    cubic(outer(pa, pb), rec[g.at(pa)], rec[g.at(pb)], outer(pb, pa))
                } else if k == 0 {
                    predict(rec[index(&t.v[a])], rec[index(&t.v[b])])
                } else if stencil == Stencil::P2 || k == 1 {
                    let parent = LatticeTet::from_id(&forest, forest.parent(id).unwrap());
                    let c = BEY_CHILDREN[forest.child_index(id).unwrap()];
                    let v10 = parent.split_points().map(|w| rec[index(&w)]);
                    predict_split(&v10, c[a], c[b])
                } else {
                    let gid = forest.parent(forest.parent(id).unwrap()).unwrap();
                    if grand.as_ref().map(|x| x.id) != Some(gid) {
                        let gt = LatticeTet::from_id(&forest, gid);
                        let (mut p4, mut p8) = (Vec::new(), HashMap::new());
                        for a0 in 0..=8u32 {
                            for a1 in 0..=8 - a0 {
                                for a2 in 0..=8 - a0 - a1 {
                                    let al = [a0, a1, a2, 8 - a0 - a1 - a2];
                                    let w: [u32; 4] = std::array::from_fn(|j| {
                                        (0..4).map(|i| al[i] * gt.v[i][j]).sum::<u32>() / 8
                                    });
                                    p8.insert(index(&w), al);
                                    if al.iter().all(|x| x % 2 == 0) {
                                        p4.push((index(&w), al.map(|x| x / 2)));
                                    }
                                }
                            }
                        }
                        grand = Some(Grandparent { id: gid, p4, p8 });
                    }
                    let Grandparent { p4, p8, .. } = grand.as_ref().unwrap();
                    let lambda = p8[&mi].map(|x| x as f64 / 8.0);
                    // Lagrange basis of the degree-4 simplex lattice at `lambda`
                    let s: f64 = p4
                        .iter()
                        .map(|(i, beta)| {
                            let w: f64 = (0..4)
                                .map(|d| {
                                    (0..beta[d])
                                        .map(|j| (4.0 * lambda[d] - j as f64) / (j as f64 + 1.0))
                                        .product::<f64>()
                                })
                                .product();
                            w * rec[*i] as f64
                        })
                        .sum();
                    s as f32
                };
                let (q, r) = g.quantize(mi, prediction);
                rec[mi] = r;
                *codes.entry(q).or_default() += 1;
            }
        }
        out.push(entropy_bits(&codes));
    }
    out
}

/// The 4-point cubic midpoint rule (one-sided at a border, linear with both outer points missing).
fn cubic(a: Option<f32>, b: f32, c: f32, d: Option<f32>) -> f32 {
    match (a, d) {
        (Some(a), Some(d)) => (-a + 9.0 * b + 9.0 * c - d) / 16.0,
        (None, Some(d)) => (3.0 * b + 6.0 * c - d) / 8.0,
        (Some(a), None) => (-a + 6.0 * b + 3.0 * c) / 8.0,
        (None, None) => predict(b, c),
    }
}

/// Runs `level` on each level of the grid, coarse to fine, with the reconstruction so far (the
/// corners first), the level's step `s` (grid points) and its code histogram; the bits of each.
fn coarse_to_fine(
    g: &Grid,
    mut level: impl FnMut(&mut [f32], i64, &mut HashMap<i64, usize>),
) -> Vec<f64> {
    let mut rec = vec![f32::NAN; g.f.len()];
    corners(g, &mut rec);
    let mut out = Vec::new();
    let mut s = (g.n as i64 - 1) / 2;
    while s >= 1 {
        let mut codes = HashMap::new();
        level(&mut rec, s, &mut codes);
        out.push(entropy_bits(&codes));
        s /= 2;
    }
    out
}

/// Tensor-product cubic from the coarser level only: a point odd along the axes `S` reads the
/// 4^|S| coarse points at offsets ±1, ±3 (in steps of the level) along those axes.
fn tensor_bits(g: &Grid) -> Vec<f64> {
    let m = g.n as i64 - 1;
    coarse_to_fine(g, |rec, s, codes| {
        let mut preds = Vec::new();
        for z in (0..=m).step_by(s as usize) {
            for y in (0..=m).step_by(s as usize) {
                for x in (0..=m).step_by(s as usize) {
                    let p = [x, y, z];
                    if p.iter().all(|c| c % (2 * s) == 0) {
                        continue;
                    }
                    // weights per axis: offsets and weights
                    let axis = |d: usize| -> Vec<(i64, f32)> {
                        if p[d] % (2 * s) == 0 {
                            return vec![(0, 1.0)];
                        }
                        let ok = |o: i64| (0..=m).contains(&(p[d] + o * s));
                        match (ok(-3), ok(3)) {
                            (true, true) => vec![
                                (-3, -1.0 / 16.0),
                                (-1, 9.0 / 16.0),
                                (1, 9.0 / 16.0),
                                (3, -1.0 / 16.0),
                            ],
                            (false, true) => vec![(-1, 3.0 / 8.0), (1, 6.0 / 8.0), (3, -1.0 / 8.0)],
                            (true, false) => {
                                vec![(-3, -1.0 / 8.0), (-1, 6.0 / 8.0), (1, 3.0 / 8.0)]
                            }
                            (false, false) => vec![(-1, 0.5), (1, 0.5)],
                        }
                    };
                    let (wx, wy, wz) = (axis(0), axis(1), axis(2));
                    let mut pred = 0.0f32;
                    for &(oz, az) in &wz {
                        for &(oy, ay) in &wy {
                            for &(ox, ax) in &wx {
                                pred +=
                                    az * ay * ax * rec[g.at([x + ox * s, y + oy * s, z + oz * s])];
                            }
                        }
                    }
                    preds.push((g.at(p), pred));
                }
            }
        }
        for (i, pred) in preds {
            let (q, r) = g.quantize(i, pred);
            rec[i] = r;
            *codes.entry(q).or_default() += 1;
        }
    })
}

/// SZ3's interpolation predictor: per level, cubic along x, then y, then z.
fn axes_bits(g: &Grid) -> Vec<f64> {
    let m = g.n as i64 - 1;
    coarse_to_fine(g, |rec, s, codes| {
        for dim in 0..3 {
            // points odd along `dim` (in steps of s); earlier axes on the fine grid, later ones coarse
            let stride = |d: usize| if d < dim { s } else { 2 * s };
            let range = |d: usize| {
                if d == dim {
                    (s..=m).step_by(2 * s as usize)
                } else {
                    (0..=m).step_by(stride(d) as usize)
                }
            };
            for z in range(2) {
                for y in range(1) {
                    for x in range(0) {
                        let p = [x, y, z];
                        let get = |o: i64| {
                            let mut r = p;
                            r[dim] += o * s;
                            (0..=m).contains(&r[dim]).then(|| rec[g.at(r)])
                        };
                        let prediction = match (get(-3), get(-1), get(1), get(3)) {
                            (Some(a), Some(b), Some(c), Some(d)) => {
                                (-a + 9.0 * b + 9.0 * c - d) / 16.0
                            }
                            (None, Some(b), Some(c), Some(d)) => (3.0 * b + 6.0 * c - d) / 8.0,
                            (Some(a), Some(b), Some(c), None) => (-a + 6.0 * b + 3.0 * c) / 8.0,
                            (_, Some(b), Some(c), _) => predict(b, c),
                            _ => unreachable!("both neighbours of an odd point are on the grid"),
                        };
                        let i = g.at(p);
                        let (q, r) = g.quantize(i, prediction);
                        rec[i] = r;
                        *codes.entry(q).or_default() += 1;
                    }
                }
            }
        }
    })
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: predictor_bits GRID.raw LEVELS [BOUND (fraction of the range, 1e-3)]";
    let (path, levels) = match (args.first(), args.get(1).and_then(|l| l.parse::<u8>().ok())) {
        (Some(p), Some(l)) if (1..=8).contains(&l) => (p, l),
        _ => {
            eprintln!("{usage}");
            std::process::exit(2);
        }
    };
    let bound: f32 = args
        .get(2)
        .map_or(Some(1e-3), |b| b.parse().ok())
        .unwrap_or_else(|| {
            eprintln!("{usage}");
            std::process::exit(2)
        });
    let n = (1usize << levels) + 1;
    let f = read_grid("predictor_bits", path, levels);
    let (lo, hi) = f
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    let g = Grid {
        n,
        f,
        step: 2.0 * bound * (hi - lo),
    };
    println!("{path}: {n}³, bound {bound} × range {}", hi - lo);
    let (p2, tensor) = (hierarchy_bits(&g, levels, Stencil::P2), tensor_bits(&g));
    let best: Vec<f64> = p2.iter().zip(&tensor).map(|(a, b)| a.min(*b)).collect();
    for (name, bits) in [
        ("p2", p2),
        (
            "p4-grandparent",
            hierarchy_bits(&g, levels, Stencil::Quartic),
        ),
        (
            "cubic-edge-line",
            hierarchy_bits(&g, levels, Stencil::EdgeLine),
        ),
        ("cubic-tensor", tensor),
        ("p2|tensor", best),
        ("cubic-axes", axes_bits(&g)),
    ] {
        let per_level: Vec<String> = bits.iter().map(|b| format!("{:.0}", b / 8.0)).collect();
        println!(
            "{name:>15}: {:>9.0} bytes (per level: {})",
            bits.iter().sum::<f64>() / 8.0,
            per_level.join(", ")
        );
    }
}
