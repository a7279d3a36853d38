//! The option groups every client command shares (`render`, `stream`, `view`, the benchmarks):
//! the orbit camera, how a session selects, image sizes, and the error their parsers give.

mod camera;
mod error;
mod selection;
mod size;

pub use camera::{angle, distance, elevation, fov, CameraArgs};
pub use error::ArgError;
pub use selection::{default_max_tets, Criterion, SelectionArgs, BYTES_PER_LEAF};
pub use size::{parse_side, parse_size, IMAGE_SIDES};
