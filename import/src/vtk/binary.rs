//! Binary `.vtu` arrays: base64 decoding, the block header and zlib inflation of compressed
//! arrays, over inline base64, appended base64 or appended raw bytes.

use std::borrow::Cow;
use std::io::Read;

use crate::lex::{Bad, Endian, Lex, Res};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Compression {
    None,
    Zlib,
}

/// How binary arrays are laid out.
#[derive(Debug, Clone, Copy)]
pub(super) struct Encoding {
    pub(super) endian: Endian,
    pub(super) header64: bool,
    pub(super) compression: Compression,
}

/// Base64 text decoded lazily, quantum by quantum; a padded quantum ends a segment and the next
/// one starts afresh, so separately encoded runs decode to their concatenation.
pub(super) struct Base64<'a> {
    text: &'a [u8],
    pos: usize,
    buf: Vec<u8>,
    start: usize,
}

fn b64_value(c: u8) -> Option<u8> {
    Some(match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => return None,
    })
}

impl<'a> Base64<'a> {
    pub(super) fn new(text: &'a [u8]) -> Self {
        Base64 {
            text,
            pos: 0,
            buf: Vec::new(),
            start: 0,
        }
    }

    /// At most this many bytes are left to decode.
    fn remaining_max(&self) -> usize {
        (self.buf.len() - self.start) + self.text.len().saturating_sub(self.pos) / 4 * 3 + 3
    }

    /// Decodes one quantum into `buf`; `Ok(false)` at the end of the text.
    fn quantum(&mut self) -> Result<bool, String> {
        let mut q = [0u8; 4];
        let mut n = 0;
        let mut pad = 0;
        while n < 4 {
            let Some(&c) = self.text.get(self.pos) else {
                break;
            };
            self.pos += 1;
            if c.is_ascii_whitespace() {
                continue;
            }
            if c == b'=' {
                pad += 1;
                q[n] = 0;
                n += 1;
                continue;
            }
            if pad > 0 {
                return Err("base64 data continues after padding inside a quantum".into());
            }
            q[n] = b64_value(c).ok_or_else(|| format!("byte {c:#04x} is not base64"))?;
            n += 1;
        }
        let bytes = match (n, pad) {
            (0, _) => return Ok(false),
            (4, 0) => 3,
            (4, 1) | (3, 0) => 2,
            (4, 2) | (2, 0) => 1,
            _ => return Err("truncated or malformed base64 quantum".into()),
        };
        let v = (u32::from(q[0]) << 18)
            | (u32::from(q[1]) << 12)
            | (u32::from(q[2]) << 6)
            | u32::from(q[3]);
        let b = [(v >> 16) as u8, (v >> 8) as u8, v as u8];
        self.buf.extend_from_slice(&b[..bytes]);
        Ok(true)
    }

    fn read(&mut self, n: usize) -> Result<Option<Vec<u8>>, String> {
        if self.start > (1 << 20) {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        while self.buf.len() - self.start < n {
            if !self.quantum()? {
                return Ok(None);
            }
        }
        let out = self.buf.get(self.start..self.start + n).map(<[u8]>::to_vec);
        self.start += n;
        Ok(out)
    }
}

/// Where a binary array's bytes come from.
pub(super) enum Stream<'a> {
    Raw(Lex<'a>),
    Base64(Base64<'a>),
}

impl<'a> Stream<'a> {
    fn remaining_max(&self) -> usize {
        match self {
            Stream::Raw(lx) => lx.remaining(),
            Stream::Base64(b) => b.remaining_max(),
        }
    }

    fn read(&mut self, n: usize, what: &str) -> Res<Cow<'a, [u8]>> {
        let got = match self {
            Stream::Raw(lx) => lx.take(n).map(Cow::Borrowed),
            Stream::Base64(b) => b.read(n).map_err(|e| Bad::new(what, e))?.map(Cow::Owned),
        };
        got.ok_or_else(|| {
            Bad::new(
                what,
                format!("file is truncated: the data ends before {n} more bytes"),
            )
        })
    }

    fn word(&mut self, enc: Encoding, what: &str) -> Res<usize> {
        let size = if enc.header64 { 8 } else { 4 };
        let b = self.read(size, what)?;
        let mut a = [0u8; 8];
        let v = match enc.endian {
            Endian::Little => {
                a[..size].copy_from_slice(&b);
                u64::from_le_bytes(a)
            }
            Endian::Big => {
                a[8 - size..].copy_from_slice(&b);
                u64::from_be_bytes(a)
            }
        };
        usize::try_from(v).map_err(|_| Bad::new(what, format!("header value {v} is too large")))
    }
}

/// Reads one binary array (its header, then the data, inflated when compressed).
pub(super) fn read_binary(s: &mut Stream<'_>, enc: Encoding, what: &str) -> Res<Vec<u8>> {
    let truncated = |claim: usize, left: usize| {
        Bad::new(what, format!("file is truncated: the array header claims {claim} bytes but at most {left} remain"))
    };
    match enc.compression {
        Compression::None => {
            let n = s.word(enc, what)?;
            if n > s.remaining_max() {
                return Err(truncated(n, s.remaining_max()));
            }
            Ok(s.read(n, what)?.into_owned())
        }
        Compression::Zlib => {
            let word = if enc.header64 { 8 } else { 4 };
            let nb = s.word(enc, what)?;
            if nb.saturating_mul(word) > s.remaining_max() {
                return Err(truncated(nb.saturating_mul(word), s.remaining_max()));
            }
            let block = s.word(enc, what)?;
            let last = s.word(enc, what)?;
            let sizes = (0..nb)
                .map(|_| s.word(enc, what))
                .collect::<Res<Vec<usize>>>()?;
            let total = sizes
                .iter()
                .try_fold(0usize, |a, &b| a.checked_add(b))
                .unwrap_or(usize::MAX);
            if total > s.remaining_max() {
                return Err(truncated(total, s.remaining_max()));
            }
            let mut out = Vec::new();
            for (i, &c) in sizes.iter().enumerate() {
                let comp = s.read(c, what)?;
                let want = if i + 1 == nb && last != 0 {
                    last
                } else {
                    block
                };
                let before = out.len();
                flate2::read::ZlibDecoder::new(&comp[..])
                    .take(want as u64 + 1)
                    .read_to_end(&mut out)
                    .map_err(|e| {
                        Bad::new(what, format!("zlib block {i} of {nb} is corrupt: {e}"))
                    })?;
                if out.len() - before != want {
                    return Err(Bad::new(
                        what,
                        format!(
                            "zlib block {i} of {nb} inflates to {} bytes; the header says {want}",
                            out.len() - before
                        ),
                    ));
                }
            }
            Ok(out)
        }
    }
}
