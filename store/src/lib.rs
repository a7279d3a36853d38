//! # tetwave-store
//!
//! The one reader and writer of a tetwave store, for both sides: a directory holding a JSON
//! manifest, the base mesh, one fixed-size record per node and the coefficients in node order, with
//! a block index for random access by node id range.
//!
//! | file              | contents                                                                  |
//! |-------------------|---------------------------------------------------------------------------|
//! | `manifest.json`   | [`Manifest`]: dataset, bounds, sizes, counts, encoding, bound, checksums    |
//! | `base.bin`        | bincode [`BaseMesh`](tetwave_protocol::BaseMesh)                            |
//! | `blocks.bin`      | the nodes in blocks of [`BLOCK`] consecutive ids, each block's bytes those |
//! |                   | of [`BlockCoder::encode`](tetwave_protocol::block::BlockCoder::encode)      |
//! | `block_index.bin` | u64 LE byte offset of each block in `blocks.bin`, then the file's length  |
//! | `block_sums.bin`  | u32 LE CRC-32 of each block, checked whenever a block is read             |
//! | `reference.f32`   | optional: the sampled value of every vertex (`--keep-reference`; for     |
//! |                   | `verify`, not streamed)                                                   |
//! | `levelset.f32`    | optional: per vertex key, the signed distance to the input domain's        |
//! |                   | boundary (positive inside), for clipping straddling tets; not streamed     |
//! | `levelset_near.bin` | with `levelset.f32`: its near band, coded                                 |
//! |                   | ([`NearLevelSet`](tetwave_protocol::levelset::NearLevelSet)), served whole |
//! |                   | at `/v1/levelset` to streaming clients                                    |
//!
//! The blocks are what the wire carries (a `Nodes` frame is a coded block of any id set): the
//! stream carries what the store holds. Reading nodes `a..b` reads the covering blocks' bytes (one
//! read, at most one block of 4096 nodes before `a` and after `b`) and decodes them: never the
//! whole file.

use std::path::{Path, PathBuf};
pub use tetwave_protocol::store_format::{
    Counts, Encoding, FileSum, FormatError, Manifest, Physical, Preview, StoreFiles, StoreHead,
    BLOCK, BLOCK_SUMS_FILE, LEVELSET_BAND_FILE, MAX_BLOCK_BYTES, PREVIEW_FILE, STORE_FORMAT,
    STORE_VERSION,
};

mod check;
pub mod location;
pub mod paged;
mod read;
mod write;

pub use location::Location;
pub use paged::PagedStore;
pub use read::{OpenOptions, Store};
pub use write::{
    delete_file, download_file, histogram_inside, upload, upload_file, write, write_streamed,
    PreviewNodes, StoreContent, StoreMeta, Totals,
};

/// The files of a store besides `manifest.json`, each with its size and CRC-32 in the manifest.
pub const STORE_FILES: [&str; 4] = ["base.bin", "blocks.bin", "block_index.bin", BLOCK_SUMS_FILE];

/// Files a store may have besides [`STORE_FILES`]; when present they are listed in the manifest
/// with their size and CRC-32 like the others.
pub const OPTIONAL_STORE_FILES: [&str; 4] = [
    REFERENCE_FILE,
    "levelset.f32",
    LEVELSET_BAND_FILE,
    PREVIEW_FILE,
];

/// The sampled value of every vertex, written only when asked (`prepare --keep-reference`): a
/// copy of the samples, as large as the input, that nothing streams; `verify --input` checks a
/// store against its input instead.
pub const REFERENCE_FILE: &str = "reference.f32";

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
    #[error("{location}: {reason}")]
    Location { location: String, reason: String },
    /// A request to object storage failed (after its retries).
    #[error("{path}: {reason}")]
    Object { path: PathBuf, reason: String },
    #[error("{path}: synthesis failed: {source}")]
    Synthesis {
        path: PathBuf,
        source: tetwave_protocol::synthesis::SynthesisError,
    },
}

impl From<FormatError> for StoreError {
    fn from(source: FormatError) -> Self {
        StoreError::Format {
            path: PathBuf::from("store"),
            source,
        }
    }
}

/// This machine's memory in bytes (`MemTotal` of `/proc/meminfo`; 4 GiB assumed where it cannot
/// be read): what the default memory bounds of both sides (`prepare --memory`, a client's leaf
/// budget) are shares of.
pub fn machine_memory() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("MemTotal:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        })
        .map(|kb| kb * 1024)
        .unwrap_or(4 << 30)
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}
