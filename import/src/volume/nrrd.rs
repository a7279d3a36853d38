//! NRRD (`.nrrd` with its samples attached, `.nhdr` with them in other files), read by hand: the
//! header is a few lines of `field: value` text, and what the box reader needs from it is the
//! samples' type, layout and where they start.
//!
//! Read: the `NRRD000x` magic, `dimension` 3 or 4, `sizes`, `type` in every spelling of the eight
//! sample types (64-bit integers and `block` are refused), `endian`, `encoding` raw, gzip
//! (`gz`), ascii (`txt`, `text`) and `hex` (bzip2 and the others are refused: re-save as raw or
//! gzip), `byte skip` (-1, "the samples end the file", with raw only) and `line skip`, `data
//! file` as one file, as `LIST` (the file names follow the header) and as a format string
//! (`data file: slice%03d.raw 1 40 1 [subdim]`); for the geometry `space` (with `space
//! dimension` 3), `space directions`, `space origin`, `space units`, else `spacings` (no spacing
//! stated reads as 1); `kinds` for the fourth axis; `sample units` as the value unit.
//! Other fields and `key:=value` pairs are read past.
//!
//! Orientation: a `space directions` vector that is not along one world axis is refused as
//! oblique. `left-posterior-superior` is the frame `LPS`, `right-anterior-superior` `RAS`, and
//! `left-anterior-superior` is turned into `RAS` (x negated); other spaces (`scanner-xyz`,
//! `3D-right-handed`) have no frame name; spaces with time are refused.
//!
//! A 4D volume has one non-spatial axis, which `kinds` names (else a `none` among the `space
//! directions`): `time` or `list` is a frame axis (`--frame`), a vector, colour, tensor or other
//! kind a component axis (`--scalar K`, `--scalar mag`, or `r` `g` `b` (`a`) for colours). It
//! must be the first axis (then interleaved) or the last (then one block each; `--scalar mag` of
//! such blocks is refused).
//!
//! Out of core: raw samples are read at their offset, box row by box row; gzip, ascii and hex
//! samples are decoded from the start of their file up to the box's end, and the decoder is kept
//! for the next box when that lies further on (as `prepare` reads them, so a whole volume is
//! decoded once). A gzip stream's `byte skip` counts decompressed bytes.
//!
//! This file also has the stream helpers the VTK image reader shares (`Reopen`, `TextValues`,
//! `axis_aligned`).

use super::raw::{read_box, ByteSource, Layout, SeekRead};
use super::samples::{choose_component, select};
use super::{
    AxisMap, DType, Endian, FileHeader, Samples, VolumeError, VolumeFormat, VolumeOptions,
    VolumeReader,
};
use std::fs::File;
use std::io::{self, BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// A header longer than this is not one (a file of samples without the blank line).
const MAX_HEADER: u64 = 1 << 24;

pub(crate) fn open(
    path: &Path,
    options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    Ok(Box::new(NrrdReader::open(path, options)?))
}

// ---------------------------------------------------------------------------------------------
// Stream helpers, shared with the VTK image reader

/// Opens a stream at its start.
pub(super) type Opener = Box<dyn FnMut() -> io::Result<Box<dyn Read + Send>> + Send>;

/// A forward-only stream made seekable: seeking forward reads past, seeking backward opens the
/// stream again. The stream is kept between reads, so boxes read in file order decode it once.
pub(super) struct Reopen {
    open: Opener,
    inner: Option<Box<dyn Read + Send>>,
    pos: u64,
    target: u64,
}

impl Reopen {
    pub(super) fn new(open: Opener) -> Self {
        Reopen {
            open,
            inner: None,
            pos: 0,
            target: 0,
        }
    }
}

impl Read for Reopen {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.inner.is_none() || self.target < self.pos {
            self.inner = None;
            self.inner = Some((self.open)()?);
            self.pos = 0;
        }
        let Some(inner) = self.inner.as_mut() else {
            return Ok(0);
        };
        if self.target > self.pos {
            let skipped = io::copy(
                &mut Read::by_ref(inner).take(self.target - self.pos),
                &mut io::sink(),
            )?;
            self.pos += skipped;
            if self.pos < self.target {
                return Ok(0);
            }
        }
        let n = inner.read(buf)?;
        self.pos += n as u64;
        self.target = self.pos;
        Ok(n)
    }
}

impl Seek for Reopen {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        self.target = match to {
            SeekFrom::Start(n) => n,
            SeekFrom::Current(d) => self
                .target
                .checked_add_signed(d)
                .ok_or_else(|| io::Error::from(io::ErrorKind::InvalidInput))?,
            SeekFrom::End(_) => {
                return Err(io::Error::new(
                    io::ErrorKind::Unsupported,
                    "a decoded stream has no known end",
                ))
            }
        };
        Ok(self.target)
    }
}

/// Numbers written as text (separated by white space or commas), given as the little-endian bytes
/// of `dtype`. With `stop_at_tag` a `<` ends them (an XML element's text).
pub(super) struct TextValues<R> {
    src: R,
    dtype: DType,
    stop_at_tag: bool,
    token: Vec<u8>,
    out: [u8; 8],
    out_at: usize,
    out_len: usize,
    values: u64,
}

impl<R: BufRead> TextValues<R> {
    pub(super) fn new(src: R, dtype: DType, stop_at_tag: bool) -> Self {
        TextValues {
            src,
            dtype,
            stop_at_tag,
            token: Vec::new(),
            out: [0; 8],
            out_at: 0,
            out_len: 0,
            values: 0,
        }
    }

    /// The next token into `self.token`; `false` at the end of the text.
    fn next_token(&mut self) -> io::Result<bool> {
        self.token.clear();
        loop {
            let buf = self.src.fill_buf()?;
            if buf.is_empty() {
                return Ok(!self.token.is_empty());
            }
            let mut used = 0;
            let mut end = false;
            for &c in buf {
                if c.is_ascii_whitespace() || c == b',' {
                    used += 1;
                    if !self.token.is_empty() {
                        end = true;
                        break;
                    }
                } else if c == b'<' && self.stop_at_tag {
                    end = true;
                    break;
                } else {
                    if self.token.len() >= 64 {
                        return Err(io::Error::new(
                            io::ErrorKind::InvalidData,
                            format!("value {} is not a number", self.values),
                        ));
                    }
                    self.token.push(c);
                    used += 1;
                }
            }
            self.src.consume(used);
            if end {
                return Ok(!self.token.is_empty());
            }
        }
    }
}

/// The little-endian bytes of the number `tok` as `dtype` (integers may be written as integral
/// floats); `None` when it is not one or out of the type's range.
fn encode_number(dtype: DType, tok: &str, out: &mut [u8; 8]) -> Option<usize> {
    let int = || -> Option<i64> {
        tok.parse::<i64>().ok().or_else(|| {
            let f = tok.parse::<f64>().ok()?;
            (f.fract() == 0.0 && f.abs() < 9.0e18).then_some(f as i64)
        })
    };
    let mut put = |b: &[u8]| {
        out[..b.len()].copy_from_slice(b);
        Some(b.len())
    };
    match dtype {
        DType::U8 => put(&u8::try_from(int()?).ok()?.to_le_bytes()),
        DType::I8 => put(&i8::try_from(int()?).ok()?.to_le_bytes()),
        DType::U16 => put(&u16::try_from(int()?).ok()?.to_le_bytes()),
        DType::I16 => put(&i16::try_from(int()?).ok()?.to_le_bytes()),
        DType::U32 => put(&u32::try_from(int()?).ok()?.to_le_bytes()),
        DType::I32 => put(&i32::try_from(int()?).ok()?.to_le_bytes()),
        DType::F32 => put(&tok.parse::<f32>().ok()?.to_le_bytes()),
        DType::F64 => put(&tok.parse::<f64>().ok()?.to_le_bytes()),
    }
}

impl<R: BufRead> Read for TextValues<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let mut n = 0;
        while n < buf.len() {
            if self.out_at == self.out_len {
                if !self.next_token()? {
                    break;
                }
                let tok = String::from_utf8_lossy(&self.token);
                self.out_len = encode_number(self.dtype, &tok, &mut self.out).ok_or_else(|| {
                    io::Error::new(
                        io::ErrorKind::InvalidData,
                        format!(
                            "value {} (\"{}\") is not a number of type {}",
                            self.values,
                            tok.chars().take(32).collect::<String>(),
                            self.dtype
                        ),
                    )
                })?;
                self.out_at = 0;
                self.values += 1;
            }
            let k = (self.out_len - self.out_at).min(buf.len() - n);
            buf[n..n + k].copy_from_slice(&self.out[self.out_at..self.out_at + k]);
            self.out_at += k;
            n += k;
        }
        Ok(n)
    }
}

/// Bytes written as pairs of hex digits (white space between them ignored).
struct HexBytes<R> {
    src: R,
}

impl<R: BufRead> Read for HexBytes<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let mut n = 0;
        let mut high: Option<u8> = None;
        while n < buf.len() {
            let avail = self.src.fill_buf()?;
            if avail.is_empty() {
                break;
            }
            let mut used = 0;
            for &c in avail {
                if n == buf.len() && high.is_none() {
                    break;
                }
                used += 1;
                if c.is_ascii_whitespace() {
                    continue;
                }
                let d = (c as char).to_digit(16).ok_or_else(|| {
                    io::Error::new(
                        io::ErrorKind::InvalidData,
                        format!("byte {c:#04x} is not a hex digit"),
                    )
                })? as u8;
                match high.take() {
                    None => high = Some(d),
                    Some(h) => {
                        buf[n] = h << 4 | d;
                        n += 1;
                    }
                }
            }
            self.src.consume(used);
        }
        if high.is_some() {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "hex data ends inside a byte",
            ));
        }
        Ok(n)
    }
}

/// Why a direction matrix is not read.
#[derive(Debug)]
pub(super) enum NotAligned {
    /// An axis with no extent or a non-finite entry (a malformed file).
    Bad(String),
    /// An axis that is not along one world axis.
    Oblique(String),
}

/// Each file axis's world axis, direction and spacing, from the world step of one voxel along it
/// (`steps[a]`: a column of the direction matrix times the spacing). A step with more than one
/// entry above 1e-6 of its largest is oblique.
pub(super) fn axis_aligned(steps: [[f64; 3]; 3]) -> Result<([AxisMap; 3], [f64; 3]), NotAligned> {
    let mut axes = [AxisMap {
        axis: 0,
        flip: false,
    }; 3];
    let mut spacing = [0.0; 3];
    let mut seen = [false; 3];
    for (a, col) in steps.iter().enumerate() {
        let big = col.iter().map(|x| x.abs()).fold(0.0, f64::max);
        if !(big.is_finite() && big > 0.0) || col.iter().any(|x| !x.is_finite()) {
            return Err(NotAligned::Bad(format!(
                "axis {a} has no extent or a non-finite direction ({col:?})"
            )));
        }
        let rows: Vec<usize> = (0..3).filter(|&i| col[i].abs() > 1e-6 * big).collect();
        if rows.len() != 1 {
            return Err(NotAligned::Oblique(format!(
                "an oblique orientation (voxel axis {a} runs along {col:?}): resample it to an \
                 axis-aligned grid first (e.g. 3D Slicer's or ANTs' resampling)"
            )));
        }
        let axis = rows[0];
        if std::mem::replace(&mut seen[axis], true) {
            return Err(NotAligned::Bad(format!(
                "two voxel axes run along world axis {axis} ({steps:?})"
            )));
        }
        axes[a] = AxisMap {
            axis,
            flip: col[axis] < 0.0,
        };
        spacing[a] = col[axis].abs();
    }
    Ok((axes, spacing))
}

// ---------------------------------------------------------------------------------------------
// The header

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Raw,
    Gzip,
    Ascii,
    Hex,
}

/// Where the samples are when not after the header's blank line.
#[derive(Debug, Clone, PartialEq)]
enum DataFile {
    One(String),
    /// One file per slab of the slowest axes; `subdim`: the axes each file holds.
    List {
        names: Vec<String>,
        subdim: Option<usize>,
    },
    Format {
        format: String,
        min: i64,
        max: i64,
        step: i64,
        subdim: Option<usize>,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Space {
    Ras,
    Las,
    Lps,
    /// A space without an anatomical name (`scanner-xyz`, `3D-right-handed`, ...).
    Plain,
}

/// What the header states, each field checked on its own.
#[derive(Debug, Clone, Default)]
struct Fields {
    dimension: Option<usize>,
    sizes: Option<Vec<usize>>,
    dtype: Option<DType>,
    encoding: Option<Encoding>,
    endian: Option<Endian>,
    spacings: Option<Vec<f64>>,
    directions: Option<Vec<Option<Vec<f64>>>>,
    origin: Option<Vec<f64>>,
    space: Option<(Space, String)>,
    space_dimension: Option<usize>,
    space_units: Option<Vec<String>>,
    units: Option<Vec<String>>,
    sample_units: Option<String>,
    kinds: Option<Vec<String>>,
    byte_skip: i64,
    line_skip: u64,
    data_file: Option<DataFile>,
}

/// The header's lines (without line ends) and where the attached samples start (`None`: the
/// file ends without the blank line, a detached header).
fn read_header(path: &Path) -> Result<(Vec<String>, Option<u64>), VolumeError> {
    let f = File::open(path).map_err(VolumeError::io(path))?;
    let mut r = BufReader::new(f).take(MAX_HEADER);
    let mut lines = Vec::new();
    let mut at = 0u64;
    let mut buf = Vec::new();
    loop {
        buf.clear();
        let n = r
            .read_until(b'\n', &mut buf)
            .map_err(VolumeError::io(path))?;
        if n == 0 {
            return Ok((lines, None));
        }
        at += n as u64;
        let ended = buf.last() == Some(&b'\n');
        if !ended && at >= MAX_HEADER {
            return Err(VolumeError::bad(
                path,
                "header",
                "no blank line ends the header in its first 16 MiB",
            ));
        }
        while matches!(buf.last(), Some(b'\n' | b'\r')) {
            buf.pop();
        }
        if buf.is_empty() && ended && !lines.is_empty() {
            return Ok((lines, Some(at)));
        }
        match std::str::from_utf8(&buf) {
            Ok(s) => lines.push(s.to_string()),
            Err(_) if lines.is_empty() => {
                return Err(VolumeError::bad(
                    path,
                    "header",
                    "not an NRRD file (no magic)",
                ))
            }
            Err(_) => {
                return Err(VolumeError::bad(
                    path,
                    "header",
                    format!(
                        "line {} is not text (is the blank line that ends the header missing?)",
                        lines.len() + 1
                    ),
                ))
            }
        }
    }
}

fn dtype_of(s: &str) -> Result<DType, String> {
    let s = s.split_whitespace().collect::<Vec<_>>().join(" ");
    Ok(match s.to_ascii_lowercase().as_str() {
        "signed char" | "int8" | "int8_t" => DType::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => DType::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            DType::I16
        }
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => DType::U16,
        "int" | "signed int" | "int32" | "int32_t" => DType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => DType::U32,
        "float" => DType::F32,
        "double" => DType::F64,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t"
        | "ulonglong"
        | "unsigned long long"
        | "unsigned long long int"
        | "uint64"
        | "uint64_t" => {
            return Err(format!(
                "type {s}: 64-bit integers are not read (u8, i8, u16, i16, u32, i32, float, \
                 double are): convert with `unu convert -t float` or numpy"
            ))
        }
        "block" => return Err("type block: opaque blocks are not voxel values".into()),
        _ => return Err(format!("type \"{s}\" is not an NRRD type")),
    })
}

/// `(a,b,c)` vectors and `none`s.
fn vectors(v: &str) -> Option<Vec<Option<Vec<f64>>>> {
    let mut out = Vec::new();
    let mut rest = v.trim();
    while !rest.is_empty() {
        if rest
            .get(..4)
            .is_some_and(|w| w.eq_ignore_ascii_case("none"))
        {
            out.push(None);
            rest = rest.get(4..).unwrap_or("").trim_start();
        } else if let Some(r) = rest.strip_prefix('(') {
            let close = r.find(')')?;
            let inner = &r[..close];
            let xs = inner
                .split(',')
                .map(|x| x.trim().parse::<f64>().ok())
                .collect::<Option<Vec<f64>>>()?;
            out.push(Some(xs));
            rest = r[close + 1..].trim_start();
        } else {
            return None;
        }
    }
    Some(out)
}

/// `"a" "b"` quoted strings (`\"` inside one).
fn quoted(v: &str) -> Option<Vec<String>> {
    let mut out = Vec::new();
    let mut chars = v.trim().chars().peekable();
    while let Some(c) = chars.next() {
        if c.is_whitespace() {
            continue;
        }
        if c != '"' {
            return None;
        }
        let mut s = String::new();
        loop {
            match chars.next()? {
                '\\' => s.push(chars.next()?),
                '"' => break,
                c => s.push(c),
            }
        }
        out.push(s);
    }
    Some(out)
}

fn parse_fields(path: &Path, lines: &[String]) -> Result<Fields, VolumeError> {
    let magic = lines.first().map(String::as_str).unwrap_or("");
    let ok_magic =
        magic.len() == 8 && magic.starts_with("NRRD000") && magic.as_bytes()[7].is_ascii_digit();
    if !ok_magic {
        return Err(VolumeError::bad(
            path,
            "header",
            "not an NRRD file: the first line is not NRRD0001 to NRRD0005",
        ));
    }
    let mut f = Fields::default();
    let mut i = 1;
    while i < lines.len() {
        let line = &lines[i];
        i += 1;
        if line.starts_with('#') || line.trim().is_empty() {
            continue;
        }
        let field_at = line.find(": ");
        let key_at = line.find(":=");
        let Some(p) = (match (field_at, key_at) {
            (Some(p), Some(k)) if p < k => Some(p),
            (Some(p), None) => Some(p),
            (_, Some(_)) => None,
            (None, None) => {
                return Err(VolumeError::bad(
                    path,
                    "header",
                    format!(
                        "line {i} (\"{}\") is neither `field: value` nor `key:=value`",
                        line.chars().take(40).collect::<String>()
                    ),
                ))
            }
        }) else {
            continue; // key:=value
        };
        let name: String = line[..p]
            .chars()
            .filter(|c| !c.is_whitespace())
            .collect::<String>()
            .to_ascii_lowercase();
        let section = line[..p].trim().to_string();
        let value = line[p + 2..].trim();
        let bad = |m: String| VolumeError::bad(path, &section, m);
        let show = || value.chars().take(60).collect::<String>();
        let count = |v: &str| v.parse::<usize>().ok();
        match name.as_str() {
            "dimension" => {
                f.dimension =
                    Some(count(value).ok_or_else(|| bad(format!("\"{}\": not a count", show())))?)
            }
            "sizes" => {
                f.sizes = Some(
                    value
                        .split_whitespace()
                        .map(count)
                        .collect::<Option<Vec<_>>>()
                        .ok_or_else(|| bad(format!("\"{}\": not counts", show())))?,
                )
            }
            "type" => {
                f.dtype = Some(dtype_of(value).map_err(|m| match m.contains("not read") {
                    true => VolumeError::unsupported(path, "type", m),
                    false => bad(m),
                })?)
            }
            "encoding" => {
                f.encoding = Some(match value.to_ascii_lowercase().as_str() {
                    "raw" => Encoding::Raw,
                    "gz" | "gzip" => Encoding::Gzip,
                    "txt" | "text" | "ascii" => Encoding::Ascii,
                    "hex" => Encoding::Hex,
                    "bz2" | "bzip2" | "zrl" | "zstd" => {
                        return Err(VolumeError::unsupported(
                            path,
                            "encoding",
                            format!(
                                "{value}: read are raw, gzip, ascii and hex; re-save it with \
                                 `unu save -e gzip` or as raw"
                            ),
                        ))
                    }
                    _ => return Err(bad(format!("\"{}\" is not an NRRD encoding", show()))),
                })
            }
            "endian" => {
                f.endian = Some(match value.to_ascii_lowercase().as_str() {
                    "little" => Endian::Little,
                    "big" => Endian::Big,
                    _ => return Err(bad(format!("\"{}\": give little or big", show()))),
                })
            }
            "spacings" => {
                f.spacings = Some(
                    value
                        .split_whitespace()
                        .map(|x| x.parse::<f64>().ok())
                        .collect::<Option<Vec<_>>>()
                        .ok_or_else(|| bad(format!("\"{}\": not numbers", show())))?,
                )
            }
            "spacedirections" => {
                f.directions = Some(
                    vectors(value)
                        .ok_or_else(|| bad(format!("\"{}\": not (x,y,z) vectors", show())))?,
                )
            }
            "spaceorigin" => {
                let v = vectors(value)
                    .and_then(|v| (v.len() == 1).then(|| v.into_iter().next()).flatten())
                    .flatten()
                    .ok_or_else(|| bad(format!("\"{}\": not one (x,y,z) vector", show())))?;
                f.origin = Some(v);
            }
            "space" => {
                let sp = match value.to_ascii_lowercase().as_str() {
                    "right-anterior-superior" | "ras" => Space::Ras,
                    "left-anterior-superior" | "las" => Space::Las,
                    "left-posterior-superior" | "lps" => Space::Lps,
                    "scanner-xyz" | "3d-right-handed" | "3d-left-handed" => Space::Plain,
                    "right-anterior-superior-time"
                    | "rast"
                    | "left-anterior-superior-time"
                    | "last"
                    | "left-posterior-superior-time"
                    | "lpst"
                    | "scanner-xyz-time"
                    | "3d-right-handed-time"
                    | "3d-left-handed-time" => {
                        return Err(VolumeError::unsupported(
                            path,
                            "space",
                            format!("{value}: a space with time (4D world coordinates)"),
                        ))
                    }
                    _ => return Err(bad(format!("\"{}\" is not an NRRD space", show()))),
                };
                f.space = Some((sp, value.to_string()));
            }
            "spacedimension" => {
                f.space_dimension =
                    Some(count(value).ok_or_else(|| bad(format!("\"{}\": not a count", show())))?)
            }
            "spaceunits" => {
                f.space_units = Some(
                    quoted(value)
                        .ok_or_else(|| bad(format!("\"{}\": not quoted strings", show())))?,
                )
            }
            "units" => f.units = quoted(value),
            "sampleunits" => f.sample_units = quoted(value).and_then(|v| v.into_iter().next()),
            "kinds" => {
                f.kinds = Some(
                    value
                        .split_whitespace()
                        .map(|k| k.to_ascii_lowercase())
                        .collect(),
                )
            }
            "byteskip" => {
                f.byte_skip = value
                    .parse::<i64>()
                    .ok()
                    .filter(|&b| b >= -1)
                    .ok_or_else(|| bad(format!("\"{}\": give -1 or a byte count", show())))?
            }
            "lineskip" => {
                f.line_skip = value
                    .parse::<u64>()
                    .map_err(|_| bad(format!("\"{}\": not a count", show())))?
            }
            "datafile" => {
                let words: Vec<&str> = value.split_whitespace().collect();
                let subdim = |w: Option<&&str>| -> Result<Option<usize>, VolumeError> {
                    w.map(|s| count(s).ok_or_else(|| bad(format!("subdim \"{s}\": not a count"))))
                        .transpose()
                };
                f.data_file = Some(if words.first() == Some(&"LIST") && words.len() <= 2 {
                    let names = lines[i..]
                        .iter()
                        .map(|l| l.trim().to_string())
                        .filter(|l| !l.is_empty())
                        .collect();
                    i = lines.len();
                    DataFile::List {
                        names,
                        subdim: subdim(words.get(1))?,
                    }
                } else if (4..=5).contains(&words.len())
                    && words[0].contains('%')
                    && words[1..4].iter().all(|w| w.parse::<i64>().is_ok())
                {
                    let n = |k: usize| words[k].parse::<i64>().unwrap_or(0);
                    DataFile::Format {
                        format: words[0].to_string(),
                        min: n(1),
                        max: n(2),
                        step: n(3),
                        subdim: subdim(words.get(4))?,
                    }
                } else if value.is_empty() {
                    return Err(bad("no file named".into()));
                } else {
                    DataFile::One(value.to_string())
                });
            }
            _ => {}
        }
    }
    Ok(f)
}

/// `format` (one printf conversion `%d`, `%i` or `%u` with optional `0` flag and width; `%%` a
/// percent sign) applied to `n`.
fn format_name(format: &str, n: i64) -> Option<String> {
    let mut out = String::new();
    let mut chars = format.chars().peekable();
    let mut used = false;
    while let Some(c) = chars.next() {
        if c != '%' {
            out.push(c);
            continue;
        }
        if chars.peek() == Some(&'%') {
            chars.next();
            out.push('%');
            continue;
        }
        let mut zero = false;
        let mut width = 0usize;
        while let Some(&d) = chars.peek() {
            if d == '0' && width == 0 {
                zero = true;
            } else if let Some(x) = d.to_digit(10) {
                width = width.checked_mul(10)?.checked_add(x as usize)?;
                if width > 64 {
                    return None;
                }
            } else {
                break;
            }
            chars.next();
        }
        if !matches!(chars.next(), Some('d' | 'i' | 'u')) || used {
            return None;
        }
        used = true;
        let s = n.unsigned_abs().to_string();
        let sign = if n < 0 { "-" } else { "" };
        let pad = width.saturating_sub(s.len() + sign.len());
        if zero {
            out.push_str(sign);
            out.extend(std::iter::repeat_n('0', pad));
        } else {
            out.extend(std::iter::repeat_n(' ', pad));
            out.push_str(sign);
        }
        out.push_str(&s);
    }
    used.then_some(out)
}

// ---------------------------------------------------------------------------------------------
// The samples

/// The samples of all the data files as one stream (file `k` holding bytes `k · per_file ..`),
/// decoded when the encoding says so.
struct NrrdData {
    files: Vec<PathBuf>,
    /// Where the header ends in an attached file (0 in a data file).
    base: u64,
    line_skip: u64,
    byte_skip: i64,
    per_file: u64,
    encoding: Encoding,
    dtype: DType,
    /// The open file: its index, its decoded stream, where that stream's samples start in it and
    /// where the stream is.
    cur: Option<(usize, Box<dyn SeekRead + Send>, u64, u64)>,
    target: u64,
}

impl NrrdData {
    /// Where the data section of `file` starts, after `line skip` lines from `base`.
    fn after_lines(&self, file: &mut File) -> io::Result<u64> {
        file.seek(SeekFrom::Start(self.base))?;
        if self.line_skip == 0 {
            return Ok(self.base);
        }
        let mut r = BufReader::new(&mut *file);
        let mut at = self.base;
        let mut buf = Vec::new();
        for _ in 0..self.line_skip {
            buf.clear();
            let n = (&mut r).take(1 << 20).read_until(b'\n', &mut buf)?;
            if n == 0 || buf.last() != Some(&b'\n') {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    format!("the file ends before its {} skipped lines", self.line_skip),
                ));
            }
            at += n as u64;
        }
        Ok(at)
    }

    /// File `k`'s decoded samples and where they start in that stream.
    fn open_file(&self, k: usize) -> io::Result<(Box<dyn SeekRead + Send>, u64)> {
        let path = &self.files[k];
        let named = |e: io::Error| io::Error::new(e.kind(), format!("{}: {e}", path.display()));
        let mut file = File::open(path).map_err(named)?;
        let start = self.after_lines(&mut file).map_err(named)?;
        let skip = self.byte_skip.max(0) as u64;
        Ok(match self.encoding {
            Encoding::Raw => {
                let offset = if self.byte_skip == -1 {
                    let len = file.metadata().map_err(named)?.len();
                    len.checked_sub(self.per_file).ok_or_else(|| {
                        io::Error::new(io::ErrorKind::UnexpectedEof, "shorter than its samples")
                    })?
                } else {
                    start.saturating_add(skip)
                };
                (Box::new(file), offset)
            }
            Encoding::Gzip | Encoding::Ascii | Encoding::Hex => {
                let (encoding, dtype, path) = (self.encoding, self.dtype, path.clone());
                // ascii and hex skip bytes of the file; gzip bytes of the decompressed stream
                let (file_at, stream_at) = match encoding {
                    Encoding::Gzip => (start, skip),
                    _ => (start.saturating_add(skip), 0),
                };
                let open: Opener = Box::new(move || {
                    let mut f = File::open(&path)?;
                    f.seek(SeekFrom::Start(file_at))?;
                    let r = BufReader::with_capacity(1 << 16, f);
                    Ok(match encoding {
                        Encoding::Gzip => Box::new(flate2::read::MultiGzDecoder::new(r)),
                        Encoding::Ascii => Box::new(TextValues::new(r, dtype, false)),
                        _ => Box::new(HexBytes { src: r }),
                    })
                });
                (Box::new(Reopen::new(open)), stream_at)
            }
        })
    }
}

impl Read for NrrdData {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.per_file == 0 {
            return Ok(0);
        }
        let k = usize::try_from(self.target / self.per_file).unwrap_or(usize::MAX);
        let local = self.target % self.per_file;
        if k >= self.files.len() {
            return Ok(0);
        }
        if self.cur.as_ref().is_none_or(|c| c.0 != k) {
            self.cur = None;
            let (s, start) = self.open_file(k)?;
            self.cur = Some((k, s, start, u64::MAX));
        }
        let Some((_, s, start, at)) = self.cur.as_mut() else {
            return Ok(0);
        };
        let want = start.saturating_add(local);
        if *at != want {
            s.seek(SeekFrom::Start(want))?;
            *at = want;
        }
        let room = (self.per_file - local).min(buf.len() as u64) as usize;
        let n = s.read(&mut buf[..room])?;
        *at += n as u64;
        self.target += n as u64;
        Ok(n)
    }
}

impl Seek for NrrdData {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        match to {
            SeekFrom::Start(n) => self.target = n,
            _ => return Err(io::Error::from(io::ErrorKind::Unsupported)),
        }
        Ok(self.target)
    }
}

// ---------------------------------------------------------------------------------------------
// The reader

/// What the fourth axis is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    Space,
    Components,
    Frames,
}

fn kind_role(kind: &str) -> Result<Option<Role>, String> {
    Ok(Some(match kind {
        "domain" | "space" => Role::Space,
        "time" | "list" => Role::Frames,
        "???" | "none" => return Ok(None),
        "stub"
        | "scalar"
        | "complex"
        | "2-vector"
        | "3-color"
        | "rgb-color"
        | "hsv-color"
        | "xyz-color"
        | "4-color"
        | "rgba-color"
        | "3-vector"
        | "3-gradient"
        | "3-normal"
        | "4-vector"
        | "quaternion"
        | "2d-symmetric-matrix"
        | "2d-masked-symmetric-matrix"
        | "2d-matrix"
        | "2d-masked-matrix"
        | "3d-symmetric-matrix"
        | "3d-masked-symmetric-matrix"
        | "3d-matrix"
        | "3d-masked-matrix"
        | "point"
        | "vector"
        | "covariant-vector"
        | "normal" => Role::Components,
        _ => return Err(format!("\"{kind}\" is not an NRRD kind")),
    }))
}

struct NrrdReader {
    /// The data file when there is one, else the header (errors name it).
    path: PathBuf,
    header: FileHeader,
    layout: Layout,
    /// Interleaved values a voxel and which of them (`None`: their magnitude).
    components: usize,
    which: Option<usize>,
    data: NrrdData,
}

impl NrrdReader {
    fn open(path: &Path, options: &VolumeOptions) -> Result<Self, VolumeError> {
        let (lines, data_start) = read_header(path)?;
        let f = parse_fields(path, &lines)?;
        let bad = |section: &str, m: String| VolumeError::bad(path, section, m);
        let missing = |field: &str| bad(field, "missing (a required field)".into());
        let dim = f.dimension.ok_or_else(|| missing("dimension"))?;
        if !(3..=4).contains(&dim) {
            return Err(VolumeError::unsupported(
                path,
                "dimension",
                format!("{dim}: read are 3D volumes and 4D ones with components or frames"),
            ));
        }
        let sizes = f.sizes.clone().ok_or_else(|| missing("sizes"))?;
        let per_axis = |name: &str, n: usize| -> Result<(), VolumeError> {
            if n != dim {
                return Err(bad(
                    name,
                    format!("{n} values for a dimension of {dim}: one an axis"),
                ));
            }
            Ok(())
        };
        per_axis("sizes", sizes.len())?;
        if sizes.contains(&0) {
            return Err(bad("sizes", format!("{sizes:?}: an axis of no samples")));
        }
        let dtype = f.dtype.ok_or_else(|| missing("type"))?;
        let encoding = f.encoding.ok_or_else(|| missing("encoding"))?;
        let endian = match (f.endian, encoding, dtype.bytes()) {
            (_, Encoding::Ascii, _) => Endian::Little,
            (Some(e), _, _) => e,
            (None, _, 1) => Endian::Little,
            (None, _, n) => {
                return Err(bad(
                    "endian",
                    format!("missing, needed for {n}-byte samples"),
                ))
            }
        };
        if f.byte_skip == -1 && encoding != Encoding::Raw {
            return Err(bad(
                "byte skip",
                "-1 (the samples end the file) is defined for raw encoding only".into(),
            ));
        }
        for (name, n) in [
            ("spacings", f.spacings.as_ref().map(Vec::len)),
            ("space directions", f.directions.as_ref().map(Vec::len)),
            ("kinds", f.kinds.as_ref().map(Vec::len)),
        ] {
            if let Some(n) = n {
                per_axis(name, n)?;
            }
        }
        let space_dim = match (f.space_dimension, &f.space) {
            (Some(n), _) => Some(n),
            (None, Some(_)) => Some(3),
            (None, None) => None,
        };
        if let Some(n) = space_dim.filter(|&n| n != 3) {
            return Err(VolumeError::unsupported(
                path,
                "space dimension",
                format!("{n}: world coordinates of 3 dimensions are read"),
            ));
        }

        // the axes' roles
        let mut roles: Vec<Option<Role>> = vec![None; dim];
        if let Some(kinds) = &f.kinds {
            for (a, k) in kinds.iter().enumerate() {
                roles[a] = kind_role(k).map_err(|m| bad("kinds", m))?;
            }
        }
        let mut odd: Vec<usize> = (0..dim)
            .filter(|&a| matches!(roles[a], Some(Role::Components | Role::Frames)))
            .collect();
        if odd.is_empty() && dim == 4 {
            if let Some(d) = &f.directions {
                odd = (0..dim)
                    .filter(|&a| d[a].is_none() && roles[a] != Some(Role::Space))
                    .collect();
            }
        }
        let nonspatial = match (dim, odd.as_slice()) {
            (3, []) => None,
            (3, _) => {
                return Err(VolumeError::unsupported(
                    path,
                    "kinds",
                    format!(
                        "{:?}: fewer than 3 spatial axes (an image, not a volume)",
                        f.kinds.clone().unwrap_or_default()
                    ),
                ))
            }
            (_, [a]) if *a == 0 || *a == 3 => {
                let role = roles[*a].unwrap_or(if *a == 0 {
                    Role::Components
                } else {
                    Role::Frames
                });
                Some((*a, role))
            }
            (_, [a]) => {
                return Err(VolumeError::unsupported(
                    path,
                    "kinds",
                    format!("the non-spatial axis is axis {a}: read are the first and the last"),
                ))
            }
            (_, []) => {
                return Err(VolumeError::unsupported(
                    path,
                    "kinds",
                    "4 axes and neither `kinds` nor `space directions` says which is not \
                     spatial: add e.g. `kinds: vector domain domain domain` or `kinds: domain \
                     domain domain time`",
                ))
            }
            (_, many) => {
                return Err(VolumeError::unsupported(
                    path,
                    "kinds",
                    format!("axes {many:?} are all non-spatial: one of 4 may be"),
                ))
            }
        };
        let spatial: [usize; 3] = match nonspatial {
            Some((0, _)) => [1, 2, 3],
            _ => [0, 1, 2],
        };
        let dims = spatial.map(|a| sizes[a]);

        // geometry
        let (mut frame, negate_x) = match f.space.as_ref().map(|s| s.0) {
            Some(Space::Ras) => (Some("RAS"), false),
            Some(Space::Las) => (Some("RAS"), true),
            Some(Space::Lps) => (Some("LPS"), false),
            _ => (None, false),
        };
        let mut notes = Vec::new();
        let origin3 = |v: &Vec<f64>| -> Result<[f64; 3], VolumeError> {
            <[f64; 3]>::try_from(v.as_slice()).map_err(|_| {
                bad(
                    "space origin",
                    format!("{} coordinates in a 3D space", v.len()),
                )
            })
        };
        let mut origin = match &f.origin {
            Some(v) => origin3(v)?,
            None => [0.0; 3],
        };
        let (axes, spacing) = if let Some(d) = &f.directions {
            let mut steps = [[0.0; 3]; 3];
            for (s, &a) in spatial.iter().enumerate() {
                let v = d[a].as_ref().ok_or_else(|| {
                    bad(
                        "space directions",
                        format!("spatial axis {a} has the direction `none`"),
                    )
                })?;
                steps[s] = <[f64; 3]>::try_from(v.as_slice()).map_err(|_| {
                    bad(
                        "space directions",
                        format!("axis {a}: {} coordinates in a 3D space", v.len()),
                    )
                })?;
            }
            if negate_x {
                for s in &mut steps {
                    s[0] = -s[0];
                }
            }
            axis_aligned(steps).map_err(|e| match e {
                NotAligned::Bad(m) => bad("space directions", m),
                NotAligned::Oblique(m) => VolumeError::unsupported(path, "space directions", m),
            })?
        } else {
            if f.space.is_some() {
                notes.push("a space without space directions: its name is not used".into());
                frame = None;
            }
            let mut axes = [0, 1, 2].map(|axis| AxisMap { axis, flip: false });
            let mut spacing = [1.0; 3];
            let mut unstated = false;
            for (s, &a) in spatial.iter().enumerate() {
                match f.spacings.as_ref().map(|v| v[a]) {
                    Some(x) if x.is_finite() && x != 0.0 => {
                        spacing[s] = x.abs();
                        axes[s].flip = x < 0.0;
                    }
                    _ => unstated = true,
                }
            }
            if unstated {
                notes.push("no spacing stated along some axes: 1 there".into());
            }
            (axes, spacing)
        };
        if negate_x {
            origin[0] = -origin[0];
            notes.push("left-anterior-superior space read as RAS (x negated)".into());
        }
        let unit = |units: &Option<Vec<String>>, pick: &dyn Fn(&Vec<String>) -> Vec<String>| {
            units.as_ref().and_then(|u| {
                let u = pick(u);
                (!u.is_empty() && !u[0].is_empty() && u.iter().all(|x| x == &u[0]))
                    .then(|| u[0].clone())
            })
        };
        let length_unit = unit(&f.space_units, &|u| u.clone()).or_else(|| {
            unit(&f.units, &|u| {
                if u.len() == dim {
                    spatial.iter().map(|&a| u[a].clone()).collect()
                } else {
                    Vec::new()
                }
            })
        });

        // the data files
        let total = sizes
            .iter()
            .try_fold(dtype.bytes() as u64, |a, &d| a.checked_mul(d as u64))
            .filter(|&b| b <= isize::MAX as u64)
            .ok_or_else(|| {
                bad(
                    "sizes",
                    format!("{sizes:?}: more samples than can be indexed"),
                )
            })?;
        let dir = path.parent().unwrap_or(Path::new(""));
        let resolve = |name: &str| {
            let p = Path::new(name);
            if p.is_absolute() {
                p.to_path_buf()
            } else {
                dir.join(p)
            }
        };
        let files_for = |subdim: Option<usize>| -> Result<usize, VolumeError> {
            let sub = subdim.unwrap_or(dim - 1);
            if !(1..=dim).contains(&sub) {
                return Err(bad("data file", format!("subdim {sub}: give 1 to {dim}")));
            }
            Ok(sizes[sub..].iter().product())
        };
        let (files, base) = match &f.data_file {
            None => {
                let at = data_start.ok_or_else(|| {
                    bad(
                        "header",
                        "no blank line ends the header and no `data file` names the samples".into(),
                    )
                })?;
                (vec![path.to_path_buf()], at)
            }
            Some(DataFile::One(name)) => (vec![resolve(name)], 0),
            Some(DataFile::List { names, subdim }) => {
                let n = files_for(*subdim)?;
                if names.len() != n {
                    return Err(bad(
                        "data file",
                        format!("LIST names {} files; the sizes need {n}", names.len()),
                    ));
                }
                (names.iter().map(|s| resolve(s)).collect(), 0)
            }
            Some(DataFile::Format {
                format,
                min,
                max,
                step,
                subdim,
            }) => {
                let n = files_for(*subdim)?;
                let span = max.checked_sub(*min);
                let count = match span {
                    Some(s) if *step != 0 && s % step == 0 && s / step >= 0 => {
                        (s / step).checked_add(1)
                    }
                    _ => None,
                };
                if count != Some(n as i64) {
                    return Err(bad(
                        "data file",
                        format!(
                            "{min} to {max} by {step} does not give the {n} files the sizes need"
                        ),
                    ));
                }
                let mut files = Vec::with_capacity(n);
                for k in 0..n as i64 {
                    let name = format_name(format, min + k * step).ok_or_else(|| {
                        bad(
                            "data file",
                            format!("\"{format}\": give one %d (or %0Nd) conversion"),
                        )
                    })?;
                    files.push(resolve(&name));
                }
                (files, 0)
            }
        };
        let per_file = total / files.len() as u64;
        for p in &files {
            let meta = std::fs::metadata(p).map_err(VolumeError::io(p))?;
            if encoding == Encoding::Raw {
                let need = if f.byte_skip == -1 {
                    per_file
                } else {
                    base.saturating_add(f.byte_skip as u64)
                        .saturating_add(per_file)
                };
                if meta.len() < need {
                    return Err(VolumeError::bad(
                        p,
                        "data",
                        format!(
                            "truncated: {} bytes; the header's sizes {sizes:?} of {dtype} need \
                             {need}",
                            meta.len()
                        ),
                    ));
                }
            }
        }

        // the component and the frame
        let (components, which, offset, out_dtype) = match nonspatial {
            None => (1, Some(0), 0, dtype),
            Some((a, role)) => {
                let n = sizes[a];
                let vol_bytes = total / n as u64;
                if role == Role::Frames {
                    let t = match options.frame {
                        Some(t) if t < n => t,
                        Some(t) => {
                            return Err(VolumeError::usage(
                                path,
                                format!(
                                    "--frame {t}: the volume has {n} frame(s) (0 to {})",
                                    n - 1
                                ),
                            ))
                        }
                        None if n == 1 => 0,
                        None => {
                            return Err(VolumeError::usage(
                                path,
                                format!(
                                    "{n} frames (axis {a} of kind {}): choose one with --frame T \
                                     (0 to {})",
                                    f.kinds.as_ref().map_or("none", |k| k[a].as_str()),
                                    n - 1
                                ),
                            ))
                        }
                    };
                    if n > 1 {
                        notes.push(format!("frame {t} of {n}"));
                    }
                    match a {
                        0 => (n, Some(t), 0, dtype),
                        _ => (1, Some(0), t as u64 * vol_bytes, dtype),
                    }
                } else {
                    let names: Vec<String> = match f.kinds.as_ref().map(|k| k[a].as_str()) {
                        Some("rgb-color") if n == 3 => ["r", "g", "b"].map(String::from).to_vec(),
                        Some("rgba-color") if n == 4 => {
                            ["r", "g", "b", "a"].map(String::from).to_vec()
                        }
                        Some("hsv-color") if n == 3 => ["h", "s", "v"].map(String::from).to_vec(),
                        _ => Vec::new(),
                    };
                    let which = choose_component(options.scalar.as_ref(), n, &names)
                        .map_err(|m| VolumeError::usage(path, m))?;
                    if n > 1 {
                        notes.push(match which {
                            Some(k) => format!("component {k} of {n}"),
                            None => format!("magnitude of {n} components"),
                        });
                    }
                    let mag_dtype = if dtype == DType::F64 {
                        DType::F64
                    } else {
                        DType::F32
                    };
                    match (a, which) {
                        (0, None) if n > 1 => (n, None, 0, mag_dtype),
                        (0, w) => (n, w, 0, dtype),
                        (_, Some(k)) => (1, Some(0), k as u64 * vol_bytes, dtype),
                        (_, None) => {
                            return Err(VolumeError::unsupported(
                                path,
                                "kinds",
                                "--scalar mag of components stored one volume each (the last \
                                 axis): choose one with --scalar K",
                            ))
                        }
                    }
                }
            }
        };

        let mut header = FileHeader::new(VolumeFormat::Nrrd, dims, out_dtype, spacing);
        header.axes = axes;
        header.origin = origin;
        header.frame = frame.map(String::from);
        header.length_unit = length_unit;
        header.value_unit = f.sample_units.clone().filter(|s| !s.is_empty());
        header.notes = notes;
        header.check(path)?;
        let err_path = if files.len() == 1 {
            files[0].clone()
        } else {
            path.to_path_buf()
        };
        Ok(NrrdReader {
            path: err_path,
            header,
            layout: Layout {
                offset,
                dims,
                components,
                dtype,
                endian,
            },
            components,
            which,
            data: NrrdData {
                files,
                base,
                line_skip: f.line_skip,
                byte_skip: f.byte_skip,
                per_file,
                encoding,
                dtype,
                cur: None,
                target: 0,
            },
        })
    }
}

impl VolumeReader for NrrdReader {
    fn header(&self) -> &FileHeader {
        &self.header
    }
    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
        super::check_box(&self.path, lo, hi, self.layout.dims)?;
        let s = read_box(
            &self.path,
            &mut ByteSource::Seek(&mut self.data),
            &self.layout,
            lo,
            hi,
        )?;
        Ok(select(s, self.components, self.which))
    }
}

#[cfg(test)]
#[path = "nrrd_tests.rs"]
mod tests;
