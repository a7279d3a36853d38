//! # tetwave-client
//!
//! The `tetwave` binary's library: the CLI's commands (`info`: [`store_info`], `render`:
//! [`render_cli`], `stream`: [`stream`], `bench progressive`: [`progressive`]) and the
//! interactive [`viewer`] (`tetwave view`). The adaptive core is `tetwave-adaptive`'s, the
//! network `tetwave-net`'s, drawing `tetwave-render`'s (CPU) and `tetwave-gpu`'s; stores are read
//! through `tetwave-store`.

pub mod arg_error;
pub mod camera_arg;
pub mod legend;
pub mod progressive;
pub mod render_cli;
pub mod render_probe;
pub mod select_args;
pub mod source;
pub mod store_info;
pub mod stream;
pub mod viewer;
