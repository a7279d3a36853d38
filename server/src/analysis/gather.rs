//! Gathering the walks' per-vertex results into node order: owned-edge masks and coefficients,
//! then each node's subtree max |d| and empty children, bottom-up by id arithmetic.

use super::par::par_map;
use super::walk::{fold_children, load, Cell, Owner};
use super::{SCATTER_PARALLEL_FROM, SEQUENTIAL_BELOW};
use rayon::prelude::*;
use std::sync::atomic::AtomicU32;
use tetwave_protocol::Forest;

/// Per node the owned-edge mask, and the owned details in node order then edge order, from the
/// per-vertex owners the walks claimed (`cells[nv..]` and `detail[nv..]`: the new vertices).
pub(super) fn owned_coefficients<O: Owner>(
    cells: &[Cell<O>],
    detail: &[AtomicU32],
    nodes: usize,
    nv: usize,
) -> (Vec<u8>, Vec<f32>) {
    let n = cells.len();
    // owned masks and coefficients (node order, then edge order) from the per-vertex owners: each
    // part of the node range scans all owners and writes only its own masks and coefficients (no
    // atomics); the masks are padded to whole 8-node words for the rank computation
    let parts = if n >= SCATTER_PARALLEL_FROM {
        rayon::current_num_threads().clamp(1, 4)
    } else {
        1
    };
    let padded = nodes.next_multiple_of(8);
    let part_len = padded.div_ceil(parts).next_multiple_of(8).max(8);
    let mut owned = vec![0u8; padded];
    let owners = &cells[nv..];
    par_map(
        owned.chunks_mut(part_len).enumerate().collect(),
        |(p, masks): (usize, &mut [u8])| {
            let lo = (p * part_len) as u64;
            for c in owners {
                let c = O::wide(c.owner.load());
                debug_assert_ne!(c, O::wide(O::UNOWNED));
                let i = (c >> 3).wrapping_sub(lo) as usize;
                if i < masks.len() {
                    masks[i] |= 1 << (c & 7);
                }
            }
        },
    );
    // coefficients before each word of 8 nodes; within a word, the popcount of the bits below
    let words: Vec<u64> = owned
        .chunks_exact(8)
        .map(|w| u64::from_le_bytes(w.try_into().unwrap()))
        .collect();
    let mut word_offsets = Vec::with_capacity(words.len() + 1);
    let mut total = 0u64;
    for w in &words {
        word_offsets.push(total);
        total += w.count_ones() as u64;
    }
    word_offsets.push(total);
    owned.truncate(nodes);
    debug_assert_eq!(total as usize, n - nv);
    let mut coeffs = vec![0f32; total as usize];
    {
        // split the coefficients at the parts' node boundaries
        let mut rest: &mut [f32] = &mut coeffs;
        let mut tasks = Vec::with_capacity(parts);
        for p in 0..padded.div_ceil(part_len) {
            let (w0, w1) = (p * part_len / 8, ((p + 1) * part_len / 8).min(words.len()));
            let (head, tail) = rest.split_at_mut((word_offsets[w1] - word_offsets[w0]) as usize);
            tasks.push((w0, w1, head));
            rest = tail;
        }
        let (words, word_offsets) = (&words, &word_offsets);
        par_map(tasks, |(w0, w1, out): (usize, usize, &mut [f32])| {
            let base = word_offsets[w0];
            for (m, c) in owners.iter().enumerate() {
                let code = O::wide(c.owner.load());
                // bit position of (node, edge) in its word = 8 × (node mod 8) + edge = code mod 64
                let w = (code >> 6) as usize;
                if w < w0 || w >= w1 {
                    continue;
                }
                let at = word_offsets[w] - base
                    + (words[w] & ((1u64 << (code & 63)) - 1)).count_ones() as u64;
                out[at as usize] = load(&detail[nv + m]);
            }
        });
    }

    (owned, coeffs)
}

/// Subtree max |detail| and empty children of the levels above the last node level (which the
/// last walk folded into its parents), children first.
pub(super) fn fold_subtrees(
    forest: Forest,
    empty_children: &mut [u8],
    subtree_max_abs: &mut [f32],
) {
    let levels = forest.levels;
    // bottom-up: subtree max |detail| and empty children, by id arithmetic only (the last node level
    // was folded into its parents by the last walk)
    for k in (0..levels.saturating_sub(2)).rev() {
        let (s, e) = (
            forest.level_start(k) as usize,
            forest.level_start(k + 1) as usize,
        );
        let (this_empty, below_empty) = empty_children.split_at_mut(e);
        let (this_max, below_max) = subtree_max_abs.split_at_mut(e);
        let fold = |(j, (em, mx)): (usize, (&mut u8, &mut f32))| {
            let first = forest.child((s + j) as u64, 0) as usize - e;
            let c = first..first + 8;
            fold_children(mx, em, &below_max[c.clone()], &below_empty[c]);
        };
        if e - s >= SEQUENTIAL_BELOW {
            this_empty[s..e]
                .par_iter_mut()
                .zip(this_max[s..e].par_iter_mut())
                .enumerate()
                .for_each(fold);
        } else {
            this_empty[s..e]
                .iter_mut()
                .zip(this_max[s..e].iter_mut())
                .enumerate()
                .for_each(fold);
        }
    }
}
