//! `tetwave-bench`: tetwave's client benchmarks, apart from the shipped `tetwave` binary.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "tetwave-bench",
    version,
    about = "tetwave client benchmarks (the progressive experiment of the thesis)"
)]
struct Cli {
    #[command(subcommand)]
    which: BenchCmd,
}

#[derive(Subcommand)]
enum BenchCmd {
    /// The thesis' progressive experiment (Tables 2–3): nodes arrive per step, the camera turns,
    /// selective refinement runs; one row (or JSON object) per tolerance.
    Progressive(tetwave_client::progressive::BenchArgs),
}

fn bench_progressive(args: &tetwave_client::progressive::BenchArgs) -> ExitCode {
    use tetwave_client::progressive::{bench, table_row, TABLE_HEADER};
    if !args.json {
        println!("{TABLE_HEADER}");
    }
    let res = bench(args, |r| {
        if args.json {
            println!("{}", serde_json::to_string(r).expect("serializes"));
        } else {
            println!("{}", table_row(r));
        }
    });
    match res {
        Ok(_) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn main() -> ExitCode {
    tetwave_client::init_process("warn");
    match Cli::parse().which {
        BenchCmd::Progressive(args) => bench_progressive(&args),
    }
}
