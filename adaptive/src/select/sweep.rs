//! Sweeps: the frame loop, the full scan and the listed (incremental) scans.

use super::apply::Limits;
use super::cache::PREFETCH;
use super::candidates::SlotFlags;
use super::certificates::Kinetic;
use super::criteria::Status;
use super::{Budget, FrameCtx, FrameStats, Mode, Selector, SCAN_CHUNK};
use crate::detail_buffer::DetailBuffer;
use crate::mesh::{AdaptiveMesh, MeshError};
use std::time::Instant;
use tetwave_protocol::view::{Camera, View};

/// Sweeps one unbudgeted [`Selector::converge`] may take before giving up.
const MAX_SWEEPS: usize = 256;

impl Selector {
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

    pub(super) fn run(
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
            st.budget_bound = self.budget_bound;
            st.elapsed = start.elapsed();
            return Ok(st);
        }
        let view = View::new(cam, self.params.tol);
        let cx = FrameCtx {
            buf,
            view: &view,
            mode,
        };
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
                self.budget_bound = false;
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
                    if self.kin_active(mode) {
                        self.kin.begin_pass();
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
                        self.kin.stop();
                    }
                }
            }
            // scan
            let len = mesh.node_slot_len();
            let have_work = !self.splits.is_empty() || !self.merges.is_empty();
            let scan_until = if have_work { scan_deadline } else { deadline };
            self.retag(mesh);
            if self.sweep_listed {
                self.scan_listed(mesh, &cx, scan_until, &mut st);
            }
            while self.cursor < len {
                let end = (self.cursor + SCAN_CHUNK).min(len);
                for slot in self.cursor..end {
                    if self.reference {
                        let Some(n) = mesh.red_node(slot) else {
                            continue;
                        };
                        let s = self.status_uncached(mesh, &cx, &n);
                        self.push(n.id, u32::MAX, s);
                    } else {
                        let s = if self.kin_active(mode) {
                            self.eval_kin(mesh, &cx, slot)
                        } else {
                            self.eval(mesh, &cx, slot)
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
                        && !self.kin.in_pass()
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
                let lim = Limits {
                    max_ops: half,
                    deadline: merge_deadline,
                    whole_until: scan_deadline,
                };
                self.apply_merges(mesh, &cx, lim, &mut ops, &mut st)?;
            }
            let lim = Limits {
                max_ops: budget.max_ops,
                deadline,
                whole_until: None,
            };
            self.apply_splits(mesh, &cx, lim, &mut ops, &mut st)?;
            if !consolidating || sweep_done {
                let lim = Limits {
                    max_ops: merge_ops,
                    deadline: merge_deadline,
                    whole_until: scan_deadline,
                };
                self.apply_merges(mesh, &cx, lim, &mut ops, &mut st)?;
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
        st.budget_bound = self.budget_bound;
        st.pending = self.splits.len() + self.merges.len();
        st.elapsed = start.elapsed();
        Ok(st)
    }

    /// Queues the slots the mesh changed since the last look (see [`Self::flush_step`]); false
    /// (and the list is no longer complete) when the mesh dropped some of its change log.
    pub(super) fn absorb_changes(&mut self, mesh: &mut AdaptiveMesh) -> bool {
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
            self.kin.stop();
        }
        ok
    }

    /// Looks again at the next `n` slots queued for this sweep (`Self::flushing`): with
    /// certificates, evaluates them (listing candidates); otherwise lists them all. Returns the
    /// slots looked at.
    fn flush_step(&mut self, mesh: &AdaptiveMesh, cx: &FrameCtx, n: usize) -> usize {
        let fl = std::mem::take(&mut self.flushing);
        let end = (self.fcursor + n).min(fl.len());
        let kin = self.kin_active(cx.mode);
        let run = &fl[self.fcursor..end];
        if kin {
            self.prefetch_slots(mesh, run, 0, PREFETCH);
        }
        for (j, &s) in run.iter().enumerate() {
            if kin {
                self.prefetch_slots(mesh, run, j + PREFETCH, 1);
            }
            if !kin || self.eval_kin(mesh, cx, s as usize) != Status::Keep {
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

    /// The scan of a listed sweep, until done or `until`: the slots changed before the sweep, the
    /// due pass, then the listed slots that still are candidates are pushed (the others leave the
    /// list).
    fn scan_listed(
        &mut self,
        mesh: &AdaptiveMesh,
        cx: &FrameCtx,
        until: Option<Instant>,
        st: &mut FrameStats,
    ) {
        loop {
            if !self.flushing.is_empty() {
                st.scanned += self.flush_step(mesh, cx, SCAN_CHUNK);
            } else if self.kin.in_pass() {
                st.scanned += self.due_pass_step(mesh, cx, 8 * SCAN_CHUNK);
            } else if self.lcursor < self.list.len() {
                let end = (self.lcursor + SCAN_CHUNK).min(self.list.len());
                let mut i = self.lcursor;
                let mut end = end;
                self.prefetch_slots(mesh, &self.list, i, PREFETCH);
                while i < end {
                    self.prefetch_slots(mesh, &self.list, i + PREFETCH, 1);
                    let slot = self.list[i] as usize;
                    st.scanned += 1;
                    if self.slot_flags[slot].contains(SlotFlags::PARKED) {
                        i += 1;
                        continue;
                    }
                    let s = self.eval(mesh, cx, slot);
                    if s == Status::Keep {
                        self.slot_flags[slot] &= SlotFlags::WAITED;
                        self.list.swap_remove(i);
                        end = end.min(self.list.len());
                        continue;
                    }
                    let id = mesh.red_node(slot).expect("a candidate is live").id;
                    self.push(id, slot as u32, s);
                    if let Status::Merge(_) = s {
                        self.wake(slot as u32, Some((mesh, cx)));
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
}
