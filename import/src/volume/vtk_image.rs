//! VTK image data: XML `.vti` (`<VTKFile type="ImageData">`) and legacy `.vtk` `DATASET
//! STRUCTURED_POINTS`, read by hand (the `vtk/` mesh readers hold whole files in memory; these
//! readers keep only where each array starts).
//!
//! `.vti`: one `<Piece>` (several are refused: VTK's writer writes one), `WholeExtent`, `Origin`,
//! `Spacing`, `Direction` (axis-aligned; an oblique one is refused), the `<PointData>` arrays of
//! the eight sample types (`Int64`, `UInt64` and `String` are refused) in every encoding VTK
//! writes: `ascii`, inline `binary` (base64) and `appended` (raw or base64), uncompressed or
//! `vtkZLibDataCompressor` (LZ4 and LZMA are refused), `header_type` `UInt32` or `UInt64`,
//! either `byte_order`. A file with only `<CellData>` is refused (one value a cell is not a value
//! a grid point: convert with VTK's `vtkCellDataToPointData` first).
//!
//! Legacy: versions 2 to 5.1, `ASCII` and `BINARY` (big-endian), `DIMENSIONS`, `SPACING` (or
//! `ASPECT_RATIO`), `ORIGIN`, and the `POINT_DATA` arrays: `SCALARS` (with its optional
//! component count and `LOOKUP_TABLE`), `COLOR_SCALARS`, `VECTORS`, `NORMALS`, `TENSORS`,
//! `TEXTURE_COORDINATES` and `FIELD` arrays; `CELL_DATA`, lookup tables and `METADATA` are read
//! past.
//!
//! The array: `--scalar NAME` picks a point array by name (`NAME:K` or `NAME:mag` a component of
//! one with several); otherwise the active scalars (`PointData Scalars=`, the first legacy
//! `SCALARS`) or the first array, and `--scalar K|mag` its component.
//!
//! Out of core: uncompressed appended raw data and legacy binary data are read at their offset,
//! box row by box row; zlib-compressed appended raw data inflates only the blocks that hold the
//! box's rows. Base64 (inline or appended) and ascii text cannot be indexed: they are decoded from
//! the array's start up to the box's end, and the decoder is kept for the next box when that lies
//! further on (compressed base64 blocks before the box are decoded from base64 but not inflated).
//! Opening a file reads its XML tags or legacy keywords; an ascii legacy file is read through up
//! to the chosen array.

use super::nrrd::{axis_aligned, NotAligned, Opener, Reopen, TextValues};
use super::raw::{read_box, ByteSource, Layout, SeekRead};
use super::samples::{choose_component, select};
use super::{
    DType, Endian, FileHeader, Samples, ScalarChoice, VolumeError, VolumeFormat, VolumeOptions,
    VolumeReader,
};
use std::fs::File;
use std::io::{self, BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

pub(crate) fn open(
    path: &Path,
    format: VolumeFormat,
    options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    Ok(Box::new(match format {
        VolumeFormat::VtkStructuredPoints => open_legacy(path, options)?,
        _ => open_vti(path, options)?,
    }))
}

/// An image's chosen point array: where its samples are and how they are laid out.
struct ImageReader {
    path: PathBuf,
    header: FileHeader,
    layout: Layout,
    components: usize,
    which: Option<usize>,
    data: Box<dyn SeekRead + Send>,
}

impl VolumeReader for ImageReader {
    fn header(&self) -> &FileHeader {
        &self.header
    }
    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
        super::check_box(&self.path, lo, hi, self.layout.dims)?;
        let s = read_box(
            &self.path,
            &mut ByteSource::Seek(&mut *self.data),
            &self.layout,
            lo,
            hi,
        )?;
        Ok(select(s, self.components, self.which))
    }
}

/// A point array as the header describes it.
#[derive(Debug, Clone)]
struct PointArray {
    name: String,
    components: usize,
    /// `None`: a type that is not read (named in `type_name`).
    dtype: Option<DType>,
    type_name: String,
    component_names: Vec<String>,
}

/// Which array and which of its components (`None`: the magnitude) `choice` names; `default`:
/// the active scalars or the first array.
fn choose_array(
    path: &Path,
    arrays: &[PointArray],
    default: usize,
    choice: Option<&ScalarChoice>,
) -> Result<(usize, Option<usize>), VolumeError> {
    let list = || {
        arrays
            .iter()
            .map(|a| format!("{} ({} component(s))", a.name, a.components))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let component = |i: usize, choice: Option<&ScalarChoice>| {
        let a = &arrays[i];
        choose_component(choice, a.components, &a.component_names).map_err(|m| {
            VolumeError::usage(
                path,
                format!("point array \"{}\": {m} (or --scalar {}:K)", a.name, a.name),
            )
        })
    };
    let (i, which) = match choice {
        Some(ScalarChoice::Name(s)) => {
            if let Some(i) = arrays.iter().position(|a| &a.name == s) {
                (i, component(i, None)?)
            } else if let Some((i, sub)) = s.rsplit_once(':').and_then(|(name, sub)| {
                arrays
                    .iter()
                    .position(|a| a.name == name)
                    .map(|i| (i, ScalarChoice::parse(sub)))
            }) {
                (i, component(i, Some(&sub))?)
            } else if arrays[default].component_names.iter().any(|c| c == s) {
                (default, component(default, choice)?)
            } else {
                return Err(VolumeError::usage(
                    path,
                    format!(
                        "--scalar {s}: no point array of that name; arrays: {}",
                        list()
                    ),
                ));
            }
        }
        _ => (default, component(default, choice)?),
    };
    let a = &arrays[i];
    if a.dtype.is_none() {
        return Err(VolumeError::unsupported(
            path,
            "type",
            format!(
                "point array \"{}\" is of type {}: read are u8, i8, u16, i16, u32, i32, f32, f64",
                a.name, a.type_name
            ),
        ));
    }
    Ok((i, which))
}

/// The header of the chosen array: dims, geometry, notes on the choice.
#[allow(clippy::too_many_arguments)]
fn image_header(
    path: &Path,
    format: VolumeFormat,
    dims: [usize; 3],
    origin: [f64; 3],
    steps: [[f64; 3]; 3],
    arrays: &[PointArray],
    chosen: usize,
    which: Option<usize>,
) -> Result<FileHeader, VolumeError> {
    let section = match format {
        VolumeFormat::Vti => "Direction",
        _ => "SPACING",
    };
    let (axes, spacing) = axis_aligned(steps).map_err(|e| match e {
        NotAligned::Bad(m) => VolumeError::bad(path, section, m),
        NotAligned::Oblique(m) => VolumeError::unsupported(path, section, m),
    })?;
    let a = &arrays[chosen];
    let dtype = a.dtype.unwrap_or(DType::F32);
    let out = match which {
        None if dtype == DType::F64 => DType::F64,
        None => DType::F32,
        Some(_) => dtype,
    };
    let mut h = FileHeader::new(format, dims, out, spacing);
    h.axes = axes;
    h.origin = origin;
    if arrays.len() > 1 {
        h.notes.push(format!(
            "point array \"{}\" (of {})",
            a.name,
            arrays
                .iter()
                .map(|a| a.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    if a.components > 1 {
        h.notes.push(match which {
            Some(k) => format!("component {k} of {}", a.components),
            None => format!("magnitude of {} components", a.components),
        });
    }
    h.check(path)?;
    Ok(h)
}

/// An opener of the file from byte `at`, buffered.
fn file_at(path: &Path, at: u64) -> impl Fn() -> io::Result<BufReader<File>> + Send + 'static {
    let path = path.to_path_buf();
    move || {
        let mut f = File::open(&path)?;
        f.seek(SeekFrom::Start(at))?;
        Ok(BufReader::with_capacity(1 << 16, f))
    }
}

/// Text values from byte `at` (up to a `<` in XML), as the little-endian bytes of `dtype`.
fn text_stream(path: &Path, at: u64, dtype: DType, xml: bool) -> Reopen {
    let open = file_at(path, at);
    Reopen::new(Box::new(move || {
        Ok(Box::new(TextValues::new(open()?, dtype, xml)) as Box<dyn Read + Send>)
    }))
}

// ---------------------------------------------------------------------------------------------
// Base64 and zlib blocks

/// Base64 text decoded as it is read: white space is skipped, a padded quantum ends a segment (the
/// next starts afresh, so separately encoded runs decode to their concatenation), and a `<` or
/// the end of the input ends the text.
struct Base64<R> {
    src: R,
    out: [u8; 3],
    out_at: usize,
    out_len: usize,
}

impl<R: BufRead> Base64<R> {
    fn new(src: R) -> Self {
        Base64 {
            src,
            out: [0; 3],
            out_at: 0,
            out_len: 0,
        }
    }

    /// Decodes one quantum; `false` at the end of the text.
    fn quantum(&mut self) -> io::Result<bool> {
        let mut q = [0u8; 4];
        let mut n = 0;
        let mut pad = 0;
        while n < 4 {
            let buf = self.src.fill_buf()?;
            let Some(&c) = buf.first() else { break };
            if c == b'<' {
                break;
            }
            self.src.consume(1);
            if c.is_ascii_whitespace() {
                continue;
            }
            let v = match c {
                b'A'..=b'Z' => c - b'A',
                b'a'..=b'z' => c - b'a' + 26,
                b'0'..=b'9' => c - b'0' + 52,
                b'+' => 62,
                b'/' => 63,
                b'=' => {
                    pad += 1;
                    n += 1;
                    continue;
                }
                _ => {
                    return Err(io::Error::new(
                        io::ErrorKind::InvalidData,
                        format!("byte {c:#04x} is not base64"),
                    ))
                }
            };
            if pad > 0 {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    "base64 continues after padding inside a quantum",
                ));
            }
            q[n] = v;
            n += 1;
        }
        let bytes = match (n, pad) {
            (0, _) => return Ok(false),
            (4, 0) => 3,
            (4, 1) | (3, 0) => 2,
            (4, 2) | (2, 0) => 1,
            _ => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    "truncated or malformed base64 quantum",
                ))
            }
        };
        let v = (u32::from(q[0]) << 18)
            | (u32::from(q[1]) << 12)
            | (u32::from(q[2]) << 6)
            | u32::from(q[3]);
        self.out = [(v >> 16) as u8, (v >> 8) as u8, v as u8];
        self.out_at = 0;
        self.out_len = bytes;
        Ok(true)
    }
}

impl<R: BufRead> Read for Base64<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let mut n = 0;
        while n < buf.len() {
            if self.out_at == self.out_len && !self.quantum()? {
                break;
            }
            let k = (self.out_len - self.out_at).min(buf.len() - n);
            buf[n..n + k].copy_from_slice(&self.out[self.out_at..self.out_at + k]);
            self.out_at += k;
            n += k;
        }
        Ok(n)
    }
}

/// The samples of a zlib-compressed VTK array: blocks of `block` bytes (the last `last` when not
/// 0), each compressed on its own, the `k`th at `data_start + ends[k - 1]` of `src`. Reads inflate
/// only the blocks they touch; the last one inflated is kept.
struct ZlibBlocks {
    src: Box<dyn SeekRead + Send>,
    data_start: u64,
    block: u64,
    last: u64,
    /// End of each compressed block, from the first block's start.
    ends: Vec<u64>,
    total: u64,
    cache: Option<(usize, Vec<u8>)>,
    pos: u64,
}

impl ZlibBlocks {
    fn load(&mut self, k: usize) -> io::Result<()> {
        if self.cache.as_ref().is_some_and(|c| c.0 == k) {
            return Ok(());
        }
        self.cache = None;
        let start = if k == 0 { 0 } else { self.ends[k - 1] };
        let size = self.ends[k] - start;
        self.src.seek(SeekFrom::Start(self.data_start + start))?;
        let mut comp = Vec::new();
        (&mut self.src).take(size).read_to_end(&mut comp)?;
        if (comp.len() as u64) < size {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                format!("zlib block {k} ends past the data"),
            ));
        }
        let want = if k + 1 == self.ends.len() && self.last != 0 {
            self.last
        } else {
            self.block
        };
        let mut out = Vec::new();
        flate2::read::ZlibDecoder::new(&comp[..])
            .take(want + 1)
            .read_to_end(&mut out)
            .map_err(|e| {
                io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!("zlib block {k} is corrupt: {e}"),
                )
            })?;
        if out.len() as u64 != want {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!(
                    "zlib block {k} inflates to {} bytes; the header says {want}",
                    out.len()
                ),
            ));
        }
        self.cache = Some((k, out));
        Ok(())
    }
}

impl Read for ZlibBlocks {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.pos >= self.total || self.block == 0 || buf.is_empty() {
            return Ok(0);
        }
        let k = usize::try_from(self.pos / self.block).unwrap_or(usize::MAX);
        if k >= self.ends.len() {
            return Ok(0);
        }
        self.load(k)?;
        let Some((_, b)) = self.cache.as_ref() else {
            return Ok(0);
        };
        let at = (self.pos - k as u64 * self.block) as usize;
        let n = b.len().saturating_sub(at).min(buf.len());
        buf[..n].copy_from_slice(&b[at..at + n]);
        self.pos += n as u64;
        Ok(n)
    }
}

impl Seek for ZlibBlocks {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        match to {
            SeekFrom::Start(n) => self.pos = n,
            _ => return Err(io::Error::from(io::ErrorKind::Unsupported)),
        }
        Ok(self.pos)
    }
}

// ---------------------------------------------------------------------------------------------
// .vti

/// One XML tag of the file.
enum Tag {
    Start(String, Vec<(String, String)>),
    Empty(String, Vec<(String, String)>),
    End(String),
    Other,
}

/// The tags of an XML file, read in order without keeping the text between them; `pos` is the
/// byte just past the last tag read.
struct TagScan {
    r: BufReader<File>,
    pos: u64,
}

const MAX_TAG: usize = 1 << 20;

impl TagScan {
    /// Skips text up to the next `<`; `false` at the end of the file.
    fn skip_text(&mut self) -> io::Result<bool> {
        loop {
            let buf = self.r.fill_buf()?;
            if buf.is_empty() {
                return Ok(false);
            }
            match buf.iter().position(|&c| c == b'<') {
                Some(i) => {
                    self.r.consume(i);
                    self.pos += i as u64;
                    return Ok(true);
                }
                None => {
                    let n = buf.len();
                    self.r.consume(n);
                    self.pos += n as u64;
                }
            }
        }
    }

    /// The bytes of the next tag, `<` to `>` (a comment to its `-->`); `None` at the end.
    fn raw_tag(&mut self) -> Result<Option<Vec<u8>>, String> {
        if !self.skip_text().map_err(|e| e.to_string())? {
            return Ok(None);
        }
        let mut tag = Vec::new();
        loop {
            let buf = self.r.fill_buf().map_err(|e| e.to_string())?;
            if buf.is_empty() {
                return Err("the file ends inside a tag".into());
            }
            let mut used = 0;
            let mut done = false;
            for &c in buf {
                tag.push(c);
                used += 1;
                if c == b'>' && (!tag.starts_with(b"<!--") || tag.ends_with(b"-->")) {
                    done = true;
                    break;
                }
            }
            self.r.consume(used);
            self.pos += used as u64;
            if done {
                return Ok(Some(tag));
            }
            if tag.len() > MAX_TAG {
                return Err("a tag longer than 1 MiB".into());
            }
        }
    }

    fn next(&mut self) -> Result<Option<Tag>, String> {
        let Some(tag) = self.raw_tag()? else {
            return Ok(None);
        };
        if tag.starts_with(b"<!") || tag.starts_with(b"<?") {
            return Ok(Some(Tag::Other));
        }
        if let Some(end) = tag.strip_prefix(b"</") {
            let end = end.strip_suffix(b">").unwrap_or(end);
            return Ok(Some(Tag::End(
                String::from_utf8_lossy(end).trim().to_string(),
            )));
        }
        let mut reader = quick_xml::Reader::from_reader(&tag[..]);
        Ok(Some(match reader.read_event() {
            Ok(quick_xml::events::Event::Start(e)) => Tag::Start(name(e.name()), attrs(&e)?),
            Ok(quick_xml::events::Event::Empty(e)) => Tag::Empty(name(e.name()), attrs(&e)?),
            Ok(quick_xml::events::Event::End(e)) => Tag::End(name(e.name())),
            Ok(_) => Tag::Other,
            Err(e) => return Err(format!("malformed XML ({e})")),
        }))
    }
}

fn name(n: quick_xml::name::QName<'_>) -> String {
    String::from_utf8_lossy(n.as_ref()).into_owned()
}

fn attrs(e: &quick_xml::events::BytesStart<'_>) -> Result<Vec<(String, String)>, String> {
    let mut out = Vec::new();
    for a in e.attributes() {
        let a = a.map_err(|e| format!("a malformed attribute ({e})"))?;
        let v = a
            .unescape_value()
            .map_err(|e| format!("a malformed attribute value ({e})"))?;
        out.push((name(a.key), v.into_owned()));
    }
    Ok(out)
}

fn attr<'a>(attrs: &'a [(String, String)], key: &str) -> Option<&'a str> {
    attrs
        .iter()
        .find(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
}

/// A `<DataArray>` of the point data.
#[derive(Debug, Clone)]
struct VtiArray {
    info: PointArray,
    format: String,
    offset: Option<String>,
    /// Where its text starts (just past its start tag).
    text_at: u64,
}

#[derive(Debug, Default)]
struct VtiDoc {
    byte_order: Option<String>,
    header_type: Option<String>,
    compressor: Option<String>,
    whole_extent: Option<String>,
    origin: Option<String>,
    spacing: Option<String>,
    direction: Option<String>,
    pieces: usize,
    extent: Option<String>,
    scalars: Option<String>,
    arrays: Vec<VtiArray>,
    cell_arrays: usize,
    /// `encoding` and where the appended data start (past the `_`).
    appended: Option<(String, u64)>,
}

const MAX_ARRAYS: usize = 4096;

/// More components a point than this is not an image's array.
const MAX_COMPONENTS: usize = 1 << 16;

fn vti_type(t: &str) -> Option<DType> {
    Some(match t {
        "Int8" | "Char" => DType::I8,
        "UInt8" | "UnsignedChar" => DType::U8,
        "Int16" | "Short" => DType::I16,
        "UInt16" | "UnsignedShort" => DType::U16,
        "Int32" | "Int" => DType::I32,
        "UInt32" | "UnsignedInt" => DType::U32,
        "Float32" | "Float" => DType::F32,
        "Float64" | "Double" => DType::F64,
        _ => return None,
    })
}

fn scan_vti(path: &Path) -> Result<VtiDoc, VolumeError> {
    let f = File::open(path).map_err(VolumeError::io(path))?;
    let mut scan = TagScan {
        r: BufReader::with_capacity(1 << 16, f),
        pos: 0,
    };
    let bad = |section: &str, m: String| VolumeError::bad(path, section, m);
    let mut doc = VtiDoc::default();
    let mut stack: Vec<String> = Vec::new();
    let mut seen_file = false;
    loop {
        let tag = scan.next().map_err(|m| bad("XML", m))?;
        let Some(tag) = tag else { break };
        let (name, attrs, empty) = match tag {
            Tag::Start(n, a) => (n, a, false),
            Tag::Empty(n, a) => (n, a, true),
            Tag::End(n) => {
                if stack.pop().as_ref() != Some(&n) {
                    return Err(bad("XML", format!("mismatched </{n}>")));
                }
                if n == "VTKFile" {
                    break;
                }
                continue;
            }
            Tag::Other => continue,
        };
        let parent = stack.last().map(String::as_str);
        if !seen_file && name != "VTKFile" {
            return Err(bad(
                "XML",
                format!("not a VTK XML file: the first element is <{name}>"),
            ));
        }
        match (name.as_str(), parent) {
            ("VTKFile", None) => {
                seen_file = true;
                let ty = attr(&attrs, "type").unwrap_or("");
                if ty != "ImageData" {
                    return Err(VolumeError::unsupported(
                        path,
                        "VTKFile",
                        format!(
                            "type=\"{ty}\": read is ImageData (a .vtu or other mesh goes through \
                             the mesh import)"
                        ),
                    ));
                }
                doc.byte_order = attr(&attrs, "byte_order").map(String::from);
                doc.header_type = attr(&attrs, "header_type").map(String::from);
                doc.compressor = attr(&attrs, "compressor").map(String::from);
            }
            ("ImageData", Some("VTKFile")) => {
                doc.whole_extent = attr(&attrs, "WholeExtent").map(String::from);
                doc.origin = attr(&attrs, "Origin").map(String::from);
                doc.spacing = attr(&attrs, "Spacing").map(String::from);
                doc.direction = attr(&attrs, "Direction").map(String::from);
            }
            ("Piece", Some("ImageData")) => {
                doc.pieces += 1;
                if doc.pieces == 1 {
                    doc.extent = attr(&attrs, "Extent").map(String::from);
                }
            }
            ("PointData", Some("Piece")) if doc.pieces == 1 => {
                doc.scalars = attr(&attrs, "Scalars").map(String::from);
            }
            ("DataArray", Some("PointData")) if doc.pieces == 1 => {
                if doc.arrays.len() >= MAX_ARRAYS {
                    return Err(bad("PointData", format!("more than {MAX_ARRAYS} arrays")));
                }
                let n = doc.arrays.len();
                let ty = attr(&attrs, "type").unwrap_or("").to_string();
                let components = match attr(&attrs, "NumberOfComponents") {
                    None => 1,
                    Some(s) => s
                        .trim()
                        .parse::<usize>()
                        .ok()
                        .filter(|c| (1..=MAX_COMPONENTS).contains(c))
                        .ok_or_else(|| {
                            bad(
                                "DataArray",
                                format!(
                                    "array {n}: NumberOfComponents=\"{s}\" is not a count \
                                     (1 to {MAX_COMPONENTS})"
                                ),
                            )
                        })?,
                };
                let names: Vec<String> = (0..components.min(64))
                    .map_while(|k| attr(&attrs, &format!("ComponentName{k}")).map(String::from))
                    .collect();
                doc.arrays.push(VtiArray {
                    info: PointArray {
                        name: attr(&attrs, "Name")
                            .map(String::from)
                            .unwrap_or_else(|| format!("array{n}")),
                        components,
                        dtype: vti_type(&ty),
                        type_name: ty,
                        component_names: if names.len() == components {
                            names
                        } else {
                            Vec::new()
                        },
                    },
                    format: attr(&attrs, "format").unwrap_or("ascii").to_string(),
                    offset: attr(&attrs, "offset").map(String::from),
                    text_at: scan.pos,
                });
            }
            ("DataArray", Some("CellData")) => doc.cell_arrays += 1,
            ("AppendedData", Some("VTKFile")) => {
                let enc = attr(&attrs, "encoding").unwrap_or("base64").to_string();
                // the data start past an underscore
                let mut b = [0u8; 1];
                loop {
                    let n = scan.r.read(&mut b).map_err(VolumeError::io(path))?;
                    if n == 0 {
                        return Err(bad("AppendedData", "truncated: no data".into()));
                    }
                    scan.pos += 1;
                    if b[0] == b'_' {
                        break;
                    }
                    if !b[0].is_ascii_whitespace() {
                        return Err(bad("AppendedData", "the data do not start with '_'".into()));
                    }
                }
                doc.appended = Some((enc, scan.pos));
                break;
            }
            _ => {}
        }
        if !empty {
            stack.push(name);
            if stack.len() > 64 {
                return Err(bad("XML", "elements nested too deep".into()));
            }
        }
    }
    if !seen_file {
        return Err(bad("XML", "not a VTK XML file: no <VTKFile>".into()));
    }
    Ok(doc)
}

fn numbers<const N: usize>(
    path: &Path,
    section: &str,
    s: Option<&str>,
    default: [f64; N],
) -> Result<[f64; N], VolumeError> {
    let Some(s) = s else { return Ok(default) };
    let v: Option<Vec<f64>> = s.split_whitespace().map(|x| x.parse().ok()).collect();
    v.and_then(|v| <[f64; N]>::try_from(v).ok())
        .filter(|v| v.iter().all(|x| x.is_finite()))
        .ok_or_else(|| {
            VolumeError::bad(
                path,
                section,
                format!(
                    "\"{}\": give {N} finite numbers",
                    s.chars().take(80).collect::<String>()
                ),
            )
        })
}

fn open_vti(path: &Path, options: &VolumeOptions) -> Result<ImageReader, VolumeError> {
    let doc = scan_vti(path)?;
    let bad = |section: &str, m: String| VolumeError::bad(path, section, m);
    if doc.pieces != 1 {
        return Err(match doc.pieces {
            0 => bad("ImageData", "no <Piece>".into()),
            n => VolumeError::unsupported(
                path,
                "ImageData",
                format!(
                    "{n} pieces: read are single-piece files (as vtkXMLImageDataWriter writes \
                     them); merge the pieces first"
                ),
            ),
        });
    }
    let ext = |s: Option<&str>, section: &str| -> Result<[i64; 6], VolumeError> {
        let v: Option<Vec<i64>> = s
            .ok_or_else(|| bad(section, "missing the extent".into()))?
            .split_whitespace()
            .map(|x| x.parse().ok())
            .collect();
        v.and_then(|v| <[i64; 6]>::try_from(v).ok())
            .filter(|e| (0..3).all(|a| e[2 * a] <= e[2 * a + 1]))
            .ok_or_else(|| {
                bad(
                    section,
                    "give 6 integers x0 x1 y0 y1 z0 z1, each lo ≤ hi".into(),
                )
            })
    };
    let whole = ext(doc.whole_extent.as_deref(), "WholeExtent")?;
    let piece = ext(
        doc.extent.as_deref().or(doc.whole_extent.as_deref()),
        "Piece Extent",
    )?;
    if piece != whole {
        return Err(VolumeError::unsupported(
            path,
            "Piece Extent",
            format!("{piece:?} is not the whole extent {whole:?}: a partial piece"),
        ));
    }
    let mut dims = [0usize; 3];
    for a in 0..3 {
        dims[a] = whole[2 * a + 1]
            .checked_sub(whole[2 * a])
            .and_then(|n| n.checked_add(1))
            .and_then(|n| usize::try_from(n).ok())
            .ok_or_else(|| bad("WholeExtent", format!("{whole:?}: too large")))?;
    }
    let origin0 = numbers(path, "Origin", doc.origin.as_deref(), [0.0; 3])?;
    let spacing = numbers(path, "Spacing", doc.spacing.as_deref(), [1.0; 3])?;
    let d = numbers(
        path,
        "Direction",
        doc.direction.as_deref(),
        [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
    )?;
    // column a of the row-major direction matrix is file axis a
    let steps: [[f64; 3]; 3] =
        std::array::from_fn(|a| std::array::from_fn(|r| d[3 * r + a] * spacing[a]));
    let mut origin = origin0;
    for r in 0..3 {
        for (a, step) in steps.iter().enumerate() {
            origin[r] += step[r] * whole[2 * a] as f64;
        }
    }

    if doc.arrays.is_empty() {
        return Err(if doc.cell_arrays > 0 {
            VolumeError::unsupported(
                path,
                "CellData",
                "cell data only: read are point data (a value a grid point); convert with \
                 VTK's vtkCellDataToPointData (ParaView's Cell Data to Point Data) first",
            )
        } else {
            bad("PointData", "no point data arrays".into())
        });
    }
    let infos: Vec<PointArray> = doc.arrays.iter().map(|a| a.info.clone()).collect();
    let default = doc
        .scalars
        .as_ref()
        .and_then(|s| infos.iter().position(|a| &a.name == s))
        .unwrap_or(0);
    let (chosen, which) = choose_array(path, &infos, default, options.scalar.as_ref())?;
    let mut header = image_header(
        path,
        VolumeFormat::Vti,
        dims,
        origin,
        steps,
        &infos,
        chosen,
        which,
    )?;
    let arr = &doc.arrays[chosen];
    let dtype = arr.info.dtype.unwrap_or(DType::U8);
    let components = arr.info.components;
    let section = format!("DataArray \"{}\"", arr.info.name);
    let expected = dims
        .iter()
        .try_fold((components * dtype.bytes()) as u64, |a, &d| {
            a.checked_mul(d as u64)
        })
        .filter(|&b| b <= isize::MAX as u64)
        .ok_or_else(|| bad(&section, "more samples than can be indexed".into()))?;
    let endian = match doc.byte_order.as_deref() {
        None | Some("LittleEndian") => Endian::Little,
        Some("BigEndian") => Endian::Big,
        Some(o) => return Err(bad("VTKFile", format!("byte_order=\"{o}\": not an order"))),
    };
    let word: u64 = match doc.header_type.as_deref() {
        None | Some("UInt32") => 4,
        Some("UInt64") => 8,
        Some(t) => {
            return Err(VolumeError::unsupported(
                path,
                "VTKFile",
                format!("header_type=\"{t}\": read are UInt32 and UInt64"),
            ))
        }
    };
    let zlib = match doc.compressor.as_deref() {
        None | Some("") => false,
        Some("vtkZLibDataCompressor") => true,
        Some(c) => {
            return Err(VolumeError::unsupported(
                path,
                "VTKFile",
                format!(
                    "compressor=\"{c}\": read are zlib and none; re-save with \
                     SetCompressorTypeToZLib()"
                ),
            ))
        }
    };
    let file_len = std::fs::metadata(path)
        .map_err(VolumeError::io(path))?
        .len();
    let layout = |offset: u64, endian: Endian| Layout {
        offset,
        dims,
        components,
        dtype,
        endian,
    };

    // where the array's encoded bytes (block header first) start, raw or as base64
    let (at, base64) = match arr.format.as_str() {
        "ascii" => {
            header
                .notes
                .push("ascii data: decoded from the array's start".into());
            return Ok(ImageReader {
                path: path.to_path_buf(),
                header,
                layout: layout(0, Endian::Little),
                components,
                which,
                data: Box::new(text_stream(path, arr.text_at, dtype, true)),
            });
        }
        "binary" => (arr.text_at, true),
        "appended" => {
            let (enc, base) = doc
                .appended
                .as_ref()
                .ok_or_else(|| bad(&section, "format=\"appended\" and no <AppendedData>".into()))?;
            let off: u64 = arr
                .offset
                .as_deref()
                .and_then(|o| o.trim().parse().ok())
                .ok_or_else(|| bad(&section, "an appended array needs an offset".into()))?;
            let at = base
                .checked_add(off)
                .filter(|&a| a <= file_len)
                .ok_or_else(|| bad(&section, format!("offset {off} is past the file's end")))?;
            match enc.as_str() {
                "raw" => (at, false),
                "base64" => (at, true),
                e => {
                    return Err(bad(
                        "AppendedData",
                        format!("encoding=\"{e}\": not raw or base64"),
                    ))
                }
            }
        }
        f => {
            return Err(bad(
                &section,
                format!("format=\"{f}\": not ascii, binary or appended"),
            ))
        }
    };
    // the encoded stream from the array's start
    let raw_at = file_at(path, at);
    let mut encoded: Opener = if base64 {
        Box::new(move || Ok(Box::new(Base64::new(raw_at()?)) as Box<dyn Read + Send>))
    } else {
        Box::new(move || Ok(Box::new(raw_at()?) as Box<dyn Read + Send>))
    };
    // at most this many encoded bytes are left
    let left = if base64 {
        file_len.saturating_sub(at) / 4 * 3 + 3
    } else {
        file_len.saturating_sub(at)
    };
    let truncated = |e: io::Error| match e.kind() {
        io::ErrorKind::UnexpectedEof => bad(
            &section,
            "truncated: the file ends in the array's header".into(),
        ),
        _ => bad(&section, format!("cannot decode: {e}")),
    };
    let mut head = encoded().map_err(VolumeError::io(path))?;
    let read_word = |r: &mut Box<dyn Read + Send>| -> Result<u64, VolumeError> {
        let mut b = [0u8; 8];
        let w = word as usize;
        r.read_exact(&mut b[..w]).map_err(truncated)?;
        Ok(match endian {
            Endian::Little => {
                let mut a = [0u8; 8];
                a[..w].copy_from_slice(&b[..w]);
                u64::from_le_bytes(a)
            }
            Endian::Big => {
                let mut a = [0u8; 8];
                a[8 - w..].copy_from_slice(&b[..w]);
                u64::from_be_bytes(a)
            }
        })
    };
    let data: Box<dyn SeekRead + Send>;
    let offset;
    if !zlib {
        let n = read_word(&mut head)?;
        if n != expected {
            return Err(bad(
                &section,
                format!(
                    "holds {n} bytes; the extent's {dims:?} points of {components} {dtype} need \
                     {expected}"
                ),
            ));
        }
        if base64 {
            data = Box::new(Reopen::new(encoded));
            offset = word;
            header
                .notes
                .push("base64 data: decoded from the array's start".into());
        } else {
            if at + word + expected > file_len {
                return Err(bad(
                    &section,
                    format!("truncated: the file ends before the array's {expected} bytes"),
                ));
            }
            data = Box::new(File::open(path).map_err(VolumeError::io(path))?);
            offset = at + word;
        }
    } else {
        let nb = read_word(&mut head)?;
        if nb.saturating_mul(word) > left {
            return Err(bad(
                &section,
                format!("truncated: {nb} compressed blocks' sizes do not fit in the file"),
            ));
        }
        let block = read_word(&mut head)?;
        let last = read_word(&mut head)?;
        let mut ends = Vec::new();
        let mut sum = 0u64;
        for _ in 0..nb {
            sum = sum.saturating_add(read_word(&mut head)?);
            ends.push(sum);
        }
        let header_bytes = word * (3 + nb);
        let size = match nb {
            0 => Some(0),
            _ => block
                .checked_mul(nb - 1)
                .and_then(|s| s.checked_add(if last == 0 { block } else { last })),
        };
        if size != Some(expected) || (last > block) {
            return Err(bad(
                &section,
                format!(
                    "{nb} blocks of {block} bytes (the last {last}) are not the {expected} bytes \
                     of the extent's {dims:?} points of {components} {dtype}"
                ),
            ));
        }
        if sum.saturating_add(header_bytes) > left {
            return Err(bad(
                &section,
                format!("truncated: the file ends before the {sum} compressed bytes"),
            ));
        }
        let (src, data_start): (Box<dyn SeekRead + Send>, u64) = if base64 {
            header
                .notes
                .push("base64 data: decoded from the array's start".into());
            (Box::new(Reopen::new(encoded)), header_bytes)
        } else {
            (
                Box::new(File::open(path).map_err(VolumeError::io(path))?),
                at + header_bytes,
            )
        };
        data = Box::new(ZlibBlocks {
            src,
            data_start,
            block,
            last,
            ends,
            total: expected,
            cache: None,
            pos: 0,
        });
        offset = 0;
    }
    Ok(ImageReader {
        path: path.to_path_buf(),
        header,
        layout: layout(offset, endian),
        components,
        which,
        data,
    })
}

// ---------------------------------------------------------------------------------------------
// Legacy STRUCTURED_POINTS

/// Words and lines of a legacy file, read in order; `pos`: the byte just past what was read.
struct Words {
    r: BufReader<File>,
    pos: u64,
}

impl Words {
    /// The rest of the line (at most 4 KiB of it kept), its end consumed; `None` at the end.
    fn line(&mut self) -> io::Result<Option<String>> {
        let mut out = Vec::new();
        let mut any = false;
        loop {
            let buf = self.r.fill_buf()?;
            if buf.is_empty() {
                break;
            }
            any = true;
            let (n, end) = match buf.iter().position(|&c| c == b'\n') {
                Some(i) => (i + 1, true),
                None => (buf.len(), false),
            };
            let keep = (4096usize.saturating_sub(out.len())).min(n);
            out.extend_from_slice(&buf[..keep]);
            self.r.consume(n);
            self.pos += n as u64;
            if end {
                break;
            }
        }
        if !any {
            return Ok(None);
        }
        Ok(Some(String::from_utf8_lossy(&out).trim().to_string()))
    }

    /// The next white-space-separated word (at most 256 bytes); `None` at the end.
    fn word(&mut self) -> io::Result<Option<String>> {
        let mut out = Vec::new();
        loop {
            let buf = self.r.fill_buf()?;
            if buf.is_empty() {
                break;
            }
            let mut used = 0;
            let mut end = false;
            for &c in buf {
                if c.is_ascii_whitespace() {
                    if !out.is_empty() {
                        end = true;
                        break;
                    }
                } else {
                    if out.len() >= 256 {
                        end = true;
                        break;
                    }
                    out.push(c);
                }
                used += 1;
            }
            self.r.consume(used);
            self.pos += used as u64;
            if end {
                break;
            }
        }
        Ok((!out.is_empty()).then(|| String::from_utf8_lossy(&out).into_owned()))
    }

    fn seek(&mut self, to: u64) -> io::Result<()> {
        self.r.seek(SeekFrom::Start(to))?;
        self.pos = to;
        Ok(())
    }

    /// Skips `n` words; how many there were.
    fn skip_words(&mut self, n: u64) -> io::Result<u64> {
        let mut k = 0;
        while k < n {
            let buf = self.r.fill_buf()?;
            if buf.is_empty() {
                break;
            }
            let mut used = 0;
            let mut in_word = false;
            for &c in buf {
                let ws = c.is_ascii_whitespace();
                if in_word && ws {
                    k += 1;
                    in_word = false;
                    if k == n {
                        break;
                    }
                } else if !ws {
                    in_word = true;
                }
                used += 1;
            }
            // a word cut at the buffer's end: finish it
            if in_word {
                self.r.consume(used);
                self.pos += used as u64;
                loop {
                    let buf = self.r.fill_buf()?;
                    let m = buf
                        .iter()
                        .position(|c| c.is_ascii_whitespace())
                        .unwrap_or(buf.len());
                    let done = m < buf.len() || buf.is_empty();
                    self.r.consume(m);
                    self.pos += m as u64;
                    if done {
                        break;
                    }
                }
                k += 1;
                continue;
            }
            self.r.consume(used);
            self.pos += used as u64;
        }
        Ok(k)
    }
}

/// A legacy type: its sample type when read, and its size on disk (`None`: cannot be skipped).
fn legacy_type(t: &str) -> (Option<DType>, Option<u64>) {
    match t.to_ascii_lowercase().as_str() {
        "unsigned_char" | "vtktypeuint8" => (Some(DType::U8), Some(1)),
        "char" | "signed_char" | "vtktypeint8" => (Some(DType::I8), Some(1)),
        "unsigned_short" | "vtktypeuint16" => (Some(DType::U16), Some(2)),
        "short" | "vtktypeint16" => (Some(DType::I16), Some(2)),
        "unsigned_int" | "vtktypeuint32" => (Some(DType::U32), Some(4)),
        "int" | "vtktypeint32" => (Some(DType::I32), Some(4)),
        "float" | "vtktypefloat32" => (Some(DType::F32), Some(4)),
        "double" | "vtktypefloat64" => (Some(DType::F64), Some(8)),
        "vtkidtype" => (None, Some(4)),
        "long" | "unsigned_long" | "vtktypeint64" | "vtktypeuint64" => (None, Some(8)),
        _ => (None, None),
    }
}

/// A legacy point array and where its data start.
struct LegacyArray {
    info: PointArray,
    at: u64,
    scalars: bool,
}

fn open_legacy(path: &Path, options: &VolumeOptions) -> Result<ImageReader, VolumeError> {
    let f = File::open(path).map_err(VolumeError::io(path))?;
    let mut w = Words {
        r: BufReader::with_capacity(1 << 16, f),
        pos: 0,
    };
    let bad = |section: &str, m: String| VolumeError::bad(path, section, m);
    let ioe = |e: io::Error| VolumeError::Io {
        path: path.to_path_buf(),
        source: e,
    };
    let first = w.line().map_err(ioe)?.unwrap_or_default();
    if !first.to_ascii_lowercase().starts_with("# vtk datafile") {
        return Err(bad(
            "header",
            "not a legacy VTK file (no `# vtk DataFile`)".into(),
        ));
    }
    w.line().map_err(ioe)?; // the title
    let binary = match w
        .line()
        .map_err(ioe)?
        .unwrap_or_default()
        .to_ascii_uppercase()
        .as_str()
    {
        "ASCII" => false,
        "BINARY" => true,
        other => return Err(bad("header", format!("\"{other}\": give ASCII or BINARY"))),
    };
    let mut dims: Option<[usize; 3]> = None;
    let mut spacing = [1.0; 3];
    let mut origin = [0.0; 3];
    let mut dataset = false;
    // the section the arrays belong to: tuples and whether they are the points'
    let mut section: Option<(u64, bool)> = None;
    let mut arrays: Vec<LegacyArray> = Vec::new();
    let mut cell_arrays = 0usize;
    let mut stopped: Option<String> = None;
    let want_name = match &options.scalar {
        Some(ScalarChoice::Name(s)) => Some(s.clone()),
        _ => None,
    };
    let chosen_found = |arrays: &[LegacyArray]| match &want_name {
        Some(s) => arrays.iter().any(|a| {
            &a.info.name == s || s.rsplit_once(':').is_some_and(|(n, _)| n == a.info.name)
        }),
        None => arrays.iter().any(|a| a.scalars),
    };
    let three = |args: &[&str], kw: &str| -> Result<[f64; 3], VolumeError> {
        let v: Option<Vec<f64>> = args.iter().map(|x| x.parse().ok()).collect();
        v.and_then(|v| <[f64; 3]>::try_from(v).ok())
            .filter(|v| v.iter().all(|x| x.is_finite()))
            .ok_or_else(|| bad(kw, format!("{args:?}: give 3 finite numbers")))
    };
    while let Some(kw) = w.word().map_err(ioe)? {
        let key = kw.to_ascii_uppercase();
        let rest = w.line().map_err(ioe)?.unwrap_or_default();
        let args: Vec<&str> = rest.split_whitespace().collect();
        let count = |s: Option<&&str>, what: &str| -> Result<u64, VolumeError> {
            s.and_then(|x| x.parse::<u64>().ok())
                .ok_or_else(|| bad(&key, format!("{args:?}: expected {what}")))
        };
        // the data of an array of `n` values of `size` bytes (ascii: words) from here
        let skip = |w: &mut Words, n: u64, size: Option<u64>| -> Result<(), VolumeError> {
            if binary {
                let bytes = size
                    .and_then(|s| n.checked_mul(s))
                    .ok_or_else(|| bad(&key, "data of a type that cannot be read past".into()))?;
                let at = w
                    .pos
                    .checked_add(bytes)
                    .ok_or_else(|| bad(&key, "too large".into()))?;
                w.seek(at).map_err(ioe)?;
            } else if w.skip_words(n).map_err(ioe)? < n {
                return Err(bad(&key, format!("truncated: fewer than {n} values")));
            }
            Ok(())
        };
        match key.as_str() {
            "DATASET" => {
                let ty = args.first().copied().unwrap_or("").to_ascii_uppercase();
                if ty != "STRUCTURED_POINTS" {
                    return Err(VolumeError::unsupported(
                        path,
                        "DATASET",
                        format!(
                            "{ty}: read is STRUCTURED_POINTS (an UNSTRUCTURED_GRID goes through \
                             the mesh import)"
                        ),
                    ));
                }
                dataset = true;
            }
            "DIMENSIONS" => {
                let v: Option<Vec<usize>> = args.iter().map(|x| x.parse().ok()).collect();
                dims = Some(
                    v.and_then(|v| <[usize; 3]>::try_from(v).ok())
                        .ok_or_else(|| bad("DIMENSIONS", format!("{args:?}: give 3 counts")))?,
                );
            }
            "SPACING" | "ASPECT_RATIO" => spacing = three(&args, &key)?,
            "ORIGIN" => origin = three(&args, &key)?,
            "POINT_DATA" => section = Some((count(args.first(), "a count")?, true)),
            "CELL_DATA" => section = Some((count(args.first(), "a count")?, false)),
            "METADATA" => loop {
                // read past to the blank line that ends it
                match w.line().map_err(ioe)? {
                    None => break,
                    Some(l) if l.is_empty() => break,
                    _ => {}
                }
            },
            "LOOKUP_TABLE" => {
                let n = count(args.get(1), "a size")?;
                let vals = n
                    .checked_mul(4)
                    .ok_or_else(|| bad(&key, "too large".into()))?;
                skip(&mut w, vals, Some(1))?;
            }
            "FIELD" => {
                let n = count(args.get(1), "an array count")?;
                for _ in 0..n {
                    let Some(name) = w.word().map_err(ioe)? else {
                        return Err(bad("FIELD", "truncated: an array is missing".into()));
                    };
                    if name.eq_ignore_ascii_case("METADATA") {
                        loop {
                            match w.line().map_err(ioe)? {
                                None => break,
                                Some(l) if l.is_empty() => break,
                                _ => {}
                            }
                        }
                        continue;
                    }
                    let line = w.line().map_err(ioe)?.unwrap_or_default();
                    let a: Vec<&str> = line.split_whitespace().collect();
                    let (Some(nc), Some(nt), Some(ty)) = (
                        a.first().and_then(|x| x.parse::<u64>().ok()),
                        a.get(1).and_then(|x| x.parse::<u64>().ok()),
                        a.get(2),
                    ) else {
                        return Err(bad(
                            "FIELD",
                            format!(
                                "array {name}: \"{line}\": expected components, tuples and a type"
                            ),
                        ));
                    };
                    if nc == 0 || nc > MAX_COMPONENTS as u64 {
                        return Err(bad("FIELD", format!("array {name}: {nc} components")));
                    }
                    let (dtype, size) = legacy_type(ty);
                    if section == Some((nt, true)) {
                        arrays.push(LegacyArray {
                            info: PointArray {
                                name: name.clone(),
                                components: nc as usize,
                                dtype,
                                type_name: ty.to_string(),
                                component_names: Vec::new(),
                            },
                            at: w.pos,
                            scalars: false,
                        });
                    }
                    let vals = nc
                        .checked_mul(nt)
                        .ok_or_else(|| bad("FIELD", "too large".into()))?;
                    if size.is_none() && binary {
                        stopped = Some(format!("FIELD array {name} of type {ty}"));
                        break;
                    }
                    skip(&mut w, vals, size)?;
                }
            }
            "SCALARS"
            | "COLOR_SCALARS"
            | "VECTORS"
            | "NORMALS"
            | "TENSORS"
            | "TENSORS6"
            | "TEXTURE_COORDINATES"
            | "GLOBAL_IDS"
            | "PEDIGREE_IDS" => {
                let Some((tuples, points)) = section else {
                    return Err(bad(&key, "an array before POINT_DATA or CELL_DATA".into()));
                };
                let name = args.first().copied().unwrap_or("").to_string();
                let (components, ty) = match key.as_str() {
                    "SCALARS" => (
                        match args.get(2) {
                            Some(c) => count(Some(c), "a component count")?,
                            None => 1,
                        },
                        args.get(1).copied().unwrap_or(""),
                    ),
                    "COLOR_SCALARS" => (
                        count(args.get(1), "a value count")?,
                        if binary { "unsigned_char" } else { "float" },
                    ),
                    "VECTORS" | "NORMALS" => (3, args.get(1).copied().unwrap_or("")),
                    "TENSORS" => (9, args.get(1).copied().unwrap_or("")),
                    "TENSORS6" => (6, args.get(1).copied().unwrap_or("")),
                    "TEXTURE_COORDINATES" => (
                        count(args.get(1), "a dimension")?,
                        args.get(2).copied().unwrap_or(""),
                    ),
                    _ => (1, args.get(1).copied().unwrap_or("")),
                };
                if components == 0 || components > MAX_COMPONENTS as u64 {
                    return Err(bad(&key, format!("{components} components")));
                }
                if key == "SCALARS" {
                    // an optional LOOKUP_TABLE line
                    let here = w.pos;
                    match w.word().map_err(ioe)? {
                        Some(t) if t.eq_ignore_ascii_case("LOOKUP_TABLE") => {
                            w.line().map_err(ioe)?;
                        }
                        _ => w.seek(here).map_err(ioe)?,
                    }
                }
                let (dtype, size) = legacy_type(ty);
                if points {
                    arrays.push(LegacyArray {
                        info: PointArray {
                            name: name.clone(),
                            components: components as usize,
                            dtype,
                            type_name: ty.to_string(),
                            component_names: match (key.as_str(), components) {
                                ("COLOR_SCALARS", 3) => ["r", "g", "b"].map(String::from).to_vec(),
                                ("COLOR_SCALARS", 4) => {
                                    ["r", "g", "b", "a"].map(String::from).to_vec()
                                }
                                _ => Vec::new(),
                            },
                        },
                        at: w.pos,
                        scalars: key == "SCALARS",
                    });
                } else {
                    cell_arrays += 1;
                }
                if chosen_found(&arrays) {
                    break;
                }
                if size.is_none() && binary {
                    stopped = Some(format!("{key} {name} of type {ty}"));
                    break;
                }
                let vals = tuples
                    .checked_mul(components)
                    .ok_or_else(|| bad(&key, "too large".into()))?;
                skip(&mut w, vals, size)?;
            }
            _ => {
                return Err(bad(
                    "header",
                    format!(
                        "unexpected \"{}\" at byte {}",
                        kw.chars().take(40).collect::<String>(),
                        w.pos
                    ),
                ))
            }
        }
        if stopped.is_some() || chosen_found(&arrays) {
            break;
        }
    }
    if !dataset {
        return Err(bad("DATASET", "missing (DATASET STRUCTURED_POINTS)".into()));
    }
    let dims = dims.ok_or_else(|| bad("DIMENSIONS", "missing".into()))?;
    let points = dims
        .iter()
        .try_fold(1u64, |a, &d| a.checked_mul(d as u64))
        .ok_or_else(|| bad("DIMENSIONS", format!("{dims:?}: too many points")))?;
    if arrays.is_empty() {
        return Err(match (cell_arrays, stopped) {
            (_, Some(s)) => VolumeError::unsupported(
                path,
                "POINT_DATA",
                format!("{s}: a type that is not read, before any point array"),
            ),
            (0, None) => bad("POINT_DATA", "no point data arrays".into()),
            _ => VolumeError::unsupported(
                path,
                "CELL_DATA",
                "cell data only: read are point data (a value a grid point); convert with \
                 VTK's vtkCellDataToPointData (ParaView's Cell Data to Point Data) first",
            ),
        });
    }
    if let Some((n, true)) = section {
        if n != points {
            return Err(bad(
                "POINT_DATA",
                format!("{n} points; DIMENSIONS {dims:?} have {points}"),
            ));
        }
    }
    let infos: Vec<PointArray> = arrays.iter().map(|a| a.info.clone()).collect();
    let default = arrays.iter().position(|a| a.scalars).unwrap_or(0);
    let (chosen, which) = choose_array(path, &infos, default, options.scalar.as_ref())?;
    let steps: [[f64; 3]; 3] =
        std::array::from_fn(|a| std::array::from_fn(|r| if r == a { spacing[a] } else { 0.0 }));
    let mut header = image_header(
        path,
        VolumeFormat::VtkStructuredPoints,
        dims,
        origin,
        steps,
        &infos,
        chosen,
        which,
    )?;
    let a = &arrays[chosen];
    let dtype = a.info.dtype.unwrap_or(DType::U8);
    let components = a.info.components;
    let (data, endian): (Box<dyn SeekRead + Send>, Endian) = if binary {
        let need = points
            .checked_mul((components * dtype.bytes()) as u64)
            .and_then(|b| b.checked_add(a.at));
        let len = std::fs::metadata(path)
            .map_err(VolumeError::io(path))?
            .len();
        if need.is_none_or(|n| n > len) {
            return Err(bad(
                &format!("array \"{}\"", a.info.name),
                format!("truncated: {len} bytes; the array's {points} points end past them"),
            ));
        }
        (
            Box::new(File::open(path).map_err(VolumeError::io(path))?),
            Endian::Big,
        )
    } else {
        header
            .notes
            .push("ascii data: decoded from the array's start".into());
        (
            Box::new(text_stream(path, a.at, dtype, false)),
            Endian::Little,
        )
    };
    Ok(ImageReader {
        path: path.to_path_buf(),
        header,
        layout: Layout {
            offset: if binary { a.at } else { 0 },
            dims,
            components,
            dtype,
            endian,
        },
        components,
        which,
        data,
    })
}

#[cfg(test)]
#[path = "vtk_image_tests.rs"]
mod tests;
