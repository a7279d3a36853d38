//! The thesis' progressive experiment on a small hierarchy: tolerance monotonicity, the simple run,
//! arrival orders, budgets reaching the unbudgeted mesh, and the leaf-mesh edge count.

use rustc_hash::FxHashSet;
use tetwave_client::detail_buffer::{Arrivals, DetailBuffer};
use tetwave_client::mesh::AdaptiveMesh;
use tetwave_client::progressive::{
    edges_on_box, order_nodes, run_progressive, ArrivalOrder, RunConfig,
};
use tetwave_client::select::Tolerance;
use tetwave_protocol::base::signed_volume;
use tetwave_protocol::hierarchy::{LevelWalker, EDGES};
use tetwave_protocol::wavelet::{analyze, predict};
use tetwave_protocol::{BaseMesh, DetailNode};

// fixtures: as in tests/select.rs

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

fn cfg(tol: Option<f64>) -> RunConfig {
    RunConfig {
        steps: 30,
        per_step: 1000,
        tol: tol.map(Tolerance::PercentOfHeight),
        ..RunConfig::default()
    }
}

/// Average tets grow strictly as the tolerance falls; 20% is a small fraction of the uniform mesh.
#[test]
fn tolerance_monotonicity() {
    // level 5: the thesis' Harmonic hierarchy size (187,245 tets); every node arrives by step 24
    let (base, mut nodes) = make_nodes(box5(5), harmonic);
    order_nodes(&mut nodes, ArrivalOrder::Level, 1);
    let uniform = base.forest().leaves() as f64;
    let mut last = 0.0;
    for tol in [20.0, 15.0, 12.5, 10.0, 6.25] {
        let r = run_progressive(
            &base,
            &nodes,
            [-1.0, 1.0],
            &cfg(Some(tol)),
            ArrivalOrder::Level,
        )
        .unwrap();
        assert!(r.avg_tets > last, "{tol}%: {} after {last}", r.avg_tets);
        assert_eq!(r.final_same, Some(true));
        if tol == 20.0 {
            assert!(
                r.avg_tets < 0.25 * uniform,
                "20%: {} of {uniform}",
                r.avg_tets
            );
        }
        last = r.avg_tets;
    }
    let simple =
        run_progressive(&base, &nodes, [-1.0, 1.0], &cfg(None), ArrivalOrder::Level).unwrap();
    assert_eq!(simple.final_tets as f64, uniform);
    assert!(simple.avg_tets > last);
}

/// Every arrival order and a per-step budget settle on the unbudgeted mesh.
#[test]
fn orders_and_budgets_settle() {
    let (base, nodes) = make_nodes(box5(3), harmonic);
    for order in [
        ArrivalOrder::Level,
        ArrivalOrder::Random,
        ArrivalOrder::Magnitude,
    ] {
        let mut ns = nodes.clone();
        order_nodes(&mut ns, order, 7);
        for (ms, ops) in [(None, None), (Some(0.2), None), (None, Some(10))] {
            let c = RunConfig {
                steps: 30,
                per_step: 20,
                budget_ms: ms,
                budget_ops: ops,
                ..cfg(Some(8.0))
            };
            let r = run_progressive(&base, &ns, [-1.0, 1.0], &c, order).unwrap();
            assert_eq!(r.final_same, Some(true), "{order:?} {ms:?} {ops:?}");
        }
    }
}

/// Euler's formula on the box gives the leaf mesh's exact edge count.
#[test]
fn euler_edges() {
    let (base, nodes) = make_nodes(box5(3), harmonic);
    let mut mesh = AdaptiveMesh::new(&base);
    let mut buf = DetailBuffer::new(base.forest(), base.vertex_keys());
    let mut arr = Arrivals::default();
    for n in &nodes {
        buf.insert(n, &mut arr).unwrap();
    }
    mesh.apply_arrivals(&buf, &arr);
    for id in [0u64, 5, 6, 13, 47, 51, 100] {
        if mesh.is_leaf(id) {
            mesh.refine(id, &buf).unwrap();
        }
        let tets = mesh.leaf_tets();
        let mut edges = FxHashSet::default();
        for t in &tets {
            for a in 0..4 {
                for b in a + 1..4 {
                    let (x, y) = (t.v[a].min(t.v[b]), t.v[a].max(t.v[b]));
                    edges.insert((x, y));
                }
            }
        }
        assert_eq!(edges_on_box(&mesh, tets.len()), edges.len());
        assert_eq!(mesh.piece_counts().0, tets.len());
    }
}
