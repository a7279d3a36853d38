//! Why a server could not open its store or serve.

use tetwave_store::StoreError;

/// Opening a store for serving ([`super::Shared::open`]) or serving it ([`super::serve`]) failed.
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
