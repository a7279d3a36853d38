//! A store read by a client with no server: the manifest, the base mesh and the first page of
//! the block index at open (two round trips), then blocks as the client's own selection asks for
//! them, each block one range of `blocks.bin` and the index a page of [`INDEX_PAGE`] entries
//! at a time. What it holds grows with what was asked, never with the store: one page of index
//! covers 2 M nodes.

use crate::location::{Files, Location};
use crate::StoreError;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::store_format::{
    FormatError, Manifest, StoreHead, BLOCK, BLOCK_SUMS_FILE, LEVELSET_BAND_FILE, MAX_BASE_BYTES,
};
use tetwave_protocol::{BaseMesh, DetailNode};

/// A page of the block index and the same blocks' checksums.
struct Page {
    entries: Vec<u64>,
    sums: Vec<u32>,
}

/// Entries of `block_index.bin` fetched at once: 4 KiB, the offsets of 512 blocks (2 M nodes).
pub const INDEX_PAGE: u64 = 512;

/// A store opened for reading by blocks ([`PagedStore::read_blocks`]).
pub struct PagedStore {
    pub location: Location,
    /// The level set's near band, when the store has one (fetched at open with the base mesh).
    pub levelset_near: Option<NearLevelSet>,
    /// Manifest, base and coder (its `index` is empty: the pages below stand in).
    head: StoreHead,
    files: Files,
    /// Index page `p`: entries `p·INDEX_PAGE ..= (p+1)·INDEX_PAGE` (the last page's up to the
    /// final entry), and those blocks' checksums (`block_sums.bin`).
    pages: Mutex<HashMap<u64, Page>>,
    bytes: AtomicU64,
    requests: AtomicU64,
}

impl PagedStore {
    /// Reads the manifest, then the base mesh, the index's first page and the level set's band
    /// together; checks them as [`crate::Store::open`] does (base checksum, counts, index
    /// entries).
    pub fn open(location: &Location) -> Result<PagedStore, StoreError> {
        let files = Files::open(location)?;
        let mpath = files.name("manifest.json");
        let (manifest, manifest_bytes) = crate::read::read_manifest(&files)?;
        let format = |source: FormatError| StoreError::Format {
            path: mpath.clone(),
            source,
        };
        let listed = |name: &str| {
            manifest
                .files
                .get(name)
                .cloned()
                .ok_or_else(|| StoreError::Corrupt {
                    path: mpath.clone(),
                    reason: format!("{name} is not listed"),
                })
        };
        let base_sum = listed("base.bin")?;
        if base_sum.bytes > MAX_BASE_BYTES as u64 {
            return Err(StoreError::Corrupt {
                path: files.name("base.bin"),
                reason: format!(
                    "{} bytes exceeds the {MAX_BASE_BYTES}-byte limit",
                    base_sum.bytes
                ),
            });
        }
        let index_sum = listed("block_index.bin")?;
        let nblocks = manifest.counts.nodes.div_ceil(BLOCK);
        if index_sum.bytes != (nblocks + 1) * 8 {
            return Err(StoreError::Corrupt {
                path: files.name("block_index.bin"),
                reason: format!(
                    "{} bytes, the manifest's {} nodes need 8 per block of {BLOCK} and 8 more",
                    index_sum.bytes, manifest.counts.nodes
                ),
            });
        }
        if listed(BLOCK_SUMS_FILE)?.bytes != nblocks * 4 {
            return Err(StoreError::Corrupt {
                path: files.name(BLOCK_SUMS_FILE),
                reason: format!("not 4 bytes for each of the {nblocks} blocks"),
            });
        }
        let mut want = vec![
            ("base.bin", 0..base_sum.bytes),
            ("block_index.bin", page_range(0, nblocks)),
            (BLOCK_SUMS_FILE, sums_range(0, nblocks)),
        ];
        let band = manifest.has_levelset_band();
        if band {
            want.push((LEVELSET_BAND_FILE, 0..listed(LEVELSET_BAND_FILE)?.bytes));
        }
        let mut got = files.read_many(&want)?.into_iter();
        let (base_bytes, page0, sums0) = (
            got.next().unwrap_or_default(),
            got.next().unwrap_or_default(),
            got.next().unwrap_or_default(),
        );
        crate::read::check_crc(&files, "base.bin", &base_bytes, &manifest)?;
        let base = StoreHead::decode_base(&manifest, &base_bytes).map_err(format)?;
        let levelset_near =
            match got.next() {
                Some(b) => Some(NearLevelSet::decode(&b, manifest.counts.vertices).map_err(
                    |e| StoreError::Corrupt {
                        path: files.name(LEVELSET_BAND_FILE),
                        reason: e.to_string(),
                    },
                )?),
                None => None,
            };
        let coder = tetwave_protocol::block::BlockCoder::new(&base, &manifest.encoding);
        let fetched = want.iter().map(|w| w.1.end - w.1.start).sum::<u64>() + manifest_bytes;
        let store = PagedStore {
            location: location.clone(),
            levelset_near,
            head: StoreHead {
                manifest,
                base,
                index: Vec::new(),
                coder,
                sums: None,
            },
            files,
            pages: Mutex::new(HashMap::new()),
            bytes: AtomicU64::new(fetched),
            requests: AtomicU64::new(1 + want.len() as u64),
        };
        store.keep_page(0, &page0, &sums0)?;
        Ok(store)
    }

    /// The store's manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.head.manifest
    }

    /// The store's base mesh.
    pub fn base(&self) -> &BaseMesh {
        &self.head.base
    }

    /// Blocks of `blocks.bin` (`ceil(nodes / BLOCK)`); block `b` holds ids `b·BLOCK ..`.
    pub fn blocks(&self) -> u64 {
        self.head.manifest.counts.nodes.div_ceil(BLOCK)
    }

    /// Bytes fetched so far (manifest, base, index pages, band, blocks).
    pub fn bytes_read(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    /// Requests made so far (a coalesced range read counts once per file).
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }

    /// Checks and keeps index page `p`.
    fn keep_page(&self, p: u64, bytes: &[u8], sums: &[u8]) -> Result<(), StoreError> {
        let path = self.files.name("block_index.bin");
        let entries = StoreHead::decode_index(bytes, p * INDEX_PAGE).map_err(|e| match e {
            FormatError::BadIndex(reason) => StoreError::Corrupt {
                path: path.clone(),
                reason,
            },
            source => StoreError::Format {
                path: path.clone(),
                source,
            },
        })?;
        let nblocks = self.blocks();
        let last_page = (p + 1) * INDEX_PAGE >= nblocks;
        let blocks_len = self.head.manifest.files.get("blocks.bin").map(|f| f.bytes);
        if last_page && entries.last().copied() != blocks_len {
            return Err(StoreError::Corrupt {
                path,
                reason: format!(
                    "its last entry ({:?}) is not blocks.bin's length ({blocks_len:?})",
                    entries.last()
                ),
            });
        }
        let sums = tetwave_protocol::store_format::decode_sums(sums);
        if sums.len() + 1 != entries.len() {
            return Err(StoreError::Corrupt {
                path: self.files.name(BLOCK_SUMS_FILE),
                reason: format!(
                    "page {p}: {} checksums for {} blocks",
                    sums.len(),
                    entries.len() - 1
                ),
            });
        }
        let page = Page { entries, sums };
        self.pages.lock().expect("index pages").insert(p, page);
        Ok(())
    }

    /// Byte range of block `b` in `blocks.bin` and its checksum, when its index page is held.
    fn span(&self, b: u64) -> Option<(std::ops::Range<u64>, u32)> {
        let pages = self.pages.lock().expect("index pages");
        let page = pages.get(&(b / INDEX_PAGE))?;
        let i = (b % INDEX_PAGE) as usize;
        Some((page.entries[i]..page.entries[i + 1], page.sums[i]))
    }

    /// Decodes blocks `blocks` (each checked: its node count and ids), fetching the index pages
    /// they need first (together), then their bytes (one request per run of neighbouring
    /// blocks). Returns each block's nodes in the order asked.
    pub fn read_blocks(&self, blocks: &[u64]) -> Result<Vec<Vec<DetailNode>>, StoreError> {
        let nblocks = self.blocks();
        if let Some(&b) = blocks.iter().find(|&&b| b >= nblocks) {
            return Err(StoreError::Format {
                path: self.files.name("blocks.bin"),
                source: FormatError::RangeOutOfBounds {
                    from: b * BLOCK,
                    to: (b + 1) * BLOCK,
                    nodes: self.head.manifest.counts.nodes,
                },
            });
        }
        let mut missing: Vec<u64> = {
            let pages = self.pages.lock().expect("index pages");
            blocks
                .iter()
                .map(|b| b / INDEX_PAGE)
                .filter(|p| !pages.contains_key(p))
                .collect()
        };
        missing.sort_unstable();
        missing.dedup();
        if !missing.is_empty() {
            let want: Vec<_> = missing
                .iter()
                .flat_map(|&p| {
                    [
                        ("block_index.bin", page_range(p, nblocks)),
                        (BLOCK_SUMS_FILE, sums_range(p, nblocks)),
                    ]
                })
                .collect();
            let got = self.files.read_many(&want)?;
            for (&p, pair) in missing.iter().zip(got.chunks(2)) {
                self.count(pair[0].len() + pair[1].len(), 2);
                self.keep_page(p, &pair[0], &pair[1])?;
            }
        }
        let spans: Vec<_> = blocks
            .iter()
            .map(|&b| self.span(b).expect("its page was fetched"))
            .collect();
        let ranges: Vec<_> = spans.iter().map(|(r, _)| r.clone()).collect();
        let got = self.files.read_ranges("blocks.bin", &ranges)?;
        self.count(got.iter().map(Vec::len).sum(), 1);
        let corrupt = |reason: String| StoreError::Corrupt {
            path: self.files.name("blocks.bin"),
            reason,
        };
        blocks
            .iter()
            .zip(spans)
            .zip(got)
            .map(|((&b, (r, want)), bytes)| {
                // a block whose bytes are not the ones written is refused before it is decoded
                let crc = crc32fast::hash(&bytes);
                if crc != want {
                    return Err(corrupt(format!(
                        "block {b} (bytes {}..{}): checksum {crc:08x}, {BLOCK_SUMS_FILE} says \
                         {want:08x}",
                        r.start, r.end
                    )));
                }
                self.head
                    .decode_block(b, &bytes)
                    .map_err(|e| corrupt(e.to_string()))
            })
            .collect()
    }

    fn count(&self, bytes: usize, requests: u64) {
        self.bytes.fetch_add(bytes as u64, Ordering::Relaxed);
        self.requests.fetch_add(requests, Ordering::Relaxed);
    }
}

/// Bytes of `block_sums.bin` for the blocks of index page `p`.
fn sums_range(p: u64, nblocks: u64) -> std::ops::Range<u64> {
    let first = p * INDEX_PAGE;
    let last = ((p + 1) * INDEX_PAGE).min(nblocks);
    first * 4..last * 4
}

/// Bytes of index page `p` of a store of `nblocks` blocks: entries `p·INDEX_PAGE` through
/// `min((p+1)·INDEX_PAGE, nblocks)`.
fn page_range(p: u64, nblocks: u64) -> std::ops::Range<u64> {
    let first = p * INDEX_PAGE;
    let last = ((p + 1) * INDEX_PAGE).min(nblocks);
    first * 8..(last + 1) * 8
}
