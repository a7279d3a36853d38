//! A fuzzing run without libFuzzer (stable Rust): random byte strings, and valid frames with random
//! byte flips, insertions, deletions, truncations and length-prefix rewrites, into the decoders.
//! `cargo run --release --bin fuzz_smoke -- [executions] [seed] [volumes]`; prints the count; a
//! failed check panics (exit code ≠ 0) after printing the offending input in hex. With `volumes`,
//! the inputs are volume files (NIfTI, NRRD, VTK image data; random bytes and mutated seeds,
//! cycling through the formats) into `tetwave_fuzz::volume::check`.

use tetwave_fuzz::volume::{self, Target};

fn main() {
    let mut args = std::env::args().skip(1);
    let runs: u64 = args
        .next()
        .and_then(|a| a.parse().ok())
        .unwrap_or(1_000_000);
    let mut s: u64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(0x5eed) | 1;
    let mut rnd = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let volumes = args.next().as_deref() == Some("volumes");
    let seeds = tetwave_fuzz::seed_frames();
    let volume_seeds: Vec<Vec<Vec<u8>>> = Target::ALL.iter().map(|&t| volume::seeds(t)).collect();
    let t0 = std::time::Instant::now();
    let mut buf = Vec::new();
    for i in 0..runs {
        buf.clear();
        let target = (i % Target::ALL.len() as u64) as usize;
        let seeds = if volumes {
            &volume_seeds[target]
        } else {
            &seeds
        };
        if i % 4 == 0 {
            let n = (rnd() % 300) as usize;
            buf.extend((0..n).map(|_| rnd() as u8));
        } else {
            buf.extend_from_slice(&seeds[(rnd() % seeds.len() as u64) as usize]);
            let edits = 1 + rnd() % 6;
            for _ in 0..edits {
                let len = buf.len().max(1);
                match rnd() % 6 {
                    0 | 1 => {
                        let at = (rnd() as usize) % len;
                        if at < buf.len() {
                            buf[at] ^= (rnd() as u8) | 1;
                        }
                    }
                    2 => {
                        let at = (rnd() as usize) % (buf.len() + 1);
                        buf.insert(at, rnd() as u8);
                    }
                    3 => {
                        if !buf.is_empty() {
                            let at = (rnd() as usize) % buf.len();
                            buf.remove(at);
                        }
                    }
                    4 => buf.truncate((rnd() as usize) % (buf.len() + 1)),
                    _ if volumes => {
                        // a run of bytes repeated or dropped: headers with lines and fields
                        // moved, duplicated or cut
                        let a = (rnd() as usize) % (buf.len() + 1);
                        let b = (a + (rnd() as usize) % 64).min(buf.len());
                        if rnd() % 2 == 0 {
                            let run = buf[a..b].to_vec();
                            buf.splice(a..a, run);
                        } else {
                            buf.drain(a..b);
                        }
                    }
                    _ => {
                        // keep the length prefix consistent with the (edited) payload, so the
                        // decoder gets past the framing checks into the message itself
                        if buf.len() >= 4 {
                            let l = (buf.len() - 4) as u32;
                            buf[..4].copy_from_slice(&l.to_le_bytes());
                        }
                    }
                }
            }
        }
        let r = std::panic::catch_unwind(|| {
            if volumes {
                volume::check(Target::ALL[target], &buf)
            } else {
                tetwave_fuzz::check(&buf)
            }
        });
        if r.is_err() {
            if volumes {
                eprintln!("format: {}", Target::ALL[target].name());
            }
            let hex: String = buf.iter().map(|b| format!("{b:02x}")).collect();
            eprintln!("failing input after {i} executions: {hex}");
            std::process::exit(1);
        }
    }
    println!(
        "fuzz_smoke: {runs} executions, no failure, {:.1} s",
        t0.elapsed().as_secs_f64()
    );
}
