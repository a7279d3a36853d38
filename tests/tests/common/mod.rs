//! Helpers shared by the cross-crate tests that run `tetwave bench progressive` on a store.
#![allow(dead_code)] // each test binary uses some of the helpers

use clap::Parser;
use std::path::PathBuf;
use tetwave_client::progressive::BenchArgs;
use tetwave_server::prepare::{prepare, PrepareOptions};

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    bench: BenchArgs,
}

/// A harmonic store of `levels` levels prepared by the server in a new temporary directory (kept
/// while the returned guard lives), and its path.
pub fn harmonic_store(levels: u8) -> (tempfile::TempDir, PathBuf) {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("s");
    let mut o = PrepareOptions::new("synthetic:harmonic", &store);
    o.levels = levels;
    prepare(&o).unwrap();
    (d, store)
}

/// `tetwave bench progressive` arguments, parsed as the CLI parses them (`args` without the
/// subcommand's name).
pub fn bench_args(args: &[&str]) -> BenchArgs {
    let all = std::iter::once("bench").chain(args.iter().copied());
    Cli::try_parse_from(all).unwrap().bench
}
