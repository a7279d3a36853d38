//! End to end on loopback: `tetwave-server serve` (the binary) and the streaming client library.
//! Every server binds 127.0.0.1 on a free port and is killed at the end of its test; every wait is
//! bounded.

use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};
use tetwave_client::stream::{run_session, Faults, Session, StreamArgs};
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_server::prepare::{prepare, PrepareOptions};
use tetwave_server::store::Store;

struct Server(Child, String);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn serve(store: &Path, order: &str) -> Server {
    let port = free_port();
    let addr = format!("127.0.0.1:{port}");
    let child = Command::new(env!("CARGO_BIN_EXE_tetwave-server"))
        .args([
            "serve",
            store.to_str().unwrap(),
            "--addr",
            &addr,
            "--order",
            order,
        ])
        .spawn()
        .expect("server starts");
    let t0 = Instant::now();
    while TcpStream::connect(&addr).is_err() {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "server did not listen on {addr}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    Server(child, format!("http://{addr}"))
}

fn store(levels: u8) -> (tempfile::TempDir, Vec<f32>, u64) {
    let d = tempfile::tempdir().unwrap();
    let mut o = PrepareOptions::new("synthetic:harmonic", &d.path().join("s"));
    o.levels = levels;
    prepare(&o).unwrap();
    let s = Store::open(&d.path().join("s")).unwrap();
    let n = s.manifest.counts.nodes;
    let values =
        synthesize_all(&s.base, &s.base.vertex_keys(), s.read_nodes(0, n).unwrap()).unwrap();
    (d, values, n)
}

fn session(url: &str, out: &Path, faults: Faults) -> Session {
    session_with(url, out, faults, true)
}

fn session_with(url: &str, out: &Path, faults: Faults, render: bool) -> Session {
    let mut a = StreamArgs::new(url, out);
    a.no_render = !render;
    a.frames = 400;
    a.until_complete = true;
    a.size = (32, 32);
    a.cpu = true;
    a.frame_ms = 5;
    run_session(&a, faults).expect("session")
}

/// The client's final mesh is the uniform finest level with the server's synthesized values.
fn assert_identical(s: &Session, values: &[f32]) {
    assert!(
        s.report.complete,
        "not all nodes arrived: {}/{}",
        s.report.nodes_received, s.report.nodes_total
    );
    let base = s.base.as_ref().unwrap();
    let mesh = s.mesh.as_ref().unwrap();
    assert_eq!(mesh.leaf_count() as u64, base.forest().leaves());
    mesh.check_conformity().unwrap();
    let keys = base.vertex_keys();
    assert_eq!(mesh.vertex_count() as u64, keys.vertex_count());
    for k in 0..keys.vertex_count() {
        let slot = mesh.slot_of_key(k).expect("every vertex present");
        assert_eq!(
            mesh.vertex_value(slot).to_bits(),
            values[k as usize].to_bits(),
            "vertex {k}"
        );
    }
}

#[test]
fn streamed_session_ends_identical_to_full_synthesis() {
    let (d, values, _) = store(3);
    for order in ["level", "magnitude", "view", "random"] {
        let srv = serve(&d.path().join("s"), order);
        let s = session(
            &srv.1,
            &d.path().join(format!("out-{order}")),
            Faults::default(),
        );
        assert_identical(&s, &values);
        assert_eq!(s.report.duplicates, 0, "{order}");
    }
}

#[test]
fn reordered_duplicated_and_lost_batches_end_identical() {
    let (d, values, _) = store(4);
    let srv = serve(&d.path().join("s"), "level");
    let faults = Faults {
        duplicate_every: Some(2),
        reverse_groups: Some(3),
        lose_every: Some(4),
        ..Default::default()
    };
    let s = session_with(&srv.1, &d.path().join("out"), faults, false);
    assert!(s.report.duplicates > 0);
    assert_identical(&s, &values);
}

#[test]
fn disconnect_and_resume_loses_nothing_and_repeats_nothing() {
    let (d, values, _) = store(5);
    let srv = serve(&d.path().join("s"), "level");
    let clean = session_with(&srv.1, &d.path().join("a"), Faults::default(), false);
    let cut = session_with(
        &srv.1,
        &d.path().join("b"),
        Faults {
            drop_after_batches: Some(5),
            ..Default::default()
        },
        false,
    );
    assert!(cut.report.reconnects >= 1);
    assert_eq!(cut.report.duplicates, 0, "a node was applied twice");
    assert_identical(&cut, &values);
    let ratio = cut.report.bytes_received as f64 / clean.report.bytes_received as f64;
    eprintln!(
        "bytes: clean {} resumed {}",
        clean.report.bytes_received, cut.report.bytes_received
    );
    assert!(ratio <= 1.05, "resumed session took {ratio:.3}x the bytes");
}
