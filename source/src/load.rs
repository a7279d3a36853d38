//! Reading what a source holds at once: a store's uniform level, a mesh file as it is, the
//! histogram `auto` is fitted to. Shared by `tetwave render`, the viewer and the benchmarks.

use std::path::{Path, PathBuf};
use tetwave_import::clean::{clean_import, CleanError, ImportOptions};
use tetwave_import::{format_of, read_mesh, ImportError, MeshFormat};
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TransferFunction, ValueHistogram, AUTO};
use tetwave_store::{Store, StoreError};

/// Why a store or mesh file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Import(#[from] ImportError),
    #[error("{path}: {source}")]
    Clean { path: PathBuf, source: CleanError },
    #[error("--levels {asked} exceeds the store's {levels} levels")]
    Level { asked: u8, levels: u8 },
}

/// The level-`level` mesh of a store (finest when `None`), clipped to the store's level set when
/// it has one, with the manifest's default value range
/// ([`Manifest::display_value_range`](tetwave_store::Manifest::display_value_range)).
pub fn store_mesh(store: &Store, level: Option<u8>) -> Result<(RenderMesh, u8), LoadError> {
    let levels = store.base.levels;
    let level = level.unwrap_or(levels);
    if level > levels {
        return Err(LoadError::Level {
            asked: level,
            levels,
        });
    }
    let values = store.synthesize_all()?;
    let empty = store.empty_children()?;
    let levelset = store.read_levelset()?;
    let mut mesh =
        RenderMesh::uniform_level_clipped(&store.base, &values, &empty, level, levelset.as_deref());
    let [lo, hi] = store.manifest.display_value_range();
    mesh.value_range = (lo, hi);
    Ok((mesh, level))
}

/// The value histogram the `auto` transfer function of a store fits to: the one its manifest
/// records (its finest vertices' samples inside the domain, what every client of the store,
/// streaming or not, fits to), whatever level is drawn, so that every level and every client draw
/// a store with the same colours. (A coarser level is not enough: a level-6 store of the heat sink
/// fitted to its level 5, whose lattice does not resolve the fins, drew 31.3 dB from its source's
/// image, 45.5 dB fitted to level 6.)
///
/// A store written before manifests recorded one: its finest level's
/// ([`ValueHistogram::of_mesh`], clipped to its level set; `drawn`, a level's mesh already built,
/// is reused when it is the finest), or past [`MOST_HISTOGRAM_LEAVES`] leaves its finest
/// vertices' samples ([`ValueHistogram::of_samples`]): building that level (100 M leaves at 257³)
/// would cost more than the drawing.
pub fn store_histogram(
    store: &Store,
    drawn: Option<(&RenderMesh, u8)>,
) -> Result<ValueHistogram, LoadError> {
    if let Some(h) = ValueHistogram::of_manifest(&store.manifest) {
        return Ok(h);
    }
    let finest = store.base.levels;
    match drawn {
        Some((mesh, l)) if l == finest => Ok(ValueHistogram::of_mesh(mesh)),
        _ if store.base.forest().level_len(finest) > MOST_HISTOGRAM_LEAVES => {
            let values = store.synthesize_all()?;
            let levelset = store.read_levelset()?;
            let [lo, hi] = store.manifest.display_value_range();
            Ok(ValueHistogram::of_samples(
                &values,
                (lo, hi),
                levelset.as_deref(),
            ))
        }
        _ => Ok(ValueHistogram::of_mesh(&store_mesh(store, None)?.0)),
    }
}

/// The most finest-level leaves [`store_histogram`] builds a store's mesh of.
pub const MOST_HISTOGRAM_LEAVES: u64 = 1 << 21;

/// Whether `tetwave render`'s input is a mesh file rather than a store directory: `--format`
/// given, or not a directory and either a mesh extension or an existing file.
pub fn is_mesh_input(path: &Path, format: Option<MeshFormat>) -> bool {
    format.is_some() || (!path.is_dir() && (format_of(path).is_some() || path.is_file()))
}

/// A mesh file as it is: its points, its cleaned tets (re-oriented, zero-volume and duplicate ones
/// dropped, other volume cells split into tets) and the chosen scalar, exactly as `prepare` reads
/// it before resampling. Returns the scalar's name too.
pub fn file_mesh(
    path: &Path,
    format: Option<MeshFormat>,
    options: &ImportOptions<'_>,
) -> Result<(RenderMesh, String), LoadError> {
    let imported = read_mesh(path, format)?;
    let (clean, report) = clean_import(imported, options).map_err(|source| LoadError::Clean {
        path: path.to_path_buf(),
        source,
    })?;
    if clean.distance && options.field.is_none() {
        // a geometry-only mesh: one line says what is drawn
        eprintln!(
            "{}: no point or cell arrays; drawing the distance to its boundary (--field distance)",
            path.display()
        );
    }
    let values = clean.values.iter().map(|&v| v as f32).collect();
    Ok((
        RenderMesh::new(clean.points, clean.tets, values),
        report.scalar,
    ))
}

/// `tf` (loaded from `spec`) fitted to `source`'s data when `spec` is `auto`: the one home of
/// `auto` for a store or a mesh file (a store's recorded histogram, a mesh's own by volume), so
/// that `tetwave render` and the viewer draw one source with the same colours. A server's stream
/// is fitted to its manifest once it arrives ([`TransferFunction::for_manifest`]).
pub fn fit_auto(
    spec: &str,
    source: &crate::Source,
    tf: TransferFunction,
) -> Result<TransferFunction, LoadError> {
    if spec != AUTO {
        return Ok(tf);
    }
    let hist = match source {
        crate::Source::Store(dir) => store_histogram(&Store::open(dir)?, None)?,
        crate::Source::Mesh(path) => {
            let options = ImportOptions {
                scalar: None,
                field: None,
                nan_as: None,
            };
            ValueHistogram::of_mesh(&file_mesh(path, None, &options)?.0)
        }
        crate::Source::Url(_) | crate::Source::Bucket(_) => return Ok(tf),
    };
    Ok(tf.fitted(&hist))
}

/// What a mesh file's viewer draws while the camera moves, when drawing the mesh itself is slow: a
/// Kuhn grid over `mesh`'s bounding box of at most `most` tets (cells as near to cubes as the box
/// allows), its values sampled from `mesh` (barycentric interpolation, as `prepare` samples it).
/// Grid points outside the mesh take the mean of their inside neighbours, and a level set of
/// +½ inside, −½ outside clips each straddling tet half way between them: the mesh's domain to
/// within half a cell. `None` when the mesh itself has at most `most` tets, when `most` holds no
/// cell, or when no grid point falls inside.
pub fn motion_proxy(mesh: &RenderMesh, most: usize) -> Option<RenderMesh> {
    if mesh.tets.len() <= most {
        return None;
    }
    let (lo, hi) = mesh.bounds();
    let (lo, hi) = (lo.to_array(), hi.to_array());
    let ext = [0, 1, 2].map(|a| (hi[a] - lo[a]).max(1e-300));
    // 6 tets a cell; the cell side h makes 6 · Π ceil(ext / h) ≤ most
    let cells_most = (most / 6) as f64;
    if cells_most < 1.0 {
        return None;
    }
    let mut h = (ext[0] * ext[1] * ext[2] / cells_most).cbrt();
    let cells = loop {
        let n = ext.map(|e| ((e / h).ceil() as usize).max(1));
        if (n[0] * n[1] * n[2]) as f64 <= cells_most {
            break n;
        }
        h *= 1.05;
    };
    let (positions, tets) = tetwave_protocol::shapes::kuhn_boxes(lo, hi, cells);
    let locator = tetwave_import::locate::Locator::new(&tetwave_import::clean::ScalarTetMesh {
        points: mesh.positions.clone(),
        tets: mesh.tets.clone(),
        values: mesh.values.iter().map(|&v| v as f64).collect(),
        distance: false,
    });
    let sampled: Vec<Option<f64>> = positions.iter().map(|&p| locator.sample(p)).collect();
    drop(locator);
    let inside: Vec<f64> = sampled.iter().flatten().copied().collect();
    if inside.is_empty() {
        return None;
    }
    let mean = inside.iter().sum::<f64>() / inside.len() as f64;
    // an outside point takes the mean of the inside points it shares a tet with
    let mut sum = vec![(0f64, 0u32); positions.len()];
    for t in &tets {
        for &a in t {
            if sampled[a as usize].is_none() {
                for &b in t {
                    if let Some(v) = sampled[b as usize] {
                        sum[a as usize].0 += v;
                        sum[a as usize].1 += 1;
                    }
                }
            }
        }
    }
    let values = sampled
        .iter()
        .zip(&sum)
        .map(|(s, &(t, n))| match s {
            Some(v) => *v as f32,
            None if n > 0 => (t / n as f64) as f32,
            None => mean as f32,
        })
        .collect();
    let levelset = sampled
        .iter()
        .map(|s| if s.is_some() { 0.5 } else { -0.5 })
        .collect();
    // tets wholly outside draw nothing: left out
    let tets: Vec<[u32; 4]> = tets
        .into_iter()
        .filter(|t| t.iter().any(|&v| sampled[v as usize].is_some()))
        .collect();
    let mut proxy = RenderMesh::new(positions, tets, values);
    proxy.value_range = mesh.value_range;
    proxy.levelset = Some(levelset);
    Some(proxy)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cube minus its upper octant with a linear field: the proxy keeps to its budget, holds
    /// the field exactly at every grid point inside, and marks the points in the missing octant
    /// outside.
    #[test]
    fn a_motion_proxy_samples_the_mesh_within_its_budget() {
        let (points, tets) = tetwave_protocol::shapes::kuhn_boxes([0.0; 3], [2.0; 3], [8; 3]);
        let in_octant = |t: &[u32; 4]| {
            (0..3).all(|a| t.iter().map(|&v| points[v as usize][a]).sum::<f64>() / 4.0 > 1.0)
        };
        let tets: Vec<[u32; 4]> = tets.into_iter().filter(|t| !in_octant(t)).collect();
        let f = |p: [f64; 3]| (p[0] + 2.0 * p[1] - p[2]) as f32;
        let values = points.iter().map(|&p| f(p)).collect();
        let mesh = RenderMesh::new(points, tets, values);
        for most in [300, 2_000] {
            let proxy = motion_proxy(&mesh, most).expect("a proxy");
            assert!(
                proxy.tets.len() <= most,
                "{} tets for {most}",
                proxy.tets.len()
            );
            assert!(
                proxy.tets.len() * 4 > most,
                "{} tets for {most}",
                proxy.tets.len()
            );
            assert_eq!(proxy.value_range, mesh.value_range);
            let ls = proxy.levelset.as_ref().unwrap();
            let (mut inside, mut outside) = (0, 0);
            for (p, (&v, &l)) in proxy.positions.iter().zip(proxy.values.iter().zip(ls)) {
                if l > 0.0 {
                    inside += 1;
                    assert!((v - f(*p)).abs() < 1e-5, "{p:?}: {v} vs {}", f(*p));
                } else {
                    outside += 1;
                    assert!(p.iter().all(|&c| c > 1.0), "{p:?} is inside the mesh");
                }
            }
            assert!(
                inside > 0 && outside > 0,
                "{inside} inside, {outside} outside"
            );
        }
        assert!(motion_proxy(&mesh, 5).is_none());
        // a mesh no larger than the budget is its own coarse mesh
        assert!(motion_proxy(&mesh, mesh.tets.len()).is_none());
    }
}
