//! Reading a store: the manifest, base mesh and block index at open, coded blocks on demand.

use crate::location::{Files, Location};
use crate::{StoreError, BLOCK_SUMS_FILE, OPTIONAL_STORE_FILES, REFERENCE_FILE, STORE_FILES};
use std::path::{Path, PathBuf};
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::block::NodeBlock;
use tetwave_protocol::levelset::{box_signed_distance, NearLevelSet};
use tetwave_protocol::store_format::{
    FormatError, Manifest, StoreHead, BLOCK, LEVELSET_BAND_FILE, MAX_BASE_BYTES, MAX_BLOCK_BYTES,
    PREVIEW_FILE, STORE_FORMAT, STORE_VERSION,
};
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_protocol::{BaseMesh, DetailNode, Forest, TetId};

/// An open store: manifest, base mesh and block index in memory, blocks read and decoded on demand.
pub struct Store {
    /// Where the store is (its display names it in messages).
    pub location: Location,
    /// The directory, for a local store; for object storage, its URL as a path (for messages).
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub base: BaseMesh,
    /// The preview's nodes (`preview.bin`, [`Manifest::preview`]), decoded and checked at open.
    pub preview: Option<Vec<DetailNode>>,
    head: StoreHead,
    files: Files,
}

/// How [`Store::open_with`] checks a store.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct OpenOptions {
    /// Also recompute every file's CRC-32 ([`Store::check_sums`]): reads the whole store.
    /// `base.bin`'s is always checked.
    pub verify_checksums: bool,
    /// Skip the structure pass (which reads every block) and each file's size check: blocks are
    /// checked when they are read (their decoding, and `verify`'s checksums). What a reader of
    /// object storage that wants only some blocks opens with.
    pub lazy: bool,
}

impl Store {
    /// Opens a store with the default [`OpenOptions`] (structural checks and `base.bin`'s
    /// checksum; not the other files' checksums). `dir` may hold a URL ([`Location::of_path`]).
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        Self::open_with(dir, OpenOptions::default())
    }

    /// Opens a store, checking the manifest, the base mesh (its CRC-32 included), every file's
    /// size against the manifest, and the structure that random access relies on (see the
    /// `check` module: counts, the block index, every block decoding to its nodes; one pass over
    /// `blocks.bin`);
    /// with [`OpenOptions::verify_checksums`], every file's CRC-32 as well.
    pub fn open_with(dir: &Path, options: OpenOptions) -> Result<Self, StoreError> {
        Self::open_visiting(dir, options, |_| {})
    }

    /// Opens a store like [`Self::open_with`] and hands every node to `visit`, block by block in
    /// id order, as the structural check decodes them: a reader that needs every node (a server
    /// loading its metadata) decodes the store once, not twice.
    pub fn open_visiting(
        dir: &Path,
        options: OpenOptions,
        visit: impl FnMut(Vec<DetailNode>),
    ) -> Result<Self, StoreError> {
        Self::open_at(&Location::of_path(dir)?, options, visit)
    }

    /// Opens a store wherever it is ([`Location`]), as [`Self::open_visiting`] does a directory.
    pub fn open_at(
        location: &Location,
        options: OpenOptions,
        mut visit: impl FnMut(Vec<DetailNode>),
    ) -> Result<Self, StoreError> {
        let files = Files::open(location)?;
        let dir = &location.name("");
        let dir = dir.as_path();
        let mpath = files.name("manifest.json");
        let (manifest, _) = read_manifest(&files)?;
        for (name, sum) in &manifest.files {
            // only the store's own files: a name like `../x` or `/dev/zero` is never opened
            if !STORE_FILES.contains(&name.as_str())
                && !OPTIONAL_STORE_FILES.contains(&name.as_str())
            {
                return Err(StoreError::Corrupt {
                    path: mpath,
                    reason: format!("{name:?} is not a file of a store"),
                });
            }
            if options.lazy {
                continue;
            }
            let p = files.name(name);
            let Some(len) = files.size(name)? else {
                return Err(crate::io_err(&p)(std::io::ErrorKind::NotFound.into()));
            };
            if len != sum.bytes {
                return Err(StoreError::Corrupt {
                    path: p,
                    reason: format!("{len} bytes, manifest says {}", sum.bytes),
                });
            }
        }
        let bpath = files.name("base.bin");
        let base_len = manifest.files.get("base.bin").map_or(0, |s| s.bytes);
        if base_len > MAX_BASE_BYTES as u64 {
            return Err(StoreError::Corrupt {
                path: bpath,
                reason: format!("{base_len} bytes exceeds the {MAX_BASE_BYTES}-byte limit"),
            });
        }
        let base_bytes = files.read("base.bin")?;
        // the base mesh is small and every render depends on it: its checksum is always checked
        check_crc(&files, "base.bin", &base_bytes, &manifest)?;
        // the index is read whole: first its size (StoreHead::decode then ties the manifest's node
        // count to the base mesh)
        let ipath = files.name("block_index.bin");
        let want = (manifest.counts.nodes.div_ceil(BLOCK) + 1).checked_mul(8);
        let index_len = match options.lazy {
            true => manifest.files.get("block_index.bin").map(|s| s.bytes),
            false => files.size("block_index.bin")?,
        };
        if index_len != want {
            return Err(StoreError::Corrupt {
                path: ipath,
                reason: format!(
                    "{} bytes, the manifest's {} nodes need 8 per block of {BLOCK} and \
                     8 more",
                    index_len.map_or("no".into(), |l| l.to_string()),
                    manifest.counts.nodes
                ),
            });
        }
        let index_bytes = files.read("block_index.bin")?;
        let head =
            StoreHead::decode(manifest, &base_bytes, &index_bytes).map_err(
                |source| match source {
                    FormatError::BadIndex(reason) => StoreError::Corrupt {
                        path: ipath.clone(),
                        reason,
                    },
                    source => StoreError::Format {
                        path: dir.to_path_buf(),
                        source,
                    },
                },
            )?;
        // every block's checksum, checked whenever a block is decoded from now on
        let spath = files.name(BLOCK_SUMS_FILE);
        let sums = match files.read(BLOCK_SUMS_FILE) {
            Ok(b) => b,
            Err(StoreError::Io { source, .. }) if source.kind() == std::io::ErrorKind::NotFound => {
                return Err(StoreError::Corrupt {
                    path: spath,
                    reason: "missing: every block's checksum is read from it".into(),
                })
            }
            Err(e) => return Err(e),
        };
        let head = head.with_sums(&sums).map_err(|e| StoreError::Corrupt {
            path: spath,
            reason: e.to_string(),
        })?;
        let preview = read_preview(&files, &head)?;
        // the structure pass decodes every block once: the preview's masks are compared there
        let mut differs = None;
        let mut check = |part: Vec<DetailNode>| {
            if let (Some(p), None) = (&preview, differs) {
                differs = part
                    .iter()
                    .take_while(|n| (n.id as usize) < p.len())
                    .find(|n| {
                        let q = &p[n.id as usize];
                        (q.owned, q.empty_children) != (n.owned, n.empty_children)
                    })
                    .map(|n| n.id);
            }
            visit(part)
        };
        if !options.lazy {
            crate::check::structure(&files, &head, &mut check)?;
        }
        if let Some(id) = differs {
            return Err(StoreError::Corrupt {
                path: files.name(PREVIEW_FILE),
                reason: format!(
                    "its node {id} has other owned or empty masks than the store's: not the \
                     store's first nodes"
                ),
            });
        }
        let store = Store {
            location: location.clone(),
            dir: dir.to_path_buf(),
            manifest: head.manifest.clone(),
            base: head.base.clone(),
            preview,
            head,
            files,
        };
        if options.verify_checksums {
            store.check_sums()?;
        }
        Ok(store)
    }

    pub fn forest(&self) -> Forest {
        self.base.forest()
    }

    /// Codes and decodes this store's blocks (its base mesh and encoding): what a server sends is
    /// coded with it, as the store's own blocks are.
    pub fn coder(&self) -> &BlockCoder {
        &self.head.coder
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
            let p = self.files.name(name);
            let len = sum.bytes;
            let mut h = crc32fast::Hasher::new();
            let mut at = 0;
            while at < len {
                let end = (at + (8 << 20)).min(len);
                h.update(&self.files.read_range(name, at..end)?);
                at = end;
            }
            if self.files.size(name)? != Some(len) {
                return Err(StoreError::Corrupt {
                    path: p,
                    reason: format!("not {len} bytes as the manifest says"),
                });
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

    /// Every node's empty-children mask, by id (bit `i`: child `i` lies outside the input domain), as
    /// the renderers' `uniform_level` wants it.
    pub fn empty_children(&self) -> Result<Vec<u8>, StoreError> {
        let n = self.manifest.counts.nodes;
        let mut out = Vec::with_capacity(n as usize);
        let mut from = 0;
        while from < n {
            let to = (from + (1 << 16)).min(n);
            out.extend(self.read_nodes(from, to)?.iter().map(|d| d.empty_children));
            from = to;
        }
        Ok(out)
    }

    /// The sampled values `verify` compares synthesis with, when the store keeps them
    /// ([`REFERENCE_FILE`]: the manifest lists it).
    pub fn read_reference(&self) -> Result<Option<Vec<f32>>, StoreError> {
        if !self.manifest.files.contains_key(REFERENCE_FILE) {
            return Ok(None);
        }
        let p = self.files.name(REFERENCE_FILE);
        let b = self.files.read(REFERENCE_FILE)?;
        if b.len() as u64 != self.manifest.counts.vertices * 4 {
            return Err(StoreError::Corrupt {
                path: p,
                reason: "size disagrees with the vertex count".into(),
            });
        }
        Ok(Some(
            b.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        ))
    }

    /// The signed distance to the input domain's boundary at every finest-level vertex (by vertex
    /// key; positive inside), when the store has one: `levelset.f32` when the manifest lists it,
    /// else computed at every vertex's position when the near band is a box domain.
    pub fn read_levelset(&self) -> Result<Option<Vec<f32>>, StoreError> {
        if !self.manifest.files.contains_key("levelset.f32") {
            let Some([lo, hi]) = self
                .read_levelset_near()?
                .and_then(|(_, near)| near.domain_box())
            else {
                return Ok(None);
            };
            let keys = self.base.vertex_keys();
            let mut out = vec![0f32; keys.vertex_count() as usize];
            for (entity, _) in keys.entities() {
                keys.for_each_in(entity, |key, tet, w| {
                    let p = self.base.position(tet, &w);
                    out[key as usize] = box_signed_distance(lo, hi, p) as f32;
                });
            }
            return Ok(Some(out));
        }
        let p = self.files.name("levelset.f32");
        let b = self.files.read("levelset.f32")?;
        if b.len() as u64 != self.manifest.counts.vertices * 4 {
            return Err(StoreError::Corrupt {
                path: p,
                reason: "size disagrees with the vertex count".into(),
            });
        }
        let ls: Vec<f32> = b
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if let Some(k) = ls.iter().position(|x| x.is_nan()) {
            return Err(StoreError::Corrupt {
                path: p,
                reason: format!("vertex {k}: the level set is NaN"),
            });
        }
        Ok(Some(ls))
    }

    /// The level set's near band (`levelset_near.bin`), when the store has one: its coded bytes,
    /// as `/v1/levelset` serves them, and what they decode to (checked: keys within the vertex
    /// count, values finite).
    pub fn read_levelset_near(&self) -> Result<Option<(Vec<u8>, NearLevelSet)>, StoreError> {
        if !self.manifest.has_levelset_band() {
            return Ok(None);
        }
        let p = self.files.name(LEVELSET_BAND_FILE);
        let b = self.files.read(LEVELSET_BAND_FILE)?;
        let near = NearLevelSet::decode(&b, self.manifest.counts.vertices).map_err(|e| {
            StoreError::Corrupt {
                path: p,
                reason: e.to_string(),
            }
        })?;
        Ok(Some((b, near)))
    }

    /// Every finest-level vertex value (by vertex key), synthesized from all nodes.
    /// Nodes are read 2^16 at a time, so only one such batch is decoded at once.
    pub fn synthesize_all(&self) -> Result<Vec<f32>, StoreError> {
        const CHUNK: u64 = 1 << 16;
        let total = self.manifest.counts.nodes;
        let mut read_error = None;
        let nodes = (0..total.div_ceil(CHUNK))
            .map_while(
                |c| match self.read_nodes(c * CHUNK, ((c + 1) * CHUNK).min(total)) {
                    Ok(batch) => Some(batch),
                    Err(e) => {
                        read_error = Some(e);
                        None
                    }
                },
            )
            .flatten();
        let values = synthesize_all(&self.base, &self.base.vertex_keys(), nodes);
        if let Some(e) = read_error {
            return Err(e);
        }
        values.map_err(|source| StoreError::Synthesis {
            path: self.dir.clone(),
            source,
        })
    }
}

/// Decodes `preview.bin` when the manifest describes a preview, checking that it holds exactly
/// the nodes of the node levels it names, block by block (their masks against the store's are
/// compared by the structure pass).
fn read_preview(files: &Files, head: &StoreHead) -> Result<Option<Vec<DetailNode>>, StoreError> {
    let (manifest, base) = (&head.manifest, &head.base);
    let path = files.name(PREVIEW_FILE);
    let corrupt = |reason: String| StoreError::Corrupt {
        path: path.clone(),
        reason,
    };
    let listed = manifest.files.get(PREVIEW_FILE);
    let Some(p) = &manifest.preview else {
        return match listed {
            Some(_) => Err(corrupt(
                "listed, but the manifest describes no preview".into(),
            )),
            None => Ok(None),
        };
    };
    let Some(sum) = listed else {
        return Err(corrupt(
            "the manifest describes a preview but lists no file".into(),
        ));
    };
    let count = p
        .check_for(manifest.base_tets, manifest.levels)
        .map_err(|e| corrupt(format!("manifest.json: {e}")))?;
    // at most a full block's limit per block of nodes, as blocks.bin
    let nblocks = count.div_ceil(BLOCK);
    let limit = nblocks * MAX_BLOCK_BYTES;
    if sum.bytes > limit {
        return Err(corrupt(format!("{} bytes, beyond {limit}", sum.bytes)));
    }
    let bytes = files.read(PREVIEW_FILE)?;
    let coder = BlockCoder::for_preview(base, &p.encoding);
    let cfg = bincode::config::standard().with_limit::<{ MAX_BLOCK_BYTES as usize + 64 }>();
    let mut nodes = Vec::new();
    let mut rest = &bytes[..];
    for b in 0..nblocks {
        let (first, want) = (b * BLOCK, BLOCK.min(count - b * BLOCK));
        let (block, used): (NodeBlock, usize) = bincode::serde::decode_from_slice(rest, cfg)
            .map_err(|e| corrupt(format!("block {b}: {e}")))?;
        rest = &rest[used..];
        if block.first != first || block.count as u64 != want {
            return Err(corrupt(format!(
                "block {b} holds {} nodes from {}, not {want} from {first}",
                block.count, block.first
            )));
        }
        nodes.extend(
            coder
                .decode(&block)
                .map_err(|e| corrupt(format!("block {b}: {e}")))?,
        );
    }
    if !rest.is_empty() {
        return Err(corrupt(format!("{} trailing bytes", rest.len())));
    }
    if let Some((i, n)) = nodes.iter().enumerate().find(|(i, n)| n.id != *i as u64) {
        return Err(corrupt(format!(
            "node {} where the store's first {count} ids need {i}",
            n.id
        )));
    }
    Ok(Some(nodes))
}

/// A store's manifest, read and parsed, its format and version checked first (a store of another
/// version names other files: its reader should learn that it needs `prepare` again, not that a
/// file is foreign); and its length in bytes.
pub(crate) fn read_manifest(files: &Files) -> Result<(Manifest, u64), StoreError> {
    let mpath = files.name("manifest.json");
    let text = files.read("manifest.json")?;
    let manifest: Manifest =
        serde_json::from_slice(&text).map_err(|e| StoreError::BadManifest {
            path: mpath.clone(),
            reason: e.to_string(),
        })?;
    if manifest.format != STORE_FORMAT || manifest.version != STORE_VERSION {
        return Err(StoreError::Format {
            path: mpath,
            source: FormatError::Version {
                format: manifest.format,
                version: manifest.version,
            },
        });
    }
    Ok((manifest, text.len() as u64))
}

/// `bytes`, the whole of `file`, against the CRC-32 the manifest lists for it.
pub(crate) fn check_crc(
    files: &Files,
    file: &str,
    bytes: &[u8],
    manifest: &Manifest,
) -> Result<(), StoreError> {
    let Some(sum) = manifest.files.get(file) else {
        return Err(StoreError::Corrupt {
            path: files.name("manifest.json"),
            reason: format!("no checksum for {file}"),
        });
    };
    let got = crc32fast::hash(bytes);
    if got != sum.crc32 {
        return Err(StoreError::Corrupt {
            path: files.name(file),
            reason: format!("checksum {got:08x}, manifest says {:08x}", sum.crc32),
        });
    }
    Ok(())
}
