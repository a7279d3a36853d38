//! Medit `.mesh` reader (ascii, `Dimension 3`).
//!
//! `Vertices` (x y z ref), then element sections whose records are 1-based vertex numbers and a
//! reference: `Tetrahedra`, `TetrahedraP2` (the corner tet is kept), `Hexahedra`, `Prisms` and
//! `Pyramids` become tets (the last three split, see `split_cell`); `Edges`, `Triangles`,
//! `Quadrilaterals` (and their P2 variants) are counted as lower-dimensional cells. The element
//! references become the cell array `ref`. Other known sections (`Corners`, `Ridges`, `Normals`,
//! ...) are read past; an unknown keyword is an error, since its size is not known. `#` starts a
//! comment. The binary `.meshb` is not read.
//!
//! A missing final `End` (meshio reads such files) is accepted only when the file could not have
//! been cut short inside a record: every section read in full (each declared count of records
//! read), the file ending in whitespace (a line end) after its last record, so that its last
//! number cannot be the prefix of a longer one, and at least one volume element section read.
//! Otherwise it is an error: a truncation inside a section, in the middle of a number or a keyword,
//! or before any volume element is refused. A file cut exactly at a section boundary after its
//! volume elements (e.g. before a trailing `Triangles` section) cannot be told from a complete file
//! without `End`; it is read with the sections it has.

use super::cells::{check_nodes, Cell, Shape};
use super::lex::{capacity, point_index, show, Bad, Lex, Res};
use super::mesh::{FieldArray, ImportedMesh};

const C4: &[usize] = &[0, 1, 2, 3];
const C5: &[usize] = &[0, 1, 2, 3, 4];
const C6: &[usize] = &[0, 1, 2, 3, 4, 5];
const C8: &[usize] = &[0, 1, 2, 3, 4, 5, 6, 7];

/// Element sections: their cell kind and the vertices per record (a reference follows).
fn element_section(kw: &str) -> Option<(Cell, usize)> {
    let v = |shape, nodes, corners| Cell::Volume {
        shape,
        nodes,
        corners,
    };
    Some(match kw {
        "tetrahedra" => (v(Shape::Tet, 4, C4), 4),
        "tetrahedrap2" => (v(Shape::Tet, 10, C4), 10),
        "hexahedra" => (v(Shape::Hex, 8, C8), 8),
        "prisms" => (v(Shape::Wedge, 6, C6), 6),
        "pyramids" => (v(Shape::Pyramid, 5, C5), 5),
        "edges" => (Cell::Lower, 2),
        "edgesp2" => (Cell::Lower, 3),
        "triangles" => (Cell::Lower, 3),
        "trianglesp2" => (Cell::Lower, 6),
        "quadrilaterals" => (Cell::Lower, 4),
        "quadrilateralsq2" => (Cell::Lower, 9),
        _ => return None,
    })
}

/// Sections read past: the numbers per record.
fn other_section(kw: &str) -> Option<usize> {
    Some(match kw {
        "corners"
        | "requiredvertices"
        | "ridges"
        | "requirededges"
        | "requiredtriangles"
        | "requiredquadrilaterals"
        | "requiredtetrahedra" => 1,
        "normals" | "tangents" => 3,
        "normalatvertices" | "tangentatvertices" => 2,
        "normalattrianglevertices" | "normalatquadrilateralvertices" => 3,
        _ => return None,
    })
}

struct Medit<'a> {
    lx: Lex<'a>,
    section: String,
}

impl<'a> Medit<'a> {
    fn token(&mut self) -> Option<&'a [u8]> {
        loop {
            let t = self.lx.token()?;
            if t.starts_with(b"#") {
                let _ = self.lx.line();
                continue;
            }
            return Some(t);
        }
    }

    fn num<T: std::str::FromStr>(&mut self, what: &str) -> Res<T> {
        let t = self.token().ok_or_else(|| {
            Bad::new(
                &self.section,
                format!("file is truncated: it ends before {what}"),
            )
        })?;
        std::str::from_utf8(t)
            .ok()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| {
                Bad::new(
                    &self.section,
                    format!("expected {what}, found \"{}\"", show(t)),
                )
            })
    }
}

pub(super) fn parse_medit(bytes: &[u8]) -> Res<ImportedMesh> {
    let mut p = Medit {
        lx: Lex::new(bytes),
        section: "header".into(),
    };
    let first = p.token().unwrap_or_default();
    if !first.eq_ignore_ascii_case(b"MeshVersionFormatted") {
        return Err(Bad::new(
            "header",
            format!(
                "not a Medit file: it starts with \"{}\", not MeshVersionFormatted",
                show(first)
            ),
        ));
    }
    let _version: i64 = p.num("the version")?;
    let mut points: Option<Vec<[f64; 3]>> = None;
    // (kind, 1-based vertices, ref) per element, in file order.
    let mut cells: Vec<(Cell, Vec<i64>, f64)> = Vec::new();
    let mut dim = 3usize;
    let mut ended = false;
    while let Some(tok) = p.token() {
        let kw = String::from_utf8_lossy(tok).to_ascii_lowercase();
        p.section = String::from_utf8_lossy(tok).into_owned();
        match kw.as_str() {
            "end" => {
                ended = true;
                break;
            }
            "dimension" => {
                dim = p.num("the dimension")?;
                if dim != 3 {
                    return Err(Bad::new(
                        "Dimension",
                        format!("Dimension {dim}: only 3-D meshes have volume cells"),
                    ));
                }
            }
            "vertices" => {
                let n: usize = p.num("the number of vertices")?;
                let mut v = Vec::with_capacity(capacity(n, 8, p.lx.remaining()));
                for _ in 0..n {
                    let x = p.num("a coordinate")?;
                    let y = p.num("a coordinate")?;
                    let z = p.num("a coordinate")?;
                    let _ref: f64 = p.num("a vertex reference")?;
                    v.push([x, y, z]);
                }
                points = Some(v);
            }
            _ => {
                if let Some((cell, k)) = element_section(&kw) {
                    let n: usize = p.num("the number of elements")?;
                    cells.reserve(capacity(n, 2 * (k + 1), p.lx.remaining()));
                    for _ in 0..n {
                        let mut nodes = Vec::with_capacity(k);
                        for _ in 0..k {
                            nodes.push(p.num("a vertex number")?);
                        }
                        let r: f64 = p.num("an element reference")?;
                        cells.push((cell, nodes, r));
                    }
                } else if let Some(k) = other_section(&kw) {
                    let n: usize = p.num("the number of records")?;
                    for _ in 0..n.saturating_mul(k) {
                        p.num::<f64>("a value")?;
                    }
                } else {
                    return Err(Bad::new(
                        "file",
                        format!("unknown keyword \"{}\": cannot read past it", show(tok)),
                    ));
                }
            }
        }
    }
    let _ = dim;
    if !ended {
        let has_volume = cells.iter().any(|c| matches!(c.0, Cell::Volume { .. }));
        if !bytes.last().is_some_and(u8::is_ascii_whitespace) || !has_volume {
            return Err(Bad::new(
                "End",
                "file is truncated: no End keyword (a file without End must end with a line end after complete sections, volume elements among them)",
            ));
        }
        tracing::warn!("Medit file without End keyword: every section is complete, read as is");
    }
    let points = points.ok_or_else(|| Bad::new("Vertices", "the file has no Vertices section"))?;
    let np = points.len();
    let mut mesh = ImportedMesh::default();
    mesh.mesh.points = points;
    let mut refs = Vec::with_capacity(cells.len());
    let mut idx = Vec::new();
    for (i, (cell, nodes, r)) in cells.iter().enumerate() {
        idx.clear();
        if let Cell::Volume { .. } = cell {
            check_nodes(*cell, nodes.len(), &format!("element {}", i + 1))
                .map_err(|e| Bad::new("elements", e))?;
            for &v in nodes {
                idx.push(
                    v.checked_sub(1)
                        .and_then(|v| point_index(v, 0, np))
                        .ok_or_else(|| {
                            Bad::new(
                                "elements",
                                format!(
                                    "element {} refers to vertex {v}, but the file has {np} vertices (numbered from 1)",
                                    i + 1
                                ),
                            )
                        })?,
                );
            }
        }
        mesh.push_cell(*cell, &idx);
        refs.push(*r);
    }
    if !refs.is_empty() {
        mesh.cell_data.push(FieldArray {
            name: "ref".into(),
            components: 1,
            values: refs,
        });
    }
    Ok(mesh)
}
