//! The viewer's frame loop (an eframe app). Each frame, in order: screenshots and server images
//! that arrived are taken in; what the network delivered is applied within [`INGEST_BUDGET`]; the
//! panel and the mouse and keys act; the script plays its next steps; the mesh is refined for the
//! camera under the selector's budget for the mode; a finished upload replaces the mesh drawn,
//! and the leaf mesh goes to the upload thread if it changed (one upload at a time, see
//! [`super::upload`]); the mesh is drawn into the offscreen target if anything it shows changed;
//! the target (or the server's image) is copied into the view.

use super::fly::Fly;
use super::gpu::{Blit, BlitCallback, Target};
use super::motion::MotionLod;
use super::perf::Perf;
use super::plan::{DrawKind, DrawMesh, FrameInputs, FramePlan};
use super::script::{Action, Step, WaitFor};
use super::spread::{Progress, SpreadDraw};
use super::upload::Uploader;
use super::{ViewArgs, ViewMode, ViewReport};
use eframe::egui::{self, Color32, PointerButton, Rect, Sense};
use eframe::egui_wgpu;
use std::path::PathBuf;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tetwave_adaptive::select::{Mode, Tolerance};
use tetwave_gpu::pt::{Accumulation, PtRenderer, TetDrawData, VisibilityOrder};
use tetwave_gpu::{GpuContext, RenderError};
use tetwave_net::HttpError;
use tetwave_protocol::view::Camera;
use tetwave_protocol::view::Orbit;
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::transfer::{TransferFunction, AUTO};
use tetwave_source::Data;

/// Width of the side panel, in points.
pub const PANEL_WIDTH: f32 = 260.0;

/// Time per frame for applying arrived nodes (refinement has the selector's own budget).
pub const INGEST_BUDGET: Duration = Duration::from_millis(8);

/// Frames a `size` step waits for the window to take its size before it fails.
const RESIZE_FRAMES: u64 = 600;

/// Bins of the editor's histogram.
const HISTOGRAM_BINS: usize = 64;
/// The transfer-function presets (what the server's `/v1/render` knows too).
const PRESETS: [&str; 5] = ["auto", "default", "transparent", "opaque", "shells"];

/// Degrees of rotation per pixel dragged, and per arrow key.
const DEG_PER_PX: f64 = 0.4;
const DEG_PER_KEY: f64 = 5.0;
/// Fly mode: degrees of turn per pixel dragged; speed in diagonals of the bounding box per
/// second (times 4 with shift); diagonals per wheel point.
const FLY_DEG_PER_PX: f64 = 0.2;
const FLY_SPEED: f64 = 0.25;
const FLY_PER_SCROLL: f64 = 5e-4;

/// The server's image of a view.
enum ServerImage {
    None,
    /// Requested for `cam`; the answer comes on `rx`.
    Pending {
        cam: Camera,
        rx: mpsc::Receiver<Result<Rgba8Image, HttpError>>,
    },
    /// Shown until the camera (or what the view shows) changes.
    Shown {
        target: Target,
        psnr_db: f64,
    },
}

/// Why a transfer function picked in the viewer could not be had.
#[derive(Debug, thiserror::Error)]
enum TfChoiceError {
    #[error("transfer function {spec}: {source}")]
    Load {
        spec: String,
        source: tetwave_render::transfer::TfError,
    },
    /// `auto` fitted to a store or mesh file that could not be read.
    #[error(transparent)]
    Fit(#[from] tetwave_source::load::LoadError),
}

pub struct ViewerApp {
    args: ViewArgs,
    gpu: Arc<GpuContext>,
    renderer: Arc<PtRenderer>,
    uploader: Uploader,
    blit: Blit,
    data: Data,
    tf: TransferFunction,
    /// The preset the transfer function is, if it is one (the server knows only presets).
    tf_preset: Option<String>,
    /// `auto` fitted to the data (a stream's: once its manifest arrives, `auto_fitted`), what
    /// picking `auto` draws with; the `default` preset until then.
    auto_tf: TransferFunction,
    auto_fitted: bool,
    tol: f64,
    mode: ViewMode,
    orbit: Orbit,
    /// Fly mode's camera, when in it (the orbit is kept for leaving it).
    fly: Option<Fly>,
    home: Option<Orbit>,
    /// The view's rectangle (points) and size (pixels) in the last frame.
    view_rect: Rect,
    view_px: (u32, u32),
    target: Option<Target>,
    /// A slow whole draw in progress, and a target of the view's size for the next one.
    pending: Option<SpreadDraw>,
    spare: Option<Target>,
    draw_data: Option<Arc<TetDrawData>>,
    /// The coarser mesh drawn in motion when whole draws are slow (`--motion-tets`).
    motion_data: Option<Arc<TetDrawData>>,
    /// The last draw was of the motion mesh (at rest the leaf mesh is drawn again).
    drew_motion: bool,
    tets: u64,
    /// Leaves of the red tree after the last refinement, and the most of any frame.
    leaves: u64,
    max_leaves: u64,
    /// The last refinement's leaf budget refused a wanted split; frames in which it did.
    budget_bound: bool,
    frames_budget_bound: u64,
    /// `--max-tets`, or its default for this machine.
    leaf_budget: u64,
    mesh_dirty: bool,
    image_dirty: bool,
    last_cam: Option<Camera>,
    /// The camera moved in this frame (by the mouse, keys or the script).
    moving: bool,
    refine_ms: f64,
    /// The last upload's time (on the upload thread).
    upload_ms: f64,
    render_ms: f64,
    /// Frames per second of the volume's draws (frames that only repaint the panel or the same
    /// image do not count), smoothed.
    fps: f64,
    /// When the volume was last drawn.
    last_draw: Option<Instant>,
    last_frame: Instant,
    started: Instant,
    frames: u64,
    /// The last frame at whose end the mesh was converged for the camera and drawn, and whether
    /// every node was held then.
    settled: Option<(u64, bool)>,
    steps: Vec<Step>,
    step: usize,
    /// The frame the current step began in.
    step_frame: Option<u64>,
    /// When the script last passed a step that is not an input (a `wait`, `frames`, a
    /// screenshot): an input after it cannot be given before, whatever its `at`.
    script_gate: Option<Instant>,
    quit: bool,
    shot_tx: mpsc::Sender<(PathBuf, Rect, f32, Arc<egui::ColorImage>)>,
    shot_rx: mpsc::Receiver<(PathBuf, Rect, f32, Arc<egui::ColorImage>)>,
    /// A screenshot requested and not yet written.
    pending_shot: Option<PathBuf>,
    server: ServerImage,
    closing: bool,
    status: String,
    report: Arc<Mutex<ViewReport>>,
    /// The editor's file for loading and saving the transfer function.
    tf_path: String,
    /// The histogram of the values held (the drawn leaf mesh's vertices), for the editor.
    hist: Vec<u32>,
    tf_canvas: super::tf_edit::CanvasState,
    screenshots: Vec<String>,
    screenshot_tets: Vec<u64>,
    server_psnr_db: Option<f64>,
    errors: Vec<String>,
    perf: Perf,
    motion: MotionLod,
    /// The period of the last frame that drew the whole view (decides `--motion-scale`).
    full_draw_ms: f64,
    /// Frames in which the panel said the stream was reconnecting.
    frames_reconnecting: u64,
    /// The last frame drew the volume in motion: its period is the next observation.
    observe_draw: bool,
    /// The tolerances of the mesh being uploaded and of the one drawn: a draw in motion tells
    /// about the factor only when its mesh was refined with it (a mesh still on its way would
    /// make the factor overshoot).
    upload_tol: f64,
    drawn_tol: f64,
    /// The selector's own interactive budget (before motion's changes).
    interactive_budget: Option<tetwave_adaptive::select::Budget>,
    /// Seconds from the window's opening until every node was held.
    complete_s: Option<f64>,
    /// The current frame's start.
    frame_start: Instant,
}

impl ViewerApp {
    pub fn new(
        args: ViewArgs,
        gpu: Arc<GpuContext>,
        rs: &egui_wgpu::RenderState,
        data: Data,
        tf: TransferFunction,
        steps: Vec<Step>,
        report: Arc<Mutex<ViewReport>>,
    ) -> Result<Self, RenderError> {
        let renderer = Arc::new(PtRenderer::with_accumulation(&gpu, Accumulation::Best));
        renderer.warm_up(&gpu, &tf)?;
        let uploader = Uploader::new(gpu.clone(), renderer.clone());
        let blit = Blit::new(&rs.device, rs.target_format);
        let (shot_tx, shot_rx) = mpsc::channel();
        // `auto` without data to fit (a stream) is the `default` preset
        let spec = if args.tf_spec() == AUTO {
            tf.name.as_str()
        } else {
            args.tf_spec()
        };
        let tf_preset = PRESETS.contains(&spec).then(|| spec.to_string());
        let auto_fitted = tf.name == AUTO;
        let auto_tf = if auto_fitted {
            tf.clone()
        } else {
            TransferFunction::preset("default").expect("the default preset exists")
        };
        let orbit = Orbit {
            target: glam::DVec3::ZERO,
            azimuth: args.camera.azimuth,
            elevation: args.camera.elevation,
            distance: args.camera.distance.unwrap_or(1.0),
            fov: args.camera.fov,
        };
        Ok(ViewerApp {
            tol: args.tol,
            mode: args.mode,
            renderer,
            uploader,
            blit,
            data,
            tf,
            tf_preset,
            auto_tf,
            auto_fitted,
            orbit,
            fly: None,
            home: None,
            view_rect: Rect::NOTHING,
            view_px: (args.size.0, args.size.1),
            target: None,
            pending: None,
            spare: None,
            draw_data: None,
            motion_data: None,
            drew_motion: false,
            tets: 0,
            leaves: 0,
            max_leaves: 0,
            budget_bound: false,
            frames_budget_bound: 0,
            leaf_budget: args.select.leaf_budget() as u64,
            mesh_dirty: true,
            image_dirty: true,
            last_cam: None,
            moving: false,
            refine_ms: 0.0,
            upload_ms: 0.0,
            render_ms: 0.0,
            fps: 0.0,
            last_draw: None,
            last_frame: Instant::now(),
            started: Instant::now(),
            frames: 0,
            settled: None,
            steps,
            step: 0,
            step_frame: None,
            script_gate: None,
            quit: false,
            shot_tx,
            shot_rx,
            pending_shot: None,
            server: ServerImage::None,
            closing: false,
            status: String::new(),
            report,
            tf_path: if args.tf_spec().ends_with(".json") {
                args.tf_spec().to_string()
            } else {
                "tf.json".into()
            },
            hist: Vec::new(),
            tf_canvas: Default::default(),
            screenshots: Vec::new(),
            screenshot_tets: Vec::new(),
            server_psnr_db: None,
            errors: Vec::new(),
            perf: Perf::default(),
            motion: MotionLod::new(if args.motion_lod { args.motion_ms } else { 0.0 }),
            full_draw_ms: 0.0,
            frames_reconnecting: 0,
            observe_draw: false,
            upload_tol: f64::NAN,
            drawn_tol: f64::NAN,
            interactive_budget: None,
            complete_s: None,
            frame_start: Instant::now(),
            gpu,
            args,
        })
    }

    fn fail(&mut self, e: String) {
        tracing::error!("{e}");
        self.status = e.clone();
        self.errors.push(e);
    }

    /// The initial view once the dataset's box is known: the orbit around its centre at the
    /// distance of the default framing (`Camera::framing`) unless given.
    fn init_home(&mut self) {
        if self.home.is_some() {
            return;
        }
        if let Some(f) = self.data.frame {
            self.orbit.target = f.center;
            self.orbit.distance = self.args.camera.distance.unwrap_or(f.distance);
            self.home = Some(self.orbit);
        }
    }

    /// The camera of the view: the fly camera in fly mode, else the orbit's.
    fn camera(&self, w: u32, h: u32) -> Camera {
        match &self.fly {
            Some(f) => f.camera(w, h),
            None => self.orbit.camera(w, h),
        }
    }

    fn diagonal(&self) -> f64 {
        self.data.frame.map_or(1.0, |f| f.diagonal)
    }

    /// Back to the initial orbit, out of fly mode.
    fn reset_view(&mut self) {
        self.fly = None;
        if let Some(h) = self.home {
            self.orbit = h;
        }
    }

    fn zoom(&mut self, factor: f64) {
        let diag = self.data.frame.map_or(1.0, |f| f.diagonal);
        self.orbit.zoom(factor, 1e-3 * diag, 100.0 * diag);
    }

    /// Loads a preset or a `.json` file as the transfer function; `auto` is the one fitted to
    /// the data.
    fn set_tf(&mut self, spec: &str) -> Result<(), TfChoiceError> {
        let tf = if spec == AUTO {
            if !self.auto_fitted && self.data.server().is_none() {
                // a store or a mesh file viewed with another function: fitted when first asked
                let source = tetwave_source::Source::parse(&self.args.source);
                let preset =
                    TransferFunction::preset("default").expect("the default preset exists");
                self.auto_tf = tetwave_source::load::fit_auto(AUTO, &source, preset)?;
                self.auto_fitted = true;
            }
            self.auto_tf.clone()
        } else {
            TransferFunction::load(spec).map_err(|source| TfChoiceError::Load {
                spec: spec.to_string(),
                source,
            })?
        };
        self.tf = tf;
        self.tf_preset = PRESETS.contains(&spec).then(|| spec.to_string());
        self.image_dirty = true;
        self.server = ServerImage::None;
        Ok(())
    }

    /// Saves the view's part of a window screenshot.
    fn save_shot(&mut self, path: PathBuf, rect: Rect, ppp: f32, img: &egui::ColorImage) {
        let [iw, ih] = img.size;
        let x0 = ((rect.min.x * ppp).round().max(0.0) as usize).min(iw);
        let y0 = ((rect.min.y * ppp).round().max(0.0) as usize).min(ih);
        let x1 = ((rect.max.x * ppp).round().max(0.0) as usize).min(iw);
        let y1 = ((rect.max.y * ppp).round().max(0.0) as usize).min(ih);
        if x1 <= x0 || y1 <= y0 {
            self.fail(format!("screenshot {}: the view is empty", path.display()));
            return;
        }
        let mut out = image::RgbaImage::new((x1 - x0) as u32, (y1 - y0) as u32);
        for (y, row) in (y0..y1).enumerate() {
            for (x, col) in (x0..x1).enumerate() {
                out.put_pixel(
                    x as u32,
                    y as u32,
                    image::Rgba(img.pixels[row * iw + col].to_array()),
                );
            }
        }
        match out.save(&path) {
            Ok(()) => {
                self.screenshots.push(path.display().to_string());
                self.screenshot_tets.push(self.tets);
            }
            Err(e) => self.fail(format!("screenshot {}: {e}", path.display())),
        }
    }

    /// Asks for a screenshot of the view (or of the whole window), written when it arrives.
    fn request_shot(&mut self, ctx: &egui::Context, path: PathBuf, whole: bool) {
        let tx = self.shot_tx.clone();
        let rect = if whole {
            Rect::EVERYTHING
        } else {
            self.view_rect
        };
        let ppp = ctx.pixels_per_point();
        let p = path.clone();
        ctx.request_screenshot(move |img| {
            let _ = tx.send((p, rect, ppp, img));
        });
        self.pending_shot = Some(path);
    }

    /// Asks the server for its image of the current view (same camera, transfer function, the
    /// finest level) on a thread of its own.
    fn request_server_image(&mut self) {
        let Some(server) = self.data.server().cloned() else {
            self.fail("server image: the view is not of a stream (give a server's URL)".into());
            return;
        };
        let Some(tf) = self.tf_preset.clone() else {
            self.fail(format!(
                "server image: the server renders only the presets {PRESETS:?}, not {:?}",
                self.tf.name
            ));
            return;
        };
        if self.fly.is_some() {
            self.fail(
                "server image: the server renders orbit views; leave fly mode (F) first".into(),
            );
            return;
        }
        if self.home.is_some_and(|h| h.target != self.orbit.target) {
            self.fail(
                "server image: the server orbits the volume's centre; reset the pan first".into(),
            );
            return;
        }
        let (w, h) = self.view_px;
        let o = self.orbit;
        let url = server.render(&format!(
            "width={w}&height={h}&azimuth={}&elevation={}&distance={}&fov={}&tf={tf}&level={}",
            o.azimuth, o.elevation, o.distance, o.fov, self.data.levels
        ));
        let token = self.args.token.clone();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(fetch_png(&url, token.as_deref()));
        });
        self.status = "server image requested".into();
        self.server = ServerImage::Pending {
            cam: o.camera(w, h),
            rx,
        };
    }

    fn take_server_image(&mut self) {
        let ServerImage::Pending { cam, rx } = &self.server else {
            return;
        };
        let res = match rx.try_recv() {
            Ok(r) => r,
            Err(mpsc::TryRecvError::Empty) => return,
            Err(mpsc::TryRecvError::Disconnected) => {
                self.server = ServerImage::None;
                self.fail("server image: the request thread ended".into());
                return;
            }
        };
        let cam = *cam;
        self.server = ServerImage::None;
        let img = match res {
            Ok(img) => img,
            Err(e) => {
                self.fail(format!("server image: {e}"));
                return;
            }
        };
        if self.last_cam != Some(cam) || (img.width, img.height) != (cam.width, cam.height) {
            self.status = "server image dropped: the view changed meanwhile".into();
            return;
        }
        // the client's own render of this camera, for the comparison
        let client = match &self.target {
            Some(t) if t.size() != (cam.width, cam.height) => {
                self.status = "server image dropped: the view was drawn with fewer pixels".into();
                return;
            }
            Some(t) => self.renderer.read_texture(&self.gpu, &t.texture),
            None => {
                self.status = "server image dropped: nothing drawn yet".into();
                return;
            }
        };
        let p = match client {
            Ok(c) => psnr(&c, &img).min(99.0),
            Err(e) => {
                self.fail(format!("server image: reading the client's render: {e}"));
                return;
            }
        };
        self.server_psnr_db = Some(p);
        self.status = format!("server image shown: {p:.2} dB against the client's render");
        self.server = ServerImage::Shown {
            target: Target::from_image(&self.gpu, &self.blit, &img),
            psnr_db: p,
        };
    }

    /// Plays script steps until one has to wait. Steps that change the view end the frame's
    /// steps, so that a following `wait` sees a frame of the new view; inputs already due are
    /// taken together (a backlog of inputs is one frame's, as queued events are).
    fn run_script(&mut self, ctx: &egui::Context) {
        while self.step < self.steps.len() && !self.closing {
            let step = self.steps[self.step].clone();
            if step
                .at
                .is_some_and(|at| self.started.elapsed().as_secs_f64() < at)
            {
                return;
            }
            // the frame the step's action began in (after its `at`)
            let first = *self.step_frame.get_or_insert(self.frames);
            // an input is given when it is due (a backlog of due inputs counts from each one's
            // `at`), but not before the script passed the last step that waited, or when the
            // script reaches it
            let given = step.at.map_or_else(Instant::now, |at| {
                let due = self.started + Duration::from_secs_f64(at);
                self.script_gate.map_or(due, |g| due.max(g))
            });
            let mut changes_view = false;
            match &step.action {
                Action::Camera(c) => {
                    self.fly = None;
                    if let Some(v) = c.azimuth {
                        self.orbit.azimuth = v;
                    }
                    if let Some(v) = c.elevation {
                        self.orbit.elevation = v;
                    }
                    if let Some(v) = c.distance {
                        self.orbit.distance = v;
                    }
                    if let Some(v) = c.fov {
                        self.orbit.fov = v;
                    }
                    changes_view = true;
                }
                Action::Orbit(d) => {
                    self.fly = None;
                    self.orbit.rotate(*d, 0.0);
                    changes_view = true;
                }
                Action::Elevate(d) => {
                    self.fly = None;
                    self.orbit.rotate(0.0, *d);
                    changes_view = true;
                }
                Action::Zoom(f) => {
                    self.fly = None;
                    self.zoom(*f);
                    changes_view = true;
                }
                Action::Fly(m) => {
                    let diag = self.diagonal();
                    let orbit = self.orbit;
                    let f = self.fly.get_or_insert_with(|| Fly::from_orbit(&orbit));
                    f.turn(m.yaw, m.pitch);
                    f.translate(m.forward * diag, m.right * diag, m.up * diag);
                    changes_view = true;
                }
                Action::Reset => {
                    self.reset_view();
                    changes_view = true;
                }
                Action::Tf(spec) => {
                    if let Err(e) = self.set_tf(spec) {
                        self.fail(e.to_string());
                    }
                    changes_view = true;
                }
                Action::Tol(t) => {
                    self.tol = *t;
                    changes_view = true;
                }
                Action::Mode(m) => {
                    self.mode = *m;
                    changes_view = true;
                }
                Action::Size(w, h) => {
                    if (self.view_px.0, self.view_px.1) != (*w, *h) {
                        if self.frames == first {
                            let ppp = ctx.pixels_per_point();
                            ctx.send_viewport_cmd(egui::ViewportCommand::InnerSize(egui::vec2(
                                *w as f32 / ppp + PANEL_WIDTH,
                                *h as f32 / ppp,
                            )));
                        }
                        if self.frames < first + RESIZE_FRAMES {
                            return;
                        }
                        let e = format!(
                            "size {w}x{h}: the view is still {}x{} after {RESIZE_FRAMES} frames",
                            self.view_px.0, self.view_px.1
                        );
                        self.fail(e);
                    }
                    changes_view = true;
                }
                Action::Wait(w) => {
                    // a frame that began after this step ended settled (with everything held)
                    let ok = self.settled.is_some_and(|(f, complete)| {
                        f > first && (complete || *w == WaitFor::Converged)
                    });
                    if !ok && self.data.error.is_none() {
                        return;
                    }
                }
                Action::Frames(n) => {
                    if self.frames < first + *n as u64 {
                        return;
                    }
                }
                Action::ServerImage => {
                    if self.frames == first {
                        self.request_server_image();
                    }
                    if matches!(self.server, ServerImage::Pending { .. }) {
                        return;
                    }
                }
                Action::Screenshot(p) | Action::WindowScreenshot(p) => {
                    if self.frames == first {
                        let whole = matches!(step.action, Action::WindowScreenshot(_));
                        self.request_shot(ctx, p.clone(), whole);
                    }
                    if self.pending_shot.is_some() {
                        return;
                    }
                }
                Action::Quit => self.quit = true,
            }
            self.step += 1;
            self.step_frame = None;
            if !step.action.is_input() {
                self.script_gate = Some(Instant::now());
            }
            if changes_view {
                self.perf.input(given);
                let elapsed = self.started.elapsed().as_secs_f64();
                let next_due = self
                    .steps
                    .get(self.step)
                    .is_some_and(|s| s.action.is_input() && s.at.is_some_and(|at| elapsed >= at));
                if !next_due {
                    return;
                }
            }
        }
    }

    /// Refines, uploads and draws for the current camera.
    fn refine_and_draw(&mut self) {
        let (w, h) = self.view_px;
        let cam = self.camera(w, h);
        self.moving = self.last_cam.is_some_and(|c| c != cam);
        let now = Instant::now();
        if self.moving {
            self.motion.moved(now);
        }
        let in_motion = self.motion.in_motion(now);
        let (motion, budget) = (&self.motion, &mut self.interactive_budget);
        let interactive_ms = self.data.session.as_ref().and_then(|s| {
            let base = *budget.get_or_insert_with(|| s.params().interactive);
            base.max_time
                .map(|t| motion.refine_budget_ms(t.as_secs_f64() * 1e3, now))
        });
        let inputs = FrameInputs {
            mode: self.mode,
            moving: self.moving,
            in_motion,
            tol_px: self.tol,
            motion_tol_px: self.motion.tolerance(self.tol, now),
            motion_ms: self.args.motion_ms,
            full_draw_ms: self.full_draw_ms,
            has_motion_mesh: self.motion_data.is_some(),
            motion_scale: self.args.motion_scale,
            view_px: (w, h),
            interactive_ms,
        };
        let mut plan = FramePlan::decide(&inputs);
        let tol = plan.tol_px;
        let rec = self.perf.current();
        rec.tol_px = tol;
        rec.in_motion = in_motion;
        if self.last_cam != Some(cam) {
            self.image_dirty = true;
            if matches!(self.server, ServerImage::Shown { .. }) {
                self.server = ServerImage::None;
                self.status = "back to the client's render".into();
            }
        }
        self.data.send_view(&cam, self.tol);
        let mut converged = true;
        if !self.auto_fitted {
            if let Some(m) = self.data.remote_manifest() {
                self.auto_fitted = true;
                if let Ok(tf) = TransferFunction::for_manifest(AUTO, m) {
                    self.auto_tf = tf;
                }
                // `--tf auto` on a stream: drawn with from now on
                if self.args.tf_spec() == AUTO {
                    // the server fits `auto` to the same histogram: its images match
                    self.tf_preset = Some(self.auto_tf.name.clone());
                    self.tf = self.auto_tf.clone();
                    self.image_dirty = true;
                }
            }
        }
        self.data.follow_tf(&self.tf);
        if let Some(s) = self.data.session.as_mut() {
            s.set_tolerance(Tolerance::Pixels(tol));
            if let Some(ms) = plan.interactive_ms {
                s.set_interactive_budget(tetwave_adaptive::select::Budget::ms(ms));
            }
            let mode = plan.refine_mode;
            let budget = match mode {
                Mode::Interactive => s.params().interactive,
                Mode::Progressive | Mode::Complete => s.params().progressive,
            };
            let t = Instant::now();
            match s.frame(&cam, mode) {
                Ok(st) => {
                    if st.splits + st.merges > 0 {
                        self.mesh_dirty = true;
                    }
                    converged = s.is_converged();
                    self.leaves = s.mesh().leaf_count() as u64;
                    self.max_leaves = self.max_leaves.max(self.leaves);
                    self.budget_bound = st.budget_bound;
                    self.frames_budget_bound += st.budget_bound as u64;
                }
                Err(e) => {
                    let e = format!("refinement: {e}");
                    self.fail(e);
                }
            }
            self.refine_ms = t.elapsed().as_secs_f64() * 1e3;
            let rec = self.perf.current();
            rec.refine_ms = self.refine_ms;
            rec.refine_budget_ms = budget.max_time.map(|d| d.as_secs_f64() * 1e3);
        }
        self.perf.current().mode = self.mode;
        self.perf.current().moving = self.moving;
        if self.data.take_changed() {
            self.mesh_dirty = true;
        }
        // nothing changed and nothing on its way: the mesh drawn is the one for this tolerance
        if converged && !self.mesh_dirty && !self.uploader.busy() {
            self.drawn_tol = tol;
        }
        // the mesh uploaded off the frame loop replaces the one drawn so far
        if let Some((res, ms)) = self.uploader.take() {
            self.drawn_tol = self.upload_tol;
            match res {
                Ok((d, motion)) => {
                    let tets = d.tet_count as u64;
                    // judged before its first draw, so that a much larger mesh is spread
                    self.full_draw_ms =
                        super::plan::expected_draw_ms(self.full_draw_ms, self.tets, tets);
                    self.tets = tets;
                    // this frame draws it: whole or spread as its expected cost says
                    plan.draw = FramePlan::decide(&FrameInputs {
                        full_draw_ms: self.full_draw_ms,
                        ..inputs
                    })
                    .draw;
                    self.draw_data = Some(Arc::new(d));
                    self.motion_data = motion.map(Arc::new);
                }
                Err(e) => self.fail(format!("upload: {e}")),
            }
            self.image_dirty = true;
            self.upload_ms = ms;
            self.perf.current().upload_ms = ms;
        }
        // one upload at a time: a mesh that changes meanwhile goes up after it; while slow
        // draws move with the coarser mesh, none (it would take the CPU the draws need: the leaf
        // mesh goes up once the camera rests)
        if self.mesh_dirty && !self.uploader.busy() && plan.upload {
            let t = Instant::now();
            let most = self.args.motion_tets;
            let (mesh, motion) = match (&self.data.session, &self.data.mesh) {
                (Some(s), _) => {
                    let (leaf, motion) = s.leaf_meshes(self.data.value_range, most);
                    (Some(leaf), motion)
                }
                (None, Some(m)) => (Some(m.clone()), self.data.mesh_motion.clone()),
                (None, None) => (None, None),
            };
            if let Some(m) = mesh {
                self.hist = super::tf_edit::histogram(
                    &m.values,
                    [m.value_range.0, m.value_range.1],
                    HISTOGRAM_BINS,
                );
                self.upload_tol = tol;
                if let Err(e) = self.uploader.start(m, motion) {
                    self.fail(format!("upload: {e}"));
                }
            }
            self.perf.current().leaf_ms = t.elapsed().as_secs_f64() * 1e3;
            self.mesh_dirty = false;
        }
        // in motion the volume may be drawn with fewer pixels (the copy into the view scales it
        // up); at rest always with the view's own
        let scale = plan.scale;
        let (dw, dh) = plan.draw_px;
        let sized = |t: &Target| t.size() == (dw, dh);
        let use_motion = plan.mesh == DrawMesh::Motion;
        let spread = plan.draw == DrawKind::Spread;
        // a spread draw is for this camera and size, and holds the renderer's uniforms
        if self.pending.as_ref().is_some_and(|p| !sized(p.target()))
            || self.last_cam != Some(cam)
            || use_motion
        {
            if let Some(p) = self.pending.take() {
                self.spare = Some(p.into_target());
            }
        }
        if !self.target.as_ref().is_some_and(sized) {
            // a spread draw at the new size replaces the image shown when it is complete
            // (meanwhile the old one is shown, scaled); any other draw goes into a new target
            if !spread || self.target.is_none() {
                self.target = Some(Target::new(
                    &self.gpu,
                    &self.blit,
                    self.renderer.format(),
                    dw,
                    dh,
                ));
            }
            if self.pending.is_none() {
                self.image_dirty = true;
            }
        }
        let draw_cam = if scale == 1 { cam } else { self.camera(dw, dh) };
        if self.drew_motion && !use_motion {
            self.image_dirty = true;
        }
        if self.image_dirty && self.pending.is_none() {
            let data = if use_motion {
                &self.motion_data
            } else {
                &self.draw_data
            };
            if let (Some(d), Some(t)) = (data, &self.target) {
                if spread {
                    // at rest a slow whole draw is spread over frames (the parts below), its
                    // sort off the frame loop
                    let target = match self.spare.take() {
                        Some(spare) if spare.size() == (dw, dh) => spare,
                        _ => Target::new(&self.gpu, &self.blit, self.renderer.format(), dw, dh),
                    };
                    self.pending = Some(SpreadDraw::start(
                        Arc::clone(d),
                        draw_cam,
                        self.tf.clone(),
                        target,
                        self.frames,
                    ));
                    self.image_dirty = false;
                    self.drew_motion = false;
                } else {
                    let times = self.renderer.draw_into(
                        &self.gpu,
                        d,
                        &draw_cam,
                        &self.tf,
                        VisibilityOrder::Centroid,
                        &t.view,
                        true,
                    );
                    self.render_ms = times.total_ms;
                    self.image_dirty = false;
                    self.drew_motion = use_motion;
                    let rec = self.perf.current();
                    rec.render_ms = times.total_ms;
                    rec.drew = true;
                    rec.draw_scale = scale;
                    self.observe_draw = in_motion && self.drawn_tol == tol;
                    let now = Instant::now();
                    if let Some(dt) = self.last_draw.map(|l| now.duration_since(l).as_secs_f64()) {
                        if dt > 0.0 {
                            self.fps = if self.fps == 0.0 {
                                1.0 / dt
                            } else {
                                0.9 * self.fps + 0.1 / dt
                            };
                        }
                    }
                    self.last_draw = Some(now);
                }
            }
        }
        // a spread draw's step: its sort handed to the renderer once done (no other draw holds
        // the renderer's uniforms meanwhile), and a part drawn in the same frame
        while let Some(p) = self.pending.as_mut() {
            match p.step(&self.renderer, &self.gpu) {
                Ok(Progress::Sorting) => break,
                Ok(Progress::Sorted { ms }) => self.perf.current().render_ms = ms,
                Ok(Progress::Drew {
                    triangles,
                    ms,
                    done,
                }) => {
                    let rec = self.perf.current();
                    rec.render_ms += ms;
                    rec.drew_part = triangles;
                    if done {
                        // the new image is shown: this frame counts as a draw at rest
                        let p = self.pending.take().expect("a spread draw");
                        let rec = self.perf.current();
                        rec.drew_part_of = Some(p.first_frame());
                        rec.drew = true;
                        rec.draw_scale = 1;
                        self.spare = self.target.replace(p.into_target());
                    }
                    break;
                }
                Err(e) => {
                    let p = self.pending.take().expect("a spread draw");
                    self.spare = Some(p.into_target());
                    self.fail(e.to_string());
                    break;
                }
            }
        }
        self.last_cam = Some(cam);
        // the tets of the mesh drawn: the coarser one's after a draw in motion
        self.perf.current().tets = match (&self.motion_data, self.drew_motion) {
            (Some(m), true) => m.tet_count as u64,
            _ => self.tets,
        };
        // drawn: the mesh refined so far, not one still being uploaded or waiting to be, with
        // all the view's pixels
        let drawn = !self.image_dirty
            && self.pending.is_none()
            && scale == 1
            && !self.drew_motion
            && self.draw_data.is_some()
            && !self.mesh_dirty
            && !self.uploader.busy();
        // converged for the user's tolerance, not the coarser one of motion
        if converged && drawn && tol == self.tol {
            // converged for the nodes held at this frame's start, which may be all of them
            let complete = self.data.is_complete() && !self.data.awaiting_levelset();
            self.settled = Some((self.frames, complete));
        }
    }

    /// The mouse and the keys move the camera: the orbit's, or in fly mode the fly camera's
    /// (`dt`: seconds since the last frame, for the keys held down).
    fn navigate(
        &mut self,
        ctx: &egui::Context,
        drag: egui::Vec2,
        pan: egui::Vec2,
        scroll: f32,
        dt: f64,
        mut reset: bool,
    ) {
        let ppp = ctx.pixels_per_point();
        let diag = self.diagonal();
        let keys = !ctx.egui_wants_keyboard_input();
        let pressed = |k: egui::Key| keys && ctx.input(|i| i.key_pressed(k));
        if pressed(egui::Key::F) {
            self.toggle_fly();
        }
        if let Some(f) = self.fly.as_mut() {
            if drag != egui::Vec2::ZERO {
                f.turn(
                    -drag.x as f64 * FLY_DEG_PER_PX,
                    -drag.y as f64 * FLY_DEG_PER_PX,
                );
            }
            // a right-drag slides the eye in the view plane
            let units_per_px = 2.0 * FLY_SPEED * diag / self.view_px.1.max(1) as f64;
            f.translate(
                scroll as f64 * FLY_PER_SCROLL * diag,
                -(pan.x * ppp) as f64 * units_per_px,
                (pan.y * ppp) as f64 * units_per_px,
            );
            if keys {
                let [fwd, right, up] = super::fly::held_move(ctx, dt, FLY_SPEED * diag);
                f.translate(fwd, right, up);
            }
        } else {
            if drag != egui::Vec2::ZERO {
                self.orbit
                    .rotate(-drag.x as f64 * DEG_PER_PX, drag.y as f64 * DEG_PER_PX);
            }
            if pan != egui::Vec2::ZERO {
                self.orbit
                    .pan((pan.x * ppp) as f64, (pan.y * ppp) as f64, self.view_px.1);
            }
            if scroll != 0.0 {
                self.zoom((-scroll as f64 * 0.002).exp());
            }
            use egui::Key;
            if pressed(Key::ArrowLeft) {
                self.orbit.rotate(-DEG_PER_KEY, 0.0);
            }
            if pressed(Key::ArrowRight) {
                self.orbit.rotate(DEG_PER_KEY, 0.0);
            }
            if pressed(Key::ArrowUp) {
                self.orbit.rotate(0.0, DEG_PER_KEY);
            }
            if pressed(Key::ArrowDown) {
                self.orbit.rotate(0.0, -DEG_PER_KEY);
            }
            if pressed(Key::Plus) || pressed(Key::Equals) {
                self.zoom(0.9);
            }
            if pressed(Key::Minus) {
                self.zoom(1.0 / 0.9);
            }
        }
        reset |= pressed(egui::Key::R);
        if reset {
            self.reset_view();
        }
    }

    /// Into fly mode from the current orbit's view, or back to the orbit as it was.
    fn toggle_fly(&mut self) {
        self.fly = match self.fly {
            Some(_) => None,
            None => Some(Fly::from_orbit(&self.orbit)),
        };
    }

    /// The colour legend (the scalar's name and range, the transfer function's colours across
    /// it) and the orientation axes of the current camera (x red, y green, z blue, as seen;
    /// named by their anatomical directions where the data states its frame: [`axis_names`]).
    fn legend(&self, ui: &mut egui::Ui) {
        ui.separator();
        ui.monospace(self.legend_text());
        let w = ui.available_width().max(16.0);
        let (bar, _) = ui.allocate_exact_size(egui::vec2(w, 12.0), Sense::hover());
        const STEPS: usize = 64;
        for k in 0..STEPS {
            let c = tetwave_render::legend::colour_at(&self.tf, k as f64 / (STEPS - 1) as f64);
            let x0 = bar.left() + bar.width() * k as f32 / STEPS as f32;
            let x1 = bar.left() + bar.width() * (k + 1) as f32 / STEPS as f32;
            ui.painter().rect_filled(
                Rect::from_min_max(egui::pos2(x0, bar.top()), egui::pos2(x1, bar.bottom())),
                0.0,
                Color32::from_rgb(c[0], c[1], c[2]),
            );
        }
        let (axes, _) = ui.allocate_exact_size(egui::vec2(64.0, 64.0), Sense::hover());
        let (r, u, _) = self.camera(1, 1).basis();
        let c = axes.center();
        let names = axis_names(self.data.physical.as_ref());
        for ((axis, color), name) in [
            (glam::DVec3::X, Color32::from_rgb(230, 80, 80)),
            (glam::DVec3::Y, Color32::from_rgb(90, 200, 90)),
            (glam::DVec3::Z, Color32::from_rgb(100, 140, 255)),
        ]
        .into_iter()
        .zip(names)
        {
            let d = egui::vec2(axis.dot(r) as f32, -(axis.dot(u) as f32)) * 22.0;
            ui.painter()
                .line_segment([c, c + d], egui::Stroke::new(2.0, color));
            ui.painter().text(
                c + d * 1.25,
                egui::Align2::CENTER_CENTER,
                name,
                egui::FontId::monospace(11.0),
                color,
            );
        }
    }

    /// The legend's line: the scalar's name (the dataset's, or the mesh file's scalar) and the
    /// value range the transfer function spans.
    fn legend_text(&self) -> String {
        let name = if self.data.name.is_empty() {
            "scalar"
        } else {
            &self.data.name
        };
        tetwave_render::legend::legend_text(name, self.data.value_range)
    }

    fn panel(&mut self, ui: &mut egui::Ui) {
        ui.heading("tetwave view");
        ui.label(egui::RichText::new(&self.args.source).small());
        ui.separator();
        let (held, total) = self.data.progress();
        egui::Grid::new("stats").num_columns(2).show(ui, |ui| {
            let mut row = |k: &str, v: String| {
                ui.label(k);
                ui.monospace(v);
                ui.end_row();
            };
            row("tets drawn", self.tets.to_string());
            row(
                "leaves / budget",
                format!(
                    "{} / {}{}",
                    self.leaves,
                    self.leaf_budget,
                    if self.budget_bound { " (binds)" } else { "" }
                ),
            );
            row("nodes held", format!("{held} / {total}"));
            row(
                "bytes received",
                format!("{:.2} MB", self.data.bytes_received() as f64 / 1e6),
            );
            row("refine", format!("{:.2} ms", self.refine_ms));
            if self.args.motion_lod {
                // the factor on the tolerance while the camera moves (1: the draws keep up)
                row(
                    "tolerance in motion",
                    format!("× {:.2}", self.motion.factor()),
                );
            }
            row("upload", format!("{:.2} ms", self.upload_ms));
            // the CPU side of a frame's draw: sort, exit faces, submission
            row("render (CPU)", format!("{:.2} ms", self.render_ms));
            // frames that drew the volume; none for a second: the view rests
            let resting = self
                .last_draw
                .is_none_or(|l| l.elapsed() > Duration::from_secs(1));
            row(
                "FPS (volume)",
                if resting {
                    "at rest".into()
                } else {
                    format!("{:.1}", self.fps)
                },
            );
            row("view", format!("{}×{}", self.view_px.0, self.view_px.1));
        });
        let frac = if total > 0 {
            held as f32 / total as f32
        } else if self.data.is_complete() {
            1.0
        } else {
            0.0
        };
        ui.add(
            egui::ProgressBar::new(frac)
                .show_percentage()
                .text(format!("stream {:.0}%", 100.0 * frac)),
        );
        self.legend(ui);
        ui.separator();
        let mut tol = self.tol;
        ui.add(
            // the slider spans 0..=32 px; `--tol` and the script may set more, which it keeps
            egui::Slider::new(&mut tol, 0.0..=32.0)
                .clamping(egui::SliderClamping::Never)
                .text("tolerance (px)")
                .step_by(0.25),
        );
        self.tol = tol;
        ui.horizontal_wrapped(|ui| {
            for m in ViewMode::ALL {
                ui.radio_value(&mut self.mode, m, m.name());
            }
        });
        let shown = self
            .tf_preset
            .clone()
            .unwrap_or_else(|| self.tf.name.clone());
        let mut preset = shown.clone();
        egui::ComboBox::from_label("transfer function")
            .selected_text(preset.clone())
            .show_ui(ui, |ui| {
                for p in PRESETS {
                    ui.selectable_value(&mut preset, p.to_string(), p);
                }
            });
        // a preset picked in the box (not a loaded or edited function that bears a preset's name)
        if preset != shown && PRESETS.contains(&preset.as_str()) {
            if let Err(e) = self.set_tf(&preset) {
                self.status = e.to_string();
            }
        }
        egui::CollapsingHeader::new("transfer function editor").show(ui, |ui| {
            if super::tf_edit::edit(ui, &mut self.tf, &self.hist, &mut self.tf_canvas) {
                self.tf_preset = None;
                self.image_dirty = true;
                self.server = ServerImage::None;
            }
            ui.horizontal(|ui| {
                ui.add(egui::TextEdit::singleline(&mut self.tf_path).desired_width(120.0));
                if ui.button("load").clicked() {
                    let p = self.tf_path.clone();
                    self.status = match self.set_tf(&p) {
                        Ok(()) => format!("loaded {p}"),
                        Err(e) => e.to_string(),
                    };
                }
                if ui.button("save").clicked() {
                    match super::tf_edit::save(&self.tf, std::path::Path::new(&self.tf_path)) {
                        Ok(()) => self.status = format!("saved {}", self.tf_path),
                        Err(e) => self.status = format!("cannot save: {e}"),
                    }
                }
            });
        });
        ui.horizontal(|ui| {
            if ui.button("Reset view").clicked() {
                self.reset_view();
            }
            let mut fly = self.fly.is_some();
            if ui.toggle_value(&mut fly, "Fly (F)").changed() {
                self.toggle_fly();
            }
            let can = self.data.server().is_some();
            if ui
                .add_enabled(can, egui::Button::new("Server image"))
                .on_hover_text("the server's /v1/render image of this view (complete mode)")
                .clicked()
            {
                self.request_server_image();
            }
        });
        if let ServerImage::Shown { psnr_db, .. } = &self.server {
            ui.label(format!(
                "showing the server's image ({psnr_db:.1} dB vs client)"
            ));
        }
        if let Some(e) = &self.data.error {
            ui.colored_label(Color32::LIGHT_RED, format!("stream: {e}"));
        } else if self.data.reconnecting() {
            ui.colored_label(Color32::YELLOW, "connection lost: reconnecting…");
            self.frames_reconnecting += 1;
        }
        if let Some(e) = self.data.levelset_error() {
            ui.colored_label(Color32::YELLOW, format!("not clipped to the domain: {e}"))
                .on_hover_text("the store's level set (/v1/levelset) could not be had");
        } else if self.data.clipped() {
            ui.label(egui::RichText::new("clipped to the mesh's domain").small());
        }
        if !self.status.is_empty() {
            ui.label(egui::RichText::new(&self.status).small());
        }
        ui.separator();
        ui.label(
            egui::RichText::new(
                "drag: orbit · right/shift-drag: pan · wheel: zoom\narrows: orbit · +/−: zoom · R: reset\nF: fly (drag: look · WASD/arrows: move · Q/E: down/up · shift: faster)",
            )
            .small(),
        );
    }

    fn publish(&self) {
        let (nodes, nodes_total) = self.data.progress();
        let elapsed = self.started.elapsed().as_secs_f64();
        let mut errors = self.errors.clone();
        if let Some(e) = &self.data.error {
            errors.push(format!("stream: {e}"));
        }
        let r = ViewReport {
            frames: self.frames,
            nodes,
            nodes_total,
            tets: self.tets,
            legend: self.legend_text(),
            leaves: self.leaves,
            max_leaves: self.max_leaves,
            leaf_budget: self.leaf_budget,
            frames_budget_bound: self.frames_budget_bound,
            bytes_received: self.data.bytes_received(),
            complete: self.data.is_complete(),
            fps: if elapsed > 0.0 {
                self.frames as f64 / elapsed
            } else {
                0.0
            },
            fps_drawn: if elapsed > 0.0 {
                self.perf.frames_drawn() as f64 / elapsed
            } else {
                0.0
            },
            refine_ms: self.refine_ms,
            upload_ms: self.upload_ms,
            render_ms: self.render_ms,
            view: [self.view_px.0, self.view_px.1],
            reconnects: self.data.reconnects(),
            frames_reconnecting: self.frames_reconnecting,
            motion_factor: self.motion.factor(),
            fly: self.fly.is_some(),
            eye: self.camera(1, 1).eye.to_array(),
            azimuth: self.orbit.azimuth,
            elevation: self.orbit.elevation,
            distance: self.orbit.distance,
            fov: self.orbit.fov,
            mode: self.mode,
            tol_px: self.tol,
            screenshots: self.screenshots.clone(),
            screenshot_tets: self.screenshot_tets.clone(),
            server_psnr_db: self.server_psnr_db,
            script_steps: [self.step, self.steps.len()],
            errors,
            perf: self.perf.report(),
            complete_s: self.complete_s,
            clipped: self.data.clipped(),
        };
        *self.report.lock().unwrap_or_else(|e| e.into_inner()) = r;
    }
}

/// GET a PNG and decode it.
fn fetch_png(url: &str, token: Option<&str>) -> Result<Rgba8Image, HttpError> {
    // the server's render deadline is 30 s by default; a larger one waits this long at most
    let bytes = tetwave_net::http::get(url, token, 256 << 20, std::time::Duration::from_secs(120))?;
    let img = image::load_from_memory(&bytes)
        .map_err(|e| HttpError {
            url: url.to_string(),
            reason: format!("the server's PNG: {e}"),
        })?
        .to_rgba8();
    Ok(Rgba8Image {
        width: img.width(),
        height: img.height(),
        pixels: img.pixels().map(|p| p.0).collect(),
    })
}

impl eframe::App for ViewerApp {
    fn clear_color(&self, _visuals: &egui::Visuals) -> [f32; 4] {
        [0.0, 0.0, 0.0, 1.0]
    }

    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let ctx = ui.ctx().clone();
        self.frames += 1;
        let now = Instant::now();
        self.frame_start = now;
        self.perf.begin_frame(
            self.frames,
            now,
            now.duration_since(self.started).as_secs_f64(),
        );
        if let Some(last) = self.perf.frames().last() {
            if last.drew && last.draw_scale == 1 && last.period_ms.is_finite() {
                self.full_draw_ms = last.period_ms;
            }
            // a spread draw ended: what its parts cost stands for a whole draw's (so a fast GPU
            // turns spreading off again)
            if let Some(first) = last.drew_part_of {
                let cost = self.perf.spread_cost(first);
                self.full_draw_ms = cost;
                self.render_ms = cost;
            }
        }
        if std::mem::take(&mut self.observe_draw) {
            if let Some(last) = self.perf.frames().last() {
                self.motion.observe(last.period_ms);
            }
        }
        let dt = now.duration_since(self.last_frame).as_secs_f64();
        self.last_frame = now;
        while let Ok((path, rect, ppp, img)) = self.shot_rx.try_recv() {
            self.save_shot(path, rect, ppp, &img);
            self.pending_shot = None;
        }
        self.take_server_image();
        let t = Instant::now();
        self.data.ingest(INGEST_BUDGET, Tolerance::Pixels(self.tol));
        self.perf.current().ingest_ms = t.elapsed().as_secs_f64() * 1e3;
        if self.complete_s.is_none() && self.data.is_complete() {
            self.complete_s = Some(self.started.elapsed().as_secs_f64());
        }
        self.init_home();
        let before = (self.orbit, self.fly, self.tol, self.mode, self.image_dirty);

        egui::Panel::left("tetwave-panel")
            .exact_size(PANEL_WIDTH)
            .resizable(false)
            .show(ui, |ui| self.panel(ui));
        let mut drag = egui::Vec2::ZERO;
        let mut pan = egui::Vec2::ZERO;
        let mut scroll = 0.0f32;
        let mut reset = false;
        egui::CentralPanel::default()
            .frame(egui::Frame::NONE.fill(Color32::BLACK))
            .show(ui, |ui| {
                let (rect, resp) =
                    ui.allocate_exact_size(ui.available_size(), Sense::click_and_drag());
                self.view_rect = rect;
                let shift = ui.input(|i| i.modifiers.shift);
                if resp.dragged_by(PointerButton::Primary) && !shift {
                    drag = resp.drag_delta();
                } else if resp.dragged_by(PointerButton::Secondary)
                    || resp.dragged_by(PointerButton::Middle)
                    || (resp.dragged_by(PointerButton::Primary) && shift)
                {
                    pan = resp.drag_delta();
                }
                if resp.hovered() {
                    scroll = ui.input(|i| i.smooth_scroll_delta.y);
                }
                reset = resp.double_clicked();
            });
        let ppp = ctx.pixels_per_point();
        let r = self.view_rect;
        self.view_px = (
            ((r.width() * ppp).round() as u32).max(1),
            ((r.height() * ppp).round() as u32).max(1),
        );
        self.navigate(&ctx, drag, pan, scroll, dt, reset);
        // the panel, the mouse and the keys: their events were read at the frame's start
        if (self.orbit, self.fly, self.tol, self.mode, self.image_dirty) != before {
            self.perf.input(now);
        }
        self.run_script(&ctx);
        self.refine_and_draw();

        let bind = match &self.server {
            ServerImage::Shown { target, .. } => Some(target.bind.clone()),
            _ => self.target.as_ref().map(|t| t.bind.clone()),
        };
        if let Some(bind) = bind {
            ui.painter().add(egui_wgpu::Callback::new_paint_callback(
                self.view_rect,
                BlitCallback {
                    blit: self.blit.clone(),
                    bind,
                },
            ));
        }

        let out_of_frames = self.args.frames.is_some_and(|n| self.frames >= n);
        if (out_of_frames || self.quit) && !self.closing {
            self.closing = true;
            if let Some(p) = self.args.screenshot.clone() {
                self.request_shot(&ctx, p, false);
            }
        }
        self.perf.end_frame(Instant::now());
        self.publish();
        if self.closing && self.pending_shot.is_none() {
            ctx.send_viewport_cmd(egui::ViewportCommand::Close);
        }
        let busy = self.closing
            || self.step < self.steps.len()
            || self.args.frames.is_some()
            || self.pending_shot.is_some()
            || self.uploader.busy()
            || self.mesh_dirty
            || self.motion.in_motion(Instant::now())
            || !matches!(self.server, ServerImage::None | ServerImage::Shown { .. })
            || self.settled.is_none_or(|(f, _)| f != self.frames);
        if busy {
            ctx.request_repaint();
        } else if !self.data.is_complete() && self.data.error.is_none() {
            ctx.request_repaint_after(Duration::from_millis(16));
        }
    }

    fn on_exit(&mut self) {
        self.data.close();
        self.publish();
    }
}

/// The names of the orientation axes' x, y and z: the anatomical direction each positive axis
/// points to where the data's world frame is known (`+x R`, `+y A`, `+z S` in RAS), else `x`,
/// `y`, `z`.
pub fn axis_names(physical: Option<&tetwave_protocol::store_format::Physical>) -> [String; 3] {
    [0, 1, 2].map(|a| {
        let plain = ["x", "y", "z"][a];
        match physical.and_then(|p| p.direction_letter(a, true)) {
            Some(c) => format!("{plain} {c}"),
            None => plain.to_string(),
        }
    })
}

#[cfg(test)]
mod axis_name_tests {
    use super::axis_names;
    use tetwave_protocol::store_format::Physical;

    /// The axes are named by the directions their positive ends point to in the data's frame.
    #[test]
    fn axes_are_named_in_the_datas_frame() {
        let world = |frame: Option<&str>| Physical {
            origin: [0.0; 3],
            frame: frame.map(String::from),
            length_unit: None,
            value_unit: None,
        };
        assert_eq!(axis_names(None), ["x", "y", "z"]);
        assert_eq!(axis_names(Some(&world(None))), ["x", "y", "z"]);
        assert_eq!(axis_names(Some(&world(Some("RAS")))), ["x R", "y A", "z S"]);
        assert_eq!(axis_names(Some(&world(Some("LPS")))), ["x L", "y P", "z S"]);
    }
}
