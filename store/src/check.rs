//! The structural checks [`Store::open`](crate::Store::open) runs: one pass decoding every block
//! of `blocks.bin`, enough that a read by node range can neither read past a file nor return
//! another block's nodes.
//!
//! - the counts of the manifest agree with the base mesh's hierarchy (tets, leaves, vertices);
//! - `block_index.bin` has `nblocks + 1` entries, starts at 0 and never decreases (checked by
//!   [`StoreHead::decode`]), and its last entry is `blocks.bin`'s length;
//! - `reference.f32` holds 4 bytes a vertex when present, and so does `levelset.f32` when the manifest lists it
//!   (with `levelset_near.bin`: one without the other is refused, but for a box domain's band);
//! - every block decodes to exactly its node count, its ids in order, each node valid with a finite
//!   subtree bound (the finest node level has none: its parent's stands in), and the blocks together own the manifest's coefficient count.
//!
//! A flipped byte inside a block usually fails to decode (or decodes to the wrong count); one that
//! still decodes to plausible nodes is found by `verify`'s checksums.

use crate::location::Files;
use crate::{io_err, StoreError};
use tetwave_protocol::store_format::{FormatError, StoreHead, LEVELSET_BAND_FILE};
use tetwave_protocol::DetailNode;

fn corrupt(files: &Files, file: &str, reason: String) -> StoreError {
    StoreError::Corrupt {
        path: files.name(file),
        reason,
    }
}

/// `file` must exist and hold `count` items of `width` bytes.
fn expect_size(
    files: &Files,
    file: &str,
    count: u64,
    width: u64,
    what: &str,
) -> Result<(), StoreError> {
    let want = count.checked_mul(width).ok_or_else(|| {
        corrupt(
            files,
            file,
            format!("{count} {what} of {width} bytes overflow a file size"),
        )
    })?;
    let Some(len) = files.size(file)? else {
        let p = files.name(file);
        return Err(io_err(&p)(std::io::ErrorKind::NotFound.into()));
    };
    if len != want {
        return Err(corrupt(
            files,
            file,
            format!("{len} bytes, the manifest's {count} {what} of {width} bytes need {want}"),
        ));
    }
    Ok(())
}

/// Runs every check of the module docs on an open store's head and files, handing each decoded
/// block's nodes to `visit` (in id order).
pub(crate) fn structure(
    files: &Files,
    head: &StoreHead,
    visit: &mut dyn FnMut(Vec<DetailNode>),
) -> Result<(), StoreError> {
    let m = &head.manifest;
    let base = &head.base;
    let forest = base.forest();
    let mpath = "manifest.json";
    // counts (the node count and the levels were compared by StoreHead::decode)
    if m.base_tets != base.tets.len() as u64 || m.base_vertices != base.positions.len() as u64 {
        return Err(corrupt(
            files,
            mpath,
            format!(
                "base_tets {} and base_vertices {} disagree with base.bin's {} tets and {} vertices",
                m.base_tets,
                m.base_vertices,
                base.tets.len(),
                base.positions.len()
            ),
        ));
    }
    let total = forest.checked_total_tets().ok_or_else(|| {
        corrupt(
            files,
            "base.bin",
            format!(
                "{} tets refined {} times: the tet count does not fit in 64 bits",
                forest.n_base, forest.levels
            ),
        )
    })?;
    // leaves ≤ total and vertices < total + base vertices: neither overflows now
    let vertices = base.vertex_keys().vertex_count();
    for (what, got, want) in [
        ("tets_total", m.counts.tets_total, total),
        ("leaves", m.counts.leaves, forest.leaves()),
        ("vertices", m.counts.vertices, vertices),
    ] {
        if got != want {
            return Err(corrupt(
                files,
                mpath,
                format!("counts.{what} is {got}, the base mesh's hierarchy has {want}"),
            ));
        }
    }
    let coefficients = m.counts.coefficients;
    if coefficients > vertices {
        return Err(corrupt(
            files,
            mpath,
            format!("counts.coefficients {coefficients} exceeds the {vertices} vertices"),
        ));
    }
    // file sizes
    if files.size("reference.f32")?.is_some() || m.files.contains_key("reference.f32") {
        expect_size(files, "reference.f32", vertices, 4, "vertices")?;
    }
    if m.files.contains_key("levelset.f32") {
        expect_size(files, "levelset.f32", vertices, 4, "vertices")?;
    }
    // a level set and its near band go together (clients clip with the band, renderers with the
    // whole set: they must describe the same domain), except a box domain's band, from which
    // every reader computes the level set
    let whole = m.files.contains_key("levelset.f32");
    if whole != m.has_levelset_band() {
        let box_alone = !whole
            && files
                .read(LEVELSET_BAND_FILE)
                .is_ok_and(|b| b.len() == 56 && b[..8] == [0xff; 8]);
        if !box_alone {
            return Err(corrupt(
                files,
                mpath,
                "the manifest lists one of levelset.f32 and levelset_near.bin without the other \
                 (only a box domain's band stands alone)"
                    .into(),
            ));
        }
    }
    let bpath = files.name("blocks.bin");
    let Some(len) = files.size("blocks.bin")? else {
        return Err(io_err(&bpath)(std::io::ErrorKind::NotFound.into()));
    };
    let index = &head.index;
    let last = *index.last().expect("decode checked nblocks + 1 entries");
    if last != len {
        return Err(corrupt(
            files,
            "block_index.bin",
            format!(
                "entry {} ({last}) is not the length of blocks.bin ({len} bytes)",
                index.len() - 1
            ),
        ));
    }
    // every block, in order, read some 8 MiB at a time
    let mut owned = 0u64;
    let mut batch = Vec::new();
    let mut batch_start = 0;
    for b in 0..head.blocks() {
        if b >= batch_start + (batch.len() as u64) {
            let mut end = b + 1;
            while end < head.blocks() && index[end as usize + 1] - index[b as usize] < 8 << 20 {
                end += 1;
            }
            let ranges: Vec<_> = (b..end)
                .map(|k| index[k as usize]..index[k as usize + 1])
                .collect();
            batch = files.read_ranges("blocks.bin", &ranges)?;
            batch_start = b;
        }
        let buf = std::mem::take(&mut batch[(b - batch_start) as usize]);
        let nodes = head.decode_block(b, &buf).map_err(|e| match e {
            FormatError::BadBlock {
                block,
                from,
                to,
                reason,
            } => corrupt(
                files,
                "blocks.bin",
                format!("block {block} (nodes {from}..{to}): {reason}"),
            ),
            other => StoreError::Format {
                path: files.name(""),
                source: other,
            },
        })?;
        owned += nodes.iter().map(|n| n.coeffs.len() as u64).sum::<u64>();
        visit(nodes);
    }
    if owned != coefficients {
        return Err(corrupt(
            files,
            "blocks.bin",
            format!("the blocks own {owned} coefficients, counts.coefficients is {coefficients}"),
        ));
    }
    Ok(())
}
