//! Tests of the DICOM reader on files written here with dicom-object (uncompressed in three
//! byte orders and VR encodings, RLE encoded by hand, multi-frame with functional groups or a
//! grid offset vector). pydicom's files are read in `server/tests/volumes.rs`.

use super::*;
use crate::volume::{ScalarChoice, Volume};
use dicom_object::FileDicomObject;

fn tmp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir()
        .join(format!("tetwave-dicom-{}", std::process::id()))
        .join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Stored value of voxel (i, j, k): distinct everywhere, some negative.
fn v(i: usize, j: usize, k: usize) -> i16 {
    (i + 10 * j + 100 * k) as i16 - 50
}

fn ds(values: &[f64]) -> PrimitiveValue {
    PrimitiveValue::from(
        values
            .iter()
            .map(|x| format!("{x}"))
            .collect::<Vec<_>>()
            .join("\\"),
    )
}

fn put(o: &mut InMemDicomObject, tag: Tag, vr: VR, value: PrimitiveValue) {
    o.put(DataElement::new(tag, vr, value));
}

fn put_us(o: &mut InMemDicomObject, tag: Tag, value: u16) {
    put(o, tag, VR::US, PrimitiveValue::from(value));
}

/// What one test slice is.
#[derive(Clone)]
struct Spec {
    cols: usize,
    rows: usize,
    modality: &'static str,
    series: &'static str,
    orientation: Option<[f64; 6]>,
    spacing: [f64; 2],
    rescale: Option<(f64, f64)>,
    /// Bits allocated, stored, high bit, signed.
    bits: (u16, u16, u16, bool),
    ts: &'static str,
}

impl Default for Spec {
    fn default() -> Self {
        Spec {
            cols: 5,
            rows: 4,
            modality: "CT",
            series: "1.2.3.4",
            orientation: Some([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
            spacing: [0.5, 0.25],
            rescale: Some((2.0, -1024.0)),
            bits: (16, 16, 15, true),
            ts: uids::EXPLICIT_VR_LITTLE_ENDIAN,
        }
    }
}

/// The attributes of an image (no position, no pixel data).
fn image(spec: &Spec, frames: usize) -> InMemDicomObject {
    let mut o = InMemDicomObject::new_empty();
    put(
        &mut o,
        tags::SOP_CLASS_UID,
        VR::UI,
        PrimitiveValue::from(uids::CT_IMAGE_STORAGE),
    );
    put(
        &mut o,
        tags::SOP_INSTANCE_UID,
        VR::UI,
        PrimitiveValue::from("1.2.3.4.5.6"),
    );
    put(
        &mut o,
        tags::MODALITY,
        VR::CS,
        PrimitiveValue::from(spec.modality),
    );
    put(
        &mut o,
        tags::SERIES_INSTANCE_UID,
        VR::UI,
        PrimitiveValue::from(spec.series),
    );
    put(
        &mut o,
        tags::SERIES_DESCRIPTION,
        VR::LO,
        PrimitiveValue::from("test series"),
    );
    if let Some(or) = spec.orientation {
        put(&mut o, tags::IMAGE_ORIENTATION_PATIENT, VR::DS, ds(&or));
    }
    put(&mut o, tags::PIXEL_SPACING, VR::DS, ds(&spec.spacing));
    if let Some((s, i)) = spec.rescale {
        put(&mut o, tags::RESCALE_SLOPE, VR::DS, ds(&[s]));
        put(&mut o, tags::RESCALE_INTERCEPT, VR::DS, ds(&[i]));
    }
    put_us(&mut o, tags::ROWS, spec.rows as u16);
    put_us(&mut o, tags::COLUMNS, spec.cols as u16);
    put_us(&mut o, tags::SAMPLES_PER_PIXEL, 1);
    put(
        &mut o,
        tags::PHOTOMETRIC_INTERPRETATION,
        VR::CS,
        PrimitiveValue::from("MONOCHROME2"),
    );
    let (ba, bs, hb, signed) = spec.bits;
    put_us(&mut o, tags::BITS_ALLOCATED, ba);
    put_us(&mut o, tags::BITS_STORED, bs);
    put_us(&mut o, tags::HIGH_BIT, hb);
    put_us(&mut o, tags::PIXEL_REPRESENTATION, signed as u16);
    if frames > 1 {
        put(
            &mut o,
            tags::NUMBER_OF_FRAMES,
            VR::IS,
            PrimitiveValue::from(frames.to_string()),
        );
    }
    o
}

/// 16-bit uncompressed pixel data of `frames` (each `cols × rows` samples, x fastest).
fn native_pixels(o: &mut InMemDicomObject, samples: Vec<u16>) {
    put(
        o,
        tags::PIXEL_DATA,
        VR::OW,
        PrimitiveValue::U16(samples.into()),
    );
}

fn frame_samples(spec: &Spec, k: usize) -> Vec<u16> {
    let mut s = Vec::new();
    for j in 0..spec.rows {
        for i in 0..spec.cols {
            s.push(v(i, j, k) as u16);
        }
    }
    s
}

fn write(o: InMemDicomObject, ts: &str, path: &Path) {
    let meta = FileMetaTableBuilder::new()
        .transfer_syntax(ts)
        .media_storage_sop_class_uid(uids::CT_IMAGE_STORAGE)
        .media_storage_sop_instance_uid("1.2.3.4.5.6");
    let f: FileDicomObject<InMemDicomObject> = o.with_meta(meta).unwrap();
    f.write_to_file(path).unwrap();
}

/// A series of `n` slices along the normal of `spec.orientation`, `step` mm apart from
/// `origin`, slice k holding `v(·, ·, k)`; files named in reverse position order and numbered
/// (InstanceNumber) in a shuffled order, so neither gives the order. Returns the file paths by k.
fn write_series(dir: &Path, spec: &Spec, n: usize, origin: [f64; 3], step: f64) -> Vec<PathBuf> {
    let nrm = normal(&spec.orientation.unwrap());
    (0..n)
        .map(|k| {
            let mut o = image(spec, 1);
            let d = step * k as f64;
            let p = [
                origin[0] + d * nrm[0],
                origin[1] + d * nrm[1],
                origin[2] + d * nrm[2],
            ];
            put(&mut o, tags::IMAGE_POSITION_PATIENT, VR::DS, ds(&p));
            put(
                &mut o,
                tags::INSTANCE_NUMBER,
                VR::IS,
                PrimitiveValue::from(((k * 3) % n + 1).to_string()),
            );
            native_pixels(&mut o, frame_samples(spec, k));
            let path = dir.join(format!("IM{:03}", n - k));
            write(o, spec.ts, &path);
            path
        })
        .collect()
}

fn open_dir(dir: &Path) -> Result<DicomReader, VolumeError> {
    DicomReader::open(dir, &VolumeOptions::default())
}

/// Asserts that the box lo..hi holds `expect(i, j, k)` (file indices).
fn assert_box(
    r: &mut DicomReader,
    lo: [usize; 3],
    hi: [usize; 3],
    expect: impl Fn(usize, usize, usize) -> f64,
) {
    let s = r.read_box(lo, hi).unwrap();
    let mut n = 0;
    for k in lo[2]..hi[2] {
        for j in lo[1]..hi[1] {
            for i in lo[0]..hi[0] {
                assert_eq!(s.get(n), expect(i, j, k), "{lo:?}..{hi:?} at {i},{j},{k}");
                n += 1;
            }
        }
    }
    assert_eq!(n, s.len());
}

const BOXES: [([usize; 3], [usize; 3]); 4] = [
    ([0, 0, 0], [5, 4, 6]),
    ([0, 0, 2], [5, 4, 3]),
    ([1, 1, 1], [4, 3, 5]),
    ([4, 3, 5], [5, 4, 6]),
];

#[test]
fn a_series_is_sorted_by_position_with_its_spacing_rescale_and_units() {
    let dir = tmp_dir("series");
    let spec = Spec::default();
    write_series(&dir, &spec, 6, [-10.0, 20.0, 30.0], 1.5);
    std::fs::write(dir.join("notes.txt"), "not DICOM").unwrap();
    let mut r = open_dir(&dir).unwrap();
    let h = r.header().clone();
    assert_eq!(h.dims, [5, 4, 6]);
    assert_eq!(h.dtype, DType::I16);
    // PixelSpacing is (between rows, between columns): x gets the second
    assert_eq!(h.spacing, [0.25, 0.5, 1.5]);
    assert_eq!(h.origin, [-10.0, 20.0, 30.0]);
    assert_eq!(h.axes, [0, 1, 2].map(|axis| AxisMap { axis, flip: false }));
    assert_eq!(h.rescale, Some((2.0, -1024.0)));
    assert_eq!(h.value_unit.as_deref(), Some("HU"));
    assert_eq!(h.frame.as_deref(), Some("LPS"));
    assert!(
        h.notes.iter().any(|n| n.contains("notes.txt")),
        "{:?}",
        h.notes
    );
    for (lo, hi) in BOXES {
        assert_box(&mut r, lo, hi, |i, j, k| v(i, j, k) as f64);
    }
    // through the seam: world values are rescaled
    let mut vol = Volume::from_reader(&dir, Box::new(r)).unwrap();
    let b = vol.read_block(0..4, 2..3).unwrap();
    assert_eq!(b.get(7), 2.0 * v(2, 1, 2) as f64 - 1024.0);
}

#[test]
fn byte_orders_and_vr_encodings_read_the_same() {
    for (name, ts) in [
        ("implicit", uids::IMPLICIT_VR_LITTLE_ENDIAN),
        ("big", "1.2.840.10008.1.2.2"),
        ("deflated", uids::DEFLATED_EXPLICIT_VR_LITTLE_ENDIAN),
    ] {
        let dir = tmp_dir(name);
        let spec = Spec {
            ts,
            ..Spec::default()
        };
        write_series(&dir, &spec, 6, [0.0; 3], 2.0);
        let mut r = open_dir(&dir).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(r.header().spacing, [0.25, 0.5, 2.0], "{name}");
        for (lo, hi) in BOXES {
            assert_box(&mut r, lo, hi, |i, j, k| v(i, j, k) as f64);
        }
    }
}

#[test]
fn flipped_orientations_map_to_flipped_axes() {
    let dir = tmp_dir("flipped");
    // rows run towards -x (right), columns towards +y; the normal is -z
    let spec = Spec {
        orientation: Some([-1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
        ..Spec::default()
    };
    write_series(&dir, &spec, 6, [5.0, 6.0, 7.0], 3.0);
    let mut r = open_dir(&dir).unwrap();
    let h = r.header().clone();
    assert_eq!(
        h.axes,
        [
            AxisMap {
                axis: 0,
                flip: true
            },
            AxisMap {
                axis: 1,
                flip: false
            },
            AxisMap {
                axis: 2,
                flip: true
            },
        ]
    );
    // sorted along the normal: slice k is at z = 7 - 3k, first in file order
    assert_eq!(h.origin, [5.0, 6.0, 7.0]);
    assert_eq!(h.spacing[2], 3.0);
    for (lo, hi) in BOXES {
        assert_box(&mut r, lo, hi, |i, j, k| v(i, j, k) as f64);
    }
    // coronal: rows along x, columns along -z (feet), normal along y
    let dir = tmp_dir("coronal");
    let spec = Spec {
        orientation: Some([1.0, 0.0, 0.0, 0.0, 0.0, -1.0]),
        ..Spec::default()
    };
    write_series(&dir, &spec, 6, [0.0; 3], 1.0);
    let r = open_dir(&dir).unwrap();
    let axes = r.header().axes;
    assert_eq!(
        axes[1],
        AxisMap {
            axis: 2,
            flip: true
        }
    );
    // (1,0,0) × (0,0,-1) = (0,1,0)
    assert_eq!(
        axes[2],
        AxisMap {
            axis: 1,
            flip: false
        }
    );
}

#[test]
fn gaps_duplicates_oblique_and_mixed_slices_are_refused() {
    let spec = Spec::default();
    // a missing slice
    let dir = tmp_dir("gap");
    let files = write_series(&dir, &spec, 6, [0.0; 3], 1.5);
    std::fs::remove_file(&files[3]).unwrap();
    let e = open_dir(&dir).err().unwrap().to_string();
    assert!(
        e.contains("gaps") && e.contains("IM004") && e.contains("IM002"),
        "{e}"
    );
    // two slices at one position
    let dir = tmp_dir("duplicate");
    write_series(&dir, &spec, 3, [0.0; 3], 1.5);
    let mut o = image(&spec, 1);
    put(
        &mut o,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        ds(&[0.0, 0.0, 1.5]),
    );
    native_pixels(&mut o, frame_samples(&spec, 0));
    write(o, spec.ts, &dir.join("extra"));
    let e = open_dir(&dir).err().unwrap().to_string();
    assert!(e.contains("same position") && e.contains("extra"), "{e}");
    // oblique
    let dir = tmp_dir("oblique");
    let c = 0.5f64.sqrt();
    let oblique = Spec {
        orientation: Some([c, c, 0.0, -c, c, 0.0]),
        ..Spec::default()
    };
    write_series(&dir, &oblique, 3, [0.0; 3], 1.0);
    let e = open_dir(&dir).err().unwrap().to_string();
    assert!(e.contains("oblique"), "{e}");
    // a slice of other dims
    let dir = tmp_dir("mixed");
    write_series(&dir, &spec, 3, [0.0; 3], 1.0);
    let other = Spec {
        cols: 6,
        ..Spec::default()
    };
    let mut o = image(&other, 1);
    put(
        &mut o,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        ds(&[0.0, 0.0, 3.0]),
    );
    native_pixels(&mut o, frame_samples(&other, 0));
    write(o, spec.ts, &dir.join("wide"));
    let e = open_dir(&dir).err().unwrap().to_string();
    assert!(e.contains("wide") && e.contains("6 × 4"), "{e}");
    // slices of different orientations
    let dir = tmp_dir("orientations");
    write_series(&dir, &spec, 3, [0.0; 3], 1.0);
    let turned = Spec {
        orientation: Some([0.0, 1.0, 0.0, 1.0, 0.0, 0.0]),
        ..Spec::default()
    };
    let mut o = image(&turned, 1);
    put(
        &mut o,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        ds(&[0.0, 0.0, 3.0]),
    );
    native_pixels(&mut o, frame_samples(&spec, 0));
    write(o, spec.ts, &dir.join("turned"));
    let e = open_dir(&dir).err().unwrap().to_string();
    assert!(
        e.contains("ImageOrientationPatient") && e.contains("turned"),
        "{e}"
    );
    // a tilted gantry: positions shift along y from slice to slice
    let dir = tmp_dir("tilted");
    for k in 0..3 {
        let mut o = image(&spec, 1);
        let p = [0.0, 0.4 * k as f64, k as f64];
        put(&mut o, tags::IMAGE_POSITION_PATIENT, VR::DS, ds(&p));
        native_pixels(&mut o, frame_samples(&spec, k));
        write(o, spec.ts, &dir.join(format!("t{k}")));
    }
    let e = open_dir(&dir).err().unwrap().to_string();
    assert!(e.contains("sheared"), "{e}");
}

#[test]
fn several_series_are_listed_and_one_slice_is_not_a_volume() {
    let dir = tmp_dir("two-series");
    write_series(&dir, &Spec::default(), 3, [0.0; 3], 1.0);
    let sub = tmp_dir("two-series-b");
    let other = Spec {
        series: "9.8.7",
        modality: "MR",
        ..Spec::default()
    };
    for (k, p) in write_series(&sub, &other, 2, [0.0; 3], 1.0)
        .into_iter()
        .enumerate()
    {
        std::fs::rename(p, dir.join(format!("mr{k}"))).unwrap();
    }
    let e = open_dir(&dir).err().unwrap().to_string();
    assert!(
        e.contains("2 series")
            && e.contains("1.2.3.4 (test series, CT, 3 slice(s))")
            && e.contains("9.8.7 (test series, MR, 2 slice(s))"),
        "{e}"
    );
    // one file
    let files = write_series(&tmp_dir("single"), &Spec::default(), 1, [0.0; 3], 1.0);
    let e = DicomReader::open(&files[0], &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("one 2D slice"), "{e}");
    // a DICOMDIR beside the slices is skipped
    let dir = tmp_dir("with-dicomdir");
    let files = write_series(&dir, &Spec::default(), 3, [0.0; 3], 1.0);
    std::fs::copy(&files[0], dir.join("DICOMDIR")).unwrap();
    let r = open_dir(&dir).unwrap();
    assert_eq!(r.header().dims[2], 3);
    assert!(r.header().notes.iter().any(|n| n.contains("DICOMDIR")));
}

#[test]
fn without_positions_instance_numbers_order_the_slices() {
    let dir = tmp_dir("no-positions");
    let spec = Spec::default();
    for k in 0..4 {
        let mut o = image(&spec, 1);
        put(
            &mut o,
            tags::INSTANCE_NUMBER,
            VR::IS,
            PrimitiveValue::from((10 + k).to_string()),
        );
        put(&mut o, tags::SLICE_THICKNESS, VR::DS, ds(&[2.5]));
        native_pixels(&mut o, frame_samples(&spec, k));
        write(o, spec.ts, &dir.join(format!("z{}", 9 - k)));
    }
    let mut r = open_dir(&dir).unwrap();
    assert_eq!(r.header().spacing[2], 2.5);
    assert!(r
        .header()
        .notes
        .iter()
        .any(|n| n.contains("InstanceNumber")));
    assert_box(&mut r, [0, 0, 0], [5, 4, 4], |i, j, k| v(i, j, k) as f64);
}

#[test]
fn slices_of_different_rescales_are_rescaled_each() {
    let dir = tmp_dir("rescales");
    let files = write_series(&dir, &Spec::default(), 3, [0.0; 3], 1.0);
    // slice 1 gets another slope
    let mut o = image(
        &Spec {
            rescale: Some((0.5, 3.0)),
            ..Spec::default()
        },
        1,
    );
    put(
        &mut o,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        ds(&[0.0, 0.0, 1.0]),
    );
    native_pixels(&mut o, frame_samples(&Spec::default(), 1));
    write(o, uids::EXPLICIT_VR_LITTLE_ENDIAN, &files[1]);
    let mut r = open_dir(&dir).unwrap();
    assert_eq!(r.header().dtype, DType::F32);
    assert_eq!(r.header().rescale, None);
    assert_box(&mut r, [0, 0, 0], [5, 4, 3], |i, j, k| {
        let s = v(i, j, k) as f64;
        if k == 1 {
            0.5 * s + 3.0
        } else {
            2.0 * s - 1024.0
        }
    });
}

#[test]
fn bits_above_bits_stored_are_masked_and_signs_extended() {
    let dir = tmp_dir("bits");
    // 12 bits stored in 16, signed; the high nibble holds garbage (an overlay)
    let spec = Spec {
        bits: (16, 12, 11, true),
        ..Spec::default()
    };
    for k in 0..2 {
        let mut o = image(&spec, 1);
        put(
            &mut o,
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            ds(&[0.0, 0.0, k as f64]),
        );
        let s = frame_samples(&spec, k)
            .into_iter()
            .map(|x| (x & 0x0fff) | 0xa000)
            .collect();
        native_pixels(&mut o, s);
        write(o, spec.ts, &dir.join(format!("b{k}")));
    }
    let mut r = open_dir(&dir).unwrap();
    assert_box(&mut r, [0, 0, 0], [5, 4, 2], |i, j, k| v(i, j, k) as f64);
    // unsigned, high bit 13 (2 bits below the stored ones)
    let dir = tmp_dir("bits-shifted");
    let spec = Spec {
        bits: (16, 12, 13, false),
        ..Spec::default()
    };
    for k in 0..2 {
        let mut o = image(&spec, 1);
        put(
            &mut o,
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            ds(&[0.0, 0.0, k as f64]),
        );
        let s = (0..20)
            .map(|i| ((i as u16 + 100 * k as u16) << 2) | 0xc003)
            .collect();
        native_pixels(&mut o, s);
        write(o, spec.ts, &dir.join(format!("b{k}")));
    }
    let mut r = open_dir(&dir).unwrap();
    assert_eq!(r.header().dtype, DType::U16);
    assert_box(&mut r, [0, 0, 0], [5, 4, 2], |i, j, k| {
        (i + 5 * j + 100 * k) as f64
    });
}

/// An enhanced multi-frame image: per-frame positions (in reverse order of the frames), shared
/// orientation, spacing and rescale.
fn enhanced(spec: &Spec, n: usize) -> InMemDicomObject {
    let mut o = image(
        &Spec {
            orientation: None,
            rescale: None,
            ..spec.clone()
        },
        n,
    );
    o.remove_element(tags::PIXEL_SPACING);
    let item = |elements: Vec<InMemElement>| InMemDicomObject::from_element_iter(elements);
    let seq = |tag: Tag, items: Vec<InMemDicomObject>| {
        DataElement::new(
            tag,
            VR::SQ,
            Value::new_sequence(items, dicom_core::Length::UNDEFINED),
        )
    };
    let shared = item(vec![
        seq(
            tags::PLANE_ORIENTATION_SEQUENCE,
            vec![item(vec![DataElement::new(
                tags::IMAGE_ORIENTATION_PATIENT,
                VR::DS,
                ds(&spec.orientation.unwrap()),
            )])],
        ),
        seq(
            tags::PIXEL_MEASURES_SEQUENCE,
            vec![item(vec![DataElement::new(
                tags::PIXEL_SPACING,
                VR::DS,
                ds(&spec.spacing),
            )])],
        ),
        seq(
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            vec![item(vec![
                DataElement::new(tags::RESCALE_SLOPE, VR::DS, ds(&[2.0])),
                DataElement::new(tags::RESCALE_INTERCEPT, VR::DS, ds(&[-1024.0])),
            ])],
        ),
    ]);
    o.put(seq(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE, vec![shared]));
    let per_frame = (0..n)
        .map(|f| {
            // frame f holds slice k = n-1-f, at z = 2k
            let k = n - 1 - f;
            item(vec![seq(
                tags::PLANE_POSITION_SEQUENCE,
                vec![item(vec![DataElement::new(
                    tags::IMAGE_POSITION_PATIENT,
                    VR::DS,
                    ds(&[1.0, 2.0, 2.0 * k as f64]),
                )])],
            )])
        })
        .collect();
    o.put(seq(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE, per_frame));
    o
}

#[test]
fn enhanced_multi_frame_files_place_each_frame() {
    let spec = Spec::default();
    let n = 6;
    let mut o = enhanced(&spec, n);
    let samples = (0..n)
        .flat_map(|f| frame_samples(&spec, n - 1 - f))
        .collect();
    native_pixels(&mut o, samples);
    let path = tmp_dir("enhanced").join("enhanced.dcm");
    write(o, spec.ts, &path);
    let mut r = DicomReader::open(&path, &VolumeOptions::default()).unwrap();
    let h = r.header().clone();
    assert_eq!(h.dims, [5, 4, 6]);
    assert_eq!(h.spacing, [0.25, 0.5, 2.0]);
    assert_eq!(h.origin, [1.0, 2.0, 0.0]);
    assert_eq!(h.rescale, Some((2.0, -1024.0)));
    for (lo, hi) in BOXES {
        assert_box(&mut r, lo, hi, |i, j, k| v(i, j, k) as f64);
    }
    // --frame other than 0 is refused
    let e = DicomReader::open(
        &path,
        &VolumeOptions {
            frame: Some(1),
            ..Default::default()
        },
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("--frame 1"), "{e}");
}

#[test]
fn rt_dose_frames_sit_at_their_grid_offsets_and_scale_to_gray() {
    let spec = Spec {
        modality: "RTDOSE",
        rescale: None,
        bits: (32, 32, 31, false),
        ..Spec::default()
    };
    let n = 4;
    let mut o = image(&spec, n);
    put(
        &mut o,
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        ds(&[-5.0, -6.0, 100.0]),
    );
    // absolute z offsets (the first is the position's z), 2.5 mm apart
    put(
        &mut o,
        tags::GRID_FRAME_OFFSET_VECTOR,
        VR::DS,
        ds(&[100.0, 102.5, 105.0, 107.5]),
    );
    put(&mut o, tags::DOSE_GRID_SCALING, VR::DS, ds(&[1e-3]));
    // written as UN by a writer that did not know it (as pydicom's rtdose_rle.dcm has it)
    put(
        &mut o,
        tags::PIXEL_SPACING,
        VR::UN,
        PrimitiveValue::U8(b"3.0\\4.5 ".to_vec().into()),
    );
    put(&mut o, tags::DOSE_UNITS, VR::CS, PrimitiveValue::from("GY"));
    let value = |i: usize, j: usize, k: usize| 70000 + (i + 10 * j + 100 * k) as u32;
    let mut bytes = Vec::new();
    for k in 0..n {
        for j in 0..spec.rows {
            for i in 0..spec.cols {
                bytes.extend_from_slice(&value(i, j, k).to_le_bytes());
            }
        }
    }
    put(
        &mut o,
        tags::PIXEL_DATA,
        VR::OB,
        PrimitiveValue::U8(bytes.into()),
    );
    let path = tmp_dir("dose").join("dose.dcm");
    write(o, uids::EXPLICIT_VR_LITTLE_ENDIAN, &path);
    let mut r = DicomReader::open(&path, &VolumeOptions::default()).unwrap();
    let h = r.header().clone();
    assert_eq!(h.dtype, DType::U32);
    assert_eq!(h.spacing, [4.5, 3.0, 2.5]);
    assert_eq!(h.origin, [-5.0, -6.0, 100.0]);
    assert_eq!(h.rescale, Some((1e-3, 0.0)));
    assert_eq!(h.value_unit.as_deref(), Some("Gy"));
    assert_box(&mut r, [0, 0, 0], [5, 4, 4], |i, j, k| {
        value(i, j, k) as f64
    });
    assert_box(&mut r, [2, 1, 3], [4, 4, 4], |i, j, k| {
        value(i, j, k) as f64
    });
}

/// DICOM RLE of one frame of 16-bit samples: two byte planes (high, then low), literal runs.
fn rle_frame(samples: &[u16]) -> Vec<u8> {
    let planes: Vec<Vec<u8>> = [8u32, 0]
        .iter()
        .map(|&shift| samples.iter().map(|&x| (x >> shift) as u8).collect())
        .collect();
    let mut segments = Vec::new();
    for plane in planes {
        let mut seg = Vec::new();
        for run in plane.chunks(128) {
            seg.push((run.len() - 1) as u8);
            seg.extend_from_slice(run);
        }
        if seg.len() % 2 == 1 {
            seg.push(0x80); // a no-op run
        }
        segments.push(seg);
    }
    let mut header = [0u32; 16];
    header[0] = segments.len() as u32;
    let mut at = 64;
    for (s, seg) in segments.iter().enumerate() {
        header[s + 1] = at;
        at += seg.len() as u32;
    }
    let mut out: Vec<u8> = header.iter().flat_map(|h| h.to_le_bytes()).collect();
    for seg in segments {
        out.extend(seg);
    }
    out
}

fn rle_multi_frame(spec: &Spec, n: usize) -> InMemDicomObject {
    let mut o = enhanced(spec, n);
    let fragments: Vec<Vec<u8>> = (0..n)
        .map(|f| rle_frame(&frame_samples(spec, n - 1 - f)))
        .collect();
    o.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OB,
        Value::PixelSequence(PixelFragmentSequence::new(Vec::<u32>::new(), fragments)),
    ));
    o
}

#[test]
fn rle_frames_are_decoded_one_at_a_time() {
    let spec = Spec::default();
    let path = tmp_dir("rle").join("rle.dcm");
    write(rle_multi_frame(&spec, 6), uids::RLE_LOSSLESS, &path);
    let mut r = DicomReader::open(&path, &VolumeOptions::default()).unwrap();
    assert_eq!(r.header().dims, [5, 4, 6]);
    for (lo, hi) in BOXES {
        assert_box(&mut r, lo, hi, |i, j, k| v(i, j, k) as f64);
    }
    // a series of RLE slices
    let dir = tmp_dir("rle-series");
    for k in 0..3 {
        let mut o = image(&spec, 1);
        put(
            &mut o,
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            ds(&[0.0, 0.0, k as f64]),
        );
        o.put(DataElement::new(
            tags::PIXEL_DATA,
            VR::OB,
            Value::PixelSequence(PixelFragmentSequence::new(
                Vec::<u32>::new(),
                vec![rle_frame(&frame_samples(&spec, k))],
            )),
        ));
        write(o, uids::RLE_LOSSLESS, &dir.join(format!("r{k}")));
    }
    let mut r = open_dir(&dir).unwrap();
    assert_box(&mut r, [1, 0, 0], [5, 3, 3], |i, j, k| v(i, j, k) as f64);
}

#[test]
fn undecodable_transfer_syntaxes_are_refused_by_name() {
    let spec = Spec::default();
    let mut o = enhanced(&spec, 2);
    o.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OB,
        Value::PixelSequence(PixelFragmentSequence::new(
            Vec::<u32>::new(),
            vec![vec![0u8; 8], vec![0u8; 8]],
        )),
    ));
    let path = tmp_dir("j2k").join("j2k.dcm");
    write(o, uids::JPEG2000_LOSSLESS, &path);
    let e = DicomReader::open(&path, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("j2k.dcm") && e.contains("JPEG 2000") && e.contains("1.2.840.10008.1.2.4.90"),
        "{e}"
    );
}

#[test]
fn rgb_needs_a_component_and_planar_colour_is_read() {
    for (planar, ts) in [
        (0u16, uids::EXPLICIT_VR_LITTLE_ENDIAN),
        (1, uids::EXPLICIT_VR_LITTLE_ENDIAN),
        (0, uids::DEFLATED_EXPLICIT_VR_LITTLE_ENDIAN),
        (1, uids::DEFLATED_EXPLICIT_VR_LITTLE_ENDIAN),
    ] {
        let dir = tmp_dir(&format!("rgb{planar}{}", ts.len()));
        let spec = Spec {
            rescale: None,
            bits: (8, 8, 7, false),
            ts,
            ..Spec::default()
        };
        let value = |i: usize, j: usize, k: usize, c: usize| (i + 5 * j + 20 * k + 60 * c) as u8;
        for k in 0..2 {
            let mut o = image(&spec, 1);
            put_us(&mut o, tags::SAMPLES_PER_PIXEL, 3);
            put_us(&mut o, tags::PLANAR_CONFIGURATION, planar);
            put(
                &mut o,
                tags::PHOTOMETRIC_INTERPRETATION,
                VR::CS,
                PrimitiveValue::from("RGB"),
            );
            put(
                &mut o,
                tags::IMAGE_POSITION_PATIENT,
                VR::DS,
                ds(&[0.0, 0.0, k as f64]),
            );
            let mut bytes = Vec::new();
            if planar == 1 {
                for c in 0..3 {
                    for j in 0..4 {
                        for i in 0..5 {
                            bytes.push(value(i, j, k, c));
                        }
                    }
                }
            } else {
                for j in 0..4 {
                    for i in 0..5 {
                        for c in 0..3 {
                            bytes.push(value(i, j, k, c));
                        }
                    }
                }
            }
            put(
                &mut o,
                tags::PIXEL_DATA,
                VR::OB,
                PrimitiveValue::U8(bytes.into()),
            );
            write(o, spec.ts, &dir.join(format!("c{k}")));
        }
        let e = open_dir(&dir).err().unwrap().to_string();
        assert!(e.contains("--scalar"), "{e}");
        let options = |s: ScalarChoice| VolumeOptions {
            scalar: Some(s),
            ..Default::default()
        };
        let mut r = DicomReader::open(&dir, &options(ScalarChoice::Name("g".into()))).unwrap();
        assert_eq!(r.header().dtype, DType::U8);
        assert_box(&mut r, [1, 1, 0], [5, 4, 2], |i, j, k| {
            value(i, j, k, 1) as f64
        });
        let mut r = DicomReader::open(&dir, &options(ScalarChoice::Magnitude)).unwrap();
        assert_eq!(r.header().dtype, DType::F32);
        let norm = |i, j, k| {
            ((0..3)
                .map(|c| (value(i, j, k, c) as f64).powi(2))
                .sum::<f64>()
                .sqrt() as f32) as f64
        };
        assert_box(&mut r, [0, 0, 0], [5, 4, 2], norm);
    }
}

#[test]
fn a_box_reads_only_its_slices() {
    let dir = tmp_dir("only");
    let files = write_series(&dir, &Spec::default(), 6, [0.0; 3], 1.0);
    let mut r = open_dir(&dir).unwrap();
    // the other slices' files are gone: a box of slices 1..3 still reads
    for (k, f) in files.iter().enumerate() {
        if !(1..3).contains(&k) {
            std::fs::write(f, b"gone").unwrap();
        }
    }
    assert_box(&mut r, [0, 0, 1], [5, 4, 3], |i, j, k| v(i, j, k) as f64);
    let e = r.read_box([0, 0, 0], [5, 4, 1]).err().unwrap().to_string();
    assert!(e.contains("IM006"), "{e}");
}

/// Truncations and byte corruptions of valid files give errors or values, never a panic.
#[test]
fn damaged_files_never_panic() {
    let spec = Spec::default();
    let dir = tmp_dir("damage");
    let native = dir.join("native.dcm");
    let mut o = enhanced(&spec, 3);
    native_pixels(
        &mut o,
        (0..3).flat_map(|f| frame_samples(&spec, f)).collect(),
    );
    write(o, spec.ts, &native);
    let rle = dir.join("rle.dcm");
    write(rle_multi_frame(&spec, 3), uids::RLE_LOSSLESS, &rle);
    let series = tmp_dir("damage-series");
    let slice = write_series(&series, &spec, 3, [0.0; 3], 1.0)[1].clone();
    let try_read = |p: &Path| {
        if let Ok(mut r) = DicomReader::open(p, &VolumeOptions::default()) {
            let d = r.header().dims;
            let _ = r.read_box([0, 0, 0], d);
            let _ = r.read_box([1, 1, d[2] - 1], d);
        }
    };
    let mut opened = 0;
    for (valid, path) in [
        (native.clone(), dir.join("bad.dcm")),
        (rle.clone(), dir.join("bad.dcm")),
        (slice.clone(), slice.clone()),
    ] {
        let bytes = std::fs::read(&valid).unwrap();
        let target = if path == valid {
            series.clone()
        } else {
            path.clone()
        };
        for cut in (0..bytes.len()).step_by(7) {
            std::fs::write(&path, &bytes[..cut]).unwrap();
            try_read(&target);
        }
        for at in (128..bytes.len()).step_by(3) {
            for x in [0x00u8, 0xff, 0x7f] {
                let mut b = bytes.clone();
                b[at] = x;
                std::fs::write(&path, &b).unwrap();
                try_read(&target);
            }
        }
        std::fs::write(&path, &bytes).unwrap();
        if DicomReader::open(&target, &VolumeOptions::default()).is_ok() {
            opened += 1;
        }
    }
    assert_eq!(opened, 3);
}
