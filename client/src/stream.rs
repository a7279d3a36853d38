//! The streaming client: connects to `tetwave-server serve`, receives the manifest and base mesh,
//! renders at once, then applies detail batches as they arrive (any order), refines selectively,
//! renders a frame per step, sends its view when the camera moves, and after a dropped connection
//! reconnects and resumes with the ranges it already holds (no node lost, none applied twice).
//!
//! The network runs on a tokio task that decodes every message and acknowledges each batch as soon as
//! it is queued for the frame loop (up to [`INGEST_QUEUE`] messages ahead), so the stream arrives at
//! the network's pace, not the frames'; the frame loop takes whatever is queued each frame and never
//! waits on the network longer than its frame period (not at all once everything has arrived).

use crate::draw::every_vertex_levelset;
use crate::ingest::{Ingest, Step};
use crate::mesh::AdaptiveMesh;
use crate::select::{Mode, SelectParams, Tolerance};
use crate::session::{NodeRejected, Session};
use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_protocol::view::Camera;
use tetwave_protocol::wire::{
    decode_server, encode, ClientMsg, IdRange, ServerMsg, SessionStart, ViewParams,
    MAX_FRAME_BYTES, MAX_RANGES, PROTOCOL_VERSION,
};
use tetwave_protocol::{BaseMesh, DetailNode, TetId};
use tetwave_render::gpu::pt::PtRenderer;
use tetwave_render::gpu::{GpuContext, RenderError};
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TfError, TransferFunction, AUTO};
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

/// `tetwave stream` options.
#[derive(Debug, Clone, clap::Args)]
pub struct StreamArgs {
    /// Server address: `http://127.0.0.1:7878` or `ws://127.0.0.1:7878` (the stream is `/v1/stream`).
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
    #[arg(long, default_value_t = 0.0, value_parser = crate::camera_arg::angle)]
    pub orbit: f64,
    /// Screen-space tolerance (`2`, `2px` or `10%` of the height); `0`: everything that arrived.
    #[arg(long, default_value = "0")]
    pub tol: String,
    /// Compute each frame's PSNR against the full-resolution reference for its camera (after the
    /// stream completes; frames must be rendered).
    #[arg(long, conflicts_with = "no_render")]
    pub psnr: bool,
    #[arg(long, default_value = "256x256", value_parser = crate::render_cli::parse_size)]
    pub size: (u32, u32),
    /// Transfer function: a preset (default, transparent, opaque, shells), a .json file, or
    /// `auto` (the `default` preset fitted to the store's value histogram, as `tetwave render`
    /// fits it: it shows more of real data, and the view-dependent selection keeps about twice
    /// the leaves for it, see docs/formats.md).
    #[arg(long, default_value = "default")]
    pub tf: String,
    #[command(flatten)]
    pub camera: crate::camera_arg::CameraArgs,
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
    pub select: crate::select_args::SelectionArgs,
}

/// `--max-nodes`' default: see [`StreamArgs::max_nodes`].
pub const DEFAULT_MAX_NODES: u64 = 1 << 27;

/// `Want` rounds after an `End` with nodes missing before the session fails
/// ([`StreamError::Unavailable`]).
pub const MAX_WANT_ROUNDS: u32 = 8;

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

/// Refuses, before anything is allocated for it, a base mesh whose hierarchy has more than
/// `limit` detail nodes (`--max-nodes`), or whose levels or node count disagree with the manifest.
/// `base` passed [`BaseMesh::validate`] (at most 16 levels), so the count is exact in u128.
pub fn check_hierarchy(base: &BaseMesh, m: &Manifest, limit: u64) -> Result<(), StreamError> {
    let tets = base.tets.len();
    let nodes = tets as u128 * ((1u128 << (3 * base.levels as u32)) - 1) / 7;
    if nodes > limit as u128 {
        return Err(StreamError::TooLarge {
            tets,
            levels: base.levels,
            nodes,
            limit,
        });
    }
    if m.levels != base.levels || m.counts.nodes as u128 != nodes {
        return Err(StreamError::Protocol(format!(
            "the base mesh ({} levels, {nodes} nodes) disagrees with the manifest ({} levels, {} nodes)",
            base.levels, m.levels, m.counts.nodes
        )));
    }
    Ok(())
}

#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    #[error("bad url {0:?}: expected http://host:port or ws://host:port")]
    Url(String),
    #[error("connection to {url} failed: {reason}")]
    Connect { url: String, reason: String },
    #[error("server error {code}: {message}")]
    Server { code: u16, message: String },
    #[error("protocol: {0}")]
    Protocol(String),
    /// A frame that does not decode, or whose contents fail their checks (a malformed node, an
    /// invalid base mesh).
    #[error("unreadable frame from the server: {0}")]
    BadFrame(String),
    /// A WebSocket message over the client's limit ([`ws_config`]).
    #[error("the server sent a message over the {MAX_FRAME_BYTES}-byte limit ({0})")]
    FrameTooLarge(String),
    /// The connection dropped and `--retries` attempts to reconnect brought nothing.
    #[error("connection to {url} lost: {reason} (gave up after {retries} reconnect attempts)")]
    Disconnected {
        url: String,
        reason: String,
        retries: u32,
    },
    /// A node the session refused (beyond the hierarchy, or claiming another node's vertex).
    #[error("the server sent an invalid node: {0}")]
    NodeRejected(#[from] NodeRejected),
    /// `End` with nodes missing, still missing after [`MAX_WANT_ROUNDS`] requests for them.
    #[error("the server ended the stream with {missing} of {total} nodes missing after {rounds} requests for them")]
    Unavailable {
        missing: u64,
        total: u64,
        rounds: u32,
    },
    /// A base mesh whose hierarchy is over the client's budget (`--max-nodes`).
    #[error("the base mesh's hierarchy ({tets} tets, {levels} levels) has {nodes} detail nodes, over the client's limit of {limit} (--max-nodes)")]
    TooLarge {
        tets: usize,
        levels: u8,
        nodes: u128,
        limit: u64,
    },
    #[error("no manifest/base mesh received within {0:?}")]
    NoBase(Duration),
    #[error(transparent)]
    Tf(#[from] TfError),
    #[error(transparent)]
    Tol(#[from] TolError),
    #[error(transparent)]
    Render(#[from] RenderError),
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

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct TolError(String);

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

/// Sorted, merged id ranges of a set.
pub fn ranges_of(ids: &BTreeSet<TetId>) -> Vec<IdRange> {
    let mut out: Vec<IdRange> = Vec::new();
    for &id in ids {
        match out.last_mut() {
            Some(r) if r.to == id => r.to += 1,
            _ => out.push(IdRange {
                from: id,
                to: id + 1,
            }),
        }
    }
    out
}

/// GETs the near band of the domain's level set from the server of stream URL `ws_url` and
/// decodes it for a hierarchy of `n_keys` vertices; returns it and the body's length.
fn fetch_levelset(
    ws_url: &str,
    token: Option<&str>,
    n_keys: u64,
) -> Result<(NearLevelSet, u64), String> {
    let url = ws_url
        .replacen("ws://", "http://", 1)
        .replacen("/v1/stream", "/v1/levelset", 1);
    let bytes = crate::http::get(&url, token, MAX_LEVELSET_BYTES, LEVELSET_TIMEOUT)?;
    let near = NearLevelSet::decode(&bytes, n_keys).map_err(|e| format!("GET {url}: {e}"))?;
    Ok((near, bytes.len() as u64))
}

/// The largest level-set body a client reads (a band of about 40 M vertices).
const MAX_LEVELSET_BYTES: u64 = 256 << 20;
/// How long the level set's request may take, all of it.
const LEVELSET_TIMEOUT: Duration = Duration::from_secs(30);
/// Requests for the level set in one session at most (a failed one is made again after a
/// reconnection).
const LEVELSET_ATTEMPTS: u32 = 3;
/// The level set's state in the network task: not asked for, asked, held, failed.
const LEVELSET_IDLE: u32 = 0;
const LEVELSET_ASKED: u32 = 1;
const LEVELSET_HELD: u32 = 2;
const LEVELSET_FAILED: u32 = 3;

pub(crate) fn ws_url(url: &str) -> Result<String, StreamError> {
    let rest = url
        .strip_prefix("http://")
        .or_else(|| url.strip_prefix("ws://"))
        .ok_or_else(|| StreamError::Url(url.into()))?;
    let host = rest.split('/').next().unwrap_or("");
    if host.is_empty() {
        return Err(StreamError::Url(url.into()));
    }
    Ok(format!("ws://{host}/v1/stream"))
}

/// Test hook: a transport fault injected into the network task.
#[derive(Debug, Clone, Copy, Default)]
pub struct Faults {
    /// Drop the connection once, after this many node batches (preview batches count too).
    pub drop_after_batches: Option<u64>,
    /// Deliver every k-th node batch twice.
    pub duplicate_every: Option<u64>,
    /// Lose every k-th node batch (the client re-requests what is missing after `End`).
    pub lose_every: Option<u64>,
    /// Deliver node batches in reversed groups of this many.
    pub reverse_groups: Option<usize>,
}

/// The runtime of a network task: one worker, and when dropped it does not wait for its blocking
/// tasks (a level-set request still in flight ends on its own; nobody takes its answer).
pub(crate) struct NetRuntime(Option<tokio::runtime::Runtime>);

impl NetRuntime {
    pub(crate) fn new(name: &str) -> std::io::Result<Self> {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name(name)
            .enable_all()
            .build()
            .map(|rt| NetRuntime(Some(rt)))
    }
}

impl std::ops::Deref for NetRuntime {
    type Target = tokio::runtime::Runtime;
    fn deref(&self) -> &Self::Target {
        self.0.as_ref().expect("a runtime until dropped")
    }
}

impl Drop for NetRuntime {
    fn drop(&mut self) {
        if let Some(rt) = self.0.take() {
            rt.shutdown_background();
        }
    }
}

/// How the network task behaves: injected faults (tests), reconnection attempts, and the largest
/// hierarchy (in nodes) it fetches a level set for.
pub(crate) struct NetPolicy {
    pub(crate) faults: Faults,
    pub(crate) retries: u32,
    pub(crate) max_nodes: u64,
    /// The session draws with `auto`: asks for the server's view order under the fitted
    /// function (`/v1/stream?tf=auto`), whose clients need other nodes first.
    pub(crate) tf_auto: bool,
}

/// The network task's counters, shared with the session that reads them (this module's frame
/// loop, or the viewer's).
pub(crate) struct Net {
    pub(crate) bytes: Arc<AtomicU64>,
    pub(crate) reconnects: Arc<AtomicU64>,
    /// A connection is open (its `Hello` sent); false before the first and while reconnecting.
    pub(crate) connected: Arc<AtomicBool>,
    /// Node ids received over the wire (for resume), whether or not applied yet.
    pub(crate) received: Arc<Mutex<BTreeSet<TetId>>>,
}

impl Net {
    pub(crate) fn new() -> Self {
        Net {
            bytes: Arc::new(AtomicU64::new(0)),
            reconnects: Arc::new(AtomicU64::new(0)),
            connected: Arc::new(AtomicBool::new(false)),
            received: Arc::new(Mutex::new(BTreeSet::new())),
        }
    }
}

/// A server message as the frame loop takes it: node blocks already decoded (on the network
/// task, so the frame loop never waits on decoding).
#[derive(Debug, Clone)]
pub(crate) enum Delivery {
    Manifest(Box<Manifest>),
    Base(Box<BaseMesh>),
    Nodes {
        seq: u64,
        nodes: Vec<DetailNode>,
    },
    /// Preview nodes, held until the store's own replace them.
    Preview {
        seq: u64,
        nodes: Vec<DetailNode>,
    },
    /// The near band of the domain's level set (`/v1/levelset`), fetched once a manifest lists
    /// one (drawn meshes are clipped to it from then on), or why it could not be had.
    LevelSet(Result<Box<NearLevelSet>, String>),
    End,
    Error {
        code: u16,
        message: String,
    },
}

/// Decodes node blocks with the coder of the manifest and base mesh that came before them.
#[derive(Default)]
struct BlockDecoder {
    manifest: Option<Box<Manifest>>,
    /// The base mesh, its coder, and the preview's coder when the manifest names a preview.
    coder: Option<(Box<BaseMesh>, BlockCoder, Option<BlockCoder>)>,
}

impl BlockDecoder {
    fn manifest(&mut self, m: Box<Manifest>) -> Result<Delivery, StreamError> {
        // the block decoder assumes an encoding it can read (bits, steps)
        m.encoding
            .check()
            .map_err(|e| StreamError::Protocol(format!("manifest: {e}")))?;
        if let Some(p) = &m.preview {
            p.encoding
                .check()
                .map_err(|e| StreamError::Protocol(format!("manifest: preview: {e}")))?;
        }
        // a server restarted with another store version: its coders, not the old ones
        if self
            .manifest
            .as_ref()
            .is_some_and(|old| old.encoding != m.encoding || old.preview != m.preview)
        {
            self.coder = None;
        }
        self.manifest = Some(m.clone());
        Ok(Delivery::Manifest(m))
    }

    fn base(&mut self, b: Box<BaseMesh>) -> Result<Delivery, StreamError> {
        // a resumed connection sends the same base again: keep its coder
        if self.coder.as_ref().is_none_or(|(held, ..)| **held != *b) {
            let m = self
                .manifest
                .as_ref()
                .ok_or_else(|| StreamError::Protocol("base before manifest".into()))?;
            let preview = m
                .preview
                .as_ref()
                .map(|p| BlockCoder::for_preview(&b, &p.encoding));
            self.coder = Some((b.clone(), BlockCoder::new(&b, &m.encoding), preview));
        }
        Ok(Delivery::Base(b))
    }

    /// What `m` delivers: a `Start`, the manifest then the base mesh; anything else, one.
    fn decode(&mut self, m: ServerMsg) -> Result<Vec<Delivery>, StreamError> {
        Ok(vec![match m {
            ServerMsg::Start(st) => {
                let SessionStart { manifest, base } = *st;
                let m = self.manifest(Box::new(manifest))?;
                return Ok(vec![m, self.base(Box::new(base))?]);
            }
            ServerMsg::Base(b) => self.base(b)?,
            ServerMsg::Nodes { seq, block } => {
                let (_, coder, _) = self
                    .coder
                    .as_ref()
                    .ok_or_else(|| StreamError::Protocol("nodes before the base mesh".into()))?;
                let nodes = coder
                    .decode(&block)
                    .map_err(|e| StreamError::BadFrame(format!("batch {seq}: {e}")))?;
                Delivery::Nodes { seq, nodes }
            }
            ServerMsg::Preview { seq, block } => {
                let coder = match &self.coder {
                    None => {
                        return Err(StreamError::Protocol("preview before the base mesh".into()))
                    }
                    Some((_, _, None)) => {
                        return Err(StreamError::Protocol(
                            "a preview the manifest does not describe".into(),
                        ))
                    }
                    Some((_, _, Some(c))) => c,
                };
                let nodes = coder
                    .decode(&block)
                    .map_err(|e| StreamError::BadFrame(format!("preview batch {seq}: {e}")))?;
                // only the preview's levels (the manifest checked them against the hierarchy)
                let (levels, base) = match (&self.manifest, &self.coder) {
                    (Some(m), Some((b, ..))) => (m.preview.as_ref().map_or(0, |p| p.levels), b),
                    _ => unreachable!("a preview coder comes with its manifest and base"),
                };
                let end = base.forest().level_start(levels);
                if let Some(n) = nodes.iter().find(|n| n.id >= end) {
                    return Err(StreamError::BadFrame(format!(
                        "preview batch {seq}: node {} is beyond the preview's {levels} levels",
                        n.id
                    )));
                }
                Delivery::Preview { seq, nodes }
            }
            ServerMsg::End { .. } => Delivery::End,
            ServerMsg::Error { code, message } => Delivery::Error { code, message },
        }])
    }
}

/// Decoded messages (batches, mostly) the network task may queue ahead of the frame loop.
pub(crate) const INGEST_QUEUE: usize = 256;

/// Waits between reconnect attempts: none before the first, then 100 ms times the attempts before.
const RETRY_STEP: Duration = Duration::from_millis(100);

pub(crate) async fn network(
    url: String,
    token: Option<String>,
    net: Arc<Net>,
    tx: mpsc::Sender<(Delivery, u64)>,
    mut out: mpsc::UnboundedReceiver<ClientMsg>,
    policy: NetPolicy,
) -> Result<(), StreamError> {
    let NetPolicy {
        faults,
        retries,
        max_nodes,
        tf_auto,
    } = policy;
    // the level set's address is derived from `url`; the stream's names the transfer function
    let stream_url = if tf_auto {
        format!("{url}?tf={AUTO}")
    } else {
        url.clone()
    };
    // consecutive connection attempts that brought no new node (a failed connect counts too)
    let mut failures = 0u32;
    // preview nodes handed to the session (a reconnection names them in `Hello`), in how many
    // batches
    let mut previewed: BTreeSet<TetId> = BTreeSet::new();
    let mut previews_delivered = 0u64;
    let mut dropped = false;
    let mut batches = 0u64;
    let mut held_back: Vec<(Delivery, u64)> = Vec::new();
    let mut blocks = BlockDecoder::default();
    // the level set is asked for after the first base mesh, and again after a later one (a
    // reconnection) while it has failed, at most LEVELSET_ATTEMPTS times in all
    let levelset = Arc::new(AtomicU32::new(LEVELSET_IDLE));
    let mut levelset_attempts = 0u32;
    // why the last connection ended, once one has
    let mut lost: Option<String> = None;
    // a connect that fails for good: after a lost connection, that loss is the cause
    let give_up = |url: String, lost: Option<String>, reason: String| match lost {
        None => StreamError::Connect { url, reason },
        Some(l) => StreamError::Disconnected {
            url,
            reason: format!("{l}; reconnecting: {reason}"),
            retries,
        },
    };
    loop {
        // the first attempt after a connection that brought nodes goes at once
        if failures > 1 {
            tokio::time::sleep(RETRY_STEP * (failures - 1)).await;
        }
        // what the client holds, so the server skips it; the server takes at most MAX_RANGES
        // ranges, and whatever a shortened list leaves out comes again (a duplicate, ignored)
        let mut have = ranges_of(&net.received.lock().expect("lock"));
        have.truncate(MAX_RANGES);
        let mut held_previews = ranges_of(&previewed);
        held_previews.truncate(MAX_RANGES);
        let conn = tokio::time::timeout(
            Duration::from_secs(5),
            tokio_tungstenite::connect_async_with_config(
                stream_url.as_str(),
                Some(ws_config()),
                false,
            ),
        )
        .await;
        let mut ws = match conn {
            Ok(Ok((ws, _))) => ws,
            Ok(Err(e)) => {
                failures += 1;
                if failures > retries {
                    return Err(give_up(url, lost, e.to_string()));
                }
                continue;
            }
            Err(_) => {
                failures += 1;
                if failures > retries {
                    return Err(give_up(url, lost, "connect timed out".into()));
                }
                continue;
            }
        };
        let hello = ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            token: token.clone(),
            have,
            previewed: held_previews,
        };
        let frame = encode(&hello).map_err(|e| StreamError::Protocol(e.to_string()))?;
        let reason = if let Err(e) = ws.send(Message::Binary(frame.into())).await {
            e.to_string()
        } else {
            net.connected.store(true, Ordering::Relaxed);
            'conn: loop {
                tokio::select! {
                    msg = ws.next() => {
                        let msg = match msg {
                            None => break "the server closed the connection".to_string(),
                            // over the limit: the same message would come again on a reconnect
                            Some(Err(WsError::Capacity(e))) => {
                                return Err(StreamError::FrameTooLarge(e.to_string()))
                            }
                            Some(Err(e)) => break e.to_string(),
                            Some(Ok(m)) => m,
                        };
                        let Message::Binary(bytes) = msg else { continue };
                        net.bytes.fetch_add(bytes.len() as u64, Ordering::Relaxed);
                        let m = decode_server(&bytes).map_err(|e| StreamError::BadFrame(e.to_string()))?;
                        let ms = blocks.decode(m)?;
                        let ask = matches!(levelset.load(Ordering::Acquire), LEVELSET_IDLE | LEVELSET_FAILED)
                            && levelset_attempts < LEVELSET_ATTEMPTS;
                        let base = ms.iter().find_map(|d| match d {
                            Delivery::Base(b) => Some(b),
                            _ => None,
                        });
                        if let (Some(base), true) = (base, ask) {
                            levelset_attempts += 1;
                            if let Some(man) = blocks.manifest.as_deref().filter(|m| m.has_levelset_band()) {
                                // beside the stream, so the nodes do not wait for it; only for a
                                // hierarchy within the client's budget (the frame loop refuses
                                // any other), decoded for its exact vertex count
                                let answer = tx.downgrade();
                                match check_hierarchy(base, man, max_nodes) {
                                    Ok(()) => {
                                        let (u, t, n) = (url.clone(), token.clone(), base.vertex_keys().vertex_count());
                                        let (bytes, state) = (net.bytes.clone(), levelset.clone());
                                        state.store(LEVELSET_ASKED, Ordering::Release);
                                        tokio::task::spawn_blocking(move || {
                                            let (got, len) = match fetch_levelset(&u, t.as_deref(), n) {
                                                Ok((near, len)) => (Ok(Box::new(near)), len),
                                                Err(e) => (Err(e), 0),
                                            };
                                            let done = if got.is_ok() { LEVELSET_HELD } else { LEVELSET_FAILED };
                                            bytes.fetch_add(len, Ordering::Relaxed);
                                            // nobody to tell once the network task has ended; the
                                            // answer goes first, so a retry cannot overtake it
                                            if let Some(tx) = answer.upgrade() {
                                                let _ = tx.blocking_send((Delivery::LevelSet(got), len));
                                            }
                                            state.store(done, Ordering::Release);
                                        });
                                    }
                                    Err(e) => {
                                        // the frame loop refuses this hierarchy too: no retry
                                        levelset_attempts = LEVELSET_ATTEMPTS;
                                        let why = format!("level set not fetched: {e}");
                                        let _ = tx.send((Delivery::LevelSet(Err(why)), 0)).await;
                                    }
                                }
                            }
                        }
                        // the frame's bytes go with its first delivery
                        let mut deliver: Vec<(Delivery, u64)> =
                            ms.into_iter().zip(std::iter::once(bytes.len() as u64).chain(std::iter::repeat(0))).collect();
                        if let [(Delivery::Nodes { nodes, .. }, _)] = &deliver[..] {
                            batches += 1;
                            if faults.lose_every.is_some_and(|k| batches.is_multiple_of(k)) {
                                deliver.clear();
                            } else {
                                let mut r = net.received.lock().expect("lock");
                                let before = r.len();
                                r.extend(nodes.iter().map(|n| n.id));
                                if r.len() > before {
                                    // progress: this connection is worth reconnecting to again
                                    failures = 0;
                                }
                                drop(r);
                                if faults.duplicate_every.is_some_and(|k| batches.is_multiple_of(k)) {
                                    deliver.push(deliver[0].clone());
                                }
                                if let Some(g) = faults.reverse_groups {
                                    held_back.append(&mut deliver);
                                    if held_back.len() >= g {
                                        held_back.reverse();
                                        deliver.append(&mut held_back);
                                    }
                                }
                            }
                        } else {
                            // anything else flushes what was held back, in order of arrival
                            let mut flushed: Vec<(Delivery, u64)> = std::mem::take(&mut held_back);
                            flushed.append(&mut deliver);
                            deliver = flushed;
                        }
                        // a batch is acknowledged once it is in the session's queue, not when the frame
                        // loop gets to it: ingestion runs at the network's pace, and the queue's bound
                        // is the backpressure
                        for m in deliver {
                            let ack = match &m.0 {
                                Delivery::Nodes { seq, .. } => Some(*seq),
                                Delivery::Preview { seq, nodes } => {
                                    // a reconnection asks for the rest of the preview only
                                    previewed.extend(nodes.iter().map(|n| n.id));
                                    previews_delivered += 1;
                                    Some(*seq)
                                }
                                _ => None,
                            };
                            if tx.send(m).await.is_err() {
                                return Ok(());
                            }
                            if let Some(seq) = ack {
                                let f = encode(&ClientMsg::Ack { seq })
                                    .map_err(|e| StreamError::Protocol(e.to_string()))?;
                                if let Err(e) = ws.send(Message::Binary(f.into())).await {
                                    break 'conn e.to_string();
                                }
                            }
                        }
                        let delivered = batches + previews_delivered;
                        if !dropped && faults.drop_after_batches.is_some_and(|n| delivered >= n) {
                            dropped = true;
                            drop(ws);
                            break "dropped (test fault)".to_string();
                        }
                    }
                    m = out.recv() => {
                        let Some(m) = m else { return Ok(()) };
                        let frame = encode(&m).map_err(|e| StreamError::Protocol(e.to_string()))?;
                        if let Err(e) = ws.send(Message::Binary(frame.into())).await {
                            break e.to_string();
                        }
                    }
                }
            }
        };
        // dropped: reconnect and resume, unless the attempts since the last progress ran out
        net.connected.store(false, Ordering::Relaxed);
        failures += 1;
        if failures > retries {
            return Err(StreamError::Disconnected {
                url,
                reason,
                retries,
            });
        }
        lost = Some(reason);
        net.reconnects.fetch_add(1, Ordering::Relaxed);
    }
}

/// The client's WebSocket limits: a message may be as large as a whole protocol frame
/// ([`MAX_FRAME_BYTES`] after the 4-byte length prefix); tungstenite's default (16 MiB) would
/// refuse a large base mesh forever.
pub fn ws_config() -> WebSocketConfig {
    WebSocketConfig::default()
        .max_message_size(Some(MAX_FRAME_BYTES + 4))
        .max_frame_size(Some(MAX_FRAME_BYTES + 4))
}

/// Draws `session`'s leaf mesh for `cam` (on the GPU when there is one, else with the CPU
/// reference) and writes it to `path`.
fn draw_png(
    gpu: &Option<(GpuContext, PtRenderer)>,
    session: &Session,
    m: &Manifest,
    cam: &Camera,
    tf: &TransferFunction,
    path: &std::path::Path,
) -> Result<Rgba8Image, StreamError> {
    let rm = session.leaf_mesh(m.display_value_range());
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
    let fitted = std::cell::RefCell::new(None);
    let tol_spec = args.tol.trim();
    let tol = if tol_spec == "0" || tol_spec == "0px" {
        None
    } else {
        Some(Tolerance::parse(tol_spec).map_err(TolError)?)
    };
    std::fs::create_dir_all(&args.out).map_err(|e| StreamError::Output {
        path: args.out.clone(),
        reason: e.to_string(),
    })?;
    let url = ws_url(&args.url)?;
    let rt = NetRuntime::new("tetwave-net").map_err(|e| StreamError::Protocol(e.to_string()))?;
    // the renderer is set up before connecting: time to first image counts from the connect
    let gpu = if args.cpu || args.no_render {
        None
    } else {
        let ctx = GpuContext::new()?;
        let r = PtRenderer::new(&ctx);
        r.warm_up(&ctx, &tf)?;
        Some((ctx, r))
    };
    let net = Arc::new(Net::new());
    // decoded messages waiting for the frame loop; the network task acknowledges a batch once it is
    // queued here, so when the queue is full the network waits, the server's window fills and the
    // server slows down (backpressure)
    let (tx, mut rx) = mpsc::channel::<(Delivery, u64)>(INGEST_QUEUE);
    let (out_tx, out_rx) = mpsc::unbounded_channel::<ClientMsg>();
    let t0 = Instant::now();
    let mut task = rt.spawn(network(
        url,
        args.token.clone(),
        net.clone(),
        tx,
        out_rx,
        NetPolicy {
            faults,
            retries: args.retries,
            max_nodes: args.max_nodes,
            tf_auto: args.tf == AUTO,
        },
    ));

    let mut ingest = Ingest::new(args.max_nodes);
    let mut state: Option<Session> = None;
    let mut received_nodes: Vec<DetailNode> = Vec::new();
    let mut frames = Vec::new();
    let mut cams = Vec::new();
    let mut images = Vec::new();
    let mut duplicates = 0u64;
    let mut previews_received = 0u64;
    let mut preview_duplicates = 0u64;
    let mut first_frame_ms = None;
    // wire bytes of the messages the client has applied (what its frames show)
    let mut bytes_applied = 0u64;
    let mut last_view: Option<ViewParams> = None;
    let wait_base = Duration::from_secs(10);
    let mut frame = 0u32;
    let mut last_cam: Option<Camera> = None;
    // a failure past the base mesh: the frames so far are written, then the session fails
    let mut failure: Option<StreamError> = None;
    let mut net_done = false;
    'frames: while frame < args.frames {
        // 1. data: wait up to one frame period for the first message, then take what is ready
        let deadline = Instant::now() + Duration::from_millis(args.frame_ms);
        let mut got_any = false;
        let mut applied = 0usize;
        loop {
            if args.per_frame > 0 && applied >= args.per_frame {
                break;
            }
            // once everything has arrived there is nothing to wait for but the level set
            let msg = if state.is_none()
                || (!got_any && (!ingest.ended() || ingest.levelset_pending()))
            {
                let left = if state.is_none() {
                    wait_base.saturating_sub(t0.elapsed())
                } else {
                    deadline.saturating_duration_since(Instant::now())
                };
                match rt.block_on(async { tokio::time::timeout(left, rx.recv()).await }) {
                    Ok(Some(m)) => Some(m),
                    Ok(None) if state.is_none() => {
                        // the network task ended before a base mesh came: report why
                        let why = rt.block_on(&mut task);
                        return Err(match why {
                            Ok(Err(e)) => e,
                            _ => StreamError::NoBase(wait_base),
                        });
                    }
                    Ok(None) => {
                        // the network task ended (after what it delivered): a failure unless
                        // everything has arrived
                        if !net_done {
                            net_done = true;
                            ingest.network_ended();
                            let why = rt.block_on(&mut task);
                            if !state.as_ref().is_some_and(Session::is_complete) {
                                failure = Some(match why {
                                    Ok(Err(e)) => e,
                                    Ok(Ok(())) => {
                                        StreamError::Protocol("the network task ended".into())
                                    }
                                    Err(e) => StreamError::Protocol(format!(
                                        "the network task failed: {e}"
                                    )),
                                });
                                break 'frames;
                            }
                        }
                        None
                    }
                    Err(_) => {
                        if state.is_none() {
                            return Err(StreamError::NoBase(wait_base));
                        }
                        None
                    }
                }
            } else {
                rx.try_recv().ok()
            };
            let Some((msg, nbytes)) = msg else { break };
            got_any = true;
            bytes_applied += nbytes;
            let start = |b: BaseMesh, m: &Manifest| {
                let tf = TransferFunction::for_manifest(&args.tf, m)
                    .map_err(|e| StreamError::Protocol(e.to_string()))?;
                let mut params =
                    SelectParams::new(tol.unwrap_or(Tolerance::Pixels(0.0)), m.value_range);
                args.select
                    .apply(&mut params, &tf, m.display_value_range(), &b);
                *fitted.borrow_mut() = Some(tf);
                Session::new(b, params)
                    .map_err(|e| StreamError::Protocol(format!("base mesh: {e}")))
            };
            let step = ingest.apply(msg, &mut state, start, &out_tx);
            if let Some(t) = fitted.borrow_mut().take() {
                tf = t;
            }
            match step {
                Ok(Step::Nodes {
                    nodes,
                    duplicates: d,
                }) => {
                    duplicates += d as u64;
                    applied += nodes.len();
                    if args.psnr {
                        received_nodes.extend(nodes);
                    }
                }
                // (frames count them as nodes applied; progress counts the store's only)
                Ok(Step::Preview { nodes, new }) => {
                    applied += nodes;
                    previews_received += new as u64;
                    preview_duplicates += (nodes - new) as u64;
                }
                Ok(_) => {}
                // before the base mesh there are no frames to keep
                Err(e) if state.is_none() => return Err(e),
                Err(e) => {
                    failure = Some(e);
                    break 'frames;
                }
            }
            // the first image goes out as soon as the base mesh is there
            if state.is_some() && (first_frame_ms.is_none() || Instant::now() >= deadline) {
                break;
            }
        }
        let Some(session) = state.as_mut() else {
            continue;
        };
        let m = ingest.manifest().expect("manifest precedes base");
        // 2. camera and view
        let (lo, hi) = session.base().bounds();
        let center = glam::DVec3::from_array([
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ]);
        let diag = glam::DVec3::from_array(hi).distance(glam::DVec3::from_array(lo));
        let cam = Camera::orbit(
            center,
            args.camera.distance.unwrap_or(1.6 * diag),
            args.camera.azimuth + args.orbit * frame as f64,
            args.camera.elevation,
            args.camera.fov,
            args.size.0,
            args.size.1,
        );
        let view = cam.view_params(tol.map(|t| t.pixels(cam.height)).unwrap_or(0.0));
        if last_view != Some(view) {
            let _ = out_tx.send(ClientMsg::View(view));
            last_view = Some(view);
        }
        // 3. refine
        let tr = Instant::now();
        let mode = match (tol, args.orbit != 0.0) {
            (None, _) => Mode::Complete,
            (Some(_), true) => Mode::Interactive,
            (Some(_), false) => Mode::Progressive,
        };
        let fst = session
            .frame(&cam, mode)
            .map_err(|e| StreamError::Protocol(e.to_string()))?;
        let refine_ms = tr.elapsed().as_secs_f64() * 1e3;
        // 4. render
        let trn = Instant::now();
        let tets = session.mesh().piece_counts().1;
        let img = if args.no_render {
            None
        } else {
            let path = args.out.join(format!("frame_{frame:04}.png"));
            Some(draw_png(&gpu, session, m, &cam, &tf, &path)?)
        };
        let render_ms = trn.elapsed().as_secs_f64() * 1e3;
        if first_frame_ms.is_none() {
            first_frame_ms = Some(t0.elapsed().as_secs_f64() * 1e3);
        }
        let view_complete = fst.converged && session.view_complete();
        last_cam = Some(cam);
        frames.push(FrameRecord {
            frame,
            bytes_received: bytes_applied,
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
        if args.until_converged && view_complete && !ingest.levelset_pending() {
            break;
        }
        if args.until_complete
            && ingest.ended()
            && session.is_converged()
            && !ingest.levelset_pending()
        {
            break;
        }
    }
    drop(out_tx);
    if let (Some(path), Some(session), Some(cam), Some(m)) =
        (&args.final_png, &state, last_cam, ingest.manifest())
    {
        draw_png(&gpu, session, m, &cam, &tf, path)?;
    }
    let (nodes_received, nodes_total) = state.as_ref().map_or((0, 0), Session::progress);
    // (a base mesh of 0 levels has no nodes: it is complete as soon as it is there)
    let complete = state.is_some() && nodes_received == nodes_total;
    let clipped = state.as_ref().is_some_and(Session::has_levelset);
    // 5. accuracy against the full-resolution reference, once everything has arrived
    if args.psnr && failure.is_none() {
        if let (true, Some(session), Some(m)) = (complete, &state, ingest.manifest()) {
            let base = session.base();
            received_nodes.sort_by_key(|n| n.id);
            received_nodes.dedup_by_key(|n| n.id);
            let empty: Vec<u8> = received_nodes.iter().map(|n| n.empty_children).collect();
            let values = synthesize_all(base, &base.vertex_keys(), received_nodes.drain(..))
                .map_err(|e| StreamError::Protocol(e.to_string()))?;
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
    task.abort();
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
        bytes_received: net.bytes.load(Ordering::Relaxed),
        reconnects: net.reconnects.load(Ordering::Relaxed),
        complete,
        first_frame_ms,
        clipped,
        levelset_error: ingest.levelset_error().map(str::to_owned),
        tf,
    };
    Ok(Streamed {
        report,
        base,
        mesh,
        levelset,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_protocol::shapes::box5;
    use tetwave_protocol::store_format::Encoding;
    use tetwave_protocol::testing::{manifest_for, unsampled_base};
    use tetwave_protocol::wavelet::LevelSteps;

    /// A manifest whose encoding the block decoder cannot read (a server of another build, a
    /// hostile one) is a protocol error, before any block is decoded with it.
    #[test]
    fn a_manifest_with_an_unreadable_encoding_is_refused() {
        let base = unsampled_base(2, box5([0.0; 3], [1.0; 3]));
        for (encoding, ok) in [
            (Encoding::uniform(12, 0.01), true),
            (Encoding::uniform(40, 0.01), false),
            (
                Encoding::Quantized {
                    bits: 12,
                    step: 0.01,
                    levels: LevelSteps {
                        ratio: 0.5,
                        cap: 2.0,
                    },
                },
                false,
            ),
        ] {
            let m = Manifest {
                encoding,
                ..manifest_for(&base)
            };
            let got = BlockDecoder::default().decode(ServerMsg::Start(Box::new(SessionStart {
                manifest: m,
                base: base.clone(),
            })));
            assert_eq!(got.is_ok(), ok, "{:?}", got.err());
        }
    }
}
