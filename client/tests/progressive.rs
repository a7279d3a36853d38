//! The thesis' progressive experiment on a small hierarchy: tolerance monotonicity, the simple run,
//! arrival orders, budgets reaching the unbudgeted mesh, and the leaf-mesh edge count.

use rustc_hash::FxHashSet;
use tetwave_adaptive::select::Tolerance;
use tetwave_client::progressive::{
    edges_on_box, order_nodes, run_progressive, ArrivalOrder, RunConfig,
};

// fixtures: as in tests/select.rs

mod common;
use common::{box5, detail_nodes, loaded, wave};

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
    let (base, mut nodes) = detail_nodes(box5(5), wave);
    order_nodes(&mut nodes, ArrivalOrder::Level, 1, base.forest());
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
    let (base, nodes) = detail_nodes(box5(3), wave);
    for order in [
        ArrivalOrder::Level,
        ArrivalOrder::Random,
        ArrivalOrder::Magnitude,
    ] {
        let mut ns = nodes.clone();
        order_nodes(&mut ns, order, 7, base.forest());
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

/// Budgets that cut merges into chunks, on a hierarchy large enough for groups of merges that
/// only hold together: the settled mesh is the unbudgeted one from the same state (parked
/// candidates must not outlive the chunk that could free them).
#[test]
fn chunked_merges_settle() {
    let (base, nodes) = detail_nodes(box5(4), wave);
    for (seed, order) in [ArrivalOrder::Level, ArrivalOrder::Random]
        .into_iter()
        .enumerate()
    {
        let mut ns = nodes.clone();
        order_nodes(&mut ns, order, seed as u64 + 3, base.forest());
        for tol in [12.5, 8.0, 5.0] {
            for ops in [16, 64, 300] {
                let c = RunConfig {
                    steps: 60,
                    per_step: 400,
                    rotate: 0.08,
                    budget_ops: Some(ops),
                    ..cfg(Some(tol))
                };
                let r = run_progressive(&base, &ns, [-1.0, 1.0], &c, order).unwrap();
                assert_eq!(r.final_same, Some(true), "{order:?} {tol}% {ops} ops");
            }
        }
    }
}

/// A time budget that never runs out takes the unbudgeted run's path exactly: its merge batches
/// are not cut into chunks (few candidates, most of the frame left), so no consolidating sweep.
#[test]
fn ample_time_budget_is_unbudgeted() {
    let (base, nodes) = detail_nodes(box5(4), wave);
    for tol in [12.5, 5.0] {
        let c = RunConfig {
            steps: 40,
            per_step: 400,
            rotate: 0.08,
            ..cfg(Some(tol))
        };
        let free = run_progressive(&base, &nodes, [-1.0, 1.0], &c, ArrivalOrder::Level).unwrap();
        let timed = RunConfig {
            budget_ms: Some(60_000.0),
            ..c
        };
        let r = run_progressive(&base, &nodes, [-1.0, 1.0], &timed, ArrivalOrder::Level).unwrap();
        assert!(free.merges > 0, "{tol}%: no merges to compare");
        let path = |r: &tetwave_client::progressive::RunReport| {
            (
                r.splits,
                r.merges,
                r.sweeps,
                r.sel_merge_attempts,
                r.final_tets,
            )
        };
        assert_eq!(path(&r), path(&free), "{tol}%");
        assert_eq!(r.final_same, Some(true), "{tol}%");
    }
}

/// Sweeps with more merge candidates than one uncut batch takes under a time budget (4,096; the
/// camera turns about half way round at every step, so what was refined in front of it coarsens):
/// the budgeted run cuts them into chunks (seen as extra, consolidating sweeps) and still settles
/// on the unbudgeted mesh.
#[test]
fn large_merge_sweeps_under_a_time_budget_settle() {
    let (base, nodes) = detail_nodes(box5(5), wave);
    let c = RunConfig {
        steps: 12,
        per_step: 20_000,
        rotate: 3.1,
        ..cfg(Some(4.0))
    };
    let free = run_progressive(&base, &nodes, [-1.0, 1.0], &c, ArrivalOrder::Level).unwrap();
    let timed = RunConfig {
        budget_ms: Some(60_000.0),
        ..c
    };
    let r = run_progressive(&base, &nodes, [-1.0, 1.0], &timed, ArrivalOrder::Level).unwrap();
    assert!(
        r.sweeps > free.sweeps,
        "no sweep was cut into chunks: {} sweeps, {} without a budget",
        r.sweeps,
        free.sweeps
    );
    assert_eq!(r.final_same, Some(true));
    assert_eq!(r.final_tets, free.final_tets);
}

/// Euler's formula on the box gives the leaf mesh's exact edge count.
#[test]
fn euler_edges() {
    let (mut mesh, buf, _) = loaded(3, wave);
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

/// `--full-scan` (the reference selector, no per-slot caches) takes the same path as the cached
/// selector: as many splits and merges, the same final mesh, and a selector that holds less
/// memory.
#[test]
fn full_scan_takes_the_same_path() {
    let (base, mut nodes) = detail_nodes(box5(4), wave);
    order_nodes(&mut nodes, ArrivalOrder::Random, 5, base.forest());
    for tol in [Some(12.5), Some(6.0), None] {
        let c = RunConfig {
            steps: 40,
            per_step: 200,
            rotate: 0.1,
            ..cfg(tol)
        };
        let fast = run_progressive(&base, &nodes, [-1.0, 1.0], &c, ArrivalOrder::Random).unwrap();
        let reference = RunConfig {
            full_scan: true,
            ..c
        };
        let slow =
            run_progressive(&base, &nodes, [-1.0, 1.0], &reference, ArrivalOrder::Random).unwrap();
        assert_eq!(
            (slow.splits, slow.merges),
            (fast.splits, fast.merges),
            "{tol:?}"
        );
        assert_eq!(slow.final_tets, fast.final_tets, "{tol:?}");
        assert_eq!(slow.final_same, Some(true), "{tol:?}");
        assert!(
            slow.sel_mb < fast.sel_mb,
            "{tol:?}: {} vs {}",
            slow.sel_mb,
            fast.sel_mb
        );
    }
}

/// Level 3, 30 steps of 20 nodes (so that the first steps lack details), every 4th step drawn at
/// 48×48 on the CPU.
fn probed_run(
    tol: Option<f64>,
    cpu: bool,
) -> (
    tetwave_client::progressive::RunReport,
    tetwave_client::render_probe::RenderSummary,
) {
    let cfg = RunConfig {
        steps: 30,
        per_step: 20,
        width: 48,
        height: 48,
        tol: tol.map(Tolerance::PercentOfHeight),
        ..RunConfig::default()
    };
    common::probed_run(3, &cfg, 4, cpu)
}

/// `--render-every` on the CPU: the sampled steps are every 4th and the last; with every detail
/// arrived, the simple run's leaf mesh is the full-resolution mesh, so its last image matches
/// the reference (up to the f32 positions), while the first, with few details, is far from it.
#[test]
fn render_probe_measures_image_error() {
    let (_, s) = probed_run(None, true);
    let steps: Vec<usize> = s.frames.iter().map(|f| f.step).collect();
    assert_eq!(steps, [0, 4, 8, 12, 16, 20, 24, 28, 29]);
    assert_eq!(s.renderer, "cpu-reference");
    let (first, last) = (&s.frames[0], s.frames.last().unwrap());
    assert!(last.psnr_db >= 60.0, "last frame {} dB", last.psnr_db);
    assert!(first.psnr_db < last.psnr_db - 10.0, "{first:?} vs {last:?}");
    assert!(first.tets < last.tets);
    assert_eq!(s.min_psnr_db, first.psnr_db);
    // a coarse tolerance keeps fewer tets and loses accuracy against the same reference
    let (r, coarse) = probed_run(Some(50.0), true);
    assert!(coarse.frames.last().unwrap().tets < last.tets);
    assert!(
        coarse.frames.last().unwrap().psnr_db < last.psnr_db,
        "{:?} {:?}",
        coarse.frames,
        last
    );
    assert!(r.final_same == Some(true));
}

/// Magnitude order ranks a node as selection would: a finest-level node, which arrives from a
/// block without a bound of its own, by its parent's, so it comes after its parent and never
/// ahead of the coarse levels.
#[test]
fn magnitude_order_ranks_finest_nodes_by_their_parents_bound() {
    use tetwave_protocol::node::INHERITED_BOUND;
    let (base, nodes) = detail_nodes(box5(3), wave);
    let forest = base.forest();
    let finest = forest.checked_finest_nodes_start().unwrap();
    let parent_bound = |id: u64| nodes[forest.parent(id).unwrap() as usize].subtree_max_abs;
    let mut decoded: Vec<_> = nodes
        .iter()
        .map(|n| {
            let mut n = n.clone();
            if n.id >= finest {
                n.subtree_max_abs = INHERITED_BOUND;
            }
            n
        })
        .collect();
    order_nodes(&mut decoded, ArrivalOrder::Magnitude, 0, forest);
    let rank: Vec<f32> = decoded
        .iter()
        .map(|n| match n.id >= finest {
            true => parent_bound(n.id),
            false => n.subtree_max_abs,
        })
        .collect();
    assert!(rank.windows(2).all(|w| w[0] >= w[1]), "largest first");
    let at: std::collections::HashMap<u64, usize> =
        decoded.iter().enumerate().map(|(i, n)| (n.id, i)).collect();
    for n in decoded.iter().filter(|n| n.id >= finest) {
        let p = forest.parent(n.id).unwrap();
        assert!(at[&p] < at[&n.id], "node {} before its parent", n.id);
    }
}
