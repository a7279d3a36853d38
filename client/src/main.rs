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
    /// Render a store's uniform level, or a mesh file (.vtu, .vtk, .msh, .mesh) as it is, to PNG
    /// (GPU projected tetrahedra, or the CPU reference), with its time and optionally its PSNR
    /// against the reference. A store and the mesh it was prepared from frame the same default view.
    Render(tetwave_client::render_cli::RenderArgs),
    /// Stream from a `tetwave-server serve` and render progressively: PNG frames and one JSON line
    /// per frame (frame, bytes_received, nodes, tets, refine_ms, render_ms, psnr_db). A stream that
    /// fails before every node has arrived (a refused node or frame, a lost connection, nodes the
    /// server never sends, a hierarchy over --max-nodes) exits with status 1.
    Stream(tetwave_client::stream::StreamArgs),
    /// The interactive viewer: a window that streams from a server (or reads a store, or a mesh
    /// file), refines and renders as the camera moves, and shows the server's `/v1/render` image
    /// on request. Orbit/pan/zoom with the mouse and keys; `--script`, `--screenshot` and
    /// `--frames` for scripted runs. Needs a display (X11; `xvfb-run -a` headless) and a GPU
    /// adapter (lavapipe works).
    View(tetwave_viewer::ViewArgs),
}

fn view(args: &tetwave_viewer::ViewArgs) -> ExitCode {
    use tetwave_viewer::{run, ViewError, ViewReport};
    let summary = |r: &ViewReport| {
        if args.json {
            println!("{}", serde_json::to_string(r).expect("serializes"));
        } else {
            eprintln!(
                "view: {} frames ({:.1} fps), {}/{} nodes, {} tets, {} bytes",
                r.frames, r.fps, r.nodes, r.nodes_total, r.tets, r.bytes_received
            );
        }
    };
    match run(args) {
        Ok(r) => {
            summary(&r);
            ExitCode::SUCCESS
        }
        Err(ViewError::Run(errors, r)) => {
            summary(&r);
            eprintln!("error: {}", errors.join("; "));
            ExitCode::FAILURE
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn main() -> ExitCode {
    tetwave_client::init_process("warn,winit=error");
    match Cli::parse().cmd {
        Cmd::Stream(args) => match tetwave_client::stream::run(&args) {
            Ok(r) => {
                for f in &r.frames {
                    println!("{}", serde_json::to_string(f).expect("serializes"));
                }
                let clip = match (&r.levelset_error, r.clipped) {
                    (Some(e), _) => format!(", not clipped to the domain: {e}"),
                    (None, true) => ", clipped to the mesh's domain".to_string(),
                    (None, false) => String::new(),
                };
                eprintln!(
                    "stream: {} frames, {}/{} nodes ({} duplicates), {} bytes, {} reconnects, first frame {:.1} ms{clip} -> {}",
                    r.frames.len(),
                    r.nodes_received,
                    r.nodes_total,
                    r.duplicates,
                    r.bytes_received,
                    r.reconnects,
                    r.first_frame_ms.unwrap_or(f64::NAN),
                    args.out.display()
                );
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("error: {e}");
                ExitCode::FAILURE
            }
        },
        Cmd::View(args) => view(&args),
        Cmd::Render(args) => match tetwave_client::render_cli::run(&args) {
            Ok(r) => {
                if args.json {
                    println!("{}", serde_json::to_string(&r).expect("serializes"));
                } else {
                    let psnr = r
                        .psnr_db
                        .map(|p| format!(", PSNR {p:.2} dB vs reference"))
                        .unwrap_or_default();
                    let what = match &r.scalar {
                        Some(s) => format!("mesh as it is, scalar {s}"),
                        None => format!("level {}", r.level),
                    };
                    println!(
                        "{}: {} tets ({what}), {}x{}, {:.1} ms{psnr} -> {}",
                        r.renderer, r.tets, r.width, r.height, r.ms, r.output
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
                        "{}: {} base tets, {} levels, {} tets, {} leaves, {} nodes, {} vertices, {} predictor — agrees with the manifest",
                        i.dataset, i.base_tets, i.levels, i.tets_total, i.leaves, i.nodes, i.vertices, i.predictor
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
