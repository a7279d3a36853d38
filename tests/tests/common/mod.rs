//! Helpers shared by the cross-crate tests: stores, `tetwave-bench progressive` arguments and
//! `tetwave render` runs.
#![allow(dead_code)] // each test binary uses some of the helpers

use clap::Parser;
use std::path::{Path, PathBuf};
use tetwave_client::progressive::BenchArgs;
use tetwave_client::render_cli::{run, RenderArgs, RenderReport};
use tetwave_render::image_metrics::Rgba8Image;
use tetwave_server::prepare::{prepare, PrepareOptions};
use tetwave_server::stream::{BackgroundServer, Order, ServeConfig};

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    bench: BenchArgs,
}

#[derive(Parser)]
struct RenderCli {
    #[command(flatten)]
    a: RenderArgs,
}

/// `tetwave render input --size SIZE -o out` with `extra` options, parsed as the CLI parses them:
/// the PNG's RGBA pixels and the report.
pub fn render_png(
    input: &Path,
    out: &Path,
    size: u32,
    extra: &[&str],
) -> (Vec<[u8; 4]>, RenderReport) {
    let mut args = vec![
        "render".to_string(),
        input.display().to_string(),
        "--size".into(),
        format!("{size}x{size}"),
        "-o".into(),
        out.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let cli = RenderCli::try_parse_from(&args).unwrap();
    let report = run(&cli.a).unwrap();
    (Rgba8Image::load_png(out).unwrap().pixels, report)
}

/// PSNR over RGB of two pixel lists of one size ([`tetwave_render::image_metrics::psnr`]).
pub fn psnr_pixels(a: &[[u8; 4]], b: &[[u8; 4]]) -> f64 {
    let img = |p: &[[u8; 4]]| Rgba8Image {
        width: p.len() as u32,
        height: 1,
        pixels: p.to_vec(),
    };
    tetwave_render::image_metrics::psnr(&img(a), &img(b))
}

/// A harmonic store of `levels` levels prepared by the server in a new temporary directory (kept
/// while the returned guard lives), and its path.
pub fn harmonic_store(levels: u8) -> (tempfile::TempDir, PathBuf) {
    harmonic_store_with(levels, |_| {})
}

/// [`harmonic_store`] with more options set by `options`.
pub fn harmonic_store_with(
    levels: u8,
    options: impl FnOnce(&mut PrepareOptions),
) -> (tempfile::TempDir, PathBuf) {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("s");
    let mut o = PrepareOptions::new("synthetic:harmonic", &store);
    o.levels = Some(levels);
    options(&mut o);
    prepare(&o).unwrap();
    (d, store)
}

/// `tetwave-bench progressive` arguments, parsed as the CLI parses them (`args` without the
/// subcommand's name).
pub fn bench_args(args: &[&str]) -> BenchArgs {
    let all = std::iter::once("bench").chain(args.iter().copied());
    Cli::try_parse_from(all).unwrap().bench
}

/// A server on 127.0.0.1, on any free port, in process; stopped when dropped.
pub fn serve(store: &Path, order: &str) -> BackgroundServer {
    let config = ServeConfig {
        order: Order::parse(order).expect("known order"),
        ..Default::default()
    };
    BackgroundServer::start(store, "127.0.0.1:0", config).expect("the store is served")
}

/// A stream session on `url` (a server, a bucket or an HTTP folder) at 2 px on 256², no images,
/// until the view is complete; the error as text.
pub fn converged(url: &str, out: &Path) -> Result<tetwave_client::stream::Streamed, String> {
    let mut a = tetwave_client::stream::StreamArgs::new(url, out);
    a.no_render = true;
    a.cpu = true;
    a.frames = 2000;
    a.tol = "2".into();
    a.size = (256, 256);
    a.frame_ms = 5;
    a.until_converged = true;
    tetwave_client::stream::run_session(&a, Default::default()).map_err(|e| e.to_string())
}

/// The final mesh's leaf ids, sorted: what "the same final mesh" compares.
pub fn leaves(s: &tetwave_client::stream::Streamed) -> Vec<u64> {
    let mut ids = s.mesh.as_ref().expect("a final mesh").leaf_ids();
    ids.sort_unstable();
    ids
}
