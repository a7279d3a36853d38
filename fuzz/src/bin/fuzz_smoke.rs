//! A fuzzing run without libFuzzer (stable Rust): random byte strings, and valid frames with random
//! byte flips, insertions, deletions, truncations and length-prefix rewrites, into the decoders.
//! `cargo run --release --bin fuzz_smoke -- [executions] [seed]`; prints the count; a failed check
//! panics (exit code ≠ 0) after printing the offending input in hex.

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
    let seeds = tetwave_fuzz::seed_frames();
    let t0 = std::time::Instant::now();
    let mut buf = Vec::new();
    for i in 0..runs {
        buf.clear();
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
        let r = std::panic::catch_unwind(|| tetwave_fuzz::check(&buf));
        if r.is_err() {
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
