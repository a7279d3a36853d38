//! Test data shared by the selection and progressive tests: a 30³ box in 5 tets and detail nodes of
//! a field computed the way the server does (lowest id owns each new vertex).
#![allow(dead_code)]

use tetwave_protocol::base::signed_volume;
use tetwave_protocol::hierarchy::{LevelWalker, EDGES};
use tetwave_protocol::wavelet::{analyze, predict};
use tetwave_protocol::{BaseMesh, DetailNode};

/// The box `[0, 30]³` in 5 positive tets.
pub fn box5(levels: u8) -> BaseMesh {
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
    BaseMesh {
        levels,
        values: vec![0.0; 8],
        empty: vec![false; 5],
        positions,
        tets,
    }
}

/// Samples `f` at every vertex and computes every detail node (lowest id of a level owns an edge).
pub fn make_nodes(mut base: BaseMesh, f: impl Fn([f64; 3]) -> f32) -> (BaseMesh, Vec<DetailNode>) {
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

pub fn harmonic(p: [f64; 3]) -> f32 {
    let s = std::f64::consts::PI / 15.0;
    ((s * p[0]).sin() * (s * p[1]).cos() * (0.5 * s * p[2]).sin()) as f32
}

/// The progressive experiment on the level-`levels` harmonic hierarchy (nodes in level order) with
/// a render probe drawing every `every`-th step (GPU, or the CPU reference when `cpu`) against the
/// full-resolution mesh: the run's report and the probe's figures.
pub fn probed_run(
    levels: u8,
    cfg: &tetwave_client::progressive::RunConfig,
    every: usize,
    cpu: bool,
) -> (
    tetwave_client::progressive::RunReport,
    tetwave_client::render_probe::RenderSummary,
) {
    use tetwave_client::mesh::AdaptiveMesh;
    use tetwave_client::progressive::{order_nodes, run_progressive_with, ArrivalOrder};
    use tetwave_client::render_probe::RenderProbe;
    use tetwave_protocol::view::Camera;
    use tetwave_render::render_mesh::RenderMesh;
    use tetwave_render::transfer::TransferFunction;
    let (base, mut nodes) = make_nodes(box5(levels), harmonic);
    order_nodes(&mut nodes, ArrivalOrder::Level, 1);
    let values = tetwave_protocol::synthesis::synthesize_all(
        &base,
        &base.vertex_keys(),
        nodes.iter().cloned(),
    )
    .unwrap();
    let range = [-1.0, 1.0];
    let full = RenderMesh::uniform_level(&base, &values, base.levels);
    let tf = TransferFunction::preset("default").unwrap();
    let mut probe = RenderProbe::new(full, range, every, cpu, tf)
        .unwrap_or_else(|e| panic!("the render probe cannot run: {e}"));
    let mut observe = |step: usize, mesh: &AdaptiveMesh, cam: &Camera| {
        if probe.wants(step, cfg.steps) {
            probe.observe(step, mesh, cam);
        }
    };
    let r =
        run_progressive_with(&base, &nodes, range, cfg, ArrivalOrder::Level, &mut observe).unwrap();
    (r, probe.finish().unwrap())
}
