//! The small mesh every valid reader fixture holds (see `scripts/gen-fixtures.py`), and the byte
//! corruptor of the no-panic suites: shared by `mesh_io.rs` and `import_formats.rs`.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

pub fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

use tetwave_protocol::shapes::{box_corners, kuhn_grid};

/// The fixtures' cube `[LO, HI]`; its corners are points 0–7, then the apex is point 8.
pub const LO: [f64; 3] = [0.1, 0.2, 0.3];
pub const HI: [f64; 3] = [0.8, 0.9, 1.0];
pub const APEX: [f64; 3] = [0.45, 0.55, 1.4];

/// The cube's corners (`x + 2y + 4z` order), then the apex.
pub fn cube_points() -> Vec<[f64; 3]> {
    let mut p = box_corners(LO, HI);
    p.push(APEX);
    p
}

/// The cube's 6 Kuhn tets as `kuhn_grid(1)` lists them (not reoriented), then the apex tet on the
/// top face: the 7 tets of every valid fixture, in file order.
pub fn tets() -> Vec<[u32; 4]> {
    let (_, mut t) = kuhn_grid(1, |_, _, _| true);
    t.push([4, 5, 7, 8]);
    t
}

pub fn temperature(p: [f64; 3]) -> f64 {
    p[0] + 2.0 * p[1] + 3.0 * p[2]
}

/// Reproducible random corruption of file bytes (xorshift64).
pub struct Corruptor(u64);

impl Corruptor {
    pub fn new(seed: u64) -> Self {
        Corruptor(seed)
    }

    /// A uniform index below `n` (0 for `n = 0`).
    pub fn next(&mut self, n: usize) -> usize {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 % n.max(1) as u64) as usize
    }

    /// `bytes` with `1 + round % 4` random edits: a random byte, a digit, a `9`, a syntax byte,
    /// a deleted run or a duplicated run. Never empty.
    pub fn corrupt(&mut self, bytes: &[u8], round: usize) -> Vec<u8> {
        let mut b = bytes.to_vec();
        for _ in 0..1 + round % 4 {
            let i = self.next(b.len());
            match self.next(6) {
                0 => b[i] = self.next(256) as u8,
                1 => b[i] = b"0123456789"[self.next(10)],
                2 => b[i] = b'9',
                3 => b[i] = b"-.e \n<>$_="[self.next(10)],
                4 => {
                    let end = (i + 1 + self.next(16)).min(b.len());
                    b.drain(i..end);
                }
                _ => {
                    let end = (i + 1 + self.next(16)).min(b.len());
                    let run = b[i..end].to_vec();
                    b.splice(i..i, run);
                }
            }
            if b.is_empty() {
                b.push(b'x');
            }
        }
        b
    }
}
