//! The on-disk store format, shared by the server (which writes and serves it) and the client (which
//! may read a local store): the manifest's types, the coefficient encodings, and random access by
//! node-id range over coded blocks. No I/O: readers supply the bytes through [`StoreFiles`].
//!
//! | file              | contents                                                                  |
//! |-------------------|---------------------------------------------------------------------------|
//! | `manifest.json`   | [`Manifest`]                                                              |
//! | `base.bin`        | bincode [`BaseMesh`]                                                      |
//! | `blocks.bin`      | per block of [`BLOCK`] consecutive ids, the bytes of a [`NodeBlock`]:     |
//! |                   | [`BlockCoder::encode`] of those nodes, concatenated                        |
//! | `block_index.bin` | u64 LE byte offset of each block in `blocks.bin`, then its length         |
//! | `block_sums.bin`  | u32 LE CRC-32 of each block's bytes ([`BLOCK_SUMS_FILE`])                  |
//! | `reference.f32`   | the sampled value of every vertex (for verification; not streamed)         |
//!
//! Block `b` holds ids `b·BLOCK .. min((b+1)·BLOCK, nodes)`: its node count and first id are
//! implied, so a block on disk is only the range coder's bytes, exactly what a `Nodes` frame would
//! carry for that id range. Reading nodes `a..b` reads the index entries of the covering blocks
//! (held in memory), the blocks' bytes (one contiguous read) and decodes them.

use crate::block::{BlockCoder, NodeBlock};
use crate::node::DetailNode;
use crate::wavelet::{LevelSteps, Quantizer};
use crate::{BaseMesh, TetId};
use serde::{Deserialize, Serialize};

/// Nodes per coded block of `blocks.bin`: small enough that reading one node costs little more
/// than decoding 4096 (a few kilobytes read, well under a millisecond), large enough that the
/// adaptive models of a block learn its statistics and an index entry (8 bytes) is negligible.
pub const BLOCK: u64 = 4096;
/// Most bytes one block of `blocks.bin` may take: far beyond what [`BlockCoder::encode`] writes for
/// [`BLOCK`] nodes (a lossless node takes at most about 33 bytes), and a bound on what one block's
/// read allocates whatever the index says.
pub const MAX_BLOCK_BYTES: u64 = BLOCK * 512;
pub const STORE_FORMAT: &str = "tetwave-store";
/// 9: each block's CRC-32 in `block_sums.bin` ([`BLOCK_SUMS_FILE`]), checked whenever a block is
/// read; 8: a base mesh that is a named box is written as its two corners ([`crate::BaseMesh`]);
/// 7: no subtree bound on the finest node level (its parent's stands in), ids as runs and jumps
/// by sibling group ([`crate::block`]), level steps ([`LevelSteps`]); 6: the base mesh names its
/// predictor; 5: base positions as f32 where that is exact ([`crate::BaseMesh`]), quantized
/// codes' signs modelled ([`crate::block`]); 4: lossless coefficients coded (sign, exponent, significant mantissa bits) and lossless subtree
/// bounds as powers of two; 3: details of the quadratic predictor, one subtree bound per sibling
/// group; 2: coded blocks (`blocks.bin`, `block_index.bin`); 1: fixed-width records (`nodes.bin`,
/// `coeffs.bin`, `coeff_index.bin`). Only the current version is read.
pub const STORE_VERSION: u32 = 9;
/// Each block's CRC-32 (IEEE, as `crc32fast` computes it) as u32 LE, `nblocks` entries: a reader
/// that fetches one block by range (from object storage) checks it alone, so that a flipped byte
/// is refused, never decoded into other values.
pub const BLOCK_SUMS_FILE: &str = "block_sums.bin";
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

/// Coefficient encoding. Externally tagged (`"f32"` or `{"quantized": {"bits": …, "step": …,
/// "levels": {"ratio": …, "cap": …}}}`) so that it also travels in bincode frames, which cannot
/// decode internally tagged enums. `step` is the finest level's; `levels` says how coarser levels'
/// steps shrink ([`LevelSteps`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Encoding {
    F32,
    Quantized {
        bits: u8,
        step: f32,
        /// One step everywhere when a manifest omits it.
        #[serde(default)]
        levels: LevelSteps,
    },
}

/// Bits a quantized encoding may use (what `tetwave-server prepare --bits` accepts).
pub const QUANTIZED_BITS: std::ops::RangeInclusive<u8> = 8..=24;

impl Encoding {
    /// Checks an encoding read from a manifest: quantized bits in [`QUANTIZED_BITS`] and a finite,
    /// positive step (the decoders assume both).
    pub fn check(&self) -> Result<(), String> {
        match *self {
            Encoding::F32 => Ok(()),
            Encoding::Quantized { bits, step, levels } => {
                if !QUANTIZED_BITS.contains(&bits) {
                    Err(format!(
                        "quantized bits {bits} outside {}..={}",
                        QUANTIZED_BITS.start(),
                        QUANTIZED_BITS.end()
                    ))
                } else if !(step.is_finite() && step > 0.0) {
                    Err(format!("quantization step {step} is not a positive number"))
                } else {
                    levels.check()
                }
            }
        }
    }

    /// The encoding of details quantized with `quantizer` (the finest level's, and how coarser
    /// levels' steps shrink), or lossless f32 without one.
    pub fn of(quantizer: Option<(Quantizer, LevelSteps)>) -> Self {
        match quantizer {
            None => Encoding::F32,
            Some((q, levels)) => Encoding::Quantized {
                bits: q.bits,
                step: q.step,
                levels,
            },
        }
    }

    /// A quantized encoding with one step for every level.
    pub fn uniform(bits: u8, step: f32) -> Self {
        Encoding::Quantized {
            bits,
            step,
            levels: LevelSteps::UNIFORM,
        }
    }

    /// The finest level's quantizer and how coarser levels' steps shrink.
    pub fn quantizer(&self) -> Option<(Quantizer, LevelSteps)> {
        match *self {
            Encoding::F32 => None,
            Encoding::Quantized { bits, step, levels } => Some((Quantizer { bits, step }, levels)),
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
    /// The range of the resampled samples inside the domain.
    pub value_range: [f32; 2],
    /// The range of the chosen scalar over the input as the importer reads it (a mesh's points,
    /// a raw grid's samples), when `prepare` knew it: at least as wide as `value_range`, since the
    /// samples interpolate that scalar. Stores written before it was recorded have none.
    #[serde(default)]
    pub source_value_range: Option<[f32; 2]>,
    pub counts: Counts,
    pub encoding: Encoding,
    /// Max |synthesis − sample| the store promises (verify fails beyond it).
    pub max_error_bound: f64,
    /// Max |synthesis − sample| measured when the store was written.
    pub max_abs_error: f64,
    pub files: std::collections::BTreeMap<String, FileSum>,
    /// A coarse copy of the coarse levels' nodes (`preview.bin`), which a server sends a new
    /// session first so that a thin link shows a whole volume early; `None` without one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preview: Option<Preview>,
    /// How the finest vertices inside the domain spread over the display value range
    /// ([`Manifest::display_value_range`]), each weighed by the volume it stands for (its home
    /// base tet's, in units of the smallest base tet's, rounded): [`HISTOGRAM_BINS`] equal bins
    /// (values outside the range in the end bins). What a renderer fits its default transfer function to
    /// (`--tf auto`); `None` in stores written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value_histogram: Option<Vec<u64>>,
    /// Where the store's lattice lies in the file's world and in which units, for a store
    /// prepared from a volume file that states them (NIfTI, NRRD, DICOM, ...); `None` otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub physical: Option<Physical>,
}

/// A volume file's world as a store keeps it: the store's coordinates are the file's world
/// coordinates less `origin` (its lattice starts at 0 on the lowest-corner voxel), along the same
/// axes and in the same length unit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Physical {
    /// World position of the store's coordinate origin.
    pub origin: [f64; 3],
    /// The world frame when the file states one: `RAS` (NIfTI: +x right, +y anterior, +z
    /// superior) or `LPS` (DICOM, NRRD: +x left, +y posterior, +z superior).
    pub frame: Option<String>,
    /// Unit of the coordinates (`mm`, `um`, ...).
    pub length_unit: Option<String>,
    /// Unit of the values (`HU`, ...).
    pub value_unit: Option<String>,
}

impl Physical {
    /// The anatomical letter of world direction `sign`·axis `axis` in [`Self::frame`] (`R`,
    /// `L`, `A`, `P`, `S`, `I`), when the frame is a known one.
    pub fn direction_letter(&self, axis: usize, positive: bool) -> Option<char> {
        let plus = match self.frame.as_deref()? {
            "RAS" => ['R', 'A', 'S'],
            "LPS" => ['L', 'P', 'S'],
            _ => return None,
        };
        let opposite = |c: char| match c {
            'R' => 'L',
            'L' => 'R',
            'A' => 'P',
            'P' => 'A',
            'S' => 'I',
            _ => 'S',
        };
        let c = *plus.get(axis)?;
        Some(if positive { c } else { opposite(c) })
    }

    /// The label of a direction `d` (world axes) as radiology viewers write it: the letters of
    /// its components larger than a third of its length, largest first (`R`, `RA`, `SLP`);
    /// `None` without a known frame or for a zero vector.
    pub fn direction_label(&self, d: [f64; 3]) -> Option<String> {
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if len.is_nan() || len <= 0.0 {
            return None;
        }
        let mut axes = [0usize, 1, 2];
        axes.sort_by(|&a, &b| d[b].abs().total_cmp(&d[a].abs()));
        let mut label = String::new();
        for a in axes {
            if d[a].abs() > len / 3.0 {
                label.push(self.direction_letter(a, d[a] > 0.0)?);
            }
        }
        Some(label)
    }
}

/// Bins of [`Manifest::value_histogram`].
pub const HISTOGRAM_BINS: usize = 256;

/// `values` weighed into [`HISTOGRAM_BINS`] equal bins of `range` (values outside it in the end
/// bins): value `k` adds `weight(k)` (0: left out, e.g. outside the domain); non-finite values are
/// left out.
pub fn value_histogram(values: &[f32], range: [f32; 2], weight: impl Fn(usize) -> u64) -> Vec<u64> {
    let n = HISTOGRAM_BINS;
    let mut counts = vec![0u64; n];
    let (lo, hi) = (range[0] as f64, range[1] as f64);
    for (k, &v) in values.iter().enumerate() {
        let w = weight(k);
        if !v.is_finite() || w == 0 {
            continue;
        }
        let s = if hi > lo {
            (v as f64 - lo) / (hi - lo)
        } else {
            0.5
        };
        counts[((s * n as f64).floor().max(0.0) as usize).min(n - 1)] += w;
    }
    counts
}

/// The store file holding the preview's nodes ([`Preview`]).
pub const PREVIEW_FILE: &str = "preview.bin";

/// What `preview.bin` holds: nodes `0..level_start(levels)` (the node levels below `levels`) of
/// a second closed-loop analysis of the same samples at the coarse bound `max_error_bound`,
/// coded with `encoding` in blocks of [`BLOCK`] nodes (each a bincode `NodeBlock`, one after the
/// other, by [`crate::block::BlockCoder::for_preview`]: no subtree bounds, which decode as
/// inherited). Their owned masks and empty children are the store's. A client holds a preview
/// node until the store's own arrives and replaces it: values from preview nodes alone are within
/// `max_error_bound` of the samples, those from a mix of both approximate (a store node's detail
/// was computed against the store's values of its stencil, not the preview's), and those from
/// the store's nodes alone within the store's bound.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Preview {
    pub encoding: Encoding,
    pub levels: u8,
    pub max_error_bound: f64,
}

/// Most nodes a preview may hold: a reader decodes it whole.
pub const MAX_PREVIEW_NODES: u64 = 1 << 20;

impl Preview {
    /// Checks a preview described for a hierarchy of `levels` levels of `n_base` base tets: some
    /// node levels but not all (`1 ≤ levels < hierarchy levels`), at most [`MAX_PREVIEW_NODES`]
    /// nodes, a readable encoding and a finite bound. Returns its node count.
    pub fn check_for(&self, n_base: u64, levels: u8) -> Result<u64, String> {
        self.check(levels)?;
        crate::Forest { n_base, levels }
            .checked_level_start(self.levels)
            .filter(|&n| n <= MAX_PREVIEW_NODES)
            .ok_or_else(|| {
                format!(
                    "a preview of {} levels of {n_base} base tets holds more than {MAX_PREVIEW_NODES} nodes",
                    self.levels
                )
            })
    }

    /// [`Self::check_for`] without the node count (a base mesh not known yet).
    pub fn check(&self, levels: u8) -> Result<(), String> {
        if !(1..levels).contains(&self.levels) {
            return Err(format!(
                "a preview of {} node levels in a hierarchy of {levels}",
                self.levels
            ));
        }
        if !(self.max_error_bound.is_finite() && self.max_error_bound >= 0.0) {
            return Err(format!("preview bound {}", self.max_error_bound));
        }
        self.encoding.check().map_err(|e| format!("preview: {e}"))
    }
}

/// The store file holding a level set's near band ([`crate::levelset::NearLevelSet`]), which
/// `/v1/levelset` serves.
pub const LEVELSET_BAND_FILE: &str = "levelset_near.bin";

impl Manifest {
    /// The name a legend gives the values: the dataset, and the values' unit when the store
    /// has one (`ct (HU)`).
    pub fn legend_name(&self) -> String {
        match self.physical.as_ref().and_then(|p| p.value_unit.as_deref()) {
            Some(u) if !u.is_empty() => format!("{} ({u})", self.dataset),
            _ => self.dataset.clone(),
        }
    }

    /// Whether the store has a level set's near band for streaming clients to clip with.
    pub fn has_levelset_band(&self) -> bool {
        self.files.contains_key(LEVELSET_BAND_FILE)
    }

    /// The value range a renderer maps to the transfer function by default: the input's
    /// ([`Manifest::source_value_range`]) when recorded, so that a store and the file it was
    /// prepared from frame the same default view, else the samples' ([`Manifest::value_range`]).
    pub fn display_value_range(&self) -> [f32; 2] {
        self.source_value_range
            .filter(|[lo, hi]| lo.is_finite() && hi.is_finite() && lo <= hi)
            .unwrap_or(self.value_range)
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FormatError {
    #[error(
        "not a tetwave store of this version: format {format} v{version}, expected \
         {STORE_FORMAT} v{STORE_VERSION}; re-run `tetwave-server prepare` to write it again"
    )]
    Version { format: String, version: u32 },
    #[error("base.bin: {0}")]
    Base(String),
    #[error("{0}")]
    Inconsistent(String),
    #[error("node range {from}..{to} is outside 0..{nodes}")]
    RangeOutOfBounds { from: u64, to: u64, nodes: u64 },
    #[error("block_index.bin: {0}")]
    BadIndex(String),
    #[error("blocks.bin: block {block} (nodes {from}..{to}): {reason}")]
    BadBlock {
        block: u64,
        from: TetId,
        to: TetId,
        reason: String,
    },
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
    /// Byte offset of each block in `blocks.bin`, then its length: `nblocks + 1` entries, the first
    /// 0, never decreasing (checked by [`StoreHead::decode`]).
    pub index: Vec<u64>,
    /// Decodes the blocks (built once from the base mesh and the encoding).
    pub coder: BlockCoder,
    /// Each block's CRC-32 ([`BLOCK_SUMS_FILE`]), once a reader has given them
    /// ([`Self::with_sums`]): [`Self::decode_block`] then checks every block against its sum.
    pub sums: Option<Vec<u32>>,
}

impl StoreHead {
    /// Checks and decodes a store's manifest, `base.bin` and `block_index.bin`. Whether the index's
    /// last entry is `blocks.bin`'s length is the reader's to check (it knows the file).
    pub fn decode(
        manifest: Manifest,
        base_bytes: &[u8],
        index_bytes: &[u8],
    ) -> Result<Self, FormatError> {
        let base = Self::decode_base(&manifest, base_bytes)?;
        let nodes = manifest.counts.nodes;
        let entries = nodes.div_ceil(BLOCK) + 1;
        if !index_bytes.len().is_multiple_of(8) || (index_bytes.len() / 8) as u64 != entries {
            return Err(FormatError::BadIndex(format!(
                "{} bytes, the {nodes} nodes need {entries} entries of 8 bytes",
                index_bytes.len()
            )));
        }
        let index = Self::decode_index(index_bytes, 0)?;
        let coder = BlockCoder::new(&base, &manifest.encoding);
        Ok(StoreHead {
            manifest,
            base,
            index,
            coder,
            sums: None,
        })
    }

    /// The blocks' checksums from `block_sums.bin`'s bytes (4 a block), checked on every block
    /// [`Self::decode_block`] decodes from now on.
    pub fn with_sums(mut self, bytes: &[u8]) -> Result<Self, FormatError> {
        let n = self.manifest.counts.nodes.div_ceil(BLOCK);
        if bytes.len() as u64 != n * 4 {
            return Err(FormatError::Inconsistent(format!(
                "{BLOCK_SUMS_FILE}: {} bytes, the {n} blocks need 4 each",
                bytes.len()
            )));
        }
        self.sums = Some(decode_sums(bytes));
        Ok(self)
    }

    /// Checks a store's manifest (its version and encoding) and decodes its `base.bin`, which
    /// must agree with the manifest's levels and node count: what a reader that fetches the
    /// index a page at a time ([`Self::decode_index`]) checks at open.
    pub fn decode_base(manifest: &Manifest, base_bytes: &[u8]) -> Result<BaseMesh, FormatError> {
        if manifest.format != STORE_FORMAT || manifest.version != STORE_VERSION {
            return Err(FormatError::Version {
                format: manifest.format.clone(),
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
        Ok(base)
    }

    /// Decodes consecutive entries of `block_index.bin` starting at entry `first` (a multiple of
    /// 8 bytes): they may not decrease, no block may claim more than a block can take, and entry
    /// 0 is 0.
    pub fn decode_index(bytes: &[u8], first: u64) -> Result<Vec<u64>, FormatError> {
        let index: Vec<u64> = bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect();
        // read_nodes subtracts neighbouring entries: they must not decrease, and no block may
        // claim more than a block can take
        if first == 0 && index.first().is_some_and(|&e| e != 0) {
            return Err(FormatError::BadIndex(format!(
                "entry 0 is {}, the first block starts at byte 0",
                index[0]
            )));
        }
        for (i, w) in index.windows(2).enumerate() {
            let b = first + i as u64;
            if w[1] < w[0] || w[1] - w[0] > MAX_BLOCK_BYTES {
                return Err(FormatError::BadIndex(format!(
                    "block {b} spans bytes {}..{} (entries {b} and {}: they may not decrease \
                     nor differ by more than {MAX_BLOCK_BYTES})",
                    w[0],
                    w[1],
                    b + 1
                )));
            }
        }
        Ok(index)
    }

    /// Number of blocks of `blocks.bin`.
    pub fn blocks(&self) -> u64 {
        self.index.len() as u64 - 1
    }

    /// Ids of block `b`: `b·BLOCK .. min((b+1)·BLOCK, nodes)`.
    pub fn block_ids(&self, b: u64) -> (TetId, TetId) {
        let nodes = self.manifest.counts.nodes;
        let from = (b * BLOCK).min(nodes);
        (from, (from + BLOCK).min(nodes))
    }

    /// Decodes block `b` from its bytes: exactly its node count, ids `block_ids(b)` in order.
    pub fn decode_block(&self, b: u64, bytes: &[u8]) -> Result<Vec<DetailNode>, FormatError> {
        let (from, to) = self.block_ids(b);
        let bad = |reason: String| FormatError::BadBlock {
            block: b,
            from,
            to,
            reason,
        };
        if let Some(want) = self.sums.as_ref().and_then(|s| s.get(b as usize)) {
            let got = crc32fast::hash(bytes);
            if got != *want {
                return Err(bad(format!(
                    "checksum {got:08x}, {BLOCK_SUMS_FILE} says {want:08x}"
                )));
            }
        }
        let block = NodeBlock {
            count: (to - from) as u32,
            first: from,
            bytes: bytes.to_vec(),
        };
        let nodes = self.coder.decode(&block).map_err(|e| bad(e.to_string()))?;
        // the decoder returns `count` nodes of increasing ids from `first`: they are the block's
        // ids exactly when the last is `to - 1` (no gap was coded)
        if nodes.len() as u64 != to - from || nodes.last().is_some_and(|n| n.id != to - 1) {
            return Err(bad(format!(
                "decodes to nodes {}..={}, not the block's ids",
                nodes.first().map_or(0, |n| n.id),
                nodes.last().map_or(0, |n| n.id)
            )));
        }
        Ok(nodes)
    }

    /// Nodes `from..to`: reads the covering blocks' bytes (one contiguous read of `blocks.bin`),
    /// decodes them and keeps the range.
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
        let (b0, b1) = (from / BLOCK, (to - 1) / BLOCK);
        // decode checked the index: entries exist for every block and never decrease
        let (start, end) = (self.index[b0 as usize], self.index[b1 as usize + 1]);
        let len = usize::try_from(end - start).map_err(|_| {
            FormatError::Inconsistent(format!(
                "blocks.bin: bytes {start}..{end} do not fit in memory"
            ))
        })?;
        let mut bytes = vec![0u8; len];
        files.read_at("blocks.bin", start, &mut bytes)?;
        let mut out = Vec::with_capacity((to - from) as usize);
        for b in b0..=b1 {
            let at = (self.index[b as usize] - start) as usize;
            let until = (self.index[b as usize + 1] - start) as usize;
            let (bf, _) = self.block_ids(b);
            let decoded = self.decode_block(b, &bytes[at..until])?;
            let lo = from.saturating_sub(bf) as usize;
            let hi = ((to - bf) as usize).min(decoded.len());
            out.extend(decoded.into_iter().take(hi).skip(lo));
        }
        Ok(out)
    }
}

/// Entries of `block_sums.bin` (u32 LE each; a trailing partial entry is ignored).
pub fn decode_sums(bytes: &[u8]) -> Vec<u32> {
    bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes")))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(f: &str) -> Physical {
        Physical {
            origin: [0.0; 3],
            frame: Some(f.into()),
            length_unit: Some("mm".into()),
            value_unit: None,
        }
    }

    /// Directions read as radiology viewers label them: the letters of the components beyond a
    /// third of the length, largest first; LPS and RAS name the x and y axes oppositely; an
    /// unknown frame or a zero vector has no label.
    #[test]
    fn directions_are_labelled_in_the_frame() {
        let (ras, lps) = (frame("RAS"), frame("LPS"));
        assert_eq!(ras.direction_label([1.0, 0.0, 0.0]).as_deref(), Some("R"));
        assert_eq!(lps.direction_label([1.0, 0.0, 0.0]).as_deref(), Some("L"));
        assert_eq!(ras.direction_label([0.0, -2.0, 0.0]).as_deref(), Some("P"));
        assert_eq!(lps.direction_label([0.0, -2.0, 0.0]).as_deref(), Some("A"));
        assert_eq!(lps.direction_label([0.0, 0.0, -1.0]).as_deref(), Some("I"));
        // the default view's screen right in LPS: mostly +y (posterior), then −x (right)
        assert_eq!(
            lps.direction_label([-0.574, 0.819, 0.0]).as_deref(),
            Some("PR")
        );
        assert_eq!(
            ras.direction_label([-0.346, -0.242, 0.906]).as_deref(),
            Some("SL")
        );
        assert_eq!(
            ras.direction_label([0.6, -0.6, 0.55]).as_deref(),
            Some("RPS")
        );
        assert_eq!(ras.direction_label([0.0; 3]), None);
        assert_eq!(frame("scanner-xyz").direction_label([1.0, 0.0, 0.0]), None);
        let (positions, tets) = crate::shapes::box5([0.0; 3], [1.0; 3]);
        let base = crate::BaseMesh {
            levels: 1,
            values: vec![0.0; positions.len()],
            empty: vec![false; tets.len()],
            predictor: Default::default(),
            positions,
            tets,
        };
        let mut m = crate::testing::manifest_for(&base);
        assert_eq!(m.legend_name(), m.dataset);
        m.physical = Some(Physical {
            value_unit: Some("HU".into()),
            ..ras
        });
        assert_eq!(m.legend_name(), format!("{} (HU)", m.dataset));
    }
}
