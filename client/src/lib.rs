//! # tetwave-client
//!
//! The client side of tetwave, one module per stage: [`camera`], [`transfer`] functions,
//! [`render_mesh`] (the leaf mesh renderers draw), the CPU [`reference`] integrator (ground truth for
//! image error), [`image_metrics`], and [`store_info`] (checks a store against the protocol contract).

pub mod camera;
pub mod detail_buffer;
pub mod image_metrics;
pub mod mesh;
pub mod progressive;
pub mod reference;
pub mod render;
pub mod render_cli;
pub mod render_mesh;
pub mod render_probe;
mod seg_vec;
pub mod select;
pub mod store_info;
pub mod store_reader;
pub mod stream;
pub mod transfer;
