//! The viewer's camera: an orbit around a target point (azimuth, elevation, distance, field of
//! view), the same parametrization as `tetwave render`'s and `/v1/render`'s camera arguments, so
//! that an unpanned view can be reproduced offscreen and by the server.

use glam::DVec3;
use tetwave_protocol::view::Camera;

/// Elevations stay inside ±89° so the orbit's up vector never flips.
pub const MAX_ELEVATION: f64 = 89.0;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orbit {
    /// The point orbited; the volume's centre until the user pans.
    pub target: DVec3,
    pub azimuth: f64,
    pub elevation: f64,
    pub distance: f64,
    pub fov: f64,
}

impl Orbit {
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

    /// The camera for a `width`×`height` view.
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        Camera::orbit(
            self.target,
            self.distance,
            self.azimuth,
            self.elevation,
            self.fov,
            width,
            height,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn orbit() -> Orbit {
        Orbit {
            target: DVec3::new(1.0, 2.0, 3.0),
            azimuth: 35.0,
            elevation: 25.0,
            distance: 10.0,
            fov: 40.0,
        }
    }

    #[test]
    fn camera_is_tetwave_renders_orbit() {
        let o = orbit();
        let a = o.camera(64, 48);
        let b = Camera::orbit(o.target, 10.0, 35.0, 25.0, 40.0, 64, 48);
        assert_eq!(a.eye, b.eye);
        assert_eq!(a.target, b.target);
    }

    #[test]
    fn elevation_is_clamped_and_zoom_bounded() {
        let mut o = orbit();
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
        let mut o = orbit();
        let fwd = o.camera(64, 64).forward();
        let before = o.target;
        o.pan(10.0, 0.0, 64);
        let moved = o.target - before;
        assert!(moved.length() > 0.0);
        assert!(moved.dot(fwd).abs() < 1e-9 * moved.length().max(1.0));
    }
}
