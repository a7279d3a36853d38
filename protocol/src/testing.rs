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
use crate::wavelet::{analyze, predict};
use crate::{BaseMesh, DetailNode};

/// A base mesh of `levels` levels on `shape` with every value 0 and no empty tet (a valid mesh to
/// sample a field on).
pub fn unsampled_base(levels: u8, shape: PointsAndTets) -> BaseMesh {
    let (positions, tets) = shape;
    BaseMesh {
        levels,
        values: vec![0.0; positions.len()],
        empty: vec![false; tets.len()],
        positions,
        tets,
    }
}

/// Samples `f` at every vertex of `base`'s hierarchy, sets the base values, and computes every
/// detail node in id order: one coefficient per new vertex, `analyze(f(m), predict(f(u), f(v)))`
/// against the sampled ends, owned by the lowest id of its level whose tet has the edge; no empty
/// children; `subtree_max_abs` the max |coefficient| of the node and its descendants.
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
    let forest = base.forest();
    let mut claimed = vec![false; n];
    let mut nodes: Vec<DetailNode> = Vec::new();
    for k in 0..forest.levels {
        for (id, t) in LevelWalker::level(forest, k) {
            let (mut owned, mut coeffs) = (0u8, Vec::new());
            for (e, &(a, b)) in EDGES.iter().enumerate() {
                let m = keys.key(t.base, &t.edge_midpoint(e)) as usize;
                if !claimed[m] {
                    claimed[m] = true;
                    owned |= 1 << e;
                    let u = keys.key(t.base, &t.v[a]) as usize;
                    let w = keys.key(t.base, &t.v[b]) as usize;
                    coeffs.push(analyze(v[m], predict(v[u], v[w])));
                }
            }
            nodes.push(DetailNode {
                id,
                owned,
                empty_children: 0,
                subtree_max_abs: 0.0,
                coeffs,
            });
        }
    }
    // subtree max |d|, finest nodes first
    let mut smax: Vec<f32> = nodes
        .iter()
        .map(|n| n.coeffs.iter().fold(0f32, |m, c| m.max(c.abs())))
        .collect();
    for i in (0..nodes.len()).rev() {
        let id = nodes[i].id;
        for c in 0..8 {
            let cid = forest.child(id, c) as usize;
            if cid < smax.len() {
                smax[i] = smax[i].max(smax[cid]);
            }
        }
        nodes[i].subtree_max_abs = smax[i];
    }
    (base, nodes)
}
