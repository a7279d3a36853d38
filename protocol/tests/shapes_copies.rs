//! TEMPORARY: pins the unified generators in `shapes` and `fields` to each copy they replace
//! (verbatim copies below), before the copies are deleted.

use tetwave_protocol::base::signed_volume;
use tetwave_protocol::fields;
use tetwave_protocol::shapes::{box5, box6, box_corners, kuhn_grid, orient_positive};

/// The unit cube `[0,1]^3` cut into `n^3` cells of 6 Kuhn tets each (around each cell's main
/// diagonal), keeping the cells where `keep(i, j, k)`: grid points in x-fastest order and tets. Tets
/// are not all positively oriented (odd permutations are negative). A test and benchmark mesh shared
/// by the server and the client.
fn old_kuhn_grid(
    n: usize,
    keep: impl Fn(usize, usize, usize) -> bool,
) -> (Vec<[f64; 3]>, Vec<[u32; 4]>) {
    let idx = |i: usize, j: usize, k: usize| (i + (n + 1) * (j + (n + 1) * k)) as u32;
    let mut points = Vec::with_capacity((n + 1).pow(3));
    for k in 0..=n {
        for j in 0..=n {
            for i in 0..=n {
                points.push([
                    i as f64 / n as f64,
                    j as f64 / n as f64,
                    k as f64 / n as f64,
                ]);
            }
        }
    }
    let perms = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut tets = Vec::with_capacity(6 * n * n * n);
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                if !keep(i, j, k) {
                    continue;
                }
                for p in perms {
                    let mut c = [i, j, k];
                    let mut t = [idx(c[0], c[1], c[2]), 0, 0, 0];
                    for (s, &a) in p.iter().enumerate() {
                        c[a] += 1;
                        t[s + 1] = idx(c[0], c[1], c[2]);
                    }
                    tets.push(t);
                }
            }
        }
    }
    (points, tets)
}

// ---- server/src/resample/base.rs
type PointsAndTets = (Vec<[f64; 3]>, Vec<[u32; 4]>);
fn corner(lo: [f64; 3], hi: [f64; 3], i: usize) -> [f64; 3] {
    [
        if i & 1 == 0 { lo[0] } else { hi[0] },
        if i & 2 == 0 { lo[1] } else { hi[1] },
        if i & 4 == 0 { lo[2] } else { hi[2] },
    ]
}
fn old_orient_positive(positions: &[[f64; 3]], tets: &mut [[u32; 4]]) -> usize {
    let mut flipped = 0;
    for t in tets.iter_mut() {
        let p = |k: usize| positions[t[k] as usize];
        if signed_volume(p(0), p(1), p(2), p(3)) < 0.0 {
            t.swap(2, 3);
            flipped += 1;
        }
    }
    flipped
}
fn old_box5(lo: [f64; 3], hi: [f64; 3]) -> PointsAndTets {
    let positions: Vec<[f64; 3]> = (0..8).map(|i| corner(lo, hi, i)).collect();
    let mut tets = vec![
        [0, 1, 2, 4],
        [3, 2, 1, 7],
        [5, 4, 7, 1],
        [6, 7, 4, 2],
        [1, 2, 4, 7],
    ];
    old_orient_positive(&positions, &mut tets);
    (positions, tets)
}
fn old_box6(lo: [f64; 3], hi: [f64; 3]) -> PointsAndTets {
    let positions: Vec<[f64; 3]> = (0..8).map(|i| corner(lo, hi, i)).collect();
    let axes = [1u32, 2, 4];
    let perms = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut tets: Vec<[u32; 4]> = perms
        .iter()
        .map(|p| {
            let a = axes[p[0]];
            let b = a + axes[p[1]];
            [0, a, b, 7]
        })
        .collect();
    old_orient_positive(&positions, &mut tets);
    (positions, tets)
}

// ---- render/src/render_mesh.rs RenderMesh::kuhn_cube (+ orient_positive), positions and tets
fn old_render_kuhn_cube(n: usize, size: f64) -> PointsAndTets {
    let (mut positions, mut tets) = old_kuhn_grid(n, |_, _, _| true);
    for p in &mut positions {
        *p = p.map(|c| c * size);
    }
    for t in &mut tets {
        let p = |k: usize| positions[t[k] as usize];
        if signed_volume(p(0), p(1), p(2), p(3)) < 0.0 {
            t.swap(2, 3);
        }
    }
    (positions, tets)
}

// ---- client/tests/adaptive.rs
fn a_corner(i: u32) -> [f64; 3] {
    [(i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64]
}
fn a_oriented(positions: Vec<[f64; 3]>, tets: Vec<[u32; 4]>) -> PointsAndTets {
    let tets: Vec<[u32; 4]> = tets
        .into_iter()
        .map(|t| {
            let p = t.map(|g| positions[g as usize]);
            if signed_volume(p[0], p[1], p[2], p[3]) < 0.0 {
                [t[0], t[1], t[3], t[2]]
            } else {
                t
            }
        })
        .collect();
    (positions, tets)
}
fn a_box5() -> PointsAndTets {
    a_oriented(
        (0..8).map(a_corner).collect(),
        vec![
            [0, 1, 2, 4],
            [3, 2, 1, 7],
            [5, 4, 7, 1],
            [6, 7, 4, 2],
            [1, 2, 4, 7],
        ],
    )
}
fn a_kuhn6() -> PointsAndTets {
    a_oriented(
        (0..8).map(a_corner).collect(),
        vec![
            [0, 1, 3, 7],
            [7, 0, 1, 5],
            [0, 4, 5, 7],
            [6, 7, 0, 4],
            [0, 2, 6, 7],
            [3, 7, 2, 0],
        ],
    )
}

// ---- client/tests/common/mod.rs
fn c_box5() -> PointsAndTets {
    let positions: Vec<[f64; 3]> = (0..8u32)
        .map(|i| {
            [
                30.0 * (i & 1) as f64,
                30.0 * ((i >> 1) & 1) as f64,
                30.0 * ((i >> 2) & 1) as f64,
            ]
        })
        .collect();
    let tets: Vec<[u32; 4]> = [
        [0, 1, 2, 4],
        [3, 2, 1, 7],
        [5, 4, 7, 1],
        [6, 7, 4, 2],
        [1, 2, 4, 7],
    ]
    .into_iter()
    .map(|t: [u32; 4]| {
        let p = t.map(|g| positions[g as usize]);
        if signed_volume(p[0], p[1], p[2], p[3]) < 0.0 {
            [t[0], t[1], t[3], t[2]]
        } else {
            t
        }
    })
    .collect();
    (positions, tets)
}

// ---- server/tests/cli.rs
fn cli_cube_points() -> Vec<[f64; 3]> {
    (0..8)
        .map(|i| [(i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64])
        .collect()
}
fn cli_cube_tets() -> Vec<(u8, Vec<u32>)> {
    vec![
        (10, vec![0, 1, 3, 7]),
        (10, vec![0, 1, 7, 5]),
        (10, vec![0, 2, 7, 3]),
        (10, vec![0, 2, 6, 7]),
        (10, vec![0, 4, 5, 7]),
        (10, vec![0, 4, 7, 6]),
    ]
}

// ---- server/tests/fixture_mesh/mod.rs
const XS: [f64; 2] = [0.1, 0.8];
const YS: [f64; 2] = [0.2, 0.9];
const ZS: [f64; 2] = [0.3, 1.0];
const TETS: [[u32; 4]; 7] = [
    [0, 1, 3, 7],
    [0, 1, 5, 7],
    [0, 2, 3, 7],
    [0, 2, 6, 7],
    [0, 4, 5, 7],
    [0, 4, 6, 7],
    [4, 5, 7, 8],
];
fn f_cube_points() -> Vec<[f64; 3]> {
    let mut p = Vec::new();
    for z in ZS {
        for y in YS {
            for x in XS {
                p.push([x, y, z]);
            }
        }
    }
    p.push([0.45, 0.55, 1.4]);
    p
}

// ---- server/tests/mesh_io.rs vtu_multi_block_zlib_grid
fn m_grid() -> PointsAndTets {
    let n = 9u32;
    let coord = |i: u32| f64::from(i) * 0.125;
    let gid = |i, j, k| i + n * j + n * n * k;
    let mut pts = Vec::new();
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                pts.push([coord(i), coord(j), coord(k)]);
            }
        }
    }
    let mut tets = Vec::new();
    for k in 0..n - 1 {
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let mut c = Vec::new();
                for d in 0..2 {
                    for b in 0..2 {
                        for a in 0..2 {
                            c.push(gid(i + a, j + b, k + d));
                        }
                    }
                }
                for t in &TETS[..6] {
                    tets.push(t.map(|v| c[v as usize]));
                }
            }
        }
    }
    (pts, tets)
}

// ---- fields: server Synthetic::Harmonic.eval, client/tests/render_gpu.rs, client/tests/common
fn server_harmonic(p: [f64; 3]) -> f64 {
    use std::f64::consts::PI;
    let u = [
        (p[0] - 15.0) / 15.0,
        (p[1] - 15.0) / 15.0,
        (p[2] - 15.0) / 15.0,
    ];
    let r2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
    let r = r2.sqrt();
    (-2.0 * r2).exp() * (4.0 * PI * r).cos()
        + 0.25 * (2.0 * PI * u[0]).sin() * (2.0 * PI * u[1]).sin() * (2.0 * PI * u[2]).sin()
}
fn render_gpu_harmonic(p: [f64; 3]) -> f64 {
    let u = p.map(|x| (x - 0.5) * 2.0);
    let r2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
    (-2.0 * r2).exp() * (4.0 * std::f64::consts::PI * r2.sqrt()).cos()
}
fn client_common_harmonic(p: [f64; 3]) -> f32 {
    let s = std::f64::consts::PI / 15.0;
    ((s * p[0]).sin() * (s * p[1]).cos() * (0.5 * s * p[2]).sin()) as f32
}

// ---------------------------------------------------------------------------------------------

/// The `kuhn6` mesh of client/tests/adaptive.rs, from `box6` (as it will be written there).
fn new_kuhn6() -> PointsAndTets {
    let (p, t) = box6([0.0; 3], [1.0; 3]);
    let mixed = [
        (0, [0, 1, 2, 3]),
        (1, [2, 0, 1, 3]),
        (4, [0, 1, 2, 3]),
        (5, [3, 2, 1, 0]),
        (3, [0, 1, 2, 3]),
        (2, [3, 2, 1, 0]),
    ];
    (p, mixed.iter().map(|&(i, s)| s.map(|k| t[i][k])).collect())
}

#[test]
fn generators_equal_every_copy() {
    for n in [1, 2, 3, 5, 8] {
        let keep = |i: usize, j: usize, k: usize| (i + 2 * j + k) % 3 != 1;
        assert_eq!(kuhn_grid(n, keep), old_kuhn_grid(n, keep));
        assert_eq!(
            kuhn_grid(n, |_, _, _| true),
            old_kuhn_grid(n, |_, _, _| true)
        );
        for size in [1.0, 2.5, 30.0] {
            let (mut p, mut t) = kuhn_grid(n, |_, _, _| true);
            for x in &mut p {
                *x = x.map(|c| c * size);
            }
            orient_positive(&p, &mut t);
            assert_eq!((p, t), old_render_kuhn_cube(n, size));
        }
    }
    for (lo, hi) in [
        ([0.0; 3], [1.0; 3]),
        ([0.0; 3], [30.0; 3]),
        ([-1.5, 0.1, 2.0], [0.3, 7.0, 2.5]),
    ] {
        assert_eq!(box5(lo, hi), old_box5(lo, hi));
        assert_eq!(box6(lo, hi), old_box6(lo, hi));
        let mut a = old_box6(lo, hi).1;
        let mut b = a.clone();
        a.iter_mut().for_each(|t| t.swap(0, 1));
        b.iter_mut().for_each(|t| t.swap(0, 1));
        assert_eq!(
            orient_positive(&box_corners(lo, hi), &mut a),
            old_orient_positive(&box_corners(lo, hi), &mut b)
        );
        assert_eq!(a, b);
    }
    // protocol/src/vertex.rs tests: box5() = (8, raw tets)
    let (p, t) = box5([0.0; 3], [1.0; 3]);
    assert_eq!(
        (p.len() as u32, t.clone()),
        (
            8,
            vec![
                [0, 1, 2, 4],
                [3, 2, 1, 7],
                [5, 4, 7, 1],
                [6, 7, 4, 2],
                [1, 2, 4, 7]
            ]
        )
    );
    assert_eq!(box5([0.0; 3], [1.0; 3]), a_box5());
    assert_eq!(new_kuhn6(), a_kuhn6());
    assert_eq!(box5([0.0; 3], [30.0; 3]), c_box5());
    let (p, t) = box6([0.0; 3], [1.0; 3]);
    assert_eq!(p, cli_cube_points());
    assert_eq!(
        t.iter().map(|t| (10u8, t.to_vec())).collect::<Vec<_>>(),
        cli_cube_tets()
    );
    // fixture mesh: box corners + apex; kuhn_grid(1) tets + apex tet
    let mut fp = box_corners([0.1, 0.2, 0.3], [0.8, 0.9, 1.0]);
    fp.push([0.45, 0.55, 1.4]);
    assert_eq!(fp, f_cube_points());
    let mut ft = kuhn_grid(1, |_, _, _| true).1;
    ft.push([4, 5, 7, 8]);
    assert_eq!(ft, TETS.to_vec());
    assert_eq!(kuhn_grid(8, |_, _, _| true), m_grid());
}

#[test]
fn harmonic_copies() {
    let mut d_gpu = 0f64;
    let mut d_client = 0f64;
    for i in 0..=20 {
        for j in 0..=20 {
            for k in 0..=20 {
                let p = [i as f64 * 1.5, j as f64 * 1.5, k as f64 * 1.5];
                assert_eq!(fields::harmonic(p).to_bits(), server_harmonic(p).to_bits());
                let q = p.map(|x| x / 30.0);
                d_gpu = d_gpu.max((fields::harmonic_unit(q) - render_gpu_harmonic(q)).abs());
                d_client = d_client
                    .max((fields::harmonic(p) as f32 - client_common_harmonic(p)).abs() as f64);
                assert_eq!(fields::linear(q), q[0] + 2.0 * q[1] + 3.0 * q[2]);
            }
        }
    }
    eprintln!("max |harmonic_unit - render_gpu copy| = {d_gpu}, max |harmonic - client common copy| = {d_client}");
}
