//! What the readers return: [`TetMesh`] (the tets with their scalar point arrays) and
//! [`ImportedMesh`] (everything else an import reads: cell arrays, vector arrays, cell counts).

/// A tetrahedral mesh as read from a file, before any cleaning (orientation, degenerate tets).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TetMesh {
    pub points: Vec<[f64; 3]>,
    /// Tets (4 point indices each, in the file's order): linear tets as they are, the corner tet
    /// of higher-order tets, and the tets hexahedra, wedges and pyramids were split into.
    pub tets: Vec<[u32; 4]>,
    /// Scalar point arrays, in file order; each has one value per point.
    pub point_data: Vec<ScalarArray>,
    /// Cells that gave no tets (points, lines, surfaces, unsupported volume kinds): skipped.
    pub cells_ignored: usize,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ScalarArray {
    pub name: String,
    pub values: Vec<f64>,
}

/// An array with `components` values per point or per cell (tuples stored one after the other).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldArray {
    pub name: String,
    pub components: usize,
    pub values: Vec<f64>,
}

impl FieldArray {
    /// Number of tuples.
    pub fn len(&self) -> usize {
        self.values.len() / self.components.max(1)
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }
}

/// What the readers did with the file's cells.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CellCounts {
    /// Every cell of the file, whatever its kind.
    pub cells_read: usize,
    /// Linear tets.
    pub tets: usize,
    /// Higher-order tets reduced to their corner tet (VTK 24, gmsh 11, ...).
    pub tets_linearized: usize,
    /// Hexahedra, wedges and pyramids split into tets.
    pub cells_split: usize,
    /// The tets the split cells gave.
    pub tets_from_split: usize,
    /// Points, lines and surface cells.
    pub cells_lower_dim: usize,
    /// Volume cells of a kind that is not read (polyhedra, Lagrange cells...).
    pub cells_unsupported: usize,
}

/// Everything an import reads: the tet mesh with its scalar point arrays, plus the cell arrays,
/// the point arrays with several components and what was done with the cells.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImportedMesh {
    pub mesh: TetMesh,
    /// For each tet of `mesh.tets`, the file cell it comes from (cell arrays are indexed by it).
    pub tet_cells: Vec<usize>,
    /// Point arrays with more than one component.
    pub point_vectors: Vec<FieldArray>,
    /// Cell arrays (any number of components), one tuple per file cell.
    pub cell_data: Vec<FieldArray>,
    pub counts: CellCounts,
}

impl From<TetMesh> for ImportedMesh {
    fn from(mesh: TetMesh) -> Self {
        let n = mesh.tets.len();
        ImportedMesh {
            counts: CellCounts {
                cells_read: n + mesh.cells_ignored,
                tets: n,
                cells_lower_dim: mesh.cells_ignored,
                ..CellCounts::default()
            },
            tet_cells: (0..n).collect(),
            mesh,
            ..ImportedMesh::default()
        }
    }
}
