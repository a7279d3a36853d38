//! A new session's preview phase: coarse copies of the store's most important coarse nodes
//! ([`tetwave_protocol::store_format::Preview`]), sent as `Preview` batches before any `Nodes`,
//! within a byte budget ([`super::ServeConfig::preview_share`]). The client holds each until the
//! store's own node replaces it, so a thin link shows the whole volume coarsely early and the
//! complete stream still ends exactly at the store's values.

use super::config::Order;
use super::state::Shared;
use std::sync::Arc;
use tetwave_protocol::wire::{encode, ServerMsg};
use tetwave_protocol::TetId;

/// Smallest batch tried when a larger one would overrun the budget.
const MIN_BATCH: usize = 64;

/// What one connection still has to send of the preview.
pub(super) struct PreviewPhase {
    /// Preview node ids in sending order (shared by every connection of the order); `None`:
    /// increasing id.
    order: Option<Arc<Vec<TetId>>>,
    /// Preview nodes in all.
    len: usize,
    /// The next one to send.
    next: usize,
    /// Bytes of preview blocks sent so far.
    sent: u64,
}

impl PreviewPhase {
    /// The phase of a new session (`fresh`: it holds nothing) of a store with a preview; `None`
    /// when there is nothing to send.
    pub(super) fn new(s: &Shared, order: Order, fresh: bool) -> Option<Self> {
        let p = s.preview.as_ref().filter(|_| fresh)?;
        let order = (order == Order::View)
            .then(|| p.view_order.get_or_init(|| Arc::new(view_order(s))).clone());
        (!p.nodes.is_empty()).then_some(PreviewPhase {
            order,
            len: p.nodes.len(),
            next: 0,
            sent: 0,
        })
    }

    /// The next `Preview` frame of at most `batch` nodes (halved while it would overrun the
    /// budget, down to [`MIN_BATCH`]); `None` when the phase is over.
    pub(super) fn next_frame(
        &mut self,
        s: &Shared,
        seq: u64,
        batch: usize,
    ) -> Result<Option<Vec<u8>>, String> {
        let Some(p) = s.preview.as_ref() else {
            return Ok(None);
        };
        let mut k = batch.min(self.len - self.next);
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
            if self.sent + frame.len() as u64 <= p.budget {
                self.sent += frame.len() as u64;
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
}

/// The preview's nodes for view order: whole sibling groups by the default view's priority of
/// their best member (as the view order sends them), a group's ids ascending.
fn view_order(s: &Shared) -> Vec<TetId> {
    let Some(p) = s.preview.as_ref() else {
        return Vec::new();
    };
    let n = p.nodes.len() as TetId;
    let pri = s.view_priorities_of(&s.default_view(), 0..n);
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
        best[gb as usize]
            .total_cmp(&best[ga as usize])
            .then(ga.cmp(&gb))
            .then(a.cmp(&b))
    });
    ids
}
