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
