//! The colour legend under a rendered image (`tetwave render --legend`): the transfer function's
//! colours across the value range it maps, the scalar's name and that range, in the Hack font
//! egui ships (so no system font is needed). The strip is drawn on black below the image. Where
//! the input states its world frame, the image's edges are labelled with the anatomical
//! directions they face, as radiology viewers do.

use ab_glyph::{Font, FontRef, PxScale, ScaleFont};
use tetwave_protocol::store_format::Physical;
use tetwave_protocol::view::Camera;
use tetwave_render::image_metrics::Rgba8Image;
use tetwave_render::legend::colour_at;
pub use tetwave_render::legend::legend_text;
use tetwave_render::transfer::TransferFunction;

/// Height of the strip added under the image, pixels.
pub const LEGEND_HEIGHT: u32 = 40;
/// Left and right margins of the colour bar and the text, pixels.
pub const MARGIN: u32 = 6;
/// Rows of the colour bar within the strip.
pub const BAR_ROWS: std::ops::Range<u32> = 4..14;
/// Top of the text's line within the strip, and its size in pixels.
pub const TEXT_TOP: u32 = 18;
pub const TEXT_PX: f32 = 15.0;

/// `img` with the legend strip under it: the colour bar (each column the transfer function's
/// colour at its place in the range) and [`legend_text`].
pub fn with_legend(
    img: &Rgba8Image,
    tf: &TransferFunction,
    name: &str,
    range: [f32; 2],
) -> Rgba8Image {
    let (w, h) = (img.width, img.height);
    let mut out = Rgba8Image {
        width: w,
        height: h + LEGEND_HEIGHT,
        pixels: img.pixels.clone(),
    };
    out.pixels
        .resize((w * (h + LEGEND_HEIGHT)) as usize, [0, 0, 0, 255]);
    let bar = w.saturating_sub(2 * MARGIN).max(1);
    for x in 0..bar.min(w) {
        let c = colour_at(tf, x as f64 / (bar.max(2) - 1) as f64);
        for y in BAR_ROWS {
            out.pixels[((h + y) * w + MARGIN + x) as usize] = [c[0], c[1], c[2], 255];
        }
    }
    draw_text(&mut out, MARGIN, h + TEXT_TOP, &legend_text(name, range));
    out
}

/// Draws `text` in white at `(x, top)` (the top of its line) into `img`, clipped to the image.
pub fn draw_text(img: &mut Rgba8Image, x: u32, top: u32, text: &str) {
    let font = FontRef::try_from_slice(epaint_default_fonts::HACK_REGULAR)
        .expect("egui's Hack font parses");
    let scaled = font.as_scaled(PxScale::from(TEXT_PX));
    let baseline = top as f32 + scaled.ascent();
    let mut pen = x as f32;
    let (w, h) = (img.width as i64, img.height as i64);
    for ch in text.chars() {
        let id = scaled.glyph_id(ch);
        let glyph =
            id.with_scale_and_position(PxScale::from(TEXT_PX), ab_glyph::point(pen, baseline));
        pen += scaled.h_advance(id);
        if let Some(g) = font.outline_glyph(glyph) {
            let b = g.px_bounds();
            g.draw(|gx, gy, cov| {
                let (px, py) = (b.min.x as i64 + gx as i64, b.min.y as i64 + gy as i64);
                if (0..w).contains(&px) && (0..h).contains(&py) {
                    let p = &mut img.pixels[(py * w + px) as usize];
                    let v = (cov.clamp(0.0, 1.0) * 255.0).round() as u8;
                    for c in &mut p[..3] {
                        *c = (*c).max(v);
                    }
                }
            });
        }
    }
}

/// The anatomical direction each edge of the image of `cam` faces, `[left, right, top, bottom]`
/// (`R`, `LA`, ...: [`Physical::direction_label`] of the camera's right and up vectors and their
/// opposites); `None` when `physical` states no known frame.
pub fn edge_labels(physical: &Physical, cam: &Camera) -> Option<[String; 4]> {
    let (r, u, _) = cam.basis();
    let label = |v: glam::DVec3| physical.direction_label(v.to_array());
    Some([label(-r)?, label(r)?, label(u)?, label(-u)?])
}

/// Draws `labels` (`[left, right, top, bottom]`) at the middle of each edge of `img`, inside it.
pub fn draw_edge_labels(img: &mut Rgba8Image, labels: &[String; 4]) {
    let (w, h) = (img.width, img.height);
    let pad = 4;
    let line = TEXT_PX.ceil() as u32;
    let width = |s: &str| text_width(s).ceil() as u32;
    let [left, right, top, bottom] = labels;
    draw_text(img, pad, h.saturating_sub(line) / 2, left);
    draw_text(
        img,
        w.saturating_sub(width(right) + pad),
        h.saturating_sub(line) / 2,
        right,
    );
    draw_text(img, w.saturating_sub(width(top)) / 2, pad, top);
    draw_text(
        img,
        w.saturating_sub(width(bottom)) / 2,
        h.saturating_sub(line + pad),
        bottom,
    );
}

/// Width of `text` in pixels as [`draw_text`] draws it.
fn text_width(text: &str) -> f32 {
    let font = FontRef::try_from_slice(epaint_default_fonts::HACK_REGULAR)
        .expect("egui's Hack font parses");
    let scaled = font.as_scaled(PxScale::from(TEXT_PX));
    text.chars()
        .map(|c| scaled.h_advance(scaled.glyph_id(c)))
        .sum()
}
