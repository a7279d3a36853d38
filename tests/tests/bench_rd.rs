//! `scripts/bench-rd --quick` end to end: 9³ grids of both fields at one bound, prepared, verified
//! and streamed by the workspace's binaries, next to zfp and SZ3 from PyPI, and the image part (a
//! 64×64 default view, streams without and with a preview, and SZ3, at two bounds). Checks the table has a row per codec with finite figures within the bound
//! and the charts were drawn. Needs the binaries `tetwave-server` and `tetwave` beside this test's
//! target directory (`cargo test --workspace` builds them), python3 and PyPI (the script installs
//! numpy, zfpy, pysz, scikit-fem and matplotlib into `.venv`): fails, never skips, without them.

use std::path::PathBuf;
use std::process::Command;

/// The directory holding the workspace's binaries of this build (`target/<profile>`).
fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    // target/<profile>/deps/bench_rd-HASH
    let dir = exe.parent().and_then(|d| d.parent()).unwrap().to_path_buf();
    for b in ["tetwave-server", "tetwave"] {
        assert!(
            dir.join(b).is_file(),
            "{} is missing: build it with `cargo build -p tetwave-server -p tetwave-client --bins` \
             (`cargo test --workspace` builds it)",
            dir.join(b).display()
        );
    }
    dir
}

#[test]
fn quick_run_measures_every_codec() {
    let bins = bin_dir();
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("rd");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../scripts/bench-rd");
    let t0 = std::time::Instant::now();
    let run = Command::new("bash")
        .arg(script)
        .args(["--quick", "--out"])
        .arg(&out)
        .env("TETWAVE_BIN_DIR", &bins)
        .output()
        .unwrap_or_else(|e| panic!("bash {script} cannot run: {e}"));
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "bench-rd failed:\n{log}");
    eprintln!("bench-rd --quick: {:.1} s", t0.elapsed().as_secs_f64());

    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("rd.json")).unwrap()).unwrap();
    let rows = json["rows"].as_array().unwrap();
    let codecs = ["tetwave stream", "tetwave store", "zfp", "SZ3"];
    assert_eq!(rows.len(), 2 * codecs.len(), "{rows:#?}");
    for (i, r) in rows.iter().enumerate() {
        assert_eq!(r["field"], ["harmonic", "fem"][i / 4], "{r}");
        assert_eq!(r["codec"], codecs[i % 4], "{r}");
        assert_eq!(r["grid"], "9^3");
        assert_eq!(r["raw_f32_bytes"], 9 * 9 * 9 * 4);
        let num = |k: &str| {
            r[k].as_f64()
                .filter(|x| x.is_finite())
                .unwrap_or_else(|| panic!("{k} not a finite number in {r}"))
        };
        assert!(num("bytes") > 0.0);
        assert!(num("psnr_db") > 20.0, "{r}");
        // every codec keeps the absolute bound (f32 arithmetic: a hair over at most)
        assert!(
            num("max_abs_error") <= num("abs_bound") * (1.0 + 1e-4),
            "{r}"
        );
    }
    // the stream carries at least the store's streamable bytes, and its tetwave frames are
    // part of what TCP delivered
    for pair in rows.chunks(4) {
        let wire = pair[0]["bytes"].as_u64().unwrap();
        let frames = pair[0]["message_bytes"].as_u64().unwrap();
        assert!(frames < wire, "{}", pair[0]);
        assert!(pair[0]["connections"] == 1, "{}", pair[0]);
    }

    // the markdown table: a row per codec, numbers in every cell
    let md = std::fs::read_to_string(out.join("rd.md")).unwrap();
    for field in ["harmonic", "fem"] {
        for codec in codecs {
            let row = md
                .lines()
                .find(|l| l.starts_with(&format!("| {field} | 9^3 | 1e-3 | {codec} |")))
                .unwrap_or_else(|| panic!("no row for {field} {codec}:\n{md}"));
            let cells: Vec<&str> = row.split('|').map(str::trim).collect();
            for c in &cells[5..10] {
                let v: f64 = c
                    .replace(',', "")
                    .parse()
                    .unwrap_or_else(|_| panic!("{row}"));
                assert!(v.is_finite(), "{row}");
            }
        }
    }

    // the image part: one stream per image bound (frames as bytes arrive), SZ3 at each, and the
    // two points read off them
    let image = &json["image"];
    let streams = image["streams"].as_array().unwrap();
    let sz3 = image["sz3"].as_array().unwrap();
    // each bound without and with a preview
    assert_eq!(streams.len(), 4, "{image}");
    for (i, s) in streams.iter().enumerate() {
        assert_eq!(s["preview"].as_str(), [None, Some("10%")][i % 2], "{s}");
        assert_eq!(s["preview_bytes"].as_u64().unwrap() > 0, i % 2 == 1, "{s}");
    }
    assert_eq!(sz3.len(), 2, "{image}");
    let mut all = Vec::new();
    for s in streams {
        let frames = s["frames"].as_array().unwrap();
        assert!(frames.len() >= 2, "{s}");
        assert!(
            frames.last().unwrap()["image_psnr_db"].as_f64().unwrap() > 20.0,
            "{s}"
        );
        let bytes: Vec<u64> = frames
            .iter()
            .map(|f| f["bytes_received"].as_u64().unwrap())
            .collect();
        assert!(bytes.windows(2).all(|w| w[0] <= w[1]), "{bytes:?}");
        all.extend(frames.iter().map(|f| {
            (
                f["bytes_received"].as_u64().unwrap(),
                f["image_psnr_db"].as_f64().unwrap(),
            )
        }));
    }
    for z in sz3 {
        assert!(z["image_psnr_db"].as_f64().unwrap() > 20.0, "{z}");
    }
    // the read-off points are the cheapest frames over every stream that pass each bar
    let target = sz3[0]["image_psnr_db"].as_f64().unwrap();
    for (key, bar) in [("reaches_sz3", target), ("usable_30db", 30.0)] {
        let cheapest = all.iter().filter(|f| f.1 >= bar).map(|f| f.0).min();
        assert_eq!(
            image[key]["bytes_received"].as_u64(),
            cheapest,
            "{key}: {image}"
        );
    }
    for name in [
        "rd-harmonic-l3.svg",
        "rd-fem-l3.svg",
        "image-psnr-vs-bytes.svg",
    ] {
        let svg = std::fs::read_to_string(out.join(name)).unwrap();
        assert!(svg.contains("<svg"), "{name}");
        assert!(
            log.contains(&format!("{name}: ")),
            "{name} not reported:\n{log}"
        );
    }
}
