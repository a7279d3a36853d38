//! The viewer's transfer-function editor: the points of the function (position over the
//! normalized scalar, colour, extinction) edited in the side panel, presets, and loading and
//! saving the JSON file `--tf FILE.json` reads (`{"name": …, "points": [{"s", "rgb",
//! "extinction"}, …]}`).
//!
//! Above the table, a canvas draws the histogram of the values held (the leaf mesh's vertices,
//! over the normalized scalar) behind the extinction curve; its points, in their colours, are
//! dragged with the mouse (x: position, y: extinction). The mappings between the canvas and the
//! function are the pure functions [`histogram`], [`to_canvas`], [`from_canvas`] and
//! [`point_at`].

use eframe::egui::{self, Color32, Pos2, Rect, Sense, Stroke};
use std::path::Path;
use tetwave_render::transfer::{TfPoint, TransferFunction};

/// Why a transfer function could not be saved.
#[derive(Debug, thiserror::Error)]
pub enum SaveError {
    #[error(transparent)]
    Invalid(#[from] tetwave_render::transfer::TfError),
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    #[error("{path}: {source}")]
    Write {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
}

/// Writes `tf` as the JSON `TransferFunction::load` reads; refuses an invalid function.
pub fn save(tf: &TransferFunction, path: &Path) -> Result<(), SaveError> {
    tf.validate()?;
    let text = serde_json::to_string_pretty(tf)?;
    std::fs::write(path, text + "\n").map_err(|source| SaveError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// Counts of `values` in `bins` equal bins over `range` (mapped to `[0, 1]` as the transfer
/// function sees them: values outside are clamped into the end bins, NaNs left out). An empty
/// or reversed range puts every value in the first bin.
pub fn histogram(values: &[f32], range: [f32; 2], bins: usize) -> Vec<u32> {
    let mut h = vec![0u32; bins.max(1)];
    let n = h.len();
    let span = range[1] - range[0];
    for &v in values {
        if v.is_nan() {
            continue;
        }
        let s = if span > 0.0 {
            (v - range[0]) / span
        } else {
            0.0
        };
        h[((s * n as f32) as isize).clamp(0, n as isize - 1) as usize] += 1;
    }
    h
}

/// The extinction at the top of the canvas: a margin above the largest point's, at least 1.
pub fn canvas_scale(tf: &TransferFunction) -> f32 {
    tf.points
        .iter()
        .map(|p| p.extinction)
        .fold(1.0f32, f32::max)
        * 1.25
}

/// Where a point `(s, extinction)` is drawn on `rect`: s left to right, extinction 0 at the
/// bottom to `scale` at the top.
pub fn to_canvas(s: f32, extinction: f32, rect: Rect, scale: f32) -> Pos2 {
    Pos2::new(
        rect.left() + s * rect.width(),
        rect.bottom() - extinction / scale * rect.height(),
    )
}

/// The `(s, extinction)` under `pos` (the inverse of [`to_canvas`]), clamped to the canvas:
/// `s` in `[0, 1]`, extinction in `[0, scale]`.
pub fn from_canvas(pos: Pos2, rect: Rect, scale: f32) -> (f32, f32) {
    let s = ((pos.x - rect.left()) / rect.width().max(1e-6)).clamp(0.0, 1.0);
    let e = ((rect.bottom() - pos.y) / rect.height().max(1e-6)).clamp(0.0, 1.0) * scale;
    (s, e)
}

/// The point drawn nearest to `pos` within `radius`, if any.
pub fn point_at(
    tf: &TransferFunction,
    pos: Pos2,
    rect: Rect,
    scale: f32,
    radius: f32,
) -> Option<usize> {
    tf.points
        .iter()
        .enumerate()
        .map(|(i, p)| (i, to_canvas(p.s, p.extinction, rect, scale).distance(pos)))
        .filter(|(_, d)| *d <= radius)
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Moves point `i` to the canvas position `pos`, keeping the points ordered: it stays between
/// its neighbours' positions. Returns its new `(s, extinction)`.
pub fn drag_point(
    tf: &mut TransferFunction,
    i: usize,
    pos: Pos2,
    rect: Rect,
    scale: f32,
) -> (f32, f32) {
    let (s, e) = from_canvas(pos, rect, scale);
    let lo = if i > 0 { tf.points[i - 1].s } else { 0.0 };
    let hi = tf.points.get(i + 1).map_or(1.0, |p| p.s);
    let p = &mut tf.points[i];
    p.s = s.clamp(lo, hi);
    p.extinction = e;
    (p.s, p.extinction)
}

/// Canvas state kept between frames: the point being dragged and the scale when it was
/// picked (the scale follows the points only between drags, so a drag does not rescale under
/// the mouse).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CanvasState {
    pub dragging: Option<(usize, f32)>,
    /// Where the canvas was drawn last, in points.
    pub rect: Option<Rect>,
}

/// Height of the canvas, in points.
const CANVAS_HEIGHT: f32 = 110.0;
/// Distance within which a press picks a point, in points.
const PICK_RADIUS: f32 = 8.0;

/// The canvas: histogram, curve, draggable points. Returns whether the function changed.
fn canvas(
    ui: &mut egui::Ui,
    tf: &mut TransferFunction,
    hist: &[u32],
    state: &mut CanvasState,
) -> bool {
    let width = ui.available_width().max(60.0);
    let (rect, resp) = ui.allocate_exact_size(egui::vec2(width, CANVAS_HEIGHT), Sense::drag());
    state.rect = Some(rect);
    let scale = state.dragging.map_or_else(|| canvas_scale(tf), |(_, s)| s);
    let mut changed = false;
    if resp.drag_started() {
        state.dragging = resp
            .interact_pointer_pos()
            .and_then(|p| point_at(tf, p, rect, scale, PICK_RADIUS))
            .map(|i| (i, scale));
    }
    if let (Some((i, sc)), Some(p)) = (state.dragging, resp.interact_pointer_pos()) {
        if resp.dragged() && i < tf.points.len() {
            let before = tf.points[i];
            drag_point(tf, i, p, rect, sc);
            changed = tf.points[i] != before;
        }
    }
    if resp.drag_stopped() || !resp.dragged() {
        state.dragging = None;
    }
    let painter = ui.painter_at(rect);
    painter.rect_filled(rect, 0.0, Color32::from_gray(20));
    // the histogram, on a log scale (a few bins hold most vertices)
    let top = hist.iter().copied().max().unwrap_or(0);
    if top > 0 {
        let bw = rect.width() / hist.len() as f32;
        let lt = (top as f32 + 1.0).ln();
        for (k, &c) in hist.iter().enumerate() {
            if c == 0 {
                continue;
            }
            let h = (c as f32 + 1.0).ln() / lt * rect.height();
            let x = rect.left() + k as f32 * bw;
            painter.rect_filled(
                Rect::from_min_max(
                    Pos2::new(x, rect.bottom() - h),
                    Pos2::new(x + bw, rect.bottom()),
                ),
                0.0,
                Color32::from_gray(70),
            );
        }
    }
    let pts: Vec<Pos2> = tf
        .points
        .iter()
        .map(|p| to_canvas(p.s, p.extinction, rect, scale))
        .collect();
    // the function is constant beyond its end points
    let mut line = vec![Pos2::new(rect.left(), pts[0].y)];
    line.extend(&pts);
    line.push(Pos2::new(rect.right(), pts[pts.len() - 1].y));
    painter.add(egui::Shape::line(line, Stroke::new(1.5, Color32::WHITE)));
    for (p, q) in tf.points.iter().zip(&pts) {
        let c = Color32::from_rgb(
            (p.rgb[0].clamp(0.0, 1.0) * 255.0) as u8,
            (p.rgb[1].clamp(0.0, 1.0) * 255.0) as u8,
            (p.rgb[2].clamp(0.0, 1.0) * 255.0) as u8,
        );
        painter.circle(*q, 5.0, c, Stroke::new(1.0, Color32::WHITE));
    }
    changed
}

/// The editor's widgets for `tf` (`hist`: the histogram of the values held); returns whether
/// the function changed (and is valid).
pub fn edit(
    ui: &mut egui::Ui,
    tf: &mut TransferFunction,
    hist: &[u32],
    state: &mut CanvasState,
) -> bool {
    let mut edited = tf.clone();
    if !edited.points.is_empty() {
        canvas(ui, &mut edited, hist, state);
    }
    let mut remove = None;
    egui::Grid::new("tf-points").num_columns(4).show(ui, |ui| {
        ui.label("s");
        ui.label("colour");
        ui.label("extinction");
        ui.label("");
        ui.end_row();
        let n = edited.points.len();
        for (i, p) in edited.points.iter_mut().enumerate() {
            ui.add(egui::DragValue::new(&mut p.s).speed(0.005).range(0.0..=1.0));
            // egui's colour button converts the colour for display and back, which moves it by
            // a rounding error: take its value only when the user changed it
            let mut rgb = p.rgb;
            if ui.color_edit_button_rgb(&mut rgb).changed() {
                p.rgb = rgb;
            }
            ui.add(
                egui::DragValue::new(&mut p.extinction)
                    .speed(0.05)
                    .range(0.0..=1000.0),
            );
            // a function keeps at least one point
            if ui.add_enabled(n > 1, egui::Button::new("−")).clicked() {
                remove = Some(i);
            }
            ui.end_row();
        }
    });
    if let Some(i) = remove {
        edited.points.remove(i);
    }
    if ui.button("add point").clicked() {
        add_point(&mut edited);
    }
    // positions stay ordered: a point dragged past its neighbour swaps with it
    edited.points.sort_by(|a, b| a.s.total_cmp(&b.s));
    if edited != *tf && edited.validate().is_ok() {
        if edited.name == tf.name && !edited.name.ends_with(" (edited)") {
            edited.name = format!("{} (edited)", edited.name);
        }
        *tf = edited;
        true
    } else {
        false
    }
}

/// Adds a point halfway between the two neighbours farthest apart (beside a lone point, one at
/// the other end of the range).
fn add_point(tf: &mut TransferFunction) {
    let pts = &tf.points;
    if pts.len() < 2 {
        let only = pts.first().copied().unwrap_or(TfPoint {
            s: 0.0,
            rgb: [1.0; 3],
            extinction: 1.0,
        });
        tf.points.push(TfPoint {
            s: if only.s < 0.5 { 1.0 } else { 0.0 },
            ..only
        });
        return;
    }
    let k = (1..pts.len())
        .max_by(|&a, &b| (pts[a].s - pts[a - 1].s).total_cmp(&(pts[b].s - pts[b - 1].s)))
        .unwrap_or(1);
    let (a, b) = (pts[k - 1], pts[k]);
    tf.points.insert(
        k,
        TfPoint {
            s: 0.5 * (a.s + b.s),
            rgb: [0, 1, 2].map(|c| 0.5 * (a.rgb[c] + b.rgb[c])),
            extinction: 0.5 * (a.extinction + b.extinction),
        },
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_bins_the_normalized_values() {
        let v = [0.0, 0.1, 0.24, 0.25, 0.5, 0.99, 1.0, -3.0, 7.0, f32::NAN];
        assert_eq!(histogram(&v, [0.0, 1.0], 4), vec![4, 1, 1, 3]);
        // an offset range
        assert_eq!(
            histogram(&[10.0, 12.5, 15.0, 19.9], [10.0, 20.0], 2),
            vec![2, 2]
        );
        // an empty range: everything in the first bin
        assert_eq!(histogram(&[5.0, 5.0], [5.0, 5.0], 3), vec![2, 0, 0]);
        let h = histogram(
            &(0..1000).map(|i| i as f32).collect::<Vec<_>>(),
            [0.0, 999.0],
            10,
        );
        assert_eq!(h.iter().sum::<u32>(), 1000);
        assert!(h.iter().all(|&c| (99..=101).contains(&c)), "{h:?}");
    }

    fn rect() -> Rect {
        Rect::from_min_size(Pos2::new(10.0, 20.0), egui::vec2(200.0, 100.0))
    }

    #[test]
    fn canvas_mapping_round_trips_and_clamps() {
        let r = rect();
        let p = to_canvas(0.25, 3.0, r, 4.0);
        assert_eq!(p, Pos2::new(60.0, 45.0));
        let (s, e) = from_canvas(p, r, 4.0);
        assert!((s - 0.25).abs() < 1e-6 && (e - 3.0).abs() < 1e-5, "{s} {e}");
        assert_eq!(from_canvas(Pos2::new(-50.0, 500.0), r, 4.0), (0.0, 0.0));
        assert_eq!(from_canvas(Pos2::new(500.0, -50.0), r, 4.0), (1.0, 4.0));
    }

    #[test]
    fn dragging_a_point_moves_it_between_its_neighbours() {
        let r = rect();
        let mut tf = TransferFunction::preset("default").unwrap();
        assert!(tf.points.len() >= 3, "{tf:?}");
        let scale = canvas_scale(&tf);
        let i = 1;
        let at = to_canvas(tf.points[i].s, tf.points[i].extinction, r, scale);
        // a press near the point picks it, one far from every point none
        assert_eq!(
            point_at(&tf, at + egui::vec2(3.0, -2.0), r, scale, 8.0),
            Some(i)
        );
        assert_eq!(
            point_at(&tf, Pos2::new(-100.0, -100.0), r, scale, 8.0),
            None
        );
        // dragged up and a little to the right: more extinction, a larger position
        let (lo, hi) = (tf.points[i - 1].s, tf.points[i + 1].s);
        let target = Pos2::new(
            at.x + 0.1 * (hi - tf.points[i].s) * r.width(),
            r.top() + 10.0,
        );
        let (s, e) = drag_point(&mut tf, i, target, r, scale);
        assert!(s > lo && s < hi, "{s}");
        assert!((e - 0.9 * scale).abs() < 1e-4, "{e}");
        assert_eq!((tf.points[i].s, tf.points[i].extinction), (s, e));
        tf.validate().unwrap();
        // dragged past the next point: stops at it, the order is kept
        drag_point(
            &mut tf,
            i,
            Pos2::new(r.right() + 50.0, r.bottom()),
            r,
            scale,
        );
        assert_eq!(tf.points[i].s, hi);
        assert_eq!(tf.points[i].extinction, 0.0);
        assert!(tf.points.windows(2).all(|w| w[0].s <= w[1].s));
    }

    #[test]
    fn saved_json_loads_back_equal() {
        let d = tempfile::tempdir().unwrap();
        for name in ["default", "transparent", "opaque", "shells"] {
            let mut tf = TransferFunction::preset(name).unwrap();
            tf.points[0].rgb = [0.25, 0.5, 0.75];
            tf.points[0].extinction = 3.5;
            let p = d.path().join(format!("{name}.json"));
            save(&tf, &p).unwrap();
            let back = TransferFunction::load(p.to_str().unwrap()).unwrap();
            assert_eq!(back, tf, "{name}");
        }
    }

    #[test]
    fn added_points_keep_the_function_valid() {
        let mut tf = TransferFunction::preset("default").unwrap();
        tf.points.truncate(1);
        for _ in 0..5 {
            add_point(&mut tf);
            tf.validate().unwrap();
        }
        assert_eq!(tf.points.len(), 6);
    }

    #[test]
    fn an_invalid_function_is_not_saved() {
        let d = tempfile::tempdir().unwrap();
        let mut tf = TransferFunction::preset("default").unwrap();
        tf.points[0].extinction = -1.0;
        let p = d.path().join("bad.json");
        assert!(save(&tf, &p).is_err());
        assert!(!p.exists());
    }
}

#[cfg(test)]
mod ui_tests {
    use super::*;

    /// The editor drawn with no input changes nothing (a widget that rounds a value on display
    /// would mark every function edited).
    #[test]
    fn drawing_the_editor_changes_nothing() {
        let ctx = egui::Context::default();
        for name in ["default", "transparent", "opaque", "shells"] {
            let mut tf = TransferFunction::preset(name).unwrap();
            let before = tf.clone();
            let mut state = CanvasState::default();
            let mut changed = false;
            for _ in 0..3 {
                let mut out = ctx.run_ui(egui::RawInput::default(), |ui| {
                    changed |= edit(ui, &mut tf, &[1, 5, 2], &mut state);
                });
                // no renderer takes the font textures here
                out.textures_delta.clear();
            }
            assert!(!changed, "{name}: {before:?} became {tf:?}");
            assert_eq!(tf, before, "{name}");
        }
    }

    /// A press on a point of the canvas and a drag up and to the right move that point: its
    /// extinction and position grow by what the mouse moved, the others stay.
    #[test]
    fn dragging_on_the_canvas_moves_the_point() {
        let ctx = egui::Context::default();
        let mut tf = TransferFunction::preset("default").unwrap();
        let before = tf.clone();
        let mut state = CanvasState::default();
        let frame = |events: Vec<egui::Event>, tf: &mut TransferFunction, st: &mut CanvasState| {
            let input = egui::RawInput {
                events,
                screen_rect: Some(Rect::from_min_size(Pos2::ZERO, egui::vec2(400.0, 600.0))),
                ..Default::default()
            };
            let mut changed = false;
            let mut out = ctx.run_ui(input, |ui| changed |= edit(ui, tf, &[], st));
            out.textures_delta.clear();
            changed
        };
        frame(vec![], &mut tf, &mut state);
        let rect = state.rect.expect("the canvas was drawn");
        let scale = canvas_scale(&tf);
        let i = 2;
        let at = to_canvas(tf.points[i].s, tf.points[i].extinction, rect, scale);
        let press = |pos, pressed| egui::Event::PointerButton {
            pos,
            button: egui::PointerButton::Primary,
            pressed,
            modifiers: Default::default(),
        };
        let to = at + egui::vec2(10.0, -40.0);
        let mut changed = frame(
            vec![egui::Event::PointerMoved(at), press(at, true)],
            &mut tf,
            &mut state,
        );
        for k in 1..=4 {
            let p = at + (to - at) * (k as f32 / 4.0);
            changed |= frame(vec![egui::Event::PointerMoved(p)], &mut tf, &mut state);
        }
        changed |= frame(vec![press(to, false)], &mut tf, &mut state);
        assert!(changed);
        let (s, e) = from_canvas(to, rect, scale);
        assert!(
            (tf.points[i].s - s).abs() < 1e-4,
            "{:?} vs {s}",
            tf.points[i]
        );
        assert!(
            (tf.points[i].extinction - e).abs() < 1e-3,
            "{:?} vs {e}",
            tf.points[i]
        );
        assert!(tf.points[i].extinction > before.points[i].extinction);
        for k in (0..tf.points.len()).filter(|&k| k != i) {
            assert_eq!(tf.points[k], before.points[k]);
        }
        assert_eq!(state.dragging, None, "released");
    }
}
