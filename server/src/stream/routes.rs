//! The axum application: every route of the table in [`super`], with the token enforced, and the
//! HTTP handlers; the stream route upgrades to a [`connection`](super::connection).

use super::admission::{NoSlot, Peer};
use super::auth::{self, require_token};
use super::config::{Order, ViewTf};
use super::connection::run_connection;
use super::error::ServeError;
use super::origin::check_origin;
use super::state::Shared;
use crate::render_service::{self, RenderParams};
use axum::body::Bytes;
use axum::error_handling::HandleErrorLayer;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::BoxError;
use axum::Extension;
use axum::Router;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering as AtomicOrdering};
use std::sync::Arc;
use std::time::Duration;
use tetwave_protocol::wire::{encode, ServerMsg};
use tetwave_protocol::TetId;
use tower::ServiceBuilder;
use tower_http::limit::RequestBodyLimitLayer;
use tower_http::timeout::TimeoutLayer;

/// The application: every route, with the Host/Origin allowlists (`stream::origin`) in front of
/// everything, token enforcement, a time limit on every request and a bounded render queue.
pub fn app(shared: Arc<Shared>) -> Router {
    let limits = &shared.config.limits;
    // one render runs (`Shared::render_run`), `render_queue` wait; beyond that 503 at once
    let render_route = get(render).layer(
        ServiceBuilder::new()
            .layer(HandleErrorLayer::new(|_: BoxError| async { busy() }))
            .load_shed()
            .concurrency_limit(1 + limits.render_queue),
    );
    let protected = Router::new()
        .route("/", get(page))
        .route("/v1/manifest", get(manifest))
        .route("/v1/base", get(base))
        .route("/v1/nodes", get(nodes))
        .route("/v1/levelset", get(levelset))
        .route("/v1/render", render_route)
        .route_layer(middleware::from_fn_with_state(
            shared.clone(),
            require_token,
        ));
    // a render's own deadline is shorter than the request time limit
    let request_timeout = limits
        .request_timeout
        .max(limits.render_deadline + Duration::from_secs(1));
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        // the stream checks the token in `Hello` (or on the upgrade request, when given there)
        .route("/v1/stream", get(stream))
        .merge(protected)
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            request_timeout,
        ))
        .layer(RequestBodyLimitLayer::new(MAX_REQUEST_BODY))
        .layer(middleware::from_fn_with_state(shared.clone(), check_origin))
        .with_state(shared)
}

/// Every route is a GET; a request body beyond this is refused (413).
const MAX_REQUEST_BODY: usize = 4096;

/// 503 with `Retry-After`: the render queue is full.
fn busy() -> Response {
    (
        StatusCode::SERVICE_UNAVAILABLE,
        [(header::RETRY_AFTER, "2")],
        "the render queue is full; try again shortly\n",
    )
        .into_response()
}

fn bad_request(msg: impl Into<String>) -> Response {
    let mut m = msg.into();
    m.push('\n');
    (StatusCode::BAD_REQUEST, m).into_response()
}

/// A wire frame. Cacheable by anyone without a token; with one, only by the client that asked
/// (`private, no-store`, `Vary: Authorization`).
fn frame_response(s: &Shared, bytes: Bytes) -> Response {
    (
        [
            (header::CONTENT_TYPE, "application/octet-stream"),
            (header::CACHE_CONTROL, cache_control(s)),
            (header::VARY, "Authorization"),
        ],
        bytes,
    )
        .into_response()
}

fn cache_control(s: &Shared) -> &'static str {
    if s.config.token.is_some() {
        "private, no-store"
    } else {
        "public, max-age=3600"
    }
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

/// `/readyz`: 200 once the store is open and the server takes streams (it is, once it listens;
/// a server of view order is ready once its view-order geometry is computed), 503 while it holds
/// its most connections; a balancer's readiness probe.
async fn readyz(State(s): State<Arc<Shared>>) -> Response {
    let ready = s.view_order_ready() && s.admission.open() < s.config.limits.max_connections;
    let code = if ready {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    (code, if ready { "ready\n" } else { "not ready\n" }).into_response()
}

async fn healthz(State(s): State<Arc<Shared>>) -> Response {
    let (rss, peak) = rss_kib();
    let (hits, reads) = (
        s.block_hits.load(AtomicOrdering::Relaxed),
        s.block_reads.load(AtomicOrdering::Relaxed),
    );
    let held = s.cache_held();
    let body = serde_json::json!({
        "block_cache": {
            "hits": hits,
            "reads": reads,
            "hit_ratio": if hits + reads > 0 { hits as f64 / (hits + reads) as f64 } else { 0.0 },
            "held_blocks": held.0,
            "held_bytes": held.1,
            "limit_bytes": s.config.cache_limit_bytes,
        },
        "status": "ok",
        "dataset": s.store.manifest.dataset,
        "nodes": s.nodes,
        "connections": s.connections(),
        "view_rescans": s.view_rescans.load(AtomicOrdering::Relaxed),
        "open_connections": s.admission.open(),
        "renders": s.render.counts(),
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
        [
            (header::CONTENT_TYPE, "application/json"),
            (header::CACHE_CONTROL, cache_control(&s)),
            (header::VARY, "Authorization"),
        ],
        s.manifest_json.clone(),
    )
        .into_response()
}

async fn base(State(s): State<Arc<Shared>>) -> Response {
    frame_response(&s, s.base_frame.clone())
}

/// The near band of the domain's level set ([`tetwave_protocol::levelset::NearLevelSet`]'s
/// coded form); 404 for a store without one (an input with no outside).
async fn levelset(State(s): State<Arc<Shared>>) -> Response {
    match &s.levelset_near {
        Some(b) => frame_response(&s, b.clone()),
        None => (
            StatusCode::NOT_FOUND,
            "this store has no level set: its input has no outside\n",
        )
            .into_response(),
    }
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
        let block = s2.fetch_block(&mut ids)?;
        encode(&ServerMsg::Nodes { seq: 0, block }).map_err(|e| ServeError::Encode(e.to_string()))
    })
    .await;
    match res {
        Ok(Ok(f)) => frame_response(&s, Bytes::from(f)),
        Ok(Err(e)) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// `GET /v1/render`: within the pixel budget, one at a time behind the bounded queue, under the
/// render deadline; a render whose request is dropped (the client went away, or the deadline
/// passed) is cancelled.
async fn render(
    State(s): State<Arc<Shared>>,
    Query(q): Query<HashMap<String, String>>,
) -> Response {
    let p = match RenderParams::parse(&q, s.store.manifest.levels) {
        Ok(p) => p,
        Err(m) => return bad_request(m),
    };
    let limits = &s.config.limits;
    let pixels = u64::from(p.width) * u64::from(p.height);
    if pixels > limits.max_render_pixels {
        return bad_request(format!(
            "{}×{} = {pixels} pixels exceeds this server's {}-pixel render budget",
            p.width, p.height, limits.max_render_pixels
        ));
    }
    /// Sets the flag when the request future is dropped before the render finished.
    struct CancelOnDrop(Arc<AtomicBool>);
    impl Drop for CancelOnDrop {
        fn drop(&mut self) {
            self.0.store(true, AtomicOrdering::Relaxed);
        }
    }
    let cancel = Arc::new(AtomicBool::new(false));
    let _guard = CancelOnDrop(cancel.clone());
    let deadline = limits.render_deadline;
    let work = async {
        let _turn = s.render_run.lock().await;
        let s2 = s.clone();
        let cancel = cancel.clone();
        tokio::task::spawn_blocking(move || {
            let r = s2.render.render(&p, &cancel)?;
            let png = r
                .image
                .png_bytes()
                .map_err(|e| (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
            Ok::<_, (StatusCode, String)>((r, png))
        })
        .await
    };
    let r = match tokio::time::timeout(deadline, work).await {
        Ok(r) => r,
        Err(_) => {
            return (
                StatusCode::SERVICE_UNAVAILABLE,
                [(header::RETRY_AFTER, "5")],
                format!(
                    "the render did not finish within the {} s deadline\n",
                    deadline.as_secs_f64()
                ),
            )
                .into_response()
        }
    };
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
    let m = &s.store.manifest;
    let html = render_service::page_html(m);
    ([(header::CACHE_CONTROL, "no-store")], Html(html)).into_response()
}

/// Largest client frame accepted on the stream (a `Hello` or `Want` of `MAX_RANGES` ranges fits).
const MAX_CLIENT_MESSAGE: usize = 4 << 20;

async fn stream(
    State(s): State<Arc<Shared>>,
    Query(q): Query<HashMap<String, String>>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
    ws: WebSocketUpgrade,
) -> Response {
    let peer = peer.map(|p| p.0 .0);
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
    // the client's transfer function, for view order's image weights
    let tf = ViewTf::parse(q.get("tf").map(String::as_str));
    // a token given on the upgrade request must be right; an absent one is checked in `Hello`
    let pre_auth = match auth::upgrade_auth(&s, peer, &headers, q.get("token")) {
        Ok(p) => p,
        Err(e) => return e.into_response(),
    };
    let ip = peer.map_or(std::net::IpAddr::from([0, 0, 0, 0]), |p| p.ip());
    let slot = match s.admission.stream(ip) {
        Ok(slot) => slot,
        Err(NoSlot::PeerStreams(n)) => {
            return (
                StatusCode::TOO_MANY_REQUESTS,
                [(header::RETRY_AFTER, "5")],
                format!("this address already has {n} open streams\n"),
            )
                .into_response()
        }
        Err(NoSlot::Full) => {
            return (
                StatusCode::SERVICE_UNAVAILABLE,
                [(header::RETRY_AFTER, "5")],
                "the server holds its most connections\n",
            )
                .into_response()
        }
    };
    ws.max_message_size(MAX_CLIENT_MESSAGE)
        .max_frame_size(MAX_CLIENT_MESSAGE)
        .on_upgrade(move |socket| async move {
            s.connections.fetch_add(1, AtomicOrdering::Relaxed);
            let r = run_connection(socket, s.clone(), (order, tf), pre_auth, peer).await;
            s.connections.fetch_sub(1, AtomicOrdering::Relaxed);
            drop(slot);
            if let Err(e) = r {
                tracing::debug!(peer = ?peer, "stream connection ended: {e}");
            }
        })
}
