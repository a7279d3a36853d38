//! Test fixtures for the crates that build on the protocol (feature `testing`, enabled from their
//! `[dev-dependencies]`; production code never calls this module).
//!
//! [`detail_nodes`] is the reference analysis: the plain definition of the design (sample every
//! vertex, lift each new vertex against its edge's sampled ends, the lowest-id tet of a level owns
//! an edge), written for clarity, not speed. The server's analysis computes the same ownership
//! closed-loop and in parallel; tests on the client side use this one to get detail nodes without
//! a server.

use crate::hierarchy::{LevelWalker, EDGES};
use crate::shapes::PointsAndTets;
use crate::synthesis::NodeAt;
use crate::wavelet::{analyze, predict, predict_split};
use crate::{BaseMesh, DetailNode};

/// A base mesh of `levels` levels on `shape` with every value 0 and no empty tet (a valid mesh to
/// sample a field on).
pub fn unsampled_base(levels: u8, shape: PointsAndTets) -> BaseMesh {
    let (positions, tets) = shape;
    BaseMesh {
        levels,
        values: vec![0.0; positions.len()],
        empty: vec![false; tets.len()],
        predictor: Default::default(),
        positions,
        tets,
    }
}

/// The manifest a lossless store of `base` would have (counts from its hierarchy, no files, a
/// value range of `[−2, 3]`): what a fake server sends before `base`.
pub fn manifest_for(base: &BaseMesh) -> crate::store_format::Manifest {
    use crate::store_format::{Counts, Encoding, Manifest, STORE_FORMAT, STORE_VERSION};
    let f = base.forest();
    let (lo, hi) = base.bounds();
    Manifest {
        format: STORE_FORMAT.into(),
        version: STORE_VERSION,
        dataset: "fake".into(),
        source: "test".into(),
        bounds: [lo, hi],
        base: "box5".into(),
        base_tets: base.tets.len() as u64,
        base_vertices: base.positions.len() as u64,
        levels: base.levels,
        value_range: [-2.0, 3.0],
        source_value_range: None,
        counts: Counts {
            tets_total: f.total_tets(),
            leaves: f.leaves(),
            nodes: f.nodes(),
            vertices: base.vertex_keys().vertex_count(),
            coefficients: 0,
            outside_vertices: 0,
            empty_base_tets: 0,
        },
        encoding: Encoding::F32,
        max_error_bound: 1e-6,
        max_abs_error: 0.0,
        files: Default::default(),
        preview: None,
        value_histogram: None,
        physical: None,
    }
}

/// Samples `f` at every vertex of `base`'s hierarchy, sets the base values, and computes every
/// detail node in id order: one coefficient per new vertex, `analyze(f(m), P(m))` with the
/// prediction ([`crate::wavelet`]) evaluated on the samples, owned by the lowest id of its level whose tet has the edge; no empty
/// children; `subtree_max_abs` the max over the node and its descendants of their edges' linear
/// details `|f(m) − (f(u) + f(v))/2|` (what the selection's error estimate reads, as the server's
/// analysis computes it).
pub fn detail_nodes(
    mut base: BaseMesh,
    f: impl Fn([f64; 3]) -> f32,
) -> (BaseMesh, Vec<DetailNode>) {
    let keys = base.vertex_keys();
    let n = keys.vertex_count() as usize;
    let mut v = vec![0f32; n];
    for (e, _) in keys.entities() {
        keys.for_each_in(e, |k, t, w| v[k as usize] = f(base.position(t, &w)));
    }
    base.values = v[..base.positions.len()].to_vec();
    // the axes predictor's details, closed loop (what synthesis will read back)
    let axes_details = (base.predictor == crate::wavelet::Predictor::Axes).then(|| {
        let grid = crate::axes::Grid::of(&base, &keys).expect("a box6 base");
        let (mut rec, mut d) = (v.clone(), vec![0f32; n]);
        grid.predict_all(&mut rec, |k, p, _| {
            d[k] = analyze(v[k], p);
            crate::wavelet::synthesize(d[k], p)
        });
        d
    });
    let forest = base.forest();
    let mut claimed = vec![false; n];
    let mut nodes: Vec<DetailNode> = Vec::new();
    let mut tets: Vec<(u64, NodeAt)> = LevelWalker::level(forest, 0)
        .map(|(id, t)| (id, NodeAt::Base(t)))
        .collect();
    for k in 0..forest.levels {
        if k > 0 {
            tets = LevelWalker::level(forest, k - 1)
                .flat_map(|(pid, parent)| {
                    (0..8).map(move |child| {
                        (forest.child(pid, child), NodeAt::Child { parent, child })
                    })
                })
                .collect();
        }
        for &(id, at) in &tets {
            let t = at.tet();
            let sampled = |w: &crate::hierarchy::Bary, base: u32| v[keys.key(base, w) as usize];
            let (mut owned, mut coeffs, mut own_max) = (0u8, Vec::new(), 0f32);
            for (e, &(a, b)) in EDGES.iter().enumerate() {
                let m = keys.key(t.base, &t.edge_midpoint(e)) as usize;
                let linear = predict(sampled(&t.v[a], t.base), sampled(&t.v[b], t.base));
                own_max = own_max.max((v[m] - linear).abs());
                if !claimed[m] {
                    claimed[m] = true;
                    owned |= 1 << e;
                    let p = match at {
                        NodeAt::Base(_) => linear,
                        NodeAt::Child { parent, child } => {
                            let c = crate::hierarchy::BEY_CHILDREN[child];
                            let v10 = parent.split_points().map(|w| sampled(&w, parent.base));
                            predict_split(&v10, c[a], c[b])
                        }
                    };
                    coeffs.push(match &axes_details {
                        Some(d) => d[m],
                        None => analyze(v[m], p),
                    });
                }
            }
            nodes.push(DetailNode {
                id,
                owned,
                empty_children: 0,
                subtree_max_abs: own_max,
                coeffs,
            });
        }
    }
    // subtree max |d|, finest nodes first
    let mut smax: Vec<f32> = nodes.iter().map(|n| n.subtree_max_abs).collect();
    for i in (0..nodes.len()).rev() {
        let id = nodes[i].id;
        for c in 0..8 {
            let cid = forest.child(id, c) as usize;
            if cid < smax.len() {
                smax[i] = smax[i].max(smax[cid]);
            }
        }
    }
    crate::node::group_siblings(base.tets.len(), &mut smax);
    for (n, m) in nodes.iter_mut().zip(smax) {
        n.subtree_max_abs = m;
    }
    (base, nodes)
}

/// The scalar of [`notched_cube_vtk`]'s points.
pub fn notched_scalar(p: [f64; 3]) -> f64 {
    p[0] + p[1] * p[1] + 0.5 * p[2]
}

/// The box `[0,1]³` without the corner `[cut,1]³` as legacy ASCII VTK: 7 hexahedra on the 27
/// points of the planes 0, `cut` and 1, with the point scalar `f` = [`notched_scalar`]. A
/// non-convex mesh whose boundary planes lie on no level of a store's lattice when `cut` is not
/// dyadic (the level-set tests' fixture).
pub fn notched_cube_vtk(cut: f64) -> String {
    let c = [0.0, cut, 1.0];
    let idx = |a: usize, b: usize, k: usize| a + 3 * b + 9 * k;
    let mut s = String::from(
        "# vtk DataFile Version 3.0\ncube minus a corner\nASCII\nDATASET UNSTRUCTURED_GRID\n",
    );
    s += "POINTS 27 double\n";
    let mut values = Vec::new();
    for k in 0..3 {
        for b in 0..3 {
            for a in 0..3 {
                let p = [c[a], c[b], c[k]];
                s += &format!("{} {} {}\n", p[0], p[1], p[2]);
                values.push(notched_scalar(p));
            }
        }
    }
    let mut hexes = Vec::new();
    for k in 0..2 {
        for j in 0..2 {
            for i in 0..2 {
                if (i, j, k) == (1, 1, 1) {
                    continue;
                }
                hexes.push([
                    idx(i, j, k),
                    idx(i + 1, j, k),
                    idx(i + 1, j + 1, k),
                    idx(i, j + 1, k),
                    idx(i, j, k + 1),
                    idx(i + 1, j, k + 1),
                    idx(i + 1, j + 1, k + 1),
                    idx(i, j + 1, k + 1),
                ]);
            }
        }
    }
    s += &format!("CELLS {} {}\n", hexes.len(), hexes.len() * 9);
    for h in &hexes {
        s += &format!("8 {}\n", h.map(|v| v.to_string()).join(" "));
    }
    s += &format!("CELL_TYPES {}\n", hexes.len());
    for _ in &hexes {
        s += "12\n";
    }
    s += "POINT_DATA 27\nSCALARS f double 1\nLOOKUP_TABLE default\n";
    for v in values {
        s += &format!("{v}\n");
    }
    s
}
