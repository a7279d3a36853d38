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
/// stored, since these entries are most of the selector's memory. The node's tag (its id plus one,
/// 40 bits) is split like a mesh node's id: a low word and the high bits of `checked`.
#[derive(Debug, Clone, Copy)]
pub(super) struct SlotEntry {
    /// The low 32 bits of the node's tag ([`info_tag`]; tag 0: none).
    tag_lo: u32,
    /// From the low bits: the check stamp ([`Selector::check_stamp`], [`CHECK_BITS`] bits; 0:
    /// never) when presence and usability were looked up, then the tag's bits from 32 up.
    checked: u32,
    smax: f32,
    /// From the low bits: the status's [`Kind`] (2 bits), the node's [`Facts`] (3 bits), its
    /// level (5 bits from [`LEVEL_SHIFT`]) and the status's epoch (from [`EPOCH_SHIFT`]: the low
    /// bits of `epoch + 1` when it was evaluated; 0: none).
    word: u32,
}

const _: () = assert!(std::mem::size_of::<SlotEntry>() == 16);

/// Bits of [`SlotEntry::checked`] that hold a check stamp; the others hold a tag's high bits.
const CHECK_BITS: u32 = 24;
const CHECK_MASK: u32 = (1 << CHECK_BITS) - 1;
// every tag fits: ids are below the mesh's MAX_TETS, and tags (id + 1) at most MAX_TETS - 1
const _: () = assert!(crate::mesh::MAX_TETS <= 1 << (64 - CHECK_BITS));
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
    tag_lo: 0,
    checked: 0,
    smax: 0.0,
    word: 0,
};

impl SlotEntry {
    /// The entry of node `tag` (see [`info_tag`]) at `level`, with no facts, no status and no
    /// check.
    #[inline(always)]
    fn new(tag: u64, level: u8) -> SlotEntry {
        debug_assert!(tag < 1 << (64 - CHECK_BITS), "tag {tag} too wide");
        SlotEntry {
            tag_lo: tag as u32,
            checked: ((tag >> 32) as u32) << CHECK_BITS,
            word: (level as u32) << LEVEL_SHIFT,
            ..NO_ENTRY
        }
    }

    /// The tag of the node the entry describes (0: none).
    #[inline(always)]
    fn tag(&self) -> u64 {
        self.tag_lo as u64 | ((self.checked >> CHECK_BITS) as u64) << 32
    }

    /// Whether the entry describes node `id`.
    #[inline(always)]
    fn holds(&self, id: TetId) -> bool {
        self.tag() == info_tag(id)
    }

    /// The check stamp of the last lookup of presence and usability (0: none).
    #[inline(always)]
    fn check(&self) -> u32 {
        self.checked & CHECK_MASK
    }

    #[inline(always)]
    fn set_check(&mut self, stamp: u32) {
        debug_assert!(stamp <= CHECK_MASK);
        self.checked = (self.checked & !CHECK_MASK) | stamp;
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

/// The name of node `id` in a [`SlotEntry`]: the id plus one, never 0, exact for every id of a
/// forest the mesh holds (40 bits, [`MAX_TETS`](crate::mesh::MAX_TETS)).
#[inline(always)]
fn info_tag(id: TetId) -> u64 {
    id + 1
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
        let e = &mut self.info[slot];
        if !e.holds(n.id) {
            *e = SlotEntry::new(info_tag(n.id), forest.level(n.id));
        }
        // the finest level has no detail nodes: nothing to look up (such leaves are never split)
        if !e.facts().contains(Facts::USABLE) && e.level() < forest.levels {
            let held = self.check_stamp(buf.generation());
            let e = &mut self.info[slot];
            if e.check() != held {
                e.set_check(held);
                if let Some(m) = buf.subtree_max(n.id) {
                    e.smax = m;
                    e.insert(Facts::PRESENT);
                    if buf.is_usable(n.id) {
                        e.insert(Facts::USABLE);
                    }
                }
            }
        }
        let e = &self.info[slot];
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
    /// holds it, live or free: one pass over the entries.
    pub(super) fn reset_nodes(&mut self, ids: &rustc_hash::FxHashSet<TetId>) {
        let tags: rustc_hash::FxHashSet<u64> = ids.iter().map(|&id| info_tag(id)).collect();
        for s in 0..self.info.len() {
            if tags.contains(&self.info[s].tag()) {
                self.info[s] = NO_ENTRY;
            }
        }
    }

    /// The check stamp that stands for buffer generation `generation` in the entries (see
    /// [`SlotEntry::check`]): a new one whenever the generation differs from the last one asked
    /// for, so an entry checked under another generation is looked up again. Stamps count up
    /// from 1; when they run out (2^24 - 1 changes of generation), every entry's is cleared and
    /// they start again, so a stamp never names two generations.
    #[inline(always)]
    fn check_stamp(&mut self, generation: u64) -> u32 {
        if generation != self.check_gen {
            self.next_check(generation);
        }
        self.check
    }

    #[cold]
    fn next_check(&mut self, generation: u64) {
        self.check_gen = generation;
        self.check += 1;
        if self.check > CHECK_MASK {
            for i in 0..self.info.len() {
                self.info[i].set_check(0);
            }
            self.check = 1;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::MAX_TETS;
    use crate::select::{SelectParams, Tolerance};

    /// Ids past 2^32 (a 1025³ box has 7.4e9 tets): a slot's entry made for one is found again by
    /// that id, and by no other id, in particular none that shares its low 32 bits; a check stamp
    /// leaves the tag alone and the other way round. No forest that large is made.
    #[test]
    fn entries_name_ids_past_32_bits() {
        let ids = [
            0,
            1,
            u32::MAX as TetId - 1,
            u32::MAX as TetId,
            1 << 32,
            (1 << 32) + 5,
            (7 << 32) + 5,
            MAX_TETS - 2,
        ];
        for &id in &ids {
            let mut e = SlotEntry::new(info_tag(id), 9);
            e.insert(Facts::GEO);
            assert!(e.holds(id), "{id}");
            assert!(!NO_ENTRY.holds(id), "{id}");
            for &other in &ids {
                assert_eq!(e.holds(other), other == id, "{id} vs {other}");
            }
            for stamp in [1, 77, CHECK_MASK] {
                e.set_check(stamp);
                assert!(e.holds(id) && e.check() == stamp, "{id}: {stamp}");
                assert_eq!((e.level(), e.facts()), (9, Facts::GEO));
            }
            e.set_check(0);
            assert!(e.holds(id) && e.check() == 0);
        }
    }

    fn selector() -> Selector {
        Selector::new(SelectParams::new(Tolerance::Pixels(1.0), [0.0, 1.0]))
    }

    /// Replaced nodes past 2^32 drop their own entries only.
    #[test]
    fn reset_nodes_past_32_bits() {
        let ids: [TetId; 4] = [5, (1 << 32) + 5, (2 << 32) + 5, MAX_TETS - 2];
        let mut sel = selector();
        for &id in &ids {
            sel.info.push(SlotEntry::new(info_tag(id), 3));
        }
        let gone: rustc_hash::FxHashSet<TetId> =
            [(1 << 32) + 5, MAX_TETS - 2].into_iter().collect();
        sel.reset_nodes(&gone);
        for (s, &id) in ids.iter().enumerate() {
            assert_eq!(sel.info[s].holds(id), !gone.contains(&id), "{id}");
        }
    }

    /// Check stamps: one per generation asked for in a row, never 0, and when they run out every
    /// entry's is cleared (tags kept) before they start again at 1.
    #[test]
    fn check_stamps_wrap_clean() {
        let mut sel = selector();
        let a = sel.check_stamp(0);
        assert_eq!((a, sel.check_stamp(0)), (1, 1));
        assert_eq!((sel.check_stamp(4), sel.check_stamp(4)), (2, 2));
        let id = (3 << 32) + 1;
        sel.info.push(SlotEntry::new(info_tag(id), 2));
        sel.check = CHECK_MASK - 1;
        let last = sel.check_stamp(5);
        assert_eq!(last, CHECK_MASK);
        sel.info[0].set_check(last);
        assert_eq!(sel.check_stamp(6), 1);
        assert!(sel.info[0].holds(id) && sel.info[0].check() == 0);
    }
}
