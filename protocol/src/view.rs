//! The view-dependent refinement criterion, defined once for both sides: the camera, the
//! screen-space error of a tet's bounding sphere (thesis eq. 43), frustum tests, tolerances and the
//! data-aware weight. The client's selection and the server's view order both call these functions,
//! so the order in which the server sends nodes follows what the client will want.

use crate::wire::ViewParams;
use glam::{DMat4, DVec3, Vec3};
use std::fmt;

/// A pinhole camera shared by the criteria, the GPU renderer and the CPU reference: the same
/// pixel → ray mapping everywhere (pixel centres, row 0 at the top).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub eye: DVec3,
    pub target: DVec3,
    pub up: DVec3,
    /// Vertical field of view, degrees.
    pub fovy_deg: f64,
    /// Near-plane distance along the view direction; rays start there.
    pub near: f64,
    pub width: u32,
    pub height: u32,
}

/// How far the default view stands from a volume's centre, in diagonals of its bounding box:
/// the whole box in view at the default 40° field of view from any direction. Every default
/// view (`tetwave render`, `stream`, `view`, the server's `/v1/render` and its view order before
/// a client's `View`) is framed by [`Camera::framing`].
pub const FRAMING_DIAGONALS: f64 = 1.6;

/// A box's default framing: the point orbited and the eye's distance from it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Framing {
    pub center: DVec3,
    /// The box's diagonal.
    pub diagonal: f64,
    /// [`FRAMING_DIAGONALS`] × the diagonal.
    pub distance: f64,
}

/// The default orbit's azimuth and elevation, in degrees, and its vertical field of view: what
/// `tetwave render`, `stream`, `view` and the server's `/v1/render` draw unless told otherwise.
pub const DEFAULT_AZIMUTH: f64 = 35.0;
pub const DEFAULT_ELEVATION: f64 = 25.0;
pub const DEFAULT_FOV: f64 = 40.0;

/// Elevations an orbit is moved to stay inside ±89°, so that its up vector never flips.
pub const MAX_ELEVATION: f64 = 89.0;

/// An orbit camera's parameters: the eye on a sphere around `target`, at `azimuth` degrees about
/// the vertical (z) axis and `elevation` degrees above the xy plane, `distance` away, with a
/// vertical field of view of `fov` degrees. The one parametrization of `tetwave render`'s,
/// `/v1/render`'s and the viewer's cameras, so that an unpanned view is reproduced offscreen and
/// by the server.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orbit {
    /// The point orbited: the volume's centre unless panned.
    pub target: DVec3,
    pub azimuth: f64,
    pub elevation: f64,
    pub distance: f64,
    pub fov: f64,
}

impl Orbit {
    /// An orbit around `target` at `distance`, with the default angles and field of view.
    pub fn around(target: DVec3, distance: f64) -> Orbit {
        Orbit {
            target,
            azimuth: DEFAULT_AZIMUTH,
            elevation: DEFAULT_ELEVATION,
            distance,
            fov: DEFAULT_FOV,
        }
    }

    /// The default orbit of a framed box: around its centre at the framing's distance.
    pub fn framed(f: Framing) -> Orbit {
        Orbit::around(f.center, f.distance)
    }

    /// The camera for a `width`×`height` view.
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let (az, el) = (self.azimuth.to_radians(), self.elevation.to_radians());
        let dir = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        let up = if el.cos().abs() < 1e-6 {
            DVec3::Y
        } else {
            DVec3::Z
        };
        Camera {
            eye: self.target + dir * self.distance,
            target: self.target,
            up,
            fovy_deg: self.fov,
            near: (self.distance * 1e-3).max(1e-6),
            width,
            height,
        }
    }

    /// Rotates by `d_az`, `d_el` degrees (elevation clamped to ±[`MAX_ELEVATION`]).
    pub fn rotate(&mut self, d_az: f64, d_el: f64) {
        self.azimuth = (self.azimuth + d_az).rem_euclid(360.0);
        self.elevation = (self.elevation + d_el).clamp(-MAX_ELEVATION, MAX_ELEVATION);
    }

    /// Multiplies the distance by `factor` (> 0), kept within `[min, max]`.
    pub fn zoom(&mut self, factor: f64, min: f64, max: f64) {
        if factor.is_finite() && factor > 0.0 {
            self.distance = (self.distance * factor).clamp(min, max);
        }
    }

    /// Moves the target by `dx`, `dy` pixels of a `height`-pixel view in the view plane (the
    /// point under the cursor follows it at the target's depth).
    pub fn pan(&mut self, dx: f64, dy: f64, height: u32) {
        let cam = self.camera(16, height.max(1));
        let (right, up) = {
            let fwd = cam.forward();
            let right = fwd.cross(cam.up).normalize_or_zero();
            (right, right.cross(fwd).normalize_or_zero())
        };
        let units_per_px =
            2.0 * self.distance * (self.fov.to_radians() / 2.0).tan() / height.max(1) as f64;
        self.target += (-dx * right + dy * up) * units_per_px;
    }
}

impl Camera {
    /// The default framing of the box `lo`..`hi` (any corner order per axis is its own box: the
    /// centre and diagonal are those of the two points).
    pub fn framing(lo: [f64; 3], hi: [f64; 3]) -> Framing {
        let (lo, hi) = (DVec3::from_array(lo), DVec3::from_array(hi));
        let diagonal = hi.distance(lo);
        Framing {
            center: (lo + hi) * 0.5,
            diagonal,
            distance: FRAMING_DIAGONALS * diagonal,
        }
    }

    /// The camera of a client's `View` message: any up vector (a degenerate one is replaced), the
    /// near plane at the eye, a viewport of at least 1×1 pixels.
    pub fn from_view_params(v: &ViewParams) -> Self {
        let eye = DVec3::from_array(v.eye);
        let target = DVec3::from_array(v.target);
        let fwd = (target - eye).try_normalize().unwrap_or(DVec3::NEG_Z);
        let up = [DVec3::from_array(v.up), DVec3::Y, DVec3::X]
            .into_iter()
            .find(|u| fwd.cross(*u).try_normalize().is_some())
            .unwrap_or(DVec3::Y);
        Camera {
            eye,
            target: eye + fwd,
            up,
            fovy_deg: v.fovy_deg,
            near: 0.0,
            width: v.width.max(1),
            height: v.height.max(1),
        }
    }

    /// The `View` message for this camera and a tolerance of `tol_px` pixels (the inverse of
    /// [`Self::from_view_params`] up to the near plane).
    pub fn view_params(&self, tol_px: f64) -> ViewParams {
        ViewParams {
            eye: self.eye.to_array(),
            target: self.target.to_array(),
            up: self.basis().1.to_array(),
            fovy_deg: self.fovy_deg,
            width: self.width,
            height: self.height,
            tol_px,
        }
    }

    /// Unit view direction.
    pub fn forward(&self) -> DVec3 {
        (self.target - self.eye).normalize()
    }

    /// Orthonormal (right, up, forward).
    pub fn basis(&self) -> (DVec3, DVec3, DVec3) {
        let f = self.forward();
        let r = f.cross(self.up).normalize();
        let u = r.cross(f);
        (r, u, f)
    }

    /// Unit direction of the ray through the centre of pixel `(x, y)`.
    pub fn ray_dir(&self, x: u32, y: u32) -> DVec3 {
        let (r, u, f) = self.basis();
        let th = (self.fovy_deg.to_radians() * 0.5).tan();
        let aspect = self.width as f64 / self.height as f64;
        let nx = 2.0 * (x as f64 + 0.5) / self.width as f64 - 1.0;
        let ny = 1.0 - 2.0 * (y as f64 + 0.5) / self.height as f64;
        (f + r * (nx * th * aspect) + u * (ny * th)).normalize()
    }

    /// Ray parameter where a unit ray `dir` crosses the near plane.
    pub fn near_t(&self, dir: DVec3) -> f64 {
        self.near / dir.dot(self.forward()).max(1e-12)
    }

    /// View-projection matrix (wgpu depth range) for world coordinates expressed relative to `origin`.
    pub fn view_proj(&self, origin: DVec3, far: f64) -> DMat4 {
        let view = DMat4::look_at_rh(self.eye - origin, self.target - origin, self.basis().1);
        let proj = DMat4::perspective_rh(
            self.fovy_deg.to_radians(),
            self.width as f64 / self.height as f64,
            self.near,
            far,
        );
        proj * view
    }
}

/// Refinement tolerance of the screen-space error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tolerance {
    Pixels(f64),
    /// Percent of the viewport height `H` (the thesis' 20%, 15%, 12.5%, 10%, 6.25%).
    PercentOfHeight(f64),
}

impl Tolerance {
    /// The tolerance in pixels for a viewport `height` pixels tall.
    pub fn pixels(&self, height: u32) -> f64 {
        match *self {
            Tolerance::Pixels(p) => p,
            Tolerance::PercentOfHeight(p) => p / 100.0 * height as f64,
        }
    }

    /// `"20%"` → 20 % of `H`; `"12"` or `"12px"` → 12 pixels.
    pub fn parse(s: &str) -> Result<Self, String> {
        let s = s.trim();
        let num = |t: &str| {
            t.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v >= 0.0)
                .ok_or_else(|| format!("bad tolerance {s:?}: give 20% or 12px"))
        };
        if let Some(p) = s.strip_suffix('%') {
            Ok(Tolerance::PercentOfHeight(num(p)?))
        } else {
            Ok(Tolerance::Pixels(num(s.strip_suffix("px").unwrap_or(s))?))
        }
    }
}

impl fmt::Display for Tolerance {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Tolerance::Pixels(p) => write!(f, "{p}px"),
            Tolerance::PercentOfHeight(p) => write!(f, "{p}%"),
        }
    }
}

/// The camera as the criteria use it: eye, frustum planes, pixels per unit of `diam/dist`.
#[derive(Debug, Clone, Copy)]
pub struct View {
    pub eye: DVec3,
    /// Inward unit normals `n` and offsets `d`: inside iff `n·p + d ≥ 0` (near + 4 sides).
    pub planes: [(DVec3, f64); 5],
    /// `H / (2·tan(fovy/2))`.
    pub pixels_per_unit: f64,
    pub tol_px: f64,
    /// The camera's right, up and forward unit vectors.
    pub basis: [DVec3; 3],
}

impl View {
    pub fn new(cam: &Camera, tol: Tolerance) -> Self {
        let (r, u, f) = cam.basis();
        let ty = (cam.fovy_deg.to_radians() * 0.5).tan();
        let tx = ty * cam.width as f64 / cam.height as f64;
        let side = |n: DVec3| {
            let n = n.normalize();
            (n, -n.dot(cam.eye))
        };
        View {
            eye: cam.eye,
            planes: [
                (f, -(f.dot(cam.eye) + cam.near)),
                side(f * tx - r),
                side(f * tx + r),
                side(f * ty - u),
                side(f * ty + u),
            ],
            pixels_per_unit: cam.height as f64 / (2.0 * ty),
            tol_px: tol.pixels(cam.height),
            basis: [r, u, f],
        }
    }

    /// Whether a sphere is at least partly inside the frustum.
    #[inline]
    pub fn sphere_visible(&self, c: DVec3, r: f64) -> bool {
        Self::offsets_visible(&self.plane_offsets(c), r)
    }

    /// Signed distances `n·c + d` of point `c` to the frustum's planes (positive inside).
    #[inline]
    pub fn plane_offsets(&self, c: DVec3) -> [f64; 5] {
        self.planes.map(|(n, d)| n.dot(c) + d)
    }

    /// [`Self::sphere_visible`] of a sphere of radius `r` whose centre has plane offsets `x`.
    #[inline]
    pub fn offsets_visible(x: &[f64; 5], r: f64) -> bool {
        x.iter().all(|&v| v >= -r)
    }

    /// Thesis eq. 43: vertical pixels of a sphere of diameter `diam` centred at `c`.
    #[inline]
    pub fn error_px(&self, c: DVec3, diam: f64) -> f64 {
        self.error_px_at((c - self.eye).length(), diam)
    }

    /// [`Self::error_px`] of a sphere at distance `dist` from the eye.
    #[inline]
    pub fn error_px_at(&self, dist: f64, diam: f64) -> f64 {
        self.pixels_per_unit * diam / dist.max(1e-12)
    }
}

/// The data-aware weight : `min(1, smax / (δ · value range))` for a subtree
/// whose details are at most `smax` in magnitude. Selection scales the screen-space error by it;
/// the server's view order ranks nodes with the same product.
#[inline]
pub fn data_weight(smax: f32, value_range: [f32; 2], delta: f32) -> f64 {
    let [lo, hi] = value_range;
    let range = ((hi - lo) as f64).max(1e-30);
    (smax as f64 / (delta.max(1e-30) as f64 * range)).min(1.0)
}

/// How fast a transfer function's output changes with the scalar, bin by bin over the normalized
/// scalar `[0, 1]`: in each bin, the largest `max_channel |d(c·τ)/ds| + |dτ/ds|` (colour `c`,
/// extinction `τ` per unit length of the TF's length unit). Outside `[0, 1]` a transfer function is
/// clamped, so it changes nothing there. Built by the renderer from a transfer function; the
/// criteria only read it.
#[derive(Debug, Clone, PartialEq)]
pub struct Sensitivity {
    bins: Vec<f32>,
}

impl Sensitivity {
    /// From per-bin maxima over `[0, 1]` (at least one bin; negative or NaN entries count as 0).
    pub fn from_bins(bins: Vec<f32>) -> Self {
        let mut bins: Vec<f32> = bins
            .into_iter()
            .map(|b| if b.is_nan() { 0.0 } else { b.max(0.0) })
            .collect();
        if bins.is_empty() {
            bins.push(0.0);
        }
        Sensitivity { bins }
    }

    /// The same sensitivity `g` everywhere in `[0, 1]` (tests; a TF one knows nothing of).
    pub fn uniform(g: f32) -> Self {
        Self::from_bins(vec![g])
    }

    /// The largest sensitivity over normalized scalars `[s0, s1]` (0 where that misses `[0, 1]`).
    #[inline]
    pub fn max_over(&self, s0: f64, s1: f64) -> f64 {
        let n = self.bins.len();
        if s1 < 0.0 || s0 > 1.0 || s0.is_nan() || s1.is_nan() || s1 < s0 {
            return 0.0;
        }
        let bin = |s: f64| ((s.clamp(0.0, 1.0) * n as f64) as usize).min(n - 1);
        self.bins[bin(s0)..=bin(s1)]
            .iter()
            .fold(0.0f32, |a, &b| a.max(b)) as f64
    }

    /// The largest sensitivity anywhere.
    pub fn max(&self) -> f64 {
        self.max_over(0.0, 1.0)
    }
}

/// [`ImageCriterion::eps`]'s default: the worst-case colour change of one ray segment counted as
/// a full error (1: the weight is that change itself). The worst case ([`ImageCriterion::weight`])
/// takes the largest slope of the transfer function and the largest detail of a subtree
/// everywhere, so the images it selects differ from the all-leaves image far less: at 2 px on
/// 512², 129³ grids converge to ≥ 50 dB against every leaf with < 3 tets a pixel
/// (docs/benchmarks.md, "Scale", where 0.5 and 2 are measured too).
pub const DEFAULT_IMAGE_EPS: f64 = 1.0;

/// Bins of the transfer function's [`Sensitivity`] table both sides build.
pub const SENSITIVITY_BINS: usize = 256;

/// The bound on how far the full-resolution field can still move inside a level-`l` tet whose
/// subtree's details are at most `smax`, `levels_below = L − l` levels above the finest:
/// `(L − l) · smax + e / 3`. Each level below adds at most `smax` (its details, interpolated
/// linearly), and `e` — the largest deviation of the tet's level-`l` corners from the midpoint
/// value of the parent edge each halves — estimates what the predictor adds beyond linear
/// interpolation: on a smooth field that shrinks 4× a level, `e/4 + e/16 + … = e/3` (exact for
/// a quadratic field). A base tet has no such corners: `e` is infinite.
#[inline]
pub fn image_bound(levels_below: u8, smax: f32, curvature: f64) -> f64 {
    levels_below as f64 * smax as f64 + curvature / 3.0
}

/// The image criterion's weight: how much of a pixel's colour a node's subtree can still change,
/// relative to `eps`, capped at 1 (see [`ImageCriterion::weight`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ImageCriterion {
    /// The transfer function's sensitivity over the normalized scalar.
    pub sens: Sensitivity,
    /// The scalar range the transfer function spans (`[0, 1]` normalized).
    pub value_range: [f32; 2],
    /// The transfer function's unit of length (world units; the bounding-box diagonal).
    pub length_unit: f64,
    /// Colour change (0–1 per channel) of one segment that counts as a full error.
    pub eps: f64,
}

impl ImageCriterion {
    /// The image weight of a tet of diameter `diam` whose vertex values span `[vmin, vmax]` and
    /// whose refinement can move the field by at most `bound` anywhere inside it:
    /// `min(1, ΔI / eps)` with `ΔI = diam / length_unit · bound / range · G`, `G` the largest
    /// [`Sensitivity`] over `[vmin − bound, vmax + bound]`. `ΔI` is the first-order change of the
    /// colour and opacity of a ray segment through the tet (at most `diam` long) when the scalar
    /// along it moves by `bound`. 0 when nothing can change (a zero bound, or a transfer function
    /// flat over every value the subtree can take); 1 for an unknown (infinite) bound where the
    /// transfer function changes at all.
    #[inline]
    pub fn weight(&self, vmin: f32, vmax: f32, bound: f64, diam: f64) -> f64 {
        if bound.is_nan() || bound <= 0.0 {
            return 0.0;
        }
        let [lo, hi] = self.value_range;
        let range = ((hi - lo) as f64).max(1e-30);
        if !bound.is_finite() {
            return if self.sens.max() > 0.0 { 1.0 } else { 0.0 };
        }
        let s0 = (vmin as f64 - bound - lo as f64) / range;
        let s1 = (vmax as f64 + bound - lo as f64) / range;
        let g = self.sens.max_over(s0, s1);
        let di = diam / self.length_unit.max(1e-30) * bound / range * g;
        (di / self.eps.max(1e-30)).min(1.0)
    }
}

impl ImageCriterion {
    /// The weight of a level-`level` node (of `levels` in all) of diameter `diam` whose subtree's
    /// details are at most `smax`, from its corner values `corners` and `curvature`: the largest
    /// deviation of its corners created at its level from the midpoint value of the parent edge
    /// each halves (ignored for a base tet, whose bound is unknown). Both sides call this: the
    /// client on the values it holds, the server on its reference samples.
    #[inline]
    pub fn node_weight(
        &self,
        corners: [f32; 4],
        curvature: f64,
        level: u8,
        levels: u8,
        smax: f32,
        diam: f64,
    ) -> f64 {
        let (vmin, vmax) = corners
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        let curvature = if level == 0 { f64::INFINITY } else { curvature };
        let bound = image_bound(levels.saturating_sub(level), smax, curvature);
        self.weight(vmin, vmax, bound, diam) as f32 as f64
    }
}

/// Bounding sphere of a tet with vertices `p`: the centroid rounded to `f32`, and the distance from
/// it to the farthest vertex rounded up to `f32` (so that the client caches it in 16 bytes, exactly).
/// A node's size in the criterion is this sphere's diameter.
#[inline]
pub fn tet_sphere(p: [DVec3; 4]) -> (Vec3, f32) {
    let c = ((p[0] + p[1] + p[2] + p[3]) * 0.25).as_vec3();
    let cd = c.as_dvec3();
    let r2 = p
        .iter()
        .map(|q| q.distance_squared(cd))
        .fold(0.0f64, f64::max);
    (c, f32_up(r2.sqrt()))
}

/// The screen-space error in pixels of a tet with bounding sphere `(c, r)` and data weight
/// `weight` (1 for the geometric criterion): `View::error_px(c, 2r) · weight`.
#[inline]
pub fn screen_error(view: &View, c: DVec3, r: f64, weight: f64) -> f64 {
    view.error_px(c, 2.0 * r) * weight
}

/// `x` rounded up to an `f32`.
#[inline]
pub fn f32_up(x: f64) -> f32 {
    let y = x as f32;
    if (y as f64) < x {
        y.next_up()
    } else {
        y
    }
}

/// `x` rounded down to an `f32`.
#[inline]
pub fn f32_down(x: f64) -> f32 {
    let y = x as f32;
    if (y as f64) > x {
        y.next_down()
    } else {
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn an_orbit() -> Orbit {
        Orbit {
            target: DVec3::new(1.0, 2.0, 3.0),
            azimuth: 35.0,
            elevation: 25.0,
            distance: 10.0,
            fov: 40.0,
        }
    }

    #[test]
    fn an_orbit_camera_stands_on_its_sphere_looking_at_the_target() {
        let o = an_orbit();
        let c = o.camera(64, 48);
        let (az, el) = (35f64.to_radians(), 25f64.to_radians());
        let dir = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        assert!((c.eye - (o.target + 10.0 * dir)).length() < 1e-12);
        assert_eq!(c.target, o.target);
        assert_eq!((c.width, c.height, c.fovy_deg), (64, 48, 40.0));
        let f = Camera::framing([0.0; 3], [3.0, 4.0, 0.0]);
        assert_eq!(f.diagonal, 5.0);
        assert_eq!(f.distance, FRAMING_DIAGONALS * 5.0);
        let d = Orbit::framed(f);
        assert_eq!(d.target, DVec3::new(1.5, 2.0, 0.0));
        assert_eq!(
            (d.azimuth, d.elevation, d.fov),
            (DEFAULT_AZIMUTH, DEFAULT_ELEVATION, DEFAULT_FOV)
        );
    }

    #[test]
    fn elevation_is_clamped_and_zoom_bounded() {
        let mut o = an_orbit();
        o.rotate(350.0, 200.0);
        assert_eq!(o.elevation, MAX_ELEVATION);
        assert!((o.azimuth - 25.0).abs() < 1e-9);
        o.zoom(0.01, 1.0, 100.0);
        assert_eq!(o.distance, 1.0);
        o.zoom(f64::NAN, 1.0, 100.0);
        assert_eq!(o.distance, 1.0);
    }

    #[test]
    fn pan_moves_the_target_in_the_view_plane() {
        let mut o = an_orbit();
        let fwd = o.camera(64, 64).forward();
        let before = o.target;
        o.pan(10.0, 0.0, 64);
        let moved = o.target - before;
        assert!(moved.length() > 0.0);
        assert!(moved.dot(fwd).abs() < 1e-9 * moved.length().max(1.0));
    }

    /// The image weight: 0 with nothing to change (zero bound, flat TF over the values), grows
    /// with the bound, the size and the TF's slope, and is capped at 1.
    #[test]
    fn image_weight_follows_bound_size_and_tf() {
        let mut bins = vec![0.0f32; 10];
        bins[8] = 4.0; // the TF changes only over s in [0.8, 0.9)
        let c = ImageCriterion {
            sens: Sensitivity::from_bins(bins),
            value_range: [0.0, 1.0],
            length_unit: 1.0,
            eps: 0.01,
        };
        assert_eq!(c.weight(0.1, 0.2, 0.0, 1.0), 0.0);
        assert_eq!(
            c.weight(0.1, 0.2, 0.05, 1.0),
            0.0,
            "flat TF over [0.05, 0.25]"
        );
        let w = c.weight(0.8, 0.85, 0.001, 0.1);
        assert!((w - 0.1 * 0.001 * 4.0 / 0.01).abs() < 1e-12, "{w}");
        assert!(c.weight(0.8, 0.85, 0.002, 0.1) > w);
        assert!(c.weight(0.8, 0.85, 0.001, 0.2) > w);
        assert_eq!(c.weight(0.8, 0.85, 1.0, 1.0), 1.0);
        assert_eq!(c.weight(0.1, 0.2, f64::INFINITY, 1.0), 1.0);
        let flat = ImageCriterion {
            sens: Sensitivity::uniform(0.0),
            ..c
        };
        assert_eq!(flat.weight(0.1, 0.2, f64::INFINITY, 1.0), 0.0);
        assert_eq!(Sensitivity::uniform(2.0).max_over(1.5, 2.0), 0.0);
        assert_eq!(Sensitivity::uniform(2.0).max_over(-1.0, 0.0), 2.0);
    }

    /// The projection maps each pixel's ray back onto that pixel's centre.
    #[test]
    fn rays_and_projection_agree() {
        let cam = Orbit {
            target: DVec3::new(1.0, 2.0, 3.0),
            distance: 10.0,
            azimuth: 30.0,
            elevation: 20.0,
            fov: 40.0,
        }
        .camera(64, 48);
        let vp = cam.view_proj(DVec3::ZERO, 100.0);
        for (x, y) in [(0, 0), (63, 47), (10, 30), (32, 24)] {
            let p = cam.eye + cam.ray_dir(x, y) * 7.0;
            let c = vp * p.extend(1.0);
            let ndc = c.truncate() / c.w;
            let px = (ndc.x + 1.0) * 0.5 * 64.0;
            let py = (1.0 - ndc.y) * 0.5 * 48.0;
            assert!((px - (x as f64 + 0.5)).abs() < 1e-9 && (py - (y as f64 + 0.5)).abs() < 1e-9);
        }
    }
}
