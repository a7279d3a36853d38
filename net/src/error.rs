//! What can go wrong between a client and a server, typed.

use std::time::Duration;
use tetwave_adaptive::mesh::MeshError;
use tetwave_adaptive::session::NodeRejected;
use tetwave_protocol::wire::{WireError, MAX_FRAME_BYTES};
use tetwave_render::transfer::TfError;

/// A stream that failed: the connection, the server's answers, or what they held.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error("bad url {0:?}: expected http://host:port or ws://host:port")]
    Url(String),
    #[error("connection to {url} failed: {reason}")]
    Connect { url: String, reason: String },
    /// Reading a store directly from object storage failed (after its retries), or a block it
    /// sent was refused: the message names the object.
    #[error("{0}")]
    Store(String),
    #[error("server error {code}: {message}")]
    Server { code: u16, message: String },
    /// A message the protocol puts later came first (`what` before `before`).
    #[error("protocol: {what} before {before}")]
    OutOfOrder {
        what: &'static str,
        before: &'static str,
    },
    /// A manifest whose coefficient encoding this client cannot read.
    #[error("protocol: manifest: {0}")]
    Manifest(String),
    #[error("protocol: the server sent a different base mesh on a resumed connection")]
    BaseChanged,
    #[error("protocol: the base mesh ({base_levels} levels, {base_nodes} nodes) disagrees with the manifest ({levels} levels, {nodes} nodes)")]
    Disagrees {
        base_levels: u8,
        base_nodes: u128,
        levels: u8,
        nodes: u64,
    },
    /// A message of the client's own that does not encode.
    #[error("protocol: {0}")]
    Encode(#[from] WireError),
    /// A frame that does not decode, or whose contents fail their checks (a malformed node, an
    /// invalid base mesh).
    #[error("unreadable frame from the server: {0}")]
    BadFrame(String),
    /// A WebSocket message over the client's limit ([`crate::connection::ws_config`]).
    #[error("the server sent a message over the {MAX_FRAME_BYTES}-byte limit ({0})")]
    FrameTooLarge(String),
    /// The connection dropped and the reconnect attempts brought nothing.
    #[error("connection to {url} lost: {reason} (gave up after {retries} reconnect attempts)")]
    Disconnected {
        url: String,
        reason: String,
        retries: u32,
    },
    /// A node the session refused (beyond the hierarchy, or claiming another node's vertex).
    #[error("the server sent an invalid node: {0}")]
    NodeRejected(#[from] NodeRejected),
    /// `End` with nodes missing, still missing after [`crate::MAX_WANT_ROUNDS`] requests.
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
    /// The session could not be built on the base mesh.
    #[error("protocol: base mesh: {0}")]
    BaseMesh(#[source] MeshError),
    /// The transfer function the session selects by could not be made for the manifest.
    #[error(transparent)]
    Tf(#[from] TfError),
    #[error("network runtime: {0}")]
    Runtime(#[source] std::io::Error),
    /// The network task stopped before the stream was complete, with no error of its own.
    #[error("protocol: the network task ended")]
    TaskEnded,
    #[error("protocol: the network task failed: {0}")]
    TaskFailed(#[from] tokio::task::JoinError),
}

/// A GET beside the stream (`/v1/levelset`, `/v1/render`) that failed; names the URL.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("GET {url}: {reason}")]
pub struct HttpError {
    pub url: String,
    pub reason: String,
}
