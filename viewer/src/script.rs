//! `tetwave view --script FILE`: a JSON list of timestamped steps the viewer plays in order.
//!
//! ```json
//! [
//!   {"wait": "complete"},
//!   {"screenshot": "front.png"},
//!   {"at": 2.0, "orbit": 90},
//!   {"camera": {"azimuth": 125, "elevation": 25}},
//!   {"tol": 4}, {"mode": "complete"}, {"tf": "shells"},
//!   {"fly": {"forward": 1.2, "yaw": 30}}, {"reset": true}, {"size": "800x600"},
//!   {"wait": "complete"}, {"server_image": true}, {"screenshot": "server.png"},
//!   {"quit": true}
//! ]
//! ```
//!
//! A step waits until `at` seconds after the window opened (if given), then does its one action.
//! A step that changes the view ends the frame's steps, except that inputs (camera, tolerance,
//! mode, transfer function) already due by then are taken in the same frame, as a frame takes
//! every mouse and key event queued since the last one.
//! `wait` and `server_image` hold the script until their condition holds; `screenshot` until the
//! image is written. Unknown keys and steps with no action or several are refused when the file
//! is read, with the step's index.

use serde::Deserialize;
use std::path::{Path, PathBuf};
use tetwave_source::options::ArgError;

/// A camera set absolutely; missing fields keep their value.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSet {
    pub azimuth: Option<f64>,
    pub elevation: Option<f64>,
    pub distance: Option<f64>,
    pub fov: Option<f64>,
}

/// A fly-camera move: distances in diagonals of the dataset's bounding box, angles in degrees;
/// missing fields are 0. The move happens after the turn.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlyMove {
    #[serde(default)]
    pub forward: f64,
    #[serde(default)]
    pub right: f64,
    #[serde(default)]
    pub up: f64,
    /// Positive: to the left.
    #[serde(default)]
    pub yaw: f64,
    /// Positive: up.
    #[serde(default)]
    pub pitch: f64,
}

/// What a script can wait for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WaitFor {
    /// Every node held (the whole stream, or the whole store) and the mesh converged for the
    /// current camera, mode and tolerance, and a frame drawn of it.
    Complete,
    /// The mesh converged for what is held now (the stream may go on), and a frame drawn of it.
    Converged,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    Camera(CameraSet),
    /// Degrees added to the azimuth.
    Orbit(f64),
    /// Degrees added to the elevation.
    Elevate(f64),
    /// Factor on the eye distance.
    Zoom(f64),
    /// Into fly mode (from the current orbit, if not in it yet), then the move.
    Fly(FlyMove),
    /// Back to the initial view (the orbit, out of fly mode).
    Reset,
    /// A preset name or a `.json` file.
    Tf(String),
    /// Tolerance in pixels.
    Tol(f64),
    Mode(super::ViewMode),
    /// Resizes the window so that the view is this many pixels, and waits until it is.
    Size(u32, u32),
    Wait(WaitFor),
    /// Holds the script for this many frames.
    Frames(u32),
    /// Requests the server's image of this view and waits until it is shown (or refused).
    ServerImage,
    Screenshot(PathBuf),
    /// A screenshot of the whole window, panel included.
    WindowScreenshot(PathBuf),
    Quit,
}

impl Action {
    /// What a user's mouse, keys or panel could do: a change of the camera, the tolerance, the
    /// mode or the transfer function.
    pub fn is_input(&self) -> bool {
        matches!(
            self,
            Action::Camera(_)
                | Action::Orbit(_)
                | Action::Elevate(_)
                | Action::Zoom(_)
                | Action::Fly(_)
                | Action::Reset
                | Action::Tf(_)
                | Action::Tol(_)
                | Action::Mode(_)
        )
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    /// Seconds after the window opened.
    pub at: Option<f64>,
    pub action: Action,
}

/// One step as written: every action key optional, exactly one given.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStep {
    at: Option<f64>,
    camera: Option<CameraSet>,
    orbit: Option<f64>,
    elevate: Option<f64>,
    zoom: Option<f64>,
    fly: Option<FlyMove>,
    reset: Option<bool>,
    tf: Option<String>,
    tol: Option<f64>,
    mode: Option<super::ViewMode>,
    size: Option<String>,
    wait: Option<WaitFor>,
    frames: Option<u32>,
    server_image: Option<bool>,
    screenshot: Option<PathBuf>,
    window_screenshot: Option<PathBuf>,
    quit: Option<bool>,
}

#[derive(Debug, thiserror::Error)]
pub enum ScriptError {
    #[error("script {path}: {reason}")]
    Read { path: PathBuf, reason: String },
    #[error("script {path}, step {index}: {reason}")]
    Step {
        path: PathBuf,
        index: usize,
        reason: String,
    },
}

/// Parses a script; a relative screenshot path is relative to the current directory.
pub fn parse(text: &str, path: &Path) -> Result<Vec<Step>, ScriptError> {
    let raw: Vec<RawStep> = serde_json::from_str(text).map_err(|e| ScriptError::Read {
        path: path.into(),
        reason: e.to_string(),
    })?;
    raw.into_iter()
        .enumerate()
        .map(|(index, r)| {
            step(r).map_err(|ArgError(reason)| ScriptError::Step {
                path: path.into(),
                index,
                reason,
            })
        })
        .collect()
}

/// Reads and parses a script file.
pub fn load(path: &Path) -> Result<Vec<Step>, ScriptError> {
    let text = std::fs::read_to_string(path).map_err(|e| ScriptError::Read {
        path: path.into(),
        reason: e.to_string(),
    })?;
    parse(&text, path)
}

fn finite(what: &str, x: f64) -> Result<f64, ArgError> {
    if x.is_finite() {
        Ok(x)
    } else {
        Err(format!("{what} must be finite").into())
    }
}

fn step(r: RawStep) -> Result<Step, ArgError> {
    if let Some(at) = r.at {
        if !(at.is_finite() && at >= 0.0) {
            return Err(format!("at {at}: must be a finite number of seconds ≥ 0").into());
        }
    }
    let mut actions = Vec::new();
    if let Some(c) = r.camera {
        for (k, v) in [
            ("azimuth", c.azimuth),
            ("elevation", c.elevation),
            ("distance", c.distance),
            ("fov", c.fov),
        ] {
            if let Some(v) = v {
                finite(k, v)?;
            }
        }
        if c.elevation
            .is_some_and(|e| e.abs() > tetwave_protocol::view::MAX_ELEVATION)
        {
            return Err(format!(
                "elevation must be within ±{}°",
                tetwave_protocol::view::MAX_ELEVATION
            )
            .into());
        }
        if c.distance.is_some_and(|d| d <= 0.0) {
            return Err("distance must be positive".into());
        }
        if c.fov.is_some_and(|f| !(1.0..=179.0).contains(&f)) {
            return Err("fov must be within 1..=179 degrees".into());
        }
        actions.push(Action::Camera(c));
    }
    if let Some(d) = r.orbit {
        actions.push(Action::Orbit(finite("orbit", d)?));
    }
    if let Some(d) = r.elevate {
        actions.push(Action::Elevate(finite("elevate", d)?));
    }
    if let Some(z) = r.zoom {
        if !(z.is_finite() && z > 0.0) {
            return Err("zoom must be a positive factor".into());
        }
        actions.push(Action::Zoom(z));
    }
    if let Some(f) = r.fly {
        for (k, v) in [
            ("forward", f.forward),
            ("right", f.right),
            ("up", f.up),
            ("yaw", f.yaw),
            ("pitch", f.pitch),
        ] {
            finite(k, v)?;
        }
        actions.push(Action::Fly(f));
    }
    if r.reset == Some(true) {
        actions.push(Action::Reset);
    }
    if let Some(tf) = r.tf {
        actions.push(Action::Tf(tf));
    }
    if let Some(t) = r.tol {
        if !(t.is_finite() && t >= 0.0) {
            return Err("tol must be a number of pixels ≥ 0".into());
        }
        actions.push(Action::Tol(t));
    }
    if let Some(m) = r.mode {
        actions.push(Action::Mode(m));
    }
    if let Some(sz) = r.size {
        let (w, h) = tetwave_source::options::parse_size(&sz).map_err(|e| format!("size: {e}"))?;
        actions.push(Action::Size(w, h));
    }
    if let Some(w) = r.wait {
        actions.push(Action::Wait(w));
    }
    if let Some(n) = r.frames {
        actions.push(Action::Frames(n));
    }
    if r.server_image == Some(true) {
        actions.push(Action::ServerImage);
    }
    if let Some(p) = r.screenshot {
        actions.push(Action::Screenshot(p));
    }
    if let Some(p) = r.window_screenshot {
        actions.push(Action::WindowScreenshot(p));
    }
    if r.quit == Some(true) {
        actions.push(Action::Quit);
    }
    match actions.len() {
        1 => Ok(Step {
            at: r.at,
            action: actions.pop().expect("one"),
        }),
        0 => Err("no action (give one of camera, orbit, elevate, zoom, fly, reset, tf, tol, mode, size, wait, frames, server_image, screenshot, window_screenshot, quit)".into()),
        n => Err(format!("{n} actions in one step; give one per step").into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ViewMode;

    #[test]
    fn parses_every_action() {
        let text = r#"[
            {"wait": "complete"}, {"at": 1.5, "orbit": 90}, {"camera": {"azimuth": 10}},
            {"elevate": -5}, {"zoom": 0.5}, {"reset": true}, {"tf": "shells"}, {"tol": 3},
            {"mode": "interactive"}, {"frames": 4}, {"server_image": true},
            {"screenshot": "a.png"}, {"quit": true}, {"fly": {"forward": 0.5, "yaw": -10}}
        ]"#;
        let s = parse(text, Path::new("s.json")).unwrap();
        assert_eq!(s.len(), 14);
        let s2 = parse(r#"[{"size": "320x200"}]"#, Path::new("s.json")).unwrap();
        assert_eq!(s2[0].action, Action::Size(320, 200));
        assert_eq!(
            s[13].action,
            Action::Fly(FlyMove {
                forward: 0.5,
                yaw: -10.0,
                ..FlyMove::default()
            })
        );
        assert_eq!(s[0].action, Action::Wait(WaitFor::Complete));
        assert_eq!(s[1].at, Some(1.5));
        assert_eq!(s[1].action, Action::Orbit(90.0));
        assert_eq!(s[8].action, Action::Mode(ViewMode::Interactive));
        assert_eq!(s[11].action, Action::Screenshot("a.png".into()));
        assert_eq!(s[12].action, Action::Quit);
    }

    #[test]
    fn refuses_bad_steps_with_their_index() {
        for (text, needle) in [
            (r#"[{"orbit": 1}, {}]"#, "step 1: no action"),
            (r#"[{"orbit": 1, "zoom": 2}]"#, "step 0: 2 actions"),
            (r#"[{"spin": 1}]"#, "unknown field"),
            (r#"[{"zoom": -1}]"#, "step 0: zoom"),
            (r#"[{"at": -1, "quit": true}]"#, "step 0: at -1"),
            (r#"[{"camera": {"elevation": 95}}]"#, "elevation"),
            (r#"[{"mode": "fast"}]"#, "unknown variant"),
            (r#"[{"fly": {"back": 1}}]"#, "unknown field"),
            (r#"[{"size": "0x10"}]"#, "step 0: size"),
        ] {
            let e = parse(text, Path::new("s.json")).unwrap_err().to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
    }
}
