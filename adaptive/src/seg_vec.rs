//! [`SegVec`]: a growable array in fixed segments that never moves what it holds (the adaptive
//! mesh's node and vertex arrays and the selector's per-slot arrays).

const SEG_BITS: u32 = 10;
const SEG_LEN: usize = 1 << SEG_BITS;
const SEG_MASK: usize = SEG_LEN - 1;

/// A growable array stored in fixed segments of [`SEG_LEN`] items: growing never moves (copies) what
/// it holds, so no single push costs more than allocating one segment, whatever the length. The
/// mesh's node and vertex arrays and the selector's per-slot arrays use it; a `Vec` that doubles or
/// grows by a fraction copies all of it at once (tens of ms for the node array of a level-6 mesh).
#[derive(Clone)]
pub(crate) struct SegVec<T> {
    /// Fixed-size segments: an index masked to a segment needs no bounds check.
    segs: Vec<Box<[T; SEG_LEN]>>,
    len: usize,
}

impl<T: Copy> SegVec<T> {
    pub(crate) const fn new() -> Self {
        SegVec {
            segs: Vec::new(),
            len: 0,
        }
    }

    #[inline]
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Items held by the allocated segments.
    #[inline]
    pub(crate) fn capacity(&self) -> usize {
        self.segs.len() * SEG_LEN
    }

    /// Bytes held (segments and the segment table).
    pub(crate) fn bytes(&self) -> usize {
        self.capacity() * std::mem::size_of::<T>()
            + self.segs.capacity() * std::mem::size_of::<Box<[T; SEG_LEN]>>()
    }

    #[inline]
    pub(crate) fn push(&mut self, x: T) {
        if self.len == self.capacity() {
            self.segs.push(segment(x));
        }
        let i = self.len;
        self.len += 1;
        self.segs[i >> SEG_BITS][i & SEG_MASK] = x;
    }

    /// Sets the length to `n`, filling new items with `x`.
    pub(crate) fn resize(&mut self, n: usize, x: T) {
        while self.len < n {
            if self.len == self.capacity() {
                self.segs.push(segment(x));
                self.len = (self.len + SEG_LEN).min(n);
            } else {
                let i = self.len;
                let end = (i | SEG_MASK) + 1;
                let end = end.min(n);
                self.segs[i >> SEG_BITS][i & SEG_MASK..((end - 1) & SEG_MASK) + 1].fill(x);
                self.len = end;
            }
        }
        self.len = n;
    }

    /// The segment of item `i < len`, without a second bounds check: `len ≤ segs.len() · SEG_LEN`
    /// always holds (`push` and `resize` add a segment before the length passes it, `clear` only
    /// lowers it), so the caller's check of `i` covers the segment table too. Indexing checked
    /// both: 7 % of the selection's instructions at level 5, 10%.
    #[inline(always)]
    fn seg(&self, i: usize) -> &[T; SEG_LEN] {
        debug_assert!(i < self.len && i >> SEG_BITS < self.segs.len());
        // SAFETY: `i < len ≤ segs.len() · SEG_LEN`, see above
        unsafe { self.segs.get_unchecked(i >> SEG_BITS) }
    }

    /// [`Self::seg`], mutable.
    #[inline(always)]
    fn seg_mut(&mut self, i: usize) -> &mut [T; SEG_LEN] {
        debug_assert!(i < self.len && i >> SEG_BITS < self.segs.len());
        // SAFETY: as in `seg`
        unsafe { self.segs.get_unchecked_mut(i >> SEG_BITS) }
    }

    /// Asks the CPU to bring item `i` into the cache (a hint: nothing when `i` is out of range or
    /// on other architectures).
    #[inline(always)]
    pub(crate) fn prefetch(&self, i: usize) {
        if i < self.len {
            let p: *const T = &self.seg(i)[i & SEG_MASK];
            #[cfg(target_arch = "x86_64")]
            // SAFETY: a prefetch reads nothing architecturally; `p` points into a live segment
            unsafe {
                use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
                _mm_prefetch::<_MM_HINT_T0>(p as *const i8);
            }
            #[cfg(not(target_arch = "x86_64"))]
            let _ = p;
        }
    }

    /// Empties it, keeping the segments.
    pub(crate) fn clear(&mut self) {
        self.len = 0;
    }

    #[inline]
    pub(crate) fn get(&self, i: usize) -> Option<&T> {
        if i < self.len {
            Some(&self.seg(i)[i & SEG_MASK])
        } else {
            None
        }
    }

    /// The contiguous run of items from `i` to `end` or to the end of `i`'s segment, whichever
    /// comes first (`i < end ≤ len`).
    #[inline]
    pub(crate) fn run(&self, i: usize, end: usize) -> &[T] {
        assert!(i < end && end <= self.len);
        let stop = ((i | SEG_MASK) + 1).min(end);
        &self.segs[i >> SEG_BITS][i & SEG_MASK..((stop - 1) & SEG_MASK) + 1]
    }

    pub(crate) fn iter(&self) -> impl Iterator<Item = &T> + '_ {
        self.segs.iter().flat_map(|s| s.iter()).take(self.len)
    }
}

/// One segment filled with `x`.
fn segment<T: Copy>(x: T) -> Box<[T; SEG_LEN]> {
    vec![x; SEG_LEN]
        .into_boxed_slice()
        .try_into()
        .unwrap_or_else(|_| unreachable!("SEG_LEN items"))
}

impl<T: Copy> Default for SegVec<T> {
    fn default() -> Self {
        SegVec::new()
    }
}

impl<T: Copy> std::ops::Index<usize> for SegVec<T> {
    type Output = T;
    #[inline]
    fn index(&self, i: usize) -> &T {
        assert!(i < self.len, "index {i} out of {}", self.len);
        &self.seg(i)[i & SEG_MASK]
    }
}

impl<T: Copy> std::ops::IndexMut<usize> for SegVec<T> {
    #[inline]
    fn index_mut(&mut self, i: usize) -> &mut T {
        assert!(i < self.len, "index {i} out of {}", self.len);
        &mut self.seg_mut(i)[i & SEG_MASK]
    }
}

impl<T> std::fmt::Debug for SegVec<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "SegVec(len {})", self.len)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segvec_matches_vec() {
        let mut s: SegVec<u32> = SegVec::new();
        let mut v: Vec<u32> = Vec::new();
        for i in 0..(3 * SEG_LEN as u32 + 17) {
            s.push(i);
            v.push(i);
        }
        s.resize(5 * SEG_LEN + 3, 7);
        v.resize(5 * SEG_LEN + 3, 7);
        s[SEG_LEN] = 99;
        v[SEG_LEN] = 99;
        assert_eq!(s.len(), v.len());
        assert!(s.capacity() >= s.len() && s.capacity().is_multiple_of(SEG_LEN));
        assert!(s.iter().copied().eq(v.iter().copied()));
        assert_eq!(s.get(v.len()), None);
        // runs cover any range segment by segment
        let (a, b) = (SEG_LEN - 5, 4 * SEG_LEN + 11);
        let mut i = a;
        let mut got = Vec::new();
        while i < b {
            let r = s.run(i, b);
            assert!(!r.is_empty() && r.len() <= SEG_LEN);
            got.extend_from_slice(r);
            i += r.len();
        }
        assert_eq!(got, v[a..b]);
        s.clear();
        assert_eq!(s.len(), 0);
        s.resize(10, 1);
        assert!(s.iter().all(|&x| x == 1));
    }
}
