//! # tetwave-render
//!
//! Drawing a tetrahedral mesh with a transfer function, shared by the client (its frames and the
//! coming viewer) and the server (fallback images): [`transfer`] functions and exact segment
//! integrals, the [`render_mesh`] renderers draw, the CPU [`reference`](mod@reference) integrator (ground truth for
//! image error), [`image_metrics`] and the [`legend`]. GPU projected tetrahedra are `tetwave-gpu`'s. The camera is the
//! protocol's ([`tetwave_protocol::view::Camera`]), so that what is drawn and what is refined use
//! one pixel → ray mapping. Depends on no tetwave crate but `protocol`.

pub mod image_metrics;
pub mod legend;
pub mod reference;
pub mod render_mesh;
pub mod transfer;
