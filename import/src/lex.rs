//! What the readers share: [`Bad`] (an error before the path is attached), [`Lex`] (a cursor over
//! the file's bytes) and the checks that keep a count or an index read from a file from allocating
//! or indexing past what the file holds.

/// A reader's error before the path is attached: the section of the file and what is wrong.
#[derive(Debug)]
pub(crate) struct Bad {
    pub(super) section: String,
    pub(super) reason: String,
}

impl Bad {
    pub(crate) fn new(section: impl Into<String>, reason: impl Into<String>) -> Bad {
        Bad {
            section: section.into(),
            reason: reason.into(),
        }
    }
}

pub(crate) type Res<T> = Result<T, Bad>;

/// Position of `needle` in `hay`.
pub(crate) fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    if needle.is_empty() || hay.len() < needle.len() {
        return None;
    }
    hay.windows(needle.len()).position(|w| w == needle)
}

/// A capacity for `n` items of at least `item_bytes` bytes each read from `remaining` bytes of
/// input: never more than the input can hold, so that a lying count cannot allocate.
pub(crate) fn capacity(n: usize, item_bytes: usize, remaining: usize) -> usize {
    n.min(remaining / item_bytes.max(1) + 1)
}

/// Converts a point index read from a file, checking it against the number of points.
pub(crate) fn point_index(v: i64, base: usize, n_points: usize) -> Option<u32> {
    let v = usize::try_from(v).ok()?;
    if v >= n_points {
        return None;
    }
    u32::try_from(base.checked_add(v)?).ok()
}

/// A file shown in an error: at most 40 characters, lossy UTF-8.
pub(crate) fn show(bytes: &[u8]) -> String {
    let s = String::from_utf8_lossy(&bytes[..bytes.len().min(40)]).into_owned();
    if bytes.len() > 40 {
        format!("{s}...")
    } else {
        s
    }
}

/// Byte order of binary data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Endian {
    Little,
    Big,
}

/// A cursor over a file's bytes: whitespace-separated tokens, lines and raw binary runs.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Lex<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Lex<'a> {
    pub(crate) fn new(b: &'a [u8]) -> Self {
        Lex { b, pos: 0 }
    }

    pub(crate) fn remaining(&self) -> usize {
        self.b.len().saturating_sub(self.pos)
    }

    pub(crate) fn skip_ws(&mut self) {
        while self.b.get(self.pos).is_some_and(u8::is_ascii_whitespace) {
            self.pos += 1;
        }
    }

    /// The next run of non-whitespace bytes; `None` at the end of the file.
    pub(crate) fn token(&mut self) -> Option<&'a [u8]> {
        self.skip_ws();
        let start = self.pos;
        while self
            .b
            .get(self.pos)
            .is_some_and(|c| !c.is_ascii_whitespace())
        {
            self.pos += 1;
        }
        self.b.get(start..self.pos).filter(|t| !t.is_empty())
    }

    pub(crate) fn peek_token(&self) -> Option<&'a [u8]> {
        let mut copy = *self;
        copy.token()
    }

    /// The rest of the current line, without its end (`\n` or `\r\n`), which is consumed;
    /// `None` at the end of the file.
    pub(crate) fn line(&mut self) -> Option<&'a [u8]> {
        if self.pos >= self.b.len() {
            return None;
        }
        let rest = self.b.get(self.pos..)?;
        let len = rest.iter().position(|&c| c == b'\n').unwrap_or(rest.len());
        self.pos += (len + 1).min(rest.len());
        let line = rest.get(..len)?;
        Some(line.strip_suffix(b"\r").unwrap_or(line))
    }

    /// Moves past the next occurrence of `needle`; `false` (and no move) if there is none.
    pub(crate) fn skip_past(&mut self, needle: &[u8]) -> bool {
        match self.b.get(self.pos..).and_then(|rest| find(rest, needle)) {
            Some(at) => {
                self.pos += at + needle.len();
                true
            }
            None => false,
        }
    }

    /// The next `n` bytes as they are.
    pub(crate) fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let run = self.b.get(self.pos..end)?;
        self.pos = end;
        Some(run)
    }
}
