//! Issue 19, the outside is empty: a store prepared from a non-convex mesh (a cube with one octant
//! removed) draws no tet that lies outside the input domain, at any level: not the translucent box
//! the whole lattice used to draw. (What remains is a staircase of lattice tets along the boundary:
//! clipping inside straddling tets is not done yet.)

use glam::DVec3;
use std::fmt::Write as _;
use tetwave_protocol::shapes::kuhn_grid;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_server::prepare::{prepare, PrepareOptions};
use tetwave_store::Store;

/// `[0,1]^3` minus the octant `[0.5,1]^3`, as 8³ Kuhn cubes, in legacy VTK with `f = x + 2y + 3z`.
fn cube_minus_octant_vtk() -> String {
    let (points, tets) = kuhn_grid(8, |i, j, k| !(i >= 4 && j >= 4 && k >= 4));
    // drop the points no tet uses
    let mut used = vec![u32::MAX; points.len()];
    let mut pts = Vec::new();
    let tets: Vec<[u32; 4]> = tets
        .iter()
        .map(|t| {
            t.map(|v| {
                if used[v as usize] == u32::MAX {
                    used[v as usize] = pts.len() as u32;
                    pts.push(points[v as usize]);
                }
                used[v as usize]
            })
        })
        .collect();
    let mut s = String::from(
        "# vtk DataFile Version 3.0\ncube minus octant\nASCII\nDATASET UNSTRUCTURED_GRID\n",
    );
    writeln!(s, "POINTS {} double", pts.len()).unwrap();
    for p in &pts {
        writeln!(s, "{} {} {}", p[0], p[1], p[2]).unwrap();
    }
    writeln!(s, "CELLS {} {}", tets.len(), 5 * tets.len()).unwrap();
    for t in &tets {
        writeln!(s, "4 {} {} {} {}", t[0], t[1], t[2], t[3]).unwrap();
    }
    writeln!(s, "CELL_TYPES {}", tets.len()).unwrap();
    for _ in &tets {
        s.push_str("10\n");
    }
    writeln!(
        s,
        "POINT_DATA {}\nSCALARS f double 1\nLOOKUP_TABLE default",
        pts.len()
    )
    .unwrap();
    for p in &pts {
        writeln!(s, "{}", p[0] + 2.0 * p[1] + 3.0 * p[2]).unwrap();
    }
    s
}

/// How far a tet reaches into the removed octant: the smallest distance from its centroid to the
/// octant's three inner faces (negative outside the octant).
fn depth_in_octant(mesh: &RenderMesh, t: &[u32; 4]) -> (f64, f64) {
    let p: Vec<DVec3> = t
        .iter()
        .map(|&v| DVec3::from_array(mesh.positions[v as usize]))
        .collect();
    let c = (p[0] + p[1] + p[2] + p[3]) / 4.0;
    let mut edge = 0f64;
    for i in 0..4 {
        for j in i + 1..4 {
            edge = edge.max(p[i].distance(p[j]));
        }
    }
    ((c.x - 0.5).min(c.y - 0.5).min(c.z - 0.5), edge)
}

#[test]
fn no_tet_outside_the_domain_at_any_level() {
    let d = tempfile::tempdir().unwrap();
    let input = d.path().join("cube_minus_octant.vtk");
    std::fs::write(&input, cube_minus_octant_vtk()).unwrap();
    let out = d.path().join("store");
    let mut o = PrepareOptions::new(input.to_str().unwrap(), &out);
    o.levels = Some(4);
    prepare(&o).unwrap();
    let store = Store::open(&out).unwrap();
    let values = store.synthesize_all().unwrap();
    let empty = store.empty_children().unwrap();
    for level in 1..=4 {
        let all = RenderMesh::uniform_level(&store.base, &values, &[], level);
        let mesh = RenderMesh::uniform_level(&store.base, &values, &empty, level);
        let deep = |m: &RenderMesh| {
            m.tets
                .iter()
                .filter(|t| {
                    let (depth, edge) = depth_in_octant(m, t);
                    depth > edge
                })
                .count()
        };
        println!(
            "level {level}: {} of {} lattice tets drawn; {} lie deeper than their size in the \
             removed octant without the empty masks, {} with them",
            mesh.tets.len(),
            all.tets.len(),
            deep(&all),
            deep(&mesh)
        );
        assert_eq!(
            deep(&mesh),
            0,
            "level {level}: a tet inside the removed octant is drawn"
        );
        if level >= 3 {
            assert!(deep(&all) > 0, "the test must see what the masks remove");
            assert!(mesh.tets.len() < all.tets.len());
        }
    }
}
