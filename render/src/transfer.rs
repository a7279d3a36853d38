//! Transfer functions: piecewise-linear colour and extinction over the normalized scalar `[0, 1]`
//! (the dataset's value range mapped to `[0, 1]`).
//!
//! Opacity is an **extinction per unit length**, so an image does not depend on how finely the volume
//! is tessellated. The unit is the dataset's bounding-box diagonal: a world-space extinction is
//! `extinction / diagonal`, so a preset looks alike on datasets of any size. Emission–absorption:
//! along a ray, `dL = T · rgb(s) · τ(s) dt`, `dT = −T · τ(s) dt` (seed 001 §2–3).

use serde::{Deserialize, Serialize};
use std::path::Path;
use tetwave_protocol::store_format::{value_histogram, Manifest};
use tetwave_protocol::view::{ImageCriterion, Sensitivity, SENSITIVITY_BINS};
use tetwave_protocol::BaseMesh;

use crate::render_mesh::RenderMesh;

/// One control point.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TfPoint {
    /// Normalized scalar in `[0, 1]`.
    pub s: f32,
    /// Emitted colour, linear, in `[0, 1]`.
    pub rgb: [f32; 3],
    /// Extinction per bounding-box diagonal.
    pub extinction: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransferFunction {
    pub name: String,
    pub points: Vec<TfPoint>,
}

#[derive(Debug, thiserror::Error)]
pub enum TfError {
    #[error("unknown transfer function {0:?} (presets: {PRESETS}; or a .json file)")]
    Unknown(String),
    #[error("{path}: {reason}")]
    File { path: String, reason: String },
    #[error("transfer function: {0}")]
    Invalid(String),
}

/// Names of the presets.
pub const PRESETS: &str = "default, transparent, opaque, shells";

/// The name of the fitted transfer function ([`TransferFunction::fitted`]): the `default` preset
/// fitted to a dataset's value histogram. [`TransferFunction::load`] reads it as `default` (a
/// renderer without a histogram falls back to the preset).
pub const AUTO: &str = "auto";

/// The volume-mean extinction (per bounding-box diagonal) of the fitted transfer function: a ray
/// through 0.2 diagonals of the data, the mean length through the domain of the default view on the
/// four FEM meshes of `scripts/bench-fidelity.py` (0.13–0.29, measured), has optical depth 2.
pub const AUTO_MEAN_EXTINCTION: f64 = 10.0;

/// The most control points a transfer function may have (the GPU table's size).
pub const MAX_POINTS: usize = 32;

fn p(s: f32, rgb: [f32; 3], extinction: f32) -> TfPoint {
    TfPoint { s, rgb, extinction }
}

impl TransferFunction {
    /// A named preset, or a JSON file (`{"name": …, "points": [{"s":…, "rgb":[…], "extinction":…}]}`).
    pub fn load(spec: &str) -> Result<Self, TfError> {
        if spec.ends_with(".json") {
            let text = std::fs::read_to_string(Path::new(spec)).map_err(|e| TfError::File {
                path: spec.into(),
                reason: e.to_string(),
            })?;
            let tf: TransferFunction = serde_json::from_str(&text).map_err(|e| TfError::File {
                path: spec.into(),
                reason: e.to_string(),
            })?;
            tf.validate()?;
            return Ok(tf);
        }
        if spec == AUTO {
            return Ok(Self::preset("default").expect("the default preset exists"));
        }
        Self::preset(spec).ok_or_else(|| TfError::Unknown(spec.into()))
    }

    /// [`Self::load`], except that `auto` is the `default` preset fitted to `histogram`
    /// ([`Self::fitted`]) when there is one.
    pub fn load_with(spec: &str, histogram: Option<&ValueHistogram>) -> Result<Self, TfError> {
        match histogram {
            Some(h) if spec == AUTO => Ok(Self::preset("default")
                .expect("the default preset exists")
                .fitted(h)),
            _ => Self::load(spec),
        }
    }

    /// [`Self::load_with`] a store manifest's histogram ([`ValueHistogram::of_manifest`]): what
    /// every client of a store draws with, streaming or not.
    pub fn for_manifest(spec: &str, m: &Manifest) -> Result<Self, TfError> {
        Self::load_with(spec, ValueHistogram::of_manifest(m).as_ref())
    }

    /// This transfer function fitted to a dataset whose normalized values have the volume
    /// histogram `h` (named [`AUTO`]): the same colours and extinctions in the same order, with
    ///
    /// - each control point moved from `s` to the data's `s`-quantile (`h`'s inverse cumulative
    ///   distribution), so that each colour band covers the share of the data's volume it covers of
    ///   `[0, 1]` (a histogram equalization; points kept at least one bin apart), and
    /// - every extinction replaced by its square root, scaled by one factor so that the volume-mean
    ///   extinction over the data is [`AUTO_MEAN_EXTINCTION`] per diagonal. The root keeps the
    ///   order (denser where the preset is denser) but narrows the preset's range (40:1 for
    ///   `default`, 6.3:1 fitted): with the bands equalized, the lower 45 % of the data would
    ///   otherwise be nearly transparent (a heat sink's fins: invisible).
    ///
    /// An empty histogram (no volume) leaves the function as it is but for the name.
    pub fn fitted(&self, h: &ValueHistogram) -> TransferFunction {
        let mut out = TransferFunction {
            name: AUTO.into(),
            points: self.points.clone(),
        };
        let total: f64 = h.weights.iter().sum();
        if total <= 0.0 || !total.is_finite() || self.points.len() < 2 {
            return out;
        }
        let n = self.points.len();
        let gap = 1.0 / h.weights.len() as f64;
        let mut s: Vec<f64> = self
            .points
            .iter()
            .map(|q| h.quantile(q.s.clamp(0.0, 1.0) as f64))
            .collect();
        let (first, last) = (self.points[0].s as f64, self.points[n - 1].s as f64);
        s[0] = first.clamp(0.0, 1.0);
        s[n - 1] = last.clamp(0.0, 1.0);
        for i in 1..n {
            s[i] = s[i].max(s[i - 1] + gap);
        }
        for i in (0..n - 1).rev() {
            s[i] = s[i].min(s[i + 1] - gap);
        }
        for (q, &si) in out.points.iter_mut().zip(&s) {
            q.s = si as f32;
        }
        for q in &mut out.points {
            q.extinction = q.extinction.sqrt();
        }
        let mean = h.mean(|x| out.eval(x).1);
        if mean > 0.0 && mean.is_finite() {
            let k = AUTO_MEAN_EXTINCTION / mean;
            for q in &mut out.points {
                q.extinction = (q.extinction as f64 * k) as f32;
            }
        }
        out
    }

    pub fn preset(name: &str) -> Option<Self> {
        let points = match name {
            // blue → white → orange ramp, moderate extinction: an opaque-ish look on the harmonic shells
            "default" => vec![
                p(0.0, [0.1, 0.2, 0.9], 0.5),
                p(0.45, [0.2, 0.6, 0.9], 1.0),
                p(0.6, [0.9, 0.9, 0.8], 4.0),
                p(0.8, [1.0, 0.6, 0.2], 12.0),
                p(1.0, [1.0, 0.3, 0.1], 20.0),
            ],
            // very transparent: light haze
            "transparent" => vec![
                p(0.0, [0.2, 0.4, 1.0], 0.05),
                p(0.5, [0.6, 0.9, 0.6], 0.2),
                p(1.0, [1.0, 0.8, 0.3], 0.6),
            ],
            // dense: most rays saturate
            "opaque" => vec![
                p(0.0, [0.3, 0.3, 0.9], 10.0),
                p(0.5, [0.9, 0.9, 0.9], 30.0),
                p(1.0, [1.0, 0.4, 0.1], 60.0),
            ],
            // narrow peaks at two iso-values
            "shells" => vec![
                p(0.0, [0.0, 0.0, 0.0], 0.0),
                p(0.25, [0.0, 0.0, 0.0], 0.0),
                p(0.3, [0.2, 0.5, 1.0], 15.0),
                p(0.35, [0.0, 0.0, 0.0], 0.0),
                p(0.75, [0.0, 0.0, 0.0], 0.0),
                p(0.8, [1.0, 0.5, 0.1], 30.0),
                p(0.85, [0.0, 0.0, 0.0], 0.0),
                p(1.0, [0.0, 0.0, 0.0], 0.0),
            ],
            _ => return None,
        };
        Some(TransferFunction {
            name: name.into(),
            points,
        })
    }

    pub fn validate(&self) -> Result<(), TfError> {
        if self.points.is_empty() || self.points.len() > MAX_POINTS {
            return Err(TfError::Invalid(format!(
                "needs 1..={MAX_POINTS} points, has {}",
                self.points.len()
            )));
        }
        for w in self.points.windows(2) {
            if w[0].s.partial_cmp(&w[1].s) == Some(std::cmp::Ordering::Greater) || w[0].s.is_nan() {
                return Err(TfError::Invalid("points must be sorted by s".into()));
            }
        }
        for q in &self.points {
            let ok = q.s.is_finite()
                && q.extinction.is_finite()
                && q.extinction >= 0.0
                && q.rgb.iter().all(|c| (0.0..=1.0).contains(c));
            if !ok {
                return Err(TfError::Invalid(
                    "values must be finite, extinction ≥ 0 and colour in [0, 1]".into(),
                ));
            }
        }
        Ok(())
    }

    /// Colour and extinction (per diagonal) at normalized scalar `s` (clamped to the end points).
    #[inline]
    pub fn eval(&self, s: f64) -> ([f64; 3], f64) {
        let pts = &self.points;
        let first = &pts[0];
        if s <= first.s as f64 || pts.len() == 1 {
            return (first.rgb.map(|c| c as f64), first.extinction as f64);
        }
        for w in pts.windows(2) {
            let (a, b) = (&w[0], &w[1]);
            if s <= b.s as f64 {
                let span = (b.s - a.s) as f64;
                let t = if span > 0.0 {
                    (s - a.s as f64) / span
                } else {
                    1.0
                };
                let lerp = |x: f32, y: f32| x as f64 + (y as f64 - x as f64) * t;
                return (
                    [
                        lerp(a.rgb[0], b.rgb[0]),
                        lerp(a.rgb[1], b.rgb[1]),
                        lerp(a.rgb[2], b.rgb[2]),
                    ],
                    lerp(a.extinction, b.extinction),
                );
            }
        }
        let last = pts.last().unwrap();
        (last.rgb.map(|c| c as f64), last.extinction as f64)
    }

    /// The image criterion of this transfer function over `value_range` on a dataset on `base`
    /// (whose bounding-box diagonal is the transfer function's unit of length), with threshold
    /// `eps`: what the client's selection and the server's view order both weigh nodes by.
    pub fn image_criterion(
        &self,
        value_range: [f32; 2],
        base: &BaseMesh,
        eps: f64,
    ) -> ImageCriterion {
        let (lo, hi) = base.bounds();
        let diag = (0..3).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f64>().sqrt();
        ImageCriterion {
            sens: self.sensitivity(SENSITIVITY_BINS),
            value_range,
            length_unit: diag,
            eps,
        }
    }

    /// The sensitivity the image criterion reads ([`Sensitivity`]), over `bins` equal bins of the
    /// normalized scalar: per bin, the largest `max_channel |d(c·τ)/ds| + |dτ/ds|` of the pieces
    /// that overlap it (exact: on a linear piece that derivative is linear, so its largest value
    /// over a bin is at one of the bin's ends). A jump (two points at one `s`) counts as 10³⁰.
    pub fn sensitivity(&self, bins: usize) -> Sensitivity {
        let bins = bins.max(1);
        let mut out = vec![0.0f32; bins];
        for w in self.points.windows(2) {
            let (a, b) = (&w[0], &w[1]);
            let (sa, sb) = (a.s as f64, b.s as f64);
            let span = sb - sa;
            let jump = a.extinction != b.extinction
                || (a.rgb != b.rgb && (a.extinction > 0.0 || b.extinction > 0.0));
            let first = ((sa.clamp(0.0, 1.0) * bins as f64) as usize).min(bins - 1);
            let last = ((sb.clamp(0.0, 1.0) * bins as f64) as usize).min(bins - 1);
            if span <= 0.0 {
                if jump {
                    out[first] = out[first].max(1e30);
                }
                continue;
            }
            let dt = (b.extinction - a.extinction) as f64 / span;
            let slope = |s: f64| {
                let t = ((s - sa) / span).clamp(0.0, 1.0);
                let tau = a.extinction as f64 + (b.extinction - a.extinction) as f64 * t;
                let mut m = 0.0f64;
                for ch in 0..3 {
                    let c = a.rgb[ch] as f64 + (b.rgb[ch] - a.rgb[ch]) as f64 * t;
                    let dc = (b.rgb[ch] - a.rgb[ch]) as f64 / span;
                    m = m.max((dc * tau + c * dt).abs());
                }
                m + dt.abs()
            };
            for (k, o) in out.iter_mut().enumerate().take(last + 1).skip(first) {
                let lo = (k as f64 / bins as f64).max(sa);
                let hi = ((k + 1) as f64 / bins as f64).min(sb);
                *o = o.max(slope(lo).max(slope(hi)) as f32);
            }
        }
        Sensitivity::from_bins(out)
    }

    /// Largest extinction (per diagonal).
    pub fn max_extinction(&self) -> f64 {
        self.points
            .iter()
            .map(|q| q.extinction as f64)
            .fold(0.0, f64::max)
    }
}

/// The distribution of a dataset's normalized scalar over its volume: `weights[k]` is the volume
/// whose value falls in the `k`-th of equal bins of `[0, 1]` (values outside are counted in the end
/// bins). What [`TransferFunction::fitted`] fits to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValueHistogram {
    pub weights: Vec<f64>,
}

impl ValueHistogram {
    /// Bins of [`Self::of_mesh`].
    pub const BINS: usize = tetwave_protocol::store_format::HISTOGRAM_BINS;

    /// The histogram of a render mesh's scalar (normalized by its `value_range`) over its volume:
    /// each tet's volume in four equal parts at the points of the degree-2 Gauss rule (barycentric
    /// 0.585, 0.138, 0.138, 0.138 and permutations), where the scalar is interpolated; with a level
    /// set, only the parts at points inside the domain (level set ≥ 0). The same for every
    /// renderer that has the mesh: a mesh file's tets, or a store's finest level.
    pub fn of_mesh(mesh: &RenderMesh) -> Self {
        const A: f64 = 0.585_410_196_624_968_5;
        const B: f64 = 0.138_196_601_125_010_5;
        let bins = Self::BINS;
        let mut weights = vec![0.0f64; bins];
        let pos = |v: u32| glam::DVec3::from_array(mesh.positions[v as usize]);
        for tet in &mesh.tets {
            let x = tet.map(pos);
            let vol = (x[1] - x[0]).dot((x[2] - x[0]).cross(x[3] - x[0])).abs() / 6.0;
            if !(vol > 0.0 && vol.is_finite()) {
                continue;
            }
            let s = tet.map(|v| mesh.normalize(mesh.values[v as usize] as f64));
            let ls = mesh
                .levelset
                .as_ref()
                .map(|l| tet.map(|v| l[v as usize] as f64));
            let sum_s: f64 = s.iter().sum();
            for k in 0..4 {
                if let Some(l) = ls {
                    let lk = A * l[k] + B * (l.iter().sum::<f64>() - l[k]);
                    if lk < 0.0 {
                        continue;
                    }
                }
                let sk = A * s[k] + B * (sum_s - s[k]);
                if !sk.is_finite() {
                    continue;
                }
                let b = ((sk * bins as f64).floor().max(0.0) as usize).min(bins - 1);
                weights[b] += vol / 4.0;
            }
        }
        ValueHistogram { weights }
    }

    /// The histogram of vertex samples (normalized over `value_range`), one equal weight per
    /// vertex, skipping vertices whose `levelset` is negative (outside the domain): on a
    /// semi-regular lattice, whose finest vertices are evenly spread, close to [`Self::of_mesh`]
    /// of its finest level without building it (a 257³ store's 100 M leaves).
    pub fn of_samples(values: &[f32], value_range: (f32, f32), levelset: Option<&[f32]>) -> Self {
        let inside = |k: usize| levelset.is_none_or(|l| l.get(k).is_none_or(|&x| x >= 0.0));
        let range = [value_range.0, value_range.1];
        Self::of_counts(&value_histogram(values, range, |k| inside(k) as u64))
    }

    /// Bin counts, e.g. a store manifest's [`Manifest::value_histogram`] (its vertex samples,
    /// as [`Self::of_samples`] counts them).
    pub fn of_counts(counts: &[u64]) -> Self {
        ValueHistogram {
            weights: counts.iter().map(|&c| c as f64).collect(),
        }
    }

    /// The histogram a manifest records, if any.
    pub fn of_manifest(m: &Manifest) -> Option<Self> {
        m.value_histogram.as_deref().map(Self::of_counts)
    }

    /// The `q`-quantile of the normalized scalar (`q` in `[0, 1]`): the inverse of the cumulative
    /// distribution, linear inside each bin; 0 for an empty histogram.
    pub fn quantile(&self, q: f64) -> f64 {
        let n = self.weights.len();
        let total: f64 = self.weights.iter().sum();
        if n == 0 || total <= 0.0 || !total.is_finite() {
            return 0.0;
        }
        let want = q.clamp(0.0, 1.0) * total;
        let mut acc = 0.0;
        for (k, &w) in self.weights.iter().enumerate() {
            if w > 0.0 && acc + w >= want {
                let f = ((want - acc) / w).clamp(0.0, 1.0);
                return (k as f64 + f) / n as f64;
            }
            acc += w;
        }
        1.0
    }

    /// The volume mean of `f` (of the normalized scalar, taken at each bin's centre); 0 for an
    /// empty histogram.
    pub fn mean(&self, f: impl Fn(f64) -> f64) -> f64 {
        let n = self.weights.len() as f64;
        let total: f64 = self.weights.iter().sum();
        if total <= 0.0 || !total.is_finite() {
            return 0.0;
        }
        self.weights
            .iter()
            .enumerate()
            .map(|(k, &w)| w * f((k as f64 + 0.5) / n))
            .sum::<f64>()
            / total
    }
}

/// Emission–absorption over a segment of world length `len` along which the normalized scalar goes
/// linearly from `s0` to `s1`, by the midpoint rule with `steps` sub-steps. `ext_scale` converts the
/// transfer function's extinction to world units (`1/diagonal`). Returns premultiplied colour and the
/// segment's transmittance.
pub fn integrate_segment(
    tf: &TransferFunction,
    s0: f64,
    s1: f64,
    len: f64,
    ext_scale: f64,
    steps: u32,
) -> ([f64; 3], f64) {
    let h = len / steps as f64;
    let mut c = [0.0f64; 3];
    let mut t = 1.0f64;
    for i in 0..steps {
        let u = (i as f64 + 0.5) / steps as f64;
        let (rgb, ext) = tf.eval(s0 + (s1 - s0) * u);
        let a = 1.0 - (-(ext * ext_scale) * h).exp();
        for k in 0..3 {
            c[k] += t * rgb[k] * a;
        }
        t *= 1.0 - a;
    }
    (c, t)
}

/// [`integrate_segment`] with sub-steps doubled until the colour and transmittance change by less than
/// `tol` (at most 2^16 sub-steps): the converged integral the reference uses.
pub fn integrate_segment_converged(
    tf: &TransferFunction,
    s0: f64,
    s1: f64,
    len: f64,
    ext_scale: f64,
    tol: f64,
) -> ([f64; 3], f64) {
    let mut steps = 4u32;
    let mut prev = integrate_segment(tf, s0, s1, len, ext_scale, steps);
    while steps < 1 << 16 {
        steps *= 2;
        let next = integrate_segment(tf, s0, s1, len, ext_scale, steps);
        let diff = (0..3)
            .map(|k| (next.0[k] - prev.0[k]).abs())
            .fold((next.1 - prev.1).abs(), f64::max);
        prev = next;
        if diff < tol {
            break;
        }
    }
    prev
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every preset's sensitivity bounds its finite differences bin by bin, and is 0 where the
    /// preset is flat.
    #[test]
    fn sensitivity_bounds_finite_differences() {
        for name in PRESETS.split(", ") {
            let tf = TransferFunction::preset(name).unwrap();
            let sens = tf.sensitivity(32);
            let f = |s: f64| {
                let (c, t) = tf.eval(s);
                (c.map(|c| c * t), t)
            };
            for i in 0..3200 {
                let (s0, s1) = (i as f64 / 3200.0, (i + 1) as f64 / 3200.0);
                let ((c0, t0), (c1, t1)) = (f(s0), f(s1));
                let h = s1 - s0;
                let dc = (0..3)
                    .map(|k| (c1[k] - c0[k]).abs() / h)
                    .fold(0.0, f64::max);
                let g = dc + (t1 - t0).abs() / h;
                let bound = sens.max_over(s0, s1);
                assert!(
                    g <= bound * (1.0 + 1e-6) + 1e-9,
                    "{name} at {s0}: {g} > {bound}"
                );
            }
        }
        let flat = TransferFunction {
            name: "flat".into(),
            points: vec![p(0.0, [1.0, 0.0, 0.0], 2.0), p(1.0, [1.0, 0.0, 0.0], 2.0)],
        };
        assert_eq!(flat.sensitivity(8).max(), 0.0);
    }

    #[test]
    fn presets_are_valid() {
        for name in PRESETS.split(", ") {
            TransferFunction::preset(name).unwrap().validate().unwrap();
        }
        assert!(TransferFunction::load("nope").is_err());
    }

    /// Colours outside `[0, 1]` are refused: the reference integrator refines its steps on the
    /// colour's variation, and colours like 3e38 made it take minutes for a small image.
    #[test]
    fn colours_outside_the_unit_range_are_refused() {
        for rgb in [
            [3e38, 1.0, 1.0],
            [0.5, 1.01, 0.0],
            [0.0, 0.0, -0.1],
            [f32::NAN, 0.0, 0.0],
        ] {
            let tf = TransferFunction {
                name: "x".into(),
                points: vec![p(0.0, rgb, 1.0), p(1.0, [1.0; 3], 1.0)],
            };
            let e = tf.validate().expect_err("refused");
            assert!(e.to_string().contains("colour in [0, 1]"), "{rgb:?}: {e}");
        }
    }

    #[test]
    fn constant_medium_matches_closed_form() {
        let tf = TransferFunction {
            name: "c".into(),
            points: vec![p(0.0, [0.5, 0.25, 1.0], 2.0)],
        };
        let (c, t) = integrate_segment_converged(&tf, 0.2, 0.9, 0.7, 1.0, 1e-12);
        let a = 1.0 - (-2.0f64 * 0.7).exp();
        assert!((t - (1.0 - a)).abs() < 1e-12);
        assert!((c[0] - 0.5 * a).abs() < 1e-12 && (c[2] - a).abs() < 1e-12);
    }

    fn hist(f: impl Fn(f64) -> f64) -> ValueHistogram {
        let n = ValueHistogram::BINS;
        ValueHistogram {
            weights: (0..n).map(|k| f((k as f64 + 0.5) / n as f64)).collect(),
        }
    }

    /// On uniformly distributed data the fit keeps the preset's points (within a bin) and only
    /// scales the extinction to the target mean.
    #[test]
    fn fitting_uniform_data_keeps_the_points() {
        let d = TransferFunction::preset("default").unwrap();
        let h = hist(|_| 1.0);
        let f = d.fitted(&h);
        assert_eq!(f.name, AUTO);
        f.validate().unwrap();
        let k = f.points[0].extinction / d.points[0].extinction.sqrt();
        for (a, b) in d.points.iter().zip(&f.points) {
            assert!((a.s - b.s).abs() <= 1.0 / 256.0, "{a:?} {b:?}");
            assert_eq!(a.rgb, b.rgb);
            assert!((b.extinction / a.extinction.sqrt() - k).abs() < 1e-5);
        }
        assert!((h.mean(|s| f.eval(s).1) - AUTO_MEAN_EXTINCTION).abs() < 1e-6);
    }

    /// Data concentrated at low values (a decaying, FEM-like field): the colour bands move to the
    /// data's quantiles, and each band covers the share of the volume it covers of [0, 1].
    #[test]
    fn fitting_skewed_data_equalizes_the_bands() {
        let d = TransferFunction::preset("default").unwrap();
        let h = hist(|s| (-20.0 * s).exp());
        let f = d.fitted(&h);
        f.validate().unwrap();
        assert_eq!((f.points[0].s, f.points[4].s), (0.0, 1.0));
        for (a, b) in d.points.iter().zip(&f.points).skip(1).take(3) {
            // the share of the volume below the fitted point is the preset's s
            let total: f64 = h.weights.iter().sum();
            let below: f64 = h
                .weights
                .iter()
                .enumerate()
                .map(|(k, w)| w * ((b.s as f64 * 256.0 - k as f64).clamp(0.0, 1.0)))
                .sum();
            assert!((below / total - a.s as f64).abs() < 1e-3, "{a:?} -> {b:?}");
            assert!(b.s < 0.15, "{b:?}");
        }
        assert!((h.mean(|s| f.eval(s).1) - AUTO_MEAN_EXTINCTION).abs() < 1e-6);
    }

    /// A constant field (one bin) and an empty histogram give valid functions: points kept a bin
    /// apart, and no scaling without volume.
    #[test]
    fn fitting_degenerate_histograms() {
        let d = TransferFunction::preset("default").unwrap();
        let one = hist(|s| if (0.5..0.51).contains(&s) { 1.0 } else { 0.0 });
        let f = d.fitted(&one);
        f.validate().unwrap();
        for w in f.points.windows(2) {
            assert!(w[1].s - w[0].s >= 1.0 / 256.0 - 1e-6, "{:?}", f.points);
        }
        assert!((one.mean(|s| f.eval(s).1) - AUTO_MEAN_EXTINCTION).abs() < 1e-6);
        let empty = hist(|_| 0.0);
        let e = d.fitted(&empty);
        assert_eq!((e.name.as_str(), &e.points), (AUTO, &d.points));
        assert_eq!(empty.quantile(0.3), 0.0);
    }

    /// `auto` is the fitted default with a histogram and the `default` preset without; explicit
    /// choices do not change with a histogram.
    #[test]
    fn auto_loads_fitted_or_default() {
        let d = TransferFunction::preset("default").unwrap();
        let h = hist(|s| (-20.0 * s).exp());
        assert_eq!(TransferFunction::load(AUTO).unwrap(), d);
        assert_eq!(TransferFunction::load_with(AUTO, None).unwrap(), d);
        assert_eq!(
            TransferFunction::load_with(AUTO, Some(&h)).unwrap(),
            d.fitted(&h)
        );
        for name in PRESETS.split(", ") {
            assert_eq!(
                TransferFunction::load_with(name, Some(&h)).unwrap(),
                TransferFunction::preset(name).unwrap()
            );
        }
    }

    /// The histogram of a mesh is its volume's: a linear field on a cube is uniform, and a level
    /// set leaves out the volume outside the domain.
    #[test]
    fn histogram_of_a_mesh_is_by_volume() {
        let mut m = RenderMesh::kuhn_cube(8, 2.0, |p| p[0]);
        let h = ValueHistogram::of_mesh(&m);
        assert_eq!(h.weights.len(), ValueHistogram::BINS);
        assert!((h.weights.iter().sum::<f64>() - 8.0).abs() < 1e-9);
        for q in [0.1, 0.25, 0.5, 0.75, 0.9] {
            assert!((h.quantile(q) - q).abs() < 0.03, "{q}: {}", h.quantile(q));
        }
        // domain: x ≤ 0.5 (a quarter of the cube's width)
        m.levelset = Some(m.positions.iter().map(|p| (0.5 - p[0]) as f32).collect());
        let h = ValueHistogram::of_mesh(&m);
        assert!((h.weights.iter().sum::<f64>() - 2.0).abs() < 0.1);
        assert!(h.quantile(1.0) <= 0.3, "{}", h.quantile(1.0));
    }

    /// A lattice's vertex samples give about the histogram of its volume, outside vertices left out.
    #[test]
    fn histogram_of_lattice_samples_is_close_to_the_volumes() {
        let m = RenderMesh::kuhn_cube(48, 2.0, |p| p[0] * p[0]);
        let by_volume = ValueHistogram::of_mesh(&m);
        let by_vertex = ValueHistogram::of_samples(&m.values, m.value_range, None);
        for q in [0.1, 0.25, 0.5, 0.75, 0.9] {
            let (a, b) = (by_volume.quantile(q), by_vertex.quantile(q));
            // a vertex stands for a lattice step (its boundary ones for half of one): quantiles
            // agree to about a step of the scalar, 2/48 here
            assert!((a - b).abs() < 0.05, "{q}: {a} by volume, {b} by vertex");
        }
        let outside: Vec<f32> = m.positions.iter().map(|p| (1.0 - p[0]) as f32).collect();
        let h = ValueHistogram::of_samples(&m.values, m.value_range, Some(&outside));
        assert!(h.quantile(1.0) <= 0.3, "{}", h.quantile(1.0));
        assert!(h.weights.iter().sum::<f64>() < m.values.len() as f64 * 0.6);
    }

    /// Splitting a segment in two and compositing gives the same result (extinction per length: no
    /// dependence on tessellation).
    #[test]
    fn splitting_a_segment_does_not_change_it() {
        let tf = TransferFunction::preset("default").unwrap();
        let whole = integrate_segment_converged(&tf, 0.1, 0.9, 0.3, 3.0, 1e-12);
        let a = integrate_segment_converged(&tf, 0.1, 0.5, 0.15, 3.0, 1e-12);
        let b = integrate_segment_converged(&tf, 0.5, 0.9, 0.15, 3.0, 1e-12);
        for k in 0..3 {
            assert!((whole.0[k] - (a.0[k] + a.1 * b.0[k])).abs() < 1e-9);
        }
        assert!((whole.1 - a.1 * b.1).abs() < 1e-9);
    }
}
