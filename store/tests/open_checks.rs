//! `Store::open` refuses a tampered store with the file and the reason, before any node is read:
//! a flipped byte in `base.bin` (its checksum is always checked), a block index entry that would
//! make a huge read, an index that goes down, a flipped byte inside `blocks.bin`, a block that
//! decodes to other ids or to another coefficient count, a truncated `blocks.bin`, a store of the
//! previous version, a preview that is not the store's coarse nodes. The other files' checksums
//! are checked on request ([`OpenOptions::verify_checksums`]).

use std::path::Path;
use tetwave_protocol::block::{pow2_bound, pow2_class, BlockCoder};
use tetwave_protocol::fields::harmonic_unit;
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::node::INHERITED_BOUND;
use tetwave_protocol::shapes::box5;
use tetwave_protocol::store_format::STORE_VERSION;
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_protocol::testing::{detail_nodes, unsampled_base};
use tetwave_protocol::DetailNode;
use tetwave_store::{
    write, Encoding, OpenOptions, Preview, PreviewNodes, Store, StoreContent, StoreError,
    StoreMeta, BLOCK, BLOCK_SUMS_FILE, MAX_BLOCK_BYTES, PREVIEW_FILE,
};

/// Writes a `box5` store of `levels` levels of the unit-cube harmonic field into `dir`; returns
/// its nodes.
fn make_store(dir: &Path, levels: u8) -> Vec<DetailNode> {
    make_store_with(dir, levels, None)
}

/// [`make_store`] with a level set (`levelset.f32`) and a source value range when `levelset`.
fn make_store_with(dir: &Path, levels: u8, levelset: Option<Vec<f32>>) -> Vec<DetailNode> {
    make_store_full(dir, levels, levelset, None)
}

/// The preview [`make_store_full`] writes with `preview_step`: the nodes of every node level but
/// the finest, their coefficients quantized with that step.
fn preview_of(nodes: &[DetailNode], levels: u8, step: f32) -> PreviewNodes {
    let encoding = Encoding::uniform(16, step);
    let (q, _) = encoding.quantizer().unwrap();
    let count = tetwave_protocol::Forest::new(5, levels).level_start(levels - 1) as usize;
    PreviewNodes {
        nodes: nodes[..count]
            .iter()
            .map(|n| DetailNode {
                coeffs: n.coeffs.iter().map(|&c| q.decode(q.encode(c))).collect(),
                ..n.clone()
            })
            .collect(),
        preview: Preview {
            encoding,
            levels: levels - 1,
            max_error_bound: step as f64,
        },
    }
}

/// [`make_store_with`], with a preview ([`preview_of`]) when `preview_step` is given.
fn make_store_full(
    dir: &Path,
    levels: u8,
    levelset: Option<Vec<f32>>,
    preview_step: Option<f32>,
) -> Vec<DetailNode> {
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
        source_value_range: levelset.as_ref().map(|_| (lo - 1.0, hi + 1.0)),
        levelset_near: levelset.as_ref().map(|ls| {
            let band = ls.iter().enumerate().filter(|(_, v)| v.abs() < 0.5);
            NearLevelSet::new(1e-3, band.map(|(k, v)| (k as u64, *v))).unwrap()
        }),
        levelset,
        preview: preview_step.map(|step| preview_of(&nodes, levels, step)),
        keep_reference: true,
        physical: None,
    };
    write(dir, &content, meta).unwrap();
    // as the store codes them: lossless subtree bounds rounded up to powers of two, none on the
    // finest node level
    let finest = base.forest().checked_finest_nodes_start().unwrap();
    nodes
        .into_iter()
        .map(|n| DetailNode {
            subtree_max_abs: if n.id >= finest {
                INHERITED_BOUND
            } else {
                pow2_bound(pow2_class(n.subtree_max_abs))
            },
            ..n
        })
        .collect()
}

/// A level-5 store (23,405 nodes: 6 blocks) in a temporary directory.
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
    std::fs::read(dir.join("block_index.bin"))
        .unwrap()
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

fn write_index(dir: &Path, index: &[u64]) {
    let b: Vec<u8> = index.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(dir.join("block_index.bin"), b).unwrap();
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
            ..Default::default()
        },
    )
    .unwrap();
}

/// A store with a level set: `levelset.f32` is listed with its checksum, reads back as written,
/// with its near band, and the manifest's source value range (what renderers map by default) comes
/// back; a store written over it without one loses the files. A truncated level set, or one
/// listed without its band, is refused at open.
#[test]
fn a_level_set_and_source_range_read_back() {
    let d = tempfile::tempdir().unwrap();
    let n = tetwave_protocol::testing::unsampled_base(3, box5([0.0; 3], [1.0; 3]))
        .vertex_keys()
        .vertex_count() as usize;
    let ls: Vec<f32> = (0..n).map(|k| k as f32 - 10.0).collect();
    make_store_with(d.path(), 3, Some(ls.clone()));
    let s = Store::open_with(
        d.path(),
        OpenOptions {
            verify_checksums: true,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(s.read_levelset().unwrap(), Some(ls.clone()));
    // its near band (|value| < 0.5 here) reads back too
    let (_, band) = s.read_levelset_near().unwrap().expect("a near band");
    assert_eq!(band.len(), ls.iter().filter(|v| v.abs() < 0.5).count());
    assert_eq!(band.get(10), Some(0.0));
    let [lo, hi] = s.manifest.value_range;
    assert_eq!(s.manifest.source_value_range, Some([lo - 1.0, hi + 1.0]));
    assert_eq!(s.manifest.display_value_range(), [lo - 1.0, hi + 1.0]);
    // truncated: refused at open, naming the file
    let path = d.path().join("levelset.f32");
    let full = std::fs::read(&path).unwrap();
    std::fs::write(&path, &full[..full.len() - 4]).unwrap();
    refused(d.path(), "levelset.f32", &["bytes"]);
    std::fs::write(&path, &full).unwrap();
    // a manifest that lists the level set without its band is refused
    let mpath = d.path().join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    let band = m["files"]["levelset_near.bin"].clone();
    m["files"]
        .as_object_mut()
        .unwrap()
        .remove("levelset_near.bin");
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    refused(d.path(), "manifest.json", &["without the other"]);
    // and a mesh's band without its level set too (only a box domain's band stands alone)
    m["files"].as_object_mut().unwrap().remove("levelset.f32");
    m["files"]["levelset_near.bin"] = band;
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    refused(d.path(), "manifest.json", &["without the other"]);
    // rewritten without a level set: no file, no range, the samples' range by default
    make_store(d.path(), 3);
    let s = Store::open(d.path()).unwrap();
    assert_eq!(s.read_levelset().unwrap(), None);
    assert!(s.read_levelset_near().unwrap().is_none());
    assert!(!path.exists() && !d.path().join("levelset_near.bin").exists());
    assert_eq!(s.manifest.display_value_range(), s.manifest.value_range);
}

#[test]
fn a_flipped_byte_in_base_bin_is_refused() {
    let (d, _) = store();
    // a byte of the positions (after the levels byte and the length): still decodes
    edit(&d.path().join("base.bin"), |b| b[20] ^= 0x01);
    refused(d.path(), "base.bin", &["checksum", "manifest says"]);
}

/// An entry near 2^62 would ask for a huge read: the block before it spans more than a block may,
/// and the last entry must be `blocks.bin`'s length.
#[test]
fn an_index_entry_that_would_overreach_is_refused() {
    let (d, _) = store();
    let mut ix = index(d.path());
    ix[2] = u64::MAX - 3;
    write_index(d.path(), &ix);
    refused(
        d.path(),
        "block_index.bin",
        &[&format!("block 1 spans bytes {}..{}", ix[1], ix[2])],
    );
    let (d, _) = store();
    let mut ix = index(d.path());
    let last = ix.len() - 1;
    ix[last] += 1;
    write_index(d.path(), &ix);
    let len = std::fs::metadata(d.path().join("blocks.bin"))
        .unwrap()
        .len();
    refused(
        d.path(),
        "block_index.bin",
        &[&format!(
            "entry {last} ({}) is not the length of blocks.bin ({len} bytes)",
            ix[last]
        )],
    );
    // a last entry beyond what any block may span
    ix[last] += 1 << 62;
    assert!(ix[last] - ix[last - 1] > MAX_BLOCK_BYTES);
    write_index(d.path(), &ix);
    refused(
        d.path(),
        "block_index.bin",
        &[&format!("block {} spans", last - 1)],
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
        "block_index.bin",
        &[&format!("block 2 spans bytes {}..{}", ix[2], ix[3])],
    );
}

#[test]
fn an_index_of_the_wrong_length_is_refused() {
    let (d, _) = store();
    let mut ix = index(d.path());
    ix.pop();
    write_index(d.path(), &ix);
    resize_in_manifest(d.path(), "block_index.bin");
    refused(d.path(), "block_index.bin", &["need 8 per block of 4096"]);
}

/// A flipped byte in the middle of block 1 desynchronizes its range decoder: the block no longer
/// decodes to its 4096 consecutive ids.
#[test]
fn a_flipped_byte_inside_blocks_bin_is_refused() {
    let (d, _) = store();
    let ix = index(d.path());
    let at = ((ix[1] + ix[2]) / 2) as usize;
    edit(&d.path().join("blocks.bin"), |b| b[at] ^= 0x5a);
    refused(
        d.path(),
        "blocks.bin",
        &[&format!("block 1 (nodes {BLOCK}..{})", 2 * BLOCK)],
    );
}

/// Replaces block `b` of the store in `dir` by `nodes` coded with the store's coder (index and
/// manifest sizes kept in step), as a writer with a bug would.
fn recode_block(dir: &Path, b: usize, nodes: &[DetailNode]) {
    let s = Store::open(dir).unwrap();
    let coder = BlockCoder::new(&s.base, &Encoding::F32);
    let ix = index(dir);
    let old = std::fs::read(dir.join("blocks.bin")).unwrap();
    let mut bytes = old[..ix[b] as usize].to_vec();
    bytes.extend(coder.encode(nodes).unwrap().bytes);
    let shift = bytes.len() as i64 - ix[b + 1] as i64;
    bytes.extend(&old[ix[b + 1] as usize..]);
    let mut new = ix.clone();
    for e in &mut new[b + 1..] {
        *e = (*e as i64 + shift) as u64;
    }
    std::fs::write(dir.join("blocks.bin"), bytes).unwrap();
    write_index(dir, &new);
    resize_in_manifest(dir, "blocks.bin");
    rewrite_sums(dir);
}

/// Recomputes `block_sums.bin` from `blocks.bin` and the index (the manifest's CRC of the file
/// left as it was), as a writer with a bug would.
fn rewrite_sums(dir: &Path) {
    let ix = index(dir);
    let blocks = std::fs::read(dir.join("blocks.bin")).unwrap();
    let sums: Vec<u8> = ix
        .windows(2)
        .flat_map(|w| crc32fast::hash(&blocks[w[0] as usize..w[1] as usize]).to_le_bytes())
        .collect();
    std::fs::write(dir.join(BLOCK_SUMS_FILE), sums).unwrap();
}

/// A block that decodes cleanly but to the wrong nodes: a node that lost a coefficient (every later
/// coefficient would land on another vertex in a fixed-width store; here the total disagrees), or
/// another id in place of one of the block's.
#[test]
fn a_block_with_other_nodes_is_refused() {
    let (d, nodes) = store();
    let (b0, b1) = (BLOCK as usize, 2 * BLOCK as usize);
    let mut block: Vec<DetailNode> = nodes[b0..b1].to_vec();
    let k = block.iter().position(|n| n.owned != 0).unwrap();
    block[k].owned &= block[k].owned - 1;
    block[k].coeffs.pop();
    recode_block(d.path(), 1, &block);
    refused(
        d.path(),
        "blocks.bin",
        &[&format!(
            "the blocks own {} coefficients, counts.coefficients is {}",
            nodes.iter().map(|n| n.coeffs.len()).sum::<usize>() - 1,
            nodes.iter().map(|n| n.coeffs.len()).sum::<usize>()
        )],
    );
    let (d, nodes) = store();
    let mut block: Vec<DetailNode> = nodes[b0..b1 - 1].to_vec();
    block.push(nodes[b1].clone());
    recode_block(d.path(), 1, &block);
    refused(
        d.path(),
        "blocks.bin",
        &[
            &format!("block 1 (nodes {b0}..{b1})"),
            &format!("decodes to nodes {b0}..={b1}, not the block's ids"),
        ],
    );
}

#[test]
fn a_truncated_blocks_file_is_refused() {
    let (d, _) = store();
    let path = d.path().join("blocks.bin");
    edit(&path, |b| b.truncate(b.len() - 4));
    refused(d.path(), "blocks.bin", &["manifest says"]);
    // with the manifest edited to the new size, the index still disagrees
    resize_in_manifest(d.path(), "blocks.bin");
    refused(
        d.path(),
        "block_index.bin",
        &["is not the length of blocks.bin"],
    );
}

/// Stores of earlier format versions (1: fixed-width node records; 2: details of the linear
/// predictor) are refused with what to do about it, before their files are looked at.
#[test]
fn an_earlier_version_store_is_refused_with_what_to_do() {
    for old in 1..STORE_VERSION {
        let (d, _) = store();
        let mpath = d.path().join("manifest.json");
        let mut m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
        m["version"] = old.into();
        if old == 1 {
            m["files"]["nodes.bin"] = serde_json::json!({"bytes": 6, "crc32": 0});
        }
        std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
        refused(
            d.path(),
            "manifest.json",
            &[
                &format!("v{old}"),
                &format!("expected tetwave-store v{STORE_VERSION}"),
                "re-run `tetwave-server prepare`",
            ],
        );
    }
}

/// Only the four store files are listed: a manifest naming another path is refused before that
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

/// A flipped byte near the end of the last block changes only the low bits of the last raw f32
/// (lossless stores send the bits raw) and keeps every structural check: its block's checksum
/// (`block_sums.bin`) refuses it at open. With the sums rewritten to match (a writer with a bug),
/// only the whole files' checksums find it, and `verify_checksums` checks them at open.
#[test]
fn checksums_are_checked_at_open_on_request() {
    let (d, _) = store();
    let path = d.path().join("blocks.bin");
    let original = std::fs::read(&path).unwrap();
    let last = index(d.path()).len() - 2;
    let at = original.len() - 2;
    edit(&path, |b| b[at] ^= 0x01);
    refused(
        d.path(),
        "blocks.bin",
        &[&format!("block {last}"), "checksum", BLOCK_SUMS_FILE],
    );
    rewrite_sums(d.path());
    Store::open(d.path()).expect("the structure is intact");
    let e = Store::open_with(
        d.path(),
        OpenOptions {
            verify_checksums: true,
            ..Default::default()
        },
    )
    .err()
    .expect("refused");
    let msg = e.to_string();
    assert!(
        msg.contains("checksum") && (msg.contains("blocks.bin") || msg.contains(BLOCK_SUMS_FILE)),
        "{msg}"
    );
}

/// A store with a preview opens with it: the preview's nodes, coded at its coarse step, with the
/// store's masks; a store without one has none.
#[test]
fn a_preview_reads_back_with_the_stores_masks() {
    let d = tempfile::tempdir().unwrap();
    let step = 0.05;
    let nodes = make_store_full(d.path(), 4, None, Some(step));
    let (_, raw) = detail_nodes(unsampled_base(4, box5([0.0; 3], [1.0; 3])), |p| {
        harmonic_unit(p) as f32
    });
    let s = Store::open(d.path()).unwrap();
    let p = s.manifest.preview.clone().expect("described");
    assert_eq!(p.levels, 3);
    assert!(s.manifest.files.contains_key(PREVIEW_FILE));
    let got = s.preview.as_ref().expect("read");
    assert_eq!(got.len() as u64, s.forest().level_start(3));
    for ((g, n), r) in got.iter().zip(&nodes).zip(&raw) {
        assert_eq!(
            (g.id, g.owned, g.empty_children),
            (n.id, n.owned, n.empty_children)
        );
        for (a, b) in g.coeffs.iter().zip(&n.coeffs) {
            assert!(
                (a - b).abs() <= step / 2.0 + 1e-6,
                "node {}: {a} for {b}",
                g.id
            );
        }
        // no bound travels with a preview: the store's node brings it
        assert_eq!(g.subtree_max_abs, INHERITED_BOUND, "node {}", g.id);
        assert!(r.subtree_max_abs.is_finite());
    }
    // written again without one, the file goes
    make_store(d.path(), 4);
    let s = Store::open(d.path()).unwrap();
    assert!(s.preview.is_none() && s.manifest.preview.is_none());
    assert!(!d.path().join(PREVIEW_FILE).exists());
}

/// A preview that is not the store's coarse nodes, one that is damaged, and a preview file the
/// manifest does not describe (or the other way round) are refused, naming `preview.bin`.
#[test]
fn a_preview_that_does_not_fit_its_store_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let nodes = make_store_full(d.path(), 4, None, Some(0.05));
    let (dir, ppath) = (d.path(), d.path().join(PREVIEW_FILE));
    let good = std::fs::read(&ppath).unwrap();

    // another node's empty children: not the store's masks
    let mut other = preview_of(&nodes, 4, 0.05);
    other.nodes[7].empty_children ^= 0b1000_0000;
    let base = unsampled_base(4, box5([0.0; 3], [1.0; 3]));
    let bytes: Vec<u8> = other
        .nodes
        .chunks(BLOCK as usize)
        .flat_map(|c| {
            let block = BlockCoder::for_preview(&base, &other.preview.encoding)
                .encode(c)
                .unwrap();
            bincode::serde::encode_to_vec(&block, bincode::config::standard()).unwrap()
        })
        .collect();
    std::fs::write(&ppath, &bytes).unwrap();
    resize_in_manifest(dir, PREVIEW_FILE);
    refused(dir, PREVIEW_FILE, &["store's first", "masks"]);

    // cut short
    std::fs::write(&ppath, &good[..good.len() - 3]).unwrap();
    resize_in_manifest(dir, PREVIEW_FILE);
    refused(dir, PREVIEW_FILE, &[]);

    // described, not listed; listed, not described
    std::fs::write(&ppath, &good).unwrap();
    resize_in_manifest(dir, PREVIEW_FILE);
    let mpath = dir.join("manifest.json");
    let text = std::fs::read_to_string(&mpath).unwrap();
    let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
    m["files"].as_object_mut().unwrap().remove(PREVIEW_FILE);
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    refused(dir, PREVIEW_FILE, &["lists no file"]);
    let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
    m.as_object_mut().unwrap().remove("preview");
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    refused(dir, PREVIEW_FILE, &["describes no preview"]);

    // every node level, and a trailing block
    let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
    m["preview"]["levels"] = 4.into();
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    refused(dir, PREVIEW_FILE, &["4 node levels in a hierarchy of 4"]);
    std::fs::write(&mpath, &text).unwrap();
    let mut more = good.clone();
    more.extend_from_slice(&good[..good.len().min(40)]);
    std::fs::write(&ppath, &more).unwrap();
    resize_in_manifest(dir, PREVIEW_FILE);
    refused(dir, PREVIEW_FILE, &["trailing"]);
}
