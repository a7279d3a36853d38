//! Green closures: which marked-edge patterns have one, how a leaf with such a pattern is split,
//! and into how many pieces.
//!
//! # Green splits
//! Built so that the split of every face depends only on that face: a face with 3 marked edges is cut
//! into Bey's 4 triangles (the pattern "3 edges of one face" cones them to the opposite vertex);
//! otherwise the tet is bisected at its marked edge whose midpoint has the smallest key, and each half
//! recursively at its remaining marked edge. On a face with two marked edges this draws the segment
//! from the smaller-key midpoint to the opposite corner and joins the two midpoints. All pieces are
//! made by replacing vertices of the (positively oriented) tet by points of the same edges, which keeps
//! the orientation.

use tetwave_protocol::hierarchy::{EDGES, FACES};

/// Edges of the face opposite vertex `d` (the edges not touching `d`), as a mask over [`EDGES`].
pub(super) const FACE_MASK: [u8; 4] = face_masks();

/// Edges touching vertex `v`, as a mask over [`EDGES`].
const VERTEX_MASK: [u8; 4] = vertex_masks();

const fn face_masks() -> [u8; 4] {
    let mut out = [0u8; 4];
    let mut d = 0;
    while d < 4 {
        let mut e = 0;
        while e < 6 {
            if EDGES[e].0 != d && EDGES[e].1 != d {
                out[d] |= 1 << e;
            }
            e += 1;
        }
        d += 1;
    }
    out
}

const fn vertex_masks() -> [u8; 4] {
    let mut out = [0u8; 4];
    let mut e = 0;
    while e < 6 {
        out[EDGES[e].0] |= 1 << e;
        out[EDGES[e].1] |= 1 << e;
        e += 1;
    }
    out
}

#[inline]
fn edge_index(a: usize, b: usize) -> usize {
    let (a, b) = if a < b { (a, b) } else { (b, a) };
    match (a, b) {
        (0, 1) => 0,
        (0, 2) => 1,
        (0, 3) => 2,
        (1, 2) => 3,
        (1, 3) => 4,
        _ => 5,
    }
}

/// Whether a marked-edge mask has a green closure.
#[inline]
pub fn green_pattern_ok(mask: u8) -> bool {
    match mask.count_ones() {
        0..=2 => true,
        3 => FACE_MASK.contains(&mask),
        _ => false,
    }
}

/// The green closure of a tet `v` (in an orientation-consistent vertex order) with marked-edge mask
/// `mask`: calls `out` with each piece, all in the orientation of `v`. `mid[e]` is the midpoint of
/// local edge `e` (read only for marked edges), `mkey[e]` its vertex key.
pub fn green_split<P: Copy>(
    v: [P; 4],
    mask: u8,
    mid: &[P; 6],
    mkey: &[u64; 6],
    out: &mut impl FnMut([P; 4]),
) {
    if mask == 0 {
        out(v);
        return;
    }
    if mask.count_ones() == 3 {
        let d = FACE_MASK
            .iter()
            .position(|&m| m == mask)
            .expect("3 marked edges not on one face: not a green pattern");
        let [a, b, c] = FACES[d];
        let (mab, mac, mbc) = (
            mid[edge_index(a, b)],
            mid[edge_index(a, c)],
            mid[edge_index(b, c)],
        );
        let mut t = v;
        t[b] = mab;
        t[c] = mac;
        out(t);
        let mut t = v;
        t[a] = mab;
        t[c] = mbc;
        out(t);
        let mut t = v;
        t[a] = mac;
        t[b] = mbc;
        out(t);
        let mut t = v;
        t[a] = mbc;
        t[b] = mac;
        t[c] = mab;
        out(t);
        return;
    }
    debug_assert!(mask.count_ones() <= 2);
    let mut e = 6;
    for i in 0..6 {
        if mask & (1 << i) != 0 && (e == 6 || mkey[i] < mkey[e]) {
            e = i;
        }
    }
    let (a, b) = EDGES[e];
    let rest = mask & !(1 << e);
    let mut t = v;
    t[a] = mid[e];
    green_split(t, rest & !VERTEX_MASK[a], mid, mkey, out);
    let mut t = v;
    t[b] = mid[e];
    green_split(t, rest & !VERTEX_MASK[b], mid, mkey, out);
}

/// Number of leaf-mesh pieces a leaf with green pattern `mask` is drawn as.
#[inline]
pub fn green_piece_count(mask: u8) -> usize {
    match mask.count_ones() {
        0 => 1,
        1 => 2,
        2 => {
            if mask == 0b100001 || mask == 0b010010 || mask == 0b001100 {
                4
            } else {
                3
            }
        }
        _ => 4,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn green_patterns() {
        assert!(green_pattern_ok(0));
        for e in 0..6 {
            assert!(green_pattern_ok(1 << e));
        }
        let mut n3 = 0;
        for m in 0u8..64 {
            if m.count_ones() == 3 && green_pattern_ok(m) {
                n3 += 1;
            }
        }
        assert_eq!(n3, 4);
        assert!(!green_pattern_ok(0b111111));
    }

    #[test]
    fn green_split_piece_counts() {
        let v = [0u32, 1, 2, 3];
        let mid = [4u32, 5, 6, 7, 8, 9];
        let mkey = [14u64, 15, 16, 17, 18, 19];
        let count = |mask: u8| {
            let mut n = 0;
            green_split(v, mask, &mid, &mkey, &mut |_| n += 1);
            n
        };
        assert_eq!(count(0), 1);
        assert_eq!(count(1), 2);
        assert_eq!(count(0b000011), 3); // (0,1),(0,2) share face 3
        assert_eq!(count(0b100001), 4); // (0,1),(2,3) opposite
        assert_eq!(count(FACE_MASK[0]), 4);
    }
}
