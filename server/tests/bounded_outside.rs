//! `prepare --max-error` keeps its promise on a mesh with an outside: the values the analysis
//! extends past the domain make the details of the inside vertices beside it larger than the
//! samples alone show, and the code width must cover them (it once did not: a torus at 0.1 % came
//! out 138 times over its bound, and `verify` refused it).

use tetwave_protocol::testing::{notched_cube_vtk, notched_scalar};
use tetwave_server::analysis::ErrorBound;
use tetwave_server::prepare::{prepare, verify, PrepareOptions};
use tetwave_server::resample::BaseSpec;

#[test]
fn a_bounded_store_of_a_nonconvex_mesh_is_within_its_bound() {
    let d = tempfile::tempdir().unwrap();
    let mesh = d.path().join("notch.vtk");
    std::fs::write(&mesh, notched_cube_vtk(0.4)).unwrap();
    for (levels, fraction, base) in [
        (5, 1e-3, BaseSpec::Box5),
        (4, 1e-2, BaseSpec::Box6),
        (5, 1e-4, BaseSpec::Box6),
    ] {
        let out = d.path().join(format!("s{levels}-{fraction}"));
        let mut o = PrepareOptions::new(mesh.to_str().unwrap(), &out);
        o.levels = Some(levels);
        o.base = base;
        o.max_error = Some(ErrorBound::OfRange(fraction));
        let s = prepare(&o).unwrap();
        assert!(s.outside_vertices > 0, "the notch is outside");
        assert!(
            s.max_abs_error <= s.max_error_bound,
            "level {levels}, {fraction} of the range: max error {} over the bound {}",
            s.max_abs_error,
            s.max_error_bound
        );
        // the promise is fraction × the samples' range; the field's own range is wider or equal
        let range = notched_scalar([1.0, 1.0, 1.0]) - notched_scalar([0.0; 3]);
        assert!(s.max_error_bound <= fraction * range * 1.0001);
        verify(&out).unwrap();
    }
}
