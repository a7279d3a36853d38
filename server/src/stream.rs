//! `tetwave-server serve`: the HTTP + WebSocket front of a store (axum on tokio).
//!
//! | route                      | answer                                                            |
//! |----------------------------|-------------------------------------------------------------------|
//! | `GET /healthz`             | JSON `{status, connections, rss_kib, peak_rss_kib}` (never needs the token) |
//! | `GET /v1/manifest`         | the store's manifest, JSON                                        |
//! | `GET /v1/base`             | one wire frame: `ServerMsg::Base`                                 |
//! | `GET /v1/nodes?from=&to=`  | one wire frame: `ServerMsg::Nodes { seq: 0, nodes: from..to }`    |
//! | `GET /v1/stream[?order=]`  | WebSocket: the progressive stream (below)                         |
//! | `GET /v1/render?…`         | fallback PNG ([`crate::render_service`])                          |
//! | `GET /`                    | a small page showing fallback images ([`crate::render_service`])  |
//!
//! **Stream.** The client sends `Hello` first (version must match; with a token configured it must
//! carry it, else `Error { code: 401 }` and close). The server answers `Manifest`, `Base`, then
//! `Nodes` batches (`seq` 0, 1, 2, …) in the configured [`Order`], skipping what `Hello.have` covers,
//! then `End { nodes_sent }`. Client messages are read concurrently: `View` re-prioritises what is not
//! sent yet (view order), `Want` queues ranges to (re)send ahead of the order (followed by another
//! `End`), `Cancel` drops ranges, `Ack { seq }` acknowledges every batch up to `seq`.
//!
//! **Backpressure.** At most [`ServeConfig::window`] batches may be un-acknowledged; beyond that the
//! connection waits for an `Ack` (and each send waits for the socket). A connection holds its
//! schedule (two bitsets over node ids, the queued `Want` ranges, and for view order one chunk of
//! ids) and at most one encoded batch: never a queue of frames. A slow client slows only itself.

use crate::render_service::{self, RenderParams, RenderService};
use axum::body::Bytes;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use futures_util::{SinkExt, StreamExt};
use glam::DVec3;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use tetwave_protocol::order::shuffle;
use tetwave_protocol::view::{data_weight, screen_error, tet_sphere, Camera, Tolerance, View};
use tetwave_protocol::wire::{
    decode_client, encode, ClientMsg, IdRange, ServerMsg, ViewParams, PROTOCOL_VERSION,
};
use tetwave_protocol::{DetailNode, Forest, LatticeTet, TetId};
use tetwave_store::{Store, StoreError};
use tokio::sync::mpsc;

/// The order detail nodes are streamed in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Order {
    /// Breadth-first: increasing id, so level by level.
    Level,
    /// Largest subtree max |detail| first.
    Magnitude,
    /// Largest screen-space (× data) error for the client's last `View` first.
    View,
    /// A seeded shuffle ([`tetwave_protocol::order::shuffle`] of the ids; testing).
    Random,
}

impl Order {
    pub fn parse(s: &str) -> Option<Order> {
        match s {
            "level" => Some(Order::Level),
            "magnitude" => Some(Order::Magnitude),
            "view" => Some(Order::View),
            "random" => Some(Order::Random),
            _ => None,
        }
    }
}

/// Serving parameters.
#[derive(Debug, Clone)]
pub struct ServeConfig {
    /// Required from every client when set (`Authorization: Bearer T`, `?token=T`, or `Hello.token`).
    pub token: Option<String>,
    /// Default stream order (a client may ask for another with `/v1/stream?order=`).
    pub order: Order,
    /// Nodes per `Nodes` batch.
    pub batch: usize,
    /// Most un-acknowledged batches in flight per connection.
    pub window: u64,
    /// A connection that sends nothing for this long while the server waits on it is closed.
    pub idle_timeout: Duration,
    /// Seed of the random order.
    pub seed: u64,
    /// Keep every node in memory when the store's nodes take at most this many bytes; above it,
    /// batches are read from the store on demand.
    pub cache_limit_bytes: u64,
    /// Most nodes one `GET /v1/nodes` may ask for.
    pub max_range: u64,
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            token: None,
            order: Order::Level,
            batch: 512,
            window: 8,
            idle_timeout: Duration::from_secs(120),
            seed: 0x7e7_3a7e,
            cache_limit_bytes: 512 << 20,
            max_range: 1 << 16,
        }
    }
}

/// Per-node geometry for view-dependent order: bounding spheres, in world units.
struct Geometry {
    centre: Vec<[f32; 3]>,
    /// Bounding-sphere radius ([`tet_sphere`]).
    radius: Vec<f32>,
}

/// What every connection shares: the store, encoded frames that never change, per-node metadata.
pub struct Shared {
    pub store: Store,
    pub config: ServeConfig,
    forest: Forest,
    nodes: u64,
    manifest_json: Bytes,
    manifest_frame: Bytes,
    base_frame: Bytes,
    /// Every node, when the store is small enough ([`ServeConfig::cache_limit_bytes`]).
    cache: Option<Vec<DetailNode>>,
    /// `subtree_max_abs` of every node.
    smax: Vec<f32>,
    magnitude_perm: OnceLock<Arc<Vec<TetId>>>,
    random_perm: OnceLock<Arc<Vec<TetId>>>,
    geometry: OnceLock<Arc<Geometry>>,
    connections: AtomicU64,
    pub render: RenderService,
}

/// Nodes read per step while loading metadata.
const LOAD_CHUNK: u64 = 1 << 16;

impl Shared {
    /// Opens the store and prepares what connections share.
    pub fn open(dir: &std::path::Path, config: ServeConfig) -> Result<Arc<Shared>, ServeError> {
        let store = Store::open(dir)?;
        let forest = store.forest();
        let nodes = store.manifest.counts.nodes;
        if nodes > u32::MAX as u64 {
            return Err(ServeError::TooLarge(nodes));
        }
        let manifest_json = Bytes::from(
            serde_json::to_vec_pretty(&store.manifest)
                .map_err(|e| ServeError::Encode(e.to_string()))?,
        );
        let manifest_frame = Bytes::from(
            encode(&ServerMsg::Manifest(Box::new(store.manifest.clone())))
                .map_err(|e| ServeError::Encode(e.to_string()))?,
        );
        let base_frame = Bytes::from(
            encode(&ServerMsg::Base(Box::new(store.base.clone())))
                .map_err(|e| ServeError::Encode(e.to_string()))?,
        );
        // rough in-memory size of every node: the struct, its allocation and its coefficients
        let est = nodes * (std::mem::size_of::<DetailNode>() as u64 + 16)
            + store.manifest.counts.coefficients * 4;
        let keep = est <= config.cache_limit_bytes;
        let mut cache = keep.then(|| Vec::with_capacity(nodes as usize));
        let mut smax = Vec::with_capacity(nodes as usize);
        let mut from = 0;
        while from < nodes {
            let to = (from + LOAD_CHUNK).min(nodes);
            let part = store.read_nodes(from, to)?;
            smax.extend(part.iter().map(|n| n.subtree_max_abs));
            if let Some(c) = cache.as_mut() {
                c.extend(part);
            }
            from = to;
        }
        tracing::info!(
            nodes,
            cached = keep,
            "store {} opened for serving",
            dir.display()
        );
        let render = RenderService::new(dir);
        Ok(Arc::new(Shared {
            store,
            config,
            forest,
            nodes,
            manifest_json,
            manifest_frame,
            base_frame,
            cache,
            smax,
            magnitude_perm: OnceLock::new(),
            random_perm: OnceLock::new(),
            geometry: OnceLock::new(),
            connections: AtomicU64::new(0),
            render,
        }))
    }

    /// Number of detail nodes.
    pub fn nodes(&self) -> u64 {
        self.nodes
    }

    /// Open WebSocket connections.
    pub fn connections(&self) -> u64 {
        self.connections.load(AtomicOrdering::Relaxed)
    }

    fn magnitude_perm(&self) -> Arc<Vec<TetId>> {
        self.magnitude_perm
            .get_or_init(|| {
                let mut p: Vec<TetId> = (0..self.nodes).collect();
                // largest first; ties by id (coarse before fine)
                p.sort_by(|&a, &b| {
                    self.smax[b as usize]
                        .total_cmp(&self.smax[a as usize])
                        .then(a.cmp(&b))
                });
                Arc::new(p)
            })
            .clone()
    }

    fn random_perm(&self) -> Arc<Vec<TetId>> {
        self.random_perm
            .get_or_init(|| {
                let mut p: Vec<TetId> = (0..self.nodes).collect();
                shuffle(&mut p, self.config.seed);
                Arc::new(p)
            })
            .clone()
    }

    fn geometry(&self) -> Arc<Geometry> {
        self.geometry
            .get_or_init(|| {
                let base = &self.store.base;
                let n = self.nodes as usize;
                let mut centre = Vec::with_capacity(n);
                let mut radius = Vec::with_capacity(n);
                for id in 0..self.nodes {
                    let t = LatticeTet::from_id(&self.forest, id);
                    let (c, r) =
                        tet_sphere(t.v.map(|w| DVec3::from_array(base.position(t.base, &w))));
                    centre.push(c.to_array());
                    radius.push(r);
                }
                Arc::new(Geometry { centre, radius })
            })
            .clone()
    }

    /// The nodes `ids` (in that order when cached, else in increasing id order).
    fn fetch(&self, ids: &mut [TetId]) -> Result<Vec<DetailNode>, StoreError> {
        if let Some(c) = &self.cache {
            return Ok(ids.iter().map(|&i| c[i as usize].clone()).collect());
        }
        ids.sort_unstable();
        let mut out = Vec::with_capacity(ids.len());
        let mut i = 0;
        while i < ids.len() {
            let mut j = i + 1;
            while j < ids.len() && ids[j] == ids[j - 1] + 1 {
                j += 1;
            }
            out.extend(self.store.read_nodes(ids[i], ids[j - 1] + 1)?);
            i = j;
        }
        Ok(out)
    }

    /// The default camera of view order before a client sends its own (the render CLI's default).
    fn default_view(&self) -> ViewParams {
        let (lo, hi) = self.store.base.bounds();
        let c = [
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ];
        let diag = (0..3).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f64>().sqrt();
        let (az, el) = (35f64.to_radians(), 25f64.to_radians());
        let d = 1.6 * diag;
        ViewParams {
            eye: [
                c[0] + d * el.cos() * az.cos(),
                c[1] + d * el.cos() * az.sin(),
                c[2] + d * el.sin(),
            ],
            target: c,
            up: [0.0, 0.0, 1.0],
            fovy_deg: 40.0,
            width: 512,
            height: 512,
            tol_px: 1.0,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("cannot encode: {0}")]
    Encode(String),
    #[error("{0} nodes: more than this server's 2^32 limit")]
    TooLarge(u64),
    #[error("{addr}: {source}")]
    Bind {
        addr: String,
        source: std::io::Error,
    },
    #[error("server: {0}")]
    Io(#[from] std::io::Error),
}

// ---------------------------------------------------------------------------------------------
// HTTP

/// The application: every route, with token enforcement.
pub fn app(shared: Arc<Shared>) -> Router {
    let protected = Router::new()
        .route("/", get(page))
        .route("/v1/manifest", get(manifest))
        .route("/v1/base", get(base))
        .route("/v1/nodes", get(nodes))
        .route("/v1/render", get(render))
        .route_layer(middleware::from_fn_with_state(
            shared.clone(),
            require_token,
        ));
    Router::new()
        .route("/healthz", get(healthz))
        // the stream checks the token in `Hello` (or on the upgrade request, when given there)
        .route("/v1/stream", get(stream))
        .merge(protected)
        .with_state(shared)
}

/// Binds `addr` and serves until the process ends.
pub async fn serve(addr: &str, shared: Arc<Shared>) -> Result<(), ServeError> {
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| ServeError::Bind {
            addr: addr.into(),
            source,
        })?;
    serve_on(listener, shared).await
}

/// Serves on a bound listener (tests bind `127.0.0.1:0`).
pub async fn serve_on(
    listener: tokio::net::TcpListener,
    shared: Arc<Shared>,
) -> Result<(), ServeError> {
    axum::serve(listener, app(shared)).await?;
    Ok(())
}

/// Constant-time string equality (the token check must not leak a prefix by timing).
fn same(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The token a request carries: `Authorization: Bearer T` or `?token=T`.
fn request_token(headers: &HeaderMap, uri: &axum::http::Uri) -> Option<String> {
    if let Some(v) = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
    {
        if let Some(t) = v.strip_prefix("Bearer ") {
            return Some(t.trim().to_string());
        }
    }
    let q: Query<HashMap<String, String>> = Query::try_from_uri(uri).ok()?;
    q.0.get("token").cloned()
}

async fn require_token(State(s): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    if let Some(want) = &s.config.token {
        let ok = request_token(req.headers(), req.uri()).is_some_and(|t| same(&t, want));
        if !ok {
            return unauthorized();
        }
    }
    next.run(req).await
}

fn unauthorized() -> Response {
    (
        StatusCode::UNAUTHORIZED,
        [(header::WWW_AUTHENTICATE, "Bearer")],
        "missing or wrong token\n",
    )
        .into_response()
}

fn bad_request(msg: impl Into<String>) -> Response {
    let mut m = msg.into();
    m.push('\n');
    (StatusCode::BAD_REQUEST, m).into_response()
}

fn frame_response(bytes: Bytes) -> Response {
    (
        [
            (header::CONTENT_TYPE, "application/octet-stream"),
            (header::CACHE_CONTROL, "public, max-age=3600"),
        ],
        bytes,
    )
        .into_response()
}

/// Resident and peak resident set size of this process, KiB (Linux; `None` elsewhere).
pub fn rss_kib() -> (Option<u64>, Option<u64>) {
    let Ok(s) = std::fs::read_to_string("/proc/self/status") else {
        return (None, None);
    };
    let field = |name: &str| {
        s.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
    };
    (field("VmRSS:"), field("VmHWM:"))
}

async fn healthz(State(s): State<Arc<Shared>>) -> Response {
    let (rss, peak) = rss_kib();
    let body = serde_json::json!({
        "status": "ok",
        "dataset": s.store.manifest.dataset,
        "nodes": s.nodes,
        "connections": s.connections(),
        "rss_kib": rss,
        "peak_rss_kib": peak,
    });
    (
        [(header::CONTENT_TYPE, "application/json")],
        body.to_string(),
    )
        .into_response()
}

async fn manifest(State(s): State<Arc<Shared>>) -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        s.manifest_json.clone(),
    )
        .into_response()
}

async fn base(State(s): State<Arc<Shared>>) -> Response {
    frame_response(s.base_frame.clone())
}

async fn nodes(State(s): State<Arc<Shared>>, Query(q): Query<HashMap<String, String>>) -> Response {
    let num = |k: &str| -> Result<u64, String> {
        let v = q.get(k).ok_or_else(|| format!("missing `{k}`"))?;
        v.parse::<u64>()
            .map_err(|_| format!("`{k}` is not a node id: {v:?}"))
    };
    let (from, to) = match (num("from"), num("to")) {
        (Ok(a), Ok(b)) => (a, b),
        (Err(e), _) | (_, Err(e)) => return bad_request(e),
    };
    if from > to || to > s.nodes {
        return bad_request(format!(
            "range {from}..{to} is not within 0..{} nodes",
            s.nodes
        ));
    }
    if to - from > s.config.max_range {
        return bad_request(format!(
            "range of {} nodes exceeds the {}-node limit",
            to - from,
            s.config.max_range
        ));
    }
    let s2 = s.clone();
    let res = tokio::task::spawn_blocking(move || {
        let mut ids: Vec<TetId> = (from..to).collect();
        let nodes = s2.fetch(&mut ids)?;
        encode(&ServerMsg::Nodes { seq: 0, nodes }).map_err(|e| ServeError::Encode(e.to_string()))
    })
    .await;
    match res {
        Ok(Ok(f)) => frame_response(Bytes::from(f)),
        Ok(Err(e)) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// `GET /v1/render`.
async fn render(
    State(s): State<Arc<Shared>>,
    Query(q): Query<HashMap<String, String>>,
) -> Response {
    let p = match RenderParams::parse(&q, s.store.manifest.levels) {
        Ok(p) => p,
        Err(m) => return bad_request(m),
    };
    let s2 = s.clone();
    let r = tokio::task::spawn_blocking(move || {
        let r = s2.render.render(&p)?;
        let png = r
            .image
            .png_bytes()
            .map_err(|e| (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        Ok::<_, (StatusCode, String)>((r, png))
    })
    .await;
    match r {
        Ok(Ok((r, png))) => (
            [
                (header::CONTENT_TYPE, "image/png".to_string()),
                (header::CACHE_CONTROL, "no-store".to_string()),
                (
                    header::HeaderName::from_static("x-tetwave-renderer"),
                    r.renderer
                        .replace(|c: char| !c.is_ascii_graphic() && c != ' ', "?"),
                ),
                (
                    header::HeaderName::from_static("x-tetwave-level"),
                    r.level.to_string(),
                ),
                (
                    header::HeaderName::from_static("x-tetwave-tets"),
                    r.tets.to_string(),
                ),
            ],
            png,
        )
            .into_response(),
        Ok(Err((code, m))) => (code, m).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// `GET /`: the fallback viewer page.
async fn page(State(s): State<Arc<Shared>>) -> Response {
    let html = render_service::page_html(&s.store.manifest.dataset);
    ([(header::CACHE_CONTROL, "no-store")], Html(html)).into_response()
}

/// Largest client frame accepted on the stream (a `Hello` or `Want` of `MAX_RANGES` ranges fits).
const MAX_CLIENT_MESSAGE: usize = 4 << 20;

async fn stream(
    State(s): State<Arc<Shared>>,
    Query(q): Query<HashMap<String, String>>,
    headers: HeaderMap,
    ws: WebSocketUpgrade,
) -> Response {
    let order = match q.get("order") {
        None => s.config.order,
        Some(o) => match Order::parse(o) {
            Some(o) => o,
            None => {
                return bad_request(format!(
                    "unknown order {o:?} (level, magnitude, view, random)"
                ))
            }
        },
    };
    // a token given on the upgrade request must be right; an absent one is checked in `Hello`
    let pre_auth = match (
        &s.config.token,
        headers.get(header::AUTHORIZATION),
        q.get("token"),
    ) {
        (None, ..) => true,
        (Some(want), Some(h), _) => match h.to_str().ok().and_then(|v| v.strip_prefix("Bearer ")) {
            Some(t) if same(t.trim(), want) => true,
            _ => return unauthorized(),
        },
        (Some(want), None, Some(t)) => {
            if !same(t, want) {
                return unauthorized();
            }
            true
        }
        (Some(_), None, None) => false,
    };
    ws.max_message_size(MAX_CLIENT_MESSAGE)
        .max_frame_size(MAX_CLIENT_MESSAGE)
        .on_upgrade(move |socket| async move {
            s.connections.fetch_add(1, AtomicOrdering::Relaxed);
            let r = run_connection(socket, s.clone(), order, pre_auth).await;
            s.connections.fetch_sub(1, AtomicOrdering::Relaxed);
            if let Err(e) = r {
                tracing::debug!("stream connection ended: {e}");
            }
        })
}

// ---------------------------------------------------------------------------------------------
// Per-connection schedule

/// A fixed-size set of node ids.
struct BitSet(Vec<u64>);

impl BitSet {
    fn new(n: u64) -> Self {
        BitSet(vec![0; n.div_ceil(64) as usize])
    }
    #[inline]
    fn get(&self, i: u64) -> bool {
        self.0[(i / 64) as usize] >> (i % 64) & 1 == 1
    }
    #[inline]
    fn set(&mut self, i: u64) {
        self.0[(i / 64) as usize] |= 1 << (i % 64);
    }
    #[inline]
    fn clear(&mut self, i: u64) {
        self.0[(i / 64) as usize] &= !(1 << (i % 64));
    }
}

enum Plan {
    /// Increasing id from `cursor`.
    Level { cursor: u64 },
    /// A shared permutation, from `cursor`.
    Perm {
        perm: Arc<Vec<TetId>>,
        cursor: usize,
    },
    /// View order: `chunk` holds the best pending ids for `view`, best last (popped from the end);
    /// recomputed when it runs out or the view changes.
    View {
        view: ViewParams,
        chunk: Vec<TetId>,
        stale: bool,
    },
}

/// What one connection still has to send.
struct Schedule {
    n: u64,
    /// Sent, held by the client (`have`), or cancelled: the order skips these.
    done: BitSet,
    /// Cancelled: `Want` ranges skip these too (until a later `Want` names them again).
    cancelled: BitSet,
    /// Ids not yet done.
    remaining: u64,
    /// Explicit requests, served before the order.
    wants: VecDeque<(TetId, TetId)>,
    plan: Plan,
}

/// Most queued `Want` ranges per connection.
const MAX_QUEUED_WANTS: usize = 1 << 18;

impl Schedule {
    fn new(s: &Shared, order: Order) -> Self {
        let n = s.nodes;
        let plan = match order {
            Order::Level => Plan::Level { cursor: 0 },
            Order::Magnitude => Plan::Perm {
                perm: s.magnitude_perm(),
                cursor: 0,
            },
            Order::Random => Plan::Perm {
                perm: s.random_perm(),
                cursor: 0,
            },
            Order::View => Plan::View {
                view: s.default_view(),
                chunk: Vec::new(),
                stale: true,
            },
        };
        Schedule {
            n,
            done: BitSet::new(n),
            cancelled: BitSet::new(n),
            remaining: n,
            wants: VecDeque::new(),
            plan,
        }
    }

    fn clip(&self, r: &IdRange) -> (u64, u64) {
        (r.from.min(self.n), r.to.min(self.n))
    }

    fn mark_done(&mut self, i: TetId) {
        if !self.done.get(i) {
            self.done.set(i);
            self.remaining -= 1;
        }
    }

    fn have(&mut self, ranges: &[IdRange]) {
        for r in ranges {
            let (a, b) = self.clip(r);
            for i in a..b {
                self.mark_done(i);
            }
        }
    }

    fn cancel(&mut self, ranges: &[IdRange]) {
        for r in ranges {
            let (a, b) = self.clip(r);
            for i in a..b {
                self.mark_done(i);
                self.cancelled.set(i);
            }
        }
    }

    /// Queues ranges; `false` when the queue would exceed its bound.
    fn want(&mut self, ranges: &[IdRange]) -> bool {
        if self.wants.len() + ranges.len() > MAX_QUEUED_WANTS {
            return false;
        }
        for r in ranges {
            let (a, b) = self.clip(r);
            if a < b {
                for i in a..b {
                    self.cancelled.clear(i);
                }
                self.wants.push_back((a, b));
            }
        }
        true
    }

    fn set_view(&mut self, v: ViewParams) {
        if let Plan::View { view, stale, .. } = &mut self.plan {
            *view = v;
            *stale = true;
        }
    }

    fn has_work(&self) -> bool {
        !self.wants.is_empty() || self.remaining > 0
    }

    /// Up to `max` ids to send next (wanted ranges first, then the order).
    fn next_batch(&mut self, s: &Shared, max: usize) -> Vec<TetId> {
        let mut out = Vec::with_capacity(max.min(self.n as usize));
        while out.len() < max {
            let Some((a, b)) = self.wants.front_mut() else {
                break;
            };
            while *a < *b && out.len() < max {
                let i = *a;
                *a += 1;
                if !self.cancelled.get(i) {
                    out.push(i);
                }
            }
            if *a >= *b {
                self.wants.pop_front();
            }
        }
        for &i in &out {
            self.mark_done(i);
        }
        while out.len() < max && self.remaining > 0 {
            let i = match &mut self.plan {
                Plan::Level { cursor } => {
                    while *cursor < self.n && self.done.get(*cursor) {
                        *cursor += 1;
                    }
                    if *cursor >= self.n {
                        break;
                    }
                    *cursor
                }
                Plan::Perm { perm, cursor } => {
                    while *cursor < perm.len() && self.done.get(perm[*cursor]) {
                        *cursor += 1;
                    }
                    if *cursor >= perm.len() {
                        break;
                    }
                    perm[*cursor]
                }
                Plan::View { view, chunk, stale } => {
                    while chunk.last().is_some_and(|&i| self.done.get(i)) {
                        chunk.pop();
                    }
                    if *stale || chunk.is_empty() {
                        *chunk = view_chunk(s, view, &self.done, self.remaining);
                        *stale = false;
                    }
                    match chunk.pop() {
                        Some(i) => i,
                        None => break,
                    }
                }
            };
            self.mark_done(i);
            out.push(i);
        }
        out
    }
}

/// Detail magnitude (relative to the value range) from which a node's data weight is full.
pub const DATA_DELTA: f32 = 0.01;

/// Screen-space error × data term of node `i` for a view: the priority of view order, with the
/// criterion selection uses ([`tetwave_protocol::view`]) so that the order follows what the client
/// will want.
struct ViewPriority {
    view: View,
    value_range: [f32; 2],
}

impl ViewPriority {
    fn new(v: &ViewParams, value_range: [f32; 2]) -> Self {
        ViewPriority {
            view: View::new(&Camera::from_view_params(v), Tolerance::Pixels(v.tol_px)),
            value_range,
        }
    }

    /// [`screen_error`] with the data weight (δ = [`DATA_DELTA`]) floored at 10⁻³, × 10⁻⁶ outside
    /// the view frustum: flat or hidden subtrees last, but still sent.
    #[inline]
    fn eval(&self, centre: [f32; 3], radius: f32, smax: f32) -> f32 {
        let c = DVec3::from_array(centre.map(f64::from));
        let r = radius as f64;
        let data = data_weight(smax, self.value_range, DATA_DELTA).max(1e-3);
        let mut e = screen_error(&self.view, c, r, data);
        if !self.view.sphere_visible(c, r) {
            e *= 1e-6;
        }
        if e.is_finite() {
            e as f32
        } else {
            f32::MAX
        }
    }
}

/// The best not-yet-done ids for `view`, best last. Takes at most `max(4096, n/16)` of them, so a
/// connection recomputes at most ~16 times over the whole stream plus once per `View`.
fn view_chunk(s: &Shared, view: &ViewParams, done: &BitSet, remaining: u64) -> Vec<TetId> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    let m = ((s.nodes / 16).max(4096)).min(remaining) as usize;
    if m == 0 {
        return Vec::new();
    }
    let g = s.geometry();
    let p = ViewPriority::new(view, s.store.manifest.value_range);
    // min-heap of the m best (priority bits: non-negative f32 order as their bits)
    let mut heap: BinaryHeap<Reverse<(u32, Reverse<TetId>)>> = BinaryHeap::with_capacity(m + 1);
    for i in 0..s.nodes {
        if done.get(i) {
            continue;
        }
        let u = i as usize;
        let e = p
            .eval(g.centre[u], g.radius[u], s.smax[u])
            .max(0.0)
            .to_bits();
        let item = Reverse((e, Reverse(i)));
        if heap.len() < m {
            heap.push(item);
        } else if heap.peek().is_some_and(|top| item < *top) {
            heap.pop();
            heap.push(item);
        }
    }
    // ascending priority (worst first), so popping from the end gives the best
    let mut v: Vec<(u32, Reverse<TetId>)> = heap.into_iter().map(|Reverse(x)| x).collect();
    v.sort_unstable();
    v.into_iter().map(|(_, Reverse(i))| i).collect()
}

// ---------------------------------------------------------------------------------------------
// Connection

#[derive(Debug, thiserror::Error)]
enum ConnError {
    #[error("socket: {0}")]
    Socket(String),
    #[error("client: {0}")]
    Client(String),
    #[error("timed out waiting for the client")]
    Idle,
}

/// What the reader task hands the connection loop.
enum Incoming {
    Msg(ClientMsg),
    Bad(String),
}

/// How long a client has to send `Hello`.
const HELLO_TIMEOUT: Duration = Duration::from_secs(10);
/// How long one frame may take to go out.
const SEND_TIMEOUT: Duration = Duration::from_secs(60);

async fn run_connection(
    socket: WebSocket,
    s: Arc<Shared>,
    order: Order,
    pre_auth: bool,
) -> Result<(), ConnError> {
    let (mut sink, mut stream) = socket.split();
    let error_frame = |code: u16, message: String| {
        Bytes::from(encode(&ServerMsg::Error { code, message }).unwrap_or_default())
    };

    // 1. Hello
    let first = match tokio::time::timeout(HELLO_TIMEOUT, read_msg(&mut stream)).await {
        Err(_) => return Err(ConnError::Idle),
        Ok(None) => return Ok(()),
        Ok(Some(m)) => m,
    };
    let have = match first {
        Incoming::Msg(ClientMsg::Hello {
            version,
            token,
            have,
        }) => {
            if version != PROTOCOL_VERSION {
                let m = format!("protocol version {version}, server speaks {PROTOCOL_VERSION}");
                let _ = send(&mut sink, error_frame(426, m.clone())).await;
                let _ = sink.close().await;
                return Err(ConnError::Client(m));
            }
            if let (Some(want), false) = (&s.config.token, pre_auth) {
                if !token.as_deref().is_some_and(|t| same(t, want)) {
                    let _ =
                        send(&mut sink, error_frame(401, "missing or wrong token".into())).await;
                    let _ = sink.close().await;
                    return Err(ConnError::Client("unauthorized".into()));
                }
            }
            have
        }
        Incoming::Msg(_) => {
            let m = "the first message must be Hello".to_string();
            let _ = send(&mut sink, error_frame(400, m.clone())).await;
            let _ = sink.close().await;
            return Err(ConnError::Client(m));
        }
        Incoming::Bad(m) => {
            let _ = send(&mut sink, error_frame(400, m.clone())).await;
            let _ = sink.close().await;
            return Err(ConnError::Client(m));
        }
    };

    // 2. reader task: decoded client messages into a small bounded channel
    let (tx, mut rx) = mpsc::channel::<Incoming>(32);
    let reader = tokio::spawn(async move {
        while let Some(m) = read_msg(&mut stream).await {
            let bad = matches!(m, Incoming::Bad(_));
            if tx.send(m).await.is_err() || bad {
                break;
            }
        }
    });
    struct AbortOnDrop(tokio::task::JoinHandle<()>);
    impl Drop for AbortOnDrop {
        fn drop(&mut self) {
            self.0.abort();
        }
    }
    let _reader = AbortOnDrop(reader);

    // 3. manifest, base
    send(&mut sink, s.manifest_frame.clone()).await?;
    send(&mut sink, s.base_frame.clone()).await?;

    // 4. nodes
    let sched_s = s.clone();
    let mut sched = tokio::task::spawn_blocking(move || {
        let mut sc = Schedule::new(&sched_s, order);
        sc.have(&have);
        sc
    })
    .await
    .map_err(|e| ConnError::Socket(e.to_string()))?;
    let mut next_seq = 0u64;
    let mut acked = 0u64; // batches acknowledged: seq < acked
    let mut nodes_sent = 0u64;
    let mut end_due = true;
    let batch = s.config.batch.max(1);
    let window = s.config.window.max(1);

    loop {
        // control messages that are already here (coalesce views: only the last one counts)
        let mut view = None;
        loop {
            match rx.try_recv() {
                Ok(m) => match handle(&mut sched, m, &mut acked, next_seq, &mut end_due) {
                    Ok(Some(v)) => view = Some(v),
                    Ok(None) => {}
                    Err(e) => {
                        let _ = send(&mut sink, error_frame(400, e.to_string())).await;
                        let _ = sink.close().await;
                        return Err(e);
                    }
                },
                Err(mpsc::error::TryRecvError::Empty) => break,
                Err(mpsc::error::TryRecvError::Disconnected) => {
                    let _ = sink.close().await;
                    return Ok(());
                }
            }
        }
        if let Some(v) = view {
            sched.set_view(v);
        }
        let can_send = next_seq - acked < window;
        if sched.has_work() && can_send {
            let (sc, frame) = {
                let s2 = s.clone();
                let seq = next_seq;
                let mut sc = sched;
                tokio::task::spawn_blocking(move || {
                    let mut ids = sc.next_batch(&s2, batch);
                    let f = s2
                        .fetch(&mut ids)
                        .map_err(|e| e.to_string())
                        .and_then(|nodes| {
                            let k = nodes.len() as u64;
                            encode(&ServerMsg::Nodes { seq, nodes })
                                .map(|f| (f, k))
                                .map_err(|e| e.to_string())
                        });
                    (sc, f)
                })
                .await
                .map_err(|e| ConnError::Socket(e.to_string()))?
            };
            sched = sc;
            let (frame, k) = match frame {
                Ok(x) => x,
                Err(m) => {
                    let _ = send(&mut sink, error_frame(500, m.clone())).await;
                    let _ = sink.close().await;
                    return Err(ConnError::Socket(m));
                }
            };
            if k == 0 {
                continue;
            }
            send(&mut sink, Bytes::from(frame)).await?;
            next_seq += 1;
            nodes_sent += k;
            end_due = true;
            continue;
        }
        if !sched.has_work() && end_due {
            let f = encode(&ServerMsg::End { nodes_sent }).unwrap_or_default();
            send(&mut sink, Bytes::from(f)).await?;
            end_due = false;
            continue;
        }
        // nothing to do until the client says something (an Ack, a Want, a View)
        match tokio::time::timeout(s.config.idle_timeout, rx.recv()).await {
            Err(_) => {
                let _ = sink.close().await;
                return Err(ConnError::Idle);
            }
            Ok(None) => {
                let _ = sink.close().await;
                return Ok(());
            }
            Ok(Some(m)) => match handle(&mut sched, m, &mut acked, next_seq, &mut end_due) {
                Ok(Some(v)) => sched.set_view(v),
                Ok(None) => {}
                Err(e) => {
                    let _ = send(&mut sink, error_frame(400, e.to_string())).await;
                    let _ = sink.close().await;
                    return Err(e);
                }
            },
        }
    }
}

/// Applies one client message; returns a view to apply (views are coalesced by the caller).
fn handle(
    sched: &mut Schedule,
    m: Incoming,
    acked: &mut u64,
    next_seq: u64,
    end_due: &mut bool,
) -> Result<Option<ViewParams>, ConnError> {
    match m {
        Incoming::Bad(e) => Err(ConnError::Client(e)),
        Incoming::Msg(m) => match m {
            ClientMsg::Hello { .. } => Err(ConnError::Client("a second Hello".into())),
            ClientMsg::View(v) => Ok(Some(v)),
            ClientMsg::Want(r) => {
                if !sched.want(&r) {
                    return Err(ConnError::Client("too many queued Want ranges".into()));
                }
                *end_due = true;
                Ok(None)
            }
            ClientMsg::Cancel(r) => {
                sched.cancel(&r);
                Ok(None)
            }
            ClientMsg::Ack { seq } => {
                *acked = (*acked).max(seq.saturating_add(1).min(next_seq));
                Ok(None)
            }
        },
    }
}

type Sink = futures_util::stream::SplitSink<WebSocket, Message>;

/// Sends one frame, bounded by [`SEND_TIMEOUT`].
async fn send(sink: &mut Sink, b: Bytes) -> Result<(), ConnError> {
    match tokio::time::timeout(SEND_TIMEOUT, sink.send(Message::Binary(b))).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(ConnError::Socket(e.to_string())),
        Err(_) => Err(ConnError::Idle),
    }
}

/// The next client message; `None` when the socket closed or failed.
async fn read_msg(stream: &mut futures_util::stream::SplitStream<WebSocket>) -> Option<Incoming> {
    loop {
        match stream.next().await? {
            Err(_) => return None,
            Ok(Message::Binary(b)) => {
                return Some(match decode_client(&b) {
                    Ok(m) => Incoming::Msg(m),
                    Err(e) => Incoming::Bad(e.to_string()),
                })
            }
            Ok(Message::Text(_)) => {
                return Some(Incoming::Bad("text message: frames are binary".into()))
            }
            Ok(Message::Close(_)) => return None,
            Ok(_) => continue, // ping / pong
        }
    }
}
