//! Readers of unstructured tetrahedral meshes: VTK XML `.vtu`, legacy `.vtk`, gmsh `.msh`.
//!
//! Every reader returns a [`TetMesh`] or an [`ImportError`] naming the file, the section and the
//! reason; none panics on malformed input and none passes on a partial mesh as if whole.
//!
//! | format | variants read | code |
//! | --- | --- | --- |
//! | `.vtu` (VTK XML `UnstructuredGrid`) | ascii, inline binary (base64), appended raw and base64, zlib or none, `UInt32`/`UInt64` headers, either byte order, several pieces | [`vtk`]: `quick-xml` tokenizer, `flate2` inflate, the rest ours |
//! | `.vtk` (legacy `UNSTRUCTURED_GRID`) | versions 2.0 to 5.1, ascii and binary; `POINT_DATA` `SCALARS` and `FIELD` arrays | [`vtk`]: ours |
//! | `.msh` (gmsh) | 2.2 and 4.1, ascii and binary; `$NodeData` | [`msh`]: ours |
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
//! DataFile`, `$MeshFormat`), otherwise from the extension.

mod msh;
mod vtk;

use std::path::{Path, PathBuf};

/// A tetrahedral mesh as read from a file, before any cleaning (orientation, degenerate tets).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TetMesh {
    pub points: Vec<[f64; 3]>,
    /// Linear tets (4 point indices each, in the file's order).
    pub tets: Vec<[u32; 4]>,
    /// Scalar point arrays, in file order; each has one value per point.
    pub point_data: Vec<ScalarArray>,
    /// Cells that are not linear tets (lines, triangles, other kinds) and were skipped.
    pub cells_ignored: usize,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ScalarArray {
    pub name: String,
    pub values: Vec<f64>,
}

/// Mesh file formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Vtu,
    LegacyVtk,
    Msh,
}

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: unknown mesh format (expected .vtu, .vtk or .msh)")]
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
        _ => None,
    }
}

/// Format from the first bytes of a file: `<VTKFile` (or an XML declaration) → [`MeshFormat::Vtu`],
/// `# vtk DataFile` → [`MeshFormat::LegacyVtk`], `$MeshFormat` → [`MeshFormat::Msh`].
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
    if head.starts_with(b"$MeshFormat") {
        return Some(MeshFormat::Msh);
    }
    None
}

/// Reads a tetrahedral mesh with its point scalars; the format comes from the content, or from the
/// extension when the content is not recognizable.
pub fn read_tet_mesh(path: &Path) -> Result<TetMesh, ImportError> {
    let bytes = read_file(path)?;
    let format = format_of_content(&bytes)
        .or_else(|| format_of(path))
        .ok_or_else(|| match bytes.is_empty() {
            true => malformed(path, Bad::new("file", "empty file")),
            false => ImportError::UnknownFormat {
                path: path.to_path_buf(),
            },
        })?;
    parse_tet_mesh(path, &bytes, format)
}

/// Reads a tetrahedral mesh in the given format, whatever the extension and the content say.
pub fn read_tet_mesh_as(path: &Path, format: MeshFormat) -> Result<TetMesh, ImportError> {
    let bytes = read_file(path)?;
    parse_tet_mesh(path, &bytes, format)
}

/// Parses a mesh held in memory; `path` only names the source in errors.
pub fn parse_tet_mesh(
    path: &Path,
    bytes: &[u8],
    format: MeshFormat,
) -> Result<TetMesh, ImportError> {
    if bytes.iter().all(u8::is_ascii_whitespace) {
        return Err(malformed(path, Bad::new("file", "empty file")));
    }
    let mesh = match format {
        MeshFormat::Vtu => vtk::parse_vtu(bytes),
        MeshFormat::LegacyVtk => vtk::parse_legacy(bytes),
        MeshFormat::Msh => msh::parse_msh(bytes),
    }
    .and_then(|mesh| {
        check_mesh(&mesh)?;
        Ok(mesh)
    });
    mesh.map_err(|bad| malformed(path, bad))
}

fn read_file(path: &Path) -> Result<Vec<u8>, ImportError> {
    std::fs::read(path).map_err(|source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    })
}

fn malformed(path: &Path, bad: Bad) -> ImportError {
    ImportError::Malformed {
        path: path.to_path_buf(),
        section: bad.section,
        reason: bad.reason,
    }
}

/// What every reader guarantees, checked once more on the result.
fn check_mesh(mesh: &TetMesh) -> Res<()> {
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
    Ok(())
}

/// A reader's error before the path is attached: the section of the file and what is wrong.
#[derive(Debug)]
pub(crate) struct Bad {
    section: String,
    reason: String,
}

impl Bad {
    pub(crate) fn new(section: impl Into<String>, reason: impl Into<String>) -> Bad {
        Bad {
            section: section.into(),
            reason: reason.into(),
        }
    }
}

pub(crate) type Res<T> = Result<T, Bad>;

/// Position of `needle` in `hay`.
pub(crate) fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    if needle.is_empty() || hay.len() < needle.len() {
        return None;
    }
    hay.windows(needle.len()).position(|w| w == needle)
}

/// A capacity for `n` items of at least `item_bytes` bytes each read from `remaining` bytes of
/// input: never more than the input can hold, so that a lying count cannot allocate.
pub(crate) fn capacity(n: usize, item_bytes: usize, remaining: usize) -> usize {
    n.min(remaining / item_bytes.max(1) + 1)
}

/// Converts a point index read from a file, checking it against the number of points.
pub(crate) fn point_index(v: i64, base: usize, n_points: usize) -> Option<u32> {
    let v = usize::try_from(v).ok()?;
    if v >= n_points {
        return None;
    }
    u32::try_from(base.checked_add(v)?).ok()
}

/// A file shown in an error: at most 40 characters, lossy UTF-8.
pub(crate) fn show(bytes: &[u8]) -> String {
    let s = String::from_utf8_lossy(&bytes[..bytes.len().min(40)]).into_owned();
    if bytes.len() > 40 {
        format!("{s}...")
    } else {
        s
    }
}

/// Byte order of binary data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Endian {
    Little,
    Big,
}

/// A cursor over a file's bytes: whitespace-separated tokens, lines and raw binary runs.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Lex<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Lex<'a> {
    pub(crate) fn new(b: &'a [u8]) -> Self {
        Lex { b, pos: 0 }
    }

    pub(crate) fn remaining(&self) -> usize {
        self.b.len().saturating_sub(self.pos)
    }

    pub(crate) fn skip_ws(&mut self) {
        while self.b.get(self.pos).is_some_and(u8::is_ascii_whitespace) {
            self.pos += 1;
        }
    }

    /// The next run of non-whitespace bytes; `None` at the end of the file.
    pub(crate) fn token(&mut self) -> Option<&'a [u8]> {
        self.skip_ws();
        let start = self.pos;
        while self
            .b
            .get(self.pos)
            .is_some_and(|c| !c.is_ascii_whitespace())
        {
            self.pos += 1;
        }
        self.b.get(start..self.pos).filter(|t| !t.is_empty())
    }

    pub(crate) fn peek_token(&self) -> Option<&'a [u8]> {
        let mut copy = *self;
        copy.token()
    }

    /// The rest of the current line, without its end (`\n` or `\r\n`), which is consumed;
    /// `None` at the end of the file.
    pub(crate) fn line(&mut self) -> Option<&'a [u8]> {
        if self.pos >= self.b.len() {
            return None;
        }
        let rest = self.b.get(self.pos..)?;
        let len = rest.iter().position(|&c| c == b'\n').unwrap_or(rest.len());
        self.pos += (len + 1).min(rest.len());
        let line = rest.get(..len)?;
        Some(line.strip_suffix(b"\r").unwrap_or(line))
    }

    /// Moves past the next occurrence of `needle`; `false` (and no move) if there is none.
    pub(crate) fn skip_past(&mut self, needle: &[u8]) -> bool {
        match self.b.get(self.pos..).and_then(|rest| find(rest, needle)) {
            Some(at) => {
                self.pos += at + needle.len();
                true
            }
            None => false,
        }
    }

    /// The next `n` bytes as they are.
    pub(crate) fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let run = self.b.get(self.pos..end)?;
        self.pos = end;
        Some(run)
    }
}
