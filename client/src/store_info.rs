//! Reads a store's manifest and base mesh and recomputes, from the protocol alone, the counts the
//! server wrote: a client-side check that both sides agree on the contract.

use serde::Serialize;
use std::path::{Path, PathBuf};
use tetwave_protocol::BaseMesh;

#[derive(Debug, thiserror::Error)]
pub enum InfoError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {reason}")]
    Bad { path: PathBuf, reason: String },
    #[error("{what}: manifest says {manifest}, the protocol computes {computed}")]
    Disagree {
        what: &'static str,
        manifest: u64,
        computed: u64,
    },
}

/// Counts derived on the client side from the base mesh.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct StoreInfo {
    pub dataset: String,
    pub base_tets: u64,
    pub levels: u8,
    pub tets_total: u64,
    pub leaves: u64,
    pub nodes: u64,
    pub vertices: u64,
    pub empty_base_tets: u64,
}

/// Loads `dir/manifest.json` and `dir/base.bin` and checks the manifest's counts.
pub fn store_info(dir: &Path) -> Result<StoreInfo, InfoError> {
    let mpath = dir.join("manifest.json");
    let text = std::fs::read_to_string(&mpath).map_err(|source| InfoError::Io {
        path: mpath.clone(),
        source,
    })?;
    let m: serde_json::Value = serde_json::from_str(&text).map_err(|e| InfoError::Bad {
        path: mpath.clone(),
        reason: e.to_string(),
    })?;
    let bpath = dir.join("base.bin");
    let bytes = std::fs::read(&bpath).map_err(|source| InfoError::Io {
        path: bpath.clone(),
        source,
    })?;
    let cfg = bincode::config::standard().with_limit::<{ 1 << 30 }>();
    let (base, _): (BaseMesh, usize) =
        bincode::serde::decode_from_slice(&bytes, cfg).map_err(|e| InfoError::Bad {
            path: bpath.clone(),
            reason: e.to_string(),
        })?;
    base.validate().map_err(|e| InfoError::Bad {
        path: bpath.clone(),
        reason: e.to_string(),
    })?;
    let f = base.forest();
    let info = StoreInfo {
        dataset: m["dataset"].as_str().unwrap_or("").to_string(),
        base_tets: f.n_base,
        levels: f.levels,
        tets_total: f.total_tets(),
        leaves: f.leaves(),
        nodes: f.nodes(),
        vertices: base.vertex_keys().vertex_count(),
        empty_base_tets: base.empty.iter().filter(|&&e| e).count() as u64,
    };
    let counts = &m["counts"];
    for (what, computed) in [
        ("tets_total", info.tets_total),
        ("leaves", info.leaves),
        ("nodes", info.nodes),
        ("vertices", info.vertices),
    ] {
        let manifest = counts[what].as_u64().ok_or_else(|| InfoError::Bad {
            path: mpath.clone(),
            reason: format!("counts.{what} missing"),
        })?;
        if manifest != computed {
            return Err(InfoError::Disagree {
                what,
                manifest,
                computed,
            });
        }
    }
    Ok(info)
}
