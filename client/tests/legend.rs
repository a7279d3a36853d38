//! `tetwave render --legend`: the image, then a strip with the transfer function's colours across
//! the value range and the scalar's name and range written in it (checked by drawing the expected
//! text the same way: a wrong name or range gives other pixels).

use std::path::Path;
use std::process::Command;
use tetwave_client::legend::{
    draw_text, legend_text, BAR_ROWS, LEGEND_HEIGHT, MARGIN, TEXT_PX, TEXT_TOP,
};
use tetwave_render::image_metrics::Rgba8Image;
use tetwave_render::transfer::TransferFunction;
use tetwave_server::prepare::{prepare, PrepareOptions};

fn render(store: &Path, out: &Path, legend: bool) -> serde_json::Value {
    let mut c = Command::new(env!("CARGO_BIN_EXE_tetwave"));
    c.arg("render")
        .arg(store)
        .args(["--reference", "--size", "240x60", "--json", "-o"])
        .arg(out);
    if legend {
        c.arg("--legend");
    }
    let o = c.output().expect("tetwave runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).expect("one JSON object")
}

/// The rows `y0..y1` of `img`.
fn rows(img: &Rgba8Image, y0: u32, y1: u32) -> &[[u8; 4]] {
    &img.pixels[(y0 * img.width) as usize..(y1 * img.width) as usize]
}

#[test]
fn render_legend_draws_the_colours_the_name_and_the_range() {
    let d = tempfile::tempdir().unwrap();
    let s = d.path().join("harmonic");
    let mut o = PrepareOptions::new("synthetic:harmonic", &s);
    o.levels = Some(2);
    prepare(&o).unwrap();
    let (plain, with) = (d.path().join("plain.png"), d.path().join("legend.png"));
    render(&s, &plain, false);
    let r = render(&s, &with, true);
    let plain = Rgba8Image::load_png(&plain).unwrap();
    let img = Rgba8Image::load_png(&with).unwrap();
    assert_eq!((img.width, img.height), (240, 60 + LEGEND_HEIGHT));
    // the volume is drawn as without the legend
    assert!(rows(&img, 0, 60) == plain.pixels.as_slice());
    // the colour bar: the transfer function's colour at each column's place in the range (the
    // one drawn with: `auto`, the default preset fitted to the store's values)
    let tf: TransferFunction = serde_json::from_value(r["tf"].clone()).unwrap();
    assert_eq!(tf.name, "auto");
    let bar = 240 - 2 * MARGIN;
    for x in [0, bar / 3, bar - 1] {
        let (rgb, _) = tf.eval(x as f64 / (bar - 1) as f64);
        let want = rgb.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8);
        let got = img.pixels[((60 + BAR_ROWS.start + 2) * 240 + MARGIN + x) as usize];
        assert_eq!(got[..3], want, "column {x}");
    }
    // the text: the dataset's name and the value range, as drawn on black
    let range = [
        r["value_range"][0].as_f64().unwrap() as f32,
        r["value_range"][1].as_f64().unwrap() as f32,
    ];
    let text_rows = (60 + TEXT_TOP, 60 + TEXT_TOP + TEXT_PX as u32 + 4);
    let strip = |text: &str| {
        let mut blank = Rgba8Image {
            width: 240,
            height: 60 + LEGEND_HEIGHT,
            pixels: vec![[0, 0, 0, 255]; (240 * (60 + LEGEND_HEIGHT)) as usize],
        };
        draw_text(&mut blank, MARGIN, 60 + TEXT_TOP, text);
        rows(&blank, text_rows.0, text_rows.1).to_vec()
    };
    let drawn = rows(&img, text_rows.0, text_rows.1);
    assert!(drawn.iter().any(|p| p[0] > 128), "no text drawn");
    assert!(drawn == strip(&legend_text("harmonic", range)).as_slice());
    assert!(drawn != strip(&legend_text("harmonics", range)).as_slice());
    assert!(drawn != strip(&legend_text("harmonic", [range[0], range[1] + 0.5])).as_slice());
}

/// A volume file drawn as it is with `--legend`: reported as a volume with its world (LPS, mm,
/// origin), its image's edges labelled with the anatomical directions the default view's edges
/// face (screen right is mostly posterior, then right: `PR`; up is superior, then right: `SR`),
/// the labels drawn near the edges' middles and nowhere else.
#[test]
fn render_labels_a_volume_files_edges_with_its_directions() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("ct.nrrd");
    let (nx, ny, nz) = (6, 5, 4);
    let mut bytes = format!(
        "NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n\
         sizes: {nx} {ny} {nz}\nspace directions: (1,0,0) (0,1,0) (0,0,1.5)\n\
         space origin: (-3,-2,5)\nspace units: \"mm\" \"mm\" \"mm\"\nendian: little\n\
         encoding: raw\n\n"
    )
    .into_bytes();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let v = (100 * i + 40 * j - 30 * k) as i16;
                bytes.extend(v.to_le_bytes());
            }
        }
    }
    std::fs::write(&path, bytes).unwrap();
    let (plain, with) = (d.path().join("plain.png"), d.path().join("legend.png"));
    let r = render(&path, &plain, false);
    assert_eq!(r["input"], "volume");
    assert_eq!(r["tets"], 6 * 5 * 4 * 3);
    assert!(r["orientation"].is_null(), "labels only with --legend");
    let r = render(&path, &with, true);
    assert_eq!(r["volume"]["format"], "NRRD");
    assert_eq!(r["volume"]["dims"], serde_json::json!([6, 5, 4]));
    assert_eq!(r["volume"]["frame"], "LPS");
    assert_eq!(r["volume"]["length_unit"], "mm");
    assert_eq!(r["volume"]["origin"], serde_json::json!([-3.0, -2.0, 5.0]));
    assert_eq!(
        r["orientation"],
        serde_json::json!(["AL", "PR", "SR", "IL"])
    );
    let plain = Rgba8Image::load_png(&plain).unwrap();
    let img = Rgba8Image::load_png(&with).unwrap();
    let (w, h) = (240u32, 60u32);
    let mut changed = 0;
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            if img.pixels[i] != plain.pixels[i] {
                changed += 1;
                // within a label's box: at the middle of an edge
                let near_side = (x < 40 || x >= w - 40) && (y as i32 - 30).abs() <= 14;
                let near_top_bottom = (x as i32 - 120).abs() <= 20 && (y < 22 || y >= h - 22);
                assert!(near_side || near_top_bottom, "pixel {x},{y} changed");
            }
        }
    }
    assert!(changed > 20, "{changed} pixels of labels");
}
