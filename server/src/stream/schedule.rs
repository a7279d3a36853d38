//! One connection's schedule: which node ids go out next. Explicit `Want` ranges first, then the
//! [`Order`]: level (increasing id), magnitude or random (a permutation [`Shared`] computes once),
//! or view (the best pending ids for the client's last `View`, a chunk at a time). Two bitsets over
//! the ids say what is done and what is cancelled.

use super::config::Order;
use super::state::Shared;
use glam::DVec3;
use std::collections::VecDeque;
use std::sync::Arc;
use tetwave_protocol::view::{data_weight, screen_error, Camera, Tolerance, View};
use tetwave_protocol::wire::{IdRange, ViewParams};
use tetwave_protocol::{BaseMesh, TetId};

/// A fixed-size set of node ids.
struct BitSet(Vec<u64>);

impl BitSet {
    fn new(n: u64) -> Self {
        BitSet(vec![0; n.div_ceil(64) as usize])
    }
    #[inline]
    fn get(&self, i: u64) -> bool {
        self.0[(i / 64) as usize] >> (i % 64) & 1 == 1
    }
    #[inline]
    fn set(&mut self, i: u64) {
        self.0[(i / 64) as usize] |= 1 << (i % 64);
    }
    #[inline]
    fn clear(&mut self, i: u64) {
        self.0[(i / 64) as usize] &= !(1 << (i % 64));
    }
}

enum Plan {
    /// Increasing id from `cursor`.
    Level { cursor: u64 },
    /// A shared permutation, from `cursor`.
    Perm {
        perm: Arc<Vec<TetId>>,
        cursor: usize,
    },
    /// View order: `chunk` holds the best pending ids for `view`, best last (popped from the end);
    /// recomputed when it runs out or the view changes.
    View {
        view: ViewParams,
        chunk: Vec<TetId>,
        stale: bool,
    },
}

/// What one connection still has to send.
pub(super) struct Schedule {
    n: u64,
    /// Sent, held by the client (`have`), or cancelled: the order skips these.
    done: BitSet,
    /// Cancelled: `Want` ranges skip these too (until a later `Want` names them again).
    cancelled: BitSet,
    /// Ids not yet done.
    remaining: u64,
    /// Explicit requests, served before the order.
    wants: VecDeque<(TetId, TetId)>,
    plan: Plan,
}

/// Most queued `Want` ranges per connection.
const MAX_QUEUED_WANTS: usize = 1 << 18;

impl Schedule {
    pub(super) fn new(s: &Shared, order: Order) -> Self {
        let n = s.nodes;
        let plan = match order {
            Order::Level => Plan::Level { cursor: 0 },
            Order::Magnitude => Plan::Perm {
                perm: s.magnitude_perm(),
                cursor: 0,
            },
            Order::Random => Plan::Perm {
                perm: s.random_perm(),
                cursor: 0,
            },
            Order::View => Plan::View {
                view: default_view(&s.store.base),
                chunk: Vec::new(),
                stale: true,
            },
        };
        Schedule {
            n,
            done: BitSet::new(n),
            cancelled: BitSet::new(n),
            remaining: n,
            wants: VecDeque::new(),
            plan,
        }
    }

    fn clip(&self, r: &IdRange) -> (u64, u64) {
        (r.from.min(self.n), r.to.min(self.n))
    }

    fn mark_done(&mut self, i: TetId) {
        if !self.done.get(i) {
            self.done.set(i);
            self.remaining -= 1;
        }
    }

    pub(super) fn have(&mut self, ranges: &[IdRange]) {
        for r in ranges {
            let (a, b) = self.clip(r);
            for i in a..b {
                self.mark_done(i);
            }
        }
    }

    pub(super) fn cancel(&mut self, ranges: &[IdRange]) {
        for r in ranges {
            let (a, b) = self.clip(r);
            for i in a..b {
                self.mark_done(i);
                self.cancelled.set(i);
            }
        }
    }

    /// Queues ranges; `false` when the queue would exceed its bound.
    pub(super) fn want(&mut self, ranges: &[IdRange]) -> bool {
        if self.wants.len() + ranges.len() > MAX_QUEUED_WANTS {
            return false;
        }
        for r in ranges {
            let (a, b) = self.clip(r);
            if a < b {
                for i in a..b {
                    self.cancelled.clear(i);
                }
                self.wants.push_back((a, b));
            }
        }
        true
    }

    pub(super) fn set_view(&mut self, v: ViewParams) {
        if let Plan::View { view, stale, .. } = &mut self.plan {
            *view = v;
            *stale = true;
        }
    }

    pub(super) fn has_work(&self) -> bool {
        !self.wants.is_empty() || self.remaining > 0
    }

    /// Up to `max` ids to send next (wanted ranges first, then the order).
    pub(super) fn next_batch(&mut self, s: &Shared, max: usize) -> Vec<TetId> {
        let mut out = Vec::with_capacity(max.min(self.n as usize));
        while out.len() < max {
            let Some((a, b)) = self.wants.front_mut() else {
                break;
            };
            while *a < *b && out.len() < max {
                let i = *a;
                *a += 1;
                if !self.cancelled.get(i) {
                    out.push(i);
                }
            }
            if *a >= *b {
                self.wants.pop_front();
            }
        }
        for &i in &out {
            self.mark_done(i);
        }
        while out.len() < max && self.remaining > 0 {
            let i = match &mut self.plan {
                Plan::Level { cursor } => {
                    while *cursor < self.n && self.done.get(*cursor) {
                        *cursor += 1;
                    }
                    if *cursor >= self.n {
                        break;
                    }
                    *cursor
                }
                Plan::Perm { perm, cursor } => {
                    while *cursor < perm.len() && self.done.get(perm[*cursor]) {
                        *cursor += 1;
                    }
                    if *cursor >= perm.len() {
                        break;
                    }
                    perm[*cursor]
                }
                Plan::View { view, chunk, stale } => {
                    while chunk.last().is_some_and(|&i| self.done.get(i)) {
                        chunk.pop();
                    }
                    if *stale || chunk.is_empty() {
                        *chunk = view_chunk(s, view, &self.done, self.remaining);
                        *stale = false;
                    }
                    match chunk.pop() {
                        Some(i) => i,
                        None => break,
                    }
                }
            };
            self.mark_done(i);
            out.push(i);
        }
        out
    }
}

/// Detail magnitude (relative to the value range) from which a node's data weight is full.
pub const DATA_DELTA: f32 = 0.01;

/// Screen-space error × data term of node `i` for a view: the priority of view order, with the
/// criterion selection uses ([`tetwave_protocol::view`]) so that the order follows what the client
/// will want.
struct ViewPriority {
    view: View,
    value_range: [f32; 2],
}

impl ViewPriority {
    fn new(v: &ViewParams, value_range: [f32; 2]) -> Self {
        ViewPriority {
            view: View::new(&Camera::from_view_params(v), Tolerance::Pixels(v.tol_px)),
            value_range,
        }
    }

    /// [`screen_error`] with the data weight (δ = [`DATA_DELTA`]) floored at 10⁻³, × 10⁻⁶ outside
    /// the view frustum: flat or hidden subtrees last, but still sent.
    #[inline]
    fn eval(&self, centre: [f32; 3], radius: f32, smax: f32) -> f32 {
        let c = DVec3::from_array(centre.map(f64::from));
        let r = radius as f64;
        let data = data_weight(smax, self.value_range, DATA_DELTA).max(1e-3);
        let mut e = screen_error(&self.view, c, r, data);
        if !self.view.sphere_visible(c, r) {
            e *= 1e-6;
        }
        if e.is_finite() {
            e as f32
        } else {
            f32::MAX
        }
    }
}

impl Shared {
    /// Every node's view-order priority for `view` (larger is sent first): what
    /// [`Order::View`](super::Order::View) ranks by.
    pub fn view_priorities(&self, view: &ViewParams) -> Vec<f32> {
        let g = self.geometry();
        let p = ViewPriority::new(view, self.store.manifest.value_range);
        (0..self.nodes as usize)
            .map(|u| p.eval(g.centre[u], g.radius[u], self.smax[u]))
            .collect()
    }
}

/// The best not-yet-done ids for `view`, best last. Takes at most `max(4096, n/16)` of them, so a
/// connection recomputes at most ~16 times over the whole stream plus once per `View`.
fn view_chunk(s: &Shared, view: &ViewParams, done: &BitSet, remaining: u64) -> Vec<TetId> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    let m = ((s.nodes / 16).max(4096)).min(remaining) as usize;
    if m == 0 {
        return Vec::new();
    }
    let g = s.geometry();
    let p = ViewPriority::new(view, s.store.manifest.value_range);
    // min-heap of the m best (priority bits: non-negative f32 order as their bits)
    let mut heap: BinaryHeap<Reverse<(u32, Reverse<TetId>)>> = BinaryHeap::with_capacity(m + 1);
    for i in 0..s.nodes {
        if done.get(i) {
            continue;
        }
        let u = i as usize;
        let e = p
            .eval(g.centre[u], g.radius[u], s.smax[u])
            .max(0.0)
            .to_bits();
        let item = Reverse((e, Reverse(i)));
        if heap.len() < m {
            heap.push(item);
        } else if heap.peek().is_some_and(|top| item < *top) {
            heap.pop();
            heap.push(item);
        }
    }
    // ascending priority (worst first), so popping from the end gives the best
    let mut v: Vec<(u32, Reverse<TetId>)> = heap.into_iter().map(|Reverse(x)| x).collect();
    v.sort_unstable();
    v.into_iter().map(|(_, Reverse(i))| i).collect()
}

/// The default camera of view order before a client sends its own (the render CLI's default).
fn default_view(base: &BaseMesh) -> ViewParams {
    let (lo, hi) = base.bounds();
    let c = [
        0.5 * (lo[0] + hi[0]),
        0.5 * (lo[1] + hi[1]),
        0.5 * (lo[2] + hi[2]),
    ];
    let diag = (0..3).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f64>().sqrt();
    let (az, el) = (35f64.to_radians(), 25f64.to_radians());
    let d = 1.6 * diag;
    ViewParams {
        eye: [
            c[0] + d * el.cos() * az.cos(),
            c[1] + d * el.cos() * az.sin(),
            c[2] + d * el.sin(),
        ],
        target: c,
        up: [0.0, 0.0, 1.0],
        fovy_deg: 40.0,
        width: 512,
        height: 512,
        tol_px: 1.0,
    }
}
