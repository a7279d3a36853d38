//! A parallel map that wakes every pool thread (the level walks are too short for rayon's lazy
//! wake-ups).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

/// Runs `f` on every item on all pool threads, which claim items from a shared counter; returns the
/// results in item order. [`rayon::broadcast`] wakes every worker explicitly: an indexed parallel
/// iterator relies on lazy wake-ups which, right after another parallel pass, often leave the second
/// worker asleep through a whole sub-millisecond level walk.
pub(super) fn par_map<T: Send, R: Send>(items: Vec<T>, f: impl Fn(T) -> R + Sync) -> Vec<R> {
    let threads = rayon::current_num_threads();
    if items.len() <= 1 || threads == 1 {
        return items.into_iter().map(f).collect();
    }
    // threads claim slots in turn: order the items so that consecutive slots come from far apart
    // (thread-many contiguous runs, interleaved), keeping concurrent tasks off each other's cache lines
    let len = items.len();
    let run = len.div_ceil(threads);
    let mut items: Vec<Option<T>> = items.into_iter().map(Some).collect();
    let slots: Vec<Mutex<Option<(usize, T)>>> = (0..run)
        .flat_map(|r| (0..threads).map(move |t| t * run + r))
        .filter(|&i| i < len)
        .map(|i| Mutex::new(items[i].take().map(|t| (i, t))))
        .collect();
    let next = AtomicUsize::new(0);
    let done = rayon::broadcast(|_| {
        let mut out = Vec::new();
        while let Some(slot) = slots.get(next.fetch_add(1, Ordering::Relaxed)) {
            let item = slot.lock().unwrap_or_else(|e| e.into_inner()).take();
            if let Some((i, t)) = item {
                out.push((i, f(t)));
            }
        }
        out
    });
    let mut results: Vec<Option<R>> = (0..len).map(|_| None).collect();
    for (i, r) in done.into_iter().flatten() {
        results[i] = Some(r);
    }
    results
        .into_iter()
        .map(|r| r.expect("every item ran"))
        .collect()
}

/// [`par_map`], reduced by `max`.
pub(super) fn par_max<T: Send>(items: Vec<T>, f: impl Fn(T) -> f64 + Sync) -> f64 {
    par_map(items, f).into_iter().fold(0.0, f64::max)
}
