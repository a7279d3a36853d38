//! Unstructured tetrahedral input: point location through a uniform grid of tet bounding boxes, with
//! barycentric interpolation (or, with `--field distance`, the distance to the boundary at each
//! point), in [`tetwave_import::locate`]. The cleaning (scalar choice, orientation, degenerate
//! tets) is [`tetwave_import::clean`], shared with `tetwave render <mesh>`.
//!
//! Points outside the input's domain (a non-convex mesh leaves parts of its bounding box empty) are
//! reported as `None`: the resampler marks those vertices outside, and they never invent material
//! (see `resample` for the rule).

pub use tetwave_import::locate::Locator;

pub use tetwave_import::clean::{
    arrays, bbox, boundary_distance, clean, clean_import, default_array, min_dihedral_deg,
    ArrayInfo, BoundaryDistance, CleanError, CleanReport, ImportOptions, ScalarTetMesh,
    SLIVER_DEGREES,
};
