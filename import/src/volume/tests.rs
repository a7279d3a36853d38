//! Tests of the shared volume machinery: raw boxes, orientation, rescale, components, NIfTI
//! headers written here byte by byte (real files from nibabel are read in
//! `server/tests/volumes.rs`).

use super::*;

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("tetwave-volume-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Voxel value of index (i, j, k): distinct everywhere.
fn v(i: usize, j: usize, k: usize) -> u16 {
    (i + 10 * j + 100 * k) as u16
}

fn write_raw(path: &Path, dims: [usize; 3]) {
    let mut b = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                b.extend_from_slice(&v(i, j, k).to_le_bytes());
            }
        }
    }
    std::fs::write(path, b).unwrap();
}

#[test]
fn raw_boxes_are_the_voxels_of_the_box() {
    let p = tmp("box.raw");
    let dims = [5, 4, 3];
    write_raw(&p, dims);
    let spec = RawSpec {
        dims,
        dtype: DType::U16,
        spacing: [1.0; 3],
    };
    let mut r = raw::RawReader::open(&p, spec).unwrap();
    for (lo, hi) in [
        ([0, 0, 0], [5, 4, 3]),
        ([0, 0, 1], [5, 4, 3]),
        ([0, 1, 0], [5, 3, 2]),
        ([1, 2, 1], [4, 4, 3]),
    ] {
        let s = r.read_box(lo, hi).unwrap();
        let mut n = 0;
        for k in lo[2]..hi[2] {
            for j in lo[1]..hi[1] {
                for i in lo[0]..hi[0] {
                    assert_eq!(s.get(n), v(i, j, k) as f64, "{lo:?}..{hi:?} at {i},{j},{k}");
                    n += 1;
                }
            }
        }
        assert_eq!(n, s.len());
    }
    // a size that does not match the dims is refused, naming both
    let bad = RawSpec {
        dims: [5, 4, 4],
        ..spec
    };
    let e = raw::RawReader::open(&p, bad).err().unwrap().to_string();
    assert!(e.contains("120 bytes") && e.contains("160"), "{e}");
}

#[test]
fn flips_and_permutations_put_voxels_where_the_world_has_them() {
    let p = tmp("orient.raw");
    let fdims = [5, 4, 3];
    write_raw(&p, fdims);
    let spec = RawSpec {
        dims: fdims,
        dtype: DType::U16,
        spacing: [1.0, 2.0, 3.0],
    };
    // file x → world z reversed, file y → world x, file z → world y reversed
    let axes = [
        AxisMap {
            axis: 2,
            flip: true,
        },
        AxisMap {
            axis: 0,
            flip: false,
        },
        AxisMap {
            axis: 1,
            flip: true,
        },
    ];
    struct Turned(raw::RawReader, FileHeader);
    impl VolumeReader for Turned {
        fn header(&self) -> &FileHeader {
            &self.1
        }
        fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
            self.0.read_box(lo, hi)
        }
    }
    let r = raw::RawReader::open(&p, spec).unwrap();
    let mut h = r.header().clone();
    h.axes = axes;
    h.origin = [10.0, 20.0, 30.0];
    let mut vol = Volume::from_reader(&p, Box::new(Turned(r, h))).unwrap();
    assert_eq!(vol.dims, [4, 3, 5]);
    assert_eq!(vol.spacing, [2.0, 3.0, 1.0]);
    // the world's low corner: file voxel 0 is at the high end of the flipped axes
    assert_eq!(vol.origin, [10.0, 20.0 - 2.0 * 3.0, 30.0 - 4.0 * 1.0]);
    for (y, z) in [(0..3, 0..5), (1..2, 2..4), (0..1, 4..5)] {
        let s = vol.read_block(y.clone(), z.clone()).unwrap();
        let mut n = 0;
        for wz in z.clone() {
            for wy in y.clone() {
                for wx in 0..4 {
                    // world (wx, wy, wz) is file (4 - wz, wx, 2 - wy)
                    assert_eq!(
                        s.get(n),
                        v(4 - wz, wx, 2 - wy) as f64,
                        "world {wx},{wy},{wz}"
                    );
                    n += 1;
                }
            }
        }
        assert_eq!(n, s.len());
    }
    assert!(vol.read_block(0..4, 0..1).is_err());
}

#[test]
fn rescale_and_components() {
    let s = Samples::U16(vec![0, 1, 1000]);
    assert_eq!(
        s.rescaled(2.0, -1024.0),
        Samples::F32(vec![-1024.0, -1022.0, 976.0])
    );
    let rgb = Samples::U8(vec![3, 4, 0, 1, 2, 3]);
    assert_eq!(
        samples::select(rgb.clone(), 3, Some(1)),
        Samples::U8(vec![4, 2])
    );
    assert_eq!(
        samples::select(rgb, 3, None),
        Samples::F32(vec![5.0, (14.0f32).sqrt()])
    );
    let names = ["r", "g", "b"].map(String::from);
    assert_eq!(samples::choose_component(None, 1, &[]), Ok(Some(0)));
    let e = samples::choose_component(None, 3, &names).unwrap_err();
    assert!(e.contains("0 (r), 1 (g), 2 (b)"), "{e}");
    assert_eq!(
        samples::choose_component(Some(&ScalarChoice::parse("g")), 3, &names),
        Ok(Some(1))
    );
    assert!(samples::choose_component(Some(&ScalarChoice::Index(3)), 3, &names).is_err());
    assert_eq!(
        samples::choose_component(Some(&ScalarChoice::parse("mag")), 3, &names),
        Ok(None)
    );
}

/// A NIfTI-1 file of `dims` i16 voxels `v` with the given sform (or pixdims alone), slope and
/// intercept, in byte order `big`.
fn nifti1(dims: [usize; 3], sform: Option<[[f32; 4]; 3]>, scl: (f32, f32), big: bool) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    let put16 = |h: &mut Vec<u8>, at: usize, x: i16| {
        h[at..at + 2].copy_from_slice(&if big {
            x.to_be_bytes()
        } else {
            x.to_le_bytes()
        })
    };
    let put32 = |h: &mut Vec<u8>, at: usize, x: i32| {
        h[at..at + 4].copy_from_slice(&if big {
            x.to_be_bytes()
        } else {
            x.to_le_bytes()
        })
    };
    let putf = |h: &mut Vec<u8>, at: usize, x: f32| {
        h[at..at + 4].copy_from_slice(&if big {
            x.to_be_bytes()
        } else {
            x.to_le_bytes()
        })
    };
    put32(&mut h, 0, 348);
    put16(&mut h, 40, 3);
    for (a, &d) in dims.iter().enumerate() {
        put16(&mut h, 42 + 2 * a, d as i16);
        putf(&mut h, 80 + 4 * a, 1.5);
    }
    put16(&mut h, 70, 4);
    put16(&mut h, 72, 16);
    putf(&mut h, 108, 352.0);
    putf(&mut h, 112, scl.0);
    putf(&mut h, 116, scl.1);
    h[123] = 2; // mm
    if let Some(m) = sform {
        put16(&mut h, 254, 1);
        for (r, row) in m.iter().enumerate() {
            for (c, &x) in row.iter().enumerate() {
                putf(&mut h, 280 + 16 * r + 4 * c, x);
            }
        }
    }
    h[344..348].copy_from_slice(b"n+1\0");
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let x = v(i, j, k) as i16;
                h.extend_from_slice(&if big {
                    x.to_be_bytes()
                } else {
                    x.to_le_bytes()
                });
            }
        }
    }
    h
}

#[test]
fn nifti_headers_give_geometry_rescale_and_voxels() {
    let dims = [4, 3, 2];
    // LPS-like sform: x flipped, spacing 0.5, 2, 3
    let sform = [
        [-0.5, 0.0, 0.0, 10.0],
        [0.0, 2.0, 0.0, -5.0],
        [0.0, 0.0, 3.0, 1.0],
    ];
    for big in [false, true] {
        let p = tmp(if big { "be.nii" } else { "le.nii" });
        std::fs::write(&p, nifti1(dims, Some(sform), (2.0, -3.0), big)).unwrap();
        assert_eq!(sniff(&p), Some(VolumeFormat::Nifti));
        let mut vol = Volume::open(&p, None, &VolumeOptions::default()).unwrap();
        let h = vol.header().clone();
        assert_eq!(h.dims, dims);
        assert_eq!(h.spacing, [0.5, 2.0, 3.0]);
        assert_eq!(h.rescale, Some((2.0, -3.0)));
        assert_eq!(h.length_unit.as_deref(), Some("mm"));
        assert_eq!(vol.origin, [10.0 - 3.0 * 0.5, -5.0, 1.0]);
        let s = vol.read_block(0..3, 0..2).unwrap();
        assert_eq!(s.dtype(), DType::F32);
        let mut n = 0;
        for k in 0..2 {
            for j in 0..3 {
                for wx in 0..4 {
                    assert_eq!(s.get(n), 2.0 * v(3 - wx, j, k) as f64 - 3.0);
                    n += 1;
                }
            }
        }
    }
    // an oblique sform is refused, naming it
    let p = tmp("oblique.nii");
    let oblique = [
        [0.7, 0.7, 0.0, 0.0],
        [-0.7, 0.7, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    std::fs::write(&p, nifti1(dims, Some(oblique), (0.0, 0.0), false)).unwrap();
    let e = Volume::open(&p, None, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("oblique") && e.contains("sform"), "{e}");
    // no sform, no qform: the pixdims, no rescale when the slope is 0
    let p = tmp("plain.nii");
    std::fs::write(&p, nifti1(dims, None, (0.0, 5.0), false)).unwrap();
    let vol = Volume::open(&p, None, &VolumeOptions::default()).unwrap();
    assert_eq!((vol.spacing, vol.origin), ([1.5; 3], [0.0; 3]));
    assert_eq!((vol.header().rescale, vol.dtype), (None, DType::I16));
}

#[test]
fn broken_niftis_are_refused_never_panic() {
    let dims = [4, 3, 2];
    let good = nifti1(dims, None, (1.0, 0.0), false);
    let p = tmp("broken.nii");
    // every truncation, and single-byte corruptions of the header
    for cut in (0..good.len()).step_by(7) {
        std::fs::write(&p, &good[..cut]).unwrap();
        if let Ok(mut v) = Volume::open(&p, Some(VolumeFormat::Nifti), &VolumeOptions::default()) {
            let _ = v.read_block(0..3, 0..2);
        }
    }
    std::fs::write(&p, &good[..good.len() - 1]).unwrap();
    let e = Volume::open(&p, None, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("truncated"), "{e}");
    for at in 0..352 {
        for x in [0u8, 0xff, 0x7f, 0x80] {
            let mut b = good.clone();
            b[at] = x;
            std::fs::write(&p, &b).unwrap();
            if let Ok(mut v) =
                Volume::open(&p, Some(VolumeFormat::Nifti), &VolumeOptions::default())
            {
                let (ny, nz) = (v.dims[1], v.dims[2]);
                let _ = v.read_block(0..ny.min(2), 0..nz.min(2));
            }
        }
    }
}

#[test]
fn natural_order_compares_numbers() {
    let mut v = vec!["s10.tif", "s2.tif", "s1.tif", "s02b.tif"];
    v.sort_by(|a, b| natural_cmp(a, b));
    assert_eq!(v, ["s1.tif", "s2.tif", "s02b.tif", "s10.tif"]);
}
