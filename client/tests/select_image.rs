//! The image criterion (`--criterion image`) and the leaf budget (`--max-tets`): a subtree with
//! nothing to change is never refined, the budget is never exceeded, and a tolerance of 0 still
//! refines to every leaf.

use glam::DVec3;
use tetwave_client::select::{Mode, SelectParams, Selector, Tolerance};
use tetwave_protocol::view::{Camera, DEFAULT_IMAGE_EPS};
use tetwave_render::transfer::TransferFunction;

mod common;
use common::{loaded, wave};

fn cam(az: f64) -> Camera {
    Camera::orbit(DVec3::splat(15.0), 60.0, az, 20.0, 45.0, 256, 256)
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
        let c = Camera::orbit(
            DVec3::splat(15.0),
            25.0 + 5.0 * k as f64,
            30.0 * k as f64,
            10.0,
            45.0,
            256,
            256,
        );
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

/// Tolerance 0 (complete mode) with the image criterion still ends at every leaf.
#[test]
fn tolerance_zero_reaches_every_leaf() {
    let (mut mesh, buf, base) = loaded(3, wave);
    let mut sel = Selector::new(image_params(&base, [-1.0, 1.0]));
    sel.converge(&mut mesh, &buf, &cam(0.0), Mode::Complete)
        .unwrap();
    assert_eq!(
        mesh.leaf_count() as u64,
        base.tets.len() as u64 * 8u64.pow(3)
    );
}
