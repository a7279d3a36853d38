//! DICOM volumes: a folder of one series' slice files, or one multi-frame file (an enhanced CT
//! or MR, an RT dose grid), read with dicom-rs (`dicom-object` for the headers,
//! `dicom-pixeldata` for compressed frames).
//!
//! What is read: the files of the folder whose content starts with the `DICM` prefix at byte 128
//! (any names, extensionless ones included; a `DICOMDIR`, files that are not DICOM and DICOM
//! files that hold no image are skipped with a note). The files are grouped by
//! SeriesInstanceUID; a folder of several series is refused with their list (UID, description,
//! modality, slice count), since which one is meant is the user's choice. A single-frame file on
//! its own is a 2D slice and is refused as not a volume.
//!
//! Geometry, in the patient frame `LPS` (mm): the slices (the frames of every file) are sorted
//! by ImagePositionPatient projected on the slice normal, the cross product of
//! ImageOrientationPatient's row and column cosines; the spacing between slices comes from those
//! positions, and is refused where it is uneven by more than 1 % (a series with gaps, naming the
//! two slices) or where two slices share a position. Without positions the slices are ordered by
//! InstanceNumber (then file name) with a note, and spaced by SpacingBetweenSlices or
//! SliceThickness. In-plane spacing is PixelSpacing, whose first value is the distance between
//! rows (along the file's y) and the second between columns (along x). The file axes are: x the
//! row direction, y the column direction, z the normal in sorted order; each must lie along a
//! patient axis within 1e-4 (flips allowed), since the volume is put on the world grid without
//! resampling: an oblique orientation, or slice positions that shift within the plane (a tilted
//! gantry), are refused. Multi-frame files give each frame's position from the per-frame
//! functional groups (PlanePositionSequence) or, for RT dose, from GridFrameOffsetVector; frames
//! without positions are refused unless SpacingBetweenSlices states their spacing.
//!
//! Values: BitsAllocated 8/16/32 with PixelRepresentation give u8/i8/u16/i16/u32/i32; the bits
//! above HighBit and below its BitsStored are masked off and signed values are sign-extended, as
//! neither the files nor the decoders promise clean high bits. RescaleSlope/Intercept (or RT
//! dose's DoseGridScaling) become the header's rescale when every slice has the same; where they
//! differ, `read_box` applies each slice's and returns f32. `HU` is the value unit of CT (when
//! RescaleType is absent or HU). Colour images (RGB, or YBR decoded from JPEG) need `--scalar`.
//! Every slice must agree on rows, columns, bits, pixel representation, samples per pixel,
//! orientation and pixel spacing.
//!
//! Out of core: `open` walks each file's structure once, up to its pixel data and through the
//! item headers of compressed frames, without reading values (every length is checked against
//! the bytes the file has, before dicom-object parses the attributes and allocates for them),
//! and keeps where each frame is. `read_box` reads only the slices the box spans: uncompressed
//! rows by seeking, a compressed frame (RLE, JPEG baseline, 8-bit extended and lossless, with
//! the pure-Rust decoders) by reading that frame's fragments and decoding them alone.
//! Transfer syntaxes without a decoder here (JPEG 2000, JPEG-LS, JPEG XL, HTJ2K, MPEG; 12-bit
//! JPEG and 32-bit RLE) are refused at open, naming the file and the syntax. A deflated data set
//! cannot be seeked, so such a file is decoded whole (as are 8-bit samples in big-endian words).

use super::raw::{read_box as read_raw_box, ByteSource, Layout};
use super::samples::{choose_component, select};
use super::{
    natural_cmp, slice_files, AxisMap, DType, Endian, FileHeader, Samples, VolumeError,
    VolumeFormat, VolumeOptions, VolumeReader,
};
use dicom_core::value::{PixelFragmentSequence, Value};
use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_encoding::transfer_syntax::{Endianness, TransferSyntax, TransferSyntaxIndex};
use dicom_encoding::Codec;
use dicom_object::mem::InMemElement;
use dicom_object::{FileMetaTableBuilder, InMemDicomObject, OpenFileOptions};
use dicom_parser::dataset::lazy_read::LazyDataSetReader;
use dicom_parser::dataset::LazyDataToken;
use dicom_parser::StatefulDecode;
use dicom_pixeldata::PixelDecoder;
use dicom_transfer_syntax_registry::TransferSyntaxRegistry;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::ops::Range;
use std::path::{Path, PathBuf};

/// Reading a file's attributes stops at the pixel data group (Pixel Data, Float Pixel Data and
/// their offset tables).
const PIXEL_GROUP: Tag = Tag(0x7FE0, 0x0000);
/// How far from ±1 and 0 a direction cosine may be and still be taken as axis-aligned; also the
/// tolerance between slices' orientations.
const AXIS_TOLERANCE: f64 = 1e-4;
/// Relative unevenness of the slice spacing beyond which a series is taken to have gaps.
const SPACING_TOLERANCE: f64 = 0.01;
/// Distance (mm) along the normal under which two slices are at the same position.
const SAME_POSITION: f64 = 1e-3;

/// Byte order of samples that dicom-rs has decoded (native).
const NATIVE: Endian = if cfg!(target_endian = "big") {
    Endian::Big
} else {
    Endian::Little
};

/// What every slice of a volume shares: the layout of its pixels.
#[derive(Debug, Clone, PartialEq)]
struct Pixels {
    rows: usize,
    cols: usize,
    samples_per_pixel: usize,
    bits_allocated: u16,
    bits_stored: u16,
    high_bit: u16,
    signed: bool,
    photometric: String,
    /// PlanarConfiguration 1: a frame's colour planes one after another (uncompressed data).
    planar: bool,
}

impl Pixels {
    fn dtype(&self) -> DType {
        match (self.bits_allocated, self.signed) {
            (8, false) => DType::U8,
            (8, true) => DType::I8,
            (16, false) => DType::U16,
            (16, true) => DType::I16,
            (32, false) => DType::U32,
            _ => DType::I32,
        }
    }
    fn frame_samples(&self) -> usize {
        self.rows * self.cols * self.samples_per_pixel
    }
    fn frame_bytes(&self) -> u64 {
        (self.frame_samples() * self.dtype().bytes()) as u64
    }
}

/// Where a frame is in the world, and how its values scale.
#[derive(Debug, Clone)]
struct FrameGeometry {
    position: Option<[f64; 3]>,
    orientation: Option<[f64; 6]>,
    /// PixelSpacing: between rows, between columns.
    pixel_spacing: Option<[f64; 2]>,
    rescale: (f64, f64),
    rescale_type: Option<String>,
}

/// One file's header: what the volume needs of it.
struct Member {
    path: PathBuf,
    ts: &'static TransferSyntax,
    series_uid: String,
    series_description: String,
    modality: String,
    instance: Option<i64>,
    pixels: Pixels,
    frames: Vec<FrameGeometry>,
    /// Multi-frame files only: SpacingBetweenSlices, for frames without positions.
    spacing_between_slices: Option<f64>,
    slice_thickness: Option<f64>,
    dose_units: Option<String>,
    /// Where each frame is.
    location: PixelLocation,
}

/// Where a file's frames are.
#[derive(Debug, Clone)]
enum PixelLocation {
    /// Uncompressed frames one after another from byte `offset`.
    Native { offset: u64, endian: Endian },
    /// Compressed frames: each frame's fragments (byte offset and length of each).
    Fragments(Vec<Vec<(u64, u32)>>),
    /// A deflated data set, or 8-bit samples in big-endian words: the file is decoded whole.
    Whole,
}

/// One slice of the volume: a frame of a file.
#[derive(Debug, Clone)]
struct Slice {
    member: usize,
    frame: usize,
}

pub(crate) struct DicomReader {
    path: PathBuf,
    header: FileHeader,
    members: Vec<Member>,
    /// The slices in file-z order.
    slices: Vec<Slice>,
    pixels: Pixels,
    /// The component read (`None`: the magnitude).
    which: Option<usize>,
    /// Each slice's rescale, applied by `read_box` (the slices disagree on it).
    per_slice_rescale: Option<Vec<(f64, f64)>>,
}

pub(crate) fn open(
    path: &Path,
    options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    Ok(Box::new(DicomReader::open(path, options)?))
}

/// Whether the file starts with a DICOM preamble and `DICM`.
fn has_dicm(path: &Path) -> Result<bool, VolumeError> {
    let mut head = [0u8; 132];
    let mut f = File::open(path).map_err(VolumeError::io(path))?;
    let mut n = 0;
    while n < head.len() {
        match f.read(&mut head[n..]).map_err(VolumeError::io(path))? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n == 132 && &head[128..132] == b"DICM")
}

/// An error and its sources, one after the other (dicom-rs's errors say what failed, their
/// sources why).
fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut source = e.source();
    while let Some(c) = source {
        let m = c.to_string();
        if !s.ends_with(&m) {
            s.push_str(": ");
            s.push_str(&m);
        }
        source = c.source();
    }
    s
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

/// A few names of a list, for notes and errors.
fn some_names(names: &[String]) -> String {
    let mut s = names.iter().take(5).cloned().collect::<Vec<_>>().join(", ");
    if names.len() > 5 {
        s.push_str(&format!(" and {} more", names.len() - 5));
    }
    s
}

// ---- attribute access ----

/// The text of a value written with VR UN (an explicit-VR file whose writer did not know the
/// attribute): its bytes when they are printable (decimal and integer strings, codes, UIDs).
fn un_text(e: &InMemElement) -> Option<String> {
    if e.vr() != VR::UN {
        return None;
    }
    let bytes = e.to_bytes().ok()?;
    bytes
        .iter()
        .all(|&b| b.is_ascii_graphic() || b == b' ' || b == 0)
        .then(|| String::from_utf8_lossy(&bytes).into_owned())
}

fn text(e: Option<&InMemElement>) -> Option<String> {
    let e = e?;
    let s = match un_text(e) {
        Some(s) => s,
        None => e.to_str().ok()?.into_owned(),
    };
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!s.is_empty()).then(|| s.to_string())
}

/// The values of a text attribute written as UN, parsed.
fn un_values<T: std::str::FromStr>(
    path: &Path,
    e: &InMemElement,
    name: &str,
) -> Option<Result<Vec<T>, VolumeError>> {
    let s = un_text(e)?;
    Some(
        s.trim_matches(|c: char| c.is_whitespace() || c == '\0')
            .split('\\')
            .map(|v| {
                v.trim()
                    .parse::<T>()
                    .map_err(|_| VolumeError::bad(path, name, format!("{s:?}: not numbers")))
            })
            .collect(),
    )
}

/// The numbers of a decimal or binary attribute (`None` when absent or empty); `n` values when
/// `n > 0`, all finite.
fn floats(
    path: &Path,
    e: Option<&InMemElement>,
    name: &str,
    n: usize,
) -> Result<Option<Vec<f64>>, VolumeError> {
    let Some(e) = e else { return Ok(None) };
    if text(Some(e)).is_none() {
        return Ok(None);
    }
    let v = match un_values::<f64>(path, e, name) {
        Some(v) => v?,
        None => e
            .to_multi_float64()
            .map_err(|err| VolumeError::bad(path, name, format!("not numbers: {err}")))?,
    };
    if v.is_empty() {
        return Ok(None);
    }
    if n > 0 && v.len() != n {
        return Err(VolumeError::bad(
            path,
            name,
            format!("{} values ({v:?}): {n} expected", v.len()),
        ));
    }
    if v.iter().any(|x| !x.is_finite()) {
        return Err(VolumeError::bad(
            path,
            name,
            format!("{v:?}: values must be finite"),
        ));
    }
    Ok(Some(v))
}

fn float(path: &Path, e: Option<&InMemElement>, name: &str) -> Result<Option<f64>, VolumeError> {
    Ok(floats(path, e, name, 0)?.map(|v| v[0]))
}

/// An integer attribute (`None` when absent or empty).
fn int(path: &Path, e: Option<&InMemElement>, name: &str) -> Result<Option<i64>, VolumeError> {
    let Some(e) = e else { return Ok(None) };
    if text(Some(e)).is_none() {
        return Ok(None);
    }
    if let Some(v) = un_values::<i64>(path, e, name) {
        return Ok(v?.first().copied());
    }
    e.to_int::<i64>()
        .map(Some)
        .map_err(|err| VolumeError::bad(path, name, format!("not an integer: {err}")))
}

fn required_uint(
    path: &Path,
    o: &InMemDicomObject,
    tag: Tag,
    name: &str,
    range: Range<i64>,
) -> Result<i64, VolumeError> {
    let v = int(path, o.get(tag), name)?
        .ok_or_else(|| VolumeError::bad(path, name, "missing: an image needs it"))?;
    if !range.contains(&v) {
        return Err(VolumeError::bad(
            path,
            name,
            format!("{v}: out of range ({}..{})", range.start, range.end),
        ));
    }
    Ok(v)
}

/// The functional groups of a multi-frame file: an attribute of a frame is looked up in its
/// per-frame group, then in the shared group, then at the top level.
struct Groups<'a> {
    top: &'a InMemDicomObject,
    shared: Option<&'a InMemDicomObject>,
    per_frame: Option<&'a [InMemDicomObject]>,
}

impl<'a> Groups<'a> {
    fn get(&self, frame: usize, sequence: Tag, attr: Tag) -> Option<&'a InMemElement> {
        let within = |o: &'a InMemDicomObject| o.get(sequence)?.items()?.first()?.get(attr);
        self.per_frame
            .and_then(|p| p.get(frame))
            .and_then(within)
            .or_else(|| self.shared.and_then(within))
            .or_else(|| self.top.get(attr))
    }
}

/// Reads a file's attributes (up to its pixel data). `Ok(None)`: a DICOM file without an image
/// (a DICOMDIR, a report, a structure set), which a folder skips.
fn read_member(path: &Path) -> Result<Option<Member>, VolumeError> {
    if !has_dicm(path)? {
        return Err(VolumeError::unsupported(
            path,
            "preamble",
            "no DICM prefix at byte 128: files without the DICOM preamble (or not DICOM) are \
             not read",
        ));
    }
    let found = scan(path)?;
    if found.sop_class == uids::MEDIA_STORAGE_DIRECTORY_STORAGE {
        return Ok(None);
    }
    let ts = found.ts.ok_or_else(|| {
        VolumeError::unsupported(
            path,
            "transfer syntax",
            format!("{}: an unknown transfer syntax", found.ts_uid),
        )
    })?;
    let obj = OpenFileOptions::new()
        .read_until(PIXEL_GROUP)
        .open_file(path)
        .map_err(|e| VolumeError::bad(path, "header", format!("cannot parse: {}", chain(&e))))?;
    let o: &InMemDicomObject = &obj;
    if o.get(tags::ROWS).is_none() || o.get(tags::COLUMNS).is_none() {
        return Ok(None);
    }
    if !ts.can_decode_all() {
        return Err(VolumeError::unsupported(
            path,
            "transfer syntax",
            format!(
                "{} ({}): no decoder for it here (read are uncompressed, deflated, RLE and \
                 JPEG baseline, 8-bit extended and lossless); convert the series first, e.g. \
                 with `gdcmconv --raw` or `dcmdjp2k`/`dcmdjpls`",
                ts.name(),
                ts.uid()
            ),
        ));
    }
    let rows = required_uint(path, o, tags::ROWS, "Rows", 1..65536)? as usize;
    let cols = required_uint(path, o, tags::COLUMNS, "Columns", 1..65536)? as usize;
    let samples_per_pixel =
        int(path, o.get(tags::SAMPLES_PER_PIXEL), "SamplesPerPixel")?.unwrap_or(1);
    let bits_allocated =
        required_uint(path, o, tags::BITS_ALLOCATED, "BitsAllocated", 1..65536)? as u16;
    let bits_stored =
        int(path, o.get(tags::BITS_STORED), "BitsStored")?.unwrap_or(bits_allocated as i64);
    let high_bit =
        int(path, o.get(tags::HIGH_BIT), "HighBit")?.unwrap_or(bits_stored.saturating_sub(1));
    let signed = match int(
        path,
        o.get(tags::PIXEL_REPRESENTATION),
        "PixelRepresentation",
    )? {
        None | Some(0) => false,
        Some(1) => true,
        Some(v) => {
            return Err(VolumeError::bad(
                path,
                "PixelRepresentation",
                format!("{v}: 0 (unsigned) or 1 (signed)"),
            ))
        }
    };
    if !matches!(bits_allocated, 8 | 16 | 32) {
        return Err(VolumeError::unsupported(
            path,
            "BitsAllocated",
            format!(
                "{bits_allocated} bits a sample: read are 8, 16 and 32 (1-bit segmentations \
                 are not volumes of values)"
            ),
        ));
    }
    if !(1..=bits_allocated as i64).contains(&bits_stored)
        || !(bits_stored - 1..bits_allocated as i64).contains(&high_bit)
    {
        return Err(VolumeError::bad(
            path,
            "BitsStored",
            format!(
                "BitsStored {bits_stored}, HighBit {high_bit} do not fit in BitsAllocated \
                 {bits_allocated}"
            ),
        ));
    }
    // what the pure-Rust decoders do not read
    let limit = match ts.uid() {
        "1.2.840.10008.1.2.4.51" if bits_stored > 8 => Some("12-bit JPEG (extended, process 4)"),
        uids::RLE_LOSSLESS if bits_allocated > 16 => Some("32-bit RLE"),
        u if u.starts_with("1.2.840.10008.1.2.4.") && bits_allocated > 16 => Some("32-bit JPEG"),
        _ => None,
    };
    if let Some(what) = limit {
        return Err(VolumeError::unsupported(
            path,
            "transfer syntax",
            format!(
                "{what} ({}, {}) is not decoded here; convert the series to uncompressed \
                 first, e.g. with `gdcmconv --raw` or `dcmdjpeg`/`dcmdrle`",
                ts.name(),
                ts.uid()
            ),
        ));
    }
    let photometric = text(o.get(tags::PHOTOMETRIC_INTERPRETATION))
        .unwrap_or_else(|| "MONOCHROME2".into())
        .to_ascii_uppercase();
    let jpeg = ts.uid().starts_with("1.2.840.10008.1.2.4.")
        && matches!(ts.codec(), Codec::EncapsulatedPixelData(..));
    match (samples_per_pixel, photometric.as_str()) {
        (1, "MONOCHROME1" | "MONOCHROME2" | "PALETTE COLOR") => {}
        (3, "RGB") => {}
        (3, p) if p.starts_with("YBR") && jpeg => {}
        (spp, p) => {
            return Err(VolumeError::unsupported(
                path,
                "PhotometricInterpretation",
                format!(
                    "{p} with {spp} samples a pixel: read are grey images (MONOCHROME1/2, \
                     palette indices), RGB, and YBR in JPEG"
                ),
            ))
        }
    }
    let planar = samples_per_pixel > 1
        && !ts.is_encapsulated_pixel_data()
        && int(
            path,
            o.get(tags::PLANAR_CONFIGURATION),
            "PlanarConfiguration",
        )? == Some(1);
    let pixels = Pixels {
        rows,
        cols,
        samples_per_pixel: samples_per_pixel as usize,
        bits_allocated,
        bits_stored: bits_stored as u16,
        high_bit: high_bit as u16,
        signed,
        photometric,
        planar,
    };
    let n_frames = match int(path, o.get(tags::NUMBER_OF_FRAMES), "NumberOfFrames")? {
        None => 1,
        Some(n) if (1..=(1 << 24)).contains(&n) => n as usize,
        Some(n) => {
            return Err(VolumeError::bad(
                path,
                "NumberOfFrames",
                format!("{n}: must be 1 to 2^24"),
            ))
        }
    };
    // each frame takes at least its item header (8 bytes) or its uncompressed bytes
    let file_len = std::fs::metadata(path)
        .map_err(VolumeError::io(path))?
        .len();
    if (n_frames as u64).saturating_mul(pixels.frame_bytes().min(8)) > file_len {
        return Err(VolumeError::bad(
            path,
            "NumberOfFrames",
            format!("{n_frames} frames cannot fit in the file's {file_len} bytes"),
        ));
    }
    let endian = match ts.endianness() {
        Endianness::Little => Endian::Little,
        Endianness::Big => Endian::Big,
    };
    let modality = text(o.get(tags::MODALITY)).unwrap_or_default();
    let items = |tag: Tag| o.get(tag).and_then(|e| e.items());
    let per_frame = items(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE);
    if let Some(p) = per_frame {
        if p.len() != n_frames {
            return Err(VolumeError::bad(
                path,
                "PerFrameFunctionalGroupsSequence",
                format!("{} items for {n_frames} frames", p.len()),
            ));
        }
    }
    let groups = Groups {
        top: o,
        shared: items(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE).and_then(|s| s.first()),
        per_frame,
    };
    let grid_offsets = floats(
        path,
        o.get(tags::GRID_FRAME_OFFSET_VECTOR),
        "GridFrameOffsetVector",
        0,
    )?;
    if let Some(g) = &grid_offsets {
        if n_frames > 1 && g.len() != n_frames {
            return Err(VolumeError::bad(
                path,
                "GridFrameOffsetVector",
                format!("{} offsets for {n_frames} frames", g.len()),
            ));
        }
    }
    let dose_scaling = float(path, o.get(tags::DOSE_GRID_SCALING), "DoseGridScaling")?;
    let mut frames = Vec::with_capacity(n_frames);
    for k in 0..n_frames {
        let pos = floats(
            path,
            groups.get(
                k,
                tags::PLANE_POSITION_SEQUENCE,
                tags::IMAGE_POSITION_PATIENT,
            ),
            "ImagePositionPatient",
            3,
        )?;
        let ori = floats(
            path,
            groups.get(
                k,
                tags::PLANE_ORIENTATION_SEQUENCE,
                tags::IMAGE_ORIENTATION_PATIENT,
            ),
            "ImageOrientationPatient",
            6,
        )?;
        let ps = floats(
            path,
            groups.get(k, tags::PIXEL_MEASURES_SEQUENCE, tags::PIXEL_SPACING),
            "PixelSpacing",
            2,
        )?;
        let pvt = tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE;
        let slope = float(
            path,
            groups.get(k, pvt, tags::RESCALE_SLOPE),
            "RescaleSlope",
        )?;
        let intercept = float(
            path,
            groups.get(k, pvt, tags::RESCALE_INTERCEPT),
            "RescaleIntercept",
        )?;
        let rescale = match (slope, intercept, dose_scaling) {
            (None, None, Some(d)) => (d, 0.0),
            (s, i, _) => (s.unwrap_or(1.0), i.unwrap_or(0.0)),
        };
        if rescale.0 == 0.0 {
            return Err(VolumeError::bad(
                path,
                "RescaleSlope",
                "0: a slope must not be zero",
            ));
        }
        let mut position = pos.map(|v| [v[0], v[1], v[2]]);
        let orientation = ori.map(|v| [v[0], v[1], v[2], v[3], v[4], v[5]]);
        // RT dose: frames at offsets along the normal from the first frame's position (the
        // offsets are relative when the first is 0, else they are z; both read as relative to
        // the first)
        if let (Some(g), Some(p)) = (&grid_offsets, position) {
            if n_frames > 1 {
                let o6 = orientation.unwrap_or([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
                let n = normal(&o6);
                let d = g[k] - g[0];
                position = Some([p[0] + d * n[0], p[1] + d * n[1], p[2] + d * n[2]]);
            }
        }
        let frame_has_own_position = per_frame.is_some_and(|p| {
            p.get(k)
                .and_then(|f| f.get(tags::PLANE_POSITION_SEQUENCE))
                .is_some()
        });
        if n_frames > 1 && grid_offsets.is_none() && !frame_has_own_position {
            // a position shared by every frame does not place them
            position = None;
        }
        frames.push(FrameGeometry {
            position,
            orientation,
            pixel_spacing: ps.map(|v| [v[0], v[1]]),
            rescale,
            rescale_type: text(groups.get(k, pvt, tags::RESCALE_TYPE)),
        });
    }
    let location = resolve(path, found.pixel, n_frames, &pixels, endian)?;
    Ok(Some(Member {
        path: path.to_path_buf(),
        ts,
        series_uid: text(o.get(tags::SERIES_INSTANCE_UID)).unwrap_or_default(),
        series_description: text(o.get(tags::SERIES_DESCRIPTION)).unwrap_or_default(),
        modality,
        instance: int(path, o.get(tags::INSTANCE_NUMBER), "InstanceNumber")?,
        pixels,
        frames,
        spacing_between_slices: float(
            path,
            o.get(tags::SPACING_BETWEEN_SLICES),
            "SpacingBetweenSlices",
        )?
        .filter(|s| *s > 0.0),
        slice_thickness: float(path, o.get(tags::SLICE_THICKNESS), "SliceThickness")?
            .filter(|s| *s > 0.0),
        dose_units: text(o.get(tags::DOSE_UNITS)),
        location,
    }))
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn row_col(o: &[f64; 6]) -> ([f64; 3], [f64; 3]) {
    ([o[0], o[1], o[2]], [o[3], o[4], o[5]])
}

fn normal(o: &[f64; 6]) -> [f64; 3] {
    let (r, c) = row_col(o);
    cross(r, c)
}

/// The patient axis a direction cosine lies along (within [`AXIS_TOLERANCE`]), `None` when
/// oblique.
fn axis_of(v: [f64; 3]) -> Option<AxisMap> {
    let axis = (0..3).max_by(|&a, &b| v[a].abs().total_cmp(&v[b].abs()))?;
    let aligned = (v[axis].abs() - 1.0).abs() <= AXIS_TOLERANCE
        && (0..3).all(|a| a == axis || v[a].abs() <= AXIS_TOLERANCE);
    aligned.then_some(AxisMap {
        axis,
        flip: v[axis] < 0.0,
    })
}

fn close(a: &[f64], b: &[f64], tolerance: f64) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tolerance)
}

fn fmt_pos(p: [f64; 3]) -> String {
    format!("({:.4}, {:.4}, {:.4})", p[0], p[1], p[2])
}

impl DicomReader {
    pub fn open(path: &Path, options: &VolumeOptions) -> Result<Self, VolumeError> {
        if let Some(t) = options.frame.filter(|&t| t > 0) {
            return Err(VolumeError::usage(
                path,
                format!("--frame {t}: a DICOM series is one 3D volume (frame 0)"),
            ));
        }
        let mut notes = Vec::new();
        let mut members = Vec::new();
        if path.is_dir() {
            let mut not_dicom = Vec::new();
            let mut no_image = Vec::new();
            for f in slice_files(path)? {
                let name = file_name(&f);
                if name.eq_ignore_ascii_case("DICOMDIR") {
                    no_image.push(name);
                    continue;
                }
                if !has_dicm(&f)? {
                    not_dicom.push(name);
                    continue;
                }
                match read_member(&f)? {
                    Some(m) => members.push(m),
                    None => no_image.push(name),
                }
            }
            if !not_dicom.is_empty() {
                notes.push(format!(
                    "skipped {} file(s) that are not DICOM: {}",
                    not_dicom.len(),
                    some_names(&not_dicom)
                ));
            }
            if !no_image.is_empty() {
                notes.push(format!(
                    "skipped {} DICOM file(s) without an image (DICOMDIR, reports, structure \
                     sets): {}",
                    no_image.len(),
                    some_names(&no_image)
                ));
            }
            if members.is_empty() {
                return Err(VolumeError::unsupported(
                    path,
                    "series",
                    "no DICOM image files in this folder",
                ));
            }
        } else {
            match read_member(path)? {
                Some(m) => members.push(m),
                None => {
                    return Err(VolumeError::unsupported(
                        path,
                        "image",
                        "a DICOM file without an image (a DICOMDIR, a report, a structure set)",
                    ))
                }
            }
        }
        // one series
        let mut series: BTreeMap<String, Vec<usize>> = BTreeMap::new();
        for (i, m) in members.iter().enumerate() {
            series.entry(m.series_uid.clone()).or_default().push(i);
        }
        if series.len() > 1 {
            let list = series
                .iter()
                .map(|(uid, idx)| {
                    let m = &members[idx[0]];
                    let slices: usize = idx.iter().map(|&i| members[i].frames.len()).sum();
                    format!(
                        "{} ({}, {}, {} slice(s))",
                        if uid.is_empty() { "(no UID)" } else { uid },
                        if m.series_description.is_empty() {
                            "no description"
                        } else {
                            &m.series_description
                        },
                        if m.modality.is_empty() {
                            "no modality"
                        } else {
                            &m.modality
                        },
                        slices
                    )
                })
                .collect::<Vec<_>>()
                .join("; ");
            return Err(VolumeError::unsupported(
                path,
                "series",
                format!(
                    "{} series in one folder: {list}. Point at a folder holding one series' \
                     files (sort them into a folder a series first, e.g. with dcm2niix or \
                     dicomsort)",
                    series.len()
                ),
            ));
        }
        let first = &members[0];
        if path.is_dir() {
            notes.insert(
                0,
                format!(
                    "series {} ({}{}), {} file(s)",
                    if first.series_uid.is_empty() {
                        "without a UID"
                    } else {
                        &first.series_uid
                    },
                    first.modality,
                    if first.series_description.is_empty() {
                        String::new()
                    } else {
                        format!(", {}", first.series_description)
                    },
                    members.len()
                ),
            );
        }
        // every file has the same pixels
        let pixels = first.pixels.clone();
        for m in &members[1..] {
            if m.pixels != pixels {
                return Err(VolumeError::unsupported(
                    &m.path,
                    "pixels",
                    format!(
                        "this slice's pixels ({} × {}, {} sample(s) of {} bits ({} stored), {}, \
                         {}) differ from {}'s ({} × {}, {} sample(s) of {} bits ({} stored), \
                         {}, {}): a volume's slices must agree",
                        m.pixels.cols,
                        m.pixels.rows,
                        m.pixels.samples_per_pixel,
                        m.pixels.bits_allocated,
                        m.pixels.bits_stored,
                        if m.pixels.signed {
                            "signed"
                        } else {
                            "unsigned"
                        },
                        m.pixels.photometric,
                        file_name(&first.path),
                        pixels.cols,
                        pixels.rows,
                        pixels.samples_per_pixel,
                        pixels.bits_allocated,
                        pixels.bits_stored,
                        if pixels.signed { "signed" } else { "unsigned" },
                        pixels.photometric,
                    ),
                ));
            }
        }
        let names: Vec<String> = if pixels.samples_per_pixel == 3 {
            ["r", "g", "b"].map(String::from).to_vec()
        } else {
            Vec::new()
        };
        let which = choose_component(options.scalar.as_ref(), pixels.samples_per_pixel, &names)
            .map_err(|m| VolumeError::usage(path, m))?;
        if pixels.samples_per_pixel > 1 {
            notes.push(match which {
                Some(k) => format!("component {} of {}", names[k], pixels.photometric),
                None => format!("magnitude of the {} components", pixels.photometric),
            });
        }
        if pixels.photometric == "PALETTE COLOR" {
            notes.push("palette colour: the values are the palette's indices".into());
        }
        if pixels.photometric == "MONOCHROME1" {
            notes.push("MONOCHROME1: low values are displayed bright".into());
        }

        // the slices, with their geometry
        let mut slices: Vec<(Slice, &FrameGeometry)> = Vec::new();
        for (i, m) in members.iter().enumerate() {
            for (k, g) in m.frames.iter().enumerate() {
                slices.push((
                    Slice {
                        member: i,
                        frame: k,
                    },
                    g,
                ));
            }
        }
        if slices.len() < 2 {
            return Err(VolumeError::unsupported(
                path,
                "slices",
                format!(
                    "one 2D slice ({}): a volume needs at least 2 slices; point at the folder \
                     of its series",
                    file_name(&first.path)
                ),
            ));
        }
        let slice_name = |s: &Slice| {
            let m = &members[s.member];
            if m.frames.len() > 1 {
                format!("{} frame {}", file_name(&m.path), s.frame)
            } else {
                file_name(&m.path)
            }
        };
        let slice_path = |s: &Slice| members[s.member].path.clone();
        // orientation and pixel spacing agree
        let (s0, g0) = &slices[0];
        for (s, g) in &slices[1..] {
            let same = match (g.orientation, g0.orientation) {
                (Some(a), Some(b)) => close(&a, &b, AXIS_TOLERANCE),
                (a, b) => a.is_none() && b.is_none(),
            };
            if !same {
                return Err(VolumeError::unsupported(
                    &slice_path(s),
                    "ImageOrientationPatient",
                    format!(
                        "{} is oriented {:?}, {} {:?}: a volume's slices share one orientation",
                        slice_name(s),
                        g.orientation,
                        slice_name(s0),
                        g0.orientation
                    ),
                ));
            }
            let same = match (g.pixel_spacing, g0.pixel_spacing) {
                (Some(a), Some(b)) => close(&a, &b, 1e-4 * b[0].abs().max(b[1].abs())),
                (a, b) => a.is_none() && b.is_none(),
            };
            if !same {
                return Err(VolumeError::unsupported(
                    &slice_path(s),
                    "PixelSpacing",
                    format!(
                        "{} has pixel spacing {:?}, {} {:?}: a volume's slices share one",
                        slice_name(s),
                        g.pixel_spacing,
                        slice_name(s0),
                        g0.pixel_spacing
                    ),
                ));
            }
        }
        let orientation = g0.orientation;
        let (row, col) = row_col(&orientation.unwrap_or([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]));
        let n = cross(row, col);
        let oblique = |what: &str| {
            VolumeError::unsupported(
                &slice_path(s0),
                "ImageOrientationPatient",
                format!(
                    "an oblique orientation ({what}; ImageOrientationPatient {:?}): resample the \
                     series to the patient axes first (e.g. 3D Slicer's or ANTs' resampling)",
                    orientation.unwrap_or_default()
                ),
            )
        };
        let ax = axis_of(row).ok_or_else(|| oblique("the rows do not run along a patient axis"))?;
        let ay =
            axis_of(col).ok_or_else(|| oblique("the columns do not run along a patient axis"))?;
        let az = axis_of(n).ok_or_else(|| oblique("the slice normal"))?;
        if ax.axis == ay.axis {
            return Err(VolumeError::bad(
                &slice_path(s0),
                "ImageOrientationPatient",
                format!(
                    "{:?}: rows and columns run along the same axis",
                    orientation.unwrap_or_default()
                ),
            ));
        }
        let pixel_spacing = match g0.pixel_spacing {
            Some(ps) if ps[0] > 0.0 && ps[1] > 0.0 => ps,
            Some(ps) => {
                return Err(VolumeError::bad(
                    &slice_path(s0),
                    "PixelSpacing",
                    format!("{ps:?}: must be positive"),
                ))
            }
            None => {
                notes.push("no PixelSpacing: 1 mm between rows and between columns".into());
                [1.0, 1.0]
            }
        };
        let positioned = slices.iter().all(|(_, g)| g.position.is_some());
        let z_spacing;
        if positioned {
            let pos = |g: &FrameGeometry| g.position.expect("every slice has a position");
            slices.sort_by(|a, b| dot(pos(a.1), n).total_cmp(&dot(pos(b.1), n)));
            let d: Vec<f64> = slices.iter().map(|(_, g)| dot(pos(g), n)).collect();
            // a stack whose positions shift within the plane is sheared
            let p0 = pos(slices[0].1);
            for (s, g) in &slices[1..] {
                let p = pos(g);
                let delta = [p[0] - p0[0], p[1] - p0[1], p[2] - p0[2]];
                let (dx, dy) = (dot(delta, row), dot(delta, col));
                let tolerance_x = (0.01 * pixel_spacing[1]).max(SAME_POSITION);
                let tolerance_y = (0.01 * pixel_spacing[0]).max(SAME_POSITION);
                if dx.abs() > tolerance_x || dy.abs() > tolerance_y {
                    return Err(VolumeError::unsupported(
                        &slice_path(s),
                        "ImagePositionPatient",
                        format!(
                            "{} at {} is shifted by ({dx:.4}, {dy:.4}) mm within the plane from \
                             {} at {}: a sheared stack (a tilted gantry?) is not on a grid; \
                             resample it first",
                            slice_name(s),
                            fmt_pos(p),
                            slice_name(&slices[0].0),
                            fmt_pos(p0)
                        ),
                    ));
                }
            }
            let steps: Vec<f64> = d.windows(2).map(|w| w[1] - w[0]).collect();
            for (i, &step) in steps.iter().enumerate() {
                if step < SAME_POSITION {
                    let (a, b) = (&slices[i].0, &slices[i + 1].0);
                    return Err(VolumeError::unsupported(
                        &slice_path(b),
                        "ImagePositionPatient",
                        format!(
                            "{} and {} are at the same position {}: two slices at one place \
                             (several stacks or time points in one series?) are not one volume",
                            slice_name(a),
                            slice_name(b),
                            fmt_pos(pos(slices[i + 1].1))
                        ),
                    ));
                }
            }
            let mut sorted = steps.clone();
            sorted.sort_by(f64::total_cmp);
            let median = sorted[sorted.len() / 2];
            for (i, &step) in steps.iter().enumerate() {
                if (step - median).abs() > SPACING_TOLERANCE * median {
                    let (a, b) = (&slices[i].0, &slices[i + 1].0);
                    return Err(VolumeError::unsupported(
                        &slice_path(b),
                        "ImagePositionPatient",
                        format!(
                            "a series with gaps: {} and {} are {step:.4} mm apart where the \
                             slices are {median:.4} mm apart elsewhere (more than 1 % off; a \
                             missing slice, or uneven spacing)",
                            slice_name(a),
                            slice_name(b)
                        ),
                    ));
                }
            }
            z_spacing = (d[d.len() - 1] - d[0]) / (d.len() - 1) as f64;
        } else {
            let multi_frame = members.iter().any(|m| m.frames.len() > 1);
            if multi_frame {
                match first.spacing_between_slices {
                    Some(s) if members.len() == 1 => {
                        z_spacing = s;
                        notes.push(format!(
                            "frames without positions: in frame order, {s} mm apart \
                             (SpacingBetweenSlices)"
                        ));
                    }
                    _ => {
                        return Err(VolumeError::unsupported(
                            &first.path,
                            "ImagePositionPatient",
                            "frames without positions in space (no per-frame \
                             PlanePositionSequence, GridFrameOffsetVector or \
                             SpacingBetweenSlices): they may be time points, not slices",
                        ))
                    }
                }
            } else {
                let numbered = members.iter().all(|m| m.instance.is_some());
                let mut order: Vec<usize> = (0..slices.len()).collect();
                if numbered {
                    order.sort_by_key(|&i| members[slices[i].0.member].instance);
                    for w in order.windows(2) {
                        let (a, b) = (&slices[w[0]].0, &slices[w[1]].0);
                        if members[a.member].instance == members[b.member].instance {
                            return Err(VolumeError::bad(
                                &slice_path(b),
                                "InstanceNumber",
                                format!(
                                    "{} and {} have the same InstanceNumber and no positions",
                                    slice_name(a),
                                    slice_name(b)
                                ),
                            ));
                        }
                    }
                } else {
                    order.sort_by(|&a, &b| {
                        natural_cmp(
                            &members[slices[a].0.member].path.to_string_lossy(),
                            &members[slices[b].0.member].path.to_string_lossy(),
                        )
                    });
                }
                let reordered: Vec<_> = order.iter().map(|&i| slices[i].clone()).collect();
                slices = reordered;
                let (s, from) = match (first.spacing_between_slices, first.slice_thickness) {
                    (Some(s), _) => (s, "SpacingBetweenSlices"),
                    (None, Some(t)) => (t, "SliceThickness"),
                    (None, None) => (1.0, "assumed"),
                };
                z_spacing = s;
                notes.push(format!(
                    "slices without ImagePositionPatient: ordered by {}, {s} mm apart ({from})",
                    if numbered {
                        "InstanceNumber"
                    } else {
                        "file name"
                    }
                ));
            }
        }
        let origin = slices[0].1.position.unwrap_or([0.0; 3]);
        // values
        let rescales: Vec<(f64, f64)> = slices.iter().map(|(_, g)| g.rescale).collect();
        let uniform = rescales.iter().all(|r| *r == rescales[0]);
        let stored = pixels.dtype();
        let dtype = if which.is_none() || !uniform {
            DType::F32
        } else {
            stored
        };
        let mut header = FileHeader::new(
            VolumeFormat::Dicom,
            [pixels.cols, pixels.rows, slices.len()],
            dtype,
            [pixel_spacing[1], pixel_spacing[0], z_spacing],
        );
        header.axes = [ax, ay, az];
        if orientation.is_none() {
            header.axes = [0, 1, 2].map(|axis| AxisMap { axis, flip: false });
            notes.push("no ImageOrientationPatient: the identity orientation".into());
        }
        header.origin = origin;
        if positioned || orientation.is_some() {
            header.frame = Some("LPS".into());
        }
        header.length_unit = Some("mm".into());
        let per_slice_rescale = if uniform {
            let r = rescales[0];
            if r != (1.0, 0.0) {
                header.rescale = Some(r);
            }
            None
        } else {
            notes.push(
                "the slices' rescales differ: each slice's applied, values as f32".to_string(),
            );
            Some(rescales)
        };
        let rescale_type = slices[0].1.rescale_type.clone();
        header.value_unit = if first.modality == "RTDOSE" {
            match first.dose_units.as_deref() {
                Some("GY") => Some("Gy".to_string()),
                Some(u) => {
                    notes.push(format!("dose units {u}"));
                    None
                }
                None => None,
            }
        } else {
            match rescale_type.as_deref() {
                None | Some("HU") if first.modality == "CT" => Some("HU".into()),
                Some("US") | None => None,
                Some(t) => Some(t.to_string()),
            }
        };
        header.notes = notes;
        let slices = slices.into_iter().map(|(s, _)| s).collect();
        Ok(DicomReader {
            path: path.to_path_buf(),
            header,
            members,
            slices,
            pixels,
            which,
            per_slice_rescale,
        })
    }

    /// The voxels of rows `y` and columns `x` of frame `frame` of file `member`, all components
    /// interleaved (planar colour: the chosen one, or each after the other), bits fitted.
    fn read_frame(
        &self,
        member: usize,
        frame: usize,
        x: Range<usize>,
        y: Range<usize>,
        cache: &mut ReadCache,
    ) -> Result<Samples, VolumeError> {
        let p = &self.pixels;
        let m = &self.members[member];
        let path = &m.path;
        let frames = m.frames.len();
        let ts = m.ts;
        let spp = p.samples_per_pixel;
        let samples = match &m.location {
            &PixelLocation::Native { offset, endian } => {
                if cache.file.as_ref().is_none_or(|(i, _)| *i != member) {
                    cache.file = Some((member, File::open(path).map_err(VolumeError::io(path))?));
                }
                let f = &mut cache.file.as_mut().expect("opened").1;
                let lo = [x.start, y.start];
                let hi = [x.end, y.end];
                if p.planar {
                    // colour planes one after another: plane `frame · spp + c`
                    let layout = Layout {
                        offset,
                        dims: [p.cols, p.rows, frames * spp],
                        components: 1,
                        dtype: p.dtype(),
                        endian,
                    };
                    let plane = |f: &mut File, c: usize| {
                        let z = frame * spp + c;
                        read_raw_box(
                            path,
                            &mut ByteSource::Seek(f),
                            &layout,
                            [lo[0], lo[1], z],
                            [hi[0], hi[1], z + 1],
                        )
                    };
                    return Ok(match self.which {
                        Some(c) => fit_bits(plane(f, c)?, p),
                        None => {
                            let planes = (0..spp)
                                .map(|c| Ok(fit_bits(plane(f, c)?, p)))
                                .collect::<Result<Vec<_>, VolumeError>>()?;
                            let n = planes[0].len();
                            Samples::F32(
                                (0..n)
                                    .map(|i| {
                                        planes.iter().map(|s| s.get(i).powi(2)).sum::<f64>().sqrt()
                                            as f32
                                    })
                                    .collect(),
                            )
                        }
                    });
                }
                let layout = Layout {
                    offset,
                    dims: [p.cols, p.rows, frames],
                    components: spp,
                    dtype: p.dtype(),
                    endian,
                };
                read_raw_box(
                    path,
                    &mut ByteSource::Seek(f),
                    &layout,
                    [lo[0], lo[1], frame],
                    [hi[0], hi[1], frame + 1],
                )?
            }
            PixelLocation::Fragments(fragments) => {
                let parts = fragments.get(frame).ok_or_else(|| {
                    VolumeError::bad(
                        path,
                        "pixel data",
                        format!("no fragments for frame {frame}"),
                    )
                })?;
                if cache.file.as_ref().is_none_or(|(i, _)| *i != member) {
                    cache.file = Some((member, File::open(path).map_err(VolumeError::io(path))?));
                }
                let f = &mut cache.file.as_mut().expect("opened").1;
                let total: u64 = parts.iter().map(|&(_, len)| len as u64).sum();
                let mut data = Vec::new();
                data.try_reserve_exact(total as usize)
                    .map_err(|_| VolumeError::NoMemory {
                        path: path.clone(),
                        bytes: total,
                    })?;
                for &(at, len) in parts {
                    f.seek(SeekFrom::Start(at)).map_err(VolumeError::io(path))?;
                    let start = data.len();
                    f.by_ref()
                        .take(len as u64)
                        .read_to_end(&mut data)
                        .map_err(VolumeError::io(path))?;
                    if data.len() - start != len as usize {
                        return Err(VolumeError::bad(
                            path,
                            "pixel data",
                            format!("truncated: a fragment of frame {frame} ends past the file"),
                        ));
                    }
                }
                let bytes = decode_frame(path, ts, p, data)?;
                crop(path, &bytes, p, frame, x, y)?
            }
            PixelLocation::Whole => {
                if cache.object.as_ref().is_none_or(|(i, _)| *i != member) {
                    let obj = dicom_object::open_file(path)
                        .map_err(|e| VolumeError::bad(path, "data set", chain(&e)))?;
                    cache.object = Some((member, obj));
                }
                let obj = &cache.object.as_ref().expect("opened").1;
                let cannot = |e: String| {
                    VolumeError::bad(
                        path,
                        "pixel data",
                        format!("frame {frame} cannot be decoded ({}): {e}", ts.name()),
                    )
                };
                let data = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    obj.decode_pixel_data_frame(frame as u32)
                        .map(|d| d.into_data())
                }))
                .map_err(|_| cannot("the decoder failed on damaged data".into()))?
                .map_err(|e| cannot(chain(&e)))?;
                let data = if p.planar { interleave(&data, p) } else { data };
                crop(path, &data, p, frame, x, y)?
            }
        };
        Ok(select(fit_bits(samples, p), spp, self.which))
    }
}

/// The open file (or the decoded data set of a file decoded whole) a box is being read from.
#[derive(Default)]
struct ReadCache {
    file: Option<(usize, File)>,
    object: Option<(usize, dicom_object::DefaultDicomObject)>,
}

/// A frame's colour planes (PlanarConfiguration 1) as interleaved samples.
fn interleave(planes: &[u8], p: &Pixels) -> Vec<u8> {
    let b = p.dtype().bytes();
    let plane = p.rows * p.cols * b;
    let spp = p.samples_per_pixel;
    let mut out = vec![0u8; (plane * spp).min(planes.len() / spp * spp)];
    for (c, src) in planes.chunks_exact(plane).take(spp).enumerate() {
        for (i, sample) in src.chunks_exact(b).enumerate() {
            let at = (i * spp + c) * b;
            if let Some(d) = out.get_mut(at..at + b) {
                d.copy_from_slice(sample);
            }
        }
    }
    out
}

/// The rows `y` and columns `x` of a decoded frame (`bytes`, native order, interleaved).
fn crop(
    path: &Path,
    bytes: &[u8],
    p: &Pixels,
    frame: usize,
    x: Range<usize>,
    y: Range<usize>,
) -> Result<Samples, VolumeError> {
    let need = p.frame_bytes() as usize;
    if bytes.len() < need {
        return Err(VolumeError::bad(
            path,
            "pixel data",
            format!(
                "frame {frame} decodes to {} bytes where {} × {} pixels of {} sample(s) of {} \
                 bits need {need}",
                bytes.len(),
                p.cols,
                p.rows,
                p.samples_per_pixel,
                p.bits_allocated
            ),
        ));
    }
    let vb = p.samples_per_pixel * p.dtype().bytes();
    let row = p.cols * vb;
    let mut out = Vec::with_capacity((x.end - x.start) * (y.end - y.start) * vb);
    for j in y {
        out.extend_from_slice(&bytes[j * row + x.start * vb..j * row + x.end * vb]);
    }
    Ok(Samples::decode(p.dtype(), &out, NATIVE))
}

/// Each sample's `BitsStored` bits below `HighBit`, sign-extended for signed pixels.
fn fit_bits(s: Samples, p: &Pixels) -> Samples {
    let width = p.bits_stored as u32;
    let shift = (p.high_bit + 1 - p.bits_stored) as u32;
    if shift == 0 && width == p.bits_allocated as u32 {
        return s;
    }
    let mask = (1u64 << width) - 1;
    let unsigned = move |u: u64| (u >> shift) & mask;
    let signed = move |u: u64| {
        let v = (u >> shift) & mask;
        if (v >> (width - 1)) & 1 == 1 {
            v as i64 - (1i64 << width)
        } else {
            v as i64
        }
    };
    match s {
        Samples::U8(v) => Samples::U8(v.into_iter().map(|x| unsigned(x as u64) as u8).collect()),
        Samples::I8(v) => Samples::I8(
            v.into_iter()
                .map(|x| signed(x as u8 as u64) as i8)
                .collect(),
        ),
        Samples::U16(v) => Samples::U16(v.into_iter().map(|x| unsigned(x as u64) as u16).collect()),
        Samples::I16(v) => Samples::I16(
            v.into_iter()
                .map(|x| signed(x as u16 as u64) as i16)
                .collect(),
        ),
        Samples::U32(v) => Samples::U32(v.into_iter().map(|x| unsigned(x as u64) as u32).collect()),
        Samples::I32(v) => Samples::I32(
            v.into_iter()
                .map(|x| signed(x as u32 as u64) as i32)
                .collect(),
        ),
        other => other,
    }
}

/// What a file's first walk finds, before any of its values is read into memory.
struct Scan {
    ts_uid: String,
    sop_class: String,
    /// The transfer syntax, when dicom-rs knows it.
    ts: Option<&'static TransferSyntax>,
    pixel: PixelScan,
}

/// Where a file's pixel data is, before the header says how it is split into frames.
enum PixelScan {
    /// Uncompressed: the value's offset and length, and whether it is 16-bit words (OW).
    Native { offset: u64, len: u64, words: bool },
    /// Encapsulated: each item's value offset and length (the first is the offset table).
    Items(Vec<(u64, u32)>),
    /// A deflated data set, not walked (decoded whole).
    Deflated,
    /// No pixel data, or a transfer syntax dicom-rs does not know.
    None,
}

/// The little-endian u16 and u32 at `at` of `b`.
fn le16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}
fn le32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// Reads exactly `buf.len()` bytes at `at`, or fails naming what was cut short.
fn read_exact_at(
    f: &mut File,
    path: &Path,
    at: u64,
    buf: &mut [u8],
    what: &str,
) -> Result<(), VolumeError> {
    f.seek(SeekFrom::Start(at)).map_err(VolumeError::io(path))?;
    f.read_exact(buf).map_err(|e| {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            VolumeError::bad(path, what, "truncated")
        } else {
            VolumeError::io(path)(e)
        }
    })
}

/// Walks a file's structure: the file meta group (parsed here, explicit VR little endian), then
/// the data set with dicom-rs's lazy parser up to the pixel data, then the items of
/// encapsulated pixel data. Every value's length is checked against the bytes left, so that the
/// parse of the attributes that follows never allocates for a length the file cannot hold.
fn scan(path: &Path) -> Result<Scan, VolumeError> {
    let mut f = File::open(path).map_err(VolumeError::io(path))?;
    let file_len = f.metadata().map_err(VolumeError::io(path))?.len();
    let bad = |section: &str, m: String| VolumeError::bad(path, section, m);
    // the file meta group: group 0002 elements from byte 132
    let mut at = 132u64;
    let (mut ts_uid, mut sop_class) = (None, String::new());
    loop {
        let mut h = [0u8; 8];
        read_exact_at(&mut f, path, at, &mut h, "file meta")?;
        if le16(&h, 0) != 0x0002 {
            break;
        }
        let element = le16(&h, 2);
        let vr = &h[4..6];
        let long = matches!(
            vr,
            b"OB"
                | b"OD"
                | b"OF"
                | b"OL"
                | b"OV"
                | b"OW"
                | b"SQ"
                | b"SV"
                | b"UC"
                | b"UN"
                | b"UR"
                | b"UT"
                | b"UV"
        );
        let short = matches!(
            vr,
            b"AE"
                | b"AS"
                | b"AT"
                | b"CS"
                | b"DA"
                | b"DS"
                | b"DT"
                | b"FD"
                | b"FL"
                | b"IS"
                | b"LO"
                | b"LT"
                | b"PN"
                | b"SH"
                | b"SL"
                | b"SS"
                | b"ST"
                | b"TM"
                | b"UI"
                | b"UL"
                | b"US"
        );
        if !long && !short {
            return Err(bad(
                "file meta",
                format!(
                    "element (0002,{element:04X}) at byte {at} has no value representation \
                     ({:?})",
                    String::from_utf8_lossy(vr)
                ),
            ));
        }
        let (len, header) = if long {
            let mut l = [0u8; 4];
            read_exact_at(&mut f, path, at + 8, &mut l, "file meta")?;
            (le32(&l, 0) as u64, 12)
        } else {
            (le16(&h, 6) as u64, 8)
        };
        let value = at + header;
        if len > 1024 || value + len > file_len {
            return Err(bad(
                "file meta",
                format!("element (0002,{element:04X}) of {len} bytes at byte {at} does not fit"),
            ));
        }
        if element == 0x0002 || element == 0x0010 {
            let mut v = vec![0u8; len as usize];
            read_exact_at(&mut f, path, value, &mut v, "file meta")?;
            let s = String::from_utf8_lossy(&v)
                .trim_matches(|c: char| c.is_whitespace() || c == '\0')
                .to_string();
            if element == 0x0010 {
                ts_uid = Some(s);
            } else {
                sop_class = s;
            }
        }
        at = value + len;
    }
    let ts_uid =
        ts_uid.ok_or_else(|| bad("file meta", "no TransferSyntaxUID (0002,0010)".into()))?;
    let ts = TransferSyntaxRegistry.get(&ts_uid);
    let mut found = Scan {
        ts_uid,
        sop_class,
        ts,
        pixel: PixelScan::None,
    };
    let Some(ts) = ts else { return Ok(found) };
    if matches!(ts.codec(), Codec::Dataset(_)) {
        found.pixel = PixelScan::Deflated;
        return Ok(found);
    }
    f.seek(SeekFrom::Start(at)).map_err(VolumeError::io(path))?;
    let mut reader = LazyDataSetReader::new_with_ts(BufReader::new(f), ts)
        .map_err(|e| bad("data set", chain(&e)))?;
    let mut depth = 0usize;
    let mut at_pixel_data = false;
    let mut items_from = None;
    while let Some(token) = reader.advance() {
        let token = token.map_err(|e| bad("data set", chain(&e)))?;
        match &token {
            LazyDataToken::SequenceStart { .. } => depth += 1,
            LazyDataToken::PixelSequenceStart if depth == 0 => {
                items_from = Some(());
                break;
            }
            LazyDataToken::PixelSequenceStart => depth += 1,
            LazyDataToken::SequenceEnd => depth = depth.saturating_sub(1),
            LazyDataToken::ElementHeader(h) if depth == 0 && h.tag == tags::PIXEL_DATA => {
                at_pixel_data = true;
            }
            LazyDataToken::ElementHeader(h) if depth == 0 && h.tag > tags::PIXEL_DATA => break,
            LazyDataToken::LazyValue { header, decoder } => {
                let offset = decoder.position();
                let len = header.len.0 as u64;
                if at_pixel_data {
                    let words = header.vr == VR::OW;
                    found.pixel = PixelScan::Native { offset, len, words };
                    return Ok(found);
                }
                if offset + len > file_len {
                    return Err(bad(
                        "data set",
                        format!(
                            "element {} of {len} bytes at byte {offset} ends past the file's \
                             {file_len} bytes",
                            header.tag
                        ),
                    ));
                }
            }
            LazyDataToken::LazyItemValue { len, decoder }
                if decoder.position() + *len as u64 > file_len =>
            {
                return Err(bad(
                    "data set",
                    format!("an item of {len} bytes ends past the file's end"),
                ));
            }
            _ => {}
        }
        if let t @ (LazyDataToken::LazyValue { .. } | LazyDataToken::LazyItemValue { .. }) = token {
            t.skip().map_err(|e| bad("data set", chain(&e)))?;
        }
    }
    if items_from.is_none() {
        return Ok(found);
    }
    // encapsulated pixel data: item headers (tag, length; little endian) from here, values
    // skipped by seeking
    let mut at = reader.into_decoder().position();
    let mut f = File::open(path).map_err(VolumeError::io(path))?;
    let mut items = Vec::new();
    loop {
        let mut h = [0u8; 8];
        read_exact_at(&mut f, path, at, &mut h, "pixel data")?;
        let (group, element, len) = (le16(&h, 0), le16(&h, 2), le32(&h, 4));
        match (group, element) {
            (0xFFFE, 0xE000) => {
                let value = at + 8;
                if value + len as u64 > file_len {
                    return Err(bad(
                        "pixel data",
                        format!(
                            "truncated: a fragment of {len} bytes at byte {value} ends past the \
                             file's {file_len} bytes"
                        ),
                    ));
                }
                items.push((value, len));
                at = value + len as u64;
            }
            (0xFFFE, 0xE0DD) => break,
            _ => {
                return Err(bad(
                    "pixel data",
                    format!(
                        "({group:04X},{element:04X}) at byte {at} where a fragment or the end of \
                         the fragments belongs"
                    ),
                ))
            }
        }
    }
    found.pixel = PixelScan::Items(items);
    Ok(found)
}

/// Where each frame of a file is, from its scan and its header's frame count and pixels.
fn resolve(
    path: &Path,
    scan: PixelScan,
    frames: usize,
    p: &Pixels,
    endian: Endian,
) -> Result<PixelLocation, VolumeError> {
    let bad = |m: String| VolumeError::bad(path, "pixel data", m);
    let file_len = std::fs::metadata(path)
        .map_err(VolumeError::io(path))?
        .len();
    let items = match scan {
        PixelScan::Deflated => return Ok(PixelLocation::Whole),
        PixelScan::None => {
            return Err(bad(
                "no Pixel Data (7FE0,0010) in the data set (Float Pixel Data is not read)".into(),
            ))
        }
        // 8-bit samples in big-endian 16-bit words: byte pairs swapped, decoded whole
        PixelScan::Native { words: true, .. } if endian == Endian::Big && p.bits_allocated == 8 => {
            return Ok(PixelLocation::Whole)
        }
        PixelScan::Native { offset, len, .. } => {
            let need = p.frame_bytes().saturating_mul(frames as u64);
            if len < need || offset.saturating_add(need) > file_len {
                return Err(bad(format!(
                    "truncated: {} bytes of pixel data where {frames} frame(s) of {} × {} \
                     pixels of {} sample(s) of {} bits need {need}",
                    len.min(file_len.saturating_sub(offset)),
                    p.cols,
                    p.rows,
                    p.samples_per_pixel,
                    p.bits_allocated
                )));
            }
            return Ok(PixelLocation::Native { offset, endian });
        }
        PixelScan::Items(items) => items,
    };
    let Some((&(bot_at, bot_len), rest)) = items.split_first() else {
        return Err(bad(
            "encapsulated pixel data without its offset table item".into()
        ));
    };
    let fragments: Vec<(u64, u32)> = rest.iter().copied().filter(|f| f.1 > 0).collect();
    if fragments.is_empty() {
        return Err(bad("encapsulated pixel data without fragments".into()));
    }
    let per_frame = if frames == 1 {
        vec![fragments]
    } else if fragments.len() == frames {
        fragments.into_iter().map(|f| vec![f]).collect()
    } else if bot_len as u64 == 4 * frames as u64 {
        // the Basic Offset Table: each frame's offset from the first fragment's item tag
        let mut table = vec![0u8; bot_len as usize];
        let mut f = File::open(path).map_err(VolumeError::io(path))?;
        read_exact_at(&mut f, path, bot_at, &mut table, "pixel data")?;
        let bot: Vec<u64> = table.chunks_exact(4).map(|c| le32(c, 0) as u64).collect();
        let base = fragments[0].0 - 8;
        let mut per_frame = vec![Vec::new(); frames];
        for f in fragments {
            let rel = f.0 - 8 - base;
            let k = bot.iter().rposition(|&o| o <= rel).unwrap_or(0);
            per_frame[k].push(f);
        }
        if let Some(k) = per_frame.iter().position(|v| v.is_empty()) {
            return Err(bad(format!(
                "the Basic Offset Table gives frame {k} no fragment"
            )));
        }
        per_frame
    } else {
        return Err(VolumeError::unsupported(
            path,
            "pixel data",
            format!(
                "{} fragments for {frames} frames without a Basic Offset Table: which fragments \
                 make each frame is not known",
                fragments.len()
            ),
        ));
    };
    Ok(PixelLocation::Fragments(per_frame))
}

/// Checks an RLE frame's header (segment count and offsets), which dicom-rs 0.10's decoder
/// indexes unchecked.
fn check_rle_header(path: &Path, p: &Pixels, frame: &[u8]) -> Result<(), VolumeError> {
    let bad = |m: String| VolumeError::bad(path, "pixel data", format!("RLE: {m}"));
    if frame.len() < 64 {
        return Err(bad(format!(
            "a frame of {} bytes has no header",
            frame.len()
        )));
    }
    let n = le32(frame, 0) as usize;
    let want = p.samples_per_pixel * p.dtype().bytes();
    if n != want {
        return Err(bad(format!(
            "{n} segments where {} sample(s) of {} bits need {want}",
            p.samples_per_pixel, p.bits_allocated
        )));
    }
    let offsets: Vec<usize> = (0..n).map(|s| le32(frame, 4 + 4 * s) as usize).collect();
    let ordered =
        offsets[0] == 64 && offsets.windows(2).all(|w| w[0] < w[1]) && offsets[n - 1] < frame.len();
    if !ordered {
        return Err(bad(format!(
            "segment offsets {offsets:?} are not increasing from 64 within the frame's {} bytes",
            frame.len()
        )));
    }
    Ok(())
}

/// Decodes one compressed frame (its fragments' bytes) with dicom-pixeldata: the bytes of its
/// samples, native byte order, components interleaved.
fn decode_frame(
    path: &Path,
    ts: &'static TransferSyntax,
    p: &Pixels,
    data: Vec<u8>,
) -> Result<Vec<u8>, VolumeError> {
    if ts.uid() == uids::RLE_LOSSLESS {
        check_rle_header(path, p, &data)?;
    }
    let us = |tag: Tag, v: u16| DataElement::new(tag, VR::US, PrimitiveValue::from(v));
    let mut o = InMemDicomObject::new_empty();
    o.put(us(tags::ROWS, p.rows as u16));
    o.put(us(tags::COLUMNS, p.cols as u16));
    o.put(us(tags::SAMPLES_PER_PIXEL, p.samples_per_pixel as u16));
    o.put(us(tags::BITS_ALLOCATED, p.bits_allocated));
    o.put(us(tags::BITS_STORED, p.bits_stored));
    o.put(us(tags::HIGH_BIT, p.high_bit));
    o.put(us(tags::PIXEL_REPRESENTATION, p.signed as u16));
    o.put(DataElement::new(
        tags::PHOTOMETRIC_INTERPRETATION,
        VR::CS,
        PrimitiveValue::from(p.photometric.as_str()),
    ));
    if p.samples_per_pixel > 1 {
        o.put(us(tags::PLANAR_CONFIGURATION, 0));
    }
    o.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OB,
        Value::PixelSequence(PixelFragmentSequence::new(Vec::<u32>::new(), vec![data])),
    ));
    let meta = FileMetaTableBuilder::new()
        .transfer_syntax(ts.uid())
        .media_storage_sop_class_uid(uids::SECONDARY_CAPTURE_IMAGE_STORAGE)
        .media_storage_sop_instance_uid("2.25.1")
        .build()
        .map_err(|e| VolumeError::bad(path, "pixel data", chain(&e)))?;
    let obj = o.with_exact_meta(meta);
    let cannot = |e: String| {
        VolumeError::bad(
            path,
            "pixel data",
            format!("cannot decode a frame ({}): {e}", ts.name()),
        )
    };
    // the decoders index their input unchecked in places (dicom-rs 0.10's RLE panics on a
    // short segment): a damaged frame is an error, not a crash
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        obj.decode_pixel_data().map(|d| d.into_data())
    }))
    .map_err(|_| cannot("the decoder failed on damaged data".into()))?
    .map_err(|e| cannot(chain(&e)))
}

impl VolumeReader for DicomReader {
    fn header(&self) -> &FileHeader {
        &self.header
    }

    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
        super::check_box(&self.path, lo, hi, self.header.dims)?;
        let n = (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2]);
        let mut out = Samples::with_capacity(self.header.dtype, 0);
        if let Samples::F32(v) = &mut out {
            v.try_reserve_exact(n).map_err(|_| VolumeError::NoMemory {
                path: self.path.clone(),
                bytes: (n * 4) as u64,
            })?;
        }
        let mut cache = ReadCache::default();
        for z in lo[2]..hi[2] {
            let Slice { member, frame } = self.slices[z].clone();
            let mut s = self.read_frame(member, frame, lo[0]..hi[0], lo[1]..hi[1], &mut cache)?;
            if let Some(r) = &self.per_slice_rescale {
                let (slope, intercept) = r[z];
                s = s.rescaled(slope, intercept);
            }
            if !out.extend(&s) {
                return Err(VolumeError::bad(
                    &self.path,
                    "pixel data",
                    format!(
                        "slice {z} read as {} where the volume is {}",
                        s.dtype(),
                        out.dtype()
                    ),
                ));
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
#[path = "dicom_tests.rs"]
mod tests;
