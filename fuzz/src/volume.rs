//! What the volume-file fuzz targets check: the header parsers written here (NIfTI-1/-2, NRRD,
//! VTK image data XML and legacy `STRUCTURED_POINTS`) are total. Any bytes, written to a file
//! with the format's extension, open to a volume or to an error, never a panic; a volume that
//! opens gives the voxel rows it promises (the first and last row of the first and last plane,
//! each `dims[0]` voxels long) or an error.
//!
//! The readers read files (a header may name a detached data file), so each input goes through
//! a file in a per-process temporary folder.

use std::path::PathBuf;
use std::sync::OnceLock;
use tetwave_import::volume::{Volume, VolumeFormat, VolumeOptions};

/// A fuzzed format: the reader's format and the extension its file gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    Nifti,
    NiftiGz,
    Nrrd,
    Vti,
    VtkLegacy,
}

impl Target {
    pub const ALL: [Target; 5] = [
        Target::Nifti,
        Target::NiftiGz,
        Target::Nrrd,
        Target::Vti,
        Target::VtkLegacy,
    ];

    fn format(self) -> VolumeFormat {
        match self {
            Target::Nifti | Target::NiftiGz => VolumeFormat::Nifti,
            Target::Nrrd => VolumeFormat::Nrrd,
            Target::Vti => VolumeFormat::Vti,
            Target::VtkLegacy => VolumeFormat::VtkStructuredPoints,
        }
    }

    fn extension(self) -> &'static str {
        match self {
            Target::Nifti => "nii",
            Target::NiftiGz => "nii.gz",
            Target::Nrrd => "nrrd",
            Target::Vti => "vti",
            Target::VtkLegacy => "vtk",
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Target::Nifti => "nifti",
            Target::NiftiGz => "nifti_gz",
            Target::Nrrd => "nrrd",
            Target::Vti => "vti",
            Target::VtkLegacy => "vtk_legacy",
        }
    }
}

/// Rows of more voxels than this are not read: a header may promise any size, and the reader
/// is allowed to allocate what its header promises once the file is long enough (the checks
/// look for panics, not for large but honest allocations).
const MAX_ROW: usize = 1 << 16;

fn scratch() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("tetwave-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&d).expect("a scratch folder for the fuzzed files");
        d
    })
}

/// Runs the checks on one input of `target`'s format; panics (a finding) only if a reader does.
pub fn check(target: Target, data: &[u8]) {
    let path = scratch().join(format!("input.{}", target.extension()));
    std::fs::write(&path, data).expect("write the fuzzed file");
    let options = VolumeOptions {
        raw: None,
        scalar: None,
        frame: None,
    };
    let Ok(mut volume) = Volume::open(&path, Some(target.format()), &options) else {
        return;
    };
    let [nx, ny, nz] = volume.dims;
    assert!(
        nx > 0 && ny > 0 && nz > 0,
        "a volume with an empty axis opened"
    );
    if nx > MAX_ROW {
        return;
    }
    for (y, z) in [(0, 0), (ny - 1, nz - 1)] {
        if let Ok(s) = volume.read_block(y..y + 1, z..z + 1) {
            assert_eq!(s.len(), nx, "a row of {nx} voxels read as {}", s.len());
        }
    }
}

/// Valid files of `target`'s format to mutate: small volumes in the format's main variants.
pub fn seeds(target: Target) -> Vec<Vec<u8>> {
    match target {
        Target::Nifti => vec![nifti1(2, 16), nifti1(4, 64), nifti2()],
        Target::NiftiGz => vec![gzip(&nifti1(2, 16)), gzip(&nifti2())],
        Target::Nrrd => nrrd_seeds(),
        Target::Vti => vti_seeds(),
        Target::VtkLegacy => legacy_seeds(),
    }
}

fn gzip(data: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(data).unwrap();
    e.finish().unwrap()
}

/// A NIfTI-1 single file of 3×2×2 voxels: `datatype` 2 (u8) or 4 (i16) / 64 (f64), sform and
/// qform set, a scaling slope.
fn nifti1(datatype: i16, bitpix: i16) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    let put_i16 = |h: &mut [u8], at: usize, v: i16| h[at..at + 2].copy_from_slice(&v.to_le_bytes());
    let put_f32 = |h: &mut [u8], at: usize, v: f32| h[at..at + 4].copy_from_slice(&v.to_le_bytes());
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    for (i, d) in [3i16, 3, 2, 2, 1, 1, 1, 1].into_iter().enumerate() {
        put_i16(&mut h, 40 + 2 * i, d);
    }
    put_i16(&mut h, 70, datatype);
    put_i16(&mut h, 72, bitpix);
    for (i, p) in [1.0f32, 0.5, 0.5, 2.0, 1.0, 1.0, 1.0, 1.0]
        .into_iter()
        .enumerate()
    {
        put_f32(&mut h, 76 + 4 * i, p);
    }
    put_f32(&mut h, 108, 352.0);
    put_f32(&mut h, 112, 2.0);
    put_f32(&mut h, 116, -1.0);
    h[123] = 10; // xyzt_units: mm, s
    put_i16(&mut h, 252, 1);
    put_i16(&mut h, 254, 1);
    for (i, v) in [-0.5f32, 0.0, 0.0, 10.0].into_iter().enumerate() {
        put_f32(&mut h, 280 + 4 * i, v);
    }
    for (i, v) in [0.0f32, 0.5, 0.0, 20.0].into_iter().enumerate() {
        put_f32(&mut h, 296 + 4 * i, v);
    }
    for (i, v) in [0.0f32, 0.0, 2.0, 30.0].into_iter().enumerate() {
        put_f32(&mut h, 312 + 4 * i, v);
    }
    h[344..348].copy_from_slice(b"n+1\0");
    let n = 12;
    let bytes = (bitpix / 8) as usize;
    h.extend((0..n * bytes).map(|i| (i * 7 % 251) as u8));
    h
}

/// A NIfTI-2 single file of 2×2×2 f32 voxels with a qform.
fn nifti2() -> Vec<u8> {
    let mut h = vec![0u8; 544];
    h[0..4].copy_from_slice(&540i32.to_le_bytes());
    h[4..12].copy_from_slice(b"n+2\0\r\n\x1a\n");
    h[12..14].copy_from_slice(&16i16.to_le_bytes());
    h[14..16].copy_from_slice(&32i16.to_le_bytes());
    for (i, d) in [3i64, 2, 2, 2, 1, 1, 1, 1].into_iter().enumerate() {
        h[16 + 8 * i..24 + 8 * i].copy_from_slice(&d.to_le_bytes());
    }
    for (i, p) in [1.0f64, 1.0, 1.0, 1.0].into_iter().enumerate() {
        h[104 + 8 * i..112 + 8 * i].copy_from_slice(&p.to_le_bytes());
    }
    h[168..176].copy_from_slice(&544i64.to_le_bytes());
    h[176..184].copy_from_slice(&1.0f64.to_le_bytes());
    h[344..348].copy_from_slice(&1i32.to_le_bytes()); // qform_code
    h.extend((0..8).flat_map(|i| (i as f32 * 1.5).to_le_bytes()));
    h
}

fn nrrd_seeds() -> Vec<Vec<u8>> {
    let raw = |head: &str, data: &[u8]| {
        let mut v = head.as_bytes().to_vec();
        v.extend_from_slice(data);
        v
    };
    let voxels: Vec<u8> = (0..24u8).collect();
    vec![
        raw(
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 3 2 2\nspacings: 1 1 2\n\
             encoding: raw\n\n",
            &voxels[..12],
        ),
        raw(
            "NRRD0005\n# a comment\ntype: short\ndimension: 3\nspace: left-posterior-superior\n\
             sizes: 3 2 2\nspace directions: (-0.5,0,0) (0,0.5,0) (0,0,2)\n\
             space origin: (1,2,3)\nkinds: domain domain domain\nendian: big\n\
             encoding: raw\nspace units: \"mm\" \"mm\" \"mm\"\n\n",
            &voxels,
        ),
        raw(
            "NRRD0004\ntype: float\ndimension: 3\nsizes: 2 2 2\nkinds: domain domain domain\n\
             space dimension: 3\nspace directions: (1,0,0) (0,1,0) (0,0,1)\nencoding: ascii\n\n",
            b"1 2 3 4\n5 6 7 8\n",
        ),
        raw(
            "NRRD0004\ntype: unsigned char\ndimension: 3\nsizes: 3 2 2\nencoding: gzip\n\n",
            &gzip(&voxels[..12]),
        ),
        raw(
            "NRRD0004\ntype: uint16\ndimension: 3\nsizes: 2 2 2\nendian: little\nencoding: hex\n\n",
            b"0001 0203 0405 0607\n0809 0a0b 0c0d 0e0f\n",
        ),
    ]
}

fn vti_seeds() -> Vec<Vec<u8>> {
    let head = |data_format: &str, payload: &str, appended: &str| {
        format!(
            "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\" \
             byte_order=\"LittleEndian\" header_type=\"UInt64\">\n  <ImageData WholeExtent=\"0 2 0 1 0 1\" \
             Origin=\"1 2 3\" Spacing=\"0.5 0.5 2\" Direction=\"1 0 0 0 1 0 0 0 1\">\n    \
             <Piece Extent=\"0 2 0 1 0 1\">\n      <PointData Scalars=\"density\">\n        \
             <DataArray type=\"Float32\" Name=\"density\" format=\"{data_format}\"{payload}\n        \
             </DataArray>\n      </PointData>\n    </Piece>\n  </ImageData>\n{appended}</VTKFile>\n"
        )
        .into_bytes()
    };
    let floats: Vec<u8> = (0..12)
        .flat_map(|i| (i as f32 * 0.25).to_le_bytes())
        .collect();
    let mut block = (floats.len() as u64).to_le_bytes().to_vec();
    block.extend_from_slice(&floats);
    let b64 = base64(&block);
    let mut appended = head(
        "appended",
        " offset=\"0\">",
        "  <AppendedData encoding=\"raw\">\n   _",
    );
    // the appended section's raw bytes, then the closing tags
    let tail = b"\n  </AppendedData>\n</VTKFile>\n";
    let end = appended.len() - "</VTKFile>\n".len();
    appended.truncate(end);
    appended.extend_from_slice(&block);
    appended.extend_from_slice(tail);
    vec![
        head("ascii", ">0 1 2 3 4 5 6 7 8 9 10 11", ""),
        head("binary", &format!(">{b64}"), ""),
        appended,
    ]
}

fn legacy_seeds() -> Vec<Vec<u8>> {
    let mut binary = b"# vtk DataFile Version 3.0\nct\nBINARY\nDATASET STRUCTURED_POINTS\n\
        DIMENSIONS 3 2 2\nSPACING 0.5 0.5 2\nORIGIN 0 0 0\nPOINT_DATA 12\n\
        SCALARS density short 1\nLOOKUP_TABLE default\n"
        .to_vec();
    binary.extend((0..12i16).flat_map(|i| (i * 100 - 300).to_be_bytes()));
    vec![
        b"# vtk DataFile Version 2.0\nct\nASCII\nDATASET STRUCTURED_POINTS\nDIMENSIONS 3 2 2\n\
          ASPECT_RATIO 1 1 1\nORIGIN 0 0 0\nPOINT_DATA 12\nSCALARS v float\nLOOKUP_TABLE default\n\
          0 1 2 3 4 5 6 7 8 9 10 11\n"
            .to_vec(),
        binary,
    ]
}

fn base64(data: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for c in data.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                out.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every seed opens (a seed that the reader refuses would fuzz the refusal only).
    #[test]
    fn seeds_open() {
        let options = VolumeOptions {
            raw: None,
            scalar: None,
            frame: None,
        };
        for t in Target::ALL {
            for (i, s) in seeds(t).into_iter().enumerate() {
                let path = scratch().join(format!("seed.{}", t.extension()));
                std::fs::write(&path, &s).unwrap();
                let v = Volume::open(&path, Some(t.format()), &options);
                assert!(v.is_ok(), "{} seed {i}: {:?}", t.name(), v.err());
                check(t, &s);
            }
        }
    }
}
