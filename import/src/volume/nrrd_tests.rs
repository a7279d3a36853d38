//! NRRD files written here line by line (pynrrd's files are read in `server/tests/volumes.rs`).

use super::super::{
    open_reader, AxisMap, DType, ScalarChoice, Volume, VolumeError, VolumeFormat, VolumeOptions,
};
use super::*;
use std::io::Write;

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("tetwave-nrrd-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Voxel value of index (i, j, k): distinct everywhere.
fn v(i: usize, j: usize, k: usize) -> i32 {
    i as i32 + 10 * j as i32 + 100 * k as i32 - 50
}

const DIMS: [usize; 3] = [4, 3, 2];

/// The voxels `v` of `DIMS` as `dtype` bytes (`f` maps the value), x fastest.
fn samples(dtype: DType, big: bool, f: impl Fn(i32) -> f64) -> Vec<u8> {
    let mut b = Vec::new();
    for k in 0..DIMS[2] {
        for j in 0..DIMS[1] {
            for i in 0..DIMS[0] {
                let x = f(v(i, j, k));
                macro_rules! put {
                    ($t:ty) => {{
                        let y = x as $t;
                        b.extend_from_slice(&if big {
                            y.to_be_bytes()
                        } else {
                            y.to_le_bytes()
                        })
                    }};
                }
                match dtype {
                    DType::U8 => put!(u8),
                    DType::I8 => put!(i8),
                    DType::U16 => put!(u16),
                    DType::I16 => put!(i16),
                    DType::U32 => put!(u32),
                    DType::I32 => put!(i32),
                    DType::F32 => put!(f32),
                    DType::F64 => put!(f64),
                }
            }
        }
    }
    b
}

fn gzip(b: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(b).unwrap();
    e.finish().unwrap()
}

fn open(p: &Path, options: &VolumeOptions) -> Result<Box<dyn VolumeReader>, VolumeError> {
    open_reader(p, VolumeFormat::Nrrd, options)
}

fn opts(scalar: Option<&str>, frame: Option<usize>) -> VolumeOptions {
    VolumeOptions {
        scalar: scalar.map(ScalarChoice::parse),
        frame,
        ..VolumeOptions::default()
    }
}

/// Checks every voxel of a few boxes against `want(i, j, k)`.
fn check_boxes(r: &mut dyn VolumeReader, want: impl Fn(usize, usize, usize) -> f64) {
    let d = r.header().dims;
    for (lo, hi) in [
        ([0, 0, 0], d),
        ([1, 1, 1], d),
        ([0, 0, 1], d),
        ([1, 0, 0], [3, 2, 1]),
        ([0, 2, 0], [d[0], 3, 2]),
    ] {
        let s = r.read_box(lo, hi).unwrap();
        let mut n = 0;
        for k in lo[2]..hi[2] {
            for j in lo[1]..hi[1] {
                for i in lo[0]..hi[0] {
                    assert_eq!(s.get(n), want(i, j, k), "{lo:?}..{hi:?} at {i},{j},{k}");
                    n += 1;
                }
            }
        }
        assert_eq!(n, s.len());
    }
}

fn header(fields: &[&str]) -> String {
    let mut h = String::from("NRRD0004\n# Complete NRRD file format specification at:\n");
    for f in fields {
        h.push_str(f);
        h.push('\n');
    }
    h
}

#[test]
fn every_type_spelling_and_byte_order_reads_its_values() {
    let spellings: [(&str, DType); 16] = [
        ("signed char", DType::I8),
        ("int8_t", DType::I8),
        ("uchar", DType::U8),
        ("unsigned char", DType::U8),
        ("short", DType::I16),
        ("signed short int", DType::I16),
        ("ushort", DType::U16),
        ("uint16", DType::U16),
        ("int", DType::I32),
        ("int32_t", DType::I32),
        ("uint", DType::U32),
        ("unsigned int", DType::U32),
        ("float", DType::F32),
        ("double", DType::F64),
        ("int16_t", DType::I16),
        ("uint8", DType::U8),
    ];
    for (name, dtype) in spellings {
        for big in [false, true] {
            let unsigned = matches!(dtype, DType::U8 | DType::U16 | DType::U32);
            let f = |x: i32| if unsigned { (x + 50) as f64 } else { x as f64 };
            let h = header(&[
                &format!("type: {name}"),
                "dimension: 3",
                "sizes: 4 3 2",
                "spacings: 0.5 1 2",
                &format!("endian: {}", if big { "big" } else { "little" }),
                "encoding: raw",
                "key:=value: ignored",
            ]);
            let mut b = h.into_bytes();
            b.push(b'\n');
            b.extend(samples(dtype, big, f));
            let p = tmp("types.nrrd");
            std::fs::write(&p, b).unwrap();
            let mut r = open(&p, &VolumeOptions::default()).unwrap();
            let h = r.header().clone();
            assert_eq!(
                (h.dims, h.dtype, h.spacing),
                (DIMS, dtype, [0.5, 1.0, 2.0]),
                "{name}"
            );
            assert_eq!(h.frame, None);
            check_boxes(&mut *r, |i, j, k| f(v(i, j, k)));
        }
    }
}

#[test]
fn space_directions_give_orientation_origin_frame_and_units() {
    // LPS: file x along -L (flipped), file y along S, file z along P
    let h = header(&[
        "type: short",
        "dimension: 3",
        "space: left-posterior-superior",
        "sizes: 4 3 2",
        "space directions: (-0.5,0,0) (0,0,2) (0, 3, 0)",
        "space origin: (10,20,30)",
        "space units: \"mm\" \"mm\" \"mm\"",
        "sample units: \"HU\"",
        "kinds: domain domain domain",
        "endian: little",
        "encoding: raw",
    ]);
    let mut b = h.into_bytes();
    b.push(b'\n');
    b.extend(samples(DType::I16, false, |x| x as f64));
    let p = tmp("lps.nrrd");
    std::fs::write(&p, &b).unwrap();
    assert_eq!(super::super::sniff(&p), Some(VolumeFormat::Nrrd));
    let r = open(&p, &VolumeOptions::default()).unwrap();
    let h = r.header().clone();
    assert_eq!(h.spacing, [0.5, 2.0, 3.0]);
    assert_eq!(
        h.axes,
        [
            AxisMap {
                axis: 0,
                flip: true
            },
            AxisMap {
                axis: 2,
                flip: false
            },
            AxisMap {
                axis: 1,
                flip: false
            }
        ]
    );
    assert_eq!(h.origin, [10.0, 20.0, 30.0]);
    assert_eq!(h.frame.as_deref(), Some("LPS"));
    assert_eq!(h.length_unit.as_deref(), Some("mm"));
    assert_eq!(h.value_unit.as_deref(), Some("HU"));
    // the world frame: x reversed, y the file's z, z the file's y
    let mut vol = Volume::open(&p, None, &VolumeOptions::default()).unwrap();
    assert_eq!(vol.dims, [4, 2, 3]);
    assert_eq!(vol.origin, [10.0 - 1.5, 20.0, 30.0]);
    let s = vol.read_block(0..2, 0..3).unwrap();
    let mut n = 0;
    for wz in 0..3 {
        for wy in 0..2 {
            for wx in 0..4 {
                assert_eq!(s.get(n), v(3 - wx, wz, wy) as f64);
                n += 1;
            }
        }
    }

    // left-anterior-superior reads as RAS with x negated
    let las = String::from_utf8(b[..b.len() - 48].to_vec())
        .unwrap()
        .replace("left-posterior-superior", "left-anterior-superior");
    let mut las = las.into_bytes();
    las.extend(samples(DType::I16, false, |x| x as f64));
    std::fs::write(&p, &las).unwrap();
    let h = open(&p, &VolumeOptions::default())
        .unwrap()
        .header()
        .clone();
    assert_eq!(h.frame.as_deref(), Some("RAS"));
    assert_eq!(h.origin, [-10.0, 20.0, 30.0]);
    assert_eq!(
        h.axes[0],
        AxisMap {
            axis: 0,
            flip: false
        }
    );

    // an oblique direction is refused, saying so
    let obl = String::from_utf8(b[..b.len() - 48].to_vec())
        .unwrap()
        .replace("(-0.5,0,0) (0,0,2)", "(-0.5,0.5,0) (0,0,2)");
    let mut obl = obl.into_bytes();
    obl.extend(samples(DType::I16, false, |x| x as f64));
    std::fs::write(&p, &obl).unwrap();
    let e = open(&p, &VolumeOptions::default()).err().unwrap();
    assert!(matches!(e, VolumeError::Unsupported { .. }), "{e}");
    assert!(e.to_string().contains("oblique"), "{e}");
}

#[test]
fn gzip_ascii_and_hex_encodings_read_the_same_voxels() {
    let raw = samples(DType::U16, true, |x| (x + 50) as f64);
    let want = |i, j, k| (v(i, j, k) + 50) as f64;
    let fields = |enc: &str, extra: &str| {
        header(&[
            "type: uint16",
            "dimension: 3",
            "sizes: 4 3 2",
            "endian: big",
            &format!("encoding: {enc}"),
            extra,
        ])
    };
    // gzip, with a byte skip counted in the decompressed stream
    let mut b = fields("gzip", "byte skip: 3").into_bytes();
    b.push(b'\n');
    let mut body = b"abc".to_vec();
    body.extend(&raw);
    b.extend(gzip(&body));
    let p = tmp("gz.nrrd");
    std::fs::write(&p, &b).unwrap();
    let mut r = open(&p, &VolumeOptions::default()).unwrap();
    check_boxes(&mut *r, want);
    // boxes in file order reuse the decoder; one before the last reopens it
    let a = r.read_box([0, 0, 1], [4, 3, 2]).unwrap();
    let c = r.read_box([0, 0, 0], [4, 3, 1]).unwrap();
    assert_eq!((a.get(0), c.get(0)), (want(0, 0, 1), want(0, 0, 0)));
    // a truncated gzip stream is an error naming the data
    std::fs::write(&p, &b[..b.len() - 20]).unwrap();
    let mut r = open(&p, &VolumeOptions::default()).unwrap();
    assert!(r.read_box([0, 0, 0], DIMS).is_err());

    // ascii, commas and line breaks between values
    let mut b = fields("ascii", "").into_bytes();
    b.push(b'\n');
    for k in 0..2 {
        for j in 0..3 {
            let row: Vec<String> = (0..4).map(|i| want(i, j, k).to_string()).collect();
            b.extend(row.join(", ").as_bytes());
            b.push(b'\n');
        }
    }
    let p = tmp("ascii.nrrd");
    std::fs::write(&p, &b).unwrap();
    let mut r = open(&p, &VolumeOptions::default()).unwrap();
    check_boxes(&mut *r, want);
    // a value that is not a number is an error naming it
    let mut bad = b.clone();
    let at = bad.len() - 3;
    bad[at] = b'x';
    std::fs::write(&p, &bad).unwrap();
    let e = open(&p, &VolumeOptions::default())
        .unwrap()
        .read_box([0, 0, 0], DIMS)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("not a number"), "{e}");

    // hex
    let mut b = fields("hex", "").into_bytes();
    b.push(b'\n');
    for (n, x) in raw.iter().enumerate() {
        b.extend(format!("{x:02x}").as_bytes());
        if n % 16 == 15 {
            b.push(b'\n');
        }
    }
    let p = tmp("hex.nrrd");
    std::fs::write(&p, &b).unwrap();
    let mut r = open(&p, &VolumeOptions::default()).unwrap();
    check_boxes(&mut *r, want);
}

#[test]
fn detached_headers_find_their_data_files() {
    let raw = samples(DType::F32, false, |x| x as f64 * 0.5);
    let want = |i, j, k| v(i, j, k) as f64 * 0.5;
    let base = [
        "type: float",
        "dimension: 3",
        "sizes: 4 3 2",
        "spacings: 1 1 1",
        "endian: little",
    ];
    let write = |name: &str, lines: &[&str]| {
        let mut l = base.to_vec();
        l.extend_from_slice(lines);
        let p = tmp(name);
        std::fs::write(&p, header(&l)).unwrap();
        p
    };
    // one file, a line skip and a byte skip
    let mut d = b"junk line\nanother\nXY".to_vec();
    d.extend(&raw);
    std::fs::write(tmp("one.raw"), &d).unwrap();
    let p = write(
        "one.nhdr",
        &[
            "encoding: raw",
            "line skip: 2",
            "byte skip: 2",
            "data file: one.raw",
        ],
    );
    check_boxes(&mut *open(&p, &VolumeOptions::default()).unwrap(), want);

    // byte skip -1: the samples end the file
    let mut d = vec![7u8; 13];
    d.extend(&raw);
    std::fs::write(tmp("tail.raw"), &d).unwrap();
    let p = write(
        "tail.nhdr",
        &["encoding: raw", "byte skip: -1", "datafile: tail.raw"],
    );
    check_boxes(&mut *open(&p, &VolumeOptions::default()).unwrap(), want);

    // gzip data file
    std::fs::write(tmp("one.raw.gz"), gzip(&raw)).unwrap();
    let p = write("gz.nhdr", &["encoding: gz", "data file: one.raw.gz"]);
    check_boxes(&mut *open(&p, &VolumeOptions::default()).unwrap(), want);

    // a LIST of slices, and a format string
    let half = raw.len() / 2;
    std::fs::write(tmp("s-007.raw"), &raw[..half]).unwrap();
    std::fs::write(tmp("s-009.raw"), &raw[half..]).unwrap();
    let p = write(
        "list.nhdr",
        &["encoding: raw", "data file: LIST", "s-007.raw", "s-009.raw"],
    );
    check_boxes(&mut *open(&p, &VolumeOptions::default()).unwrap(), want);
    let p = write(
        "fmt.nhdr",
        &["encoding: raw", "data file: s-%03d.raw 7 9 2 2"],
    );
    check_boxes(&mut *open(&p, &VolumeOptions::default()).unwrap(), want);
    // a list of the wrong length, and a missing file, are refused naming them
    let p = write(
        "short.nhdr",
        &["encoding: raw", "data file: LIST", "s-007.raw"],
    );
    let e = open(&p, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("LIST names 1 files; the sizes need 2"), "{e}");
    let p = write("gone.nhdr", &["encoding: raw", "data file: nothere.raw"]);
    let e = open(&p, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("nothere.raw"), "{e}");
    // a data file shorter than the samples
    std::fs::write(tmp("short.raw"), &raw[..raw.len() - 1]).unwrap();
    let p = write("trunc.nhdr", &["encoding: raw", "data file: short.raw"]);
    let e = open(&p, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("short.raw") && e.contains("truncated"), "{e}");
}

#[test]
fn a_fourth_axis_is_components_or_frames() {
    // RGB-color first: interleaved, named r g b
    let mut data = Vec::new();
    for k in 0..2 {
        for j in 0..3 {
            for i in 0..4 {
                for c in 0..3 {
                    data.push((v(i, j, k) + 50 + c) as u8);
                }
            }
        }
    }
    let mut b = header(&[
        "type: uchar",
        "dimension: 4",
        "sizes: 3 4 3 2",
        "kinds: RGB-color domain domain domain",
        "space directions: none (1,0,0) (0,1,0) (0,0,1)",
        "encoding: raw",
    ])
    .into_bytes();
    b.push(b'\n');
    b.extend(&data);
    let p = tmp("rgb.nrrd");
    std::fs::write(&p, &b).unwrap();
    let e = open(&p, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("0 (r), 1 (g), 2 (b)"), "{e}");
    let mut r = open(&p, &opts(Some("g"), None)).unwrap();
    assert_eq!((r.header().dims, r.header().dtype), (DIMS, DType::U8));
    check_boxes(&mut *r, |i, j, k| (v(i, j, k) + 51) as f64);
    let mut r = open(&p, &opts(Some("mag"), None)).unwrap();
    assert_eq!(r.header().dtype, DType::F32);
    check_boxes(&mut *r, |i, j, k| {
        let x = (v(i, j, k) + 50) as f64;
        ((x * x + (x + 1.0).powi(2) + (x + 2.0).powi(2)).sqrt() as f32) as f64
    });

    // time last: one volume a frame
    let mut b = header(&[
        "type: int",
        "dimension: 4",
        "sizes: 4 3 2 3",
        "kinds: domain domain domain time",
        "endian: little",
        "encoding: raw",
    ])
    .into_bytes();
    b.push(b'\n');
    for t in 0..3 {
        b.extend(samples(DType::I32, false, |x| (x + 1000 * t) as f64));
    }
    let p = tmp("time.nrrd");
    std::fs::write(&p, &b).unwrap();
    let e = open(&p, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("3 frames") && e.contains("--frame"), "{e}");
    let e = open(&p, &opts(None, Some(3))).err().unwrap().to_string();
    assert!(e.contains("--frame 3"), "{e}");
    let mut r = open(&p, &opts(None, Some(2))).unwrap();
    check_boxes(&mut *r, |i, j, k| (v(i, j, k) + 2000) as f64);

    // a vector axis last: --scalar K picks a volume, mag is refused
    let vec_last = {
        let mut h = header(&[
            "type: int",
            "dimension: 4",
            "sizes: 4 3 2 3",
            "kinds: domain domain domain 3-vector",
            "endian: little",
            "encoding: raw",
        ])
        .into_bytes();
        h.push(b'\n');
        for t in 0..3 {
            h.extend(samples(DType::I32, false, |x| (x + 1000 * t) as f64));
        }
        h
    };
    std::fs::write(&p, &vec_last).unwrap();
    let mut r = open(&p, &opts(Some("1"), None)).unwrap();
    check_boxes(&mut *r, |i, j, k| (v(i, j, k) + 1000) as f64);
    let e = open(&p, &opts(Some("mag"), None)).err().unwrap();
    assert!(matches!(e, VolumeError::Unsupported { .. }), "{e}");

    // list first: interleaved frames
    let mut b = header(&[
        "type: short",
        "dimension: 4",
        "sizes: 2 4 3 2",
        "kinds: list domain domain domain",
        "endian: little",
        "encoding: raw",
    ])
    .into_bytes();
    b.push(b'\n');
    for k in 0..2 {
        for j in 0..3 {
            for i in 0..4 {
                for t in 0..2 {
                    b.extend(((v(i, j, k) + 1000 * t) as i16).to_le_bytes());
                }
            }
        }
    }
    std::fs::write(&p, &b).unwrap();
    let mut r = open(&p, &opts(None, Some(1))).unwrap();
    check_boxes(&mut *r, |i, j, k| (v(i, j, k) + 1000) as f64);

    // no kinds and no directions: which axis is not spatial is unknown
    let amb = String::from_utf8_lossy(&b).replace("kinds: list domain domain domain\n", "");
    std::fs::write(&p, amb.as_bytes()).unwrap();
    let e = open(&p, &opts(None, Some(1))).err().unwrap().to_string();
    assert!(e.contains("kinds"), "{e}");
}

#[test]
fn unsupported_fields_are_refused_clearly() {
    let cases: [(&[&str], &str); 8] = [
        (
            &[
                "type: int64",
                "dimension: 3",
                "sizes: 2 2 2",
                "encoding: raw",
            ],
            "64-bit",
        ),
        (
            &[
                "type: block",
                "dimension: 3",
                "sizes: 2 2 2",
                "encoding: raw",
            ],
            "block",
        ),
        (
            &[
                "type: uchar",
                "dimension: 3",
                "sizes: 2 2 2",
                "encoding: bzip2",
            ],
            "bzip2",
        ),
        (
            &["type: uchar", "dimension: 2", "sizes: 2 2", "encoding: raw"],
            "dimension",
        ),
        (
            &[
                "type: short",
                "dimension: 3",
                "sizes: 2 2 2",
                "encoding: raw",
            ],
            "endian",
        ),
        (
            &["type: uchar", "dimension: 3", "sizes: 2 2", "encoding: raw"],
            "2 values",
        ),
        (
            &[
                "type: uchar",
                "dimension: 3",
                "sizes: 2 2 2",
                "encoding: gzip",
                "byte skip: -1",
            ],
            "raw encoding only",
        ),
        (
            &[
                "type: uchar",
                "dimension: 3",
                "sizes: 2 2 2",
                "encoding: raw",
                "space: RAST",
            ],
            "time",
        ),
    ];
    for (lines, needle) in cases {
        let mut b = header(lines).into_bytes();
        b.push(b'\n');
        b.extend([0u8; 64]);
        let p = tmp("refused.nrrd");
        std::fs::write(&p, &b).unwrap();
        let e = open(&p, &VolumeOptions::default())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains(needle), "{needle}: {e}");
        assert!(e.contains("refused.nrrd"), "{e}");
    }
    // an attached file one byte short
    let mut b = header(&[
        "type: uchar",
        "dimension: 3",
        "sizes: 4 3 2",
        "encoding: raw",
    ])
    .into_bytes();
    b.push(b'\n');
    b.extend([0u8; 23]);
    let p = tmp("short.nrrd");
    std::fs::write(&p, &b).unwrap();
    let e = open(&p, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("truncated"), "{e}");
}

#[test]
fn broken_nrrds_are_refused_never_panic() {
    let raw = samples(DType::I16, false, |x| x as f64);
    let fields = [
        "type: short",
        "dimension: 4",
        "space: left-posterior-superior",
        "sizes: 2 4 3 2",
        "kinds: vector domain domain domain",
        "space directions: none (-1,0,0) (0,1,0) (0,0,2.5)",
        "space origin: (1,2,3)",
        "endian: little",
    ];
    let mut good_raw = header(&[&fields[..], &["encoding: raw"]].concat()).into_bytes();
    good_raw.push(b'\n');
    let head = good_raw.len();
    for x in raw.chunks(2) {
        good_raw.extend(x);
        good_raw.extend(x);
    }
    let mut good_gz = header(&[&fields[..], &["encoding: gzip"]].concat()).into_bytes();
    good_gz.push(b'\n');
    let gz_head = good_gz.len();
    good_gz.extend(gzip(&good_raw[head..]));
    let p = tmp("broken.nrrd");
    let try_read = |b: &[u8]| {
        std::fs::write(&p, b).unwrap();
        for o in [opts(Some("1"), None), opts(Some("mag"), None)] {
            if let Ok(mut v) = Volume::open(&p, Some(VolumeFormat::Nrrd), &o) {
                let (ny, nz) = (v.dims[1], v.dims[2]);
                let _ = v.read_block(0..ny.min(2), 0..nz.min(2));
                let _ = v.read_block(ny.saturating_sub(1)..ny, nz.saturating_sub(1)..nz);
            }
        }
    };
    // the good files read
    for g in [&good_raw, &good_gz] {
        std::fs::write(&p, g).unwrap();
        let mut r = open(&p, &opts(Some("0"), None)).unwrap();
        check_boxes(&mut *r, |i, j, k| v(i, j, k) as f64);
    }
    for good in [&good_raw, &good_gz] {
        for cut in 0..good.len() {
            try_read(&good[..cut]);
        }
    }
    for (good, h) in [(&good_raw, head), (&good_gz, gz_head)] {
        for at in 0..h + 8 {
            for x in [b'\n', b' ', b'0', b'9', b'-', b'(', b')', b',', b':', 0xff] {
                let mut b = good.clone();
                b[at] = x;
                try_read(&b);
            }
        }
    }
}

#[test]
fn format_strings_expand_like_printf() {
    assert_eq!(format_name("s%03d.raw", 7).as_deref(), Some("s007.raw"));
    assert_eq!(format_name("s%d.raw", 12).as_deref(), Some("s12.raw"));
    assert_eq!(format_name("%4u%%", 3).as_deref(), Some("   3%"));
    assert_eq!(format_name("no conversion", 3), None);
    assert_eq!(format_name("%d%d", 3), None);
    assert_eq!(format_name("%s", 3), None);
}
