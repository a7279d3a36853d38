//! One WebSocket connection of the stream: `Hello`, then manifest, base and `Nodes` batches under the
//! acknowledgement window, with `Ack`, `Want`, `Cancel` and `View` read concurrently.

use super::admission::PeerBudgets;
use super::auth::same;
use super::config::{Order, ViewTf};
use super::preview::PreviewPhase;
use super::schedule::{Schedule, MAX_QUEUED_WANTS};
use super::state::Shared;
use axum::body::Bytes;
use axum::extract::ws::{CloseFrame, Message, WebSocket};
use futures_util::{SinkExt, StreamExt};
use std::sync::atomic::Ordering as AtomicOrdering;
use std::sync::Arc;
use std::time::Duration;
use tetwave_protocol::wire::{decode_client, encode, ClientMsg, ServerMsg, PROTOCOL_VERSION};
use tokio::sync::mpsc;

#[derive(Debug, thiserror::Error)]
pub(super) enum ConnError {
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
    /// A frame that does not decode, or a text frame.
    Bad(String),
    /// A message over the size limit (the socket is unusable for reading after it).
    TooBig(String),
}

/// WebSocket close codes (RFC 6455 §7.4.1) the server uses.
mod close_code {
    pub const NORMAL: u16 = 1000;
    /// Idle timeout.
    pub const GOING_AWAY: u16 = 1001;
    /// A message the protocol does not allow: wrong version, token, order or budget.
    pub const POLICY: u16 = 1008;
    pub const TOO_BIG: u16 = 1009;
    pub const INTERNAL: u16 = 1011;
}

/// How long a client has to send `Hello`.
const HELLO_TIMEOUT: Duration = Duration::from_secs(10);
/// How long one frame may take to go out.
const SEND_TIMEOUT: Duration = Duration::from_secs(60);

/// Control messages with more ranges than this are applied on a blocking thread.
const BLOCKING_RANGES: usize = 256;

/// The peer's control-message budget ([`PeerBudgets`]).
struct Budget<'a> {
    budgets: &'a PeerBudgets,
    ip: std::net::IpAddr,
}

impl Budget<'_> {
    fn charge(&mut self, cost: usize) -> bool {
        self.budgets.charge(self.ip, cost)
    }
}

/// Ranges a control message carries.
fn ranges_of(m: &ClientMsg) -> usize {
    match m {
        ClientMsg::Hello { have, .. } => have.len(),
        ClientMsg::Want(r) | ClientMsg::Cancel(r) => r.len(),
        ClientMsg::View(_) | ClientMsg::Ack { .. } => 0,
    }
}

/// Why a connection is being closed: a code for the close frame, and an `Error` message first when
/// the client should learn why.
struct Closing {
    code: u16,
    reason: String,
    /// `Error { code }` sent before the close frame.
    error: Option<u16>,
    result: Result<(), ConnError>,
}

impl Closing {
    fn client(error: u16, reason: String) -> Self {
        Closing {
            code: close_code::POLICY,
            error: Some(error),
            result: Err(ConnError::Client(reason.clone())),
            reason,
        }
    }
    fn from_incoming_failure(m: Incoming) -> Self {
        match m {
            Incoming::TooBig(r) => Closing {
                code: close_code::TOO_BIG,
                error: None,
                result: Err(ConnError::Client(r.clone())),
                reason: r,
            },
            Incoming::Bad(r) => Closing::client(400, r),
            Incoming::Msg(_) => Closing::client(400, "unexpected message".into()),
        }
    }
    fn internal(reason: String) -> Self {
        Closing {
            code: close_code::INTERNAL,
            error: Some(500),
            result: Err(ConnError::Socket(reason.clone())),
            reason,
        }
    }
    fn idle() -> Self {
        Closing {
            code: close_code::GOING_AWAY,
            reason: "idle timeout".into(),
            error: None,
            result: Err(ConnError::Idle),
        }
    }
    fn normal() -> Self {
        Closing {
            code: close_code::NORMAL,
            reason: String::new(),
            error: None,
            result: Ok(()),
        }
    }
}

pub(super) async fn run_connection(
    socket: WebSocket,
    s: Arc<Shared>,
    (order, tf): (Order, ViewTf),
    pre_auth: bool,
    peer: Option<std::net::SocketAddr>,
) -> Result<(), ConnError> {
    let (mut sink, stream) = socket.split();
    let closing = match stream_to(&mut sink, stream, &s, (order, tf), pre_auth, peer).await {
        Ok(c) => c,
        // the socket failed: nothing more can be said on it
        Err(e) => return Err(e),
    };
    if let Some(code) = closing.error {
        let f = encode(&ServerMsg::Error {
            code,
            message: closing.reason.clone(),
        })
        .unwrap_or_default();
        let _ = send(&mut sink, Bytes::from(f)).await;
    }
    let mut reason = closing.reason;
    // a close frame's reason is at most 123 bytes
    while reason.len() > 123 {
        reason.pop();
    }
    let frame = CloseFrame {
        code: closing.code,
        reason: reason.into(),
    };
    let _ = tokio::time::timeout(
        Duration::from_secs(2),
        sink.send(Message::Close(Some(frame))),
    )
    .await;
    closing.result
}

/// The stream proper; returns how to close (or a socket error, when nothing can be sent).
async fn stream_to(
    sink: &mut Sink,
    mut stream: futures_util::stream::SplitStream<WebSocket>,
    s: &Arc<Shared>,
    (order, tf): (Order, ViewTf),
    pre_auth: bool,
    peer: Option<std::net::SocketAddr>,
) -> Result<Closing, ConnError> {
    // 1. Hello
    let first = match tokio::time::timeout(HELLO_TIMEOUT, read_msg(&mut stream)).await {
        Err(_) => return Ok(Closing::idle()),
        Ok(None) => return Ok(Closing::normal()),
        Ok(Some(m)) => m,
    };
    let (have, previewed) = match first {
        Incoming::Msg(ClientMsg::Hello {
            version,
            token,
            have,
            previewed,
        }) => {
            if version != PROTOCOL_VERSION {
                let m = format!("protocol version {version}, server speaks {PROTOCOL_VERSION}");
                return Ok(Closing::client(426, m));
            }
            if let (Some(want), false) = (&s.config.token, pre_auth) {
                if !token.as_deref().is_some_and(|t| same(t, want)) {
                    if token.is_some() {
                        s.auth_failures.failed(peer, "stream Hello");
                    }
                    return Ok(Closing::client(401, "missing or wrong token".into()));
                }
            }
            (have, previewed)
        }
        Incoming::Msg(_) => {
            return Ok(Closing::client(
                400,
                "the first message must be Hello".into(),
            ))
        }
        other => return Ok(Closing::from_incoming_failure(other)),
    };

    // 2. reader task: decoded client messages into a small bounded channel
    let (tx, mut rx) = mpsc::channel::<Incoming>(32);
    let reader = tokio::spawn(async move {
        while let Some(m) = read_msg(&mut stream).await {
            let last = !matches!(m, Incoming::Msg(_));
            if tx.send(m).await.is_err() || last {
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

    let mut budget = Budget {
        budgets: &s.budgets,
        ip: peer.map_or(std::net::IpAddr::from([0, 0, 0, 0]), |p| p.ip()),
    };
    if !budget.charge(1 + have.len() + previewed.len()) {
        return Ok(Closing::client(
            429,
            "this address's control messages exceed its budget".into(),
        ));
    }

    // 3. manifest and base mesh
    send(sink, s.start_frame.clone()).await?;

    // 4. nodes (a new session's preview first)
    let sched_s = s.clone();
    let (sched, mut preview) = tokio::task::spawn_blocking(move || {
        let preview = PreviewPhase::new(&sched_s, order, &have, &previewed);
        let sc = Schedule::new(&sched_s, order, tf).map(|mut sc| {
            sc.have(&have);
            sc
        });
        (sc, preview)
    })
    .await
    .map_err(|e| ConnError::Socket(e.to_string()))?;
    let mut sched = match sched {
        Ok(sc) => sc,
        Err(e) => return Ok(Closing::internal(e.to_string())),
    };
    let mut next_seq = 0u64;
    let mut acked = 0u64; // batches acknowledged: seq < acked
    let mut nodes_sent = 0u64;
    let mut end_due = true;
    let first_batch = s.config.batch.max(1);
    let max_batch = s.config.max_batch.max(first_batch);
    let mut batch = first_batch;
    let window = s.config.window.max(1);
    let mut rescans = 0u64;
    // control messages received and not applied yet (Acks are applied at once)
    let mut pending: Vec<ClientMsg> = Vec::new();

    loop {
        // control messages that are already here
        loop {
            match rx.try_recv() {
                Ok(m) => {
                    if let Some(c) = accept(m, &mut budget, &mut acked, next_seq, &mut pending) {
                        return Ok(c);
                    }
                }
                Err(mpsc::error::TryRecvError::Empty) => break,
                Err(mpsc::error::TryRecvError::Disconnected) => return Ok(Closing::normal()),
            }
        }
        let can_send = next_seq - acked < window;
        // the preview first (control messages that came meanwhile are applied below first)
        let preview_due = can_send && pending.is_empty();
        if let Some(p) = preview.take_if(|_| preview_due) {
            let (s2, seq) = (s.clone(), next_seq);
            let (p, frame) = tokio::task::spawn_blocking(move || {
                let mut p = p;
                let f = p.next_frame(&s2, seq, max_batch);
                (p, f)
            })
            .await
            .map_err(|e| ConnError::Socket(e.to_string()))?;
            match frame {
                Err(m) => return Ok(Closing::internal(m)),
                Ok(Some(frame)) => {
                    preview = Some(p);
                    send(sink, Bytes::from(frame)).await?;
                    next_seq += 1;
                    continue;
                }
                Ok(None) => {}
            }
        }
        if !pending.is_empty() || (sched.has_work() && can_send) {
            let heavy = pending.iter().map(ranges_of).sum::<usize>() > BLOCKING_RANGES;
            let wants = pending.iter().any(|m| matches!(m, ClientMsg::Want(_)));
            if pending.iter().any(|m| matches!(m, ClientMsg::View(_))) {
                // the priorities changed: paint the new view's first nodes early
                batch = first_batch;
            }
            let msgs = std::mem::take(&mut pending);
            // (while the preview lasts, control messages are applied and nodes wait)
            let send_now = can_send && preview.is_none();
            let step = move |mut sc: Schedule, s2: &Shared, seq: u64| {
                let applied = apply(&mut sc, msgs);
                let frame = (applied && send_now && sc.has_work()).then(|| {
                    sc.next_batch(s2, batch)
                        .map_err(|e| e.to_string())
                        .and_then(|mut ids| s2.fetch_block(&mut ids).map_err(|e| e.to_string()))
                        .and_then(|block| {
                            let k = block.count as u64;
                            encode(&ServerMsg::Nodes { seq, block })
                                .map(|f| (f, k))
                                .map_err(|e| e.to_string())
                        })
                });
                (sc, applied, frame)
            };
            // batches and large control messages on a blocking thread; small ones here
            let (sc, applied, frame) = if heavy || send_now && sched.has_work() {
                let s2 = s.clone();
                let seq = next_seq;
                // as many batches at once as there are cores: more would only share them, and
                // delay every other request (`/healthz` included) behind the batches' threads
                let _turn = s
                    .batch_slots
                    .acquire()
                    .await
                    .map_err(|e| ConnError::Socket(e.to_string()))?;
                tokio::task::spawn_blocking(move || step(sched, &s2, seq))
                    .await
                    .map_err(|e| ConnError::Socket(e.to_string()))?
            } else {
                step(sched, s, next_seq)
            };
            sched = sc;
            let r = sched.rescans();
            s.view_rescans
                .fetch_add(r - rescans, AtomicOrdering::Relaxed);
            rescans = r;
            if !applied {
                return Ok(Closing::client(
                    429,
                    format!("more than {MAX_QUEUED_WANTS} queued Want ranges"),
                ));
            }
            if wants {
                end_due = true;
            }
            match frame {
                None => {}
                Some(Err(m)) => return Ok(Closing::internal(m)),
                Some(Ok((_, 0))) => {}
                Some(Ok((frame, k))) => {
                    send(sink, Bytes::from(frame)).await?;
                    next_seq += 1;
                    nodes_sent += k;
                    batch = (batch * 2).min(max_batch);
                    end_due = true;
                }
            }
            continue;
        }
        if !sched.has_work() && end_due && preview.is_none() {
            let f = encode(&ServerMsg::End { nodes_sent }).unwrap_or_default();
            send(sink, Bytes::from(f)).await?;
            end_due = false;
            continue;
        }
        // nothing to do until the client says something (an Ack, a Want, a View)
        match tokio::time::timeout(s.config.idle_timeout, rx.recv()).await {
            Err(_) => return Ok(Closing::idle()),
            Ok(None) => return Ok(Closing::normal()),
            Ok(Some(m)) => {
                if let Some(c) = accept(m, &mut budget, &mut acked, next_seq, &mut pending) {
                    return Ok(c);
                }
            }
        }
    }
}

/// Takes one client message: an `Ack` is applied at once, other control messages are charged to
/// the budget and queued in `pending` (only the last `View` of a run counts). `Some` closes.
fn accept(
    m: Incoming,
    budget: &mut Budget<'_>,
    acked: &mut u64,
    next_seq: u64,
    pending: &mut Vec<ClientMsg>,
) -> Option<Closing> {
    let m = match m {
        Incoming::Msg(m) => m,
        other => return Some(Closing::from_incoming_failure(other)),
    };
    if !budget.charge(1 + ranges_of(&m)) {
        return Some(Closing::client(
            429,
            "this address's control messages exceed its budget".into(),
        ));
    }
    match m {
        ClientMsg::Hello { .. } => Some(Closing::client(400, "a second Hello".into())),
        ClientMsg::Ack { seq } => {
            *acked = (*acked).max(seq.saturating_add(1).min(next_seq));
            None
        }
        ClientMsg::View(v) => {
            // views coalesce: a newer one replaces one not applied yet
            pending.retain(|p| !matches!(p, ClientMsg::View(_)));
            pending.push(ClientMsg::View(v));
            None
        }
        m => {
            pending.push(m);
            None
        }
    }
}

/// Applies queued control messages in order; `false` when a `Want` overflows the queue.
fn apply(sched: &mut Schedule, msgs: Vec<ClientMsg>) -> bool {
    for m in msgs {
        match m {
            ClientMsg::View(v) => sched.set_view(v),
            ClientMsg::Want(r) => {
                if !sched.want(&r) {
                    return false;
                }
            }
            ClientMsg::Cancel(r) => sched.cancel(&r),
            ClientMsg::Hello { .. } | ClientMsg::Ack { .. } => {}
        }
    }
    true
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
            Err(e) => {
                let inner = e.into_inner();
                return match inner.downcast_ref::<tungstenite::Error>() {
                    Some(tungstenite::Error::Capacity(c)) => Some(Incoming::TooBig(c.to_string())),
                    _ => None,
                };
            }
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
