//! The viewer's timing record: per frame, where the time went (ingest, refinement against its
//! budget, leaf-mesh build, upload, render) and, per input (a camera, tolerance, mode or
//! transfer-function change, from the mouse, the keys or the script), the time until the frame
//! that presents it. `--json` carries the summary ([`PerfReport`]).
//!
//! Input-to-frame latency runs from the input's time to the start of the frame after the one
//! that applied it: eframe paints and presents a frame's output after its `ui` returns and only
//! then starts the next, so that start bounds the presentation from above. The input's time is
//! a script step's `at` (when it is due, so a long frame that delays the step counts; but not
//! before the script passed a step that waited, such as `wait`, which holds it back), or the
//! start of the frame that read a mouse or key event (egui gives no event times; the wait
//! before that frame is not seen).
//!
//! The bound the viewer is held to: an input waits at most for the frame in flight when it came,
//! then is drawn by the next, so its latency is below that frame's period plus the applying
//! frame's (its work, paint, GPU and present). That holds exactly when the first frame to start
//! after the input applies it; [`PerfReport::inputs_past_bound`] counts the inputs it did not.

use super::ViewMode;
use serde::Serialize;
use std::time::Instant;

/// One frame's times, in milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct FrameRecord {
    pub frame: u64,
    /// Seconds since the window opened, at the frame's start.
    pub t_s: f64,
    /// From this frame's start to the next one's (NaN for the last frame): its work and its
    /// paint.
    pub period_ms: f64,
    pub ingest_ms: f64,
    pub refine_ms: f64,
    /// The selector's time budget for this frame's mode (`None`: unlimited, or no refinement).
    pub refine_budget_ms: Option<f64>,
    /// Building the leaf mesh for an upload, in the frame (0 when none started).
    pub leaf_ms: f64,
    /// An upload of the leaf mesh that finished by this frame (it runs on the upload thread,
    /// beside the frames; 0 when none did).
    pub upload_ms: f64,
    /// The CPU side of the volume's draw (0 when the image did not change).
    pub render_ms: f64,
    /// The frame's own work (from its start to the end of the viewer's part).
    pub work_ms: f64,
    /// From the end of the frame's work to the next frame's start: eframe painting the window,
    /// the GPU finishing (the volume's draw included), presenting, and any idle wait.
    pub paint_ms: f64,
    pub tets: u64,
    /// The tolerance refined with (the user's, or a coarser one in motion), pixels.
    pub tol_px: f64,
    /// The camera moved within [`super::motion::HOLD`].
    pub in_motion: bool,
    /// The volume was drawn with 1/`draw_scale` of the view's width and height.
    pub draw_scale: u32,
    /// Inputs applied in this frame.
    pub inputs: u32,
    pub mode: ViewMode,
    /// The camera moved in this frame.
    pub moving: bool,
    /// The volume was drawn in this frame.
    pub drew: bool,
    /// Triangles of a whole draw spread over frames drawn in this frame (0: none).
    pub drew_part: u32,
    /// This frame drew the last part of a spread draw, whose first part was drawn in this frame.
    pub drew_part_of: Option<u64>,
}

/// p50, p95 and maximum of a set of times (nearest rank), and how many.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Stats {
    pub n: usize,
    pub p50: f64,
    pub p95: f64,
    pub max: f64,
}

impl Stats {
    /// The statistics of `xs` (all zero when empty); NaNs are left out.
    pub fn of(xs: impl IntoIterator<Item = f64>) -> Stats {
        let mut v: Vec<f64> = xs.into_iter().filter(|x| !x.is_nan()).collect();
        if v.is_empty() {
            return Stats::default();
        }
        v.sort_by(f64::total_cmp);
        let rank = |p: f64| v[((p * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1];
        Stats {
            n: v.len(),
            p50: rank(0.50),
            p95: rank(0.95),
            max: v[v.len() - 1],
        }
    }
}

/// The summary `--json` prints.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PerfReport {
    /// Input to the frame presenting it.
    pub latency_ms: Stats,
    /// Inputs that waited past the frame in flight when they came (a frame started after them
    /// and did not apply them): their latency exceeds that frame's period plus the applying
    /// frame's.
    pub inputs_past_bound: usize,
    /// Frame periods (start to the next start), the last frame left out.
    pub frame_ms: Stats,
    /// The periods of the frames in motion (the camera moved within
    /// [`super::motion::HOLD`]): how the window answers while the user drags.
    pub frame_ms_in_motion: Stats,
    pub ingest_ms: Stats,
    /// Refinement, every frame that refined.
    pub refine_ms: Stats,
    /// Leaf-mesh builds and uploads, the frames whose mesh changed.
    pub leaf_ms: Stats,
    pub upload_ms: Stats,
    /// The volume's draws (CPU side), the frames that drew.
    pub render_ms: Stats,
    /// The viewer's own work per frame.
    pub work_ms: Stats,
    /// Paint, GPU and present per frame (see [`FrameRecord::paint_ms`]), and for the frames
    /// that drew the volume.
    pub paint_ms: Stats,
    pub paint_drawn_ms: Stats,
    /// The frame whose refinement took longest.
    pub worst_refine: Option<FrameRecord>,
    /// The frame with the longest period.
    pub worst_frame: Option<FrameRecord>,
    /// Frames whose refinement ran past its budget by more than [`OVER_BUDGET_SLACK_MS`].
    pub refine_over_budget: usize,
    /// Frames that drew the volume, of all frames.
    pub frames_drawn: u64,
    /// Tets drawn by the frames that drew in motion, and at rest.
    pub tets_drawn_in_motion: Stats,
    pub tets_drawn_at_rest: Stats,
    /// The largest tolerance refined with, pixels.
    pub max_tol_px: f64,
    /// Frames that drew the volume with fewer pixels than the view's (`--motion-scale`).
    pub frames_drawn_scaled: u64,
    /// Whole draws spread over frames (slow draws at rest), and the frames that drew their parts.
    pub spread_draws: u64,
    pub spread_frames: u64,
    /// The periods of the frames that drew a part of one.
    pub spread_frame_ms: Stats,
}

/// A selector checks its clock between operations, so a frame overruns its budget by up to one
/// operation: overruns up to this much are not counted.
pub const OVER_BUDGET_SLACK_MS: f64 = 1.0;

/// Times the viewer's frames and inputs.
#[derive(Debug, Default)]
pub struct Perf {
    frames: Vec<FrameRecord>,
    latencies_ms: Vec<f64>,
    /// Inputs applied in the frame being built, by the time they were given.
    applied: Vec<Instant>,
    /// Inputs of the last frame, presented when the next one starts.
    presenting: Vec<Instant>,
    current: FrameRecord,
    frame_start: Option<Instant>,
    /// When the last frame's work ended.
    work_end: Option<Instant>,
    /// When the frame before the current one started.
    prev_start: Option<Instant>,
    inputs_past_bound: usize,
}

impl Perf {
    /// A frame starts: the previous one's output has been presented.
    pub fn begin_frame(&mut self, frame: u64, now: Instant, since_start_s: f64) {
        for t in self.presenting.drain(..) {
            self.latencies_ms
                .push(now.saturating_duration_since(t).as_secs_f64() * 1e3);
        }
        if let (Some(start), Some(end), Some(last)) =
            (self.frame_start, self.work_end, self.frames.last_mut())
        {
            last.paint_ms = now.saturating_duration_since(end).as_secs_f64() * 1e3;
            last.period_ms = now.saturating_duration_since(start).as_secs_f64() * 1e3;
        }
        self.prev_start = self.frame_start;
        self.frame_start = Some(now);
        self.current = FrameRecord {
            frame,
            t_s: since_start_s,
            period_ms: f64::NAN,
            ..FrameRecord::default()
        };
    }

    /// The frame's record, filled in as the frame goes.
    pub fn current(&mut self) -> &mut FrameRecord {
        &mut self.current
    }

    /// An input given at `at` was applied in this frame.
    pub fn input(&mut self, at: Instant) {
        if self.prev_start.is_some_and(|p| p >= at) {
            // the previous frame started after the input and left it
            self.inputs_past_bound += 1;
        }
        self.applied.push(at);
        self.current.inputs += 1;
    }

    /// The frame's work is submitted; its inputs are presented with it.
    pub fn end_frame(&mut self, now: Instant) {
        if let Some(s) = self.frame_start {
            self.current.work_ms = now.saturating_duration_since(s).as_secs_f64() * 1e3;
        }
        self.work_end = Some(now);
        self.presenting.append(&mut self.applied);
        tracing::trace!(record = ?self.current, "viewer frame");
        self.frames.push(self.current);
    }

    pub fn frames(&self) -> &[FrameRecord] {
        &self.frames
    }

    /// What the parts of the spread draw first drawn in frame `first` cost, in ms: each part
    /// frame's draw calls (`render_ms`) and its paint beyond an idle frame's (the median paint of
    /// the last frames that drew nothing: panel, copy, present), where the GPU's work is waited
    /// for. Not the part frames' periods: those hold each frame's own work and present, and
    /// would keep a fast GPU's draws spread.
    pub fn spread_cost(&self, first: u64) -> f64 {
        let mut idle: Vec<f64> = (self.frames.iter().rev())
            .filter(|r| !r.drew && r.drew_part == 0 && r.paint_ms.is_finite())
            .take(120)
            .map(|r| r.paint_ms)
            .collect();
        idle.sort_by(f64::total_cmp);
        let base = idle.get(idle.len() / 2).copied().unwrap_or(0.0);
        (self.frames.iter())
            .filter(|r| r.frame >= first && r.drew_part > 0)
            .map(|r| r.render_ms + (r.paint_ms - base).max(0.0))
            .filter(|c| c.is_finite())
            .sum()
    }

    /// Frames that drew the volume.
    pub fn frames_drawn(&self) -> u64 {
        self.frames.iter().filter(|r| r.drew).count() as u64
    }

    pub fn report(&self) -> PerfReport {
        let f = &self.frames;
        let worst = |key: fn(&FrameRecord) -> f64| {
            f.iter()
                .filter(|r| !key(r).is_nan())
                .max_by(|a, b| key(a).total_cmp(&key(b)))
                .copied()
        };
        PerfReport {
            latency_ms: Stats::of(self.latencies_ms.iter().copied()),
            inputs_past_bound: self.inputs_past_bound,
            frame_ms: Stats::of(f.iter().map(|r| r.period_ms)),
            frame_ms_in_motion: Stats::of(f.iter().filter(|r| r.in_motion).map(|r| r.period_ms)),
            ingest_ms: Stats::of(f.iter().map(|r| r.ingest_ms)),
            refine_ms: Stats::of(f.iter().filter(|r| r.refine_ms > 0.0).map(|r| r.refine_ms)),
            leaf_ms: Stats::of(f.iter().filter(|r| r.leaf_ms > 0.0).map(|r| r.leaf_ms)),
            upload_ms: Stats::of(f.iter().filter(|r| r.upload_ms > 0.0).map(|r| r.upload_ms)),
            render_ms: Stats::of(f.iter().filter(|r| r.drew).map(|r| r.render_ms)),
            work_ms: Stats::of(f.iter().map(|r| r.work_ms)),
            // the last frame's paint is not seen
            paint_ms: Stats::of(f[..f.len().saturating_sub(1)].iter().map(|r| r.paint_ms)),
            paint_drawn_ms: Stats::of(
                f[..f.len().saturating_sub(1)]
                    .iter()
                    .filter(|r| r.drew)
                    .map(|r| r.paint_ms),
            ),
            worst_refine: worst(|r| r.refine_ms).filter(|r| r.refine_ms > 0.0),
            worst_frame: worst(|r| r.period_ms),
            refine_over_budget: f
                .iter()
                .filter(|r| {
                    r.refine_budget_ms
                        .is_some_and(|b| r.refine_ms > b + OVER_BUDGET_SLACK_MS)
                })
                .count(),
            frames_drawn: f.iter().filter(|r| r.drew).count() as u64,
            tets_drawn_in_motion: Stats::of(
                f.iter()
                    .filter(|r| r.drew && r.in_motion)
                    .map(|r| r.tets as f64),
            ),
            tets_drawn_at_rest: Stats::of(
                f.iter()
                    .filter(|r| r.drew && !r.in_motion)
                    .map(|r| r.tets as f64),
            ),
            max_tol_px: f.iter().map(|r| r.tol_px).fold(0.0, f64::max),
            frames_drawn_scaled: f.iter().filter(|r| r.drew && r.draw_scale > 1).count() as u64,
            spread_draws: f.iter().filter(|r| r.drew_part_of.is_some()).count() as u64,
            spread_frames: f.iter().filter(|r| r.drew_part > 0).count() as u64,
            spread_frame_ms: Stats::of(f.iter().filter(|r| r.drew_part > 0).map(|r| r.period_ms)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// A spread draw costs its parts' draw calls and their paint beyond an idle frame's, not the
    /// part frames' periods: 24 parts of 1 ms on a GPU whose idle paint is 16 ms cost 24 ms, not
    /// the ~400 ms the periods add up to.
    #[test]
    fn a_spread_draw_costs_its_parts_not_its_frames() {
        let t0 = Instant::now();
        let mut p = Perf::default();
        let mut at = 0u64;
        let mut frame = |p: &mut Perf, n: u64, part: u32, paint: u64| {
            p.begin_frame(n, t0 + Duration::from_millis(at), 0.0);
            p.current().drew_part = part;
            p.current().render_ms = if part > 0 { 0.5 } else { 0.0 };
            p.end_frame(t0 + Duration::from_millis(at + 1));
            at += 1 + paint;
        };
        for n in 0..10 {
            frame(&mut p, n, 0, 16);
        }
        for n in 10..34 {
            frame(&mut p, n, 4096, 16 + 1);
        }
        frame(&mut p, 34, 0, 16);
        let cost = p.spread_cost(10);
        // 24 × (0.5 ms of calls + 1 ms of paint over the idle 16)
        assert!((cost - 36.0).abs() < 1e-6, "{cost}");
        let periods: f64 = p.frames()[10..34].iter().map(|r| r.period_ms).sum();
        assert!(periods > 400.0, "{periods}");
    }

    #[test]
    fn stats_are_nearest_rank() {
        let s = Stats::of((1..=100).map(f64::from));
        assert_eq!((s.n, s.p50, s.p95, s.max), (100, 50.0, 95.0, 100.0));
        let s = Stats::of([3.0, f64::NAN, 1.0]);
        assert_eq!((s.n, s.p50, s.p95, s.max), (2, 1.0, 3.0, 3.0));
        assert_eq!(Stats::of([]), Stats::default());
    }

    #[test]
    fn latency_runs_from_the_input_to_the_next_frames_start() {
        let t0 = Instant::now();
        let ms = |m: u64| t0 + Duration::from_millis(m);
        let mut p = Perf::default();
        p.begin_frame(1, ms(0), 0.0);
        p.current().refine_ms = 3.0;
        p.current().refine_budget_ms = Some(8.0);
        p.end_frame(ms(4));
        // an input due at 5 ms is applied in the frame that starts at 20 ms, presented at 50
        p.begin_frame(2, ms(20), 0.02);
        p.input(ms(5));
        p.current().refine_ms = 12.0;
        p.current().refine_budget_ms = Some(8.0);
        p.current().drew = true;
        p.end_frame(ms(30));
        p.begin_frame(3, ms(50), 0.05);
        p.end_frame(ms(51));
        let r = p.report();
        assert_eq!(r.latency_ms.n, 1);
        assert!((r.latency_ms.max - 45.0).abs() < 1e-6, "{r:?}");
        assert_eq!(r.frame_ms.n, 2);
        assert!((r.frame_ms.max - 30.0).abs() < 1e-6);
        assert_eq!(r.worst_refine.unwrap().frame, 2);
        // frame 2 ran from 20 to 50 ms
        assert_eq!(r.worst_frame.unwrap().frame, 2);
        assert_eq!(r.refine_over_budget, 1);
        assert_eq!(r.refine_ms.n, 2);
        assert_eq!(r.frames_drawn, 1);
        // frame 1 worked 4 ms and painted 16; frame 2 worked 10 and painted 20
        let near = |a: f64, b: f64| (a - b).abs() < 1e-6;
        assert!(near(p.frames()[0].work_ms, 4.0));
        assert!(near(p.frames()[0].paint_ms, 16.0));
        assert!(r.paint_ms.n == 2 && near(r.paint_ms.max, 20.0), "{r:?}");
        assert!(r.paint_drawn_ms.n == 1 && near(r.paint_drawn_ms.max, 20.0));
        assert!(near(r.work_ms.max, 10.0));
        // applied by the first frame after it: within the bound (frame 1's period, 20 ms, plus
        // frame 2's, 30 ms)
        assert_eq!(r.inputs_past_bound, 0);
        assert!(r.latency_ms.max < 20.0 + 30.0);
    }

    #[test]
    fn an_input_left_by_a_frame_is_past_the_bound() {
        let t0 = Instant::now();
        let ms = |m: u64| t0 + Duration::from_millis(m);
        let mut p = Perf::default();
        p.begin_frame(1, ms(0), 0.0);
        p.end_frame(ms(4));
        // due at 5 ms; frame 2 starts at 10 ms without it, frame 3 applies it
        p.begin_frame(2, ms(10), 0.01);
        p.end_frame(ms(12));
        p.begin_frame(3, ms(20), 0.02);
        p.input(ms(5));
        p.end_frame(ms(22));
        p.begin_frame(4, ms(30), 0.03);
        p.end_frame(ms(31));
        let r = p.report();
        assert_eq!(r.inputs_past_bound, 1);
        // 25 ms, more than frame 1's period (10) plus frame 3's (10)
        assert!((r.latency_ms.max - 25.0).abs() < 1e-6);
    }
}
