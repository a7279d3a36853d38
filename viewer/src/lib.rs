//! `tetwave view`: the interactive client. A native window (winit and egui through egui-wgpu, by
//! eframe) that streams from a server (or reads a store, or a mesh file), refines the adaptive
//! mesh for the camera every frame under a time budget, and draws it with the projected
//! tetrahedra renderer on the window's own wgpu device.
//!
//! - [`tetwave_source::Data`]: the source, shared with `tetwave stream`; a stream's network runs on
//!   its own thread, and each frame applies what has arrived within a budget.
//! - [`tetwave_protocol::view::Orbit`]: the camera (orbit, pan, zoom), parametrized like
//!   `tetwave render` and `/v1/render`.
//! - [`plan`]: what each frame decides (refinement, which mesh, whole or spread draw, pixels,
//!   upload), a pure function.
//! - [`spread`]: a slow whole draw at rest spread over frames (sorted off the frame loop, drawn
//!   in parts).
//! - [`fly`]: fly mode's camera (`F`): a free eye that may enter the volume.
//! - [`gpu`]: the offscreen target the volume is drawn into, and the copy into the window.
//! - [`script`]: `--script` steps (camera, tolerance, mode, transfer function, waits, server image,
//!   screenshots).
//! - [`upload`]: leaf meshes uploaded on a thread of their own, off the frame loop.
//! - [`tf_edit`]: the transfer-function editor (points, presets, the JSON `--tf` reads).
//! - [`motion`]: a coarser tolerance while the camera moves, when the draws are slow.
//! - [`perf`]: frame times and input-to-frame latency, for `--json`.
//! - [`app`]: the window's frame loop and side panel.
//!
//! Failures to start (no display, no GPU adapter, a bad source or script) are one-line errors;
//! failures after the window opened (a lost stream, a refused server image, a screenshot that
//! cannot be written) are shown in the panel and make the command exit with status 1.

pub mod app;
pub mod fly;
pub mod gpu;
pub mod motion;
pub mod perf;
pub mod plan;
pub mod script;
pub mod spread;
pub mod tf_edit;
pub mod upload;

use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use tetwave_gpu::{GpuContext, RenderError};
use tetwave_render::transfer::{TransferFunction, AUTO};

/// Refinement modes of the viewer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ViewMode {
    /// The interactive budget every frame (8 ms of refinement), moving or not.
    Interactive,
    /// The interactive budget while the camera moves, the progressive one (50 ms) at rest.
    #[default]
    Progressive,
    /// Everything that has arrived, whatever the view (no tolerance, no frustum): the full
    /// level once the stream is complete, the same mesh the server's `/v1/render` draws.
    Complete,
}

impl ViewMode {
    pub const ALL: [ViewMode; 3] = [
        ViewMode::Interactive,
        ViewMode::Progressive,
        ViewMode::Complete,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ViewMode::Interactive => "interactive",
            ViewMode::Progressive => "progressive",
            ViewMode::Complete => "complete",
        }
    }
}

/// `tetwave view` options.
#[derive(Debug, Clone, clap::Args)]
pub struct ViewArgs {
    /// A server (`http://host:port`), a store directory, or a mesh file (`.vtu`, `.vtk`, `.msh`,
    /// `.mesh`, drawn as it is).
    #[arg(value_name = "URL|STORE|MESH")]
    pub source: String,
    /// Size of the view (the window adds the side panel), `WxH` pixels.
    #[arg(long, default_value = "640x480", value_parser = tetwave_source::options::parse_size)]
    pub size: (u32, u32),
    /// Transfer function: `auto` (the `default` preset fitted to the data as `tetwave render`
    /// fits it: a store's or a stream's to the histogram its manifest carries), a preset (default,
    /// transparent, opaque, shells) or a .json file. Default: `auto` for a store directory or a
    /// mesh file, `default` for a stream or a store read directly from object storage or HTTP
    /// (`auto` makes the view-dependent selection keep about twice the leaves: see
    /// docs/formats.md).
    #[arg(long)]
    pub tf: Option<String>,
    /// Screen-space tolerance in pixels (0: refine everything visible to the finest level).
    #[arg(long, default_value_t = 2.0, value_parser = tol_px)]
    pub tol: f64,
    #[arg(long, value_enum, default_value_t = ViewMode::Progressive)]
    pub mode: ViewMode,
    /// Frame time (ms) aimed at while the camera moves: when a frame that drew the whole view
    /// took longer, frames in motion draw with 1/`--motion-scale` of its width and height
    /// (scaled up into the view); at rest the view is drawn whole. 0: never.
    #[arg(long, default_value_t = 60.0, value_parser = motion_ms)]
    pub motion_ms: f64,
    /// The divisor of the view's width and height for slow draws in motion (1: full size).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub motion_scale: u32,
    /// For slow draws in motion, draw a coarser mesh of at most this many tets instead: the leaf
    /// mesh with its deepest levels merged into their ancestors, uploaded beside it; meanwhile the
    /// leaf mesh is refined within a short budget and drawn once the camera rests. A mesh file
    /// has no levels: its coarser mesh is a Kuhn grid sampled from it
    /// (`tetwave_source::load::motion_proxy`). 0: never.
    #[arg(long, default_value_t = 4_000)]
    pub motion_tets: usize,
    /// Also raise the tolerance in motion while frames draw slower than `--motion-ms` (a
    /// coarser mesh; off by default: at 10⁵ tets the selector coarsens over more frames than a
    /// motion lasts on a CPU rasterizer, see docs/benchmarks.md, "Viewer").
    #[arg(long)]
    pub motion_lod: bool,
    #[command(flatten)]
    pub camera: tetwave_source::options::CameraArgs,
    /// A JSON script of timestamped steps (see `viewer::script`).
    #[arg(long)]
    pub script: Option<PathBuf>,
    /// Write the view (the volume, without the panel) to this PNG when the run ends.
    #[arg(long)]
    pub screenshot: Option<PathBuf>,
    /// Close after this many frames (after the script's `quit` if that comes first).
    #[arg(long)]
    pub frames: Option<u64>,
    /// Print the run's summary as one JSON object on exit.
    #[arg(long)]
    pub json: bool,
    /// Bearer token for the server.
    #[arg(long, env = "TETWAVE_TOKEN")]
    pub token: Option<String>,
    /// Refuse a stream whose hierarchy has more detail nodes than this (as `tetwave stream`).
    #[arg(long, default_value_t = tetwave_net::DEFAULT_MAX_NODES, value_parser = clap::value_parser!(u64).range(1..))]
    pub max_nodes: u64,
    #[command(flatten)]
    pub select: tetwave_source::options::SelectionArgs,
}

fn motion_ms(s: &str) -> Result<f64, tetwave_source::options::ArgError> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && (0.0..=10_000.0).contains(&v) => Ok(v),
        _ => Err(format!("expected milliseconds within 0..=10000, got {s:?}").into()),
    }
}

fn tol_px(s: &str) -> Result<f64, tetwave_source::options::ArgError> {
    let s = s.trim();
    let v: f64 = s
        .strip_suffix("px")
        .unwrap_or(s)
        .trim()
        .parse()
        .map_err(|_| format!("expected a number of pixels, got {s:?}"))?;
    if v.is_finite() && (0.0..=1000.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!("{v} pixels is outside 0..=1000").into())
    }
}

/// What a run did: printed with `--json`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ViewReport {
    pub frames: u64,
    pub nodes: u64,
    pub nodes_total: u64,
    /// Tets drawn in the last frame.
    pub tets: u64,
    /// The legend's line in the panel: the scalar's name and the value range
    /// (`legend::legend_text`).
    pub legend: String,
    /// Leaves of the red tree at the end (what `--max-tets` bounds), and the most of any frame.
    pub leaves: u64,
    pub max_leaves: u64,
    /// The leaf budget in force (`--max-tets` or its default).
    pub leaf_budget: u64,
    /// Frames in which the leaf budget refused a split the criterion wanted.
    pub frames_budget_bound: u64,
    pub bytes_received: u64,
    /// Times the stream's connection was lost and made again.
    pub reconnects: u64,
    /// Frames whose panel said the stream was reconnecting.
    pub frames_reconnecting: u64,
    /// The factor on the tolerance in motion at the end (see `viewer::motion`).
    pub motion_factor: f64,
    pub complete: bool,
    /// Frames per second over the run.
    pub fps: f64,
    /// Frames that drew the volume per second over the run (the others repainted the panel or
    /// showed the same image).
    pub fps_drawn: f64,
    /// Last frame's refinement time.
    pub refine_ms: f64,
    /// The last upload of the leaf mesh (on the upload thread, off the frame loop).
    pub upload_ms: f64,
    /// Last drawn frame's CPU side: sort, exit faces, submission (the GPU runs after).
    pub render_ms: f64,
    /// The view's size in pixels.
    pub view: [u32; 2],
    /// The run ended in fly mode.
    pub fly: bool,
    /// The eye's position at the end.
    pub eye: [f64; 3],
    /// The orbit's camera (kept while flying).
    pub azimuth: f64,
    pub elevation: f64,
    pub distance: f64,
    pub fov: f64,
    pub mode: ViewMode,
    pub tol_px: f64,
    pub screenshots: Vec<String>,
    /// Tets drawn in each screenshot's view.
    pub screenshot_tets: Vec<u64>,
    /// PSNR of the server's image against the client's render of the same camera, transfer
    /// function and mesh (the last server image shown).
    pub server_psnr_db: Option<f64>,
    /// Script steps done, of the total.
    pub script_steps: [usize; 2],
    /// Failures after the window opened (also shown in the panel).
    pub errors: Vec<String>,
    /// Frame times and input-to-frame latency over the run.
    pub perf: perf::PerfReport,
    /// Seconds from the window's opening until every node was held.
    pub complete_s: Option<f64>,
    /// Whether the last frame was clipped to the store's level set (its near band arrived).
    pub clipped: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error("{0}")]
    Start(String),
    #[error("the viewer ran into errors: {}", .0.join("; "))]
    Run(Vec<String>, Box<ViewReport>),
}

/// Whether a display to open a window on is set (this build speaks X11, under Wayland through
/// XWayland's `DISPLAY`).
fn display_set() -> bool {
    std::env::var_os("DISPLAY").is_some_and(|d| !d.is_empty())
}

/// One line: eframe's and winit's errors may span several.
fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

impl ViewArgs {
    /// The transfer function asked for (`auto` when none was).
    pub fn tf_spec(&self) -> &str {
        self.tf.as_deref().unwrap_or(AUTO)
    }
}

/// Opens the window and runs until it is closed, `--frames` ran out or the script quit.
pub fn run(args: &ViewArgs) -> Result<ViewReport, ViewError> {
    let start = |s: String| ViewError::Start(one_line(&s));
    let source = tetwave_source::Source::parse(&args.source);
    let spec = match (&args.tf, &source) {
        (Some(spec), _) => spec.clone(),
        (None, tetwave_source::Source::Url(_) | tetwave_source::Source::Bucket(_)) => {
            "default".into()
        }
        (None, _) => AUTO.into(),
    };
    let args = &ViewArgs {
        tf: Some(spec),
        ..args.clone()
    };
    let tf = TransferFunction::load(args.tf_spec()).map_err(|e| start(e.to_string()))?;
    let steps = match &args.script {
        Some(p) => script::load(p).map_err(|e| start(e.to_string()))?,
        None => Vec::new(),
    };
    if !display_set() {
        return Err(start(
            "cannot open the viewer's window: no display (DISPLAY is not set); run it on a desktop, or headless under `xvfb-run -a tetwave view …`".into(),
        ));
    }
    let ctx = GpuContext::new().map_err(|e| match e {
        RenderError::NoAdapter => start(
            "cannot start the viewer: no GPU adapter found (wgpu saw none for Vulkan or GL; on \
             Debian, `apt-get install mesa-vulkan-drivers` gives the lavapipe CPU driver)"
                .into(),
        ),
        e => start(format!("cannot start the viewer: {e}")),
    })?;
    let tf = tetwave_source::load::fit_auto(args.tf_spec(), &source, tf)
        .map_err(|e| start(format!("{}: {e}", args.source)))?;
    let data = tetwave_source::Data::open(
        &source,
        tetwave_source::OpenOptions {
            token: args.token.clone(),
            tol: tetwave_adaptive::select::Tolerance::Pixels(args.tol),
            max_nodes: args.max_nodes,
            retries: tetwave_source::RECONNECT_ATTEMPTS,
            faults: Default::default(),
        },
        tetwave_source::Selection {
            args: args.select.clone(),
            tf: tf.clone(),
            fit_auto: args.tf_spec() == AUTO,
        },
    )
    .map_err(|e| start(format!("{}: {e}", args.source)))?;
    let mut data = data;
    if let Some(m) = &data.mesh {
        // a mesh file has no coarser levels: in motion a slow draw takes a proxy sampled from it
        data.mesh_motion = tetwave_source::load::motion_proxy(m, args.motion_tets);
    }
    let report = Arc::new(Mutex::new(ViewReport::default()));
    let mut options = eframe::NativeOptions {
        viewport: eframe::egui::ViewportBuilder::default()
            .with_title(format!("tetwave view {}", args.source))
            .with_inner_size([args.size.0 as f32 + app::PANEL_WIDTH, args.size.1 as f32]),
        renderer: eframe::Renderer::Wgpu,
        // egui's dithering would add noise to the view's black background
        dithering: false,
        ..Default::default()
    };
    options.wgpu_options.wgpu_setup = gpu::shared_setup(&ctx);
    let ctx = Arc::new(ctx);
    let shared = report.clone();
    let app_args = args.clone();
    let res = eframe::run_native(
        "tetwave view",
        options,
        Box::new(move |cc| {
            let rs = cc
                .wgpu_render_state
                .as_ref()
                .ok_or("eframe started without its wgpu renderer")?;
            Ok(Box::new(app::ViewerApp::new(
                app_args, ctx, rs, data, tf, steps, shared,
            )?))
        }),
    );
    if let Err(e) = res {
        return Err(start(format!("cannot open the viewer's window: {e}")));
    }
    let report = report.lock().unwrap_or_else(|e| e.into_inner()).clone();
    if report.errors.is_empty() {
        Ok(report)
    } else {
        Err(ViewError::Run(report.errors.clone(), Box::new(report)))
    }
}
