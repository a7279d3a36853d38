//! The streaming client: connects to `tetwave-server serve`, receives the manifest and base mesh,
//! renders at once, then applies detail batches as they arrive (any order), refines selectively,
//! renders a frame per step, sends its view when the camera moves, and after a dropped connection
//! reconnects and resumes with the ranges it already holds (no node lost, none applied twice).
//!
//! The network runs on a tokio task that decodes every message and acknowledges each batch as soon as
//! it is queued for the frame loop (up to [`tetwave_net::connection::INGEST_QUEUE`] messages ahead), so the stream arrives at
//! the network's pace, not the frames'; the frame loop takes whatever is queued each frame and never
//! waits on the network longer than its frame period (not at all once everything has arrived).

use serde::Serialize;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use tetwave_adaptive::draw::every_vertex_levelset;
use tetwave_adaptive::mesh::{AdaptiveMesh, MeshError};
use tetwave_adaptive::select::{Mode, Tolerance};
use tetwave_adaptive::session::Session;
use tetwave_gpu::pt::PtRenderer;
use tetwave_gpu::{GpuContext, RenderError};
use tetwave_net::ingest::Step;
pub use tetwave_net::Faults;
use tetwave_net::{NetError, ServerUrl};
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::synthesis::{synthesize_all, SynthesisError};
use tetwave_protocol::view::Camera;
use tetwave_protocol::{BaseMesh, DetailNode};
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TfError, TransferFunction, AUTO};
use tetwave_source::{Data, OpenOptions, Pump, Selection, Source, SourceError};

/// `tetwave stream` options.
#[derive(Debug, Clone, clap::Args)]
pub struct StreamArgs {
    /// Server address: `http://127.0.0.1:7878` or `ws://127.0.0.1:7878` (the stream is
    /// `/v1/stream`); or a store read directly with no server: `s3://BUCKET/PREFIX` (endpoint and
    /// credentials from AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION,
    /// AWS_ALLOW_HTTP) or a folder over HTTP (`http://HOST/PATH`, `https://…`), its blocks fetched
    /// by range as this client's selection asks for them.
    pub url: String,
    /// No window: write PNG frames and JSON lines (the only mode this build has).
    #[arg(long)]
    pub headless: bool,
    /// Frames to render (at least 1).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..))]
    pub frames: u32,
    /// Output directory for `frame_NNNN.png` and `frames.jsonl`.
    #[arg(long, default_value = "out/stream")]
    pub out: PathBuf,
    /// Camera rotation per frame, degrees (about the vertical axis).
    #[arg(long, default_value_t = 0.0, value_parser = tetwave_source::options::angle)]
    pub orbit: f64,
    /// Screen-space tolerance (`2`, `2px` or `10%` of the height); `0`: everything that arrived.
    #[arg(long, default_value = "0")]
    pub tol: String,
    /// Compute each frame's PSNR against the full-resolution reference for its camera (after the
    /// stream completes; frames must be rendered).
    #[arg(long, conflicts_with = "no_render")]
    pub psnr: bool,
    #[arg(long, default_value = "256x256", value_parser = tetwave_source::options::parse_size)]
    pub size: (u32, u32),
    /// Transfer function: a preset (default, transparent, opaque, shells), a .json file, or
    /// `auto` (the `default` preset fitted to the store's value histogram, as `tetwave render`
    /// fits it: it shows more of real data, and the view-dependent selection keeps about twice
    /// the leaves for it, see docs/formats.md).
    #[arg(long, default_value = "default")]
    pub tf: String,
    #[command(flatten)]
    pub camera: tetwave_source::options::CameraArgs,
    #[arg(long)]
    pub token: Option<String>,
    /// Wait at most this long per frame for new data (at most 60,000 ms).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(0..=60_000))]
    pub frame_ms: u64,
    /// Render with the CPU reference instead of the GPU.
    #[arg(long)]
    pub cpu: bool,
    /// Stop as soon as every node has arrived and the mesh has converged (at most `--frames`);
    /// ending with nodes missing is then an error (exit status 1).
    #[arg(long)]
    pub until_complete: bool,
    /// Refine but do not render (network and mesh measurements only).
    #[arg(long)]
    pub no_render: bool,
    /// Apply at most about this many nodes per frame (the thesis' +1000 per step); 0: all that
    /// arrived. Unread batches wait in the connection, which slows the server (backpressure).
    #[arg(long, default_value_t = 0)]
    pub per_frame: usize,
    /// Reconnect attempts after the connection drops (or the first connect fails) before giving
    /// up with an error; an attempt that brings new nodes starts the count again. Attempts wait
    /// 0, 100, 200, … ms.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(0..=100))]
    pub retries: u32,
    /// Refuse a dataset whose hierarchy has more detail nodes than this (the base mesh's tets
    /// times (8^levels − 1)/7), before allocating anything for it. The default, 2^27 =
    /// 134,217,728, is about 48 GB at the ~360 bytes a node the client holds once everything has
    /// arrived and is refined (51 B per leaf tet measured, 7 leaves per node).
    #[arg(long, default_value_t = DEFAULT_MAX_NODES, value_parser = clap::value_parser!(u64).range(1..))]
    pub max_nodes: u64,
    /// Stop at the first frame whose mesh is final for its camera: converged, every leaf that
    /// could still be split holding its node (`view_complete` in the frames), without waiting
    /// for the rest of the stream (at most `--frames`).
    #[arg(long, conflicts_with = "until_complete")]
    pub until_converged: bool,
    /// Draw the last frame's mesh to this PNG after the session: on the GPU, or with the CPU
    /// reference under `--cpu` or `--no-render`.
    #[arg(long)]
    pub final_png: Option<PathBuf>,
    #[command(flatten)]
    pub select: tetwave_source::options::SelectionArgs,
}

pub use tetwave_net::DEFAULT_MAX_NODES;

impl StreamArgs {
    /// The CLI defaults, for `url`, writing into `out`.
    pub fn new(url: &str, out: &std::path::Path) -> Self {
        StreamArgs {
            url: url.into(),
            headless: true,
            frames: 30,
            out: out.to_path_buf(),
            orbit: 0.0,
            tol: "0".into(),
            psnr: false,
            size: (256, 256),
            tf: "default".into(),
            camera: Default::default(),
            token: None,
            frame_ms: 30,
            cpu: false,
            until_complete: false,
            no_render: false,
            per_frame: 0,
            retries: 5,
            max_nodes: DEFAULT_MAX_NODES,
            until_converged: false,
            final_png: None,
            select: Default::default(),
        }
    }
}

/// Why `tetwave stream` failed.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    /// The connection, the server, or what it sent.
    #[error(transparent)]
    Net(#[from] NetError),
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error(transparent)]
    Tf(#[from] TfError),
    #[error("bad --tol: {0}")]
    Tol(String),
    #[error(transparent)]
    Render(#[from] RenderError),
    /// Selective refinement failed (a broken mesh invariant: a bug, reported rather than drawn).
    #[error("refinement: {0}")]
    Refine(#[from] MeshError),
    /// The final values could not be synthesized for `--psnr`.
    #[error("synthesis for --psnr: {0}")]
    Synthesis(#[from] SynthesisError),
    #[error("{path}: {reason}")]
    Output { path: PathBuf, reason: String },
    /// `--until-complete` and the frames ran out with nodes missing (a stream that fails past
    /// the base mesh is its own error); the frames written so far are kept.
    #[error("the session ended incomplete: {received} of {total} nodes after {frames} frames")]
    Incomplete {
        received: u64,
        total: u64,
        frames: usize,
    },
}

/// One frame's line in `frames.jsonl`.
#[derive(Debug, Clone, Serialize)]
pub struct FrameRecord {
    pub frame: u32,
    pub bytes_received: u64,
    pub nodes: u64,
    pub tets: u64,
    /// Leaves of the red tree (what `--max-tets` bounds).
    pub leaves: u64,
    /// The selector has nothing left to do for this frame's camera and the nodes held.
    pub converged: bool,
    /// The mesh is final for this frame's camera ([`Session::view_complete`]).
    pub view_complete: bool,
    /// The leaf budget (`--max-tets`) refused a split the criterion wanted.
    pub budget_bound: bool,
    pub refine_ms: f64,
    pub render_ms: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub psnr_db: Option<f64>,
    pub ms_since_connect: f64,
}

/// What a session did.
#[derive(Debug, Clone, Serialize)]
pub struct StreamReport {
    pub frames: Vec<FrameRecord>,
    pub nodes_total: u64,
    pub nodes_received: u64,
    /// Preview nodes held (each until the store's own replaced it).
    pub previews_received: u64,
    /// Preview nodes received again, or after the store's own (ignored).
    pub preview_duplicates: u64,
    pub duplicates: u64,
    pub bytes_received: u64,
    pub reconnects: u64,
    pub complete: bool,
    /// From connect to the first rendered frame.
    pub first_frame_ms: Option<f64>,
    /// Whether the frames were clipped to the domain's level set (the store has one and it
    /// arrived; it is asked for beside the stream, so the first frames may be drawn unclipped).
    pub clipped: bool,
    /// Why a store's level set could not be had, when it could not.
    pub levelset_error: Option<String>,
    /// The transfer function drawn with (`auto` fitted to the manifest's histogram, once the
    /// session started), as a `--tf` .json file holds it.
    pub tf: TransferFunction,
}

/// Draws `session`'s leaf mesh (`value_range` mapped to `tf`) for `cam` (on the GPU when there is one, else with the CPU
/// reference) and writes it to `path`.
fn draw_png(
    gpu: &Option<(GpuContext, PtRenderer)>,
    session: &Session,
    value_range: [f32; 2],
    cam: &Camera,
    tf: &TransferFunction,
    path: &std::path::Path,
) -> Result<Rgba8Image, StreamError> {
    let rm = session.leaf_mesh(value_range);
    let img = match gpu {
        Some((ctx, r)) => {
            let data = r.upload(ctx, &rm)?;
            r.render(ctx, &data, cam, tf)?.0
        }
        None => render_reference(&rm, cam, tf),
    };
    img.save_png(path).map_err(|e| StreamError::Output {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    Ok(img)
}

/// Runs a headless streaming session. With `--until-complete`, a session that ends with nodes
/// missing is an error.
pub fn run(args: &StreamArgs) -> Result<StreamReport, StreamError> {
    let report = run_session(args, Faults::default())?.report;
    if args.until_complete && !report.complete {
        return Err(StreamError::Incomplete {
            received: report.nodes_received,
            total: report.nodes_total,
            frames: report.frames.len(),
        });
    }
    Ok(report)
}

/// A finished session: the report and the client's final state.
pub struct Streamed {
    pub report: StreamReport,
    pub base: Option<BaseMesh>,
    pub mesh: Option<AdaptiveMesh>,
    /// The level set's near band the frames were clipped to, when one arrived.
    pub levelset: Option<NearLevelSet>,
}

/// [`run`] with injected transport faults, returning the final mesh (tests).
pub fn run_session(args: &StreamArgs, faults: Faults) -> Result<Streamed, StreamError> {
    // `auto` is fitted to the manifest's histogram when the session starts (the preset until then)
    let mut tf = TransferFunction::load(&args.tf)?;
    let fit_auto = args.tf == AUTO;
    let tol_spec = args.tol.trim();
    let tol = if tol_spec == "0" || tol_spec == "0px" {
        None
    } else {
        Some(Tolerance::parse(tol_spec).map_err(StreamError::Tol)?)
    };
    std::fs::create_dir_all(&args.out).map_err(|e| StreamError::Output {
        path: args.out.clone(),
        reason: e.to_string(),
    })?;
    // a bad address fails before the renderer is set up
    let source = Source::parse(&args.url);
    match &source {
        Source::Url(url) => drop(ServerUrl::parse(url)?),
        Source::Bucket(_) => {}
        _ => return Err(NetError::Url(args.url.clone()).into()),
    }
    let gpu = if args.cpu || args.no_render {
        None
    } else {
        let ctx = GpuContext::new()?;
        let r = PtRenderer::new(&ctx);
        r.warm_up(&ctx, &tf)?;
        Some((ctx, r))
    };
    // the renderer is set up before connecting: time to first image counts from the connect
    let t0 = Instant::now();
    let session_tol = tol.unwrap_or(Tolerance::Pixels(0.0));
    let mut data = Data::open(
        &source,
        OpenOptions {
            token: args.token.clone(),
            tol: session_tol,
            max_nodes: args.max_nodes,
            retries: args.retries,
            faults,
        },
        Selection {
            args: args.select.clone(),
            tf: tf.clone(),
            fit_auto,
        },
    )?;

    let mut received_nodes: Vec<DetailNode> = Vec::new();
    let mut frames = Vec::new();
    let mut cams = Vec::new();
    let mut images = Vec::new();
    let mut duplicates = 0u64;
    let mut previews_received = 0u64;
    let mut preview_duplicates = 0u64;
    let mut first_frame_ms = None;
    let wait_base = Duration::from_secs(10);
    let mut frame = 0u32;
    let mut last_cam: Option<Camera> = None;
    // a failure past the base mesh: the frames so far are written, then the session fails
    let mut failure: Option<StreamError> = None;
    while frame < args.frames {
        // 1. data: wait up to one frame period for the first message (before the base mesh, up to
        //    `wait_base` from the connect), then take what is ready until the frame's deadline; the
        //    first image goes out as soon as the base mesh is there
        let started = data.session.is_some();
        let pump = Pump {
            until: if started {
                Instant::now() + Duration::from_millis(args.frame_ms)
            } else {
                t0 + wait_base
            },
            wait: true,
            max_nodes: args.per_frame,
            stop_once_started: first_frame_ms.is_none(),
        };
        let pumped = data.pump(pump, session_tol, |step| match step {
            Step::Nodes {
                nodes,
                duplicates: d,
            } => {
                duplicates += d as u64;
                if args.psnr {
                    received_nodes.extend(nodes);
                }
            }
            // (frames count them as nodes applied; progress counts the store's only)
            Step::Preview { nodes, new } => {
                previews_received += new as u64;
                preview_duplicates += (nodes - new) as u64;
            }
            _ => {}
        });
        match pumped {
            // before the base mesh there are no frames to keep
            Err(NetError::TaskEnded | NetError::TaskFailed(_)) if data.session.is_none() => {
                return Err(NetError::NoBase(wait_base).into())
            }
            Err(e) if data.session.is_none() => return Err(e.into()),
            Err(e) => {
                failure = Some(e.into());
                break;
            }
            Ok(_) if data.session.is_none() => return Err(NetError::NoBase(wait_base).into()),
            Ok(_) => {}
        }
        if fit_auto && !started {
            tf = data.selection_tf().clone();
        }
        // (the manifest's display range, which came before the base mesh)
        let value_range = data.value_range;
        // 2. camera and view
        let Some((lo, hi)) = data.session.as_ref().map(|s| s.base().bounds()) else {
            unreachable!("a session by now")
        };
        let mut orbit = args.camera.orbit(Camera::framing(lo, hi));
        orbit.azimuth += args.orbit * frame as f64;
        let cam = orbit.camera(args.size.0, args.size.1);
        data.send_view(&cam, tol.map(|t| t.pixels(cam.height)).unwrap_or(0.0));
        let Some(session) = data.session.as_mut() else {
            unreachable!("a session by now")
        };
        // 3. refine
        let tr = Instant::now();
        let mode = match (tol, args.orbit != 0.0) {
            (None, _) => Mode::Complete,
            (Some(_), true) => Mode::Interactive,
            (Some(_), false) => Mode::Progressive,
        };
        let fst = session.frame(&cam, mode)?;
        let refine_ms = tr.elapsed().as_secs_f64() * 1e3;
        // 4. render
        let trn = Instant::now();
        let tets = session.mesh().piece_counts().1;
        let img = if args.no_render {
            None
        } else {
            let path = args.out.join(format!("frame_{frame:04}.png"));
            Some(draw_png(&gpu, session, value_range, &cam, &tf, &path)?)
        };
        let render_ms = trn.elapsed().as_secs_f64() * 1e3;
        if first_frame_ms.is_none() {
            first_frame_ms = Some(t0.elapsed().as_secs_f64() * 1e3);
        }
        let view_complete = fst.converged && session.view_complete();
        last_cam = Some(cam);
        frames.push(FrameRecord {
            frame,
            bytes_received: data.bytes_applied,
            nodes: session.progress().0,
            tets: tets as u64,
            leaves: session.mesh().leaf_count() as u64,
            converged: fst.converged,
            view_complete,
            budget_bound: fst.budget_bound,
            refine_ms,
            render_ms,
            psnr_db: None,
            ms_since_connect: t0.elapsed().as_secs_f64() * 1e3,
        });
        if let (true, Some(img)) = (args.psnr, img) {
            cams.push(cam);
            images.push(img);
        }
        frame += 1;
        let converged = session.is_converged();
        if args.until_converged && view_complete && !data.awaiting_levelset() {
            break;
        }
        if args.until_complete && data.stream_ended() && converged && !data.awaiting_levelset() {
            break;
        }
    }
    let state = data.session.take();
    if let (Some(path), Some(session), Some(cam), Some(m)) =
        (&args.final_png, &state, last_cam, data.remote_manifest())
    {
        draw_png(&gpu, session, m.display_value_range(), &cam, &tf, path)?;
    }
    let (nodes_received, nodes_total) = state.as_ref().map_or((0, 0), Session::progress);
    // (a base mesh of 0 levels has no nodes: it is complete as soon as it is there)
    let complete = state.is_some() && nodes_received == nodes_total;
    let clipped = state.as_ref().is_some_and(Session::has_levelset);
    // 5. accuracy against the full-resolution reference, once everything has arrived
    if args.psnr && failure.is_none() {
        if let (true, Some(session), Some(m)) = (complete, &state, data.remote_manifest()) {
            let base = session.base();
            received_nodes.sort_by_key(|n| n.id);
            received_nodes.dedup_by_key(|n| n.id);
            let empty: Vec<u8> = received_nodes.iter().map(|n| n.empty_children).collect();
            let values = synthesize_all(base, &base.vertex_keys(), received_nodes.drain(..))?;
            // clipped as the session draws (with the band it has), so that the reference is
            // what a complete stream should show
            let levelset = session
                .levelset()
                .map(|near| every_vertex_levelset(base, near));
            let mut full = RenderMesh::uniform_level_clipped(
                base,
                &values,
                &empty,
                base.levels,
                levelset.as_deref(),
            );
            let [lo, hi] = m.display_value_range();
            full.value_range = (lo, hi);
            for (rec, (cam, img)) in frames.iter_mut().zip(cams.iter().zip(&images)) {
                let reference: Rgba8Image = render_reference(&full, cam, &tf);
                rec.psnr_db = Some(psnr(img, &reference).min(99.0));
            }
        }
    }
    let lines: String = frames
        .iter()
        .map(|f| serde_json::to_string(f).expect("serializes") + "\n")
        .collect();
    let jpath = args.out.join("frames.jsonl");
    std::fs::write(&jpath, lines).map_err(|e| StreamError::Output {
        path: jpath,
        reason: e.to_string(),
    })?;
    data.close();
    if let Some(e) = failure {
        return Err(e);
    }
    let levelset = state.as_ref().and_then(|s| s.levelset().cloned());
    let (base, mesh) = match state.map(Session::into_parts) {
        Some((base, _, mesh, _)) => (Some(base), Some(mesh)),
        None => (None, None),
    };
    let report = StreamReport {
        frames,
        nodes_total,
        nodes_received,
        previews_received,
        preview_duplicates,
        duplicates,
        bytes_received: data.bytes_received(),
        reconnects: data.reconnects(),
        complete,
        first_frame_ms,
        clipped,
        levelset_error: data.levelset_error().map(ToString::to_string),
        tf,
    };
    Ok(Streamed {
        report,
        base,
        mesh,
        levelset,
    })
}
