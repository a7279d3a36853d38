//! A raw grid whose hierarchy does not fit `--memory` is prepared by parts in one process: its
//! peak RSS (measured by `wait4` on the real binary) stays under `--memory`, the store equals the
//! in-memory store of the same levels byte for byte, and a `--memory` below its smallest part
//! (one row of boxes) is refused with the least that works. One test in this file: it measures
//! its own child process.

mod ct_common;

use std::path::Path;
use std::process::{Command, Stdio};

const BIN: &str = env!("CARGO_BIN_EXE_tetwave-server");

/// A 129×129×257 u8 CT-like volume ([`ct_common::ct_field`] scaled to a byte).
fn write_ct(path: &Path) -> [usize; 3] {
    let dims = [129usize, 129, 257];
    let v: Vec<u8> = ct_common::ct_field(dims)
        .iter()
        .map(|x| (x / 5.0).min(255.0) as u8)
        .collect();
    std::fs::write(path, v).unwrap();
    dims
}

/// Runs the binary; its exit status, stdout, stderr and peak RSS in bytes.
// the child is reaped by `wait4`, which gives its resource usage (std's `wait` does not)
#[allow(clippy::zombie_processes)]
fn run(args: &[&str]) -> (bool, String, String, u64) {
    let child = Command::new(BIN)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id() as libc::pid_t;
    // drain the pipes on threads, then reap the child with its resource usage
    let mut out = child.stdout.unwrap();
    let mut err = child.stderr.unwrap();
    let t_out = std::thread::spawn(move || {
        let mut s = String::new();
        std::io::Read::read_to_string(&mut out, &mut s).unwrap();
        s
    });
    let t_err = std::thread::spawn(move || {
        let mut s = String::new();
        std::io::Read::read_to_string(&mut err, &mut s).unwrap();
        s
    });
    let mut status = 0;
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
    assert_eq!(r, pid, "wait4 failed");
    let ok = libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0;
    (
        ok,
        t_out.join().unwrap(),
        t_err.join().unwrap(),
        usage.ru_maxrss as u64 * 1024,
    )
}

#[test]
fn a_grid_larger_than_memory_is_prepared_by_parts_within_it() {
    let tmp = tempfile::tempdir().unwrap();
    let raw = tmp.path().join("ct.raw");
    let dims = write_ct(&raw);
    let dims_arg = format!("{},{},{}", dims[0], dims[1], dims[2]);
    let ooc = tmp.path().join("ooc");
    let common = [
        "prepare",
        raw.to_str().unwrap(),
        "--dims",
        &dims_arg,
        "--max-error",
        "0.5%",
    ];

    // 4.3 M vertices at 40 bytes: about 170 MB whole; 100 MiB makes it go by parts
    let memory = 100u64 << 20;
    let mut args = common.to_vec();
    args.extend(["--memory", "100M", "--json", "--out", ooc.to_str().unwrap()]);
    let (ok, out, err, peak) = run(&args);
    assert!(ok, "{err}");
    let s: serde_json::Value = serde_json::from_str(&out).unwrap();
    let levels = s["levels"].as_u64().unwrap();
    assert!(
        s["base"].as_str().unwrap().starts_with("kuhn-boxes"),
        "{}",
        s["base"]
    );
    assert!(
        peak <= memory,
        "peak RSS {peak} bytes over --memory {memory}"
    );
    eprintln!(
        "out of core: peak RSS {} MiB within --memory 100M",
        peak >> 20
    );

    // the same levels in memory: the same store
    let one = tmp.path().join("one");
    let levels_arg = levels.to_string();
    let mut args = common.to_vec();
    args.extend([
        "--levels",
        &levels_arg,
        "--json",
        "--out",
        one.to_str().unwrap(),
    ]);
    let (ok, _, err, peak_whole) = run(&args);
    assert!(ok, "{err}");
    eprintln!("in memory: peak RSS {} MiB", peak_whole >> 20);
    for e in std::fs::read_dir(&one).unwrap() {
        let name = e.unwrap().file_name();
        let (a, b) = (
            std::fs::read(one.join(&name)).unwrap(),
            std::fs::read(ooc.join(&name)).unwrap(),
        );
        assert!(a == b, "{name:?} differs");
    }
    assert!(!ooc.join("parts").exists());

    // too little for one row of boxes: refused, with the least that works, which works
    let small = tmp.path().join("small");
    let mut args = common.to_vec();
    args.extend(["--memory", "8M", "--out", small.to_str().unwrap()]);
    let (ok, _, err, _) = run(&args);
    assert!(!ok);
    assert!(
        err.contains("--memory 8388608") && err.contains("give --memory"),
        "{err}"
    );
    assert!(!small.join("manifest.json").exists());
    let least = err
        .split("give --memory ")
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .unwrap()
        .to_string();
    let mut args = common.to_vec();
    args.extend(["--memory", &least, "--out", small.to_str().unwrap()]);
    let (ok, _, err, peak) = run(&args);
    assert!(ok, "--memory {least}: {err}");
    let least_bytes = least.trim_end_matches('M').parse::<u64>().unwrap() << 20;
    assert!(peak <= least_bytes, "peak RSS {peak} over --memory {least}");
}
