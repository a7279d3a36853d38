//! The axum application: every route of the table in [`super`], with the token enforced, and the
//! HTTP handlers; the stream route upgrades to a [`connection`](super::connection).

use super::auth::{self, require_token};
use super::config::Order;
use super::connection::run_connection;
use super::error::ServeError;
use super::state::Shared;
use crate::render_service::{self, RenderParams};
use axum::body::Bytes;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use std::collections::HashMap;
use std::sync::atomic::Ordering as AtomicOrdering;
use std::sync::Arc;
use tetwave_protocol::wire::{encode, ServerMsg};
use tetwave_protocol::TetId;

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
    let pre_auth = match auth::upgrade_auth(s.config.token.as_ref(), &headers, q.get("token")) {
        Ok(p) => p,
        Err(e) => return e.into_response(),
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
