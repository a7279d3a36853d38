//! Command-line parsers for camera arguments: a clear error for values that would give a blank or
//! meaningless image (NaN, a negative distance, a field of view of 0).

use tetwave_protocol::view::{Framing, Orbit, DEFAULT_AZIMUTH, DEFAULT_ELEVATION, DEFAULT_FOV};

/// The orbit camera's options, shared by `render`, `stream` and `view`: the eye on a sphere around
/// the volume's centre.
#[derive(Debug, Clone, clap::Args)]
pub struct CameraArgs {
    #[arg(long, default_value_t = DEFAULT_AZIMUTH, value_parser = angle)]
    pub azimuth: f64,
    #[arg(long, default_value_t = DEFAULT_ELEVATION, value_parser = elevation)]
    pub elevation: f64,
    /// Eye distance from the volume's centre (default: 1.6 × the bounding-box diagonal).
    #[arg(long, value_parser = distance)]
    pub distance: Option<f64>,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = DEFAULT_FOV, value_parser = fov)]
    pub fov: f64,
}

impl Default for CameraArgs {
    fn default() -> Self {
        CameraArgs {
            azimuth: DEFAULT_AZIMUTH,
            elevation: DEFAULT_ELEVATION,
            distance: None,
            fov: DEFAULT_FOV,
        }
    }
}

impl CameraArgs {
    /// The orbit these options ask for around a box framed by `f`: its centre, at the framing's
    /// distance unless `--distance` says otherwise.
    pub fn orbit(&self, f: Framing) -> Orbit {
        Orbit {
            target: f.center,
            azimuth: self.azimuth,
            elevation: self.elevation,
            distance: self.distance.unwrap_or(f.distance),
            fov: self.fov,
        }
    }
}

fn number(s: &str) -> Result<f64, crate::options::ArgError> {
    let x: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("not a number: {s:?}"))?;
    if x.is_finite() {
        Ok(x)
    } else {
        Err(format!("{x} is not finite").into())
    }
}

/// An angle or a rotation in degrees or radians: finite, magnitude at most 10^6.
pub fn angle(s: &str) -> Result<f64, crate::options::ArgError> {
    let x = number(s)?;
    if x.abs() <= 1e6 {
        Ok(x)
    } else {
        Err(format!("{x} is out of range (magnitude at most 1e6)").into())
    }
}

/// An elevation in degrees, within ±90.
pub fn elevation(s: &str) -> Result<f64, crate::options::ArgError> {
    let x = number(s)?;
    if (-90.0..=90.0).contains(&x) {
        Ok(x)
    } else {
        Err(format!("{x} is outside -90..=90 degrees").into())
    }
}

/// An eye distance: finite and positive.
pub fn distance(s: &str) -> Result<f64, crate::options::ArgError> {
    let x = number(s)?;
    if x > 0.0 {
        Ok(x)
    } else {
        Err(format!("{x} is not a positive distance").into())
    }
}

/// A vertical field of view in degrees, strictly between 0 and 180.
pub fn fov(s: &str) -> Result<f64, crate::options::ArgError> {
    let x = number(s)?;
    if x > 0.0 && x < 180.0 {
        Ok(x)
    } else {
        Err(format!("{x} is outside (0, 180) degrees").into())
    }
}
