//! The log of structural changes (splits, merges, `empty` flips) that incremental consumers read,
//! and the identity of a mesh object.

use super::AdaptiveMesh;
use std::sync::atomic::{AtomicU64, Ordering};

/// A node slot whose structure changed: split (`block` = its new children), merged (`block` = its
/// former children, now free), or whose `empty` flag flipped (`block` = its children or `u32::MAX`).
/// The slots whose selection status may have changed are `slot`, the 8 slots of `block` and the
/// slot of the parent of the node in `slot` (if the node that changed has gone since, so has its
/// parent's split, which is recorded too).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SlotChange {
    pub slot: u32,
    pub block: u32,
}

/// Most [`SlotChange`]s kept unread (beyond, the log restarts and a reader rescans).
const MAX_CHANGES: usize = 1 << 16;

static NEXT_UID: AtomicU64 = AtomicU64::new(1);

#[derive(Debug)]
pub(super) struct MeshUid(u64);

impl MeshUid {
    pub(super) fn new() -> Self {
        MeshUid(NEXT_UID.fetch_add(1, Ordering::Relaxed))
    }
}

impl Clone for MeshUid {
    fn clone(&self) -> Self {
        MeshUid::new()
    }
}

impl AdaptiveMesh {
    /// Identity of this mesh object: unique per process, a clone gets a new one.
    pub(crate) fn uid(&self) -> u64 {
        self.uid.0
    }

    /// Sequence number after the last recorded [`SlotChange`].
    pub fn change_seq(&self) -> u64 {
        self.changes_start + self.changes.len() as u64
    }

    /// The structural changes since sequence number `seq` (from [`Self::change_seq`]); `None` when
    /// some of them were dropped (the log is bounded; the selector trims what it has read).
    pub fn changes_since(&self, seq: u64) -> Option<&[SlotChange]> {
        let i = seq.checked_sub(self.changes_start)? as usize;
        self.changes.get(i..)
    }

    /// Forgets the changes before sequence number `seq`.
    pub(crate) fn trim_changes(&mut self, seq: u64) {
        if seq >= self.change_seq() {
            self.changes_start = self.change_seq();
            self.changes.clear();
        } else if seq > self.changes_start {
            self.changes.drain(..(seq - self.changes_start) as usize);
            self.changes_start = seq;
        }
    }

    #[inline]
    pub(super) fn log_change(&mut self, slot: u32, block: u32) {
        if self.changes.len() >= MAX_CHANGES {
            self.changes_start += self.changes.len() as u64;
            self.changes.clear();
        }
        self.changes.push(SlotChange { slot, block });
    }
}
