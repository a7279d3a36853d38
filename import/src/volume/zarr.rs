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

/// Whether `dir` is a Zarr array or group (v2 `.zarray`/`.zgroup`, v3 `zarr.json`).
pub(crate) fn is_zarr_dir(dir: &Path) -> bool {
    [".zarray", ".zgroup", "zarr.json"]
        .iter()
        .any(|f| dir.join(f).is_file())
}
