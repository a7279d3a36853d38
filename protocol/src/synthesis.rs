//! Whole-hierarchy synthesis: every vertex value of the finest level from the base values and all
//! detail nodes. The server's `verify` and the client's "complete" mode both use it.
//!
//! With [`Predictor::Axes`] the nodes give every vertex its detail first, and the axes passes
//! ([`Grid::predict_all`]) then synthesize the values, coarse to fine.

use crate::axes::{AxesError, Grid};
use crate::base::BaseMesh;
use crate::hierarchy::{Forest, LevelWalker};
use crate::hierarchy::{TetId, BEY_CHILDREN, EDGES};
use crate::node::{DetailNode, NodeError};
use crate::vertex::VertexKeys;
use crate::wavelet::{predict, predict_split, synthesize, Predictor};
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
    #[error(transparent)]
    Axes(#[from] AxesError),
}

/// Values of all `keys.vertex_count()` vertices, from nodes given in increasing id order `0..nodes`.
pub fn synthesize_all(
    base: &BaseMesh,
    keys: &VertexKeys,
    nodes: impl IntoIterator<Item = DetailNode>,
) -> Result<Vec<f32>, SynthesisError> {
    let grid = match base.predictor {
        Predictor::Parent => None,
        Predictor::Axes => Some(Grid::of(base, keys)?),
    };
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
    // nodes come in id order: walk the parents' level alongside (a level-k node is the child of a
    // level-(k−1) tet, whose 10 split points its prediction reads) instead of rebuilding each tet
    // from its id
    let mut level = 0u8;
    let mut bases = LevelWalker::level(forest, 0);
    let mut parents: Option<LevelWalker> = None;
    let mut parent: Option<LatticeTet> = None;
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
            parents = Some(LevelWalker::level(forest, level - 1));
        }
        let at = match parents.as_mut() {
            None => NodeAt::Base(bases.next().expect("ids within the level").1),
            Some(walker) => {
                let child = forest.child_index(node.id).expect("a child");
                if child == 0 {
                    parent = Some(walker.next().expect("parents within the level").1);
                }
                NodeAt::Child {
                    parent: parent.expect("child 0 comes first"),
                    child,
                }
            }
        };
        apply_node(keys, &at, &node, grid.is_some(), &mut values, &mut set)?;
    }
    if expected != total {
        return Err(SynthesisError::Missing {
            missing: total - expected,
        });
    }
    if let Some(k) = set.iter().position(|&s| !s) {
        return Err(SynthesisError::Uncovered { key: k as u64 });
    }
    if let Some(grid) = grid {
        let details = values.clone();
        grid.predict_all(&mut values, |k, p, _| synthesize(details[k], p));
    }
    Ok(values)
}

/// Where a node's tet sits: a base tet, or child `child` (Bey order) of a parent tet.
#[derive(Debug, Clone, Copy)]
pub enum NodeAt {
    Base(LatticeTet),
    Child { parent: LatticeTet, child: usize },
}

impl NodeAt {
    /// The position of tet `id` (O(level)).
    pub fn from_id(forest: &Forest, id: TetId) -> Self {
        match forest.parent(id) {
            None => NodeAt::Base(LatticeTet::from_id(forest, id)),
            Some(p) => NodeAt::Child {
                parent: LatticeTet::from_id(forest, p),
                child: forest.child_index(id).expect("a child has an index"),
            },
        }
    }

    /// The node's own tet.
    pub fn tet(&self) -> LatticeTet {
        match self {
            NodeAt::Base(t) => *t,
            NodeAt::Child { parent, child } => parent.child(*child),
        }
    }
}

/// Sets the values of the vertices `node` owns on its tet (the points its parent predictions
/// read — the edge's ends, or the parent's 10 split points — must already have values); with
/// `axes`, their details instead (the axes passes synthesize them once every detail is in place).
fn apply_node(
    keys: &VertexKeys,
    at: &NodeAt,
    node: &DetailNode,
    axes: bool,
    values: &mut [f32],
    set: &mut [bool],
) -> Result<(), SynthesisError> {
    let tet = at.tet();
    let parent_values = match at {
        NodeAt::Child { parent, child } if !axes => {
            let sp = parent.split_points();
            Some((
                sp.map(|w| values[keys.key(parent.base, &w) as usize]),
                BEY_CHILDREN[*child],
            ))
        }
        _ => None,
    };
    for (e, &(a, b)) in EDGES.iter().enumerate() {
        if let Some(d) = node.coeff(e) {
            let k = keys.key(tet.base, &tet.edge_midpoint(e)) as usize;
            if std::mem::replace(&mut set[k], true) {
                return Err(SynthesisError::OwnedTwice {
                    key: k as u64,
                    id: node.id,
                });
            }
            values[k] = if axes {
                d
            } else {
                let p = match &parent_values {
                    Some((v, c)) => predict_split(v, c[a], c[b]),
                    None => {
                        let u = keys.key(tet.base, &tet.v[a]) as usize;
                        let v = keys.key(tet.base, &tet.v[b]) as usize;
                        predict(values[u], values[v])
                    }
                };
                synthesize(d, p)
            };
        }
    }
    Ok(())
}
