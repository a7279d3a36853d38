//! `tetwave bench progressive` on a store whose node file was tampered with, consistently enough
//! that it still reads (the same coefficient count): one owned vertex bit moved from one node to
//! another, so two nodes claim one vertex. The run stops with an error that names the store and
//! the node, instead of panicking or dropping the node.

mod common;

use tetwave_client::progressive::bench;

/// `nodes.bin`: 6 bytes per node, the first the owned-edge mask.
const NODE_BYTES: usize = 6;

#[test]
fn bench_on_a_tampered_store_is_an_error() {
    let (_d, store) = common::harmonic_store(2);
    let path = store.join("nodes.bin");
    let mut bytes = std::fs::read(&path).unwrap();
    let masks: Vec<u8> = bytes.iter().step_by(NODE_BYTES).copied().collect();
    // node `from` gives up its lowest owned edge; a later node that owns some edge but not all six
    // takes its lowest free one (which another node owns: every vertex has an owner)
    let from = masks.iter().position(|&m| m != 0).unwrap();
    let to = (from + 1..masks.len())
        .find(|&j| masks[j] != 0 && masks[j] != 0x3f)
        .unwrap();
    bytes[from * NODE_BYTES] &= masks[from] - 1;
    let free = !masks[to] & 0x3f;
    bytes[to * NODE_BYTES] |= free & free.wrapping_neg();
    std::fs::write(&path, bytes).unwrap();

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
