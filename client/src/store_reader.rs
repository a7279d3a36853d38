//! A local store directory read from the client side (for `tetwave render <store>` and the
//! benchmarks), through the protocol's store format: the same decoding the server uses.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use tetwave_protocol::store_format::{FormatError, Manifest, StoreFiles, StoreHead};
use tetwave_protocol::synthesis::{synthesize_all, SynthesisError};
use tetwave_protocol::{BaseMesh, DetailNode, TetId};

#[derive(Debug, thiserror::Error)]
pub enum StoreReadError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {reason}")]
    Manifest { path: PathBuf, reason: String },
    #[error("store: {0}")]
    Format(#[from] FormatError),
    #[error("store: synthesis failed: {0}")]
    Synthesis(#[from] SynthesisError),
}

struct Dir(PathBuf);

impl StoreFiles for Dir {
    type Error = StoreReadError;
    fn read_at(&self, file: &str, offset: u64, buf: &mut [u8]) -> Result<(), StoreReadError> {
        let path = self.0.join(file);
        let io = |source| StoreReadError::Io {
            path: path.clone(),
            source,
        };
        let mut f = File::open(&path).map_err(io)?;
        f.seek(SeekFrom::Start(offset)).map_err(io)?;
        f.read_exact(buf).map_err(io)
    }
}

/// An open local store.
pub struct LocalStore {
    head: StoreHead,
    dir: Dir,
}

impl LocalStore {
    pub fn open(dir: &Path) -> Result<Self, StoreReadError> {
        let read = |name: &str| {
            let path = dir.join(name);
            std::fs::read(&path).map_err(|source| StoreReadError::Io { path, source })
        };
        let text = read("manifest.json")?;
        let manifest: Manifest =
            serde_json::from_slice(&text).map_err(|e| StoreReadError::Manifest {
                path: dir.join("manifest.json"),
                reason: e.to_string(),
            })?;
        let head = StoreHead::decode(manifest, &read("base.bin")?, &read("coeff_index.bin")?)?;
        Ok(LocalStore {
            head,
            dir: Dir(dir.to_path_buf()),
        })
    }

    pub fn manifest(&self) -> &Manifest {
        &self.head.manifest
    }

    pub fn base(&self) -> &BaseMesh {
        &self.head.base
    }

    /// Nodes `from..to`.
    pub fn read_nodes(&self, from: TetId, to: TetId) -> Result<Vec<DetailNode>, StoreReadError> {
        self.head.read_nodes(&self.dir, from, to)
    }

    /// Every finest-level vertex value (by vertex key), from all nodes.
    pub fn synthesize_all(&self) -> Result<Vec<f32>, StoreReadError> {
        let nodes = self.read_nodes(0, self.head.manifest.counts.nodes)?;
        Ok(synthesize_all(
            self.base(),
            &self.base().vertex_keys(),
            nodes,
        )?)
    }
}
