//! Writing a store: every file with its size and CRC-32, the manifest last.

use crate::{
    io_err, StoreError, BLOCK, MAX_BLOCK_BYTES, REFERENCE_FILE, STORE_FORMAT, STORE_VERSION,
};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::levelset::{box_signed_distance, NearLevelSet};
use tetwave_protocol::store_format::{
    value_histogram, Counts, Encoding, FileSum, Manifest, Physical, Preview, LEVELSET_BAND_FILE,
    PREVIEW_FILE,
};
use tetwave_protocol::wavelet::{LevelSteps, Quantizer};
use tetwave_protocol::{BaseMesh, DetailNode};

/// Writes files while computing their checksums.
struct SumWriter {
    inner: BufWriter<File>,
    hasher: crc32fast::Hasher,
    bytes: u64,
    /// The file written (errors name it).
    path: PathBuf,
}

impl SumWriter {
    fn create(path: &Path) -> Result<Self, StoreError> {
        let f = File::create(path).map_err(io_err(path))?;
        Ok(SumWriter {
            inner: BufWriter::with_capacity(1 << 20, f),
            hasher: crc32fast::Hasher::new(),
            bytes: 0,
            path: path.to_path_buf(),
        })
    }
    fn put(&mut self, b: &[u8]) -> Result<(), StoreError> {
        self.hasher.update(b);
        self.bytes += b.len() as u64;
        self.inner.write_all(b).map_err(io_err(&self.path))
    }
    /// Flushes and syncs the file: it is on disk before the commit renames it into place.
    fn finish(mut self) -> Result<FileSum, StoreError> {
        self.inner.flush().map_err(io_err(&self.path))?;
        self.inner
            .get_ref()
            .sync_all()
            .map_err(io_err(&self.path))?;
        Ok(FileSum {
            bytes: self.bytes,
            crc32: self.hasher.finalize(),
        })
    }
}

/// A store's files written beside the ones in place (`NAME.partial`), which they replace only
/// once every one is written: a write that fails before then leaves the store that was there.
/// Dropped uncommitted, it removes what it wrote.
struct Staged<'a> {
    dir: &'a Path,
    written: Vec<&'static str>,
    /// Files of an earlier store that this one does not have.
    stale: Vec<&'static str>,
    committed: bool,
}

impl<'a> Staged<'a> {
    fn new(dir: &'a Path) -> Self {
        Staged {
            dir,
            written: Vec::new(),
            stale: Vec::new(),
            committed: false,
        }
    }

    fn partial(&self, name: &str) -> PathBuf {
        self.dir.join(format!("{name}.partial"))
    }

    /// A writer of `name`'s new contents.
    fn create(&mut self, name: &'static str) -> Result<SumWriter, StoreError> {
        let w = SumWriter::create(&self.partial(name))?;
        self.written.push(name);
        Ok(w)
    }

    /// `name` goes at the commit (a file an earlier store had and this one does not).
    fn remove(&mut self, name: &'static str) {
        self.stale.push(name);
    }

    /// Replaces the store in place: its manifest goes first, then every file is renamed into
    /// place, and the new manifest comes last, so a commit cut short leaves a directory that
    /// does not open as a store, never an old manifest over new files.
    fn commit(mut self, manifest: &str) -> Result<(), StoreError> {
        let manifest_path = self.dir.join("manifest.json");
        remove_if_there(&manifest_path)?;
        for name in &self.written {
            let to = self.dir.join(name);
            std::fs::rename(self.partial(name), &to).map_err(io_err(&to))?;
        }
        for name in &self.stale {
            remove_if_there(&self.dir.join(name))?;
        }
        let partial = self.partial("manifest.json");
        let mut w = SumWriter::create(&partial)?;
        w.put(manifest.as_bytes())?;
        w.finish()?;
        std::fs::rename(&partial, &manifest_path).map_err(io_err(&manifest_path))?;
        self.committed = true;
        sync_dir(self.dir)
    }
}

impl Drop for Staged<'_> {
    fn drop(&mut self) {
        if !self.committed {
            for name in &self.written {
                let _ = std::fs::remove_file(self.partial(name));
            }
        }
    }
}

/// Makes the renames into `dir` durable (the files themselves were synced when written). Where a
/// directory cannot be opened as a file (not Unix), the renames are left to the system.
fn sync_dir(dir: &Path) -> Result<(), StoreError> {
    #[cfg(unix)]
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io_err(dir))?;
    #[cfg(not(unix))]
    let _ = dir;
    Ok(())
}

fn remove_if_there(path: &Path) -> Result<(), StoreError> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io_err(path)(e)),
        _ => Ok(()),
    }
}

/// What a store holds, in node-id order: the analysis' output.
pub struct StoreContent<'a> {
    /// Base mesh with reconstructed base values and empty flags.
    pub base: &'a BaseMesh,
    /// Per node: owned-edge mask.
    pub owned: &'a [u8],
    /// Per node: bit `i` set when child `i` is empty.
    pub empty_children: &'a [u8],
    /// Per node: max |detail| of all vertices created by refining it and its descendants.
    pub subtree_max_abs: &'a [f32],
    /// Owned details in node order, then edge order (dequantized when quantized).
    pub coeffs: &'a [f32],
    /// The finest level's quantizer, when quantized, and how coarser levels' steps shrink.
    pub quantizer: Option<(Quantizer, LevelSteps)>,
    /// The sampled value of every vertex (outside ones as analysis filled them): the manifest's
    /// histogram, and `reference.f32` when [`StoreMeta::keep_reference`].
    pub reference: &'a [f32],
    /// Inside samples' range.
    pub value_range: (f32, f32),
    /// Measured max |synthesis − sample|.
    pub max_abs_error: f64,
    /// The bound the store promises.
    pub error_bound: f64,
}

impl<'a> StoreContent<'a> {
    /// The nodes in id order, each with its share of the coefficients; the caller checks that
    /// the masks and bounds come one per node ([`Self::check_lengths`]).
    fn node_cursor(&self) -> NodeCursor<'_, 'a> {
        NodeCursor {
            content: self,
            next: 0,
            coeffs: self.coeffs,
        }
    }

    /// One owned mask, empty-children mask and subtree max per node, or why not.
    fn check_lengths(&self) -> Result<(), String> {
        let n = self.owned.len();
        if self.empty_children.len() != n || self.subtree_max_abs.len() != n {
            return Err(format!(
                "{n} owned masks, {} empty-children masks and {} subtree maxima",
                self.empty_children.len(),
                self.subtree_max_abs.len()
            ));
        }
        Ok(())
    }

    /// Nodes `0..end` as detail nodes, or why the content cannot give them.
    pub fn nodes(&self, end: usize) -> Result<Vec<DetailNode>, String> {
        self.check_lengths()?;
        if end > self.owned.len() {
            return Err(format!("{end} nodes asked of {}", self.owned.len()));
        }
        let mut c = self.node_cursor();
        (0..end).map(|_| c.next_node()).collect()
    }
}

/// Walks a [`StoreContent`]'s nodes, handing each its coefficients.
struct NodeCursor<'c, 'a> {
    content: &'c StoreContent<'a>,
    next: usize,
    /// The coefficients not handed out yet.
    coeffs: &'a [f32],
}

impl NodeCursor<'_, '_> {
    /// The next node (there must be one).
    fn next_node(&mut self) -> Result<DetailNode, String> {
        let (a, i) = (self.content, self.next);
        let k = a.owned[i].count_ones() as usize;
        if self.coeffs.len() < k {
            return Err(format!(
                "node {i}: owns {k} coefficients, {} are left",
                self.coeffs.len()
            ));
        }
        let (mine, rest) = self.coeffs.split_at(k);
        self.coeffs = rest;
        self.next += 1;
        Ok(DetailNode {
            id: i as u64,
            owned: a.owned[i],
            empty_children: a.empty_children[i],
            subtree_max_abs: a.subtree_max_abs[i],
            coeffs: mine.to_vec(),
        })
    }
}

/// A store's preview: what the manifest says of it, and its nodes `0..level_start(levels)`.
pub struct PreviewNodes {
    pub preview: Preview,
    pub nodes: Vec<DetailNode>,
}

/// What [`write`](fn@write) needs besides the content.
pub struct StoreMeta {
    pub dataset: String,
    pub source: String,
    pub base: String,
    pub outside_vertices: u64,
    /// The range of the input's scalar as the importer read it (the manifest's
    /// `source_value_range`), when known.
    pub source_value_range: Option<(f32, f32)>,
    /// Per vertex key, the signed distance to the input domain's boundary (positive inside),
    /// written as `levelset.f32`; `None` for inputs with no outside (a raw grid, a convex mesh).
    pub levelset: Option<Vec<f32>>,
    /// The level set's near band (what streaming clients clip with), written coded as
    /// `levelset_near.bin`; present exactly when `levelset` is, or alone when it is a box domain
    /// ([`NearLevelSet::of_box`]: a raw grid's padded lattice), whose level set readers compute.
    pub levelset_near: Option<NearLevelSet>,
    /// Written as `preview.bin` when given.
    pub preview: Option<PreviewNodes>,
    /// Write the samples as `reference.f32` ([`REFERENCE_FILE`]).
    pub keep_reference: bool,
    /// The volume file's world (the manifest's `physical`), when the input states one.
    pub physical: Option<Physical>,
}

/// Writes a store directory (created if needed) and returns its manifest. The files are written
/// beside an existing store's and replace them only once all are written (`Staged`): a write
/// that fails before then leaves the old store as it was; one cut short while replacing leaves a
/// directory that does not open as a store, never an old manifest over new files.
pub fn write(dir: &Path, a: &StoreContent<'_>, meta: StoreMeta) -> Result<Manifest, StoreError> {
    a.check_lengths().map_err(|reason| StoreError::Corrupt {
        path: dir.join("blocks.bin"),
        reason,
    })?;
    let range = meta
        .source_value_range
        .map(|(lo, hi)| [lo, hi])
        .unwrap_or([a.value_range.0, a.value_range.1]);
    let histogram = histogram_inside(
        a.base,
        a.reference,
        meta.levelset.as_deref(),
        meta.levelset_near
            .as_ref()
            .and_then(NearLevelSet::domain_box),
        range,
        |_, _| true,
    );
    let totals = Totals {
        vertices: a.reference.len() as u64,
        coefficients: a.coeffs.len() as u64,
        value_range: a.value_range,
        max_abs_error: a.max_abs_error,
        error_bound: a.error_bound,
        histogram,
    };
    let mut cursor = a.node_cursor();
    let mut nodes = (0..a.owned.len()).map(move |_| cursor.next_node());
    let reference = meta.keep_reference.then_some(a.reference);
    write_streamed(
        dir,
        a.base,
        a.quantizer,
        (a.owned.len() as u64, &mut nodes),
        &totals,
        reference,
        meta,
    )
}

/// What a store's manifest counts and promises besides its nodes: [`write_streamed`]'s summary of
/// an analysis it does not hold (`prepare --finish` sums the parts').
#[derive(Debug, Clone)]
pub struct Totals {
    /// Vertices of every level (the manifest's `counts.vertices`).
    pub vertices: u64,
    /// Coefficients the nodes own, all together: checked against the nodes written.
    pub coefficients: u64,
    /// Inside samples' range.
    pub value_range: (f32, f32),
    /// Measured max |synthesis − sample|.
    pub max_abs_error: f64,
    /// The bound the store promises.
    pub error_bound: f64,
    /// The manifest's value histogram ([`histogram_inside`]).
    pub histogram: Vec<u64>,
}

/// Writes a store as [`write`](fn@write) does, from `nodes`: `count` detail nodes in id order
/// (ids `0..count`, each checked), coded block by block as they come, so that a caller need not
/// hold them (`prepare --finish` streams them from the parts' files). `reference`, when given, is
/// written as `reference.f32` (and `meta.keep_reference` is not read).
pub fn write_streamed(
    dir: &Path,
    base: &BaseMesh,
    quantizer: Option<(Quantizer, LevelSteps)>,
    (n, nodes): (u64, &mut dyn Iterator<Item = Result<DetailNode, String>>),
    totals: &Totals,
    reference: Option<&[f32]>,
    meta: StoreMeta,
) -> Result<Manifest, StoreError> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let mut staged = Staged::new(dir);
    let forest = base.forest();
    let mut files = std::collections::BTreeMap::new();
    let encoding = Encoding::of(quantizer);
    if n != forest.nodes() {
        return Err(StoreError::Corrupt {
            path: dir.join("blocks.bin"),
            reason: format!("{n} nodes for a hierarchy of {}", forest.nodes()),
        });
    }

    let path = dir.join("base.bin");
    let mut w = staged.create("base.bin")?;
    let bytes = bincode::serde::encode_to_vec(base, bincode::config::standard()).map_err(|e| {
        StoreError::Corrupt {
            path: path.clone(),
            reason: e.to_string(),
        }
    })?;
    w.put(&bytes)?;
    files.insert("base.bin".into(), w.finish()?);

    // the nodes in blocks of BLOCK ids, each coded on its own (random access decodes one block
    // without its neighbours); the index gets each block's offset, then the file's length
    let coder = BlockCoder::new(base, &encoding);
    let path = dir.join("blocks.bin");
    let corrupt = |reason: String| StoreError::Corrupt {
        path: path.clone(),
        reason,
    };
    let mut w = staged.create("blocks.bin")?;
    let mut index = Vec::with_capacity(n.div_ceil(BLOCK) as usize + 1);
    let mut sums = Vec::with_capacity(n.div_ceil(BLOCK) as usize);
    let mut offset = 0u64;
    let mut coefficients = 0u64;
    let mut block_nodes = Vec::with_capacity(BLOCK as usize);
    for start in (0..n).step_by(BLOCK as usize) {
        let end = (start + BLOCK).min(n);
        block_nodes.clear();
        for id in start..end {
            let node = nodes
                .next()
                .ok_or_else(|| corrupt(format!("the nodes end at {id} of {n}")))?
                .map_err(&corrupt)?;
            if node.id != id {
                return Err(corrupt(format!("node {} where node {id} belongs", node.id)));
            }
            coefficients += node.coeffs.len() as u64;
            block_nodes.push(node);
        }
        let block = coder
            .encode(&block_nodes)
            .map_err(|e| corrupt(format!("nodes {start}..{end}: {e}")))?;
        if block.bytes.len() as u64 > MAX_BLOCK_BYTES {
            return Err(corrupt(format!(
                "nodes {start}..{end} code to {} bytes, beyond the {MAX_BLOCK_BYTES}-byte limit",
                block.bytes.len()
            )));
        }
        index.push(offset);
        sums.push(crc32fast::hash(&block.bytes));
        offset += block.bytes.len() as u64;
        w.put(&block.bytes)?;
    }
    index.push(offset);
    if nodes.next().is_some() {
        return Err(corrupt(format!("more than the hierarchy's {n} nodes")));
    }
    if coefficients != totals.coefficients {
        return Err(corrupt(format!(
            "the nodes own {coefficients} coefficients of {}",
            totals.coefficients
        )));
    }
    files.insert("blocks.bin".into(), w.finish()?);

    let mut w = staged.create("block_index.bin")?;
    for o in &index {
        w.put(&o.to_le_bytes())?;
    }
    files.insert("block_index.bin".into(), w.finish()?);
    let mut w = staged.create(crate::BLOCK_SUMS_FILE)?;
    for s in &sums {
        w.put(&s.to_le_bytes())?;
    }
    files.insert(crate::BLOCK_SUMS_FILE.into(), w.finish()?);

    if let Some(reference) = reference {
        let mut w = staged.create(REFERENCE_FILE)?;
        for &x in reference {
            w.put(&x.to_le_bytes())?;
        }
        files.insert(REFERENCE_FILE.into(), w.finish()?);
    } else {
        // a copy left by an earlier store in this directory is not this store's
        staged.remove(REFERENCE_FILE);
    }

    let path = dir.join("levelset.f32");
    match &meta.levelset {
        Some(ls) => {
            if ls.len() as u64 != totals.vertices {
                return Err(StoreError::Corrupt {
                    path,
                    reason: format!(
                        "{} level-set values for {} vertices",
                        ls.len(),
                        totals.vertices
                    ),
                });
            }
            let mut w = staged.create("levelset.f32")?;
            for &x in ls {
                w.put(&x.to_le_bytes())?;
            }
            files.insert("levelset.f32".into(), w.finish()?);
        }
        // a level set left by an earlier store in this directory is not this store's
        None => staged.remove("levelset.f32"),
    }

    let path = dir.join(LEVELSET_BAND_FILE);
    match (&meta.levelset, &meta.levelset_near) {
        // a band goes with its whole level set, but a box domain's alone: readers compute it
        (whole, Some(near)) if whole.is_some() || near.domain_box().is_some() => {
            let bytes = near.encode().map_err(|e| StoreError::Corrupt {
                path: path.clone(),
                reason: e.to_string(),
            })?;
            let mut w = staged.create(LEVELSET_BAND_FILE)?;
            w.put(&bytes)?;
            files.insert(LEVELSET_BAND_FILE.into(), w.finish()?);
        }
        (None, None) => staged.remove(LEVELSET_BAND_FILE),
        _ => {
            return Err(StoreError::Corrupt {
                path,
                reason: "a level set needs its near band and the near band its level set".into(),
            })
        }
    }

    let path = dir.join(PREVIEW_FILE);
    let preview = match &meta.preview {
        Some(p) => {
            let corrupt = |reason: String| StoreError::Corrupt {
                path: path.clone(),
                reason,
            };
            let want = p
                .preview
                .check_for(forest.n_base, forest.levels)
                .map_err(|e| corrupt(e.to_string()))?;
            if want != p.nodes.len() as u64
                || p.nodes.iter().enumerate().any(|(i, n)| n.id != i as u64)
            {
                return Err(corrupt(format!(
                    "{} preview nodes for the node levels below {} of {}",
                    p.nodes.len(),
                    p.preview.levels,
                    forest.levels
                )));
            }
            // the blocks one after the other, each a bincode NodeBlock
            let coder = BlockCoder::for_preview(base, &p.preview.encoding);
            let mut w = staged.create(PREVIEW_FILE)?;
            for c in p.nodes.chunks(BLOCK as usize) {
                let block = coder.encode(c).map_err(|e| corrupt(e.to_string()))?;
                let bytes = bincode::serde::encode_to_vec(&block, bincode::config::standard())
                    .map_err(|e| corrupt(e.to_string()))?;
                w.put(&bytes)?;
            }
            files.insert(PREVIEW_FILE.into(), w.finish()?);
            Some(p.preview.clone())
        }
        None => {
            staged.remove(PREVIEW_FILE);
            None
        }
    };

    let value_range = [totals.value_range.0, totals.value_range.1];
    let source_value_range = meta.source_value_range.map(|(lo, hi)| [lo, hi]);
    let (lo, hi) = base.bounds();
    let manifest = Manifest {
        format: STORE_FORMAT.into(),
        version: STORE_VERSION,
        dataset: meta.dataset,
        source: meta.source,
        bounds: [lo, hi],
        base: meta.base,
        base_tets: base.tets.len() as u64,
        base_vertices: base.positions.len() as u64,
        levels: base.levels,
        value_range,
        source_value_range,
        counts: Counts {
            tets_total: forest.total_tets(),
            leaves: forest.leaves(),
            nodes: forest.nodes(),
            vertices: totals.vertices,
            coefficients: totals.coefficients,
            outside_vertices: meta.outside_vertices,
            empty_base_tets: base.empty.iter().filter(|&&e| e).count() as u64,
        },
        encoding,
        max_error_bound: totals.error_bound,
        max_abs_error: totals.max_abs_error,
        files,
        preview,
        value_histogram: Some(totals.histogram.clone()),
        physical: meta.physical,
    };
    let text = serde_json::to_string_pretty(&manifest).expect("manifest serializes");
    staged.commit(&text)?;
    Ok(manifest)
}

/// The manifest's value histogram: the samples of the vertices inside the domain (level set ≥ 0,
/// from the whole level set or a box domain's distance at each vertex) over `range`, each weighed
/// by its home base tet's volume in units of the smallest one's (rounded, at least 1): the finest
/// vertices are spread evenly through each base tet, and base tets differ in volume (box5's
/// central tet is twice a corner tet), so a count alone would misweigh them. Only the vertices
/// where `counted(tet, weights)` (a base tet holding the vertex, and its lattice weights there)
/// count: a part of a store leaves out those another part counts.
pub fn histogram_inside(
    base: &BaseMesh,
    reference: &[f32],
    levelset: Option<&[f32]>,
    domain_box: Option<[[f64; 3]; 2]>,
    range: [f32; 2],
    counted: impl Fn(u32, &[u32; 4]) -> bool,
) -> Vec<u64> {
    let volume = |t: &[u32; 4]| {
        let p = |k: usize| base.positions[t[k] as usize];
        tetwave_protocol::base::signed_volume(p(0), p(1), p(2), p(3)).abs()
    };
    let volumes: Vec<f64> = base.tets.iter().map(volume).collect();
    let smallest = volumes
        .iter()
        .copied()
        .filter(|v| *v > 0.0)
        .fold(f64::INFINITY, f64::min);
    // a vertex on the domain box's faces is inside: within a billionth of the box's extent, as
    // its coordinates are computed from a part's sub-box or from the whole's and may differ in
    // the last bits (other lattice vertices are a lattice step or more away)
    let slack = domain_box.map_or(0.0, |[lo, hi]| {
        1e-9 * (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max)
    });
    let keys = base.vertex_keys();
    let mut weight = vec![0u32; reference.len()];
    for (entity, _) in keys.entities() {
        keys.for_each_in(entity, |key, tet, w| {
            let inside = counted(tet, &w)
                && levelset.is_none_or(|l| l[key as usize] >= 0.0)
                && domain_box.is_none_or(|[lo, hi]| {
                    box_signed_distance(lo, hi, base.position(tet, &w)) >= -slack
                });
            let units = (volumes[tet as usize] / smallest).round().clamp(1.0, 1e9);
            weight[key as usize] = if inside { units as u32 } else { 0 };
        });
    }
    value_histogram(reference, range, |k| weight[k] as u64)
}

/// Copies the store in `dir` to object storage at `to`: every file the manifest lists (large
/// ones in parts), then the manifest, so that a reader sees the new store whole or not at all.
/// An earlier store's manifest there is removed first: a copy cut short leaves no manifest,
/// never an old manifest over new files. Nothing is listed (a bucket need not allow it).
pub fn upload(dir: &Path, to: &crate::Location) -> Result<Manifest, StoreError> {
    let mpath = dir.join("manifest.json");
    let text = std::fs::read_to_string(&mpath).map_err(io_err(&mpath))?;
    let manifest: Manifest = serde_json::from_str(&text).map_err(|e| StoreError::BadManifest {
        path: mpath.clone(),
        reason: e.to_string(),
    })?;
    let objects = crate::location::Objects::connect(to)?;
    objects.delete("manifest.json")?;
    for name in manifest.files.keys() {
        objects.upload(name, &dir.join(name))?;
    }
    objects.upload("manifest.json", &mpath)?;
    Ok(manifest)
}

/// Copies one file to object storage at `to` (a part's files, written as they are made).
pub fn upload_file(from: &Path, to: &crate::Location, name: &str) -> Result<(), StoreError> {
    crate::location::Objects::connect(to)?.upload(name, from)
}

/// Copies object `name` at `from` into the local file `to`; `Ok(false)` when there is none.
pub fn download_file(from: &crate::Location, name: &str, to: &Path) -> Result<bool, StoreError> {
    crate::location::Objects::connect(from)?.download(name, to)
}

/// Removes object `name` at `at` (absent is fine).
pub fn delete_file(at: &crate::Location, name: &str) -> Result<(), StoreError> {
    crate::location::Objects::connect(at)?.delete(name)
}
