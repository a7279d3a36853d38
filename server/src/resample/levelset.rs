//! The input domain's level set at the semi-regular vertices: the signed distance to the boundary
//! of an unstructured input (positive inside, negative outside), stored with the store
//! (`levelset.f32`) so that renderers clip each tet's ray segment to where its linear
//! interpolant is ≥ 0, recovering the boundary inside the tets that straddle it instead of
//! drawing them whole.
//!
//! **Exactness where it matters.** The signed distance `φ` is 1-Lipschitz, so across a tet of
//! diameter `h` whose corners have both signs every corner has `|φ| ≤ h`. A vertex is a corner of
//! tets of every level from the one that created it to the finest, and a streaming client's green
//! closure draws pieces of its parent tet with it as a corner (the pieces' corners are the
//! parent's corners and edge midpoints); `cap` is the largest diameter of all those tets. Its
//! value is therefore only ever interpolated across a drawn tet with corners on both sides when
//! `|φ| ≤ cap`, so `sign · min(|φ|, cap)` renders exactly as `φ` at every level and in every green
//! piece, and the distance query stops at `cap` (a few box tests for the many fine vertices far
//! from the boundary).

use super::Resampled;
use rayon::prelude::*;
use tetwave_import::clean::BoundaryDistance;
use tetwave_protocol::hierarchy::{Bary, LatticeTet, LevelWalker};
use tetwave_protocol::levelset::{LevelSetError, NearLevelSet, FAR_OUTSIDE};

/// The level set of a store: every vertex's value and the near band streaming clients need.
pub struct LevelSet {
    /// Per vertex key: `+min(d, cap)` inside the domain (a sample exists there), `−min(d, cap)`
    /// outside (`NaN` sample), `d` the distance to the boundary, `cap` the largest diameter of a
    /// tet the vertex is a corner or an edge midpoint of (see the module docs).
    pub values: Vec<f32>,
    /// What streaming clients clip with ([`NearLevelSet`]): every corner and edge midpoint of a
    /// tet (of any level) with one of them outside, with its value, or flagged when it is outside
    /// beyond its clamp.
    pub near: NearLevelSet,
}

/// The corners of `t` and, when `midpoints` (it is not a finest-level tet), its edge midpoints.
fn points(t: &LatticeTet, midpoints: bool) -> impl Iterator<Item = Bary> + '_ {
    let mids = if midpoints { 6 } else { 0 };
    t.v.iter()
        .copied()
        .chain((0..mids).map(|e| t.edge_midpoint(e)))
}

/// The domain's level set at every vertex of `r`'s hierarchy; the near band's values in steps of
/// 1/32 of the smallest clamp (a finest vertex is an edge midpoint of a level-`L − 1` tet, so
/// about two finest tets' diameter).
pub fn signed_distance(
    r: &Resampled,
    boundary: &BoundaryDistance,
) -> Result<LevelSet, LevelSetError> {
    let base = &r.base;
    let keys = &r.keys;
    let forest = base.forest();
    let n = r.samples.len();
    let mut cap = vec![0f32; n];
    for level in 0..=forest.levels {
        for (_, t) in LevelWalker::level(forest, level) {
            let p = t.v.map(|w| base.position(t.base, &w));
            let mut h2 = 0f64;
            for i in 0..4 {
                for j in i + 1..4 {
                    let d2: f64 = (0..3).map(|k| (p[i][k] - p[j][k]).powi(2)).sum();
                    h2 = h2.max(d2);
                }
            }
            // rounded up so that the clamp never cuts a distance the tet can see
            let h = (h2.sqrt() * (1.0 + 1e-6)) as f32;
            // its corners, and its edge midpoints, which a client's green closure joins to its
            // corners in pieces of this tet
            for w in points(&t, level < forest.levels) {
                let c = &mut cap[keys.key(t.base, &w) as usize];
                *c = c.max(h);
            }
        }
    }
    let mut out = vec![0f32; n];
    // the entities' contiguous key ranges, filled in parallel (as the resampler does)
    let mut chunks = Vec::new();
    let mut rest: &mut [f32] = &mut out;
    let mut at = 0u64;
    for (e, range) in keys.entities() {
        let (_, tail) = rest.split_at_mut((range.start - at) as usize);
        let (mine, tail) = tail.split_at_mut((range.end - range.start) as usize);
        chunks.push((e, range.start, mine));
        rest = tail;
        at = range.end;
    }
    chunks.into_par_iter().for_each(|(entity, start, out)| {
        keys.for_each_in(entity, |key, tet, w| {
            let p = base.position(tet, &w);
            let k = key as usize;
            let d = boundary.distance_within(p, cap[k] as f64) as f32;
            out[(key - start) as usize] = if r.samples[k].is_nan() { -d } else { d };
        });
    });
    let finest = cap
        .iter()
        .copied()
        .filter(|&c| c > 0.0)
        .fold(f32::INFINITY, f32::min);
    let step = if finest.is_finite() {
        finest / 32.0
    } else {
        1.0
    };
    // a vertex's value matters only in tets with a corner outside: elsewhere every corner is
    // ≥ 0 and the tet is drawn whole whatever they hold; a client's green pieces of a tet have
    // its corners and edge midpoints for corners, so those count as one tet's
    let mut beside_outside = vec![false; n];
    for level in 0..=forest.levels {
        for (_, t) in LevelWalker::level(forest, level) {
            let (mut k, mut n) = ([0usize; 10], 0);
            for w in points(&t, level < forest.levels) {
                k[n] = keys.key(t.base, &w) as usize;
                n += 1;
            }
            if k[..n].iter().any(|&k| out[k] < 0.0) {
                for &k in &k[..n] {
                    beside_outside[k] = true;
                }
            }
        }
    }
    let near = NearLevelSet::new(
        step,
        out.iter()
            .zip(&cap)
            .zip(&beside_outside)
            .enumerate()
            .filter(|(_, (_, &beside))| beside)
            .map(|(k, ((&v, &c), _))| {
                let far_outside = v < 0.0 && v.abs() >= c;
                (k as u64, if far_outside { FAR_OUTSIDE } else { v })
            }),
    )?;
    Ok(LevelSet { values: out, near })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resample::unstructured::{Locator, ScalarTetMesh};
    use crate::resample::{resample, BaseSpec, Source};
    use tetwave_protocol::shapes;

    /// The unit cube without its upper octant `[½,1]³`, as 7 cubes of 6 Kuhn tets.
    fn l_cube() -> ScalarTetMesh {
        let (points, mut tets) = shapes::kuhn_grid(2, |i, j, k| !(i == 1 && j == 1 && k == 1));
        shapes::orient_positive(&points, &mut tets);
        let values = points.iter().map(|p| p[0]).collect();
        ScalarTetMesh {
            points,
            tets,
            values,
            distance: false,
        }
    }

    /// Exact signed distance to the boundary of the cube minus its upper octant.
    fn exact(p: [f64; 3]) -> f64 {
        let in_octant = (0..3).all(|k| p[k] >= 0.5);
        if !in_octant {
            // inside: the nearest of the cube's faces and the octant's (a face point of the cube
            // that lies on the octant is farther than the octant itself)
            let to_cube = (0..3)
                .map(|k| p[k].min(1.0 - p[k]))
                .fold(f64::INFINITY, f64::min);
            let d_oct = (0..3)
                .map(|k| (0.5 - p[k]).max(0.0).powi(2))
                .sum::<f64>()
                .sqrt();
            to_cube.min(d_oct)
        } else {
            // in the removed octant: its faces at ½ are the domain's boundary
            -(0..3).map(|k| p[k] - 0.5).fold(f64::INFINITY, f64::min)
        }
    }

    /// On the L-shaped cube at 3 levels: every vertex gets its exact signed distance, clamped at
    /// the diameter of the coarsest tet it belongs to, with the sign of the sample (inside or not).
    #[test]
    fn signed_distance_of_a_cube_minus_an_octant() {
        let mesh = l_cube();
        let loc = Locator::new(&mesh);
        let bounds = tetwave_import::clean::bbox(&mesh.points);
        let source = Source::Mesh(Box::new(loc), bounds);
        let r = resample(&source, &BaseSpec::Box6, 3).unwrap();
        let b = BoundaryDistance::new(&mesh.points, &mesh.tets);
        let set = signed_distance(&r, &b).unwrap();
        let ls = &set.values;
        let fine_diam = 3f64.sqrt() / 8.0;
        let mut checked = 0;
        let mut negative = 0;
        for entity in r.keys.entities() {
            r.keys.for_each_in(entity.0, |key, tet, w| {
                let p = r.base.position(tet, &w);
                let want = exact(p);
                let got = ls[key as usize] as f64;
                assert!(got.abs() <= want.abs() + 1e-6, "{p:?}: {got} vs {want}");
                // clamped values keep the sign; unclamped ones are exact
                assert!(
                    got * want >= 0.0 || want.abs() < 1e-9,
                    "{p:?}: {got} vs {want}"
                );
                if want.abs() <= fine_diam {
                    assert!((got - want).abs() < 1e-6, "{p:?}: {got} vs {want}");
                    checked += 1;
                }
                if got < 0.0 {
                    negative += 1;
                }
            });
        }
        assert!(checked > 100 && negative > 10, "{checked} {negative}");
        // the near band holds, with its value, every corner and edge midpoint (the corners of a
        // client's green pieces) of every tet, at every level, whose corners and midpoints lie on
        // both sides (outside, and inside or on the boundary)
        let forest = r.base.forest();
        let mut straddling = 0;
        for level in 0..=forest.levels {
            for (_, t) in LevelWalker::level(forest, level) {
                let k: Vec<u64> = points(&t, level < forest.levels)
                    .map(|w| r.keys.key(t.base, &w))
                    .collect();
                let v: Vec<f32> = k.iter().map(|&k| ls[k as usize]).collect();
                if v.iter().any(|&x| x < 0.0) && v.iter().any(|&x| x >= 0.0) {
                    straddling += 1;
                    for (k, &v) in k.iter().zip(&v) {
                        let got = set
                            .near
                            .get(*k)
                            .expect("a straddling tet's corner is listed");
                        assert!(
                            (got - v).abs() <= set.near.step() / 2.0 + 1e-7
                                && (got < 0.0) == (v < 0.0),
                            "key {k} at level {level}: {got} for {v}"
                        );
                    }
                }
            }
        }
        assert!(straddling > 50, "{straddling}");
        // every outside vertex is listed (near with its value, or far outside)
        for (k, &v) in ls.iter().enumerate() {
            if v < 0.0 {
                let got = set.near.get(k as u64).expect("an outside vertex is listed");
                assert!(got < 0.0, "key {k}: {got} for {v}");
            }
        }
    }
}
