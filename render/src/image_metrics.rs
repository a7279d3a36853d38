//! Image error: RMSE and PSNR between two RGBA8 images, over the RGB channels, in 8-bit units.

/// An RGBA8 image, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct Rgba8Image {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[u8; 4]>,
}

/// A `[0, 1]` channel value in 8 bits (clamped, rounded to nearest).
#[inline]
pub fn unit_to_u8(x: f64) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0).round() as u8
}

impl Rgba8Image {
    /// From premultiplied linear colour over black, `[0, 1]` per channel.
    pub fn from_f64(width: u32, height: u32, rgba: &[[f64; 4]]) -> Self {
        Rgba8Image {
            width,
            height,
            pixels: rgba.iter().map(|p| p.map(unit_to_u8)).collect(),
        }
    }

    /// PNG bytes of the image as it looks over black: RGB only, opaque. The colour channels are
    /// premultiplied, i.e. already composited over black; a PNG with the alpha channel kept would be
    /// shown darkened a second time by any viewer (PNG alpha is straight). The metrics compare these
    /// same RGB channels.
    pub fn png_bytes(&self) -> Result<Vec<u8>, image::ImageError> {
        use image::ImageEncoder;
        let flat: Vec<u8> = self
            .pixels
            .iter()
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect();
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out).write_image(
            &flat,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
        )?;
        Ok(out)
    }

    /// Writes [`Self::png_bytes`] to `path`.
    pub fn save_png(&self, path: &std::path::Path) -> Result<(), image::ImageError> {
        std::fs::write(path, self.png_bytes()?).map_err(image::ImageError::IoError)
    }

    /// Reads an image file (a PNG written by [`Self::save_png`], or any format `image` reads)
    /// as RGBA8.
    pub fn load_png(path: &std::path::Path) -> Result<Rgba8Image, image::ImageError> {
        let img = image::open(path)?.to_rgba8();
        Ok(Rgba8Image {
            width: img.width(),
            height: img.height(),
            pixels: img.pixels().map(|p| p.0).collect(),
        })
    }

    /// Fraction of pixels with any non-zero RGB.
    pub fn coverage(&self) -> f64 {
        self.pixels
            .iter()
            .filter(|p| p[0] | p[1] | p[2] != 0)
            .count() as f64
            / self.pixels.len().max(1) as f64
    }
}

/// Root-mean-square error over RGB, in 8-bit units.
pub fn rmse(a: &Rgba8Image, b: &Rgba8Image) -> f64 {
    assert_eq!(
        (a.width, a.height),
        (b.width, b.height),
        "images differ in size"
    );
    let mut sum = 0f64;
    for (p, q) in a.pixels.iter().zip(&b.pixels) {
        for k in 0..3 {
            let d = p[k] as f64 - q[k] as f64;
            sum += d * d;
        }
    }
    (sum / (3 * a.pixels.len()).max(1) as f64).sqrt()
}

/// Peak signal-to-noise ratio in dB (`∞` for identical images).
pub fn psnr(a: &Rgba8Image, b: &Rgba8Image) -> f64 {
    let e = rmse(a, b);
    if e == 0.0 {
        f64::INFINITY
    } else {
        20.0 * (255.0 / e).log10()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_of_known_error() {
        let a = Rgba8Image {
            width: 2,
            height: 1,
            pixels: vec![[10, 10, 10, 255], [0, 0, 0, 0]],
        };
        let mut b = a.clone();
        assert_eq!(psnr(&a, &b), f64::INFINITY);
        b.pixels[0] = [13, 10, 10, 255];
        // one channel of six off by 3: rmse = sqrt(9/6)
        assert!((rmse(&a, &b) - 1.5f64.sqrt()).abs() < 1e-12);
        assert!((psnr(&a, &b) - 20.0 * (255.0 / 1.5f64.sqrt()).log10()).abs() < 1e-9);
    }
}
