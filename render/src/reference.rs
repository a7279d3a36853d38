//! The CPU reference integrator: the ground truth for every image-accuracy figure.
//!
//! For each pixel the ray through its centre is intersected exactly (f64) with every leaf tet whose
//! screen footprint covers the pixel; the scalar is linear inside each tet, so the ray's scalar is
//! exactly piecewise linear; segments are sorted by entry distance (no visibility-order assumption:
//! non-convex meshes and gaps are exact) and each is integrated with sub-steps doubled until the
//! result changes by less than `1e-7`. Rays start at the camera's near plane. When the mesh has a
//! level set ([`RenderMesh::levelset`]), each segment is first clipped exactly to where its
//! linear level set is ≥ 0 (the scalar re-interpolated at the clipped ends).

use crate::image_metrics::{unit_to_u8, Rgba8Image};
use crate::render_mesh::{clip_to_levelset, RenderMesh};
use crate::transfer::{integrate_segment_converged, TransferFunction};
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use tetwave_protocol::view::Camera;

/// Convergence tolerance of each segment's integral.
pub const SEGMENT_TOL: f64 = 1e-7;

struct TetRay {
    planes: [(DVec3, f64); 4],
    g: DVec3,
    c: f64,
    /// The level set `lg·x + lc` (`(0, 1)` without one).
    lg: DVec3,
    lc: f64,
}

/// Renders `mesh` exactly; returns premultiplied RGBA in `[0, 1]` per pixel, rows top to bottom.
pub fn render_reference_f64(
    mesh: &RenderMesh,
    cam: &Camera,
    tf: &TransferFunction,
) -> Vec<[f64; 4]> {
    trace(mesh, cam, tf, None, BAND_TETS, |p| p).expect("not cancellable")
}

/// [`render_reference_f64`] quantized to RGBA8.
pub fn render_reference(mesh: &RenderMesh, cam: &Camera, tf: &TransferFunction) -> Rgba8Image {
    let pixels =
        trace(mesh, cam, tf, None, BAND_TETS, |p| p.map(unit_to_u8)).expect("not cancellable");
    Rgba8Image {
        width: cam.width,
        height: cam.height,
        pixels,
    }
}

/// [`render_reference`] that stops when `cancel` becomes true (checked before each row): `None`
/// then. Memory: 4 bytes per pixel for the image and 8 per tet (its screen footprint), plus, for
/// the tets over the band of rows being drawn (`BAND_TETS` tets' worth of rows at a time), each
/// one's ray geometry (~140 bytes) and a 12-byte entry per row of the band its footprint spans.
pub fn render_reference_cancellable(
    mesh: &RenderMesh,
    cam: &Camera,
    tf: &TransferFunction,
    cancel: &AtomicBool,
) -> Option<Rgba8Image> {
    let pixels = trace(mesh, cam, tf, Some(cancel), BAND_TETS, |p| {
        p.map(unit_to_u8)
    })?;
    Some(Rgba8Image {
        width: cam.width,
        height: cam.height,
        pixels,
    })
}

/// A tet's pixel bounding box, `[x0, x1, y0, y1]` inclusive.
type Footprint = [u16; 4];

/// The footprint of a tet that covers no pixel centre.
const EMPTY_FOOTPRINT: Footprint = [u16::MAX, 0, u16::MAX, 0];

/// Tets whose ray geometry one band of rows holds at most (about): a larger mesh is drawn a band
/// of rows at a time, each band with the geometry of the tets over it only.
const BAND_TETS: usize = 1 << 23;

/// The integrator: every pixel's premultiplied RGBA through `px`, in bands of rows over about
/// `band_tets` tets each; `None` when cancelled.
fn trace<T: Send + Copy + Default>(
    mesh: &RenderMesh,
    cam: &Camera,
    tf: &TransferFunction,
    cancel: Option<&AtomicBool>,
    band_tets: usize,
    px: impl Fn([f64; 4]) -> T + Sync,
) -> Option<Vec<T>> {
    let cancelled = || cancel.is_some_and(|c| c.load(Ordering::Relaxed));
    let (w, h) = (cam.width as usize, cam.height as usize);
    if w == 0 || h == 0 {
        return Some(Vec::new());
    }
    let origin = mesh.center();
    let eye = cam.eye - origin;
    let ext_scale = 1.0 / mesh.diagonal();
    // screen footprint of each tet: pixel bbox (whole screen if it reaches behind the near plane)
    let vp = cam.view_proj(origin, 1.0);
    let fwd = cam.forward();
    let foot: Vec<Footprint> = mesh
        .tets
        .par_iter()
        .map(|tet| {
            let mut lo = [f64::INFINITY; 2];
            let mut hi = [f64::NEG_INFINITY; 2];
            for &v in tet {
                let p = DVec3::from_array(mesh.positions[v as usize]) - origin;
                if (p - eye).dot(fwd) <= cam.near * 0.999 {
                    return [0, w as u16 - 1, 0, h as u16 - 1];
                }
                let c = vp * p.extend(1.0);
                let px = ((c.x / c.w) + 1.0) * 0.5 * w as f64;
                let py = (1.0 - c.y / c.w) * 0.5 * h as f64;
                lo = [lo[0].min(px), lo[1].min(py)];
                hi = [hi[0].max(px), hi[1].max(py)];
            }
            // pixel centres inside [lo, hi], with a one-pixel margin for rounding
            let clamp = |v: f64, n: usize| v.clamp(-1.0, n as f64) as i64;
            let (x0, x1) = (
                clamp((lo[0] - 1.5).floor(), w),
                clamp((hi[0] + 0.5).ceil(), w),
            );
            let (y0, y1) = (
                clamp((lo[1] - 1.5).floor(), h),
                clamp((hi[1] + 0.5).ceil(), h),
            );
            let (x0, x1) = (x0.max(0), x1.min(w as i64 - 1));
            let (y0, y1) = (y0.max(0), y1.min(h as i64 - 1));
            if x0 > x1 || y0 > y1 {
                EMPTY_FOOTPRINT
            } else {
                [x0 as u16, x1 as u16, y0 as u16, y1 as u16]
            }
        })
        .collect();
    // bands of rows, each with the ray geometry of the tets over it only: a mesh of any size is
    // drawn within about BAND_TETS tets' geometry at a time (one band below that)
    let bands = mesh.tets.len().div_ceil(band_tets.max(1)).clamp(1, h);
    let band_h = h.div_ceil(bands);
    let mut out = vec![T::default(); w * h];
    for (b, band) in out.chunks_mut(band_h * w).enumerate() {
        let (by0, by1) = (b * band_h, (b * band_h + band.len() / w).min(h));
        let mut local: Vec<u32> = Vec::new();
        let mut rows: Vec<Vec<(u32, u32, u32)>> = vec![Vec::new(); by1 - by0];
        for (t, f) in foot.iter().enumerate() {
            let (y0, y1) = (f[2] as usize, f[3] as usize);
            if *f == EMPTY_FOOTPRINT || y1 < by0 || y0 >= by1 {
                continue;
            }
            let l = local.len() as u32;
            local.push(t as u32);
            for row in &mut rows[y0.max(by0) - by0..=y1.min(by1 - 1) - by0] {
                row.push((l, f[0] as u32, f[1] as u32));
            }
        }
        let geo: Vec<TetRay> = local
            .par_iter()
            .map(|&t| {
                let (planes, g, c) = mesh.tet_geometry(t as usize, origin);
                let (lg, lc) = mesh.tet_levelset(t as usize, origin);
                TetRay {
                    planes,
                    g,
                    c,
                    lg,
                    lc,
                }
            })
            .collect();
        if cancelled() {
            return None;
        }
        band.par_chunks_mut(w).enumerate().for_each(|(dy, line)| {
            if cancelled() {
                return;
            }
            let y = by0 + dy;
            let mut segs: Vec<(f64, f64, f64, f64)> = Vec::new();
            for (x, pixel) in line.iter_mut().enumerate() {
                let dir = cam.ray_dir(x as u32, y as u32);
                let t_near = cam.near_t(dir);
                segs.clear();
                for &(t, x0, x1) in &rows[dy] {
                    if (x as u32) < x0 || (x as u32) > x1 {
                        continue;
                    }
                    let g = &geo[t as usize];
                    if g.planes[0].0 == DVec3::ZERO {
                        continue;
                    }
                    let (mut t0, mut t1) = (t_near, f64::INFINITY);
                    for &(n, d) in &g.planes {
                        let denom = n.dot(dir);
                        let num = d - n.dot(eye);
                        if denom > 0.0 {
                            t1 = t1.min(num / denom);
                        } else if denom < 0.0 {
                            t0 = t0.max(num / denom);
                        } else if num < 0.0 {
                            t1 = f64::NEG_INFINITY;
                        }
                    }
                    if t1 > t0 {
                        let l0 = g.lg.dot(eye + dir * t0) + g.lc;
                        let l1 = g.lg.dot(eye + dir * t1) + g.lc;
                        let Some((a, b)) = clip_to_levelset(l0, l1) else {
                            continue;
                        };
                        let (t0, t1) = (t0 + (t1 - t0) * a, t0 + (t1 - t0) * b);
                        if t1 > t0 {
                            let s0 = g.g.dot(eye + dir * t0) + g.c;
                            let s1 = g.g.dot(eye + dir * t1) + g.c;
                            segs.push((t0, t1, s0, s1));
                        }
                    }
                }
                segs.sort_by(|a, b| a.0.total_cmp(&b.0));
                let mut c = [0f64; 3];
                let mut tr = 1f64;
                for &(t0, t1, s0, s1) in &segs {
                    let (sc, st) =
                        integrate_segment_converged(tf, s0, s1, t1 - t0, ext_scale, SEGMENT_TOL);
                    for k in 0..3 {
                        c[k] += tr * sc[k];
                    }
                    tr *= st;
                    if tr < 1e-12 {
                        break;
                    }
                }
                *pixel = px([c[0], c[1], c[2], 1.0 - tr]);
            }
        });
    }
    (!cancelled()).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tetwave_protocol::view::Orbit;

    /// The unit corner tet with the value `v` at every vertex.
    fn one_tet(v: f32) -> RenderMesh {
        RenderMesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
            ],
            vec![[0, 1, 2, 3]],
            vec![v; 4],
        )
    }

    /// Drawn a band of rows at a time, a mesh gives the image it gives in one band, bit for bit.
    #[test]
    fn bands_of_rows_change_nothing() {
        let mesh = RenderMesh::kuhn_cube(4, 2.0, |p| (p[0] * 1.3 + p[1] * p[2]).sin());
        let tf = TransferFunction::preset("default").unwrap();
        let cam = Orbit::around(mesh.center(), 5.0).camera(40, 33);
        let whole = trace(&mesh, &cam, &tf, None, usize::MAX, |p| p).unwrap();
        for band_tets in [1, 7, 100] {
            let banded = trace(&mesh, &cam, &tf, None, band_tets, |p| p).unwrap();
            assert!(whole == banded, "{band_tets} tets a band");
        }
        assert!(whole.iter().any(|p| p[3] > 0.1), "the cube is drawn");
    }

    /// A single tet with a constant field: every covered pixel equals the closed form
    /// `rgb · (1 − exp(−τ ℓ))` for its chord length ℓ.
    #[test]
    fn constant_field_matches_closed_form() {
        let mesh = one_tet(0.5);
        let tf = TransferFunction::preset("default").unwrap();
        let cam = Orbit {
            target: mesh.center(),
            distance: 4.0,
            azimuth: 30.0,
            elevation: 25.0,
            fov: 30.0,
        }
        .camera(48, 48);
        let img = render_reference_f64(&mesh, &cam, &tf);
        let (rgb, ext) = tf.eval(0.5);
        let tau = ext / mesh.diagonal();
        let origin = mesh.center();
        let (planes, _, _) = mesh.tet_geometry(0, origin);
        let mut covered = 0;
        for y in 0..48 {
            for x in 0..48 {
                let dir = cam.ray_dir(x, y);
                let eye = cam.eye - origin;
                let (mut t0, mut t1) = (cam.near_t(dir), f64::INFINITY);
                for (n, d) in planes {
                    let den = n.dot(dir);
                    let num = d - n.dot(eye);
                    if den > 0.0 {
                        t1 = t1.min(num / den)
                    } else if den < 0.0 {
                        t0 = t0.max(num / den)
                    }
                }
                let a = if t1 > t0 {
                    1.0 - (-tau * (t1 - t0)).exp()
                } else {
                    0.0
                };
                let p = img[(y * 48 + x) as usize];
                assert!((p[3] - a).abs() < 1e-9 && (p[0] - rgb[0] * a).abs() < 1e-9);
                if a > 0.0 {
                    covered += 1;
                }
            }
        }
        assert!(covered > 100);
    }

    /// Refining the same linear field (8× more tets) leaves the reference image unchanged.
    #[test]
    fn tessellation_independent_for_linear_fields() {
        let f = |p: [f64; 3]| p[0] + 2.0 * p[1] - p[2];
        let coarse = RenderMesh::kuhn_cube(2, 1.0, f);
        let fine = RenderMesh::kuhn_cube(4, 1.0, f);
        let tf = TransferFunction::preset("default").unwrap();
        let cam = Orbit {
            target: coarse.center(),
            distance: 3.0,
            azimuth: 20.0,
            elevation: 30.0,
            fov: 35.0,
        }
        .camera(40, 40);
        let a = render_reference_f64(&coarse, &cam, &tf);
        let b = render_reference_f64(&fine, &cam, &tf);
        let worst = a
            .iter()
            .zip(&b)
            .map(|(p, q)| (0..4).map(|k| (p[k] - q[k]).abs()).fold(0.0, f64::max))
            .fold(0.0, f64::max);
        // each segment converges to 1e-7; summed over the segments of a ray: far below one 8-bit level
        assert!(worst < 1e-5, "{worst}");
    }

    /// A tet cut by the plane `x = 0.3` through its level set (`φ = x − 0.3` at the corners, a
    /// linear scalar): the clipped image is the image of the exact part `x ≥ 0.3`, a smaller tet
    /// drawn without a level set (same bounds, so the same extinction unit), to the integrator's
    /// tolerance; and the clip removes material (pixels covered before are background now).
    #[test]
    fn straddling_tet_is_clipped_to_its_exact_inside() {
        let corners = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let s = |p: [f64; 3]| (p[0] + 0.3 * p[1] + 0.7 * p[2]) as f32;
        let mut clipped = RenderMesh::new(
            corners.to_vec(),
            vec![[0, 1, 2, 3]],
            corners.map(s).to_vec(),
        );
        clipped.value_range = (0.0, 1.0);
        clipped.levelset = Some(corners.iter().map(|p| (p[0] - 0.3) as f32).collect());
        // the part x ≥ 0.3: the corner (1,0,0) and the cut points on its 3 edges from the others;
        // the full tet's corners are kept as unused points so that the bounds are the same
        let part = [
            [0.3, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.3, 0.7, 0.0],
            [0.3, 0.0, 0.7],
        ];
        let mut positions = corners.to_vec();
        positions.extend(part);
        let values = positions.iter().map(|&p| s(p)).collect();
        let mut exact = RenderMesh::new(positions, vec![[4, 5, 6, 7]], values);
        exact.value_range = (0.0, 1.0);
        let mut whole = clipped.clone();
        whole.levelset = None;
        let tf = TransferFunction::preset("default").unwrap();
        for (az, el) in [(30.0, 25.0), (120.0, -20.0), (250.0, 60.0)] {
            let cam = Orbit {
                target: clipped.center(),
                distance: 3.0,
                azimuth: az,
                elevation: el,
                fov: 35.0,
            }
            .camera(40, 40);
            let a = render_reference_f64(&clipped, &cam, &tf);
            let b = render_reference_f64(&exact, &cam, &tf);
            let w = render_reference_f64(&whole, &cam, &tf);
            let worst = a
                .iter()
                .zip(&b)
                .map(|(p, q)| (0..4).map(|k| (p[k] - q[k]).abs()).fold(0.0, f64::max))
                .fold(0.0, f64::max);
            assert!(worst < 1e-6, "az {az}: {worst}");
            let covered = |img: &[[f64; 4]]| img.iter().filter(|p| p[3] > 0.0).count();
            assert!(covered(&a) > 20, "az {az}: the part is in view");
            assert!(
                covered(&w) > covered(&a),
                "az {az}: the clip removes pixels"
            );
        }
    }

    /// The cancellable integrator gives the same image when left alone and nothing once cancelled.
    #[test]
    fn cancellable_matches_and_cancels() {
        let mut mesh = one_tet(0.5);
        mesh.values = vec![0.0, 0.3, 0.6, 1.0];
        mesh.value_range = (0.0, 1.0);
        let cam = Orbit::around(mesh.center(), 3.0).camera(24, 20);
        let tf = TransferFunction::preset("default").unwrap();
        let keep = AtomicBool::new(false);
        let a = render_reference(&mesh, &cam, &tf);
        let b = render_reference_cancellable(&mesh, &cam, &tf, &keep).unwrap();
        assert_eq!(a.pixels, b.pixels);
        assert!(a.pixels.iter().any(|p| p[3] > 0), "the tet is in view");
        let stop = AtomicBool::new(true);
        assert!(render_reference_cancellable(&mesh, &cam, &tf, &stop).is_none());
    }
}
