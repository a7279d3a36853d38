//! Bey's red refinement as barycentric arithmetic: per child, the map from parent to child
//! coordinates (in closed form for point location) and its orientation, and the small 4×4 linear
//! algebra that derives them.

use std::sync::OnceLock;
use tetwave_protocol::hierarchy::{BEY_CHILDREN, EDGES};

/// Per Bey child: the matrix whose column `j` holds the parent barycentrics of child vertex `j`.
fn child_matrix(c: &[usize; 4]) -> [[f64; 4]; 4] {
    let mut m = [[0f64; 4]; 4];
    for (j, &p) in c.iter().enumerate() {
        if p < 4 {
            m[p][j] = 1.0;
        } else {
            let (a, b) = EDGES[p - 4];
            m[a][j] = 0.5;
            m[b][j] = 0.5;
        }
    }
    m
}

/// Per Bey child: whether it is mirrored w.r.t. its parent.
pub(super) fn child_flips() -> &'static [bool; 8] {
    static CELL: OnceLock<[bool; 8]> = OnceLock::new();
    CELL.get_or_init(|| std::array::from_fn(|i| det4(&child_matrix(&BEY_CHILDREN[i])) < 0.0))
}

/// Per Bey child: the integer matrix taking barycentric coordinates w.r.t. the parent to those
/// w.r.t. the child (both scaled to the same sum); [`child_weights`] is its closed form.
#[cfg(test)]
fn to_child_maps() -> [[[i64; 4]; 4]; 8] {
    std::array::from_fn(|i| {
        let inv = invert4(&child_matrix(&BEY_CHILDREN[i]));
        inv.map(|row| {
            row.map(|x| {
                assert!((x - x.round()).abs() < 1e-9, "Bey child map not integral");
                x.round() as i64
            })
        })
    })
}

/// Barycentric weights of a point w.r.t. each Bey child, from its nonnegative weights `lam`
/// w.r.t. the parent (`to_child_maps` applied, in closed form: every row is one of
/// `2λ_j`, `a_j = 2λ_j − Σλ`, `b = λ0 + λ1 − λ2 − λ3`, `c = λ0 − λ1 − λ2 + λ3` or a negation),
/// and the mask of the children that hold the point (all weights ≥ 0). Point location's inner
/// loop: 6 sums instead of up to 128 products.
#[inline]
pub(super) fn child_weights(lam: [i64; 4]) -> ([[i64; 4]; 8], u8) {
    let [l0, l1, l2, l3] = lam;
    let s = l0 + l1 + l2 + l3;
    let (d0, d1, d2, d3) = (2 * l0, 2 * l1, 2 * l2, 2 * l3);
    let (a0, a1, a2, a3) = (d0 - s, d1 - s, d2 - s, d3 - s);
    let b = l0 + l1 - l2 - l3;
    let c = l0 - l1 - l2 + l3;
    let mu = [
        [a0, d1, d2, d3],
        [d0, a1, d2, d3],
        [d0, d1, a2, d3],
        [d0, d1, d2, a3],
        [b, d2, c, -a0],
        [b, -a1, -c, d3],
        [-a3, c, d1, -b],
        [d0, -c, -a2, -b],
    ];
    // with `lam ≥ 0` every `2λ_j` is too, so only the other weights decide
    debug_assert!(lam.iter().all(|&l| l >= 0), "{lam:?}");
    let holds = (a0 >= 0) as u8
        | ((a1 >= 0) as u8) << 1
        | ((a2 >= 0) as u8) << 2
        | ((a3 >= 0) as u8) << 3
        | ((b >= 0 && c >= 0 && a0 <= 0) as u8) << 4
        | ((b >= 0 && a1 <= 0 && c <= 0) as u8) << 5
        | ((a3 <= 0 && c >= 0 && b <= 0) as u8) << 6
        | ((c <= 0 && a2 <= 0 && b <= 0) as u8) << 7;
    (mu, holds)
}

#[allow(clippy::needless_range_loop)] // small dense linear algebra reads best indexed
fn det4(m: &[[f64; 4]; 4]) -> f64 {
    let mut a = *m;
    let mut det = 1.0;
    for c in 0..4 {
        let p = (c..4)
            .max_by(|&x, &y| a[x][c].abs().total_cmp(&a[y][c].abs()))
            .unwrap();
        if a[p][c] == 0.0 {
            return 0.0;
        }
        if p != c {
            a.swap(p, c);
            det = -det;
        }
        det *= a[c][c];
        for r in c + 1..4 {
            let f = a[r][c] / a[c][c];
            for k in c..4 {
                a[r][k] -= f * a[c][k];
            }
        }
    }
    det
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
fn invert4(m: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    let mut a = *m;
    let mut inv = [[0f64; 4]; 4];
    for (i, row) in inv.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for c in 0..4 {
        let p = (c..4)
            .max_by(|&x, &y| a[x][c].abs().total_cmp(&a[y][c].abs()))
            .unwrap();
        a.swap(p, c);
        inv.swap(p, c);
        let d = a[c][c];
        for k in 0..4 {
            a[c][k] /= d;
            inv[c][k] /= d;
        }
        for r in 0..4 {
            if r != c {
                let f = a[r][c];
                for k in 0..4 {
                    a[r][k] -= f * a[c][k];
                    inv[r][k] -= f * inv[c][k];
                }
            }
        }
    }
    inv
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_protocol::hierarchy::Lattice;
    use tetwave_protocol::order::splitmix;
    use tetwave_protocol::LatticeTet;

    #[test]
    fn child_maps_invert_bey() {
        let to_child = to_child_maps();
        let flips = child_flips();
        let lat = Lattice { levels: 3 };
        let t = LatticeTet::base_tet(lat, 0);
        for (i, c) in t.children().iter().enumerate() {
            // the child's own vertices map to its unit corners (scaled by m)
            for j in 0..4 {
                let lam = c.v[j].map(|x| x as i64);
                let a = &to_child[i];
                let mu: [i64; 4] = std::array::from_fn(|r| (0..4).map(|s| a[r][s] * lam[s]).sum());
                let mut want = [0i64; 4];
                want[j] = 8;
                assert_eq!(mu, want, "child {i} vertex {j}");
            }
        }
        // corner children keep the orientation
        assert!(!flips[0] && !flips[1] && !flips[2] && !flips[3]);
    }

    #[test]
    fn child_weights_match_child_maps() {
        // the closed form against the inverted Bey matrices, on lattice-like weights with zeros
        let to_child = to_child_maps();
        let mut x = 0u64;
        for n in 0..20_000u64 {
            let mut lam = [0i64; 4];
            for (k, l) in lam.iter_mut().enumerate() {
                x = splitmix(n * 4 + k as u64);
                // every 4th weight 0 (points on faces and edges), others up to 64
                *l = if x & 3 == 0 { 0 } else { (x >> 8) as i64 % 65 };
            }
            if n % 7 == 0 {
                lam[(x % 4) as usize] = 0;
            }
            let (mu, holds) = child_weights(lam);
            for (i, (m, a)) in mu.iter().zip(&to_child).enumerate() {
                let want: [i64; 4] =
                    std::array::from_fn(|r| (0..4).map(|c| a[r][c] * lam[c]).sum());
                assert_eq!(*m, want, "child {i} of {lam:?}");
                assert_eq!(holds & (1 << i) != 0, want.iter().all(|&w| w >= 0));
            }
        }
    }
}
