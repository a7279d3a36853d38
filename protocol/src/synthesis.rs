//! Whole-hierarchy synthesis: every vertex value of the finest level from the base values and all
//! detail nodes. The server's `verify` and the client's "complete" mode both use it.

use crate::base::BaseMesh;
use crate::hierarchy::LevelWalker;
use crate::hierarchy::{TetId, EDGES};
use crate::node::{DetailNode, NodeError};
use crate::vertex::VertexKeys;
use crate::wavelet::{predict, synthesize};
use crate::LatticeTet;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SynthesisError {
    #[error(
        "expected node {expected}, got {got}: nodes must come in increasing id order without gaps"
    )]
    OutOfOrder { expected: TetId, got: TetId },
    #[error("node {id} is beyond the hierarchy's {nodes} nodes")]
    OutOfRange { id: TetId, nodes: u64 },
    #[error("{missing} nodes missing at the end")]
    Missing { missing: u64 },
    #[error("vertex {key} was never given a value (ownership masks do not cover it)")]
    Uncovered { key: u64 },
    #[error("vertex {key} is owned twice (by node {id} and an earlier node)")]
    OwnedTwice { key: u64, id: TetId },
    #[error(transparent)]
    Node(#[from] NodeError),
}

/// Values of all `keys.vertex_count()` vertices, from nodes given in increasing id order `0..nodes`.
pub fn synthesize_all(
    base: &BaseMesh,
    keys: &VertexKeys,
    nodes: impl IntoIterator<Item = DetailNode>,
) -> Result<Vec<f32>, SynthesisError> {
    let forest = base.forest();
    let n = keys.vertex_count() as usize;
    let mut values = vec![f32::NAN; n];
    let mut set = vec![false; n];
    for (v, &x) in base.values.iter().enumerate() {
        values[v] = x;
        set[v] = true;
    }
    let total = forest.nodes();
    let mut expected: TetId = 0;
    // nodes come in id order: walk the levels alongside instead of rebuilding each tet from its id
    let mut level = 0u8;
    let mut walker = LevelWalker::level(forest, 0);
    for node in nodes {
        if node.id >= total {
            return Err(SynthesisError::OutOfRange {
                id: node.id,
                nodes: total,
            });
        }
        if node.id != expected {
            return Err(SynthesisError::OutOfOrder {
                expected,
                got: node.id,
            });
        }
        node.validate()?;
        expected += 1;
        while node.id >= forest.level_start(level + 1) {
            level += 1;
            walker = LevelWalker::level(forest, level);
        }
        let (id, tet) = walker.next().expect("ids within the level");
        debug_assert_eq!(id, node.id);
        apply_node(keys, &tet, &node, &mut values, &mut set)?;
    }
    if expected != total {
        return Err(SynthesisError::Missing {
            missing: total - expected,
        });
    }
    if let Some(k) = set.iter().position(|&s| !s) {
        return Err(SynthesisError::Uncovered { key: k as u64 });
    }
    Ok(values)
}

/// Sets the values of the vertices `node` owns on `tet` (its endpoints must already have values).
pub fn apply_node(
    keys: &VertexKeys,
    tet: &LatticeTet,
    node: &DetailNode,
    values: &mut [f32],
    set: &mut [bool],
) -> Result<(), SynthesisError> {
    for (e, &(a, b)) in EDGES.iter().enumerate() {
        if let Some(d) = node.coeff(e) {
            let k = keys.key(tet.base, &tet.edge_midpoint(e)) as usize;
            if set[k] {
                return Err(SynthesisError::OwnedTwice {
                    key: k as u64,
                    id: node.id,
                });
            }
            let u = keys.key(tet.base, &tet.v[a]) as usize;
            let v = keys.key(tet.base, &tet.v[b]) as usize;
            values[k] = synthesize(d, predict(values[u], values[v]));
            set[k] = true;
        }
    }
    Ok(())
}
