//! Base meshes: the bounding box split into 5 tets (thesis) or 6 Kuhn tets, a box cut into Kuhn
//! cells (a raw grid's voxel lattice), or a coarse tet mesh file
//! (read in [`super::base_mesh`]). Store manifests name the box splits, so their one implementation
//! is in the protocol crate ([`tetwave_protocol::shapes`]), which both sides compile.

pub use tetwave_protocol::shapes::{box5, box6, kuhn_boxes, orient_positive, PointsAndTets};
