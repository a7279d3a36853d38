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

use crate::detail_buffer::DetailBuffer;
use crate::mesh::{AdaptiveMesh, MeshError, RedNode, SegVec};
use glam::{DVec3, Vec3};
use rustc_hash::FxHashMap;
use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;
use std::time::{Duration, Instant};
pub use tetwave_protocol::view::{data_weight, Tolerance, View};
use tetwave_protocol::view::{f32_down, f32_up, tet_sphere, Camera};
use tetwave_protocol::TetId;

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

/// Bounding sphere of mesh vertices `v`: the centroid rounded to `f32`, and the distance from it to
/// the farthest vertex rounded up to `f32` (so that selection caches it in 16 bytes, exactly).
#[inline]
pub fn bounding_sphere(mesh: &AdaptiveMesh, v: &[u32; 4]) -> (DVec3, f64) {
    let (c, r) = sphere32(mesh, v);
    (c.as_dvec3(), r as f64)
}

#[inline]
fn sphere32(mesh: &AdaptiveMesh, v: &[u32; 4]) -> (Vec3, f32) {
    let pos = mesh.positions();
    tet_sphere(v.map(|s| {
        let q = pos[s as usize];
        DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64)
    }))
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
    /// The mesh is where the criteria want it (for this view and buffer).
    pub converged: bool,
    pub elapsed: Duration,
    /// Time inside the mesh's refine / coarsen calls (the rest is sweeping and bookkeeping).
    pub op_time: Duration,
}

/// A candidate: priority, tet id, the node slot it had when pushed (a hint) and the selector's tag
/// then (see `Selector::tag`); only the first two are ordered.
#[derive(Debug, Clone, Copy)]
struct Cand(f64, TetId, u32, u32);
impl PartialEq for Cand {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o) == Ordering::Equal
    }
}
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

/// A max-priority queue for a sweep's candidates: what a scan pushes before the first pop is
/// sorted once (cheaper than a heap for the bulk), later pushes go to a heap. Pops come in the
/// order a `BinaryHeap` would give (up to equal items).
#[derive(Debug, Clone)]
struct CandQueue<T> {
    /// Ascending once `sorted`: popped from the back.
    bulk: Vec<T>,
    sorted: bool,
    heap: BinaryHeap<T>,
}

impl<T: Ord> Default for CandQueue<T> {
    fn default() -> Self {
        CandQueue {
            bulk: Vec::new(),
            sorted: false,
            heap: BinaryHeap::new(),
        }
    }
}

impl<T: Ord> CandQueue<T> {
    #[inline]
    fn push(&mut self, x: T) {
        if self.sorted {
            self.heap.push(x);
        } else {
            self.bulk.push(x);
        }
    }

    #[inline]
    fn pop(&mut self) -> Option<T> {
        if !self.sorted {
            self.bulk.sort_unstable();
            self.sorted = true;
        }
        match (self.bulk.last(), self.heap.peek()) {
            (Some(a), Some(b)) if b > a => self.heap.pop(),
            (Some(_), _) => self.bulk.pop(),
            _ => self.heap.pop(),
        }
    }

    fn clear(&mut self) {
        self.bulk.clear();
        self.heap.clear();
        self.sorted = false;
    }

    /// Moves every item to `out`, in no particular order (nothing is sorted).
    fn drain_into(&mut self, out: &mut Vec<T>) {
        out.append(&mut self.bulk);
        out.extend(self.heap.drain());
        self.sorted = false;
    }

    fn len(&self) -> usize {
        self.bulk.len() + self.heap.len()
    }

    fn capacity(&self) -> usize {
        self.bulk.capacity() + self.heap.capacity()
    }

    fn is_empty(&self) -> bool {
        self.bulk.is_empty() && self.heap.is_empty()
    }
}

/// Merges handed to one [`AdaptiveMesh::coarsen_batch`] at most, when a batch is cut into chunks.
const MERGE_CHUNK: usize = 256;
/// Under a time budget only, merge candidates taken in one uncut batch when at most this many wait
/// and at least half of the frame is left (or what is left covers them, see [`uncut_batch`]), and
/// the size of a chunk taken early in a frame when more wait (see `Selector::apply_merges`). With
/// 2,048, level 6 at 10% and 8 ms fell behind in half of its runs (chunks refuse merges a whole
/// batch allows; 1.84–2.13 M tets/s, 6–11 frames to settle); with 4,096 in none of 8 (2.27–2.44
/// M/s), its largest step at 6.25% 10.4–11.2 ms instead of about 9 (8,192: 12.9–14.5 ms).
const WHOLE_MERGES: usize = 4096;
/// [`Selector::merge_cost`] before any uncut batch was timed: one microsecond per candidate (a
/// level-6 run's batches take about 0.4).
const INITIAL_MERGE_COST: f64 = 1e-6;
/// How many slots ahead the loops over listed slots ask for their cache lines
/// ([`Selector::prefetch_slot`]).
const PREFETCH: usize = 8;
/// Node slots scanned between two clock reads.
const SCAN_CHUNK: usize = 512;
/// Sweeps one unbudgeted [`Selector::converge`] may take before giving up.
const MAX_SWEEPS: usize = 256;

/// What selection keeps of one node slot (16 bytes): pure functions of the node's id (level; the
/// bounding sphere, kept apart in `Selector::geo` since complete mode needs none), what the buffer
/// said of it (presence, subtree max, usability: these only grow) and the status last evaluated
/// (reused while the epoch lasts and the slot does not change, see `Selector::eval`; its priority
/// is computed again from the entry). The status had an 8-byte array of its own, with the
/// priority: folded in here, the selector's bytes per average tet fell from 63.5 to 54.4 (level 6,
/// 10%) and from 28.9 to 19.8 (level 6, simple; 20.9 at level 5), with the same counts.
#[derive(Debug, Clone, Copy)]
struct SlotEntry {
    /// The node the entry describes, as [`info_tag`] names it; 0: none.
    tag: u32,
    /// [`DetailBuffer::nodes_held`] (low 32 bits) when presence and usability were looked up.
    checked: u32,
    smax: f32,
    /// Bits: the status's kind (2: [`KIND_SPLIT`]..), [`PRESENT`], [`USABLE`], [`GEO`], the level
    /// (5 bits from [`LEVEL_SHIFT`]) and the status's epoch (from [`EPOCH_SHIFT`]: the low bits of
    /// `epoch + 1` when it was evaluated; 0: none).
    word: u32,
}

const _: () = assert!(std::mem::size_of::<SlotEntry>() == 16);
const _: () = assert!(tetwave_protocol::hierarchy::MAX_LEVELS as u32 <= LEVEL_MASK);

/// [`SlotEntry::word`]: status kinds (the priority is computed again from the entry, see
/// `Selector::cached_status`): keep, split, merge with the error as priority, merge outside the
/// frustum (priority [`OUTSIDE`]).
const KIND_MASK: u32 = 3;
const KIND_SPLIT: u32 = 1;
const KIND_MERGE: u32 = 2;
const KIND_MERGE_OUT: u32 = 3;
const PRESENT: u32 = 4;
const USABLE: u32 = 8;
/// `Selector::geo` holds the node's bounding sphere.
const GEO: u32 = 16;
const LEVEL_SHIFT: u32 = 5;
const LEVEL_MASK: u32 = 31;
const EPOCH_SHIFT: u32 = 10;
/// The bits of [`SlotEntry::word`] that describe the node (not the status).
const FACTS_MASK: u32 = ((1 << EPOCH_SHIFT) - 1) & !KIND_MASK;
/// Bits of an epoch a [`SlotEntry`] keeps.
const STAT_EPOCH_MASK: u64 = (1 << (32 - EPOCH_SHIFT)) - 1;

const NO_ENTRY: SlotEntry = SlotEntry {
    tag: 0,
    checked: u32::MAX,
    smax: 0.0,
    word: 0,
};

impl SlotEntry {
    #[inline(always)]
    fn level(&self) -> u8 {
        ((self.word >> LEVEL_SHIFT) & LEVEL_MASK) as u8
    }

    #[inline(always)]
    fn epoch(&self) -> u32 {
        self.word >> EPOCH_SHIFT
    }

    /// Forgets the status.
    #[inline(always)]
    fn forget(&mut self) {
        self.word &= FACTS_MASK;
    }
}

/// The facts of one node [`Selector::info_of`] gives (from its [`SlotEntry`]).
#[derive(Debug, Clone, Copy)]
struct SlotInfo {
    smax: f32,
    level: u8,
    present: bool,
    usable: bool,
}

/// The name of node `id` in [`SlotEntry::tag`]: its low 32 bits plus one, never 0. Two nodes that
/// share a slot over time have different tags as long as ids fit in 32 bits; a forest with more
/// tets (`wide`) gets tag 0, which never matches: its entries are filled again at every use.
#[inline]
fn info_tag(id: TetId, wide: bool) -> u32 {
    if wide {
        0
    } else {
        (id as u32).wrapping_add(1)
    }
}

/// The merge priority of a node outside the frustum (below every in-view error, so merged first).
const OUTSIDE: f64 = -1.0;

/// What the criteria want of one node of the red tree.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Status {
    Keep,
    /// A leaf wanted split, with its priority.
    Split(f64),
    /// A refined node with 8 leaf children whose split should be undone, with its priority.
    Merge(f64),
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
/// ([`AdaptiveMesh::batch_held`]) are *parked*: listed scans leave them out, which changes no
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
    /// Per slot: [`LISTED`]; [`PARKED`] for a listed merge candidate the last batch settled by
    /// owners outside it (see [`AdaptiveMesh::batch_held`]): the listed scan leaves it out until
    /// one of those owners is queued to merge or changes, and it is refused meanwhile; [`WAITED`]
    /// for such an owner.
    slot_flags: SegVec<u8>,
    /// Parked slots by the owner slot that holds them.
    waiters: FxHashMap<u32, Vec<u32>>,
    /// Per slot: what selection keeps of its node.
    info: SegVec<SlotEntry>,
    /// Bounding spheres by slot ([`bounding_sphere`]), valid where `info` says so.
    geo: SegVec<(Vec3, f32)>,
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
}

/// Motion-bounded re-evaluation (see [`Selector`]): a slot's split criterion, evaluated for one
/// view, keeps its answer while the camera moves less than the slot's *margins*: its distance to
/// the error threshold (the eye moves it at most by the eye's displacement) and, for the frustum,
/// to the planes that decide (a motion moves a plane relative to a scene point at most by the eye's
/// displacement plus the normal's change times the point's distance from the eye). The bounds add
/// up over motions in `we` and `wf`; each slot records the values of those sums at which it must be
/// evaluated again (or sooner, when its node changes).
#[derive(Debug, Clone, Default)]
struct Kinetic {
    /// Full epoch whose certificates are held (`None`: not following).
    epoch: Option<u64>,
    /// The view the bounds were last brought to.
    view: Option<View>,
    /// Sums of the motion bounds for the eye distance and for the plane offsets, per unit of a
    /// slot's *reach* `max(|c − o| + r, rho_floor)` (its bounding sphere's farthest distance from
    /// the scene's centre `o`): a rotation by `θ` about `o` moves a point at most `2·sin(θ/2)`
    /// times its distance from `o`, so slots near the centre keep their certificates longer.
    we: f64,
    wf: f64,
    /// Per slot: evaluate again once `we` or `wf` reaches these (rounded down).
    until_e: SegVec<f32>,
    until_f: SegVec<f32>,
    /// Bounding box of the scene (the base vertices), its centre and the least reach counted
    /// (a quarter of its half diagonal: translations and the other bounds divide by it).
    lo: DVec3,
    hi: DVec3,
    centre: DVec3,
    rho_floor: f64,
    scene: bool,
    due: Vec<u32>,
    /// No slot's certificate ends at or below these bounds.
    clean: (f64, f64),
    /// The due pass in progress (the bounds it started from) and its next slot.
    pass: Option<(f64, f64)>,
    cursor: usize,
}

/// [`Selector::slot_flags`]: on the candidate list.
const LISTED: u8 = 1;
/// [`Selector::slot_flags`]: parked.
const PARKED: u8 = 2;
/// [`Selector::slot_flags`]: has slots parked on it (exactly the keys of `Selector::waiters`): lets
/// `Selector::wake` skip the map for the others.
const WAITED: u8 = 4;

/// Bit `j` set when slot `j` is due, `ue[j] ≤ we` or `uf[j] ≤ wf`, for up to 64 slots. On x86-64
/// four slots per vector compare (SSE2, always there); one slot at a time took 6–7 instructions, a
/// twentieth of the selection's at 10%.
#[inline]
fn due_mask(ue: &[f32], uf: &[f32], we: f32, wf: f32) -> u64 {
    assert!(ue.len() == uf.len() && ue.len() <= 64);
    let mut mask = 0u64;
    let mut j = 0;
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{
            _mm_cmple_ps, _mm_loadu_ps, _mm_movemask_ps, _mm_or_ps, _mm_set1_ps,
        };
        // SAFETY: SSE2 is part of the x86-64 baseline; every load reads 4 floats at `j < len − 3`.
        unsafe {
            let (vwe, vwf) = (_mm_set1_ps(we), _mm_set1_ps(wf));
            while j + 4 <= ue.len() {
                let e = _mm_cmple_ps(_mm_loadu_ps(ue.as_ptr().add(j)), vwe);
                let f = _mm_cmple_ps(_mm_loadu_ps(uf.as_ptr().add(j)), vwf);
                mask |= (_mm_movemask_ps(_mm_or_ps(e, f)) as u64) << j;
                j += 4;
            }
        }
    }
    for k in j..ue.len() {
        mask |= (((ue[k] <= we) | (uf[k] <= wf)) as u64) << k;
    }
    mask
}

/// Whether `queued` merge candidates go in one uncut batch ([`Selector::apply_merges`], no
/// operation budget): always without a time budget (`left`, the time left in the frame: `None`);
/// under one, when at most [`WHOLE_MERGES`] wait and either half of the frame is left (`early`) or
/// what is left covers their expected time at `cost` seconds per candidate. The last case stops
/// the second half of a frame from cutting into 256-candidate chunks a batch that fits: chunks
/// refuse the merges that hold only together (level 6, 10%, 8 ms: in one run 2,609 late chunks
/// attempted 646 k merges and 21 k held), and a sweep whose batches were cut takes one more
/// sweep to consolidate.
fn uncut_batch(queued: usize, early: bool, left: Option<Duration>, cost: f64) -> bool {
    match left {
        None => true,
        Some(left) => {
            queued <= WHOLE_MERGES && (early || left.as_secs_f64() >= cost * queued as f64)
        }
    }
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
            geo: SegVec::new(),
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
    /// the arrived nodes are looked at again (their usability is all that changed).
    pub fn notify_arrived(&mut self, mesh: &AdaptiveMesh, ids: &[TetId]) {
        if ids.is_empty() {
            return;
        }
        if self.reference || mesh.uid() != self.mesh_uid {
            self.notify_arrivals();
            return;
        }
        self.dirty = true;
        self.converged = false;
        let from = self.todo.len();
        for &id in ids {
            if let Some(s) = mesh.slot_of(id) {
                mesh.subtree_slots(s, &mut self.todo);
            }
        }
        for i in from..self.todo.len() {
            let s = self.todo[i];
            self.forget(s);
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
            ("spheres", self.geo.bytes()),
            ("certificates", k.until_e.bytes() + k.until_f.bytes()),
            (
                "lists",
                self.waiters.capacity() * (size_of::<(u32, Vec<u32>)>() + 1)
                    + self
                        .waiters
                        .values()
                        .map(|v| v.capacity() * 4)
                        .sum::<usize>()
                    + (k.due.capacity() + self.list.capacity() + self.todo.capacity()) * 4
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
    #[doc(hidden)]
    pub fn verify_remembered(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        cam: &Camera,
        mode: Mode,
    ) -> Result<usize, String> {
        if self.seen != mesh.change_seq() {
            return Err("the mesh changed since the last frame".into());
        }
        let view = View::new(cam, self.params.tol);
        let levels = mesh.forest().levels;
        let evals = self.evals;
        let mut n = 0;
        for slot in 0..self.info.len() {
            let e = self.info[slot];
            if e.epoch() != self.stat_epoch() {
                continue;
            }
            let kept = self.cached_status(&view, mode, levels, slot, &e);
            let fresh = self.eval_cert(mesh, buf, &view, mode, slot, false).0;
            if kept != fresh {
                self.evals = evals;
                return Err(format!(
                    "slot {slot}: remembered {kept:?}, evaluated {fresh:?}"
                ));
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
        let (c, r) = bounding_sphere(mesh, &mesh.node_verts(n.slot as usize));
        self.sphere_error(view, c, r, buf.subtree_max(n.id))
    }

    /// [`Self::error`] of a node with bounding sphere `(c, r)` and subtree max `smax`.
    #[inline]
    fn sphere_error(&self, view: &View, c: DVec3, r: f64, smax: Option<f32>) -> Option<f64> {
        if self.params.frustum && !view.sphere_visible(c, r) {
            return None;
        }
        Some(self.weighted_error(view, c, r, smax).0)
    }

    /// Screen-space error of a sphere times its data weight (the frustum aside), and that weight
    /// (1 unless data-aware with a known subtree max).
    #[inline]
    fn weighted_error(&self, view: &View, c: DVec3, r: f64, smax: Option<f32>) -> (f64, f64) {
        let fac = self.weight(smax);
        (view.error_px(c, 2.0 * r) * fac, fac)
    }

    /// The data weight of a node with subtree max `smax` (1 unless data-aware with one).
    #[inline]
    fn weight(&self, smax: Option<f32>) -> f64 {
        match (self.params.data_aware, smax) {
            (Some(delta), Some(m)) => data_weight(m, self.params.value_range, delta),
            _ => 1.0,
        }
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
            self.error(mesh, buf, view, n).unwrap_or(OUTSIDE)
        })
    }

    // ------------------------------------------------------------ cached criteria

    /// The cached facts of node `n` in `slot`, filled or refreshed as needed.
    #[inline(always)]
    fn info_of(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        slot: usize,
        n: &RedNode,
    ) -> SlotInfo {
        if slot >= self.info.len() {
            self.info
                .resize(mesh.node_slot_len().max(slot + 1), NO_ENTRY);
        }
        let forest = mesh.forest();
        let tag = info_tag(n.id, forest.total_tets() > u32::MAX as u64);
        let e = &mut self.info[slot];
        if e.tag != tag || tag == 0 {
            *e = SlotEntry {
                tag,
                word: (forest.level(n.id) as u32) << LEVEL_SHIFT,
                ..NO_ENTRY
            };
        }
        // the finest level has no detail nodes: nothing to look up (such leaves are never split)
        if e.word & USABLE == 0 && e.level() < forest.levels {
            let held = buf.nodes_held() as u32;
            if e.checked != held {
                e.checked = held;
                if let Some(m) = buf.subtree_max(n.id) {
                    e.smax = m;
                    e.word |= PRESENT;
                    if buf.is_usable(n.id) {
                        e.word |= USABLE;
                    }
                }
            }
        }
        SlotInfo {
            smax: e.smax,
            level: e.level(),
            present: e.word & PRESENT != 0,
            usable: e.word & USABLE != 0,
        }
    }

    /// The cached bounding sphere of node `n` in `slot` (after [`Self::info_of`]).
    #[inline(always)]
    fn sphere_of(&mut self, mesh: &AdaptiveMesh, slot: usize) -> (DVec3, f64) {
        let e = &mut self.info[slot];
        if e.word & GEO == 0 {
            e.word |= GEO;
            if slot >= self.geo.len() {
                self.geo
                    .resize(mesh.node_slot_len().max(slot + 1), (Vec3::ZERO, 0.0));
            }
            self.geo[slot] = sphere32(mesh, &mesh.node_verts(slot));
        }
        let (c, r) = self.geo[slot];
        (c.as_dvec3(), r as f64)
    }

    /// [`Self::want_split`] from the cache.
    #[inline]
    fn split_cached(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        slot: usize,
        n: &RedNode,
    ) -> (Option<f64>, SlotInfo) {
        let levels = mesh.forest().levels;
        let i = self.info_of(mesh, buf, slot, n);
        if n.empty || !i.usable || i.level >= levels {
            return (None, i);
        }
        if mode == Mode::Complete {
            return (Some((levels - i.level) as f64), i);
        }
        let (c, r) = self.sphere_of(mesh, slot);
        let e = self
            .sphere_error(view, c, r, Some(i.smax))
            .filter(|&e| e > view.tol_px);
        (e, i)
    }

    /// The status of the live node in `slot` (the cached [`Self::want_split`] /
    /// [`Self::want_merge`]).
    #[inline]
    fn eval(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        slot: usize,
    ) -> Status {
        // the status is a function of the node for one epoch: reused unless the slot changed
        // since (changes not yet read from the mesh could concern it)
        if self.seen == mesh.change_seq() && !self.reference {
            if let Some(&e) = self.info.get(slot) {
                if e.epoch() == self.stat_epoch() {
                    return self.cached_status(view, mode, mesh.forest().levels, slot, &e);
                }
            }
        }
        let st = self.eval_cert(mesh, buf, view, mode, slot, false).0;
        self.remember(slot, st);
        st
    }

    /// The status an entry with a current epoch keeps, its priority computed again from the
    /// entry's facts as [`Self::eval_cert`] computed it (the same operations on the same values).
    #[inline]
    fn cached_status(
        &self,
        view: &View,
        mode: Mode,
        levels: u8,
        slot: usize,
        e: &SlotEntry,
    ) -> Status {
        let kind = e.word & KIND_MASK;
        if kind == 0 {
            return Status::Keep;
        }
        if kind == KIND_MERGE_OUT {
            return Status::Merge(OUTSIDE);
        }
        let prio = if mode == Mode::Complete {
            if kind == KIND_SPLIT {
                (levels - e.level()) as f64
            } else {
                0.0
            }
        } else {
            debug_assert!(e.word & GEO != 0, "a split or merge status has its sphere");
            let (c, r) = self.geo[slot];
            let smax = (e.word & PRESENT != 0).then_some(e.smax);
            self.weighted_error(view, c.as_dvec3(), r as f64, smax).0
        };
        if kind == KIND_SPLIT {
            Status::Split(prio)
        } else {
            Status::Merge(prio)
        }
    }

    /// The low bits of `epoch + 1`, as [`SlotEntry`] keeps them.
    #[inline]
    fn stat_epoch(&self) -> u32 {
        ((self.epoch + 1) & STAT_EPOCH_MASK) as u32
    }

    /// Forgets every remembered status.
    fn forget_all(&mut self) {
        for i in 0..self.info.len() {
            self.info[i].forget();
        }
    }

    /// Moves to a new epoch (every remembered status is stale).
    fn bump_epoch(&mut self) {
        self.epoch += 1;
        if self.stat_epoch() == 0 {
            // the bits wrapped: forget everything rather than trust an entry that many epochs old
            self.forget_all();
            self.epoch += 1;
        }
    }

    /// Records the status just evaluated for `slot` (see [`Self::eval`]).
    #[inline]
    fn remember(&mut self, slot: usize, st: Status) {
        if slot >= self.info.len() {
            self.info.resize(slot + 1, NO_ENTRY);
        }
        let kind = match st {
            Status::Keep => 0,
            Status::Split(_) => KIND_SPLIT,
            Status::Merge(e) if e == OUTSIDE => KIND_MERGE_OUT,
            Status::Merge(_) => KIND_MERGE,
        };
        let epoch = self.stat_epoch();
        let e = &mut self.info[slot];
        e.word = (e.word & FACTS_MASK) | kind | epoch << EPOCH_SHIFT;
    }

    /// Forgets the status recorded for `slot`.
    #[inline]
    fn forget(&mut self, slot: u32) {
        if (slot as usize) < self.info.len() {
            self.info[slot as usize].forget();
        }
    }

    /// [`Self::eval`], and with `cert` the slot's certificate (see [`Kinetic`]): the values of
    /// `we` and `wf` up to which its status cannot change without a change of its node.
    #[inline(always)]
    fn eval_cert(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        slot: usize,
        cert: bool,
    ) -> (Status, f32, f32) {
        const INF: f32 = f32::INFINITY;
        self.evals += 1;
        let Some(n) = mesh.red_node(slot) else {
            return (Status::Keep, INF, INF);
        };
        if !n.leaf && !n.children_leaves {
            return (Status::Keep, INF, INF);
        }
        let levels = mesh.forest().levels;
        let i = self.info_of(mesh, buf, slot, &n);
        if n.empty || !i.usable || i.level >= levels {
            // not wanted split, whatever the view
            if n.leaf {
                return (Status::Keep, INF, INF);
            }
            return (
                self.merge_status(mesh, buf, view, mode, slot, &n, i),
                INF,
                INF,
            );
        }
        if mode == Mode::Complete {
            let s = if n.leaf {
                Status::Split((levels - i.level) as f64)
            } else {
                Status::Keep
            };
            return (s, INF, INF);
        }
        // the criterion, as `want_split` computes it
        let (c, r) = self.sphere_of(mesh, slot);
        // `View::sphere_visible` and `Self::weighted_error` in steps whose terms the certificate
        // below uses again
        let x = view.plane_offsets(c);
        let visible = !self.params.frustum || View::offsets_visible(&x, r);
        let d = (c - view.eye).length();
        let fac = self.weight(Some(i.smax));
        let e = view.error_px_at(d, 2.0 * r) * fac;
        let err = e > view.tol_px;
        let status = if n.leaf {
            if visible && err {
                Status::Split(e)
            } else {
                Status::Keep
            }
        } else if (visible && err)
            || (self.params.coarsen_ref == CoarsenRef::Grandparent
                && self.parent_wants_split(mesh, buf, view, mode, &n))
        {
            Status::Keep
        } else {
            Status::Merge(if visible { e } else { OUTSIDE })
        };
        if !cert {
            return (status, INF, INF);
        }
        let m_e = if fac <= 0.0 || r <= 0.0 || view.tol_px <= 0.0 || !e.is_finite() {
            f64::INFINITY
        } else {
            let big_r = view.pixels_per_unit * 2.0 * r * fac / view.tol_px;
            ((d - big_r).abs() - 1e-9 * (d + big_r) - 1e-12).max(0.0)
        };
        let (we, wf) = (self.kin.we, self.kin.wf);
        // margins in units of the slot's reach (see `Kinetic::we`)
        let reach = ((c - self.kin.centre).length() + r).max(self.kin.rho_floor);
        let m_e = m_e / reach;
        if !self.params.frustum {
            return (status, f32_down(we + m_e), INF);
        }
        let eps = 1e-9 * (c.length() + view.eye.length() + r + 1.0);
        let vals = x.map(|v| v + r);
        if visible {
            if err {
                let min = vals.iter().copied().fold(f64::INFINITY, f64::min);
                (
                    status,
                    f32_down(we + m_e),
                    f32_down(wf + (min - eps).max(0.0) / reach),
                )
            } else {
                (status, f32_down(we + m_e), INF) // leaving the view keeps it unwanted
            }
        } else {
            let worst = vals.iter().map(|&v| -v).fold(0.0, f64::max);
            let m_f = (worst - eps).max(0.0) / reach;
            // back in view and, unless already, over the threshold: wf bounds both motions
            let m = if err { m_f } else { m_f.max(m_e) };
            (status, INF, f32_down(wf + m))
        }
    }

    /// Grandparent rule: whether the parent of refined node `n` is wanted split.
    fn parent_wants_split(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: &RedNode,
    ) -> bool {
        if let Some(p) = mesh.forest().parent(n.id) {
            if let Some(ps) = mesh.slot_of(p) {
                let pn = mesh.red_node(ps).expect("slot_of gives live slots");
                return self
                    .split_cached(mesh, buf, view, mode, ps, &pn)
                    .0
                    .is_some();
            }
        }
        false
    }

    /// Merge status of refined node `n` (8 leaf children) that is not wanted split.
    #[allow(clippy::too_many_arguments)]
    fn merge_status(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        slot: usize,
        n: &RedNode,
        i: SlotInfo,
    ) -> Status {
        if mode == Mode::Complete {
            return Status::Merge(0.0);
        }
        if self.params.coarsen_ref == CoarsenRef::Grandparent
            && self.parent_wants_split(mesh, buf, view, mode, n)
        {
            return Status::Keep;
        }
        let smax = i.present.then_some(i.smax);
        let (c, r) = self.sphere_of(mesh, slot);
        Status::Merge(self.sphere_error(view, c, r, smax).unwrap_or(OUTSIDE))
    }

    /// The status of hierarchy tet `id` (not in the red tree: [`Status::Keep`]) and its slot;
    /// `hint`: the slot it probably is in.
    fn status_of(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        id: TetId,
        hint: u32,
    ) -> (Status, u32) {
        if self.reference {
            let Some(n) = mesh.red_node_of(id) else {
                return (Status::Keep, u32::MAX);
            };
            return (self.status_uncached(mesh, buf, view, mode, &n), u32::MAX);
        }
        let slot = if mesh.slot_holds(hint as usize, id) {
            Some(hint as usize)
        } else {
            mesh.slot_of(id)
        };
        match slot {
            Some(s) => (self.eval(mesh, buf, view, mode, s), s as u32),
            None => (Status::Keep, u32::MAX),
        }
    }

    fn status_uncached(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: &RedNode,
    ) -> Status {
        if n.leaf {
            if let Some(e) = self.want_split(mesh, buf, view, mode, n) {
                return Status::Split(e);
            }
        } else if n.children_leaves {
            if let Some(e) = self.want_merge(mesh, buf, view, mode, n) {
                return Status::Merge(e);
            }
        }
        Status::Keep
    }

    /// Moves [`Self::tag`] on if the mesh changed since it was set.
    #[inline]
    fn retag(&mut self, mesh: &AdaptiveMesh) {
        if mesh.change_seq() != self.tag_seq {
            self.tag_seq = mesh.change_seq();
            self.tag = self.tag.wrapping_add(1);
        }
    }

    /// Whether a candidate pushed with `tag` into slot `slot` still has its status.
    #[inline]
    fn trusted(&mut self, mesh: &AdaptiveMesh, tag: u32, slot: u32) -> bool {
        self.retag(mesh);
        !self.reference && tag == self.tag && slot != u32::MAX
    }

    /// Asks the CPU for the cache lines an evaluation of `slot` reads first: its node, entry and
    /// sphere. The loops over listed slots (scattered over the arrays) issue it a few slots ahead,
    /// so that the misses overlap. Prefetching the two certificate arrays too cost level 5 6 % of
    /// its time (0 of 8 alternating runs faster) for no clearer gain at level 6; these three cost
    /// level 5 about 3 % and save level 6 4–7 % (12.5%, 10%; 7 and 8 of 8 runs faster).
    #[inline(always)]
    fn prefetch_slot(&self, mesh: &AdaptiveMesh, slot: usize) {
        mesh.prefetch_node(slot);
        self.info.prefetch(slot);
        self.geo.prefetch(slot);
    }

    /// Prefetches ([`Self::prefetch_slot`]) `slots[k..k + n]` (those that exist). A loop over
    /// `slots` calls it with `n = PREFETCH` before its first item and with `k = j + PREFETCH`,
    /// `n = 1` at item `j`.
    #[inline(always)]
    fn prefetch_slots(&self, mesh: &AdaptiveMesh, slots: &[u32], k: usize, n: usize) {
        for i in k..k + n {
            if let Some(&s) = slots.get(i) {
                self.prefetch_slot(mesh, s as usize);
            }
        }
    }

    /// Queues a candidate, its priority rounded to an `f32` (as remembered statuses once kept it:
    /// the order the README's figures were measured with).
    #[inline]
    fn push(&mut self, id: TetId, slot: u32, s: Status) {
        let q = |e: f64| e as f32 as f64;
        match s {
            Status::Split(e) => self.splits.push(Cand(q(e), id, slot, self.tag)),
            Status::Merge(e) => self.merges.push(Reverse(Cand(q(e), id, slot, self.tag))),
            Status::Keep => {}
        }
    }

    #[inline]
    fn list_add(&mut self, slot: usize) {
        if slot >= self.slot_flags.len() {
            self.slot_flags.resize(slot + 1, 0);
        }
        if self.slot_flags[slot] & LISTED == 0 {
            self.slot_flags[slot] |= LISTED;
            self.list.push(slot as u32);
        }
    }

    fn list_clear(&mut self) {
        for &s in &self.list {
            self.slot_flags[s as usize] = 0;
        }
        self.list.clear();
        self.list_epoch = None;
        self.clear_waiters();
    }

    /// Forgets every parked slot's owners (the parked flags are the caller's to clear).
    fn clear_waiters(&mut self) {
        for &o in self.waiters.keys() {
            self.slot_flags[o as usize] &= !WAITED;
        }
        self.waiters.clear();
    }

    /// Parks the listed candidates the last merge batch settled by owners outside it.
    fn park(&mut self, mesh: &AdaptiveMesh) {
        for &(slot, owners) in mesh.batch_held() {
            let s = slot as usize;
            if s < self.slot_flags.len() && self.slot_flags[s] & LISTED != 0 {
                self.slot_flags[s] |= PARKED;
                for o in owners {
                    if o != u32::MAX {
                        self.waiters.entry(o).or_default().push(slot);
                        let o = o as usize;
                        if o >= self.slot_flags.len() {
                            self.slot_flags.resize(o + 1, 0);
                        }
                        self.slot_flags[o] |= WAITED;
                    }
                }
            }
        }
    }

    /// Clears `slot`'s parked flag; whether it was parked.
    #[inline]
    fn unpark(&mut self, slot: u32) -> bool {
        match self.slot_flags.get(slot as usize) {
            Some(&f) if f & PARKED != 0 => {
                self.slot_flags[slot as usize] = f & !PARKED;
                true
            }
            _ => false,
        }
    }

    /// Unparks the slots parked on `owner` (it changed, or is queued to merge); with `now`, the
    /// view of a listed scan, queues them too (the scan may have passed them), and so on for
    /// the slots parked on those.
    #[inline]
    fn wake(&mut self, owner: u32, now: Option<(&AdaptiveMesh, &DetailBuffer, &View, Mode)>) {
        if self
            .slot_flags
            .get(owner as usize)
            .is_some_and(|&f| f & WAITED != 0)
        {
            self.wake_parked(owner, now);
        }
    }

    /// [`Self::wake`] for an owner flagged [`WAITED`].
    #[inline(never)]
    fn wake_parked(
        &mut self,
        owner: u32,
        now: Option<(&AdaptiveMesh, &DetailBuffer, &View, Mode)>,
    ) {
        let mut owners = vec![owner];
        while let Some(o) = owners.pop() {
            let Some(parked) = self.waiters.remove(&o) else {
                continue;
            };
            self.slot_flags[o as usize] &= !WAITED;
            for &a in &parked {
                if !self.unpark(a) {
                    continue;
                }
                if let Some((mesh, buf, view, mode)) = now {
                    let s = self.eval(mesh, buf, view, mode, a as usize);
                    if let (Status::Merge(_), Some(n)) = (s, mesh.red_node(a as usize)) {
                        self.push(n.id, a, s);
                        owners.push(a);
                    }
                }
            }
        }
    }

    /// Queues the slots the mesh changed since the last look (see [`Self::flush_step`]); false
    /// (and the list is no longer complete) when the mesh dropped some of its change log.
    fn absorb_changes(&mut self, mesh: &mut AdaptiveMesh) -> bool {
        let seq = mesh.change_seq();
        if seq == self.seen {
            return true;
        }
        let ok = match mesh.changes_since(self.seen) {
            Some(ch) => {
                let from = self.todo.len();
                for c in ch {
                    self.todo.push(c.slot);
                    if c.block != u32::MAX {
                        self.todo.extend(c.block..c.block + 8);
                    }
                    if let Some(n) = mesh.red_node(c.slot as usize) {
                        if let Some(p) = mesh.forest().parent(n.id) {
                            if let Some(ps) = mesh.slot_of(p) {
                                self.todo.push(ps as u32);
                            }
                        }
                    }
                }
                for i in from..self.todo.len() {
                    let s = self.todo[i];
                    self.forget(s);
                    self.unpark(s);
                    self.wake(s, None);
                }
                true
            }
            None => false,
        };
        self.seen = seq;
        mesh.trim_changes(seq);
        if !ok {
            // changes unknown: no parked slot can be trusted
            for i in 0..self.list.len() {
                self.unpark(self.list[i]);
            }
            self.clear_waiters();
            self.forget_all();
            self.scan_ok = false;
            self.list_epoch = None;
            self.kin.epoch = None;
        }
        ok
    }

    /// Whether camera motions are followed by [`Kinetic`] certificates in `mode`.
    fn kin_capable(&self, mode: Mode) -> bool {
        !self.reference && mode != Mode::Complete && self.params.coarsen_ref == CoarsenRef::Parent
    }

    fn kin_active(&self, mode: Mode) -> bool {
        self.kin.epoch == Some(self.full_epoch) && self.kin_capable(mode)
    }

    /// Looks again at the next `n` slots queued for this sweep (`Self::flushing`): with
    /// certificates, evaluates them (listing candidates); otherwise lists them all. Returns the
    /// slots looked at.
    fn flush_step(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: usize,
    ) -> usize {
        let fl = std::mem::take(&mut self.flushing);
        let end = (self.fcursor + n).min(fl.len());
        let kin = self.kin_active(mode);
        let run = &fl[self.fcursor..end];
        if kin {
            self.prefetch_slots(mesh, run, 0, PREFETCH);
        }
        for (j, &s) in run.iter().enumerate() {
            if kin {
                self.prefetch_slots(mesh, run, j + PREFETCH, 1);
            }
            if !kin || self.eval_kin(mesh, buf, view, mode, s as usize) != Status::Keep {
                self.list_add(s as usize);
            }
        }
        let done = end - self.fcursor;
        self.fcursor = end;
        self.flushing = fl;
        if self.fcursor == self.flushing.len() {
            self.flushing.clear();
            self.fcursor = 0;
        }
        done
    }

    /// Starts following camera motions for a full scan with `view`.
    fn kin_start(&mut self, mesh: &AdaptiveMesh, view: &View) {
        let k = &mut self.kin;
        if !k.scene {
            let nb = mesh.vertex_keys().base_vertex_count() as u32;
            let (mut lo, mut hi) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
            for v in 0..nb {
                let p = mesh.vertex_position(v);
                let p = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                lo = lo.min(p);
                hi = hi.max(p);
            }
            k.lo = lo;
            k.hi = hi;
            k.centre = (lo + hi) * 0.5;
            k.rho_floor = ((hi - lo).length() * 0.125).max(1e-9);
            k.scene = true;
        }
        k.epoch = Some(self.full_epoch);
        k.view = Some(*view);
        k.clean = (k.we, k.wf); // once the scan is done
        k.pass = None;
        let len = mesh.node_slot_len();
        k.until_e.clear();
        k.until_f.clear();
        k.until_e.resize(len, f32::NEG_INFINITY);
        k.until_f.resize(len, f32::NEG_INFINITY);
    }

    /// [`Self::eval`], recording the slot's certificate for later motions.
    fn eval_kin(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        slot: usize,
    ) -> Status {
        let (s, ue, uf) = self.eval_cert(mesh, buf, view, mode, slot, true);
        if slot >= self.kin.until_e.len() {
            let len = mesh.node_slot_len().max(slot + 1);
            self.kin.until_e.resize(len, f32::NEG_INFINITY);
            self.kin.until_f.resize(len, f32::NEG_INFINITY);
        }
        self.kin.until_e[slot] = ue;
        self.kin.until_f[slot] = uf;
        self.remember(slot, s);
        s
    }

    /// The camera moved from `Kinetic::view` to `view`: adds the motion's bounds (the slots whose
    /// certificates they reach are evaluated by the next listed sweep's due pass).
    fn kin_advance(&mut self, view: &View) {
        let k = &mut self.kin;
        let old = k.view.expect("following");
        let dm = (view.eye - old.eye).length();
        let dn = (0..5)
            .map(|i| (view.planes[i].0 - old.planes[i].0).length())
            .fold(0.0, f64::max);
        let mut dmax: f64 = 0.0;
        for i in 0..8 {
            let p = DVec3::new(
                if i & 1 == 0 { k.lo.x } else { k.hi.x },
                if i & 2 == 0 { k.lo.y } else { k.hi.y },
                if i & 4 == 0 { k.lo.z } else { k.hi.z },
            );
            dmax = dmax.max((p - view.eye).length());
        }
        // Same lens: the frustum's planes and the eye are fixed in the camera's frame, which moved
        // rigidly. Written as a rotation `R` about the scene's centre `o` and a translation `t`,
        // the motion moves every scene point relative to the camera by at most
        // `|R − I|·ρ + |t| = 2·sin(θ/2)·ρ + |t|` (`ρ`: the scene's radius about `o`), which bounds
        // the change of its distance to the eye and to each plane. An orbit about the scene is
        // a pure rotation: `t = 0`.
        let o = (k.lo + k.hi) * 0.5;
        let rho = (k.hi - k.lo).length() * 0.5;
        let [r0, u0, f0] = old.basis;
        let [r1, u1, f1] = view.basis;
        // |R − I| (operator norm) = 2·sin(θ/2) = |B1 − B0|_F / √2 for orthonormal bases B
        let s2 = (((r1 - r0).length_squared()
            + (u1 - u0).length_squared()
            + (f1 - f0).length_squared())
            * 0.5)
            .sqrt();
        let rot = |v: DVec3| r1 * r0.dot(v) + u1 * u0.dot(v) + f1 * f0.dot(v);
        let t = (view.eye - o - rot(old.eye - o)).length();
        // per unit of reach `ρ' ≥ rho_floor`: a point within `ρ'` of `o` moves at most
        // `s2·ρ' + t ≤ ρ'·(s2 + t/rho_floor)`, and any bound `b` independent of the point is at most
        // `ρ'·b/rho_floor`
        let rf = k.rho_floor;
        let rigid = s2 + t / rf;
        let slack = 1.0 + 1e-6;
        let abs = 1e-9 * (rho + o.length() + view.eye.length() + 1.0) / rf;
        k.we += (dm / rf).min(rigid) * slack + abs;
        k.wf += ((dm + dn * dmax) / rf).min(rigid) * slack + abs;
        k.view = Some(*view);
    }

    /// Evaluates the due slots (certificates used up) among the next `n` slots of the due pass,
    /// listing the candidates; returns the slots looked at. Ends the pass at the last slot.
    fn due_pass_step(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: usize,
    ) -> usize {
        let k = &mut self.kin;
        let len = k.until_e.len().min(mesh.node_slot_len());
        let start = k.cursor.min(len);
        let end = (start + n).min(len);
        let mut due = std::mem::take(&mut k.due);
        due.clear();
        // rounded up: a slot in doubt is due
        let (we, wf) = (f32_up(k.we), f32_up(k.wf));
        // stops after a chunk's worth of due slots, so that the caller reads the clock often
        let mut i = start;
        while i < end && due.len() < SCAN_CHUNK {
            let ue = k.until_e.run(i, end);
            let uf = k.until_f.run(i, end);
            let mut off = 0;
            while off < ue.len() && due.len() < SCAN_CHUNK {
                let c = (ue.len() - off).min(64);
                let mut mask = due_mask(&ue[off..off + c], &uf[off..off + c], we, wf);
                while mask != 0 {
                    due.push((i + off) as u32 + mask.trailing_zeros());
                    mask &= mask - 1;
                }
                off += c;
            }
            i += off;
        }
        let end = i;
        k.cursor = end;
        if end == len {
            // every slot is certified beyond the bounds the pass started from
            k.clean = k.pass.take().expect("a pass in progress");
        }
        self.prefetch_slots(mesh, &due, 0, PREFETCH);
        for (j, &slot) in due.iter().enumerate() {
            self.prefetch_slots(mesh, &due, j + PREFETCH, 1);
            if self.eval_kin(mesh, buf, view, mode, slot as usize) != Status::Keep {
                self.list_add(slot as usize);
            }
        }
        self.kin.due = due;
        end - start
    }

    /// The scan of a listed sweep, until done or `until`: the slots changed before the sweep, the
    /// due pass, then the listed slots that still are candidates are pushed (the others leave the
    /// list).
    fn scan_listed(
        &mut self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        until: Option<Instant>,
        st: &mut FrameStats,
    ) {
        loop {
            if !self.flushing.is_empty() {
                st.scanned += self.flush_step(mesh, buf, view, mode, SCAN_CHUNK);
            } else if self.kin.pass.is_some() {
                st.scanned += self.due_pass_step(mesh, buf, view, mode, 8 * SCAN_CHUNK);
            } else if self.lcursor < self.list.len() {
                let end = (self.lcursor + SCAN_CHUNK).min(self.list.len());
                let mut i = self.lcursor;
                let mut end = end;
                self.prefetch_slots(mesh, &self.list, i, PREFETCH);
                while i < end {
                    self.prefetch_slots(mesh, &self.list, i + PREFETCH, 1);
                    let slot = self.list[i] as usize;
                    st.scanned += 1;
                    if self.slot_flags[slot] & PARKED != 0 {
                        i += 1;
                        continue;
                    }
                    let s = self.eval(mesh, buf, view, mode, slot);
                    if s == Status::Keep {
                        self.slot_flags[slot] &= WAITED;
                        self.list.swap_remove(i);
                        end = end.min(self.list.len());
                        continue;
                    }
                    let id = mesh.red_node(slot).expect("a candidate is live").id;
                    self.push(id, slot as u32, s);
                    if let Status::Merge(_) = s {
                        self.wake(slot as u32, Some((mesh, buf, view, mode)));
                    }
                    i += 1;
                }
                self.lcursor = i;
            } else {
                return;
            }
            if until.is_some_and(|t| Instant::now() >= t) {
                return;
            }
        }
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

    /// Notices what changed since the last frame: another mesh, other parameters, a camera that
    /// matters (not in [`Mode::Complete`]), another mode.
    fn sync(&mut self, mesh: &mut AdaptiveMesh, cam: &Camera, mode: Mode) {
        let mut full = false;
        if mesh.uid() != self.mesh_uid {
            self.mesh_uid = mesh.uid();
            self.seen = mesh.change_seq();
            self.info.clear();
            self.geo.clear();
            self.kin = Kinetic::default();
            self.todo.clear();
            self.flushing.clear();
            self.fcursor = 0;
            self.list_clear();
            self.cursor = 0;
            self.scan_ok = false;
            full = true;
        }
        if self.last_params.as_ref() != Some(&self.params) {
            self.last_params = Some(self.params.clone());
            full = true;
        }
        let mut moved = false;
        if self.last_mode != Some(mode) {
            full = true;
        } else if mode != Mode::Complete && self.last_cam.as_ref() != Some(cam) {
            // a motion of the eye and the view direction only can be followed
            let same_lens = self.last_cam.as_ref().is_some_and(|l| {
                l.fovy_deg == cam.fovy_deg
                    && l.near == cam.near
                    && l.width == cam.width
                    && l.height == cam.height
            });
            if same_lens && self.kin_active(mode) {
                moved = true;
            } else {
                full = true;
            }
        }
        self.last_cam = Some(*cam);
        self.last_mode = Some(mode);
        if full {
            self.full_epoch += 1;
        }
        if full || moved {
            self.bump_epoch();
            self.dirty = true;
            self.converged = false;
        }
        self.moved = moved && !full;
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
        self.tag = self.tag.wrapping_add(1);
        self.tag_seq = mesh.change_seq();
        self.sync(mesh, cam, mode);
        if self.converged {
            st.converged = true;
            st.elapsed = start.elapsed();
            return Ok(st);
        }
        let view = View::new(cam, self.params.tol);
        if self.moved {
            self.moved = false;
            if self.kin_active(mode) {
                self.kin_advance(&view);
            } else {
                self.full_epoch += 1;
            }
        }
        let deadline = budget.max_time.map(|d| start + d);
        let scan_deadline = budget.max_time.map(|d| start + d / 2);
        let past = |t: Option<Instant>| t.is_some_and(|t| Instant::now() >= t);
        let mut ops = 0usize;
        loop {
            let listed = !self.reference && self.absorb_changes(mesh);
            if self.cursor == 0 {
                // a new sweep sees the current view and buffer
                self.splits.clear();
                self.merges.clear();
                self.sweep_changes = 0;
                self.sweep_refused = 0;
                self.sweep_chunked = false;
                self.dirty = false;
                self.sweep_epoch = self.epoch;
                self.sweep_seq = mesh.change_seq();
                self.sweep_listed = listed && self.list_epoch == Some(self.full_epoch);
                if self.sweep_listed {
                    // the changed slots, the slots whose certificates the camera's motion used
                    // up, then the listed slots (see `Self::scan_listed`)
                    self.cursor = usize::MAX;
                    self.lcursor = 0;
                    debug_assert!(self.flushing.is_empty());
                    std::mem::swap(&mut self.todo, &mut self.flushing);
                    self.fcursor = 0;
                    if self.kin_active(mode) && (self.kin.we, self.kin.wf) != self.kin.clean {
                        self.kin.pass = Some((self.kin.we, self.kin.wf));
                        self.kin.cursor = 0;
                    }
                } else if !self.reference {
                    self.list_clear();
                    self.scan_ok = true;
                    self.scan_full_epoch = self.full_epoch;
                    self.todo.clear();
                    self.flushing.clear();
                    self.fcursor = 0;
                    if self.kin_capable(mode) {
                        self.kin_start(mesh, &view);
                    } else {
                        self.kin.epoch = None;
                    }
                }
            }
            // scan
            let len = mesh.node_slot_len();
            let have_work = !self.splits.is_empty() || !self.merges.is_empty();
            let scan_until = if have_work { scan_deadline } else { deadline };
            self.retag(mesh);
            if self.sweep_listed {
                self.scan_listed(mesh, buf, &view, mode, scan_until, &mut st);
            }
            while self.cursor < len {
                let end = (self.cursor + SCAN_CHUNK).min(len);
                for slot in self.cursor..end {
                    if self.reference {
                        let Some(n) = mesh.red_node(slot) else {
                            continue;
                        };
                        let s = self.status_uncached(mesh, buf, &view, mode, &n);
                        self.push(n.id, u32::MAX, s);
                    } else {
                        let s = if self.kin_active(mode) {
                            self.eval_kin(mesh, buf, &view, mode, slot)
                        } else {
                            self.eval(mesh, buf, &view, mode, slot)
                        };
                        if s != Status::Keep {
                            let id = mesh.red_node(slot).expect("a candidate is live").id;
                            self.push(id, slot as u32, s);
                            self.list_add(slot);
                            if let Status::Merge(_) = s {
                                self.wake(slot as u32, None);
                            }
                        }
                    }
                }
                st.scanned += end - self.cursor;
                self.cursor = end;
                if past(if have_work { scan_deadline } else { deadline }) {
                    break;
                }
            }
            let sweep_done = self.cursor >= len
                && (!self.sweep_listed
                    || (self.flushing.is_empty()
                        && self.kin.pass.is_none()
                        && self.lcursor >= self.list.len()));
            if sweep_done && !self.reference && !self.sweep_listed {
                // a full scan done within one full epoch, every change seen: the list is complete
                let ok = self.absorb_changes(mesh);
                if ok && self.scan_ok && self.scan_full_epoch == self.full_epoch {
                    self.list_epoch = Some(self.full_epoch);
                }
            }
            // apply: merges (up to half the ops while splits wait), splits, merges again
            let consolidating = self.consolidating;
            let merge_ops = if consolidating {
                usize::MAX
            } else {
                budget.max_ops
            };
            let half = if consolidating {
                usize::MAX
            } else if self.splits.is_empty() || budget.max_ops == usize::MAX {
                // (without an operation budget: one batch, not chunks of a huge "half")
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
                    scan_deadline,
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
                    scan_deadline,
                    &mut st,
                )?;
            }
            let out_of_budget = ops >= budget.max_ops || past(deadline);
            if sweep_done && self.splits.is_empty() && self.merges.is_empty() {
                st.sweeps += 1;
                self.cursor = 0;
                if self.sweep_changes == 0 && !self.dirty {
                    // A sweep whose merges were never cut into chunks merged all its candidates
                    // in one batch; if it left the mesh as it was, a consolidating sweep would
                    // replay it exactly.
                    let replay = !self.sweep_chunked
                        && !self.reference
                        && mesh.change_seq() == self.sweep_seq
                        && self.sweep_epoch == self.epoch;
                    if self.sweep_refused > 0 && !self.consolidating && !replay {
                        self.consolidating = true;
                        // its batch cannot be cut: under a time budget it starts with at least
                        // half of a frame left, if need be in the next frame
                        if budget.max_time.is_some_and(|d| start.elapsed() > d / 2) {
                            break;
                        }
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
        if self.reference {
            // it reads no changes: the log would only grow to its bound
            mesh.trim_changes(mesh.change_seq());
        } else {
            self.absorb_changes(mesh);
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
        whole_until: Option<Instant>,
        st: &mut FrameStats,
    ) -> Result<(), MeshError> {
        let mut batch = std::mem::take(&mut self.batch);
        let mut slots = std::mem::take(&mut self.batch_slots);
        while *ops < max_ops && !self.merges.is_empty() {
            if deadline.is_some_and(|t| Instant::now() >= t) {
                break;
            }
            batch.clear();
            slots.clear();
            // One batch without a budget, and under a time budget alone when few candidates wait
            // and half of the frame is left: a batch finds every merge its candidates allow
            // together, chunks only those each chunk allows, so chunking costs a consolidating
            // sweep (level 5, 10%, 8 ms: 1,688 sweeps instead of 626, 2.7 times the attempts).
            // Otherwise chunks, with a clock check between them.
            let early = max_ops == usize::MAX && whole_until.is_some_and(|t| Instant::now() < t);
            let left = deadline.map(|t| t.saturating_duration_since(Instant::now()));
            let whole = max_ops == usize::MAX
                && uncut_batch(self.merges.len(), early, left, self.merge_cost);
            let chunk = if whole {
                usize::MAX
            } else {
                self.sweep_chunked = true;
                if early {
                    WHOLE_MERGES
                } else {
                    MERGE_CHUNK.min(max_ops - *ops)
                }
            };
            // read what the last batch changed: the statuses of the other slots stay known
            if !self.reference {
                self.absorb_changes(mesh);
            }
            // one batch takes them all, in any order: no need to sort them
            let mut all = std::mem::take(&mut self.unordered);
            if chunk == usize::MAX {
                self.merges.drain_into(&mut all);
            }
            let mut next = all.drain(..);
            let mut popped = 0usize;
            while batch.len() < chunk {
                popped += 1;
                if popped.is_multiple_of(64) && deadline.is_some_and(|t| Instant::now() >= t) {
                    break;
                }
                let Some(Reverse(Cand(_, id, hint, tag))) =
                    next.next().or_else(|| self.merges.pop())
                else {
                    break;
                };
                if self.trusted(mesh, tag, hint) {
                    batch.push(id);
                    slots.push(hint);
                } else if let (Status::Merge(_), s) =
                    self.status_of(mesh, buf, view, mode, id, hint)
                {
                    batch.push(id);
                    slots.push(s);
                }
            }
            // (all taken unless cut short: the rest wait in the queue)
            for c in next {
                self.merges.push(c);
            }
            self.unordered = all;
            if chunk == usize::MAX && !self.merges.is_empty() {
                // a whole batch the clock cut: its candidates are split across batches
                self.sweep_chunked = true;
            }
            if batch.is_empty() {
                continue;
            }
            *ops += batch.len();
            st.merge_attempts += batch.len();
            let t = Instant::now();
            let held = mesh.coarsen_batch_at(&batch, &slots, buf);
            let took = t.elapsed();
            st.op_time += took;
            if chunk == usize::MAX {
                let per = took.as_secs_f64() / batch.len() as f64;
                self.merge_cost += (per - self.merge_cost) / 4.0;
            }
            let held = match held {
                Ok(h) => h,
                Err(e) => {
                    self.batch = batch;
                    self.batch_slots = slots;
                    return Err(e);
                }
            };
            // Parking needs every merge candidate of the sweep in this batch or an earlier one:
            // a candidate still queued for a later chunk could be an owner that holds one here.
            if !self.reference && self.merges.is_empty() {
                self.park(mesh);
            }
            st.merges += held;
            self.sweep_changes += held;
            self.sweep_refused += batch.len() - held;
            // parents whose children are now all leaves may merge next (ROAM-style)
            let forest = mesh.forest();
            for (&id, &slot) in batch.iter().zip(&slots) {
                if let Some(p) = forest.parent(id) {
                    let leaf = if mesh.slot_holds(slot as usize, id) {
                        mesh.red_node(slot as usize).is_some_and(|n| n.leaf)
                    } else {
                        mesh.is_leaf(id)
                    };
                    if leaf {
                        let (s, ps) = self.status_of(mesh, buf, view, mode, p, u32::MAX);
                        if let Status::Merge(_) = s {
                            self.push(p, ps, s);
                            self.wake(ps, None);
                        }
                    }
                }
            }
        }
        self.batch = batch;
        self.batch_slots = slots;
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
        while *ops < max_ops {
            // one split (with its closure) can take tens of µs: the clock is read before each
            if deadline.is_some_and(|t| Instant::now() >= t) {
                break;
            }
            let Some(Cand(_, id, hint, tag)) = self.splits.pop() else {
                break;
            };
            if !self.reference {
                self.absorb_changes(mesh);
            }
            if !self.trusted(mesh, tag, hint)
                && !matches!(
                    self.status_of(mesh, buf, view, mode, id, hint).0,
                    Status::Split(_)
                )
            {
                continue;
            }
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
                let (s, cs) = self.status_of(mesh, buf, view, mode, c, u32::MAX);
                if let Status::Split(_) = s {
                    self.push(c, cs, s);
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uncut merge batches: always without a time budget; under one only up to `WHOLE_MERGES`
    /// candidates, taken whole early in the frame whatever their cost, and late only when the
    /// time left covers them at the measured cost.
    #[test]
    fn uncut_batch_when_it_fits() {
        let ms = Duration::from_millis;
        assert!(uncut_batch(1 << 20, false, None, 1.0));
        assert!(uncut_batch(WHOLE_MERGES, true, Some(ms(0)), 1.0));
        assert!(!uncut_batch(WHOLE_MERGES + 1, true, Some(ms(100)), 0.0));
        // 2,000 candidates at 0.5 µs each: 1 ms
        assert!(uncut_batch(2000, false, Some(ms(1)), 5e-7));
        assert!(!uncut_batch(
            2000,
            false,
            Some(Duration::from_micros(999)),
            5e-7
        ));
        assert!(!uncut_batch(2000, false, Some(ms(0)), 5e-7));
        assert!(uncut_batch(0, false, Some(ms(0)), 5e-7));
    }

    /// The vector due mask against its definition, on every length up to 64, with values at,
    /// around and beyond the bounds (infinities and NaN included).
    #[test]
    fn due_mask_matches_definition() {
        let vals = [
            f32::NEG_INFINITY,
            -1.0,
            0.5,
            1.0,
            1.0f32.next_up(),
            2.0,
            f32::INFINITY,
            f32::NAN,
        ];
        let mut x = 7u64;
        for len in 0..=64 {
            for _ in 0..50 {
                let mut pick = || {
                    x += 1;
                    vals[(crate::progressive::splitmix(x) >> 61) as usize]
                };
                let ue: Vec<f32> = (0..len).map(|_| pick()).collect();
                let uf: Vec<f32> = (0..len).map(|_| pick()).collect();
                let (we, wf) = (1.0, 0.5);
                let want = (0..len).fold(0u64, |m, j| {
                    m | (((ue[j] <= we) || (uf[j] <= wf)) as u64) << j
                });
                assert_eq!(due_mask(&ue, &uf, we, wf), want, "{ue:?} {uf:?}");
            }
        }
    }
}
