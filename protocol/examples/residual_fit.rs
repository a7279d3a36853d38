//! How much of the `p2` predictor's residual a local correction could remove: the benchmark behind
//! "a purely local correction does not close it" in docs/benchmarks.md.
//!
//! ```text
//! cargo run --release -p tetwave-protocol --example residual_fit -- GRID.raw LEVELS
//! ```
//!
//! `GRID.raw` as for `predictor_bits` (`(2^LEVELS + 1)³` little-endian f32, x fastest). For each
//! new vertex from level 3 on, the target is its value minus the parent's quadratic interpolant
//! (`p2`'s residual, open loop on the samples); the features are the parent's six edge midpoints'
//! residuals against the grandparent's quadratic interpolant, values every client refining the
//! tet holds. A least-squares fit per configuration (child index, parent's child index, edge) on
//! the data itself, so the reduction it prints is an upper bound for any fixed local correction.

mod common;

use common::{read_grid, unit_box6};
use std::collections::HashMap;
use tetwave_protocol::hierarchy::{LatticeTet, LevelWalker, EDGES};

/// Solves `a x = b` by Gaussian elimination with partial pivoting; `None` when singular.
fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    for c in 0..N {
        let p = (c..N).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if a[p][c].abs() < 1e-12 {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        let (pivot_row, pivot_b) = (a[c], b[c]);
        for (_, (row, rb)) in a
            .iter_mut()
            .zip(b.iter_mut())
            .enumerate()
            .filter(|(r, _)| *r != c)
        {
            let f = row[c] / pivot_row[c];
            for (x, y) in row.iter_mut().zip(pivot_row.iter()) {
                *x -= f * y;
            }
            *rb -= f * pivot_b;
        }
    }
    Some(std::array::from_fn(|i| b[i] / a[i][i]))
}

/// Barycentric coordinates of lattice point `w` in tet `t`.
fn bary(t: &LatticeTet, w: &[u32; 4]) -> [f64; 4] {
    let a: [[f64; 4]; 4] = std::array::from_fn(|r| std::array::from_fn(|c| t.v[c][r] as f64));
    solve(a, w.map(|x| x as f64)).expect("a tet's corners are independent")
}

/// The quadratic interpolant of a tet's 10 split-point values at barycentric `l`.
fn p2(l: [f64; 4], v: &[f64; 10]) -> f64 {
    let corners: f64 = (0..4).map(|i| l[i] * (2.0 * l[i] - 1.0) * v[i]).sum();
    let edges: f64 = EDGES
        .iter()
        .zip(&v[4..])
        .map(|(&(i, j), x)| 4.0 * l[i] * l[j] * x)
        .sum();
    corners + edges
}

/// Normal equations of one configuration's least-squares fit.
#[derive(Default)]
struct Fit {
    ata: [[f64; 6]; 6],
    atb: [f64; 6],
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (path, levels) = match (args.first(), args.get(1).and_then(|l| l.parse::<u8>().ok())) {
        (Some(p), Some(l)) if (3..=8).contains(&l) => (p, l),
        _ => {
            eprintln!("usage: residual_fit GRID.raw LEVELS (3..=8)");
            std::process::exit(2);
        }
    };
    let n = (1usize << levels) + 1;
    let f: Vec<f64> = read_grid("residual_fit", path, levels)
        .into_iter()
        .map(f64::from)
        .collect();
    let base = unit_box6(levels);
    let forest = base.forest();
    let m = (n - 1) as f64;
    let val = |t: &LatticeTet, w: &[u32; 4]| {
        let p = base.position(t.base, w).map(|x| (x * m).round() as usize);
        f[(p[2] * n + p[1]) * n + p[0]]
    };
    println!("{path}: {n}³");
    for k in 2..levels {
        let mut fits: HashMap<(usize, usize, usize), Fit> = HashMap::new();
        let mut samples = Vec::new();
        for (id, t) in LevelWalker::level(forest, k) {
            let pid = forest.parent(id).expect("level ≥ 2");
            let gid = forest.parent(pid).expect("level ≥ 2");
            let (p, g) = (
                LatticeTet::from_id(&forest, pid),
                LatticeTet::from_id(&forest, gid),
            );
            let (pw, gw) = (p.split_points(), g.split_points());
            let pv: [f64; 10] = std::array::from_fn(|i| val(&p, &pw[i]));
            let gv: [f64; 10] = std::array::from_fn(|i| val(&g, &gw[i]));
            let r: [f64; 6] = std::array::from_fn(|e| pv[4 + e] - p2(bary(&g, &pw[4 + e]), &gv));
            for e in 0..6 {
                let mw = t.edge_midpoint(e);
                let target = val(&t, &mw) - p2(bary(&p, &mw), &pv);
                let key = (
                    forest.child_index(id).expect("level ≥ 2"),
                    forest.child_index(pid).expect("level ≥ 2"),
                    e,
                );
                let fit = fits.entry(key).or_default();
                for (row, ri) in fit.ata.iter_mut().zip(r) {
                    for (x, rj) in row.iter_mut().zip(r) {
                        *x += ri * rj;
                    }
                }
                for (x, ri) in fit.atb.iter_mut().zip(r) {
                    *x += ri * target;
                }
                samples.push((key, r, target));
            }
        }
        let weights: HashMap<_, _> = fits
            .iter()
            .map(|(key, fit)| {
                let mut ata = fit.ata;
                for (i, row) in ata.iter_mut().enumerate() {
                    row[i] += 1e-12 * (1.0 + row[i]);
                }
                (*key, solve(ata, fit.atb).unwrap_or([0.0; 6]))
            })
            .collect();
        let (mut before, mut after) = (0.0, 0.0);
        for (key, r, t) in &samples {
            let fitted: f64 = weights[key].iter().zip(r).map(|(w, x)| w * x).sum();
            before += t * t;
            after += (t - fitted) * (t - fitted);
        }
        let ratio = (after / before).sqrt();
        println!(
            "level {}: {} residuals, {} configurations, rms × {ratio:.3} (about {:.2} bits a sample)",
            k + 1,
            samples.len(),
            fits.len(),
            -ratio.log2()
        );
    }
}
