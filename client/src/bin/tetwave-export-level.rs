//! Writes one uniform level of a store as a legacy binary `.vtk` unstructured grid (the exact tets
//! and vertex values `tetwave render STORE --levels L` draws), for renderers outside tetwave:
//! `scripts/speed-accuracy.py` draws it with VTK's `vtkProjectedTetrahedraMapper`.
//!
//! `tetwave-export-level STORE LEVEL OUT.vtk` (built with the client: `cargo build --release --locked -p
//! tetwave-client`; a helper for benchmarks, not a user command).
//!
//! Prints one JSON object: level, tets, vertices, value_range (the store's display range, which
//! `tetwave render` maps to the transfer function's [0, 1]), bounds. A store with a level set is
//! refused: its image is clipped inside the tets, which a plain unstructured grid cannot say.

use anyhow::{bail, Context, Result};
use tetwave_source::load::store_mesh;
use tetwave_store::Store;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [store, level, out] = args.as_slice() else {
        bail!("usage: tetwave-export-level STORE LEVEL OUT.vtk");
    };
    let level: u8 = level.parse().context("LEVEL must be a small integer")?;
    let store = Store::open(std::path::Path::new(store))
        .with_context(|| format!("opening store {store}"))?;
    let (mesh, level) = store_mesh(&store, Some(level))?;
    if mesh.levelset.is_some() {
        bail!("the store has a level set: its image is clipped inside tets, which a .vtk grid cannot carry");
    }
    mesh.write_vtk(std::path::Path::new(out))
        .with_context(|| format!("writing {out}"))?;
    let (lo, hi) = mesh.bounds();
    println!(
        "{}",
        serde_json::json!({
            "level": level,
            "tets": mesh.tets.len(),
            "vertices": mesh.positions.len(),
            "value_range": [mesh.value_range.0, mesh.value_range.1],
            "bounds": [lo.to_array(), hi.to_array()],
            "output": out,
        })
    );
    Ok(())
}
