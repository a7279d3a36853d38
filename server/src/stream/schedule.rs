//! One connection's schedule: which node ids go out next. Explicit `Want` ranges first, then the
//! [`Order`]: level (increasing id), magnitude (best first by subtree bound, from the top down),
//! random (a seeded bijection of the ids, computed per id) or view (a walk of the hierarchy in the
//! order the client will split it, [`super::walk`]). What was sent and what was cancelled are
//! sets of id ranges: a connection holds what it has sent and reached, never arrays over every
//! node.

use super::config::{Order, ViewTf};
use super::state::Shared;
use super::walk::{Ranker, Walk};
use std::collections::{BTreeMap, BinaryHeap};
use std::time::{Duration, Instant};
use tetwave_protocol::wire::{IdRange, ViewParams};
use tetwave_protocol::TetId;
use tetwave_store::StoreError;

pub use super::walk::DATA_DELTA;

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
    /// Whether `i` is in the set.
    fn contains(&self, i: u64) -> bool {
        self.0.range(..=i).next_back().is_some_and(|(_, &e)| i < e)
    }
    /// The first id at or after `i` not in the set.
    fn next_absent(&self, i: u64) -> u64 {
        match self.0.range(..=i).next_back() {
            Some((_, &e)) if i < e => e,
            _ => i,
        }
    }
    /// Adds `a..b`; returns how many of its ids were not in the set.
    fn insert(&mut self, a: u64, b: u64) -> u64 {
        if a >= b {
            return 0;
        }
        let (a0, b0) = (a, b);
        let (mut a, mut b) = (a, b);
        let mut overlap = 0;
        let absorb = |s: u64, e: u64| s.max(a0).min(b0).abs_diff(e.max(a0).min(b0));
        // a range that starts before `a` and reaches it absorbs the new one's start
        if let Some((&s, &e)) = self.0.range(..=a).next_back() {
            if e >= a {
                overlap += absorb(s, e);
                a = s;
                b = b.max(e);
                self.0.remove(&s);
            }
        }
        // ranges that start within `a..=b` are absorbed
        while let Some((&s, &e)) = self.0.range(a..=b).next() {
            overlap += absorb(s, e);
            b = b.max(e);
            self.0.remove(&s);
        }
        self.0.insert(a, b);
        (b0 - a0) - overlap
    }
    /// Removes `a..b`.
    fn remove(&mut self, a: u64, b: u64) {
        if a >= b {
            return;
        }
        if let Some((&s, &e)) = self.0.range(..a).next_back() {
            if e > a {
                self.0.insert(s, a);
                if e > b {
                    self.0.insert(b, e);
                }
            }
        }
        while let Some((&s, &e)) = self.0.range(a..b).next() {
            self.0.remove(&s);
            if e > b {
                self.0.insert(b, e);
            }
        }
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

/// A seeded bijection of `0..n` computed one index at a time: a balanced Feistel network on the
/// smallest even number of bits that covers `n`, walked along its cycle until it lands below `n`
/// (fewer than 4 steps on average, since that domain is under `4n`).
struct Shuffle {
    n: u64,
    half: u32,
    keys: [u64; 4],
}

impl Shuffle {
    fn new(n: u64, seed: u64) -> Self {
        let bits = (64 - n.saturating_sub(1).leading_zeros()).max(2);
        let half = bits.div_ceil(2);
        let mut x = seed;
        let keys = std::array::from_fn(|_| {
            x = splitmix(x);
            x
        });
        Shuffle { n, half, keys }
    }

    /// The `i`-th id of the order (`i < n`).
    fn at(&self, i: u64) -> u64 {
        let mask = (1u64 << self.half) - 1;
        let mut x = i;
        loop {
            let (mut l, mut r) = (x >> self.half, x & mask);
            for k in self.keys {
                let f = splitmix(r ^ k) & mask;
                (l, r) = (r, l ^ f);
            }
            x = (l << self.half) | r;
            if x < self.n {
                return x;
            }
        }
    }
}

/// SplitMix64's finaliser: a well-mixed 64-bit hash.
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

enum Plan {
    /// Increasing id from `cursor`.
    Level { cursor: u64 },
    /// [`Shuffle`]'s order, from `cursor`.
    Random { order: Shuffle, cursor: u64 },
    /// Largest subtree bound first, ties by id: the frontier of a best-first walk from the base
    /// tets (a node's bound covers its children's, so popping the best gives the sorted order).
    Magnitude {
        frontier: BinaryHeap<(u32, std::cmp::Reverse<TetId>)>,
    },
    /// View order: a walk for the client's last view, then the ids it never reached by
    /// increasing id from `tail`.
    View(Box<ViewPlan>),
}

struct ViewPlan {
    view: ViewParams,
    /// The walk for `view` (`None`: start one).
    walk: Option<Walk>,
    tail: u64,
    stale: bool,
    /// When the last walk started, and what starting it cost.
    last: Option<(Instant, Duration)>,
    /// The client has sent a `View` (before that, `view` is the default one).
    client_view: bool,
    /// The transfer function whose image weights rank the nodes (the client's).
    tf: ViewTf,
}

impl ViewPlan {
    /// A changed view restarts the walk only [`RESCAN_SPACING`] × what the last start cost (at
    /// least [`RESCAN_MIN_INTERVAL`]) after it, so a client that sends a `View` before every
    /// batch cannot make the connection spend its time restarting. Until then the current walk
    /// (the old view's) goes on.
    fn restart_due(&self, now: Instant) -> bool {
        if self.walk.is_none() {
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

/// Restarts wait at least this many times the last one's cost.
const RESCAN_SPACING: u32 = 4;
/// … and at least this long.
const RESCAN_MIN_INTERVAL: Duration = Duration::from_millis(50);

/// What one connection still has to send.
pub(super) struct Schedule {
    n: u64,
    /// Sent, held by the client (`have`), or cancelled: the order skips these.
    done: RangeSet,
    /// Cancelled: `Want` ranges skip these too (until a later `Want` names them again).
    cancelled: RangeSet,
    /// Ids not yet done.
    remaining: u64,
    /// Explicit requests, served before the order, lowest id first.
    wants: RangeSet,
    plan: Plan,
    /// Walks started (tests and `/healthz` read it).
    rescans: u64,
}

/// Most disjoint `Want` ranges a connection may have queued (after merging).
pub(super) const MAX_QUEUED_WANTS: usize = 1 << 16;

impl Schedule {
    /// A schedule in `order`; view order ranks by the image weights of `tf`.
    pub(super) fn new(s: &Shared, order: Order, tf: ViewTf) -> Result<Self, StoreError> {
        let n = s.nodes;
        let plan = match order {
            Order::Level => Plan::Level { cursor: 0 },
            Order::Random => Plan::Random {
                order: Shuffle::new(n, s.config.seed),
                cursor: 0,
            },
            Order::Magnitude => {
                let roots = (s.store.base.tets.len() as TetId).min(n);
                let bounds = s.bounds(0, roots, f32::INFINITY)?;
                Plan::Magnitude {
                    frontier: bounds
                        .iter()
                        .enumerate()
                        .map(|(i, b)| (magnitude_key(*b), std::cmp::Reverse(i as TetId)))
                        .collect(),
                }
            }
            Order::View => Plan::View(Box::new(ViewPlan {
                view: s.default_view(),
                walk: None,
                tail: 0,
                stale: true,
                last: None,
                client_view: false,
                tf,
            })),
        };
        Ok(Schedule {
            n,
            done: RangeSet::default(),
            cancelled: RangeSet::default(),
            remaining: n,
            wants: RangeSet::default(),
            plan,
            rescans: 0,
        })
    }

    fn mark_done(&mut self, i: TetId) {
        self.remaining -= self.done.insert(i, i + 1);
    }

    /// The client already holds `ranges`. `O(r log r + r log k)`.
    pub(super) fn have(&mut self, ranges: &[IdRange]) {
        for (a, b) in merged(ranges, self.n) {
            self.remaining -= self.done.insert(a, b);
        }
    }

    /// Drops `ranges` from the order and from queued `Want`s.
    pub(super) fn cancel(&mut self, ranges: &[IdRange]) {
        for (a, b) in merged(ranges, self.n) {
            self.remaining -= self.done.insert(a, b);
            self.cancelled.insert(a, b);
        }
    }

    /// Queues ranges to send ahead of the order; `false` when the queue would exceed
    /// [`MAX_QUEUED_WANTS`] disjoint ranges.
    pub(super) fn want(&mut self, ranges: &[IdRange]) -> bool {
        let m = merged(ranges, self.n);
        if self.wants.len() + m.len() > MAX_QUEUED_WANTS {
            return false;
        }
        for (a, b) in m {
            self.cancelled.remove(a, b);
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
                // re-prioritising, and the default view's walk is nobody's camera
                p.client_view = true;
                p.last = None;
            }
        }
    }

    pub(super) fn has_work(&self) -> bool {
        !self.wants.is_empty() || self.remaining > 0
    }

    /// Walks started so far.
    pub(super) fn rescans(&self) -> u64 {
        self.rescans
    }

    /// Up to `max` ids to send next (wanted ranges first, then the order).
    pub(super) fn next_batch(&mut self, s: &Shared, max: usize) -> Result<Vec<TetId>, StoreError> {
        let mut out = Vec::with_capacity(max.min(self.n as usize));
        while out.len() < max {
            let Some((a, b)) = self.wants.pop_front((max - out.len()) as u64) else {
                break;
            };
            let mut i = a;
            while i < b {
                let skip = self.cancelled.next_absent(i);
                if skip > i {
                    i = skip;
                    continue;
                }
                out.push(i);
                i += 1;
            }
        }
        for &i in &out {
            self.mark_done(i);
        }
        while out.len() < max && self.remaining > 0 {
            let i = match &mut self.plan {
                Plan::Level { cursor } => {
                    *cursor = self.done.next_absent(*cursor);
                    if *cursor >= self.n {
                        break;
                    }
                    *cursor
                }
                Plan::Random { order, cursor } => {
                    let next = (*cursor..self.n)
                        .map(|k| (k, order.at(k)))
                        .find(|&(_, i)| !self.done.contains(i));
                    let Some((k, i)) = next else {
                        *cursor = self.n;
                        break;
                    };
                    *cursor = k;
                    i
                }
                Plan::Magnitude { frontier } => {
                    let Some((key, std::cmp::Reverse(i))) = frontier.pop() else {
                        break;
                    };
                    let forest = s.forest();
                    if forest.level(i) + 1 < forest.levels {
                        let first = forest.child(i, 0);
                        let parent = f32::from_bits(key);
                        for (k, b) in s.bounds(first, first + 8, parent)?.into_iter().enumerate() {
                            frontier
                                .push((magnitude_key(b), std::cmp::Reverse(first + k as TetId)));
                        }
                    }
                    if self.done.contains(i) {
                        continue;
                    }
                    i
                }
                Plan::View(p) => {
                    let now = Instant::now();
                    if p.restart_due(now) {
                        let ranker = Ranker::new(s, &p.view, s.criterion(p.tf));
                        p.walk = Some(Walk::new(s, ranker)?);
                        p.stale = false;
                        let end = Instant::now();
                        p.last = Some((end, end - now));
                        self.rescans += 1;
                    }
                    let walk = p.walk.as_mut().expect("a walk");
                    match walk.next(s)? {
                        Some(i) if self.done.contains(i) => continue,
                        Some(i) => {
                            // with its unsent siblings: they lie beside it (the client reads
                            // them too), and a batch of whole sibling groups codes its ids as
                            // runs (protocol::block) instead of scattered gaps
                            self.mark_done(i);
                            out.push(i);
                            if let Some(c) = s.forest().child_index(i) {
                                let first = i - c as u64;
                                for j in first..first + 8 {
                                    if out.len() < max && !self.done.contains(j) {
                                        self.mark_done(j);
                                        out.push(j);
                                    }
                                }
                            }
                            continue;
                        }
                        None => {
                            // what the walk never reached: nothing the client reads
                            p.tail = self.done.next_absent(p.tail);
                            if p.tail >= self.n {
                                break;
                            }
                            p.tail
                        }
                    }
                }
            };
            self.mark_done(i);
            out.push(i);
        }
        Ok(out)
    }
}

/// A subtree bound as a heap key: ordered as the non-negative floats (a NaN or negative bound,
/// which no store writes, as 0).
fn magnitude_key(b: f32) -> u32 {
    if b >= 0.0 {
        b.to_bits()
    } else {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Range insertions and removals agree with a set of single ids: `insert` counts the
        /// new ids, and `contains` / `next_absent` answer as the model does.
        #[test]
        fn range_set_matches_single_ids(
            ops in prop::collection::vec((0u64..320, 0u64..40, any::<bool>()), 0..30),
            probes in prop::collection::vec(0u64..400, 1..20),
        ) {
            let mut set = RangeSet::default();
            let mut slow = [false; 400];
            for (a, len, add) in ops {
                let b = a + len;
                if add {
                    let want = (a..b).filter(|&i| !slow[i as usize]).count() as u64;
                    prop_assert_eq!(set.insert(a, b), want);
                    (a..b).for_each(|i| slow[i as usize] = true);
                } else {
                    set.remove(a, b);
                    (a..b).for_each(|i| slow[i as usize] = false);
                }
                let spans: Vec<(u64, u64)> = set.0.iter().map(|(&a, &b)| (a, b)).collect();
                for w in spans.windows(2) {
                    prop_assert!(w[0].1 < w[1].0, "{:?} overlap or touch", w);
                }
            }
            for i in probes {
                prop_assert_eq!(set.contains(i), slow[i as usize]);
                let next = (i..400).find(|&j| !slow[j as usize]).unwrap_or(400);
                prop_assert_eq!(set.next_absent(i), next);
            }
        }

        /// The random order is a permutation of the ids, whatever their count.
        #[test]
        fn shuffle_is_a_permutation(n in 1u64..3000, seed in any::<u64>()) {
            let order = Shuffle::new(n, seed);
            let mut seen = vec![false; n as usize];
            for i in 0..n {
                let x = order.at(i);
                prop_assert!(x < n && !seen[x as usize], "{} at {}", x, i);
                seen[x as usize] = true;
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
