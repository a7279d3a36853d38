//! (being written)

use super::{VolumeError, VolumeOptions, VolumeReader};
use std::path::Path;

pub(crate) fn open(
    path: &Path,
    _options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    Err(VolumeError::unsupported(
        path,
        "format",
        "this format is not read yet",
    ))
}
