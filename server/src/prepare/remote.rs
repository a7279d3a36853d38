//! `prepare --out s3://BUCKET/PREFIX`: a store (or a part) is written to a local staging folder
//! as for a directory, then copied to the bucket (large files in parts, the manifest last;
//! `store::upload`) and the folder removed. `--parts N --finish` first copies the parts' files
//! down from the bucket, and removes them there once the store is written. An HTTP(S) folder is
//! read-only and refused as `--out`.

use super::parts::{part_rel, NODES_FILE, SUMMARY_FILE};
use super::{PrepareError, PrepareOptions, Summary};
use std::path::PathBuf;
use tetwave_store::{self as store, Location};

/// Where `--out` points when it is object storage; `None` for a directory.
pub(super) fn remote_out(o: &PrepareOptions) -> Result<Option<Location>, PrepareError> {
    let out = o.out.to_string_lossy();
    match Location::parse(&out)? {
        Location::Dir(_) => Ok(None),
        Location::Http { .. } => Err(PrepareError::Usage(format!(
            "--out {out}: an HTTP(S) folder is read-only; write to a directory or s3://BUCKET/PREFIX \
             (and serve that over HTTP)"
        ))),
        s3 => Ok(Some(s3)),
    }
}

/// A local folder that is removed when dropped.
struct Stage(PathBuf);

impl Stage {
    fn new(o: &PrepareOptions) -> Result<Stage, PrepareError> {
        let root = o.stage.clone().unwrap_or_else(std::env::temp_dir);
        let dir = root.join(format!("tetwave-stage-{}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| {
            PrepareError::Usage(format!(
                "{}: cannot make the staging folder (give --stage DIR): {e}",
                dir.display()
            ))
        })?;
        Ok(Stage(dir))
    }
}

impl Drop for Stage {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A whole store (or `--finish`) written to `to`.
pub(super) fn prepare_to(o: &PrepareOptions, to: &Location) -> Result<Summary, PrepareError> {
    let stage = Stage::new(o)?;
    let local = PrepareOptions {
        out: stage.0.clone(),
        ..o.clone()
    };
    let finish = match (o.by_parts.parts, o.by_parts.finish) {
        (Some(n), true) => Some(n),
        _ => None,
    };
    if let Some(n) = finish {
        for k in 0..n {
            let rel = part_rel(n, k);
            let dir = stage.0.join(&rel);
            std::fs::create_dir_all(&dir).map_err(|e| store::StoreError::Io {
                path: dir.clone(),
                source: e,
            })?;
            // the summary only when the nodes came: a part without them is one not done
            if store::download_file(&to.join(&rel), NODES_FILE, &dir.join(NODES_FILE))? {
                store::download_file(&to.join(&rel), SUMMARY_FILE, &dir.join(SUMMARY_FILE))?;
            }
        }
    }
    tracing::info!(staging = %stage.0.display(), "writing the store here before copying it to {to}");
    let mut s = super::prepare(&local)?;
    tracing::info!("copying the store to {to}");
    store::upload(&stage.0, to)?;
    if let Some(n) = finish {
        for k in 0..n {
            let at = to.join(&part_rel(n, k));
            store::delete_file(&at, SUMMARY_FILE)?;
            store::delete_file(&at, NODES_FILE)?;
        }
    }
    s.store = to.to_string();
    Ok(s)
}

/// Part `k` of `n` written to `to`'s `parts/part-K-of-N/`: its nodes, then its summary (what
/// says the part is done).
pub(super) fn prepare_part_to(
    o: &PrepareOptions,
    n: u32,
    k: u32,
    to: &Location,
) -> Result<super::parts::PartSummary, PrepareError> {
    let stage = Stage::new(o)?;
    let local = PrepareOptions {
        out: stage.0.clone(),
        ..o.clone()
    };
    let p = super::parts::prepare_part(&local, n, k)?;
    let rel = part_rel(n, k);
    let at = to.join(&rel);
    // an earlier summary goes first: a copy cut short leaves the part not done
    store::delete_file(&at, SUMMARY_FILE)?;
    for file in [NODES_FILE, SUMMARY_FILE] {
        store::upload_file(&stage.0.join(&rel).join(file), &at, file)?;
    }
    Ok(p)
}
