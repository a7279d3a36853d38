//! # tetwave-adaptive
//!
//! The client's adaptive core, with no GPU, network or window: the [`detail_buffer`] (every node
//! that has arrived, in any order), the adaptive red/green [`mesh`], view-dependent
//! [`select`]ion, the [`session`] that wires the three for one dataset, and the leaf mesh as
//! renderers [`draw`] it (`tetwave-render`'s render mesh). Whatever feeds a session (a server's
//! stream, a store directory, a mesh file) and whatever draws it (the headless CLI, the viewer)
//! lives in other crates.

pub mod detail_buffer;
pub mod draw;
pub mod mesh;
mod seg_vec;
pub mod select;
pub mod session;
