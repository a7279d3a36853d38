//! Candidates: the queues a sweep fills, the candidate list kept across sweeps, and parking.

use super::criteria::Status;
use super::{FrameCtx, Selector};
use crate::mesh::AdaptiveMesh;
use bitflags::bitflags;
use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;
use tetwave_protocol::TetId;

/// A candidate: priority, tet id, the node slot it had when pushed (a hint) and the selector's tag
/// then (see `Selector::tag`); only the first two are ordered.
#[derive(Debug, Clone, Copy)]
pub(super) struct Cand(
    pub(super) f64,
    pub(super) TetId,
    pub(super) u32,
    pub(super) u32,
);
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
pub(super) struct CandQueue<T> {
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
    pub(super) fn push(&mut self, x: T) {
        if self.sorted {
            self.heap.push(x);
        } else {
            self.bulk.push(x);
        }
    }

    #[inline]
    pub(super) fn pop(&mut self) -> Option<T> {
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

    pub(super) fn clear(&mut self) {
        self.bulk.clear();
        self.heap.clear();
        self.sorted = false;
    }

    /// Moves every item to `out`, in no particular order (nothing is sorted).
    pub(super) fn drain_into(&mut self, out: &mut Vec<T>) {
        out.append(&mut self.bulk);
        out.extend(self.heap.drain());
        self.sorted = false;
    }

    pub(super) fn len(&self) -> usize {
        self.bulk.len() + self.heap.len()
    }

    pub(super) fn capacity(&self) -> usize {
        self.bulk.capacity() + self.heap.capacity()
    }

    pub(super) fn is_empty(&self) -> bool {
        self.bulk.is_empty() && self.heap.is_empty()
    }
}

bitflags! {
    /// What the candidate list knows of one slot (`Selector::slot_flags`).
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub(super) struct SlotFlags: u8 {
        /// On the candidate list.
        const LISTED = 1;
        /// A listed merge candidate the last batch settled by owners outside it (see
        /// [`AdaptiveMesh::batch_held`]): the listed scan leaves it out until one of those owners
        /// is queued to merge or changes, and it is refused meanwhile.
        const PARKED = 2;
        /// Has slots parked on it (exactly the keys of `Selector::waiters`): lets
        /// `Selector::wake` skip the map for the others.
        const WAITED = 4;
    }
}

/// One byte per slot, as the selector's memory figures count it.
const _: () = assert!(std::mem::size_of::<SlotFlags>() == 1);

impl Selector {
    /// Queues a candidate, its priority rounded to an `f32`: the order remembered statuses gave
    /// when they kept the priority, kept so that runs reproduce the documented results.
    #[inline]
    pub(super) fn push(&mut self, id: TetId, slot: u32, s: Status) {
        let q = |e: f64| e as f32 as f64;
        match s {
            Status::Split(e) => self.splits.push(Cand(q(e), id, slot, self.tag)),
            Status::Merge(e) => self.merges.push(Reverse(Cand(q(e), id, slot, self.tag))),
            Status::Keep => {}
        }
    }

    /// Moves [`Self::tag`] on if the mesh changed since it was set.
    #[inline]
    pub(super) fn retag(&mut self, mesh: &AdaptiveMesh) {
        if mesh.change_seq() != self.tag_seq {
            self.tag_seq = mesh.change_seq();
            self.tag = self.tag.wrapping_add(1);
        }
    }

    /// Whether a candidate pushed with `tag` into slot `slot` still has its status.
    #[inline]
    pub(super) fn trusted(&mut self, mesh: &AdaptiveMesh, tag: u32, slot: u32) -> bool {
        self.retag(mesh);
        !self.reference && tag == self.tag && slot != u32::MAX
    }

    #[inline]
    pub(super) fn list_add(&mut self, slot: usize) {
        if slot >= self.slot_flags.len() {
            self.slot_flags.resize(slot + 1, SlotFlags::empty());
        }
        if !self.slot_flags[slot].contains(SlotFlags::LISTED) {
            self.slot_flags[slot] |= SlotFlags::LISTED;
            self.list.push(slot as u32);
        }
    }

    pub(super) fn list_clear(&mut self) {
        for &s in &self.list {
            self.slot_flags[s as usize] = SlotFlags::empty();
        }
        self.list.clear();
        self.list_epoch = None;
        self.clear_waiters();
    }

    /// Forgets every parked slot's owners (the parked flags are the caller's to clear).
    pub(super) fn clear_waiters(&mut self) {
        for &o in self.waiters.keys() {
            self.slot_flags[o as usize].remove(SlotFlags::WAITED);
        }
        self.waiters.clear();
    }

    /// Parks the listed candidates the last merge batch settled by owners outside it.
    pub(super) fn park(&mut self, mesh: &AdaptiveMesh) {
        for &(slot, owners) in mesh.batch_held() {
            let s = slot as usize;
            if s < self.slot_flags.len() && self.slot_flags[s].contains(SlotFlags::LISTED) {
                self.slot_flags[s] |= SlotFlags::PARKED;
                for o in owners {
                    if o != u32::MAX {
                        self.waiters.entry(o).or_default().push(slot);
                        let o = o as usize;
                        if o >= self.slot_flags.len() {
                            self.slot_flags.resize(o + 1, SlotFlags::empty());
                        }
                        self.slot_flags[o] |= SlotFlags::WAITED;
                    }
                }
            }
        }
    }

    /// Clears `slot`'s parked flag; whether it was parked.
    #[inline]
    pub(super) fn unpark(&mut self, slot: u32) -> bool {
        match self.slot_flags.get(slot as usize) {
            Some(&f) if f.contains(SlotFlags::PARKED) => {
                self.slot_flags[slot as usize] = f - SlotFlags::PARKED;
                true
            }
            _ => false,
        }
    }

    /// Unparks the slots parked on `owner` (it changed, or is queued to merge); with `now`, the
    /// view of a listed scan, queues them too (the scan may have passed them), and so on for
    /// the slots parked on those.
    #[inline]
    pub(super) fn wake(&mut self, owner: u32, now: Option<(&AdaptiveMesh, &FrameCtx)>) {
        if self
            .slot_flags
            .get(owner as usize)
            .is_some_and(|&f| f.contains(SlotFlags::WAITED))
        {
            self.wake_parked(owner, now);
        }
    }

    /// [`Self::wake`] for an owner flagged [`SlotFlags::WAITED`].
    #[inline(never)]
    fn wake_parked(&mut self, owner: u32, now: Option<(&AdaptiveMesh, &FrameCtx)>) {
        let mut owners = vec![owner];
        while let Some(o) = owners.pop() {
            let Some(parked) = self.waiters.remove(&o) else {
                continue;
            };
            self.slot_flags[o as usize].remove(SlotFlags::WAITED);
            for &a in &parked {
                if !self.unpark(a) {
                    continue;
                }
                if let Some((mesh, cx)) = now {
                    let s = self.eval(mesh, cx, a as usize);
                    if let (Status::Merge(_), Some(n)) = (s, mesh.red_node(a as usize)) {
                        self.push(n.id, a, s);
                        owners.push(a);
                    }
                }
            }
        }
    }
}
