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
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
pub use tetwave_protocol::store_format::{
    encode_node_record, Counts, Encoding, FileSum, FormatError, Manifest, StoreFiles, StoreHead,
    BLOCK, STORE_FORMAT, STORE_VERSION,
};
use tetwave_protocol::{BaseMesh, DetailNode, Forest, TetId};

/// The files of a store besides `manifest.json`, each with its size and CRC-32 in the manifest.
pub const STORE_FILES: [&str; 5] = [
    "base.bin",
    "nodes.bin",
    "coeffs.bin",
    "coeff_index.bin",
    "reference.f32",
];

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
    #[error("{path}: {source}")]
    Format { path: PathBuf, source: FormatError },
}

impl From<FormatError> for StoreError {
    fn from(source: FormatError) -> Self {
        StoreError::Format {
            path: PathBuf::from("store"),
            source,
        }
    }
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

/// Writes a store directory (created if needed) and returns its manifest. Over an existing store,
/// its manifest goes first and the new one is written last (renamed into place): a write that
/// stops half way leaves a directory that does not open as a store, never an old manifest over
/// new files.
pub fn write(dir: &Path, a: &Analysis, meta: StoreMeta) -> Result<Manifest, StoreError> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let manifest_path = dir.join("manifest.json");
    match std::fs::remove_file(&manifest_path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            return Err(io_err(&manifest_path)(e));
        }
        _ => {}
    }
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
        w.put(&encode_node_record(
            a.owned[i],
            a.empty_children[i],
            a.subtree_max_abs[i],
        ))
        .map_err(io_err(&path))?;
    }
    files.insert("nodes.bin".into(), w.finish().map_err(io_err(&path))?);

    let path = dir.join("coeffs.bin");
    let mut w = SumWriter::create(&path)?;
    let mut buf = Vec::with_capacity(1 << 16);
    for chunk in a.coeffs.chunks(1 << 14) {
        buf.clear();
        for &d in chunk {
            encoding.encode(d, &mut buf);
        }
        w.put(&buf).map_err(io_err(&path))?;
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
    let text = serde_json::to_string_pretty(&manifest).expect("manifest serializes");
    let partial = dir.join("manifest.json.partial");
    std::fs::write(&partial, text).map_err(io_err(&partial))?;
    std::fs::rename(&partial, &manifest_path).map_err(io_err(&manifest_path))?;
    Ok(manifest)
}

/// A store directory as a [`StoreFiles`] source.
pub struct DirFiles(pub PathBuf);

impl StoreFiles for DirFiles {
    type Error = StoreError;
    fn read_at(&self, file: &str, offset: u64, buf: &mut [u8]) -> Result<(), StoreError> {
        let path = self.0.join(file);
        let mut f = File::open(&path).map_err(io_err(&path))?;
        f.seek(SeekFrom::Start(offset)).map_err(io_err(&path))?;
        f.read_exact(buf).map_err(io_err(&path))
    }
}

/// An open store: manifest, base mesh and block index in memory, node records and coefficients read
/// on demand.
pub struct Store {
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub base: BaseMesh,
    head: StoreHead,
    files: DirFiles,
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
        let base_bytes = std::fs::read(&bpath).map_err(io_err(&bpath))?;
        let ipath = dir.join("coeff_index.bin");
        let index_bytes = std::fs::read(&ipath).map_err(io_err(&ipath))?;
        let head = StoreHead::decode(manifest, &base_bytes, &index_bytes).map_err(|source| {
            StoreError::Format {
                path: dir.to_path_buf(),
                source,
            }
        })?;
        Ok(Store {
            dir: dir.to_path_buf(),
            manifest: head.manifest.clone(),
            base: head.base.clone(),
            head,
            files: DirFiles(dir.to_path_buf()),
        })
    }

    pub fn forest(&self) -> Forest {
        self.base.forest()
    }

    /// Recomputes every file's CRC-32 and compares it with the manifest, which must list every
    /// file of a store ([`STORE_FILES`]).
    pub fn check_sums(&self) -> Result<(), StoreError> {
        if let Some(missing) = STORE_FILES
            .iter()
            .find(|f| !self.manifest.files.contains_key(**f))
        {
            return Err(StoreError::Corrupt {
                path: self.dir.join("manifest.json"),
                reason: format!("no checksum for {missing}"),
            });
        }
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

    /// Nodes `from..to` (random access: reads only what the range needs).
    pub fn read_nodes(&self, from: TetId, to: TetId) -> Result<Vec<DetailNode>, StoreError> {
        self.head
            .read_nodes(&self.files, from, to)
            .map_err(|e| match e {
                StoreError::Format { source, .. } => StoreError::Format {
                    path: self.dir.clone(),
                    source,
                },
                other => other,
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
