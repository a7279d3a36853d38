//! Legacy VTK `.vtk` (`DATASET UNSTRUCTURED_GRID`) reader.
//!
//! Details: versions up to 4.2 (`CELLS n size` with counts) and 5.x (`OFFSETS` and
//! `CONNECTIVITY`), ascii and binary (big-endian); `POINT_DATA` and `CELL_DATA` `SCALARS`,
//! `VECTORS`, `NORMALS` and `FIELD` arrays are read (point arrays of one component as point
//! scalars); `METADATA` blocks and the other attributes are read past. `long` is 8 bytes and
//! `vtkIdType` 4, as VTK writes them on 64-bit Linux.

use super::scalar::{bytes_to_f64, bytes_to_i64, Scalar};
use crate::cells::{check_nodes, vtk_cell, Cell};
use crate::lex::{capacity, point_index, show, Bad, Endian, Lex, Res};
use crate::mesh::{FieldArray, ImportedMesh, ScalarArray};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LegacyType {
    Num(Scalar),
    Bit,
    Str,
}

fn legacy_type(tok: &[u8]) -> Option<LegacyType> {
    let t = String::from_utf8_lossy(tok).to_ascii_lowercase();
    Some(LegacyType::Num(match t.as_str() {
        "bit" => return Some(LegacyType::Bit),
        "string" | "utf8_string" => return Some(LegacyType::Str),
        "char" | "signed_char" | "vtktypeint8" => Scalar::I8,
        "unsigned_char" | "vtktypeuint8" => Scalar::U8,
        "short" | "vtktypeint16" => Scalar::I16,
        "unsigned_short" | "vtktypeuint16" => Scalar::U16,
        "int" | "vtkidtype" | "vtktypeint32" => Scalar::I32,
        "unsigned_int" | "vtktypeuint32" => Scalar::U32,
        "long" | "vtktypeint64" => Scalar::I64,
        "unsigned_long" | "vtktypeuint64" => Scalar::U64,
        "float" | "vtktypefloat32" => Scalar::F32,
        "double" | "vtktypefloat64" => Scalar::F64,
        _ => return None,
    }))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Attr {
    None,
    Points,
    Cells,
}

struct Legacy<'a> {
    lx: Lex<'a>,
    binary: bool,
}

fn is(tok: &[u8], kw: &str) -> bool {
    tok.eq_ignore_ascii_case(kw.as_bytes())
}

impl<'a> Legacy<'a> {
    fn token(&mut self, section: &str, what: &str) -> Res<&'a [u8]> {
        self.lx
            .token()
            .ok_or_else(|| Bad::new(section, format!("file is truncated: it ends before {what}")))
    }

    fn count(&mut self, section: &str, what: &str) -> Res<usize> {
        let t = self.token(section, what)?;
        std::str::from_utf8(t)
            .ok()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| Bad::new(section, format!("expected {what}, found \"{}\"", show(t))))
    }

    fn data_type(&mut self, section: &str) -> Res<LegacyType> {
        let t = self.token(section, "a data type")?;
        legacy_type(t)
            .ok_or_else(|| Bad::new(section, format!("unknown data type \"{}\"", show(t))))
    }

    /// Ends a keyword line: in binary files the data starts on the next line.
    fn end_header(&mut self) {
        if self.binary {
            let _ = self.lx.line();
        }
    }

    fn binary_run(&mut self, n: usize, size: usize, section: &str) -> Res<&'a [u8]> {
        let bytes = n.saturating_mul(size);
        if bytes > self.lx.remaining() {
            return Err(Bad::new(
                section,
                format!(
                    "file is truncated: {n} values need {bytes} bytes but only {} remain",
                    self.lx.remaining()
                ),
            ));
        }
        self.lx
            .take(bytes)
            .ok_or_else(|| Bad::new(section, "file is truncated"))
    }

    fn ascii_run<T: std::str::FromStr>(&mut self, n: usize, section: &str) -> Res<Vec<T>> {
        let mut out = Vec::with_capacity(capacity(n, 2, self.lx.remaining()));
        while out.len() < n {
            let Some(tok) = self.lx.token() else {
                return Err(Bad::new(
                    section,
                    format!(
                        "expected {n} values, the file ends after {} (truncated?)",
                        out.len()
                    ),
                ));
            };
            match std::str::from_utf8(tok).ok().and_then(|s| s.parse().ok()) {
                Some(v) => out.push(v),
                None => {
                    return Err(Bad::new(
                        section,
                        format!(
                            "expected {n} values, found {} before \"{}\"",
                            out.len(),
                            show(tok)
                        ),
                    ))
                }
            }
        }
        Ok(out)
    }

    fn values_f64(&mut self, n: usize, ty: LegacyType, section: &str) -> Res<Vec<f64>> {
        match ty {
            LegacyType::Num(s) if self.binary => Ok(bytes_to_f64(
                self.binary_run(n, s.size(), section)?,
                s,
                Endian::Big,
            )),
            LegacyType::Num(_) => self.ascii_run(n, section),
            _ => Err(Bad::new(section, "expected a numeric data type")),
        }
    }

    fn values_i64(&mut self, n: usize, ty: LegacyType, section: &str) -> Res<Vec<i64>> {
        match ty {
            LegacyType::Num(s) if self.binary => {
                bytes_to_i64(self.binary_run(n, s.size(), section)?, s, Endian::Big)
                    .map_err(|e| Bad::new(section, e))
            }
            LegacyType::Num(_) => self.ascii_run(n, section),
            _ => Err(Bad::new(section, "expected an integer data type")),
        }
    }

    /// Reads past `n` values of any type.
    fn skip_values(&mut self, n: usize, ty: LegacyType, section: &str) -> Res<()> {
        match ty {
            LegacyType::Num(s) if self.binary => self.binary_run(n, s.size(), section).map(drop),
            LegacyType::Bit if self.binary => self.binary_run(n.div_ceil(8), 1, section).map(drop),
            LegacyType::Str if self.binary => {
                for _ in 0..n {
                    self.lx.line().ok_or_else(|| {
                        Bad::new(section, "file is truncated inside a string array")
                    })?;
                }
                Ok(())
            }
            _ => {
                for i in 0..n {
                    self.lx.token().ok_or_else(|| {
                        Bad::new(
                            section,
                            format!("expected {n} values, the file ends after {i} (truncated?)"),
                        )
                    })?;
                }
                Ok(())
            }
        }
    }

    /// `METADATA` blocks run to the next empty line.
    fn skip_metadata(&mut self) {
        let _ = self.lx.line();
        while let Some(line) = self.lx.line() {
            if line.iter().all(u8::is_ascii_whitespace) {
                break;
            }
        }
    }

    fn skip_metadata_if_any(&mut self) {
        if self.lx.peek_token().is_some_and(|t| is(t, "METADATA")) {
            let _ = self.lx.token();
            self.skip_metadata();
        }
    }
}

pub(crate) fn parse_legacy(bytes: &[u8]) -> Res<ImportedMesh> {
    let mut lx = Lex::new(bytes);
    lx.skip_ws();
    let first = lx.line().unwrap_or_default();
    let words: Vec<String> = String::from_utf8_lossy(first)
        .trim_start_matches('#')
        .split_whitespace()
        .take(2)
        .map(str::to_ascii_lowercase)
        .collect();
    if !first.starts_with(b"#") || words != ["vtk", "datafile"] {
        return Err(Bad::new(
            "header",
            format!("not a legacy VTK file: the first line is \"{}\", not \"# vtk DataFile Version x.y\"", show(first)),
        ));
    }
    let _title = lx.line();
    let mut p = Legacy { lx, binary: false };
    let ft = p.token("header", "ASCII or BINARY")?;
    p.binary = if is(ft, "ASCII") {
        false
    } else if is(ft, "BINARY") {
        true
    } else {
        return Err(Bad::new(
            "header",
            format!("expected ASCII or BINARY, found \"{}\"", show(ft)),
        ));
    };
    let ds = p.token("header", "DATASET")?;
    if !is(ds, "DATASET") {
        return Err(Bad::new(
            "header",
            format!("expected DATASET, found \"{}\"", show(ds)),
        ));
    }
    let kind = p.token("DATASET", "the dataset type")?;
    if !is(kind, "UNSTRUCTURED_GRID") {
        return Err(Bad::new(
            "DATASET",
            format!(
                "DATASET {} is not supported; expected UNSTRUCTURED_GRID",
                show(kind)
            ),
        ));
    }

    let mut points: Option<Vec<f64>> = None;
    // Cells as (ends, connectivity).
    let mut cells: Option<(Vec<usize>, Vec<i64>)> = None;
    let mut types: Option<Vec<i64>> = None;
    let mut attr = Attr::None;
    let mut attr_n = 0usize;
    let mut point_data = Vec::new();
    let mut point_vectors = Vec::new();
    let mut cell_data = Vec::new();
    // Point and cell arrays go to their lists; other attributes are read past.
    let mut keep = |attr: Attr, name: String, components: usize, values: Vec<f64>| match attr {
        Attr::Points if components == 1 => point_data.push(ScalarArray { name, values }),
        Attr::Points => point_vectors.push(FieldArray {
            name,
            components,
            values,
        }),
        Attr::Cells => cell_data.push(FieldArray {
            name,
            components,
            values,
        }),
        Attr::None => {}
    };

    while let Some(tok) = p.lx.token() {
        let kw = String::from_utf8_lossy(tok).to_ascii_uppercase();
        match kw.as_str() {
            "POINTS" => {
                let n = p.count("POINTS", "the number of points")?;
                let ty = p.data_type("POINTS")?;
                p.end_header();
                let v = p.values_f64(n.saturating_mul(3), ty, "POINTS")?;
                points = Some(v);
            }
            "CELLS" => {
                let a = p.count("CELLS", "the number of cells")?;
                let b = p.count("CELLS", "the size of the cell list")?;
                p.end_header();
                if p.lx.peek_token().is_some_and(|t| is(t, "OFFSETS")) {
                    let _ = p.lx.token();
                    let ty = p.data_type("OFFSETS")?;
                    p.end_header();
                    let offsets = p.values_i64(a, ty, "OFFSETS")?;
                    p.skip_metadata_if_any();
                    let kw = p.token("CELLS", "CONNECTIVITY")?;
                    if !is(kw, "CONNECTIVITY") {
                        return Err(Bad::new(
                            "CELLS",
                            format!("expected CONNECTIVITY, found \"{}\"", show(kw)),
                        ));
                    }
                    let ty = p.data_type("CONNECTIVITY")?;
                    p.end_header();
                    let conn = p.values_i64(b, ty, "CONNECTIVITY")?;
                    cells = Some(cells_from_offsets(&offsets, conn)?);
                } else {
                    let ty = if p.binary {
                        LegacyType::Num(Scalar::I32)
                    } else {
                        LegacyType::Num(Scalar::I64)
                    };
                    let list = p.values_i64(b, ty, "CELLS")?;
                    cells = Some(cells_from_counts(a, list)?);
                }
            }
            "CELL_TYPES" => {
                let n = p.count("CELL_TYPES", "the number of cells")?;
                p.end_header();
                let ty = if p.binary {
                    LegacyType::Num(Scalar::I32)
                } else {
                    LegacyType::Num(Scalar::I64)
                };
                types = Some(p.values_i64(n, ty, "CELL_TYPES")?);
            }
            "POINT_DATA" => {
                attr_n = p.count("POINT_DATA", "the number of points")?;
                let np = points.as_ref().map_or(0, |v| v.len() / 3);
                if attr_n != np {
                    return Err(Bad::new(
                        "POINT_DATA",
                        format!("POINT_DATA {attr_n} but the file has {np} points"),
                    ));
                }
                attr = Attr::Points;
            }
            "CELL_DATA" => {
                attr_n = p.count("CELL_DATA", "the number of cells")?;
                if let Some((ends, _)) = &cells {
                    if attr_n != ends.len() {
                        return Err(Bad::new(
                            "CELL_DATA",
                            format!("CELL_DATA {attr_n} but the file has {} cells", ends.len()),
                        ));
                    }
                }
                attr = Attr::Cells;
            }
            "METADATA" => p.skip_metadata(),
            "FIELD" => {
                let _name = p.token("FIELD", "the field name")?;
                let arrays = p.count("FIELD", "the number of arrays")?;
                for _ in 0..arrays {
                    let name = p.token("FIELD", "an array name")?;
                    if is(name, "NULL_ARRAY") {
                        continue;
                    }
                    let name = String::from_utf8_lossy(name).into_owned();
                    let section = format!("FIELD array \"{name}\"");
                    let nc = p.count(&section, "the number of components")?;
                    let nt = p.count(&section, "the number of tuples")?;
                    let ty = p.data_type(&section)?;
                    p.end_header();
                    let n = nc.saturating_mul(nt);
                    if attr != Attr::None && nc > 0 && matches!(ty, LegacyType::Num(_)) {
                        if nt != attr_n {
                            let which = if attr == Attr::Points {
                                "POINT_DATA"
                            } else {
                                "CELL_DATA"
                            };
                            return Err(Bad::new(
                                section,
                                format!("{nt} tuples for {which} {attr_n}"),
                            ));
                        }
                        let values = p.values_f64(n, ty, &section)?;
                        keep(attr, name, nc, values);
                    } else {
                        p.skip_values(n, ty, &section)?;
                    }
                    p.skip_metadata_if_any();
                }
            }
            "SCALARS" => {
                let line = p.lx.line().unwrap_or_default();
                let words: Vec<&[u8]> = line
                    .split(u8::is_ascii_whitespace)
                    .filter(|w| !w.is_empty())
                    .collect();
                let (Some(name), Some(ty)) = (words.first(), words.get(1)) else {
                    return Err(Bad::new(
                        "SCALARS",
                        "expected \"SCALARS name type [components]\"",
                    ));
                };
                let name = String::from_utf8_lossy(name).into_owned();
                let section = format!("SCALARS \"{name}\"");
                let ty = legacy_type(ty).ok_or_else(|| {
                    Bad::new(&section, format!("unknown data type \"{}\"", show(ty)))
                })?;
                let nc: usize = match words.get(2) {
                    Some(w) => std::str::from_utf8(w)
                        .ok()
                        .and_then(|s| s.parse().ok())
                        .ok_or_else(|| {
                            Bad::new(
                                &section,
                                format!("bad number of components \"{}\"", show(w)),
                            )
                        })?,
                    None => 1,
                };
                if p.lx.peek_token().is_some_and(|t| is(t, "LOOKUP_TABLE")) {
                    let _ = p.lx.token();
                    let _ = p.lx.line();
                }
                let n = attr_n.saturating_mul(nc);
                if attr != Attr::None && nc > 0 && matches!(ty, LegacyType::Num(_)) {
                    let values = p.values_f64(n, ty, &section)?;
                    keep(attr, name, nc, values);
                } else {
                    p.skip_values(n, ty, &section)?;
                }
                p.skip_metadata_if_any();
            }
            "VECTORS" | "NORMALS" if attr != Attr::None => {
                let name = p.token(&kw, "the array name")?;
                let name = String::from_utf8_lossy(name).into_owned();
                let section = format!("{kw} \"{name}\"");
                let ty = p.data_type(&section)?;
                p.end_header();
                let values = p.values_f64(attr_n.saturating_mul(3), ty, &section)?;
                keep(attr, name, 3, values);
                p.skip_metadata_if_any();
            }
            "VECTORS" | "NORMALS" | "TENSORS" | "TENSORS6" | "GLOBAL_IDS" | "PEDIGREE_IDS"
            | "EDGE_FLAGS" => {
                let _name = p.token(&kw, "the array name")?;
                let ty = p.data_type(&kw)?;
                p.end_header();
                let per = match kw.as_str() {
                    "VECTORS" | "NORMALS" => 3,
                    "TENSORS" => 9,
                    "TENSORS6" => 6,
                    _ => 1,
                };
                p.skip_values(attr_n.saturating_mul(per), ty, &kw)?;
                p.skip_metadata_if_any();
            }
            "TEXTURE_COORDINATES" => {
                let _name = p.token(&kw, "the array name")?;
                let dim = p.count(&kw, "the dimension")?;
                let ty = p.data_type(&kw)?;
                p.end_header();
                p.skip_values(attr_n.saturating_mul(dim), ty, &kw)?;
                p.skip_metadata_if_any();
            }
            "COLOR_SCALARS" | "LOOKUP_TABLE" => {
                let _name = p.token(&kw, "the array name")?;
                let m = p.count(&kw, "a count")?;
                p.end_header();
                let n = if kw == "COLOR_SCALARS" {
                    attr_n.saturating_mul(m)
                } else {
                    m.saturating_mul(4)
                };
                let ty = if p.binary {
                    LegacyType::Num(Scalar::U8)
                } else {
                    LegacyType::Num(Scalar::F64)
                };
                p.skip_values(n, ty, &kw)?;
            }
            _ => {
                let hint = if p.binary {
                    " (binary data longer or shorter than its header declares?)"
                } else {
                    ""
                };
                let found = if tok.iter().all(u8::is_ascii_graphic) {
                    format!("keyword \"{}\"", show(tok))
                } else {
                    format!(
                        "{} bytes of binary data where a keyword should be",
                        tok.len()
                    )
                };
                return Err(Bad::new("file", format!("unexpected {found}{hint}")));
            }
        }
    }

    let points = points.ok_or_else(|| Bad::new("POINTS", "the file has no POINTS section"))?;
    let np = points.len() / 3;
    let mut mesh = ImportedMesh::default();
    mesh.mesh.points = points.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    mesh.mesh.point_data = point_data;
    mesh.point_vectors = point_vectors;
    mesh.cell_data = cell_data;
    let (ends, conn) =
        cells.ok_or_else(|| Bad::new("CELLS", "the file has no CELLS section (truncated?)"))?;
    let types = types.ok_or_else(|| {
        Bad::new(
            "CELL_TYPES",
            "the file has no CELL_TYPES section (truncated?)",
        )
    })?;
    if types.len() != ends.len() {
        return Err(Bad::new(
            "CELL_TYPES",
            format!(
                "CELL_TYPES has {} entries but CELLS has {} cells",
                types.len(),
                ends.len()
            ),
        ));
    }
    let mut start = 0;
    let mut nodes = Vec::new();
    for (i, (&end, &ty)) in ends.iter().zip(&types).enumerate() {
        let cell = conn.get(start..end).unwrap_or_default();
        start = end;
        let kind = vtk_cell(ty);
        nodes.clear();
        if let Cell::Volume { .. } = kind {
            check_nodes(kind, cell.len(), &format!("cell {i} (type {ty})"))
                .map_err(|e| Bad::new("CELLS", e))?;
            for &v in cell {
                nodes.push(point_index(v, 0, np).ok_or_else(|| {
                    Bad::new(
                        "CELLS",
                        format!("cell {i} refers to point {v}, but the file has {np} points"),
                    )
                })?);
            }
        }
        mesh.push_cell(kind, &nodes);
    }
    Ok(mesh)
}

/// Legacy cell list `n k i1..ik ...` into end offsets and connectivity.
fn cells_from_counts(n: usize, list: Vec<i64>) -> Res<(Vec<usize>, Vec<i64>)> {
    let mut ends = Vec::with_capacity(capacity(n, 1, list.len()));
    let mut conn = Vec::with_capacity(list.len());
    let mut pos = 0usize;
    for i in 0..n {
        let k = list
            .get(pos)
            .and_then(|&k| usize::try_from(k).ok())
            .ok_or_else(|| {
                Bad::new(
                    "CELLS",
                    format!(
                        "the cell list ({} values) ends before cell {i} of {n}",
                        list.len()
                    ),
                )
            })?;
        let end = pos
            .checked_add(1)
            .and_then(|p| p.checked_add(k))
            .unwrap_or(usize::MAX);
        let cell = list.get(pos + 1..end).ok_or_else(|| {
            Bad::new(
                "CELLS",
                format!(
                    "cell {i} with {k} points runs past the cell list ({} values)",
                    list.len()
                ),
            )
        })?;
        conn.extend_from_slice(cell);
        ends.push(conn.len());
        pos = end;
    }
    if pos != list.len() {
        return Err(Bad::new(
            "CELLS",
            format!(
                "the header says {} values but the {n} cells use {pos}",
                list.len()
            ),
        ));
    }
    Ok((ends, conn))
}

/// 5.x `OFFSETS` (n + 1 start offsets) and `CONNECTIVITY` into end offsets and connectivity.
fn cells_from_offsets(offsets: &[i64], conn: Vec<i64>) -> Res<(Vec<usize>, Vec<i64>)> {
    if offsets.is_empty() {
        return Ok((Vec::new(), conn));
    }
    if offsets.first() != Some(&0) {
        return Err(Bad::new("OFFSETS", "the first offset must be 0"));
    }
    let mut ends = Vec::with_capacity(offsets.len() - 1);
    let mut prev = 0usize;
    for (i, &o) in offsets.iter().enumerate().skip(1) {
        let o = usize::try_from(o)
            .ok()
            .filter(|&o| o >= prev && o <= conn.len())
            .ok_or_else(|| {
                Bad::new(
                    "OFFSETS",
                    format!(
                        "offset {i} ({o}) is out of order or past the connectivity ({} values)",
                        conn.len()
                    ),
                )
            })?;
        ends.push(o);
        prev = o;
    }
    if prev != conn.len() {
        return Err(Bad::new(
            "OFFSETS",
            format!(
                "the last offset is {prev} but CONNECTIVITY has {} values",
                conn.len()
            ),
        ));
    }
    Ok((ends, conn))
}
