//! Vertex storage: creating a midpoint vertex (position, synthesized value) and reading vertices by
//! slot.

use super::{AdaptiveMesh, NONE, OWNERS};
use crate::detail_buffer::DetailBuffer;
use tetwave_protocol::hierarchy::Bary;
use tetwave_protocol::wavelet::{
    predict, predict_at_centre, predict_on_edge, predict_on_face, synthesize,
};

/// The vertices a midpoint's prediction reads (slots), by where it lies in the parent of the tet
/// whose split created it ([`tetwave_protocol::wavelet`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VertexPrediction {
    /// A base vertex: no prediction.
    Base,
    /// The midpoint of a base tet's edge.
    Linear { ends: [u32; 2] },
    /// Half of a parent edge `(near, far)` with midpoint `mid`.
    Edge { near: u32, mid: u32, far: u32 },
    /// Mid-segment `(a, b)` of a parent face, `opp` the midpoint of the face's edge `(j, k)`.
    Face {
        a: u32,
        b: u32,
        opp: u32,
        j: u32,
        k: u32,
    },
    /// A parent's centre.
    Centre { mids: [u32; 6], corners: [u32; 4] },
}

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
        src: [u32; 4],
        point: Option<[u32; 3]>,
    ) -> u32 {
        // the caller synthesizes the value once the vertex is in place
        let val = f32::NAN;
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
                self.vsrc[i] = src;
                self.vowner[i] = [NONE; OWNERS];
                if let Some(p) = point {
                    self.vpoint[i] = p;
                }
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
                self.vsrc.push(src);
                self.vowner.push([NONE; OWNERS]);
                if let Some(p) = point {
                    self.vpoint.push(p);
                }
                (self.vkey.len() - 1) as u32
            }
        };
        for d in ends.into_iter().chain(src).filter(|&d| d != NONE) {
            self.vdeps[d as usize] += 1;
        }
        self.n_vertices += 1;
        s
    }

    /// Releases the dependencies of vertex slot `s` (being removed) on the vertices its prediction
    /// reads.
    pub(super) fn drop_dependencies(&mut self, s: usize) {
        let (ends, src) = (self.vends[s], self.vsrc[s]);
        for d in ends.into_iter().chain(src).filter(|&d| d != NONE) {
            self.vdeps[d as usize] -= 1;
        }
    }

    pub(super) fn lattice_position(&self, b: u32, w: &Bary) -> [f64; 3] {
        tetwave_protocol::base::lattice_position(
            &self.base_positions,
            &self.base_tets[b as usize],
            self.keys.lattice().m(),
            w,
        )
    }

    /// The vertices slot `s`'s prediction reads.
    pub fn vertex_prediction(&self, s: u32) -> VertexPrediction {
        let s = s as usize;
        let [a, b] = self.vends[s];
        if a == NONE {
            return VertexPrediction::Base;
        }
        let src = self.vsrc[s];
        if src[1] != NONE {
            let (ea, eb) = (self.vends[a as usize], self.vends[b as usize]);
            return VertexPrediction::Centre {
                mids: [a, b, src[0], src[1], src[2], src[3]],
                corners: [ea[0], ea[1], eb[0], eb[1]],
            };
        }
        if src[0] != NONE {
            let [j, k] = self.vends[src[0] as usize];
            return VertexPrediction::Face {
                a,
                b,
                opp: src[0],
                j,
                k,
            };
        }
        if self.vlevel[s] == 1 {
            return VertexPrediction::Linear { ends: [a, b] };
        }
        // half of a parent edge: the end created later is that edge's midpoint
        let (near, mid) = if self.vlevel[a as usize] < self.vlevel[b as usize] {
            (a, b)
        } else {
            (b, a)
        };
        let me = self.vends[mid as usize];
        let far = if me[0] == near { me[1] } else { me[0] };
        VertexPrediction::Edge { near, mid, far }
    }

    /// The value of prediction `p` from the present values.
    pub(super) fn prediction_value(&self, p: &VertexPrediction) -> f32 {
        let v = |s: u32| self.vval[s as usize];
        match *p {
            VertexPrediction::Base => f32::NAN,
            VertexPrediction::Linear { ends } => predict(v(ends[0]), v(ends[1])),
            VertexPrediction::Edge { near, mid, far } => predict_on_edge(v(near), v(mid), v(far)),
            VertexPrediction::Face { a, b, opp, j, k } => {
                predict_on_face(v(a), v(b), v(opp), v(j), v(k))
            }
            VertexPrediction::Centre { mids, corners } => {
                predict_at_centre(mids.map(v), corners.map(v))
            }
        }
    }

    /// Vertex slot `s`'s value from its coefficient (0 while missing) and its prediction.
    #[inline]
    pub(super) fn synth_value(&mut self, buf: &DetailBuffer, s: u32) -> f32 {
        let key = self.vkey[s as usize];
        if let Some(axes) = self.axes.as_mut() {
            return axes.value(key as usize, self.vpoint[s as usize], buf);
        }
        let d = buf.coeff(key).unwrap_or(0.0);
        synthesize(d, self.prediction_value(&self.vertex_prediction(s)))
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
