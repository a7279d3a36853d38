//! Image sizes on the command line.

use super::ArgError;

/// Image widths and heights the CLIs accept, in pixels.
pub const IMAGE_SIDES: std::ops::RangeInclusive<u32> = 1..=8192;

/// One image side in pixels (`--width`, `--height`), within [`IMAGE_SIDES`].
pub fn parse_side(s: &str) -> Result<u32, ArgError> {
    let v: u32 = s
        .parse()
        .map_err(|_| format!("expected a whole number of pixels, got {s:?}"))?;
    if IMAGE_SIDES.contains(&v) {
        Ok(v)
    } else {
        Err(format!(
            "{v} pixels is outside {}..={}",
            IMAGE_SIDES.start(),
            IMAGE_SIDES.end()
        )
        .into())
    }
}

pub fn parse_size(s: &str) -> Result<(u32, u32), ArgError> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("expected WxH, got {s:?}"))?;
    let w: u32 = w
        .trim()
        .parse()
        .map_err(|_| format!("bad width in {s:?}"))?;
    let h: u32 = h
        .trim()
        .parse()
        .map_err(|_| format!("bad height in {s:?}"))?;
    if !IMAGE_SIDES.contains(&w) || !IMAGE_SIDES.contains(&h) {
        return Err(format!("size {w}x{h} outside 1..={}", IMAGE_SIDES.end()).into());
    }
    Ok((w, h))
}
