//! Selective refinement: frustum culling, data-aware error, budgets (conforming frames, same fixed
//! point as an unbudgeted run), modes and the client session.

use glam::DVec3;
use tetwave_adaptive::detail_buffer::{Arrivals, DetailBuffer};
use tetwave_adaptive::mesh::AdaptiveMesh;
use tetwave_adaptive::select::{
    bounding_sphere, Budget, CoarsenRef, Mode, SelectParams, Selector, Tolerance, View,
};
use tetwave_adaptive::session::Session;
use tetwave_protocol::order::splitmix;
use tetwave_protocol::view::{Camera, Orbit};
use tetwave_protocol::TetId;

mod common;
use common::{box5, detail_nodes, loaded, wave};

fn cam(az_deg: f64, dist: f64) -> Camera {
    Orbit {
        target: DVec3::splat(15.0),
        distance: dist,
        azimuth: az_deg,
        elevation: 10.0,
        fov: 45.0,
    }
    .camera(256, 256)
}

/// Frames of `s` for `c` in `mode` until the selector is satisfied (at most 10,000).
fn settle(s: &mut Session, c: &Camera, mode: Mode) {
    let mut frames = 0;
    while !s.is_converged() {
        s.frame(c, mode).unwrap();
        frames += 1;
        assert!(frames < 10_000, "no final mesh");
    }
}

fn sorted_leaves(m: &AdaptiveMesh) -> Vec<TetId> {
    let mut v = m.leaf_ids();
    v.sort_unstable();
    v
}

#[test]
fn tolerance_parse() {
    assert_eq!(
        Tolerance::parse("12.5%").unwrap(),
        Tolerance::PercentOfHeight(12.5)
    );
    assert_eq!(Tolerance::parse("7px").unwrap(), Tolerance::Pixels(7.0));
    assert_eq!(Tolerance::parse("7").unwrap(), Tolerance::Pixels(7.0));
    assert!(Tolerance::parse("x%").is_err());
    assert_eq!(Tolerance::PercentOfHeight(20.0).pixels(512), 102.4);
}

/// Tets outside the view end coarse: every refined tet whose sphere is outside the frustum is only
/// there for conformity (coarsening it alone is refused), and culling removes most of the mesh.
#[test]
fn frustum_outside_stays_coarse() {
    let (mut mesh, buf, _) = loaded(4, wave);
    // close to one face, looking at it: most of the box is behind or beside the view
    let c = Orbit {
        target: DVec3::new(15.0, 15.0, 15.0),
        distance: 20.0,
        azimuth: 0.0,
        elevation: 0.0,
        fov: 30.0,
    }
    .camera(256, 256);
    let mut p = SelectParams::new(Tolerance::Pixels(2.0), [-1.0, 1.0]);
    let mut sel = Selector::new(p.clone());
    let st = sel
        .converge(&mut mesh, &buf, &c, Mode::Progressive)
        .unwrap();
    assert!(st.converged);
    mesh.check_conformity().unwrap();
    let view = View::new(&c, p.tol);
    let mut outside_refined = 0;
    for slot in 0..mesh.node_slot_len() {
        let Some(n) = mesh.red_node(slot) else {
            continue;
        };
        let (ctr, r) = bounding_sphere(&mesh, &mesh.node_verts(slot));
        if !view.sphere_visible(ctr, r) && !n.leaf && n.children_leaves {
            outside_refined += 1;
            let mut m2 = mesh.clone();
            assert!(
                m2.coarsen(n.id, &buf).is_err(),
                "tet {} is outside the view, mergeable, and still refined",
                n.id
            );
        }
    }
    let with = mesh.leaf_count();
    p.frustum = false;
    let (mut all, buf2, _) = loaded(4, wave);
    Selector::new(p)
        .converge(&mut all, &buf2, &c, Mode::Progressive)
        .unwrap();
    assert!(
        with * 2 < all.leaf_count(),
        "culling: {with} leaves vs {} without",
        all.leaf_count()
    );
    let _ = outside_refined;
}

/// A field constant in half of the box: with the data-aware error that half stays coarse, the other
/// is refined as the geometric error asks.
#[test]
fn data_aware_keeps_flat_half_coarse() {
    let f = |p: [f64; 3]| {
        if p[0] <= 15.0 {
            0.5
        } else {
            0.5 + wave(p) * ((p[0] - 15.0) / 15.0) as f32
        }
    };
    let (mut mesh, buf, _) = loaded(4, f);
    let c = cam(30.0, 60.0);
    let mut p = SelectParams::new(Tolerance::Pixels(4.0), [-0.5, 1.5]);
    p.data_aware = Some(0.01);
    Selector::new(p.clone())
        .converge(&mut mesh, &buf, &c, Mode::Progressive)
        .unwrap();
    mesh.check_conformity().unwrap();
    let levels = |m: &AdaptiveMesh| {
        let (mut flat, mut busy) = (0usize, 0usize);
        for t in m.leaf_tets() {
            let x =
                t.v.iter()
                    .map(|&s| m.vertex_position(s)[0])
                    .fold(0f32, f32::max);
            let xmin =
                t.v.iter()
                    .map(|&s| m.vertex_position(s)[0])
                    .fold(99f32, f32::min);
            if x < 13.0 {
                flat += 1;
            } else if xmin > 17.0 {
                busy += 1;
            }
        }
        (flat, busy)
    };
    let (flat, busy) = levels(&mesh);
    assert!(
        flat * 10 < busy,
        "flat half: {flat} tets, busy half: {busy}"
    );
    // without the data term both halves refine alike
    p.data_aware = None;
    let (mut geo, buf2, _) = loaded(4, f);
    Selector::new(p)
        .converge(&mut geo, &buf2, &c, Mode::Progressive)
        .unwrap();
    let (gflat, gbusy) = levels(&geo);
    assert!(gflat * 3 > gbusy, "geometric: {gflat} vs {gbusy}");
}

/// With an operation budget every frame ends conforming and repeated frames reach the mesh of an
/// unbudgeted run; also when the camera moves in between, and with the grandparent rule.
#[test]
fn budget_frames_conform_and_converge() {
    for coarsen_ref in [CoarsenRef::Parent, CoarsenRef::Grandparent] {
        let (mut mesh, buf, _) = loaded(4, wave);
        let mut p = SelectParams::new(Tolerance::PercentOfHeight(5.0), [-1.0, 1.0]);
        p.coarsen_ref = coarsen_ref;
        p.interactive = Budget::ops(40);
        p.progressive = Budget::ops(40);
        let mut sel = Selector::new(p.clone());
        let mut frames = 0;
        for (az, rest) in [(0.0, false), (25.0, false), (90.0, true)] {
            let c = cam(az, 40.0);
            loop {
                let st = sel.frame(&mut mesh, &buf, &c, Mode::Progressive).unwrap();
                frames += 1;
                assert!(st.splits + st.merge_attempts <= 40, "{st:?}");
                mesh.check_conformity().unwrap();
                sel.verify_remembered(&mesh, &buf, &c, Mode::Progressive)
                    .unwrap();
                if st.converged || (!rest && frames % 7 == 0) {
                    break;
                }
                assert!(frames < 5000);
            }
        }
        let c = cam(90.0, 40.0);
        let (mut reference, buf2, _) = loaded(4, wave);
        p.progressive = Budget::UNLIMITED;
        Selector::new(p)
            .converge(&mut reference, &buf2, &c, Mode::Progressive)
            .unwrap();
        assert_eq!(sorted_leaves(&mesh), sorted_leaves(&reference));
        assert!(frames > 3);
    }
}

/// A time budget cuts frames short and the carried work still converges.
#[test]
fn time_budget_carries_over() {
    let (mut mesh, buf, _) = loaded(4, wave);
    let mut p = SelectParams::new(Tolerance::Pixels(3.0), [-1.0, 1.0]);
    p.progressive = Budget::ms(0.5);
    let c = cam(10.0, 50.0);
    let mut sel = Selector::new(p.clone());
    let mut frames = 0;
    while !sel
        .frame(&mut mesh, &buf, &c, Mode::Progressive)
        .unwrap()
        .converged
    {
        frames += 1;
        assert!(frames < 100_000);
    }
    mesh.check_conformity().unwrap();
    assert!(frames > 1, "a 0.5 ms budget should take several frames");
    let (mut reference, buf2, _) = loaded(4, wave);
    Selector::new(p)
        .converge(&mut reference, &buf2, &c, Mode::Progressive)
        .unwrap();
    assert_eq!(sorted_leaves(&mesh), sorted_leaves(&reference));
    // converged and unchanged: the next frame returns at once, doing nothing
    let st = sel.frame(&mut mesh, &buf, &c, Mode::Progressive).unwrap();
    assert!(st.converged && st.scanned == 0);
}

/// Interactive frames obey the tight budget, progressive ones refine toward the tolerance, complete
/// mode shows everything that arrived (the uniform finest mesh once all has).
#[test]
fn modes() {
    let (mut mesh, buf, base) = loaded(3, wave);
    let mut p = SelectParams::new(Tolerance::PercentOfHeight(30.0), [-1.0, 1.0]);
    p.interactive = Budget::ops(5);
    p.progressive = Budget::ops(200);
    let mut sel = Selector::new(p.clone());
    let c = cam(0.0, 45.0);
    let st = sel.frame(&mut mesh, &buf, &c, Mode::Interactive).unwrap();
    assert!(st.splits + st.merge_attempts <= 5 && !st.converged);
    let mut n = 0;
    while !sel
        .frame(&mut mesh, &buf, &c, Mode::Progressive)
        .unwrap()
        .converged
    {
        n += 1;
        assert!(n < 1000);
    }
    let progressive = mesh.leaf_count();
    assert!(progressive < base.forest().leaves() as usize);
    while !sel
        .frame(&mut mesh, &buf, &c, Mode::Complete)
        .unwrap()
        .converged
    {}
    mesh.check_conformity().unwrap();
    assert_eq!(mesh.leaf_count(), base.forest().leaves() as usize);
    // back to the view-dependent mesh
    while !sel
        .frame(&mut mesh, &buf, &c, Mode::Progressive)
        .unwrap()
        .converged
    {}
    assert_eq!(mesh.leaf_count(), progressive);

    // complete mode with half of the nodes: exactly the usable ones are refined
    let (base, nodes) = detail_nodes(box5(3), wave);
    let mut m = AdaptiveMesh::new(&base).unwrap();
    let mut b = DetailBuffer::new(base.forest(), base.vertex_keys());
    let mut arr = Arrivals::default();
    for nd in nodes.iter().step_by(2) {
        b.insert(nd, &mut arr).unwrap();
    }
    m.apply_arrivals(&b, &arr);
    Selector::new(p)
        .converge(&mut m, &b, &c, Mode::Complete)
        .unwrap();
    m.check_conformity().unwrap();
    for nd in &nodes {
        if b.is_usable(nd.id) && !m.is_empty_tet(nd.id) {
            assert!(m.is_refined(nd.id), "usable {} not refined", nd.id);
        }
    }
}

/// A session takes nodes in chunks, in any order and with duplicates, and refines frame by frame
/// under its budget to the uniform finest level in complete mode; an invalid node is refused with
/// its id, the nodes before it still held.
#[test]
fn session_takes_chunks_and_settles() {
    let (base, mut nodes) = detail_nodes(box5(3), wave);
    let leaves = base.forest().leaves() as usize;
    let total = nodes.len();
    nodes.reverse();
    let p = SelectParams::new(Tolerance::PercentOfHeight(10.0), [-1.0, 1.0]);
    let mut s = Session::new(base, p).unwrap();
    let c = cam(0.0, 45.0);
    let mut dup = 0;
    for chunk in nodes.chunks(50) {
        let done = s.insert(chunk.iter().chain(&chunk[..1])).unwrap();
        dup += done.duplicates;
        s.frame(&c, Mode::Complete).unwrap();
        s.mesh().check_conformity().unwrap();
    }
    assert_eq!(dup, nodes.chunks(50).count());
    assert_eq!(s.progress(), (total as u64, total as u64));
    settle(&mut s, &c, Mode::Complete);
    assert_eq!(s.mesh().leaf_count(), leaves);
    let rm = s.leaf_mesh([-1.0, 1.0]);
    assert_eq!(rm.tets.len(), leaves);

    let (base, nodes) = detail_nodes(box5(2), wave);
    let mut s = Session::new(base, SelectParams::new(Tolerance::Pixels(1.0), [-1.0, 1.0])).unwrap();
    let mut bad = nodes[3].clone();
    bad.id = u64::MAX;
    let err = s
        .insert(nodes[..3].iter().chain([&bad]).chain(&nodes[3..]))
        .unwrap_err();
    assert_eq!(err.id, u64::MAX);
    assert_eq!(s.progress().0, 3);
}

/// A converged session stays converged when nodes of tets its mesh does not hold arrive (a stream
/// goes on sending what the view does not need: before, every such batch started the selector's
/// sweep again, and under a steady stream it never declared the mesh final); the node of a leaf it
/// holds makes it look again.
#[test]
fn nodes_below_the_leaves_leave_a_converged_session_converged() {
    let (base, nodes) = detail_nodes(box5(4), wave);
    let forest = base.forest();
    let (coarse, deep): (Vec<_>, Vec<_>) = nodes.into_iter().partition(|n| forest.level(n.id) < 2);
    let mut s = Session::new(base, SelectParams::new(Tolerance::Pixels(2.0), [-1.0, 1.0])).unwrap();
    s.insert(&coarse).unwrap();
    let c = cam(20.0, 45.0);
    settle(&mut s, &c, Mode::Progressive);
    let leaves = sorted_leaves(s.mesh());
    let (below, at_leaves): (Vec<_>, Vec<_>) = deep
        .into_iter()
        .partition(|n| s.mesh().slot_of(n.id).is_none());
    assert!(
        below.len() > 100 && !at_leaves.is_empty(),
        "{} {}",
        below.len(),
        at_leaves.len()
    );
    for chunk in below.chunks(64) {
        s.insert(chunk).unwrap();
        assert!(
            s.is_converged(),
            "nodes below the leaves un-converged the session"
        );
        assert!(s.frame(&c, Mode::Progressive).unwrap().converged);
    }
    assert_eq!(sorted_leaves(s.mesh()), leaves);
    s.insert(&at_leaves[..1]).unwrap();
    assert!(!s.is_converged(), "a held leaf's node is looked at");
}

/// The motion mesh of `Session::leaf_meshes` holds only its own vertices, and draws the same tets
/// with the same corners and values as the coarsened leaf tets over every vertex slot.
#[test]
fn the_motion_mesh_holds_only_its_own_vertices() {
    let (base, nodes) = detail_nodes(box5(3), wave);
    let mut s = Session::new(base, SelectParams::new(Tolerance::Pixels(0.0), [-1.0, 1.0])).unwrap();
    s.insert(&nodes).unwrap();
    let c = cam(0.0, 45.0);
    settle(&mut s, &c, Mode::Complete);
    let (leaf, motion) = s.leaf_meshes([-1.0, 1.0], 100);
    let motion = motion.expect("2,560 leaves are more than 100");
    assert_eq!(leaf.tets.len(), s.mesh().leaf_count());
    assert!(!motion.tets.is_empty() && motion.tets.len() <= 100);
    let nbase = s.base().positions.len();
    assert!(motion.positions.len() <= nbase + 4 * motion.tets.len());
    assert!(motion.positions.len() < leaf.positions.len() / 4);
    // the base vertices keep the mesh's box: the same unit of length for the transfer function
    assert_eq!(motion.diagonal(), leaf.diagonal());
    let coarse = s.mesh().coarse_leaf_tets(100);
    let whole = tetwave_adaptive::draw::tets_mesh(s.mesh(), &coarse, [-1.0, 1.0], None, false);
    assert_eq!(whole.tets.len(), motion.tets.len());
    for (a, b) in whole.tets.iter().zip(&motion.tets) {
        for k in 0..4 {
            let (i, j) = (a[k] as usize, b[k] as usize);
            assert_eq!(whole.positions[i], motion.positions[j]);
            assert_eq!(whole.values[i].to_bits(), motion.values[j].to_bits());
        }
    }
}

/// A uniform draw in `[0, 1)` from the state `s`.
fn unit(s: &mut u64) -> f64 {
    *s = splitmix(*s);
    (*s >> 11) as f64 / (1u64 << 53) as f64
}

/// The incremental selector (candidate list, motion certificates, arrivals by subtree) converges
/// to exactly the mesh of the full-scan reference, frame after frame: random arrival orders and
/// camera paths (small turns, jumps, zooms, other lenses, other modes), each criterion variant.
/// After every frame each status it remembers equals a fresh evaluation, priority included.
#[test]
fn incremental_equals_full_scan() {
    use tetwave_client::progressive::{order_nodes, ArrivalOrder};
    let (base, all_nodes) = detail_nodes(box5(4), wave);
    let variants: [(Tolerance, bool, Option<f32>, CoarsenRef); 5] = [
        (
            Tolerance::PercentOfHeight(12.5),
            true,
            None,
            CoarsenRef::Parent,
        ),
        (
            Tolerance::PercentOfHeight(6.0),
            true,
            None,
            CoarsenRef::Parent,
        ),
        (Tolerance::Pixels(20.0), false, None, CoarsenRef::Parent),
        (
            Tolerance::PercentOfHeight(8.0),
            true,
            Some(0.05),
            CoarsenRef::Parent,
        ),
        (
            Tolerance::PercentOfHeight(10.0),
            true,
            None,
            CoarsenRef::Grandparent,
        ),
    ];
    let (mut frames, mut remembered) = (0, 0);
    for (vi, &(tol, frustum, data_aware, coarsen_ref)) in variants.iter().enumerate() {
        for seed in 0..5u64 {
            let mut s = splitmix(seed * 31 + vi as u64 + 1);
            let mut nodes = all_nodes.clone();
            let order = if seed == 0 {
                ArrivalOrder::Level
            } else {
                ArrivalOrder::Random
            };
            order_nodes(&mut nodes, order, s, base.forest());
            let mut p = SelectParams::new(tol, [-1.0, 1.0]);
            p.frustum = frustum;
            p.data_aware = data_aware;
            p.coarsen_ref = coarsen_ref;
            p.interactive = Budget::UNLIMITED;
            p.progressive = Budget::UNLIMITED;
            let mut a = AdaptiveMesh::new(&base).unwrap();
            let mut b = AdaptiveMesh::new(&base).unwrap();
            let mut ba = DetailBuffer::new(base.forest(), base.vertex_keys());
            let mut bb = DetailBuffer::new(base.forest(), base.vertex_keys());
            let mut inc = Selector::new(p.clone());
            let mut full = Selector::full_scan(p.clone());
            let (mut az, mut el, mut dist, mut fovy) = (0.0f64, 10.0f64, 40.0f64, 45.0f64);
            let mut target = DVec3::splat(15.0);
            let mut next = 0;
            let mut arr = Arrivals::default();
            for step in 0..60 {
                // nodes arrive for a while
                if next < nodes.len() && step % 2 == 0 {
                    let end = (next + 150).min(nodes.len());
                    arr.clear();
                    for n in &nodes[next..end] {
                        ba.insert(n, &mut arr).unwrap();
                    }
                    a.apply_arrivals(&ba, &arr);
                    inc.notify_arrived(&a, &arr.nodes);
                    arr.clear();
                    for n in &nodes[next..end] {
                        bb.insert(n, &mut arr).unwrap();
                    }
                    b.apply_arrivals(&bb, &arr);
                    full.notify_arrivals();
                    next = end;
                }
                // the camera: mostly small turns (some about a point off the scene's centre, some
                // with a pan), sometimes a jump, a zoom or another lens
                let r = unit(&mut s);
                if r < 0.6 {
                    az += 3.0 * unit(&mut s);
                    el += unit(&mut s) - 0.5;
                    if unit(&mut s) < 0.3 {
                        let d = DVec3::new(unit(&mut s), unit(&mut s), unit(&mut s)) - 0.5;
                        target = (target + 4.0 * d).clamp(DVec3::splat(0.0), DVec3::splat(30.0));
                    }
                } else if r < 0.75 {
                    az = 360.0 * unit(&mut s);
                    el = 60.0 * unit(&mut s) - 30.0;
                } else if r < 0.9 {
                    dist = 20.0 + 40.0 * unit(&mut s);
                } else if r < 0.95 {
                    fovy = 30.0 + 30.0 * unit(&mut s);
                }
                let c = Orbit {
                    target,
                    distance: dist,
                    azimuth: az,
                    elevation: el,
                    fov: fovy,
                }
                .camera(256, 192);
                let mode = match step % 23 {
                    7 => Mode::Complete,
                    11 => Mode::Interactive,
                    _ => Mode::Progressive,
                };
                let sa = inc.converge(&mut a, &ba, &c, mode).unwrap();
                let sb = full.converge(&mut b, &bb, &c, mode).unwrap();
                assert!(sa.converged && sb.converged);
                // a remembered status (its priority computed again) is what evaluating gives
                remembered += inc
                    .verify_remembered(&a, &ba, &c, mode)
                    .unwrap_or_else(|e| panic!("variant {vi}, seed {seed}, step {step}: {e}"));
                assert_eq!(
                    sorted_leaves(&a),
                    sorted_leaves(&b),
                    "variant {vi}, seed {seed}, step {step}"
                );
                assert_eq!(a.op_counts(), b.op_counts());
                if step % 15 == 0 {
                    a.check_conformity().unwrap();
                }
                frames += 1;
            }
        }
    }
    assert_eq!(frames, 5 * 5 * 60);
    assert!(
        remembered > 10_000,
        "{remembered} remembered statuses compared"
    );
}

/// Previews first, then the store's nodes replacing them in random order (their bounds tighter,
/// their coefficients other), with data-aware selection and a moving camera, so that subtrees are
/// split, merged and split again around replacements: the incremental selector reaches the
/// reference's mesh after every frame, and both end with every leaf's value the same.
#[test]
fn incremental_equals_full_scan_through_previews() {
    use tetwave_client::progressive::{order_nodes, ArrivalOrder};
    use tetwave_protocol::DetailNode;
    let (base, all_nodes) = detail_nodes(box5(4), wave);
    let preview_end = base.forest().level_start(3);
    // previews with a looser bound than the store's, and (as `BlockCoder::for_preview` decodes
    // them) with none: inherited, so infinite under a preview parent
    let previews = |bound: fn(f32) -> f32| -> Vec<DetailNode> {
        all_nodes[..preview_end as usize]
            .iter()
            .map(|n| DetailNode {
                coeffs: n.coeffs.iter().map(|c| (c * 4.0).round() / 4.0).collect(),
                subtree_max_abs: bound(n.subtree_max_abs),
                ..n.clone()
            })
            .collect()
    };
    let loose: fn(f32) -> f32 = |b| 3.0 * b + 0.1;
    let inherited: fn(f32) -> f32 = |_| tetwave_protocol::node::INHERITED_BOUND;
    let mut frames = 0;
    for (seed, bound) in (0..4u64).zip([loose, inherited, loose, inherited]) {
        let previews = previews(bound);
        let mut s = splitmix(seed * 17 + 3);
        let mut nodes = all_nodes.clone();
        order_nodes(&mut nodes, ArrivalOrder::Random, s, base.forest());
        let mut p = SelectParams::new(Tolerance::PercentOfHeight(8.0), [-1.0, 1.0]);
        p.data_aware = Some(0.3);
        p.interactive = Budget::UNLIMITED;
        p.progressive = Budget::UNLIMITED;
        let mut inc = Session::with_selector(base.clone(), Selector::new(p.clone())).unwrap();
        let mut full = Session::with_selector(base.clone(), Selector::full_scan(p)).unwrap();
        for x in [&mut inc, &mut full] {
            x.insert_preview(&previews).unwrap();
        }
        let (mut az, mut dist) = (0.0f64, 40.0f64);
        let mut next = 0;
        for step in 0..40 {
            if step >= 6 && next < nodes.len() && step % 2 == 0 {
                let end = (next + 200).min(nodes.len());
                for x in [&mut inc, &mut full] {
                    x.insert(&nodes[next..end]).unwrap();
                }
                next = end;
            }
            // turns, and zooms out and in: merges, then splits again over the same slots
            if unit(&mut s) < 0.5 {
                az += 20.0 * unit(&mut s);
            } else {
                dist = if dist < 60.0 {
                    90.0
                } else {
                    25.0 + 10.0 * unit(&mut s)
                };
            }
            let c = Orbit {
                target: DVec3::splat(15.0),
                distance: dist,
                azimuth: az,
                elevation: 10.0,
                fov: 45.0,
            }
            .camera(256, 192);
            let sa = inc.converge(&c, Mode::Progressive).unwrap();
            let sb = full.converge(&c, Mode::Progressive).unwrap();
            assert!(sa.converged && sb.converged);
            assert_eq!(
                sorted_leaves(inc.mesh()),
                sorted_leaves(full.mesh()),
                "seed {seed}, step {step}"
            );
            frames += 1;
        }
        assert!(inc.is_complete(), "seed {seed}: {:?}", inc.progress());
        assert_eq!(inc.buffer().previews_held(), 0);
        let c = Orbit {
            target: DVec3::splat(15.0),
            distance: 25.0,
            azimuth: az,
            elevation: 10.0,
            fov: 45.0,
        }
        .camera(256, 192);
        inc.converge(&c, Mode::Complete).unwrap();
        full.converge(&c, Mode::Complete).unwrap();
        let values = |x: &Session| {
            let m = x.mesh();
            let mut v: Vec<(u64, u32)> = (0..m.vertex_count())
                .filter_map(|k| {
                    m.slot_of_key(k as u64)
                        .map(|s| (k as u64, m.vertex_value(s).to_bits()))
                })
                .collect();
            v.sort_unstable();
            v
        };
        assert_eq!(values(&inc), values(&full), "seed {seed}");
    }
    assert_eq!(frames, 4 * 40);
}

/// A selector that follows a mesh changed behind its back (refinements it did not ask for) still
/// reaches the reference mesh.
#[test]
fn incremental_sees_outside_changes() {
    let (mut a, buf, _) = loaded(4, wave);
    let mut b = a.clone();
    let p = SelectParams::new(Tolerance::PercentOfHeight(10.0), [-1.0, 1.0]);
    let mut inc = Selector::new(p.clone());
    let mut full = Selector::full_scan(p);
    for (i, az) in [0.0, 2.0, 4.0, 6.0].into_iter().enumerate() {
        let c = cam(az, 45.0);
        // refine a few leaves by hand in both meshes
        for m in [&mut a, &mut b] {
            let mut leaves = sorted_leaves(m);
            leaves.retain(|&t| !m.is_empty_tet(t) && m.forest().level(t) < 3);
            for &t in leaves.iter().skip(i).step_by(7).take(5) {
                m.refine(t, &buf).unwrap();
            }
        }
        inc.converge(&mut a, &buf, &c, Mode::Progressive).unwrap();
        full.converge(&mut b, &buf, &c, Mode::Progressive).unwrap();
        assert_eq!(sorted_leaves(&a), sorted_leaves(&b), "round {i}");
    }
}

/// The reference selector reads no mesh changes, so it trims the mesh's change log after every
/// frame instead of letting it grow to its bound (memory a `--full-scan` run would hold for
/// nothing); the cached selector trims what it has read.
#[test]
fn selectors_leave_the_change_log_trimmed() {
    for reference in [true, false] {
        let (mut mesh, buf, _) = loaded(3, wave);
        let mut p = SelectParams::new(Tolerance::Pixels(4.0), [-1.0, 1.0]);
        // a budget in operations, not time: every frame does some work however loaded the machine
        p.interactive = Budget::ops(500);
        let mut sel = if reference {
            Selector::full_scan(p)
        } else {
            Selector::new(p)
        };
        for (az, dist) in [(0.0, 60.0), (90.0, 30.0), (200.0, 22.0)] {
            let before = mesh.change_seq();
            sel.frame(&mut mesh, &buf, &cam(az, dist), Mode::Interactive)
                .unwrap();
            assert!(mesh.change_seq() > before, "frame at {az}° changed nothing");
            assert_eq!(mesh.changes_since(mesh.change_seq()), Some(&[][..]));
            assert!(
                mesh.changes_since(before).is_none(),
                "reference {reference}: the changes of the frame at {az}° are still logged"
            );
        }
    }
}
