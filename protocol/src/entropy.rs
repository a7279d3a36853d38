//! Adaptive binary models over `constriction`'s range coder: the entropy coding of
//! [`crate::block`].
//!
//! Every symbol is coded as binary decisions, each with a probability that adapts to what it has
//! seen (an exponential moving average in 16-bit fixed point); integers as an adaptive unary
//! bit-length followed by their mantissa bits. Encoder and decoder update the same models in the
//! same order, so a block decodes only with the contexts it was coded with: every block starts
//! from fresh models and depends on nothing outside itself.

use constriction::stream::model::{DecoderModel, EncoderModel, EntropyModel};
use constriction::stream::queue::{DefaultRangeDecoder, DefaultRangeEncoder};
use constriction::stream::{Decode, Encode};
use std::borrow::Borrow;
use std::num::NonZeroU32;

const PRECISION: usize = 16;
const ONE: u32 = 1 << PRECISION;
/// Adaptation rate: the probability moves 1/2^SHIFT of the way toward each new bit, once the
/// model has seen SHIFT bits; before that 1/2, 1/4, …: a fresh model (every block starts with
/// fresh ones) learns from its first bits at once, a settled one follows drifting statistics.
const SHIFT: u32 = 4;
/// Probabilities stay within [MIN_P, ONE - MIN_P] so that neither symbol becomes impossible.
const MIN_P: u32 = 31;

/// An adaptive probability that the next bit is 0.
#[derive(Debug, Clone, Copy)]
pub struct Bit {
    p0: u32,
    /// Bits seen, up to SHIFT.
    seen: u32,
}

impl Default for Bit {
    fn default() -> Self {
        Bit {
            p0: ONE / 2,
            seen: 0,
        }
    }
}

impl Bit {
    fn update(&mut self, bit: bool) {
        self.seen = (self.seen + 1).min(SHIFT);
        let shift = self.seen;
        if bit {
            self.p0 -= self.p0 >> shift;
        } else {
            self.p0 += (ONE - self.p0) >> shift;
        }
        self.p0 = self.p0.clamp(MIN_P, ONE - MIN_P);
    }
}

/// A fixed binary model (`p0` in 1/2^16), the form `constriction` codes with.
#[derive(Debug, Clone, Copy)]
struct Binary(u32);

impl EntropyModel<PRECISION> for Binary {
    type Symbol = bool;
    type Probability = u32;
}

impl EncoderModel<PRECISION> for Binary {
    fn left_cumulative_and_probability(
        &self,
        symbol: impl Borrow<bool>,
    ) -> Option<(u32, NonZeroU32)> {
        if *symbol.borrow() {
            Some((self.0, NonZeroU32::new(ONE - self.0)?))
        } else {
            Some((0, NonZeroU32::new(self.0)?))
        }
    }
}

impl DecoderModel<PRECISION> for Binary {
    fn quantile_function(&self, quantile: u32) -> (bool, u32, NonZeroU32) {
        if quantile < self.0 {
            (false, 0, NonZeroU32::new(self.0).expect("p0 >= MIN_P"))
        } else {
            (
                true,
                self.0,
                NonZeroU32::new(ONE - self.0).expect("p0 <= ONE - MIN_P"),
            )
        }
    }
}

/// `n` equiprobable bits (1 ≤ n ≤ 16) as one symbol: raw bits cost one coder step per 16.
#[derive(Debug, Clone, Copy)]
struct RawBits(u32);

impl EntropyModel<PRECISION> for RawBits {
    type Symbol = u32;
    type Probability = u32;
}

impl EncoderModel<PRECISION> for RawBits {
    fn left_cumulative_and_probability(
        &self,
        symbol: impl Borrow<u32>,
    ) -> Option<(u32, NonZeroU32)> {
        let (s, free) = (*symbol.borrow(), PRECISION as u32 - self.0);
        (s < 1 << self.0).then(|| {
            (
                s << free,
                NonZeroU32::new(1 << free).expect("a power of two"),
            )
        })
    }
}

impl DecoderModel<PRECISION> for RawBits {
    fn quantile_function(&self, quantile: u32) -> (u32, u32, NonZeroU32) {
        let free = PRECISION as u32 - self.0;
        let s = quantile >> free;
        (
            s,
            s << free,
            NonZeroU32::new(1 << free).expect("a power of two"),
        )
    }
}

/// The models of an unsigned integer: adaptive unary bit-length (up to [`UInt::MAX_BITS`]), then
/// the mantissa bits below the leading one, the first `UInt::MODELLED` of them adaptive.
#[derive(Debug, Clone)]
pub struct UInt {
    len: [Bit; UInt::MAX_BITS as usize + 1],
    mantissa: [[Bit; UInt::MODELLED]; UInt::MAX_BITS as usize + 1],
}

impl Default for UInt {
    fn default() -> Self {
        UInt {
            len: [Bit::default(); UInt::MAX_BITS as usize + 1],
            mantissa: [[Bit::default(); UInt::MODELLED]; UInt::MAX_BITS as usize + 1],
        }
    }
}

impl UInt {
    /// Largest bit length a coded integer may have.
    pub const MAX_BITS: u32 = 48;
    const MODELLED: usize = 2;
}

/// The models of a sequence of f32s kept bit for bit ([`Encoder::float`]): sign raw, the biased
/// exponent as its zigzag difference to the previous one's, the count `s` of mantissa bits down to
/// the lowest set one (context: the exponent) and the `s − 1` bits above that one raw. A difference
/// of two values of one binade is a multiple of their ulp, so its low mantissa bits are zeros and
/// cost nothing; smooth sequences keep their exponents close.
#[derive(Debug, Clone)]
pub struct Floats {
    exponent_delta: UInt,
    significant: Vec<UInt>,
    prev_exponent: u32,
}

impl Floats {
    /// Contexts of the mantissa length: the biased exponent minus `SIG_CONTEXT_FROM`, clamped.
    const SIG_CONTEXTS: usize = 48;
    const SIG_CONTEXT_FROM: u32 = 90;
    /// The exponent the first value is coded against (that of 2^−7).
    const FIRST_EXPONENT: u32 = 120;

    fn sig_context(exponent: u32) -> usize {
        (exponent.saturating_sub(Self::SIG_CONTEXT_FROM) as usize).min(Self::SIG_CONTEXTS - 1)
    }
}

impl Default for Floats {
    fn default() -> Self {
        Floats {
            exponent_delta: UInt::default(),
            significant: vec![UInt::default(); Self::SIG_CONTEXTS],
            prev_exponent: Self::FIRST_EXPONENT,
        }
    }
}

/// A signed integer as an unsigned one: 0, −1, 1, −2, … → 0, 1, 2, 3, …
pub fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

/// The inverse of [`zigzag`].
pub fn unzigzag(z: u64) -> i64 {
    (z >> 1) as i64 ^ -((z & 1) as i64)
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EntropyError {
    #[error("the coded data is invalid")]
    Invalid,
    #[error("integer {0} has more than {max} bits", max = UInt::MAX_BITS)]
    TooLarge(u64),
}

/// Writes binary decisions and integers.
pub struct Encoder {
    coder: DefaultRangeEncoder,
}

impl Default for Encoder {
    fn default() -> Self {
        Encoder {
            coder: DefaultRangeEncoder::new(),
        }
    }
}

impl Encoder {
    pub fn bit(&mut self, model: &mut Bit, bit: bool) {
        self.coder
            .encode_symbol(bit, Binary(model.p0))
            .expect("both symbols have nonzero probability");
        model.update(bit);
    }

    /// The low `n` bits of `v` (at most 64), each with probability 1/2, up to 16 at a time.
    pub fn raw(&mut self, v: u64, n: u32) {
        let mut i = 0;
        while i < n {
            let k = (n - i).min(16);
            self.coder
                .encode_symbol((v >> i & ((1 << k) - 1)) as u32, RawBits(k))
                .expect("every k-bit value has nonzero probability");
            i += k;
        }
    }

    pub fn uint(&mut self, model: &mut UInt, v: u64) -> Result<(), EntropyError> {
        self.uint_within(model, v, UInt::MAX_BITS)
    }

    /// [`Self::uint`] of a `v` known to both sides to have at most `max_bits` bits (at most
    /// [`UInt::MAX_BITS`]): the bit length's unary code stops at `max_bits`.
    pub fn uint_within(
        &mut self,
        model: &mut UInt,
        v: u64,
        max_bits: u32,
    ) -> Result<(), EntropyError> {
        let max_bits = max_bits.min(UInt::MAX_BITS);
        let bits = u64::BITS - v.leading_zeros();
        if bits > max_bits {
            return Err(EntropyError::TooLarge(v));
        }
        for i in 0..bits {
            self.bit(&mut model.len[i as usize], true);
        }
        if bits < max_bits {
            self.bit(&mut model.len[bits as usize], false);
        }
        // the mantissa below the leading one: the first MODELLED bits adaptive, the rest raw
        let below = bits.saturating_sub(1);
        let modelled = below.min(UInt::MODELLED as u32);
        for pos in 0..modelled {
            let b = v >> (below - 1 - pos) & 1 == 1;
            self.bit(&mut model.mantissa[bits as usize][pos as usize], b);
        }
        let rest = below - modelled;
        self.raw(v & ((1u64 << rest) - 1), rest);
        Ok(())
    }

    /// Every bit of `x` (see [`Floats`]).
    pub fn float(&mut self, model: &mut Floats, x: f32) -> Result<(), EntropyError> {
        let bits = x.to_bits();
        self.raw((bits >> 31) as u64, 1);
        let exponent = bits >> 23 & 0xff;
        self.uint(
            &mut model.exponent_delta,
            zigzag(exponent as i64 - model.prev_exponent as i64),
        )?;
        model.prev_exponent = exponent;
        let mantissa = bits & 0x7f_ffff;
        let sig = if mantissa == 0 {
            0
        } else {
            23 - mantissa.trailing_zeros()
        };
        self.uint_within(
            &mut model.significant[Floats::sig_context(exponent)],
            sig as u64,
            5,
        )?;
        // the bits above the lowest set one (which is implied)
        self.raw(
            (mantissa >> (24 - sig.max(1))) as u64,
            sig.saturating_sub(1),
        );
        Ok(())
    }

    /// The coded bytes (whole 32-bit words, little-endian).
    pub fn finish(self) -> Vec<u8> {
        let words = self
            .coder
            .into_compressed()
            .expect("a Vec backend cannot fail");
        words.iter().flat_map(|w| w.to_le_bytes()).collect()
    }
}

/// Reads what an [`Encoder`] wrote, with the same models in the same order.
pub struct Decoder {
    coder: DefaultRangeDecoder,
}

impl Decoder {
    pub fn new(bytes: &[u8]) -> Result<Self, EntropyError> {
        if !bytes.len().is_multiple_of(4) {
            return Err(EntropyError::Invalid);
        }
        let words: Vec<u32> = bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let coder =
            DefaultRangeDecoder::from_compressed(words).map_err(|_| EntropyError::Invalid)?;
        Ok(Decoder { coder })
    }

    pub fn bit(&mut self, model: &mut Bit) -> Result<bool, EntropyError> {
        let b = self
            .coder
            .decode_symbol(Binary(model.p0))
            .map_err(|_| EntropyError::Invalid)?;
        model.update(b);
        Ok(b)
    }

    pub fn raw(&mut self, n: u32) -> Result<u64, EntropyError> {
        let mut v = 0u64;
        let mut i = 0;
        while i < n {
            let k = (n - i).min(16);
            let w = self
                .coder
                .decode_symbol(RawBits(k))
                .map_err(|_| EntropyError::Invalid)?;
            v |= (w as u64) << i;
            i += k;
        }
        Ok(v)
    }

    pub fn uint(&mut self, model: &mut UInt) -> Result<u64, EntropyError> {
        self.uint_within(model, UInt::MAX_BITS)
    }

    /// Reads what [`Encoder::uint_within`] wrote with the same `max_bits`.
    pub fn uint_within(&mut self, model: &mut UInt, max_bits: u32) -> Result<u64, EntropyError> {
        let max_bits = max_bits.min(UInt::MAX_BITS);
        let mut bits = 0;
        while bits < max_bits && self.bit(&mut model.len[bits as usize])? {
            bits += 1;
        }
        if bits == 0 {
            return Ok(0);
        }
        let mut v = 1u64;
        let below = bits - 1;
        let modelled = below.min(UInt::MODELLED as u32);
        for pos in 0..modelled {
            v = v << 1 | self.bit(&mut model.mantissa[bits as usize][pos as usize])? as u64;
        }
        let rest = below - modelled;
        Ok(v << rest | self.raw(rest)?)
    }

    /// Reads what [`Encoder::float`] wrote (any f32, NaN and infinities included).
    pub fn float(&mut self, model: &mut Floats) -> Result<f32, EntropyError> {
        let sign = self.raw(1)? as u32;
        let exponent = model.prev_exponent as i64 + unzigzag(self.uint(&mut model.exponent_delta)?);
        if !(0..=0xff).contains(&exponent) {
            return Err(EntropyError::Invalid);
        }
        let exponent = exponent as u32;
        model.prev_exponent = exponent;
        let sig =
            self.uint_within(&mut model.significant[Floats::sig_context(exponent)], 5)? as u32;
        if sig > 23 {
            return Err(EntropyError::Invalid);
        }
        let mantissa = match sig {
            0 => 0,
            _ => ((self.raw(sig - 1)? as u32) << 1 | 1) << (23 - sig),
        };
        Ok(f32::from_bits(sign << 31 | exponent << 23 | mantissa))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn integers_and_bits_round_trip(vals in proptest::collection::vec(0u64..(1 << 47), 0..200), bits in proptest::collection::vec(any::<bool>(), 0..200), raws in proptest::collection::vec((any::<u64>(), 0u32..=64), 0..20)) {
            let (mut mu, mut mb) = (UInt::default(), Bit::default());
            let mut e = Encoder::default();
            for &v in &vals { e.uint(&mut mu, v).unwrap(); }
            for &b in &bits { e.bit(&mut mb, b); }
            e.raw(0xdead_beef, 32);
            for &(v, n) in &raws { e.raw(v, n); }
            let bytes = e.finish();
            let (mut mu, mut mb) = (UInt::default(), Bit::default());
            let mut d = Decoder::new(&bytes).unwrap();
            for &v in &vals { prop_assert_eq!(d.uint(&mut mu).unwrap(), v); }
            for &b in &bits { prop_assert_eq!(d.bit(&mut mb).unwrap(), b); }
            prop_assert_eq!(d.raw(32).unwrap(), 0xdead_beef);
            for &(v, n) in &raws {
                let mask = if n == 64 { u64::MAX } else { (1u64 << n) - 1 };
                prop_assert_eq!(d.raw(n).unwrap(), v & mask);
            }
        }

        #[test]
        fn decoding_garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            if let Ok(mut d) = Decoder::new(&bytes) {
                let mut m = UInt::default();
                for _ in 0..64 { if d.uint(&mut m).is_err() { break; } }
            }
        }
    }

    #[test]
    fn skewed_bits_cost_little() {
        let mut m = Bit::default();
        let mut e = Encoder::default();
        for i in 0..10_000 {
            e.bit(&mut m, i % 100 == 0);
        }
        // entropy of p = 0.01 is 0.081 bits; allow the adaptation's overhead
        let bytes = e.finish().len();
        assert!(bytes * 8 < 10_000 * 15 / 100, "{bytes} bytes");
    }
}
