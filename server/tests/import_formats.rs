//! Import of real-world files (issue 7), at the reader and cleaning level: gmsh 1.0, Medit,
//! quirks, cell data, vector components, higher-order and mixed volume cells, the geometric
//! field, quality, and the broken files. Fixtures: `scripts/gen-fixtures.py` (meshio and
//! hand-written Python, not the readers' code).

use std::collections::HashMap;
use std::path::Path;
use tetwave_protocol::shapes::box_corners;

mod fixture_mesh;
use fixture_mesh::{cube_points, fixture, temperature, tets, Corruptor};

use tetwave_import::{read_mesh, ImportError, ImportedMesh, MeshFormat};
use tetwave_server::resample::unstructured::{
    boundary_distance, clean_import, min_dihedral_deg, CleanError, ImportOptions,
};

fn read(name: &str) -> ImportedMesh {
    read_mesh(&fixture(name), None).unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn cell_array<'m>(m: &'m ImportedMesh, name: &str) -> &'m [f64] {
    &m.cell_data
        .iter()
        .find(|a| a.name == name)
        .unwrap_or_else(|| panic!("no cell array {name}"))
        .values
}

#[test]
fn gmsh_1_0_reads_the_cube() {
    let m = read("cube_10.msh");
    assert_eq!(m.mesh.points, cube_points());
    assert_eq!(m.mesh.tets, tets());
    assert_eq!(m.counts.cells_read, 8);
    assert_eq!(m.mesh.cells_ignored, 1, "the triangle");
    assert_eq!(m.tet_cells, (1..8).collect::<Vec<_>>());
}

#[test]
fn medit_reads_the_cube_with_element_references() {
    for name in ["cube.mesh", "cube_mesh_as_dat"] {
        let m = if name == "cube.mesh" {
            read(name)
        } else {
            // --format mesh on a file whose extension says nothing.
            let dir = tempfile::tempdir().unwrap();
            let p = dir.path().join("cube.dat");
            std::fs::copy(fixture("cube.mesh"), &p).unwrap();
            read_mesh(&p, Some(MeshFormat::Medit)).unwrap()
        };
        assert_eq!(m.mesh.points, cube_points(), "{name}");
        assert_eq!(m.mesh.tets, tets(), "{name}");
        assert_eq!(m.mesh.cells_ignored, 2, "{name}: 2 triangles");
        let refs: Vec<f64> = [1., 2., 3., 4., 5., 6., 7., 20., 21.].to_vec();
        assert_eq!(cell_array(&m, "ref"), refs.as_slice(), "{name}");
    }
}

#[test]
fn format_override_beats_content_and_extension() {
    let err = read_mesh(&fixture("cube_binary.vtu"), Some(MeshFormat::Msh)).unwrap_err();
    assert!(err.to_string().contains("not a gmsh file"), "{err}");
    let err = read_mesh(&fixture("cube.mesh"), Some(MeshFormat::LegacyVtk)).unwrap_err();
    assert!(err.to_string().contains("not a legacy VTK file"), "{err}");
    assert_eq!("mesh".parse::<MeshFormat>(), Ok(MeshFormat::Medit));
    assert_eq!("VTU".parse::<MeshFormat>(), Ok(MeshFormat::Vtu));
    assert!("stl".parse::<MeshFormat>().is_err());
}

#[test]
fn legacy_blank_lines_and_crlf_read_the_same() {
    let a = read("cube_42_ascii.vtk");
    let b = read("cube_42_blank_crlf.vtk");
    assert_eq!(a, b);
    assert_eq!(b.mesh.tets, tets());
}

#[test]
fn quadratic_tets_keep_their_corner_tet() {
    for name in ["quadratic.vtu", "quadratic_22.msh"] {
        let m = read(name);
        assert_eq!(m.mesh.tets, tets(), "{name}");
        assert_eq!(m.counts.tets_linearized, 7, "{name}");
        assert_eq!(m.counts.tets, 0, "{name}");
        // 9 corners and one node on each of the 22 distinct edges of the 7 tets.
        assert_eq!(m.mesh.points.len(), 9 + 22, "{name}");
        let t = &m.mesh.point_data[0];
        assert_eq!(t.name, "temperature");
        for (i, p) in cube_points().into_iter().enumerate() {
            assert!((t.values[i] - temperature(p)).abs() < 1e-11, "{name}: {i}");
        }
    }
}

/// Triangles (sorted point triples) of the tets and how many tets have each.
fn face_counts(tets: &[[u32; 4]]) -> HashMap<[u32; 3], usize> {
    let mut faces = HashMap::new();
    for t in tets {
        for skip in 0..4 {
            let mut f: Vec<u32> = (0..4).filter(|&k| k != skip).map(|k| t[k]).collect();
            f.sort_unstable();
            *faces.entry([f[0], f[1], f[2]]).or_insert(0) += 1;
        }
    }
    faces
}

fn volume(p: &[[f64; 3]], t: [u32; 4]) -> f64 {
    tetwave_protocol::base::signed_volume(
        p[t[0] as usize],
        p[t[1] as usize],
        p[t[2] as usize],
        p[t[3] as usize],
    )
}

#[test]
fn hexahedra_wedges_and_pyramids_split_conformingly() {
    for name in [
        "volcells.vtu",
        "volcells_51.vtk",
        "volcells_22.msh",
        "volcells_22_binary.msh",
    ] {
        let m = read(name);
        let c = m.counts;
        assert_eq!(c.cells_read, 5, "{name}");
        assert_eq!(c.cells_split, 4, "{name}");
        assert_eq!(c.tets_from_split, 6 + 6 + 3 + 2, "{name}");
        assert_eq!(c.cells_lower_dim, 1, "{name}: the triangle");
        assert_eq!(
            m.tet_cells,
            [vec![0; 6], vec![1; 6], vec![2; 3], vec![3; 2]].concat()
        );
        // Every tet positive (VTK / gmsh orientation kept), volumes add up.
        let total: f64 = m.mesh.tets.iter().map(|&t| volume(&m.mesh.points, t)).sum();
        assert!(
            m.mesh.tets.iter().all(|&t| volume(&m.mesh.points, t) > 0.0),
            "{name}"
        );
        assert!(
            (total - (2.0 + 0.25 + 1.0 / 6.0)).abs() < 1e-12,
            "{name}: {total}"
        );
        // Conforming: no triangle in three tets, and the boundary is the 8 outer quads of the
        // hexes (16 triangles), the wedge's 2 triangles and 2 slanted quads (6) and the
        // pyramid's 4 sides: 26 triangles. A non-conforming split of the shared faces would
        // leave more triangles with one tet.
        let faces = face_counts(&m.mesh.tets);
        assert!(faces.values().all(|&k| k <= 2), "{name}");
        assert_eq!(faces.values().filter(|&&k| k == 1).count(), 26, "{name}");
        assert_eq!(
            cell_array(&m, "density"),
            &[1.0, 2.0, 3.0, 4.0, 9.0],
            "{name}"
        );
    }
}

#[test]
fn cell_and_vector_arrays_are_read() {
    for name in [
        "cube_celldata.vtu",
        "cube_celldata_42.vtk",
        "cube_celldata_41.msh",
    ] {
        let m = read(name);
        let density: Vec<f64> = (1..=7).map(f64::from).collect();
        assert_eq!(cell_array(&m, "density"), density.as_slice(), "{name}");
        let flow: Vec<f64> = (0..7)
            .flat_map(|i| [f64::from(i), 2.0 * f64::from(i), 0.0])
            .collect();
        let f = m.cell_data.iter().find(|a| a.name == "flow").unwrap();
        assert_eq!((f.components, f.values.as_slice()), (3, flow.as_slice()));
        let v = m
            .point_vectors
            .iter()
            .find(|a| a.name == "velocity")
            .unwrap();
        assert_eq!(v.components, 3, "{name}");
        let flat: Vec<f64> = cube_points().into_iter().flatten().collect();
        assert_eq!(v.values, flat, "{name}");
    }
}

fn opts(scalar: Option<&str>) -> ImportOptions<'_> {
    ImportOptions {
        scalar,
        field: None,
        nan_as: None,
    }
}

#[test]
fn cell_data_becomes_point_data_by_volume_weighting() {
    let (m, r) = clean_import(read("cube_celldata.vtu"), &opts(Some("density"))).unwrap();
    assert_eq!(r.scalar, "density");
    assert_eq!(r.scalar_source, "cell");
    assert!(r.notes.iter().any(|n| n.contains("volume-weighted")));
    // The 6 box tets have the same volume (0.7^3 / 6); the apex tet 0.245 * 0.4 / 3.
    let (v, w) = (0.343 / 6.0, 0.245 * 0.4 / 3.0);
    let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
    assert!(
        close(m.values[0], 3.5),
        "point 0 in tets 1..6: {}",
        m.values[0]
    );
    assert!(close(m.values[1], 1.5), "point 1 in tets 1, 2");
    assert!(close(m.values[8], 7.0), "the apex, in tet 7 only");
    let p4 = (5.0 * v + 6.0 * v + 7.0 * w) / (2.0 * v + w);
    assert!(close(m.values[4], p4), "point 4: {} vs {p4}", m.values[4]);
    // A component of a cell vector.
    let (m, r) = clean_import(read("cube_celldata.vtu"), &opts(Some("flow:1"))).unwrap();
    assert_eq!(
        (r.scalar.as_str(), r.scalar_source.as_str()),
        ("flow:1", "cell")
    );
    assert!(close(m.values[8], 12.0));
}

#[test]
fn vector_components_and_magnitude() {
    let pts = cube_points();
    let (m, r) = clean_import(read("cube_binary.vtu"), &opts(Some("velocity:0"))).unwrap();
    assert_eq!(
        (r.scalar.as_str(), r.scalar_source.as_str()),
        ("velocity:0", "point")
    );
    let x: Vec<f64> = pts.iter().map(|p| p[0]).collect();
    assert_eq!(m.values, x);
    let (m, _) = clean_import(read("cube_binary.vtu"), &opts(Some("velocity:z"))).unwrap();
    assert_eq!(m.values, pts.iter().map(|p| p[2]).collect::<Vec<_>>());
    for spec in ["velocity:mag", "velocity"] {
        let (m, r) = clean_import(read("cube_binary.vtu"), &opts(Some(spec))).unwrap();
        assert_eq!(r.scalar, "velocity:mag");
        let mag: Vec<f64> = pts
            .iter()
            .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
            .collect();
        assert_eq!(m.values, mag, "{spec}");
    }
    let err = clean_import(read("cube_binary.vtu"), &opts(Some("velocity:3")))
        .err()
        .unwrap();
    assert!(
        matches!(err, CleanError::UnknownComponent { components: 3, .. }),
        "{err}"
    );
    let err = clean_import(read("cube_binary.vtu"), &opts(Some("nope")))
        .err()
        .unwrap();
    let text = err.to_string();
    for needle in [
        "nope",
        "temperature (point)",
        "velocity (point, 3 components",
    ] {
        assert!(text.contains(needle), "{text}");
    }
}

#[test]
fn inverted_duplicate_and_degenerate_tets_are_counted() {
    let mut m = read("cube_42_ascii.vtk");
    // The fixture's tets 1, 3 and 5 (0-based) are negative; add a duplicate of tet 0 (permuted)
    // and a zero-volume tet.
    m.mesh.tets.push([7, 3, 1, 0]);
    m.mesh.tets.push([0, 1, 2, 3]);
    m.tet_cells.extend([0, 0]);
    let (clean, r) = clean_import(m, &opts(None)).unwrap();
    assert_eq!(r.tets_read, 9);
    assert_eq!(r.tets_reoriented, 3);
    assert_eq!(r.tets_dropped_duplicate, 1);
    assert_eq!(r.tets_dropped_degenerate, 1);
    assert_eq!(r.tets_dropped, 2);
    assert_eq!(r.tets_kept, 7);
    assert!(clean.tets.iter().all(|&t| volume(&clean.points, t) > 0.0));
}

#[test]
fn quality_min_dihedral_and_slivers() {
    let kuhn = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [1.0, 1.0, 1.0],
    ];
    assert!((min_dihedral_deg(kuhn) - 45.0).abs() < 1e-9);
    let regular = [
        [1.0, 1.0, 1.0],
        [1.0, -1.0, -1.0],
        [-1.0, 1.0, -1.0],
        [-1.0, -1.0, 1.0],
    ];
    assert!((min_dihedral_deg(regular) - (1.0f64 / 3.0).acos().to_degrees()).abs() < 1e-9);
    // A sliver: four points almost on a plane.
    let sliver = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.01],
    ];
    assert!(min_dihedral_deg(sliver) < 5.0);
    let (_, r) = clean_import(read("volcells.vtu"), &opts(None)).unwrap();
    assert_eq!(r.slivers, 0);
    assert!(
        (r.min_dihedral_deg - 26.565051177078).abs() < 1e-9,
        "{}",
        r.min_dihedral_deg
    );
}

#[test]
fn distance_field_for_a_bare_mesh() {
    // without arrays the distance field is the default, and a note says so
    let (m0, r0) = clean_import(read("bare_42.vtk"), &opts(None)).unwrap();
    assert!(m0.distance);
    assert_eq!(
        (r0.scalar.as_str(), r0.scalar_source.as_str()),
        ("distance", "geometric")
    );
    assert!(
        r0.notes
            .iter()
            .any(|n| n.contains("no point or cell arrays")),
        "{:?}",
        r0.notes
    );
    let o = ImportOptions {
        field: Some("distance"),
        ..opts(None)
    };
    let (m, r) = clean_import(read("bare_42.vtk"), &o).unwrap();
    assert_eq!(
        (r.scalar.as_str(), r.scalar_source.as_str()),
        ("distance", "geometric")
    );
    assert_eq!(m.values, m0.values);
    assert!(
        m.values.iter().all(|&d| d == 0.0),
        "every cube point is on the boundary"
    );
    // A cube coned from its centre: the centre is 0.5 from the boundary.
    let mut points = box_corners([0.0; 3], [1.0; 3]);
    points.push([0.5, 0.5, 0.5]);
    let quads = [
        [0, 1, 3, 2],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 3, 7, 5],
    ];
    let tets: Vec<[u32; 4]> = quads
        .iter()
        .flat_map(|q| [[8, q[0], q[1], q[2]], [8, q[0], q[2], q[3]]])
        .collect();
    let d = boundary_distance(&points, &tets);
    assert_eq!(d[8], 0.5);
    assert!(d[..8].iter().all(|&x| x == 0.0));
    let bad = ImportOptions {
        field: Some("curvature"),
        ..opts(None)
    };
    assert!(matches!(
        clean_import(read("bare_42.vtk"), &bad),
        Err(CleanError::UnknownField(_))
    ));
}

/// Without `--scalar`, a constant first array (a `node_groups` of zeros) is passed over for the
/// first array that varies; when every array is constant the first is kept, with a warning that
/// names them. `arrays` lists them all either way.
#[test]
fn default_scalar_skips_constant_arrays() {
    use tetwave_import::{FieldArray, ScalarArray, TetMesh};
    let points = cube_points();
    let mesh = |arrays: Vec<(&str, Vec<f64>)>, cells: Option<Vec<f64>>| {
        let tm = TetMesh {
            points: points.clone(),
            tets: tets(),
            point_data: arrays
                .into_iter()
                .map(|(name, values)| ScalarArray {
                    name: name.into(),
                    values,
                })
                .collect(),
            cells_ignored: 0,
        };
        let mut m = ImportedMesh::from(tm);
        if let Some(values) = cells {
            m.cell_data.push(FieldArray {
                name: "ref".into(),
                components: 1,
                values,
            });
        }
        m
    };
    let zeros = vec![0.0; points.len()];
    let temp: Vec<f64> = points.iter().map(|&p| temperature(p)).collect();
    let (m, r) = clean_import(
        mesh(
            vec![
                ("node_groups", zeros.clone()),
                ("temperature", temp.clone()),
            ],
            None,
        ),
        &opts(None),
    )
    .unwrap();
    assert_eq!(r.scalar, "temperature");
    assert_eq!(m.values, temp);
    let listed: Vec<(&str, bool)> = r
        .arrays
        .iter()
        .map(|a| (a.name.as_str(), a.constant))
        .collect();
    assert_eq!(listed, [("node_groups", true), ("temperature", false)]);
    assert!(
        r.notes.iter().any(|n| n.contains("chosen by default") && n.contains("node_groups (point, constant)")),
        "{:?}",
        r.notes
    );
    // A varying cell array after a constant point array is chosen too.
    let (_, r) = clean_import(
        mesh(
            vec![("node_groups", zeros.clone())],
            Some((1..=7).map(f64::from).collect()),
        ),
        &opts(None),
    )
    .unwrap();
    assert_eq!(
        (r.scalar.as_str(), r.scalar_source.as_str()),
        ("ref", "cell")
    );
    // Every array constant (Medit's ref of zeros too): the first, with a warning naming them.
    let (_, r) = clean_import(
        mesh(vec![("node_groups", zeros.clone())], Some(vec![0.0; 7])),
        &opts(None),
    )
    .unwrap();
    assert_eq!(r.scalar, "node_groups");
    let warning = r
        .notes
        .iter()
        .find(|n| n.starts_with("warning"))
        .expect("a warning");
    assert!(
        warning.contains("every array is constant")
            && warning.contains("node_groups (point, constant), ref (cell, constant)"),
        "{warning}"
    );
    // --scalar still picks a constant array without complaint.
    let (_, r) = clean_import(
        mesh(vec![("node_groups", zeros), ("temperature", temp)], None),
        &opts(Some("node_groups")),
    )
    .unwrap();
    assert_eq!(r.scalar, "node_groups");
    assert!(!r
        .notes
        .iter()
        .any(|n| n.contains("by default") || n.starts_with("warning")));
}

#[test]
fn surface_only_mesh_is_refused() {
    let err = clean_import(read("surface_only.msh"), &opts(None))
        .err()
        .unwrap();
    assert!(matches!(err, CleanError::NoTets { ignored: 2, .. }));
    assert!(err.to_string().contains("surface-only"), "{err}");
}

/// Malformed, naming the file, and the section and reason contain `needle`.
fn assert_fails(name: &str, needle: &str) {
    let err = match read_mesh(&fixture(name), None) {
        Ok(_) => panic!("{name}: read a broken file"),
        Err(e) => e,
    };
    let text = err.to_string();
    assert_eq!(text.lines().count(), 1, "{text}");
    let ImportError::Malformed {
        section, reason, ..
    } = err
    else {
        panic!("{name}: {text}")
    };
    assert!(text.contains(name), "{text}");
    let problem = format!("{section}: {reason}");
    assert!(
        problem.contains(needle),
        "{name}: expected \"{needle}\" in: {text}"
    );
}

#[test]
fn more_broken_files_fail_with_a_telling_error() {
    for (name, needle) in [
        (
            "wrong_type.vtu",
            "Piece 0 Cells: the offsets end at 28 but the connectivity has 56 values",
        ),
        ("wrong_type.vtk", "binary data where a keyword should be"),
        (
            "corrupt_zlib.vtu",
            "Piece 0 Points: zlib block 0 of 4 is corrupt",
        ),
        (
            "bad_cell_data_count.vtk",
            "CELL_DATA: CELL_DATA 5 but the file has 7 cells",
        ),
        (
            "bad_node_count_10.msh",
            "$ELM: element 2 announces 4 nodes but its line has 3",
        ),
    ] {
        assert_fails(name, needle);
    }
}

/// A Medit file whose sections are complete but which lacks `End` is read (meshio reads it); one
/// cut inside a section, inside the last number, or before its volume elements is still refused.
#[test]
fn medit_without_end_is_read_when_every_section_is_complete() {
    let bytes = std::fs::read(fixture("cube.mesh")).unwrap();
    let text = String::from_utf8(bytes.clone()).unwrap();
    let at = text.rfind("End").unwrap();
    let parse = |b: &[u8]| tetwave_import::parse_mesh(Path::new("cube.mesh"), b, MeshFormat::Medit);
    let full = parse(&bytes).unwrap();
    // No End, the file ends with the line end after the last record.
    let no_end = parse(&bytes[..at]).unwrap();
    assert_eq!(no_end, full);
    // The same without the blank line: still a line end after the last record.
    let trimmed = text[..at].trim_end().to_string() + "\n";
    assert_eq!(parse(trimmed.as_bytes()).unwrap(), full);
    // The last number without its line end could be the prefix of a longer one.
    let err = parse(text[..at].trim_end().as_bytes()).unwrap_err();
    assert!(err.to_string().contains("no End keyword"), "{err}");
    // Cut inside the Tetrahedra section (after a whole line): a count is not read in full.
    let tets_at = text.find("Tetrahedra").unwrap();
    let line2 = tets_at + text[tets_at..].match_indices('\n').nth(2).unwrap().0 + 1;
    let err = parse(&bytes[..line2]).unwrap_err();
    assert!(err.to_string().contains("truncated"), "{err}");
    // Cut after the vertices, before any volume element: refused.
    let err = parse(&bytes[..tets_at]).unwrap_err();
    assert!(err.to_string().contains("no End keyword"), "{err}");
}

#[test]
fn new_fixtures_survive_truncation() {
    for name in [
        "cube_10.msh",
        "cube.mesh",
        "volcells.vtu",
        "volcells_22_binary.msh",
        "cube_celldata_41.msh",
        "quadratic_22.msh",
    ] {
        let bytes = std::fs::read(fixture(name)).unwrap();
        let fmt = tetwave_import::format_of(Path::new(name)).unwrap();
        let full = tetwave_import::parse_mesh(Path::new(name), &bytes, fmt).unwrap();
        for len in 0..bytes.len() {
            match tetwave_import::parse_mesh(Path::new(name), &bytes[..len], fmt) {
                Err(ImportError::Malformed { .. }) => {}
                Err(e) => panic!("{name}[..{len}]: {e:?}"),
                Ok(m) => {
                    assert_eq!(m.mesh.points, full.mesh.points, "{name}[..{len}]");
                    assert_eq!(m.mesh.tets, full.mesh.tets, "{name}[..{len}]");
                }
            }
        }
    }
}

/// Random byte changes on the new fixtures: an error or a consistent mesh, never a panic.
#[test]
fn new_fixtures_corrupted_never_panic() {
    let mut rng = Corruptor::new(0x9e37_79b9_7f4a_7c15);
    for name in [
        "cube_10.msh",
        "cube.mesh",
        "volcells.vtu",
        "volcells_51.vtk",
        "volcells_22_binary.msh",
        "cube_celldata.vtu",
        "cube_celldata_42.vtk",
        "cube_celldata_41.msh",
        "quadratic.vtu",
    ] {
        let bytes = std::fs::read(fixture(name)).unwrap();
        let fmt = tetwave_import::format_of(Path::new(name)).unwrap();
        for round in 0..300 {
            let b = rng.corrupt(&bytes, round);
            match tetwave_import::parse_mesh(Path::new(name), &b, fmt) {
                Ok(m) => {
                    let n = m.mesh.points.len();
                    assert!(m.mesh.tets.iter().flatten().all(|&v| (v as usize) < n));
                    let _ = clean_import(m, &opts(None));
                }
                Err(e) => assert!(matches!(e, ImportError::Malformed { .. }), "{e:?}"),
            }
        }
    }
}

/// Two tets in two physical groups (1: elementary 10, 2: elementary 20) and a triangle (3, 30),
/// in every gmsh variant the reader takes, written here byte by byte.
fn two_groups_msh() -> Vec<(&'static str, Vec<u8>)> {
    const P: [[f64; 3]; 5] = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 1.0, 1.0],
    ];
    let i = |b: &mut Vec<u8>, v: i32| b.extend_from_slice(&v.to_le_bytes());
    let z = |b: &mut Vec<u8>, v: u64| b.extend_from_slice(&v.to_le_bytes());
    let f = |b: &mut Vec<u8>, v: f64| b.extend_from_slice(&v.to_le_bytes());
    let s = |b: &mut Vec<u8>, t: &str| b.extend_from_slice(t.as_bytes());
    let nodes_ascii: String = P
        .iter()
        .enumerate()
        .map(|(k, p)| format!("{} {} {} {}\n", k + 1, p[0], p[1], p[2]))
        .collect();
    let v10 = format!(
        "$NOD\n5\n{nodes_ascii}$ENDNOD\n$ELM\n3\n1 2 3 30 3 2 3 4\n2 4 1 10 4 1 2 3 4\n3 4 2 20 4 2 3 4 5\n$ENDELM\n"
    );
    let v22 = format!(
        "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$PhysicalNames\n2\n3 1 \"inner\"\n3 2 \"outer\"\n$EndPhysicalNames\n\
         $Nodes\n5\n{nodes_ascii}$EndNodes\n$Elements\n3\n1 2 2 3 30 2 3 4\n2 4 2 1 10 1 2 3 4\n3 4 2 2 20 2 3 4 5\n$EndElements\n"
    );
    let mut b22 = Vec::new();
    s(&mut b22, "$MeshFormat\n2.2 1 8\n");
    i(&mut b22, 1);
    s(&mut b22, "\n$EndMeshFormat\n$Nodes\n5\n");
    for (k, p) in P.iter().enumerate() {
        i(&mut b22, k as i32 + 1);
        p.iter().for_each(|&x| f(&mut b22, x));
    }
    s(&mut b22, "\n$EndNodes\n$Elements\n3\n");
    for v in [
        vec![2, 1, 2, 1, 3, 30, 2, 3, 4],
        vec![4, 2, 2, 2, 1, 10, 1, 2, 3, 4, 3, 2, 20, 2, 3, 4, 5],
    ] {
        v.iter().for_each(|&x| i(&mut b22, x));
    }
    s(&mut b22, "\n$EndElements\n");
    let v41 = format!(
        "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Entities\n0 0 1 2\n30 0 0 0 1 1 1 1 3 0\n\
         10 0 0 0 1 1 1 1 1 1 30\n20 0 0 0 1 1 1 1 2 1 -30\n$EndEntities\n\
         $Nodes\n1 5 1 5\n3 10 0 5\n1\n2\n3\n4\n5\n{}$EndNodes\n\
         $Elements\n3 3 1 3\n2 30 2 1\n1 2 3 4\n3 10 4 1\n2 1 2 3 4\n3 20 4 1\n3 2 3 4 5\n$EndElements\n",
        P.iter().map(|p| format!("{} {} {}\n", p[0], p[1], p[2])).collect::<String>()
    );
    let mut b41 = Vec::new();
    s(&mut b41, "$MeshFormat\n4.1 1 8\n");
    i(&mut b41, 1);
    s(&mut b41, "\n$EndMeshFormat\n$Entities\n");
    [0, 0, 1, 2].iter().for_each(|&n| z(&mut b41, n));
    for (tag, phys, bound) in [(30, 3, None), (10, 1, Some(30)), (20, 2, Some(-30))] {
        i(&mut b41, tag);
        [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
            .iter()
            .for_each(|&x| f(&mut b41, x));
        z(&mut b41, 1);
        i(&mut b41, phys);
        match bound {
            None => z(&mut b41, 0),
            Some(t) => {
                z(&mut b41, 1);
                i(&mut b41, t);
            }
        }
    }
    s(&mut b41, "\n$EndEntities\n$Nodes\n");
    [1, 5, 1, 5].iter().for_each(|&n| z(&mut b41, n));
    [3, 10, 0].iter().for_each(|&n| i(&mut b41, n));
    z(&mut b41, 5);
    (1..=5).for_each(|k| z(&mut b41, k));
    P.iter().flatten().for_each(|&x| f(&mut b41, x));
    s(&mut b41, "\n$EndNodes\n$Elements\n");
    [3, 3, 1, 3].iter().for_each(|&n| z(&mut b41, n));
    for (dim, ent, ty, rec) in [
        (2, 30, 2, vec![1u64, 2, 3, 4]),
        (3, 10, 4, vec![2, 1, 2, 3, 4]),
        (3, 20, 4, vec![3, 2, 3, 4, 5]),
    ] {
        [dim, ent, ty].iter().for_each(|&n| i(&mut b41, n));
        z(&mut b41, 1);
        rec.iter().for_each(|&n| z(&mut b41, n));
    }
    s(&mut b41, "\n$EndElements\n");
    vec![
        ("1.0", v10.into_bytes()),
        ("2.2 ascii", v22.into_bytes()),
        ("2.2 binary", b22),
        ("4.1 ascii", v41.into_bytes()),
        ("4.1 binary", b41),
    ]
}

/// gmsh physical and elementary tags become the cell arrays `gmsh:physical` and
/// `gmsh:geometrical` (one value per element, the triangle's too) in 1.0, 2.2 and 4.1, ascii and
/// binary; the default scalar is the physical group, which varies.
#[test]
fn gmsh_tags_become_cell_arrays() {
    for (variant, bytes) in two_groups_msh() {
        let m = tetwave_import::parse_mesh(Path::new("two.msh"), &bytes, MeshFormat::Msh)
            .unwrap_or_else(|e| panic!("{variant}: {e}"));
        assert_eq!(m.mesh.tets, [[0, 1, 2, 3], [1, 2, 3, 4]], "{variant}");
        assert_eq!(m.tet_cells, [1, 2], "{variant}");
        let names: Vec<&str> = m.cell_data.iter().map(|a| a.name.as_str()).collect();
        assert_eq!(names, ["gmsh:physical", "gmsh:geometrical"], "{variant}");
        assert_eq!(
            cell_array(&m, "gmsh:physical"),
            [3.0, 1.0, 2.0],
            "{variant}"
        );
        assert_eq!(
            cell_array(&m, "gmsh:geometrical"),
            [30.0, 10.0, 20.0],
            "{variant}"
        );
        let (_, r) = clean_import(m, &opts(None)).unwrap();
        assert_eq!(r.scalar, "gmsh:physical", "{variant}");
    }
}

/// `--field distance` on meshes whose every vertex lies on the boundary (one big tet; a slab of
/// 6 Kuhn tets): zero at every input vertex, yet the resampled field is the exact distance to the
/// boundary at every lattice vertex inside, since it is computed there and not interpolated.
#[test]
fn distance_field_is_computed_at_the_resampled_vertices() {
    use tetwave_import::TetMesh;
    use tetwave_server::resample::unstructured::{bbox, Locator};
    use tetwave_server::resample::{resample, BaseSpec, Source};
    let s3 = 3f64.sqrt();
    let tet = |p: [f64; 3]| (p[0].min(p[1]).min(p[2])).min((1.0 - p[0] - p[1] - p[2]) / s3);
    let slab = |p: [f64; 3]| {
        [p[0], 4.0 - p[0], p[1], 4.0 - p[1], p[2], 1.0 - p[2]]
            .into_iter()
            .fold(f64::INFINITY, f64::min)
    };
    let (slab_points, slab_tets) = tetwave_server::resample::base::box6([0.0; 3], [4.0, 4.0, 1.0]);
    /// Name, points, tets and the exact distance to the boundary.
    type Case<'a> = (
        &'a str,
        Vec<[f64; 3]>,
        Vec<[u32; 4]>,
        &'a dyn Fn([f64; 3]) -> f64,
    );
    let cases: [Case; 2] = [
        (
            "tet",
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            vec![[0, 1, 2, 3]],
            &tet,
        ),
        ("slab", slab_points, slab_tets, &slab),
    ];
    for (name, points, tets, exact) in cases {
        let m = ImportedMesh::from(TetMesh {
            points,
            tets,
            ..TetMesh::default()
        });
        let o = ImportOptions {
            field: Some("distance"),
            ..opts(None)
        };
        let (clean, _) = clean_import(m, &o).unwrap();
        assert!(
            clean.values.iter().all(|&v| v == 0.0),
            "{name}: every vertex is on the boundary"
        );
        let loc = Locator::new(&clean);
        for p in [
            [0.1, 0.2, 0.3],
            [0.2, 0.2, 0.2],
            [0.25, 0.25, 0.25],
            [0.05, 0.1, 0.02],
        ] {
            let d = loc.sample(p).expect("inside");
            assert!(
                (d - exact(p)).abs() < 1e-12,
                "{name} at {p:?}: {d} vs {}",
                exact(p)
            );
        }
        assert_eq!(loc.sample([2.0, 2.0, 2.0]), None, "{name}");
        let bounds = bbox(&clean.points);
        let r = resample(&Source::Mesh(Box::new(loc), bounds), &BaseSpec::Box6, 3).unwrap();
        let (mut inside, mut positive) = (0, 0);
        for (e, _) in r.keys.entities() {
            r.keys.for_each_in(e, |key, t, w| {
                let v = r.samples[key as usize];
                if v.is_nan() {
                    return;
                }
                let p = r.base.position(t, &w);
                let want = exact(p).max(0.0);
                assert!(
                    (f64::from(v) - want).abs() < 1e-6,
                    "{name}: lattice vertex {p:?}: {v} vs {want}"
                );
                inside += 1;
                positive += usize::from(v > 0.0);
            });
        }
        assert!(
            positive > 0 && inside > positive,
            "{name}: {positive} of {inside} positive"
        );
    }
}
