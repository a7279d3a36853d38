//! What a colour legend says, for every place that draws one (`tetwave render --legend`, the
//! viewer's panel, the server's page): the scalar's name and the range the transfer function
//! spans, and the transfer function's colours across it.

use crate::transfer::TransferFunction;

/// The legend's line: the scalar's name and the range the transfer function spans.
pub fn legend_text(name: &str, range: [f32; 2]) -> String {
    format!("{name}  {} .. {}", short(range[0]), short(range[1]))
}

/// A value in at most 4 decimals (trailing zeros dropped), or 4 significant digits in
/// scientific notation outside `[1e-3, 1e5)`: as a person reads a legend.
pub fn short(v: f32) -> String {
    let v = v as f64;
    if v == 0.0 || (1e-3..1e5).contains(&v.abs()) {
        let s = format!("{v:.4}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        if s.is_empty() || s == "-" || s == "-0" {
            "0".into()
        } else {
            s.into()
        }
    } else {
        format!("{v:.3e}")
    }
}

/// The transfer function's colour (RGB, 0–255) at `s` of its normalized range.
pub fn colour_at(tf: &TransferFunction, s: f64) -> [u8; 3] {
    let (rgb, _) = tf.eval(s);
    rgb.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8)
}

/// A CSS `linear-gradient` of the transfer function's colours, left to right, at `stops` evenly
/// spaced places (at least 2).
pub fn css_gradient(tf: &TransferFunction, stops: usize) -> String {
    let n = stops.max(2);
    let parts: Vec<String> = (0..n)
        .map(|k| {
            let s = k as f64 / (n - 1) as f64;
            let [r, g, b] = colour_at(tf, s);
            format!("rgb({r},{g},{b}) {:.1}%", 100.0 * s)
        })
        .collect();
    format!("linear-gradient(to right, {})", parts.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_values() {
        assert_eq!(short(0.0), "0");
        assert_eq!(short(1.0), "1");
        assert_eq!(short(-0.25), "-0.25");
        assert_eq!(short(979.5), "979.5");
        assert_eq!(short(1.5e-7), "1.500e-7");
        assert_eq!(legend_text("p", [0.0, 1.0]), "p  0 .. 1");
    }

    #[test]
    fn gradient_has_the_end_colours() {
        let tf = TransferFunction::preset("default").unwrap();
        let g = css_gradient(&tf, 5);
        let [r, gr, b] = colour_at(&tf, 0.0);
        assert!(g.starts_with(&format!("linear-gradient(to right, rgb({r},{gr},{b}) 0.0%")));
        let [r, gr, b] = colour_at(&tf, 1.0);
        assert!(g.ends_with(&format!("rgb({r},{gr},{b}) 100.0%)")), "{g}");
    }
}
