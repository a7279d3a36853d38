//! Selective refinement: which leaves to split and which red splits to undo, frame by frame.
//!
//! # Criteria (thesis §5.4, design "Selective refinement")
//! - **Frustum**: a tet's bounding sphere (centroid, farthest vertex) against the near plane and the
//!   4 side planes of the view; a sphere wholly outside is not refined and its split is undone.
//! - **Screen-space error** (thesis eq. 43): `err(t) = H / (2·tan(fovy/2)) · diam(t) / dist(eye,
//!   centre(t))` pixels, with the tolerance in pixels or in % of `H` ([`Tolerance`]).
//! - **Data-aware** ([`SelectParams::data_aware`]): `err` is scaled by
//!   `min(1, subtree_max|d| / (δ · value range))`, so a subtree whose details are all below `δ` of the
//!   value range counts as less than a pixel-perfect one, and a constant (or empty) subtree as 0: it
//!   stays coarse wherever the camera is.
//! - A leaf `t` is **wanted** split when its node and all its ancestors have arrived, it is not empty
//!   nor at the finest level, and (in [`Mode::Complete`], always; otherwise) it is inside the frustum
//!   with `err(t) > tol`. A refined tet `P` whose 8 children are leaves is **merged** when `P` is not
//!   wanted (its own error is below the tolerance: the thesis' "parent" rule seen from the children),
//!   and, with [`CoarsenRef::Grandparent`], its parent is not wanted either (gentler). The two tests
//!   are complementary, so a static view never oscillates between them.
//!
//! # Budget
//! A frame sweeps the node array (resumable: a sweep may span frames), pushing split candidates on a
//! max-heap and merge candidates on a min-heap by error, then applies merges (smallest error first, in
//! batches through [`AdaptiveMesh::coarsen_batch`], so that uniformly refined regions coarsen) and
//! splits (largest error first), each re-checked against the current view when popped. It stops at
//! [`Budget::max_ops`] operations or [`Budget::max_time`]; what is left stays in the heaps or is found
//! by the next sweep. Every operation ends with a conforming mesh, so every frame does. A sweep that
//! changes nothing while the view and the buffer stayed the same marks the selector *converged*: later
//! frames return at once until the camera moves or [`Selector::notify_arrivals`] is called.

use crate::camera::Camera;
use crate::detail_buffer::DetailBuffer;
use crate::mesh::{AdaptiveMesh, MeshError, RedNode};
use glam::DVec3;
use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;
use std::fmt;
use std::time::{Duration, Instant};
use tetwave_protocol::TetId;

/// Refinement tolerance of the screen-space error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tolerance {
    Pixels(f64),
    /// Percent of the viewport height `H` (the thesis' 20%, 15%, 12.5%, 10%, 6.25%).
    PercentOfHeight(f64),
}

impl Tolerance {
    /// The tolerance in pixels for a viewport `height` pixels tall.
    pub fn pixels(&self, height: u32) -> f64 {
        match *self {
            Tolerance::Pixels(p) => p,
            Tolerance::PercentOfHeight(p) => p / 100.0 * height as f64,
        }
    }

    /// `"20%"` → 20 % of `H`; `"12"` or `"12px"` → 12 pixels.
    pub fn parse(s: &str) -> Result<Self, String> {
        let s = s.trim();
        let num = |t: &str| {
            t.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v >= 0.0)
                .ok_or_else(|| format!("bad tolerance {s:?}: give 20% or 12px"))
        };
        if let Some(p) = s.strip_suffix('%') {
            Ok(Tolerance::PercentOfHeight(num(p)?))
        } else {
            Ok(Tolerance::Pixels(num(s.strip_suffix("px").unwrap_or(s))?))
        }
    }
}

impl fmt::Display for Tolerance {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Tolerance::Pixels(p) => write!(f, "{p}px"),
            Tolerance::PercentOfHeight(p) => write!(f, "{p}%"),
        }
    }
}

/// Whose error decides a merge (thesis: parent; grandparent "adds tolerance to over-refinement").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CoarsenRef {
    Parent,
    Grandparent,
}

/// Refinement modes of a progressive client.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// The camera moves: [`SelectParams::interactive`] budget per frame.
    Interactive,
    /// The camera rests: keep refining toward the tolerance with [`SelectParams::progressive`].
    Progressive,
    /// Everything that has arrived, no view heuristics (the thesis' "simple selective refinement"),
    /// with the progressive budget.
    Complete,
}

/// Work allowed per frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Budget {
    /// Splits + merge attempts per frame.
    pub max_ops: usize,
    /// Wall time per frame (sweep included); `None`: unlimited.
    pub max_time: Option<Duration>,
}

impl Budget {
    pub const UNLIMITED: Budget = Budget {
        max_ops: usize::MAX,
        max_time: None,
    };

    pub fn ms(ms: f64) -> Budget {
        Budget {
            max_ops: usize::MAX,
            max_time: Some(Duration::from_secs_f64(ms.max(0.0) / 1000.0)),
        }
    }

    pub fn ops(n: usize) -> Budget {
        Budget {
            max_ops: n,
            max_time: None,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct SelectParams {
    pub tol: Tolerance,
    pub coarsen_ref: CoarsenRef,
    /// Frustum culling on/off.
    pub frustum: bool,
    /// Data-aware weighting threshold `δ` (relative to the value range); `None`: geometric only.
    pub data_aware: Option<f32>,
    /// The data set's value range (manifest), for the data-aware weight.
    pub value_range: [f32; 2],
    pub interactive: Budget,
    pub progressive: Budget,
}

impl SelectParams {
    /// Thesis defaults: geometric error only, parent rule, frustum on; 8 ms interactive frames,
    /// 50 ms progressive ones.
    pub fn new(tol: Tolerance, value_range: [f32; 2]) -> Self {
        SelectParams {
            tol,
            coarsen_ref: CoarsenRef::Parent,
            frustum: true,
            data_aware: None,
            value_range,
            interactive: Budget::ms(8.0),
            progressive: Budget::ms(50.0),
        }
    }
}

/// The camera as the criteria use it: eye, frustum planes, pixels per unit of `diam/dist`.
#[derive(Debug, Clone, Copy)]
pub struct View {
    pub eye: DVec3,
    /// Inward unit normals `n` and offsets `d`: inside iff `n·p + d ≥ 0` (near + 4 sides).
    pub planes: [(DVec3, f64); 5],
    /// `H / (2·tan(fovy/2))`.
    pub pixels_per_unit: f64,
    pub tol_px: f64,
}

impl View {
    pub fn new(cam: &Camera, tol: Tolerance) -> Self {
        let (r, u, f) = cam.basis();
        let ty = (cam.fovy_deg.to_radians() * 0.5).tan();
        let tx = ty * cam.width as f64 / cam.height as f64;
        let side = |n: DVec3| {
            let n = n.normalize();
            (n, -n.dot(cam.eye))
        };
        View {
            eye: cam.eye,
            planes: [
                (f, -(f.dot(cam.eye) + cam.near)),
                side(f * tx - r),
                side(f * tx + r),
                side(f * ty - u),
                side(f * ty + u),
            ],
            pixels_per_unit: cam.height as f64 / (2.0 * ty),
            tol_px: tol.pixels(cam.height),
        }
    }

    /// Whether a sphere is at least partly inside the frustum.
    #[inline]
    pub fn sphere_visible(&self, c: DVec3, r: f64) -> bool {
        self.planes.iter().all(|&(n, d)| n.dot(c) + d >= -r)
    }

    /// Thesis eq. 43: vertical pixels of a sphere of diameter `diam` centred at `c`.
    #[inline]
    pub fn error_px(&self, c: DVec3, diam: f64) -> f64 {
        self.pixels_per_unit * diam / (c - self.eye).length().max(1e-12)
    }
}

/// Bounding sphere (centroid, distance to the farthest vertex) of mesh vertices `v`.
#[inline]
pub fn bounding_sphere(mesh: &AdaptiveMesh, v: &[u32; 4]) -> (DVec3, f64) {
    let pos = mesh.positions();
    let p = v.map(|s| {
        let q = pos[s as usize];
        DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64)
    });
    let c = (p[0] + p[1] + p[2] + p[3]) * 0.25;
    let r2 = p
        .iter()
        .map(|q| q.distance_squared(c))
        .fold(0.0f64, f64::max);
    (c, r2.sqrt())
}

/// What one [`Selector::frame`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FrameStats {
    pub splits: usize,
    /// Merges that held (the tet is a leaf after the batch's closure).
    pub merges: usize,
    pub merge_attempts: usize,
    /// Node slots looked at by the sweep.
    pub scanned: usize,
    /// Sweeps completed in this frame.
    pub sweeps: usize,
    /// Candidates left in the heaps for later frames.
    pub pending: usize,
    /// The mesh is where the criteria want it (for this view and buffer).
    pub converged: bool,
    pub elapsed: Duration,
    /// Time inside the mesh's refine / coarsen calls (the rest is sweeping and bookkeeping).
    pub op_time: Duration,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Cand(f64, TetId);
impl Eq for Cand {}
impl PartialOrd for Cand {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Cand {
    fn cmp(&self, o: &Self) -> Ordering {
        self.0.total_cmp(&o.0).then(o.1.cmp(&self.1))
    }
}

/// Merges handed to one [`AdaptiveMesh::coarsen_batch`] at most.
const MERGE_CHUNK: usize = 256;
/// Node slots scanned between two clock reads.
const SCAN_CHUNK: usize = 512;
/// Sweeps one unbudgeted [`Selector::converge`] may take before giving up.
const MAX_SWEEPS: usize = 256;

/// Frame-by-frame selective refinement (see the module docs).
#[derive(Debug, Clone)]
pub struct Selector {
    pub params: SelectParams,
    cursor: usize,
    splits: BinaryHeap<Cand>,
    merges: BinaryHeap<Reverse<Cand>>,
    sweep_changes: usize,
    /// Merges refused by the closure in this sweep.
    sweep_refused: usize,
    /// This sweep merges all its candidates in one batch, without the budget: the last sweep
    /// changed nothing but refused merges that may only hold together (a group split across
    /// batches); run once before declaring convergence, so budgeted frames reach the unbudgeted mesh.
    consolidating: bool,
    /// The view or the buffer changed since the current sweep started.
    dirty: bool,
    converged: bool,
    last_cam: Option<Camera>,
    last_mode: Option<Mode>,
}

impl Selector {
    pub fn new(params: SelectParams) -> Self {
        Selector {
            params,
            cursor: 0,
            splits: BinaryHeap::new(),
            merges: BinaryHeap::new(),
            sweep_changes: 0,
            sweep_refused: 0,
            consolidating: false,
            dirty: true,
            converged: false,
            last_cam: None,
            last_mode: None,
        }
    }

    /// New nodes arrived in the buffer (or the parameters changed): the selector looks again.
    pub fn notify_arrivals(&mut self) {
        self.dirty = true;
        self.converged = false;
    }

    /// Whether the last frame found nothing left to do.
    pub fn is_converged(&self) -> bool {
        self.converged
    }

    /// Split priority of leaf `n`: `Some(error)` when it is wanted split.
    pub fn want_split(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: &RedNode,
    ) -> Option<f64> {
        let forest = mesh.forest();
        if n.empty || !buf.is_present(n.id) {
            return None;
        }
        let level = forest.level(n.id);
        if level >= forest.levels || !buf.is_usable(n.id) {
            return None;
        }
        if mode == Mode::Complete {
            return Some((forest.levels - level) as f64);
        }
        let e = self.error(mesh, buf, view, n)?;
        (e > view.tol_px).then_some(e)
    }

    /// Data-aware screen-space error of `n`; `None` outside the frustum (when culling).
    fn error(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        n: &RedNode,
    ) -> Option<f64> {
        let (c, r) = bounding_sphere(mesh, &n.v);
        if self.params.frustum && !view.sphere_visible(c, r) {
            return None;
        }
        let mut e = view.error_px(c, 2.0 * r);
        if let Some(delta) = self.params.data_aware {
            if let Some(m) = buf.subtree_max(n.id) {
                let [lo, hi] = self.params.value_range;
                let range = ((hi - lo) as f64).max(1e-30);
                e *= (m as f64 / (delta.max(1e-30) as f64 * range)).min(1.0);
            }
        }
        Some(e)
    }

    /// Merge priority of refined node `n` (children all leaves): `Some(error)` when its split
    /// should be undone.
    pub fn want_merge(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: &RedNode,
    ) -> Option<f64> {
        if self.want_split(mesh, buf, view, mode, n).is_some() {
            return None;
        }
        if self.params.coarsen_ref == CoarsenRef::Grandparent && mode != Mode::Complete {
            if let Some(p) = mesh.forest().parent(n.id) {
                if let Some(pn) = mesh.red_node_of(p) {
                    if self.want_split(mesh, buf, view, mode, &pn).is_some() {
                        return None;
                    }
                }
            }
        }
        Some(if mode == Mode::Complete {
            0.0
        } else {
            self.error(mesh, buf, view, n).unwrap_or(-1.0)
        })
    }

    /// One frame of selective refinement under the mode's budget (see the module docs).
    pub fn frame(
        &mut self,
        mesh: &mut AdaptiveMesh,
        buf: &DetailBuffer,
        cam: &Camera,
        mode: Mode,
    ) -> Result<FrameStats, MeshError> {
        let budget = match mode {
            Mode::Interactive => self.params.interactive,
            Mode::Progressive | Mode::Complete => self.params.progressive,
        };
        self.run(mesh, buf, cam, mode, budget)
    }

    /// Frames without a budget until converged: the mesh the criteria want for this view (the
    /// reference a budgeted run must reach).
    pub fn converge(
        &mut self,
        mesh: &mut AdaptiveMesh,
        buf: &DetailBuffer,
        cam: &Camera,
        mode: Mode,
    ) -> Result<FrameStats, MeshError> {
        self.run(mesh, buf, cam, mode, Budget::UNLIMITED)
    }

    fn run(
        &mut self,
        mesh: &mut AdaptiveMesh,
        buf: &DetailBuffer,
        cam: &Camera,
        mode: Mode,
        budget: Budget,
    ) -> Result<FrameStats, MeshError> {
        let start = Instant::now();
        let mut st = FrameStats::default();
        if self.last_cam.as_ref() != Some(cam) || self.last_mode != Some(mode) {
            self.last_cam = Some(*cam);
            self.last_mode = Some(mode);
            self.dirty = true;
            self.converged = false;
        }
        if self.converged {
            st.converged = true;
            st.elapsed = start.elapsed();
            return Ok(st);
        }
        let view = View::new(cam, self.params.tol);
        let deadline = budget.max_time.map(|d| start + d);
        let scan_deadline = budget.max_time.map(|d| start + d / 2);
        let past = |t: Option<Instant>| t.is_some_and(|t| Instant::now() >= t);
        let mut ops = 0usize;
        loop {
            if self.cursor == 0 {
                // a new sweep sees the current view and buffer
                self.splits.clear();
                self.merges.clear();
                self.sweep_changes = 0;
                self.sweep_refused = 0;
                self.dirty = false;
            }
            // scan
            let len = mesh.node_slot_len();
            let have_work = !self.splits.is_empty() || !self.merges.is_empty();
            while self.cursor < len {
                let end = (self.cursor + SCAN_CHUNK).min(len);
                for slot in self.cursor..end {
                    let Some(n) = mesh.red_node(slot) else {
                        continue;
                    };
                    if n.leaf {
                        if let Some(e) = self.want_split(mesh, buf, &view, mode, &n) {
                            self.splits.push(Cand(e, n.id));
                        }
                    } else if n.children_leaves {
                        if let Some(e) = self.want_merge(mesh, buf, &view, mode, &n) {
                            self.merges.push(Reverse(Cand(e, n.id)));
                        }
                    }
                }
                st.scanned += end - self.cursor;
                self.cursor = end;
                if past(if have_work { scan_deadline } else { deadline }) {
                    break;
                }
            }
            let sweep_done = self.cursor >= len;
            // apply: merges (up to half the ops while splits wait), splits, merges again
            let consolidating = self.consolidating;
            let merge_ops = if consolidating {
                usize::MAX
            } else {
                budget.max_ops
            };
            let half = if consolidating {
                usize::MAX
            } else if self.splits.is_empty() {
                budget.max_ops
            } else {
                budget.max_ops / 2 + 1
            };
            let merge_deadline = if consolidating { None } else { deadline };
            if !consolidating || sweep_done {
                self.apply_merges(
                    mesh,
                    buf,
                    &view,
                    mode,
                    &mut ops,
                    half,
                    merge_deadline,
                    &mut st,
                )?;
            }
            self.apply_splits(
                mesh,
                buf,
                &view,
                mode,
                &mut ops,
                budget.max_ops,
                deadline,
                &mut st,
            )?;
            if !consolidating || sweep_done {
                self.apply_merges(
                    mesh,
                    buf,
                    &view,
                    mode,
                    &mut ops,
                    merge_ops,
                    merge_deadline,
                    &mut st,
                )?;
            }
            let out_of_budget = ops >= budget.max_ops || past(deadline);
            if sweep_done && self.splits.is_empty() && self.merges.is_empty() {
                st.sweeps += 1;
                self.cursor = 0;
                if self.sweep_changes == 0 && !self.dirty {
                    if self.sweep_refused > 0 && !self.consolidating {
                        self.consolidating = true;
                        continue;
                    }
                    self.consolidating = false;
                    self.converged = true;
                    break;
                }
                self.consolidating = false;
                if st.sweeps >= MAX_SWEEPS {
                    break;
                }
            }
            if out_of_budget {
                break;
            }
        }
        st.converged = self.converged;
        st.pending = self.splits.len() + self.merges.len();
        st.elapsed = start.elapsed();
        Ok(st)
    }

    #[allow(clippy::too_many_arguments)]
    fn apply_merges(
        &mut self,
        mesh: &mut AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        ops: &mut usize,
        max_ops: usize,
        deadline: Option<Instant>,
        st: &mut FrameStats,
    ) -> Result<(), MeshError> {
        let mut batch = Vec::new();
        while *ops < max_ops && !self.merges.is_empty() {
            if deadline.is_some_and(|t| Instant::now() >= t) {
                break;
            }
            batch.clear();
            let chunk = if max_ops == usize::MAX {
                usize::MAX
            } else {
                MERGE_CHUNK.min(max_ops - *ops)
            };
            while batch.len() < chunk {
                let Some(Reverse(Cand(_, id))) = self.merges.pop() else {
                    break;
                };
                if let Some(n) = mesh.red_node_of(id) {
                    if !n.leaf
                        && n.children_leaves
                        && self.want_merge(mesh, buf, view, mode, &n).is_some()
                    {
                        batch.push(id);
                    }
                }
            }
            if batch.is_empty() {
                continue;
            }
            *ops += batch.len();
            st.merge_attempts += batch.len();
            let t = Instant::now();
            let held = mesh.coarsen_batch(&batch, buf)?;
            st.op_time += t.elapsed();
            st.merges += held;
            self.sweep_changes += held;
            self.sweep_refused += batch.len() - held;
            // parents whose children are now all leaves may merge next (ROAM-style)
            let forest = mesh.forest();
            for &id in &batch {
                if let Some(p) = forest.parent(id) {
                    if mesh.is_leaf(id) {
                        if let Some(pn) = mesh.red_node_of(p) {
                            if pn.children_leaves {
                                if let Some(e) = self.want_merge(mesh, buf, view, mode, &pn) {
                                    self.merges.push(Reverse(Cand(e, p)));
                                }
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    fn apply_splits(
        &mut self,
        mesh: &mut AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        ops: &mut usize,
        max_ops: usize,
        deadline: Option<Instant>,
        st: &mut FrameStats,
    ) -> Result<(), MeshError> {
        let mut k = 0usize;
        while *ops < max_ops {
            if deadline.is_some()
                && k.is_multiple_of(8)
                && deadline.is_some_and(|t| Instant::now() >= t)
            {
                break;
            }
            let Some(Cand(_, id)) = self.splits.pop() else {
                break;
            };
            let Some(n) = mesh.red_node_of(id) else {
                continue;
            };
            if !n.leaf || self.want_split(mesh, buf, view, mode, &n).is_none() {
                continue;
            }
            k += 1;
            *ops += 1;
            let t = Instant::now();
            mesh.refine(id, buf)?;
            st.op_time += t.elapsed();
            st.splits += 1;
            self.sweep_changes += 1;
            // its children may want splitting too (ROAM-style), without waiting for the next sweep
            let forest = mesh.forest();
            for i in 0..8 {
                let c = forest.child(id, i);
                if let Some(cn) = mesh.red_node_of(c) {
                    if cn.leaf {
                        if let Some(e) = self.want_split(mesh, buf, view, mode, &cn) {
                            self.splits.push(Cand(e, c));
                        }
                    }
                }
            }
        }
        Ok(())
    }
}
