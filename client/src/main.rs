//! `tetwave`: the tetwave client.

use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "tetwave",
    version,
    about = "tetwave client: progressive wavelet-domain tetrahedral volume visualization"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Check a store's base mesh and counts against the protocol contract and print them.
    Info {
        store: PathBuf,
        #[arg(long)]
        json: bool,
    },
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter("warn")
        .init();
    match Cli::parse().cmd {
        Cmd::Info { store, json } => match tetwave_client::store_info::store_info(&store) {
            Ok(i) => {
                if json {
                    println!("{}", serde_json::to_string(&i).expect("serializes"));
                } else {
                    println!(
                        "{}: {} base tets, {} levels, {} tets, {} leaves, {} nodes, {} vertices — agrees with the manifest",
                        i.dataset, i.base_tets, i.levels, i.tets_total, i.leaves, i.nodes, i.vertices
                    );
                }
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("error: {e}");
                ExitCode::FAILURE
            }
        },
    }
}
