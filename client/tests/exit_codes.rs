//! `tetwave stream` does not lie with its exit status: the real binary against a small fake server
//! (tokio-tungstenite on 127.0.0.1:0, a script per scenario). A failure past the base mesh — a node
//! the session refuses, a frame it cannot read, a message over the limit, a connection lost for
//! good, a hierarchy over the client's budget, nodes the server never delivers — ends with one
//! `error:` line naming the cause and a non-zero status, with or without `--until-complete`; a
//! session the user bounds (`--frames`) or that completes is a success. Loopback only, every wait
//! bounded, reconnects limited with `--retries`.

use futures_util::{SinkExt, StreamExt};
use std::future::Future;
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tetwave_protocol::block::{BlockCoder, NodeBlock};
use tetwave_protocol::shapes::box5;
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::testing::{detail_nodes, manifest_for, unsampled_base};
use tetwave_protocol::wire::{
    decode_client, encode, ClientMsg, IdRange, ServerMsg, SessionStart, MAX_FRAME_BYTES,
};
use tetwave_protocol::{BaseMesh, DetailNode};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::WebSocketStream;

type Ws = WebSocketStream<TcpStream>;

/// The longest a client run may take (they take well under a second or two).
const CLIENT_LIMIT: Duration = Duration::from_secs(60);

/// A level-`levels` box5 hierarchy: its manifest, base mesh and every detail node.
fn dataset(levels: u8) -> (Manifest, BaseMesh, Vec<DetailNode>) {
    let (base, nodes) = detail_nodes(unsampled_base(levels, box5([0.0; 3], [1.0; 3])), |p| {
        (p[0] + 2.0 * p[1] - p[2]) as f32
    });
    (manifest_for(&base), base, nodes)
}

/// A fake server: runs `script(connection index, socket)` for each connection, at most
/// `max_conns` of them (then the listener closes: a reconnect is refused).
struct Fake {
    addr: SocketAddr,
    conns: Arc<AtomicUsize>,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for Fake {
    fn drop(&mut self) {
        self.task.abort();
    }
}

async fn fake<F, Fut>(max_conns: usize, script: F) -> Fake
where
    F: Fn(usize, Ws) -> Fut + Send + Sync + 'static,
    Fut: Future<Output = ()> + Send + 'static,
{
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let conns = Arc::new(AtomicUsize::new(0));
    let counter = conns.clone();
    let script = Arc::new(script);
    let task = tokio::spawn(async move {
        let mut handlers = Vec::new();
        for i in 0..max_conns {
            let Ok((tcp, _)) = listener.accept().await else {
                break;
            };
            counter.fetch_add(1, Ordering::SeqCst);
            let script = script.clone();
            handlers.push(tokio::spawn(async move {
                if let Ok(ws) = tokio_tungstenite::accept_async(tcp).await {
                    script(i, ws).await;
                }
            }));
        }
        drop(listener);
        // keep the connections' tasks until the test ends (dropping the handles detaches them)
        futures_util::future::join_all(handlers).await;
    });
    Fake { addr, conns, task }
}

/// The client's next message (`None` once it is gone).
async fn recv(ws: &mut Ws) -> Option<ClientMsg> {
    loop {
        match tokio::time::timeout(Duration::from_secs(30), ws.next()).await {
            Ok(Some(Ok(Message::Binary(b)))) => return Some(decode_client(&b).unwrap()),
            Ok(Some(Ok(_))) => continue,
            _ => return None,
        }
    }
}

/// A `Nodes` frame carrying `nodes` coded as the server codes them.
fn nodes_msg(m: &Manifest, base: &BaseMesh, seq: u64, nodes: &[DetailNode]) -> ServerMsg {
    let block = BlockCoder::new(base, &m.encoding).encode(nodes).unwrap();
    ServerMsg::Nodes { seq, block }
}

async fn send(ws: &mut Ws, m: &ServerMsg) {
    let _ = ws.send(Message::Binary(encode(m).unwrap().into())).await;
}

/// Reads the client's Hello and sends the manifest and the base mesh.
async fn open(ws: &mut Ws, m: &Manifest, base: &BaseMesh) {
    assert!(matches!(recv(ws).await, Some(ClientMsg::Hello { .. })));
    let start = SessionStart {
        manifest: m.clone(),
        base: base.clone(),
    };
    send(ws, &ServerMsg::Start(Box::new(start))).await;
}

/// Keeps the connection open, reading (and dropping) what the client sends, until it leaves.
async fn idle(ws: &mut Ws) {
    while recv(ws).await.is_some() {}
}

/// What one run of the client did.
struct Run {
    status: Option<i32>,
    stderr: String,
    secs: f64,
}

impl Run {
    /// The one `error:` line (asserting there is exactly one, of one line).
    fn error_line(&self) -> &str {
        let lines: Vec<&str> = self
            .stderr
            .lines()
            .filter(|l| l.starts_with("error:"))
            .collect();
        assert_eq!(lines.len(), 1, "one error line expected:\n{}", self.stderr);
        lines[0]
    }

    /// Failed, with one error line that contains every needle.
    fn assert_fails_with(&self, needles: &[&str]) {
        assert!(
            self.status.is_some_and(|c| c != 0),
            "expected a failure, got {:?}:\n{}",
            self.status,
            self.stderr
        );
        let line = self.error_line();
        for n in needles {
            assert!(line.contains(n), "{n:?} not in {line:?}");
        }
        assert!(!self.stderr.contains("panicked"), "{}", self.stderr);
    }
}

/// Runs `tetwave stream ws://addr --headless --no-render --frame-ms 5 --out DIR/out` plus `args`,
/// killed after [`CLIENT_LIMIT`].
async fn client(addr: SocketAddr, dir: &Path, args: &[&str]) -> Run {
    let out = dir.join("out");
    let (so, se) = (dir.join("stdout"), dir.join("stderr"));
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_tetwave"));
    cmd.args([
        "stream",
        &format!("ws://{addr}"),
        "--headless",
        "--no-render",
    ])
    .args(["--frame-ms", "5", "--out", out.to_str().unwrap()])
    .args(args)
    .stdin(Stdio::null())
    .stdout(std::fs::File::create(&so).unwrap())
    .stderr(std::fs::File::create(&se).unwrap());
    let t0 = Instant::now();
    let status = tokio::task::spawn_blocking(move || {
        let mut child = cmd.spawn().expect("tetwave runs");
        loop {
            if let Some(s) = child.try_wait().unwrap() {
                return Some(s);
            }
            if t0.elapsed() > CLIENT_LIMIT {
                let _ = child.kill();
                let _ = child.wait();
                return None;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    })
    .await
    .unwrap()
    .unwrap_or_else(|| panic!("tetwave stream ran past {CLIENT_LIMIT:?}"));
    Run {
        status: status.code(),
        stderr: std::fs::read_to_string(&se).unwrap(),
        secs: t0.elapsed().as_secs_f64(),
    }
}

/// A node claiming a vertex another node owns, after valid ones: the session refuses it, and the
/// run fails although `--until-complete` is not given and frames are left.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_the_session_refuses_is_an_error() {
    let (m, base, nodes) = dataset(2);
    let srv = fake(1, move |_, mut ws| {
        let (m, base, nodes) = (m.clone(), base.clone(), nodes.clone());
        async move {
            open(&mut ws, &m, &base).await;
            // the last node that does not own all its edges, after every node below it (the
            // owners of its other edges among them), then claiming every edge
            let k = nodes.iter().rposition(|x| x.owned != 0x3f).unwrap();
            send(&mut ws, &nodes_msg(&m, &base, 0, &nodes[..k])).await;
            let bad = DetailNode {
                owned: 0x3f,
                coeffs: vec![0.0; 6],
                ..nodes[k].clone()
            };
            send(&mut ws, &nodes_msg(&m, &base, 1, &[bad])).await;
            idle(&mut ws).await;
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "400", "--retries", "0"]).await;
    r.assert_fails_with(&["invalid node", "which another node already owns"]);
    // the frames before the failure are kept
    assert!(d.path().join("out/frames.jsonl").exists());
}

/// A node whose mask and coefficients disagree does not pass the frame's checks, and a frame of
/// garbage does not decode: each is an error naming it, not a reconnect loop.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_the_client_cannot_read_is_an_error() {
    let (m, base, nodes) = dataset(2);
    let n = nodes.len() as u64;
    let srv = fake(1, move |_, mut ws| {
        let (m, base) = (m.clone(), base.clone());
        async move {
            open(&mut ws, &m, &base).await;
            // a block whose nodes lie beyond the hierarchy
            let block = NodeBlock {
                count: 2,
                first: n + 3,
                bytes: vec![],
            };
            send(&mut ws, &ServerMsg::Nodes { seq: 0, block }).await;
            idle(&mut ws).await;
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "400"]).await;
    r.assert_fails_with(&[
        "unreadable frame from the server",
        &format!("node id {} is outside the hierarchy's {n} nodes", n + 3),
    ]);
    assert_eq!(srv.conns.load(Ordering::SeqCst), 1, "no reconnect");

    let (m, base, _) = dataset(2);
    let srv = fake(1, move |_, mut ws| {
        let (m, base) = (m.clone(), base.clone());
        async move {
            open(&mut ws, &m, &base).await;
            let _ = ws
                .send(Message::Binary(vec![9, 0, 0, 0, 1, 0, 7].into()))
                .await;
            idle(&mut ws).await;
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "400"]).await;
    r.assert_fails_with(&["unreadable frame from the server", "truncated"]);
}

/// The server goes away in the middle of a frame, before `End`, with nodes missing: every
/// reconnect (`--retries 2`) gets the base mesh again and no node, so the run gives up after
/// three connections, quickly, and says the connection was lost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_lost_before_end_is_an_error() {
    let (m, base, nodes) = dataset(2);
    let srv = fake(10, move |i, mut ws| {
        let (m, base, nodes) = (m.clone(), base.clone(), nodes.clone());
        async move {
            open(&mut ws, &m, &base).await;
            if i == 0 {
                let first = nodes[..20].to_vec();
                send(&mut ws, &nodes_msg(&m, &base, 0, &first)).await;
                // half a frame: a binary frame header announcing 1000 bytes, 10 of them, then
                // the socket closes without a close handshake
                let tcp = ws.get_mut();
                let mut raw = vec![0x82, 126, 0x03, 0xe8];
                raw.extend_from_slice(&[0u8; 10]);
                let _ = tcp.write_all(&raw).await;
                let _ = tcp.flush().await;
            }
            // dropped: the connection closes
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "2000", "--retries", "2"]).await;
    r.assert_fails_with(&[
        "connection to ws://",
        "lost",
        "gave up after 2 reconnect attempts",
    ]);
    assert_eq!(srv.conns.load(Ordering::SeqCst), 3);
    assert!(r.secs < 20.0, "{} s", r.secs);

    // the server does not come back at all: the reconnects are refused
    let (m, base, nodes) = dataset(2);
    let srv = fake(1, move |_, mut ws| {
        let (m, base, nodes) = (m.clone(), base.clone(), nodes.clone());
        async move {
            open(&mut ws, &m, &base).await;
            send(&mut ws, &nodes_msg(&m, &base, 0, &nodes[..5])).await;
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "2000", "--retries", "1"]).await;
    r.assert_fails_with(&["lost", "reconnecting", "gave up after 1 reconnect attempts"]);
}

/// A WebSocket frame announcing more than the client's limit is refused when its header arrives
/// (nothing of it is allocated), and not fetched again by reconnecting.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_message_over_the_limit_is_an_error() {
    let (m, base, _) = dataset(2);
    let srv = fake(5, move |_, mut ws| {
        let (m, base) = (m.clone(), base.clone());
        async move {
            open(&mut ws, &m, &base).await;
            let tcp = ws.get_mut();
            let mut raw = vec![0x82, 127];
            // one byte over a whole maximal frame (MAX_FRAME_BYTES and its 4-byte length prefix)
            raw.extend_from_slice(&(MAX_FRAME_BYTES as u64 + 5).to_be_bytes());
            raw.extend_from_slice(&[0u8; 64]);
            let _ = tcp.write_all(&raw).await;
            let _ = tcp.flush().await;
            idle(&mut ws).await;
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "400"]).await;
    r.assert_fails_with(&[&format!(
        "the server sent a message over the {MAX_FRAME_BYTES}-byte limit"
    )]);
    assert_eq!(srv.conns.load(Ordering::SeqCst), 1, "no reconnect");
}

/// A 266-byte base mesh claiming 10 levels (766,958,445 nodes) is refused before anything is
/// allocated for it; with the budget raised to take it, `End` with every node missing costs one
/// range, each `Want` asks for it as one range, and the session fails after its rounds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hierarchy_over_the_budget_is_refused_and_end_is_bounded() {
    let base = unsampled_base(10, box5([0.0; 3], [1.0; 3]));
    let m = manifest_for(&base);
    let nodes = m.counts.nodes;
    assert_eq!(nodes, 766_958_445);
    let wants = Arc::new(Mutex::new(Vec::<Vec<IdRange>>::new()));
    let seen = wants.clone();
    let script = move |_, mut ws: Ws| {
        let (m, base, seen) = (m.clone(), base.clone(), seen.clone());
        async move {
            open(&mut ws, &m, &base).await;
            send(&mut ws, &ServerMsg::End { nodes_sent: 0 }).await;
            // every Want is answered with End, sending nothing
            while let Some(msg) = recv(&mut ws).await {
                if let ClientMsg::Want(r) = msg {
                    seen.lock().unwrap().push(r);
                    send(&mut ws, &ServerMsg::End { nodes_sent: 0 }).await;
                }
            }
        }
    };
    let srv = fake(1, script.clone()).await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "400"]).await;
    r.assert_fails_with(&[
        "(5 tets, 10 levels) has 766958445 detail nodes",
        "over the client's limit of 134217728 (--max-nodes)",
    ]);

    let srv = fake(1, script).await;
    let d = tempfile::tempdir().unwrap();
    let r = client(
        srv.addr,
        d.path(),
        &["--frames", "4000", "--max-nodes", "1000000000"],
    )
    .await;
    r.assert_fails_with(&[&format!(
        "the server ended the stream with {nodes} of {nodes} nodes missing after 8 requests"
    )]);
    let wants = wants.lock().unwrap();
    assert_eq!(wants.len(), 8);
    for w in wants.iter() {
        assert_eq!(w, &[IdRange { from: 0, to: nodes }]);
    }
    assert!(r.secs < 30.0, "{} s", r.secs);
}

/// The manifest and the base mesh must agree on the hierarchy (the session's manifest derives
/// its node count from its base tets and levels).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_base_mesh_that_disagrees_with_the_manifest_is_refused() {
    let (mut m, base, _) = dataset(2);
    m.base_tets += 1;
    let srv = fake(1, move |_, mut ws| {
        let (m, base) = (m.clone(), base.clone());
        async move {
            open(&mut ws, &m, &base).await;
            idle(&mut ws).await;
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "400"]).await;
    r.assert_fails_with(&["disagrees with the manifest"]);
}

/// What the user bounds is not a failure: `--frames 3` against a server that is still sending
/// ends with status 0; a complete session whose server then goes away (`--retries 0`) too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bounded_and_complete_sessions_succeed() {
    let (m, base, nodes) = dataset(2);
    let srv = fake(1, move |_, mut ws| {
        let (m, base, nodes) = (m.clone(), base.clone(), nodes.clone());
        async move {
            open(&mut ws, &m, &base).await;
            send(&mut ws, &nodes_msg(&m, &base, 0, &nodes[..5])).await;
            idle(&mut ws).await;
        }
    })
    .await;
    let d = tempfile::tempdir().unwrap();
    let r = client(srv.addr, d.path(), &["--frames", "3"]).await;
    assert_eq!(r.status, Some(0), "{}", r.stderr);
    assert!(r.stderr.contains("stream: 3 frames, "), "{}", r.stderr);
    assert!(r.stderr.contains("/45 nodes"), "{}", r.stderr);

    let (m, base, nodes) = dataset(2);
    let srv = fake(2, move |_, mut ws| {
        let (m, base, nodes) = (m.clone(), base.clone(), nodes.clone());
        async move {
            open(&mut ws, &m, &base).await;
            send(&mut ws, &nodes_msg(&m, &base, 0, &nodes)).await;
            send(&mut ws, &ServerMsg::End { nodes_sent: 45 }).await;
            let _ = ws.close(None).await;
        }
    })
    .await;
    for extra in [&["--until-complete"][..], &[]] {
        let d = tempfile::tempdir().unwrap();
        let args = [&["--frames", "50", "--retries", "0"][..], extra].concat();
        let r = client(srv.addr, d.path(), &args).await;
        assert_eq!(r.status, Some(0), "{extra:?}: {}", r.stderr);
        assert!(r.stderr.contains("45/45 nodes"), "{}", r.stderr);
    }
}

/// `--psnr` needs rendered frames: with `--no-render` it is refused (exit status 2, naming both).
#[test]
fn psnr_without_rendering_is_refused() {
    let out = Command::new(env!("CARGO_BIN_EXE_tetwave"))
        .args(["stream", "ws://127.0.0.1:9", "--no-render", "--psnr"])
        .output()
        .expect("tetwave runs");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("--psnr") && err.contains("--no-render"),
        "{err}"
    );
}
