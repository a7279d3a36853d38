//! Vertex keys of the tets a level walk visits: split points and split-edge midpoints, from the
//! parent's split rather than recomputed per tet, and the parallel chunks of a level.

use super::{BASE_PER_TASK, PARENTS_PER_TASK};
use tetwave_protocol::hierarchy::Bary;
use tetwave_protocol::hierarchy::{midpoint, LevelWalker, BEY_CHILDREN, BEY_SPLIT};
use tetwave_protocol::vertex::VertexKeys;
use tetwave_protocol::{Forest, LatticeTet};

/// Keys of the 10 split points of a tet: its 4 vertices, then its 6 edge midpoints.
#[inline]
pub(super) fn split_keys(keys: &VertexKeys, t: &LatticeTet) -> [usize; 10] {
    let p = t.split_points();
    std::array::from_fn(|i| keys.key(t.base, &p[i]) as usize)
}

/// Calls `f(id, keys, mids)` for every tet of level `k` in `ids`, in increasing id order, with `keys`
/// the keys of its 10 split points (4 vertices, 6 edge midpoints) and `mids` the keys of the midpoints
/// of the 25 edges of its split ([`BEY_SPLIT`]): the new vertices of its children's edges.
pub(super) fn for_each_split_keys(
    forest: Forest,
    keys: &VertexKeys,
    k: u8,
    ids: std::ops::Range<u64>,
    mut f: impl FnMut(u64, &[usize; 10], &[usize; 25]),
) {
    let split = &BEY_SPLIT;
    let mids = |tet: &LatticeTet, pp: &[Bary; 10]| -> [usize; 25] {
        let mut m = [0usize; 25];
        for (j, &(a, b)) in split.edges.iter().enumerate() {
            m[j] = keys.key(tet.base, &midpoint(&pp[a], &pp[b])) as usize;
        }
        m
    };
    let split_keys = |tet: &LatticeTet, pp: &[Bary; 10]| -> [usize; 10] {
        let mut k = [0usize; 10];
        for (i, p) in pp.iter().enumerate() {
            k[i] = keys.key(tet.base, p) as usize;
        }
        k
    };
    if k == 0 {
        for (id, tet) in LevelWalker::new(forest, k, ids) {
            let pp = tet.split_points();
            f(id, &split_keys(&tet, &pp), &mids(&tet, &pp));
        }
        return;
    }
    if ids.is_empty() {
        return;
    }
    // walk the parents: a tet's split keys are its parent's split keys and split-edge midpoints
    let (Some(first), Some(last)) = (forest.parent(ids.start), forest.parent(ids.end - 1)) else {
        return;
    };
    for (gid, g) in LevelWalker::new(forest, k - 1, first..last + 1) {
        let gp = g.split_points();
        let gk = split_keys(&g, &gp);
        let gm = mids(&g, &gp);
        for (i, c) in BEY_CHILDREN.iter().enumerate() {
            let id = forest.child(gid, i);
            if !ids.contains(&id) {
                continue;
            }
            let tet = LatticeTet {
                base: g.base,
                v: [gp[c[0]], gp[c[1]], gp[c[2]], gp[c[3]]],
            };
            let ce = &split.child_edges[i];
            let pk = [
                gk[c[0]], gk[c[1]], gk[c[2]], gk[c[3]], gm[ce[0]], gm[ce[1]], gm[ce[2]], gm[ce[3]],
                gm[ce[4]], gm[ce[5]],
            ];
            f(id, &pk, &mids(&tet, &tet.split_points()));
        }
    }
}

/// Calls `f(id, keys)` for every tet of level `k` whose parent lies in `parents` (level `k − 1`;
/// for `k = 0`, `parents` are base tet ids and the base tets themselves are visited), in increasing id
/// order, with `keys` the keys of its 4 vertices then its 6 edge midpoints. Children's vertex keys come
/// from the parent's split, and the 25 midpoints of the split's edges are keyed once per parent.
pub(super) fn for_each_tet_keys(
    forest: Forest,
    keys: &VertexKeys,
    k: u8,
    parents: std::ops::Range<u64>,
    mut f: impl FnMut(u64, &[usize; 10]),
) {
    if k == 0 {
        for (id, tet) in LevelWalker::new(forest, 0, parents) {
            f(id, &split_keys(keys, &tet));
        }
        return;
    }
    let split = &BEY_SPLIT;
    for_each_split_keys(forest, keys, k - 1, parents, |pid, pk, mid| {
        let first = forest.child(pid, 0);
        for (i, c) in BEY_CHILDREN.iter().enumerate() {
            let ce = &split.child_edges[i];
            let ck = [
                pk[c[0]], pk[c[1]], pk[c[2]], pk[c[3]], mid[ce[0]], mid[ce[1]], mid[ce[2]],
                mid[ce[3]], mid[ce[4]], mid[ce[5]],
            ];
            f(first + i as u64, &ck);
        }
    });
}

/// Parent-id chunks whose children make up level `k` (base tet ids for `k = 0`).
pub(super) fn parent_chunks(forest: Forest, k: u8) -> Vec<std::ops::Range<u64>> {
    let (lo, hi, step) = if k == 0 {
        (0, forest.n_base, BASE_PER_TASK as u64)
    } else {
        (
            forest.level_start(k - 1),
            forest.level_start(k),
            PARENTS_PER_TASK as u64,
        )
    };
    (lo..hi)
        .step_by(step as usize)
        .map(|s| s..(s + step).min(hi))
        .collect()
}
