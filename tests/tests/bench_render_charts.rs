//! `tetwave-bench progressive --render-every` on a store the server prepared, then
//! `scripts/charts.py` and `scripts/progressive-table.py` on its JSON lines: every run carries its
//! drawn frames (render ms, PSNR against the full-resolution reference), the chart script turns them
//! into SVG charts and the table script prints the memory per tet by part.
//! Needs `python3` and the venv `.venv` with matplotlib (both from `scripts/setup`); fails if they
//! cannot run.

mod common;

use std::process::Command;
use tetwave_client::progressive::bench;

#[test]
fn render_every_feeds_the_charts() {
    let (d, store) = common::harmonic_store(3);
    let args = common::bench_args(&[
        "--store",
        store.to_str().unwrap(),
        "--steps",
        "12",
        "--per-step",
        "40",
        "--width",
        "40",
        "--height",
        "40",
        "--tol",
        "50%,10%",
        "--simple",
        "--render-every",
        "5",
        "--render-cpu",
    ]);
    let mut lines = String::new();
    let runs = bench(&args, |r| {
        // tagged as `scripts/bench-progressive` tags its runs
        let json = serde_json::to_string(r).unwrap();
        lines += &json.replacen('{', "{\"store\":\"s\",\"run\":\"l5\",", 1);
        lines.push('\n');
    })
    .unwrap();
    assert_eq!(runs.len(), 3);
    for r in &runs {
        let s = r.render.as_ref().expect("drawn");
        let steps: Vec<usize> = s.frames.iter().map(|f| f.step).collect();
        assert_eq!(steps, [0, 5, 10, 11], "{}", r.tol);
        assert!(s.frames.iter().all(|f| f.psnr_db.is_finite() && f.ms > 0.0));
        let fps = r.fps.unwrap();
        assert!((fps - 1e3 / (r.avg_refine_ms + s.avg_ms)).abs() < 1e-9);
    }
    // the simple run ends on the full-resolution mesh: its last image is the reference's
    let simple = runs[2].render.as_ref().unwrap();
    assert!(simple.frames.last().unwrap().psnr_db >= 60.0);
    let jsonl = d.path().join("runs.jsonl");
    std::fs::write(&jsonl, lines).unwrap();
    let charts = d.path().join("charts");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../scripts/charts.py");
    let python = concat!(env!("CARGO_MANIFEST_DIR"), "/../.venv/bin/python");
    let out = Command::new(python)
        .args([script, "progressive"])
        .arg(&jsonl)
        .arg(&charts)
        .output()
        .unwrap_or_else(|e| panic!("{python} cannot run ({e}); scripts/setup creates it"));
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    // one point per tolerance, or per drawn frame of every run
    for (name, points) in [
        ("progressive-psnr-vs-frame-ms.svg", 3),
        ("progressive-psnr-by-step.svg", 12),
    ] {
        let svg = std::fs::read_to_string(charts.join(name)).unwrap();
        assert!(svg.contains("<svg") && svg.trim_end().ends_with("</svg>"));
        let line = log
            .lines()
            .find(|l| l.contains(name))
            .unwrap_or_else(|| panic!("no report of {name}:\n{log}"));
        assert!(line.contains(&format!(": {points} points in ")), "{line}");
    }

    // the memory table: mesh, buffer and selector bytes per average tet, and their sum
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../scripts/progressive-table.py"
    );
    let out = Command::new("python3")
        .arg(script)
        .arg(&jsonl)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let memory = &text[text
        .find("Memory per average leaf tet")
        .expect("memory table")..];
    let row = memory
        .lines()
        .find(|l| l.starts_with("| simple (all arrived) | l5 |"))
        .unwrap_or_else(|| panic!("no memory row for the simple run:\n{text}"));
    let cells: Vec<f64> = row
        .split('|')
        .skip(3)
        .take(4)
        .map(|c| c.trim().parse().unwrap())
        .collect();
    let r = &runs[2];
    let per_tet = |mb: f64| mb * 1e6 / r.avg_tets;
    let want = [
        per_tet(r.mesh_mb),
        per_tet(r.mb - r.mesh_mb),
        per_tet(r.sel_mb),
        per_tet(r.mb + r.sel_mb),
    ];
    for (have, want) in cells.iter().zip(want) {
        assert!(
            (have - want).abs() <= 0.051,
            "{row}: {have} against {want:.2}"
        );
    }
}
