//! Visibility orders for projected tetrahedra (back to front).
//!
//! - [`centroid_order`]: sort by the eye-to-centroid distance, farthest first. Fast and usually right;
//!   it fails where a tet lies in front of a neighbour along some rays although its centroid is
//!   farther (tets of very different sizes side by side, long slivers), and it cannot be right when
//!   the "in front of" relation has a cycle.
//! - [`mpvo_order`]: Williams' Meshed Polyhedra Visibility Ordering. Every interior face orders its
//!   two tets by the side of the face's plane the eye is on; a topological sort of that relation is an
//!   exact visibility order for a *convex* mesh whose relation is acyclic (e.g. Delaunay meshes). On
//!   non-convex meshes it is not exact (gaps between parts are not ordered); cycles (possible in
//!   non-Delaunay meshes) are broken by taking the remaining tet with the farthest centroid, and
//!   counted.

use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;

/// Face adjacency of a tet mesh: `neighbors[t][i]` is the tet across face `i` (opposite vertex `i`)
/// of tet `t`, `u32::MAX` on the boundary.
pub fn face_neighbors(tets: &[[u32; 4]]) -> Vec<[u32; 4]> {
    let mut map: HashMap<[u32; 3], (u32, u8)> = HashMap::with_capacity(tets.len() * 2);
    let mut nb = vec![[u32::MAX; 4]; tets.len()];
    for (t, tet) in tets.iter().enumerate() {
        for i in 0..4 {
            let mut f = [0u32; 3];
            let mut k = 0;
            for (j, &v) in tet.iter().enumerate() {
                if j != i {
                    f[k] = v;
                    k += 1;
                }
            }
            f.sort_unstable();
            if let Some((o, oi)) = map.remove(&f) {
                nb[t][i] = o;
                nb[o as usize][oi as usize] = t as u32;
            } else {
                map.insert(f, (t as u32, i as u8));
            }
        }
    }
    nb
}

/// Whether the mesh's domain is convex, judged from its boundary (the faces of one tet): every
/// boundary edge joins exactly two boundary faces with a dihedral angle that is not reflex (the
/// far corner of each face lies on the inner side of the other's plane, within `1e-9` of the
/// mesh's size), and the boundary is one connected surface. A closed, connected surface that is
/// locally convex at every edge bounds a convex body, so this is exact up to the tolerance; a mesh
/// with gaps, holes, concavities, cavities or several parts is reported non-convex. MPVO is
/// exact only on convex meshes ([`mpvo_order`]).
pub fn is_convex(positions: &[[f64; 3]], tets: &[[u32; 4]], neighbors: &[[u32; 4]]) -> bool {
    let p = |v: u32| DVec3::from_array(positions[v as usize]);
    // boundary faces: their 3 vertices and the outward normal (away from the tet's 4th vertex)
    let mut faces: Vec<([u32; 3], DVec3)> = Vec::new();
    for (t, tet) in tets.iter().enumerate() {
        for i in 0..4 {
            if neighbors[t][i] != u32::MAX {
                continue;
            }
            let f: [u32; 3] = std::array::from_fn(|k| tet[(i + 1 + k) % 4]);
            let mut n = (p(f[1]) - p(f[0])).cross(p(f[2]) - p(f[0]));
            if n.dot(p(tet[i]) - p(f[0])) > 0.0 {
                n = -n;
            }
            faces.push((f, n.normalize_or_zero()));
        }
    }
    if faces.is_empty() {
        return false;
    }
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for v in positions {
        lo = lo.min(DVec3::from_array(*v));
        hi = hi.max(DVec3::from_array(*v));
    }
    let eps = 1e-9 * (hi - lo).length();
    let mut edges: HashMap<[u32; 2], Vec<u32>> = HashMap::with_capacity(faces.len() * 3 / 2);
    for (fi, (f, _)) in faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            edges
                .entry([a.min(b), a.max(b)])
                .or_default()
                .push(fi as u32);
        }
    }
    // union-find over the faces, joined across their edges
    let mut parent: Vec<u32> = (0..faces.len() as u32).collect();
    fn root(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            parent[x as usize] = parent[parent[x as usize] as usize];
            x = parent[x as usize];
        }
        x
    }
    for (e, fs) in &edges {
        let &[f, g] = fs.as_slice() else {
            return false;
        };
        let far = |of: u32| {
            let vs = faces[of as usize].0;
            *vs.iter()
                .find(|&&v| !e.contains(&v))
                .expect("a face has a vertex off its edge")
        };
        for (a, b) in [(f, g), (g, f)] {
            let (va, na) = faces[a as usize];
            if na.dot(p(far(b)) - p(va[0])) > eps {
                return false;
            }
        }
        let (rf, rg) = (root(&mut parent, f), root(&mut parent, g));
        parent[rf as usize] = rg;
    }
    let r0 = root(&mut parent, 0);
    (1..faces.len() as u32).all(|f| root(&mut parent, f) == r0)
}

/// Tets sorted farthest centroid first.
pub fn centroid_order(centroids: &[[f32; 3]], eye: [f32; 3]) -> Vec<u32> {
    let mut keyed: Vec<(u32, u32)> = centroids
        .par_iter()
        .enumerate()
        .map(|(i, c)| {
            let d = (c[0] - eye[0]).powi(2) + (c[1] - eye[1]).powi(2) + (c[2] - eye[2]).powi(2);
            (!d.to_bits(), i as u32)
        })
        .collect();
    keyed.par_sort_unstable_by_key(|k| k.0);
    keyed.into_iter().map(|k| k.1).collect()
}

/// MPVO order for the eye at `eye`; `planes[t][i]` is the outward plane `(n, d)` (`n·x = d`) of face
/// `i` of tet `t`, and `eye`, `planes` and `centroids` share one coordinate frame. Returns the order and
/// the number of cycle breaks.
pub fn mpvo_order(
    planes: &[[[f32; 4]; 4]],
    neighbors: &[[u32; 4]],
    centroids: &[[f32; 3]],
    eye: [f32; 3],
) -> (Vec<u32>, usize) {
    let n = planes.len();
    let e = DVec3::new(eye[0] as f64, eye[1] as f64, eye[2] as f64);
    // decided once per face, by its lower-numbered tet, so both sides agree even when the eye lies
    // in the face's plane (then the lower tet counts as in front: edge-on faces need no order)
    let mut in_front_of_neighbor: Vec<[bool; 4]> = planes
        .par_iter()
        .enumerate()
        .map(|(t, pl)| {
            let mut r = [false; 4];
            for i in 0..4 {
                let o = neighbors[t][i];
                if o == u32::MAX || (o as usize) < t {
                    continue;
                }
                let q = pl[i];
                let side = q[0] as f64 * e.x + q[1] as f64 * e.y + q[2] as f64 * e.z - q[3] as f64;
                // eye beyond the face: the neighbour is in front of this tet
                r[i] = side <= 0.0;
            }
            r
        })
        .collect();
    for t in 0..n {
        for i in 0..4 {
            let o = neighbors[t][i];
            if o != u32::MAX && (o as usize) > t {
                if let Some(j) = neighbors[o as usize].iter().position(|&x| x == t as u32) {
                    in_front_of_neighbor[o as usize][j] = !in_front_of_neighbor[t][i];
                }
            }
        }
    }
    let mut indeg = vec![0u32; n];
    for t in 0..n {
        for i in 0..4 {
            let o = neighbors[t][i];
            if o != u32::MAX && in_front_of_neighbor[t][i] {
                indeg[t] += 1;
            }
        }
    }
    let mut stack: Vec<u32> = (0..n as u32).filter(|&t| indeg[t as usize] == 0).collect();
    let mut order = Vec::with_capacity(n);
    let mut done = vec![false; n];
    let mut breaks = 0;
    let mut fallback: Option<Vec<u32>> = None;
    let mut fb_at = 0;
    while order.len() < n {
        let t = match stack.pop() {
            Some(t) => t,
            None => {
                // a cycle: take the farthest remaining tet
                let fb = fallback.get_or_insert_with(|| centroid_order(centroids, eye));
                while done[fb[fb_at] as usize] {
                    fb_at += 1;
                }
                breaks += 1;
                fb[fb_at]
            }
        };
        if done[t as usize] {
            continue;
        }
        done[t as usize] = true;
        order.push(t);
        for i in 0..4 {
            let o = neighbors[t as usize][i];
            if o != u32::MAX && !in_front_of_neighbor[t as usize][i] {
                // t is behind o: o loses one blocker
                let oi = o as usize;
                indeg[oi] = indeg[oi].saturating_sub(1);
                if indeg[oi] == 0 && !done[oi] {
                    stack.push(o);
                }
            }
        }
    }
    (order, breaks)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Kuhn cube is convex; without one of its 8 sub-cubes (a notch at a corner), or as two
    /// separate cubes, it is not.
    #[test]
    fn convexity_of_boundaries() {
        let check = |keep: &dyn Fn(usize, usize, usize) -> bool, shift: bool| {
            let (mut pts, mut tets) = tetwave_protocol::shapes::kuhn_grid(2, keep);
            if shift {
                // a second copy, apart from the first
                let n = pts.len() as u32;
                let more: Vec<[f64; 3]> = pts.iter().map(|p| [p[0] + 3.0, p[1], p[2]]).collect();
                pts.extend(more);
                let t2: Vec<[u32; 4]> = tets.iter().map(|t| t.map(|v| v + n)).collect();
                tets.extend(t2);
            }
            is_convex(&pts, &tets, &face_neighbors(&tets))
        };
        assert!(check(&|_, _, _| true, false));
        assert!(!check(&|i, j, k| (i, j, k) != (1, 1, 1), false));
        assert!(!check(&|_, _, _| true, true));
    }
    use tetwave_render::render_mesh::RenderMesh;

    /// On a convex Kuhn-cube mesh, MPVO respects every face: whenever two tets share a face, the one
    /// on the eye's side of it comes later.
    #[test]
    fn mpvo_respects_every_shared_face() {
        let mesh = RenderMesh::kuhn_cube(4, 1.0, |p| p[0]);
        let nb = face_neighbors(&mesh.tets);
        let interior = nb.iter().flatten().filter(|&&o| o != u32::MAX).count();
        assert_eq!(interior, 2 * (6 * 64 * 4 - 6 * 16 * 2) / 2);
        for eye in [
            DVec3::new(3.0, 2.0, 1.5),
            DVec3::new(0.4, 0.6, 0.5),
            DVec3::new(-2.0, 0.5, 0.5),
        ] {
            let planes: Vec<[[f32; 4]; 4]> = (0..mesh.tets.len())
                .map(|t| {
                    mesh.tet_geometry(t, DVec3::ZERO)
                        .0
                        .map(|(n, d)| [n.x as f32, n.y as f32, n.z as f32, d as f32])
                })
                .collect();
            let cents: Vec<[f32; 3]> = vec![[0.0; 3]; mesh.tets.len()];
            let e32 = [eye.x as f32, eye.y as f32, eye.z as f32];
            let (order, breaks) = mpvo_order(&planes, &nb, &cents, e32);
            assert_eq!(breaks, 0);
            let mut pos = vec![0usize; order.len()];
            for (k, &t) in order.iter().enumerate() {
                pos[t as usize] = k;
            }
            let mut sorted = order.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, (0..mesh.tets.len() as u32).collect::<Vec<_>>());
            for (t, tet) in mesh.tets.iter().enumerate() {
                for i in 0..4 {
                    let o = nb[t][i];
                    if o == u32::MAX {
                        continue;
                    }
                    let p = |v: u32| DVec3::from_array(mesh.positions[v as usize]);
                    let f: Vec<u32> = (0..4).filter(|&j| j != i).map(|j| tet[j]).collect();
                    let mut nrm = (p(f[1]) - p(f[0])).cross(p(f[2]) - p(f[0]));
                    if nrm.dot(p(tet[i]) - p(f[0])) > 0.0 {
                        nrm = -nrm;
                    }
                    let eye_beyond = nrm.dot(eye - p(f[0])) > 0.0;
                    if eye_beyond {
                        assert!(pos[t] < pos[o as usize], "tet {t} must precede {o}");
                    }
                }
            }
        }
    }
}
