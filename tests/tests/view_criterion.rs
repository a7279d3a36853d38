//! One refinement criterion for both sides: the server's view order and the client's default
//! (image) selection rank the nodes of a store identically for one view (both call
//! `tetwave_protocol::view`'s `ImageCriterion::node_weight`, the server on its reference samples),
//! under the `default` preset and under `auto` (`/v1/stream?tf=auto`: the preset fitted to the
//! manifest's histogram, which the server fits as the client does).

use tetwave_adaptive::select::{Mode, SelectParams, Selector};
use tetwave_adaptive::session::Session;
use tetwave_protocol::view::{Camera, Orbit, Tolerance, View, DEFAULT_IMAGE_EPS};
use tetwave_render::transfer::TransferFunction;
use tetwave_server::analysis::ErrorBound;
use tetwave_server::stream::{ServeConfig, Shared, ViewTf};
use tetwave_store::Store;

mod common;

#[test]
fn server_view_order_and_client_selection_rank_nodes_alike() {
    rank_alike(ViewTf::Default, "default");
}

#[test]
fn server_view_order_under_auto_ranks_nodes_as_a_client_drawing_auto() {
    rank_alike(ViewTf::Auto, "auto");
}

/// A harmonic store of `levels` levels at `bound` (`None`: lossless), and an orbit camera at
/// `distance` from its centre (close enough that part of the volume is outside the frustum),
/// drawing `size` pixels.
fn store_and_camera(
    levels: u8,
    bound: Option<&str>,
    distance: f64,
    size: (u32, u32),
) -> (tempfile::TempDir, std::path::PathBuf, Store, Camera) {
    let (d, dir) = common::harmonic_store_with(levels, |o| {
        o.max_error = bound.map(|b| ErrorBound::parse(b).unwrap())
    });
    let store = Store::open(&dir).unwrap();
    let (lo, hi) = store.base.bounds();
    let cam = Orbit {
        target: glam::DVec3::from(lo).lerp(glam::DVec3::from(hi), 0.5),
        distance,
        azimuth: 30.0,
        elevation: 20.0,
        fov: 40.0,
    }
    .camera(size.0, size.1);
    (d, dir, store, cam)
}

/// The server's view order for a session asking `tf` against a client drawing `spec`.
fn rank_alike(tf: ViewTf, spec: &str) {
    let (_d, dir, store, cam) = store_and_camera(3, None, 1.2, (320, 240));
    let nodes = store.read_nodes(0, store.manifest.counts.nodes).unwrap();
    let value_range = store.manifest.value_range;
    let vp = cam.view_params(0.0);

    let server = Shared::open(&dir, ServeConfig::default())
        .unwrap()
        .view_priorities(&vp, tf)
        .unwrap();

    // the client: every node held and refined (complete mode), then each node's split priority
    // under the image criterion of its transfer function and a zero tolerance
    let mut params = SelectParams::new(Tolerance::Pixels(0.0), value_range);
    let tf = TransferFunction::for_manifest(spec, &store.manifest).unwrap();
    assert_eq!(tf.name, spec, "the store's manifest has a histogram to fit");
    let img = tf.image_criterion(value_range, &store.base, DEFAULT_IMAGE_EPS);
    params.image = Some(img);
    let mut session = Session::new(store.base.clone(), params.clone()).unwrap();
    session.insert(&nodes).unwrap();
    session.converge(&cam, Mode::Complete).unwrap();
    let (mesh, buf) = (session.mesh(), session.buffer());
    let sel = Selector::new(params);
    let view = View::new(&Camera::from_view_params(&vp), Tolerance::Pixels(0.0));
    let (mut visible, mut hidden) = (Vec::new(), Vec::new());
    for (id, &s) in server.iter().enumerate() {
        let slot = mesh.slot_of(id as u64).expect("every node is in the mesh");
        let n = mesh.red_node(slot).unwrap();
        match sel.want_split(mesh, buf, &view, Mode::Interactive, &n) {
            Some(c) => visible.push((id, s as f64, c)),
            None => hidden.push((id, s as f64)),
        }
    }
    assert!(
        visible.len() > 10 && !hidden.is_empty(),
        "{} visible, {} hidden",
        visible.len(),
        hidden.len()
    );
    // where the client sees a node, the server gives it the same error (its weight is floored at
    // 10⁻³ so that subtrees that cannot change the image are still sent: compare above the floor)
    let mut compared = 0;
    for &(id, s, c) in &visible {
        let t = tetwave_protocol::LatticeTet::from_id(&store.forest(), id as u64);
        let (centre, r) = tetwave_protocol::view::tet_sphere(
            t.v.map(|w| glam::DVec3::from_array(store.base.position(t.base, &w))),
        );
        let unweighted = view.error_px(centre.as_dvec3(), 2.0 * r as f64);
        if c >= 1e-3 * unweighted {
            assert!(
                (s - c).abs() <= 1e-5 * c.abs(),
                "node {id}: server {s}, client {c}"
            );
            compared += 1;
        }
    }
    assert!(compared > 10);
    // ranked by the server, the client's priorities come in the same order
    let mut ranked: Vec<_> = visible.iter().filter(|v| v.2 > 0.0).collect();
    ranked.sort_by(|a, b| b.1.total_cmp(&a.1));
    for w in ranked.windows(2) {
        assert!(
            w[1].2 <= w[0].2 * (1.0 + 1e-5),
            "nodes {} and {} ranked apart",
            w[0].0,
            w[1].0
        );
    }
    // what the client culls, the server sends after everything the client sees
    let min_visible = visible.iter().map(|v| v.1).fold(f64::INFINITY, f64::min);
    for &(id, s) in &hidden {
        assert!(
            s < min_visible,
            "hidden node {id} ({s}) before a visible one ({min_visible})"
        );
    }
}

/// Below the levels whose values the server synthesizes, view order ranks a node by an enclosure
/// of its values (`server/src/stream/walk.rs`): never below the exact rank, so a node the client
/// reads is never sent later than the exact weights would send it. Lossless and at a 1 % bound
/// (quantized details), on a store and under a view where part of the volume is culled.
#[test]
fn the_enclosure_below_the_coarse_levels_never_ranks_a_node_lower() {
    for bound in [None, Some("1%")] {
        let (_d, dir, _, cam) = store_and_camera(5, bound, 1.5, (320, 240));
        let vp = cam.view_params(2.0);
        let exact = Shared::open(&dir, ServeConfig::default()).unwrap();
        for coarse_nodes in [0, 60] {
            let cfg = ServeConfig {
                coarse_nodes,
                ..ServeConfig::default()
            };
            let enclosed = Shared::open(&dir, cfg).unwrap();
            for tf in [ViewTf::Default, ViewTf::Auto] {
                let e = exact.view_priorities(&vp, tf).unwrap();
                let w = enclosed.view_priorities(&vp, tf).unwrap();
                let mut above = 0;
                for (id, (x, y)) in e.iter().zip(&w).enumerate() {
                    assert!(
                        *y >= x * (1.0 - 1e-5),
                        "{bound:?}, {coarse_nodes} coarse nodes, {tf:?}: node {id} ranked \
                         {y} under the enclosure, {x} exactly"
                    );
                    above += usize::from(*y > x * (1.0 + 1e-5));
                }
                // the enclosure is looser than the exact values somewhere (the test tests it)
                assert!(
                    above > 0,
                    "{bound:?}, {coarse_nodes}: no node ranked differently"
                );
            }
        }
    }
}

/// View order's walk holds every node a client converging on the view reads, and not the whole
/// store: a client given only the walk's nodes (a view whose tolerance leaves part of the volume
/// coarse, and part outside the frustum) has a final mesh for that view, equal to the one of a
/// client given every node. Lossless and quantized stores, under both transfer functions.
#[test]
fn a_client_given_only_the_walk_s_nodes_converges_on_its_view() {
    use tetwave_adaptive::select::Tolerance as ClientTol;
    for bound in [None, Some("0.1%")] {
        let (_d, dir, store, cam) = store_and_camera(5, bound, 1.3, (256, 256));
        let all = store.read_nodes(0, store.manifest.counts.nodes).unwrap();
        let tol = 2.0;
        let vp = cam.view_params(tol);
        for coarse_nodes in [
            0,
            tetwave_server::stream::ServeConfig::default().coarse_nodes,
        ] {
            let cfg = ServeConfig {
                coarse_nodes,
                ..ServeConfig::default()
            };
            let shared = Shared::open(&dir, cfg).unwrap();
            for (tf, spec) in [(ViewTf::Default, "default"), (ViewTf::Auto, "auto")] {
                let walk = shared.view_walk(&vp, tf).unwrap();
                let mut params =
                    SelectParams::new(ClientTol::Pixels(tol), store.manifest.value_range);
                let f = TransferFunction::for_manifest(spec, &store.manifest).unwrap();
                params.image = Some(f.image_criterion(
                    store.manifest.value_range,
                    &store.base,
                    DEFAULT_IMAGE_EPS,
                ));
                let leaves_of = |nodes: &[tetwave_protocol::DetailNode]| {
                    let mut s = Session::new(store.base.clone(), params.clone()).unwrap();
                    s.insert(nodes).unwrap();
                    s.converge(&cam, Mode::Interactive).unwrap();
                    (s.view_complete(), s.mesh().leaf_count())
                };
                let mut ids = walk.clone();
                ids.sort_unstable();
                ids.dedup();
                assert_eq!(ids.len(), walk.len(), "the walk hands out each node once");
                let given: Vec<_> = ids.iter().map(|&i| all[i as usize].clone()).collect();
                let (complete, leaves) = leaves_of(&given);
                let (_, every) = leaves_of(&all);
                let case = format!("{bound:?}, {coarse_nodes} coarse nodes, {spec}");
                assert!(
                    complete,
                    "{case}: the walk's nodes leave the view unfinished"
                );
                assert_eq!(leaves, every, "{case}");
                assert!(
                    walk.len() < all.len() / 2,
                    "{case}: the walk holds {} of {} nodes",
                    walk.len(),
                    all.len()
                );
            }
        }
    }
}
