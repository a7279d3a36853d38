//! VTK readers: XML `.vtu` (`UnstructuredGrid`) and legacy `.vtk` (`DATASET UNSTRUCTURED_GRID`).
//!
//! Both are written here rather than with `vtkio` (see the parent module for what `vtkio` 0.6.3
//! failed on). The XML is tokenized by `quick-xml`; zlib blocks are inflated by `flate2`; base64,
//! the block headers, the appended-data layout and the legacy grammar are ours.
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
//!
//! Legacy details: versions up to 4.2 (`CELLS n size` with counts) and 5.x (`OFFSETS` and
//! `CONNECTIVITY`), ascii and binary (big-endian); `POINT_DATA` and `CELL_DATA` `SCALARS`,
//! `VECTORS`, `NORMALS` and `FIELD` arrays are read (point arrays of one component as point
//! scalars); `METADATA` blocks and the other attributes are read past. `long` is 8 bytes and `vtkIdType` 4, as VTK writes them on 64-bit Linux.

use std::borrow::Cow;
use std::io::Read;

use quick_xml::events::{BytesStart, Event};
use quick_xml::Reader;

use super::cells::{check_nodes, vtk_cell, Cell};
use super::lex::{capacity, find, point_index, show, Bad, Endian, Lex, Res};
use super::mesh::{FieldArray, ImportedMesh, ScalarArray};

// ------------------------------------------------------------------------------------------------
// Scalars shared by both formats.

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::I64 | Scalar::U64 | Scalar::F64 => 8,
        }
    }

    fn from_xml(name: &str) -> Option<Scalar> {
        Some(match name {
            "Int8" | "Char" => Scalar::I8,
            "UInt8" => Scalar::U8,
            "Int16" => Scalar::I16,
            "UInt16" => Scalar::U16,
            "Int32" => Scalar::I32,
            "UInt32" => Scalar::U32,
            "Int64" => Scalar::I64,
            "UInt64" => Scalar::U64,
            "Float32" => Scalar::F32,
            "Float64" => Scalar::F64,
            _ => return None,
        })
    }
}

macro_rules! convert {
    ($bytes:expr, $endian:expr, $ty:ty, $map:expr) => {{
        const N: usize = std::mem::size_of::<$ty>();
        $bytes
            .chunks_exact(N)
            .map(|c| {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                let v = match $endian {
                    Endian::Little => <$ty>::from_le_bytes(a),
                    Endian::Big => <$ty>::from_be_bytes(a),
                };
                $map(v)
            })
            .collect()
    }};
}

/// Binary values as f64 (`bytes.len()` a multiple of the scalar size; a tail is ignored).
fn bytes_to_f64(bytes: &[u8], t: Scalar, e: Endian) -> Vec<f64> {
    match t {
        Scalar::I8 => bytes.iter().map(|&b| f64::from(b as i8)).collect(),
        Scalar::U8 => bytes.iter().map(|&b| f64::from(b)).collect(),
        Scalar::I16 => convert!(bytes, e, i16, f64::from),
        Scalar::U16 => convert!(bytes, e, u16, f64::from),
        Scalar::I32 => convert!(bytes, e, i32, f64::from),
        Scalar::U32 => convert!(bytes, e, u32, f64::from),
        Scalar::I64 => convert!(bytes, e, i64, |v: i64| v as f64),
        Scalar::U64 => convert!(bytes, e, u64, |v: u64| v as f64),
        Scalar::F32 => convert!(bytes, e, f32, f64::from),
        Scalar::F64 => convert!(bytes, e, f64, |v: f64| v),
    }
}

/// Binary values as i64; floating-point types and values past `i64::MAX` are refused.
fn bytes_to_i64(bytes: &[u8], t: Scalar, e: Endian) -> Result<Vec<i64>, String> {
    Ok(match t {
        Scalar::I8 => bytes.iter().map(|&b| i64::from(b as i8)).collect(),
        Scalar::U8 => bytes.iter().map(|&b| i64::from(b)).collect(),
        Scalar::I16 => convert!(bytes, e, i16, i64::from),
        Scalar::U16 => convert!(bytes, e, u16, i64::from),
        Scalar::I32 => convert!(bytes, e, i32, i64::from),
        Scalar::U32 => convert!(bytes, e, u32, i64::from),
        Scalar::I64 => convert!(bytes, e, i64, |v: i64| v),
        Scalar::U64 => {
            let v: Vec<u64> = convert!(bytes, e, u64, |v: u64| v);
            v.into_iter()
                .map(i64::try_from)
                .collect::<Result<_, _>>()
                .map_err(|_| "holds a value past 2^63".to_string())?
        }
        Scalar::F32 | Scalar::F64 => {
            return Err(format!("has type {t:?}; expected an integer type"))
        }
    })
}

/// Parses whitespace-separated numbers.
fn ascii_values<T: std::str::FromStr>(text: &[u8], what: &str) -> Res<Vec<T>> {
    let text = std::str::from_utf8(text)
        .map_err(|_| Bad::new(what, "ascii data is not valid UTF-8 text"))?;
    text.split_ascii_whitespace()
        .enumerate()
        .map(|(i, tok)| {
            tok.parse::<T>().map_err(|_| {
                Bad::new(
                    what,
                    format!("value {i} \"{}\" is not a number", show(tok.as_bytes())),
                )
            })
        })
        .collect()
}

// ------------------------------------------------------------------------------------------------
// VTK XML.

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Ctx {
    Points,
    Cells,
    PointData,
    CellData,
    Other,
}

#[derive(Debug, Default)]
struct XmlArray {
    name: String,
    ty: String,
    ncomp: Option<String>,
    format: String,
    offset: Option<String>,
    text: Vec<u8>,
}

#[derive(Debug, Default)]
struct XmlPiece {
    n_points: usize,
    n_cells: usize,
    points: Option<XmlArray>,
    cells: Vec<XmlArray>,
    point_data: Vec<XmlArray>,
    cell_data: Vec<XmlArray>,
}

#[derive(Debug, Default)]
struct XmlDoc {
    byte_order: Option<String>,
    header_type: Option<String>,
    compressor: Option<String>,
    pieces: Vec<XmlPiece>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Compression {
    None,
    Zlib,
}

/// How binary arrays are laid out.
#[derive(Debug, Clone, Copy)]
struct Encoding {
    endian: Endian,
    header64: bool,
    compression: Compression,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum AppendedEncoding {
    Raw,
    Base64,
}

struct Appended<'a> {
    encoding: AppendedEncoding,
    data: &'a [u8],
}

pub(super) fn parse_vtu(bytes: &[u8]) -> Res<ImportedMesh> {
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

/// `<AppendedData encoding="...">` then `_` then the data up to `</AppendedData>` (or the end of a
/// truncated file).
fn split_appended(tail: &[u8]) -> Res<Appended<'_>> {
    let section = "AppendedData";
    let close = tail
        .iter()
        .position(|&c| c == b'>')
        .ok_or_else(|| Bad::new(section, "file is truncated inside the <AppendedData> tag"))?;
    let tag = tail.get(..=close).unwrap_or_default();
    let mut reader = Reader::from_reader(tag);
    let encoding = match reader.read_event() {
        Ok(Event::Start(e)) | Ok(Event::Empty(e)) => attrs(&e)?
            .into_iter()
            .find(|(k, _)| k == "encoding")
            .map(|(_, v)| v)
            .unwrap_or_else(|| "base64".into()),
        _ => return Err(Bad::new(section, "malformed <AppendedData> tag")),
    };
    let encoding = match encoding.as_str() {
        "raw" => AppendedEncoding::Raw,
        "base64" => AppendedEncoding::Base64,
        other => return Err(Bad::new(section, format!("unknown encoding \"{other}\""))),
    };
    let rest = tail.get(close + 1..).unwrap_or_default();
    let start = rest
        .iter()
        .position(|c| !c.is_ascii_whitespace())
        .ok_or_else(|| Bad::new(section, "file is truncated: no appended data"))?;
    if rest.get(start) != Some(&b'_') {
        return Err(Bad::new(section, "appended data does not start with '_'"));
    }
    let data = rest.get(start + 1..).unwrap_or_default();
    let data = match data.windows(15).rposition(|w| w == b"</AppendedData>") {
        Some(end) => data.get(..end).unwrap_or_default(),
        None => data,
    };
    Ok(Appended { encoding, data })
}

fn attrs(e: &BytesStart) -> Res<Vec<(String, String)>> {
    let mut out = Vec::new();
    for a in e.attributes() {
        let a =
            a.map_err(|err| Bad::new("XML", format!("not a VTK XML file (bad attribute: {err})")))?;
        let value = a.unescape_value().map_err(|err| {
            Bad::new(
                "XML",
                format!("not a VTK XML file (bad attribute value: {err})"),
            )
        })?;
        out.push((
            String::from_utf8_lossy(a.key.as_ref()).into_owned(),
            value.into_owned(),
        ));
    }
    Ok(out)
}

fn attr<'v>(attrs: &'v [(String, String)], key: &str) -> Option<&'v str> {
    attrs
        .iter()
        .find(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
}

fn parse_count(attrs: &[(String, String)], key: &str, section: &str) -> Res<usize> {
    let v =
        attr(attrs, key).ok_or_else(|| Bad::new(section, format!("missing attribute {key}")))?;
    v.trim().parse().map_err(|_| {
        Bad::new(
            section,
            format!("{key}=\"{}\" is not a count", show(v.as_bytes())),
        )
    })
}

const MAX_DEPTH: usize = 64;

/// Collects the pieces and their arrays (text content included) from the XML part of the file.
fn walk_xml(xml: &[u8], has_appended: bool) -> Res<XmlDoc> {
    let mut reader = Reader::from_reader(xml);
    let mut doc = XmlDoc::default();
    let mut seen_file = false;
    let mut stack: Vec<Vec<u8>> = Vec::new();
    let mut current: Option<(XmlArray, Ctx)> = None;
    loop {
        let event = reader.read_event().map_err(|e| {
            let at = reader.error_position();
            // quick-xml's syntax errors all mean "the input ended inside markup".
            if seen_file && matches!(e, quick_xml::Error::Syntax(_)) {
                Bad::new(
                    "XML",
                    format!("file is truncated: the XML ends inside a tag ({e})"),
                )
            } else {
                Bad::new(
                    "XML",
                    format!("not a VTK XML file (XML error near byte {at}: {e})"),
                )
            }
        })?;
        match event {
            Event::Start(e) | Event::Empty(e) if !seen_file && e.name().as_ref() != b"VTKFile" => {
                return Err(Bad::new(
                    "XML",
                    format!(
                        "not a VTK XML file: first element is <{}>",
                        show(e.name().as_ref())
                    ),
                ));
            }
            Event::Start(e) => {
                let name = e.name().as_ref().to_vec();
                open_element(&e, &stack, &mut doc, &mut current, &mut seen_file)?;
                stack.push(name);
                if stack.len() > MAX_DEPTH {
                    return Err(Bad::new("XML", "elements nested too deep"));
                }
            }
            Event::Empty(e) => {
                open_element(&e, &stack, &mut doc, &mut current, &mut seen_file)?;
                if e.name().as_ref() == b"DataArray" {
                    close_array(&mut doc, &mut current)?;
                }
            }
            Event::End(e) => {
                if stack.pop().as_deref() != Some(e.name().as_ref()) {
                    return Err(Bad::new(
                        "XML",
                        format!("mismatched </{}>", show(e.name().as_ref())),
                    ));
                }
                if e.name().as_ref() == b"DataArray" {
                    close_array(&mut doc, &mut current)?;
                }
            }
            Event::Text(t) => {
                if let Some((a, _)) = current.as_mut() {
                    if stack.last().map(Vec::as_slice) == Some(b"DataArray") {
                        a.text.extend_from_slice(&t);
                    }
                } else if !seen_file && !t.iter().all(u8::is_ascii_whitespace) {
                    return Err(Bad::new(
                        "XML",
                        "not a VTK XML file: text outside of any element",
                    ));
                }
            }
            Event::CData(t) => {
                if let Some((a, _)) = current.as_mut() {
                    a.text.extend_from_slice(&t);
                }
            }
            Event::Eof => break,
            _ => {}
        }
    }
    if !seen_file {
        return Err(Bad::new("XML", "not a VTK XML file: no <VTKFile> element"));
    }
    if !has_appended && !stack.is_empty() {
        let inside = stack.last().map(|n| show(n)).unwrap_or_default();
        return Err(Bad::new(
            "XML",
            format!("file is truncated: it ends inside <{inside}>"),
        ));
    }
    Ok(doc)
}

fn open_element(
    e: &BytesStart,
    stack: &[Vec<u8>],
    doc: &mut XmlDoc,
    current: &mut Option<(XmlArray, Ctx)>,
    seen_file: &mut bool,
) -> Res<()> {
    let parent = stack.last().map(Vec::as_slice);
    match e.name().as_ref() {
        b"VTKFile" => {
            if *seen_file {
                return Err(Bad::new("VTKFile", "more than one <VTKFile> element"));
            }
            *seen_file = true;
            let a = attrs(e)?;
            let ty = attr(&a, "type").unwrap_or("");
            if ty != "UnstructuredGrid" {
                return Err(Bad::new(
                    "VTKFile",
                    format!(
                        "type=\"{}\" is not supported; expected UnstructuredGrid",
                        show(ty.as_bytes())
                    ),
                ));
            }
            doc.byte_order = attr(&a, "byte_order").map(str::to_string);
            doc.header_type = attr(&a, "header_type").map(str::to_string);
            doc.compressor = attr(&a, "compressor").map(str::to_string);
        }
        b"Piece" if parent == Some(b"UnstructuredGrid") => {
            let a = attrs(e)?;
            let section = format!("Piece {}", doc.pieces.len());
            doc.pieces.push(XmlPiece {
                n_points: parse_count(&a, "NumberOfPoints", &section)?,
                n_cells: parse_count(&a, "NumberOfCells", &section)?,
                ..XmlPiece::default()
            });
        }
        b"DataArray" => {
            let ctx = match (
                parent,
                stack.len() >= 2 && stack[stack.len() - 2] == b"Piece",
            ) {
                (Some(b"Points"), true) => Ctx::Points,
                (Some(b"Cells"), true) => Ctx::Cells,
                (Some(b"PointData"), true) => Ctx::PointData,
                (Some(b"CellData"), true) => Ctx::CellData,
                _ => Ctx::Other,
            };
            let a = attrs(e)?;
            let array = XmlArray {
                name: attr(&a, "Name").unwrap_or("").to_string(),
                ty: attr(&a, "type").unwrap_or("").to_string(),
                ncomp: attr(&a, "NumberOfComponents").map(str::to_string),
                format: attr(&a, "format").unwrap_or("ascii").to_string(),
                offset: attr(&a, "offset").map(str::to_string),
                text: Vec::new(),
            };
            *current = Some((array, ctx));
        }
        _ => {}
    }
    Ok(())
}

fn close_array(doc: &mut XmlDoc, current: &mut Option<(XmlArray, Ctx)>) -> Res<()> {
    let Some((array, ctx)) = current.take() else {
        return Ok(());
    };
    let n = doc.pieces.len().saturating_sub(1);
    let Some(piece) = doc.pieces.last_mut() else {
        return Ok(());
    };
    match ctx {
        Ctx::Points if piece.points.is_some() => {
            return Err(Bad::new(
                format!("Piece {n} Points"),
                "more than one <DataArray>",
            ));
        }
        Ctx::Points => piece.points = Some(array),
        Ctx::Cells => piece.cells.push(array),
        Ctx::PointData => piece.point_data.push(array),
        Ctx::CellData => piece.cell_data.push(array),
        Ctx::Other => {}
    }
    Ok(())
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

/// Base64 text decoded lazily, quantum by quantum; a padded quantum ends a segment and the next
/// one starts afresh, so separately encoded runs decode to their concatenation.
struct Base64<'a> {
    text: &'a [u8],
    pos: usize,
    buf: Vec<u8>,
    start: usize,
}

fn b64_value(c: u8) -> Option<u8> {
    Some(match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => return None,
    })
}

impl<'a> Base64<'a> {
    fn new(text: &'a [u8]) -> Self {
        Base64 {
            text,
            pos: 0,
            buf: Vec::new(),
            start: 0,
        }
    }

    /// At most this many bytes are left to decode.
    fn remaining_max(&self) -> usize {
        (self.buf.len() - self.start) + self.text.len().saturating_sub(self.pos) / 4 * 3 + 3
    }

    /// Decodes one quantum into `buf`; `Ok(false)` at the end of the text.
    fn quantum(&mut self) -> Result<bool, String> {
        let mut q = [0u8; 4];
        let mut n = 0;
        let mut pad = 0;
        while n < 4 {
            let Some(&c) = self.text.get(self.pos) else {
                break;
            };
            self.pos += 1;
            if c.is_ascii_whitespace() {
                continue;
            }
            if c == b'=' {
                pad += 1;
                q[n] = 0;
                n += 1;
                continue;
            }
            if pad > 0 {
                return Err("base64 data continues after padding inside a quantum".into());
            }
            q[n] = b64_value(c).ok_or_else(|| format!("byte {c:#04x} is not base64"))?;
            n += 1;
        }
        let bytes = match (n, pad) {
            (0, _) => return Ok(false),
            (4, 0) => 3,
            (4, 1) | (3, 0) => 2,
            (4, 2) | (2, 0) => 1,
            _ => return Err("truncated or malformed base64 quantum".into()),
        };
        let v = (u32::from(q[0]) << 18)
            | (u32::from(q[1]) << 12)
            | (u32::from(q[2]) << 6)
            | u32::from(q[3]);
        let b = [(v >> 16) as u8, (v >> 8) as u8, v as u8];
        self.buf.extend_from_slice(&b[..bytes]);
        Ok(true)
    }

    fn read(&mut self, n: usize) -> Result<Option<Vec<u8>>, String> {
        if self.start > (1 << 20) {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        while self.buf.len() - self.start < n {
            if !self.quantum()? {
                return Ok(None);
            }
        }
        let out = self.buf.get(self.start..self.start + n).map(<[u8]>::to_vec);
        self.start += n;
        Ok(out)
    }
}

/// Where a binary array's bytes come from.
enum Stream<'a> {
    Raw(Lex<'a>),
    Base64(Base64<'a>),
}

impl<'a> Stream<'a> {
    fn remaining_max(&self) -> usize {
        match self {
            Stream::Raw(lx) => lx.remaining(),
            Stream::Base64(b) => b.remaining_max(),
        }
    }

    fn read(&mut self, n: usize, what: &str) -> Res<Cow<'a, [u8]>> {
        let got = match self {
            Stream::Raw(lx) => lx.take(n).map(Cow::Borrowed),
            Stream::Base64(b) => b.read(n).map_err(|e| Bad::new(what, e))?.map(Cow::Owned),
        };
        got.ok_or_else(|| {
            Bad::new(
                what,
                format!("file is truncated: the data ends before {n} more bytes"),
            )
        })
    }

    fn word(&mut self, enc: Encoding, what: &str) -> Res<usize> {
        let size = if enc.header64 { 8 } else { 4 };
        let b = self.read(size, what)?;
        let mut a = [0u8; 8];
        let v = match enc.endian {
            Endian::Little => {
                a[..size].copy_from_slice(&b);
                u64::from_le_bytes(a)
            }
            Endian::Big => {
                a[8 - size..].copy_from_slice(&b);
                u64::from_be_bytes(a)
            }
        };
        usize::try_from(v).map_err(|_| Bad::new(what, format!("header value {v} is too large")))
    }
}

/// Reads one binary array (its header, then the data, inflated when compressed).
fn read_binary(s: &mut Stream<'_>, enc: Encoding, what: &str) -> Res<Vec<u8>> {
    let truncated = |claim: usize, left: usize| {
        Bad::new(what, format!("file is truncated: the array header claims {claim} bytes but at most {left} remain"))
    };
    match enc.compression {
        Compression::None => {
            let n = s.word(enc, what)?;
            if n > s.remaining_max() {
                return Err(truncated(n, s.remaining_max()));
            }
            Ok(s.read(n, what)?.into_owned())
        }
        Compression::Zlib => {
            let word = if enc.header64 { 8 } else { 4 };
            let nb = s.word(enc, what)?;
            if nb.saturating_mul(word) > s.remaining_max() {
                return Err(truncated(nb.saturating_mul(word), s.remaining_max()));
            }
            let block = s.word(enc, what)?;
            let last = s.word(enc, what)?;
            let sizes = (0..nb)
                .map(|_| s.word(enc, what))
                .collect::<Res<Vec<usize>>>()?;
            let total = sizes
                .iter()
                .try_fold(0usize, |a, &b| a.checked_add(b))
                .unwrap_or(usize::MAX);
            if total > s.remaining_max() {
                return Err(truncated(total, s.remaining_max()));
            }
            let mut out = Vec::new();
            for (i, &c) in sizes.iter().enumerate() {
                let comp = s.read(c, what)?;
                let want = if i + 1 == nb && last != 0 {
                    last
                } else {
                    block
                };
                let before = out.len();
                flate2::read::ZlibDecoder::new(&comp[..])
                    .take(want as u64 + 1)
                    .read_to_end(&mut out)
                    .map_err(|e| {
                        Bad::new(what, format!("zlib block {i} of {nb} is corrupt: {e}"))
                    })?;
                if out.len() - before != want {
                    return Err(Bad::new(
                        what,
                        format!(
                            "zlib block {i} of {nb} inflates to {} bytes; the header says {want}",
                            out.len() - before
                        ),
                    ));
                }
            }
            Ok(out)
        }
    }
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

// ------------------------------------------------------------------------------------------------
// Legacy VTK.

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

pub(super) fn parse_legacy(bytes: &[u8]) -> Res<ImportedMesh> {
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
