//! One WebSocket connection of the stream: `Hello`, then manifest, base and `Nodes` batches under the
//! acknowledgement window, with `Ack`, `Want`, `Cancel` and `View` read concurrently.

use super::auth::same;
use super::config::Order;
use super::schedule::Schedule;
use super::state::Shared;
use axum::body::Bytes;
use axum::extract::ws::{Message, WebSocket};
use futures_util::{SinkExt, StreamExt};
use std::sync::Arc;
use std::time::Duration;
use tetwave_protocol::wire::{
    decode_client, encode, ClientMsg, ServerMsg, ViewParams, PROTOCOL_VERSION,
};
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
    Bad(String),
}

/// How long a client has to send `Hello`.
const HELLO_TIMEOUT: Duration = Duration::from_secs(10);
/// How long one frame may take to go out.
const SEND_TIMEOUT: Duration = Duration::from_secs(60);

pub(super) async fn run_connection(
    socket: WebSocket,
    s: Arc<Shared>,
    order: Order,
    pre_auth: bool,
) -> Result<(), ConnError> {
    let (mut sink, mut stream) = socket.split();
    let error_frame = |code: u16, message: String| {
        Bytes::from(encode(&ServerMsg::Error { code, message }).unwrap_or_default())
    };

    // 1. Hello
    let first = match tokio::time::timeout(HELLO_TIMEOUT, read_msg(&mut stream)).await {
        Err(_) => return Err(ConnError::Idle),
        Ok(None) => return Ok(()),
        Ok(Some(m)) => m,
    };
    let have = match first {
        Incoming::Msg(ClientMsg::Hello {
            version,
            token,
            have,
        }) => {
            if version != PROTOCOL_VERSION {
                let m = format!("protocol version {version}, server speaks {PROTOCOL_VERSION}");
                let _ = send(&mut sink, error_frame(426, m.clone())).await;
                let _ = sink.close().await;
                return Err(ConnError::Client(m));
            }
            if let (Some(want), false) = (&s.config.token, pre_auth) {
                if !token.as_deref().is_some_and(|t| same(t, want)) {
                    let _ =
                        send(&mut sink, error_frame(401, "missing or wrong token".into())).await;
                    let _ = sink.close().await;
                    return Err(ConnError::Client("unauthorized".into()));
                }
            }
            have
        }
        Incoming::Msg(_) => {
            let m = "the first message must be Hello".to_string();
            let _ = send(&mut sink, error_frame(400, m.clone())).await;
            let _ = sink.close().await;
            return Err(ConnError::Client(m));
        }
        Incoming::Bad(m) => {
            let _ = send(&mut sink, error_frame(400, m.clone())).await;
            let _ = sink.close().await;
            return Err(ConnError::Client(m));
        }
    };

    // 2. reader task: decoded client messages into a small bounded channel
    let (tx, mut rx) = mpsc::channel::<Incoming>(32);
    let reader = tokio::spawn(async move {
        while let Some(m) = read_msg(&mut stream).await {
            let bad = matches!(m, Incoming::Bad(_));
            if tx.send(m).await.is_err() || bad {
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

    // 3. manifest, base
    send(&mut sink, s.manifest_frame.clone()).await?;
    send(&mut sink, s.base_frame.clone()).await?;

    // 4. nodes
    let sched_s = s.clone();
    let mut sched = tokio::task::spawn_blocking(move || {
        let mut sc = Schedule::new(&sched_s, order);
        sc.have(&have);
        sc
    })
    .await
    .map_err(|e| ConnError::Socket(e.to_string()))?;
    let mut next_seq = 0u64;
    let mut acked = 0u64; // batches acknowledged: seq < acked
    let mut nodes_sent = 0u64;
    let mut end_due = true;
    let batch = s.config.batch.max(1);
    let window = s.config.window.max(1);

    loop {
        // control messages that are already here (coalesce views: only the last one counts)
        let mut view = None;
        loop {
            match rx.try_recv() {
                Ok(m) => match handle(&mut sched, m, &mut acked, next_seq, &mut end_due) {
                    Ok(Some(v)) => view = Some(v),
                    Ok(None) => {}
                    Err(e) => {
                        let _ = send(&mut sink, error_frame(400, e.to_string())).await;
                        let _ = sink.close().await;
                        return Err(e);
                    }
                },
                Err(mpsc::error::TryRecvError::Empty) => break,
                Err(mpsc::error::TryRecvError::Disconnected) => {
                    let _ = sink.close().await;
                    return Ok(());
                }
            }
        }
        if let Some(v) = view {
            sched.set_view(v);
        }
        let can_send = next_seq - acked < window;
        if sched.has_work() && can_send {
            let (sc, frame) = {
                let s2 = s.clone();
                let seq = next_seq;
                let mut sc = sched;
                tokio::task::spawn_blocking(move || {
                    let mut ids = sc.next_batch(&s2, batch);
                    let f = s2
                        .fetch(&mut ids)
                        .map_err(|e| e.to_string())
                        .and_then(|nodes| {
                            let k = nodes.len() as u64;
                            encode(&ServerMsg::Nodes { seq, nodes })
                                .map(|f| (f, k))
                                .map_err(|e| e.to_string())
                        });
                    (sc, f)
                })
                .await
                .map_err(|e| ConnError::Socket(e.to_string()))?
            };
            sched = sc;
            let (frame, k) = match frame {
                Ok(x) => x,
                Err(m) => {
                    let _ = send(&mut sink, error_frame(500, m.clone())).await;
                    let _ = sink.close().await;
                    return Err(ConnError::Socket(m));
                }
            };
            if k == 0 {
                continue;
            }
            send(&mut sink, Bytes::from(frame)).await?;
            next_seq += 1;
            nodes_sent += k;
            end_due = true;
            continue;
        }
        if !sched.has_work() && end_due {
            let f = encode(&ServerMsg::End { nodes_sent }).unwrap_or_default();
            send(&mut sink, Bytes::from(f)).await?;
            end_due = false;
            continue;
        }
        // nothing to do until the client says something (an Ack, a Want, a View)
        match tokio::time::timeout(s.config.idle_timeout, rx.recv()).await {
            Err(_) => {
                let _ = sink.close().await;
                return Err(ConnError::Idle);
            }
            Ok(None) => {
                let _ = sink.close().await;
                return Ok(());
            }
            Ok(Some(m)) => match handle(&mut sched, m, &mut acked, next_seq, &mut end_due) {
                Ok(Some(v)) => sched.set_view(v),
                Ok(None) => {}
                Err(e) => {
                    let _ = send(&mut sink, error_frame(400, e.to_string())).await;
                    let _ = sink.close().await;
                    return Err(e);
                }
            },
        }
    }
}

/// Applies one client message; returns a view to apply (views are coalesced by the caller).
fn handle(
    sched: &mut Schedule,
    m: Incoming,
    acked: &mut u64,
    next_seq: u64,
    end_due: &mut bool,
) -> Result<Option<ViewParams>, ConnError> {
    match m {
        Incoming::Bad(e) => Err(ConnError::Client(e)),
        Incoming::Msg(m) => match m {
            ClientMsg::Hello { .. } => Err(ConnError::Client("a second Hello".into())),
            ClientMsg::View(v) => Ok(Some(v)),
            ClientMsg::Want(r) => {
                if !sched.want(&r) {
                    return Err(ConnError::Client("too many queued Want ranges".into()));
                }
                *end_due = true;
                Ok(None)
            }
            ClientMsg::Cancel(r) => {
                sched.cancel(&r);
                Ok(None)
            }
            ClientMsg::Ack { seq } => {
                *acked = (*acked).max(seq.saturating_add(1).min(next_seq));
                Ok(None)
            }
        },
    }
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
            Err(_) => return None,
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
