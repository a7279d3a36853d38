//! Test data shared by the selection and progressive tests: the thesis' 30³ box in 5 tets, a smooth
//! test field on it, and detail nodes from the protocol's reference analysis.
#![allow(dead_code)]

use tetwave_protocol::shapes;
use tetwave_protocol::testing::unsampled_base;
use tetwave_protocol::BaseMesh;

pub use tetwave_protocol::testing::detail_nodes;

/// The box `[0, 30]³` (the thesis' HARMONIC box) in 5 positive tets.
pub fn box5(levels: u8) -> BaseMesh {
    unsampled_base(levels, shapes::box5([0.0; 3], [30.0; 3]))
}

/// A smooth separable wave on `[0, 30]³`, `sin(πx/15) · cos(πy/15) · sin(πz/30)`, values in
/// `[−1, 1]`. Not the `synthetic:harmonic` dataset (`tetwave_protocol::fields::harmonic`): these
/// tests' figures (e.g. that the first frame of a progressive run is its worst) are measured on
/// this field.
pub fn wave(p: [f64; 3]) -> f32 {
    let s = std::f64::consts::PI / 15.0;
    ((s * p[0]).sin() * (s * p[1]).cos() * (0.5 * s * p[2]).sin()) as f32
}

/// The level-`levels` [`box5`] hierarchy of `f` with every detail node delivered: the base-level
/// adaptive mesh, the buffer holding every node, and the base mesh.
pub fn loaded(
    levels: u8,
    f: impl Fn([f64; 3]) -> f32,
) -> (
    tetwave_adaptive::mesh::AdaptiveMesh,
    tetwave_adaptive::detail_buffer::DetailBuffer,
    BaseMesh,
) {
    use tetwave_adaptive::detail_buffer::{Arrivals, DetailBuffer};
    use tetwave_adaptive::mesh::AdaptiveMesh;
    let (base, nodes) = detail_nodes(box5(levels), f);
    let mut mesh = AdaptiveMesh::new(&base).unwrap();
    let mut buf = DetailBuffer::new(base.forest(), base.vertex_keys());
    let mut arr = Arrivals::default();
    for n in &nodes {
        buf.insert(n, &mut arr).unwrap();
    }
    mesh.apply_arrivals(&buf, &arr);
    (mesh, buf, base)
}

/// The progressive experiment on the level-`levels` [`wave`] hierarchy (nodes in level order) with
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
    use tetwave_adaptive::mesh::AdaptiveMesh;
    use tetwave_client::progressive::{order_nodes, run_progressive_with, ArrivalOrder};
    use tetwave_client::render_probe::RenderProbe;
    use tetwave_protocol::view::Camera;
    use tetwave_render::render_mesh::RenderMesh;
    use tetwave_render::transfer::TransferFunction;
    let (base, mut nodes) = detail_nodes(box5(levels), wave);
    order_nodes(&mut nodes, ArrivalOrder::Level, 1, base.forest());
    let values = tetwave_protocol::synthesis::synthesize_all(
        &base,
        &base.vertex_keys(),
        nodes.iter().cloned(),
    )
    .unwrap();
    let range = [-1.0, 1.0];
    let empty: Vec<u8> = nodes.iter().map(|d| d.empty_children).collect();
    let full = RenderMesh::uniform_level(&base, &values, &empty, base.levels);
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
