//! A new session of a store with a preview: `Preview` batches first (numbered with the `Nodes`
//! batches, acknowledged like them), within the configured share of the store's bytes, most
//! important first; then every node of the store's own, once. A resumed session, one that says
//! it holds previews, and a server configured with no share get none. Every wait is bounded.

mod stream_common;

use std::collections::HashSet;
use stream_common::*;
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::wire::{ClientMsg, IdRange, ServerMsg};
use tetwave_protocol::DetailNode;
use tetwave_server::analysis::ErrorBound;
use tetwave_server::prepare::{prepare, PrepareOptions};
use tetwave_server::resample::BaseSpec;
use tetwave_server::stream::{Order, ServeConfig};
use tetwave_store::Store;

/// A box6 harmonic store of 4 levels at 0.1 % with a 10 % preview.
fn preview_store() -> (tempfile::TempDir, std::path::PathBuf) {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("store");
    let mut o = PrepareOptions::new("synthetic:harmonic", &p);
    o.levels = 4;
    o.base = BaseSpec::Box6;
    o.max_error = Some(ErrorBound::OfRange(1e-3));
    o.preview = Some(ErrorBound::OfRange(0.1));
    prepare(&o).unwrap();
    (d, p)
}

/// What a session received after the opening: preview nodes and their frames' bytes, then the
/// store's nodes, in arrival order; `End`'s count.
struct Received {
    previews: Vec<DetailNode>,
    preview_bytes: u64,
    nodes: Vec<DetailNode>,
    end: u64,
}

/// Receives (acking every batch, checking `seq` increases by one over both kinds and that no
/// preview follows a `Nodes` batch) until `End`.
async fn receive(ws: &mut Ws, coder: &BlockCoder, preview: &BlockCoder) -> Received {
    let mut r = Received {
        previews: Vec::new(),
        preview_bytes: 0,
        nodes: Vec::new(),
        end: 0,
    };
    let mut next = 0u64;
    loop {
        let (seq, msg) = match recv(ws).await {
            Some(ServerMsg::End { nodes_sent }) => {
                r.end = nodes_sent;
                return r;
            }
            Some(m @ ServerMsg::Preview { seq, .. }) | Some(m @ ServerMsg::Nodes { seq, .. }) => {
                (seq, m)
            }
            other => panic!("unexpected {other:?}"),
        };
        assert_eq!(seq, next, "seq counts both kinds");
        next += 1;
        match msg {
            ServerMsg::Preview { block, .. } => {
                assert!(r.nodes.is_empty(), "a preview after the store's nodes");
                let frame = tetwave_protocol::wire::encode(&ServerMsg::Preview {
                    seq,
                    block: block.clone(),
                })
                .unwrap();
                r.preview_bytes += frame.len() as u64;
                r.previews.extend(preview.decode(&block).unwrap());
            }
            ServerMsg::Nodes { block, .. } => r.nodes.extend(coder.decode(&block).unwrap()),
            _ => unreachable!(),
        }
        send(ws, &ClientMsg::Ack { seq }).await;
    }
}

async fn session_of(
    addr: std::net::SocketAddr,
    store: &Store,
    have: Vec<IdRange>,
) -> (Received, tetwave_store::Manifest) {
    let mut ws = connect(addr, "").await;
    send(&mut ws, &hello(None, have)).await;
    let manifest = match recv(&mut ws).await {
        Some(ServerMsg::Manifest(m)) => *m,
        other => panic!("expected the manifest, got {other:?}"),
    };
    assert!(matches!(recv(&mut ws).await, Some(ServerMsg::Base(_))));
    let coder = BlockCoder::new(&store.base, &store.manifest.encoding);
    let p = store.manifest.preview.as_ref().unwrap();
    let preview = BlockCoder::for_preview(&store.base, &p.encoding);
    let r = receive(&mut ws, &coder, &preview).await;
    let _ = ws.close(None).await;
    (r, manifest)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_new_session_gets_the_preview_first_then_every_node() {
    let (_d, dir) = preview_store();
    let store = Store::open(&dir).unwrap();
    let want = store.preview.clone().unwrap();
    let n = store.manifest.counts.nodes;
    for order in [Order::View, Order::Level] {
        let config = ServeConfig {
            order,
            ..ServeConfig::default()
        };
        let (addr, _) = start(&dir, config).await;
        let (r, manifest) = session_of(addr, &store, vec![]).await;
        assert_eq!(manifest.preview, store.manifest.preview, "{order:?}");
        // the whole preview (the default share), each node once and as the store holds it
        let mut got = r.previews.clone();
        got.sort_by_key(|x| x.id);
        assert_eq!(got, want, "{order:?}");
        // then every node of the store's own, once
        let ids: HashSet<u64> = r.nodes.iter().map(|x| x.id).collect();
        assert_eq!((ids.len() as u64, r.nodes.len() as u64, r.end), (n, n, n));
        if order == Order::Level {
            let sent: Vec<u64> = r.previews.iter().map(|x| x.id).collect();
            assert!(sent.windows(2).all(|w| w[0] < w[1]), "level order: by id");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_share_bounds_the_preview_and_a_resumed_session_gets_none() {
    let (_d, dir) = preview_store();
    let store = Store::open(&dir).unwrap();
    let blocks = store.manifest.files["blocks.bin"].bytes;
    let whole = store.manifest.files[tetwave_store::PREVIEW_FILE].bytes;
    let share = 0.5 * whole as f64 / blocks as f64;
    let config = ServeConfig {
        order: Order::View,
        preview_share: share,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, config).await;
    let (r, _) = session_of(addr, &store, vec![]).await;
    let budget = (share * blocks as f64) as u64;
    assert!(r.preview_bytes <= budget, "{} > {budget}", r.preview_bytes);
    assert!(!r.previews.is_empty());
    assert!((r.previews.len() as u64) < store.forest().level_start(3));
    // the base tets (the view's most important group) come first
    let first: Vec<u64> = r.previews.iter().take(5).map(|x| x.id).collect();
    assert_eq!(first, [0, 1, 2, 3, 4]);
    assert_eq!(r.end, store.manifest.counts.nodes);

    // resumed: no preview, only what is missing
    let (r, _) = session_of(addr, &store, vec![IdRange { from: 0, to: 1 }]).await;
    assert!(r.previews.is_empty());
    assert_eq!(r.end, store.manifest.counts.nodes - 1);
    // holding previews only (cut during the preview): none again, every node
    let mut ws = connect(addr, "").await;
    let mut h = hello(None, vec![]);
    if let ClientMsg::Hello { previewed, .. } = &mut h {
        *previewed = true;
    }
    send(&mut ws, &h).await;
    expect_opening(&mut ws).await;
    let p = store.manifest.preview.as_ref().unwrap();
    let r = receive(
        &mut ws,
        &BlockCoder::new(&store.base, &store.manifest.encoding),
        &BlockCoder::for_preview(&store.base, &p.encoding),
    )
    .await;
    assert!(r.previews.is_empty());
    assert_eq!(r.end, store.manifest.counts.nodes);

    // a server told to send none
    let config = ServeConfig {
        preview_share: 0.0,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, config).await;
    let (r, _) = session_of(addr, &store, vec![]).await;
    assert!(r.previews.is_empty());
}
