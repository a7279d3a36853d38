//! Reading what a source holds at once: a store's uniform level, a mesh file as it is, the
//! histogram `auto` is fitted to. Shared by `tetwave render`, the viewer and the benchmarks.

use std::path::{Path, PathBuf};
use tetwave_import::clean::{clean_import, CleanError, ImportOptions};
use tetwave_import::volume::{sniff, Volume, VolumeError, VolumeFormat, VolumeOptions};
use tetwave_import::{format_of, read_mesh, ImportError, MeshFormat};
use tetwave_protocol::shapes::kuhn_boxes;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TransferFunction, ValueHistogram, AUTO};
use tetwave_store::{Physical, Store, StoreError};

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
    #[error(transparent)]
    Volume(#[from] VolumeError),
    /// A volume file that cannot be drawn as it is: too few voxels along an axis, a value that
    /// is not finite, more tets than memory holds.
    #[error("{path}: {message}")]
    VolumeMesh { path: PathBuf, message: String },
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

/// Whether `path` is a volume file or folder the volume readers recognize (NIfTI, NRRD, VTK
/// image data, TIFF, DICOM, Zarr): by content and extension, not a store directory.
pub fn is_volume_input(path: &Path) -> bool {
    !path.join("manifest.json").is_file() && !matches!(sniff(path), None | Some(VolumeFormat::Raw))
}

/// A file drawn as it is, with the name its legend gives the values: a volume file
/// ([`volume_mesh`]; its name and the values' unit) or a mesh file ([`file_mesh`] with the default
/// scalar; the scalar's name), and a volume's world. What the viewer opens a file with.
pub fn drawn_file(path: &Path) -> Result<(RenderMesh, String, Option<Physical>), LoadError> {
    if is_volume_input(path) {
        let (mesh, drawn) = volume_mesh(path, &VolumeOptions::default(), None)?;
        let name = drawn.legend_name(path);
        return Ok((mesh, name, Some(drawn.physical)));
    }
    let (mesh, name) = file_mesh(path, None, &ImportOptions::default())?;
    Ok((mesh, name, None))
}

/// What [`volume_mesh`] drew.
#[derive(Debug, Clone)]
pub struct VolumeDrawn {
    /// The format's name (`NIfTI`, `DICOM`, ...).
    pub format: &'static str,
    /// Voxels along the world axes.
    pub dims: [usize; 3],
    /// The file's world: the mesh's coordinates are its world's less `origin`, as a store
    /// prepared from the file has them, so that both frame the same view.
    pub physical: Physical,
}

impl VolumeDrawn {
    /// The legend's name of the values of the volume at `path`: the file's name up to its first
    /// dot, and the values' unit where the file states one (`head (HU)`).
    pub fn legend_name(&self, path: &Path) -> String {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let stem = name.split('.').next().unwrap_or_default();
        match &self.physical.value_unit {
            Some(u) if !u.is_empty() => format!("{stem} ({u})"),
            _ => stem.to_string(),
        }
    }
}

/// A volume file as it is: a vertex at each voxel centre (world axes, spacing from the file, the
/// lowest-corner voxel at 0) and each cell of 8 voxels cut into the 6 tets around its diagonal
/// from the low corner to the high one (Kuhn's triangulation: every cell cut the same way, so
/// the tets of neighbouring cells share their faces; [`kuhn_boxes`]), the value linear in each
/// tet. The voxels
/// are read plane by plane through the reader. Refused with one error when the mesh would take
/// more than half the memory the system reports available.
pub fn volume_mesh(
    path: &Path,
    options: &VolumeOptions,
    nan_as: Option<f64>,
) -> Result<(RenderMesh, VolumeDrawn), LoadError> {
    let mut volume = Volume::open(path, None, options)?;
    let header = volume.header().clone();
    let [nx, ny, nz] = volume.dims;
    let bad = |message: String| LoadError::VolumeMesh {
        path: path.to_path_buf(),
        message,
    };
    // (a volume with fewer than 2 voxels along an axis is refused when opened)
    let points = (nx * ny * nz) as u64;
    let cells = ((nx - 1) * (ny - 1) * (nz - 1)) as u64;
    let bytes = points * (24 + 4) + 6 * cells * 16;
    if let Some(avail) = available_memory() {
        if bytes > avail / 2 || points > u32::MAX as u64 {
            return Err(bad(format!(
                "drawing {nx}×{ny}×{nz} voxels as they are needs {:.1} GB ({} tets), more than                  half the {:.1} GB available: prepare a store (`tetwave-server prepare`) and                  render a coarser level of it (`--levels`)",
                bytes as f64 / 1e9,
                6 * cells,
                avail as f64 / 1e9
            )));
        }
    }
    let mut values = Vec::with_capacity(points as usize);
    // planes in slabs of at most ~16 M voxels
    let slab = (16usize << 20).div_ceil(nx * ny).clamp(1, nz);
    let mut z = 0;
    while z < nz {
        let z1 = (z + slab).min(nz);
        let block = volume.read_block(0..ny, z..z1)?;
        for i in 0..block.len() {
            let v = block.get(i);
            let v = match (v.is_finite(), nan_as) {
                (true, _) => v,
                (false, Some(r)) => r,
                (false, None) => {
                    let k = values.len();
                    return Err(bad(format!(
                        "voxel ({}, {}, {}) is {v}: give --nan-as VALUE to draw it as VALUE",
                        k % nx,
                        k / nx % ny,
                        k / (nx * ny)
                    )));
                }
            };
            values.push(v as f32);
        }
        z = z1;
    }
    let sp = volume.spacing;
    let hi = [0, 1, 2].map(|a| (volume.dims[a] - 1) as f64 * sp[a]);
    let (positions, tets) = kuhn_boxes([0.0; 3], hi, [nx - 1, ny - 1, nz - 1]);
    let drawn = VolumeDrawn {
        format: header.format.name(),
        dims: volume.dims,
        physical: Physical {
            origin: volume.origin,
            frame: header.frame.clone(),
            length_unit: header.length_unit.clone(),
            value_unit: header.value_unit.clone(),
        },
    };
    Ok((RenderMesh::new(positions, tets, values), drawn))
}

/// The memory the system reports available (`MemAvailable` of `/proc/meminfo`), in bytes; `None`
/// where it cannot be read.
fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
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
        crate::Source::Mesh(path) => ValueHistogram::of_mesh(&drawn_file(path)?.0),
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

    /// A folder of its own for a test's files.
    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("tetwave-load-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// A 4×3×2 NRRD volume in LPS millimetres, i16 big-endian, x flipped by its space directions:
    /// drawn as it is, each vertex holds its voxel's value at its place in the world frame, the
    /// tets fill the box exactly, positively oriented, and the legend names the file.
    #[test]
    fn a_volume_file_is_drawn_as_its_voxels() {
        let dir = scratch("nrrd");
        let path = dir.join("head.nrrd");
        let stored: Vec<i16> = (0..24).map(|v| v * 10 - 50).collect();
        let mut bytes = b"NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n\
            sizes: 4 3 2\nspace directions: (-0.5,0,0) (0,0.25,0) (0,0,2)\n\
            space origin: (10,20,30)\nspace units: \"mm\" \"mm\" \"mm\"\nendian: big\n\
            encoding: raw\n\n"
            .to_vec();
        bytes.extend(stored.iter().flat_map(|v| v.to_be_bytes()));
        std::fs::write(&path, bytes).unwrap();
        assert!(is_volume_input(&path));
        assert!(!is_volume_input(&dir.join("missing.vtu")));
        let (mesh, drawn) = volume_mesh(&path, &VolumeOptions::default(), None).unwrap();
        assert_eq!(drawn.dims, [4, 3, 2]);
        assert_eq!(drawn.physical.frame.as_deref(), Some("LPS"));
        assert_eq!(drawn.physical.length_unit.as_deref(), Some("mm"));
        // file x runs against world x: the world's lowest-corner voxel is the file's last along x
        assert_eq!(drawn.physical.origin, [10.0 - 1.5, 20.0, 30.0]);
        assert_eq!(drawn.legend_name(&path), "head");
        assert_eq!(mesh.positions.len(), 24);
        assert_eq!(mesh.tets.len(), 6 * 3 * 2);
        for k in 0..2 {
            for j in 0..3 {
                for i in 0..4 {
                    let v = i + 4 * (j + 3 * k);
                    assert_eq!(
                        mesh.positions[v],
                        [i as f64 * 0.5, j as f64 * 0.25, k as f64 * 2.0]
                    );
                    let file = (3 - i) + 4 * (j + 3 * k);
                    assert_eq!(mesh.values[v], stored[file] as f32, "voxel {i},{j},{k}");
                }
            }
        }
        let volume: f64 = mesh
            .tets
            .iter()
            .map(|t| {
                let p = t.map(|v| mesh.positions[v as usize]);
                let d = |k: usize| [0, 1, 2].map(|a| p[k][a] - p[0][a]);
                let (a, b, c) = (d(1), d(2), d(3));
                let vol = (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0]))
                    / 6.0;
                assert!(vol > 0.0, "a tet of volume {vol}");
                vol
            })
            .sum();
        assert!(
            (volume - 1.5 * 0.5 * 2.0).abs() < 1e-12,
            "tets fill {volume}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Non-finite voxels are refused with their place, or drawn as `--nan-as`; a volume one voxel
    /// thin is refused; no panic.
    #[test]
    fn a_volume_that_cannot_be_drawn_says_why() {
        let dir = scratch("bad");
        let nan = dir.join("nan.nrrd");
        let mut bytes =
            b"NRRD0004\ntype: float\ndimension: 3\nsizes: 2 2 2\nencoding: raw\nendian: little\n\n"
                .to_vec();
        let values = [0.0f32, 1.0, 2.0, f32::NAN, 4.0, 5.0, 6.0, 7.0];
        bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
        std::fs::write(&nan, bytes).unwrap();
        let e = volume_mesh(&nan, &VolumeOptions::default(), None).unwrap_err();
        assert!(e.to_string().contains("voxel (1, 1, 0) is NaN"), "{e}");
        let (mesh, _) = volume_mesh(&nan, &VolumeOptions::default(), Some(-1.0)).unwrap();
        assert_eq!(mesh.values[3], -1.0);
        let thin = dir.join("thin.nrrd");
        let mut bytes =
            b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 3 3 1\nencoding: raw\n\n".to_vec();
        bytes.extend([0u8; 9]);
        std::fs::write(&thin, bytes).unwrap();
        let e = volume_mesh(&thin, &VolumeOptions::default(), None).unwrap_err();
        assert!(
            e.to_string().contains("at least 2 voxels along every axis"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
