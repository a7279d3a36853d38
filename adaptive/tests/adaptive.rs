//! Adaptive mesh + detail buffer against whole-hierarchy synthesis: conformity after every operation,
//! exact values, order independence, prediction fallback and in-place correction.

use proptest::prelude::*;
use std::collections::HashMap;
use std::time::Instant;
use tetwave_adaptive::detail_buffer::{Arrivals, DetailBuffer, Inserted};
use tetwave_adaptive::mesh::{AdaptiveMesh, MeshError, VertexPrediction};
use tetwave_protocol::order::{shuffle, splitmix};
use tetwave_protocol::shapes;
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_protocol::testing::{detail_nodes, unsampled_base};
use tetwave_protocol::wavelet::{
    predict, predict_at_centre, predict_on_edge, predict_on_face, synthesize, Predictor,
};
use tetwave_protocol::{BaseMesh, DetailNode, TetId, VertexKeys};

// ------------------------------------------------------------------ fixtures

/// The unit box in 5 tets.
fn box5(levels: u8) -> BaseMesh {
    unsampled_base(levels, shapes::box5([0.0; 3], [1.0; 3]))
}

/// The unit box in 6 Kuhn tets around the diagonal 0–7: `box6` with its tets reordered and the
/// vertices of three of them permuted evenly (so they stay positive), so the base tets' vertex
/// orders are deliberately mixed.
fn kuhn6(levels: u8) -> BaseMesh {
    let (positions, tets) = shapes::box6([0.0; 3], [1.0; 3]);
    // (tet of box6, its vertices in this order)
    let mixed = [
        (0, [0, 1, 2, 3]),
        (1, [2, 0, 1, 3]),
        (4, [0, 1, 2, 3]),
        (5, [3, 2, 1, 0]),
        (3, [0, 1, 2, 3]),
        (2, [3, 2, 1, 0]),
    ];
    let tets = mixed.iter().map(|&(t, v)| v.map(|i| tets[t][i])).collect();
    unsampled_base(levels, (positions, tets))
}

/// [`kuhn6`] with the axes predictor (SZ3's interpolation along the grid's axes).
fn kuhn6_axes(levels: u8) -> BaseMesh {
    let mut b = kuhn6(levels);
    b.predictor = Predictor::Axes;
    b
}

/// The unit box's corner tet at 000 (corners 0, 1, 2, 4).
fn corner_tet(levels: u8) -> BaseMesh {
    let c = shapes::box_corners([0.0; 3], [1.0; 3]);
    unsampled_base(levels, (vec![c[0], c[1], c[2], c[4]], vec![[0, 1, 2, 3]]))
}

/// One tet, with a skewed shape.
fn single(levels: u8) -> BaseMesh {
    let positions = vec![
        [0.0, 0.0, 0.0],
        [2.0, 0.1, 0.0],
        [0.3, 1.5, 0.2],
        [0.1, 0.4, 1.7],
    ];
    let mut tets = vec![[0, 1, 2, 3]];
    shapes::orient_positive(&positions, &mut tets);
    unsampled_base(levels, (positions, tets))
}

fn field(p: [f64; 3]) -> f32 {
    let (x, y, z) = (p[0], p[1], p[2]);
    // offset keeps values in [1.5, 5]: predictions within a factor 2 of the value, details exact
    (3.0 + (3.0 * x).sin() * (2.0 * y).cos() + z * z * x + 0.3 * (5.0 * z * y).sin()) as f32
}

/// The hierarchy of `base` with `field` sampled and analysed by the reference analysis
/// ([`detail_nodes`]), the synthesized value of every vertex key, and (when `empty_seed` is nonzero)
/// pseudo-random `empty_children` bits.
struct Data {
    base: BaseMesh,
    keys: VertexKeys,
    nodes: Vec<DetailNode>,
    reference: Vec<f32>,
}

fn make_data(base: BaseMesh, empty_seed: u64) -> Data {
    let (base, mut nodes) = detail_nodes(base, field);
    if empty_seed != 0 {
        let mut rng = empty_seed;
        for n in &mut nodes {
            rng = splitmix(rng);
            if matches!(rng % 5, 0) {
                n.empty_children = (rng >> 8) as u8 & (rng >> 16) as u8;
            }
        }
    }
    let keys = base.vertex_keys();
    let reference = synthesize_all(&base, &keys, nodes.iter().cloned()).unwrap();
    Data {
        base,
        keys,
        nodes,
        reference,
    }
}

/// The value the mesh must hold for `slot` given what the buffer has: synthesis with d = 0 for
/// missing coefficients, from the points its prediction reads (memoized in `memo`). Also says
/// whether every coefficient it depends on has arrived.
fn expected(
    mesh: &AdaptiveMesh,
    buf: &DetailBuffer,
    base: &BaseMesh,
    slot: u32,
    memo: &mut HashMap<u32, (f32, bool)>,
) -> (f32, bool) {
    if let Some(&r) = memo.get(&slot) {
        return r;
    }
    let mut all = true;
    let mut val = |s: u32, memo: &mut HashMap<u32, (f32, bool)>| {
        let (v, a) = expected(mesh, buf, base, s, memo);
        all &= a;
        v
    };
    let prediction = match mesh.vertex_prediction(slot) {
        VertexPrediction::Base => {
            let r = (base.values[mesh.vertex_key(slot) as usize], true);
            memo.insert(slot, r);
            return r;
        }
        VertexPrediction::Linear { ends } => predict(val(ends[0], memo), val(ends[1], memo)),
        VertexPrediction::Edge { near, mid, far } => {
            predict_on_edge(val(near, memo), val(mid, memo), val(far, memo))
        }
        VertexPrediction::Face { a, b, opp, j, k } => predict_on_face(
            val(a, memo),
            val(b, memo),
            val(opp, memo),
            val(j, memo),
            val(k, memo),
        ),
        VertexPrediction::Centre { mids, corners } => {
            predict_at_centre(mids.map(|s| val(s, memo)), corners.map(|s| val(s, memo)))
        }
    };
    let d = buf.coeff(mesh.vertex_key(slot));
    let r = (synthesize(d.unwrap_or(0.0), prediction), all && d.is_some());
    memo.insert(slot, r);
    r
}

/// With the axes predictor: every vertex value whole-hierarchy synthesis gives when the nodes
/// `buf` does not hold have zero coefficients.
fn axes_expected(data: &Data, buf: &DetailBuffer) -> Vec<f32> {
    let held = data.nodes.iter().map(|n| {
        let mut n = n.clone();
        if buf.meta(n.id).is_none() {
            n.coeffs.fill(0.0);
        }
        n
    });
    synthesize_all(&data.base, &data.keys, held).unwrap()
}

fn check_values(mesh: &AdaptiveMesh, buf: &DetailBuffer, data: &Data) {
    if data.base.predictor == Predictor::Axes {
        let want = axes_expected(data, buf);
        for s in mesh.vertex_slots() {
            let k = mesh.vertex_key(s) as usize;
            assert_eq!(mesh.vertex_value(s).to_bits(), want[k].to_bits(), "key {k}");
        }
        return;
    }
    let mut memo = HashMap::new();
    for s in mesh.vertex_slots() {
        let (want, complete) = expected(mesh, buf, &data.base, s, &mut memo);
        let have = mesh.vertex_value(s);
        assert_eq!(have.to_bits(), want.to_bits(), "slot {s}");
        if complete {
            assert_eq!(
                have.to_bits(),
                data.reference[mesh.vertex_key(s) as usize].to_bits(),
                "slot {s} key {}",
                mesh.vertex_key(s)
            );
        }
    }
}

/// Refines every leaf whose node is usable until nothing changes.
fn refine_all_usable(mesh: &mut AdaptiveMesh, buf: &DetailBuffer) -> usize {
    let levels = mesh.forest().levels;
    let mut total = 0;
    loop {
        let mut changed = 0;
        for id in mesh.leaf_ids() {
            if mesh.forest().level(id) < levels && buf.is_usable(id) && mesh.is_leaf(id) {
                mesh.refine(id, buf).unwrap();
                changed += 1;
            }
        }
        total += changed;
        if changed == 0 {
            return total;
        }
    }
}

fn assert_uniform_finest(mesh: &AdaptiveMesh, data: &Data) {
    let forest = data.base.forest();
    let leaves = forest.leaves() as usize;
    assert_eq!(mesh.leaf_count(), leaves);
    let tets = mesh.leaf_tets();
    assert_eq!(tets.len(), leaves);
    assert!(tets.iter().all(|t| !t.green));
    assert_eq!(mesh.vertex_count() as u64, data.keys.vertex_count());
    for s in mesh.vertex_slots() {
        assert_eq!(
            mesh.vertex_value(s).to_bits(),
            data.reference[mesh.vertex_key(s) as usize].to_bits()
        );
    }
}

// ------------------------------------------------------------------ tests

#[test]
fn helper_round_trips_samples() {
    for base in [box5(3), kuhn6(2), single(3)] {
        let data = make_data(base, 0);
        let mut f = vec![0f32; data.reference.len()];
        for (e, _) in data.keys.entities() {
            data.keys.for_each_in(e, |k, t, w| {
                f[k as usize] = field(data.base.position(t, &w))
            });
        }
        assert_eq!(f, data.reference);
    }
}

#[derive(Clone, Copy, PartialEq)]
enum Order {
    Level,
    Random,
    ReversedWithinLevel,
    Duplicated,
}

fn deliver_and_refine(data: &Data, order: Order) -> (AdaptiveMesh, DetailBuffer) {
    let forest = data.base.forest();
    let mut buf = DetailBuffer::new(forest, data.keys.clone());
    let mut mesh = AdaptiveMesh::new(&data.base).unwrap();
    let mut list: Vec<&DetailNode> = data.nodes.iter().collect();
    match order {
        Order::Level => {}
        Order::Random => shuffle(&mut list, 0xfeed),
        Order::ReversedWithinLevel => {
            list.sort_by_key(|n| (forest.level(n.id), std::cmp::Reverse(n.id)));
        }
        Order::Duplicated => {
            let mut d = Vec::with_capacity(list.len() * 2);
            for (i, n) in list.iter().enumerate() {
                d.push(*n);
                d.push(list[i / 2]);
            }
            list = d;
        }
    }
    let mut arr = Arrivals::default();
    let chunk = if order == Order::Random {
        list.len() / 7 + 1
    } else {
        list.len()
    };
    let mut dups = 0;
    for part in list.chunks(chunk) {
        for n in part {
            if buf.insert(n, &mut arr).unwrap() == Inserted::Duplicate {
                dups += 1;
            }
        }
        mesh.apply_arrivals(&buf, &arr);
        mesh.refresh_values(&buf);
        arr.clear();
        // interleave refinement with delivery for the random order
        refine_all_usable(&mut mesh, &buf);
    }
    assert_eq!(buf.duplicates(), dups);
    assert_eq!(buf.nodes_held(), forest.nodes());
    assert_eq!(buf.nodes_pending(), 0);
    (mesh, buf)
}

#[test]
fn order_independence_level3() {
    for base in [box5(3), kuhn6(3), single(3), kuhn6_axes(3)] {
        let data = make_data(base, 0);
        for order in [
            Order::Level,
            Order::Random,
            Order::ReversedWithinLevel,
            Order::Duplicated,
        ] {
            let (mesh, _) = deliver_and_refine(&data, order);
            mesh.check_conformity().unwrap();
            assert_uniform_finest(&mesh, &data);
        }
    }
}

/// The thesis-size case: box5 at level 5 → 163,840 leaves, every value exact.
#[test]
fn order_independence_box5_level5() {
    let t0 = Instant::now();
    let data = make_data(box5(5), 0);
    let t_data = t0.elapsed();
    assert_eq!(data.nodes.len(), 23_405);
    for order in [
        Order::Level,
        Order::Random,
        Order::ReversedWithinLevel,
        Order::Duplicated,
    ] {
        let t = Instant::now();
        let (mesh, _) = deliver_and_refine(&data, order);
        let t_refine = t.elapsed();
        let t = Instant::now();
        mesh.check_conformity().unwrap();
        let t_check = t.elapsed();
        assert_eq!(mesh.leaf_count(), 163_840);
        assert_uniform_finest(&mesh, &data);
        eprintln!(
            "level 5: data {t_data:?}, deliver+refine {t_refine:?}, conformity check {t_check:?}, {} bytes",
            mesh.bytes_held()
        );
        if order == Order::Level {
            // tear down to the base and build up again, timing the leaf tets created + removed
            let (mut mesh, buf) = (
                mesh,
                DetailBuffer::new(data.base.forest(), data.keys.clone()),
            );
            let mut full = DetailBuffer::new(data.base.forest(), data.keys.clone());
            let mut arr = Arrivals::default();
            for n in &data.nodes {
                full.insert(n, &mut arr).unwrap();
            }
            let t = Instant::now();
            let mut moved = 0usize;
            for _ in 0..5 {
                let before = mesh.leaf_count();
                let c = mesh.coarsenable_ids();
                assert_eq!(mesh.coarsen_batch(&c, &buf).unwrap(), c.len());
                moved += before + mesh.leaf_count();
            }
            assert_eq!(mesh.leaf_count(), 5);
            let t_down = t.elapsed();
            let t = Instant::now();
            refine_all_usable(&mut mesh, &full);
            let t_up = t.elapsed();
            moved += 163_840 * 8 / 7;
            assert_eq!(mesh.leaf_count(), 163_840);
            eprintln!(
                "level 5 coarsen to base {t_down:?}, refine back {t_up:?}: {:.2} M leaf tets created+removed/s",
                moved as f64 / (t_down + t_up).as_secs_f64() / 1e6
            );
        }
    }
}

/// With the axes predictor a vertex's value reads coefficients owned far from it: while nodes
/// are missing, every present vertex holds what whole-hierarchy synthesis gives with the missing
/// nodes' coefficients taken as 0 (a different code path: the passes in order, not the client's
/// memoized recursion by key), and the complete set gives the server's values.
#[test]
fn axes_values_follow_arrivals_in_any_order() {
    let data = make_data(kuhn6_axes(3), 0);
    let forest = data.base.forest();
    let mut list: Vec<&DetailNode> = data.nodes.iter().collect();
    shuffle(&mut list, 0xa4e5);
    let mut buf = DetailBuffer::new(forest, data.keys.clone());
    let mut mesh = AdaptiveMesh::new(&data.base).unwrap();
    let mut arr = Arrivals::default();
    let mut partial_differs = false;
    for part in list.chunks(list.len() / 5 + 1) {
        for n in part {
            buf.insert(n, &mut arr).unwrap();
        }
        mesh.apply_arrivals(&buf, &arr);
        mesh.refresh_values(&buf);
        arr.clear();
        refine_all_usable(&mut mesh, &buf);
        check_values(&mesh, &buf, &data);
        partial_differs |= mesh
            .vertex_slots()
            .any(|s| mesh.vertex_value(s) != data.reference[mesh.vertex_key(s) as usize]);
        mesh.check_conformity().unwrap();
    }
    // the test could fail: values were approximate on the way
    assert!(partial_differs);
    assert_uniform_finest(&mesh, &data);
}

/// Every present vertex's slot and value bits.
fn value_bits(mesh: &AdaptiveMesh) -> Vec<(u32, u32)> {
    mesh.vertex_slots()
        .map(|s| (s, mesh.vertex_value(s).to_bits()))
        .collect()
}

/// The box5 hierarchy of 3 levels with no node held yet, base tet 0 refined (its midpoints linear
/// predictions): the data, the empty buffer, the mesh and an empty arrival record.
fn tet0_refined_without_nodes() -> (Data, DetailBuffer, AdaptiveMesh, Arrivals) {
    let data = make_data(box5(3), 0);
    let buf = DetailBuffer::new(data.base.forest(), data.keys.clone());
    let mut mesh = AdaptiveMesh::new(&data.base).unwrap();
    mesh.refine(0, &buf).unwrap();
    (data, buf, mesh, Arrivals::default())
}

/// A node whose details are all zero changes no present value: `apply_arrivals` reports none, so
/// a converged image criterion has nothing to look at again.
#[test]
fn a_zero_detail_node_changes_no_value() {
    let (data, mut buf, mut mesh, mut arr) = tet0_refined_without_nodes();
    let before = value_bits(&mesh);
    let mut zero = data.nodes[0].clone();
    zero.coeffs.iter_mut().for_each(|c| *c = 0.0);
    buf.insert(&zero, &mut arr).unwrap();
    assert_eq!(arr.keys.len(), 6, "node 0 owns the 6 present midpoints");
    assert_eq!(mesh.apply_arrivals(&buf, &arr), 0);
    assert_eq!(mesh.refresh_values(&buf), 0);
    for (s, bits) in before {
        assert_eq!(mesh.vertex_value(s).to_bits(), bits);
    }
}

#[test]
fn fallback_prediction_then_correction() {
    // base tet 0 refined with no node at all: its midpoints are linear predictions
    let (data, mut buf, mut mesh, mut arr) = tet0_refined_without_nodes();
    let forest = data.base.forest();
    mesh.check_conformity().unwrap();
    let lt = mesh.lattice_of(0);
    let mids: Vec<u32> = (0..6)
        .map(|e| {
            mesh.slot_of_key(data.keys.key(lt.base, &lt.edge_midpoint(e)))
                .unwrap()
        })
        .collect();
    for &s in &mids {
        let [u, v] = mesh.vertex_ends(s).unwrap();
        assert_eq!(
            mesh.vertex_value(s),
            predict(mesh.vertex_value(u), mesh.vertex_value(v))
        );
    }
    check_values(&mesh, &buf, &data);
    // a node owning nothing present changes nothing
    let before = value_bits(&mesh);
    buf.insert(&data.nodes[3], &mut arr).unwrap();
    assert_eq!(mesh.apply_arrivals(&buf, &arr), 0);
    arr.clear();
    // node 0 owns all 6 midpoints of tet 0: exactly those change, to the reference values
    buf.insert(&data.nodes[0], &mut arr).unwrap();
    assert_eq!(arr.keys.len(), 6);
    let reported = mesh.apply_arrivals(&buf, &arr);
    arr.clear();
    let mut n_changed = 0;
    for (s, bits) in before {
        let now = mesh.vertex_value(s);
        if mids.contains(&s) {
            assert_eq!(
                now.to_bits(),
                data.reference[mesh.vertex_key(s) as usize].to_bits()
            );
            n_changed += (now.to_bits() != bits) as usize;
        } else {
            assert_eq!(now.to_bits(), bits);
        }
    }
    assert!(
        n_changed >= 4,
        "the field is not linear: most midpoints move"
    );
    assert_eq!(
        reported, n_changed,
        "apply_arrivals counts the values that moved"
    );
    mesh.check_conformity().unwrap();

    // dependants: refine a child of tet 1 before tet 1's node arrives; the child's midpoints are
    // predicted from tet 1's predicted midpoints, and are corrected with them
    mesh.refine(1, &buf).unwrap();
    let c = forest.child(1, 4);
    if !mesh.is_leaf(c) {
        mesh.coarsen(c, &buf).ok();
    }
    if mesh.is_leaf(c) {
        mesh.refine(c, &buf).unwrap();
    }
    mesh.check_conformity().unwrap();
    check_values(&mesh, &buf, &data);
    let before = value_bits(&mesh);
    buf.insert(&data.nodes[1], &mut arr).unwrap();
    let owned: Vec<u32> = arr
        .keys
        .iter()
        .filter_map(|&k| mesh.slot_of_key(k))
        .collect();
    assert!(!owned.is_empty());
    let changed = mesh.apply_arrivals(&buf, &arr);
    mesh.refresh_values(&buf);
    arr.clear();
    assert!(changed > owned.len(), "finer vertices depend on node 1's");
    check_values(&mesh, &buf, &data);
    // whatever changed is either owned by node 1 or (transitively) predicted from one of those
    let mut n_changed = 0;
    for (s, bits) in before {
        if mesh.vertex_value(s).to_bits() != bits {
            n_changed += 1;
            assert!(owned.contains(&s) || mesh.vertex_level(s) >= 2);
        }
    }
    assert!(n_changed <= changed);
    // everything delivered: all present values are the reference
    for n in &data.nodes {
        buf.insert(n, &mut arr).unwrap();
    }
    mesh.apply_arrivals(&buf, &arr);
    mesh.refresh_values(&buf);
    for s in mesh.vertex_slots() {
        assert_eq!(
            mesh.vertex_value(s).to_bits(),
            data.reference[mesh.vertex_key(s) as usize].to_bits()
        );
    }
}

/// The box5 hierarchy of `levels` levels with every node held and applied to a base-level mesh.
fn everything_held(levels: u8) -> (Data, DetailBuffer, AdaptiveMesh) {
    let data = make_data(box5(levels), 0);
    let mut buf = DetailBuffer::new(data.base.forest(), data.keys.clone());
    let mut arr = Arrivals::default();
    for n in &data.nodes {
        buf.insert(n, &mut arr).unwrap();
    }
    let mut mesh = AdaptiveMesh::new(&data.base).unwrap();
    mesh.apply_arrivals(&buf, &arr);
    mesh.refresh_values(&buf);
    (data, buf, mesh)
}

#[test]
fn coarsen_everything_back() {
    let (data, buf, mut mesh) = everything_held(3);
    let forest = data.base.forest();
    refine_all_usable(&mut mesh, &buf);
    assert_eq!(mesh.leaf_count(), 5 * 512);
    // in a uniform mesh an interior tet cannot be coarsened alone: its neighbours keep its edges
    // split (a corner tet can: its boundary edges belong to it only)
    let (mut ok, mut refused) = (0, 0);
    for id in mesh.coarsenable_ids() {
        match mesh.coarsen(id, &buf) {
            Ok(()) => ok += 1,
            Err(MeshError::Forced(t)) => {
                assert_eq!(t, id);
                refused += 1
            }
            Err(e) => panic!("{e}"),
        }
    }
    mesh.check_conformity().unwrap();
    assert!(refused > ok && ok > 0, "{ok} coarsened, {refused} refused");
    refine_all_usable(&mut mesh, &buf);
    assert_eq!(mesh.leaf_count(), 5 * 512);
    // a whole level at a time works, down to the base
    for level in (0..3u8).rev() {
        let c = mesh.coarsenable_ids();
        assert!(c.iter().all(|&t| forest.level(t) == level));
        assert_eq!(mesh.coarsen_batch(&c, &buf).unwrap(), c.len());
        mesh.check_conformity().unwrap();
        assert_eq!(mesh.leaf_count(), 5 << (3 * level));
        check_values(&mesh, &buf, &data);
    }
    assert_eq!(mesh.leaf_count(), 5);
    assert_eq!(mesh.vertex_count(), 8);
    assert_eq!(mesh.leaf_tets().len(), 5);
}

#[test]
fn empty_tets_are_not_drawn_or_refined() {
    let mut base = box5(2);
    base.empty[2] = true;
    let data = make_data(base, 0);
    let forest = data.base.forest();
    let buf = DetailBuffer::new(forest, data.keys.clone());
    let mut mesh = AdaptiveMesh::new(&data.base).unwrap();
    assert_eq!(mesh.refine(2, &buf), Err(MeshError::Empty(2)));
    mesh.refine(4, &buf).unwrap();
    mesh.check_conformity().unwrap();
    let all = mesh.leaf_tets();
    let drawable = mesh.drawable_leaf_tets();
    assert!(drawable.len() < all.len());
    assert!(drawable.iter().all(|t| t.hier != 2 && !t.empty));
    assert_eq!(
        all.iter().filter(|t| t.hier == 2).count(),
        all.len() - drawable.len()
    );
}

// ------------------------------------------------------------------ property test

#[derive(Debug, Clone, Copy)]
enum Op {
    Deliver(u8),
    Refine(u32),
    Coarsen(u32),
    CoarsenBatch(u32),
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        2 => (1u8..40).prop_map(Op::Deliver),
        5 => any::<u32>().prop_map(Op::Refine),
        2 => any::<u32>().prop_map(Op::Coarsen),
        1 => any::<u32>().prop_map(Op::CoarsenBatch),
    ]
}

/// What a sequence exercised (to check that the random sequences are not vacuous).
#[derive(Debug, Default)]
struct Stats {
    green_pieces: usize,
    closure_refines: usize,
    coarsened: usize,
    refused: usize,
    corrected: usize,
}

fn run_sequence(kind: u8, levels: u8, seed: u64, empties: bool, ops: &[Op]) -> Stats {
    let mut stats = Stats::default();
    let base = match kind {
        0 => box5(levels),
        1 => kuhn6(levels),
        2 => single(levels),
        _ => kuhn6_axes(levels),
    };
    let data = make_data(base, if empties { seed | 1 } else { 0 });
    let forest = data.base.forest();
    let mut buf = DetailBuffer::new(forest, data.keys.clone());
    let mut mesh = AdaptiveMesh::new(&data.base).unwrap();
    // the same operations without the refusal records (they must only save work)
    let mut twin = AdaptiveMesh::new(&data.base).unwrap();
    let mut order: Vec<usize> = (0..data.nodes.len()).collect();
    // some duplicates, then a random arrival order
    for i in 0..data.nodes.len() / 4 {
        order.push(i * 3 % data.nodes.len());
    }
    shuffle(&mut order, seed);
    let mut next = 0;
    let mut arr = Arrivals::default();
    mesh.check_conformity().unwrap();
    for &o in ops {
        match o {
            Op::Deliver(n) => {
                for _ in 0..n {
                    if next < order.len() {
                        buf.insert(&data.nodes[order[next]], &mut arr).unwrap();
                        next += 1;
                    }
                }
                stats.corrected += mesh.apply_arrivals(&buf, &arr);
                mesh.refresh_values(&buf);
                twin.apply_arrivals(&buf, &arr);
                arr.clear();
            }
            Op::Refine(pick) => {
                let cands: Vec<TetId> = mesh
                    .leaf_ids()
                    .into_iter()
                    .filter(|&t| forest.level(t) < levels && !mesh.is_empty_tet(t))
                    .collect();
                if !cands.is_empty() {
                    let t = cands[pick as usize % cands.len()];
                    let leaves = mesh.leaf_count();
                    mesh.refine(t, &buf).unwrap();
                    twin.refine(t, &buf).unwrap();
                    assert!(mesh.is_refined(t));
                    stats.closure_refines += (mesh.leaf_count() - leaves - 7) / 7;
                }
            }
            Op::Coarsen(pick) => {
                let cands = mesh.coarsenable_ids();
                if !cands.is_empty() {
                    let t = cands[pick as usize % cands.len()];
                    let leaves = mesh.leaf_count();
                    let verts = mesh.vertex_count();
                    let r = mesh.coarsen(t, &buf);
                    assert_eq!(r, twin.coarsen(t, &buf));
                    match r {
                        Ok(()) => {
                            assert!(mesh.is_leaf(t));
                            stats.coarsened += 1;
                        }
                        Err(MeshError::Forced(_)) => {
                            stats.refused += 1;
                            assert_eq!(mesh.leaf_count(), leaves);
                            assert_eq!(mesh.vertex_count(), verts);
                        }
                        Err(e) => panic!("{e}"),
                    }
                }
            }
            Op::CoarsenBatch(bits) => {
                // a pseudo-random subset of the coarsenable tets
                let cands: Vec<TetId> = mesh
                    .coarsenable_ids()
                    .into_iter()
                    .enumerate()
                    .filter(|(i, _)| bits.rotate_left(*i as u32) & 3 != 0)
                    .map(|(_, t)| t)
                    .collect();
                let leaves = mesh.leaf_count();
                // twice: the second batch meets the records of the first one's refusals
                for _ in 0..2 {
                    let done = mesh.coarsen_batch(&cands, &buf).unwrap();
                    twin.clear_refusal_records();
                    assert_eq!(done, twin.coarsen_batch(&cands, &buf).unwrap());
                    assert!(done <= cands.len());
                    assert!(mesh.leaf_count() <= leaves);
                }
            }
        }
        assert_eq!(mesh.leaf_ids(), twin.leaf_ids(), "after {o:?}");
        assert_eq!(mesh.op_counts(), twin.op_counts(), "after {o:?}");
        if let Err(e) = mesh.check_conformity() {
            panic!("after {o:?}: {e}");
        }
        check_values(&mesh, &buf, &data);
        let all = mesh.leaf_tets();
        let drawable = mesh.drawable_leaf_tets();
        assert_eq!(all.iter().filter(|t| !t.empty).count(), drawable.len());
        stats.green_pieces += all.iter().filter(|t| t.green).count();
    }
    stats
}

proptest! {
    #![proptest_config(ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::with_cases(1000)
    })]

    #[test]
    fn random_sequences_stay_conforming(
        kind in 0u8..4,
        levels in 1u8..=3,
        seed in any::<u64>(),
        empties in proptest::bool::weighted(0.2),
        ops in proptest::collection::vec(op(), 1..=20),
    ) {
        run_sequence(kind, levels, seed, empties, &ops);
    }
}

/// A deeper, longer deterministic sequence at level 4 (still quick).
#[test]
fn long_sequence_level4() {
    let mut rng = 7u64;
    let ops: Vec<Op> = (0..300)
        .map(|_| {
            rng = splitmix(rng);
            match rng % 9 {
                0 | 1 => Op::Deliver((rng >> 8) as u8 % 200),
                2..=6 => Op::Refine((rng >> 16) as u32),
                7 => Op::CoarsenBatch((rng >> 16) as u32),
                _ => Op::Coarsen((rng >> 16) as u32),
            }
        })
        .collect();
    let s = run_sequence(0, 4, 99, false, &ops);
    eprintln!("{s:?}");
    assert!(s.green_pieces > 0 && s.closure_refines > 0 && s.coarsened > 0 && s.refused > 0);
    assert!(s.corrected > 0);
}

/// A hierarchy whose ids do not fit the mesh's 40-bit node ids (one tet, 14 levels: about 5e12
/// tets) is refused with an error, not a panic or a wrapped id.
#[test]
fn too_many_tets_is_an_error() {
    let base = corner_tet(14);
    base.validate().expect("a valid base mesh");
    let total = base.forest().total_tets();
    assert!(total >= tetwave_adaptive::mesh::MAX_TETS);
    match AdaptiveMesh::new(&base) {
        Err(MeshError::TooManyTets(n)) => assert_eq!(n, total),
        other => panic!("expected TooManyTets, got {:?}", other.map(|_| ())),
    }
}

/// Node ids past 32 bits (one tet, 11 levels: about 9.8e9 tets) survive the mesh's packed nodes:
/// refining the last child down to the finest level finds every node by its id, and the mesh
/// conforms and coarsens back to the base tet.
#[test]
fn ids_past_32_bits_round_trip() {
    let base = single(11);
    base.validate().expect("a valid base mesh");
    let forest = base.forest();
    assert!(forest.total_tets() > u32::MAX as u64);
    let buf = DetailBuffer::new(forest, base.vertex_keys());
    let mut mesh = AdaptiveMesh::new(&base).expect("fits the mesh");
    let mut path = vec![0 as TetId];
    for _ in 0..11 {
        let t = *path.last().unwrap();
        mesh.refine(t, &buf).expect("refine");
        path.push(forest.child(t, 7));
    }
    let deepest = *path.last().unwrap();
    assert!(deepest > u32::MAX as u64, "id {deepest} fits 32 bits");
    mesh.check_conformity().expect("conforming");
    assert!(mesh.is_leaf(deepest) && mesh.slot_of(deepest).is_some());
    let mut leaf_ids = Vec::new();
    mesh.for_each_leaf_tet(|t| leaf_ids.push(t.hier));
    assert!(leaf_ids.contains(&deepest));
    // the closure refined neighbours too: coarsen every candidate, batch by batch, back to the base
    for _ in 0..64 {
        let ids = mesh.coarsenable_ids();
        if ids.is_empty() {
            break;
        }
        assert!(mesh.coarsen_batch(&ids, &buf).expect("coarsen") > 0);
        mesh.check_conformity().expect("conforming");
    }
    assert!(mesh.is_leaf(0));
}

/// The leaf mesh merged for drawing in motion ([`AdaptiveMesh::coarse_leaf_tets`]): on a mesh
/// refined in one corner only (red leaves of several levels and green pieces), every budget gives
/// positively oriented tets over the mesh's own vertices that fill the same volume, at most the
/// budget's count when the base mesh fits it, and the leaf mesh itself when that fits.
#[test]
fn coarse_leaf_tets_fill_the_domain_within_the_budget() {
    let (data, buf, mut mesh) = everything_held(4);
    let forest = data.base.forest();
    // refine near the corner 000, deeper the closer
    for round in 0..4 {
        for id in mesh.leaf_ids() {
            if !mesh.is_leaf(id) || forest.level(id) >= forest.levels {
                continue;
            }
            let lt = mesh.lattice_of(id);
            let c = lt.v.map(|w| data.base.position(lt.base, &w));
            let centre: f64 = (0..3)
                .map(|a| (0..4).map(|k| c[k][a]).sum::<f64>() / 4.0)
                .sum();
            if centre < 1.2 / (round + 1) as f64 {
                mesh.refine(id, &buf).unwrap();
            }
        }
    }
    let all = mesh.drawable_leaf_tets();
    assert!(all.iter().any(|t| t.green), "the closure made green pieces");
    let p = mesh.positions();
    let volume = |t: &tetwave_adaptive::mesh::LeafTet| {
        let q = t.v.map(|s| p[s as usize].map(|x| x as f64));
        tetwave_protocol::base::signed_volume(q[0], q[1], q[2], q[3])
    };
    let whole: f64 = all.iter().map(volume).sum();
    assert!((whole - 1.0).abs() < 1e-9, "{whole}");
    for most in [all.len(), all.len() / 2, 200, 40, 5, 1] {
        let coarse = mesh.coarse_leaf_tets(most);
        if most >= all.len() {
            assert_eq!(coarse, all);
        }
        if most >= 5 {
            assert!(coarse.len() <= most, "{} tets for {most}", coarse.len());
        }
        let v: f64 = coarse.iter().map(volume).sum();
        assert!((v - 1.0).abs() < 1e-9, "{most}: volume {v}");
        for t in &coarse {
            assert!(volume(t) > 0.0, "{most}: {t:?}");
        }
        eprintln!("budget {most}: {} of {} tets", coarse.len(), all.len());
    }
}
