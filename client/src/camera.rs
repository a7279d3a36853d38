//! A pinhole camera shared by the GPU renderer and the CPU reference: the same pixel → ray mapping
//! on both sides (pixel centres, row 0 at the top).

use glam::{DMat4, DVec3};

/// Command-line parsers for camera arguments: a clear error for values that would give a blank or
/// meaningless image (NaN, a negative distance, a field of view of 0).
pub mod arg {
    fn number(s: &str) -> Result<f64, String> {
        let x: f64 = s
            .trim()
            .parse()
            .map_err(|_| format!("not a number: {s:?}"))?;
        if x.is_finite() {
            Ok(x)
        } else {
            Err(format!("{x} is not finite"))
        }
    }

    /// An angle or a rotation in degrees or radians: finite, magnitude at most 10^6.
    pub fn angle(s: &str) -> Result<f64, String> {
        let x = number(s)?;
        if x.abs() <= 1e6 {
            Ok(x)
        } else {
            Err(format!("{x} is out of range (magnitude at most 1e6)"))
        }
    }

    /// An elevation in degrees, within ±90.
    pub fn elevation(s: &str) -> Result<f64, String> {
        let x = number(s)?;
        if (-90.0..=90.0).contains(&x) {
            Ok(x)
        } else {
            Err(format!("{x} is outside -90..=90 degrees"))
        }
    }

    /// An eye distance: finite and positive.
    pub fn distance(s: &str) -> Result<f64, String> {
        let x = number(s)?;
        if x > 0.0 {
            Ok(x)
        } else {
            Err(format!("{x} is not a positive distance"))
        }
    }

    /// A vertical field of view in degrees, strictly between 0 and 180.
    pub fn fov(s: &str) -> Result<f64, String> {
        let x = number(s)?;
        if x > 0.0 && x < 180.0 {
            Ok(x)
        } else {
            Err(format!("{x} is outside (0, 180) degrees"))
        }
    }
}

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

impl Camera {
    /// Orbit camera around `center`: azimuth about the vertical (z) axis, elevation above the xy plane.
    pub fn orbit(
        center: DVec3,
        distance: f64,
        azimuth_deg: f64,
        elevation_deg: f64,
        fovy_deg: f64,
        width: u32,
        height: u32,
    ) -> Self {
        let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
        let dir = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        let up = if el.cos().abs() < 1e-6 {
            DVec3::Y
        } else {
            DVec3::Z
        };
        Camera {
            eye: center + dir * distance,
            target: center,
            up,
            fovy_deg,
            near: (distance * 1e-3).max(1e-6),
            width,
            height,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The projection maps each pixel's ray back onto that pixel's centre.
    #[test]
    fn rays_and_projection_agree() {
        let cam = Camera::orbit(DVec3::new(1.0, 2.0, 3.0), 10.0, 30.0, 20.0, 40.0, 64, 48);
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
