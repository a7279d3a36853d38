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
//! | `nodes.bin`       | per node 6 bytes: owned mask u8, empty children u8, subtree max |d| f32 LE |
//! | `coeffs.bin`      | owned coefficients, node order then edge order: f32 LE, or quantized codes |
//! |                   | as signed little-endian integers of `ceil(bits/8)` bytes                   |
//! | `coeff_index.bin` | u64 LE per block of [`BLOCK`] nodes: coefficients before the block         |
//! | `reference.f32`   | the sampled value of every vertex (for `verify`; not streamed)             |
//!
//! Reading nodes `a..b` touches one index entry, at most [`BLOCK`] node records before `a`, and the
//! range's own records and coefficients: never the whole file.

use std::path::{Path, PathBuf};
pub use tetwave_protocol::store_format::{
    encode_node_record, Counts, Encoding, FileSum, FormatError, Manifest, StoreFiles, StoreHead,
    BLOCK, STORE_FORMAT, STORE_VERSION,
};

mod check;
mod read;
mod write;

pub use read::{OpenOptions, Store};
pub use write::{write, StoreContent, StoreMeta};

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

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}
