//! A new session's preview phase: coarse copies of the store's coarse nodes
//! ([`tetwave_protocol::store_format::Preview`]), sent as `Preview` batches before any `Nodes`,
//! within a byte budget ([`super::ServeConfig::preview_share`]). The client holds each until the
//! store's own node replaces it, so a thin link shows the whole volume coarsely early and the
//! complete stream still ends exactly at the store's values.
//!
//! Coarse to fine: level by level, within a level by the order's priority (view order: the
//! default view's). The batches are sized in bytes, not nodes, because a coarse level's nodes
//! cost several times a fine level's: the first carries every preview level but the finest (the
//! whole volume, coarsely), and each later one about as many bytes as were sent before it, so
//! what the client holds about doubles with every frame it draws.

use super::config::{Order, ViewTf};
use super::schedule::merged;
use super::state::{ServedPreview, Shared};
use std::sync::Arc;
use tetwave_protocol::wire::{encode, IdRange, ServerMsg};
use tetwave_protocol::TetId;

/// Smallest batch: sent whole even where it goes past a batch's byte target, and the smallest
/// tried when a larger one would overrun the budget.
const MIN_BATCH: usize = 64;

/// What one connection still has to send of the preview.
pub(super) struct PreviewPhase {
    /// Preview node ids in sending order (shared by every connection of the order, or this
    /// connection's, without the nodes its client holds); `None`: every one by increasing id.
    order: Option<Arc<Vec<TetId>>>,
    /// Preview nodes in all.
    len: usize,
    /// The next one to send.
    next: usize,
    /// Bytes of preview blocks sent so far (on a resumed preview, first the estimated bytes of
    /// what the client holds: they count against the budget, and batches go on doubling).
    sent: u64,
}

impl PreviewPhase {
    /// The phase of a session of a store with a preview that holds none of the store's nodes
    /// (`have`) and the preview nodes `previewed` (a cut preview resumes without them); `None`
    /// when there is nothing to send.
    pub(super) fn new(
        s: &Shared,
        order: Order,
        have: &[IdRange],
        previewed: &[IdRange],
    ) -> Option<Self> {
        let p = s.preview.as_ref().filter(|_| have.is_empty())?;
        let mut order = (order == Order::View)
            .then(|| p.view_order.get_or_init(|| Arc::new(view_order(s))).clone());
        let mut sent = 0;
        if !previewed.is_empty() {
            let all = p.nodes.len() as TetId;
            let ranges = merged(previewed, all);
            let held = |id: TetId| {
                let i = ranges.partition_point(|r| r.0 <= id);
                i > 0 && id < ranges[i - 1].1
            };
            let rest: Vec<TetId> = match &order {
                Some(o) => o.iter().copied().filter(|&i| !held(i)).collect(),
                None => (0..all).filter(|&i| !held(i)).collect(),
            };
            order = Some(Arc::new(rest));
            let forest = s.forest();
            let costs = p.level_costs.get_or_init(|| level_costs(p, forest));
            let bytes: f64 = ranges
                .iter()
                .flat_map(|&(a, b)| a..b)
                .map(|i| costs[forest.level(i) as usize])
                .sum();
            sent = bytes as u64;
        }
        let len = order.as_ref().map_or(p.nodes.len(), |o| o.len());
        (len > 0).then_some(PreviewPhase {
            order,
            len,
            next: 0,
            sent,
        })
    }

    /// The next `Preview` frame (of at most `max_nodes` nodes, fewer where the estimate of its
    /// bytes was short by over a quarter; halved while it would overrun the budget, down to
    /// [`MIN_BATCH`]); `None` when the phase is over.
    pub(super) fn next_frame(
        &mut self,
        s: &Shared,
        seq: u64,
        max_nodes: usize,
    ) -> Result<Option<Vec<u8>>, String> {
        let Some(p) = s.preview.as_ref() else {
            return Ok(None);
        };
        let mut k = self.batch_nodes(s, p).min(max_nodes.max(1));
        // the first batch is whole levels; a later one aims at the bytes sent so far
        let target = (self.sent > 0).then_some(self.sent);
        let mut resized = 0;
        while k > 0 {
            let take = self.next..self.next + k;
            let nodes: Vec<_> = match &self.order {
                Some(o) => o[take]
                    .iter()
                    .map(|&i| p.nodes[i as usize].clone())
                    .collect(),
                None => p.nodes[take].to_vec(),
            };
            let block = p.coder.encode(&nodes).map_err(|e| e.to_string())?;
            let frame = encode(&ServerMsg::Preview { seq, block }).map_err(|e| e.to_string())?;
            let len = frame.len() as u64;
            if let Some(t) = target.filter(|&t| len > t + t / 4 && k > MIN_BATCH && resized < 2) {
                // (a view's subset of a level costs more per node than the level: its ids)
                resized += 1;
                k = ((k as u64 * t / len) as usize).max(MIN_BATCH);
                continue;
            }
            if self.sent + len <= p.budget {
                self.sent += len;
                self.next += k;
                return Ok(Some(frame));
            }
            if k <= MIN_BATCH {
                break;
            }
            k /= 2;
        }
        self.next = self.len;
        Ok(None)
    }

    /// Nodes of the next batch: the first batch, every level but the preview's finest (all of
    /// it when that is the only one); later ones, about as many bytes as were sent before.
    fn batch_nodes(&self, s: &Shared, p: &ServedPreview) -> usize {
        let left = self.len - self.next;
        let forest = s.forest();
        let id = |i: usize| match &self.order {
            Some(o) => o[i],
            None => i as TetId,
        };
        if self.sent == 0 {
            let finest = forest.level(id(self.len - 1));
            let coarse = (0..self.len).take_while(|&i| forest.level(id(i)) < finest);
            let k = coarse.count();
            if k > 0 {
                return k;
            }
        }
        let costs = p.level_costs.get_or_init(|| level_costs(p, forest));
        let target = self.sent as f64;
        let mut bytes = 0.0;
        let mut k = 0;
        while k < left && (k < MIN_BATCH || bytes < target) {
            bytes += costs[forest.level(id(self.next + k)) as usize];
            k += 1;
        }
        k
    }
}

/// Estimated bytes a preview node costs, by level: its level's nodes coded alone as one block,
/// per node.
fn level_costs(p: &ServedPreview, forest: tetwave_protocol::hierarchy::Forest) -> Vec<f64> {
    let mut costs = Vec::new();
    let mut from = 0;
    for level in 0.. {
        let to = (forest.level_start(level + 1) as usize).min(p.nodes.len());
        if from >= to {
            break;
        }
        let bytes = p
            .coder
            .encode(&p.nodes[from..to])
            .map_or(0, |b| b.bytes.len());
        costs.push(bytes as f64 / (to - from) as f64);
        from = to;
    }
    costs
}

/// The preview's nodes for view order: level by level, within a level whole sibling groups by
/// the default view's priority of their best member (as the view order sends them), a group's
/// ids ascending.
fn view_order(s: &Shared) -> Vec<TetId> {
    let Some(p) = s.preview.as_ref() else {
        return Vec::new();
    };
    let n = p.nodes.len() as TetId;
    let pri = s
        .priorities_of(&s.default_view(), s.criterion(ViewTf::Default), 0..n)
        .unwrap_or_else(|e| {
            tracing::warn!("the preview goes by increasing id: {e}");
            vec![0.0; n as usize]
        });
    let forest = s.forest();
    // a sibling group by its parent (the base tets: one group); a parent precedes its children,
    // so groups are below n + 1
    let group = |i: TetId| forest.parent(i).map_or(0, |p| p + 1);
    let mut best = vec![f32::MIN; n as usize + 1];
    for i in 0..n {
        let b = &mut best[group(i) as usize];
        *b = b.max(pri[i as usize]);
    }
    let mut ids: Vec<TetId> = (0..n).collect();
    ids.sort_by(|&a, &b| {
        let (ga, gb) = (group(a), group(b));
        forest
            .level(a)
            .cmp(&forest.level(b))
            .then(best[gb as usize].total_cmp(&best[ga as usize]))
            .then(ga.cmp(&gb))
            .then(a.cmp(&b))
    });
    ids
}
