//! # tetwave-client
//!
//! The client side of tetwave: the [`detail_buffer`] (every node that has arrived), the adaptive
//! red/green [`mesh`], view-dependent [`select`]ion, the leaf mesh as renderers [`draw`] it, the
//! stream client ([`stream`]), the interactive [`viewer`] (`tetwave view`), the progressive benchmark ([`progressive`]) and the CLI's render and
//! store commands. Rendering itself is `tetwave-render`'s; stores are read through `tetwave-store`.

pub mod camera_arg;
pub mod detail_buffer;
pub mod draw;
mod http;
mod ingest;
pub mod legend;
pub mod mesh;
pub mod progressive;
pub mod render_cli;
pub mod render_probe;
mod seg_vec;
pub mod select;
pub mod select_args;
pub mod session;
pub mod store_info;
pub mod stream;
pub mod viewer;
