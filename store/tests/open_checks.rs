//! `Store::open` refuses a tampered store with the file and the reason, before any node is read:
//! a flipped byte in `base.bin` (its checksum is always checked), a coefficient index entry that
//! would wrap an offset, an index that goes down, an owned mask that no longer matches the index,
//! a truncated coefficient file. The other files' checksums are checked on request
//! ([`OpenOptions::verify_checksums`]).

use std::path::Path;
use tetwave_protocol::fields::harmonic_unit;
use tetwave_protocol::shapes::box5;
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_protocol::testing::{detail_nodes, unsampled_base};
use tetwave_protocol::DetailNode;
use tetwave_store::{write, OpenOptions, Store, StoreContent, StoreError, StoreMeta, BLOCK};

/// Writes a `box5` store of `levels` levels of the unit-cube harmonic field into `dir`; returns
/// its nodes.
fn make_store(dir: &Path, levels: u8) -> Vec<DetailNode> {
    let base = unsampled_base(levels, box5([0.0; 3], [1.0; 3]));
    let (base, nodes) = detail_nodes(base, |p| harmonic_unit(p) as f32);
    let reference = synthesize_all(&base, &base.vertex_keys(), nodes.iter().cloned()).unwrap();
    let coeffs: Vec<f32> = nodes
        .iter()
        .flat_map(|n| n.coeffs.iter().copied())
        .collect();
    let lo = reference.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = reference.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let content = StoreContent {
        base: &base,
        owned: &nodes.iter().map(|n| n.owned).collect::<Vec<_>>(),
        empty_children: &nodes.iter().map(|n| n.empty_children).collect::<Vec<_>>(),
        subtree_max_abs: &nodes.iter().map(|n| n.subtree_max_abs).collect::<Vec<_>>(),
        coeffs: &coeffs,
        quantizer: None,
        reference: &reference,
        value_range: (lo, hi),
        max_abs_error: 0.0,
        error_bound: 1e-6,
    };
    let meta = StoreMeta {
        dataset: "harmonic".into(),
        source: "test".into(),
        base: "box5".into(),
        outside_vertices: 0,
    };
    write(dir, &content, meta).unwrap();
    nodes
}

/// A level-5 store (23,405 nodes: 6 index blocks) in a temporary directory.
fn store() -> (tempfile::TempDir, Vec<DetailNode>) {
    let d = tempfile::tempdir().unwrap();
    let nodes = make_store(d.path(), 5);
    assert!(nodes.len() as u64 > 4 * BLOCK);
    (d, nodes)
}

fn edit(path: &Path, f: impl FnOnce(&mut Vec<u8>)) {
    let mut b = std::fs::read(path).unwrap();
    f(&mut b);
    std::fs::write(path, b).unwrap();
}

/// Sets the manifest's size of `file` to its size on disk (a tamper that kept the manifest in
/// step, so that the check under test is the one that refuses).
fn resize_in_manifest(dir: &Path, file: &str) {
    let mpath = dir.join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["files"][file]["bytes"] = std::fs::metadata(dir.join(file)).unwrap().len().into();
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
}

fn index(dir: &Path) -> Vec<u64> {
    std::fs::read(dir.join("coeff_index.bin"))
        .unwrap()
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

fn write_index(dir: &Path, index: &[u64]) {
    let b: Vec<u8> = index.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(dir.join("coeff_index.bin"), b).unwrap();
}

/// The error of opening `dir`, which must name `file` and contain every part of `why`.
fn refused(dir: &Path, file: &str, why: &[&str]) -> StoreError {
    let e = Store::open(dir)
        .err()
        .expect("the store is refused at open");
    let msg = e.to_string();
    assert!(
        msg.contains(&dir.join(file).display().to_string()),
        "{file} not named: {msg}"
    );
    for w in why {
        assert!(msg.contains(w), "{w:?} not in: {msg}");
    }
    e
}

#[test]
fn an_intact_store_opens_and_reads_back() {
    let (d, nodes) = store();
    let s = Store::open(d.path()).unwrap();
    assert_eq!(s.read_nodes(0, nodes.len() as u64).unwrap(), nodes);
    Store::open_with(
        d.path(),
        OpenOptions {
            verify_checksums: true,
        },
    )
    .unwrap();
}

#[test]
fn a_flipped_byte_in_base_bin_is_refused() {
    let (d, _) = store();
    // a byte of the positions (after the levels byte and the length): still decodes
    edit(&d.path().join("base.bin"), |b| b[20] ^= 0x01);
    refused(d.path(), "base.bin", &["checksum", "manifest says"]);
}

/// An entry near 2^62 would wrap `offset × 4` back into the file; it is beyond the coefficient
/// count, and so is refused.
#[test]
fn an_index_entry_that_would_wrap_is_refused() {
    let (d, _) = store();
    let mut ix = index(d.path());
    let last = ix.len() - 1;
    ix[last] += 1u64 << 62;
    assert_eq!(ix[last].wrapping_mul(4) / 4, ix[last] - (1 << 62));
    write_index(d.path(), &ix);
    resize_in_manifest(d.path(), "coeff_index.bin");
    refused(
        d.path(),
        "coeff_index.bin",
        &[
            &format!("entry {last} ({})", ix[last]),
            "beyond the manifest's",
        ],
    );
    // a huge entry in the middle: the next one is below it
    let (d, _) = store();
    let mut ix = index(d.path());
    ix[2] = u64::MAX - 3;
    write_index(d.path(), &ix);
    refused(
        d.path(),
        "coeff_index.bin",
        &[&format!("entry 3 ({}) is below entry 2 ({})", ix[3], ix[2])],
    );
}

#[test]
fn a_decreasing_index_is_refused() {
    let (d, _) = store();
    let mut ix = index(d.path());
    ix.swap(2, 3);
    assert!(ix[3] < ix[2]);
    write_index(d.path(), &ix);
    refused(
        d.path(),
        "coeff_index.bin",
        &[&format!("entry 3 ({}) is below entry 2 ({})", ix[3], ix[2])],
    );
}

/// A mask that gains or loses a bit shifts every later coefficient onto the wrong vertex: its
/// block's masks no longer own what the index says. A bit beyond the 6 edges is refused as such.
#[test]
fn a_changed_owned_mask_is_refused() {
    let (d, nodes) = store();
    let k = BLOCK as usize
        + 17
        + nodes[BLOCK as usize + 17..]
            .iter()
            .position(|n| n.owned != 0)
            .unwrap();
    let path = d.path().join("nodes.bin");
    let original = std::fs::read(&path).unwrap();
    edit(&path, |b| b[k * 6] &= b[k * 6] - 1);
    refused(
        d.path(),
        "nodes.bin",
        &[
            &format!("the owned masks of nodes {BLOCK}..{}", 2 * BLOCK),
            "coeff_index.bin entries 1 and 2",
        ],
    );
    // in the last block, the count to match is the manifest's
    std::fs::write(&path, &original).unwrap();
    let last = nodes.len() - 1 - nodes.iter().rev().position(|n| n.owned != 0x3f).unwrap();
    edit(&path, |b| b[last * 6] |= !b[last * 6] & 0x3f);
    refused(d.path(), "nodes.bin", &["the manifest's coefficient count"]);
    std::fs::write(&path, &original).unwrap();
    edit(&path, |b| b[k * 6] |= 0x80);
    refused(
        d.path(),
        "nodes.bin",
        &[&format!("node {k}: owned mask"), "beyond the 6 edges"],
    );
}

#[test]
fn a_truncated_coefficient_file_is_refused() {
    let (d, _) = store();
    let path = d.path().join("coeffs.bin");
    edit(&path, |b| b.truncate(b.len() - 4));
    refused(d.path(), "coeffs.bin", &["manifest says"]);
    // with the manifest edited to the new size, the coefficient count still disagrees
    resize_in_manifest(d.path(), "coeffs.bin");
    refused(d.path(), "coeffs.bin", &["coefficients of 4 bytes need"]);
}

/// Only the five store files are listed: a manifest naming another path is refused before that
/// path is opened.
#[test]
fn a_manifest_naming_other_files_is_refused() {
    let (d, _) = store();
    let mpath = d.path().join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["files"]["../elsewhere"] = serde_json::json!({"bytes": 0, "crc32": 0});
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    refused(
        d.path(),
        "manifest.json",
        &["\"../elsewhere\" is not a file of a store"],
    );
}

/// A flipped coefficient keeps every structural check: only the checksums find it, and
/// `verify_checksums` checks them at open.
#[test]
fn checksums_are_checked_at_open_on_request() {
    let (d, _) = store();
    edit(&d.path().join("coeffs.bin"), |b| b[100] ^= 0x10);
    Store::open(d.path()).expect("structurally sound");
    let e = Store::open_with(
        d.path(),
        OpenOptions {
            verify_checksums: true,
        },
    )
    .err()
    .expect("refused");
    let msg = e.to_string();
    assert!(
        msg.contains("coeffs.bin") && msg.contains("checksum"),
        "{msg}"
    );
}
