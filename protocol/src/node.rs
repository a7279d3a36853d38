//! Detail nodes: what the server stores and streams per tet that has children.

use crate::hierarchy::{Forest, TetId};
use serde::{Deserialize, Serialize};

/// The coefficients one tet owns, with the metadata the client's selection uses.
///
/// Bit `e` of `owned` says the tet owns the coefficient of its local edge `e`'s midpoint; `coeffs`
/// holds those coefficients in increasing `e`. Each new vertex has exactly one owner: the lowest id of
/// its level's tets that contain the vertex's edge.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DetailNode {
    pub id: TetId,
    /// Owned-edge mask (6 bits, [`crate::hierarchy::EDGES`] order).
    pub owned: u8,
    /// Bit `i`: child `i` lies entirely outside the input domain (empty, never refined, not drawn).
    pub empty_children: u8,
    /// The selection's error estimate: the largest linear detail `|f(m) − (f(u) + f(v))/2|` of a
    /// vertex created by refining this tet, its descendants, or its siblings and theirs (one
    /// value per group of 8 siblings, so a group codes as one; see [`group_siblings`]).
    ///
    /// A node of the finest node level (its children are the hierarchy's leaves) arrives without
    /// one of its own: [`INHERITED_BOUND`], and its parent's bound, which covers this subtree,
    /// stands in for it ([`resolve_bound`]). Coding it would cost more than its coefficients tell.
    pub subtree_max_abs: f32,
    pub coeffs: Vec<f32>,
}

/// The [`DetailNode::subtree_max_abs`] of a node whose bound is not coded (the finest node
/// level, see [`crate::block`]): its parent's applies.
pub const INHERITED_BOUND: f32 = f32::INFINITY;

/// The subtree bound a selection uses for a node with bound `own`: its own, or for an
/// [`INHERITED_BOUND`] its `parent`'s (an upper bound too: the parent's subtree holds this one).
/// Without a parent's bound (not arrived, or a base tet) it stays infinite: full weight, the safe
/// side of every criterion that scales by it.
#[inline]
pub fn resolve_bound(own: f32, parent: impl FnOnce() -> Option<f32>) -> f32 {
    if own == INHERITED_BOUND {
        parent().unwrap_or(INHERITED_BOUND)
    } else {
        own
    }
}

/// [`resolve_bound`] for every node of `nodes` (any order), parents looked up among `nodes`: the
/// bounds selection and the server's orders rank by, in `nodes`' order.
pub fn resolved_bounds(forest: Forest, nodes: &[DetailNode]) -> Vec<f32> {
    let own: std::collections::HashMap<TetId, f32> =
        nodes.iter().map(|n| (n.id, n.subtree_max_abs)).collect();
    nodes
        .iter()
        .map(|n| {
            resolve_bound(n.subtree_max_abs, || {
                forest.parent(n.id).and_then(|p| own.get(&p).copied())
            })
        })
        .collect()
}

/// Raises every node's subtree bound to its sibling group's largest (`bounds` by id, as
/// [`DetailNode::subtree_max_abs`] defines; base tets, ids `0..n_base`, have no siblings).
pub fn group_siblings(n_base: usize, bounds: &mut [f32]) {
    if bounds.len() > n_base {
        for g in bounds[n_base..].chunks_mut(8) {
            let m = g.iter().fold(0f32, |m, &x| m.max(x));
            g.fill(m);
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NodeError {
    #[error("node {id}: owned mask {mask:#04x} has bits beyond the 6 edges")]
    BadMask { id: TetId, mask: u8 },
    #[error("node {id}: {got} coefficients for an owned mask of {want}")]
    CountMismatch { id: TetId, got: usize, want: usize },
    #[error("node {id}: non-finite coefficient or metadata")]
    NonFinite { id: TetId },
}

impl DetailNode {
    /// Structural checks a receiver applies before using a node.
    pub fn validate(&self) -> Result<(), NodeError> {
        if self.owned & !0x3f != 0 {
            return Err(NodeError::BadMask {
                id: self.id,
                mask: self.owned,
            });
        }
        let want = self.owned.count_ones() as usize;
        if self.coeffs.len() != want {
            return Err(NodeError::CountMismatch {
                id: self.id,
                got: self.coeffs.len(),
                want,
            });
        }
        let bound_ok = self.subtree_max_abs.is_finite() || self.subtree_max_abs == INHERITED_BOUND;
        if !bound_ok || self.coeffs.iter().any(|c| !c.is_finite()) {
            return Err(NodeError::NonFinite { id: self.id });
        }
        Ok(())
    }

    /// The coefficient of local edge `e`, if this node owns it.
    pub fn coeff(&self, e: usize) -> Option<f32> {
        if self.owned & (1 << e) == 0 {
            return None;
        }
        let idx = (self.owned & ((1u8 << e) - 1)).count_ones() as usize;
        self.coeffs.get(idx).copied()
    }
}
