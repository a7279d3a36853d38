//! Recomputes, from the protocol alone, the counts a store's manifest declares: a client-side check
//! that both sides agree on the contract.

use serde::Serialize;
use std::path::Path;
use tetwave_store::{Store, StoreError};

#[derive(Debug, thiserror::Error)]
pub enum InfoError {
    #[error(transparent)]
    Read(#[from] StoreError),
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
    /// `parent` or `axes` (how new vertices are predicted, from the base mesh).
    pub predictor: &'static str,
}

/// Opens the store in `dir` and checks the manifest's counts against the protocol's.
pub fn store_info(dir: &Path) -> Result<StoreInfo, InfoError> {
    let store = Store::open(dir)?;
    let base = &store.base;
    let f = base.forest();
    let info = StoreInfo {
        dataset: store.manifest.dataset.clone(),
        base_tets: f.n_base,
        levels: f.levels,
        tets_total: f.total_tets(),
        leaves: f.leaves(),
        nodes: f.nodes(),
        vertices: base.vertex_keys().vertex_count(),
        empty_base_tets: base.empty.iter().filter(|&&e| e).count() as u64,
        predictor: base.predictor.name(),
    };
    let c = &store.manifest.counts;
    for (what, manifest, computed) in [
        ("tets_total", c.tets_total, info.tets_total),
        ("leaves", c.leaves, info.leaves),
        ("nodes", c.nodes, info.nodes),
        ("vertices", c.vertices, info.vertices),
    ] {
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
