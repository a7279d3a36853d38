//! A new session of a store with a preview: `Preview` batches first (numbered with the `Nodes`
//! batches, acknowledged like them), within the configured share of the store's bytes, coarse
//! levels first and whole, the finest in batches that about double what was sent; then every
//! node of the store's own, once. A resumed session and a server configured with no share get
//! no preview; a session that says it holds preview nodes gets only the others. Every wait is bounded.

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
    o.levels = Some(4);
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
    /// Each preview frame's bytes.
    preview_frames: Vec<u64>,
    nodes: Vec<DetailNode>,
    end: u64,
}

/// Receives (acking every batch, checking `seq` increases by one over both kinds and that no
/// preview follows a `Nodes` batch) until `End`.
async fn receive(ws: &mut Ws, coder: &BlockCoder, preview: &BlockCoder) -> Received {
    let mut r = Received {
        previews: Vec::new(),
        preview_bytes: 0,
        preview_frames: Vec::new(),
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
                r.preview_frames.push(frame.len() as u64);
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
        Some(ServerMsg::Start(st)) => st.manifest,
        other => panic!("expected the session's start, got {other:?}"),
    };
    let coder = BlockCoder::new(&store.base, &store.manifest.encoding);
    let p = store.manifest.preview.as_ref().unwrap();
    let preview = BlockCoder::for_preview(&store.base, &p.encoding);
    let r = receive(&mut ws, &coder, &preview).await;
    let _ = ws.close(None).await;
    (r, manifest)
}

/// A session whose `Hello` names the preview nodes `held` (and no store node).
async fn session_holding(
    addr: std::net::SocketAddr,
    store: &Store,
    held: Vec<IdRange>,
) -> Received {
    let mut ws = connect(addr, "").await;
    let mut h = hello(None, vec![]);
    if let ClientMsg::Hello { previewed, .. } = &mut h {
        *previewed = held;
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
    let _ = ws.close(None).await;
    r
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
        let sent: Vec<u64> = r.previews.iter().map(|x| x.id).collect();
        if order == Order::Level {
            assert!(sent.windows(2).all(|w| w[0] < w[1]), "level order: by id");
        }
        // coarse to fine, the coarse levels whole in the first frame
        let forest = store.forest();
        let levels: Vec<u8> = sent.iter().map(|&i| forest.level(i)).collect();
        assert!(
            levels.windows(2).all(|w| w[0] <= w[1]),
            "{order:?}: {levels:?}"
        );
        let finest = manifest.preview.as_ref().unwrap().levels - 1;
        let coarse = forest.level_start(finest) as usize;
        let mut first: Vec<u64> = sent[..coarse].to_vec();
        first.sort_unstable();
        assert_eq!(first, (0..coarse as u64).collect::<Vec<_>>(), "{order:?}");
        // then batches that about double what was sent (a few, not one per level's group)
        let f = &r.preview_frames;
        assert!(f.len() >= 3, "{order:?}: {f:?}");
        let mut before = f[0];
        for &b in &f[1..f.len() - 1] {
            assert!(b <= 2 * before && 2 * b >= before, "{order:?}: {f:?}");
            before += b;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_share_bounds_the_preview_and_a_resumed_one_gets_only_what_it_lacks() {
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
    // that preview resumed (say the link was cut at its end): what the client holds counts
    // against the share (estimated), so the two connections together stay near it
    let mut ids: Vec<u64> = r.previews.iter().map(|x| x.id).collect();
    ids.sort_unstable();
    let mut held: Vec<IdRange> = Vec::new();
    for id in ids {
        match held.last_mut() {
            Some(x) if x.to == id => x.to += 1,
            _ => held.push(IdRange {
                from: id,
                to: id + 1,
            }),
        }
    }
    let again = session_holding(addr, &store, held).await;
    assert!(
        r.preview_bytes + again.preview_bytes <= budget + budget / 4,
        "{} + {} against {budget}",
        r.preview_bytes,
        again.preview_bytes
    );

    // resumed: no preview, only what is missing
    let (r, _) = session_of(addr, &store, vec![IdRange { from: 0, to: 1 }]).await;
    assert!(r.previews.is_empty());
    assert_eq!(r.end, store.manifest.counts.nodes - 1);
    // holding preview nodes only (cut during the preview): the rest of the preview, then every
    // node; holding all of it: no preview (a server with the whole preview to give)
    let config = ServeConfig {
        order: Order::View,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, config).await;
    let all = store.preview.as_ref().unwrap().len() as u64;
    for held in [
        vec![IdRange { from: 0, to: 7 }, IdRange { from: 20, to: 90 }],
        vec![IdRange { from: 0, to: all }],
    ] {
        let r = session_holding(addr, &store, held.clone()).await;
        let mut got: Vec<u64> = r.previews.iter().map(|x| x.id).collect();
        got.sort_unstable();
        let rest: Vec<u64> = (0..all)
            .filter(|&i| !held.iter().any(|r| (r.from..r.to).contains(&i)))
            .collect();
        assert_eq!(got, rest);
        assert_eq!(r.end, store.manifest.counts.nodes);
    }

    // a server told to send none
    let config = ServeConfig {
        preview_share: 0.0,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, config).await;
    let (r, _) = session_of(addr, &store, vec![]).await;
    assert!(r.previews.is_empty());
}
