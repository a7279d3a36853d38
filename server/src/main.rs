//! `tetwave-server`: prepare stores from volumes, verify them and serve them.

use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;
use tetwave_server::prepare::{prepare, verify, verify_source, PrepareOptions, ReadArgs};

#[derive(Parser)]
#[command(
    name = "tetwave-server",
    version,
    about = "tetwave server: resample volumes onto a semi-regular tet mesh, wavelet-analyse them and store the coefficients"
)]
struct Cli {
    /// Log filter (tracing EnvFilter syntax), e.g. `info` or `tetwave_server=debug`.
    #[arg(long, global = true, default_value = "warn", env = "TETWAVE_LOG")]
    log: String,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Resample a volume onto a semi-regular tet mesh, run the wavelet analysis and write a store.
    Prepare {
        #[command(flatten)]
        options: PrepareOptions,
        /// Print one JSON object instead of the summary.
        #[arg(long)]
        json: bool,
    },
    /// Re-run synthesis from a store and check it: against the samples it keeps
    /// (`prepare --keep-reference`), else against its bound (finite values within the value
    /// range); fails beyond the manifest's bound. With --input (what the store was prepared from,
    /// read with the options it was prepared with: --dims/--dtype/--spacing for a raw grid,
    /// --scalar for a mesh): also every voxel of a grid, or every vertex where the input has data,
    /// against the store, and the value ranges.
    Verify {
        store: PathBuf,
        #[arg(long)]
        json: bool,
        /// The input the store was prepared from (a raw grid, `synthetic:NAME`, a mesh file).
        #[arg(long)]
        input: Option<String>,
        #[command(flatten)]
        read: ReadArgs,
    },
    /// Copy a store directory to object storage (`s3://BUCKET/PREFIX`): its files as the
    /// manifest lists them (large ones in parts), the manifest last, after the store is checked
    /// (structure and every checksum).
    Copy {
        /// The store directory.
        from: PathBuf,
        /// `s3://BUCKET/PREFIX` (endpoint and credentials from AWS_ENDPOINT_URL,
        /// AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION, AWS_ALLOW_HTTP).
        to: String,
    },
    /// Serve a store: manifest, base mesh and nodes over HTTP, the progressive stream over
    /// WebSocket (`/v1/stream`), fallback images (`/v1/render`) and a viewer page (`/`).
    Serve {
        store: PathBuf,
        /// Address to bind (loopback by default).
        #[arg(long, default_value = "127.0.0.1:7878")]
        addr: String,
        /// Require this token from every client (`Authorization: Bearer T`, `?token=T`, or the
        /// stream's Hello); requests without it get 401. An empty token is refused. A token given
        /// on the command line is visible to every user of this machine (`ps`): prefer the
        /// TETWAVE_TOKEN environment variable. Wrong tokens are logged with the peer's address and
        /// limited to 10 in a burst, then one a second, per address.
        #[arg(long, env = "TETWAVE_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// Also serve requests whose Host is this name (repeatable; `*`: any). IP addresses and
        /// `localhost` are always served; other names are refused against DNS rebinding.
        #[arg(long = "allow-host", value_name = "NAME")]
        allow_hosts: Vec<String>,
        /// Also accept browser requests from this origin, e.g. `https://viz.example:8443`
        /// (repeatable; `*`: any). By default only pages served by this server may use it.
        #[arg(long = "allow-origin", value_name = "ORIGIN")]
        allow_origins: Vec<String>,
        /// Most open connections (HTTP and WebSocket); default: 1024, or less under a low
        /// open-file limit (`ulimit -n` minus 64).
        #[arg(long)]
        max_connections: Option<usize>,
        /// Most open HTTP connections per client address.
        #[arg(long, default_value_t = 128)]
        max_connections_per_peer: usize,
        /// Most WebSocket streams per client address (behind a reverse proxy every client has the
        /// proxy's address: raise it there).
        #[arg(long, default_value_t = 16)]
        max_streams_per_peer: usize,
        /// Seconds a client has to send a request's headers (and an idle keep-alive connection
        /// stays open).
        #[arg(long, default_value_t = 10.0)]
        header_timeout: f64,
        /// Seconds a stream may stay silent while the server waits on it.
        #[arg(long, default_value_t = 120.0)]
        idle_timeout: f64,
        /// Renders that may wait behind the running one (`/v1/render`); more get 503.
        #[arg(long, default_value_t = 4)]
        render_queue: usize,
        /// Seconds a render may take, waiting included; then 503 and it is cancelled.
        #[arg(long, default_value_t = 30.0)]
        render_deadline: f64,
        /// Most pixels (width × height) of one render.
        #[arg(long, default_value_t = 2048 * 2048)]
        max_render_pixels: u64,
        /// Default order of the stream (a client may pick another with `/v1/stream?order=`).
        #[arg(long, value_enum, default_value_t = tetwave_server::stream::Order::Level)]
        order: tetwave_server::stream::Order,
        /// What view order weighs a node's screen-space error by: `image` (how much its subtree
        /// can change the image under the default transfer function, as the client's default
        /// selection does) or `data` (its details relative to the value range).
        #[arg(long, value_enum, default_value_t = tetwave_server::stream::ViewCriterion::Image)]
        view_criterion: tetwave_server::stream::ViewCriterion,
        /// Nodes in the first batch (and the first after each view change); later batches
        /// double up to --max-batch.
        #[arg(long, default_value_t = 512)]
        batch: usize,
        /// Most nodes in one batch.
        #[arg(long, default_value_t = 16384)]
        max_batch: usize,
        /// Most un-acknowledged batches in flight per connection.
        #[arg(long, default_value_t = 8)]
        window: u64,
        /// For a store prepared with `--preview`: a new session first gets preview nodes worth at
        /// most this share of the store's nodes' bytes (0 sends none; 1, the default, in
        /// practice all of the preview).
        #[arg(long, default_value_t = 1.0)]
        preview_share: f64,
        /// Worker threads (default: the number of cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Recompute every store file's CRC-32 before serving (reads the whole store; base.bin's
        /// checksum is always checked, and every block's when it is read).
        #[arg(long)]
        verify: bool,
        /// Most MiB of decoded blocks held (least recently used dropped first; `/healthz`
        /// reports hits, reads and what is held). With it, a server holds this plus about
        /// what its sessions have sent (docs/object-storage.md, "Memory"), whatever the store's
        /// size. base.bin's checksum is checked at start, each block's when it is read.
        #[arg(long, default_value_t = 256)]
        cache_mb: u64,
    },
}

fn main() -> ExitCode {
    // before any thread: fallback renders would otherwise print a Wayland probe's error
    tetwave_gpu::quiet_headless_vulkan_layers();
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&cli.log).unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(cli.cmd) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(cmd: Cmd) -> Result<(), Box<dyn std::error::Error>> {
    let interactive = std::io::IsTerminal::is_terminal(&std::io::stderr());
    match cmd {
        Cmd::Prepare { options, json } => {
            let o = PrepareOptions {
                progress: interactive && !json,
                ..options
            };
            if let (Some(n), Some(k)) = (o.by_parts.parts, o.by_parts.part) {
                let p = tetwave_server::prepare::parts::prepare_part(&o, n, k)?;
                if json {
                    println!("{}", serde_json::to_string(&p)?);
                } else {
                    println!(
                        "part {k} of {n}: base tets {}..{}, {} coefficients, max error {:e} \
                         (bound {:e}), {} bytes of nodes -> {} ({:.3} s)",
                        p.base_tets[0],
                        p.base_tets[1],
                        p.coefficients,
                        p.max_abs_error,
                        p.error_bound,
                        p.nodes_bytes,
                        o.out.display(),
                        p.seconds
                    );
                }
                return Ok(());
            }
            let s = prepare(&o)?;
            if json {
                println!("{}", serde_json::to_string(&s)?);
            } else {
                println!(
                    "dataset      {} ({} base, {} levels) -> {}",
                    s.dataset, s.base, s.levels, s.store
                );
                println!(
                    "tets         {} in all levels, {} leaves, {} detail nodes",
                    s.tets_total, s.leaves, s.nodes
                );
                println!(
                    "vertices     {} ({} outside the input's domain)",
                    s.vertices, s.outside_vertices
                );
                println!(
                    "coefficients {} ({}), {} bytes streamable",
                    s.coefficients, s.encoding, s.bytes
                );
                println!(
                    "max error    {:e} (bound {:e}), values in [{}, {}]",
                    s.max_abs_error, s.max_error_bound, s.value_range[0], s.value_range[1]
                );
                if let Some(v) = &s.volume {
                    let [x, y, z] = v.dims;
                    let unit = v
                        .length_unit
                        .as_deref()
                        .map(|u| format!(" {u}"))
                        .unwrap_or_default();
                    println!(
                        "volume       {} {x}×{y}×{z} {}, spacing {:?}{unit}, origin {:?}{}{}",
                        v.format,
                        v.dtype,
                        v.spacing,
                        v.origin,
                        v.frame
                            .as_ref()
                            .map(|f| format!(" ({f})"))
                            .unwrap_or_default(),
                        v.rescale
                            .map(|(s, i)| format!(", values × {s} + {i}"))
                            .unwrap_or_default()
                    );
                    for note in &v.notes {
                        println!("             {note}");
                    }
                }
                if let Some(r) = &s.import {
                    println!(
                        "import       {} cells read; scalar {:?} ({}): {} tets kept, {} re-oriented, {} dropped, {} cells split, {} ignored",
                        r.cells_read, r.scalar, r.scalar_source, r.tets_kept, r.tets_reoriented, r.tets_dropped, r.cells_split, r.cells_ignored
                    );
                    for note in &r.notes {
                        println!("             {note}");
                    }
                }
                println!("time         {:.3} s", s.seconds);
            }
        }
        Cmd::Verify {
            store,
            json,
            input,
            read,
        } => {
            let r = match &input {
                Some(input) => verify_source(&store, input, &read)?,
                None if read.grid.dims.is_some() => {
                    return Err("--dims describes the grid of --input; give --input too".into())
                }
                None => verify(&store)?,
            };
            if json {
                println!("{}", serde_json::to_string(&r)?);
            } else {
                match (r.max_abs_error, r.exact_vertices) {
                    (Some(e), Some(exact)) => println!(
                        "ok: {} vertices from {} nodes against the kept samples, max abs error {e:e} (bound {:e}), {exact} bit-exact, {:.3} s",
                        r.vertices, r.nodes, r.max_error_bound, r.seconds
                    ),
                    _ => println!(
                        "ok: {} vertices from {} nodes synthesize to finite values within the value range and the bound {:e}, {:.3} s{}",
                        r.vertices, r.nodes, r.max_error_bound, r.seconds,
                        if r.input.is_none() { " (the store keeps no samples: give --input to compare with the input)" } else { "" }
                    ),
                }
                if let Some(c) = &r.input {
                    println!(
                        "input: {} {}, max abs error {:e} (bound {:e}), {} bit-exact; values in [{}, {}], store [{}, {}]",
                        c.points, c.points_are, c.max_abs_error, r.max_error_bound, c.exact_points,
                        c.input_range[0], c.input_range[1], c.store_range[0], c.store_range[1]
                    );
                }
            }
        }
        Cmd::Copy { from, to } => {
            let to = tetwave_store::Location::parse(&to)?;
            if !matches!(to, tetwave_store::Location::S3 { .. }) {
                return Err(format!("copy writes to s3://BUCKET/PREFIX, not {to}").into());
            }
            tetwave_store::Store::open_with(
                &from,
                tetwave_store::OpenOptions {
                    verify_checksums: true,
                    ..Default::default()
                },
            )?;
            let t0 = std::time::Instant::now();
            let m = tetwave_store::upload(&from, &to)?;
            let bytes: u64 = m.files.values().map(|f| f.bytes).sum();
            println!(
                "copied {} ({} files, {bytes} bytes) -> {to} ({:.3} s)",
                from.display(),
                m.files.len() + 1,
                t0.elapsed().as_secs_f64()
            );
        }
        Cmd::Serve {
            store,
            addr,
            token,
            allow_hosts,
            allow_origins,
            max_connections,
            max_connections_per_peer,
            max_streams_per_peer,
            header_timeout,
            idle_timeout,
            render_queue,
            render_deadline,
            max_render_pixels,
            order,
            view_criterion,
            batch,
            max_batch,
            window,
            preview_share,
            threads,
            verify,
            cache_mb,
        } => {
            use tetwave_server::stream::{serve_on, ServeConfig, Shared};
            if !(1..=1 << 16).contains(&batch) {
                return Err(format!("--batch {batch} outside 1..=65536").into());
            }
            if !(batch..=1 << 16).contains(&max_batch) {
                return Err(format!("--max-batch {max_batch} outside {batch}..=65536").into());
            }
            if !(1..=1024).contains(&window) {
                return Err(format!("--window {window} outside 1..=1024").into());
            }
            if !(0.0..=1.0).contains(&preview_share) {
                return Err(format!("--preview-share {preview_share} outside 0..=1").into());
            }
            if token.as_deref() == Some("") {
                // an unset variable in `--token "$T"` must not serve without authentication
                return Err("--token is empty; leave it out to serve without a token".into());
            }
            let secs = |name: &str, v: f64| {
                if v.is_finite() && v > 0.0 && v <= 86_400.0 {
                    Ok(std::time::Duration::from_secs_f64(v))
                } else {
                    Err(format!("--{name} {v}: give seconds in (0, 86400]"))
                }
            };
            let mut limits = tetwave_server::stream::Limits::default();
            if let Some(m) = max_connections {
                if m == 0 {
                    return Err("--max-connections must be at least 1".into());
                }
                if let Some(files) = tetwave_server::stream::open_file_limit() {
                    if m as u64 + 64 > files {
                        tracing::warn!(
                            "--max-connections {m} is close to the open-file limit {files}; \
                             raise `ulimit -n` or connections will fail at accept"
                        );
                    }
                }
                limits.max_connections = m;
            }
            limits.max_connections_per_peer = max_connections_per_peer.max(1);
            limits.max_streams_per_peer = max_streams_per_peer.max(1);
            limits.header_read_timeout = secs("header-timeout", header_timeout)?;
            limits.render_queue = render_queue;
            limits.render_deadline = secs("render-deadline", render_deadline)?;
            limits.max_render_pixels = max_render_pixels.max(1);
            let lower = |v: Vec<String>| v.into_iter().map(|s| s.to_ascii_lowercase()).collect();
            let config = ServeConfig {
                token,
                order,
                batch,
                max_batch,
                window,
                preview_share,
                idle_timeout: secs("idle-timeout", idle_timeout)?,
                limits,
                origins: tetwave_server::stream::OriginPolicy {
                    allow_hosts: lower(allow_hosts),
                    allow_origins: lower(allow_origins),
                },
                verify_checksums: verify,
                cache_limit_bytes: cache_mb.saturating_mul(1 << 20),
                view_criterion,
                ..ServeConfig::default()
            };
            let shared = Shared::open(&store, config)?;
            if order == tetwave_server::stream::Order::View {
                shared.warm_view_order();
            }
            let mut rt = tokio::runtime::Builder::new_multi_thread();
            if let Some(t) = threads {
                rt.worker_threads(t.max(1));
            }
            let rt = rt.enable_all().build()?;
            rt.block_on(async move {
                let listener = tokio::net::TcpListener::bind(&addr)
                    .await
                    .map_err(|e| format!("{addr}: {e}"))?;
                let local = listener.local_addr()?;
                if !local.ip().is_loopback() && shared.config.token.is_none() {
                    tracing::warn!(
                        "serving on {local} without a token: anyone who can reach this address \
                         can read the data (set TETWAVE_TOKEN)"
                    );
                }
                {
                    use std::io::Write;
                    let mut out = std::io::stdout().lock();
                    writeln!(
                        out,
                        "listening on http://{local} ({} nodes, order {order:?}{})",
                        shared.nodes(),
                        if shared.config.token.is_some() {
                            ", token required"
                        } else {
                            ""
                        }
                    )?;
                    out.flush()?;
                }
                serve_on(listener, shared).await?;
                Ok::<(), Box<dyn std::error::Error>>(())
            })?;
        }
    }
    Ok(())
}
