//! The viewer's fly camera: an eye that moves freely (inside the volume too) and looks along a
//! yaw and pitch, z up. Entered from an orbit it keeps that orbit's view, so flying forward
//! along the view is an orbit camera at a shorter distance (what the tests compare against).
//!
//! The projected-tetrahedra renderer handles an eye inside the mesh: each ray starts at the near
//! plane (`pt.wgsl` clamps a tet's entry to it), and the rasterizer clips the exit faces of tets
//! behind the eye (their vertices have `w < 0` in clip space).

use eframe::egui;
use glam::DVec3;
use tetwave_protocol::view::Camera;
use tetwave_protocol::view::{Orbit, MAX_ELEVATION};

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

/// The move the keys held ask for in a frame of `dt` seconds at `speed` units a second: `W`/`S`
/// or up/down forward and back, `A`/`D` or left/right to the sides, `Q`/`E` down and up, shift
/// 4× faster. A long frame (or the first) moves at most a tenth of a second's worth. Returns
/// `[forward, right, up]`, as [`Fly::translate`] takes them.
pub fn held_move(ctx: &egui::Context, dt: f64, speed: f64) -> [f64; 3] {
    use egui::Key;
    let [fwd, back, left, right, down, up, fast] = ctx.input(|i| {
        [
            i.key_down(Key::W) || i.key_down(Key::ArrowUp),
            i.key_down(Key::S) || i.key_down(Key::ArrowDown),
            i.key_down(Key::A) || i.key_down(Key::ArrowLeft),
            i.key_down(Key::D) || i.key_down(Key::ArrowRight),
            i.key_down(Key::Q),
            i.key_down(Key::E),
            i.modifiers.shift,
        ]
    });
    let axis = |p: bool, n: bool| f64::from(u8::from(p)) - f64::from(u8::from(n));
    let step = speed * dt.clamp(0.0, 0.1) * if fast { 4.0 } else { 1.0 };
    [
        axis(fwd, back) * step,
        axis(right, left) * step,
        axis(up, down) * step,
    ]
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

    /// Keys held down move the eye: W forward, A+D cancel, shift 4×, E up, a long frame capped.
    #[test]
    fn held_keys_move_the_eye() {
        use egui::{Event, Key, Modifiers};
        let ctx = egui::Context::default();
        let key = |key, pressed| Event::Key {
            key,
            physical_key: None,
            pressed,
            repeat: false,
            modifiers: Modifiers::NONE,
        };
        let moves = |mut events: Vec<Event>, modifiers: Modifiers, dt: f64| {
            let mut m = [0.0; 3];
            events.insert(0, Event::ModifiersChanged(modifiers));
            let input = egui::RawInput {
                events,
                ..Default::default()
            };
            let mut out = ctx.run_ui(input, |ui| m = held_move(ui.ctx(), dt, 2.0));
            out.textures_delta.clear();
            m
        };
        let none = Modifiers::NONE;
        assert_eq!(moves(vec![], none, 0.05), [0.0; 3]);
        assert_eq!(moves(vec![key(Key::W, true)], none, 0.05), [0.1, 0.0, 0.0]);
        // W still held in the next frame; A and D together cancel
        assert_eq!(
            moves(vec![key(Key::A, true), key(Key::D, true)], none, 0.05),
            [0.1, 0.0, 0.0]
        );
        // released; E with shift over a 5 s frame: 4 × 2 units/s × 0.1 s
        let released = vec![
            key(Key::W, false),
            key(Key::A, false),
            key(Key::D, false),
            key(Key::E, true),
        ];
        assert_eq!(moves(released, Modifiers::SHIFT, 5.0), [0.0, 0.0, 0.8]);
    }
}
