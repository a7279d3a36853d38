//! Applying arrived coefficients and node metadata to the mesh in place.

use super::node::NodeFlags;
use super::{AdaptiveMesh, NONE};
use crate::detail_buffer::{Arrivals, DetailBuffer};

impl AdaptiveMesh {
    /// Applies coefficients and node metadata that arrived in `buf` (as recorded in `arrivals`):
    /// present vertices owning a new coefficient are recomputed in place, then every present vertex
    /// whose prediction reads a changed one (level by level); children of arrived nodes get their `empty`
    /// flags. Returns the number of vertex values that changed (a zero detail, the common case
    /// deep in a smooth field, changes none: what reads values need not look again). With the
    /// axes predictor values are brought up to date by [`Self::refresh_values`] instead (0 here).
    pub fn apply_arrivals(&mut self, buf: &DetailBuffer, arrivals: &Arrivals) -> usize {
        let nbase = self.keys.base_vertex_count();
        if self.axes.is_some() {
            return self.apply_arrivals_axes(buf, arrivals);
        }
        let mut dirty: Vec<u32> = Vec::new();
        for &key in &arrivals.keys {
            if let Some(s) = self.slot_of_key(key).filter(|&s| s as u64 >= nbase) {
                if self.resynth(buf, s) {
                    dirty.push(s);
                }
            }
        }
        let mut count = dirty.len();
        if dirty.iter().any(|&s| self.vdeps[s as usize] > 0) {
            let lo = dirty
                .iter()
                .map(|&s| self.vlevel[s as usize])
                .min()
                .unwrap_or(0);
            let mut mark = vec![false; self.vkey.len()];
            for &s in &dirty {
                mark[s as usize] = true;
            }
            let mut by_level: Vec<Vec<u32>> = vec![Vec::new(); self.forest.levels as usize + 1];
            for s in 0..self.vkey.len() {
                if self.vref[s] != 0 && self.vlevel[s] > lo {
                    by_level[self.vlevel[s] as usize].push(s as u32);
                }
            }
            for lv in by_level {
                for s in lv {
                    let (ends, src) = (self.vends[s as usize], self.vsrc[s as usize]);
                    // every point the prediction reads is an end, a source, or an end of one of
                    // those (marked already: they are coarser)
                    let read_changed = ends
                        .into_iter()
                        .chain(src)
                        .any(|d| d != NONE && mark[d as usize]);
                    if read_changed && self.resynth(buf, s) && !mark[s as usize] {
                        mark[s as usize] = true;
                        count += 1;
                    }
                }
            }
        }
        self.refresh_arrived_nodes(buf, arrivals);
        count
    }

    /// [`Self::apply_arrivals`] with the axes predictor: a coefficient changes vertices far
    /// from its owner (every one whose stencils read it, transitively), so arrivals are only
    /// queued, and [`Self::refresh_values`] marks where values may have changed and recomputes
    /// the present vertices there, once per frame rather than once per batch (and off the
    /// network side). Values must be refreshed before they are read or new vertices made.
    fn apply_arrivals_axes(&mut self, buf: &DetailBuffer, arrivals: &Arrivals) -> usize {
        self.axes
            .as_mut()
            .expect("axes values")
            .arrived(&arrivals.nodes);
        self.refresh_arrived_nodes(buf, arrivals);
        0
    }

    /// Brings every present vertex's value up to the coefficients `buf` holds; returns how many
    /// changed. Only meshes with the axes predictor defer this (see
    /// [`Self::apply_arrivals`]); for the others values are always current and this is free.
    pub fn refresh_values(&mut self, buf: &DetailBuffer) -> usize {
        let Some(axes) = self.axes.as_mut() else {
            return 0;
        };
        axes.mark_arrived();
        if !axes.any_stale() {
            return 0;
        }
        let nbase = self.keys.base_vertex_count() as usize;
        let mut count = 0;
        for s in nbase..self.vkey.len() {
            if self.vref[s] != 0
                && self.axes.as_ref().is_some_and(|a| a.stale(self.vpoint[s]))
                && self.resynth(buf, s as u32)
            {
                count += 1;
            }
        }
        self.axes.as_mut().expect("axes values").refreshed();
        count
    }

    /// Recomputes vertex `s`'s value from the coefficients held; whether it changed (bit for bit).
    fn resynth(&mut self, buf: &DetailBuffer, s: u32) -> bool {
        let v = self.synth_value(buf, s);
        let old = std::mem::replace(&mut self.vval[s as usize], v);
        old.to_bits() != v.to_bits()
    }

    /// Whether every present vertex's value reflects the coefficients held (always, but with the
    /// axes predictor between arrivals and [`Self::refresh_values`]).
    pub fn values_current(&self) -> bool {
        !self.axes.as_ref().is_some_and(|a| a.behind())
    }

    /// Children of arrived nodes get their `empty` flags.
    fn refresh_arrived_nodes(&mut self, buf: &DetailBuffer, arrivals: &Arrivals) {
        for &id in &arrivals.nodes {
            if let Some(slot) = self.find(id) {
                if !self.nodes[slot as usize].is_leaf() {
                    self.refresh_empty(slot, buf);
                }
            }
        }
    }

    fn refresh_empty(&mut self, slot: u32, buf: &DetailBuffer) {
        let n = self.nodes[slot as usize];
        if n.is_leaf() {
            return;
        }
        for i in 0..8u32 {
            let c = (n.children + i) as usize;
            let empty = n.flags.contains(NodeFlags::EMPTY) || buf.child_empty(n.id(), i as usize);
            let old = self.nodes[c].flags.contains(NodeFlags::EMPTY);
            if empty != old {
                self.nodes[c].flags.toggle(NodeFlags::EMPTY);
                let block = self.nodes[c].children;
                self.log_change(c as u32, block);
                self.refresh_empty(c as u32, buf);
            }
        }
    }
}
