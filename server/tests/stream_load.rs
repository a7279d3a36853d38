//! 64 concurrent stream clients against the `tetwave-server serve` binary on loopback, for a bounded
//! time: every one completes with every node exactly once, none starves, and the server's peak RSS
//! (its own `/healthz`, i.e. the server process alone) stays bounded. Prints the figures.

mod stream_common;

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use stream_common::*;
use tetwave_protocol::wire::ServerMsg;

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts the binary on 127.0.0.1:0 and reads the address it prints.
fn spawn_server(store: &std::path::Path, extra: &[&str]) -> (Server, SocketAddr) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_tetwave-server"))
        .arg("serve")
        .arg(store)
        .args(["--addr", "127.0.0.1:0"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("server starts");
    let stdout = child.stdout.take().unwrap();
    let server = Server(child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let line = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("server prints its address");
    let addr = line
        .split_whitespace()
        .nth(2)
        .and_then(|u| u.strip_prefix("http://"))
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .parse()
        .unwrap();
    (server, addr)
}

fn health(addr: SocketAddr, rt: &tokio::runtime::Runtime) -> serde_json::Value {
    let r = rt.block_on(get(addr, "/healthz", &[]));
    assert_eq!(r.status, 200);
    serde_json::from_slice(&r.body).unwrap()
}

#[test]
fn sixty_four_concurrent_clients_all_complete() {
    let (_d, dir) = make_store(5);
    // every client comes from 127.0.0.1: allow them all (the default is 16 streams per address)
    let (_server, addr) = spawn_server(&dir, &["--batch", "256", "--max-streams-per-peer", "64"]);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let before = health(addr, &rt);
    let n = before["nodes"].as_u64().unwrap();
    let t0 = Instant::now();
    let results = rt.block_on(async move {
        let mut tasks = Vec::new();
        for i in 0..64 {
            let order = ["level", "magnitude", "view", "random"][i % 4];
            tasks.push(tokio::spawn(async move {
                let start = Instant::now();
                let mut ws = connect(addr, &format!("?order={order}")).await;
                send(&mut ws, &hello(None, vec![])).await;
                assert!(matches!(recv(&mut ws).await, Some(ServerMsg::Manifest(_))));
                assert!(matches!(recv(&mut ws).await, Some(ServerMsg::Base(_))));
                let (nodes, sent, _) = receive_nodes(&mut ws).await;
                let _ = ws.close(None).await;
                let mut ids: Vec<u64> = nodes.iter().map(|x| x.id).collect();
                ids.sort_unstable();
                ids.dedup();
                (ids.len() as u64, sent, start.elapsed())
            }));
        }
        let mut out = Vec::new();
        for t in tasks {
            out.push(
                tokio::time::timeout(Duration::from_secs(300), t)
                    .await
                    .expect("a client did not finish within 300 s")
                    .expect("client task"),
            );
        }
        out
    });
    let wall = t0.elapsed();
    // the server notices the closes asynchronously: wait (bounded) until it has
    let mut after = health(addr, &rt);
    let t1 = Instant::now();
    while after["connections"].as_u64() != Some(0) && t1.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(50));
        after = health(addr, &rt);
    }
    let mut times: Vec<f64> = results.iter().map(|r| r.2.as_secs_f64()).collect();
    times.sort_by(f64::total_cmp);
    for (got, sent, _) in &results {
        assert_eq!(*got, n, "every client gets every node once");
        assert_eq!(*sent, n);
    }
    let rss0 = before["rss_kib"].as_u64().unwrap_or(0);
    let peak = after["peak_rss_kib"].as_u64().unwrap_or(0);
    eprintln!(
        "64 clients x {n} nodes: wall {:.2} s; per-client time min {:.2} s, median {:.2} s, max {:.2} s; \
         server RSS before {} KiB, peak {} KiB",
        wall.as_secs_f64(),
        times[0],
        times[32],
        times[63],
        rss0,
        peak
    );
    // no starvation: the slowest client is within a small factor of the median
    assert!(
        times[63] <= 4.0 * times[32] + 2.0,
        "a client starved: max {} s vs median {} s",
        times[63],
        times[32]
    );
    // bounded memory: the server grows by well under what 64 whole streams would take
    if peak > 0 {
        assert!(
            peak.saturating_sub(rss0) < 256 * 1024,
            "server peak RSS grew by {} KiB",
            peak - rss0
        );
    }
    assert_eq!(after["connections"].as_u64(), Some(0), "connections closed");
}
