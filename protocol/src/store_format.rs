//! The on-disk store format, shared by the server (which writes and serves it) and the client (which
//! may read a local store): the manifest's types, the node record and coefficient encodings, and the
//! arithmetic of random access by node-id range. No I/O: readers supply the bytes through
//! [`StoreFiles`].
//!
//! | file              | contents                                                                  |
//! |-------------------|---------------------------------------------------------------------------|
//! | `manifest.json`   | [`Manifest`]                                                              |
//! | `base.bin`        | bincode [`BaseMesh`]                                                      |
//! | `nodes.bin`       | per node 6 bytes: owned mask u8, empty children u8, subtree max |d| f32 LE |
//! | `coeffs.bin`      | owned coefficients, node order then edge order: f32 LE, or quantized codes |
//! |                   | as signed little-endian integers of `ceil(bits/8)` bytes                   |
//! | `coeff_index.bin` | u64 LE per block of [`BLOCK`] nodes: coefficients before the block         |
//! | `reference.f32`   | the sampled value of every vertex (for verification; not streamed)         |

use crate::node::DetailNode;
use crate::wavelet::Quantizer;
use crate::{BaseMesh, TetId};
use serde::{Deserialize, Serialize};

/// Nodes per index block.
pub const BLOCK: u64 = 4096;
/// Bytes per node record in `nodes.bin`.
pub const NODE_RECORD: u64 = 6;
pub const STORE_FORMAT: &str = "tetwave-store";
pub const STORE_VERSION: u32 = 1;
/// Largest `base.bin` a reader accepts.
pub const MAX_BASE_BYTES: usize = 1 << 30;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Counts {
    pub tets_total: u64,
    pub leaves: u64,
    pub nodes: u64,
    pub vertices: u64,
    pub coefficients: u64,
    pub outside_vertices: u64,
    pub empty_base_tets: u64,
}

/// Coefficient encoding. Externally tagged (`"f32"` or `{"quantized": {"bits": …, "step": …}}`) so
/// that it also travels in bincode frames, which cannot decode internally tagged enums.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Encoding {
    F32,
    Quantized { bits: u8, step: f32 },
}

/// Bits a quantized encoding may use (what `tetwave-server prepare --bits` accepts).
pub const QUANTIZED_BITS: std::ops::RangeInclusive<u8> = 8..=24;

impl Encoding {
    /// Checks an encoding read from a manifest: quantized bits in [`QUANTIZED_BITS`] and a finite,
    /// positive step (the decoders assume both).
    pub fn check(&self) -> Result<(), String> {
        match *self {
            Encoding::F32 => Ok(()),
            Encoding::Quantized { bits, step } => {
                if !QUANTIZED_BITS.contains(&bits) {
                    Err(format!(
                        "quantized bits {bits} outside {}..={}",
                        QUANTIZED_BITS.start(),
                        QUANTIZED_BITS.end()
                    ))
                } else if !(step.is_finite() && step > 0.0) {
                    Err(format!("quantization step {step} is not a positive number"))
                } else {
                    Ok(())
                }
            }
        }
    }

    /// Bytes per stored coefficient.
    pub fn width(&self) -> usize {
        match self {
            Encoding::F32 => 4,
            Encoding::Quantized { bits, .. } => (*bits as usize).div_ceil(8),
        }
    }

    pub fn quantizer(&self) -> Option<Quantizer> {
        match *self {
            Encoding::F32 => None,
            Encoding::Quantized { bits, step } => Some(Quantizer { bits, step }),
        }
    }

    /// Bytes of one coefficient (the dequantized value `d` for quantized encodings is re-encoded).
    pub fn encode(&self, d: f32, out: &mut Vec<u8>) {
        match self.quantizer() {
            None => out.extend_from_slice(&d.to_le_bytes()),
            Some(q) => out.extend_from_slice(&q.encode(d).to_le_bytes()[..self.width()]),
        }
    }

    /// One coefficient from `width()` bytes.
    pub fn decode(&self, c: &[u8]) -> f32 {
        match self.quantizer() {
            None => f32::from_le_bytes([c[0], c[1], c[2], c[3]]),
            Some(q) => {
                let mut b = [0u8; 4];
                b[..c.len()].copy_from_slice(c);
                // sign-extend from width bytes
                let shift = 32 - 8 * c.len() as u32;
                q.decode((i32::from_le_bytes(b) << shift) >> shift)
            }
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileSum {
    pub bytes: u64,
    pub crc32: u32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub version: u32,
    pub dataset: String,
    pub source: String,
    pub bounds: [[f64; 3]; 2],
    pub base: String,
    pub base_tets: u64,
    pub base_vertices: u64,
    pub levels: u8,
    pub value_range: [f32; 2],
    pub counts: Counts,
    pub encoding: Encoding,
    /// Max |synthesis − sample| the store promises (verify fails beyond it).
    pub max_error_bound: f64,
    /// Max |synthesis − sample| measured when the store was written.
    pub max_abs_error: f64,
    pub files: std::collections::BTreeMap<String, FileSum>,
}

/// A node's 6-byte record.
pub fn encode_node_record(owned: u8, empty_children: u8, subtree_max_abs: f32) -> [u8; 6] {
    let mut rec = [0u8; 6];
    rec[0] = owned;
    rec[1] = empty_children;
    rec[2..6].copy_from_slice(&subtree_max_abs.to_le_bytes());
    rec
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FormatError {
    #[error(
        "not a tetwave store: format {format} v{version}, expected {STORE_FORMAT} v{STORE_VERSION}"
    )]
    Version { format: String, version: u32 },
    #[error("base.bin: {0}")]
    Base(String),
    #[error("{0}")]
    Inconsistent(String),
    #[error("node range {from}..{to} is outside 0..{nodes}")]
    RangeOutOfBounds { from: u64, to: u64, nodes: u64 },
    #[error("nodes.bin: {0}")]
    BadNode(String),
}

/// Random-access reads of a store's files (a directory, an HTTP range source, a test double).
pub trait StoreFiles {
    type Error: From<FormatError>;
    /// Fills `buf` from `file` at `offset` (exactly, or an error).
    fn read_at(&self, file: &str, offset: u64, buf: &mut [u8]) -> Result<(), Self::Error>;
}

/// The parts of a store a reader keeps in memory.
#[derive(Debug, Clone)]
pub struct StoreHead {
    pub manifest: Manifest,
    pub base: BaseMesh,
    /// Coefficients before each block of [`BLOCK`] nodes.
    pub index: Vec<u64>,
}

impl StoreHead {
    /// Checks and decodes a store's manifest, `base.bin` and `coeff_index.bin`.
    pub fn decode(
        manifest: Manifest,
        base_bytes: &[u8],
        index_bytes: &[u8],
    ) -> Result<Self, FormatError> {
        if manifest.format != STORE_FORMAT || manifest.version != STORE_VERSION {
            return Err(FormatError::Version {
                format: manifest.format,
                version: manifest.version,
            });
        }
        if base_bytes.len() > MAX_BASE_BYTES {
            return Err(FormatError::Base(format!(
                "{} bytes exceeds the {MAX_BASE_BYTES}-byte limit",
                base_bytes.len()
            )));
        }
        let cfg = bincode::config::standard().with_limit::<MAX_BASE_BYTES>();
        let (base, _): (BaseMesh, usize) = bincode::serde::decode_from_slice(base_bytes, cfg)
            .map_err(|e| FormatError::Base(e.to_string()))?;
        base.validate()
            .map_err(|e| FormatError::Base(e.to_string()))?;
        manifest
            .encoding
            .check()
            .map_err(|e| FormatError::Inconsistent(format!("manifest.json: {e}")))?;
        let forest = base.forest();
        let nodes = forest.checked_nodes().ok_or_else(|| {
            FormatError::Base(format!(
                "{} tets refined {} times: the node count does not fit in 64 bits",
                forest.n_base, forest.levels
            ))
        })?;
        if base.levels != manifest.levels || nodes != manifest.counts.nodes {
            return Err(FormatError::Inconsistent(
                "base mesh disagrees with the manifest".into(),
            ));
        }
        if !index_bytes.len().is_multiple_of(8)
            || (index_bytes.len() / 8) as u64 != nodes.div_ceil(BLOCK)
        {
            return Err(FormatError::Inconsistent(
                "coeff_index.bin size disagrees with the node count".into(),
            ));
        }
        let index = index_bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect();
        Ok(StoreHead {
            manifest,
            base,
            index,
        })
    }

    /// Nodes `from..to`: reads one block's worth of records before `from` at most, the range's records
    /// and its coefficients.
    pub fn read_nodes<F: StoreFiles>(
        &self,
        files: &F,
        from: TetId,
        to: TetId,
    ) -> Result<Vec<DetailNode>, F::Error> {
        let nodes = self.manifest.counts.nodes;
        if from > to || to > nodes {
            return Err(FormatError::RangeOutOfBounds { from, to, nodes }.into());
        }
        if from == to {
            return Ok(Vec::new());
        }
        // offsets and lengths in checked arithmetic: the index comes from a file, and a wrapped
        // product would read another node's coefficients
        let overflow = |what: &str| FormatError::Inconsistent(format!("{what} overflows"));
        let block = from / BLOCK;
        let block_start = block * BLOCK;
        let recs_len = (to - block_start)
            .checked_mul(NODE_RECORD)
            .and_then(|n| usize::try_from(n).ok())
            .ok_or_else(|| overflow("nodes.bin: the range's length"))?;
        let mut recs = vec![0u8; recs_len];
        let recs_at = block_start
            .checked_mul(NODE_RECORD)
            .ok_or_else(|| overflow("nodes.bin: the range's offset"))?;
        files.read_at("nodes.bin", recs_at, &mut recs)?;
        let skip = ((from - block_start) * NODE_RECORD) as usize;
        let entry = *self.index.get(block as usize).ok_or_else(|| {
            FormatError::Inconsistent(format!("coeff_index.bin: no entry for block {block}"))
        })?;
        let coeff_at = entry
            .checked_add(
                recs[..skip]
                    .chunks_exact(6)
                    .map(|r| r[0].count_ones() as u64)
                    .sum::<u64>(),
            )
            .ok_or_else(|| overflow("coeff_index.bin: a coefficient offset"))?;
        let recs = &recs[skip..];
        let count: u64 = recs.chunks_exact(6).map(|r| r[0].count_ones() as u64).sum();
        let enc = &self.manifest.encoding;
        let width = enc.width() as u64;
        let cb_len = count
            .checked_mul(width)
            .and_then(|n| usize::try_from(n).ok())
            .ok_or_else(|| overflow("coeffs.bin: the range's length"))?;
        let mut cb = vec![0u8; cb_len];
        let cb_at = coeff_at
            .checked_mul(width)
            .ok_or_else(|| overflow("coeffs.bin: the range's offset"))?;
        files.read_at("coeffs.bin", cb_at, &mut cb)?;
        let mut coeffs = cb.chunks_exact(width as usize).map(|c| enc.decode(c));
        let mut out = Vec::with_capacity((to - from) as usize);
        for (j, r) in recs.chunks_exact(6).enumerate() {
            let owned = r[0];
            let node = DetailNode {
                id: from + j as u64,
                owned,
                empty_children: r[1],
                subtree_max_abs: f32::from_le_bytes([r[2], r[3], r[4], r[5]]),
                coeffs: coeffs.by_ref().take(owned.count_ones() as usize).collect(),
            };
            node.validate()
                .map_err(|e| FormatError::BadNode(e.to_string()))?;
            out.push(node);
        }
        Ok(out)
    }
}
