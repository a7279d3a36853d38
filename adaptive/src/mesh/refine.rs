//! Red refinement of a leaf.

use super::lattice::child_flips;
use super::node::{Node, NodeFlags};
use super::{AdaptiveMesh, MeshError, NONE};
use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::hierarchy::{BEY_CHILDREN, EDGES};
use tetwave_protocol::wavelet::{split_edge, SplitEdge};
use tetwave_protocol::{LatticeTet, TetId};

impl AdaptiveMesh {
    fn alloc_block(&mut self) -> u32 {
        match self.free_blocks.pop() {
            Some(b) => b,
            None => {
                let b = self.nodes.len() as u32;
                for _ in 0..8 {
                    self.nodes.push(Node::DEAD);
                }
                self.bverts.push([NONE; 10]);
                b
            }
        }
    }

    /// Red-splits leaf `slot` (lattice tet `lt`): creates or references its 6 midpoints and its 8
    /// children, and queues the children and the leaves around new vertices.
    pub(super) fn refine_slot(
        &mut self,
        slot: u32,
        lt: &LatticeTet,
        buf: &DetailBuffer,
    ) -> Result<(), MeshError> {
        let n = self.nodes[slot as usize];
        debug_assert!(n.is_leaf());
        let level = self.forest.level(n.id());
        if level >= self.forest.levels {
            return Err(MeshError::Finest(n.id()));
        }
        let nv = self.node_verts(slot as usize);
        let mut pts = [0u32; 10];
        pts[..4].copy_from_slice(&nv);
        // the parent's split points and this tet's place among its children (none for a base tet)
        let nbase = self.base_tets.len();
        let parent = (slot as usize >= nbase).then(|| {
            let pp = self.bverts[self.block_of(slot as usize)];
            (pp, BEY_CHILDREN[(slot as usize - nbase) & 7])
        });
        let mut created = [false; 6];
        for (e, &(a, b)) in EDGES.iter().enumerate() {
            let (sa, sb) = (nv[a], nv[b]);
            let w = lt.edge_midpoint(e);
            let key = self.keys.key(lt.base, &w);
            let s = match self.by_key.get(key) {
                s if s != NONE => {
                    self.vref[s as usize] += 1;
                    s
                }
                _ => {
                    let p = self.lattice_position(lt.base, &w);
                    // the parent points the prediction reads beyond the edge's ends
                    // (`VertexPrediction`); the value comes from the same mechanism that
                    // corrects it later
                    let src = match &parent {
                        None => [NONE; 4],
                        Some((pp, c)) => {
                            let (q0, q1) = (c[a], c[b]);
                            match split_edge(q0, q1) {
                                Some(SplitEdge::Face { opp, .. }) => {
                                    [pp[opp as usize], NONE, NONE, NONE]
                                }
                                Some(SplitEdge::Centre) => {
                                    let mut o = [NONE; 4];
                                    let others = (4..10).filter(|&x| x != q0 && x != q1);
                                    for (o, x) in o.iter_mut().zip(others) {
                                        *o = pp[x];
                                    }
                                    o
                                }
                                _ => [NONE; 4],
                            }
                        }
                    };
                    let s = self.new_vertex(
                        key,
                        [p[0] as f32, p[1] as f32, p[2] as f32],
                        level + 1,
                        [sa, sb],
                        src,
                        self.axes.as_ref().map(|a| a.point(lt.base, &w)),
                    );
                    self.vval[s as usize] = self.synth_value(buf, s);
                    self.by_key.insert(key, s);
                    created[e] = true;
                    s
                }
            };
            pts[4 + e] = s;
            if let Some(o) = self.vowner[s as usize].iter_mut().find(|o| **o == NONE) {
                *o = slot;
            }
        }
        let block = self.alloc_block();
        let bi = self.block_of(block as usize);
        self.bverts[bi] = pts;
        for (i, &flip) in child_flips().iter().enumerate() {
            let mut flags = NodeFlags::ALIVE | (n.flags & (NodeFlags::EMPTY | NodeFlags::FLIP));
            if flip {
                flags.toggle(NodeFlags::FLIP);
            }
            if buf.child_empty(n.id(), i) {
                flags |= NodeFlags::EMPTY;
            }
            let id = self.forest.child(n.id(), i);
            self.nodes[(block + i as u32) as usize] =
                Node::new(id, NONE, 0, flags | NodeFlags::QUEUED);
            self.work.push((block + i as u32, id));
        }
        let node = &mut self.nodes[slot as usize];
        node.children = block;
        node.mask = 0;
        self.n_leaves += 7;
        self.n_splits += 1;
        self.log_change(slot, block);
        self.count_in_parent(n.id(), 1);
        for (e, &c) in created.iter().enumerate() {
            if c {
                self.locate(lt.base, &lt.edge_midpoint(e), level);
            }
        }
        Ok(())
    }

    /// Red-refines leaf `t` and restores conformity (green closure, domino refinements). Missing
    /// coefficients are taken as 0 (the value is the prediction) and corrected by [`Self::apply_arrivals`] later.
    pub fn refine(&mut self, t: TetId, buf: &DetailBuffer) -> Result<(), MeshError> {
        let slot = self.find(t).ok_or(MeshError::NotInMesh(t))?;
        let n = self.nodes[slot as usize];
        if !n.is_leaf() {
            return Err(MeshError::NotLeaf(t));
        }
        if n.flags.contains(NodeFlags::EMPTY) {
            return Err(MeshError::Empty(t));
        }
        if self.forest.level(t) >= self.forest.levels {
            return Err(MeshError::Finest(t));
        }
        let lt = self.lattice_of(t);
        self.refine_slot(slot, &lt, buf)?;
        self.close(buf)
    }
}
