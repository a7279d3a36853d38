//! The viewer's per-frame decisions, as a pure function of what the frame knows: how to refine
//! (mode, tolerance, time budget), which mesh to draw (the leaf mesh or the coarser motion mesh),
//! whether to draw it whole or spread over frames, with how many pixels, and whether a changed
//! mesh may go up now. [`FramePlan::decide`] holds every rule; `app.rs` carries them out.

use super::ViewMode;
use tetwave_adaptive::select::Mode;

/// Refinement's time per frame while slow whole draws move with the coarser mesh: the leaf mesh
/// is refined only a little then (its upload waits for rest), so the frame is the draw.
pub const MOVING_COARSE_REFINE_MS: f64 = 8.0;

/// A first mesh of at least this many tets is taken as slow to draw before any draw of it is
/// measured (so spread over frames): a whole draw of 8 M tets holds a CPU rasterizer's window
/// for 13 s (docs/benchmarks.md, "Large meshes").
pub const SLOW_FIRST_DRAW_TETS: u64 = 1 << 20;

/// What a whole draw of a new mesh of `tets` tets is expected to cost, from the last measured
/// whole draw (`last_ms` for `last_tets` tets; 0 when none): scaled by the tets when the mesh
/// grew, since the draw's work is per tet; unknown and slow (∞) for a first mesh past
/// [`SLOW_FIRST_DRAW_TETS`]. A measured draw replaces the estimate.
pub fn expected_draw_ms(last_ms: f64, last_tets: u64, tets: u64) -> f64 {
    if tets <= last_tets {
        last_ms
    } else if last_ms > 0.0 && last_tets > 0 {
        last_ms * tets as f64 / last_tets as f64
    } else if tets >= SLOW_FIRST_DRAW_TETS {
        f64::INFINITY
    } else {
        last_ms
    }
}

/// What one frame knows when it decides.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameInputs {
    /// The refinement mode the user chose.
    pub mode: ViewMode,
    /// The camera moved in this frame.
    pub moving: bool,
    /// The camera moved recently enough to count as in motion (motion's tolerance applies).
    pub in_motion: bool,
    /// The user's tolerance, in pixels, and the one motion's level of detail asks for now.
    pub tol_px: f64,
    pub motion_tol_px: f64,
    /// `--motion-ms` (0: never slow), and the period of the last frame that drew the whole view.
    pub motion_ms: f64,
    pub full_draw_ms: f64,
    /// A coarser motion mesh is uploaded.
    pub has_motion_mesh: bool,
    /// `--motion-scale`: the divisor of the view's pixels for draws in motion.
    pub motion_scale: u32,
    /// The view's size in pixels.
    pub view_px: (u32, u32),
    /// The interactive refinement budget after motion's changes, when it is one of time.
    pub interactive_ms: Option<f64>,
}

/// The mesh a frame draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DrawMesh {
    /// Every drawable leaf of the refined mesh.
    Leaf,
    /// The coarser motion mesh (`--motion-tets`).
    Motion,
}

/// How the frame's image is drawn when it must be drawn again.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DrawKind {
    /// In one draw, this frame.
    Whole,
    /// Sorted off the frame loop, then drawn in parts over frames (`app.rs`'s `PendingDraw`).
    Spread,
}

/// What one frame does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FramePlan {
    /// The tolerance refinement runs with (the user's in complete mode or at rest).
    pub tol_px: f64,
    pub refine_mode: Mode,
    /// The interactive budget to set, in ms, when it is one of time.
    pub interactive_ms: Option<f64>,
    pub mesh: DrawMesh,
    pub draw: DrawKind,
    /// The divisor of the view's pixels (1: all of them) and the size drawn.
    pub scale: u32,
    pub draw_px: (u32, u32),
    /// A mesh that changed may be listed and uploaded this frame (not while slow draws move
    /// with the coarser mesh: the upload would take the CPU the draws need).
    pub upload: bool,
}

impl FramePlan {
    /// The frame's plan: whole draws slower than `--motion-ms` are "slow"; in motion they draw the
    /// coarser mesh (when one is uploaded) with `--motion-scale` fewer pixels a side and refine
    /// within [`MOVING_COARSE_REFINE_MS`]; at rest they draw the leaf mesh spread over frames.
    pub fn decide(i: &FrameInputs) -> FramePlan {
        let tol_px = match i.mode {
            ViewMode::Complete => i.tol_px,
            _ => i.motion_tol_px,
        };
        let slow = i.motion_ms > 0.0 && i.full_draw_ms > i.motion_ms;
        let moving_coarse = i.in_motion && slow && i.has_motion_mesh;
        let refine_mode = match i.mode {
            ViewMode::Interactive => Mode::Interactive,
            ViewMode::Progressive if i.moving || moving_coarse => Mode::Interactive,
            ViewMode::Progressive => Mode::Progressive,
            ViewMode::Complete => Mode::Complete,
        };
        let interactive_ms = i.interactive_ms.map(|ms| {
            if moving_coarse {
                ms.min(MOVING_COARSE_REFINE_MS)
            } else {
                ms
            }
        });
        let scale = if i.in_motion && slow {
            i.motion_scale.max(1)
        } else {
            1
        };
        let (w, h) = i.view_px;
        let mesh = if moving_coarse {
            DrawMesh::Motion
        } else {
            DrawMesh::Leaf
        };
        let draw = if mesh == DrawMesh::Leaf && slow && scale == 1 {
            DrawKind::Spread
        } else {
            DrawKind::Whole
        };
        FramePlan {
            tol_px,
            refine_mode,
            interactive_ms,
            mesh,
            draw,
            scale,
            draw_px: ((w / scale).max(1), (h / scale).max(1)),
            upload: !moving_coarse,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grown mesh is expected to cost the last draw scaled by its tets; a large first mesh is
    /// slow until measured; a small one or a shrunk one keeps the last figure.
    #[test]
    fn a_new_meshs_draw_is_expected_to_cost_its_tets() {
        assert_eq!(expected_draw_ms(20.0, 1_000, 4_000), 80.0);
        assert_eq!(expected_draw_ms(20.0, 1_000, 500), 20.0);
        assert_eq!(
            expected_draw_ms(0.0, 0, SLOW_FIRST_DRAW_TETS),
            f64::INFINITY
        );
        assert_eq!(expected_draw_ms(0.0, 0, 1_000), 0.0);
        // ∞ makes the next frame's plan spread the draw at rest
        let i = FrameInputs {
            full_draw_ms: expected_draw_ms(0.0, 0, 8_000_000),
            ..at_rest()
        };
        assert_eq!(FramePlan::decide(&i).draw, DrawKind::Spread);
    }

    /// A frame at rest with fast draws, in progressive mode.
    fn at_rest() -> FrameInputs {
        FrameInputs {
            mode: ViewMode::Progressive,
            moving: false,
            in_motion: false,
            tol_px: 2.0,
            motion_tol_px: 2.0,
            motion_ms: 60.0,
            full_draw_ms: 20.0,
            has_motion_mesh: true,
            motion_scale: 2,
            view_px: (801, 600),
            interactive_ms: Some(8.0),
        }
    }

    #[test]
    fn fast_draws_are_whole_leaf_draws_with_every_pixel() {
        let p = FramePlan::decide(&at_rest());
        assert_eq!(p.refine_mode, Mode::Progressive);
        assert_eq!(
            (p.mesh, p.draw, p.scale),
            (DrawMesh::Leaf, DrawKind::Whole, 1)
        );
        assert_eq!(p.draw_px, (801, 600));
        assert!(p.upload);
        // moving with fast draws: interactive refinement, the same draw
        let moving = FramePlan::decide(&FrameInputs {
            moving: true,
            in_motion: true,
            motion_tol_px: 3.0,
            ..at_rest()
        });
        assert_eq!(moving.refine_mode, Mode::Interactive);
        assert_eq!(moving.tol_px, 3.0);
        assert_eq!(
            (moving.mesh, moving.draw, moving.scale),
            (DrawMesh::Leaf, DrawKind::Whole, 1)
        );
        assert_eq!(moving.interactive_ms, Some(8.0));
    }

    #[test]
    fn slow_draws_in_motion_draw_the_motion_mesh_with_fewer_pixels_and_no_upload() {
        let p = FramePlan::decide(&FrameInputs {
            moving: true,
            in_motion: true,
            full_draw_ms: 300.0,
            interactive_ms: Some(40.0),
            ..at_rest()
        });
        assert_eq!(
            (p.mesh, p.draw, p.scale),
            (DrawMesh::Motion, DrawKind::Whole, 2)
        );
        assert_eq!(p.draw_px, (400, 300));
        assert!(!p.upload);
        assert_eq!(p.interactive_ms, Some(MOVING_COARSE_REFINE_MS));
        assert_eq!(p.refine_mode, Mode::Interactive);
        // still in motion though this frame's camera is where the last one's was
        let held = FramePlan::decide(&FrameInputs {
            moving: false,
            ..FrameInputs {
                moving: true,
                in_motion: true,
                full_draw_ms: 300.0,
                ..at_rest()
            }
        });
        assert_eq!(
            held.refine_mode,
            Mode::Interactive,
            "motion's mesh refines as in motion"
        );
        // no motion mesh yet: the leaf mesh, with fewer pixels, whole
        let none = FramePlan::decide(&FrameInputs {
            moving: true,
            in_motion: true,
            full_draw_ms: 300.0,
            has_motion_mesh: false,
            ..at_rest()
        });
        assert_eq!(
            (none.mesh, none.draw, none.scale),
            (DrawMesh::Leaf, DrawKind::Whole, 2)
        );
        assert!(none.upload);
    }

    #[test]
    fn slow_draws_at_rest_are_spread_over_frames_with_every_pixel() {
        let p = FramePlan::decide(&FrameInputs {
            full_draw_ms: 300.0,
            ..at_rest()
        });
        assert_eq!(
            (p.mesh, p.draw, p.scale),
            (DrawMesh::Leaf, DrawKind::Spread, 1)
        );
        assert_eq!(p.draw_px, (801, 600));
        assert!(p.upload);
        assert_eq!(p.refine_mode, Mode::Progressive);
        // --motion-ms 0: never slow
        let off = FramePlan::decide(&FrameInputs {
            full_draw_ms: 300.0,
            motion_ms: 0.0,
            ..at_rest()
        });
        assert_eq!(off.draw, DrawKind::Whole);
    }

    #[test]
    fn complete_mode_refines_everything_at_the_users_tolerance() {
        let p = FramePlan::decide(&FrameInputs {
            mode: ViewMode::Complete,
            moving: true,
            in_motion: true,
            motion_tol_px: 8.0,
            ..at_rest()
        });
        assert_eq!(p.refine_mode, Mode::Complete);
        assert_eq!(p.tol_px, 2.0);
        let i = FramePlan::decide(&FrameInputs {
            mode: ViewMode::Interactive,
            ..at_rest()
        });
        assert_eq!(i.refine_mode, Mode::Interactive);
    }

    #[test]
    fn a_tiny_view_still_draws_a_pixel() {
        let p = FramePlan::decide(&FrameInputs {
            moving: true,
            in_motion: true,
            full_draw_ms: 300.0,
            motion_scale: 4,
            view_px: (3, 1),
            ..at_rest()
        });
        assert_eq!(p.draw_px, (1, 1));
    }
}
