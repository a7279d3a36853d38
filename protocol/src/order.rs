//! The seeded shuffle behind every test order: the server's `random` stream order, the client's
//! random arrival order and the tests' shuffles. It is part of the contract only in that both sides
//! reproduce the same order from the same seed; no wire frame carries it.

/// SplitMix64's step: adds the golden-ratio increment to `x` and mixes the sum. Feeding each output
/// back in (`s = splitmix(s)`) gives the sequence [`shuffle`] draws from.
pub fn splitmix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    let mut z = x;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Fisher–Yates shuffle of `v` seeded by `seed`: from the last slot down, slot `i` swaps with
/// `s % (i + 1)` where `s = splitmix(s)` is drawn anew for each slot. The same seed and length
/// always give the same permutation.
pub fn shuffle<T>(v: &mut [T], seed: u64) {
    let mut s = seed;
    for i in (1..v.len()).rev() {
        s = splitmix(s);
        v.swap(i, (s % (i as u64 + 1)) as usize);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shuffle_is_a_reproducible_permutation() {
        let mut a: Vec<u32> = (0..1000).collect();
        let mut b = a.clone();
        shuffle(&mut a, 42);
        shuffle(&mut b, 42);
        assert_eq!(a, b);
        assert_ne!(a, (0..1000).collect::<Vec<_>>());
        let mut sorted = a.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..1000).collect::<Vec<_>>());
    }

    #[test]
    fn splitmix_matches_the_reference_sequence() {
        // SplitMix64 seeded with 0: its first outputs (Vigna's reference implementation)
        assert_eq!(splitmix(0), 0xe220_a839_7b1d_cdaf);
        assert_eq!(splitmix(0x9e37_79b9_7f4a_7c15), 0x6e78_9e6a_a1b9_65f4);
    }

    #[test]
    fn shuffles_of_zero_or_one_element_are_identity() {
        let mut e: [u8; 0] = [];
        shuffle(&mut e, 7);
        let mut one = [9u8];
        shuffle(&mut one, 7);
        assert_eq!(one, [9]);
    }
}
