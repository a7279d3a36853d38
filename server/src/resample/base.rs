//! Base meshes: the bounding box split into 5 tets (thesis) or 6 Kuhn tets, or a coarse tet mesh file.

use tetwave_protocol::base::signed_volume;

/// Vertex positions and tets (4 vertex indices each).
pub type PointsAndTets = (Vec<[f64; 3]>, Vec<[u32; 4]>);

/// Corner `i` of the box `[lo, hi]`: bit 0 → x, bit 1 → y, bit 2 → z.
fn corner(lo: [f64; 3], hi: [f64; 3], i: usize) -> [f64; 3] {
    [
        if i & 1 == 0 { lo[0] } else { hi[0] },
        if i & 2 == 0 { lo[1] } else { hi[1] },
        if i & 4 == 0 { lo[2] } else { hi[2] },
    ]
}

/// Reorders each tet's last two vertices where needed so every tet has positive volume.
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

/// The box split into 5 tets: four corner tets cut off at corners 000, 110, 101, 011 and the central
/// tet on corners 100, 010, 001, 111 (thesis §6).
pub fn box5(lo: [f64; 3], hi: [f64; 3]) -> PointsAndTets {
    let positions: Vec<[f64; 3]> = (0..8).map(|i| corner(lo, hi, i)).collect();
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

/// The box split into 6 Kuhn tets around the diagonal 000 → 111. Refined `L` times, its vertices are
/// exactly the `(2^L + 1)^3` grid points.
pub fn box6(lo: [f64; 3], hi: [f64; 3]) -> PointsAndTets {
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
    orient_positive(&positions, &mut tets);
    (positions, tets)
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
}
