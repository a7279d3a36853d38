//! Cell kinds as the readers see them ([`vtk_cell`], [`gmsh_cell`]), the split of hexahedra, wedges
//! and pyramids into tets ([`split_cell`]) and [`ImportedMesh::push_cell`], which counts each file
//! cell and keeps its tets.

use super::mesh::ImportedMesh;

/// Volume cell shapes that become tets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Shape {
    Tet,
    Hex,
    Wedge,
    Pyramid,
}

impl Shape {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Shape::Tet => "tetra",
            Shape::Hex => "hexahedron",
            Shape::Wedge => "wedge",
            Shape::Pyramid => "pyramid",
        }
    }
}

/// A cell kind as a reader sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Cell {
    /// A volume cell: its shape, its node count, and the positions of its corners in its node list
    /// in VTK order (`corners.len()` < `nodes` for higher-order cells).
    Volume {
        shape: Shape,
        nodes: usize,
        corners: &'static [usize],
    },
    /// Points, lines, surfaces.
    Lower,
    /// A volume kind that is not read.
    Unsupported,
}

const C4: &[usize] = &[0, 1, 2, 3];
const C5: &[usize] = &[0, 1, 2, 3, 4];
const C6: &[usize] = &[0, 1, 2, 3, 4, 5];
const C8: &[usize] = &[0, 1, 2, 3, 4, 5, 6, 7];

const fn vol(shape: Shape, nodes: usize, corners: &'static [usize]) -> Cell {
    Cell::Volume {
        shape,
        nodes,
        corners,
    }
}

/// VTK cell types (legacy and XML).
pub(crate) fn vtk_cell(ty: i64) -> Cell {
    match ty {
        10 => vol(Shape::Tet, 4, C4),
        24 => vol(Shape::Tet, 10, C4),
        12 => vol(Shape::Hex, 8, C8),
        // voxel: x fastest, then y, then z
        11 => vol(Shape::Hex, 8, &[0, 1, 3, 2, 4, 5, 7, 6]),
        25 => vol(Shape::Hex, 20, C8),
        29 => vol(Shape::Hex, 27, C8),
        13 => vol(Shape::Wedge, 6, C6),
        26 => vol(Shape::Wedge, 15, C6),
        32 => vol(Shape::Wedge, 18, C6),
        14 => vol(Shape::Pyramid, 5, C5),
        27 => vol(Shape::Pyramid, 13, C5),
        1..=9 | 21..=23 | 28 | 30 | 34..=37 | 68..=70 | 75..=77 => Cell::Lower,
        _ => Cell::Unsupported,
    }
}

/// gmsh element types (all versions). gmsh lists the corners first; its prism turns the other way
/// round than VTK's wedge.
pub(crate) fn gmsh_cell(ty: i64) -> Cell {
    const PRISM: &[usize] = &[0, 2, 1, 3, 5, 4];
    match ty {
        4 => vol(Shape::Tet, 4, C4),
        11 => vol(Shape::Tet, 10, C4),
        29 => vol(Shape::Tet, 20, C4),
        30 => vol(Shape::Tet, 35, C4),
        31 => vol(Shape::Tet, 56, C4),
        5 => vol(Shape::Hex, 8, C8),
        12 => vol(Shape::Hex, 27, C8),
        17 => vol(Shape::Hex, 20, C8),
        92 => vol(Shape::Hex, 64, C8),
        93 => vol(Shape::Hex, 125, C8),
        6 => vol(Shape::Wedge, 6, PRISM),
        13 => vol(Shape::Wedge, 18, PRISM),
        18 => vol(Shape::Wedge, 15, PRISM),
        7 => vol(Shape::Pyramid, 5, C5),
        14 => vol(Shape::Pyramid, 14, C5),
        19 => vol(Shape::Pyramid, 13, C5),
        1..=3 | 8..=10 | 15 | 16 | 20..=28 => Cell::Lower,
        _ => Cell::Unsupported,
    }
}

// Faces of each shape in VTK corner order, counter-clockwise seen from outside.
const HEX_FACES: &[&[usize]] = &[
    &[0, 3, 2, 1],
    &[4, 5, 6, 7],
    &[0, 1, 5, 4],
    &[1, 2, 6, 5],
    &[2, 3, 7, 6],
    &[3, 0, 4, 7],
];
const WEDGE_FACES: &[&[usize]] = &[
    &[0, 1, 2],
    &[3, 5, 4],
    &[0, 3, 4, 1],
    &[1, 4, 5, 2],
    &[2, 5, 3, 0],
];
const PYRAMID_FACES: &[&[usize]] = &[
    &[0, 3, 2, 1],
    &[0, 1, 4],
    &[1, 2, 4],
    &[2, 3, 4],
    &[3, 0, 4],
];

/// Splits a convex cell (its corner point indices in VTK order) into tets, conforming across
/// shared faces: every quad face is cut by the diagonal from its smallest point index, and the
/// cell is coned from its smallest point index over the faces that do not hold it (a hexahedron
/// gives 6 tets, a wedge 3, a pyramid 2). With VTK's orientation the tets are positive.
pub(crate) fn split_cell(v: &[u32], shape: Shape, out: &mut Vec<[u32; 4]>) {
    let faces = match shape {
        Shape::Tet => {
            if let [a, b, c, d] = *v {
                out.push([a, b, c, d]);
            }
            return;
        }
        Shape::Hex => HEX_FACES,
        Shape::Wedge => WEDGE_FACES,
        Shape::Pyramid => PYRAMID_FACES,
    };
    let Some(apex) = (0..v.len()).min_by_key(|&i| v[i]) else {
        return;
    };
    let p = |i: usize| v.get(i).copied().unwrap_or(0);
    for f in faces {
        if f.contains(&apex) {
            continue;
        }
        match f.len() {
            3 => out.push([p(apex), p(f[0]), p(f[1]), p(f[2])]),
            _ => {
                let k = (0..4).min_by_key(|&i| p(f[i])).unwrap_or(0);
                let q = |j: usize| p(f[(k + j) % 4]);
                out.push([p(apex), q(0), q(1), q(2)]);
                out.push([p(apex), q(0), q(2), q(3)]);
            }
        }
    }
}

impl ImportedMesh {
    /// Adds the next file cell. `nodes` are point indices already checked against the points
    /// (only read for volume cells, whose node count the caller has checked).
    pub(crate) fn push_cell(&mut self, cell: Cell, nodes: &[u32]) {
        let index = self.counts.cells_read;
        self.counts.cells_read += 1;
        match cell {
            Cell::Lower => {
                self.counts.cells_lower_dim += 1;
                self.mesh.cells_ignored += 1;
            }
            Cell::Unsupported => {
                self.counts.cells_unsupported += 1;
                self.mesh.cells_ignored += 1;
            }
            Cell::Volume {
                shape,
                nodes: n,
                corners,
            } => {
                let c: Vec<u32> = corners
                    .iter()
                    .map(|&i| nodes.get(i).copied().unwrap_or(0))
                    .collect();
                let before = self.mesh.tets.len();
                split_cell(&c, shape, &mut self.mesh.tets);
                let made = self.mesh.tets.len() - before;
                self.tet_cells.extend(std::iter::repeat_n(index, made));
                match shape {
                    Shape::Tet if n > 4 => self.counts.tets_linearized += 1,
                    Shape::Tet => self.counts.tets += 1,
                    _ => {
                        self.counts.cells_split += 1;
                        self.counts.tets_from_split += made;
                    }
                }
            }
        }
    }
}

/// Checks a volume cell's node count: `Err(reason)` when it disagrees with its kind.
pub(crate) fn check_nodes(cell: Cell, got: usize, what: &str) -> Result<(), String> {
    match cell {
        Cell::Volume { shape, nodes, .. } if nodes != got => Err(format!(
            "{what} is a {nodes}-node {} with {got} points",
            shape.name()
        )),
        _ => Ok(()),
    }
}
