//! End to end on loopback: the server's stream (in process) and the streaming client library.
//! Every server binds 127.0.0.1 on a free port and stops at the end of its test; every wait is
//! bounded.

use std::path::Path;
use tetwave_client::stream::{run, run_session, Faults, StreamArgs, StreamError, Streamed};
use tetwave_store::Store;

mod common;

use common::serve;

/// A harmonic store in `<dir>/s`, its synthesized values and its node count.
fn store(levels: u8) -> (tempfile::TempDir, Vec<f32>, u64) {
    let (d, dir) = common::harmonic_store(levels);
    let s = Store::open(&dir).unwrap();
    (d, s.synthesize_all().unwrap(), s.manifest.counts.nodes)
}

fn session(url: &str, out: &Path, faults: Faults) -> Streamed {
    session_with(url, out, faults, true)
}

fn session_with(url: &str, out: &Path, faults: Faults, render: bool) -> Streamed {
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
fn assert_identical(s: &Streamed, values: &[f32]) {
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

/// Streams `store` whole in every order (outputs under `work`): each session ends identical to
/// `values`, with no duplicates.
fn every_order_ends_identical(store: &Path, work: &Path, values: &[f32]) {
    for order in ["level", "magnitude", "view", "random"] {
        let srv = serve(store, order);
        let s = session(
            srv.url(),
            &work.join(format!("out-{order}")),
            Faults::default(),
        );
        assert_identical(&s, values);
        assert_eq!(s.report.duplicates, 0, "{order}");
    }
}

/// Streams `store` in `order` through duplicated, reversed and lost batches: the session ends
/// identical to `values` all the same.
fn lossy_session_ends_identical(store: &Path, order: &str, out: &Path, values: &[f32]) {
    let srv = serve(store, order);
    let faults = Faults {
        duplicate_every: Some(2),
        reverse_groups: Some(3),
        lose_every: Some(4),
        ..Default::default()
    };
    let s = session_with(srv.url(), out, faults, false);
    assert!(s.report.duplicates > 0);
    assert_identical(&s, values);
}

/// `--tf auto` is the default preset fitted to the histogram the manifest carries, the same
/// function `tetwave render` of the store draws with; the default, a preset, stays itself.
#[test]
fn a_session_draws_with_the_stores_fitted_transfer_function() {
    use tetwave_render::transfer::TransferFunction;
    let (d, _, _) = store(3);
    let dir = d.path().join("s");
    let m = Store::open(&dir).unwrap().manifest;
    assert!(m.value_histogram.is_some(), "prepare records a histogram");
    let srv = serve(&dir, "level");
    let s = session_with(srv.url(), &d.path().join("out"), Faults::default(), false);
    assert_eq!(s.report.tf, TransferFunction::preset("default").unwrap());
    let mut a = StreamArgs::new(srv.url(), &d.path().join("out2"));
    a.no_render = true;
    a.until_complete = true;
    a.frame_ms = 5;
    a.tf = "auto".into();
    let s = run_session(&a, Faults::default()).unwrap();
    let want = TransferFunction::for_manifest("auto", &m).unwrap();
    assert_eq!(s.report.tf, want);
    assert_eq!(s.report.tf.name, "auto");
    assert_ne!(want, TransferFunction::preset("default").unwrap());
}

#[test]
fn streamed_session_ends_identical_to_full_synthesis() {
    let (d, values, _) = store(3);
    every_order_ends_identical(&d.path().join("s"), d.path(), &values);
}

/// With the axes predictor (a box6 grid at a bounded error, what `prepare` picks there), in
/// every order and through lost, reordered and duplicated batches: the client's values by grid
/// point end exactly the server's; `tetwave info` names the predictor.
#[test]
fn axes_sessions_end_identical_to_full_synthesis() {
    let (d, dir) = common::harmonic_store_with(4, |o| {
        o.base = tetwave_server::resample::BaseSpec::Box6;
        o.max_error = Some(tetwave_server::analysis::ErrorBound::OfRange(1e-3));
    });
    let info = tetwave_client::store_info::store_info(&dir).unwrap();
    assert_eq!(info.predictor, "axes");
    let values = Store::open(&dir).unwrap().synthesize_all().unwrap();
    every_order_ends_identical(&dir, d.path(), &values);
    lossy_session_ends_identical(&dir, "random", &d.path().join("out-faults"), &values);
}

/// A store with a preview (a box6 grid with the axes predictor, a box5 mesh with the parent
/// predictor): a new session gets the whole preview first and the store's nodes replace it, so
/// every order, a session through lost, reordered and duplicated batches, and one cut and resumed
/// (which gets no preview again) end exactly at the store's values.
#[test]
fn sessions_with_a_preview_end_identical_to_full_synthesis() {
    use tetwave_server::analysis::ErrorBound;
    for box6 in [true, false] {
        let (d, dir) = common::harmonic_store_with(4, |o| {
            if box6 {
                o.base = tetwave_server::resample::BaseSpec::Box6;
            }
            o.max_error = Some(ErrorBound::OfRange(1e-3));
            o.preview = Some(ErrorBound::OfRange(0.1));
        });
        let s = Store::open(&dir).unwrap();
        let previews = s.preview.as_ref().expect("a preview").len() as u64;
        assert_eq!(previews, s.forest().level_start(3));
        let values = s.synthesize_all().unwrap();
        for order in ["level", "view", "random"] {
            let srv = serve(&dir, order);
            let out = d.path().join(format!("out-{order}"));
            let got = session(srv.url(), &out, Faults::default());
            assert_eq!(got.report.previews_received, previews, "{order}");
            assert_eq!(got.report.duplicates, 0, "{order}");
            assert_eq!(got.report.preview_duplicates, 0, "{order}");
            assert_identical(&got, &values);
        }
        lossy_session_ends_identical(&dir, "view", &d.path().join("lossy"), &values);
        // cut during the preview (after its first and second batches of three) and after it:
        // the reconnection names the preview nodes it holds and gets only the others
        let srv = serve(&dir, "view");
        for after in [1, 2, 4] {
            let cut = session_with(
                srv.url(),
                &d.path().join(format!("cut-{after}")),
                Faults {
                    drop_after_batches: Some(after),
                    ..Default::default()
                },
                false,
            );
            assert!(cut.report.reconnects >= 1);
            assert_eq!(cut.report.previews_received, previews);
            assert_eq!(cut.report.duplicates, 0);
            assert_identical(&cut, &values);
            assert_eq!(cut.report.preview_duplicates, 0, "after {after}");
        }
    }
}

#[test]
fn reordered_duplicated_and_lost_batches_end_identical() {
    let (d, values, _) = store(4);
    lossy_session_ends_identical(&d.path().join("s"), "level", &d.path().join("out"), &values);
}

#[test]
fn disconnect_and_resume_loses_nothing_and_repeats_nothing() {
    let (d, values, _) = store(5);
    let srv = serve(&d.path().join("s"), "level");
    let clean = session_with(srv.url(), &d.path().join("a"), Faults::default(), false);
    let cut = session_with(
        srv.url(),
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

/// `--until-complete` and too few frames to receive everything: an error naming what arrived,
/// not a success (the frames written so far stay on disk).
#[test]
fn until_complete_and_incomplete_is_an_error() {
    let (d, _, n) = store(5);
    let srv = serve(&d.path().join("s"), "level");
    let mut a = StreamArgs::new(srv.url(), &d.path().join("out"));
    a.no_render = true;
    a.frames = 1;
    a.per_frame = 10;
    a.until_complete = true;
    a.frame_ms = 5;
    match run(&a) {
        Err(StreamError::Incomplete {
            received,
            total,
            frames,
        }) => {
            assert_eq!(total, n);
            assert!(received < total, "{received} of {total}");
            assert_eq!(frames, 1);
        }
        other => panic!("expected an incomplete session, got {other:?}"),
    }
    assert!(d.path().join("out/frames.jsonl").exists());
}

/// `--until-converged` stops at the first frame whose mesh is final for its camera (a grid store
/// at 0.1 % in view order, 6 px: a third of the leaves), and `--final-png` draws that mesh, which
/// matches the CPU image of every leaf of the store.
#[test]
fn until_converged_stops_at_the_final_view_and_draws_it() {
    use tetwave_server::analysis::ErrorBound;
    use tetwave_server::resample::BaseSpec;
    let (d, dir) = common::harmonic_store_with(5, |o| {
        o.base = BaseSpec::Box6;
        o.max_error = Some(ErrorBound::OfRange(1e-3));
    });
    let total = Store::open(&dir).unwrap();
    let (nodes, leaves) = (
        total.manifest.counts.nodes,
        total.base.tets.len() as u64 * 8u64.pow(5),
    );
    let srv = serve(&dir, "view");
    let png = d.path().join("final.png");
    let mut a = StreamArgs::new(srv.url(), &d.path().join("out"));
    a.no_render = true;
    a.frames = 5000;
    a.until_converged = true;
    a.size = (96, 96);
    a.tol = "6".into();
    a.frame_ms = 5;
    a.final_png = Some(png.clone());
    let r = run(&a).expect("session");
    let last = r.frames.last().unwrap();
    assert!(last.view_complete && last.converged, "{last:?}");
    assert!(
        r.frames[..r.frames.len() - 1]
            .iter()
            .all(|f| !f.view_complete),
        "stops at the first final frame"
    );
    assert!(
        last.leaves < leaves / 2,
        "{} of {leaves} leaves",
        last.leaves
    );
    eprintln!(
        "final after {} frames: {} of {nodes} nodes, {} of {leaves} leaves",
        r.frames.len(),
        last.nodes,
        last.leaves
    );
    let drawn = tetwave_render::image_metrics::Rgba8Image::load_png(&png).expect("the final PNG");
    // the stream draws the `default` preset by default, `tetwave render` fits `auto`
    let (every, _) = common::render_png(
        &dir,
        &d.path().join("every.png"),
        96,
        &["--reference", "--tf", "default"],
    );
    let db = common::psnr_pixels(&drawn.pixels, &every);
    eprintln!("final view against every leaf: {db:.2} dB");
    assert!(db >= 40.0, "{db:.2} dB");
}

/// Each connection's client messages, in order, as a [`ViewDroppingProxy`] saw them.
type ClientLog = std::sync::Arc<std::sync::Mutex<Vec<Vec<tetwave_protocol::wire::ClientMsg>>>>;

/// A WebSocket proxy on 127.0.0.1 in front of a server's stream that records what the client
/// says on each connection. The first connection passes the server's first message (`Start`) and
/// nothing more until the client has sent a `View`, then drops: a connection lost after the
/// camera was told, before any node came. Later connections pass everything.
struct ViewDroppingProxy {
    url: String,
    log: ClientLog,
    _rt: tokio::runtime::Runtime,
}

impl ViewDroppingProxy {
    fn start(upstream: String) -> Self {
        use futures_util::{SinkExt, StreamExt};
        use tetwave_protocol::wire::{decode_client, ClientMsg};
        use tokio_tungstenite::tungstenite::Message;
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let listener = rt
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let log = ClientLog::default();
        let l = log.clone();
        rt.spawn(async move {
            while let Ok((tcp, _)) = listener.accept().await {
                let conn = {
                    let mut g = l.lock().unwrap();
                    g.push(Vec::new());
                    g.len() - 1
                };
                let (l, up) = (l.clone(), upstream.clone());
                tokio::spawn(async move {
                    let config = Some(tetwave_net::connection::ws_config());
                    let Ok(client) = tokio_tungstenite::accept_async_with_config(tcp, config).await
                    else {
                        return;
                    };
                    let Ok((server, _)) =
                        tokio_tungstenite::connect_async_with_config(up.as_str(), config, false)
                            .await
                    else {
                        return;
                    };
                    let (mut to_client, mut from_client) = client.split();
                    let (mut to_server, mut from_server) = server.split();
                    let viewed = std::sync::Arc::new(tokio::sync::Notify::new());
                    let seen = viewed.clone();
                    let upward = async move {
                        while let Some(Ok(m)) = from_client.next().await {
                            if let Message::Binary(b) = &m {
                                let msg = decode_client(b).expect("the client's frames decode");
                                if matches!(msg, ClientMsg::View(_)) {
                                    seen.notify_one();
                                }
                                l.lock().unwrap()[conn].push(msg);
                            }
                            if to_server.send(m).await.is_err() {
                                break;
                            }
                        }
                    };
                    let downward = async move {
                        let mut passed = 0u64;
                        while let Some(Ok(m)) = from_server.next().await {
                            if conn == 0 && passed == 1 {
                                viewed.notified().await;
                                return;
                            }
                            if to_client.send(m).await.is_err() {
                                return;
                            }
                            passed += 1;
                        }
                    };
                    tokio::select! {
                        _ = upward => {}
                        _ = downward => {}
                    }
                });
            }
        });
        ViewDroppingProxy { url, log, _rt: rt }
    }
}

/// A stream with a fixed camera whose connection is lost after it told the server its view: the
/// new connection is told the view again right after its `Hello` (the server's view order is per
/// connection), and the stream completes.
#[test]
fn a_fixed_camera_stream_sends_its_view_again_after_a_reconnect() {
    use tetwave_protocol::wire::ClientMsg;
    let (_d, dir) = common::harmonic_store(3);
    let srv = serve(&dir, "view");
    let upstream = tetwave_net::ServerUrl::parse(srv.url())
        .unwrap()
        .stream(None);
    let proxy = ViewDroppingProxy::start(upstream);
    let out = tempfile::tempdir().unwrap();
    let mut a = StreamArgs::new(&proxy.url, out.path());
    a.no_render = true;
    a.frames = 400;
    a.until_complete = true;
    a.size = (32, 32);
    a.frame_ms = 5;
    a.tol = "2px".into();
    let s = run_session(&a, Faults::default()).expect("session");
    assert!(s.report.complete, "{:?}", s.report.nodes_received);
    assert!(
        s.report.reconnects >= 1,
        "the proxy dropped the first connection"
    );
    let log = proxy.log.lock().unwrap();
    let kinds = |c: &Vec<ClientMsg>| -> Vec<&'static str> {
        c.iter()
            .map(|m| match m {
                ClientMsg::Hello { .. } => "hello",
                ClientMsg::View(_) => "view",
                ClientMsg::Ack { .. } => "ack",
                _ => "other",
            })
            .collect()
    };
    assert!(log.len() >= 2, "{} connections", log.len());
    assert!(
        log[0].iter().any(|m| matches!(m, ClientMsg::View(_))),
        "first connection: {:?}",
        kinds(&log[0])
    );
    for (k, c) in log.iter().enumerate().skip(1) {
        assert_eq!(
            kinds(c).get(..2),
            Some(&["hello", "view"][..]),
            "connection {k}: {:?}",
            kinds(c)
        );
    }
}
