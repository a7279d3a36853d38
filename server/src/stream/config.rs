//! What `tetwave-server serve` is told: the stream [`Order`] and the [`ServeConfig`].

use super::origin::OriginPolicy;
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

/// The transfer function a session's view order weighs nodes by (image criterion): what the
/// client draws with, named in `/v1/stream?tf=`. `auto` is the `default` preset fitted to the
/// manifest's value histogram, as every client fits it; any other name (or none) gets `default`'s
/// weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ViewTf {
    #[default]
    Default,
    Auto,
}

impl ViewTf {
    /// The `tf` query value: `auto`, else [`ViewTf::Default`].
    pub fn parse(s: Option<&str>) -> ViewTf {
        match s {
            Some(tetwave_render::transfer::AUTO) => ViewTf::Auto,
            _ => ViewTf::Default,
        }
    }
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

/// What view order weighs a node's screen-space error by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ViewCriterion {
    /// How much the node's subtree can change the image under the default transfer function
    /// (`tetwave_protocol::view::ImageCriterion`, the client's default selection).
    Image,
    /// The node's subtree detail relative to the value range (δ = `DATA_DELTA`).
    Data,
}

/// Serving parameters.
#[derive(Debug, Clone)]
pub struct ServeConfig {
    /// Required from every client when set (`Authorization: Bearer T`, `?token=T`, or `Hello.token`).
    pub token: Option<String>,
    /// Default stream order (a client may ask for another with `/v1/stream?order=`).
    pub order: Order,
    /// Nodes in the first `Nodes` batch (and the first after each `View`); each further batch
    /// doubles, up to [`Self::max_batch`]: small batches paint early, large ones code tightly
    /// (each block's adaptive models start afresh, and each frame has its own header).
    pub batch: usize,
    /// Most nodes in one batch.
    pub max_batch: usize,
    /// Most un-acknowledged batches in flight per connection.
    pub window: u64,
    /// A new session of a store with a preview ([`tetwave_protocol::store_format::Preview`]) first
    /// gets preview nodes, most important first, worth at most this share of the store's
    /// `blocks.bin` (0: none; 1, the default: in practice all of it, since `prepare --preview`
    /// makes it a few percent of the store).
    pub preview_share: f64,
    /// A connection that sends nothing for this long while the server waits on it is closed.
    pub idle_timeout: Duration,
    /// Seed of the random order.
    pub seed: u64,
    /// Most bytes of decoded blocks held (least recently used dropped first).
    pub cache_limit_bytes: u64,
    /// Most nodes one `GET /v1/nodes` may ask for.
    pub max_range: u64,
    /// Connection, time and render limits.
    pub limits: Limits,
    /// Host and Origin allowlists.
    pub origins: OriginPolicy,
    /// Recompute every store file's CRC-32 when the store opens (`serve --verify`; reads the whole
    /// store). `base.bin`'s checksum is always checked, and every block's when it is read.
    pub verify_checksums: bool,
    /// What view order weighs the screen-space error by.
    pub view_criterion: ViewCriterion,
    /// Most nodes whose levels' vertex values view order synthesizes at start for exact image
    /// weights (below them it ranks by an enclosure: `walk`'s module documentation).
    pub coarse_nodes: u64,
}

/// What a server admits and for how long; `docs/security.md` lists each with its flag.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Open connections (HTTP and WebSocket) at most; more are closed on accept.
    pub max_connections: usize,
    /// Open HTTP connections per peer address.
    pub max_connections_per_peer: usize,
    /// WebSocket streams per peer address; more get 429.
    pub max_streams_per_peer: usize,
    /// Request headers must arrive within this; an idle keep-alive connection is closed after it.
    pub header_read_timeout: Duration,
    /// Longest an HTTP request other than a render may take (408 after it).
    pub request_timeout: Duration,
    /// Renders that may wait behind the running one; more get 503 with `Retry-After`.
    pub render_queue: usize,
    /// Longest a render may take, waiting included: then 503 and the render is cancelled.
    pub render_deadline: Duration,
    /// Most pixels (width × height) one render may have.
    pub max_render_pixels: u64,
}

impl Default for Limits {
    fn default() -> Self {
        // leave room below the open-file limit for the store's files and the process itself
        let files = super::admission::open_file_limit().unwrap_or(1024);
        Limits {
            max_connections: (files.saturating_sub(64) as usize).clamp(16, 1024),
            max_connections_per_peer: 128,
            max_streams_per_peer: 16,
            header_read_timeout: Duration::from_secs(10),
            request_timeout: Duration::from_secs(60),
            render_queue: 4,
            render_deadline: Duration::from_secs(30),
            max_render_pixels: 2048 * 2048,
        }
    }
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            token: None,
            order: Order::Level,
            batch: 512,
            max_batch: 16384,
            window: 8,
            preview_share: 1.0,
            idle_timeout: Duration::from_secs(120),
            seed: 0x7e7_3a7e,
            cache_limit_bytes: 256 << 20,
            max_range: 1 << 16,
            limits: Limits::default(),
            origins: OriginPolicy::default(),
            verify_checksums: false,
            view_criterion: ViewCriterion::Image,
            coarse_nodes: super::walk::COARSE_NODES,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_auto_asks_for_the_fitted_weights() {
        assert_eq!(ViewTf::parse(Some("auto")), ViewTf::Auto);
        for other in [
            None,
            Some("default"),
            Some("opaque"),
            Some("my.json"),
            Some(""),
        ] {
            assert_eq!(ViewTf::parse(other), ViewTf::Default, "{other:?}");
        }
    }
}
