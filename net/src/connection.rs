//! The connection task shared by `tetwave stream` and the viewer: connects to
//! `tetwave-server serve`, says `Hello` with the ranges already held, decodes every message on
//! the network's own thread and queues it for the frame loop (up to [`INGEST_QUEUE`] ahead,
//! acknowledging each batch once queued: the queue's bound is the backpressure), forwards the
//! frame loop's messages (`View`, `Want`), and after a lost connection reconnects and resumes:
//! `Hello` again with what is held, then the last `View` sent, so that the server's view order
//! goes on for the same camera whether or not it moves again.

use crate::error::{HttpError, NetError};
use crate::transport::{Transport, WebSocket};
use crate::url::ServerUrl;
use futures_util::{SinkExt, StreamExt};
use std::collections::BTreeSet;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::wire::{
    decode_server, encode, ClientMsg, IdRange, ServerMsg, SessionStart, ViewParams,
    MAX_FRAME_BYTES, MAX_RANGES, PROTOCOL_VERSION,
};
use tetwave_protocol::{BaseMesh, DetailNode, TetId};
use tetwave_render::transfer::AUTO;
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

/// Refuses, before anything is allocated for it, a base mesh whose hierarchy has more than
/// `limit` detail nodes (`--max-nodes`), or whose levels or node count disagree with the manifest.
/// `base` passed [`BaseMesh::validate`] (at most 16 levels), so the count is exact in u128.
pub fn check_hierarchy(base: &BaseMesh, m: &Manifest, limit: u64) -> Result<(), NetError> {
    let tets = base.tets.len();
    let nodes = tets as u128 * ((1u128 << (3 * base.levels as u32)) - 1) / 7;
    if nodes > limit as u128 {
        return Err(NetError::TooLarge {
            tets,
            levels: base.levels,
            nodes,
            limit,
        });
    }
    if m.levels != base.levels || m.counts.nodes as u128 != nodes {
        return Err(NetError::Disagrees {
            base_levels: base.levels,
            base_nodes: nodes,
            levels: m.levels,
            nodes: m.counts.nodes,
        });
    }
    Ok(())
}

/// Sorted, merged id ranges of a set.
pub fn ranges_of(ids: &BTreeSet<TetId>) -> Vec<IdRange> {
    let mut out: Vec<IdRange> = Vec::new();
    for &id in ids {
        match out.last_mut() {
            Some(r) if r.to == id => r.to += 1,
            _ => out.push(IdRange {
                from: id,
                to: id + 1,
            }),
        }
    }
    out
}

/// GETs the near band of the domain's level set from `server` and decodes it for a hierarchy of
/// `n_keys` vertices; returns it and the body's length.
fn fetch_levelset(
    server: &ServerUrl,
    token: Option<&str>,
    n_keys: u64,
) -> Result<(NearLevelSet, u64), HttpError> {
    let url = server.levelset();
    let bytes = crate::http::get(&url, token, MAX_LEVELSET_BYTES, LEVELSET_TIMEOUT)?;
    let near = NearLevelSet::decode(&bytes, n_keys).map_err(|e| HttpError {
        url,
        reason: e.to_string(),
    })?;
    Ok((near, bytes.len() as u64))
}

/// The largest level-set body a client reads (a band of about 40 M vertices).
const MAX_LEVELSET_BYTES: u64 = 256 << 20;
/// How long the level set's request may take, all of it.
const LEVELSET_TIMEOUT: Duration = Duration::from_secs(30);
/// Requests for the level set in one session at most (a failed one is made again after a
/// reconnection).
const LEVELSET_ATTEMPTS: u32 = 3;
/// The level set's state in the network task: not asked for, asked, held, failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
enum LevelSetFetch {
    Idle = 0,
    Asked = 1,
    Held = 2,
    Failed = 3,
}

/// A [`LevelSetFetch`] shared by the connection task and the thread that fetches the band.
#[derive(Debug)]
struct SharedFetch(AtomicU8);

impl SharedFetch {
    fn new() -> Self {
        SharedFetch(AtomicU8::new(LevelSetFetch::Idle as u8))
    }

    fn get(&self) -> LevelSetFetch {
        match self.0.load(Ordering::Acquire) {
            0 => LevelSetFetch::Idle,
            1 => LevelSetFetch::Asked,
            2 => LevelSetFetch::Held,
            _ => LevelSetFetch::Failed,
        }
    }

    fn set(&self, s: LevelSetFetch) {
        self.0.store(s as u8, Ordering::Release);
    }
}

/// The runtime of a network task: one worker, and when dropped it does not wait for its blocking
/// tasks (a level-set request still in flight ends on its own; nobody takes its answer).
pub(crate) struct NetRuntime(Option<tokio::runtime::Runtime>);

impl NetRuntime {
    pub(crate) fn new(name: &str) -> std::io::Result<Self> {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name(name)
            .enable_all()
            .build()
            .map(|rt| NetRuntime(Some(rt)))
    }
}

impl std::ops::Deref for NetRuntime {
    type Target = tokio::runtime::Runtime;
    fn deref(&self) -> &Self::Target {
        self.0.as_ref().expect("a runtime until dropped")
    }
}

impl Drop for NetRuntime {
    fn drop(&mut self) {
        if let Some(rt) = self.0.take() {
            rt.shutdown_background();
        }
    }
}

/// How the network task behaves: reconnection attempts, and the largest
/// hierarchy (in nodes) it fetches a level set for.
pub struct NetPolicy {
    pub retries: u32,
    pub max_nodes: u64,
    /// The session draws with `auto`: asks for the server's view order under the fitted
    /// function (`/v1/stream?tf=auto`), whose clients need other nodes first.
    pub tf_auto: bool,
}

/// The network task's counters, shared with the session that reads them (this module's frame
/// loop, or the viewer's).
pub(crate) struct Net {
    pub(crate) bytes: Arc<AtomicU64>,
    pub(crate) reconnects: Arc<AtomicU64>,
    /// A connection is open (its `Hello` sent); false before the first and while reconnecting.
    pub(crate) connected: Arc<AtomicBool>,
    /// Node ids received over the wire (for resume), whether or not applied yet.
    pub(crate) received: Arc<Mutex<BTreeSet<TetId>>>,
}

impl Net {
    pub(crate) fn new() -> Self {
        Net {
            bytes: Arc::new(AtomicU64::new(0)),
            reconnects: Arc::new(AtomicU64::new(0)),
            connected: Arc::new(AtomicBool::new(false)),
            received: Arc::new(Mutex::new(BTreeSet::new())),
        }
    }
}

/// A server message as the frame loop takes it: node blocks already decoded (on the network
/// task, so the frame loop never waits on decoding).
#[derive(Debug, Clone)]
pub enum Delivery {
    Manifest(Box<Manifest>),
    Base(Box<BaseMesh>),
    Nodes {
        seq: u64,
        nodes: Vec<DetailNode>,
    },
    /// Preview nodes, held until the store's own replace them.
    Preview {
        seq: u64,
        nodes: Vec<DetailNode>,
    },
    /// The near band of the domain's level set (`/v1/levelset`), fetched once a manifest lists
    /// one (drawn meshes are clipped to it from then on), or why it could not be had.
    LevelSet(Result<Box<NearLevelSet>, HttpError>),
    End,
    Error {
        code: u16,
        message: String,
    },
}

/// Decodes node blocks with the coder of the manifest and base mesh that came before them.
#[derive(Default)]
struct BlockDecoder {
    manifest: Option<Box<Manifest>>,
    /// The base mesh, its coder, and the preview's coder when the manifest names a preview.
    coder: Option<(Box<BaseMesh>, BlockCoder, Option<BlockCoder>)>,
}

impl BlockDecoder {
    fn manifest(&mut self, m: Box<Manifest>) -> Result<Delivery, NetError> {
        // the block decoder assumes an encoding it can read (bits, steps)
        m.encoding.check().map_err(NetError::Manifest)?;
        if let Some(p) = &m.preview {
            p.encoding
                .check()
                .map_err(|e| NetError::Manifest(format!("preview: {e}")))?;
        }
        // a server restarted with another store version: its coders, not the old ones
        if self
            .manifest
            .as_ref()
            .is_some_and(|old| old.encoding != m.encoding || old.preview != m.preview)
        {
            self.coder = None;
        }
        self.manifest = Some(m.clone());
        Ok(Delivery::Manifest(m))
    }

    fn base(&mut self, b: Box<BaseMesh>) -> Result<Delivery, NetError> {
        // a resumed connection sends the same base again: keep its coder
        if self.coder.as_ref().is_none_or(|(held, ..)| **held != *b) {
            let m = self.manifest.as_ref().ok_or_else(|| NetError::OutOfOrder {
                what: "base",
                before: "manifest",
            })?;
            let preview = m
                .preview
                .as_ref()
                .map(|p| BlockCoder::for_preview(&b, &p.encoding));
            self.coder = Some((b.clone(), BlockCoder::new(&b, &m.encoding), preview));
        }
        Ok(Delivery::Base(b))
    }

    /// What `m` delivers: a `Start`, the manifest then the base mesh; anything else, one.
    fn decode(&mut self, m: ServerMsg) -> Result<Vec<Delivery>, NetError> {
        Ok(vec![match m {
            ServerMsg::Start(st) => {
                let SessionStart { manifest, base } = *st;
                let m = self.manifest(Box::new(manifest))?;
                return Ok(vec![m, self.base(Box::new(base))?]);
            }
            ServerMsg::Base(b) => self.base(b)?,
            ServerMsg::Nodes { seq, block } => {
                let (_, coder, _) = self.coder.as_ref().ok_or_else(|| NetError::OutOfOrder {
                    what: "nodes",
                    before: "the base mesh",
                })?;
                let nodes = coder
                    .decode(&block)
                    .map_err(|e| NetError::BadFrame(format!("batch {seq}: {e}")))?;
                Delivery::Nodes { seq, nodes }
            }
            ServerMsg::Preview { seq, block } => {
                let coder = match &self.coder {
                    None => {
                        return Err(NetError::OutOfOrder {
                            what: "preview",
                            before: "the base mesh",
                        })
                    }
                    Some((_, _, None)) => {
                        return Err(NetError::OutOfOrder {
                            what: "a preview",
                            before: "a manifest that describes one",
                        })
                    }
                    Some((_, _, Some(c))) => c,
                };
                let nodes = coder
                    .decode(&block)
                    .map_err(|e| NetError::BadFrame(format!("preview batch {seq}: {e}")))?;
                // only the preview's levels (the manifest checked them against the hierarchy)
                let (levels, base) = match (&self.manifest, &self.coder) {
                    (Some(m), Some((b, ..))) => (m.preview.as_ref().map_or(0, |p| p.levels), b),
                    _ => unreachable!("a preview coder comes with its manifest and base"),
                };
                let end = base.forest().level_start(levels);
                if let Some(n) = nodes.iter().find(|n| n.id >= end) {
                    return Err(NetError::BadFrame(format!(
                        "preview batch {seq}: node {} is beyond the preview's {levels} levels",
                        n.id
                    )));
                }
                Delivery::Preview { seq, nodes }
            }
            ServerMsg::End { .. } => Delivery::End,
            ServerMsg::Error { code, message } => Delivery::Error { code, message },
        }])
    }
}

/// Decoded messages (batches, mostly) the network task may queue ahead of the frame loop.
pub const INGEST_QUEUE: usize = 256;

/// Waits between reconnect attempts: none before the first, then 100 ms times the attempts before.
const RETRY_STEP: Duration = Duration::from_millis(100);

async fn network<T: Transport>(
    transport: T,
    server: ServerUrl,
    token: Option<String>,
    net: Arc<Net>,
    tx: mpsc::Sender<(Delivery, u64)>,
    mut out: mpsc::UnboundedReceiver<ClientMsg>,
    policy: NetPolicy,
) -> Result<(), NetError> {
    let NetPolicy {
        retries,
        max_nodes,
        tf_auto,
    } = policy;
    // errors name the stream's address; its request names the transfer function
    let url = server.stream(None);
    let stream_url = server.stream(tf_auto.then_some(AUTO));
    // the last View the frame loop sent: a new connection gets it again after its Hello (the
    // server's view order is per connection, and the camera may never move again)
    let mut last_view: Option<ClientMsg> = None;
    // consecutive connection attempts that brought no new node (a failed connect counts too)
    let mut failures = 0u32;
    // preview nodes handed to the session (a reconnection names them in `Hello`), in how many
    // batches
    let mut previewed: BTreeSet<TetId> = BTreeSet::new();
    let mut blocks = BlockDecoder::default();
    // the level set is asked for after the first base mesh, and again after a later one (a
    // reconnection) while it has failed, at most LEVELSET_ATTEMPTS times in all
    let levelset = Arc::new(SharedFetch::new());
    let mut levelset_attempts = 0u32;
    // why the last connection ended, once one has
    let mut lost: Option<String> = None;
    // a connect that fails for good: after a lost connection, that loss is the cause
    let give_up = |url: String, lost: Option<String>, reason: String| match lost {
        None => NetError::Connect { url, reason },
        Some(l) => NetError::Disconnected {
            url,
            reason: format!("{l}; reconnecting: {reason}"),
            retries,
        },
    };
    loop {
        // the first attempt after a connection that brought nodes goes at once
        if failures > 1 {
            tokio::time::sleep(RETRY_STEP * (failures - 1)).await;
        }
        // what the client holds, so the server skips it; the server takes at most MAX_RANGES
        // ranges, and whatever a shortened list leaves out comes again (a duplicate, ignored)
        let mut have = ranges_of(&net.received.lock().expect("lock"));
        have.truncate(MAX_RANGES);
        let mut held_previews = ranges_of(&previewed);
        held_previews.truncate(MAX_RANGES);
        let conn = tokio::time::timeout(
            Duration::from_secs(5),
            transport.connect(stream_url.as_str()),
        )
        .await;
        let mut ws = match conn {
            Ok(Ok(ws)) => ws,
            Ok(Err(e)) => {
                failures += 1;
                if failures > retries {
                    return Err(give_up(url, lost, e.to_string()));
                }
                continue;
            }
            Err(_) => {
                failures += 1;
                if failures > retries {
                    return Err(give_up(url, lost, "connect timed out".into()));
                }
                continue;
            }
        };
        let hello = ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            token: token.clone(),
            have,
            previewed: held_previews,
        };
        let mut opening = vec![encode(&hello)?];
        if let Some(v) = &last_view {
            opening.push(encode(v)?);
        }
        let mut sent = Ok(());
        for frame in opening {
            sent = ws.send(Message::Binary(frame.into())).await;
            if sent.is_err() {
                break;
            }
        }
        let reason = if let Err(e) = sent {
            e.to_string()
        } else {
            net.connected.store(true, Ordering::Relaxed);
            'conn: loop {
                tokio::select! {
                    msg = ws.next() => {
                        let msg = match msg {
                            None => break "the server closed the connection".to_string(),
                            // over the limit: the same message would come again on a reconnect
                            Some(Err(WsError::Capacity(e))) => {
                                return Err(NetError::FrameTooLarge(e.to_string()))
                            }
                            Some(Err(e)) => break e.to_string(),
                            Some(Ok(m)) => m,
                        };
                        let Message::Binary(bytes) = msg else { continue };
                        net.bytes.fetch_add(bytes.len() as u64, Ordering::Relaxed);
                        let m = decode_server(&bytes).map_err(|e| NetError::BadFrame(e.to_string()))?;
                        let ms = blocks.decode(m)?;
                        let ask = matches!(levelset.get(), LevelSetFetch::Idle | LevelSetFetch::Failed)
                            && levelset_attempts < LEVELSET_ATTEMPTS;
                        let base = ms.iter().find_map(|d| match d {
                            Delivery::Base(b) => Some(b),
                            _ => None,
                        });
                        if let (Some(base), true) = (base, ask) {
                            levelset_attempts += 1;
                            if let Some(man) = blocks.manifest.as_deref().filter(|m| m.has_levelset_band()) {
                                // beside the stream, so the nodes do not wait for it; only for a
                                // hierarchy within the client's budget (the frame loop refuses
                                // any other), decoded for its exact vertex count
                                let answer = tx.downgrade();
                                match check_hierarchy(base, man, max_nodes) {
                                    Ok(()) => {
                                        let (u, t, n) = (server.clone(), token.clone(), base.vertex_keys().vertex_count());
                                        let (bytes, state) = (net.bytes.clone(), levelset.clone());
                                        state.set(LevelSetFetch::Asked);
                                        tokio::task::spawn_blocking(move || {
                                            let (got, len) = match fetch_levelset(&u, t.as_deref(), n) {
                                                Ok((near, len)) => (Ok(Box::new(near)), len),
                                                Err(e) => (Err(e), 0),
                                            };
                                            let done = if got.is_ok() { LevelSetFetch::Held } else { LevelSetFetch::Failed };
                                            bytes.fetch_add(len, Ordering::Relaxed);
                                            // nobody to tell once the network task has ended; the
                                            // answer goes first, so a retry cannot overtake it
                                            if let Some(tx) = answer.upgrade() {
                                                let _ = tx.blocking_send((Delivery::LevelSet(got), len));
                                            }
                                            state.set(done);
                                        });
                                    }
                                    Err(e) => {
                                        // the frame loop refuses this hierarchy too: no retry
                                        levelset_attempts = LEVELSET_ATTEMPTS;
                                        let why = HttpError {
                                            url: server.levelset(),
                                            reason: format!("level set not fetched: {e}"),
                                        };
                                        let _ = tx.send((Delivery::LevelSet(Err(why)), 0)).await;
                                    }
                                }
                            }
                        }
                        // the frame's bytes go with its first delivery
                        let deliver: Vec<(Delivery, u64)> =
                            ms.into_iter().zip(std::iter::once(bytes.len() as u64).chain(std::iter::repeat(0))).collect();
                        if let [(Delivery::Nodes { nodes, .. }, _)] = &deliver[..] {
                            let mut r = net.received.lock().expect("lock");
                            let before = r.len();
                            r.extend(nodes.iter().map(|n| n.id));
                            if r.len() > before {
                                // progress: this connection is worth reconnecting to again
                                failures = 0;
                            }
                        }
                        // a batch is acknowledged once it is in the session's queue, not when the frame
                        // loop gets to it: ingestion runs at the network's pace, and the queue's bound
                        // is the backpressure
                        for m in deliver {
                            let ack = match &m.0 {
                                Delivery::Nodes { seq, .. } => Some(*seq),
                                Delivery::Preview { seq, nodes } => {
                                    // a reconnection asks for the rest of the preview only
                                    previewed.extend(nodes.iter().map(|n| n.id));
                                    Some(*seq)
                                }
                                _ => None,
                            };
                            if tx.send(m).await.is_err() {
                                return Ok(());
                            }
                            if let Some(seq) = ack {
                                let f = encode(&ClientMsg::Ack { seq })
                                    ?;
                                if let Err(e) = ws.send(Message::Binary(f.into())).await {
                                    break 'conn e.to_string();
                                }
                            }
                        }
                    }
                    m = out.recv() => {
                        let Some(m) = m else { return Ok(()) };
                        let frame = encode(&m)?;
                        if matches!(m, ClientMsg::View(_)) {
                            last_view = Some(m);
                        }
                        if let Err(e) = ws.send(Message::Binary(frame.into())).await {
                            break e.to_string();
                        }
                    }
                }
            }
        };
        // dropped: reconnect and resume, unless the attempts since the last progress ran out
        net.connected.store(false, Ordering::Relaxed);
        failures += 1;
        if failures > retries {
            return Err(NetError::Disconnected {
                url,
                reason,
                retries,
            });
        }
        lost = Some(reason);
        net.reconnects.fetch_add(1, Ordering::Relaxed);
    }
}

/// The client's WebSocket limits: a message may be as large as a whole protocol frame
/// ([`MAX_FRAME_BYTES`] after the 4-byte length prefix); tungstenite's default (16 MiB) would
/// refuse a large base mesh forever.
pub fn ws_config() -> WebSocketConfig {
    WebSocketConfig::default()
        .max_message_size(Some(MAX_FRAME_BYTES + 4))
        .max_frame_size(Some(MAX_FRAME_BYTES + 4))
}

/// What [`Connection::next`] found.
#[derive(Debug)]
pub enum Next {
    /// A delivery and the wire bytes of the message it came in (0 after a message's first).
    Ready(Delivery, u64),
    /// Nothing within the time allowed.
    Empty,
    /// The connection task has ended: everything it delivered has been taken. Why it ended is
    /// [`Connection::finish`]'s.
    Ended,
}

/// A stream from a server on a thread of its own: the connection task on a one-worker runtime,
/// its queue of decoded deliveries, and the frame loop's way back (`View`, `Want`). What
/// `tetwave stream` and the viewer both hold.
pub struct Connection {
    rt: NetRuntime,
    task: tokio::task::JoinHandle<Result<(), NetError>>,
    rx: mpsc::Receiver<(Delivery, u64)>,
    out: mpsc::UnboundedSender<ClientMsg>,
    net: Arc<Net>,
    last_view: Option<ViewParams>,
    server: ServerUrl,
}

impl Connection {
    /// Starts connecting to `server` by WebSocket (on a thread named `thread`); deliveries are
    /// queued from then on.
    pub fn open(
        server: ServerUrl,
        token: Option<String>,
        policy: NetPolicy,
        thread: &str,
    ) -> Result<Connection, NetError> {
        Self::open_with(WebSocket, server, token, policy, thread)
    }

    /// [`Self::open`] through `transport` (tests wrap the WebSocket in [`crate::transport::Faulty`]).
    pub fn open_with<T: Transport>(
        transport: T,
        server: ServerUrl,
        token: Option<String>,
        policy: NetPolicy,
        thread: &str,
    ) -> Result<Connection, NetError> {
        let rt = NetRuntime::new(thread).map_err(NetError::Runtime)?;
        let net = Arc::new(Net::new());
        // the network task acknowledges a batch once it is queued here: when the queue is full
        // the network waits, the server's window fills and the server slows down
        let (tx, rx) = mpsc::channel(INGEST_QUEUE);
        let (out, out_rx) = mpsc::unbounded_channel();
        let task = rt.spawn(network(
            transport,
            server.clone(),
            token,
            net.clone(),
            tx,
            out_rx,
            policy,
        ));
        Ok(Connection {
            rt,
            task,
            rx,
            out,
            net,
            last_view: None,
            server,
        })
    }

    /// The server's address.
    pub fn server(&self) -> &ServerUrl {
        &self.server
    }

    /// The frame loop's messages to the server (what [`crate::ingest::Ingest::apply`] sends).
    pub fn sender(&self) -> &mpsc::UnboundedSender<ClientMsg> {
        &self.out
    }

    /// Tells the server the view when it changed. A new connection after a lost one gets the
    /// last view again from the connection task, whether or not the camera moves.
    pub fn send_view(&mut self, view: ViewParams) {
        if self.last_view != Some(view) {
            let _ = self.out.send(ClientMsg::View(view));
            self.last_view = Some(view);
        }
    }

    /// The next delivery, waiting for it at most `wait` (not at all for zero).
    pub fn next(&mut self, wait: Duration) -> Next {
        let got = if wait.is_zero() {
            match self.rx.try_recv() {
                Ok(m) => Some(m),
                Err(mpsc::error::TryRecvError::Empty) => return Next::Empty,
                Err(mpsc::error::TryRecvError::Disconnected) => None,
            }
        } else {
            let rx = &mut self.rx;
            match self
                .rt
                .block_on(async { tokio::time::timeout(wait, rx.recv()).await })
            {
                Ok(m) => m,
                Err(_) => return Next::Empty,
            }
        };
        match got {
            Some((d, bytes)) => Next::Ready(d, bytes),
            None => Next::Ended,
        }
    }

    /// Why the connection task ended, once [`Self::next`] said it has (it does not wait then):
    /// its error, or [`NetError::TaskEnded`] when it stopped without one.
    pub fn finish(&mut self) -> NetError {
        match self.rt.block_on(&mut self.task) {
            Ok(Err(e)) => e,
            Ok(Ok(())) => NetError::TaskEnded,
            Err(e) => NetError::TaskFailed(e),
        }
    }

    /// Wire bytes received so far (the level set's included).
    pub fn bytes(&self) -> u64 {
        self.net.bytes.load(Ordering::Relaxed)
    }

    /// Connections lost and retried so far.
    pub fn reconnects(&self) -> u64 {
        self.net.reconnects.load(Ordering::Relaxed)
    }

    /// A connection is open (its `Hello` sent).
    pub fn connected(&self) -> bool {
        self.net.connected.load(Ordering::Relaxed)
    }

    /// Stops the connection task (the frame loop is done with it).
    pub fn close(&mut self) {
        self.task.abort();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_protocol::shapes::box5;
    use tetwave_protocol::store_format::Encoding;
    use tetwave_protocol::store_format::Manifest;
    use tetwave_protocol::testing::{manifest_for, unsampled_base};
    use tetwave_protocol::wavelet::LevelSteps;

    /// A manifest whose encoding the block decoder cannot read (a server of another build, a
    /// hostile one) is a protocol error, before any block is decoded with it.
    #[test]
    fn a_manifest_with_an_unreadable_encoding_is_refused() {
        let base = unsampled_base(2, box5([0.0; 3], [1.0; 3]));
        for (encoding, ok) in [
            (Encoding::uniform(12, 0.01), true),
            (Encoding::uniform(40, 0.01), false),
            (
                Encoding::Quantized {
                    bits: 12,
                    step: 0.01,
                    levels: LevelSteps {
                        ratio: 0.5,
                        cap: 2.0,
                    },
                },
                false,
            ),
        ] {
            let m = Manifest {
                encoding,
                ..manifest_for(&base)
            };
            let got = BlockDecoder::default().decode(ServerMsg::Start(Box::new(SessionStart {
                manifest: m,
                base: base.clone(),
            })));
            assert_eq!(got.is_ok(), ok, "{:?}", got.err());
        }
    }
}
