//! The image criterion (`--criterion image`) and the leaf budget (`--max-tets`): a subtree with
//! nothing to change is never refined, the budget is never exceeded, and a tolerance of 0 still
//! refines to every leaf.

use glam::DVec3;
use tetwave_adaptive::select::{Mode, SelectParams, Selector, Tolerance};
use tetwave_protocol::view::{Camera, Orbit, DEFAULT_IMAGE_EPS};
use tetwave_render::transfer::TransferFunction;

mod common;
use common::{loaded, wave};

fn cam(az: f64) -> Camera {
    Orbit {
        target: DVec3::splat(15.0),
        distance: 60.0,
        azimuth: az,
        elevation: 20.0,
        fov: 45.0,
    }
    .camera(256, 256)
}

fn image_params(base: &tetwave_protocol::BaseMesh, range: [f32; 2]) -> SelectParams {
    let mut p = SelectParams::new(Tolerance::Pixels(1.0), range);
    let tf = TransferFunction::preset("default").unwrap();
    p.image = Some(tf.image_criterion(range, base, DEFAULT_IMAGE_EPS));
    p
}

/// A linear field has no details and no curvature: under the image criterion nothing below the
/// base's children is split (the base tets' own bound is unknown), where the geometric criterion
/// refines thousands of tets.
#[test]
fn zero_detail_subtrees_are_never_refined() {
    let linear = |p: [f64; 3]| (p[0] / 30.0) as f32;
    let (mut mesh, buf, base) = loaded(4, linear);
    let mut sel = Selector::new(image_params(&base, [0.0, 1.0]));
    assert!(
        sel.converge(&mut mesh, &buf, &cam(30.0), Mode::Progressive)
            .unwrap()
            .converged
    );
    mesh.check_conformity().unwrap();
    for slot in 0..mesh.node_slot_len() {
        if let Some(n) = mesh.red_node(slot) {
            if !n.leaf {
                assert_eq!(mesh.forest().level(n.id), 0, "node {} refined", n.id);
            }
        }
    }
    let image_leaves = mesh.leaf_count();
    let (mut mesh, buf, _) = loaded(4, linear);
    let mut geo = Selector::new(SelectParams::new(Tolerance::Pixels(1.0), [0.0, 1.0]));
    geo.converge(&mut mesh, &buf, &cam(30.0), Mode::Progressive)
        .unwrap();
    assert!(
        mesh.leaf_count() > 20 * image_leaves,
        "{} vs {image_leaves}",
        mesh.leaf_count()
    );
}

/// A leaf budget is never exceeded, over cameras that move around the volume, and the frames say
/// when it binds; without the budget the same views want more.
#[test]
fn the_leaf_budget_is_never_exceeded() {
    let (mut mesh, buf, base) = loaded(4, wave);
    let mut p = image_params(&base, [-1.0, 1.0]);
    p.max_tets = Some(600);
    let mut sel = Selector::new(p.clone());
    let mut bound = 0;
    for k in 0..12 {
        let c = Orbit {
            target: DVec3::splat(15.0),
            distance: 25.0 + 5.0 * k as f64,
            azimuth: 30.0 * k as f64,
            elevation: 10.0,
            fov: 45.0,
        }
        .camera(256, 256);
        let st = sel
            .converge(&mut mesh, &buf, &c, Mode::Progressive)
            .unwrap();
        assert!(
            mesh.leaf_count() <= 600,
            "view {k}: {} leaves",
            mesh.leaf_count()
        );
        mesh.check_conformity().unwrap();
        bound += st.budget_bound as usize;
    }
    assert!(bound > 0, "the budget never bound");
    let (mut free, buf, _) = loaded(4, wave);
    p.max_tets = None;
    Selector::new(p)
        .converge(&mut free, &buf, &cam(0.0), Mode::Progressive)
        .unwrap();
    assert!(free.leaf_count() > 600);
}

/// A tolerance of 0 with the image criterion still ends at every leaf where the field changes
/// the image: by view (progressive mode, 0 px, no culling) on a field whose every subtree has
/// details, and in complete mode.
#[test]
fn tolerance_zero_reaches_every_leaf() {
    let all = common::box5(3).tets.len() as u64 * 8u64.pow(3);
    for mode in [Mode::Progressive, Mode::Complete] {
        let (mut mesh, buf, base) = loaded(3, wave);
        let mut p = image_params(&base, [-1.0, 1.0]);
        p.tol = Tolerance::Pixels(8.0);
        p.frustum = false;
        let mut sel = Selector::new(p);
        let st = sel.converge(&mut mesh, &buf, &cam(0.0), mode).unwrap();
        assert!(st.converged, "{mode:?}");
        assert_eq!(mesh.leaf_count() as u64, all, "{mode:?}");
        mesh.check_conformity().unwrap();
    }
}

/// A bump in one corner of an otherwise flat field: most of the volume has nothing to show.
fn bump(p: [f64; 3]) -> f32 {
    let d2 = (0..3).map(|k| (p[k] - 7.0).powi(2)).sum::<f64>();
    (-d2 / 18.0).exp() as f32
}

/// A session that says its view is complete (`Session::view_complete`) before every node has
/// arrived holds the mesh it holds once every node has arrived: the leaves whose own nodes were
/// missing stayed unsplit under their ancestors' bounds, which cover them. Over random arrival
/// orders (by view, 2 px, image criterion); and with exactly the nodes the final mesh reads
/// (its refined nodes, and its leaves' own nodes where the parent's bound does not settle them)
/// it says so without the rest.
#[test]
fn view_complete_before_every_node_is_final() {
    use tetwave_adaptive::session::Session;
    let (base, nodes) = common::detail_nodes(common::box5(4), bump);
    let c = cam(40.0);
    let session = || {
        let mut p = image_params(&base, [0.0, 1.0]);
        p.tol = Tolerance::Pixels(2.0);
        Session::new(base.clone(), p).unwrap()
    };
    let sorted_leaves = |s: &Session| {
        let mut v = s.mesh().leaf_ids();
        v.sort_unstable();
        v
    };
    let mut full = session();
    full.insert(&nodes).unwrap();
    full.converge(&c, Mode::Progressive).unwrap();
    assert!(full.view_complete());
    let reference = sorted_leaves(&full);

    // the nodes the final mesh reads
    let f = base.forest();
    let refined = |id| full.mesh().red_node_of(id).is_some_and(|n| !n.leaf);
    let settled = |id| {
        full.mesh().red_node_of(id).is_some_and(|n| {
            n.leaf
                && full
                    .selector()
                    .stays_unsplit_without_node(full.mesh(), full.buffer(), &n)
        })
    };
    let (read, rest): (Vec<_>, Vec<_>) = nodes
        .iter()
        .cloned()
        .partition(|n| f.parent(n.id).is_none_or(refined) && !settled(n.id));
    let settled_leaves = nodes.iter().filter(|n| settled(n.id)).count();
    assert!(
        settled_leaves > 100,
        "{settled_leaves} leaves settled by their parent's bound"
    );
    let mut s = session();
    s.insert(&read).unwrap();
    s.converge(&c, Mode::Progressive).unwrap();
    assert!(s.view_complete(), "{} of {} nodes", read.len(), nodes.len());
    assert_eq!(sorted_leaves(&s), reference);
    s.insert(&rest).unwrap();
    s.converge(&c, Mode::Progressive).unwrap();
    assert_eq!(sorted_leaves(&s), reference);

    for seed in 0..6u64 {
        let mut order = nodes.clone();
        tetwave_protocol::order::shuffle(&mut order, seed);
        let mut s = session();
        for chunk in order.chunks(64) {
            s.insert(chunk).unwrap();
            s.converge(&c, Mode::Progressive).unwrap();
            if s.view_complete() {
                assert_eq!(sorted_leaves(&s), reference, "seed {seed}");
                s.mesh().check_conformity().unwrap();
            }
        }
        assert!(s.view_complete());
    }
}
