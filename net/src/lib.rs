//! # tetwave-net
//!
//! The client's side of the wire: a server's address ([`ServerUrl`]), the connection task shared
//! by `tetwave stream` and the viewer ([`connection`]: reconnects, resumes with what is held and
//! re-sends the view) over a [`transport`] (a WebSocket; tests wrap it to inject faults), what the frame loop does with each delivery ([`ingest`]), GETs beside the
//! stream ([`http`]) and the typed [`NetError`]. Feeds a `tetwave-adaptive` session; draws nothing.

pub mod connection;
pub mod error;
pub mod http;
pub mod ingest;
pub mod transport;
pub mod url;

pub use connection::{Connection, Delivery};
pub use error::{HttpError, NetError};
pub use transport::Faults;
pub use url::ServerUrl;

/// `Want` rounds after an `End` with nodes missing before the session fails
/// ([`NetError::Unavailable`]).
pub const MAX_WANT_ROUNDS: u32 = 8;

/// `--max-nodes`' default: see `--max-nodes` of `tetwave stream` and `tetwave view`.
pub const DEFAULT_MAX_NODES: u64 = 1 << 27;
