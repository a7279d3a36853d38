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
        crate::Source::Url(_) => return Ok(tf),
    };
    Ok(tf.fitted(&hist))
}
