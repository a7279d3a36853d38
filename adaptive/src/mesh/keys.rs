//! The vertex key → slot table.

use super::NONE;
use crate::seg_vec::SegVec;

/// Keys per page of [`KeySlots`].
const KEY_PAGE_BITS: u32 = 4;

const KEY_PAGE: usize = 1 << KEY_PAGE_BITS;

/// Vertex slot by vertex key (`NONE`: absent), in pages of [`KEY_PAGE`] keys made on first use and
/// recycled when emptied. A view-dependent mesh holds a few of the hierarchy's keys, scattered:
/// a dense table sized for every key costs far more per leaf than small pages plus a directory
/// of 0.25 B per key (docs/benchmarks.md, "Vertex key table"). No operation moves the table (pages sit
/// in a [`SegVec`]), so it never stalls a frame the way a growing hash map's rehash would.
#[derive(Clone, Debug)]
pub(super) struct KeySlots {
    /// Page index by key / [`KEY_PAGE`] (`NONE`: no page); sized once for every key.
    dir: Vec<u32>,
    pages: SegVec<[u32; KEY_PAGE]>,
    /// Present keys per page.
    fill: SegVec<u8>,
    free: Vec<u32>,
}

impl KeySlots {
    pub(super) fn new(nkeys: usize) -> Self {
        KeySlots {
            dir: vec![NONE; nkeys.div_ceil(KEY_PAGE)],
            pages: SegVec::new(),
            fill: SegVec::new(),
            free: Vec::new(),
        }
    }

    #[inline]
    pub(super) fn get(&self, key: u64) -> u32 {
        match self.dir[(key >> KEY_PAGE_BITS) as usize] {
            NONE => NONE,
            p => self.pages[p as usize][key as usize & (KEY_PAGE - 1)],
        }
    }

    /// Maps absent key `key` to `slot`.
    pub(super) fn insert(&mut self, key: u64, slot: u32) {
        let d = (key >> KEY_PAGE_BITS) as usize;
        let p = match self.dir[d] {
            NONE => {
                let p = match self.free.pop() {
                    Some(p) => p,
                    None => {
                        self.pages.push([NONE; KEY_PAGE]);
                        self.fill.push(0);
                        (self.pages.len() - 1) as u32
                    }
                };
                self.dir[d] = p;
                p
            }
            p => p,
        } as usize;
        let e = &mut self.pages[p][key as usize & (KEY_PAGE - 1)];
        debug_assert_eq!(*e, NONE, "key {key} mapped twice");
        *e = slot;
        self.fill[p] += 1;
    }

    /// Unmaps present key `key`.
    pub(super) fn remove(&mut self, key: u64) {
        let d = (key >> KEY_PAGE_BITS) as usize;
        let p = self.dir[d] as usize;
        let e = &mut self.pages[p][key as usize & (KEY_PAGE - 1)];
        debug_assert_ne!(*e, NONE, "key {key} not mapped");
        *e = NONE;
        self.fill[p] -= 1;
        if self.fill[p] == 0 {
            self.dir[d] = NONE;
            self.free.push(p as u32);
        }
    }

    /// Keys mapped.
    pub(super) fn count(&self) -> usize {
        self.fill.iter().map(|&f| f as usize).sum()
    }

    pub(super) fn bytes(&self) -> usize {
        self.dir.capacity() * 4 + self.pages.bytes() + self.fill.bytes() + self.free.capacity() * 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_protocol::order::splitmix;

    /// The paged key table against a map, with pages emptied, recycled and refilled.
    #[test]
    fn key_slots_match_a_map() {
        let nkeys = 1000u64;
        let mut t = KeySlots::new(nkeys as usize);
        let mut want = std::collections::BTreeMap::new();
        for step in 0..20_000u32 {
            let x = splitmix(step as u64);
            // keys clustered in a window that drifts, so pages empty and come back
            let key = ((x >> 33) % 96 + (step as u64 / 50) % (nkeys - 96)) % nkeys;
            if want.remove(&key).is_some() {
                t.remove(key);
            } else {
                want.insert(key, step);
                t.insert(key, step);
            }
            if step % 997 == 0 {
                for k in 0..nkeys {
                    assert_eq!(t.get(k), want.get(&k).copied().unwrap_or(NONE), "key {k}");
                }
            }
        }
        assert_eq!(t.count(), want.len());
        // the pages in use are exactly those of the present keys (emptied ones are recycled)
        let used = t.pages.len() - t.free.len();
        let mut pages: Vec<u64> = want.keys().map(|k| k >> KEY_PAGE_BITS).collect();
        pages.dedup();
        assert_eq!(used, pages.len());
    }
}
