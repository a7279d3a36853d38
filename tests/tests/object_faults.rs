//! A store read directly over HTTP through a file server that misbehaves on purpose (in this
//! test, on loopback): answers late, answers 503, stalls past the request timeout, cuts a body
//! short, flips a byte, or has no such object. Each fault is retried or refused with an error
//! naming the object; the final mesh is the undisturbed one, never another. With 50 ms added to
//! every request, the first image (the base mesh) comes within 4 round trips, and so does the
//! first image with nodes of the store.
//!
//! Its own test binary: it sets `TETWAVE_REQUEST_TIMEOUT` for the process.

use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, Uri};
use axum::response::Response;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tetwave_client::stream::Streamed;
use tetwave_server::analysis::ErrorBound;
use tetwave_server::prepare::{prepare, PrepareOptions};

mod common;

/// What the file server does wrong, and how often it did.
#[derive(Default)]
struct Policy {
    delay_ms: u64,
    /// Every nth request answers 503.
    unavailable_every: Option<u64>,
    /// Every nth request waits this long before answering (past the client's timeout).
    stall_every: Option<(u64, Duration)>,
    /// Every nth ranged request sends half its bytes (a consistent, shorter Content-Length).
    truncate_every: Option<u64>,
    /// Every answer from blocks.bin has a byte flipped.
    flip_blocks: bool,
    /// This file is not there.
    missing: Option<String>,
}

struct Server {
    root: PathBuf,
    policy: Mutex<Policy>,
    requests: AtomicU64,
    faults: AtomicU64,
}

async fn serve_file(State(s): State<Arc<Server>>, uri: Uri, headers: HeaderMap) -> Response {
    let n = s.requests.fetch_add(1, Ordering::SeqCst) + 1;
    let (delay, unavailable, stall, truncate, flip, missing) = {
        let p = s.policy.lock().unwrap();
        (
            p.delay_ms,
            p.unavailable_every.is_some_and(|k| n.is_multiple_of(k)),
            p.stall_every
                .filter(|(k, _)| n.is_multiple_of(*k))
                .map(|(_, d)| d),
            p.truncate_every.is_some_and(|k| n.is_multiple_of(k)),
            p.flip_blocks,
            p.missing.clone(),
        )
    };
    tokio::time::sleep(Duration::from_millis(delay)).await;
    let fault = |s: &Server| s.faults.fetch_add(1, Ordering::SeqCst);
    if unavailable {
        fault(&s);
        return status(StatusCode::SERVICE_UNAVAILABLE);
    }
    if let Some(d) = stall {
        fault(&s);
        tokio::time::sleep(d).await;
    }
    let rel = uri.path().trim_start_matches('/');
    if rel.contains("..") || missing.as_deref().is_some_and(|m| rel.ends_with(m)) {
        return status(StatusCode::NOT_FOUND);
    }
    let Ok(bytes) = std::fs::read(s.root.join(rel)) else {
        return status(StatusCode::NOT_FOUND);
    };
    let len = bytes.len() as u64;
    let range = headers
        .get("range")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("bytes="))
        .and_then(|v| v.split_once('-'))
        .and_then(|(a, b)| Some((a.parse::<u64>().ok()?, b.parse::<u64>().ok()?)));
    let (code, from, to) = match range {
        Some((a, b)) if a <= b && b < len => (StatusCode::PARTIAL_CONTENT, a, b + 1),
        Some(_) => return status(StatusCode::RANGE_NOT_SATISFIABLE),
        None => (StatusCode::OK, 0, len),
    };
    let mut body = bytes[from as usize..to as usize].to_vec();
    if flip && rel.ends_with("blocks.bin") && !body.is_empty() {
        fault(&s);
        let mid = body.len() / 2;
        body[mid] ^= 0x10;
    }
    if truncate && range.is_some() && body.len() > 1 {
        fault(&s);
        body.truncate(body.len() / 2);
    }
    let mut r = Response::builder()
        .status(code)
        .header("content-length", body.len())
        .header("accept-ranges", "bytes");
    if code == StatusCode::PARTIAL_CONTENT {
        r = r.header("content-range", format!("bytes {from}-{}/{len}", to - 1));
    }
    r.body(Body::from(body)).unwrap()
}

fn status(code: StatusCode) -> Response {
    Response::builder()
        .status(code)
        .body(Body::empty())
        .unwrap()
}

/// The misbehaving server on a free loopback port, on its own runtime thread.
fn start(root: &Path) -> (Arc<Server>, u16) {
    let server = Arc::new(Server {
        root: root.to_path_buf(),
        policy: Mutex::new(Policy::default()),
        requests: AtomicU64::new(0),
        faults: AtomicU64::new(0),
    });
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.set_nonblocking(true).unwrap();
    let port = listener.local_addr().unwrap().port();
    let state = server.clone();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async move {
            let app = axum::Router::new().fallback(serve_file).with_state(state);
            let l = tokio::net::TcpListener::from_std(listener).unwrap();
            axum::serve(l, app).await.unwrap();
        });
    });
    (server, port)
}

#[test]
fn faults_are_retried_or_refused_by_name() {
    std::env::set_var("TETWAVE_REQUEST_TIMEOUT", "1");
    let work = tempfile::tempdir().unwrap();
    let mut o = PrepareOptions::new("synthetic:harmonic", &work.path().join("www/h6"));
    o.levels = Some(6);
    o.max_error = Some(ErrorBound::parse("0.1%").unwrap());
    prepare(&o).unwrap();
    let (srv, port) = start(&work.path().join("www"));
    let url = format!("http://127.0.0.1:{port}/h6");
    let out = |name: &str| work.path().join(name);
    let set = |f: &dyn Fn(&mut Policy)| {
        let mut p = srv.policy.lock().unwrap();
        *p = Policy::default();
        f(&mut p);
        srv.faults.store(0, Ordering::SeqCst);
    };

    set(&|_| {});
    let clean = common::converged(&url, &out("clean")).unwrap();
    let want = common::leaves(&clean);
    assert!(clean.report.frames.last().unwrap().view_complete);
    let first_clean = clean.report.first_frame_ms.unwrap();
    // the first frame drawn with some of the store's nodes
    let first_data = |s: &Streamed| {
        let f = s
            .report
            .frames
            .iter()
            .find(|f| f.nodes > 0)
            .expect("nodes came");
        f.ms_since_connect
    };
    let data_clean = first_data(&clean);

    // 50 ms on every request: the first image within 4 round trips of the undelayed one
    set(&|p| p.delay_ms = 50);
    let slow = common::converged(&url, &out("slow")).unwrap();
    let first_slow = slow.report.first_frame_ms.unwrap();
    let trips = (first_slow - first_clean) / 50.0;
    let data_slow = first_data(&slow);
    let data_trips = (data_slow - data_clean) / 50.0;
    eprintln!(
        "first image: {first_clean:.1} ms, with 50 ms a request {first_slow:.1} ms ({trips:.2} \
         round trips); first image with nodes: {data_clean:.1} ms, {data_slow:.1} ms \
         ({data_trips:.2} round trips)"
    );
    assert!(
        data_trips <= 4.0,
        "{data_trips:.2} round trips before the first image with nodes"
    );
    assert!(
        trips <= 4.0,
        "{trips:.2} round trips before the first image"
    );
    assert_eq!(common::leaves(&slow), want);

    // transient faults: retried, the same final mesh
    type Setup = fn(&mut Policy);
    let transient: [(&str, Setup); 3] = [
        ("503", |p| p.unavailable_every = Some(4)),
        ("stall", |p| {
            p.stall_every = Some((5, Duration::from_secs(3)))
        }),
        ("truncated", |p| p.truncate_every = Some(3)),
    ];
    for (name, f) in transient {
        set(&|p| f(p));
        let s = common::converged(&url, &out(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(
            srv.faults.load(Ordering::SeqCst) > 0,
            "{name}: no fault was injected"
        );
        assert_eq!(common::leaves(&s), want, "{name}: another final mesh");
    }

    // a flipped byte: refused by its block's checksum, naming the object
    set(&|p| p.flip_blocks = true);
    let e = common::converged(&url, &out("flipped"))
        .err()
        .expect("refused");
    assert!(
        e.contains(&format!("{url}/blocks.bin")) && e.contains("checksum"),
        "{e}"
    );
    // a missing object: named
    set(&|p| p.missing = Some("block_index.bin".into()));
    let e = common::converged(&url, &out("missing"))
        .err()
        .expect("refused");
    assert!(e.contains(&format!("{url}/block_index.bin")), "{e}");
    let e = common::converged(&format!("http://127.0.0.1:{port}/nothing"), &out("none"))
        .err()
        .expect("refused");
    assert!(e.contains("/nothing/manifest.json"), "{e}");
}
