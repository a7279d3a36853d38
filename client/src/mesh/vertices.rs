//! Vertex storage: creating a midpoint vertex (position, synthesized value) and reading vertices by
//! slot.

use super::{AdaptiveMesh, NONE, OWNERS};
use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::hierarchy::Bary;
use tetwave_protocol::wavelet::{predict, synthesize};

/// Makes room for `extra` more items growing by 1/8 (not doubling): the mesh's arrays are its
/// memory, and doubling would leave up to half of them unused.
#[inline]
fn grow<T>(v: &mut Vec<T>, extra: usize) {
    if v.len() + extra > v.capacity() {
        v.reserve_exact((v.capacity() / 8).max(extra).max(64));
    }
}

impl AdaptiveMesh {
    pub(super) fn new_vertex(
        &mut self,
        key: u64,
        pos: [f32; 3],
        level: u8,
        ends: [u32; 2],
        val: f32,
    ) -> u32 {
        let s = match self.free_vertices.pop() {
            Some(s) => {
                let i = s as usize;
                self.vkey[i] = key;
                self.vpos[i] = pos;
                self.vval[i] = val;
                self.vends[i] = ends;
                self.vref[i] = 1;
                self.vlevel[i] = level;
                self.vdeps[i] = 0;
                self.vowner[i] = [NONE; OWNERS];
                s
            }
            None => {
                grow(&mut self.vpos, 1);
                grow(&mut self.vval, 1);
                self.vkey.push(key);
                self.vpos.push(pos);
                self.vval.push(val);
                self.vends.push(ends);
                self.vref.push(1);
                self.vlevel.push(level);
                self.vdeps.push(0);
                self.vowner.push([NONE; OWNERS]);
                (self.vkey.len() - 1) as u32
            }
        };
        self.vdeps[ends[0] as usize] += 1;
        self.vdeps[ends[1] as usize] += 1;
        self.n_vertices += 1;
        s
    }

    pub(super) fn lattice_position(&self, b: u32, w: &Bary) -> [f64; 3] {
        tetwave_protocol::base::lattice_position(
            &self.base_positions,
            &self.base_tets[b as usize],
            self.keys.lattice().m(),
            w,
        )
    }

    #[inline]
    pub(super) fn synth_value(&self, buf: &DetailBuffer, key: u64, ends: [u32; 2]) -> f32 {
        let d = buf.coeff(key).unwrap_or(0.0);
        synthesize(
            d,
            predict(self.vval[ends[0] as usize], self.vval[ends[1] as usize]),
        )
    }

    /// Number of present vertices.
    pub fn vertex_count(&self) -> usize {
        self.n_vertices
    }

    /// Length of the vertex slot arrays (present and free slots).
    pub fn vertex_slot_len(&self) -> usize {
        self.vkey.len()
    }

    /// Slots of the present vertices.
    pub fn vertex_slots(&self) -> impl Iterator<Item = u32> + '_ {
        (0..self.vkey.len() as u32).filter(|&s| self.vref[s as usize] != 0)
    }

    /// Slot of the present vertex with key `key`.
    pub fn slot_of_key(&self, key: u64) -> Option<u32> {
        if key < self.keys.base_vertex_count() {
            return Some(key as u32);
        }
        (key < self.keys.vertex_count())
            .then(|| self.by_key.get(key))
            .filter(|&s| s != NONE)
    }

    pub fn vertex_key(&self, slot: u32) -> u64 {
        self.vkey[slot as usize]
    }

    pub fn vertex_value(&self, slot: u32) -> f32 {
        self.vval[slot as usize]
    }

    pub fn vertex_position(&self, slot: u32) -> [f32; 3] {
        self.vpos[slot as usize]
    }

    /// The edge endpoints a midpoint vertex is predicted from; `None` for base vertices.
    pub fn vertex_ends(&self, slot: u32) -> Option<[u32; 2]> {
        let e = self.vends[slot as usize];
        (e[0] != NONE).then_some(e)
    }

    /// Level at which a vertex appears (0 for base vertices).
    pub fn vertex_level(&self, slot: u32) -> u8 {
        self.vlevel[slot as usize]
    }

    /// Position array by slot (free slots hold stale data).
    pub fn positions(&self) -> &[[f32; 3]] {
        &self.vpos
    }

    /// Value array by slot (free slots hold stale data).
    pub fn values(&self) -> &[f32] {
        &self.vval
    }
}
