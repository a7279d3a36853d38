//! Hostile and careless clients against an in-process server on loopback (issue 21): work per
//! message proportional to ranges, rate-limited view rescans, WebSocket close codes, the Host and
//! Origin allowlists, token handling, the render queue, deadline and cancellation, header and
//! connection limits. Peers are told apart by their loopback source address (127.0.0.x). Every wait
//! is bounded.

mod stream_common;

use futures_util::{SinkExt, StreamExt};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::{Duration, Instant};
use stream_common::*;
use tetwave_protocol::wire::{ClientMsg, IdRange, ServerMsg};
use tetwave_server::stream::{Limits, Order, ServeConfig};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::Message;

/// One level-5 harmonic store shared by every test of this file.
fn store() -> PathBuf {
    static STORE: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    STORE.get_or_init(|| make_store(5)).1.clone()
}

const ATTACKER: [u8; 4] = [127, 0, 0, 2];
const HONEST: [u8; 4] = [127, 0, 0, 3];

async fn health(addr: SocketAddr) -> serde_json::Value {
    let r = get_from(HONEST, addr, "/healthz", &[]).await;
    assert_eq!(r.status, 200);
    serde_json::from_slice(&r.body).unwrap()
}

/// A stream from [`ATTACKER`] after `Hello` (with `have`), the manifest and the base mesh.
async fn opened(addr: SocketAddr, have: Vec<IdRange>) -> Ws {
    let mut ws = connect_from(ATTACKER, addr, "", &[]).await.unwrap();
    send(&mut ws, &hello(None, have)).await;
    expect_opening(&mut ws).await;
    ws
}

fn whole(n: u64) -> IdRange {
    IdRange { from: 0, to: n }
}

/// The close frame's code, skipping data frames; `None` if the socket ends without one.
async fn close_code(ws: &mut Ws) -> Option<CloseCode> {
    tokio::time::timeout(T, async {
        while let Some(m) = ws.next().await {
            match m {
                Ok(Message::Close(f)) => return f.map(|f| f.code),
                Ok(_) => continue,
                Err(_) => return None,
            }
        }
        None
    })
    .await
    .expect("close within the time limit")
}

/// A `Hello` whose `have` holds 65,536 whole-range entries, then two `Want`s of 65,536 whole
/// ranges each (the attack of the issue: 10.9 s of frozen `/healthz` and ~1.5e9 queued sends). Now
/// each message costs its ranges: the wanted nodes arrive once per `Want` at most, and `/healthz`
/// answers meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn range_floods_cost_ranges_not_ids() {
    let (addr, shared) = start(&store(), ServeConfig::default()).await;
    let n = shared.nodes();
    let t0 = Instant::now();
    let mut ws = opened(addr, vec![whole(n); 65_536]).await;
    match recv(&mut ws).await {
        Some(ServerMsg::End { nodes_sent: 0 }) => {}
        other => panic!("a client that has everything gets End at once, got {other:?}"),
    }
    let hello_s = t0.elapsed().as_secs_f64();
    for _ in 0..2 {
        send(&mut ws, &ClientMsg::Want(vec![whole(n); 65_536])).await;
    }
    let probe = tokio::spawn(async move {
        let mut worst = Duration::ZERO;
        for _ in 0..5 {
            let t = Instant::now();
            health(addr).await;
            worst = worst.max(t.elapsed());
        }
        worst
    });
    // every node at least once, and at most once per Want (a Want applied after nodes went out
    // asks for them again); the per-id code queued 65,536 sends of each
    let (nodes, end_sent, _) = receive_nodes(&mut ws, &coder_for(&store())).await;
    let mut seen = vec![0u32; n as usize];
    for node in &nodes {
        seen[node.id as usize] += 1;
    }
    assert!(
        seen.iter().all(|&k| (1..=2).contains(&k)),
        "each node once or twice"
    );
    assert_eq!(end_sent, nodes.len() as u64);
    let worst = probe.await.unwrap();
    println!(
        "{n} nodes: Hello with 65,536 whole ranges answered in {hello_s:.3} s; \
         worst /healthz during two 65,536-range Wants {:.1} ms",
        worst.as_secs_f64() * 1e3
    );
    // a generous bound for a loaded 2-core machine; the per-id code took seconds here
    assert!(worst < Duration::from_secs(2), "/healthz took {worst:?}");
}

/// A `Cancel` of everything, then a `Want` of one range: only that range arrives.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_then_want_sends_only_the_wanted() {
    let config = ServeConfig {
        window: 1,
        batch: 64,
        ..ServeConfig::default()
    };
    let (addr, shared) = start(&store(), config).await;
    let n = shared.nodes();
    let mut ws = opened(addr, vec![]).await;
    // the first batch is in flight (window 1, not acked): cancel everything, want 100..300
    send(&mut ws, &ClientMsg::Cancel(vec![whole(n); 1000])).await;
    send(
        &mut ws,
        &ClientMsg::Want(vec![IdRange { from: 100, to: 300 }; 10]),
    )
    .await;
    // the Cancel may end the stream (End) before the Want arrives; the Want brings another End
    let (mut nodes, _, _) = receive_nodes(&mut ws, &coder_for(&store())).await;
    if !nodes.iter().any(|d| d.id >= 64) {
        nodes.extend(receive_nodes(&mut ws, &coder_for(&store())).await.0);
    }
    let after_first: Vec<u64> = nodes.iter().map(|d| d.id).filter(|&i| i >= 64).collect();
    let want: Vec<u64> = (100..300).collect();
    assert_eq!(
        after_first, want,
        "only the wanted range after the first batch"
    );
}

/// View order with a `View` before every batch: rescans are rate-limited, not one per batch.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_view_per_batch_does_not_rescan_per_batch() {
    let config = ServeConfig {
        order: Order::View,
        batch: 64,
        ..ServeConfig::default()
    };
    let (addr, shared) = start(&store(), config).await;
    let n = shared.nodes();
    let mut ws = opened(addr, vec![]).await;
    let t0 = Instant::now();
    let mut batches = 0u64;
    let mut got = 0u64;
    loop {
        match recv(&mut ws).await {
            Some(ServerMsg::Nodes { seq, block }) => {
                batches += 1;
                got += block.count as u64;
                // a slightly different camera every batch
                let a = batches as f64 * 0.05;
                let v = view_from([3.0 * a.cos(), 3.0 * a.sin(), 1.0], [0.5, 0.5, 0.5]);
                send(&mut ws, &ClientMsg::View(v)).await;
                send(&mut ws, &ClientMsg::Ack { seq }).await;
            }
            Some(ServerMsg::End { .. }) => break,
            other => panic!("unexpected {other:?}"),
        }
    }
    let secs = t0.elapsed().as_secs_f64();
    let rescans = health(addr).await["view_rescans"].as_u64().unwrap();
    println!("{n} nodes, {batches} batches with a View each, {secs:.2} s: {rescans} rescans");
    assert_eq!(got, n);
    // chunks of max(4096, n/16) ids: at most n/4096 + 1 rescans for running out, plus changed
    // views at most one per 50 ms
    let bound = n / 4096 + 2 + (secs / 0.05).ceil() as u64;
    assert!(rescans <= bound, "{rescans} rescans > {bound}");
    assert!(
        rescans < batches / 2,
        "{rescans} rescans for {batches} batches"
    );
}

/// Close codes: a message over the limit closes with 1009, a frame that does not decode with 1008
/// (after an `Error` message), a wrong token in `Hello` with 1008.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_closes_carry_codes() {
    let config = ServeConfig {
        token: Some("s3cret".into()),
        ..ServeConfig::default()
    };
    let (addr, _) = start(&store(), config).await;
    // oversized: 5 MiB against a 4 MiB limit
    let mut ws = connect_from(ATTACKER, addr, "", &[]).await.unwrap();
    let _ = ws.send(Message::Binary(vec![0u8; 5 << 20].into())).await;
    assert_eq!(close_code(&mut ws).await, Some(CloseCode::Size));
    // garbage after a good Hello
    let mut ws = connect_from(ATTACKER, addr, "", &[]).await.unwrap();
    send(&mut ws, &hello(Some("s3cret"), vec![])).await;
    ws.send(Message::Binary(vec![0xff; 40].into()))
        .await
        .unwrap();
    assert_eq!(close_code(&mut ws).await, Some(CloseCode::Policy));
    // wrong token in Hello: an Error then 1008
    let mut ws = connect_from(ATTACKER, addr, "", &[]).await.unwrap();
    send(&mut ws, &hello(Some("guess"), vec![])).await;
    match recv(&mut ws).await {
        Some(ServerMsg::Error { code: 401, .. }) => {}
        other => panic!("expected Error 401, got {other:?}"),
    }
    assert_eq!(close_code(&mut ws).await, Some(CloseCode::Policy));
}

/// Cross-origin WebSockets and foreign Hosts are refused; same-origin and non-browser clients pass.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn foreign_origins_and_hosts_are_refused() {
    let (addr, _) = start(&store(), ServeConfig::default()).await;
    let evil = connect_from(ATTACKER, addr, "", &[("Origin", "http://evil.example")]).await;
    match evil {
        Err(tokio_tungstenite::tungstenite::Error::Http(r)) => assert_eq!(r.status(), 403),
        other => panic!(
            "a cross-origin stream must be refused, got {:?}",
            other.map(|_| ())
        ),
    }
    let own = format!("http://{addr}");
    let mut ws = connect_from(HONEST, addr, "", &[("Origin", own.as_str())])
        .await
        .expect("same origin streams");
    send(&mut ws, &hello(None, vec![])).await;
    assert!(matches!(recv(&mut ws).await, Some(ServerMsg::Start(_))));
    for path in ["/healthz", "/v1/manifest", "/"] {
        let r = get_from(ATTACKER, addr, path, &[("Host", "evil.example")]).await;
        assert_eq!(r.status, 403, "{path} with a foreign Host");
        let r = get_from(
            ATTACKER,
            addr,
            path,
            &[("Host", &format!("localhost:{}", addr.port()))],
        )
        .await;
        assert_eq!(r.status, 200, "{path} as localhost");
    }
    // an <img> on another site must not start a render
    let r = get_from(
        ATTACKER,
        addr,
        "/v1/render?width=8&height=8",
        &[
            ("Sec-Fetch-Site", "cross-site"),
            ("Sec-Fetch-Mode", "no-cors"),
        ],
    )
    .await;
    assert_eq!(r.status, 403);
}

/// Wrong tokens: 401, logged, then 429 with `Retry-After` for that address only (even with the
/// right token); the scheme is case-insensitive; authenticated answers are not publicly cacheable.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn token_failures_are_rate_limited() {
    let config = ServeConfig {
        token: Some("s3cret".into()),
        ..ServeConfig::default()
    };
    let (addr, _) = start(&store(), config).await;
    let ok = get_from(
        HONEST,
        addr,
        "/v1/manifest",
        &[("Authorization", "bearer s3cret")],
    )
    .await;
    assert_eq!(ok.status, 200, "lowercase scheme");
    assert_eq!(ok.headers["cache-control"], "private, no-store");
    assert!(ok.headers["vary"].contains("Authorization"));
    let mut statuses = Vec::new();
    for i in 0..12 {
        let t = format!("Bearer guess{i}");
        statuses.push(
            get_from(ATTACKER, addr, "/v1/manifest", &[("Authorization", &t)])
                .await
                .status,
        );
    }
    assert_eq!(&statuses[..10], &[401; 10]);
    assert_eq!(&statuses[10..], &[429; 2], "{statuses:?}");
    let locked = get_from(
        ATTACKER,
        addr,
        "/v1/manifest",
        &[("Authorization", "Bearer s3cret")],
    )
    .await;
    assert_eq!(locked.status, 429);
    assert!(locked.headers.contains_key("retry-after"));
    let r = connect_from(ATTACKER, addr, "?token=guess", &[]).await;
    assert!(r.is_err(), "the stream is locked too");
    let other = get_from(
        HONEST,
        addr,
        "/v1/manifest",
        &[("Authorization", "Bearer s3cret")],
    )
    .await;
    assert_eq!(other.status, 200, "another address is not affected");
}

/// The render queue: one runs and `render_queue` wait; more get 503 with `Retry-After` at once. A
/// render past its deadline answers 503 and is cancelled; an abandoned one is cancelled too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn renders_are_queued_bounded_and_cancelled() {
    let config = ServeConfig {
        limits: Limits {
            render_queue: 1,
            render_deadline: Duration::from_secs(3),
            ..Limits::default()
        },
        ..ServeConfig::default()
    };
    let (addr, _) = start(&store(), config).await;
    // warm up: the store's synthesis happens on the first render
    let r = get_from(
        HONEST,
        addr,
        "/v1/render?width=8&height=8&renderer=cpu",
        &[],
    )
    .await;
    assert_eq!(r.status, 200);
    let slow = "/v1/render?width=2048&height=2048&renderer=cpu";
    let mut tasks = Vec::new();
    for k in 0..4u8 {
        tasks.push(tokio::spawn(async move {
            let t = Instant::now();
            let r = get_from([127, 0, 0, 10 + k], addr, slow, &[]).await;
            (r.status, r.headers.get("retry-after").cloned(), t.elapsed())
        }));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let mut results = Vec::new();
    for t in tasks {
        results.push(t.await.unwrap());
    }
    println!("4 concurrent 2048² CPU renders, queue 1, deadline 3 s: {results:?}");
    let busy = results
        .iter()
        .filter(|r| r.0 == 503 && r.2 < Duration::from_secs(1))
        .count();
    assert!(
        busy >= 2,
        "two beyond the running one and the queue get 503 at once: {results:?}"
    );
    assert!(
        results.iter().all(|r| r.0 == 503 && r.1.is_some()),
        "{results:?}"
    );
    // the deadline cancelled the ones that ran; nothing keeps running
    let deadline = Instant::now() + T;
    loop {
        let h = health(addr).await;
        let r = &h["renders"];
        if r["running"] == 0 && r["cancelled"].as_u64().unwrap() >= 1 {
            break;
        }
        assert!(Instant::now() < deadline, "renders still running: {r}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // abandoned: the client goes away after 300 ms
    let before = health(addr).await["renders"]["cancelled"].as_u64().unwrap();
    let mut s = tcp_from(HONEST, addr).await.unwrap();
    s.write_all(format!("GET {slow} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    drop(s);
    let t0 = Instant::now();
    loop {
        let h = health(addr).await;
        let r = &h["renders"];
        if r["running"] == 0 && r["cancelled"].as_u64().unwrap() > before {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(2),
            "abandoned render still running: {r}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    println!(
        "abandoned render stopped {:.0} ms after the client left",
        t0.elapsed().as_secs_f64() * 1e3
    );
    // over the pixel budget: refused before any work
    let r = get_from(HONEST, addr, "/v1/render?width=4096&height=4096", &[]).await;
    assert_eq!(r.status, 400);
    assert!(String::from_utf8_lossy(&r.body).contains("render budget"));
}

/// Slow headers and idle keep-alive connections are closed after the header timeout; a peer's
/// connections and streams beyond its limits are refused while another peer is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn header_timeout_and_peer_limits() {
    let config = ServeConfig {
        limits: Limits {
            header_read_timeout: Duration::from_secs(1),
            max_connections_per_peer: 4,
            max_streams_per_peer: 2,
            ..Limits::default()
        },
        ..ServeConfig::default()
    };
    let (addr, _) = start(&store(), config).await;
    async fn closed_within(s: &mut tokio::net::TcpStream, d: Duration) -> bool {
        let mut buf = [0u8; 4096];
        let t = Instant::now();
        while t.elapsed() < d {
            match tokio::time::timeout(d, s.read(&mut buf)).await {
                Ok(Ok(0)) | Ok(Err(_)) => return true,
                Ok(Ok(_)) => continue, // a response; keep reading
                Err(_) => return false,
            }
        }
        false
    }
    // slowloris: half a request line, then nothing
    let mut slow = tcp_from(ATTACKER, addr).await.unwrap();
    slow.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127")
        .await
        .unwrap();
    assert!(
        closed_within(&mut slow, Duration::from_secs(5)).await,
        "slow headers closed"
    );
    // idle keep-alive after one request
    let mut idle = tcp_from(ATTACKER, addr).await.unwrap();
    idle.write_all(format!("GET /healthz HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    assert!(
        closed_within(&mut idle, Duration::from_secs(5)).await,
        "idle keep-alive closed"
    );
    // connections per peer: 4 held, the 5th is closed at once, another peer is served
    let mut held = Vec::new();
    for _ in 0..4 {
        held.push(tcp_from(ATTACKER, addr).await.unwrap());
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    let mut fifth = tcp_from(ATTACKER, addr).await.unwrap();
    assert!(
        closed_within(&mut fifth, Duration::from_millis(1500)).await,
        "5th connection refused"
    );
    assert_eq!(get_from(HONEST, addr, "/healthz", &[]).await.status, 200);
    drop(held);
    // the server sees them close
    let t0 = Instant::now();
    while health(addr).await["open_connections"].as_u64().unwrap() > 1 {
        assert!(t0.elapsed() < T, "closed connections still counted");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // streams per peer: 2, then 429
    let mut streams = Vec::new();
    for _ in 0..2 {
        streams.push(connect_from(ATTACKER, addr, "", &[]).await.unwrap());
    }
    match connect_from(ATTACKER, addr, "", &[]).await {
        Err(tokio_tungstenite::tungstenite::Error::Http(r)) => assert_eq!(r.status(), 429),
        other => panic!(
            "a third stream must be refused, got {:?}",
            other.map(|_| ())
        ),
    }
    assert!(connect_from(HONEST, addr, "", &[]).await.is_ok());
}

/// A stream the client leaves silent closes with 1001 after the idle timeout; a store that fails to
/// read mid-stream gets `Error 500` and a close with 1011.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_and_internal_failures_close_with_codes() {
    // idle: the client takes the window's batches and never acknowledges them
    let config = ServeConfig {
        idle_timeout: Duration::from_secs(1),
        ..ServeConfig::default()
    };
    let (addr, _) = start(&store(), config).await;
    let mut ws = connect_from(ATTACKER, addr, "", &[]).await.unwrap();
    send(&mut ws, &hello(None, vec![])).await;
    let t0 = Instant::now();
    assert_eq!(close_code(&mut ws).await, Some(CloseCode::Away));
    assert!(t0.elapsed() >= Duration::from_secs(1));

    // internal: nodes are read from disk (no cache), and the blocks vanish after opening
    let d = tempfile::tempdir().unwrap();
    let copy = d.path().join("store");
    std::fs::create_dir(&copy).unwrap();
    for e in std::fs::read_dir(store()).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), copy.join(e.file_name())).unwrap();
    }
    let config = ServeConfig {
        cache_limit_bytes: 0,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&copy, config).await;
    std::fs::write(copy.join("blocks.bin"), b"").unwrap();
    let mut ws = connect_from(ATTACKER, addr, "", &[]).await.unwrap();
    send(&mut ws, &hello(None, vec![])).await;
    let mut error = None;
    let code = tokio::time::timeout(T, async {
        while let Some(m) = ws.next().await {
            match m {
                Ok(Message::Binary(b)) => {
                    if let Ok(ServerMsg::Error { code, .. }) =
                        tetwave_protocol::wire::decode_server(&b)
                    {
                        error = Some(code);
                    }
                }
                Ok(Message::Close(f)) => return f.map(|f| f.code),
                Ok(_) => {}
                Err(_) => return None,
            }
        }
        None
    })
    .await
    .unwrap();
    assert_eq!(error, Some(500));
    assert_eq!(code, Some(CloseCode::Error));
}

/// The total connection limit holds across addresses.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn total_connection_limit() {
    let config = ServeConfig {
        limits: Limits {
            max_connections: 3,
            ..Limits::default()
        },
        ..ServeConfig::default()
    };
    let (addr, _) = start(&store(), config).await;
    let mut held = Vec::new();
    for k in 0..3u8 {
        held.push(tcp_from([127, 0, 7, k], addr).await.unwrap());
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    let mut fourth = tcp_from([127, 0, 7, 9], addr).await.unwrap();
    let mut buf = [0u8; 16];
    let r = tokio::time::timeout(Duration::from_secs(2), fourth.read(&mut buf)).await;
    assert!(
        matches!(r, Ok(Ok(0)) | Ok(Err(_))),
        "the 4th connection is closed at once: {r:?}"
    );
    drop(held);
    // room again once they are gone
    let t0 = Instant::now();
    loop {
        let mut s = tcp_from(HONEST, addr).await.unwrap();
        s.write_all(
            format!("GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n")
                .as_bytes(),
        )
        .await
        .unwrap();
        let mut out = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(2), s.read_to_end(&mut out)).await;
        if out.starts_with(b"HTTP/1.1 200") {
            break;
        }
        assert!(t0.elapsed() < T, "no room after the connections closed");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
