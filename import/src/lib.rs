//! Readers of unstructured volume meshes: VTK XML `.vtu`, legacy `.vtk`, gmsh `.msh`, Medit
//! `.mesh`. `docs/formats.md` has the user-facing table.
//!
//! Every reader returns an [`ImportedMesh`] (or its [`TetMesh`]) or an [`ImportError`] naming the
//! file, the section and the reason; none panics on malformed input and none passes on a partial
//! mesh as if whole.
//!
//! | format | variants read | code |
//! | --- | --- | --- |
//! | `.vtu` (VTK XML `UnstructuredGrid`) | ascii, inline binary (base64), appended raw and base64, zlib or none, `UInt32`/`UInt64` headers, either byte order, several pieces; point and cell arrays | `vtk/`: `quick-xml` tokenizer, `flate2` inflate, the rest ours |
//! | `.vtk` (legacy `UNSTRUCTURED_GRID`) | versions 2.0 to 5.1, ascii and binary; `POINT_DATA`/`CELL_DATA` `SCALARS`, `VECTORS`, `NORMALS` and `FIELD` arrays | `vtk/legacy.rs`: ours |
//! | `.msh` (gmsh) | 1.0, 2.2 and 4.1, ascii and binary (2.2, 4.1); `$NodeData`, `$ElementData`; element tags as `gmsh:physical`, `gmsh:geometrical` | `msh.rs`: ours |
//! | `.mesh` (Medit) | ascii; element references as the cell array `ref` | `medit.rs`: ours |
//!
//! Cells: linear tets are kept; higher-order tets give their corner tet; hexahedra, wedges and
//! pyramids (and their higher-order variants, by their corners) are split into tets by
//! `split_cell`, conformingly across shared faces; points, lines and surface cells are counted
//! and skipped, as are volume kinds that are not read (polyhedra, Lagrange cells).
//!
//! Why no `vtkio` or `mshio`: both were tried on the fixtures of `server/tests/fixtures/`
//! (written by meshio, `scripts/gen-fixtures.py`). `vtkio` 0.6.3 read one `.vtu` variant of eight
//! (appended raw, uncompressed): it ignores the compressor of inline binary arrays, rejects base64
//! written as VTK and meshio write it (header and data encoded separately), inflates only the first
//! zlib block, slices appended data without bounds checks (a truncated file panics), does not parse
//! legacy 5.1 (`OFFSETS`/`CONNECTIVITY`, what VTK 9 and meshio write), and sizes its buffers from
//! header counts (`POINTS 4000000000 double` aborts the process on allocation). `mshio` 0.4 reads
//! gmsh 4.1 only, skips `$NodeData`, rejects parametric nodes, drops the node tags when they span a
//! contiguous range (so a permuted numbering is silently misread) and panics on an empty `$Nodes`
//! section (`num_nodes - 1` underflow). The hand-written readers check every count against the
//! bytes that are left before allocating for it, and every index before using it.
//!
//! The format comes from the content when it is recognizable (`<VTKFile` or `<?xml`, `# vtk
//! DataFile`, `$MeshFormat` or `$NOD`, `MeshVersionFormatted`), otherwise from the extension;
//! [`read_mesh`] takes an override (`prepare --format`).
//!
//! [`clean`] turns an [`ImportedMesh`] and a scalar choice (`--scalar NAME`, `NAME:mag`, `NAME:K`,
//! `--field distance`, `--nan-as`) into one value per point; `prepare` (server) resamples that and
//! `tetwave render <mesh>` (client) draws it as it is.
//!
//! This file: format detection and the entry points. What the readers return is in `mesh.rs`,
//! the cell kinds and their split into tets in `cells.rs`, the error and byte cursor they share in
//! `lex.rs`; each format has its own file (VTK a folder, `vtk/`).

mod cells;
pub mod clean;
mod lex;
pub mod locate;
mod medit;
mod mesh;
mod msh;
pub mod volume;
mod vtk;

pub use mesh::{CellCounts, FieldArray, ImportedMesh, ScalarArray, TetMesh};

use lex::{find, Bad, Lex, Res};
use std::path::{Path, PathBuf};

/// Mesh file formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Vtu,
    LegacyVtk,
    Msh,
    /// Medit `.mesh` (ascii).
    Medit,
}

impl MeshFormat {
    /// The `--format` names: `vtu`, `vtk`, `msh`, `mesh`.
    pub fn from_name(name: &str) -> Option<MeshFormat> {
        match name
            .trim()
            .trim_start_matches('.')
            .to_ascii_lowercase()
            .as_str()
        {
            "vtu" => Some(MeshFormat::Vtu),
            "vtk" => Some(MeshFormat::LegacyVtk),
            "msh" | "gmsh" => Some(MeshFormat::Msh),
            "mesh" | "medit" => Some(MeshFormat::Medit),
            _ => None,
        }
    }
}

impl std::str::FromStr for MeshFormat {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        MeshFormat::from_name(s)
            .ok_or_else(|| format!("unknown mesh format {s:?} (vtu, vtk, msh or mesh)"))
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: unknown mesh format (expected .vtu, .vtk, .msh or .mesh; or pass --format)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: {section}: {reason}")]
    Malformed {
        path: PathBuf,
        section: String,
        reason: String,
    },
}

/// Format from the file's extension.
pub fn format_of(path: &Path) -> Option<MeshFormat> {
    match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
        "vtu" => Some(MeshFormat::Vtu),
        "vtk" => Some(MeshFormat::LegacyVtk),
        "msh" => Some(MeshFormat::Msh),
        "mesh" => Some(MeshFormat::Medit),
        _ => None,
    }
}

/// Format from the first bytes of a file: `<VTKFile` (or an XML declaration) → [`MeshFormat::Vtu`],
/// `# vtk DataFile` → [`MeshFormat::LegacyVtk`], `$MeshFormat` or `$NOD` → [`MeshFormat::Msh`],
/// `MeshVersionFormatted` → [`MeshFormat::Medit`].
pub fn format_of_content(bytes: &[u8]) -> Option<MeshFormat> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let start = bytes.iter().position(|b| !b.is_ascii_whitespace())?;
    let head = &bytes[start..bytes.len().min(start + 4096)];
    if head.starts_with(b"<VTKFile") {
        return Some(MeshFormat::Vtu);
    }
    if head.starts_with(b"<?xml") || head.starts_with(b"<!--") {
        return find(head, b"<VTKFile").map(|_| MeshFormat::Vtu);
    }
    if head.starts_with(b"#") {
        let line_end = head.iter().position(|&b| b == b'\n').unwrap_or(head.len());
        let words: Vec<String> = String::from_utf8_lossy(&head[1..line_end])
            .split_whitespace()
            .take(2)
            .map(str::to_ascii_lowercase)
            .collect();
        if words == ["vtk", "datafile"] {
            return Some(MeshFormat::LegacyVtk);
        }
    }
    if head.starts_with(b"$MeshFormat") || head.starts_with(b"$NOD") {
        return Some(MeshFormat::Msh);
    }
    // Medit: comment lines may come first.
    let mut lx = Lex::new(head);
    while let Some(line) = lx.line() {
        let line = String::from_utf8_lossy(line);
        let word = line.split_whitespace().next().unwrap_or("");
        if word.is_empty() || word.starts_with('#') {
            continue;
        }
        if word.eq_ignore_ascii_case("MeshVersionFormatted") {
            return Some(MeshFormat::Medit);
        }
        break;
    }
    None
}

/// Reads a tetrahedral mesh with its point scalars; the format comes from the content, or from the
/// extension when the content is not recognizable.
pub fn read_tet_mesh(path: &Path) -> Result<TetMesh, ImportError> {
    read_mesh(path, None).map(|m| m.mesh)
}

/// Reads a tetrahedral mesh in the given format, whatever the extension and the content say.
pub fn read_tet_mesh_as(path: &Path, format: MeshFormat) -> Result<TetMesh, ImportError> {
    read_mesh(path, Some(format)).map(|m| m.mesh)
}

/// Reads everything an import needs (cell arrays, vector arrays, what was done with the cells).
/// `format` overrides the detection from the content and the extension.
pub fn read_mesh(path: &Path, format: Option<MeshFormat>) -> Result<ImportedMesh, ImportError> {
    let bytes = read_file(path)?;
    let format = match format {
        Some(f) => f,
        None => format_of_content(&bytes)
            .or_else(|| format_of(path))
            .ok_or_else(|| match bytes.is_empty() {
                true => malformed(path, Bad::new("file", "empty file")),
                false => ImportError::UnknownFormat {
                    path: path.to_path_buf(),
                },
            })?,
    };
    parse_mesh(path, &bytes, format)
}

/// Parses a mesh held in memory; `path` only names the source in errors.
pub fn parse_tet_mesh(
    path: &Path,
    bytes: &[u8],
    format: MeshFormat,
) -> Result<TetMesh, ImportError> {
    parse_mesh(path, bytes, format).map(|m| m.mesh)
}

/// [`parse_tet_mesh`] with the cell arrays, the vector arrays and the cell counts.
pub fn parse_mesh(
    path: &Path,
    bytes: &[u8],
    format: MeshFormat,
) -> Result<ImportedMesh, ImportError> {
    if bytes.iter().all(u8::is_ascii_whitespace) {
        return Err(malformed(path, Bad::new("file", "empty file")));
    }
    let mesh = match format {
        MeshFormat::Vtu => vtk::parse_vtu(bytes),
        MeshFormat::LegacyVtk => vtk::parse_legacy(bytes),
        MeshFormat::Msh => msh::parse_msh(bytes),
        MeshFormat::Medit => medit::parse_medit(bytes),
    }
    .and_then(|mesh| {
        check_mesh(&mesh)?;
        Ok(mesh)
    });
    mesh.map_err(|bad| malformed(path, bad))
}

/// The whole file. Only regular files: a device or a pipe (`/dev/zero`) could be read until memory
/// runs out.
fn read_file(path: &Path) -> Result<Vec<u8>, ImportError> {
    let io = |source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    };
    if !std::fs::metadata(path).map_err(io)?.is_file() {
        return Err(io(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "not a regular file",
        )));
    }
    std::fs::read(path).map_err(io)
}

fn malformed(path: &Path, bad: Bad) -> ImportError {
    ImportError::Malformed {
        path: path.to_path_buf(),
        section: bad.section,
        reason: bad.reason,
    }
}

/// What every reader guarantees, checked once more on the result.
fn check_mesh(m: &ImportedMesh) -> Res<()> {
    let mesh = &m.mesh;
    let n = mesh.points.len();
    if u32::try_from(n).is_err() {
        return Err(Bad::new(
            "points",
            format!("{n} points do not fit 32-bit indices"),
        ));
    }
    if let Some((i, t)) = mesh
        .tets
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&v| v as usize >= n))
    {
        return Err(Bad::new(
            "cells",
            format!("tet {i} refers to point {t:?} out of range ({n} points)"),
        ));
    }
    if let Some(a) = mesh.point_data.iter().find(|a| a.values.len() != n) {
        return Err(Bad::new(
            "point data",
            format!(
                "array \"{}\" has {} values for {n} points",
                a.name,
                a.values.len()
            ),
        ));
    }
    let cells = m.counts.cells_read;
    let bad_len = |a: &FieldArray, k: usize| {
        a.components == 0 || Some(a.values.len()) != k.checked_mul(a.components)
    };
    if let Some(a) = m.point_vectors.iter().find(|a| bad_len(a, n)) {
        return Err(Bad::new(
            "point data",
            format!(
                "array \"{}\" has {} values for {n} points of {} components",
                a.name,
                a.values.len(),
                a.components
            ),
        ));
    }
    if let Some(a) = m.cell_data.iter().find(|a| bad_len(a, cells)) {
        return Err(Bad::new(
            "cell data",
            format!(
                "array \"{}\" has {} values for {cells} cells of {} components",
                a.name,
                a.values.len(),
                a.components
            ),
        ));
    }
    if m.tet_cells.len() != mesh.tets.len() || m.tet_cells.iter().any(|&c| c >= cells) {
        return Err(Bad::new("cells", "tets and cells disagree"));
    }
    Ok(())
}
