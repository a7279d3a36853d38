//! A whole draw at rest spread over frames, when whole draws are slower than `--motion-ms`
//! ([`super::plan::DrawKind::Spread`]): its visibility sort on a thread of its own
//! ([`PtRenderer::plan`]), then the frame's triangles in consecutive ranges, one a frame, into a
//! second target, which replaces the one shown once it holds every triangle (the same image as
//! one whole draw: see [`PtRenderer::draw_range`]). Meanwhile the window answers, showing the last
//! image. The frame loop drops it when the camera or the view's size changes or another draw
//! needs the renderer; a new mesh or transfer function waits for it, then is drawn.

use super::gpu::Target;
use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;
use tetwave_gpu::pt::{FrameDraw, FramePlan as SortPlan, PtRenderer, TetDrawData, VisibilityOrder};
use tetwave_gpu::GpuContext;
use tetwave_protocol::view::Camera;
use tetwave_render::transfer::TransferFunction;

/// The fewest triangles one frame of a spread draw draws.
pub const MIN_PART_TRIANGLES: u32 = 4096;

/// The parts a spread draw is cut into: fixed, because a part size measured from frame times
/// would follow the frame's own work (refinement, the leaf mesh, often larger than a part), not
/// the draw (the measurements behind the count: docs/benchmarks.md, "Whole draws at rest, spread
/// over frames").
pub const SPREAD_PARTS: u32 = 24;

/// The triangles of an `n`-triangle draw that the part starting at `next` covers:
/// `n / SPREAD_PARTS` (rounded up), at least [`MIN_PART_TRIANGLES`], never past `n`.
pub fn part(n: u32, next: u32) -> Range<u32> {
    let end = next
        .saturating_add(n.div_ceil(SPREAD_PARTS).max(MIN_PART_TRIANGLES))
        .min(n);
    next.min(n)..end
}

enum Stage {
    /// The visibility sort and the exit faces, on their thread.
    Sorting(std::thread::JoinHandle<SortPlan>),
    /// Triangles drawn so far.
    Drawing { frame: FrameDraw, next: u32 },
}

/// What one frame of a spread draw did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Progress {
    /// Still sorting.
    Sorting,
    /// The sort was handed to the renderer this frame, in `ms`.
    Sorted { ms: f64 },
    /// A part of `triangles` triangles was drawn, in `ms`; `done`: it was the last.
    Drew { triangles: u32, ms: f64, done: bool },
}

/// The sort's thread ended without a result (it panicked).
#[derive(Debug, thiserror::Error)]
#[error("the visibility sort of a spread draw failed")]
pub struct SortFailed;

/// A draw in progress over frames.
pub struct SpreadDraw {
    stage: Option<Stage>,
    target: Target,
    /// The mesh and transfer function it draws.
    data: Arc<TetDrawData>,
    tf: TransferFunction,
    /// The frame it started in.
    first_frame: u64,
}

impl SpreadDraw {
    /// Starts sorting `data` for `cam` on a thread of its own; the parts will go into `target`.
    pub fn start(
        data: Arc<TetDrawData>,
        cam: Camera,
        tf: TransferFunction,
        target: Target,
        first_frame: u64,
    ) -> SpreadDraw {
        let (d, t) = (Arc::clone(&data), tf.clone());
        let sort =
            std::thread::spawn(move || PtRenderer::plan(&d, &cam, &t, VisibilityOrder::Centroid));
        SpreadDraw {
            stage: Some(Stage::Sorting(sort)),
            target,
            data,
            tf,
            first_frame,
        }
    }

    /// The target it draws into.
    pub fn target(&self) -> &Target {
        &self.target
    }

    /// The target, given back (the draw is dropped or complete).
    pub fn into_target(self) -> Target {
        self.target
    }

    /// The frame it started in.
    pub fn first_frame(&self) -> u64 {
        self.first_frame
    }

    /// This frame's step: hands a finished sort to `renderer`, or draws the next part.
    pub fn step(
        &mut self,
        renderer: &PtRenderer,
        gpu: &GpuContext,
    ) -> Result<Progress, SortFailed> {
        let t = Instant::now();
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        match self.stage.take() {
            Some(Stage::Sorting(h)) if !h.is_finished() => {
                self.stage = Some(Stage::Sorting(h));
                Ok(Progress::Sorting)
            }
            Some(Stage::Sorting(h)) => {
                let plan = h.join().map_err(|_| SortFailed)?;
                let frame = renderer.finish(gpu, &self.data, &self.tf, plan);
                self.stage = Some(Stage::Drawing { frame, next: 0 });
                Ok(Progress::Sorted { ms: ms(t) })
            }
            Some(Stage::Drawing { frame, next }) => {
                let n = frame.triangles();
                let r = part(n, next);
                renderer.draw_range_into(gpu, &frame, r.clone(), &self.target.view, next == 0);
                let done = r.end >= n;
                self.stage = Some(Stage::Drawing { frame, next: r.end });
                Ok(Progress::Drew {
                    triangles: (r.end - r.start).max(1),
                    ms: ms(t),
                    done,
                })
            }
            None => Err(SortFailed),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_cover_every_triangle_once_in_order() {
        for n in [0u32, 1, 4095, 4096, 4097, 98_304, 750_001, u32::MAX] {
            let (mut next, mut parts) = (0u32, 0u32);
            loop {
                let r = part(n, next);
                assert_eq!(r.start, next, "n = {n}");
                assert!(r.end <= n);
                assert!(
                    r.end - r.start >= MIN_PART_TRIANGLES.min(n - next),
                    "n = {n}: a part of {} at {next}",
                    r.end - r.start
                );
                parts += 1;
                next = r.end;
                if next >= n {
                    break;
                }
            }
            assert!(parts <= SPREAD_PARTS.max(1), "n = {n}: {parts} parts");
        }
        // large draws take SPREAD_PARTS parts; small ones fewer, of MIN_PART_TRIANGLES
        let count = |n: u32| {
            let mut next = 0;
            let mut k = 0;
            while next < n {
                next = part(n, next).end;
                k += 1;
            }
            k
        };
        assert_eq!(count(750_001), SPREAD_PARTS);
        assert_eq!(count(20_480), 5);
    }
}
