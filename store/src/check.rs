//! The structural checks [`Store::open`](crate::Store::open) runs: cheap (one pass over the node
//! records, no coefficient read), and enough that a read by node range can neither wrap an offset
//! nor land on another node's coefficients.
//!
//! - the counts of the manifest agree with the base mesh's hierarchy (tets, leaves, vertices);
//! - each file's size on disk is what the counts need (`nodes.bin` 6 bytes a node, `coeffs.bin`
//!   the coefficient width per coefficient, `reference.f32` 4 bytes a vertex), in checked
//!   arithmetic;
//! - `coeff_index.bin` starts at 0, never decreases and stays within the coefficient count;
//! - every owned mask of `nodes.bin` names edges only (6 bits), every subtree max |d| is finite,
//!   and the masks of each block of [`BLOCK`] nodes own exactly the coefficients the index puts
//!   between that block and the next (the last block: up to the manifest's coefficient count).
//!
//! A mask changed so that the count stays the same (a bit moved inside one block) passes; it is
//! refused when the node is read (a vertex owned twice) or by `verify`'s checksums.

use crate::{io_err, StoreError};
use std::io::{BufReader, Read};
use std::path::Path;
use tetwave_protocol::store_format::{StoreHead, BLOCK, NODE_RECORD};

fn corrupt(dir: &Path, file: &str, reason: String) -> StoreError {
    StoreError::Corrupt {
        path: dir.join(file),
        reason,
    }
}

/// Size on disk of `file`, or `None` when it is absent.
fn size_of(dir: &Path, file: &str) -> Result<Option<u64>, StoreError> {
    let p = dir.join(file);
    match std::fs::metadata(&p) {
        Ok(m) => Ok(Some(m.len())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io_err(&p)(e)),
    }
}

/// `file` must exist and hold `count` items of `width` bytes.
fn expect_size(
    dir: &Path,
    file: &str,
    count: u64,
    width: u64,
    what: &str,
) -> Result<(), StoreError> {
    let want = count.checked_mul(width).ok_or_else(|| {
        corrupt(
            dir,
            file,
            format!("{count} {what} of {width} bytes overflow a file size"),
        )
    })?;
    let Some(len) = size_of(dir, file)? else {
        let p = dir.join(file);
        return Err(io_err(&p)(std::io::ErrorKind::NotFound.into()));
    };
    if len != want {
        return Err(corrupt(
            dir,
            file,
            format!("{len} bytes, the manifest's {count} {what} of {width} bytes need {want}"),
        ));
    }
    Ok(())
}

/// Runs every check of the module docs on an open store's head and files.
pub(crate) fn structure(dir: &Path, head: &StoreHead) -> Result<(), StoreError> {
    let m = &head.manifest;
    let base = &head.base;
    let forest = base.forest();
    let mpath = "manifest.json";
    // counts (the node count and the levels were compared by StoreHead::decode)
    if m.base_tets != base.tets.len() as u64 || m.base_vertices != base.positions.len() as u64 {
        return Err(corrupt(
            dir,
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
            dir,
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
                dir,
                mpath,
                format!("counts.{what} is {got}, the base mesh's hierarchy has {want}"),
            ));
        }
    }
    let coefficients = m.counts.coefficients;
    if coefficients > vertices {
        return Err(corrupt(
            dir,
            mpath,
            format!("counts.coefficients {coefficients} exceeds the {vertices} vertices"),
        ));
    }
    // file sizes
    let nodes = m.counts.nodes;
    expect_size(dir, "nodes.bin", nodes, NODE_RECORD, "nodes")?;
    let width = m.encoding.width() as u64;
    expect_size(dir, "coeffs.bin", coefficients, width, "coefficients")?;
    if size_of(dir, "reference.f32")?.is_some() || m.files.contains_key("reference.f32") {
        expect_size(dir, "reference.f32", vertices, 4, "vertices")?;
    }
    // the index
    let ipath = "coeff_index.bin";
    let index = &head.index;
    if let Some(&first) = index.first() {
        if first != 0 {
            return Err(corrupt(
                dir,
                ipath,
                format!("entry 0 is {first}, the first block starts at coefficient 0"),
            ));
        }
    }
    for (i, w) in index.windows(2).enumerate() {
        if w[1] < w[0] {
            return Err(corrupt(
                dir,
                ipath,
                format!("entry {} ({}) is below entry {i} ({})", i + 1, w[1], w[0]),
            ));
        }
    }
    if let Some(&last) = index.last() {
        if last > coefficients {
            return Err(corrupt(
                dir,
                ipath,
                format!(
                    "entry {} ({last}) is beyond the manifest's {coefficients} coefficients",
                    index.len() - 1
                ),
            ));
        }
    }
    if index.is_empty() && coefficients != 0 {
        return Err(corrupt(
            dir,
            mpath,
            format!("counts.coefficients is {coefficients}, a hierarchy without nodes has none"),
        ));
    }
    // the node records, one block at a time
    let npath = dir.join("nodes.bin");
    let file = std::fs::File::open(&npath).map_err(io_err(&npath))?;
    let mut r = BufReader::with_capacity(1 << 20, file);
    let mut recs = vec![0u8; (BLOCK * NODE_RECORD) as usize];
    for (b, &before) in index.iter().enumerate() {
        let start = b as u64 * BLOCK;
        let end = (start + BLOCK).min(nodes);
        let recs = &mut recs[..((end - start) * NODE_RECORD) as usize];
        r.read_exact(recs).map_err(io_err(&npath))?;
        let mut owned = 0u64;
        for (j, rec) in recs.chunks_exact(NODE_RECORD as usize).enumerate() {
            let id = start + j as u64;
            if rec[0] & !0x3f != 0 {
                return Err(corrupt(
                    dir,
                    "nodes.bin",
                    format!(
                        "node {id}: owned mask {:#04x} has bits beyond the 6 edges",
                        rec[0]
                    ),
                ));
            }
            let smax = f32::from_le_bytes([rec[2], rec[3], rec[4], rec[5]]);
            if !smax.is_finite() {
                return Err(corrupt(
                    dir,
                    "nodes.bin",
                    format!("node {id}: subtree max |d| {smax} is not finite"),
                ));
            }
            owned += rec[0].count_ones() as u64;
        }
        let (next, said) = match index.get(b + 1) {
            Some(&n) => (n, format!("coeff_index.bin entries {b} and {}", b + 1)),
            None => (
                coefficients,
                format!("coeff_index.bin entry {b} and the manifest's coefficient count"),
            ),
        };
        // before ≤ next: the index is monotone and within the count
        if owned != next - before {
            return Err(corrupt(
                dir,
                "nodes.bin",
                format!(
                    "the owned masks of nodes {start}..{end} own {owned} coefficients, {said} give {}",
                    next - before
                ),
            ));
        }
    }
    Ok(())
}
