//! Readers of unstructured tetrahedral meshes: VTK XML `.vtu`, legacy `.vtk`, gmsh `.msh`.
//!
//! Every reader returns a [`TetMesh`] or an [`ImportError`] naming the file, the section and the
//! reason; none panics on malformed input and none passes on a partial mesh as if whole.

use std::path::{Path, PathBuf};

/// A tetrahedral mesh as read from a file, before any cleaning (orientation, degenerate tets).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TetMesh {
    pub points: Vec<[f64; 3]>,
    /// Linear tets (4 point indices each, in the file's order).
    pub tets: Vec<[u32; 4]>,
    /// Scalar point arrays, in file order; each has one value per point.
    pub point_data: Vec<ScalarArray>,
    /// Cells that are not linear tets (lines, triangles, other kinds) and were skipped.
    pub cells_ignored: usize,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ScalarArray {
    pub name: String,
    pub values: Vec<f64>,
}

/// Mesh file formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Vtu,
    LegacyVtk,
    Msh,
}

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: unknown mesh format (expected .vtu, .vtk or .msh)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: {section}: {reason}")]
    Malformed {
        path: PathBuf,
        section: String,
        reason: String,
    },
}

/// Format from the file's extension.
pub fn format_of(path: &Path) -> Option<MeshFormat> {
    match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
        "vtu" => Some(MeshFormat::Vtu),
        "vtk" => Some(MeshFormat::LegacyVtk),
        "msh" => Some(MeshFormat::Msh),
        _ => None,
    }
}

/// Reads a tetrahedral mesh with its point scalars.
pub fn read_tet_mesh(path: &Path) -> Result<TetMesh, ImportError> {
    let _ = format_of(path).ok_or_else(|| ImportError::UnknownFormat {
        path: path.to_path_buf(),
    })?;
    Err(ImportError::Malformed {
        path: path.to_path_buf(),
        section: "reader".into(),
        reason: "mesh readers are being written".into(),
    })
}
