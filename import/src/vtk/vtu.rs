//! VTK XML `.vtu` (`UnstructuredGrid`) reader.
//!
//! `.vtu` details:
//! - `<AppendedData encoding="raw">` holds bytes that are not XML: the file is split at
//!   `<AppendedData`, the part before it goes to the XML tokenizer and array offsets index the part
//!   after the `_` marker.
//! - base64 is decoded as a run of independently padded quanta, so header and data encoded
//!   separately (VTK) or together (meshio, uncompressed) both decode.
//! - compressed arrays: `[nblocks][block size][last block size][compressed sizes...]` then the
//!   blocks; each block is inflated to at most the size its header announces and must reach it.
//! - several `<Piece>`s are concatenated (each piece's connectivity is shifted by the points of the
//!   pieces before it); a point array is kept only if every piece has it.
//! - cells go through `vtk_cell`: tets (10), quadratic tets (24, corner tet), hexahedra,
//!   voxels, wedges and pyramids (split, see `split_cell`); the node count of a volume
//!   cell must match its type; other cells are counted. Point arrays with one component are
//!   point scalars, with more point vectors; cell arrays keep their components; arrays that are
//!   not numeric are skipped. The offsets must end where the connectivity does.
//! - LZ4 and LZMA compression are not supported (an error names the compressor).

use super::binary::{read_binary, Base64, Compression, Encoding, Stream};
use super::scalar::{ascii_values, bytes_to_f64, bytes_to_i64, Scalar};
use super::xml::{
    split_appended, walk_xml, Appended, AppendedEncoding, XmlArray, XmlDoc, XmlPiece,
};
use crate::cells::{check_nodes, vtk_cell, Cell};
use crate::lex::{find, point_index, show, Bad, Endian, Lex, Res};
use crate::mesh::{FieldArray, ImportedMesh, ScalarArray};

pub(crate) fn parse_vtu(bytes: &[u8]) -> Res<ImportedMesh> {
    let (xml, appended) = match find(bytes, b"<AppendedData") {
        Some(pos) => (
            bytes.get(..pos).unwrap_or_default(),
            Some(split_appended(bytes.get(pos..).unwrap_or_default())?),
        ),
        None => (bytes, None),
    };
    let doc = walk_xml(xml, appended.is_some())?;
    let enc = encoding(&doc)?;
    if doc.pieces.is_empty() {
        return Err(Bad::new("UnstructuredGrid", "no <Piece> element"));
    }

    let mut mesh = ImportedMesh::default();
    let mut point_arrays: Vec<FieldArray> = Vec::new();
    let mut cell_arrays: Vec<FieldArray> = Vec::new();
    for (pi, piece) in doc.pieces.iter().enumerate() {
        let base = mesh.mesh.points.len();
        read_piece_geometry(piece, pi, base, enc, appended.as_ref(), &mut mesh)?;
        let app = appended.as_ref();
        let points =
            read_piece_arrays(&piece.point_data, piece.n_points, pi, "PointData", enc, app)?;
        let cells = read_piece_arrays(&piece.cell_data, piece.n_cells, pi, "CellData", enc, app)?;
        if pi == 0 {
            point_arrays = points;
            cell_arrays = cells;
        } else {
            point_arrays = merge_piece_arrays(point_arrays, &points, pi, "point");
            cell_arrays = merge_piece_arrays(cell_arrays, &cells, pi, "cell");
        }
    }
    for a in point_arrays {
        if a.components == 1 {
            mesh.mesh.point_data.push(ScalarArray {
                name: a.name,
                values: a.values,
            });
        } else {
            mesh.point_vectors.push(a);
        }
    }
    mesh.cell_data = cell_arrays;
    Ok(mesh)
}

/// Keeps the arrays of the pieces so far that the next piece has too (same components), with
/// its values appended.
fn merge_piece_arrays(
    arrays: Vec<FieldArray>,
    next: &[FieldArray],
    pi: usize,
    kind: &str,
) -> Vec<FieldArray> {
    let mut kept = Vec::with_capacity(arrays.len());
    for mut a in arrays {
        match next
            .iter()
            .find(|b| b.name == a.name && b.components == a.components)
        {
            Some(b) => {
                a.values.extend_from_slice(&b.values);
                kept.push(a);
            }
            None => tracing::warn!(
                "{kind} array \"{}\" is missing from piece {pi}: skipped",
                a.name
            ),
        }
    }
    kept
}

fn encoding(doc: &XmlDoc) -> Res<Encoding> {
    let endian = match doc.byte_order.as_deref() {
        None | Some("LittleEndian") => Endian::Little,
        Some("BigEndian") => Endian::Big,
        Some(other) => {
            return Err(Bad::new(
                "VTKFile",
                format!("unknown byte_order \"{}\"", show(other.as_bytes())),
            ))
        }
    };
    let header64 = match doc.header_type.as_deref() {
        None | Some("UInt32") => false,
        Some("UInt64") => true,
        Some(other) => {
            return Err(Bad::new(
                "VTKFile",
                format!("unknown header_type \"{}\"", show(other.as_bytes())),
            ))
        }
    };
    let compression = match doc.compressor.as_deref() {
        None | Some("") => Compression::None,
        Some("vtkZLibDataCompressor") => Compression::Zlib,
        Some(other) => {
            return Err(Bad::new(
                "VTKFile",
                format!(
                    "compressor \"{}\" is not supported (only vtkZLibDataCompressor)",
                    show(other.as_bytes())
                ),
            ))
        }
    };
    Ok(Encoding {
        endian,
        header64,
        compression,
    })
}

enum Data<'a> {
    Ascii(&'a [u8]),
    Binary(Vec<u8>, Scalar),
}

/// The raw content of an array: its text (ascii) or its decoded bytes with their type.
fn array_data<'a>(
    a: &'a XmlArray,
    enc: Encoding,
    appended: Option<&Appended<'a>>,
    what: &str,
) -> Res<Data<'a>> {
    let ty = Scalar::from_xml(&a.ty).ok_or_else(|| {
        Bad::new(
            what,
            format!("unsupported data type \"{}\"", show(a.ty.as_bytes())),
        )
    })?;
    let mut stream = match a.format.as_str() {
        "ascii" => return Ok(Data::Ascii(&a.text)),
        "binary" => Stream::Base64(Base64::new(&a.text)),
        "appended" => {
            let app = appended.ok_or_else(|| {
                Bad::new(
                    what,
                    "format=\"appended\" but the file has no <AppendedData>",
                )
            })?;
            let offset: usize = a
                .offset
                .as_deref()
                .and_then(|o| o.trim().parse().ok())
                .ok_or_else(|| Bad::new(what, "appended array without a valid offset"))?;
            let rest = app.data.get(offset..).ok_or_else(|| {
                Bad::new(
                    what,
                    format!("file is truncated: offset {offset} is past the end of the appended data ({} bytes)", app.data.len()),
                )
            })?;
            match app.encoding {
                AppendedEncoding::Raw => Stream::Raw(Lex::new(rest)),
                AppendedEncoding::Base64 => Stream::Base64(Base64::new(rest)),
            }
        }
        other => {
            return Err(Bad::new(
                what,
                format!("unknown format \"{}\"", show(other.as_bytes())),
            ))
        }
    };
    let bytes = read_binary(&mut stream, enc, what)?;
    if bytes.len() % ty.size() != 0 {
        return Err(Bad::new(
            what,
            format!(
                "{} bytes is not a whole number of {} values",
                bytes.len(),
                a.ty
            ),
        ));
    }
    Ok(Data::Binary(bytes, ty))
}

fn array_f64(a: &XmlArray, enc: Encoding, app: Option<&Appended<'_>>, what: &str) -> Res<Vec<f64>> {
    Ok(match array_data(a, enc, app, what)? {
        Data::Ascii(text) => ascii_values(text, what)?,
        Data::Binary(bytes, ty) => bytes_to_f64(&bytes, ty, enc.endian),
    })
}

fn array_i64(a: &XmlArray, enc: Encoding, app: Option<&Appended<'_>>, what: &str) -> Res<Vec<i64>> {
    match array_data(a, enc, app, what)? {
        Data::Ascii(text) => ascii_values(text, what),
        Data::Binary(bytes, ty) => {
            bytes_to_i64(&bytes, ty, enc.endian).map_err(|e| Bad::new(what, e))
        }
    }
}

fn ncomp(a: &XmlArray, default: usize, what: &str) -> Res<usize> {
    match a.ncomp.as_deref() {
        None => Ok(default),
        Some(v) => v.trim().parse().map_err(|_| {
            Bad::new(
                what,
                format!(
                    "NumberOfComponents=\"{}\" is not a count",
                    show(v.as_bytes())
                ),
            )
        }),
    }
}

fn read_piece_geometry(
    piece: &XmlPiece,
    pi: usize,
    base: usize,
    enc: Encoding,
    app: Option<&Appended<'_>>,
    mesh: &mut ImportedMesh,
) -> Res<()> {
    let np = piece.n_points;
    let what = format!("Piece {pi} Points");
    match &piece.points {
        Some(a) => {
            if ncomp(a, 3, &what)? != 3 {
                return Err(Bad::new(what, "points must have 3 components"));
            }
            let v = array_f64(a, enc, app, &what)?;
            if Some(v.len()) != np.checked_mul(3) {
                return Err(Bad::new(
                    what,
                    format!(
                        "NumberOfPoints is {np}: expected {} values, found {}",
                        np.saturating_mul(3),
                        v.len()
                    ),
                ));
            }
            mesh.mesh
                .points
                .extend(v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
        }
        None if np == 0 => {}
        None => return Err(Bad::new(what, "missing <Points> array")),
    }

    let nc = piece.n_cells;
    let section = format!("Piece {pi} Cells");
    let get = |name: &str| piece.cells.iter().find(|a| a.name == name);
    let (Some(conn), Some(offsets), Some(types)) =
        (get("connectivity"), get("offsets"), get("types"))
    else {
        if nc == 0 {
            return Ok(());
        }
        return Err(Bad::new(
            section,
            "missing one of the connectivity, offsets and types arrays",
        ));
    };
    let conn = array_i64(conn, enc, app, &format!("{section} connectivity"))?;
    let offsets = array_i64(offsets, enc, app, &format!("{section} offsets"))?;
    let types = array_i64(types, enc, app, &format!("{section} types"))?;
    if types.len() != nc {
        return Err(Bad::new(
            section,
            format!(
                "NumberOfCells is {nc} but there are {} cell types",
                types.len()
            ),
        ));
    }
    // End offsets (one per cell); also accept start offsets with a trailing end (nc + 1 values).
    let ends: &[i64] = if offsets.len() == nc {
        &offsets
    } else if offsets.len() == nc + 1 && offsets.first() == Some(&0) {
        offsets.get(1..).unwrap_or_default()
    } else {
        return Err(Bad::new(
            section,
            format!(
                "NumberOfCells is {nc} but there are {} offsets",
                offsets.len()
            ),
        ));
    };
    let mut start = 0usize;
    for (i, (&end, &ty)) in ends.iter().zip(&types).enumerate() {
        let end = usize::try_from(end)
            .ok()
            .filter(|&e| e >= start && e <= conn.len())
            .ok_or_else(|| {
                Bad::new(
                    section.clone(),
                    format!("offset {end} of cell {i} is out of order or past the connectivity ({} values)", conn.len()),
                )
            })?;
        let cell = conn.get(start..end).unwrap_or_default();
        start = end;
        let kind = vtk_cell(ty);
        let mut nodes = Vec::new();
        if let Cell::Volume { .. } = kind {
            check_nodes(kind, cell.len(), &format!("cell {i} (type {ty})"))
                .map_err(|e| Bad::new(section.clone(), e))?;
            for &v in cell {
                nodes.push(point_index(v, base, np).ok_or_else(|| {
                    Bad::new(
                        section.clone(),
                        format!("cell {i} refers to point {v}, but the piece has {np} points"),
                    )
                })?);
            }
        }
        mesh.push_cell(kind, &nodes);
    }
    if start != conn.len() {
        return Err(Bad::new(
            section,
            format!(
                "the offsets end at {start} but the connectivity has {} values (a data type that is not what the header declares?)",
                conn.len()
            ),
        ));
    }
    Ok(())
}

/// A piece's point or cell arrays (`n` tuples each); arrays that are not numeric are skipped.
fn read_piece_arrays(
    arrays: &[XmlArray],
    n: usize,
    pi: usize,
    kind: &str,
    enc: Encoding,
    app: Option<&Appended<'_>>,
) -> Res<Vec<FieldArray>> {
    let mut out = Vec::new();
    for (k, a) in arrays.iter().enumerate() {
        let name = if a.name.is_empty() {
            format!("array{k}")
        } else {
            a.name.clone()
        };
        let what = format!("Piece {pi} {kind} \"{name}\"");
        let components = ncomp(a, 1, &what)?;
        if components == 0 {
            return Err(Bad::new(what, "NumberOfComponents is 0"));
        }
        if Scalar::from_xml(&a.ty).is_none() {
            tracing::warn!("{what}: type \"{}\" is not numeric: skipped", a.ty);
            continue;
        }
        let values = array_f64(a, enc, app, &what)?;
        if Some(values.len()) != n.checked_mul(components) {
            let count = if kind == "PointData" {
                "NumberOfPoints"
            } else {
                "NumberOfCells"
            };
            return Err(Bad::new(
                what,
                format!(
                    "{} values for {count} {n} and {components} components",
                    values.len(),
                ),
            ));
        }
        out.push(FieldArray {
            name,
            components,
            values,
        });
    }
    Ok(out)
}
