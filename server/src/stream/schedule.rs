//! One connection's schedule: which node ids go out next. Explicit `Want` ranges first, then the
//! [`Order`]: level (increasing id), magnitude or random (a permutation [`Shared`] computes once),
//! or view (the best pending ids for the client's last `View`, a chunk at a time). Two bitsets over
//! the ids say what is done and what is cancelled.

use super::config::{Order, ViewTf};
use super::state::Shared;
use glam::DVec3;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tetwave_protocol::view::{data_weight, screen_error, Camera, Tolerance, View};
use tetwave_protocol::wire::{IdRange, ViewParams};
use tetwave_protocol::{BaseMesh, TetId};

/// A fixed-size set of node ids. Range operations work a 64-bit word at a time, so a range costs
/// `O(len / 64)`, never `O(len)` single-bit steps.
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
    fn set(&mut self, i: u64) -> bool {
        let (w, m) = ((i / 64) as usize, 1u64 << (i % 64));
        let new = self.0[w] & m == 0;
        self.0[w] |= m;
        new
    }
    /// Applies `f(word, mask)` to every word that `a..b` touches (`mask`: the range's bits in it).
    fn for_words(&mut self, a: u64, b: u64, mut f: impl FnMut(&mut u64, u64)) {
        if a >= b {
            return;
        }
        let (wa, wb) = ((a / 64) as usize, ((b - 1) / 64) as usize);
        for w in wa..=wb {
            let lo = if w == wa { a % 64 } else { 0 };
            let hi = if w == wb { (b - 1) % 64 } else { 63 };
            let mask = (u64::MAX >> (63 - hi)) & (u64::MAX << lo);
            f(&mut self.0[w], mask);
        }
    }
    /// Sets `a..b`; returns how many ids were not set before.
    fn set_range(&mut self, a: u64, b: u64) -> u64 {
        let mut new = 0;
        self.for_words(a, b, |w, m| {
            new += u64::from((!*w & m).count_ones());
            *w |= m;
        });
        new
    }
    fn clear_range(&mut self, a: u64, b: u64) {
        self.for_words(a, b, |w, m| *w &= !m);
    }
}

/// Disjoint, non-adjacent id ranges `start → end`, merged on insert: a range costs `O(log k)` plus
/// the ranges it absorbs, however many ids it names.
#[derive(Default)]
struct RangeSet(BTreeMap<u64, u64>);

impl RangeSet {
    fn len(&self) -> usize {
        self.0.len()
    }
    fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    fn insert(&mut self, mut a: u64, mut b: u64) {
        if a >= b {
            return;
        }
        // a range that starts before `a` and reaches it absorbs the new one's start
        if let Some((&s, &e)) = self.0.range(..=a).next_back() {
            if e >= a {
                a = s;
                b = b.max(e);
                self.0.remove(&s);
            }
        }
        // ranges that start within `a..=b` are absorbed
        while let Some((&s, &e)) = self.0.range(a..=b).next() {
            b = b.max(e);
            self.0.remove(&s);
        }
        self.0.insert(a, b);
    }
    /// Removes and returns up to `max` ids from the front (lowest first).
    fn pop_front(&mut self, max: u64) -> Option<(u64, u64)> {
        let (&a, &b) = self.0.iter().next()?;
        self.0.remove(&a);
        let end = b.min(a.saturating_add(max));
        if end < b {
            self.0.insert(end, b);
        }
        Some((a, end))
    }
}

/// A message's ranges clipped to `0..n`, sorted and merged: at most `ranges.len()` disjoint ranges,
/// `O(r log r)` whatever the ranges cover.
pub(super) fn merged(ranges: &[IdRange], n: u64) -> Vec<(u64, u64)> {
    let mut v: Vec<(u64, u64)> = ranges
        .iter()
        .map(|r| (r.from.min(n), r.to.min(n)))
        .filter(|(a, b)| a < b)
        .collect();
    v.sort_unstable();
    let mut out: Vec<(u64, u64)> = Vec::with_capacity(v.len());
    for (a, b) in v {
        match out.last_mut() {
            Some(last) if a <= last.1 => last.1 = last.1.max(b),
            _ => out.push((a, b)),
        }
    }
    out
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
    /// recomputed when it runs out, or when the view changed and the last rescan is old enough
    /// ([`ViewPlan::rescan_due`]).
    View(ViewPlan),
}

struct ViewPlan {
    view: ViewParams,
    chunk: Vec<TetId>,
    stale: bool,
    /// When the last rescan ended, and what it cost.
    last: Option<(Instant, Duration)>,
    /// The client has sent a `View` (before that, `view` is the default one).
    client_view: bool,
    /// The transfer function whose image weights rank the nodes (the client's).
    tf: ViewTf,
}

impl ViewPlan {
    /// A changed view triggers a rescan only [`RESCAN_SPACING`] × its cost (at least
    /// [`RESCAN_MIN_INTERVAL`]) after the last one, so a client that sends a `View` before every
    /// batch cannot make the connection spend more than about a fifth of its time rescanning. Until
    /// then the current chunk (the old view's best) goes on.
    fn rescan_due(&self, now: Instant) -> bool {
        if self.chunk.is_empty() {
            return true;
        }
        if !self.stale {
            return false;
        }
        match self.last {
            None => true,
            Some((at, cost)) => now >= at + (cost * RESCAN_SPACING).max(RESCAN_MIN_INTERVAL),
        }
    }
}

/// Rescans wait at least this many times the last one's cost.
const RESCAN_SPACING: u32 = 4;
/// … and at least this long.
const RESCAN_MIN_INTERVAL: Duration = Duration::from_millis(50);

/// What one connection still has to send.
pub(super) struct Schedule {
    n: u64,
    /// Sent, held by the client (`have`), or cancelled: the order skips these.
    done: BitSet,
    /// Cancelled: `Want` ranges skip these too (until a later `Want` names them again).
    cancelled: BitSet,
    /// Ids not yet done.
    remaining: u64,
    /// Explicit requests, served before the order, lowest id first.
    wants: RangeSet,
    plan: Plan,
    /// View rescans so far (tests read it).
    rescans: u64,
}

/// Most disjoint `Want` ranges a connection may have queued (after merging).
pub(super) const MAX_QUEUED_WANTS: usize = 1 << 16;

impl Schedule {
    /// A schedule in `order`; view order ranks by the image weights of `tf`.
    pub(super) fn new(s: &Shared, order: Order, tf: ViewTf) -> Self {
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
            Order::View => Plan::View(ViewPlan {
                view: default_view(&s.store.base),
                chunk: Vec::new(),
                stale: true,
                last: None,
                client_view: false,
                tf,
            }),
        };
        Schedule {
            n,
            done: BitSet::new(n),
            cancelled: BitSet::new(n),
            remaining: n,
            wants: RangeSet::default(),
            plan,
            rescans: 0,
        }
    }

    fn mark_done(&mut self, i: TetId) {
        if self.done.set(i) {
            self.remaining -= 1;
        }
    }

    /// The client already holds `ranges`. `O(r log r + n/64)`.
    pub(super) fn have(&mut self, ranges: &[IdRange]) {
        for (a, b) in merged(ranges, self.n) {
            self.remaining -= self.done.set_range(a, b);
        }
    }

    /// Drops `ranges` from the order and from queued `Want`s. `O(r log r + n/64)`.
    pub(super) fn cancel(&mut self, ranges: &[IdRange]) {
        for (a, b) in merged(ranges, self.n) {
            self.remaining -= self.done.set_range(a, b);
            self.cancelled.set_range(a, b);
        }
    }

    /// Queues ranges to send ahead of the order; `false` when the queue would exceed
    /// [`MAX_QUEUED_WANTS`] disjoint ranges. `O(r log r + n/64)`.
    pub(super) fn want(&mut self, ranges: &[IdRange]) -> bool {
        let m = merged(ranges, self.n);
        if self.wants.len() + m.len() > MAX_QUEUED_WANTS {
            return false;
        }
        for (a, b) in m {
            self.cancelled.clear_range(a, b);
            self.wants.insert(a, b);
        }
        true
    }

    pub(super) fn set_view(&mut self, v: ViewParams) {
        if let Plan::View(p) = &mut self.plan {
            p.view = v;
            p.stale = true;
            if !p.client_view {
                // the client's first view replaces the default at once: the rate limit is for
                // re-prioritising, and the default view's chunk is nobody's camera
                p.client_view = true;
                p.last = None;
            }
        }
    }

    pub(super) fn has_work(&self) -> bool {
        !self.wants.is_empty() || self.remaining > 0
    }

    /// View rescans so far.
    pub(super) fn rescans(&self) -> u64 {
        self.rescans
    }

    /// Up to `max` ids to send next (wanted ranges first, then the order).
    pub(super) fn next_batch(&mut self, s: &Shared, max: usize) -> Vec<TetId> {
        let mut out = Vec::with_capacity(max.min(self.n as usize));
        while out.len() < max {
            let Some((a, b)) = self.wants.pop_front((max - out.len()) as u64) else {
                break;
            };
            out.extend((a..b).filter(|&i| !self.cancelled.get(i)));
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
                Plan::View(p) => {
                    while p.chunk.last().is_some_and(|&i| self.done.get(i)) {
                        p.chunk.pop();
                    }
                    let now = Instant::now();
                    if p.rescan_due(now) {
                        p.chunk = view_chunk(s, &p.view, p.tf, &self.done, self.remaining);
                        p.stale = false;
                        let end = Instant::now();
                        p.last = Some((end, end - now));
                        self.rescans += 1;
                    }
                    match p.chunk.pop() {
                        Some(i) => {
                            // with its unsent siblings: they lie beside it (about the same
                            // priority), and a batch of whole sibling groups codes its ids as
                            // runs (protocol::block) instead of scattered gaps
                            self.mark_done(i);
                            out.push(i);
                            if let Some(c) = s.forest().child_index(i) {
                                let first = i - c as u64;
                                for j in first..first + 8 {
                                    if out.len() < max && !self.done.get(j) {
                                        self.mark_done(j);
                                        out.push(j);
                                    }
                                }
                            }
                            continue;
                        }
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

    /// Whether the client will split a node with this sphere, subtree bound and image weight
    /// under this view: inside the frustum, with its weighted screen-space error (unfloored, as
    /// the client computes it) over the view's tolerance.
    #[inline]
    fn splits(&self, centre: [f32; 3], radius: f32, smax: f32, image: Option<f32>) -> bool {
        let c = DVec3::from_array(centre.map(f64::from));
        let r = radius as f64;
        let w = self.weight(smax, image);
        self.view.sphere_visible(c, r) && screen_error(&self.view, c, r, w) > self.view.tol_px
    }

    /// A node's weight: its image weight when view order has one, else its data weight
    /// (δ = [`DATA_DELTA`]) from its subtree bound `smax`.
    #[inline]
    fn weight(&self, smax: f32, image: Option<f32>) -> f64 {
        match image {
            Some(w) => w as f64,
            None => data_weight(smax, self.value_range, DATA_DELTA),
        }
    }

    /// [`screen_error`] with the node's image weight ([`Geometry::image`](super::state)) or
    /// else its data weight (δ = [`DATA_DELTA`]), floored at 10⁻³, × 10⁻⁶ outside the view
    /// frustum: subtrees that cannot change the image or are hidden go last, but are still sent.
    #[inline]
    fn eval(&self, centre: [f32; 3], radius: f32, smax: f32, image: Option<f32>) -> f32 {
        let c = DVec3::from_array(centre.map(f64::from));
        let r = radius as f64;
        let mut e = screen_error(&self.view, c, r, self.weight(smax, image).max(1e-3));
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
    /// Every node's view-order priority for `view` and a client drawing with `tf` (larger is
    /// sent first): what [`Order::View`](super::Order::View) ranks by.
    pub fn view_priorities(&self, view: &ViewParams, tf: ViewTf) -> Vec<f32> {
        self.view_priorities_of(view, tf, 0..self.nodes)
    }

    /// [`Self::view_priorities`] of nodes `ids`.
    pub(super) fn view_priorities_of(
        &self,
        view: &ViewParams,
        tf: ViewTf,
        ids: std::ops::Range<TetId>,
    ) -> Vec<f32> {
        let g = self.geometry();
        let image = self.image_weights(&g, tf);
        let p = ViewPriority::new(view, self.store.manifest.value_range);
        ids.map(|u| {
            let u = u as usize;
            p.eval(g.centre[u], g.radius[u], self.smax[u], image.map(|w| w[u]))
        })
        .collect()
    }

    /// The camera view order follows until a session's first `View`.
    pub(super) fn default_view(&self) -> ViewParams {
        default_view(&self.store.base)
    }
}

/// Factor on the priority of a node whose parent the client will not split under the view
/// ([`ViewPriority::splits`]): the client does not read it, so every node it will read goes
/// before it (it is still sent, last).
const NOT_READ: f32 = 1e-6;

/// The best not-yet-done ids for `view`, best last: by [`ViewPriority::eval`], times
/// [`NOT_READ`] where the node's parent will not be split, so that the nodes a client converging
/// on the view reads — the children of what it splits, which its leaves' bounds are — come before
/// nodes below its leaves. Takes at most `max(4096, n/16)` of them, so a connection recomputes at
/// most ~16 times over the whole stream plus once per `View`.
fn view_chunk(
    s: &Shared,
    view: &ViewParams,
    tf: ViewTf,
    done: &BitSet,
    remaining: u64,
) -> Vec<TetId> {
    use rayon::prelude::*;
    use std::cmp::Reverse;
    let m = ((s.nodes / 16).max(4096)).min(remaining) as usize;
    if m == 0 {
        return Vec::new();
    }
    let g = s.geometry();
    let image = s.image_weights(&g, tf);
    let forest = s.forest();
    let p = ViewPriority::new(view, s.store.manifest.value_range);
    // every node's priority as the bits of a non-negative f32 (ordered as the floats; done nodes
    // DONE, a NaN's bits, which no priority has): one parallel pass, then the m best by a
    // histogram of the top 16 bits and a selection within the bucket where they begin (no heap
    // over every node; 4 bytes a node while it runs)
    const DONE: u32 = u32::MAX;
    let keys: Vec<u32> = (0..s.nodes as usize)
        .into_par_iter()
        .with_min_len(1 << 14)
        .map(|u| {
            let i = u as TetId;
            if done.get(i) {
                return DONE;
            }
            let mut e = p
                .eval(g.centre[u], g.radius[u], s.smax[u], image.map(|w| w[u]))
                .max(0.0);
            if let Some(q) = forest.parent(i).map(|q| q as usize) {
                if !p.splits(g.centre[q], g.radius[q], s.smax[q], image.map(|w| w[q])) {
                    e *= NOT_READ;
                }
            }
            e.to_bits()
        })
        .collect();
    let hist = keys
        .par_iter()
        .with_min_len(1 << 14)
        .fold(
            || vec![0u64; 1 << 16],
            |mut h, &k| {
                if k != DONE {
                    h[(k >> 16) as usize] += 1;
                }
                h
            },
        )
        .reduce(
            || vec![0u64; 1 << 16],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
                a
            },
        );
    let mut seen = 0u64;
    let mut cut = 0usize;
    for b in (0..hist.len()).rev() {
        seen += hist[b];
        if seen >= m as u64 {
            cut = b;
            break;
        }
    }
    let mut v: Vec<(u32, Reverse<TetId>)> = keys
        .par_iter()
        .enumerate()
        .with_min_len(1 << 14)
        .filter(|&(_, &k)| k != DONE && (k >> 16) as usize >= cut)
        .map(|(i, &k)| (k, Reverse(i as TetId)))
        .collect();
    // the m best (ties: the smaller id first), ascending, so popping from the end gives the best
    if v.len() > m {
        let drop = v.len() - m;
        v.select_nth_unstable(drop);
        v.drain(..drop);
    }
    v.sort_unstable();
    v.into_iter().map(|(_, Reverse(i))| i).collect()
}

/// The default camera of view order before a client sends its own (the render CLI's default).
fn default_view(base: &BaseMesh) -> ViewParams {
    use tetwave_protocol::view::{Camera, Orbit};
    let (lo, hi) = base.bounds();
    let cam = Orbit::framed(Camera::framing(lo, hi)).camera(512, 512);
    ViewParams {
        eye: cam.eye.to_array(),
        target: cam.target.to_array(),
        up: [0.0, 0.0, 1.0],
        fovy_deg: cam.fovy_deg,
        width: cam.width,
        height: cam.height,
        tol_px: 1.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Word-wise range operations agree with bit-by-bit ones, and `set_range` counts the
        /// newly set ids.
        #[test]
        fn bitset_ranges_match_single_bits(
            n in 1u64..300,
            ops in prop::collection::vec((0u64..320, 0u64..320, any::<bool>()), 0..20),
        ) {
            let mut fast = BitSet::new(n);
            let mut slow = vec![false; n as usize];
            for (a, b, set) in ops {
                let (a, b) = (a.min(n), b.min(n));
                if set {
                    let new = fast.set_range(a, b);
                    let mut want = 0;
                    for i in a..b {
                        want += u64::from(!slow[i as usize]);
                        slow[i as usize] = true;
                    }
                    prop_assert_eq!(new, want);
                } else {
                    fast.clear_range(a, b);
                    for i in a..b {
                        slow[i as usize] = false;
                    }
                }
            }
            for i in 0..n {
                prop_assert_eq!(fast.get(i), slow[i as usize]);
            }
        }

        /// A range set holds exactly the union of what was inserted, as disjoint non-adjacent
        /// ranges, and pops it lowest first.
        #[test]
        fn range_set_is_the_union(ranges in prop::collection::vec((0u64..200, 0u64..40), 0..30)) {
            let mut set = RangeSet::default();
            let mut slow = [false; 240];
            for (a, len) in ranges {
                set.insert(a, a + len);
                for i in a..a + len {
                    slow[i as usize] = true;
                }
            }
            let spans: Vec<(u64, u64)> = set.0.iter().map(|(&a, &b)| (a, b)).collect();
            for w in spans.windows(2) {
                prop_assert!(w[0].1 < w[1].0, "{:?} overlap or touch", w);
            }
            let mut popped = Vec::new();
            while let Some((a, b)) = set.pop_front(7) {
                prop_assert!(b - a <= 7 && a < b);
                popped.extend(a..b);
            }
            let want: Vec<u64> = (0..240).filter(|&i| slow[i as usize]).collect();
            prop_assert_eq!(popped, want);
        }
    }

    #[test]
    fn merged_sorts_clips_and_joins() {
        let r = |from, to| IdRange { from, to };
        let m = merged(
            &[r(8, 12), r(0, 3), r(2, 5), r(5, 6), r(30, 40), r(9, 9)],
            32,
        );
        assert_eq!(m, vec![(0, 6), (8, 12), (30, 32)]);
    }
}
