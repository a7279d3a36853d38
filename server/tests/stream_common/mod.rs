//! Helpers shared by the `stream_*` tests: a store, an in-process server on 127.0.0.1:0, a minimal
//! HTTP/1.1 GET, and a minimal WebSocket stream client (tokio-tungstenite). Every wait is bounded.
#![allow(dead_code)]

use futures_util::{SinkExt, StreamExt};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::wire::{
    decode_server, encode, ClientMsg, IdRange, ServerMsg, SessionStart, ViewParams,
    PROTOCOL_VERSION,
};
use tetwave_protocol::{BaseMesh, DetailNode};
use tetwave_server::prepare::{prepare, PrepareOptions};
use tetwave_server::stream::{serve_on, ServeConfig, Shared};
use tetwave_store::Manifest;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite::Message;

pub const T: Duration = Duration::from_secs(60);

/// A harmonic store of `levels` levels in a temporary directory.
pub fn make_store(levels: u8) -> (tempfile::TempDir, PathBuf) {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("store");
    let mut o = PrepareOptions::new("synthetic:harmonic", &p);
    o.levels = Some(levels);
    prepare(&o).unwrap();
    (d, p)
}

/// The block coder of a store (what a client builds from its manifest and base mesh).
pub fn coder_for(store: &Path) -> BlockCoder {
    let s = tetwave_store::Store::open(store).unwrap();
    BlockCoder::new(&s.base, &s.manifest.encoding)
}

/// Starts a server on 127.0.0.1:0 in the current runtime.
pub async fn start(store: &Path, config: ServeConfig) -> (SocketAddr, Arc<Shared>) {
    let shared = Shared::open(store, config).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(serve_on(listener, shared.clone()));
    (addr, shared)
}

pub struct HttpResponse {
    pub status: u16,
    pub headers: HashMap<String, String>,
    pub body: Vec<u8>,
}

/// `GET path` with extra header lines, `Connection: close`.
pub async fn get(addr: SocketAddr, path: &str, extra: &[(&str, &str)]) -> HttpResponse {
    get_from([127, 0, 0, 1], addr, path, extra).await
}

/// A TCP connection to `addr` from the loopback address `ip` (any 127.x.y.z works on Linux), so a
/// test can play several peers.
pub async fn tcp_from(ip: [u8; 4], addr: SocketAddr) -> std::io::Result<tokio::net::TcpStream> {
    let sock = tokio::net::TcpSocket::new_v4()?;
    sock.bind(SocketAddr::from((ip, 0)))?;
    sock.connect(addr).await
}

/// [`get`] from the loopback address `ip`. A `Host` in `extra` replaces the default one.
pub async fn get_from(
    ip: [u8; 4],
    addr: SocketAddr,
    path: &str,
    extra: &[(&str, &str)],
) -> HttpResponse {
    tokio::time::timeout(T, async {
        let mut s = tcp_from(ip, addr).await.unwrap();
        let mut req = format!("GET {path} HTTP/1.1\r\n");
        if !extra.iter().any(|(k, _)| k.eq_ignore_ascii_case("host")) {
            req.push_str(&format!("Host: {addr}\r\n"));
        }
        req.push_str("Connection: close\r\n");
        for (k, v) in extra {
            req.push_str(&format!("{k}: {v}\r\n"));
        }
        req.push_str("\r\n");
        s.write_all(req.as_bytes()).await.unwrap();
        let mut buf = Vec::new();
        s.read_to_end(&mut buf).await.unwrap();
        let split = buf
            .windows(4)
            .position(|w| w == b"\r\n\r\n")
            .expect("header end");
        let head = String::from_utf8_lossy(&buf[..split]).to_string();
        let mut lines = head.split("\r\n");
        let status: u16 = lines
            .next()
            .unwrap()
            .split_whitespace()
            .nth(1)
            .unwrap()
            .parse()
            .unwrap();
        let headers: HashMap<String, String> = lines
            .filter_map(|l| l.split_once(':'))
            .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
            .collect();
        let mut body = buf[split + 4..].to_vec();
        if headers
            .get("transfer-encoding")
            .is_some_and(|v| v.contains("chunked"))
        {
            body = dechunk(&body);
        }
        HttpResponse {
            status,
            headers,
            body,
        }
    })
    .await
    .expect("HTTP request timed out")
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let eol = b.windows(2).position(|w| w == b"\r\n").unwrap();
        let n = usize::from_str_radix(std::str::from_utf8(&b[..eol]).unwrap().trim(), 16).unwrap();
        b = &b[eol + 2..];
        if n == 0 {
            return out;
        }
        out.extend_from_slice(&b[..n]);
        b = &b[n + 2..];
    }
}

pub type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

pub async fn connect(addr: SocketAddr, query: &str) -> Ws {
    let url = format!("ws://{addr}/v1/stream{query}");
    let (ws, _) = tokio::time::timeout(T, tokio_tungstenite::connect_async(url))
        .await
        .expect("connect timed out")
        .expect("connect");
    ws
}

/// A stream WebSocket from the loopback address `ip`, with extra request headers.
pub async fn connect_from(
    ip: [u8; 4],
    addr: SocketAddr,
    query: &str,
    headers: &[(&str, &str)],
) -> Result<Ws, tokio_tungstenite::tungstenite::Error> {
    use tokio_tungstenite::tungstenite::client::IntoClientRequest;
    let mut req = format!("ws://{addr}/v1/stream{query}")
        .into_client_request()
        .unwrap();
    for (k, v) in headers {
        req.headers_mut().insert(
            tokio_tungstenite::tungstenite::http::HeaderName::from_bytes(k.as_bytes()).unwrap(),
            v.parse().unwrap(),
        );
    }
    let tcp = tcp_from(ip, addr).await?;
    let (ws, _) = tokio::time::timeout(
        T,
        tokio_tungstenite::client_async(req, tokio_tungstenite::MaybeTlsStream::Plain(tcp)),
    )
    .await
    .expect("connect timed out")?;
    Ok(ws)
}

pub async fn send(ws: &mut Ws, m: &ClientMsg) {
    ws.send(Message::Binary(encode(m).unwrap().into()))
        .await
        .unwrap();
}

pub fn hello(token: Option<&str>, have: Vec<IdRange>) -> ClientMsg {
    ClientMsg::Hello {
        version: PROTOCOL_VERSION,
        token: token.map(String::from),
        have,
        previewed: vec![],
    }
}

/// Takes a session's opening after `Hello`: `Start`, the manifest and the base mesh.
pub async fn expect_opening(ws: &mut Ws) {
    assert!(matches!(recv(ws).await, Some(ServerMsg::Start(_))));
}

/// A stream opened with `Hello` (no token, no `have`), past the manifest and base mesh.
pub async fn open(addr: SocketAddr, query: &str) -> Ws {
    let mut ws = connect(addr, query).await;
    send(&mut ws, &hello(None, vec![])).await;
    expect_opening(&mut ws).await;
    ws
}

/// The next server message (`None` when the socket closed), bounded by `T`.
pub async fn recv(ws: &mut Ws) -> Option<ServerMsg> {
    recv_within(ws, T).await.expect("server message timed out")
}

/// The next server message within `d`: `Err(())` on timeout, `Ok(None)` on close.
pub async fn recv_within(ws: &mut Ws, d: Duration) -> Result<Option<ServerMsg>, ()> {
    let fut = async {
        loop {
            match ws.next().await {
                None | Some(Err(_)) => return None,
                Some(Ok(Message::Binary(b))) => return Some(decode_server(&b).expect("decodes")),
                Some(Ok(Message::Close(_))) => return None,
                Some(Ok(_)) => continue,
            }
        }
    };
    tokio::time::timeout(d, fut).await.map_err(|_| ())
}

/// What one streamed session received.
pub struct Session {
    pub manifest: Manifest,
    pub base: BaseMesh,
    /// Nodes in arrival order.
    pub nodes: Vec<DetailNode>,
    pub end_nodes_sent: u64,
    /// Nodes per batch, in arrival order (a batch's nodes arrive in id order, a block's order).
    pub batches: Vec<usize>,
}

/// Receives `Start`, then batches (acking each) until `End`.
pub async fn receive_all(ws: &mut Ws) -> Session {
    let SessionStart { manifest, base } = match recv(ws).await {
        Some(ServerMsg::Start(st)) => *st,
        other => panic!("expected the session's start, got {other:?}"),
    };
    let coder = BlockCoder::new(&base, &manifest.encoding);
    let (nodes, end_nodes_sent, batches) = receive_nodes(ws, &coder).await;
    Session {
        manifest,
        base,
        nodes,
        end_nodes_sent,
        batches,
    }
}

/// Node batches (acked, `seq` checked to increase by one) until `End`: the nodes, `End`'s count
/// and the batches' sizes.
pub async fn receive_nodes(ws: &mut Ws, coder: &BlockCoder) -> (Vec<DetailNode>, u64, Vec<usize>) {
    let mut nodes = Vec::new();
    let mut expect_seq: Option<u64> = None;
    let mut batches = Vec::new();
    loop {
        match recv(ws).await {
            Some(ServerMsg::Nodes { seq, block }) => {
                let n = coder.decode(&block).unwrap();
                if let Some(e) = expect_seq {
                    assert_eq!(seq, e, "seq increases by one");
                }
                expect_seq = Some(seq + 1);
                batches.push(n.len());
                nodes.extend(n);
                send(ws, &ClientMsg::Ack { seq }).await;
            }
            Some(ServerMsg::End { nodes_sent }) => return (nodes, nodes_sent, batches),
            other => panic!("unexpected {other:?}"),
        }
    }
}

/// A full session: connect, Hello, receive everything, close.
pub async fn session(addr: SocketAddr, query: &str, token: Option<&str>) -> Session {
    let mut ws = connect(addr, query).await;
    send(&mut ws, &hello(token, vec![])).await;
    let s = receive_all(&mut ws).await;
    let _ = ws.close(None).await;
    s
}

/// A camera looking at the volume's centre from `eye`.
pub fn view_from(eye: [f64; 3], target: [f64; 3]) -> ViewParams {
    ViewParams {
        eye,
        target,
        up: [0.0, 0.0, 1.0],
        fovy_deg: 40.0,
        width: 256,
        height: 256,
        tol_px: 1.0,
    }
}
