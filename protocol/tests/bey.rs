//! Geometry of Bey's refinement in the contract's child order: the 8 children tile the parent, and
//! over 6 levels the shapes stay in at most 3 similarity classes (aspect ratio does not degrade).

use proptest::prelude::*;
use std::collections::HashSet;
use tetwave_protocol::base::{lattice_position, signed_volume};
use tetwave_protocol::hierarchy::{Lattice, LatticeTet};

fn pos(corners: &[[f64; 3]; 4], t: &LatticeTet, m: u32) -> [[f64; 3]; 4] {
    let tet = [0u32, 1, 2, 3];
    t.v.map(|w| lattice_position(corners, &tet, m, &w))
}

fn vol(p: &[[f64; 3]; 4]) -> f64 {
    signed_volume(p[0], p[1], p[2], p[3])
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Complete similarity invariant: over the 24 vertex orders, the smallest vector of the 6 edge
/// lengths (scaled by the longest), rounded.
fn shape_class(p: &[[f64; 3]; 4]) -> Vec<i64> {
    let mut best: Option<Vec<i64>> = None;
    let longest = (0..4)
        .flat_map(|i| (0..4).map(move |j| (i, j)))
        .map(|(i, j)| dist(p[i], p[j]))
        .fold(0.0, f64::max);
    let perms = permutations4();
    for q in perms {
        let e = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
        let v: Vec<i64> = e
            .iter()
            .map(|&(a, b)| (dist(p[q[a]], p[q[b]]) / longest * 1e6).round() as i64)
            .collect();
        if best.as_ref().is_none_or(|b| v < *b) {
            best = Some(v);
        }
    }
    best.unwrap()
}

fn permutations4() -> Vec<[usize; 4]> {
    let mut out = Vec::new();
    for a in 0..4 {
        for b in 0..4 {
            for c in 0..4 {
                for d in 0..4 {
                    let s: HashSet<usize> = [a, b, c, d].into_iter().collect();
                    if s.len() == 4 {
                        out.push([a, b, c, d]);
                    }
                }
            }
        }
    }
    out
}

/// Barycentric coordinates of `x` in tet `p`.
fn bary(p: &[[f64; 3]; 4], x: [f64; 3]) -> [f64; 4] {
    let v = vol(p);
    [
        signed_volume(x, p[1], p[2], p[3]) / v,
        signed_volume(p[0], x, p[2], p[3]) / v,
        signed_volume(p[0], p[1], x, p[3]) / v,
        signed_volume(p[0], p[1], p[2], x) / v,
    ]
}

fn corners_strategy() -> impl Strategy<Value = [[f64; 3]; 4]> {
    prop::array::uniform4(prop::array::uniform3(-10.0f64..10.0)).prop_filter("well shaped", |c| {
        let v = signed_volume(c[0], c[1], c[2], c[3]).abs();
        let l = (0..4)
            .flat_map(|i| (0..4).map(move |j| (i, j)))
            .map(|(i, j)| dist(c[i], c[j]))
            .fold(0.0, f64::max);
        v > 1e-2 * l.powi(3)
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn children_tile_the_parent(c in corners_strategy(), pts in prop::collection::vec(prop::array::uniform4(0.001f64..1.0), 200)) {
        let lat = Lattice { levels: 1 };
        let parent = LatticeTet::base_tet(lat, 0);
        let children = parent.children();
        let pv = vol(&pos(&c, &parent, 2)).abs();
        let mut sum = 0.0;
        for ch in &children {
            let cv = vol(&pos(&c, ch, 2)).abs();
            prop_assert!((cv - pv / 8.0).abs() < 1e-9 * pv);
            sum += cv;
        }
        prop_assert!((sum - pv).abs() < 1e-9 * pv);
        // no overlap: a random interior point lies strictly inside exactly one child (points within
        // 1e-9 of a child face are skipped)
        let pp = pos(&c, &parent, 2);
        for w in pts {
            let s: f64 = w.iter().sum();
            let x = [0, 1, 2].map(|a| (0..4).map(|k| w[k] / s * pp[k][a]).sum::<f64>());
            let mut inside = 0;
            let mut on_face = false;
            for ch in &children {
                let b = bary(&pos(&c, ch, 2), x);
                let mn = b.iter().cloned().fold(f64::INFINITY, f64::min);
                if mn.abs() < 1e-9 { on_face = true; }
                if mn > 1e-9 { inside += 1; }
            }
            if !on_face { prop_assert_eq!(inside, 1); }
        }
    }
}

#[test]
fn at_most_three_similarity_classes_over_six_levels() {
    // a generic, irregular tet
    let c = [
        [0.0, 0.0, 0.0],
        [3.0, 0.2, 0.1],
        [0.7, 2.1, 0.3],
        [0.4, 0.9, 2.6],
    ];
    let levels = 6u8;
    let lat = Lattice { levels };
    let m = lat.m();
    let mut classes = HashSet::new();
    let mut level = vec![LatticeTet::base_tet(lat, 0)];
    let mut worst_ratio_per_level = Vec::new();
    for _ in 0..levels {
        level = level.iter().flat_map(|t| t.children()).collect();
        let mut level_classes = HashSet::new();
        let mut worst: f64 = 0.0;
        for t in &level {
            let p = pos(&c, t, m);
            level_classes.insert(shape_class(&p));
            // aspect ratio: longest edge^3 / volume
            let l = (0..4)
                .flat_map(|i| (0..4).map(move |j| (i, j)))
                .map(|(i, j)| dist(p[i], p[j]))
                .fold(0.0, f64::max);
            worst = worst.max(l.powi(3) / vol(&p).abs());
        }
        assert!(
            level_classes.len() <= 3,
            "{} classes at one level",
            level_classes.len()
        );
        classes.extend(level_classes);
        worst_ratio_per_level.push(worst);
    }
    assert!(
        classes.len() <= 3,
        "{} similarity classes over {levels} levels",
        classes.len()
    );
    // the worst aspect ratio is the same at every level from the first on
    for w in &worst_ratio_per_level {
        assert!(
            (w - worst_ratio_per_level[0]).abs() < 1e-6 * w,
            "{worst_ratio_per_level:?}"
        );
    }
}
