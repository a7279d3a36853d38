//! # tetwave-client
//!
//! The `tetwave` binary's library: the CLI's commands (`info`: [`store_info`], `render`:
//! [`render_cli`], `stream`: [`stream`], `bench progressive`: [`progressive`]); `tetwave view`
//! is `tetwave-viewer`'s. What a command reads from (a server, a store, a mesh file) and the
//! options every command shares are `tetwave-source`'s, the adaptive core `tetwave-adaptive`'s,
//! the network `tetwave-net`'s, drawing `tetwave-render`'s (CPU) and `tetwave-gpu`'s.

pub mod legend;
pub mod progressive;
pub mod render_cli;
pub mod render_probe;
pub mod store_info;
pub mod stream;

/// What `tetwave` and `tetwave-bench` do first, before any thread exists: keep headless Vulkan
/// quiet (a Wayland probe would print an error on every headless run) and log to stderr through
/// `TETWAVE_LOG` (EnvFilter syntax, as the server's `--log`; e.g. `tetwave_viewer=trace` for the
/// viewer's frame records), `default_filter` when it is unset.
pub fn init_process(default_filter: &str) {
    tetwave_gpu::quiet_headless_vulkan_layers();
    let filter = tracing_subscriber::EnvFilter::try_from_env("TETWAVE_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter));
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(filter)
        .init();
}
