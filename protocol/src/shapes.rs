//! The base meshes both sides know by name: a box in 5 tets (`box5`, the thesis' split), a box in 6
//! Kuhn tets (`box6`), and the unit cube cut into `n³` Kuhn cells (test and benchmark meshes). Store
//! manifests name the base mesh, so its generator lives here, in the one contract. Each returns plain
//! points and tets; the vertex order of every tet is part of the contract (it fixes the hierarchy's
//! child order), so these functions are pinned exactly, order included, by the tests below.

use crate::base::signed_volume;

/// Vertex positions and tets (4 vertex indices each).
pub type PointsAndTets = (Vec<[f64; 3]>, Vec<[u32; 4]>);

/// The three axis steps of a Kuhn cell's six paths from corner 000 to 111, one per permutation of
/// the axes: each tet is `[c, c + e_p0, c + e_p0 + e_p1, c + 1]`.
const KUHN_PATHS: [[usize; 3]; 6] = [
    [0, 1, 2],
    [0, 2, 1],
    [1, 0, 2],
    [1, 2, 0],
    [2, 0, 1],
    [2, 1, 0],
];

/// The 8 corners of the box `[lo, hi]`, corner `i` taking `hi` on axis `a` where bit `a` of `i` is
/// set (index `x + 2y + 4z`). Coordinates are copied from `lo` and `hi`, never computed.
pub fn box_corners(lo: [f64; 3], hi: [f64; 3]) -> Vec<[f64; 3]> {
    (0..8)
        .map(|i| std::array::from_fn(|a| if (i >> a) & 1 == 0 { lo[a] } else { hi[a] }))
        .collect()
}

/// Swaps the last two vertices of every tet with negative signed volume, so all are positive (zero
/// volume tets are left as they are); returns how many it swapped.
pub fn orient_positive(positions: &[[f64; 3]], tets: &mut [[u32; 4]]) -> usize {
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

/// The box split into 5 tets (base `box5`): four corner tets cut off at corners 000, 110, 101, 011
/// and the central tet on corners 100, 010, 001, 111 (thesis §6), all positively oriented.
/// Points are [`box_corners`].
pub fn box5(lo: [f64; 3], hi: [f64; 3]) -> PointsAndTets {
    let positions = box_corners(lo, hi);
    let mut tets = vec![
        [0, 1, 2, 4],
        [3, 2, 1, 7],
        [5, 4, 7, 1],
        [6, 7, 4, 2],
        [1, 2, 4, 7],
    ];
    orient_positive(&positions, &mut tets);
    (positions, tets)
}

/// The box split into 6 Kuhn tets around the diagonal 000 → 111 (base `box6`): the one cell of
/// [`kuhn_grid`]`(1)` on [`box_corners`], positively oriented. Refined `L` times, its vertices are
/// exactly the `(2^L + 1)^3` grid points.
pub fn box6(lo: [f64; 3], hi: [f64; 3]) -> PointsAndTets {
    let positions = box_corners(lo, hi);
    let (_, mut tets) = kuhn_grid(1, |_, _, _| true);
    orient_positive(&positions, &mut tets);
    (positions, tets)
}

/// The box `[lo, hi]` cut into `n[0] × n[1] × n[2]` equal cells of 6 Kuhn tets each, positively
/// oriented: the cells of [`kuhn_grid`] on a grid of `n` cells per axis (points x-fastest, a
/// cell's tets in the order of `kuhn_grid`'s), so that cells share faces and every refinement
/// level's vertices are the points of one grid. `n = [1, 1, 1]` is [`box6`], bit for bit.
/// Coordinates on the box's faces are copied from `lo` and `hi`; inner ones are
/// `lo + (hi − lo) · i / n`.
pub fn kuhn_boxes(lo: [f64; 3], hi: [f64; 3], n: [usize; 3]) -> PointsAndTets {
    let coord = |a: usize, i: usize| match i {
        0 => lo[a],
        i if i == n[a] => hi[a],
        i => lo[a] + (hi[a] - lo[a]) * i as f64 / n[a] as f64,
    };
    let (points, mut tets) = kuhn_cells(n, coord, |_, _, _| true);
    orient_positive(&points, &mut tets);
    (points, tets)
}

/// The unit cube `[0,1]^3` cut into `n^3` cells of 6 Kuhn tets each (around each cell's main
/// diagonal), keeping the cells where `keep(i, j, k)`: grid points in x-fastest order (all of them,
/// including those of dropped cells) and tets, cell by cell in x-fastest order; within a cell, tet
/// `[c, c + e_a, c + e_a + e_b, c + 1]` for the axis orders `ab` = xy, xz, yx, yz, zx, zy. Tets are
/// not reoriented: odd permutations are negative.
pub fn kuhn_grid(n: usize, keep: impl Fn(usize, usize, usize) -> bool) -> PointsAndTets {
    kuhn_cells([n; 3], |_, i| i as f64 / n as f64, keep)
}

/// `n[0] × n[1] × n[2]` Kuhn cells: grid points `coord(axis, index)` in x-fastest order, and the
/// tets of the cells where `keep`, in [`kuhn_grid`]'s order, not reoriented.
fn kuhn_cells(
    n: [usize; 3],
    coord: impl Fn(usize, usize) -> f64,
    keep: impl Fn(usize, usize, usize) -> bool,
) -> PointsAndTets {
    let idx = |c: [usize; 3]| (c[0] + (n[0] + 1) * (c[1] + (n[1] + 1) * c[2])) as u32;
    let mut points = Vec::with_capacity((n[0] + 1) * (n[1] + 1) * (n[2] + 1));
    for k in 0..=n[2] {
        for j in 0..=n[1] {
            for i in 0..=n[0] {
                points.push([coord(0, i), coord(1, j), coord(2, k)]);
            }
        }
    }
    let mut tets = Vec::with_capacity(6 * n[0] * n[1] * n[2]);
    for k in 0..n[2] {
        for j in 0..n[1] {
            for i in 0..n[0] {
                if !keep(i, j, k) {
                    continue;
                }
                for path in KUHN_PATHS {
                    let mut c = [i, j, k];
                    let mut t = [idx(c); 4];
                    for (s, &a) in path.iter().enumerate() {
                        c[a] += 1;
                        t[s + 1] = idx(c);
                    }
                    tets.push(t);
                }
            }
        }
    }
    (points, tets)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn volume(positions: &[[f64; 3]], tets: &[[u32; 4]]) -> f64 {
        tets.iter()
            .map(|t| {
                let p = |k: usize| positions[t[k] as usize];
                signed_volume(p(0), p(1), p(2), p(3))
            })
            .sum()
    }

    #[test]
    fn boxes_tile_the_box_positively() {
        let (lo, hi) = ([0.0, 0.0, 0.0], [30.0, 20.0, 10.0]);
        for (p, t) in [box5(lo, hi), box6(lo, hi)] {
            assert!((volume(&p, &t) - 6000.0).abs() < 1e-9);
            for tet in &t {
                let q = |k: usize| p[tet[k] as usize];
                assert!(signed_volume(q(0), q(1), q(2), q(3)) > 0.0);
            }
        }
    }

    #[test]
    fn kuhn_boxes_of_one_cell_is_box6_and_cells_tile_the_box() {
        let (lo, hi) = ([-1.0, 0.5, 2.0], [30.0, 20.0, 10.0]);
        let (p1, t1) = kuhn_boxes(lo, hi, [1, 1, 1]);
        let (p6, t6) = box6(lo, hi);
        assert_eq!(t1, t6);
        let bits = |p: &[[f64; 3]]| p.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&p1), bits(&p6));
        let (p, t) = kuhn_boxes(lo, hi, [3, 2, 1]);
        assert_eq!((p.len(), t.len()), (4 * 3 * 2, 36));
        let want = (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2]);
        assert!((volume(&p, &t) - want).abs() < 1e-9 * want);
        for tet in &t {
            let q = |k: usize| p[tet[k] as usize];
            assert!(signed_volume(q(0), q(1), q(2), q(3)) > 0.0);
        }
        // shared faces: every face of a tet is another tet's or lies on the box's boundary
        let mut faces = std::collections::HashMap::new();
        for tet in &t {
            for skip in 0..4 {
                let mut f: Vec<u32> = (0..4).filter(|&i| i != skip).map(|i| tet[i]).collect();
                f.sort();
                *faces.entry(f).or_insert(0) += 1;
            }
        }
        let on_boundary = |f: &Vec<u32>| {
            (0..3).any(|a| {
                let c = p[f[0] as usize][a];
                (c == lo[a] || c == hi[a]) && f.iter().all(|&v| p[v as usize][a] == c)
            })
        };
        for (f, n) in &faces {
            assert!(*n == 2 || (*n == 1 && on_boundary(f)), "{f:?} in {n} tets");
        }
    }

    /// The exact meshes, order included: store manifests and the hierarchy's ids depend on them.
    #[test]
    fn boxes_are_pinned() {
        let (p, t) = box5([0.0; 3], [1.0; 3]);
        assert_eq!(p[6], [0.0, 1.0, 1.0]);
        assert_eq!(
            t,
            [
                [0, 1, 2, 4],
                [3, 2, 1, 7],
                [5, 4, 7, 1],
                [6, 7, 4, 2],
                [1, 2, 4, 7]
            ]
        );
        let (q, t) = box6([0.0; 3], [1.0; 3]);
        assert_eq!(p, q);
        assert_eq!(
            t,
            [
                [0, 1, 3, 7],
                [0, 1, 7, 5],
                [0, 2, 7, 3],
                [0, 2, 6, 7],
                [0, 4, 5, 7],
                [0, 4, 7, 6]
            ]
        );
        assert_eq!(kuhn_grid(1, |_, _, _| true).0, p);
    }

    #[test]
    fn kuhn_grid_tiles_the_kept_cells() {
        let n = 3;
        let (p, t) = kuhn_grid(n, |i, _, k| i != k);
        assert_eq!(p.len(), 64);
        assert_eq!(t.len(), 6 * 18);
        let v: f64 = t
            .iter()
            .map(|t| {
                let q = |k: usize| p[t[k] as usize];
                signed_volume(q(0), q(1), q(2), q(3)).abs()
            })
            .sum();
        assert!((v - 18.0 / 27.0).abs() < 1e-12);
    }
}
