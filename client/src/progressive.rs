//! The progressive client loop without a network: detail nodes arrive in batches, the camera moves,
//! selective refinement runs under a budget. [`run_progressive`] is the thesis' experiment (§6.4,
//! Tables 2–3: 312 steps of +1000 nodes and a 0.05 rad turn about the vertical axis); `tetwave-bench
//! progressive` prints its rows. The buffer, mesh and selector are a [`Session`]'s.

use crate::render_probe::{RenderProbe, RenderSummary};
use glam::DVec3;
use serde::Serialize;
use std::time::{Duration, Instant};
use tetwave_adaptive::mesh::{AdaptiveMesh, MeshError};
use tetwave_adaptive::select::{Budget, CoarsenRef, Mode, SelectParams, Selector, Tolerance};
use tetwave_adaptive::session::{NodeRejected, Session};
use tetwave_protocol::node::resolved_bounds;
use tetwave_protocol::order::shuffle;
/// The seeded mixing behind [`order_nodes`]'s random order, re-exported for the client's tests.
use tetwave_protocol::view::{Camera, Orbit};
use tetwave_protocol::{BaseMesh, DetailNode, Forest, TetId};

/// Order in which the detail nodes arrive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ArrivalOrder {
    /// By id: coarse levels first (the thesis).
    Level,
    /// Shuffled (seeded): parents often arrive after their children.
    Random,
    /// Largest subtree max |detail| first (a finest-level node's is its parent's,
    /// [`tetwave_protocol::node::resolve_bound`]).
    Magnitude,
}

/// Puts `nodes` (of a hierarchy with `forest`'s ids) in arrival order `order`.
pub fn order_nodes(nodes: &mut [DetailNode], order: ArrivalOrder, seed: u64, forest: Forest) {
    match order {
        ArrivalOrder::Level => nodes.sort_by_key(|n| n.id),
        ArrivalOrder::Magnitude => {
            let bound: std::collections::HashMap<TetId, f32> = nodes
                .iter()
                .map(|n| n.id)
                .zip(resolved_bounds(forest, nodes))
                .collect();
            nodes.sort_by(|a, b| bound[&b.id].total_cmp(&bound[&a.id]).then(a.id.cmp(&b.id)));
        }
        ArrivalOrder::Random => {
            nodes.sort_by_key(|n| n.id);
            shuffle(nodes, seed);
        }
    }
}

/// One run of the experiment.
#[derive(Debug, Clone, PartialEq)]
pub struct RunConfig {
    pub steps: usize,
    pub per_step: usize,
    /// Radians per step about the vertical axis.
    pub rotate: f64,
    pub distance: f64,
    pub elevation_deg: f64,
    pub fovy_deg: f64,
    pub width: u32,
    pub height: u32,
    /// `None`: the thesis' simple selective refinement (everything that arrived, [`Mode::Complete`]).
    pub tol: Option<Tolerance>,
    pub coarsen_ref: CoarsenRef,
    pub frustum: bool,
    pub data_aware: Option<f32>,
    /// The image criterion ([`SelectParams::image`]); `None`: the screen-space error alone (the
    /// thesis' criterion, and this struct's default).
    pub image: Option<tetwave_protocol::view::ImageCriterion>,
    /// The leaf budget ([`SelectParams::max_tets`]); `None`: unbounded.
    pub max_tets: Option<usize>,
    /// Per-step time budget (ms); `None`: each step refines until converged.
    pub budget_ms: Option<f64>,
    /// Per-step operation budget; `None`: unlimited.
    pub budget_ops: Option<usize>,
    /// After the steps, keep running frames (camera at rest, progressive mode) until converged and
    /// compare with an unbudgeted convergence from the same state.
    pub settle: bool,
    /// Select with [`Selector::full_scan`]: every node scanned with the uncached criteria at every
    /// sweep, no per-slot caches (the memory floor of selection, and its slowest way).
    pub full_scan: bool,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            steps: 312,
            per_step: 1000,
            rotate: 0.05,
            distance: 30.0,
            elevation_deg: 0.0,
            fovy_deg: 45.0,
            width: 512,
            height: 512,
            tol: Some(Tolerance::PercentOfHeight(20.0)),
            coarsen_ref: CoarsenRef::Parent,
            frustum: true,
            data_aware: None,
            image: None,
            max_tets: None,
            budget_ms: None,
            budget_ops: None,
            settle: true,
            full_scan: false,
        }
    }
}

/// Figures of one run (thesis Table 2 columns and ours). Averages are over steps.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    pub tol: String,
    pub tol_px: Option<f64>,
    pub steps: usize,
    /// Leaf-mesh tets (red leaves + green pieces, drawable).
    pub avg_tets: f64,
    pub max_tets: usize,
    pub final_tets: usize,
    pub avg_leaves: f64,
    pub avg_vertices: f64,
    /// Leaf-mesh edges by Euler's formula on a box domain: `E = V + T + V_boundary − 3`.
    pub avg_edges: f64,
    /// Mesh + detail buffer bytes (capacities), average, in MB (10^6).
    pub mb: f64,
    pub mesh_mb: f64,
    /// Mesh bytes per hierarchy leaf at the end of the run.
    pub bytes_per_leaf: f64,
    /// Largest hierarchy leaf count of the run, and the mesh bytes at the end per such leaf (the
    /// arrays keep the capacity of the largest mesh).
    pub max_leaves: usize,
    pub bytes_per_max_leaf: f64,
    /// Mesh bytes at the end of the run by part ([`AdaptiveMesh::bytes_parts`]).
    pub mesh_parts: Vec<(&'static str, usize)>,
    /// Selector bytes at the end of the run by part ([`Selector::bytes_parts`]).
    pub sel_parts: Vec<(&'static str, usize)>,
    /// Mesh bytes over leaf-mesh tets (the `avg_tets` column), both averaged over the steps: the
    /// thesis' MB over its tets.
    pub avg_bytes_per_tet: f64,
    /// Selector bytes (caches, candidates, certificates; see `Selector::bytes_held`): average in
    /// MB, and per hierarchy leaf at the end of the run.
    pub sel_mb: f64,
    pub sel_bytes_per_leaf: f64,
    /// Selection + refinement per step.
    pub avg_refine_ms: f64,
    pub max_refine_ms: f64,
    /// Buffer inserts + in-place value correction per step.
    pub avg_arrive_ms: f64,
    pub max_arrive_ms: f64,
    /// Red splits and merges (closure ones included) over the run.
    pub splits: u64,
    pub merges: u64,
    /// Tets created + removed per second of refinement time (sweeps included): 9 per split or
    /// merge.
    pub tets_per_s: f64,
    /// The same per second spent inside the mesh's refine / coarsen calls only.
    pub op_tets_per_s: f64,
    /// Sweeps over the node array, over the run.
    pub sweeps: usize,
    /// Splits the selector asked for, merges it attempted and merges that held (the rest of
    /// [`Self::splits`] / [`Self::merges`] is the green closure's doing).
    pub sel_splits: usize,
    pub sel_merge_attempts: usize,
    /// Criteria evaluations by the selector (machine-independent work).
    pub sel_evals: u64,
    pub sel_merges: usize,
    /// Uniform finest-level leaves of the hierarchy.
    pub uniform_leaves: u64,
    /// Steps whose frame was cut by the budget (work carried over).
    pub cut_steps: usize,
    /// Frames needed after the last step to converge (camera at rest), when settling.
    pub settle_frames: Option<usize>,
    /// The settled mesh equals an unbudgeted convergence from the same state.
    pub final_same: Option<bool>,
    pub order: ArrivalOrder,
    pub budget_ms: Option<f64>,
    /// Sampled steps drawn and compared with the full-resolution reference (`--render-every`).
    pub render: Option<RenderSummary>,
    /// Frames per second of refinement + rendering, `1000 / (avg_refine_ms + render.avg_ms)`:
    /// the thesis' FPS column.
    pub fps: Option<f64>,
}

/// The orbit camera of step `step`.
pub fn step_camera(cfg: &RunConfig, center: DVec3, step: usize) -> Camera {
    Orbit {
        target: center,
        distance: cfg.distance,
        azimuth: (step as f64 * cfg.rotate).to_degrees(),
        elevation: cfg.elevation_deg,
        fov: cfg.fovy_deg,
    }
    .camera(cfg.width, cfg.height)
}

/// Leaf-mesh edge count by Euler's formula for a mesh of a ball whose boundary is the bounding box
/// of the base vertices: `V − E + F − T = 1`, `2F = 4T + F_b`, `F_b = 2V_b − 4`.
pub fn edges_on_box(mesh: &AdaptiveMesh, tets: usize) -> usize {
    let nb = mesh.vertex_keys().base_vertex_count() as u32;
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for s in 0..nb {
        let p = mesh.vertex_position(s);
        for i in 0..3 {
            lo[i] = lo[i].min(p[i]);
            hi[i] = hi[i].max(p[i]);
        }
    }
    let eps: [f32; 3] = std::array::from_fn(|i| (hi[i] - lo[i]) * 1e-6);
    let vb = mesh
        .vertex_slots()
        .filter(|&s| {
            let p = mesh.vertex_position(s);
            (0..3).any(|i| (p[i] - lo[i]).abs() <= eps[i] || (p[i] - hi[i]).abs() <= eps[i])
        })
        .count();
    (mesh.vertex_count() + tets + vb).saturating_sub(3)
}

fn select_params(cfg: &RunConfig, value_range: [f32; 2]) -> SelectParams {
    let mut p = SelectParams::new(
        cfg.tol.unwrap_or(Tolerance::PercentOfHeight(100.0)),
        value_range,
    );
    p.coarsen_ref = cfg.coarsen_ref;
    p.frustum = cfg.frustum;
    p.data_aware = cfg.data_aware;
    p.image = cfg.image.clone();
    p.max_tets = cfg.max_tets;
    let b = Budget {
        max_ops: cfg.budget_ops.unwrap_or(usize::MAX),
        max_time: cfg
            .budget_ms
            .map(|ms| Duration::from_secs_f64(ms.max(0.0) / 1000.0)),
    };
    p.interactive = b;
    p.progressive = b;
    p
}

fn sorted_leaves(mesh: &AdaptiveMesh) -> Vec<TetId> {
    let mut v = mesh.leaf_ids();
    v.sort_unstable();
    v
}

/// Why a progressive run stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Mesh(#[from] MeshError),
    /// A detail node of the run is invalid (a corrupt store): the run stops instead of dropping it.
    #[error(transparent)]
    Node(#[from] NodeRejected),
}

/// Runs the experiment on `base` with `nodes` already in arrival order (see [`RunConfig`]).
pub fn run_progressive(
    base: &BaseMesh,
    nodes: &[DetailNode],
    value_range: [f32; 2],
    cfg: &RunConfig,
    order: ArrivalOrder,
) -> Result<RunReport, RunError> {
    run_progressive_with(base, nodes, value_range, cfg, order, &mut |_, _, _| {})
}

/// [`run_progressive`], calling `observe(step, mesh, camera)` after each step's refinement and
/// outside its timings (`tetwave-bench progressive --render-every` draws there).
pub fn run_progressive_with(
    base: &BaseMesh,
    nodes: &[DetailNode],
    value_range: [f32; 2],
    cfg: &RunConfig,
    order: ArrivalOrder,
    observe: &mut dyn FnMut(usize, &AdaptiveMesh, &Camera),
) -> Result<RunReport, RunError> {
    let (lo, hi) = base.bounds();
    let center = DVec3::from(lo).lerp(DVec3::from(hi), 0.5);
    let params = select_params(cfg, value_range);
    let mut session = Session::with_selector(
        base.clone(),
        if cfg.full_scan {
            Selector::full_scan(params)
        } else {
            Selector::new(params)
        },
    )?;
    let mode = if cfg.tol.is_none() {
        Mode::Complete
    } else {
        Mode::Interactive
    };
    let budgeted = cfg.budget_ms.is_some() || cfg.budget_ops.is_some();
    let (mut sum_tets, mut sum_leaves, mut sum_v, mut sum_e, mut sum_b, mut sum_mb) =
        (0f64, 0f64, 0f64, 0f64, 0f64, 0f64);
    let (mut sum_sel, mut max_leaves) = (0f64, 0usize);
    let (mut max_tets, mut refine_total, mut refine_max) = (0usize, 0f64, 0f64);
    let (mut arrive_total, mut arrive_max) = (0f64, 0f64);
    let mut cut_steps = 0;
    let (mut sweeps, mut op_s) = (0usize, 0f64);
    let (mut sel_splits, mut sel_merge_attempts, mut sel_merges) = (0, 0, 0);
    let mut next = 0usize;
    let mut last_tets = 0;
    for step in 0..cfg.steps {
        let t0 = Instant::now();
        let end = (next + cfg.per_step).min(nodes.len());
        session.insert(&nodes[next..end])?;
        next = end;
        let arrive = t0.elapsed().as_secs_f64() * 1e3;
        let cam = step_camera(cfg, center, step);
        let t1 = Instant::now();
        let st = if budgeted {
            session.frame(&cam, mode)?
        } else {
            session.converge(&cam, mode)?
        };
        let refine = t1.elapsed().as_secs_f64() * 1e3;
        if !st.converged {
            cut_steps += 1;
        }
        sweeps += st.sweeps;
        sel_splits += st.splits;
        sel_merge_attempts += st.merge_attempts;
        sel_merges += st.merges;
        op_s += st.op_time.as_secs_f64();
        arrive_total += arrive;
        arrive_max = f64::max(arrive_max, arrive);
        refine_total += refine;
        refine_max = f64::max(refine_max, refine);
        let (mesh, buf, sel) = (session.mesh(), session.buffer(), session.selector());
        let (all, drawable) = mesh.piece_counts();
        last_tets = drawable;
        max_tets = max_tets.max(drawable);
        sum_tets += drawable as f64;
        sum_leaves += mesh.leaf_count() as f64;
        sum_v += mesh.vertex_count() as f64;
        sum_e += edges_on_box(mesh, all) as f64;
        sum_b += mesh.bytes_held() as f64;
        sum_mb += (mesh.bytes_held() + buf.bytes_held()) as f64;
        sum_sel += sel.bytes_held() as f64;
        max_leaves = max_leaves.max(mesh.leaf_count());
        observe(step, mesh, &cam);
    }
    let (splits, merges) = session.mesh().op_counts();
    let (mut settle_frames, mut final_same) = (None, None);
    if cfg.settle {
        let cam = step_camera(cfg, center, cfg.steps.saturating_sub(1));
        let rest = if mode == Mode::Complete {
            Mode::Complete
        } else {
            Mode::Progressive
        };
        let mut frames = 0;
        loop {
            let st = session.frame(&cam, rest)?;
            frames += 1;
            if st.converged || frames > 100_000 {
                break;
            }
        }
        settle_frames = Some(frames);
        // the reference: unbudgeted convergence from the same state
        let mut reference = session.mesh().clone();
        let mut params = session.selector().params.clone();
        params.interactive = Budget::UNLIMITED;
        params.progressive = Budget::UNLIMITED;
        let mut unb = Selector::new(params);
        unb.converge(&mut reference, session.buffer(), &cam, rest)?;
        final_same = Some(sorted_leaves(&reference) == sorted_leaves(session.mesh()));
    }
    let (mesh, sel) = (session.mesh(), session.selector());
    let n = cfg.steps.max(1) as f64;
    let leaves = mesh.leaf_count().max(1);
    Ok(RunReport {
        tol: cfg
            .tol
            .map(|t| t.to_string())
            .unwrap_or_else(|| "simple".into()),
        tol_px: cfg.tol.map(|t| t.pixels(cfg.height)),
        steps: cfg.steps,
        avg_tets: sum_tets / n,
        max_tets,
        final_tets: last_tets,
        avg_leaves: sum_leaves / n,
        avg_vertices: sum_v / n,
        avg_edges: sum_e / n,
        mb: sum_mb / n / 1e6,
        mesh_mb: sum_b / n / 1e6,
        bytes_per_leaf: mesh.bytes_held() as f64 / leaves as f64,
        max_leaves,
        bytes_per_max_leaf: mesh.bytes_held() as f64 / max_leaves.max(leaves) as f64,
        mesh_parts: mesh.bytes_parts().to_vec(),
        sel_parts: sel.bytes_parts().to_vec(),
        avg_bytes_per_tet: sum_b / sum_tets.max(1.0),
        sel_mb: sum_sel / n / 1e6,
        sel_bytes_per_leaf: sel.bytes_held() as f64 / leaves as f64,
        avg_refine_ms: refine_total / n,
        max_refine_ms: refine_max,
        avg_arrive_ms: arrive_total / n,
        max_arrive_ms: arrive_max,
        splits,
        merges,
        tets_per_s: if refine_total > 0.0 {
            9.0 * (splits + merges) as f64 / (refine_total / 1e3)
        } else {
            0.0
        },
        op_tets_per_s: if op_s > 0.0 {
            9.0 * (splits + merges) as f64 / op_s
        } else {
            0.0
        },
        sweeps,
        sel_splits,
        sel_merge_attempts,
        sel_evals: sel.evaluations(),
        sel_merges,
        uniform_leaves: base.forest().leaves(),
        cut_steps,
        settle_frames,
        final_same,
        order,
        budget_ms: cfg.budget_ms,
        render: None,
        fps: None,
    })
}

// ------------------------------------------------------------------ `tetwave-bench progressive`

/// Arguments of `tetwave-bench progressive`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchArgs {
    /// Store directory (`tetwave-server prepare … --out DIR`).
    #[arg(long)]
    pub store: std::path::PathBuf,
    #[arg(long, default_value_t = 312)]
    pub steps: usize,
    /// Detail nodes arriving per step.
    #[arg(long, default_value_t = 1000)]
    pub per_step: usize,
    /// Radians per step about the vertical axis.
    #[arg(long, default_value_t = 0.05, value_parser = tetwave_source::options::angle)]
    pub rotate: f64,
    /// Camera distance from the volume's centre (thesis: 30 for Harmonic, 269 for Head256).
    #[arg(long, default_value_t = 30.0, value_parser = tetwave_source::options::distance)]
    pub distance: f64,
    #[arg(long, default_value_t = 0.0, value_parser = tetwave_source::options::elevation)]
    pub elevation: f64,
    #[arg(long, default_value_t = 45.0, value_parser = tetwave_source::options::fov)]
    pub fovy: f64,
    /// Viewport width in pixels (1..=8192).
    #[arg(long, default_value_t = 512, value_parser = tetwave_source::options::parse_side)]
    pub width: u32,
    /// Viewport height in pixels (1..=8192); `%` tolerances are of this height.
    #[arg(long, default_value_t = 512, value_parser = tetwave_source::options::parse_side)]
    pub height: u32,
    /// Tolerances, comma-separated: `20%` (of the viewport height) or `12px`.
    #[arg(long, default_value = "20%,15%,12.5%,10%,6.25%", value_delimiter = ',')]
    pub tol: Vec<String>,
    /// Also run the thesis' simple selective refinement (everything that arrived).
    #[arg(long)]
    pub simple: bool,
    /// Only the simple run (no tolerances).
    #[arg(long)]
    pub simple_only: bool,
    #[arg(long, value_enum, default_value_t = ArrivalOrder::Level)]
    pub order: ArrivalOrder,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Per-step time budget (ms); without it every step refines until converged.
    #[arg(long)]
    pub budget_ms: Option<f64>,
    /// Per-step operation budget.
    #[arg(long)]
    pub budget_ops: Option<usize>,
    /// Coarsen by the grandparent's error (gentler) instead of the parent's.
    #[arg(long)]
    pub grandparent: bool,
    /// No frustum culling.
    #[arg(long)]
    pub no_frustum: bool,
    /// Data-aware error: weight by subtree max |detail| / (DELTA · value range), capped at 1.
    #[arg(long)]
    pub data_aware: Option<f32>,
    #[command(flatten)]
    pub select: tetwave_source::options::SelectionArgs,
    /// Skip the settle-and-compare phase after the steps.
    #[arg(long)]
    pub no_settle: bool,
    /// Select with the reference selector: every node scanned with the uncached criteria at every
    /// sweep, without the per-slot caches (less memory, much slower).
    #[arg(long)]
    pub full_scan: bool,
    /// Also draw the leaf mesh of every K-th step (and of the last) on the GPU (projected
    /// tetrahedra; Mesa's lavapipe without a GPU) and report render ms, FPS (refinement +
    /// rendering) and PSNR against the CPU reference image of the full-resolution mesh.
    #[arg(long, value_name = "K", value_parser = at_least_one)]
    pub render_every: Option<usize>,
    /// With `--render-every`: draw with the CPU reference integrator instead of the GPU.
    #[arg(long, requires = "render_every")]
    pub render_cpu: bool,
    /// Transfer function drawn by `--render-every` and weighed by the image criterion: a preset
    /// (default, transparent, opaque, shells) or a .json file.
    #[arg(long, default_value = "default")]
    pub tf: String,
    /// One JSON object per run on stdout.
    #[arg(long)]
    pub json: bool,
    /// Recompute every store file's CRC-32 when opening it (reads the whole store; `base.bin`'s
    /// and the structure are always checked).
    #[arg(long)]
    pub verify: bool,
}

/// A count of at least 1 (`--render-every`).
fn at_least_one(s: &str) -> Result<usize, tetwave_source::options::ArgError> {
    match s.parse::<usize>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!("expected a whole number of at least 1, got {s:?}").into()),
    }
}

/// Runs `tetwave-bench progressive`: one [`RunReport`] per tolerance (and the simple run).
pub fn bench(args: &BenchArgs, mut emit: impl FnMut(&RunReport)) -> anyhow::Result<Vec<RunReport>> {
    let store = tetwave_store::Store::open_with(
        &args.store,
        tetwave_store::OpenOptions {
            verify_checksums: args.verify,
            ..Default::default()
        },
    )?;
    let m = &store.manifest;
    let mut nodes = store.read_nodes(0, m.counts.nodes)?;
    order_nodes(&mut nodes, args.order, args.seed, store.forest());
    let mut tols: Vec<Option<Tolerance>> = Vec::new();
    if !args.simple_only {
        for t in &args.tol {
            tols.push(Some(Tolerance::parse(t).map_err(anyhow::Error::msg)?));
        }
    }
    if args.simple || args.simple_only {
        tols.push(None);
    }
    // the criterion and leaf budget of --criterion / --max-tets, for the transfer function --tf
    let mut select = SelectParams::new(Tolerance::Pixels(0.0), m.value_range);
    let tf = tetwave_render::transfer::TransferFunction::load(&args.tf)?;
    args.select
        .apply(&mut select, &tf, m.display_value_range(), &store.base);
    let mut probe = match args.render_every {
        Some(every) => {
            let tf = tf.clone();
            let (full, _) = tetwave_source::load::store_mesh(&store, None)?;
            let probe =
                RenderProbe::new(full, m.value_range, every, args.render_cpu, tf).map_err(|e| {
                    anyhow::anyhow!("--render-every: {e} (--render-cpu draws on the CPU instead)")
                })?;
            tracing::info!("bench progressive draws with {}", probe.renderer());
            Some(probe)
        }
        None => None,
    };
    let mut out = Vec::new();
    for tol in tols {
        let cfg = RunConfig {
            steps: args.steps,
            per_step: args.per_step,
            rotate: args.rotate,
            distance: args.distance,
            elevation_deg: args.elevation,
            fovy_deg: args.fovy,
            width: args.width,
            height: args.height,
            tol,
            coarsen_ref: if args.grandparent {
                CoarsenRef::Grandparent
            } else {
                CoarsenRef::Parent
            },
            frustum: !args.no_frustum,
            data_aware: args.data_aware,
            image: select.image.clone(),
            max_tets: select.max_tets,
            budget_ms: args.budget_ms,
            budget_ops: args.budget_ops,
            settle: !args.no_settle,
            full_scan: args.full_scan,
        };
        let steps = cfg.steps;
        let mut observe = |step: usize, mesh: &AdaptiveMesh, cam: &Camera| {
            if let Some(p) = probe.as_mut().filter(|p| p.wants(step, steps)) {
                p.observe(step, mesh, cam);
            }
        };
        let mut r = run_progressive_with(
            &store.base,
            &nodes,
            m.value_range,
            &cfg,
            args.order,
            &mut observe,
        )
        .map_err(|e| match e {
            RunError::Node(_) => anyhow::anyhow!("store {}: {e}", args.store.display()),
            RunError::Mesh(e) => e.into(),
        })?;
        if let Some(p) = probe.as_mut() {
            let summary = p.finish()?;
            r.fps = Some(1e3 / (r.avg_refine_ms + summary.avg_ms));
            r.render = Some(summary);
        }
        emit(&r);
        out.push(r);
    }
    Ok(out)
}

/// Header of the text table [`table_row`] fills.
pub const TABLE_HEADER: &str = "tol      avg tets  max tets  vertices     edges      MB  B/leaf (+sel)  refine ms avg/max  arrive ms avg/max  tets/s (ops only)  sweeps  final=unbudgeted  render ms avg/max  FPS  PSNR dB avg/min";

/// One text row of the table.
pub fn table_row(r: &RunReport) -> String {
    let render = match (&r.render, r.fps) {
        (Some(s), Some(fps)) => format!(
            "  {:>8.1}/{:<8.1} {:>5.2}  {:.2}/{:.2}",
            s.avg_ms, s.max_ms, fps, s.avg_psnr_db, s.min_psnr_db
        ),
        _ => "  -".into(),
    };
    format!(
        "{:<7} {:>9.0} {:>9} {:>9.0} {:>9.0} {:>7.2} {:>6.1} (+{:>5.1}) {:>9.3}/{:<8.3} {:>8.3}/{:<8.3} {:>6.2}M ({:>6.2}M) {:>7}  {}{render}",
        r.tol,
        r.avg_tets,
        r.max_tets,
        r.avg_vertices,
        r.avg_edges,
        r.mb,
        r.bytes_per_leaf,
        r.sel_bytes_per_leaf,
        r.avg_refine_ms,
        r.max_refine_ms,
        r.avg_arrive_ms,
        r.max_arrive_ms,
        r.tets_per_s / 1e6,
        r.op_tets_per_s / 1e6,
        r.sweeps,
        r.final_same
            .map(|b| format!("{b} (+{} frames)", r.settle_frames.unwrap_or(0)))
            .unwrap_or_else(|| "-".into()),
    )
}
