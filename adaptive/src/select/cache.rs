//! What selection keeps per node slot: the node's facts, its last status (valid for one epoch)
//! and its bounding sphere.

use super::criteria::{sphere32, SlotInfo, Status, OUTSIDE};
use super::{FrameCtx, Mode, Selector};
use crate::detail_buffer::DetailBuffer;
use crate::mesh::{AdaptiveMesh, RedNode};
use bitflags::bitflags;
use glam::{DVec3, Vec3};
use tetwave_protocol::TetId;

/// How many slots ahead the loops over listed slots ask for their cache lines
/// ([`Selector::prefetch_slot`]).
pub(super) const PREFETCH: usize = 8;

/// What selection keeps of one node slot (16 bytes): pure functions of the node's id (level; the
/// bounding sphere, kept apart in `Selector::geo` since complete mode needs none), what the buffer
/// said of it (presence and usability, which only grow; the subtree max, final once usable but
/// for a preview's, which `Selector::notify_replaced` drops with the entry: a finest-level
/// node's is infinite until its parent arrives) and the status last evaluated
/// (reused while the epoch lasts and the slot does not change, see `Selector::eval`). The status
/// takes spare bits of the word and its priority is computed again from the entry rather than
/// stored, since these entries are most of the selector's memory.
#[derive(Debug, Clone, Copy)]
pub(super) struct SlotEntry {
    /// The node the entry describes, as [`info_tag`] names it; 0: none.
    tag: u32,
    /// [`DetailBuffer::generation`] (low 32 bits) when presence and usability were looked up.
    checked: u32,
    smax: f32,
    /// From the low bits: the status's [`Kind`] (2 bits), the node's [`Facts`] (3 bits), its
    /// level (5 bits from [`LEVEL_SHIFT`]) and the status's epoch (from [`EPOCH_SHIFT`]: the low
    /// bits of `epoch + 1` when it was evaluated; 0: none).
    word: u32,
}

const _: () = assert!(std::mem::size_of::<SlotEntry>() == 16);
const _: () = assert!(tetwave_protocol::hierarchy::MAX_LEVELS as u32 <= LEVEL_MASK);

bitflags! {
    /// What a [`SlotEntry`] knows of its node besides the level: bits 2 to 4 of its word.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    struct Facts: u32 {
        /// The buffer holds the node: `SlotEntry::smax` is its subtree max.
        const PRESENT = 1 << 2;
        /// The node and its ancestors have arrived: it may be split.
        const USABLE = 1 << 3;
        /// `Selector::geo` holds the node's bounding sphere.
        const GEO = 1 << 4;
    }
}

/// The kind of a remembered status, in the low bits of [`SlotEntry::word`] (the priority is
/// computed again from the entry, see `Selector::cached_status`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Keep = 0,
    Split = 1,
    /// A merge with the error as priority.
    Merge = 2,
    /// A merge outside the frustum (priority [`OUTSIDE`]).
    MergeOut = 3,
}

const KIND_MASK: u32 = 3;
const LEVEL_SHIFT: u32 = 5;
const LEVEL_MASK: u32 = 31;
const EPOCH_SHIFT: u32 = 10;
/// The bits of [`SlotEntry::word`] that describe the node (not the status): facts and level.
const FACTS_MASK: u32 = ((1 << EPOCH_SHIFT) - 1) & !KIND_MASK;
/// Bits of an epoch a [`SlotEntry`] keeps.
const STAT_EPOCH_MASK: u64 = (1 << (32 - EPOCH_SHIFT)) - 1;

const _: () = assert!(FACTS_MASK == Facts::all().bits() | LEVEL_MASK << LEVEL_SHIFT);
const _: () = assert!(Facts::all().bits() & KIND_MASK == 0);

pub(super) const NO_ENTRY: SlotEntry = SlotEntry {
    tag: 0,
    checked: u32::MAX,
    smax: 0.0,
    word: 0,
};

impl SlotEntry {
    /// The entry of node `tag` (see [`info_tag`]) at `level`, with no facts and no status.
    #[inline(always)]
    fn new(tag: u32, level: u8) -> SlotEntry {
        SlotEntry {
            tag,
            word: (level as u32) << LEVEL_SHIFT,
            ..NO_ENTRY
        }
    }

    #[inline(always)]
    fn facts(&self) -> Facts {
        Facts::from_bits_truncate(self.word)
    }

    #[inline(always)]
    fn insert(&mut self, f: Facts) {
        self.word |= f.bits();
    }

    #[inline(always)]
    fn kind(&self) -> Kind {
        match self.word & KIND_MASK {
            0 => Kind::Keep,
            1 => Kind::Split,
            2 => Kind::Merge,
            _ => Kind::MergeOut,
        }
    }

    /// Records a status of `kind` evaluated in the epoch whose low bits are `epoch`.
    #[inline(always)]
    fn set_status(&mut self, kind: Kind, epoch: u32) {
        self.word = (self.word & FACTS_MASK) | kind as u32 | epoch << EPOCH_SHIFT;
    }

    #[inline(always)]
    pub(super) fn level(&self) -> u8 {
        ((self.word >> LEVEL_SHIFT) & LEVEL_MASK) as u8
    }

    #[inline(always)]
    pub(super) fn epoch(&self) -> u32 {
        self.word >> EPOCH_SHIFT
    }

    /// Forgets the status.
    #[inline(always)]
    fn forget(&mut self) {
        self.word &= FACTS_MASK;
    }
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

impl Selector {
    /// The cached facts of node `n` in `slot`, filled or refreshed as needed.
    #[inline(always)]
    pub(super) fn info_of(
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
            *e = SlotEntry::new(tag, forest.level(n.id));
        }
        // the finest level has no detail nodes: nothing to look up (such leaves are never split)
        if !e.facts().contains(Facts::USABLE) && e.level() < forest.levels {
            let held = buf.generation() as u32;
            if e.checked != held {
                e.checked = held;
                if let Some(m) = buf.subtree_max(n.id) {
                    e.smax = m;
                    e.insert(Facts::PRESENT);
                    if buf.is_usable(n.id) {
                        e.insert(Facts::USABLE);
                    }
                }
            }
        }
        let facts = e.facts();
        SlotInfo {
            smax: e.smax,
            level: e.level(),
            present: facts.contains(Facts::PRESENT),
            usable: facts.contains(Facts::USABLE),
        }
    }

    /// The cached bounding sphere of node `n` in `slot` (after [`Self::info_of`]).
    #[inline(always)]
    pub(super) fn sphere_of(&mut self, mesh: &AdaptiveMesh, slot: usize) -> (DVec3, f64) {
        let e = &mut self.info[slot];
        if !e.facts().contains(Facts::GEO) {
            e.insert(Facts::GEO);
            if slot >= self.geo.len() {
                self.geo
                    .resize(mesh.node_slot_len().max(slot + 1), (Vec3::ZERO, 0.0));
            }
            self.geo[slot] = sphere32(mesh, &mesh.node_verts(slot));
        }
        let (c, r) = self.geo[slot];
        (c.as_dvec3(), r as f64)
    }

    /// Keeps the image weight just computed for `slot`, which [`Self::cached_status`] reads while
    /// the status lasts (the image weight reads vertex values, which the cache does not hold).
    #[inline]
    pub(super) fn keep_weight(&mut self, slot: usize, fac: f64) {
        if self.params.image.is_some() {
            if slot >= self.wt.len() {
                self.wt.resize(slot + 1, 1.0);
            }
            self.wt[slot] = fac as f32;
        }
    }

    /// Records the status just evaluated for `slot` (see [`Self::eval`]).
    #[inline]
    pub(super) fn remember(&mut self, slot: usize, st: Status) {
        if slot >= self.info.len() {
            self.info.resize(slot + 1, NO_ENTRY);
        }
        let kind = match st {
            Status::Keep => Kind::Keep,
            Status::Split(_) => Kind::Split,
            Status::Merge(e) if e == OUTSIDE => Kind::MergeOut,
            Status::Merge(_) => Kind::Merge,
        };
        let epoch = self.stat_epoch();
        self.info[slot].set_status(kind, epoch);
    }

    /// The status an entry with a current epoch keeps, its priority computed again from the
    /// entry's facts as [`Self::eval_cert`] computed it (the same operations on the same values).
    #[inline]
    pub(super) fn cached_status(
        &self,
        cx: &FrameCtx,
        levels: u8,
        slot: usize,
        e: &SlotEntry,
    ) -> Status {
        let kind = e.kind();
        match kind {
            Kind::Keep => return Status::Keep,
            Kind::MergeOut => return Status::Merge(OUTSIDE),
            Kind::Split | Kind::Merge => {}
        }
        let prio = if cx.mode == Mode::Complete {
            if kind == Kind::Split {
                (levels - e.level()) as f64
            } else {
                0.0
            }
        } else {
            debug_assert!(
                e.facts().contains(Facts::GEO),
                "a split or merge status has its sphere"
            );
            let (c, r) = self.geo[slot];
            let fac = if self.params.image.is_some() {
                self.wt[slot] as f64
            } else {
                self.weight(e.facts().contains(Facts::PRESENT).then_some(e.smax))
            };
            cx.view.error_px(c.as_dvec3(), 2.0 * r as f64) * fac
        };
        if kind == Kind::Split {
            Status::Split(prio)
        } else {
            Status::Merge(prio)
        }
    }

    /// Forgets the status recorded for `slot`.
    #[inline]
    pub(super) fn forget(&mut self, slot: u32) {
        if (slot as usize) < self.info.len() {
            self.info[slot as usize].forget();
        }
    }

    /// Forgets all that any entry knows of nodes `ids` (their metadata changed), whichever slot
    /// holds it, live or free: one pass over the entries. `wide`: the forest's ids do not fit the
    /// tags, whose entries are filled again at every use anyway.
    pub(super) fn reset_nodes(&mut self, ids: &rustc_hash::FxHashSet<TetId>, wide: bool) {
        if wide {
            return;
        }
        let tags: rustc_hash::FxHashSet<u32> = ids.iter().map(|&id| info_tag(id, false)).collect();
        for s in 0..self.info.len() {
            if tags.contains(&self.info[s].tag) {
                self.info[s] = NO_ENTRY;
            }
        }
    }

    /// Forgets every remembered status.
    pub(super) fn forget_all(&mut self) {
        for i in 0..self.info.len() {
            self.info[i].forget();
        }
    }

    /// The low bits of `epoch + 1`, as [`SlotEntry`] keeps them.
    #[inline]
    pub(super) fn stat_epoch(&self) -> u32 {
        ((self.epoch + 1) & STAT_EPOCH_MASK) as u32
    }

    /// Moves to a new epoch (every remembered status is stale).
    pub(super) fn bump_epoch(&mut self) {
        self.epoch += 1;
        if self.stat_epoch() == 0 {
            // the bits wrapped: forget everything rather than trust an entry that many epochs old
            self.forget_all();
            self.epoch += 1;
        }
    }

    /// Asks the CPU for the cache lines an evaluation of `slot` reads first: its node, entry and
    /// sphere. The loops over listed slots (scattered over the arrays) issue it a few slots ahead,
    /// so that the misses overlap. The certificate arrays are left out: prefetching them too cost
    /// more than it saved.
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
    pub(super) fn prefetch_slots(&self, mesh: &AdaptiveMesh, slots: &[u32], k: usize, n: usize) {
        for i in k..k + n {
            if let Some(&s) = slots.get(i) {
                self.prefetch_slot(mesh, s as usize);
            }
        }
    }
}
