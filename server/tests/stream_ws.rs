//! The progressive WebSocket stream (`/v1/stream`) with a minimal tokio-tungstenite client: every
//! order delivers every node exactly once and synthesis of what arrived equals the store's; view
//! order follows the client's camera and re-prioritises when it changes; resume with `have`; `Want`
//! and `Cancel`; flow control by `Ack`; malformed input. Servers bind 127.0.0.1:0; waits are bounded.

mod stream_common;

use std::collections::HashSet;
use std::time::Duration;
use stream_common::*;
use tetwave_protocol::node::resolved_bounds;
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_protocol::wire::{encode, ClientMsg, IdRange, ServerMsg};
use tetwave_protocol::{DetailNode, LatticeTet};
use tetwave_server::stream::{served_manifest, ServeConfig};
use tetwave_store::Store;
use tokio_tungstenite::tungstenite::Message;

use futures_util::SinkExt;

fn store_values(store: &Store) -> Vec<f32> {
    let n = store.manifest.counts.nodes;
    synthesize_all(
        &store.base,
        &store.base.vertex_keys(),
        store.read_nodes(0, n).unwrap(),
    )
    .unwrap()
}

/// Every node exactly once, and synthesis of the received nodes (sorted by id) equals the store's.
fn assert_complete(s: &Session, store: &Store, values: &[f32]) {
    let n = store.manifest.counts.nodes;
    // the session's manifest: the served one without the input's name
    let mut sent = served_manifest(&store.manifest);
    sent.source.clear();
    assert_eq!(s.manifest, sent);
    assert_eq!(s.base, store.base);
    assert_eq!(s.nodes.len() as u64, n, "node count");
    assert_eq!(s.end_nodes_sent, n);
    let ids: HashSet<u64> = s.nodes.iter().map(|x| x.id).collect();
    assert_eq!(ids.len() as u64, n, "no duplicates");
    let mut sorted = s.nodes.clone();
    sorted.sort_by_key(|x| x.id);
    let got = synthesize_all(&s.base, &s.base.vertex_keys(), sorted).unwrap();
    assert_eq!(got.len(), values.len());
    for (a, b) in got.iter().zip(values) {
        assert_eq!(a.to_bits(), b.to_bits());
    }
}

/// A session's nodes, batch by batch.
fn by_batch(s: &Session) -> Vec<&[DetailNode]> {
    let mut out = Vec::new();
    let mut rest = &s.nodes[..];
    for &n in &s.batches {
        let (b, r) = rest.split_at(n);
        out.push(b);
        rest = r;
    }
    out
}

/// Every node's subtree bound as selection sees it, by id: its own, or on the finest node level
/// (which arrives without one) its parent's.
fn selection_bounds(store: &Store) -> Vec<f32> {
    let nodes = store.read_nodes(0, store.manifest.counts.nodes).unwrap();
    resolved_bounds(store.forest(), &nodes)
}

fn min_smax(b: &[DetailNode], bounds: &[f32]) -> f32 {
    b.iter()
        .map(|n| bounds[n.id as usize])
        .fold(f32::MAX, f32::min)
}

fn max_smax(b: &[DetailNode], bounds: &[f32]) -> f32 {
    b.iter().map(|n| bounds[n.id as usize]).fold(0.0, f32::max)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_order_delivers_everything_once_and_synthesis_matches() {
    let (_d, dir) = make_store(4);
    let store = Store::open(&dir).unwrap();
    let values = store_values(&store);
    let bounds = selection_bounds(&store);
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    for order in ["level", "magnitude", "view", "random"] {
        let s = session(addr, &format!("?order={order}"), None).await;
        assert_complete(&s, &store, &values);
        let ids: Vec<u64> = s.nodes.iter().map(|x| x.id).collect();
        match order {
            "level" => assert!(
                ids.windows(2).all(|w| w[0] < w[1]),
                "level order is id order"
            ),
            "magnitude" => assert!(
                by_batch(&s)
                    .windows(2)
                    .all(|w| min_smax(w[0], &bounds) >= max_smax(w[1], &bounds)),
                "magnitude order: largest subtree error first"
            ),
            // a batch holds its nodes in id order (a block's order); each batch of a random
            // order is drawn from the whole hierarchy
            "random" => assert!(
                by_batch(&s).iter().filter(|b| b.len() >= 16).all(|b| {
                    let span = b.last().unwrap().id - b[0].id;
                    span > store.manifest.counts.nodes / 2
                }),
                "random order is shuffled"
            ),
            _ => {}
        }
        eprintln!(
            "{order}: {} nodes in {} batches",
            s.nodes.len(),
            s.batches.len()
        );
    }
    // the server's default order comes from its configuration
    let cfg = ServeConfig {
        order: tetwave_server::stream::Order::Magnitude,
        batch: 100,
        max_batch: 100,
        ..ServeConfig::default()
    };
    let (addr2, _) = start(&dir, cfg).await;
    let s = session(addr2, "", None).await;
    assert_complete(&s, &store, &values);
    assert!(by_batch(&s)
        .windows(2)
        .all(|w| min_smax(w[0], &bounds) >= max_smax(w[1], &bounds)));
    assert!(s.batches.len() as u64 >= store.manifest.counts.nodes / 100);
    // an unknown order is refused before the upgrade
    let url = format!("ws://{addr}/v1/stream?order=sideways");
    assert!(tokio_tungstenite::connect_async(url).await.is_err());
}

fn centre(store: &Store, id: u64) -> [f64; 3] {
    let t = LatticeTet::from_id(&store.forest(), id);
    let mut c = [0.0; 3];
    for w in &t.v {
        let p = store.base.position(t.base, w);
        for a in 0..3 {
            c[a] += 0.25 * p[a];
        }
    }
    c
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt()
}

/// Fraction of `nodes` of the finest node level whose centre is nearer `a` than `b`.
fn nearer(store: &Store, nodes: &[DetailNode], a: [f64; 3], b: [f64; 3]) -> (f64, usize) {
    let f = store.forest();
    let fine: Vec<&DetailNode> = nodes
        .iter()
        .filter(|x| f.level(x.id) + 1 == f.levels)
        .collect();
    let k = fine
        .iter()
        .filter(|x| {
            let c = centre(store, x.id);
            dist(c, a) < dist(c, b)
        })
        .count();
    (k as f64 / fine.len().max(1) as f64, fine.len())
}

/// View order sends first what is near the camera, and re-prioritises when a new `View` arrives.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn view_order_follows_the_camera() {
    let (_d, dir) = make_store(5);
    let store = Store::open(&dir).unwrap();
    let cfg = ServeConfig {
        batch: 256,
        max_batch: 256,
        window: 4,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, cfg).await;
    let coder = coder_for(&dir);
    let (lo, hi) = store.base.bounds();
    let c = [
        0.5 * (lo[0] + hi[0]),
        0.5 * (lo[1] + hi[1]),
        0.5 * (lo[2] + hi[2]),
    ];
    // eyes beyond two opposite corners, looking at the centre, the whole volume in view
    let eye = |p: [f64; 3]| [0, 1, 2].map(|k| c[k] + 1.6 * (p[k] - c[k]));
    let (ea, eb) = (eye(lo), eye(hi));

    let mut ws = connect(addr, "?order=view").await;
    send(&mut ws, &hello(None, vec![])).await;
    send(&mut ws, &ClientMsg::View(view_from(ea, c))).await;
    expect_opening(&mut ws).await;
    // take 40 batches under view A (acking), then switch to view B
    let mut under_a = Vec::new();
    let mut seq_last = 0;
    for _ in 0..40 {
        match recv(&mut ws).await {
            Some(ServerMsg::Nodes { seq, block }) => {
                under_a.extend(coder.decode(&block).unwrap());
                seq_last = seq;
            }
            other => panic!("{other:?}"),
        }
        // keep the window full so the switch takes effect quickly: ack everything but the last
        send(
            &mut ws,
            &ClientMsg::Ack {
                seq: seq_last.saturating_sub(1),
            },
        )
        .await;
    }
    send(&mut ws, &ClientMsg::View(view_from(eb, c))).await;
    send(&mut ws, &ClientMsg::Ack { seq: seq_last }).await;
    // batches still in flight were chosen under A; skip the window's worth, then measure
    let mut after = Vec::new();
    let mut skipped = Vec::new();
    let mut n_batches = 0;
    while n_batches < 20 {
        match recv(&mut ws).await {
            Some(ServerMsg::Nodes { seq, block }) => {
                n_batches += 1;
                let nodes = coder.decode(&block).unwrap();
                if n_batches > 4 {
                    after.extend(nodes);
                } else {
                    skipped.extend(nodes);
                }
                send(&mut ws, &ClientMsg::Ack { seq }).await;
            }
            Some(ServerMsg::End { .. }) => break,
            other => panic!("{other:?}"),
        }
    }
    let (fa, na) = nearer(&store, &under_a, ea, eb);
    let (fb, nb) = nearer(&store, &after, eb, ea);
    eprintln!(
        "finest-level nodes nearer the camera: {:.0}% of {na} under view A, {:.0}% of {nb} after the switch to B",
        100.0 * fa,
        100.0 * fb
    );
    assert!(na > 100 && nb > 100, "enough fine nodes to judge");
    // (a node goes with its unsent siblings, for the coding of ids: a few of those lie across the
    // bisector of the two eyes, so the bar is 3 in 4 rather than 4 in 5; a random order gives 1 in 2)
    assert!(fa > 0.75, "view A: {fa}");
    assert!(fb > 0.75, "view B: {fb}");
    // and the session still completes with everything exactly once
    let (rest, _, _) = receive_nodes(&mut ws, &coder_for(&dir)).await;
    let _ = ws.close(None).await;
    let mut ids: Vec<u64> = under_a
        .iter()
        .chain(&skipped)
        .chain(&after)
        .chain(&rest)
        .map(|x| x.id)
        .collect();
    ids.sort_unstable();
    assert_eq!(ids, (0..store.manifest.counts.nodes).collect::<Vec<_>>());
}

/// Resume: with `have` ranges the server sends exactly the rest.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn resume_with_have_sends_only_the_rest() {
    let (_d, dir) = make_store(4);
    let store = Store::open(&dir).unwrap();
    let n = store.manifest.counts.nodes;
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    let have = vec![
        IdRange { from: 0, to: n / 2 },
        IdRange {
            from: n / 2 + 10,
            to: n / 2 + 20,
        },
        IdRange {
            from: n - 5,
            to: n + 1000, // beyond the store: clipped
        },
    ];
    let held: HashSet<u64> = have.iter().flat_map(|r| r.from..r.to.min(n)).collect();
    for order in ["level", "magnitude", "view", "random"] {
        let mut ws = connect(addr, &format!("?order={order}")).await;
        send(&mut ws, &hello(None, have.clone())).await;
        let s = receive_all(&mut ws).await;
        let _ = ws.close(None).await;
        let ids: HashSet<u64> = s.nodes.iter().map(|x| x.id).collect();
        assert_eq!(ids.len(), s.nodes.len(), "{order}: no duplicates");
        let want: HashSet<u64> = (0..n).filter(|i| !held.contains(i)).collect();
        assert_eq!(ids, want, "{order}");
        assert_eq!(s.end_nodes_sent, want.len() as u64);
        // what was held plus what came is the whole store
        let mut all = store.read_nodes(0, n).unwrap();
        all.retain(|x| held.contains(&x.id));
        all.extend(s.nodes);
        all.sort_by_key(|x| x.id);
        assert_eq!(all, store.read_nodes(0, n).unwrap());
    }
}

/// `Want` re-sends ranges (then `End` again); `Cancel` drops ranges not sent yet.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn want_and_cancel() {
    let (_d, dir) = make_store(4);
    let store = Store::open(&dir).unwrap();
    let n = store.manifest.counts.nodes;
    let (addr, _) = start(&dir, ServeConfig::default()).await;

    let mut ws = connect(addr, "").await;
    send(&mut ws, &hello(None, vec![])).await;
    let s = receive_all(&mut ws).await;
    assert_eq!(s.nodes.len() as u64, n);
    send(
        &mut ws,
        &ClientMsg::Want(vec![
            IdRange { from: 3, to: 13 },
            IdRange {
                from: n - 2,
                to: n + 5,
            },
        ]),
    )
    .await;
    let (again, sent, _) = receive_nodes(&mut ws, &coder_for(&dir)).await;
    let ids: Vec<u64> = again.iter().map(|x| x.id).collect();
    assert_eq!(ids, (3..13).chain(n - 2..n).collect::<Vec<_>>());
    assert_eq!(sent, n + 12, "End counts every node sent on the connection");
    assert_eq!(again, {
        let mut v = store.read_nodes(3, 13).unwrap();
        v.extend(store.read_nodes(n - 2, n).unwrap());
        v
    });
    let _ = ws.close(None).await;

    // Cancel the upper half right after Hello: none of it arrives (level order sends it last). A
    // window of one small batch keeps the server from sending past the first batch before it has
    // read the Cancel (it waits for the Ack, which the socket delivers after the Cancel).
    let cfg = ServeConfig {
        batch: 64,
        max_batch: 64,
        window: 1,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, cfg).await;
    let mut ws = connect(addr, "").await;
    send(&mut ws, &hello(None, vec![])).await;
    send(
        &mut ws,
        &ClientMsg::Cancel(vec![IdRange { from: n / 2, to: n }]),
    )
    .await;
    let s = receive_all(&mut ws).await;
    let ids: Vec<u64> = s.nodes.iter().map(|x| x.id).collect();
    assert_eq!(ids, (0..n / 2).collect::<Vec<_>>());
    // a later Want brings cancelled nodes back
    send(
        &mut ws,
        &ClientMsg::Want(vec![IdRange {
            from: n / 2,
            to: n / 2 + 3,
        }]),
    )
    .await;
    let (again, _, _) = receive_nodes(&mut ws, &coder_for(&dir)).await;
    assert_eq!(
        again.iter().map(|x| x.id).collect::<Vec<_>>(),
        vec![n / 2, n / 2 + 1, n / 2 + 2]
    );
    let _ = ws.close(None).await;
}

/// Flow control: a client that does not acknowledge gets `window` batches and then nothing more
/// until it acks; the stream then goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unacknowledged_batches_are_bounded_by_the_window() {
    let (_d, dir) = make_store(4);
    let n = Store::open(&dir).unwrap().manifest.counts.nodes;
    let cfg = ServeConfig {
        batch: 64,
        max_batch: 64,
        window: 3,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, cfg).await;
    let mut ws = open(addr, "").await;
    let mut got = Vec::new();
    for round in 0..3 {
        let mut seqs = Vec::new();
        loop {
            match recv_within(&mut ws, Duration::from_millis(700)).await {
                Ok(Some(ServerMsg::Nodes { seq, block })) => {
                    seqs.push(seq);
                    got.extend(coder_for(&dir).decode(&block).unwrap());
                }
                Ok(other) => panic!("{other:?}"),
                Err(()) => break, // nothing more without an ack
            }
        }
        assert_eq!(seqs.len(), 3, "round {round}: exactly the window");
        send(
            &mut ws,
            &ClientMsg::Ack {
                seq: *seqs.last().unwrap(),
            },
        )
        .await;
    }
    let (rest, sent, _) = receive_nodes(&mut ws, &coder_for(&dir)).await;
    assert_eq!(got.len() + rest.len(), n as usize);
    assert_eq!(sent, n);
    let _ = ws.close(None).await;
}

/// Malformed input gets an `Error` and a closed socket, never a crash; the server goes on serving.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_client_input() {
    let (_d, dir) = make_store(2);
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    let expect_error = |code: u16| {
        move |m: Option<ServerMsg>| match m {
            Some(ServerMsg::Error { code: c, .. }) => assert_eq!(c, code),
            other => panic!("expected Error {code}, got {other:?}"),
        }
    };
    // garbage instead of Hello
    let mut ws = connect(addr, "").await;
    ws.send(Message::Binary(vec![1, 2, 3, 4, 5, 6, 7].into()))
        .await
        .unwrap();
    expect_error(400)(recv(&mut ws).await);
    assert!(recv(&mut ws).await.is_none());
    // text instead of binary
    let mut ws = connect(addr, "").await;
    ws.send(Message::Text("hello".into())).await.unwrap();
    expect_error(400)(recv(&mut ws).await);
    // a message other than Hello first
    let mut ws = connect(addr, "").await;
    send(&mut ws, &ClientMsg::Ack { seq: 0 }).await;
    expect_error(400)(recv(&mut ws).await);
    // a wrong protocol version inside Hello
    let mut ws = connect(addr, "").await;
    send(
        &mut ws,
        &ClientMsg::Hello {
            version: 999,
            token: None,
            have: vec![],
            previewed: vec![],
        },
    )
    .await;
    expect_error(426)(recv(&mut ws).await);
    // garbage in the middle of a session
    let mut ws = connect(addr, "").await;
    send(&mut ws, &hello(None, vec![])).await;
    let mut f = encode(&ClientMsg::Ack { seq: 1 }).unwrap();
    f[6] = 200; // unknown message kind
    ws.send(Message::Binary(f.into())).await.unwrap();
    let mut saw_error = false;
    while let Some(m) = recv(&mut ws).await {
        if let ServerMsg::Error { code, .. } = m {
            assert_eq!(code, 400);
            saw_error = true;
        }
    }
    assert!(saw_error);
    // the server is still fine
    let s = session(addr, "", None).await;
    assert_eq!(s.nodes.len() as u64, s.manifest.counts.nodes);
}

/// Batches start at `batch` nodes and double up to `max_batch` (small batches paint early, large
/// ones code tightly); a `View` starts them small again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batches_grow_and_a_view_starts_them_small_again() {
    let (_d, dir) = make_store(4);
    let store = Store::open(&dir).unwrap();
    let cfg = ServeConfig {
        batch: 16,
        max_batch: 128,
        // one batch in flight: the View below is read before the next batch is chosen
        window: 1,
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, cfg).await;
    let s = session(addr, "", None).await;
    assert_eq!(s.nodes.len() as u64, store.manifest.counts.nodes);
    let full = &s.batches[..s.batches.len() - 1]; // the last may be short
    assert_eq!(&full[..4], &[16, 32, 64, 128], "{:?}", s.batches);
    assert!(full[4..].iter().all(|&n| n == 128), "{:?}", s.batches);

    // view order: a View after a few batches makes the next batch small again
    let coder = coder_for(&dir);
    let mut ws = open(addr, "?order=view").await;
    let mut sizes = Vec::new();
    for i in 0..8 {
        match recv(&mut ws).await {
            Some(ServerMsg::Nodes { seq, block }) => {
                sizes.push(coder.decode(&block).unwrap().len());
                if i == 4 {
                    send(&mut ws, &ClientMsg::View(view_from([3.0; 3], [0.5; 3]))).await;
                }
                send(&mut ws, &ClientMsg::Ack { seq }).await;
            }
            other => panic!("{other:?}"),
        }
    }
    let _ = ws.close(None).await;
    assert!(sizes[..5].windows(2).all(|w| w[1] >= w[0]), "{sizes:?}");
    assert_eq!(sizes[4], 128, "{sizes:?}");
    assert_eq!(&sizes[5..], &[16, 32, 64], "{sizes:?}");
}
