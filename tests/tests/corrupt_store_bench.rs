//! `tetwave bench progressive` on a store whose node file was tampered with, consistently enough
//! that it still reads (the same coefficient count): one owned vertex bit moved from one node to
//! another, so two nodes claim one vertex. The run stops with an error that names the store and
//! the node, instead of panicking or dropping the node.

use clap::Parser;
use tetwave_client::progressive::{bench, BenchArgs};
use tetwave_server::prepare::{prepare, PrepareOptions};

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    bench: BenchArgs,
}

/// `nodes.bin`: 6 bytes per node, the first the owned-edge mask.
const NODE_BYTES: usize = 6;

#[test]
fn bench_on_a_tampered_store_is_an_error() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("s");
    let mut o = PrepareOptions::new("synthetic:harmonic", &store);
    o.levels = 2;
    prepare(&o).unwrap();
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

    let cli = Cli::try_parse_from([
        "bench",
        "--store",
        store.to_str().unwrap(),
        "--steps",
        "4",
        "--per-step",
        "1000",
        "--tol",
        "20%",
    ])
    .unwrap();
    let e = bench(&cli.bench, |_| {}).expect_err("a tampered store fails the run");
    let msg = e.to_string();
    assert!(msg.contains(store.to_str().unwrap()), "{msg}");
    assert!(
        msg.contains(&format!("detail node {to} is invalid")),
        "{msg}"
    );
    assert!(msg.contains("already owns"), "{msg}");
}
