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
//! A sweep takes the candidates of the current mesh (see "Incremental sweeps" at [`Selector`]: a
//! scan of the node array, resumable across frames, or the candidate list kept up to date), pushing
//! split candidates on a max-heap and merge candidates on a min-heap by error, then applies merges
//! (smallest error first, in batches through [`AdaptiveMesh::coarsen_batch`], so that uniformly
//! refined regions coarsen) and splits (largest error first), each re-checked when popped unless the
//! mesh and the view stayed as they were since it was pushed. It stops at [`Budget::max_ops`]
//! operations or [`Budget::max_time`]; what is left stays in the heaps or is found by the next sweep.
//! Under a time budget the clock is read before every split, every 64 merge candidates popped and
//! every merge batch (at most `MERGE_CHUNK` candidates), and every few hundred slots scanned; a
//! consolidating sweep (one batch of every merge candidate, run before declaring convergence when
//! merges were refused), which cannot be cut, starts only with at least half of a frame's budget
//! left. Per-slot storage grows by segments that are never copied, so no frame pays for moving a
//! large array.
//! Every operation ends with a conforming mesh, so every frame does. A sweep that changes nothing
//! while the view and the buffer stayed the same marks the selector *converged*: later frames return
//! at once until the camera moves (in [`Mode::Complete`] the camera does not matter) or
//! [`Selector::notify_arrivals`] / [`Selector::notify_arrived`] is called. Without a budget, a sweep
//! that changed nothing and left the mesh untouched is not replayed as a consolidating sweep (it
//! would do exactly the same).
//!
//! # Layout
//! `criteria`: the criteria, uncached (the reference selector's) and through the caches; `cache`:
//! what is kept per node slot; `certificates`: how far the camera may move before a slot must be
//! evaluated again; `candidates`: the queues, the candidate list and parking; `sweep`: the frame
//! loop and its scans; `apply`: merge batches and splits within the budget.

mod apply;
mod cache;
mod candidates;
mod certificates;
mod criteria;
mod sweep;

use crate::detail_buffer::DetailBuffer;
use crate::mesh::{AdaptiveMesh, MeshError};
use crate::seg_vec::SegVec;
use apply::INITIAL_MERGE_COST;
use cache::SlotEntry;
use candidates::{Cand, CandQueue, SlotFlags};
use certificates::Kinetic;
use glam::Vec3;
use rustc_hash::FxHashMap;
use std::cmp::Reverse;
use std::time::Duration;
use tetwave_protocol::view::Camera;
pub use tetwave_protocol::view::{data_weight, ImageCriterion, Sensitivity, Tolerance, View};
use tetwave_protocol::TetId;

pub use criteria::bounding_sphere;

/// Node slots scanned between two clock reads.
pub(super) const SCAN_CHUNK: usize = 512;

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
    /// The image criterion: the screen-space error is weighted by how much of a pixel's colour
    /// the node's subtree can still change under the transfer function
    /// (`criteria::image_weight`), instead of by [`Self::data_aware`]'s weight. `None`: that
    /// weight (geometric when it is `None` too).
    pub image: Option<ImageCriterion>,
    /// Most leaves the red tree may hold: a split that would go beyond is not made (the
    /// candidates wait, largest error first). `None`: no limit.
    pub max_tets: Option<usize>,
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
            image: None,
            max_tets: None,
            interactive: Budget::ms(8.0),
            progressive: Budget::ms(50.0),
        }
    }
}

/// What one [`Selector::frame`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FrameStats {
    pub splits: usize,
    /// Merges that held (the tet is a leaf after the batch's closure).
    pub merges: usize,
    pub merge_attempts: usize,
    /// Node slots looked at by the sweeps (scanned, or listed candidates evaluated).
    pub scanned: usize,
    /// Sweeps completed in this frame.
    pub sweeps: usize,
    /// Candidates left in the heaps for later frames.
    pub pending: usize,
    /// The mesh is where the criteria want it (for this view and buffer), or as near as the leaf
    /// budget allows.
    pub converged: bool,
    /// The leaf budget ([`SelectParams::max_tets`]) refused a split the criteria wanted, in this
    /// frame's sweep or the last one.
    pub budget_bound: bool,
    pub elapsed: Duration,
    /// Time inside the mesh's refine / coarsen calls (the rest is sweeping and bookkeeping).
    pub op_time: Duration,
}

/// What one frame's evaluations read besides the mesh: the buffer, the view and the mode. The mesh
/// is passed apart, since a frame refines and coarsens it between evaluations.
#[derive(Debug, Clone, Copy)]
struct FrameCtx<'a> {
    buf: &'a DetailBuffer,
    view: &'a View,
    mode: Mode,
}

/// Frame-by-frame selective refinement (see the module docs).
///
/// # Incremental sweeps
/// A sweep starts from the candidates of the current mesh, view and buffer: the leaves wanted split
/// and the refined nodes (with 8 leaf children) wanted merged. Finding them by looking at every node
/// is the *full scan*; it runs once per *epoch* (the view, the mode, the parameters or the buffer
/// changed) and records the candidate slots in a list. Later sweeps of the same epoch start from that
/// list plus the slots the mesh reports as changed since ([`AdaptiveMesh::changes_since`]): the
/// criteria are pure functions of the node's id for a given view and buffer, so a node whose slot
/// did not change keeps its status, and the list is a superset of the candidates. Each listed slot
/// is evaluated again (dropped when it is no candidate any more), so a sweep sees exactly the
/// candidates a full scan would. Per slot the bounding sphere, level, subtree max and usability are
/// cached (keyed by the node id). [`Selector::full_scan`] builds the reference selector that scans
/// every node with [`Selector::want_split`] / [`Selector::want_merge`] at every sweep.
///
/// A camera motion that keeps the lens (field of view, near plane, viewport) does not need a full
/// scan either (except with [`CoarsenRef::Grandparent`]): every evaluated slot keeps a certificate,
/// how far the camera may move before its criterion could answer otherwise (see `Kinetic`), and a
/// motion evaluates again only the slots whose certificates it uses up. Arrivals reported with
/// [`Selector::notify_arrived`] change the status of the arrived nodes' subtrees only.
///
/// Merge candidates the mesh settles by refined tets outside their batch
/// (`AdaptiveMesh::batch_held`) are *parked*: listed scans leave them out, which changes no
/// outcome while those tets stay refined and out of the batches. When one of them is queued to
/// merge by a listed scan, the candidates parked on it are queued with it (and, in turn, those
/// parked on them); when one changes, or is queued by a full scan or as the parent of a merge,
/// they are only unparked, for the next sweep. A batch that leaves merge candidates queued (under
/// a budget) parks nothing: a later chunk could hold one of the owners.
#[derive(Debug, Clone)]
pub struct Selector {
    pub params: SelectParams,
    cursor: usize,
    splits: CandQueue<Cand>,
    merges: CandQueue<Reverse<Cand>>,
    sweep_changes: usize,
    /// Merges refused by the closure in this sweep.
    sweep_refused: usize,
    /// Whether a merge batch of this sweep was cut into chunks (see `Selector::run`'s replay).
    sweep_chunked: bool,
    /// Seconds per candidate of the uncut merge batches so far (a running average), to tell
    /// whether one fits in what is left of a frame (see `Self::apply_merges`).
    merge_cost: f64,
    /// This sweep merges all its candidates in one batch, without the budget: the last sweep
    /// changed nothing but refused merges that may only hold together (a group split across
    /// batches); run once before declaring convergence, so budgeted frames reach the unbudgeted mesh.
    consolidating: bool,
    /// The view or the buffer changed since the current sweep started.
    dirty: bool,
    converged: bool,
    last_cam: Option<Camera>,
    last_mode: Option<Mode>,
    last_params: Option<SelectParams>,
    /// Reference mode: scan every node with the uncached criteria at every sweep.
    reference: bool,
    /// Bumped whenever the criteria may give other answers (view, mode, parameters, buffer, mesh).
    epoch: u64,
    /// Epoch of the sweep in progress.
    sweep_epoch: u64,
    /// [`AdaptiveMesh::change_seq`] when the sweep in progress started.
    sweep_seq: u64,
    /// The sweep in progress started from the candidate list (no scan).
    sweep_listed: bool,
    /// The full scan in progress has seen every change of the mesh since it started.
    scan_ok: bool,
    /// The candidate list holds every candidate of this epoch (see the type's docs).
    list_epoch: Option<u64>,
    list: Vec<u32>,
    /// Per slot: on the candidate list, parked, an owner others are parked on.
    slot_flags: SegVec<SlotFlags>,
    /// Parked slots by the owner slot that holds them.
    waiters: FxHashMap<u32, Vec<u32>>,
    /// Per slot: what selection keeps of its node.
    info: SegVec<SlotEntry>,
    /// The entries' current check stamp and the buffer generation it stands for (see
    /// [`Self::check_stamp`]).
    check: u32,
    check_gen: u64,
    /// Bounding spheres by slot ([`bounding_sphere`]), valid where `info` says so.
    geo: SegVec<(Vec3, f32)>,
    /// Image weights by slot (with [`SelectParams::image`]), valid where `info` holds a status.
    wt: SegVec<f32>,
    /// The mesh followed ([`AdaptiveMesh::uid`]) and the changes read from it.
    mesh_uid: u64,
    seen: u64,
    batch: Vec<TetId>,
    batch_slots: Vec<u32>,
    /// Scratch: the merge candidates of an unbudgeted batch, unsorted.
    unordered: Vec<Reverse<Cand>>,
    /// Changes with every frame and every change of the mesh ([`Self::retag`]): a candidate popped
    /// with the tag it was pushed with has the status it was pushed with.
    tag: u32,
    tag_seq: u64,
    /// Bumped when the criteria change other than by a camera motion (see `Kinetic`).
    full_epoch: u64,
    /// Full epoch of the full scan in progress.
    scan_full_epoch: u64,
    /// Next list entry a listed sweep looks at.
    lcursor: usize,
    /// Slots to look at again (changed by the mesh or by arrivals), by the next listed sweep.
    todo: Vec<u32>,
    /// The slots the listed sweep in progress looks at again first, and the next one.
    flushing: Vec<u32>,
    fcursor: usize,
    kin: Kinetic,
    /// The camera moved since the last frame, by a motion `Kinetic` can follow.
    moved: bool,
    /// Criteria evaluated so far (see [`Self::evaluations`]).
    evals: u64,
    /// The leaf budget refused a wanted split in the last sweep ([`FrameStats::budget_bound`]).
    budget_bound: bool,
}

impl Selector {
    pub fn new(params: SelectParams) -> Self {
        Selector {
            params,
            cursor: 0,
            splits: CandQueue::default(),
            merges: CandQueue::default(),
            sweep_changes: 0,
            sweep_refused: 0,
            sweep_chunked: false,
            merge_cost: INITIAL_MERGE_COST,
            consolidating: false,
            dirty: true,
            converged: false,
            last_cam: None,
            last_mode: None,
            last_params: None,
            reference: false,
            epoch: 0,
            sweep_epoch: 0,
            sweep_seq: 0,
            sweep_listed: false,
            scan_ok: false,
            list_epoch: None,
            list: Vec::new(),
            slot_flags: SegVec::new(),
            waiters: Default::default(),
            info: SegVec::new(),
            check: 0,
            check_gen: u64::MAX,
            geo: SegVec::new(),
            wt: SegVec::new(),
            mesh_uid: 0,
            seen: 0,
            batch: Vec::new(),
            batch_slots: Vec::new(),
            unordered: Vec::new(),
            tag: 0,
            tag_seq: 0,
            full_epoch: 0,
            scan_full_epoch: 0,
            lcursor: 0,
            todo: Vec::new(),
            flushing: Vec::new(),
            fcursor: 0,
            kin: Kinetic::default(),
            moved: false,
            evals: 0,
            budget_bound: false,
        }
    }

    /// The reference selector: every sweep scans every node with [`Self::want_split`] and
    /// [`Self::want_merge`] (no candidate list, no caches). Same meshes as [`Self::new`], slower.
    pub fn full_scan(params: SelectParams) -> Self {
        Selector {
            reference: true,
            ..Selector::new(params)
        }
    }

    /// New nodes arrived in the buffer (or the parameters changed): the selector looks again.
    pub fn notify_arrivals(&mut self) {
        self.full_epoch += 1;
        self.bump_epoch();
        self.dirty = true;
        self.converged = false;
    }

    /// Nodes `ids` arrived in the buffer and `mesh` has applied them
    /// ([`AdaptiveMesh::apply_arrivals`]): like [`Self::notify_arrivals`], but only the subtrees of
    /// the arrived nodes are looked at again (their usability is all that changed). Nodes of tets
    /// the mesh does not hold change nothing the criteria read (what their coefficients change in
    /// present vertex values is reported by the mesh, see [`Session`](crate::session::Session)):
    /// they leave a converged selector converged, so a stream that goes on sending what the view
    /// does not need cannot keep a client from converging.
    pub fn notify_arrived(&mut self, mesh: &AdaptiveMesh, ids: &[TetId]) {
        if ids.is_empty() {
            return;
        }
        if self.reference || mesh.uid() != self.mesh_uid {
            self.notify_arrivals();
            return;
        }
        let from = self.todo.len();
        for &id in ids {
            if let Some(s) = mesh.slot_of(id) {
                mesh.subtree_slots(s, &mut self.todo);
            }
        }
        if self.todo.len() == from {
            return;
        }
        self.dirty = true;
        self.converged = false;
        for i in from..self.todo.len() {
            let s = self.todo[i];
            self.forget(s);
        }
    }

    /// Nodes `ids` replaced their previews (`Arrivals::replaced`): their subtree bounds, and the
    /// ones their finest-level children inherit, may have changed. Every entry that remembers one
    /// of those nodes or their children is dropped, in a live slot or a free one a later split
    /// would reuse, and the live ones (with the nodes' parents, whose merges read them) are looked
    /// at again. Their usability did not change: pass [`Self::notify_arrived`] only the other
    /// arrivals.
    pub fn notify_replaced(&mut self, mesh: &AdaptiveMesh, ids: &[TetId]) {
        if ids.is_empty() {
            return;
        }
        let forest = mesh.forest();
        let mut affected: rustc_hash::FxHashSet<TetId> = Default::default();
        for &id in ids {
            affected.insert(id);
            if forest.level(id) < forest.levels {
                affected.extend((0..8).map(|i| forest.child(id, i)));
            }
        }
        self.reset_nodes(&affected);
        self.dirty = true;
        self.converged = false;
        let parents = ids.iter().filter_map(|&id| forest.parent(id));
        for id in affected.iter().copied().chain(parents) {
            if let Some(s) = mesh.slot_of(id) {
                self.todo.push(s as u32);
                self.forget(s as u32);
            }
        }
    }

    /// How many times a node's criteria were evaluated (cached statuses not counted) since this
    /// selector was made: a measure of selection work that does not depend on the machine's load.
    pub fn evaluations(&self) -> u64 {
        self.evals
    }

    /// Bytes held by the selector's per-slot caches, candidate list, heaps and certificates
    /// (capacities).
    pub fn bytes_held(&self) -> usize {
        self.bytes_parts().iter().map(|&(_, b)| b).sum()
    }

    /// [`Self::bytes_held`] by part: per-slot entries and flags, bounding spheres, motion
    /// certificates, candidate lists and scratch, heaps.
    pub fn bytes_parts(&self) -> [(&'static str, usize); 5] {
        use std::mem::size_of;
        let k = &self.kin;
        [
            ("entries", self.info.bytes() + self.slot_flags.bytes()),
            ("spheres", self.geo.bytes() + self.wt.bytes()),
            ("certificates", k.certificate_bytes()),
            (
                "lists",
                self.waiters.capacity() * (size_of::<(u32, Vec<u32>)>() + 1)
                    + self
                        .waiters
                        .values()
                        .map(|v| v.capacity() * 4)
                        .sum::<usize>()
                    + k.scratch_bytes()
                    + (self.list.capacity() + self.todo.capacity()) * 4
                    + (self.flushing.capacity() + self.batch_slots.capacity()) * 4
                    + self.batch.capacity() * size_of::<TetId>(),
            ),
            (
                "heaps",
                self.splits.capacity() * size_of::<Cand>()
                    + (self.merges.capacity() + self.unordered.capacity())
                        * size_of::<Reverse<Cand>>(),
            ),
        ]
    }

    /// Test support: compares every remembered status that is still current (its priority
    /// included, as [`Self::eval`] would return it) with a fresh evaluation for `cam` and `mode`,
    /// the camera and mode of the last frame. Returns how many were compared, or the first that
    /// differs.
    #[cfg(any(test, feature = "testing"))]
    pub fn verify_remembered(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        cam: &Camera,
        mode: Mode,
    ) -> Result<usize, RememberedMismatch> {
        if self.seen != mesh.change_seq() {
            return Err(RememberedMismatch(
                "the mesh changed since the last frame".into(),
            ));
        }
        let view = View::new(cam, self.params.tol);
        let cx = FrameCtx {
            buf,
            view: &view,
            mode,
        };
        let levels = mesh.forest().levels;
        let evals = self.evals;
        let mut n = 0;
        for slot in 0..self.info.len() {
            let e = self.info[slot];
            if e.epoch() != self.stat_epoch() {
                continue;
            }
            let kept = self.cached_status(&cx, levels, slot, &e);
            let fresh = self.eval_cert(mesh, &cx, slot, false).0;
            if kept != fresh {
                self.evals = evals;
                return Err(RememberedMismatch(format!(
                    "slot {slot}: remembered {kept:?}, evaluated {fresh:?}"
                )));
            }
            n += 1;
        }
        self.evals = evals;
        Ok(n)
    }

    /// Whether the last frame found nothing left to do.
    pub fn is_converged(&self) -> bool {
        self.converged
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
}
/// What [`Selector::verify_remembered`] found that differs from a fresh evaluation.
#[cfg(any(test, feature = "testing"))]
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct RememberedMismatch(pub String);
