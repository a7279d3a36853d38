//! How the connection task reaches a server ([`Transport`]: a WebSocket by default), and a
//! transport wrapper that injects faults for tests ([`Faulty`]): batches lost, duplicated,
//! reordered, a connection dropped. The connection task knows nothing of faults; a test wraps
//! the transport it is given.

use crate::connection::ws_config;
use futures_util::{Sink, Stream};
use std::collections::VecDeque;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{ready, Context, Poll};
use tetwave_protocol::wire::{decode_server, ServerMsg};
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

/// A way to open a message stream to a server's `/v1/stream`.
pub trait Transport: Send + Sync + 'static {
    /// An open connection: server messages in, client messages out.
    type Conn: Stream<Item = Result<Message, WsError>>
        + Sink<Message, Error = WsError>
        + Unpin
        + Send
        + 'static;

    /// Opens a connection to `url` (`ws://host:port/v1/stream…`).
    fn connect(&self, url: &str) -> impl Future<Output = Result<Self::Conn, WsError>> + Send;
}

/// A WebSocket over TCP with the client's limits ([`ws_config`]).
#[derive(Debug, Clone, Copy, Default)]
pub struct WebSocket;

impl Transport for WebSocket {
    type Conn = tokio_tungstenite::WebSocketStream<
        tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>,
    >;

    async fn connect(&self, url: &str) -> Result<Self::Conn, WsError> {
        tokio_tungstenite::connect_async_with_config(url, Some(ws_config()), false)
            .await
            .map(|(ws, _)| ws)
    }
}

/// Transport faults to inject (tests): counts are of node batches over the whole session, across
/// reconnections.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Faults {
    /// Drop the connection once, after this many node batches (preview batches count too).
    pub drop_after_batches: Option<u64>,
    /// Deliver every k-th node batch twice.
    pub duplicate_every: Option<u64>,
    /// Lose every k-th node batch (the client re-requests what is missing after `End`).
    pub lose_every: Option<u64>,
    /// Deliver node batches in reversed groups of this many. The transport holds a group until
    /// it is whole (or another server message comes): a connection dropped meanwhile does not
    /// name the held nodes in its next `Hello`, so the server sends them again (duplicates).
    pub reverse_groups: Option<usize>,
}

impl Faults {
    /// No fault at all.
    pub fn none(&self) -> bool {
        *self == Faults::default()
    }
}

/// What the faults have done so far, shared by a session's connections.
#[derive(Debug, Default)]
struct FaultState {
    batches: u64,
    previews: u64,
    dropped: bool,
    /// Node batches held back to be delivered reversed; anything else flushes them first.
    held: Vec<Message>,
}

/// `T` with `faults` injected into what its connections receive.
pub struct Faulty<T> {
    inner: T,
    faults: Faults,
    state: Arc<Mutex<FaultState>>,
}

impl<T> Faulty<T> {
    pub fn new(inner: T, faults: Faults) -> Self {
        Faulty {
            inner,
            faults,
            state: Arc::default(),
        }
    }
}

impl<T: Transport> Transport for Faulty<T> {
    type Conn = FaultyConn<T::Conn>;

    async fn connect(&self, url: &str) -> Result<Self::Conn, WsError> {
        Ok(FaultyConn {
            inner: self.inner.connect(url).await?,
            faults: self.faults,
            state: self.state.clone(),
            ready: VecDeque::new(),
            cut: false,
        })
    }
}

/// One connection of a [`Faulty`] transport.
pub struct FaultyConn<C> {
    inner: C,
    faults: Faults,
    state: Arc<Mutex<FaultState>>,
    /// Messages to hand out before reading more.
    ready: VecDeque<Message>,
    /// The connection is dropped once `ready` is empty.
    cut: bool,
}

impl<C> FaultyConn<C> {
    /// Takes one message from the server: what reaches the client goes to `ready`.
    fn take(&mut self, m: Message) {
        let f = self.faults;
        let mut st = self.state.lock().expect("fault state");
        let kind = match &m {
            Message::Binary(b) => decode_server(b).ok(),
            _ => None,
        };
        match kind {
            Some(ServerMsg::Nodes { .. }) => {
                st.batches += 1;
                let k = st.batches;
                if !f.lose_every.is_some_and(|n| k.is_multiple_of(n)) {
                    let twice = f.duplicate_every.is_some_and(|n| k.is_multiple_of(n));
                    let copies = if twice { vec![m.clone(), m] } else { vec![m] };
                    match f.reverse_groups {
                        Some(g) => {
                            st.held.extend(copies);
                            if st.held.len() >= g {
                                let mut group = std::mem::take(&mut st.held);
                                group.reverse();
                                self.ready.extend(group);
                            }
                        }
                        None => self.ready.extend(copies),
                    }
                }
            }
            Some(other) => {
                if matches!(other, ServerMsg::Preview { .. }) {
                    st.previews += 1;
                }
                // any other server message flushes what was held back, in order of arrival
                self.ready.extend(st.held.drain(..));
                self.ready.push_back(m);
            }
            // a WebSocket control frame (Close, Ping, Pong) or what does not decode: as it is
            None => self.ready.push_back(m),
        }
        let delivered = st.batches + st.previews;
        if !st.dropped && f.drop_after_batches.is_some_and(|n| delivered >= n) {
            st.dropped = true;
            self.cut = true;
        }
    }
}

impl<C> Stream for FaultyConn<C>
where
    C: Stream<Item = Result<Message, WsError>> + Unpin,
{
    type Item = Result<Message, WsError>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let this = &mut *self;
        loop {
            if let Some(m) = this.ready.pop_front() {
                return Poll::Ready(Some(Ok(m)));
            }
            if this.cut {
                return Poll::Ready(None);
            }
            match ready!(Pin::new(&mut this.inner).poll_next(cx)) {
                Some(Ok(m)) => this.take(m),
                other => return Poll::Ready(other),
            }
        }
    }
}

impl<C> Sink<Message> for FaultyConn<C>
where
    C: Sink<Message, Error = WsError> + Unpin,
{
    type Error = WsError;

    fn poll_ready(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), WsError>> {
        Pin::new(&mut self.inner).poll_ready(cx)
    }

    fn start_send(mut self: Pin<&mut Self>, item: Message) -> Result<(), WsError> {
        Pin::new(&mut self.inner).start_send(item)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), WsError>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_close(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), WsError>> {
        Pin::new(&mut self.inner).poll_close(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use futures_util::StreamExt;
    use tetwave_protocol::block::NodeBlock;
    use tetwave_protocol::wire::encode;

    /// A connection that yields `incoming` and swallows what is sent.
    struct Scripted(VecDeque<Message>);

    impl Stream for Scripted {
        type Item = Result<Message, WsError>;
        fn poll_next(mut self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Option<Self::Item>> {
            Poll::Ready(self.0.pop_front().map(Ok))
        }
    }

    impl Sink<Message> for Scripted {
        type Error = WsError;
        fn poll_ready(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), WsError>> {
            Poll::Ready(Ok(()))
        }
        fn start_send(self: Pin<&mut Self>, _: Message) -> Result<(), WsError> {
            Ok(())
        }
        fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), WsError>> {
            Poll::Ready(Ok(()))
        }
        fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), WsError>> {
            Poll::Ready(Ok(()))
        }
    }

    fn nodes(seq: u64) -> Message {
        let block = NodeBlock {
            count: 0,
            first: 0,
            bytes: Vec::new(),
        };
        Message::Binary(encode(&ServerMsg::Nodes { seq, block }).unwrap().into())
    }

    fn end() -> Message {
        Message::Binary(encode(&ServerMsg::End { nodes_sent: 0 }).unwrap().into())
    }

    /// What a faulty connection over `incoming` hands out: batch seqs, `0` for the end and
    /// `u64::MAX` for a WebSocket control frame.
    fn through(faults: Faults, state: &Arc<Mutex<FaultState>>, incoming: Vec<Message>) -> Vec<u64> {
        let conn = FaultyConn {
            inner: Scripted(incoming.into()),
            faults,
            state: state.clone(),
            ready: VecDeque::new(),
            cut: false,
        };
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let got: Vec<Message> = rt.block_on(conn.map(|m| m.unwrap()).collect::<Vec<_>>());
        got.iter()
            .map(|m| match m {
                Message::Binary(b) => match decode_server(b).unwrap() {
                    ServerMsg::Nodes { seq, .. } => seq,
                    _ => 0,
                },
                _ => u64::MAX,
            })
            .collect()
    }

    #[test]
    fn faults_lose_duplicate_reverse_and_cut_what_the_client_receives() {
        let batches = |n: u64| (1..=n).map(nodes).chain([end()]).collect::<Vec<_>>();
        let fresh = Arc::<Mutex<FaultState>>::default;
        assert_eq!(
            through(Faults::default(), &fresh(), batches(3)),
            [1, 2, 3, 0]
        );
        let lose = Faults {
            lose_every: Some(2),
            ..Default::default()
        };
        assert_eq!(through(lose, &fresh(), batches(5)), [1, 3, 5, 0]);
        let dup = Faults {
            duplicate_every: Some(2),
            ..Default::default()
        };
        assert_eq!(through(dup, &fresh(), batches(3)), [1, 2, 2, 3, 0]);
        // reversed in groups of 2; the end flushes what is held, in order
        let rev = Faults {
            reverse_groups: Some(2),
            ..Default::default()
        };
        assert_eq!(through(rev, &fresh(), batches(5)), [2, 1, 4, 3, 5, 0]);
        // a control frame passes and flushes nothing: the held batch waits for the next
        // connection's first server message
        let session = fresh();
        let closing = vec![nodes(1), nodes(2), nodes(3), Message::Close(None)];
        assert_eq!(through(rev, &session, closing), [2, 1, u64::MAX]);
        assert_eq!(through(rev, &session, vec![end()]), [3, 0]);
        // cut once after 2 batches; the next connection (same session) is not cut again
        let cut = Faults {
            drop_after_batches: Some(2),
            ..Default::default()
        };
        let session = fresh();
        assert_eq!(through(cut, &session, batches(4)), [1, 2]);
        assert_eq!(through(cut, &session, batches(4)), [1, 2, 3, 4, 0]);
    }
}
