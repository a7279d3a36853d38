//! TIFF stacks: one multi-page TIFF (classic or BigTIFF, either byte order), its pages the z
//! planes in order, or a folder of TIFF slices (single- or multi-page files, their pages
//! concatenated) in natural name order (`slice2` before `slice10`). Decoded with the `tiff` crate.
//!
//! What is read:
//! - Samples: unsigned and signed 8, 16 and 32-bit integers, 32 and 64-bit floats (and 16-bit
//!   floats, widened to f32), grayscale (`BlackIsZero`; `WhiteIsZero` is inverted as the `tiff`
//!   crate does, so that bright is high) or several samples a pixel (RGB, RGBA, extra bands), chunky
//!   or planar: `--scalar K|NAME|mag` chooses one (`r`, `g`, `b`, `a` for RGB(A)).
//! - Compression: none, LZW, Deflate (Adobe and old), PackBits and Zstandard, with or without a
//!   horizontal or floating-point predictor. Others (JPEG, CCITT fax, WebP, ...) are refused
//!   naming the compression: lossy codecs change the values, and bilevel fax images are not
//!   volumes.
//! - Every page (every slice) must have the same width, height, sample type and samples a pixel;
//!   the first that differs is named. Reduced-resolution pages (thumbnails, pyramid levels,
//!   `NewSubfileType` bit 0) and transparency masks (bit 2) are skipped with a note.
//! - A folder: files that do not start with a TIFF byte-order mark are skipped with a note (a
//!   README, an XML of acquisition settings) unless they are named `.tif`/`.tiff`, which are
//!   refused as damaged slices. A folder of ImageJ hyperstacks is refused: open one file.
//!
//! Geometry, in this order of trust:
//! - ImageJ's description (`ImageJ=` ...): `unit=` (`micron`, `\u00B5m` → `um`), x and y spacing
//!   `1 / XResolution`, `1 / YResolution` (ImageJ stores pixels a unit), z spacing `spacing=` (a
//!   negative one flips z), the origin from `xorigin=`/`yorigin=`/`zorigin=` (in voxels, as
//!   ImageJ's calibration has it), the calibration `cf=0 c0= c1=` (a straight line, e.g. 16-bit
//!   signed images stored shifted) as the rescale with `vunit=` as the value unit. A hyperstack's
//!   `channels=` are the components (`--scalar K` or `mag`) and its `frames=` the time points
//!   (`--frame T`), pages in ImageJ's order (channel fastest, then slice, then frame). An ImageJ
//!   file larger than 4 GiB holds one IFD and its `images=` pages contiguous after the first: read
//!   as such when the first page is uncompressed and its strips contiguous.
//! - Otherwise `XResolution`/`YResolution` with `ResolutionUnit` inch or centimetre give x and y
//!   spacing in mm (no unit: `1 / resolution`, unitless); z is not stated in TIFF and is taken
//!   equal to x, with a note. A tifffile description (`{"shape": [...]}`) with several leading
//!   dimensions reads its last as z and the others as frames.
//! - The file index axes are the world axes (row 0, the top row of a page, at y = 0); no frame
//!   name.
//!
//! Out of core: [`VolumeReader::read_box`] reads only the pages of the box's planes and, in each,
//! only the strips or tiles that overlap its rows (and columns for tiles); uncompressed chunks
//! are read row by row straight from the file, so no more than the box's rows are read. The
//! decoder keeps the offsets of the pages it walked, so going to page k is one directory read.

use super::samples::{choose_component, select};
use super::{
    DType, Endian, FileHeader, Samples, VolumeError, VolumeFormat, VolumeOptions, VolumeReader,
};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use tiff::decoder::{ChunkType, Decoder, Limits};
use tiff::tags::{ByteOrder, CompressionMethod, Tag};
use tiff::{ColorType, TiffError};

type Dec = Decoder<BufReader<File>>;

pub(crate) fn open(
    path: &Path,
    options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    Ok(Box::new(TiffStack::open(path, options)?))
}

/// A sample's stored type: one of the volume types, or a half float read as f32.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stored {
    T(DType),
    F16,
}

impl Stored {
    fn bytes(self) -> usize {
        match self {
            Stored::T(t) => t.bytes(),
            Stored::F16 => 2,
        }
    }
    /// The type its samples are returned in.
    fn dtype(self) -> DType {
        match self {
            Stored::T(t) => t,
            Stored::F16 => DType::F32,
        }
    }
    fn name(self) -> &'static str {
        match self {
            Stored::T(t) => t.name(),
            Stored::F16 => "f16",
        }
    }
}

/// What every page of a stack shares.
#[derive(Debug, Clone, PartialEq)]
struct Format {
    width: usize,
    height: usize,
    stored: Stored,
    /// Samples a pixel as decoded (the photometric ones and kept extra samples).
    components: usize,
    /// `PlanarConfiguration` 2: each sample in its own strips or tiles.
    planar: bool,
    /// Component names (`r`, `g`, `b`, `a` for RGB(A); empty otherwise).
    names: Vec<String>,
}

impl Format {
    fn describe(&self) -> String {
        let mut s = format!("{}×{} {}", self.width, self.height, self.stored.name());
        if self.components > 1 {
            s += &format!(
                ", {} samples a pixel{}",
                self.components,
                if self.planar { " (planar)" } else { "" }
            );
        }
        s
    }
    /// Bytes of one pixel in a chunk (one sample in a planar chunk).
    fn chunk_pixel_bytes(&self) -> usize {
        self.stored.bytes() * if self.planar { 1 } else { self.components }
    }
}

/// One page of the stack: the `index`th image of file `file`, or, for an ImageJ file of one IFD
/// and contiguous pages, its `raw`th page.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Page {
    file: usize,
    index: usize,
    raw: Option<u64>,
}

/// An ImageJ file whose pages lie contiguous after its first: where they start and their size.
#[derive(Debug, Clone, Copy)]
struct RawPages {
    offset: u64,
    page_bytes: u64,
    count: usize,
    endian: Endian,
}

pub(crate) struct TiffStack {
    path: PathBuf,
    files: Vec<PathBuf>,
    header: FileHeader,
    format: Format,
    /// The stack's pages in file order (IFDs).
    pages: Vec<Page>,
    raw: Option<RawPages>,
    /// Pages are `channel + channels · (z + slices · frame)` (ImageJ's order).
    channels: usize,
    slices: usize,
    frame: usize,
    /// The channels read for each plane: one, or all of them for their magnitude.
    chosen_channels: Vec<usize>,
    /// The sample of a pixel read (`None`: their magnitude), when a pixel has several.
    which: Option<usize>,
    /// The open decoder, and the file it reads.
    dec: Option<(usize, Dec)>,
}

fn open_decoder(path: &Path) -> Result<Dec, VolumeError> {
    let f = File::open(path).map_err(VolumeError::io(path))?;
    let len = f.metadata().map_err(VolumeError::io(path))?.len();
    let mut limits = Limits::default();
    // the decoder sizes a tag's array (64 bytes a value at most) by this limit before reading
    // it: no array holds more values than the file has bytes. Decoded chunks are allocated
    // here, fallibly, and compressed ones are read as streams.
    limits.decoding_buffer_size = usize::try_from(len.saturating_mul(64).min(1 << 30))
        .unwrap_or(1 << 30)
        .max(1 << 16);
    limits.intermediate_buffer_size = usize::MAX;
    Decoder::new(BufReader::with_capacity(1 << 16, f))
        .map(|d| d.with_limits(limits))
        .map_err(|e| tiff_error(path, "header", e))
}

/// A `tiff` crate error as this crate's: truncation and damage as `Bad`, what the decoder does
/// not read as `Unsupported`.
fn tiff_error(path: &Path, section: &str, e: TiffError) -> VolumeError {
    match e {
        TiffError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            VolumeError::bad(path, section, "truncated: the file ends inside its data")
        }
        TiffError::IoError(io) if io.kind() == std::io::ErrorKind::InvalidData => {
            VolumeError::bad(path, section, format!("damaged compressed data: {io}"))
        }
        TiffError::IoError(io) => VolumeError::Io {
            path: path.to_path_buf(),
            source: io,
        },
        TiffError::UnsupportedError(u) => VolumeError::unsupported(path, section, u.to_string()),
        TiffError::LimitsExceeded => VolumeError::bad(
            path,
            section,
            "a tag or chunk larger than this reader reads (a damaged file?)",
        ),
        e => VolumeError::bad(path, section, e.to_string()),
    }
}

fn compression_name(code: u16) -> String {
    match code {
        2 => "CCITT modified Huffman (2)".into(),
        3 => "CCITT fax 3 (3)".into(),
        4 => "CCITT fax 4 (4)".into(),
        6 => "old-style JPEG (6)".into(),
        7 => "JPEG (7)".into(),
        34712 => "JPEG 2000 (34712)".into(),
        34887 => "LERC (34887)".into(),
        34925 => "LZMA (34925)".into(),
        50001 => "WebP (50001)".into(),
        50002 => "JPEG XL (50002)".into(),
        c => format!("code {c}"),
    }
}

/// Whether the decoder reads compression `code`.
fn compression_read(code: u16) -> bool {
    matches!(
        CompressionMethod::from_u16_exhaustive(code),
        CompressionMethod::None
            | CompressionMethod::LZW
            | CompressionMethod::Deflate
            | CompressionMethod::OldDeflate
            | CompressionMethod::PackBits
            | CompressionMethod::ZSTD
    )
}

/// The format of the decoder's current page (`None`: a page to skip, a thumbnail or a mask).
fn page_format(dec: &mut Dec, path: &Path, section: &str) -> Result<Option<Format>, VolumeError> {
    let err = |e| tiff_error(path, section, e);
    let subfile = dec
        .find_tag_unsigned::<u32>(Tag::NewSubfileType)
        .map_err(err)?
        .unwrap_or(0);
    if subfile & 0b101 != 0 {
        return Ok(None);
    }
    let compression = dec
        .find_tag_unsigned::<u16>(Tag::Compression)
        .map_err(err)?
        .unwrap_or(1);
    if !compression_read(compression) {
        return Err(VolumeError::unsupported(
            path,
            section,
            format!(
                "compression {}: read are none, LZW, Deflate, PackBits and Zstandard (convert \
                 the stack, e.g. with tifffile or ImageJ, to one of those)",
                compression_name(compression)
            ),
        ));
    }
    let photometric = dec
        .find_tag_unsigned::<u16>(Tag::PhotometricInterpretation)
        .map_err(err)?;
    match photometric {
        Some(0..=2) => {}
        Some(3) => {
            return Err(VolumeError::unsupported(
                path,
                section,
                "a palette (indexed colour) image: its samples are indices into a colour map, \
                 not values",
            ))
        }
        Some(p) => {
            let name = match p {
                4 => "a transparency mask".to_string(),
                5 => "CMYK".into(),
                6 => "YCbCr".into(),
                8..=10 => "CIE L*a*b*".into(),
                p => format!("photometric interpretation {p}"),
            };
            return Err(VolumeError::unsupported(
                path,
                section,
                format!("{name}: read are grayscale and RGB(A) images"),
            ));
        }
        None => {
            return Err(VolumeError::bad(
                path,
                section,
                "no PhotometricInterpretation tag",
            ))
        }
    }
    let color = dec.colortype().map_err(err)?;
    let components = color.num_samples() as usize;
    let names: Vec<String> = match color {
        ColorType::RGB(_) => ["r", "g", "b"].map(String::from).to_vec(),
        ColorType::RGBA(_) => ["r", "g", "b", "a"].map(String::from).to_vec(),
        _ => Vec::new(),
    };
    let bits = color.bit_depth();
    let sample_format = dec
        .find_tag_unsigned_vec::<u16>(Tag::SampleFormat)
        .map_err(err)?
        .and_then(|v| v.first().copied())
        .unwrap_or(1);
    let stored = match (sample_format, bits) {
        (1, 8) => Stored::T(DType::U8),
        (1, 16) => Stored::T(DType::U16),
        (1, 32) => Stored::T(DType::U32),
        (2, 8) => Stored::T(DType::I8),
        (2, 16) => Stored::T(DType::I16),
        (2, 32) => Stored::T(DType::I32),
        (3, 16) => Stored::F16,
        (3, 32) => Stored::T(DType::F32),
        (3, 64) => Stored::T(DType::F64),
        (f, b) => {
            let kind = match f {
                1 => "unsigned integer",
                2 => "signed integer",
                3 => "floating-point",
                4 => "untyped",
                5 => "complex integer",
                6 => "complex floating-point",
                _ => "unknown-format",
            };
            return Err(VolumeError::unsupported(
                path,
                section,
                format!(
                    "{b}-bit {kind} samples: read are u8, i8, u16, i16, u32, i32, f16, f32 and f64"
                ),
            ));
        }
    };
    let planar = dec
        .find_tag_unsigned::<u16>(Tag::PlanarConfiguration)
        .map_err(err)?
        == Some(2);
    let (width, height) = dec.dimensions().map_err(err)?;
    let f = Format {
        width: width as usize,
        height: height as usize,
        stored,
        components,
        planar: planar && components > 1,
        names,
    };
    check_chunks(dec, path, section, &f, compression)?;
    Ok(Some(f))
}

/// The most bytes one compressed byte of a strip or tile can expand to, by compression code:
/// PackBits 64 (a run of 128 in 2 bytes), Deflate about 1030, LZW about 2730 (a 4096-byte string
/// a 12-bit code), Zstandard about 33000 (a 128 KiB run-length block in 4 bytes).
fn max_ratio(compression: u16) -> u64 {
    match compression {
        1 => 1,
        32773 => 65,
        8 | 32946 => 1100,
        5 => 3000,
        _ => 40_000,
    }
}

/// Checks that the current page's strips or tiles lie inside the file and hold enough bytes
/// for its pixels (at most [`max_ratio`] decoded bytes a stored byte), so that dims a damaged
/// header inflates are refused before anything is allocated for them.
fn check_chunks(
    dec: &mut Dec,
    path: &Path,
    section: &str,
    f: &Format,
    compression: u16,
) -> Result<(), VolumeError> {
    let err = |e| tiff_error(path, section, e);
    let file_len = dec
        .inner()
        .get_ref()
        .metadata()
        .map_err(VolumeError::io(path))?
        .len();
    let (o, c) = match dec.get_chunk_type() {
        ChunkType::Strip => (Tag::StripOffsets, Tag::StripByteCounts),
        ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts),
    };
    let offsets = dec.find_tag_unsigned_vec::<u64>(o).map_err(err)?;
    let counts = dec.find_tag_unsigned_vec::<u64>(c).map_err(err)?;
    let (offsets, counts) = (offsets.unwrap_or_default(), counts.unwrap_or_default());
    let mut total = 0u64;
    for (k, (&at, &n)) in offsets.iter().zip(&counts).enumerate() {
        if at.checked_add(n).is_none_or(|end| end > file_len) {
            return Err(VolumeError::bad(
                path,
                section,
                format!(
                    "truncated: strip or tile {k} ({n} bytes from byte {at}) ends past the \
                     file's end ({file_len} bytes)"
                ),
            ));
        }
        total = total.saturating_add(n);
    }
    let need = (f.width as u64)
        .saturating_mul(f.height as u64)
        .saturating_mul((f.components * f.stored.bytes()) as u64);
    let compressed = compression != 1;
    if total.saturating_mul(max_ratio(compression)) < need {
        return Err(VolumeError::bad(
            path,
            section,
            format!(
                "its strips or tiles hold {total} {}bytes, too few for {} pixels",
                if compressed { "compressed " } else { "" },
                f.describe()
            ),
        ));
    }
    Ok(())
}

/// What the first page says of the stack's geometry.
#[derive(Debug, Default)]
struct Meta {
    description: Option<String>,
    resolution: [Option<f64>; 2],
    resolution_unit: Option<u16>,
    endian: Option<Endian>,
}

/// A rational (or plain number) tag's value.
fn number(v: tiff::decoder::ifd::Value) -> Option<f64> {
    use tiff::decoder::ifd::Value;
    match v {
        Value::Rational(n, d) if d != 0 => Some(n as f64 / d as f64),
        Value::SRational(n, d) if d != 0 => Some(n as f64 / d as f64),
        Value::Float(x) => Some(x as f64),
        Value::Double(x) => Some(x),
        Value::Short(x) => Some(x as f64),
        Value::Unsigned(x) => Some(x as f64),
        Value::List(v) => v.into_iter().next().and_then(number),
        _ => None,
    }
    .filter(|x| x.is_finite() && *x > 0.0)
}

fn read_meta(dec: &mut Dec) -> Meta {
    // a damaged or non-ASCII description or resolution is ignored (the geometry falls back)
    let description = dec
        .find_tag(Tag::ImageDescription)
        .ok()
        .flatten()
        .and_then(|v| v.into_string().ok());
    let mut res = |t| dec.find_tag(t).ok().flatten().and_then(number);
    let resolution = [res(Tag::XResolution), res(Tag::YResolution)];
    let resolution_unit = dec
        .find_tag_unsigned::<u16>(Tag::ResolutionUnit)
        .ok()
        .flatten();
    Meta {
        description,
        resolution,
        resolution_unit,
        endian: Some(endian_of(dec)),
    }
}

fn endian_of(dec: &Dec) -> Endian {
    match dec.byte_order() {
        ByteOrder::LittleEndian => Endian::Little,
        ByteOrder::BigEndian => Endian::Big,
    }
}

/// ImageJ's description: `key=value` lines.
#[derive(Debug, Default, PartialEq)]
struct ImageJ {
    images: Option<usize>,
    channels: Option<usize>,
    slices: Option<usize>,
    frames: Option<usize>,
    spacing: Option<f64>,
    unit: Option<String>,
    origin: [Option<f64>; 3],
    cf: Option<i64>,
    c0: Option<f64>,
    c1: Option<f64>,
    vunit: Option<String>,
}

fn parse_imagej(desc: &str) -> Option<ImageJ> {
    if !desc.starts_with("ImageJ=") {
        return None;
    }
    let mut ij = ImageJ::default();
    for line in desc.lines() {
        let Some((k, v)) = line.split_once('=') else {
            continue;
        };
        let v = v.trim();
        let count = || v.parse::<usize>().ok();
        let real = || v.parse::<f64>().ok().filter(|x| x.is_finite());
        match k.trim() {
            "images" => ij.images = count(),
            "channels" => ij.channels = count(),
            "slices" => ij.slices = count(),
            "frames" => ij.frames = count(),
            "spacing" => ij.spacing = real(),
            "unit" => ij.unit = Some(v.to_string()),
            "xorigin" => ij.origin[0] = real(),
            "yorigin" => ij.origin[1] = real(),
            "zorigin" => ij.origin[2] = real(),
            "cf" => ij.cf = v.parse().ok(),
            "c0" => ij.c0 = real(),
            "c1" => ij.c1 = real(),
            "vunit" => ij.vunit = Some(v.to_string()),
            _ => {}
        }
    }
    Some(ij)
}

/// A length unit as this crate names it (`None`: no unit, ImageJ's `pixel`).
fn length_unit(u: &str) -> Option<String> {
    let u = u.trim();
    match u {
        "" | "pixel" | "pixels" | "px" => None,
        "micron" | "microns" | "um" | "µm" | "μm" | "\\u00B5m" | "\\u00b5m" => Some("um".into()),
        "nm" | "nanometer" | "nanometers" => Some("nm".into()),
        "mm" | "millimeter" | "millimeters" => Some("mm".into()),
        "cm" | "centimeter" | "centimeters" => Some("cm".into()),
        "m" | "meter" | "meters" => Some("m".into()),
        "inch" | "inches" | "in" => Some("inch".into()),
        u => Some(u.to_string()),
    }
}

/// The leading (page) dimensions of a tifffile `{"shape": [...]}` description, when it has
/// several above 1.
fn tifffile_shape(desc: &str, f: &Format) -> Option<Vec<usize>> {
    let v: serde_json::Value = serde_json::from_str(desc.trim()).ok()?;
    let shape: Vec<usize> = v
        .get("shape")?
        .as_array()?
        .iter()
        .map(|x| x.as_u64().map(|x| x as usize))
        .collect::<Option<_>>()?;
    let n = shape.len();
    let (h, w, s) = (f.height, f.width, f.components);
    let samples_last = s > 1 && !f.planar && n >= 3 && shape[n - 3..] == [h, w, s];
    let samples_first = s > 1 && f.planar && n >= 3 && shape[n - 3..] == [s, h, w];
    let lead = if s == 1 && n >= 2 && shape[n - 2..] == [h, w] {
        &shape[..n - 2]
    } else if samples_last || samples_first {
        &shape[..n - 3]
    } else {
        return None;
    };
    (lead.iter().filter(|&&d| d > 1).count() >= 2).then(|| lead.to_vec())
}

/// Whether a file starts with a TIFF byte-order mark.
fn has_tiff_magic(path: &Path) -> Result<bool, VolumeError> {
    let mut head = Vec::with_capacity(4);
    File::open(path)
        .and_then(|f| f.take(4).read_to_end(&mut head))
        .map_err(VolumeError::io(path))?;
    Ok(matches!(
        &head[..],
        b"II*\0" | b"MM\0*" | b"II+\0" | b"MM\0+"
    ))
}

/// The TIFF slices of a folder in natural name order, and the names of the other files.
fn slices_of(dir: &Path) -> Result<(Vec<PathBuf>, Vec<String>), VolumeError> {
    let mut slices = Vec::new();
    let mut skipped = Vec::new();
    for f in super::slice_files(dir)? {
        let name = f
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let lower = name.to_ascii_lowercase();
        if has_tiff_magic(&f)? {
            slices.push(f);
        } else if lower.ends_with(".tif") || lower.ends_with(".tiff") {
            return Err(VolumeError::bad(
                &f,
                "header",
                "named as a TIFF slice but does not start with a TIFF byte-order mark (II*, MM*)",
            ));
        } else {
            skipped.push(name);
        }
    }
    Ok((slices, skipped))
}

fn page_section(k: usize) -> String {
    format!("page {k}")
}

impl TiffStack {
    fn open(path: &Path, options: &VolumeOptions) -> Result<Self, VolumeError> {
        let folder = path.is_dir();
        let (files, skipped) = if folder {
            slices_of(path)?
        } else {
            (vec![path.to_path_buf()], Vec::new())
        };
        if files.is_empty() {
            return Err(VolumeError::bad(
                path,
                "folder",
                "no TIFF files (files starting with a TIFF byte-order mark) in it",
            ));
        }
        let mut notes = Vec::new();
        if !skipped.is_empty() {
            let shown: Vec<&str> = skipped.iter().take(3).map(|s| s.as_str()).collect();
            notes.push(format!(
                "{} file(s) that are not TIFF skipped: {}{}",
                skipped.len(),
                shown.join(", "),
                if skipped.len() > 3 { ", ..." } else { "" }
            ));
        }
        // walk every page of every file: the same format everywhere
        let mut pages = Vec::new();
        let mut first: Option<(Format, usize, usize)> = None;
        let mut meta = Meta::default();
        let mut skipped_pages = 0;
        let mut first_strips: Option<(Vec<u64>, Vec<u64>, u16, u16)> = None;
        // the last file's decoder, which has walked (and keeps) its pages' offsets
        let mut last_dec = None;
        for (fi, file) in files.iter().enumerate() {
            let mut dec = open_decoder(file)?;
            if fi == 0 {
                meta = read_meta(&mut dec);
            }
            let mut k = 0;
            loop {
                let section = page_section(k);
                match page_format(&mut dec, file, &section)? {
                    None => skipped_pages += 1,
                    Some(f) => {
                        match &first {
                            None => {
                                if fi == 0 && k == 0 {
                                    first_strips = strips_of(&mut dec);
                                }
                                first = Some((f, fi, k));
                            }
                            Some((f0, fi0, k0)) if *f0 != f => {
                                return Err(VolumeError::bad(
                                    file,
                                    &section,
                                    format!(
                                        "{}, but {} page {k0} is {}: every page of a stack must \
                                         have the same size and sample type",
                                        f.describe(),
                                        files[*fi0].display(),
                                        f0.describe()
                                    ),
                                ));
                            }
                            Some(_) => {}
                        }
                        pages.push(Page {
                            file: fi,
                            index: k,
                            raw: None,
                        });
                    }
                }
                if !dec.more_images() {
                    break;
                }
                k += 1;
                dec.next_image()
                    .map_err(|e| tiff_error(file, &page_section(k), e))?;
            }
            last_dec = Some((fi, dec));
        }
        let Some((format, _, _)) = first else {
            return Err(VolumeError::bad(
                path,
                "pages",
                "no full-resolution image in it (only thumbnails or masks)",
            ));
        };
        if skipped_pages > 0 {
            notes.push(format!(
                "{skipped_pages} reduced-resolution or mask page(s) skipped"
            ));
        }
        if folder {
            notes.push(format!(
                "{} TIFF file(s), {} page(s), in natural name order",
                files.len(),
                pages.len()
            ));
        }

        let desc = meta.description.clone().unwrap_or_default();
        let imagej = parse_imagej(&desc);
        let mut raw = None;
        let (channels, slices, frames) = match &imagej {
            Some(ij) if folder && ij.channels.unwrap_or(1).max(ij.frames.unwrap_or(1)) > 1 => {
                return Err(VolumeError::unsupported(
                    &files[0],
                    "ImageJ",
                    "a folder of ImageJ hyperstacks (channels or frames): open one file",
                ))
            }
            Some(ij) if !folder => {
                let c = ij.channels.unwrap_or(1).max(1);
                let t = ij.frames.unwrap_or(1).max(1);
                let n = ij.images.unwrap_or(pages.len());
                let z = ij.slices.unwrap_or(n / c.saturating_mul(t)).max(1);
                if c.checked_mul(z).and_then(|x| x.checked_mul(t)) != Some(n) {
                    return Err(VolumeError::bad(
                        path,
                        "ImageJ",
                        format!(
                            "channels {c} × slices {z} × frames {t} is not images={n} (the \
                             description does not fit the stack)"
                        ),
                    ));
                }
                if n != pages.len() {
                    raw = Some(contiguous_pages(
                        path,
                        &format,
                        pages.len(),
                        n,
                        first_strips.take(),
                        meta.endian.unwrap_or(Endian::Little),
                    )?);
                    notes.push(format!(
                        "ImageJ file of one IFD: {n} pages read contiguous after the first"
                    ));
                }
                if z == 1 && t > 1 {
                    return Err(VolumeError::unsupported(
                        path,
                        "ImageJ",
                        format!(
                            "a time series of {t} frames of one slice: 2D images over time, \
                             not a volume"
                        ),
                    ));
                }
                (c, z, t)
            }
            _ => match tifffile_shape(&desc, &format) {
                Some(lead)
                    if lead.iter().try_fold(1usize, |a, &d| a.checked_mul(d))
                        == Some(pages.len()) =>
                {
                    let z = *lead.last().expect("two or more leading dims");
                    let t = pages.len() / z.max(1);
                    notes.push(format!(
                        "tifffile shape {lead:?} of pages: the last is z, the others {t} frames"
                    ));
                    (1, z, t)
                }
                _ => (1, pages.len(), 1),
            },
        };
        if channels > 1 && format.components > 1 {
            return Err(VolumeError::unsupported(
                path,
                "ImageJ",
                format!(
                    "{channels} channels of {} samples a pixel each: choose one in ImageJ \
                     (Image > Color > Split Channels) first",
                    format.components
                ),
            ));
        }

        // the component: a channel of a hyperstack, or a sample of a pixel
        let n = channels.max(format.components);
        let names = if channels > 1 {
            Vec::new()
        } else {
            format.names.clone()
        };
        let choice = choose_component(options.scalar.as_ref(), n, &names)
            .map_err(|m| VolumeError::usage(path, m))?;
        // the magnitude of a lone component is the component itself, in its own type
        let choice = if n <= 1 { Some(0) } else { choice };
        let (chosen_channels, which) = if channels > 1 {
            match choice {
                Some(c) => (vec![c], Some(0)),
                None => ((0..channels).collect(), Some(0)),
            }
        } else {
            (vec![0], choice)
        };
        if n > 1 {
            let what = if channels > 1 { "channel" } else { "component" };
            notes.push(match choice {
                Some(k) => match names.get(k) {
                    Some(name) => format!("{what} {k} ({name}) of {n}"),
                    None => format!("{what} {k} of {n}"),
                },
                None => format!("magnitude of {n} {what}s"),
            });
        }
        let frame = match (options.frame, frames) {
            (Some(t), n) if t < n => t,
            (Some(t), n) => {
                return Err(VolumeError::usage(
                    path,
                    format!("--frame {t}: the stack has {n} frame(s) (0 to {})", n - 1),
                ))
            }
            (None, 1) => 0,
            (None, n) => {
                return Err(VolumeError::usage(
                    path,
                    format!(
                        "{n} frames (a 4D stack): choose one with --frame T (0 to {})",
                        n - 1
                    ),
                ))
            }
        };
        if frames > 1 {
            notes.push(format!("frame {frame} of {frames}"));
        }

        let dtype = match choice {
            None if format.stored.dtype() == DType::F64 => DType::F64,
            None => DType::F32,
            Some(_) => format.stored.dtype(),
        };
        if format.stored == Stored::F16 {
            notes.push("16-bit float samples widened to f32".into());
        }
        let mut header = FileHeader::new(
            VolumeFormat::Tiff,
            [format.width, format.height, slices],
            dtype,
            [1.0; 3],
        );
        geometry(&mut header, &meta, imagej.as_ref());
        header.notes.extend(notes);
        Ok(TiffStack {
            path: path.to_path_buf(),
            files,
            header,
            format,
            pages,
            raw,
            channels,
            slices,
            frame,
            chosen_channels,
            which,
            dec: last_dec,
        })
    }

    /// The page of channel `c` of plane `z` of the chosen frame.
    fn page(&self, c: usize, z: usize) -> Result<Page, VolumeError> {
        let n = c + self.channels * (z + self.slices * self.frame);
        match self.raw {
            Some(r) if n < r.count => Ok(Page {
                file: 0,
                index: 0,
                raw: Some(n as u64),
            }),
            None if n < self.pages.len() => Ok(self.pages[n]),
            _ => Err(VolumeError::bad(
                &self.path,
                "pages",
                format!("page {n} asked of a stack of fewer"),
            )),
        }
    }

    fn decoder(&mut self, file: usize) -> Result<&mut Dec, VolumeError> {
        if self.dec.as_ref().is_none_or(|(f, _)| *f != file) {
            self.dec = None;
            self.dec = Some((file, open_decoder(&self.files[file])?));
        }
        Ok(&mut self.dec.as_mut().expect("opened above").1)
    }

    /// The chosen component of the pixels `lo..hi` (x, y) of one page, x fastest.
    fn read_page(
        &mut self,
        page: Page,
        lo: [usize; 2],
        hi: [usize; 2],
    ) -> Result<Samples, VolumeError> {
        let f = self.format.clone();
        let path = self.files[page.file].clone();
        let section = match page.raw {
            Some(k) => page_section(k as usize),
            None => page_section(page.index),
        };
        let which = self.which;
        let raw = self.raw;
        let dec = self.decoder(page.file)?;
        let err = |e| tiff_error(&path, &section, e);
        let planes: Vec<usize> = match (f.planar, which) {
            (false, _) => vec![0],
            (true, Some(k)) => vec![k],
            (true, None) => (0..f.components).collect(),
        };
        let mut parts = Vec::with_capacity(planes.len());
        if let (Some(k), Some(r)) = (page.raw, raw) {
            // an ImageJ page after the first: one uncompressed strip of the whole page
            let chunks = Chunks {
                grid: Grid {
                    cw: f.width,
                    ch: f.height,
                    across: 1,
                    down: 1,
                },
                offsets: vec![r.offset + k * r.page_bytes],
                counts: vec![r.page_bytes],
                endian: r.endian,
            };
            let bytes = read_direct(dec, &path, &section, &f, &chunks, 0, lo, hi)?;
            parts.push(decode(f.stored, &bytes, r.endian));
        } else {
            dec.seek_to_image(page.index).map_err(err)?;
            let grid = Grid::of(dec, &f).map_err(err)?;
            let direct = direct_chunks(dec, &f, &grid).map_err(err)?;
            let total = match dec.get_chunk_type() {
                ChunkType::Strip => dec.strip_count(),
                ChunkType::Tile => dec.tile_count(),
            }
            .map_err(err)? as usize;
            let planes_in_file = if f.planar { f.components } else { 1 };
            if total < grid.per_plane() * planes_in_file {
                return Err(VolumeError::bad(
                    &path,
                    &section,
                    format!(
                        "{total} strips or tiles, its size needs {}",
                        grid.per_plane() * planes_in_file
                    ),
                ));
            }
            for &p in &planes {
                let (bytes, endian) = match &direct {
                    Some(chunks) => (
                        read_direct(dec, &path, &section, &f, chunks, p, lo, hi)?,
                        chunks.endian,
                    ),
                    None => (
                        read_decoded(dec, &path, &section, &f, &grid, p, lo, hi)?,
                        native(),
                    ),
                };
                parts.push(decode(f.stored, &bytes, endian));
            }
        }
        Ok(match (f.planar, which) {
            (false, w) => select(parts.pop().expect("one plane"), f.components, w),
            (true, Some(_)) => parts.pop().expect("one plane"),
            (true, None) => magnitude(&parts),
        })
    }
}

fn native() -> Endian {
    if cfg!(target_endian = "little") {
        Endian::Little
    } else {
        Endian::Big
    }
}

/// The strip offsets and byte counts of the decoder's current page, its compression and
/// predictor, when it is in strips.
fn strips_of(dec: &mut Dec) -> Option<(Vec<u64>, Vec<u64>, u16, u16)> {
    let offsets = dec.find_tag_unsigned_vec(Tag::StripOffsets).ok()??;
    let counts = dec.find_tag_unsigned_vec(Tag::StripByteCounts).ok()??;
    let compression = dec.find_tag_unsigned(Tag::Compression).ok()?.unwrap_or(1);
    let predictor = dec.find_tag_unsigned(Tag::Predictor).ok()?.unwrap_or(1);
    Some((offsets, counts, compression, predictor))
}

/// The pages of an ImageJ file that holds one IFD (ImageJ writes files over 4 GiB so): `n`
/// pages of the first page's size, contiguous from its first strip.
fn contiguous_pages(
    path: &Path,
    f: &Format,
    ifds: usize,
    n: usize,
    strips: Option<(Vec<u64>, Vec<u64>, u16, u16)>,
    endian: Endian,
) -> Result<RawPages, VolumeError> {
    let mismatch = |why: &str| {
        VolumeError::bad(
            path,
            "ImageJ",
            format!("the description says images={n}, the file has {ifds} page(s){why}"),
        )
    };
    if ifds != 1 || f.planar || !matches!(f.stored, Stored::T(_)) {
        return Err(mismatch(""));
    }
    let Some((offsets, counts, compression, predictor)) = strips else {
        return Err(mismatch(" (and its first is not in strips)"));
    };
    if compression != 1 || predictor != 1 {
        return Err(mismatch(
            " (and its first is compressed: its pages cannot be contiguous)",
        ));
    }
    let page_bytes = (f.width * f.height * f.components * f.stored.bytes()) as u64;
    let contiguous = offsets.len() == counts.len()
        && !offsets.is_empty()
        && offsets
            .windows(2)
            .zip(&counts)
            .all(|(w, &c)| w[0].checked_add(c) == Some(w[1]));
    if !contiguous || counts.iter().sum::<u64>() != page_bytes {
        return Err(mismatch(
            " (and its first page's strips are not contiguous)",
        ));
    }
    let len = std::fs::metadata(path)
        .map_err(VolumeError::io(path))?
        .len();
    let need = (n as u64)
        .checked_mul(page_bytes)
        .and_then(|b| b.checked_add(offsets[0]));
    if need.is_none_or(|need| need > len) {
        return Err(VolumeError::bad(
            path,
            "ImageJ",
            format!(
                "truncated: {n} contiguous pages of {page_bytes} bytes from byte {} end past \
                 the file's {len} bytes",
                offsets[0]
            ),
        ));
    }
    Ok(RawPages {
        offset: offsets[0],
        page_bytes,
        count: n,
        endian,
    })
}

/// How a page is cut into strips or tiles: `cw × ch` pixels each (the last column and row of
/// chunks are cut by the page's edge), `across × down` of them a sample plane.
#[derive(Debug, Clone, Copy)]
struct Grid {
    cw: usize,
    ch: usize,
    across: usize,
    down: usize,
}

impl Grid {
    fn of(dec: &Dec, f: &Format) -> Result<Grid, TiffError> {
        let (cw, ch) = dec.chunk_dimensions();
        let (cw, ch) = match dec.get_chunk_type() {
            ChunkType::Strip => (f.width, (ch as usize).clamp(1, f.height)),
            ChunkType::Tile => (cw as usize, ch as usize),
        };
        if cw == 0 || ch == 0 {
            return Err(TiffError::IntSizeError);
        }
        Ok(Grid {
            cw,
            ch,
            across: f.width.div_ceil(cw),
            down: f.height.div_ceil(ch),
        })
    }
    fn per_plane(&self) -> usize {
        self.across * self.down
    }
    /// The chunks of sample plane `plane` that overlap the pixels `lo..hi`: their index and
    /// pixel rectangle (x0, y0, x1, y1), cut by the page of `w × h`.
    fn overlapping(
        &self,
        plane: usize,
        lo: [usize; 2],
        hi: [usize; 2],
        w: usize,
        h: usize,
    ) -> Vec<(usize, [usize; 4])> {
        let mut v = Vec::new();
        for r in lo[1] / self.ch..=(hi[1] - 1) / self.ch {
            for c in lo[0] / self.cw..=(hi[0] - 1) / self.cw {
                let idx = plane * self.per_plane() + r * self.across + c;
                let rect = [
                    c * self.cw,
                    r * self.ch,
                    ((c + 1) * self.cw).min(w),
                    ((r + 1) * self.ch).min(h),
                ];
                v.push((idx, rect));
            }
        }
        v
    }
}

/// Uncompressed chunks read straight from the file: their grid, offsets, byte counts and the
/// file's byte order.
struct Chunks {
    grid: Grid,
    offsets: Vec<u64>,
    counts: Vec<u64>,
    endian: Endian,
}

/// The current page's chunks when they can be read without the decoder: uncompressed, no
/// predictor, not inverted, every sample kept.
fn direct_chunks(dec: &mut Dec, f: &Format, grid: &Grid) -> Result<Option<Chunks>, TiffError> {
    let compression = dec.find_tag_unsigned::<u16>(Tag::Compression)?.unwrap_or(1);
    let predictor = dec.find_tag_unsigned::<u16>(Tag::Predictor)?.unwrap_or(1);
    let photometric = dec.find_tag_unsigned::<u16>(Tag::PhotometricInterpretation)?;
    let samples = dec
        .find_tag_unsigned::<u16>(Tag::SamplesPerPixel)?
        .unwrap_or(1) as usize;
    if compression != 1 || predictor != 1 || photometric == Some(0) || samples != f.components {
        return Ok(None);
    }
    let (o, c) = match dec.get_chunk_type() {
        ChunkType::Strip => (Tag::StripOffsets, Tag::StripByteCounts),
        ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts),
    };
    let offsets = dec.find_tag_unsigned_vec::<u64>(o)?.unwrap_or_default();
    let counts = dec.find_tag_unsigned_vec::<u64>(c)?.unwrap_or_default();
    Ok(Some(Chunks {
        grid: *grid,
        offsets,
        counts,
        endian: endian_of(dec),
    }))
}

/// The bytes of pixels `lo..hi` of sample plane `plane` read straight from uncompressed chunks,
/// in the file's byte order: only the rows (and columns) of the box.
#[allow(clippy::too_many_arguments)]
fn read_direct(
    dec: &mut Dec,
    path: &Path,
    section: &str,
    f: &Format,
    chunks: &Chunks,
    plane: usize,
    lo: [usize; 2],
    hi: [usize; 2],
) -> Result<Vec<u8>, VolumeError> {
    let vb = f.chunk_pixel_bytes();
    let bw = hi[0] - lo[0];
    let mut out = alloc(path, bw * (hi[1] - lo[1]) * vb)?;
    let file = dec.inner();
    for (idx, [x0, y0, x1, y1]) in chunks.grid.overlapping(plane, lo, hi, f.width, f.height) {
        let (Some(&at), Some(&count)) = (chunks.offsets.get(idx), chunks.counts.get(idx)) else {
            return Err(VolumeError::bad(
                path,
                section,
                format!("strip or tile {idx} has no offset or byte count"),
            ));
        };
        let (xs, xe) = (lo[0].max(x0), hi[0].min(x1));
        let (ys, ye) = (lo[1].max(y0), hi[1].min(y1));
        // rows of the stored chunk are its full width (tiles are padded to theirs)
        let row = (chunks.grid.cw * vb) as u64;
        let need = (ye - y0) as u64 * row;
        if need > count {
            return Err(VolumeError::bad(
                path,
                section,
                format!("strip or tile {idx} holds {count} bytes, its rows {y0}..{ye} need {need}"),
            ));
        }
        let len = (xe - xs) * vb;
        let whole_rows = xs == x0 && xe - xs == chunks.grid.cw && bw == xe - xs;
        let read = |file: &mut BufReader<File>, from: u64, into: &mut [u8]| {
            file.seek(SeekFrom::Start(from))
                .and_then(|_| file.read_exact(into))
                .map_err(|e| tiff_error(path, section, TiffError::IoError(e)))
        };
        if whole_rows {
            let dst = (ys - lo[1]) * bw * vb;
            let n = (ye - ys) * len;
            read(file, at + (ys - y0) as u64 * row, &mut out[dst..dst + n])?;
        } else {
            for y in ys..ye {
                let dst = ((y - lo[1]) * bw + (xs - lo[0])) * vb;
                let from = at + (y - y0) as u64 * row + ((xs - x0) * vb) as u64;
                read(file, from, &mut out[dst..dst + len])?;
            }
        }
    }
    Ok(out)
}

/// The bytes of pixels `lo..hi` of sample plane `plane` from chunks the decoder expands, in the
/// machine's byte order.
#[allow(clippy::too_many_arguments)]
fn read_decoded(
    dec: &mut Dec,
    path: &Path,
    section: &str,
    f: &Format,
    grid: &Grid,
    plane: usize,
    lo: [usize; 2],
    hi: [usize; 2],
) -> Result<Vec<u8>, VolumeError> {
    let err = |e| tiff_error(path, section, e);
    let vb = f.chunk_pixel_bytes();
    let bw = hi[0] - lo[0];
    let mut out = alloc(path, bw * (hi[1] - lo[1]) * vb)?;
    let mut buf = Vec::new();
    for (idx, [x0, y0, x1, y1]) in grid.overlapping(plane, lo, hi, f.width, f.height) {
        let chunk = u32::try_from(idx).map_err(|_| err(TiffError::IntSizeError))?;
        let layout = dec.image_chunk_buffer_layout(chunk).map_err(err)?;
        buf.clear();
        buf.try_reserve_exact(layout.len)
            .map_err(|_| VolumeError::NoMemory {
                path: path.to_path_buf(),
                bytes: layout.len as u64,
            })?;
        buf.resize(layout.len, 0);
        dec.read_chunk_bytes(chunk, &mut buf).map_err(err)?;
        // the decoder's rows are the chunk's data width (less any padding)
        let (dw, _) = dec.chunk_data_dimensions(chunk);
        let stride = dw as usize * vb;
        let (xs, xe) = (lo[0].max(x0), hi[0].min(x1));
        let (ys, ye) = (lo[1].max(y0), hi[1].min(y1));
        let len = (xe - xs) * vb;
        if (xe - x0) > dw as usize || (ye - y0) * stride > buf.len() {
            return Err(VolumeError::bad(
                path,
                section,
                format!(
                    "strip or tile {idx} decodes to {} bytes, fewer than its pixels",
                    buf.len()
                ),
            ));
        }
        for y in ys..ye {
            let src = (y - y0) * stride + (xs - x0) * vb;
            let dst = ((y - lo[1]) * bw + (xs - lo[0])) * vb;
            out[dst..dst + len].copy_from_slice(&buf[src..src + len]);
        }
    }
    Ok(out)
}

fn alloc(path: &Path, n: usize) -> Result<Vec<u8>, VolumeError> {
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| VolumeError::NoMemory {
        path: path.to_path_buf(),
        bytes: n as u64,
    })?;
    v.resize(n, 0);
    Ok(v)
}

/// Samples of `stored` type from bytes in byte order `endian` (half floats widened to f32).
fn decode(stored: Stored, bytes: &[u8], endian: Endian) -> Samples {
    match stored {
        Stored::T(t) => Samples::decode(t, bytes, endian),
        Stored::F16 => match Samples::decode(DType::U16, bytes, endian) {
            Samples::U16(v) => Samples::F32(v.into_iter().map(f16_to_f32).collect()),
            _ => unreachable!("decoded as u16"),
        },
    }
}

/// An IEEE half float's value.
fn f16_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let man = (h & 0x3ff) as f32;
    match exp {
        0 => sign * man * 2f32.powi(-24),
        31 if man == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        e => sign * (1.0 + man / 1024.0) * 2f32.powi(e - 15),
    }
}

/// The Euclidean norm of the voxels of several parts (planes or channels) of the same box, as
/// f32 (f64 for f64), as [`Samples::magnitude`] gives it for interleaved components.
fn magnitude(parts: &[Samples]) -> Samples {
    let n = parts.iter().map(|p| p.len()).min().unwrap_or(0);
    let norm = |i: usize| parts.iter().map(|p| p.get(i).powi(2)).sum::<f64>().sqrt();
    if parts.first().is_some_and(|p| p.dtype() == DType::F64) {
        Samples::F64((0..n).map(norm).collect())
    } else {
        Samples::F32((0..n).map(|i| norm(i) as f32).collect())
    }
}

/// Spacing, origin, units and rescale from ImageJ's description or the resolution tags.
fn geometry(h: &mut FileHeader, meta: &Meta, imagej: Option<&ImageJ>) {
    let [rx, ry] = meta.resolution;
    match imagej {
        Some(ij) => {
            let unit = ij.unit.as_deref().and_then(length_unit);
            let calibrated = unit.is_some() || rx.is_some_and(|r| r != 1.0);
            h.spacing[0] = rx.map_or(1.0, |r| 1.0 / r);
            h.spacing[1] = ry.or(rx).map_or(1.0, |r| 1.0 / r);
            match ij.spacing {
                Some(s) if s < 0.0 => {
                    h.spacing[2] = -s;
                    h.axes[2].flip = true;
                    h.notes
                        .push("ImageJ spacing is negative: z runs against the pages".into());
                }
                Some(s) if s > 0.0 => h.spacing[2] = s,
                _ => {
                    h.spacing[2] = 1.0;
                    if h.dims[2] > 1 && calibrated {
                        h.notes
                            .push("no ImageJ z spacing (spacing=): z spacing 1".into());
                    }
                }
            }
            if !calibrated && ij.spacing.is_none() {
                h.notes
                    .push("an uncalibrated ImageJ stack: spacing 1, 1, 1 voxel".into());
            }
            h.length_unit = unit;
            for a in 0..3 {
                if let Some(o) = ij.origin[a] {
                    // ImageJ's origin is the voxel at world 0
                    let s = if h.axes[a].flip {
                        -h.spacing[a]
                    } else {
                        h.spacing[a]
                    };
                    h.origin[a] = -o * s;
                }
            }
            if ij.cf == Some(0) {
                let (c0, c1) = (ij.c0.unwrap_or(0.0), ij.c1.unwrap_or(1.0));
                if c1 != 0.0 && (c0, c1) != (0.0, 1.0) {
                    h.rescale = Some((c1, c0));
                }
                h.value_unit = ij
                    .vunit
                    .clone()
                    .filter(|u| !u.is_empty() && u != "Gray Value");
            } else if let Some(cf) = ij.cf.filter(|&cf| cf != 20 && cf != 21) {
                // 20: NONE, 21: UNCALIBRATED_OD; others are curves not read
                h.notes.push(format!(
                    "ImageJ calibration function {cf} (not a straight line) ignored"
                ));
            }
        }
        None => {
            let scale = match meta.resolution_unit.unwrap_or(2) {
                2 => Some((25.4, "mm")),
                3 => Some((10.0, "mm")),
                _ => None,
            };
            match (rx, scale) {
                (Some(rx), Some((k, unit))) => {
                    let ry = ry.unwrap_or(rx);
                    h.spacing = [k / rx, k / ry, k / rx];
                    h.length_unit = Some(unit.into());
                    h.notes.push(format!(
                        "x, y spacing from the resolution tags; z is not stated in TIFF: taken \
                         equal to x ({} {unit})",
                        k / rx
                    ));
                }
                (Some(rx), None) if rx != 1.0 || ry.is_some_and(|r| r != 1.0) => {
                    let ry = ry.unwrap_or(rx);
                    h.spacing = [1.0 / rx, 1.0 / ry, 1.0 / rx];
                    h.notes.push(
                        "x, y spacing from the resolution tags (no unit); z is not stated in \
                         TIFF: taken equal to x"
                            .into(),
                    );
                }
                _ => h
                    .notes
                    .push("no spacing in the file: spacing 1, 1, 1 voxel".into()),
            }
        }
    }
}

impl VolumeReader for TiffStack {
    fn header(&self) -> &FileHeader {
        &self.header
    }

    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
        super::check_box(&self.path, lo, hi, self.header.dims)?;
        let n = (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2]);
        let mut out = Samples::with_capacity(self.header.dtype, n);
        let channels = self.chosen_channels.clone();
        for z in lo[2]..hi[2] {
            let mut parts = Vec::with_capacity(channels.len());
            for &c in &channels {
                let page = self.page(c, z)?;
                parts.push(self.read_page(page, [lo[0], lo[1]], [hi[0], hi[1]])?);
            }
            let plane = if parts.len() == 1 {
                parts.pop().expect("one part")
            } else {
                magnitude(&parts)
            };
            if !out.extend(&plane) {
                return Err(VolumeError::bad(
                    &self.path,
                    "pages",
                    format!(
                        "plane {z} decoded as {}, the stack is {}",
                        plane.dtype(),
                        self.header.dtype
                    ),
                ));
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
#[path = "tiff_stack_tests.rs"]
mod tests;
