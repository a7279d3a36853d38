//! The XML part of a `.vtu`: the pieces and their `<DataArray>`s (attributes and text) as
//! `quick-xml` tokenizes them, and the split of the file at `<AppendedData>`.

use quick_xml::events::{BytesStart, Event};
use quick_xml::Reader;

use crate::lex::{show, Bad, Res};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Ctx {
    Points,
    Cells,
    PointData,
    CellData,
    Other,
}

#[derive(Debug, Default)]
pub(super) struct XmlArray {
    pub(super) name: String,
    pub(super) ty: String,
    pub(super) ncomp: Option<String>,
    pub(super) format: String,
    pub(super) offset: Option<String>,
    pub(super) text: Vec<u8>,
}

#[derive(Debug, Default)]
pub(super) struct XmlPiece {
    pub(super) n_points: usize,
    pub(super) n_cells: usize,
    pub(super) points: Option<XmlArray>,
    pub(super) cells: Vec<XmlArray>,
    pub(super) point_data: Vec<XmlArray>,
    pub(super) cell_data: Vec<XmlArray>,
}

#[derive(Debug, Default)]
pub(super) struct XmlDoc {
    pub(super) byte_order: Option<String>,
    pub(super) header_type: Option<String>,
    pub(super) compressor: Option<String>,
    pub(super) pieces: Vec<XmlPiece>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum AppendedEncoding {
    Raw,
    Base64,
}

pub(super) struct Appended<'a> {
    pub(super) encoding: AppendedEncoding,
    pub(super) data: &'a [u8],
}

/// `<AppendedData encoding="...">` then `_` then the data up to `</AppendedData>` (or the end of a
/// truncated file).
pub(super) fn split_appended(tail: &[u8]) -> Res<Appended<'_>> {
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
pub(super) fn walk_xml(xml: &[u8], has_appended: bool) -> Res<XmlDoc> {
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
