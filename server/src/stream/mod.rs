//! `tetwave-server serve`: the HTTP + WebSocket front of a store (axum on tokio).
//!
//! | route                      | answer                                                            |
//! |----------------------------|-------------------------------------------------------------------|
//! | `GET /healthz`             | JSON `{status, connections, rss_kib, peak_rss_kib}` (never needs the token) |
//! | `GET /v1/manifest`         | the store's manifest, JSON                                        |
//! | `GET /v1/base`             | one wire frame: `ServerMsg::Base`                                 |
//! | `GET /v1/nodes?from=&to=`  | one wire frame: `ServerMsg::Nodes { seq: 0, block: from..to }`    |
//! | `GET /v1/stream[?order=&tf=]` | WebSocket: the progressive stream (below); `tf=auto`: view order weighs by the fitted function |
//! | `GET /v1/render?…`         | fallback PNG ([`crate::render_service`])                          |
//! | `GET /`                    | a small page showing fallback images ([`crate::render_service`])  |
//!
//! **Stream.** The client sends `Hello` first (version must match; with a token configured it must
//! carry it, else `Error { code: 401 }` and close). The server answers `Start` (manifest and base mesh), then
//! `Nodes` batches (`seq` 0, 1, 2, …) in the configured [`Order`], skipping what `Hello.have` covers,
//! then `End { nodes_sent }`. A session with an empty `have` of a store with a preview first gets
//! `Preview` batches (numbered with the others) of the preview nodes that `Hello.previewed` does
//! not name, within [`ServeConfig::preview_share`] (see `preview`). Client messages are read concurrently: `View` re-prioritises what is not
//! sent yet (view order), `Want` queues ranges to (re)send ahead of the order (followed by another
//! `End`), `Cancel` drops ranges, `Ack { seq }` acknowledges every batch up to `seq`.
//!
//! **Backpressure.** At most [`ServeConfig::window`] batches may be un-acknowledged; beyond that the
//! connection waits for an `Ack` (and each send waits for the socket). A connection holds its
//! schedule (the id ranges sent and cancelled, the queued `Want` ranges, and for view order the
//! frontier of its walk: all growing with what it sent, not with the store) and at most one encoded
//! batch: never a queue of frames. A slow client slows only itself.
//!
//! One concern per file: `config` (order, parameters), `error`, `state` (what connections share),
//! `routes` (the axum application and HTTP handlers), `auth` (the token), `schedule` (what a
//! connection sends next), `walk` (view order's walk of the hierarchy), `preview` (a new session's coarse preview) and `connection` (one
//! WebSocket stream). Dependencies point one way:
//! routes → connection → schedule → state → config; `render_service` knows nothing of this module.

mod admission;
mod auth;
mod background;
mod config;
mod connection;
mod error;
mod origin;
mod preview;
mod routes;
mod schedule;
mod state;
mod walk;

pub use admission::{open_file_limit, Peer};
pub use background::BackgroundServer;
pub use config::{Limits, Order, ServeConfig, ViewCriterion, ViewTf};
pub use error::ServeError;
pub use origin::OriginPolicy;
pub use routes::{app, rss_kib};
pub use schedule::DATA_DELTA;
pub use state::{served_manifest, Shared};

use std::sync::Arc;

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

/// Serves on a bound listener (tests bind `127.0.0.1:0`) under the admission limits
/// ([`Limits`]) until the process ends.
pub async fn serve_on(
    listener: tokio::net::TcpListener,
    shared: Arc<Shared>,
) -> Result<(), ServeError> {
    let app = app(shared.clone());
    admission::accept_loop(listener, shared, app).await;
    Ok(())
}
