//! The coefficient store: a directory holding a JSON manifest, the base mesh, one fixed-size record per
//! node and the coefficients in node order, with a block index for random access by node id range.
//!
//! | file              | contents                                                                  |
//! |-------------------|---------------------------------------------------------------------------|
//! | `manifest.json`   | [`Manifest`]: dataset, bounds, sizes, counts, encoding, bound, checksums    |
//! | `base.bin`        | bincode [`BaseMesh`]                                                       |
//! | `nodes.bin`       | per node 6 bytes: owned mask u8, empty children u8, subtree max |d| f32 LE |
//! | `coeffs.bin`      | owned coefficients, node order then edge order: f32 LE, or quantized codes |
//! |                   | as signed little-endian integers of `ceil(bits/8)` bytes                   |
//! | `coeff_index.bin` | u64 LE per block of [`BLOCK`] nodes: coefficients before the block         |
//! | `reference.f32`   | the sampled value of every vertex (for `verify`; not streamed)             |
//!
//! Reading nodes `a..b` touches one index entry, at most [`BLOCK`] node records before `a`, and the
//! range's own records and coefficients: never the whole file.

use crate::analysis::Analysis;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use tetwave_protocol::wavelet::Quantizer;
use tetwave_protocol::{BaseMesh, DetailNode, Forest, TetId};

/// Nodes per index block.
pub const BLOCK: u64 = 4096;
const NODE_RECORD: u64 = 6;
pub const STORE_FORMAT: &str = "tetwave-store";
pub const STORE_VERSION: u32 = 1;

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

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Encoding {
    F32,
    Quantized { bits: u8, step: f32 },
}

impl Encoding {
    pub fn width(&self) -> usize {
        match self {
            Encoding::F32 => 4,
            Encoding::Quantized { bits, .. } => (*bits as usize).div_ceil(8),
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

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not a tetwave store manifest: {reason}")]
    BadManifest { path: PathBuf, reason: String },
    #[error("{path}: {reason}")]
    Corrupt { path: PathBuf, reason: String },
    #[error("node range {from}..{to} is outside 0..{nodes}")]
    RangeOutOfBounds { from: u64, to: u64, nodes: u64 },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes files while computing their checksums.
struct SumWriter {
    inner: BufWriter<File>,
    hasher: crc32fast::Hasher,
    bytes: u64,
}

impl SumWriter {
    fn create(path: &Path) -> Result<Self, StoreError> {
        let f = File::create(path).map_err(io_err(path))?;
        Ok(SumWriter {
            inner: BufWriter::with_capacity(1 << 20, f),
            hasher: crc32fast::Hasher::new(),
            bytes: 0,
        })
    }
    fn put(&mut self, b: &[u8]) -> std::io::Result<()> {
        self.hasher.update(b);
        self.bytes += b.len() as u64;
        self.inner.write_all(b)
    }
    fn finish(mut self) -> std::io::Result<FileSum> {
        self.inner.flush()?;
        Ok(FileSum {
            bytes: self.bytes,
            crc32: self.hasher.finalize(),
        })
    }
}

/// What `write` needs besides the analysis.
pub struct StoreMeta {
    pub dataset: String,
    pub source: String,
    pub base: String,
    pub outside_vertices: u64,
}

/// Writes a store directory (created if needed) and returns its manifest.
pub fn write(dir: &Path, a: &Analysis, meta: StoreMeta) -> Result<Manifest, StoreError> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let forest = a.base.forest();
    let mut files = std::collections::BTreeMap::new();
    let encoding = match &a.quantizer {
        None => Encoding::F32,
        Some(q) => Encoding::Quantized {
            bits: q.bits,
            step: q.step,
        },
    };

    let path = dir.join("base.bin");
    let mut w = SumWriter::create(&path)?;
    let bytes =
        bincode::serde::encode_to_vec(&a.base, bincode::config::standard()).map_err(|e| {
            StoreError::Corrupt {
                path: path.clone(),
                reason: e.to_string(),
            }
        })?;
    w.put(&bytes).map_err(io_err(&path))?;
    files.insert("base.bin".into(), w.finish().map_err(io_err(&path))?);

    let path = dir.join("nodes.bin");
    let mut w = SumWriter::create(&path)?;
    for i in 0..a.owned.len() {
        let mut rec = [0u8; 6];
        rec[0] = a.owned[i];
        rec[1] = a.empty_children[i];
        rec[2..6].copy_from_slice(&a.subtree_max_abs[i].to_le_bytes());
        w.put(&rec).map_err(io_err(&path))?;
    }
    files.insert("nodes.bin".into(), w.finish().map_err(io_err(&path))?);

    let path = dir.join("coeffs.bin");
    let mut w = SumWriter::create(&path)?;
    let width = encoding.width();
    for &d in &a.coeffs {
        match &a.quantizer {
            None => w.put(&d.to_le_bytes()),
            Some(q) => w.put(&q.encode(d).to_le_bytes()[..width]),
        }
        .map_err(io_err(&path))?;
    }
    files.insert("coeffs.bin".into(), w.finish().map_err(io_err(&path))?);

    let path = dir.join("coeff_index.bin");
    let mut w = SumWriter::create(&path)?;
    let mut before = 0u64;
    for (i, m) in a.owned.iter().enumerate() {
        if (i as u64).is_multiple_of(BLOCK) {
            w.put(&before.to_le_bytes()).map_err(io_err(&path))?;
        }
        before += m.count_ones() as u64;
    }
    files.insert("coeff_index.bin".into(), w.finish().map_err(io_err(&path))?);

    let path = dir.join("reference.f32");
    let mut w = SumWriter::create(&path)?;
    for &x in &a.reference {
        w.put(&x.to_le_bytes()).map_err(io_err(&path))?;
    }
    files.insert("reference.f32".into(), w.finish().map_err(io_err(&path))?);

    let (lo, hi) = a.base.bounds();
    let manifest = Manifest {
        format: STORE_FORMAT.into(),
        version: STORE_VERSION,
        dataset: meta.dataset,
        source: meta.source,
        bounds: [lo, hi],
        base: meta.base,
        base_tets: a.base.tets.len() as u64,
        base_vertices: a.base.positions.len() as u64,
        levels: a.base.levels,
        value_range: [a.value_range.0, a.value_range.1],
        counts: Counts {
            tets_total: forest.total_tets(),
            leaves: forest.leaves(),
            nodes: forest.nodes(),
            vertices: a.reference.len() as u64,
            coefficients: a.coeffs.len() as u64,
            outside_vertices: meta.outside_vertices,
            empty_base_tets: a.base.empty.iter().filter(|&&e| e).count() as u64,
        },
        encoding,
        max_error_bound: a.error_bound,
        max_abs_error: a.max_abs_error,
        files,
    };
    let path = dir.join("manifest.json");
    let text = serde_json::to_string_pretty(&manifest).expect("manifest serializes");
    std::fs::write(&path, text).map_err(io_err(&path))?;
    Ok(manifest)
}

/// An open store: manifest, base mesh and block index in memory, node records and coefficients read
/// on demand.
pub struct Store {
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub base: BaseMesh,
    index: Vec<u64>,
}

impl Store {
    /// Opens a store, checking the manifest, the base mesh and every file's size (not checksums: see
    /// [`Store::check_sums`]).
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        let mpath = dir.join("manifest.json");
        let text = std::fs::read_to_string(&mpath).map_err(io_err(&mpath))?;
        let manifest: Manifest =
            serde_json::from_str(&text).map_err(|e| StoreError::BadManifest {
                path: mpath.clone(),
                reason: e.to_string(),
            })?;
        if manifest.format != STORE_FORMAT || manifest.version != STORE_VERSION {
            return Err(StoreError::BadManifest {
                path: mpath,
                reason: format!(
                    "format {} v{}, expected {STORE_FORMAT} v{STORE_VERSION}",
                    manifest.format, manifest.version
                ),
            });
        }
        for (name, sum) in &manifest.files {
            let p = dir.join(name);
            let len = std::fs::metadata(&p).map_err(io_err(&p))?.len();
            if len != sum.bytes {
                return Err(StoreError::Corrupt {
                    path: p,
                    reason: format!("{len} bytes, manifest says {}", sum.bytes),
                });
            }
        }
        let bpath = dir.join("base.bin");
        let bytes = std::fs::read(&bpath).map_err(io_err(&bpath))?;
        let cfg = bincode::config::standard().with_limit::<{ 1 << 30 }>();
        let (base, _): (BaseMesh, usize) =
            bincode::serde::decode_from_slice(&bytes, cfg).map_err(|e| StoreError::Corrupt {
                path: bpath.clone(),
                reason: e.to_string(),
            })?;
        base.validate().map_err(|e| StoreError::Corrupt {
            path: bpath.clone(),
            reason: e.to_string(),
        })?;
        let forest = base.forest();
        if base.levels != manifest.levels || forest.nodes() != manifest.counts.nodes {
            return Err(StoreError::Corrupt {
                path: bpath,
                reason: "base mesh disagrees with the manifest".into(),
            });
        }
        let ipath = dir.join("coeff_index.bin");
        let ib = std::fs::read(&ipath).map_err(io_err(&ipath))?;
        let index: Vec<u64> = ib
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().unwrap()))
            .collect();
        if index.len() as u64 != forest.nodes().div_ceil(BLOCK) {
            return Err(StoreError::Corrupt {
                path: ipath,
                reason: "index size disagrees with the node count".into(),
            });
        }
        Ok(Store {
            dir: dir.to_path_buf(),
            manifest,
            base,
            index,
        })
    }

    pub fn forest(&self) -> Forest {
        self.base.forest()
    }

    /// Recomputes every file's CRC-32 and compares it with the manifest.
    pub fn check_sums(&self) -> Result<(), StoreError> {
        for (name, sum) in &self.manifest.files {
            let p = self.dir.join(name);
            let mut f = File::open(&p).map_err(io_err(&p))?;
            let mut h = crc32fast::Hasher::new();
            let mut buf = vec![0u8; 1 << 20];
            loop {
                let n = f.read(&mut buf).map_err(io_err(&p))?;
                if n == 0 {
                    break;
                }
                h.update(&buf[..n]);
            }
            let got = h.finalize();
            if got != sum.crc32 {
                return Err(StoreError::Corrupt {
                    path: p,
                    reason: format!("checksum {got:08x}, manifest says {:08x}", sum.crc32),
                });
            }
        }
        Ok(())
    }

    fn quantizer(&self) -> Option<Quantizer> {
        match self.manifest.encoding {
            Encoding::F32 => None,
            Encoding::Quantized { bits, step } => Some(Quantizer { bits, step }),
        }
    }

    /// Nodes `from..to` (random access: reads only what the range needs).
    pub fn read_nodes(&self, from: TetId, to: TetId) -> Result<Vec<DetailNode>, StoreError> {
        let nodes = self.manifest.counts.nodes;
        if from > to || to > nodes {
            return Err(StoreError::RangeOutOfBounds { from, to, nodes });
        }
        if from == to {
            return Ok(Vec::new());
        }
        let block = from / BLOCK;
        let block_start = block * BLOCK;
        let npath = self.dir.join("nodes.bin");
        let mut nf = File::open(&npath).map_err(io_err(&npath))?;
        nf.seek(SeekFrom::Start(block_start * NODE_RECORD))
            .map_err(io_err(&npath))?;
        let mut recs = vec![0u8; ((to - block_start) * NODE_RECORD) as usize];
        nf.read_exact(&mut recs).map_err(io_err(&npath))?;
        let mut coeff_at = self.index[block as usize];
        for r in recs.chunks_exact(6).take((from - block_start) as usize) {
            coeff_at += r[0].count_ones() as u64;
        }
        let recs = &recs[((from - block_start) * NODE_RECORD) as usize..];
        let count: u64 = recs.chunks_exact(6).map(|r| r[0].count_ones() as u64).sum();
        let width = self.manifest.encoding.width() as u64;
        let cpath = self.dir.join("coeffs.bin");
        let mut cf = File::open(&cpath).map_err(io_err(&cpath))?;
        cf.seek(SeekFrom::Start(coeff_at * width))
            .map_err(io_err(&cpath))?;
        let mut cb = vec![0u8; (count * width) as usize];
        cf.read_exact(&mut cb).map_err(io_err(&cpath))?;
        let q = self.quantizer();
        let decode = |c: &[u8]| -> f32 {
            match &q {
                None => f32::from_le_bytes([c[0], c[1], c[2], c[3]]),
                Some(q) => {
                    let mut b = [0u8; 4];
                    b[..c.len()].copy_from_slice(c);
                    // sign-extend from width bytes
                    let shift = 32 - 8 * c.len() as u32;
                    let code = (i32::from_le_bytes(b) << shift) >> shift;
                    q.decode(code)
                }
            }
        };
        let mut coeffs = cb.chunks_exact(width as usize).map(decode);
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
            node.validate().map_err(|e| StoreError::Corrupt {
                path: npath.clone(),
                reason: e.to_string(),
            })?;
            out.push(node);
        }
        Ok(out)
    }

    /// All nodes in id order, read in chunks.
    pub fn iter_nodes(
        &self,
        chunk: u64,
    ) -> impl Iterator<Item = Result<DetailNode, StoreError>> + '_ {
        let nodes = self.manifest.counts.nodes;
        (0..nodes)
            .step_by(chunk.max(1) as usize)
            .flat_map(move |s| match self.read_nodes(s, (s + chunk).min(nodes)) {
                Ok(v) => v.into_iter().map(Ok).collect::<Vec<_>>(),
                Err(e) => vec![Err(e)],
            })
    }

    /// The sampled values `verify` compares synthesis with.
    pub fn read_reference(&self) -> Result<Vec<f32>, StoreError> {
        let p = self.dir.join("reference.f32");
        let b = std::fs::read(&p).map_err(io_err(&p))?;
        if b.len() as u64 != self.manifest.counts.vertices * 4 {
            return Err(StoreError::Corrupt {
                path: p,
                reason: "size disagrees with the vertex count".into(),
            });
        }
        Ok(b.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }
}
