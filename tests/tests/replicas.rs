//! Stateless replicas: two servers of one store behind a real load balancer (Debian's nginx,
//! round robin, WebSocket proxying) on loopback. The replica serving a client is stopped
//! mid-stream; the client reconnects through the balancer to the other, resumes (its `Hello`
//! says what it holds) and ends with the undisturbed stream's final mesh, within 1.05× its bytes.

use std::path::Path;
use std::time::{Duration, Instant};
use tetwave_client::stream::{run_session, Faults, StreamArgs, Streamed};
use tetwave_server::stream::{BackgroundServer, ServeConfig};

mod common;

fn session(url: &str, out: &Path) -> Streamed {
    let mut a = StreamArgs::new(url, out);
    a.no_render = true;
    a.cpu = true;
    a.frames = 5000;
    a.size = (64, 64);
    a.frame_ms = 5;
    // a slow reader: the stream lasts long enough to lose its server mid-way
    a.per_frame = 4096;
    a.until_complete = true;
    run_session(&a, Faults::default()).expect("the session completes")
}

/// `/healthz`'s count of streams the server at `url` holds.
fn streams(url: &str) -> u64 {
    let addr = url.trim_start_matches("http://");
    let Ok(mut c) = std::net::TcpStream::connect(addr) else {
        return 0;
    };
    use std::io::{Read, Write};
    let _ = c.set_read_timeout(Some(Duration::from_secs(2)));
    let _ = write!(
        c,
        "GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    );
    let mut s = String::new();
    let _ = c.read_to_string(&mut s);
    let body = s.split("\r\n\r\n").nth(1).unwrap_or("");
    serde_json::from_str::<serde_json::Value>(body)
        .ok()
        .and_then(|v| v["connections"].as_u64())
        .unwrap_or(0)
}

#[test]
fn a_client_finishes_on_another_replica() {
    let (_d, store) = common::harmonic_store(6);
    let a = BackgroundServer::start(&store, "127.0.0.1:0", ServeConfig::default()).unwrap();
    let b = BackgroundServer::start(&store, "127.0.0.1:0", ServeConfig::default()).unwrap();
    let upstream = format!(
        "upstream replicas {{ server {}; server {}; }}",
        a.url().trim_start_matches("http://"),
        b.url().trim_start_matches("http://")
    );
    let nginx = tetwave_tests::Nginx::start_with(
        &upstream,
        "location / { proxy_pass http://replicas; proxy_http_version 1.1; \
         proxy_set_header Upgrade $http_upgrade; proxy_set_header Connection \"upgrade\"; \
         proxy_set_header Host $host; proxy_read_timeout 60s; \
         proxy_next_upstream error timeout http_502; }",
    );
    let url = format!("http://127.0.0.1:{}", nginx.port);
    let work = tempfile::tempdir().unwrap();
    let calm = session(&url, &work.path().join("calm"));
    assert!(calm.report.complete);
    assert_eq!(calm.report.reconnects, 0);

    // again, and the replica serving it goes away once the stream is under way
    let urls = [a.url().to_string(), b.url().to_string()];
    let mut replicas = [Some(a), Some(b)];
    let out = work.path().join("lossy");
    let client = std::thread::spawn(move || session(&url, &out));
    let t0 = Instant::now();
    let serving = loop {
        if let Some(k) = (0..2).find(|&k| streams(&urls[k]) > 0) {
            break k;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no replica got the stream"
        );
        std::thread::sleep(Duration::from_millis(5));
    };
    std::thread::sleep(Duration::from_millis(200));
    drop(replicas[serving].take());
    let lossy = client.join().unwrap();
    assert!(lossy.report.complete, "{:?}", lossy.report.nodes_received);
    assert!(
        lossy.report.reconnects >= 1,
        "the stream ended before its replica was stopped: nothing was tested"
    );
    // the client has closed its stream; the replica notices within moments
    let t0 = Instant::now();
    while streams(&urls[1 - serving]) > 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "the other replica still holds a stream"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(common::leaves(&lossy), common::leaves(&calm));
    let ratio = lossy.report.bytes_received as f64 / calm.report.bytes_received as f64;
    eprintln!(
        "bytes: undisturbed {}, replica lost mid-stream {} ({ratio:.3}x), {} reconnects",
        calm.report.bytes_received, lossy.report.bytes_received, lossy.report.reconnects
    );
    assert!(ratio <= 1.05, "{ratio:.3}x the undisturbed stream's bytes");
}
