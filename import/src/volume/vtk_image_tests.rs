//! `.vti` and legacy `STRUCTURED_POINTS` files written here in each encoding VTK writes (VTK's own
//! files are read in `server/tests/volumes.rs`).

use super::super::{
    open_reader, AxisMap, DType, ScalarChoice, Volume, VolumeError, VolumeFormat, VolumeOptions,
};
use super::*;
use std::io::Write;

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("tetwave-vtkimage-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

const DIMS: [usize; 3] = [4, 3, 2];

/// Voxel value of index (i, j, k): distinct everywhere.
fn v(i: usize, j: usize, k: usize) -> i16 {
    (i + 10 * j + 100 * k) as i16 - 50
}

/// The scalar array "density" (i16) in file order.
fn density() -> Vec<i16> {
    let mut out = Vec::new();
    for k in 0..DIMS[2] {
        for j in 0..DIMS[1] {
            for i in 0..DIMS[0] {
                out.push(v(i, j, k));
            }
        }
    }
    out
}

/// The vector array "vel" (f32, 3 components): (d, -d, 2d).
fn vel() -> Vec<f32> {
    density()
        .iter()
        .flat_map(|&d| [d as f32, -(d as f32), 2.0 * d as f32])
        .collect()
}

fn b64(b: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in b.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                s.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

#[derive(Clone, Copy, Debug)]
struct Enc {
    big: bool,
    header64: bool,
    /// zlib block size (`None`: uncompressed)
    zlib: Option<usize>,
}

/// An array's binary form: header words then data (compressed in blocks when asked); with
/// `split`, header and data as VTK's base64 writes them (each encoded on its own).
fn binary_parts(data: &[u8], e: Enc) -> (Vec<u8>, Vec<u8>) {
    let word = |x: usize| -> Vec<u8> {
        match (e.header64, e.big) {
            (true, true) => (x as u64).to_be_bytes().to_vec(),
            (true, false) => (x as u64).to_le_bytes().to_vec(),
            (false, true) => (x as u32).to_be_bytes().to_vec(),
            (false, false) => (x as u32).to_le_bytes().to_vec(),
        }
    };
    match e.zlib {
        None => (word(data.len()), data.to_vec()),
        Some(bs) => {
            let blocks: Vec<Vec<u8>> = data
                .chunks(bs)
                .map(|c| {
                    let mut z =
                        flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
                    z.write_all(c).unwrap();
                    z.finish().unwrap()
                })
                .collect();
            let last = data.len() % bs;
            let mut h = word(blocks.len());
            h.extend(word(bs));
            h.extend(word(last));
            for b in &blocks {
                h.extend(word(b.len()));
            }
            (h, blocks.concat())
        }
    }
}

fn le_or_be_i16(x: &[i16], big: bool) -> Vec<u8> {
    x.iter()
        .flat_map(|v| {
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        })
        .collect()
}

fn le_or_be_f32(x: &[f32], big: bool) -> Vec<u8> {
    x.iter()
        .flat_map(|v| {
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        })
        .collect()
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Mode {
    Ascii,
    Binary,
    AppendedRaw,
    AppendedBase64,
}

/// A `.vti` of "density" and "vel" on extent x 2..5, y 0..2, z 1..2, origin (1, 2, 3), spacing
/// (0.5, 1, 2), with `direction`.
fn vti(mode: Mode, e: Enc, direction: &str) -> Vec<u8> {
    let arrays = [
        ("density", "Int16", 1, le_or_be_i16(&density(), e.big)),
        ("vel", "Float32", 3, le_or_be_f32(&vel(), e.big)),
    ];
    let mut s = format!(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\" \
         byte_order=\"{}\" header_type=\"{}\"{}>\n  <ImageData WholeExtent=\"2 5 0 2 1 2\" \
         Origin=\"1 2 3\" Spacing=\"0.5 1 2\" Direction=\"{direction}\">\n  <Piece \
         Extent=\"2 5 0 2 1 2\">\n    <PointData Scalars=\"density\">\n",
        if e.big { "BigEndian" } else { "LittleEndian" },
        if e.header64 { "UInt64" } else { "UInt32" },
        if e.zlib.is_some() {
            " compressor=\"vtkZLibDataCompressor\""
        } else {
            ""
        },
    );
    let mut appended: Vec<u8> = Vec::new();
    for (name, ty, nc, bytes) in &arrays {
        let open =
            format!("      <DataArray type=\"{ty}\" Name=\"{name}\" NumberOfComponents=\"{nc}\"");
        match mode {
            Mode::Ascii => {
                let text: Vec<String> = if *ty == "Int16" {
                    density().iter().map(|x| x.to_string()).collect()
                } else {
                    vel().iter().map(|x| x.to_string()).collect()
                };
                s += &format!(
                    "{open} format=\"ascii\">\n        {}\n        <InformationKey \
                     name=\"x\"><Value index=\"0\">1</Value></InformationKey>\n      \
                     </DataArray>\n",
                    text.join(" ")
                );
            }
            Mode::Binary => {
                let (h, d) = binary_parts(bytes, e);
                s += &format!(
                    "{open} format=\"binary\">\n        {}{}\n      </DataArray>\n",
                    b64(&h),
                    b64(&d)
                );
            }
            Mode::AppendedRaw | Mode::AppendedBase64 => {
                let (h, d) = binary_parts(bytes, e);
                s += &format!(
                    "{open} format=\"appended\" offset=\"{}\"/>\n",
                    appended.len()
                );
                if mode == Mode::AppendedRaw {
                    appended.extend(h);
                    appended.extend(d);
                } else {
                    appended.extend(b64(&h).bytes());
                    appended.extend(b64(&d).bytes());
                }
            }
        }
    }
    s += "    </PointData>\n    <CellData>\n    </CellData>\n  </Piece>\n  </ImageData>\n";
    let mut out = s.into_bytes();
    if matches!(mode, Mode::AppendedRaw | Mode::AppendedBase64) {
        out.extend(
            format!(
                "  <AppendedData encoding=\"{}\">\n   _",
                if mode == Mode::AppendedRaw {
                    "raw"
                } else {
                    "base64"
                }
            )
            .bytes(),
        );
        out.extend(appended);
        out.extend(b"\n  </AppendedData>\n");
    }
    out.extend(b"</VTKFile>\n");
    out
}

fn opts(scalar: Option<&str>) -> VolumeOptions {
    VolumeOptions {
        scalar: scalar.map(ScalarChoice::parse),
        ..VolumeOptions::default()
    }
}

fn check_boxes(r: &mut dyn VolumeReader, want: impl Fn(usize, usize, usize) -> f64) {
    let d = r.header().dims;
    for (lo, hi) in [
        ([0, 0, 0], d),
        ([1, 1, 1], d),
        ([0, 0, 1], d),
        ([1, 0, 0], [3, 2, 1]),
        ([0, 2, 0], [d[0], 3, 2]),
        ([0, 0, 0], [d[0], 1, 1]),
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

const IDENTITY: &str = "1 0 0 0 1 0 0 0 1";

#[test]
fn vti_in_every_encoding_reads_the_same_voxels() {
    let encs = [
        Enc {
            big: false,
            header64: false,
            zlib: None,
        },
        Enc {
            big: true,
            header64: true,
            zlib: None,
        },
        // blocks of 10 bytes: a row of the box spans several, the last is partial
        Enc {
            big: false,
            header64: false,
            zlib: Some(10),
        },
        Enc {
            big: true,
            header64: true,
            zlib: Some(16),
        },
        Enc {
            big: false,
            header64: true,
            zlib: Some(1 << 15),
        },
    ];
    let mut n = 0;
    for mode in [
        Mode::Ascii,
        Mode::Binary,
        Mode::AppendedRaw,
        Mode::AppendedBase64,
    ] {
        for e in encs {
            if mode == Mode::Ascii && (e.zlib.is_some() || e.big) {
                continue;
            }
            let p = tmp(&format!("t{n}.vti"));
            n += 1;
            std::fs::write(&p, vti(mode, e, IDENTITY)).unwrap();
            assert_eq!(super::super::sniff(&p), Some(VolumeFormat::Vti));
            let what = format!("{mode:?} {e:?}");
            let mut r = open_reader(&p, VolumeFormat::Vti, &VolumeOptions::default())
                .unwrap_or_else(|err| panic!("{what}: {err}"));
            let h = r.header().clone();
            assert_eq!((h.dims, h.dtype), (DIMS, DType::I16), "{what}");
            assert_eq!(h.spacing, [0.5, 1.0, 2.0]);
            // voxel [0,0,0] is the extent's start (2, 0, 1)
            assert_eq!(h.origin, [2.0, 2.0, 5.0]);
            check_boxes(&mut *r, |i, j, k| v(i, j, k) as f64);
            // the vector array by name and component, or its magnitude
            let mut r = open_reader(&p, VolumeFormat::Vti, &opts(Some("vel:2"))).unwrap();
            assert_eq!(r.header().dtype, DType::F32);
            check_boxes(&mut *r, |i, j, k| 2.0 * v(i, j, k) as f64);
            let mut r = open_reader(&p, VolumeFormat::Vti, &opts(Some("vel:mag"))).unwrap();
            check_boxes(&mut *r, |i, j, k| {
                ((6.0f64).sqrt() * (v(i, j, k) as f64).abs()) as f32 as f64
            });
            let e = open_reader(&p, VolumeFormat::Vti, &opts(Some("vel")))
                .err()
                .unwrap()
                .to_string();
            assert!(e.contains("3 components") && e.contains("vel:K"), "{e}");
            let e = open_reader(&p, VolumeFormat::Vti, &opts(Some("nope")))
                .err()
                .unwrap()
                .to_string();
            assert!(e.contains("density (1 component(s)), vel (3"), "{e}");
        }
    }
}

#[test]
fn vti_direction_gives_orientation() {
    // file x along -y, file y along +x, file z along +z
    let p = tmp("dir.vti");
    let e = Enc {
        big: false,
        header64: false,
        zlib: None,
    };
    std::fs::write(&p, vti(Mode::AppendedRaw, e, "0 1 0 -1 0 0 0 0 1")).unwrap();
    let r = open_reader(&p, VolumeFormat::Vti, &VolumeOptions::default()).unwrap();
    let h = r.header().clone();
    assert_eq!(
        h.axes,
        [
            AxisMap {
                axis: 1,
                flip: true
            },
            AxisMap {
                axis: 0,
                flip: false
            },
            AxisMap {
                axis: 2,
                flip: false
            }
        ]
    );
    assert_eq!(h.spacing, [0.5, 1.0, 2.0]);
    // origin + D · (extent start · spacing) = (1, 2, 3) + (0, -1, 2)
    assert_eq!(h.origin, [1.0, 1.0, 5.0]);
    let mut vol = Volume::open(&p, None, &VolumeOptions::default()).unwrap();
    assert_eq!(vol.dims, [3, 4, 2]);
    let s = vol.read_block(0..4, 0..2).unwrap();
    let mut n = 0;
    for wz in 0..2 {
        for wy in 0..4 {
            for wx in 0..3 {
                assert_eq!(s.get(n), v(3 - wy, wx, wz) as f64);
                n += 1;
            }
        }
    }
    std::fs::write(&p, vti(Mode::AppendedRaw, e, "0.7 0.7 0 -0.7 0.7 0 0 0 1")).unwrap();
    let e = open_reader(&p, VolumeFormat::Vti, &VolumeOptions::default())
        .err()
        .unwrap();
    assert!(
        matches!(e, VolumeError::Unsupported { .. }) && e.to_string().contains("oblique"),
        "{e}"
    );
}

#[test]
fn vti_refusals_name_what_is_not_read() {
    let e = Enc {
        big: false,
        header64: false,
        zlib: None,
    };
    let good = String::from_utf8(vti(Mode::Ascii, e, IDENTITY)).unwrap();
    let cases = [
        (
            "type=\"ImageData\"",
            "type=\"UnstructuredGrid\"",
            "mesh import",
        ),
        (
            "<PointData Scalars=\"density\">",
            "<CellData>",
            "mismatched",
        ),
        (
            "  <Piece Extent=\"2 5 0 2 1 2\">",
            "<Piece Extent=\"2 5 0 2 1 2\"></Piece><Piece Extent=\"2 5 0 2 1 2\">",
            "2 pieces",
        ),
        ("type=\"Int16\"", "type=\"Int64\"", "Int64"),
        (
            "header_type=\"UInt32\"",
            "header_type=\"UInt32\" compressor=\"vtkLZ4DataCompressor\"",
            "LZ4",
        ),
        (
            "Extent=\"2 5 0 2 1 2\">\n    <P",
            "Extent=\"2 4 0 2 1 2\">\n    <P",
            "partial piece",
        ),
    ];
    for (from, to, needle) in cases {
        let p = tmp("refused.vti");
        assert!(good.contains(from), "{from}");
        std::fs::write(&p, good.replacen(from, to, 1)).unwrap();
        let e = open_reader(&p, VolumeFormat::Vti, &VolumeOptions::default())
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains(needle) && e.contains("refused.vti"),
            "{needle}: {e}"
        );
    }
    // cell data only
    let cells =
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\">\n<ImageData \
                 WholeExtent=\"0 2 0 2 0 2\"><Piece Extent=\"0 2 0 2 0 2\"><PointData/><CellData \
                 Scalars=\"c\"><DataArray type=\"Float32\" Name=\"c\" format=\"ascii\">1 2 3 4 5 \
                 6 7 8</DataArray></CellData></Piece></ImageData></VTKFile>";
    let p = tmp("cells.vti");
    std::fs::write(&p, cells).unwrap();
    let e = open_reader(&p, VolumeFormat::Vti, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("cell data only"), "{e}");
}

/// A legacy file of "density" (SCALARS, with a lookup table line), then a FIELD with "vel", and
/// cell data and METADATA blocks in between, as VTK 9 writes them.
fn legacy(binary: bool, spacing: &str) -> Vec<u8> {
    let mut b = format!(
        "# vtk DataFile Version 5.1\nvtk output\n{}\nDATASET STRUCTURED_POINTS\nDIMENSIONS 4 3 \
         2\nSPACING {spacing}\nORIGIN 1 2 3\nCELL_DATA 6\nSCALARS cells float\nLOOKUP_TABLE \
         default\n",
        if binary { "BINARY" } else { "ASCII" }
    )
    .into_bytes();
    let cells: Vec<f32> = (0..6).map(|x| x as f32).collect();
    let put_f32 = |b: &mut Vec<u8>, xs: &[f32]| {
        if binary {
            for x in xs {
                b.extend(x.to_be_bytes());
            }
        } else {
            let s: Vec<String> = xs.iter().map(|x| x.to_string()).collect();
            b.extend(s.join(" ").bytes());
        }
        b.push(b'\n');
    };
    put_f32(&mut b, &cells);
    b.extend(b"POINT_DATA 24\nFIELD FieldData 1\nvel 3 24 float\n");
    put_f32(&mut b, &vel());
    b.extend(b"METADATA\nINFORMATION 1\nNAME L2_NORM_RANGE LOCATION vtkDataArray\nDATA 2 0 56\n\n");
    b.extend(b"SCALARS density short 1\nLOOKUP_TABLE default\n");
    if binary {
        for x in density() {
            b.extend(x.to_be_bytes());
        }
    } else {
        let s: Vec<String> = density().iter().map(|x| x.to_string()).collect();
        b.extend(s.join(" ").bytes());
    }
    b.extend(b"\nMETADATA\nINFORMATION 0\n\n");
    b
}

#[test]
fn legacy_structured_points_ascii_and_binary() {
    for binary in [false, true] {
        let p = tmp(if binary { "sp_bin.vtk" } else { "sp_ascii.vtk" });
        std::fs::write(&p, legacy(binary, "0.5 1 -2")).unwrap();
        assert_eq!(
            super::super::sniff(&p),
            Some(VolumeFormat::VtkStructuredPoints)
        );
        let mut r = open_reader(
            &p,
            VolumeFormat::VtkStructuredPoints,
            &VolumeOptions::default(),
        )
        .unwrap();
        let h = r.header().clone();
        assert_eq!((h.dims, h.dtype), (DIMS, DType::I16));
        assert_eq!(h.spacing, [0.5, 1.0, 2.0]);
        assert_eq!(
            h.axes[2],
            AxisMap {
                axis: 2,
                flip: true
            }
        );
        assert_eq!(h.origin, [1.0, 2.0, 3.0]);
        check_boxes(&mut *r, |i, j, k| v(i, j, k) as f64);
        let mut r =
            open_reader(&p, VolumeFormat::VtkStructuredPoints, &opts(Some("vel:1"))).unwrap();
        check_boxes(&mut *r, |i, j, k| -(v(i, j, k) as f64));
        let e = open_reader(&p, VolumeFormat::VtkStructuredPoints, &opts(Some("cells")))
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("no point array"), "{e}");
    }
    // a binary file cut inside the chosen array
    let b = legacy(true, "1 1 1");
    let p = tmp("sp_short.vtk");
    std::fs::write(&p, &b[..b.len() - 30]).unwrap();
    let e = open_reader(
        &p,
        VolumeFormat::VtkStructuredPoints,
        &VolumeOptions::default(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("truncated"), "{e}");
    // an unstructured grid is for the mesh import
    let p = tmp("ug.vtk");
    std::fs::write(
        &p,
        "# vtk DataFile Version 3.0\nx\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 0 float\n",
    )
    .unwrap();
    let e = open_reader(
        &p,
        VolumeFormat::VtkStructuredPoints,
        &VolumeOptions::default(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("STRUCTURED_POINTS"), "{e}");
}

#[test]
fn broken_image_files_are_refused_never_panic() {
    let e = Enc {
        big: false,
        header64: false,
        zlib: Some(16),
    };
    let files: Vec<(Vec<u8>, VolumeFormat)> = vec![
        (vti(Mode::AppendedRaw, e, IDENTITY), VolumeFormat::Vti),
        (vti(Mode::AppendedBase64, e, IDENTITY), VolumeFormat::Vti),
        (vti(Mode::Binary, e, IDENTITY), VolumeFormat::Vti),
        (
            vti(Mode::Ascii, Enc { zlib: None, ..e }, IDENTITY),
            VolumeFormat::Vti,
        ),
        (legacy(true, "1 1 1"), VolumeFormat::VtkStructuredPoints),
        (legacy(false, "1 1 1"), VolumeFormat::VtkStructuredPoints),
    ];
    let p = tmp("broken.img");
    let try_read = |b: &[u8], format: VolumeFormat| {
        std::fs::write(&p, b).unwrap();
        for o in [opts(None), opts(Some("vel:mag"))] {
            if let Ok(mut v) = Volume::open(&p, Some(format), &o) {
                let (ny, nz) = (v.dims[1], v.dims[2]);
                let _ = v.read_block(0..ny.min(2), 0..nz.min(2));
                let _ = v.read_block(ny.saturating_sub(1)..ny, nz.saturating_sub(1)..nz);
            }
        }
    };
    for (good, format) in &files {
        std::fs::write(&p, good).unwrap();
        let mut r = open_reader(&p, *format, &VolumeOptions::default()).unwrap();
        check_boxes(&mut *r, |i, j, k| v(i, j, k) as f64);
        for cut in (0..good.len()).step_by(7) {
            try_read(&good[..cut], *format);
        }
        for at in (0..good.len()).step_by(4) {
            for x in [b'9', b'<', b'"', b'_', 0xff] {
                let mut b = good.clone();
                b[at] = x;
                try_read(&b, *format);
            }
        }
    }
}

#[test]
fn zlib_blocks_outside_the_box_are_not_inflated() {
    // blocks of 10 bytes: density's 48 bytes are blocks 0..5, plane z = 1 its bytes 24..48
    // (blocks 2..5)
    let e = Enc {
        big: false,
        header64: false,
        zlib: Some(10),
    };
    let mut b = vti(Mode::AppendedRaw, e, IDENTITY);
    let data = b.windows(5).position(|w| w == b"\n   _").unwrap() + 5;
    // density's header is 3 + 5 words; block 0's zlib header follows
    let block0 = data + 32;
    assert_eq!(b[block0], 0x78);
    b[block0] = 0;
    let p = tmp("bad_block0.vti");
    std::fs::write(&p, &b).unwrap();
    let mut r = open_reader(&p, VolumeFormat::Vti, &VolumeOptions::default()).unwrap();
    let s = r.read_box([0, 0, 1], [4, 3, 2]).unwrap();
    assert_eq!(s.get(0), v(0, 0, 1) as f64);
    let e = r.read_box([0, 0, 0], [4, 3, 1]).err().unwrap().to_string();
    assert!(e.contains("zlib block 0"), "{e}");
}
