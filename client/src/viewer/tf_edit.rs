//! The viewer's transfer-function editor: the points of the function (position over the
//! normalized scalar, colour, extinction) edited in the side panel, presets, and loading and
//! saving the JSON file `--tf FILE.json` reads (`{"name": …, "points": [{"s", "rgb",
//! "extinction"}, …]}`).

use eframe::egui;
use std::path::Path;
use tetwave_render::transfer::{TfPoint, TransferFunction};

/// Writes `tf` as the JSON `TransferFunction::load` reads; refuses an invalid function.
pub fn save(tf: &TransferFunction, path: &Path) -> Result<(), String> {
    tf.validate().map_err(|e| e.to_string())?;
    let text = serde_json::to_string_pretty(tf).map_err(|e| e.to_string())?;
    std::fs::write(path, text + "\n").map_err(|e| format!("{}: {e}", path.display()))
}

/// The editor's widgets for `tf`; returns whether the function changed (and is valid).
pub fn edit(ui: &mut egui::Ui, tf: &mut TransferFunction) -> bool {
    let mut edited = tf.clone();
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
            ui.color_edit_button_rgb(&mut p.rgb);
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
