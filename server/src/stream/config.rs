//! What `tetwave-server serve` is told: the stream [`Order`] and the [`ServeConfig`].

use std::time::Duration;

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
    /// Recompute every store file's CRC-32 when the store opens (`serve --verify`; reads the whole
    /// store). The structure and `base.bin`'s checksum are always checked.
    pub verify_checksums: bool,
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
            verify_checksums: false,
        }
    }
}
