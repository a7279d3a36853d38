//! Readers of unstructured volume meshes: VTK XML `.vtu`, legacy `.vtk`, gmsh `.msh`, Medit
//! `.mesh`. `docs/formats.md` has the user-facing table.
//!
//! Every reader returns an [`ImportedMesh`] (or its [`TetMesh`]) or an [`ImportError`] naming the
//! file, the section and the reason; none panics on malformed input and none passes on a partial
//! mesh as if whole.
//!
//! | format | variants read | code |
//! | --- | --- | --- |
//! | `.vtu` (VTK XML `UnstructuredGrid`) | ascii, inline binary (base64), appended raw and base64, zlib or none, `UInt32`/`UInt64` headers, either byte order, several pieces; point and cell arrays | `vtk.rs`: `quick-xml` tokenizer, `flate2` inflate, the rest ours |
//! | `.vtk` (legacy `UNSTRUCTURED_GRID`) | versions 2.0 to 5.1, ascii and binary; `POINT_DATA`/`CELL_DATA` `SCALARS`, `VECTORS`, `NORMALS` and `FIELD` arrays | `vtk.rs`: ours |
//! | `.msh` (gmsh) | 1.0, 2.2 and 4.1, ascii and binary (2.2, 4.1); `$NodeData`, `$ElementData` | `msh.rs`: ours |
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

mod medit;
mod msh;
mod vtk;

use std::path::{Path, PathBuf};

/// A tetrahedral mesh as read from a file, before any cleaning (orientation, degenerate tets).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TetMesh {
    pub points: Vec<[f64; 3]>,
    /// Tets (4 point indices each, in the file's order): linear tets as they are, the corner tet
    /// of higher-order tets, and the tets hexahedra, wedges and pyramids were split into.
    pub tets: Vec<[u32; 4]>,
    /// Scalar point arrays, in file order; each has one value per point.
    pub point_data: Vec<ScalarArray>,
    /// Cells that gave no tets (points, lines, surfaces, unsupported volume kinds): skipped.
    pub cells_ignored: usize,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ScalarArray {
    pub name: String,
    pub values: Vec<f64>,
}

/// An array with `components` values per point or per cell (tuples stored one after the other).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldArray {
    pub name: String,
    pub components: usize,
    pub values: Vec<f64>,
}

impl FieldArray {
    /// Number of tuples.
    pub fn len(&self) -> usize {
        self.values.len() / self.components.max(1)
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }
}

/// What the readers did with the file's cells.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CellCounts {
    /// Every cell of the file, whatever its kind.
    pub cells_read: usize,
    /// Linear tets.
    pub tets: usize,
    /// Higher-order tets reduced to their corner tet (VTK 24, gmsh 11, ...).
    pub tets_linearized: usize,
    /// Hexahedra, wedges and pyramids split into tets.
    pub cells_split: usize,
    /// The tets the split cells gave.
    pub tets_from_split: usize,
    /// Points, lines and surface cells.
    pub cells_lower_dim: usize,
    /// Volume cells of a kind that is not read (polyhedra, Lagrange cells...).
    pub cells_unsupported: usize,
}

/// Everything an import reads: the tet mesh with its scalar point arrays, plus the cell arrays,
/// the point arrays with several components and what was done with the cells.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImportedMesh {
    pub mesh: TetMesh,
    /// For each tet of `mesh.tets`, the file cell it comes from (cell arrays are indexed by it).
    pub tet_cells: Vec<usize>,
    /// Point arrays with more than one component.
    pub point_vectors: Vec<FieldArray>,
    /// Cell arrays (any number of components), one tuple per file cell.
    pub cell_data: Vec<FieldArray>,
    pub counts: CellCounts,
}

impl From<TetMesh> for ImportedMesh {
    fn from(mesh: TetMesh) -> Self {
        let n = mesh.tets.len();
        ImportedMesh {
            counts: CellCounts {
                cells_read: n + mesh.cells_ignored,
                tets: n,
                cells_lower_dim: mesh.cells_ignored,
                ..CellCounts::default()
            },
            tet_cells: (0..n).collect(),
            mesh,
            ..ImportedMesh::default()
        }
    }
}

/// Volume cell shapes that become tets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Shape {
    Tet,
    Hex,
    Wedge,
    Pyramid,
}

impl Shape {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Shape::Tet => "tetra",
            Shape::Hex => "hexahedron",
            Shape::Wedge => "wedge",
            Shape::Pyramid => "pyramid",
        }
    }
}

/// A cell kind as a reader sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Cell {
    /// A volume cell: its shape, its node count, and the positions of its corners in its node list
    /// in VTK order (`corners.len()` < `nodes` for higher-order cells).
    Volume {
        shape: Shape,
        nodes: usize,
        corners: &'static [usize],
    },
    /// Points, lines, surfaces.
    Lower,
    /// A volume kind that is not read.
    Unsupported,
}

const C4: &[usize] = &[0, 1, 2, 3];
const C5: &[usize] = &[0, 1, 2, 3, 4];
const C6: &[usize] = &[0, 1, 2, 3, 4, 5];
const C8: &[usize] = &[0, 1, 2, 3, 4, 5, 6, 7];

const fn vol(shape: Shape, nodes: usize, corners: &'static [usize]) -> Cell {
    Cell::Volume {
        shape,
        nodes,
        corners,
    }
}

/// VTK cell types (legacy and XML).
pub(crate) fn vtk_cell(ty: i64) -> Cell {
    match ty {
        10 => vol(Shape::Tet, 4, C4),
        24 => vol(Shape::Tet, 10, C4),
        12 => vol(Shape::Hex, 8, C8),
        // voxel: x fastest, then y, then z
        11 => vol(Shape::Hex, 8, &[0, 1, 3, 2, 4, 5, 7, 6]),
        25 => vol(Shape::Hex, 20, C8),
        29 => vol(Shape::Hex, 27, C8),
        13 => vol(Shape::Wedge, 6, C6),
        26 => vol(Shape::Wedge, 15, C6),
        32 => vol(Shape::Wedge, 18, C6),
        14 => vol(Shape::Pyramid, 5, C5),
        27 => vol(Shape::Pyramid, 13, C5),
        1..=9 | 21..=23 | 28 | 30 | 34..=37 | 68..=70 | 75..=77 => Cell::Lower,
        _ => Cell::Unsupported,
    }
}

/// gmsh element types (all versions). gmsh lists the corners first; its prism turns the other way
/// round than VTK's wedge.
pub(crate) fn gmsh_cell(ty: i64) -> Cell {
    const PRISM: &[usize] = &[0, 2, 1, 3, 5, 4];
    match ty {
        4 => vol(Shape::Tet, 4, C4),
        11 => vol(Shape::Tet, 10, C4),
        29 => vol(Shape::Tet, 20, C4),
        30 => vol(Shape::Tet, 35, C4),
        31 => vol(Shape::Tet, 56, C4),
        5 => vol(Shape::Hex, 8, C8),
        12 => vol(Shape::Hex, 27, C8),
        17 => vol(Shape::Hex, 20, C8),
        92 => vol(Shape::Hex, 64, C8),
        93 => vol(Shape::Hex, 125, C8),
        6 => vol(Shape::Wedge, 6, PRISM),
        13 => vol(Shape::Wedge, 18, PRISM),
        18 => vol(Shape::Wedge, 15, PRISM),
        7 => vol(Shape::Pyramid, 5, C5),
        14 => vol(Shape::Pyramid, 14, C5),
        19 => vol(Shape::Pyramid, 13, C5),
        1..=3 | 8..=10 | 15 | 16 | 20..=28 => Cell::Lower,
        _ => Cell::Unsupported,
    }
}

// Faces of each shape in VTK corner order, counter-clockwise seen from outside.
const HEX_FACES: &[&[usize]] = &[
    &[0, 3, 2, 1],
    &[4, 5, 6, 7],
    &[0, 1, 5, 4],
    &[1, 2, 6, 5],
    &[2, 3, 7, 6],
    &[3, 0, 4, 7],
];
const WEDGE_FACES: &[&[usize]] = &[
    &[0, 1, 2],
    &[3, 5, 4],
    &[0, 3, 4, 1],
    &[1, 4, 5, 2],
    &[2, 5, 3, 0],
];
const PYRAMID_FACES: &[&[usize]] = &[
    &[0, 3, 2, 1],
    &[0, 1, 4],
    &[1, 2, 4],
    &[2, 3, 4],
    &[3, 0, 4],
];

/// Splits a convex cell (its corner point indices in VTK order) into tets, conforming across
/// shared faces: every quad face is cut by the diagonal from its smallest point index, and the
/// cell is coned from its smallest point index over the faces that do not hold it (a hexahedron
/// gives 6 tets, a wedge 3, a pyramid 2). With VTK's orientation the tets are positive.
pub(crate) fn split_cell(v: &[u32], shape: Shape, out: &mut Vec<[u32; 4]>) {
    let faces = match shape {
        Shape::Tet => {
            if let [a, b, c, d] = *v {
                out.push([a, b, c, d]);
            }
            return;
        }
        Shape::Hex => HEX_FACES,
        Shape::Wedge => WEDGE_FACES,
        Shape::Pyramid => PYRAMID_FACES,
    };
    let Some(apex) = (0..v.len()).min_by_key(|&i| v[i]) else {
        return;
    };
    let p = |i: usize| v.get(i).copied().unwrap_or(0);
    for f in faces {
        if f.contains(&apex) {
            continue;
        }
        match f.len() {
            3 => out.push([p(apex), p(f[0]), p(f[1]), p(f[2])]),
            _ => {
                let k = (0..4).min_by_key(|&i| p(f[i])).unwrap_or(0);
                let q = |j: usize| p(f[(k + j) % 4]);
                out.push([p(apex), q(0), q(1), q(2)]);
                out.push([p(apex), q(0), q(2), q(3)]);
            }
        }
    }
}

impl ImportedMesh {
    /// Adds the next file cell. `nodes` are point indices already checked against the points
    /// (only read for volume cells, whose node count the caller has checked).
    pub(crate) fn push_cell(&mut self, cell: Cell, nodes: &[u32]) {
        let index = self.counts.cells_read;
        self.counts.cells_read += 1;
        match cell {
            Cell::Lower => {
                self.counts.cells_lower_dim += 1;
                self.mesh.cells_ignored += 1;
            }
            Cell::Unsupported => {
                self.counts.cells_unsupported += 1;
                self.mesh.cells_ignored += 1;
            }
            Cell::Volume {
                shape,
                nodes: n,
                corners,
            } => {
                let c: Vec<u32> = corners
                    .iter()
                    .map(|&i| nodes.get(i).copied().unwrap_or(0))
                    .collect();
                let before = self.mesh.tets.len();
                split_cell(&c, shape, &mut self.mesh.tets);
                let made = self.mesh.tets.len() - before;
                self.tet_cells.extend(std::iter::repeat_n(index, made));
                match shape {
                    Shape::Tet if n > 4 => self.counts.tets_linearized += 1,
                    Shape::Tet => self.counts.tets += 1,
                    _ => {
                        self.counts.cells_split += 1;
                        self.counts.tets_from_split += made;
                    }
                }
            }
        }
    }
}

/// Checks a volume cell's node count: `Err(reason)` when it disagrees with its kind.
pub(crate) fn check_nodes(cell: Cell, got: usize, what: &str) -> Result<(), String> {
    match cell {
        Cell::Volume { shape, nodes, .. } if nodes != got => Err(format!(
            "{what} is a {nodes}-node {} with {got} points",
            shape.name()
        )),
        _ => Ok(()),
    }
}

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
