//! Raw grids are voxel-exact by default (`--base auto`): every voxel of the input is a vertex of
//! the semi-regular mesh, `--max-error` bounds every voxel, `verify --input` checks that against
//! the file, the stored value range is the input's, the lattice's padding is clipped by the level
//! set, and a non-cubic grid is not padded to a cube.

use std::path::Path;
use std::process::Command;
use tetwave_protocol::store_format::Manifest;
use tetwave_server::analysis::ErrorBound;
use tetwave_server::prepare::{prepare, verify_input, GridArgs, PrepareOptions};
use tetwave_server::resample::BaseSpec;
use tetwave_store::Store;

/// A field with structure at every scale: a smooth part, a ridge and one spike, in `[-1, 1]`.
fn field(dims: [usize; 3]) -> Vec<f32> {
    let mut v = Vec::with_capacity(dims.iter().product());
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let (x, y, z) = (i as f32, j as f32, k as f32);
                let mut f = 0.5 * (0.4 * x).sin() * (0.3 * y).cos() + 0.02 * z;
                if i == dims[0] / 2 {
                    f += 0.3;
                }
                if [i, j, k] == [1, 2, 1] {
                    f = 1.0;
                }
                if [i, j, k] == [dims[0] - 1, dims[1] - 1, dims[2] - 1] {
                    f = -1.0;
                }
                v.push(f);
            }
        }
    }
    v
}

fn write_f32(path: &Path, v: &[f32]) {
    std::fs::write(
        path,
        v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>(),
    )
    .unwrap();
}

fn grid_args(dims: [usize; 3], dtype: &str, spacing: [f64; 3]) -> GridArgs {
    GridArgs {
        dims: Some(dims),
        dtype: dtype.into(),
        spacing,
        volume: None,
    }
}

fn options(raw: &Path, out: &Path, grid: &GridArgs, max_error: &str) -> PrepareOptions {
    let mut o = PrepareOptions::new(raw.to_str().unwrap(), out);
    o.read.grid = grid.clone();
    o.max_error = Some(ErrorBound::parse(max_error).unwrap());
    o
}

#[test]
fn every_voxel_is_kept_within_the_bound_and_the_range_is_the_inputs() {
    let d = tempfile::tempdir().unwrap();
    // a cube one voxel short of a lattice (padded), one that fills it, and non-cubic ones with
    // unequal spacings
    let cases: [([usize; 3], [f64; 3]); 4] = [
        ([16, 16, 16], [1.0; 3]),
        ([17, 17, 17], [0.5; 3]),
        ([13, 9, 6], [0.7, 0.1, 3.3]),
        ([40, 33, 5], [1.0, 1.0, 4.0]),
    ];
    for (dims, spacing) in cases {
        let raw = d.path().join(format!("{dims:?}.raw"));
        let v = field(dims);
        write_f32(&raw, &v);
        let grid = grid_args(dims, "f32", spacing);
        for bound in ["0.1%", "1e-6"] {
            let out = d.path().join(format!("{dims:?}-{bound}"));
            let s = prepare(&options(&raw, &out, &grid, bound)).unwrap();
            let input = grid.read(&raw, None).unwrap();
            let r = verify_input(&out, &input).unwrap();
            let c = r.input.as_ref().unwrap();
            let voxels: usize = dims.iter().product();
            assert_eq!((c.points_are, c.points), ("voxels", voxels as u64));
            assert!(
                c.max_abs_error <= s.max_error_bound,
                "{dims:?} {bound}: {c:?}"
            );
            assert_eq!(c.input_range, [-1.0, 1.0], "{dims:?}");
            assert_eq!(c.store_range, c.input_range, "{dims:?}");
            assert_eq!(s.value_range, c.input_range, "{dims:?}");
            // the padding adds at most half the grid's points
            assert!(
                s.vertices as f64 <= 1.5 * voxels as f64,
                "{dims:?}: {} vertices for {voxels} voxels",
                s.vertices
            );
            eprintln!(
                "{dims:?} at {bound}: base {} at {} levels, {} vertices for {voxels} voxels, \
                 voxels within {:e} (bound {:e}), {} bit-exact",
                s.base, s.levels, s.vertices, c.max_abs_error, s.max_error_bound, c.exact_points
            );
        }
    }
}

#[test]
fn a_non_cubic_grid_gets_boxes_along_its_long_axes_and_its_padding_is_clipped() {
    let d = tempfile::tempdir().unwrap();
    let dims = [40, 33, 5];
    let raw = d.path().join("g.raw");
    write_f32(&raw, &field(dims));
    let grid = grid_args(dims, "f32", [1.0, 1.0, 4.0]);
    let out = d.path().join("s");
    let s = prepare(&options(&raw, &out, &grid, "0.1%")).unwrap();
    assert!(s.base.starts_with("kuhn-boxes"), "{}", s.base);
    let store = Store::open(&out).unwrap();
    let m: &Manifest = &store.manifest;
    // the lattice covers the voxels (x from 0 to 39, y to 32, z to 16) with less than a box more
    let [lo, hi] = m.bounds;
    assert_eq!(lo, [0.0; 3]);
    assert!(hi[0] >= 39.0 && hi[1] >= 32.0 && hi[2] >= 16.0, "{hi:?}");
    assert!(
        hi[0] < 2.0 * 39.0 && hi[1] < 2.0 * 32.0 && hi[2] < 2.0 * 16.0,
        "{hi:?}"
    );
    // the level set: ≥ 0 at every voxel, < 0 at every padding vertex, and a near band streams
    assert!(m.has_levelset_band());
    let (band_bytes, band) = store.read_levelset_near().unwrap().unwrap();
    assert_eq!(band_bytes.len(), 56, "the voxels' box, no band");
    assert_eq!(band.domain_box(), Some([[0.0; 3], [39.0, 32.0, 16.0]]));
    let ls = store
        .read_levelset()
        .unwrap()
        .expect("a padded grid has a level set");
    let keys = store.base.vertex_keys();
    let (mut inside, mut outside) = (0, 0);
    for (entity, _) in keys.entities() {
        keys.for_each_in(entity, |key, tet, w| {
            let p = store.base.position(tet, &w);
            let in_box = p[0] <= 39.0 && p[1] <= 32.0 && p[2] <= 16.0;
            let phi = ls[key as usize];
            assert_eq!(phi >= 0.0, in_box, "{p:?}: {phi}");
            if in_box {
                inside += 1;
            } else {
                outside += 1;
            }
        });
    }
    assert_eq!(inside, 40 * 33 * 5);
    assert!(outside > 0);
}

#[test]
fn an_explicit_base_resamples_and_verify_input_says_so() {
    let d = tempfile::tempdir().unwrap();
    let dims = [13, 9, 6];
    let raw = d.path().join("g.raw");
    write_f32(&raw, &field(dims));
    let grid = grid_args(dims, "f32", [1.0; 3]);
    let out = d.path().join("s");
    let mut o = options(&raw, &out, &grid, "0.1%");
    o.base = BaseSpec::Box6;
    o.levels = Some(3);
    prepare(&o).unwrap();
    let err = verify_input(&out, &grid.read(&raw, None).unwrap()).unwrap_err();
    let msg = err.to_string();
    assert!(msg.contains("not the voxels of this grid"), "{msg}");
    // and another grid than the store's is refused by its voxels' errors or its shape
    let out = d.path().join("exact");
    prepare(&options(&raw, &out, &grid, "0.1%")).unwrap();
    let mut other = field(dims);
    other[100] += 0.5;
    let raw2 = d.path().join("other.raw");
    write_f32(&raw2, &other);
    let msg = verify_input(&out, &grid.read(&raw2, None).unwrap())
        .unwrap_err()
        .to_string();
    assert!(msg.contains("exceeds the manifest's bound"), "{msg}");
    let grid2 = grid_args([9, 13, 6], "f32", [1.0; 3]);
    assert!(verify_input(&out, &grid2.read(&raw, None).unwrap()).is_err());
}

/// The command line: `prepare` of a u8 grid (no --base, no --levels), then `verify --input`.
#[test]
fn verify_input_on_the_command_line() {
    let d = tempfile::tempdir().unwrap();
    let dims = [20, 12, 7];
    let bytes: Vec<u8> = (0..dims.iter().product::<usize>())
        .map(|i| ((i * 37) % 251) as u8)
        .collect();
    let raw = d.path().join("g.raw");
    std::fs::write(&raw, &bytes).unwrap();
    let out = d.path().join("s");
    let bin = env!("CARGO_BIN_EXE_tetwave-server");
    let (raw_s, out_s) = (raw.to_str().unwrap(), out.to_str().unwrap());
    let st = Command::new(bin)
        .args(["prepare", raw_s, "--dims", "20,12,7", "--max-error", "0.1%"])
        .args(["--out", out_s, "--json"])
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let v = Command::new(bin)
        .args([
            "verify", out_s, "--input", raw_s, "--dims", "20,12,7", "--json",
        ])
        .output()
        .unwrap();
    assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stderr));
    let j: serde_json::Value = serde_json::from_slice(&v.stdout).unwrap();
    assert_eq!(j["input"]["points"], 20 * 12 * 7);
    assert_eq!(j["input"]["points_are"], "voxels");
    assert_eq!(j["input"]["input_range"], serde_json::json!([0.0, 250.0]));
    assert_eq!(j["input"]["store_range"], j["input"]["input_range"]);
    assert!(j["input"]["max_abs_error"].as_f64().unwrap() <= 0.25 + 1e-9);
    // --dims without --input is a usage error, not a silent plain verify
    let v = Command::new(bin)
        .args(["verify", out_s, "--dims", "20,12,7"])
        .output()
        .unwrap();
    assert!(!v.status.success());
    assert!(String::from_utf8_lossy(&v.stderr).contains("--input"));
}
