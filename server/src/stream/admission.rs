//! Admission: the accept loop and what it admits. Every TCP connection takes a slot (at most
//! [`Limits::max_connections`] in all and [`Limits::max_connections_per_peer`] per peer address;
//! beyond them a connection is closed at once), request headers must arrive within
//! [`Limits::header_read_timeout`] (hyper's timer: slow-header clients and idle keep-alive
//! connections are closed), and each WebSocket stream holds one of [`Limits::max_streams_per_peer`]
//! stream slots of its peer for its whole life. Handlers find the peer's address in the [`Peer`]
//! request extension.

use super::config::Limits;
use super::state::Shared;
use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tower::ServiceExt;

/// The peer of the connection a request came on.
#[derive(Debug, Clone, Copy)]
pub struct Peer(pub SocketAddr);

#[derive(Default)]
struct Counts {
    connections: usize,
    streams: usize,
}

/// Open connections and streams, in all and per peer address.
pub struct Admission {
    limits: Limits,
    state: Mutex<(usize, HashMap<IpAddr, Counts>)>,
}

/// A held connection or stream slot; released on drop.
pub struct Slot {
    adm: Arc<Admission>,
    ip: IpAddr,
    stream: bool,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut st = self.adm.state.lock().unwrap_or_else(|e| e.into_inner());
        st.0 -= 1;
        if let Some(c) = st.1.get_mut(&self.ip) {
            if self.stream {
                c.streams -= 1;
            } else {
                c.connections -= 1;
            }
            if c.connections == 0 && c.streams == 0 {
                st.1.remove(&self.ip);
            }
        }
    }
}

/// Why a stream slot was refused.
#[derive(Debug)]
pub enum NoSlot {
    /// The server holds its most connections.
    Full,
    /// This peer holds its most streams.
    PeerStreams(usize),
}

impl Admission {
    pub fn new(limits: Limits) -> Arc<Self> {
        Arc::new(Admission {
            limits,
            state: Mutex::new((0, HashMap::new())),
        })
    }

    /// Open connections and streams.
    pub fn open(&self) -> usize {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).0
    }

    /// A slot for a new TCP connection from `ip`, if the limits allow.
    pub fn connection(self: &Arc<Self>, ip: IpAddr) -> Option<Slot> {
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if st.0 >= self.limits.max_connections {
            return None;
        }
        let c = st.1.entry(ip).or_default();
        if c.connections >= self.limits.max_connections_per_peer {
            return None;
        }
        c.connections += 1;
        st.0 += 1;
        Some(Slot {
            adm: self.clone(),
            ip,
            stream: false,
        })
    }

    /// A slot for a WebSocket stream from `ip`, held for the stream's life.
    pub fn stream(self: &Arc<Self>, ip: IpAddr) -> Result<Slot, NoSlot> {
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if st.0 >= self.limits.max_connections {
            return Err(NoSlot::Full);
        }
        let c = st.1.entry(ip).or_default();
        if c.streams >= self.limits.max_streams_per_peer {
            return Err(NoSlot::PeerStreams(self.limits.max_streams_per_peer));
        }
        c.streams += 1;
        st.0 += 1;
        Ok(Slot {
            adm: self.clone(),
            ip,
            stream: true,
        })
    }
}

/// Stream control messages draw on a budget per peer address, shared by all its connections (so
/// reconnecting does not refill it): each message costs one unit plus one per id range. It holds
/// [`BUDGET_BURST`] units and refills at [`BUDGET_PER_SEC`]; a connection whose message overdraws
/// it is closed (1008). An honest client sends a few `Want`s, a `View` per frame and an `Ack` per
/// batch.
pub const BUDGET_PER_SEC: f64 = tetwave_protocol::wire::MAX_RANGES as f64;
/// See [`BUDGET_PER_SEC`].
pub const BUDGET_BURST: f64 = 4.0 * tetwave_protocol::wire::MAX_RANGES as f64;
/// Peers whose budgets are remembered at most (full buckets are forgotten first).
const MAX_BUDGET_PEERS: usize = 4096;

/// Per-peer token buckets of stream control work.
#[derive(Default)]
pub struct PeerBudgets(Mutex<HashMap<IpAddr, (f64, std::time::Instant)>>);

impl PeerBudgets {
    /// Charges `cost` units to `ip`; `false` when its budget is overdrawn.
    pub fn charge(&self, ip: IpAddr, cost: usize) -> bool {
        let now = std::time::Instant::now();
        let level = |e: &(f64, std::time::Instant)| {
            (e.0 + (now - e.1).as_secs_f64() * BUDGET_PER_SEC).min(BUDGET_BURST)
        };
        let mut m = self.0.lock().unwrap_or_else(|e| e.into_inner());
        if m.len() >= MAX_BUDGET_PEERS && !m.contains_key(&ip) {
            m.retain(|_, e| level(e) < BUDGET_BURST);
            if m.len() >= MAX_BUDGET_PEERS {
                m.clear();
            }
        }
        let e = m.entry(ip).or_insert((BUDGET_BURST, now));
        let units = level(e) - cost as f64;
        *e = (units, now);
        units >= 0.0
    }
}

/// The soft limit on open files of this process (Linux: `/proc/self/limits`).
pub fn open_file_limit() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = s.lines().find(|l| l.starts_with("Max open files"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// Accepts connections on `listener` and serves `app` on each, under `shared`'s admission limits,
/// until the process ends.
pub(super) async fn accept_loop(
    listener: tokio::net::TcpListener,
    shared: Arc<Shared>,
    app: axum::Router,
) {
    let header_timeout = shared.config.limits.header_read_timeout;
    loop {
        let (tcp, peer) = match listener.accept().await {
            Ok(x) => x,
            Err(e) => {
                // out of file descriptors or a connection reset before accept: wait, go on
                tracing::warn!("accept: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Some(slot) = shared.admission.connection(peer.ip()) else {
            tracing::debug!(%peer, "connection refused: connection limit");
            drop(tcp);
            continue;
        };
        let _ = tcp.set_nodelay(true);
        let app = app.clone();
        tokio::spawn(async move {
            let svc = hyper::service::service_fn(
                move |mut req: hyper::Request<hyper::body::Incoming>| {
                    req.extensions_mut().insert(Peer(peer));
                    app.clone().oneshot(req.map(axum::body::Body::new))
                },
            );
            let mut b = hyper::server::conn::http1::Builder::new();
            b.timer(hyper_util::rt::TokioTimer::new())
                .header_read_timeout(header_timeout)
                .max_buf_size(64 << 10);
            let conn = b
                .serve_connection(hyper_util::rt::TokioIo::new(tcp), svc)
                .with_upgrades();
            if let Err(e) = conn.await {
                tracing::debug!(%peer, "connection: {e}");
            }
            drop(slot);
        });
    }
}
