//! The check of every invariant of the leaf mesh (for tests and debugging).

use super::green::green_split;
use super::node::NodeFlags;
use super::{AdaptiveMesh, NONE};
use rustc_hash::FxHashMap;
use tetwave_protocol::base::signed_volume;
use tetwave_protocol::hierarchy::{Bary, Lattice, FACES};
use tetwave_protocol::{LatticeTet, TetId};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConformityError {
    #[error("node {id}: vertex {local} has slot {slot} with key {have:?}, lattice key {want}")]
    VertexMismatch {
        id: TetId,
        local: usize,
        slot: u32,
        have: Option<u64>,
        want: u64,
    },
    #[error("leaf {id}: green pattern {mask:#04x} stored, {want:#04x} computed")]
    StaleGreen { id: TetId, mask: u8, want: u8 },
    #[error("leaf {id} is forced (pattern {mask:#04x}) but not refined")]
    NotClosed { id: TetId, mask: u8 },
    #[error("leaf {id}: piece of volume {volume} ≤ 0")]
    NonPositive { id: TetId, volume: f64 },
    #[error("face {face:?} used {count} times (boundary: {boundary})")]
    Face {
        face: [u64; 3],
        count: u32,
        boundary: bool,
    },
    #[error("vertex {key} (slot {slot}) is present but no leaf uses it")]
    Unused { key: u64, slot: u32 },
    #[error("vertex {key}: reference count {have}, {want} refined tets create it")]
    RefCount { key: u64, have: u32, want: u32 },
    #[error("leaf volumes sum to {sum}, the domain's volume is {domain}")]
    Volume { sum: f64, domain: f64 },
    #[error("{0}")]
    Other(String),
}

impl AdaptiveMesh {
    /// Checks every invariant of the leaf mesh (see [`ConformityError`]): node vertices agree with the
    /// lattice, the closure is settled and stored green patterns are current, every piece has
    /// positive volume, every face is shared by exactly two pieces or lies on the domain boundary,
    /// every present vertex is used by a piece, reference counts match the refined tets, and the
    /// volumes sum to the domain's (relative 1e-9).
    pub fn check_conformity(&self) -> Result<(), ConformityError> {
        let mut faces: FxHashMap<[u64; 3], (u32, bool)> = FxHashMap::default();
        let mut used = vec![false; self.vkey.len()];
        let mut want_ref = vec![0u32; self.vkey.len()];
        let mut total = 0.0f64;
        let lattice = Lattice {
            levels: self.forest.levels,
        };
        let mut stack: Vec<(u32, LatticeTet)> = (0..self.base_tets.len() as u32)
            .map(|b| (b, LatticeTet::base_tet(lattice, b)))
            .collect();
        let mut alive_nodes = 0usize;
        while let Some((slot, lt)) = stack.pop() {
            let n = self.nodes[slot as usize];
            if !n.alive() {
                return Err(ConformityError::Other(format!(
                    "dead node in tree: slot {slot}"
                )));
            }
            alive_nodes += 1;
            for i in 0..4 {
                let want = self.keys.key(lt.base, &lt.v[i]);
                let s = self.node_verts(slot as usize)[i];
                let have = (s != NONE && self.vref[s as usize] != 0).then(|| self.vkey[s as usize]);
                if have != Some(want) {
                    return Err(ConformityError::VertexMismatch {
                        id: n.id(),
                        local: i,
                        slot: s,
                        have,
                        want,
                    });
                }
            }
            let level = self.forest.level(n.id());
            if !n.is_leaf() {
                let mids = self.lattice_mids(&lt, level);
                for &m in &mids {
                    if m == NONE {
                        return Err(ConformityError::Other(format!(
                            "refined tet {} misses a midpoint",
                            n.id()
                        )));
                    }
                    want_ref[m as usize] += 1;
                }
                let nref = (0..8)
                    .filter(|&i| !self.nodes[(n.children + i) as usize].is_leaf())
                    .count();
                if nref != n.nref as usize {
                    return Err(ConformityError::Other(format!(
                        "refined tet {} counts {} refined children, has {nref}",
                        n.id(),
                        n.nref
                    )));
                }
                for (i, c) in lt.children().into_iter().enumerate() {
                    let cs = n.children + i as u32;
                    let cn = &self.nodes[cs as usize];
                    if cn.id() != self.forest.child(n.id(), i) {
                        return Err(ConformityError::Other(format!(
                            "child {i} of {} has id {}",
                            n.id(),
                            cn.id()
                        )));
                    }
                    stack.push((cs, c));
                }
                continue;
            }
            let mid = self.lattice_mids(&lt, level);
            let (mask, forced) = self.classify(&lt, level, &mid, |_| true);
            if forced {
                return Err(ConformityError::NotClosed { id: n.id(), mask });
            }
            if mask != n.mask {
                return Err(ConformityError::StaleGreen {
                    id: n.id(),
                    mask: n.mask,
                    want: mask,
                });
            }
            // pieces over (slot, lattice point)
            let nv = self.node_verts(slot as usize);
            let v: [(u32, Bary); 4] = std::array::from_fn(|i| (nv[i], lt.v[i]));
            let midp: [(u32, Bary); 6] = std::array::from_fn(|e| (mid[e], lt.edge_midpoint(e)));
            let mkey: [u64; 6] = std::array::from_fn(|e| {
                if mid[e] != NONE {
                    self.vkey[mid[e] as usize]
                } else {
                    u64::MAX
                }
            });
            let flip = n.flags.contains(NodeFlags::FLIP);
            let mut err = None;
            green_split(v, mask, &midp, &mkey, &mut |p: [(u32, Bary); 4]| {
                if err.is_some() {
                    return;
                }
                let p = if flip { [p[0], p[1], p[3], p[2]] } else { p };
                let x = p.map(|q| self.lattice_position(lt.base, &q.1));
                let vol = signed_volume(x[0], x[1], x[2], x[3]);
                if vol <= 0.0 {
                    err = Some(ConformityError::NonPositive {
                        id: n.id(),
                        volume: vol,
                    });
                    return;
                }
                total += vol;
                for q in &p {
                    used[q.0 as usize] = true;
                }
                for f in &FACES {
                    let mut k = [
                        self.vkey[p[f[0]].0 as usize],
                        self.vkey[p[f[1]].0 as usize],
                        self.vkey[p[f[2]].0 as usize],
                    ];
                    k.sort_unstable();
                    let on_boundary = (0..4).any(|z| {
                        self.boundary[lt.base as usize][z] && f.iter().all(|&j| p[j].1[z] == 0)
                    });
                    let entry = faces.entry(k).or_insert((0, on_boundary));
                    entry.0 += 1;
                    entry.1 |= on_boundary;
                }
            });
            if let Some(e) = err {
                return Err(e);
            }
        }
        let alive_total = self.nodes.iter().filter(|n| n.alive()).count();
        if alive_total != alive_nodes {
            return Err(ConformityError::Other(format!(
                "{alive_total} live nodes, {alive_nodes} reachable"
            )));
        }
        for (face, &(count, boundary)) in &faces {
            let ok = if boundary { count == 1 } else { count == 2 };
            if !ok {
                return Err(ConformityError::Face {
                    face: *face,
                    count,
                    boundary,
                });
            }
        }
        let nv = self.keys.base_vertex_count() as usize;
        let mut present = 0usize;
        for s in 0..self.vkey.len() {
            if self.vref[s] == 0 {
                continue;
            }
            present += 1;
            if !used[s] {
                return Err(ConformityError::Unused {
                    key: self.vkey[s],
                    slot: s as u32,
                });
            }
            if s >= nv && self.vref[s] != want_ref[s] {
                return Err(ConformityError::RefCount {
                    key: self.vkey[s],
                    have: self.vref[s],
                    want: want_ref[s],
                });
            }
        }
        for s in 0..self.vkey.len() {
            for &o in &self.vowner[s] {
                if o == NONE {
                    continue;
                }
                let n = &self.nodes[o as usize];
                if self.vref[s] == 0
                    || !n.alive()
                    || n.is_leaf()
                    || !self.child_mids(n).contains(&(s as u32))
                {
                    return Err(ConformityError::Other(format!(
                        "vertex {} names slot {o} as an owner, which does not refine its edge",
                        self.vkey[s]
                    )));
                }
            }
        }
        for &slot in self.refused.keys() {
            let n = self.nodes.get(slot as usize);
            if !n.is_some_and(|n| n.alive() && !n.is_leaf()) {
                return Err(ConformityError::Other(format!(
                    "a refusal record for slot {slot}, which holds no refined tet"
                )));
            }
        }
        let keyed = self.by_key.count();
        if present != self.n_vertices || keyed != present {
            return Err(ConformityError::Other(format!(
                "{present} present vertices, counter {}, key map {}",
                self.n_vertices, keyed
            )));
        }
        if (total - self.domain_volume).abs() > 1e-9 * self.domain_volume {
            return Err(ConformityError::Volume {
                sum: total,
                domain: self.domain_volume,
            });
        }
        Ok(())
    }
}
