//! Level of detail in motion (`--motion-lod`): while the camera moves, a slow draw coarsens the
//! mesh rather than delaying the frames that answer the mouse. (The viewer's other, default
//! remedy draws fewer pixels in motion, `--motion-scale`; this one also tracks when the camera
//! last moved for it.) The tolerance is multiplied by a factor that
//! follows the measured period of the frames drawn in motion toward a target; at rest (no camera
//! change for [`HOLD`]) the user's tolerance returns, and with it the progressive refinement.
//! The factor is kept between motions: it is what this machine needs for this mesh and view.
//!
//! Coarsening takes merges, and a frame's refinement has a budget (8 ms when the camera moves):
//! with frames of a second, a budget of milliseconds would take the whole motion to coarsen. While
//! the factor is raised, a moving frame's refinement may take a tenth of the last slow period
//! (at most [`MAX_REFINE_MS`]): next to that draw it is little, and it gets the coarser mesh.

use std::time::{Duration, Instant};

/// The camera counts as moving for this long after its last change (inputs come in bursts with
/// gaps of a few frames; refining back in each gap would cost a slow frame each time).
pub const HOLD: Duration = Duration::from_millis(400);

/// The largest factor on the tolerance.
pub const MAX_FACTOR: f64 = 64.0;

/// The most refinement time a moving frame gets while the factor is raised.
pub const MAX_REFINE_MS: f64 = 50.0;

/// A tolerance of 0 (refine everything) is scaled from this many pixels.
const MIN_TOL_PX: f64 = 0.5;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionLod {
    /// Frame period aimed at while moving, in ms; 0: off.
    pub target_ms: f64,
    factor: f64,
    last_motion: Option<Instant>,
    /// The last period observed.
    last_period_ms: f64,
}

impl MotionLod {
    pub fn new(target_ms: f64) -> MotionLod {
        MotionLod {
            target_ms,
            factor: 1.0,
            last_motion: None,
            last_period_ms: 0.0,
        }
    }

    /// The camera changed at `now`.
    pub fn moved(&mut self, now: Instant) {
        self.last_motion = Some(now);
    }

    pub fn in_motion(&self, now: Instant) -> bool {
        self.last_motion
            .is_some_and(|t| now.saturating_duration_since(t) < HOLD)
    }

    pub fn factor(&self) -> f64 {
        self.factor
    }

    /// A frame that drew the volume in motion took `period_ms` from its start to the next's.
    /// The draw's cost goes with the tets drawn, which fall with the square to the cube of the
    /// tolerance: a frame `r` times too slow raises the factor by √r (at most 2× a frame); one
    /// well under the target lowers it by a fifth.
    pub fn observe(&mut self, period_ms: f64) {
        if self.target_ms <= 0.0 || !period_ms.is_finite() {
            return;
        }
        self.last_period_ms = period_ms;
        let r = period_ms / self.target_ms;
        if r > 1.2 {
            self.factor = (self.factor * r.sqrt().min(2.0)).min(MAX_FACTOR);
        } else if r < 0.5 {
            self.factor = (self.factor / 1.2).max(1.0);
        }
    }

    /// The refinement budget of a moving frame, from the selector's `base_ms`: more while the
    /// factor is raised (see the module's notes).
    pub fn refine_budget_ms(&self, base_ms: f64, now: Instant) -> f64 {
        if self.target_ms > 0.0 && self.factor > 1.0 && self.in_motion(now) {
            (0.1 * self.last_period_ms).clamp(base_ms, MAX_REFINE_MS.max(base_ms))
        } else {
            base_ms
        }
    }

    /// The tolerance to refine with: `tol` at rest, scaled by the factor in motion.
    pub fn tolerance(&self, tol: f64, now: Instant) -> f64 {
        if self.target_ms > 0.0 && self.factor > 1.0 && self.in_motion(now) {
            tol.max(MIN_TOL_PX) * self.factor
        } else {
            tol
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slow_frames_in_motion_raise_the_tolerance_and_rest_restores_it() {
        let t0 = Instant::now();
        let mut m = MotionLod::new(50.0);
        assert_eq!(m.tolerance(2.0, t0), 2.0);
        m.moved(t0);
        // 4× too slow: √4 = 2× per frame, up to the cap
        m.observe(200.0);
        assert_eq!(m.factor(), 2.0);
        assert_eq!(m.tolerance(2.0, t0), 4.0);
        assert_eq!(m.tolerance(0.0, t0), 1.0);
        for _ in 0..20 {
            m.observe(1000.0);
        }
        assert_eq!(m.factor(), MAX_FACTOR);
        // near the target: kept; fast: lowered, never under 1
        let f = m.factor();
        m.observe(55.0);
        assert_eq!(m.factor(), f);
        for _ in 0..100 {
            m.observe(10.0);
        }
        assert_eq!(m.factor(), 1.0);
        m.observe(400.0);
        // a slow frame in motion: a tenth of it to refine, within 8..=50 ms
        assert_eq!(m.refine_budget_ms(8.0, t0), 40.0);
        m.observe(2000.0);
        assert_eq!(m.refine_budget_ms(8.0, t0), MAX_REFINE_MS);
        m.observe(30.0);
        assert_eq!(m.refine_budget_ms(8.0, t0), 8.0);
        assert_eq!(m.refine_budget_ms(8.0, t0 + HOLD), 8.0);
        m.observe(400.0);
        // at rest the user's tolerance, whatever the factor
        assert!(m.tolerance(2.0, t0 + HOLD / 2) > 2.0);
        assert_eq!(m.tolerance(2.0, t0 + HOLD), 2.0);
        assert!(!m.in_motion(t0 + HOLD));
    }

    #[test]
    fn a_target_of_zero_is_off() {
        let t0 = Instant::now();
        let mut m = MotionLod::new(0.0);
        m.moved(t0);
        m.observe(10_000.0);
        assert_eq!(m.factor(), 1.0);
        assert_eq!(m.tolerance(2.0, t0), 2.0);
    }
}
