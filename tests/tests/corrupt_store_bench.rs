//! `tetwave-bench progressive` on a store whose blocks were re-coded with tampered nodes,
//! consistently enough that the store still opens (every block decodes, the same coefficient
//! count): one owned vertex bit moved from one node to another, so two nodes claim one vertex. The
//! run stops with an error that names the store and the node, instead of panicking or dropping the
//! node.

mod common;

use std::path::Path;
use tetwave_client::progressive::bench;
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::DetailNode;
use tetwave_store::{Store, BLOCK, BLOCK_SUMS_FILE};

/// Rewrites the store's `blocks.bin`, `block_index.bin` and `block_sums.bin` from `nodes` (all of
/// them, in id order) with the store's coder, and their sizes in the manifest, as a writer with a
/// bug would.
fn recode(store: &Path, nodes: &[DetailNode]) {
    let s = Store::open(store).unwrap();
    let coder = BlockCoder::new(&s.base, &s.manifest.encoding);
    let (mut blocks, mut index, mut sums) = (Vec::new(), vec![0u8; 8], Vec::new());
    for chunk in nodes.chunks(BLOCK as usize) {
        let b = coder.encode(chunk).unwrap().bytes;
        sums.extend(crc32fast::hash(&b).to_le_bytes());
        blocks.extend(b);
        index.extend((blocks.len() as u64).to_le_bytes());
    }
    std::fs::write(store.join(BLOCK_SUMS_FILE), &sums).unwrap();
    std::fs::write(store.join("blocks.bin"), &blocks).unwrap();
    std::fs::write(store.join("block_index.bin"), &index).unwrap();
    let mpath = store.join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["files"]["blocks.bin"]["bytes"] = (blocks.len() as u64).into();
    m["files"]["block_index.bin"]["bytes"] = (index.len() as u64).into();
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
}

#[test]
fn bench_on_a_tampered_store_is_an_error() {
    let (_d, store) = common::harmonic_store(2);
    let mut nodes = {
        let s = Store::open(&store).unwrap();
        s.read_nodes(0, s.manifest.counts.nodes).unwrap()
    };
    // node `from` gives up its lowest owned edge (and that coefficient); a later node that owns
    // some edge but not all six takes its lowest free one (which another node owns: every vertex
    // has an owner), with a coefficient of 0 in edge order
    let from = nodes.iter().position(|n| n.owned != 0).unwrap();
    let to = (from + 1..nodes.len())
        .find(|&j| nodes[j].owned != 0 && nodes[j].owned != 0x3f)
        .unwrap();
    nodes[from].owned &= nodes[from].owned - 1;
    nodes[from].coeffs.remove(0);
    let free = !nodes[to].owned & 0x3f;
    let bit = free & free.wrapping_neg();
    let at = (nodes[to].owned & (bit - 1)).count_ones() as usize;
    nodes[to].owned |= bit;
    nodes[to].coeffs.insert(at, 0.0);
    recode(&store, &nodes);
    Store::open(&store).expect("the tampered store is structurally sound");

    let args = common::bench_args(&[
        "--store",
        store.to_str().unwrap(),
        "--steps",
        "4",
        "--per-step",
        "1000",
        "--tol",
        "20%",
    ]);
    let e = bench(&args, |_| {}).expect_err("a tampered store fails the run");
    let msg = e.to_string();
    assert!(msg.contains(store.to_str().unwrap()), "{msg}");
    assert!(
        msg.contains(&format!("detail node {to} is invalid")),
        "{msg}"
    );
    assert!(msg.contains("already owns"), "{msg}");
}
