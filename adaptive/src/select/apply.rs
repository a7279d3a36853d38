//! Applying the queued candidates: merges in batches, then splits, within a frame's budget.

use super::candidates::Cand;
use super::criteria::Status;
use super::{FrameCtx, FrameStats, Selector};
use crate::mesh::{AdaptiveMesh, MeshError};
use std::cmp::Reverse;
use std::time::{Duration, Instant};

/// Merges handed to one [`AdaptiveMesh::coarsen_batch`] at most, when a batch is cut into chunks.
const MERGE_CHUNK: usize = 256;
/// Under a time budget only, merge candidates taken in one uncut batch when at most this many wait
/// and at least half of the frame is left (or what is left covers them, see [`uncut_batch`]), and
/// the size of a chunk taken early in a frame when more wait (see `Selector::apply_merges`). Large
/// enough that a deep mesh keeps up under an interactive budget (chunks refuse merges a whole batch
/// allows), small enough to cap how far one batch can overrun a frame.
const WHOLE_MERGES: usize = 4096;
/// [`Selector::merge_cost`] before any uncut batch was timed: one microsecond per candidate, a
/// pessimistic guess, so that late in a frame an untimed batch is cut rather than let run over.
pub(super) const INITIAL_MERGE_COST: f64 = 1e-6;

/// Whether `queued` merge candidates go in one uncut batch ([`Selector::apply_merges`], no
/// operation budget): always without a time budget (`left`, the time left in the frame: `None`);
/// under one, when at most [`WHOLE_MERGES`] wait and either half of the frame is left (`early`) or
/// what is left covers their expected time at `cost` seconds per candidate. The last case stops
/// the second half of a frame from cutting into [`MERGE_CHUNK`]-candidate chunks a batch that
/// fits: chunks refuse the merges that hold only together, and a sweep whose batches were cut
/// takes one more sweep to consolidate.
fn uncut_batch(queued: usize, early: bool, left: Option<Duration>, cost: f64) -> bool {
    match left {
        None => true,
        Some(left) => {
            queued <= WHOLE_MERGES && (early || left.as_secs_f64() >= cost * queued as f64)
        }
    }
}

/// How far one call of [`Selector::apply_merges`] or [`Selector::apply_splits`] may go.
#[derive(Debug, Clone, Copy)]
pub(super) struct Limits {
    /// Stop once the frame's operations reach this.
    pub(super) max_ops: usize,
    /// Stop at this time; `None`: no time budget.
    pub(super) deadline: Option<Instant>,
    /// Merges: until this time a batch may be taken uncut (or a large chunk) however long it
    /// takes (see [`uncut_batch`]).
    pub(super) whole_until: Option<Instant>,
}

impl Selector {
    /// Merges the queued merge candidates (smallest error first when cut into chunks) in batches
    /// through [`AdaptiveMesh::coarsen_batch_at`], within `lim`; `ops` counts the frame's
    /// operations. The parents of held merges are queued in turn.
    pub(super) fn apply_merges(
        &mut self,
        mesh: &mut AdaptiveMesh,
        cx: &FrameCtx,
        lim: Limits,
        ops: &mut usize,
        st: &mut FrameStats,
    ) -> Result<(), MeshError> {
        let Limits {
            max_ops,
            deadline,
            whole_until,
        } = lim;
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
            // sweep and attempts repeated there. Otherwise chunks, with a clock check between them.
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
                } else if let (Status::Merge(_), s) = self.status_of(mesh, cx, id, hint) {
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
            let held = mesh.coarsen_batch_at(&batch, &slots, cx.buf);
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
                        let (s, ps) = self.status_of(mesh, cx, p, u32::MAX);
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

    /// Splits the queued split candidates, largest error first, within `lim` (`whole_until` is not
    /// used); `ops` counts the frame's operations. The children of a split are queued in turn.
    pub(super) fn apply_splits(
        &mut self,
        mesh: &mut AdaptiveMesh,
        cx: &FrameCtx,
        lim: Limits,
        ops: &mut usize,
        st: &mut FrameStats,
    ) -> Result<(), MeshError> {
        let Limits {
            max_ops, deadline, ..
        } = lim;
        while *ops < max_ops {
            // a split (with its closure) costs far more than a clock read: read before each
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
                && !matches!(self.status_of(mesh, cx, id, hint).0, Status::Split(_))
            {
                continue;
            }
            if let Some(max) = self.params.max_tets {
                // the red split adds 7 leaves; its closure may add more (domino splits), which
                // is undone below if it goes over
                if mesh.leaf_count() + 7 > max {
                    self.refuse_splits();
                    break;
                }
            }
            *ops += 1;
            let t = Instant::now();
            let seq = mesh.change_seq();
            mesh.refine(id, cx.buf)?;
            if self
                .params
                .max_tets
                .is_some_and(|max| mesh.leaf_count() > max)
            {
                undo_split(mesh, id, seq, cx.buf)?;
                st.op_time += t.elapsed();
                self.refuse_splits();
                break;
            }
            st.op_time += t.elapsed();
            st.splits += 1;
            self.sweep_changes += 1;
            // its children may want splitting too (ROAM-style), without waiting for the next sweep
            let forest = mesh.forest();
            for i in 0..8 {
                let c = forest.child(id, i);
                let (s, cs) = self.status_of(mesh, cx, c, u32::MAX);
                if let Status::Split(_) = s {
                    self.push(c, cs, s);
                }
            }
        }
        Ok(())
    }
}

/// Undoes the split of `id` made after change sequence `seq`, with the red splits its closure
/// forced (domino splits): all merged in one batch, which allows the merges that hold only
/// together (`id` alone is forced by its neighbours' splits, they by `id`'s).
fn undo_split(
    mesh: &mut AdaptiveMesh,
    id: tetwave_protocol::TetId,
    seq: u64,
    buf: &crate::detail_buffer::DetailBuffer,
) -> Result<(), MeshError> {
    let mut ids: Vec<_> = match mesh.changes_since(seq) {
        Some(ch) => ch
            .iter()
            .filter_map(|c| mesh.red_node(c.slot as usize))
            .filter(|n| !n.leaf)
            .map(|n| n.id)
            .collect(),
        None => vec![id],
    };
    ids.sort_unstable();
    ids.dedup();
    mesh.coarsen_batch(&ids, buf)?;
    Ok(())
}

impl Selector {
    /// The leaf budget ([`super::SelectParams::max_tets`]) refuses the split candidates left:
    /// they are dropped for this sweep (a later sweep finds them again, and they are split once
    /// merges have made room), and the frame reports that the budget binds.
    fn refuse_splits(&mut self) {
        self.budget_bound = true;
        self.splits.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

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
}
