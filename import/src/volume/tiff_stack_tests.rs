//! Tests of the TIFF stack reader on files written here with the `tiff` crate's encoder (and,
//! for tiles, planar pages and odd tags, directories written tag by tag).

use super::*;
use crate::volume::{sniff, ScalarChoice, Volume};
use tiff::encoder::colortype::{self, ColorType as EncColor};
use tiff::encoder::compression::DeflateLevel;
use tiff::encoder::{Compression, Rational, TiffEncoder, TiffKind, TiffValue};
use tiff::tags::ResolutionUnit;

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("tetwave-tiff-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Voxel value of index (i, j, k): distinct everywhere in the small stacks here.
fn v(i: usize, j: usize, k: usize) -> u16 {
    (i + 10 * j + 100 * k) as u16
}

fn plane<T>(dims: [usize; 3], k: usize, f: impl Fn(u16) -> T) -> Vec<T> {
    let mut p = Vec::new();
    for j in 0..dims[1] {
        for i in 0..dims[0] {
            p.push(f(v(i, j, k)));
        }
    }
    p
}

/// Options to write a stack with.
#[derive(Clone)]
struct How<'a> {
    compression: Compression,
    rows_per_strip: Option<u32>,
    big: bool,
    description: Option<&'a str>,
    /// XResolution, YResolution, ResolutionUnit.
    resolution: Option<(Rational, Rational, ResolutionUnit)>,
}

const PLAIN: How = How {
    compression: Compression::Uncompressed,
    rows_per_strip: None,
    big: false,
    description: None,
    resolution: None,
};

fn write_pages<C: EncColor, K: TiffKind>(
    enc: &mut TiffEncoder<&mut std::fs::File, K>,
    dims: [usize; 3],
    how: &How,
    page: &dyn Fn(usize) -> Vec<C::Inner>,
) where
    [C::Inner]: TiffValue,
{
    for k in 0..dims[2] {
        let mut img = enc.new_image::<C>(dims[0] as u32, dims[1] as u32).unwrap();
        if let Some(r) = how.rows_per_strip {
            img.rows_per_strip(r).unwrap();
        }
        if k == 0 {
            if let Some(d) = how.description {
                img.encoder().write_tag(Tag::ImageDescription, d).unwrap();
            }
        }
        if let Some((x, y, u)) = &how.resolution {
            img.x_resolution(x.clone());
            img.y_resolution(y.clone());
            img.resolution_unit(*u);
        }
        img.write_data(&page(k)).unwrap();
    }
}

/// A multi-page TIFF of `dims[2]` pages of colour type `C`, page `k` given by `page`.
fn write_stack<C: EncColor>(
    path: &Path,
    dims: [usize; 3],
    how: How,
    page: &dyn Fn(usize) -> Vec<C::Inner>,
) where
    [C::Inner]: TiffValue,
{
    let mut f = std::fs::File::create(path).unwrap();
    if how.big {
        let mut enc = TiffEncoder::new_big(&mut f)
            .unwrap()
            .with_compression(how.compression);
        write_pages::<C, _>(&mut enc, dims, &how, page);
    } else {
        let mut enc = TiffEncoder::new(&mut f)
            .unwrap()
            .with_compression(how.compression);
        write_pages::<C, _>(&mut enc, dims, &how, page);
    }
}

fn write_u16(path: &Path, dims: [usize; 3], how: How) {
    write_stack::<colortype::Gray16>(path, dims, how, &|k| plane(dims, k, |x| x));
}

fn open_opts(p: &Path, o: &VolumeOptions) -> Result<Box<dyn VolumeReader>, VolumeError> {
    let r = open(p, o)?;
    r.header().check(p)?;
    Ok(r)
}

fn open_default(p: &Path) -> Result<Box<dyn VolumeReader>, VolumeError> {
    open_opts(p, &VolumeOptions::default())
}

/// Checks every voxel of several boxes against `expect(i, j, k)`.
fn check_boxes(r: &mut dyn VolumeReader, expect: &dyn Fn(usize, usize, usize) -> f64) {
    let d = r.header().dims;
    let boxes = [
        ([0, 0, 0], d),
        ([1, 1, 1], [d[0] - 1, d[1] - 1, d[2]]),
        ([0, d[1] - 2, d[2] - 1], [d[0], d[1], d[2]]),
        ([d[0] - 1, 0, 0], [d[0], 1, 1]),
        ([2, 3, 1], [d[0].min(5), d[1].min(5), 2]),
    ];
    for (lo, hi) in boxes {
        let s = r.read_box(lo, hi).unwrap();
        assert_eq!(s.dtype(), r.header().dtype);
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
}

fn err_of(r: Result<Box<dyn VolumeReader>, VolumeError>) -> String {
    r.err().expect("an error").to_string()
}

#[test]
fn multi_page_stacks_in_every_compression() {
    let dims = [7, 6, 4];
    let deflate = Compression::Deflate(DeflateLevel::Balanced);
    for (name, how) in [
        ("none.tif", PLAIN),
        (
            "strips.tif",
            How {
                rows_per_strip: Some(2),
                ..PLAIN
            },
        ),
        (
            "lzw.tif",
            How {
                compression: Compression::Lzw,
                rows_per_strip: Some(4),
                ..PLAIN
            },
        ),
        (
            "deflate.tif",
            How {
                compression: deflate,
                ..PLAIN
            },
        ),
        (
            "packbits.tif",
            How {
                compression: Compression::Packbits,
                ..PLAIN
            },
        ),
        ("big.tif", How { big: true, ..PLAIN }),
        (
            "big-deflate.tif",
            How {
                big: true,
                compression: deflate,
                rows_per_strip: Some(3),
                ..PLAIN
            },
        ),
    ] {
        let p = tmp(name);
        write_u16(&p, dims, how);
        assert_eq!(sniff(&p), Some(VolumeFormat::Tiff));
        let mut r = open_default(&p).unwrap();
        let h = r.header().clone();
        assert_eq!(h.format, VolumeFormat::Tiff);
        assert_eq!((h.dims, h.dtype), (dims, DType::U16), "{name}");
        // the encoder writes resolution 1/1 without unit: nothing stated
        assert_eq!(h.spacing, [1.0; 3]);
        assert_eq!(h.length_unit, None);
        assert!(
            h.notes.iter().any(|n| n.contains("no spacing")),
            "{:?}",
            h.notes
        );
        check_boxes(&mut *r, &|i, j, k| v(i, j, k) as f64);
    }
    // one component: --scalar mag is that component, --scalar 1 is not there
    let p = tmp("none.tif");
    let mag = VolumeOptions {
        scalar: Some(ScalarChoice::Magnitude),
        ..Default::default()
    };
    let mut r = open_opts(&p, &mag).unwrap();
    assert_eq!(r.header().dtype, DType::U16);
    check_boxes(&mut *r, &|i, j, k| v(i, j, k) as f64);
    let one = VolumeOptions {
        scalar: Some(ScalarChoice::Index(1)),
        ..Default::default()
    };
    assert!(err_of(open_opts(&p, &one)).contains("--scalar 1"));
}

#[test]
fn every_sample_type() {
    let dims = [5, 4, 3];
    let p = tmp("types.tif");
    let cases: Vec<(DType, Box<dyn Fn()>)> = vec![
        (
            DType::U8,
            Box::new(|| {
                write_stack::<colortype::Gray8>(&tmp("types.tif"), dims, PLAIN, &|k| {
                    plane(dims, k, |x| x as u8)
                })
            }),
        ),
        (
            DType::I8,
            Box::new(|| {
                write_stack::<colortype::GrayI8>(&tmp("types.tif"), dims, PLAIN, &|k| {
                    plane(dims, k, |x| (x as i32 - 120) as i8)
                })
            }),
        ),
        (
            DType::I16,
            Box::new(|| {
                write_stack::<colortype::GrayI16>(&tmp("types.tif"), dims, PLAIN, &|k| {
                    plane(dims, k, |x| -(x as i16))
                })
            }),
        ),
        (
            DType::U32,
            Box::new(|| {
                write_stack::<colortype::Gray32>(&tmp("types.tif"), dims, PLAIN, &|k| {
                    plane(dims, k, |x| x as u32 * 100_000)
                })
            }),
        ),
        (
            DType::I32,
            Box::new(|| {
                write_stack::<colortype::GrayI32>(&tmp("types.tif"), dims, PLAIN, &|k| {
                    plane(dims, k, |x| -(x as i32) * 100_000)
                })
            }),
        ),
        (
            DType::F32,
            Box::new(|| {
                write_stack::<colortype::Gray32Float>(&tmp("types.tif"), dims, PLAIN, &|k| {
                    plane(dims, k, |x| x as f32 * 0.25)
                })
            }),
        ),
        (
            DType::F64,
            Box::new(|| {
                write_stack::<colortype::Gray64Float>(&tmp("types.tif"), dims, PLAIN, &|k| {
                    plane(dims, k, |x| x as f64 * -0.5)
                })
            }),
        ),
    ];
    for (dtype, write) in cases {
        write();
        let mut r = open_default(&p).unwrap();
        assert_eq!(r.header().dtype, dtype);
        let expect = move |i, j, k| {
            let x = v(i, j, k);
            match dtype {
                DType::U8 => x as u8 as f64,
                DType::I8 => (x as i32 - 120) as i8 as f64,
                DType::I16 => -(x as f64),
                DType::U32 => x as f64 * 100_000.0,
                DType::I32 => -(x as f64) * 100_000.0,
                DType::F32 => x as f64 * 0.25,
                DType::F64 => x as f64 * -0.5,
                DType::U16 => unreachable!(),
            }
        };
        check_boxes(&mut *r, &expect);
    }
    // 64-bit integers are refused, naming the type
    write_stack::<colortype::Gray64>(&p, dims, PLAIN, &|k| plane(dims, k, |x| x as u64));
    let e = err_of(open_default(&p));
    assert!(
        e.contains("64-bit unsigned integer") && e.contains("page 0"),
        "{e}"
    );
}

#[test]
fn rgb_components_by_name_index_and_magnitude() {
    let dims = [5, 4, 3];
    let p = tmp("rgb.tif");
    let rgb = |i, j, k| [v(i, j, k) as u8, (v(i, j, k) / 2) as u8, 7u8];
    write_stack::<colortype::RGB8>(
        &p,
        dims,
        How {
            rows_per_strip: Some(3),
            compression: Compression::Lzw,
            ..PLAIN
        },
        &|k| {
            let mut out = Vec::new();
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    out.extend(rgb(i, j, k));
                }
            }
            out
        },
    );
    let e = err_of(open_default(&p));
    assert!(e.contains("0 (r), 1 (g), 2 (b)"), "{e}");
    for (choice, c) in [("g", 1), ("2", 2), ("r", 0)] {
        let o = VolumeOptions {
            scalar: Some(ScalarChoice::parse(choice)),
            ..Default::default()
        };
        let mut r = open_opts(&p, &o).unwrap();
        assert_eq!(r.header().dtype, DType::U8);
        check_boxes(&mut *r, &|i, j, k| rgb(i, j, k)[c] as f64);
    }
    let o = VolumeOptions {
        scalar: Some(ScalarChoice::Magnitude),
        ..Default::default()
    };
    let mut r = open_opts(&p, &o).unwrap();
    assert_eq!(r.header().dtype, DType::F32);
    check_boxes(&mut *r, &|i, j, k| {
        let c = rgb(i, j, k).map(|x| x as f64);
        ((c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt() as f32) as f64
    });
    let o = VolumeOptions {
        scalar: Some(ScalarChoice::Index(3)),
        ..Default::default()
    };
    assert!(err_of(open_opts(&p, &o)).contains("--scalar 3"));
}

/// One page's tags, written directory by directory (tiles, planar samples, odd tags).
struct RawPage {
    width: u32,
    height: u32,
    /// (tile width, tile height), or strips of `rows` rows.
    tile: Option<(u32, u32)>,
    rows: u32,
    samples: u16,
    planar: bool,
    bits: u16,
    sample_format: u16,
    compression: u16,
    photometric: u16,
    /// Each chunk's bytes, as stored.
    chunks: Vec<Vec<u8>>,
    description: Option<String>,
}

fn write_raw_pages(path: &Path, pages: &[RawPage]) {
    let mut f = std::fs::File::create(path).unwrap();
    let mut enc = TiffEncoder::new(&mut f).unwrap();
    for pg in pages {
        let mut d = enc.image_directory().unwrap();
        let mut offsets = Vec::new();
        let mut counts = Vec::new();
        for c in &pg.chunks {
            offsets.push(d.write_data(&c[..]).unwrap() as u32);
            counts.push(c.len() as u32);
        }
        d.write_tag(Tag::ImageWidth, pg.width).unwrap();
        d.write_tag(Tag::ImageLength, pg.height).unwrap();
        d.write_tag(Tag::BitsPerSample, &vec![pg.bits; pg.samples as usize][..])
            .unwrap();
        d.write_tag(Tag::Compression, pg.compression).unwrap();
        d.write_tag(Tag::PhotometricInterpretation, pg.photometric)
            .unwrap();
        d.write_tag(Tag::SamplesPerPixel, pg.samples).unwrap();
        d.write_tag(
            Tag::SampleFormat,
            &vec![pg.sample_format; pg.samples as usize][..],
        )
        .unwrap();
        if pg.planar {
            d.write_tag(Tag::PlanarConfiguration, 2u16).unwrap();
        }
        if let Some(desc) = &pg.description {
            d.write_tag(Tag::ImageDescription, desc.as_str()).unwrap();
        }
        match pg.tile {
            Some((tw, th)) => {
                d.write_tag(Tag::TileWidth, tw).unwrap();
                d.write_tag(Tag::TileLength, th).unwrap();
                d.write_tag(Tag::TileOffsets, &offsets[..]).unwrap();
                d.write_tag(Tag::TileByteCounts, &counts[..]).unwrap();
            }
            None => {
                d.write_tag(Tag::RowsPerStrip, pg.rows).unwrap();
                d.write_tag(Tag::StripOffsets, &offsets[..]).unwrap();
                d.write_tag(Tag::StripByteCounts, &counts[..]).unwrap();
            }
        }
        d.finish().unwrap();
    }
}

fn zlib(b: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(b).unwrap();
    e.finish().unwrap()
}

/// The tiles (`tw × th`, padded with 0xEE bytes past the page) of u16 little-endian page `k`,
/// `samples` planes of it when `planar` (plane `s` holds `v + 1000 s`).
fn tiles(dims: [usize; 3], k: usize, tw: usize, th: usize, samples: usize) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for s in 0..samples {
        for ty in 0..dims[1].div_ceil(th) {
            for tx in 0..dims[0].div_ceil(tw) {
                let mut t = Vec::new();
                for y in ty * th..(ty + 1) * th {
                    for x in tx * tw..(tx + 1) * tw {
                        if x < dims[0] && y < dims[1] {
                            t.extend_from_slice(&(v(x, y, k) + 1000 * s as u16).to_le_bytes());
                        } else {
                            t.extend_from_slice(&[0xEE, 0xEE]);
                        }
                    }
                }
                out.push(t);
            }
        }
    }
    out
}

fn tiled_page(dims: [usize; 3], k: usize, samples: u16, deflate: bool) -> RawPage {
    let chunks = tiles(dims, k, 16, 16, samples as usize);
    RawPage {
        width: dims[0] as u32,
        height: dims[1] as u32,
        tile: Some((16, 16)),
        rows: 0,
        samples,
        planar: samples > 1,
        bits: 16,
        sample_format: 1,
        compression: if deflate { 8 } else { 1 },
        photometric: 1,
        chunks: if deflate {
            chunks.iter().map(|c| zlib(c)).collect()
        } else {
            chunks
        },
        description: None,
    }
}

#[test]
fn tiles_read_only_what_overlaps_and_planar_samples() {
    // 37 × 21 pages in 16 × 16 tiles: 3 × 2 tiles, the last column and row padded
    let dims = [37, 21, 3];
    for deflate in [false, true] {
        let p = tmp(if deflate { "tiles-z.tif" } else { "tiles.tif" });
        let pages: Vec<RawPage> = (0..3).map(|k| tiled_page(dims, k, 1, deflate)).collect();
        write_raw_pages(&p, &pages);
        let mut r = open_default(&p).unwrap();
        assert_eq!(r.header().dims, dims);
        check_boxes(&mut *r, &|i, j, k| v(i, j, k) as f64);
        // a box inside one tile, across tile edges, and the padded corner
        for (lo, hi) in [
            ([17, 3, 0], [20, 9, 3]),
            ([14, 14, 1], [18, 18, 2]),
            ([33, 17, 2], [37, 21, 3]),
        ] {
            let s = r.read_box(lo, hi).unwrap();
            let mut n = 0;
            for k in lo[2]..hi[2] {
                for j in lo[1]..hi[1] {
                    for i in lo[0]..hi[0] {
                        assert_eq!(s.get(n), v(i, j, k) as f64);
                        n += 1;
                    }
                }
            }
        }
        // planar tiles of two samples (a "Multiband" gray page): --scalar 1 reads plane 1
        let p = tmp(if deflate {
            "planar-z.tif"
        } else {
            "planar.tif"
        });
        let pages: Vec<RawPage> = (0..3).map(|k| tiled_page(dims, k, 2, deflate)).collect();
        write_raw_pages(&p, &pages);
        let e = err_of(open_default(&p));
        assert!(e.contains("2 components"), "{e}");
        for (s, off) in [(0, 0.0), (1, 1000.0)] {
            let o = VolumeOptions {
                scalar: Some(ScalarChoice::Index(s)),
                ..Default::default()
            };
            let mut r = open_opts(&p, &o).unwrap();
            check_boxes(&mut *r, &|i, j, k| v(i, j, k) as f64 + off);
        }
        let o = VolumeOptions {
            scalar: Some(ScalarChoice::Magnitude),
            ..Default::default()
        };
        let mut r = open_opts(&p, &o).unwrap();
        check_boxes(&mut *r, &|i, j, k| {
            let a = v(i, j, k) as f64;
            ((a * a + (a + 1000.0).powi(2)).sqrt() as f32) as f64
        });
    }
}

#[test]
fn imagej_geometry_units_and_calibration() {
    let dims = [6, 5, 4];
    let p = tmp("ij.tif");
    let desc = "ImageJ=1.54f\nimages=4\nslices=4\nunit=micron\nspacing=2.5\nxorigin=2\n\
                cf=0\nc0=-32768.0\nc1=1.0\nvunit=Gray Value\nloop=false\n";
    write_u16(
        &p,
        dims,
        How {
            description: Some(desc),
            resolution: Some((
                Rational { n: 2, d: 1 },
                Rational { n: 4, d: 1 },
                ResolutionUnit::None,
            )),
            ..PLAIN
        },
    );
    let mut vol = Volume::open(&p, None, &VolumeOptions::default()).unwrap();
    let h = vol.header().clone();
    assert_eq!(h.spacing, [0.5, 0.25, 2.5]);
    assert_eq!(h.length_unit.as_deref(), Some("um"));
    assert_eq!(h.origin, [-1.0, 0.0, 0.0]);
    assert_eq!(h.rescale, Some((1.0, -32768.0)));
    assert_eq!(h.value_unit, None);
    let s = vol.read_block(0..5, 0..4).unwrap();
    assert_eq!(s.dtype(), DType::F32);
    assert_eq!(s.get(0), -32768.0);
    assert_eq!(s.get(6 * 5 + 7), v(1, 1, 1) as f64 - 32768.0);

    // µm as ImageJ escapes it, a negative spacing flips z
    let desc = "ImageJ=1.54f\nimages=4\nslices=4\nunit=\\u00B5m\nspacing=-3\n";
    write_u16(
        &p,
        dims,
        How {
            description: Some(desc),
            resolution: Some((
                Rational { n: 10, d: 1 },
                Rational { n: 10, d: 1 },
                ResolutionUnit::None,
            )),
            ..PLAIN
        },
    );
    let r = open_default(&p).unwrap();
    let h = r.header();
    assert_eq!(h.length_unit.as_deref(), Some("um"));
    assert_eq!(h.spacing, [0.1, 0.1, 3.0]);
    assert!(h.axes[2].flip && !h.axes[0].flip);

    // no ImageJ: resolution in dots per centimetre gives mm, z taken equal to x
    write_u16(
        &p,
        dims,
        How {
            resolution: Some((
                Rational { n: 20, d: 1 },
                Rational { n: 40, d: 1 },
                ResolutionUnit::Centimeter,
            )),
            ..PLAIN
        },
    );
    let r = open_default(&p).unwrap();
    let h = r.header();
    assert_eq!(h.spacing, [0.5, 0.25, 0.5]);
    assert_eq!(h.length_unit.as_deref(), Some("mm"));
    assert!(
        h.notes.iter().any(|n| n.contains("equal to x")),
        "{:?}",
        h.notes
    );
}

#[test]
fn imagej_hyperstacks_give_channels_and_frames() {
    // 2 channels × 3 slices × 2 frames: page = c + 2 (z + 3 t), value v(i, j, page)
    let (c, z, t) = (2, 3, 2);
    let dims = [5, 4, c * z * t];
    let p = tmp("hyper.tif");
    let desc = "ImageJ=1.54f\nimages=12\nchannels=2\nslices=3\nframes=2\nhyperstack=true\n";
    write_u16(
        &p,
        dims,
        How {
            description: Some(desc),
            ..PLAIN
        },
    );
    let e = err_of(open_default(&p));
    assert!(e.contains("2 components") || e.contains("--scalar"), "{e}");
    let o = VolumeOptions {
        scalar: Some(ScalarChoice::Index(1)),
        ..Default::default()
    };
    let e = err_of(open_opts(&p, &o));
    assert!(e.contains("2 frames") && e.contains("--frame"), "{e}");
    for (ch, fr) in [(0, 0), (1, 1), (0, 1)] {
        let o = VolumeOptions {
            scalar: Some(ScalarChoice::Index(ch)),
            frame: Some(fr),
            ..Default::default()
        };
        let mut r = open_opts(&p, &o).unwrap();
        assert_eq!(r.header().dims, [5, 4, 3]);
        check_boxes(&mut *r, &|i, j, k| v(i, j, ch + 2 * (k + 3 * fr)) as f64);
    }
    let o = VolumeOptions {
        scalar: Some(ScalarChoice::Magnitude),
        frame: Some(1),
        ..Default::default()
    };
    let mut r = open_opts(&p, &o).unwrap();
    assert_eq!(r.header().dtype, DType::F32);
    check_boxes(&mut *r, &|i, j, k| {
        let a = v(i, j, 2 * (k + 3)) as f64;
        let b = v(i, j, 1 + 2 * (k + 3)) as f64;
        ((a * a + b * b).sqrt() as f32) as f64
    });
    let o = VolumeOptions {
        scalar: Some(ScalarChoice::Index(0)),
        frame: Some(2),
        ..Default::default()
    };
    assert!(err_of(open_opts(&p, &o)).contains("--frame 2"));
    // a description that does not fit the pages
    let desc = "ImageJ=1.54f\nimages=12\nchannels=5\nslices=3\n";
    write_u16(
        &p,
        dims,
        How {
            description: Some(desc),
            ..PLAIN
        },
    );
    let e = err_of(open_default(&p));
    assert!(e.contains("images=12"), "{e}");
}

#[test]
fn imagej_files_of_one_ifd_hold_contiguous_pages() {
    // ImageJ's way past 4 GiB: one IFD, images=4 pages one after the other
    let dims = [6, 5, 4];
    let mut all = Vec::new();
    for k in 0..dims[2] {
        for x in plane(dims, k, |x| x) {
            all.extend_from_slice(&x.to_le_bytes());
        }
    }
    let p = tmp("ij-contiguous.tif");
    let page = RawPage {
        width: 6,
        height: 5,
        tile: None,
        rows: 5,
        samples: 1,
        planar: false,
        bits: 16,
        sample_format: 1,
        compression: 1,
        photometric: 1,
        chunks: vec![all.clone()],
        description: Some("ImageJ=1.54f\nimages=4\nslices=4\n".into()),
    };
    write_raw_pages(&p, std::slice::from_ref(&page));
    // the strip's byte count says one page; the pages after it are in the file
    let mut b = std::fs::read(&p).unwrap();
    let count_at = b
        .windows(4)
        .position(|w| w == (all.len() as u32).to_le_bytes())
        .unwrap();
    b[count_at..count_at + 4].copy_from_slice(&60u32.to_le_bytes());
    std::fs::write(&p, &b).unwrap();
    let mut r = open_default(&p).unwrap();
    assert_eq!(r.header().dims, dims);
    check_boxes(&mut *r, &|i, j, k| v(i, j, k) as f64);
    // cut short: refused at open, naming the truncation
    std::fs::write(&p, &b[..b.len() - 200]).unwrap();
    let e = err_of(open_default(&p));
    assert!(e.contains("truncated"), "{e}");
}

#[test]
fn folders_of_slices_in_natural_order() {
    let dir = tmp("slices");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let dims = [6, 5, 1];
    // slice k holds plane k; names sort as 2 < 10 only by number
    for (k, name) in [(0, "s_1.tif"), (1, "s_2.tif"), (2, "s_10.tif")] {
        let how = How {
            compression: if k == 1 {
                Compression::Lzw
            } else {
                Compression::Uncompressed
            },
            ..PLAIN
        };
        write_stack::<colortype::Gray16>(&dir.join(name), dims, how, &|_| plane(dims, k, |x| x));
    }
    // a two-page file continues the stack
    write_stack::<colortype::Gray16>(&dir.join("s_11.tif"), [6, 5, 2], PLAIN, &|k| {
        plane(dims, 3 + k, |x| x)
    });
    assert_eq!(sniff(&dir), Some(VolumeFormat::Tiff));
    std::fs::write(dir.join("README.txt"), "acquired on a Tuesday").unwrap();
    let mut r = open_default(&dir).unwrap();
    assert_eq!(r.header().dims, [6, 5, 5]);
    let notes = r.header().notes.join("; ");
    assert!(
        notes.contains("README.txt") && notes.contains("4 TIFF file(s)"),
        "{notes}"
    );
    check_boxes(&mut *r, &|i, j, k| v(i, j, k) as f64);
    // a slice of another size is named
    write_stack::<colortype::Gray16>(&dir.join("s_12.tif"), [6, 4, 1], PLAIN, &|_| vec![0; 24]);
    let e = err_of(open_default(&dir));
    assert!(
        e.contains("s_12.tif") && e.contains("6×4") && e.contains("6×5"),
        "{e}"
    );
    // a damaged .tif is not skipped
    std::fs::write(dir.join("s_12.tif"), b"not a tiff").unwrap();
    let e = err_of(open_default(&dir));
    assert!(
        e.contains("s_12.tif") && e.contains("byte-order mark"),
        "{e}"
    );
}

#[test]
fn differing_pages_and_unread_features_are_refused_by_name() {
    let dims = [6, 5, 3];
    let p = tmp("differ.tif");
    {
        let mut f = std::fs::File::create(&p).unwrap();
        let mut enc = TiffEncoder::new(&mut f).unwrap();
        enc.write_image::<colortype::Gray16>(6, 5, &plane(dims, 0, |x| x))
            .unwrap();
        enc.write_image::<colortype::Gray16>(6, 5, &plane(dims, 1, |x| x))
            .unwrap();
        enc.write_image::<colortype::Gray8>(6, 5, &plane(dims, 2, |x| x as u8))
            .unwrap();
    }
    let e = err_of(open_default(&p));
    assert!(
        e.contains("page 2") && e.contains("u8") && e.contains("u16"),
        "{e}"
    );

    // JPEG compression is named
    let pg = |compression: u16, photometric: u16, bits: u16, sample_format: u16| RawPage {
        width: 4,
        height: 4,
        tile: None,
        rows: 4,
        samples: 1,
        planar: false,
        bits,
        sample_format,
        compression,
        photometric,
        chunks: vec![vec![0; 4 * 4 * (bits as usize).div_ceil(8)]],
        description: None,
    };
    for (page, what) in [
        (pg(7, 1, 8, 1), "JPEG (7)"),
        (pg(1, 3, 8, 1), "palette"),
        (pg(1, 5, 8, 1), "CMYK"),
        (pg(1, 1, 16, 3), "f16"),
        (pg(1, 1, 8, 6), "complex"),
    ] {
        let want_ok = what == "f16";
        write_raw_pages(&p, &[page, pg(1, 1, 8, 1)]);
        let r = open_default(&p);
        if want_ok {
            // two pages of different types: the f16 page is read, the u8 one differs
            let e = err_of(r);
            assert!(e.contains("page 1") && e.contains("f16"), "{e}");
        } else {
            let e = err_of(r);
            assert!(e.contains(what) && e.contains("page 0"), "{what}: {e}");
        }
    }
    // a box past the dims
    write_u16(&p, dims, PLAIN);
    let mut r = open_default(&p).unwrap();
    assert!(r.read_box([0, 0, 0], [6, 5, 4]).is_err());
    assert!(r.read_box([2, 0, 0], [2, 5, 1]).is_err());
}

#[test]
fn half_floats_widen_to_f32() {
    assert_eq!(f16_to_f32(0x3c00), 1.0);
    assert_eq!(f16_to_f32(0xc000), -2.0);
    assert_eq!(f16_to_f32(0x3555), 0.333_251_95);
    assert_eq!(f16_to_f32(0x0001), 2f32.powi(-24));
    assert_eq!(f16_to_f32(0x7bff), 65504.0);
    assert_eq!(f16_to_f32(0x7c00), f32::INFINITY);
    assert!(f16_to_f32(0x7e00).is_nan());
    let dims = [4, 4, 2];
    let half = |x: f32| -> [u8; 2] {
        // exact for small integers: 1.m × 2^e
        if x == 0.0 {
            return [0, 0];
        }
        let e = x.log2().floor() as i32;
        let m = ((x / 2f32.powi(e) - 1.0) * 1024.0) as u16;
        (((e + 15) as u16) << 10 | m).to_le_bytes()
    };
    let p = tmp("half.tif");
    let pages: Vec<RawPage> = (0..2)
        .map(|k| RawPage {
            width: 4,
            height: 4,
            tile: None,
            rows: 2,
            samples: 1,
            planar: false,
            bits: 16,
            sample_format: 3,
            compression: 1,
            photometric: 1,
            chunks: (0..2)
                .map(|s| {
                    (0..8)
                        .flat_map(|n| half((k * 16 + s * 8 + n) as f32))
                        .collect()
                })
                .collect(),
            description: None,
        })
        .collect();
    write_raw_pages(&p, &pages);
    let mut r = open_default(&p).unwrap();
    assert_eq!((r.header().dims, r.header().dtype), (dims, DType::F32));
    check_boxes(&mut *r, &|i, j, k| (k * 16 + j * 4 + i) as f64);
}

#[test]
fn three_hundred_pages_seek_in_any_order() {
    let dims = [8, 8, 300];
    let p = tmp("300.tif");
    write_stack::<colortype::Gray16>(&p, dims, PLAIN, &|k| vec![k as u16; 64]);
    let t = std::time::Instant::now();
    let mut r = open_default(&p).unwrap();
    assert_eq!(r.header().dims, dims);
    // backwards, one plane a read: each seeks to its page directly
    for k in (0..300).rev().step_by(7) {
        let s = r.read_box([0, 0, k], [8, 8, k + 1]).unwrap();
        assert_eq!((s.get(0), s.get(63)), (k as f64, k as f64));
    }
    let s = r.read_box([3, 3, 0], [5, 5, 300]).unwrap();
    assert!((0..300).all(|k| s.get(4 * k + 3) == k as f64));
    assert!(t.elapsed().as_secs_f64() < 10.0, "{:?}", t.elapsed());
}

#[test]
fn broken_stacks_are_refused_never_panic() {
    let dims = [6, 5, 3];
    let mut goods = Vec::new();
    for (name, how) in [
        ("b-plain.tif", PLAIN),
        (
            "b-lzw.tif",
            How {
                compression: Compression::Lzw,
                rows_per_strip: Some(2),
                description: Some("ImageJ=1.54f\nimages=3\nslices=3\nspacing=2\nunit=um\n"),
                ..PLAIN
            },
        ),
        (
            "b-deflate.tif",
            How {
                compression: Compression::Deflate(DeflateLevel::Fast),
                big: true,
                ..PLAIN
            },
        ),
    ] {
        let p = tmp(name);
        write_u16(&p, dims, how);
        goods.push(std::fs::read(&p).unwrap());
    }
    let p = tmp("tiles-b.tif");
    let pages: Vec<RawPage> = (0..2)
        .map(|k| tiled_page([18, 10, 2], k, 2, true))
        .collect();
    write_raw_pages(&p, &pages);
    goods.push(std::fs::read(&p).unwrap());
    let p = tmp("broken.tif");
    // the tiled file has two samples a pixel: read their magnitude
    let try_read = |p: &Path, scalar: Option<ScalarChoice>| {
        let o = VolumeOptions {
            scalar,
            ..Default::default()
        };
        if let Ok(mut r) = open_opts(p, &o) {
            let d = r.header().dims;
            // what is read is the box, in the header's type
            for (lo, hi) in [([0, 0, 0], d), ([1, 1, d[2] - 1], d)] {
                if let Ok(s) = r.read_box(lo, hi) {
                    let n: usize = (0..3).map(|a| hi[a] - lo[a]).product();
                    assert_eq!((s.len(), s.dtype()), (n, r.header().dtype));
                }
            }
        }
    };
    for (n, good) in goods.iter().enumerate() {
        let scalar = (n == 3).then_some(ScalarChoice::Magnitude);
        for cut in (0..good.len()).step_by(5) {
            std::fs::write(&p, &good[..cut]).unwrap();
            try_read(&p, scalar.clone());
        }
        for at in 0..good.len() {
            for x in [0u8, 0xff, 0x80]
                .into_iter()
                .take(if at % 3 == 0 { 3 } else { 2 })
            {
                let mut b = good.clone();
                b[at] = x;
                std::fs::write(&p, &b).unwrap();
                try_read(&p, scalar.clone());
            }
        }
    }
    // a truncated stack names the truncation
    let good = &goods[0];
    std::fs::write(&p, &good[..good.len() / 2]).unwrap();
    let e = match open_default(&p) {
        Err(e) => e.to_string(),
        Ok(mut r) => {
            let d = r.header().dims;
            r.read_box([0, 0, 0], d).unwrap_err().to_string()
        }
    };
    assert!(e.contains("broken.tif"), "{e}");
}
