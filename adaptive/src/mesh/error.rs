//! Errors of the mesh's operations.

use tetwave_protocol::TetId;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MeshError {
    #[error("tet {0} is not in the mesh (an ancestor is a leaf)")]
    NotInMesh(TetId),
    #[error("tet {0} is already refined")]
    NotLeaf(TetId),
    #[error("tet {0} is at the finest level")]
    Finest(TetId),
    #[error("tet {0} is empty (outside the domain) and is not refined on request")]
    Empty(TetId),
    #[error("tet {0} is not refined")]
    NotRefined(TetId),
    #[error("tet {0}: some children are refined")]
    ChildrenRefined(TetId),
    #[error("coarsening tet {0} refused: the closure would refine it again")]
    Forced(TetId),
    #[error("green closure did not settle within {0} refinements")]
    ClosureBound(usize),
    #[error("the hierarchy has {0} vertex keys: more than this target's key table can index")]
    TooManyKeys(u64),
    #[error("the hierarchy has {0} tets: the adaptive mesh holds at most 2^40")]
    TooManyTets(u64),
    #[error(transparent)]
    Axes(#[from] tetwave_protocol::axes::AxesError),
}
