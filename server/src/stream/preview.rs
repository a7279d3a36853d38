//! A new session's preview phase: coarse copies of the store's most important coarse nodes
//! ([`tetwave_protocol::store_format::Preview`]), sent as `Preview` batches before any `Nodes`,
//! within a byte budget ([`super::ServeConfig::preview_share`]). The client holds each until the
//! store's own node replaces it, so a thin link shows the whole volume coarsely early and the
//! complete stream still ends exactly at the store's values.

use super::config::Order;
use super::schedule::view_priority_of;
use super::state::Shared;
use tetwave_protocol::wire::{encode, ServerMsg};
use tetwave_protocol::TetId;

/// Smallest batch tried when a larger one would overrun the budget.
const MIN_BATCH: usize = 64;

/// What one connection still has to send of the preview.
pub(super) struct PreviewPhase {
    /// Preview node ids still to send, the next last.
    ids: Vec<TetId>,
    /// Bytes of preview blocks sent so far.
    sent: u64,
}

impl PreviewPhase {
    /// The phase of a new session (`fresh`: it holds nothing) of a store with a preview: its
    /// nodes in the order's sense of importance (for view order, whole sibling groups by the
    /// default view's priority of their best member, as the view order sends them; increasing id
    /// otherwise). `None` when there is nothing to send.
    pub(super) fn new(s: &Shared, order: Order, fresh: bool) -> Option<Self> {
        let p = s.preview.as_ref().filter(|_| fresh)?;
        let n = p.nodes.len() as TetId;
        let mut ids: Vec<TetId> = (0..n).rev().collect();
        if order == Order::View {
            let pri = view_priority_of(s, 0..n);
            let forest = s.forest();
            // a sibling group by its parent (the base tets: one group)
            let group = |i: TetId| forest.parent(i).map_or(0, |p| p + 1);
            // (a parent precedes its children: groups are below n + 1)
            let mut best = vec![f32::MIN; n as usize + 1];
            for i in 0..n {
                let b = &mut best[group(i) as usize];
                *b = b.max(pri[i as usize]);
            }
            // best group last, a group's ids descending (so they go out ascending)
            ids.sort_by(|&a, &b| {
                let (ga, gb) = (group(a), group(b));
                best[ga as usize]
                    .total_cmp(&best[gb as usize])
                    .then(gb.cmp(&ga))
                    .then(b.cmp(&a))
            });
        }
        (!ids.is_empty()).then_some(PreviewPhase { ids, sent: 0 })
    }

    /// The next `Preview` frame of at most `batch` nodes (halved while it would overrun the
    /// budget, down to [`MIN_BATCH`]) and its node count; `None` when the phase is over.
    pub(super) fn next_frame(
        &mut self,
        s: &Shared,
        seq: u64,
        batch: usize,
    ) -> Result<Option<(Vec<u8>, usize)>, String> {
        let Some(p) = s.preview.as_ref() else {
            return Ok(None);
        };
        let mut k = batch.min(self.ids.len());
        while k > 0 {
            let take = &self.ids[self.ids.len() - k..];
            let nodes: Vec<_> = take.iter().map(|&i| p.nodes[i as usize].clone()).collect();
            let block = p.coder.encode(&nodes).map_err(|e| e.to_string())?;
            let frame = encode(&ServerMsg::Preview { seq, block }).map_err(|e| e.to_string())?;
            if self.sent + frame.len() as u64 <= p.budget {
                self.sent += frame.len() as u64;
                self.ids.truncate(self.ids.len() - k);
                return Ok(Some((frame, k)));
            }
            if k <= MIN_BATCH {
                break;
            }
            k /= 2;
        }
        self.ids.clear();
        Ok(None)
    }
}
