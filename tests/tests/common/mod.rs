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

/// `tool`'s path (searched in ~/.cargo/bin, PATH, /usr/sbin); panics naming `hint` when it is
/// missing: a test that needs it fails rather than skip.
pub fn need(tool: &str, hint: &str) -> PathBuf {
    let home = std::env::var("HOME").unwrap_or_default();
    let path = std::env::var("PATH").unwrap_or_default();
    for dir in std::iter::once(format!("{home}/.cargo/bin"))
        .chain(path.split(':').map(String::from))
        .chain(["/usr/sbin".to_string(), "/sbin".to_string()])
    {
        let p = Path::new(&dir).join(tool);
        if p.is_file() {
            return p;
        }
    }
    panic!("{tool} is not installed ({hint}): this test needs it and does not skip");
}

/// A free loopback port (bound and released: another process may take it first, rarely).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Debian's nginx on a free loopback port with `server` as its server block's body (beside
/// `listen`) and `http` before it, from a temporary prefix; stopped when dropped.
pub struct Nginx {
    child: std::process::Child,
    pub port: u16,
    _dir: tempfile::TempDir,
}

impl Nginx {
    pub fn start(server: &str) -> Nginx {
        Self::start_with("", server)
    }

    pub fn start_with(http: &str, server: &str) -> Nginx {
        let nginx = need("nginx", "scripts/setup installs Debian's nginx-light");
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let d = dir.path().display();
        let conf = format!(
            "daemon off; user root; worker_processes 1; pid {d}/nginx.pid; error_log {d}/error.log;\n\
             events {{}}\n\
             http {{ access_log off; client_body_temp_path {d}/b; proxy_temp_path {d}/p;\n\
               fastcgi_temp_path {d}/f; uwsgi_temp_path {d}/u; scgi_temp_path {d}/s;\n\
               {http}\n\
               server {{ listen 127.0.0.1:{port}; {server} }} }}\n"
        );
        std::fs::write(dir.path().join("nginx.conf"), conf).unwrap();
        let child = std::process::Command::new(nginx)
            .arg("-p")
            .arg(dir.path())
            .arg("-c")
            .arg(dir.path().join("nginx.conf"))
            .stdout(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let t0 = std::time::Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                t0.elapsed() < std::time::Duration::from_secs(20),
                "nginx did not listen"
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        Nginx {
            child,
            port,
            _dir: dir,
        }
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
