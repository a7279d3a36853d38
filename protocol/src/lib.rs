//! # tetwave-protocol
//!
//! The contract both the server and the client compile: ids and child order of the semi-regular
//! hierarchy ([`hierarchy`]), global vertex keys ([`vertex`]), the lifting steps ([`wavelet`]), detail
//! nodes ([`node`]), which edges a node owns ([`ownership`]), coded blocks of nodes ([`block`], over
//! the adaptive models of [`entropy`]), the base mesh ([`base`]), whole-hierarchy synthesis ([`synthesis`]), the near-boundary
//! level set streaming clients clip with ([`levelset`]), the wire frames ([`wire`]), the store format ([`store_format`]), the refinement criterion ([`view`]), the
//! seeded shuffle both sides' test orders use ([`order`]), the base meshes known by name
//! ([`shapes`]) and the named synthetic fields ([`fields`]). With the feature `testing`, the module
//! `testing` holds fixtures for other crates' tests.
//! This crate does no I/O.

pub mod axes;
pub mod base;
pub mod block;
pub mod entropy;
pub mod fields;
pub mod hierarchy;
pub mod levelset;
pub mod node;
pub mod order;
pub mod ownership;
pub mod shapes;
pub mod store_format;
pub mod synthesis;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod vertex;
pub mod view;
pub mod wavelet;
pub mod wire;

pub use base::BaseMesh;
pub use hierarchy::{Forest, LatticeTet, TetId};
pub use node::DetailNode;
pub use vertex::VertexKeys;
