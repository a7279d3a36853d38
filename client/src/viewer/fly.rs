//! The viewer's fly camera: an eye that moves freely (inside the volume too) and looks along a
//! yaw and pitch, z up. Entered from an orbit it keeps that orbit's view, so flying forward
//! along the view is an orbit camera at a shorter distance (what the tests compare against).
//!
//! The projected-tetrahedra renderer handles an eye inside the mesh: each ray starts at the near
//! plane (`pt.wgsl` clamps a tet's entry to it), and the rasterizer clips the exit faces of tets
//! behind the eye (their vertices have `w < 0` in clip space).

use super::orbit::{Orbit, MAX_ELEVATION};
use glam::DVec3;
use tetwave_protocol::view::Camera;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fly {
    pub eye: DVec3,
    /// Degrees about z from +x toward +y, of the view direction.
    pub yaw: f64,
    /// Degrees above the xy plane, within ±[`MAX_ELEVATION`].
    pub pitch: f64,
    pub fov: f64,
    /// The near plane's distance: small against the volume, so that a tet close to the eye is
    /// still drawn from the plane on.
    pub near: f64,
}

impl Fly {
    /// The fly camera that sees what `o` sees (the same eye, direction and near plane).
    pub fn from_orbit(o: &Orbit) -> Fly {
        let cam = o.camera(1, 1);
        Fly {
            eye: cam.eye,
            // the orbit looks from (azimuth, elevation) toward its target: the opposite way
            yaw: (o.azimuth + 180.0).rem_euclid(360.0),
            pitch: -o.elevation,
            fov: o.fov,
            near: cam.near,
        }
    }

    /// The unit view direction.
    pub fn forward(&self) -> DVec3 {
        let (y, p) = (self.yaw.to_radians(), self.pitch.to_radians());
        DVec3::new(p.cos() * y.cos(), p.cos() * y.sin(), p.sin())
    }

    /// Unit vector to the right of the view, in the xy plane.
    pub fn right(&self) -> DVec3 {
        let y = self.yaw.to_radians();
        DVec3::new(y.sin(), -y.cos(), 0.0)
    }

    /// Turns the view by `d_yaw` (positive: to the left) and `d_pitch` (positive: up) degrees.
    pub fn turn(&mut self, d_yaw: f64, d_pitch: f64) {
        self.yaw = (self.yaw + d_yaw).rem_euclid(360.0);
        self.pitch = (self.pitch + d_pitch).clamp(-MAX_ELEVATION, MAX_ELEVATION);
    }

    /// Moves the eye by `forward` along the view, `right` to its right and `up` along z.
    pub fn translate(&mut self, forward: f64, right: f64, up: f64) {
        let d = forward * self.forward() + right * self.right() + up * DVec3::Z;
        if d.is_finite() {
            self.eye += d;
        }
    }

    /// The camera for a `width`×`height` view.
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let f = self.forward();
        Camera {
            eye: self.eye,
            target: self.eye + f,
            up: if f.cross(DVec3::Z).length() < 1e-6 {
                DVec3::Y
            } else {
                DVec3::Z
            },
            fovy_deg: self.fov,
            near: self.near,
            width,
            height,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn orbit() -> Orbit {
        Orbit {
            target: DVec3::new(0.5, 0.5, 0.5),
            azimuth: 35.0,
            elevation: 25.0,
            distance: 2.0,
            fov: 40.0,
        }
    }

    #[test]
    fn entering_keeps_the_orbits_view() {
        let o = orbit();
        let f = Fly::from_orbit(&o);
        let (a, b) = (o.camera(64, 48), f.camera(64, 48));
        assert!((a.eye - b.eye).length() < 1e-12);
        assert!((a.forward() - b.forward()).length() < 1e-12);
        assert_eq!(a.near, b.near);
    }

    #[test]
    fn flying_forward_is_an_orbit_at_a_shorter_distance() {
        let o = orbit();
        let mut f = Fly::from_orbit(&o);
        f.translate(1.7, 0.0, 0.0);
        let closer = Orbit { distance: 0.3, ..o };
        let (a, b) = (closer.camera(64, 48), f.camera(64, 48));
        assert!((a.eye - b.eye).length() < 1e-9, "{:?} {:?}", a.eye, b.eye);
        assert!((a.forward() - b.forward()).length() < 1e-12);
    }

    #[test]
    fn strafing_and_turning() {
        let mut f = Fly::from_orbit(&orbit());
        let fwd = f.forward();
        let before = f.eye;
        f.translate(0.0, 1.0, 0.0);
        let moved = f.eye - before;
        assert!((moved.length() - 1.0).abs() < 1e-12);
        assert!(moved.dot(fwd).abs() < 1e-12 && moved.z == 0.0);
        // right is to the right: forward × right points down
        assert!(fwd.cross(f.right()).z < 0.0);
        f.turn(0.0, 500.0);
        assert_eq!(f.pitch, MAX_ELEVATION);
        f.translate(f64::NAN, 0.0, 0.0);
        assert!(f.eye.is_finite());
    }
}
