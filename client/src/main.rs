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
    /// Render a store's uniform level to PNG (GPU projected tetrahedra, or the CPU reference), with
    /// its time and optionally its PSNR against the reference.
    Render(tetwave_client::render_cli::RenderArgs),
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter("warn")
        .init();
    match Cli::parse().cmd {
        Cmd::Render(args) => match tetwave_client::render_cli::run(&args) {
            Ok(r) => {
                if args.json {
                    println!("{}", serde_json::to_string(&r).expect("serializes"));
                } else {
                    let psnr = r
                        .psnr_db
                        .map(|p| format!(", PSNR {p:.2} dB vs reference"))
                        .unwrap_or_default();
                    println!(
                        "{}: {} tets (level {}), {}x{}, {:.1} ms{psnr} -> {}",
                        r.renderer, r.tets, r.level, r.width, r.height, r.ms, r.output
                    );
                }
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("error: {e}");
                ExitCode::FAILURE
            }
        },
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
