//! `tetwave view`, the interactive client, as a user runs it: a real window on an X server
//! (`xvfb-run`, which `scripts/setup` installs) drawn by lavapipe, streaming from a server on
//! loopback. A test that needs Xvfb fails, with the reason, when `xvfb-run` is missing: it never
//! skips. Every run is bounded (`timeout`, `--frames`).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_server::prepare::{prepare, PrepareOptions};
use tetwave_server::stream::{BackgroundServer, ServeConfig};

/// A server on 127.0.0.1, on any free port (in process, stopped when dropped).
fn serve(store: &Path) -> BackgroundServer {
    serve_with(store, "127.0.0.1:0", ServeConfig::default())
}

fn serve_with(store: &Path, addr: &str, config: ServeConfig) -> BackgroundServer {
    BackgroundServer::start(store, addr, config).expect("the store is served")
}

/// The default dataset (`synthetic:harmonic`) with `levels` levels, in `<dir>/s`.
fn store(levels: u8) -> (tempfile::TempDir, PathBuf) {
    let d = tempfile::tempdir().unwrap();
    let s = d.path().join("s");
    let mut o = PrepareOptions::new("synthetic:harmonic", &s);
    o.levels = Some(levels);
    prepare(&o).unwrap();
    (d, s)
}

fn xvfb_run() -> &'static str {
    let found = Command::new("sh")
        .args(["-c", "command -v xvfb-run"])
        .output()
        .is_ok_and(|o| o.status.success());
    assert!(
        found,
        "xvfb-run is missing: the viewer's window tests need Xvfb (scripts/setup installs the \
         xvfb and xauth packages; `apt-get install xvfb xauth`)"
    );
    "xvfb-run"
}

/// One Xvfb at a time: `xvfb-run -a` picks a free display number, racily when two start at once.
static XVFB: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// `tetwave view ARGS` in a 24-bit Xvfb screen, killed after `limit_s` seconds.
fn view_under_xvfb(args: &[&str], limit_s: u32) -> Output {
    let _one = XVFB.lock().unwrap_or_else(|e| e.into_inner());
    let out = Command::new("timeout")
        .arg(limit_s.to_string())
        .args([xvfb_run(), "-a", "-s", "-screen 0 1024x768x24"])
        .arg(env!("CARGO_BIN_EXE_tetwave"))
        .arg("view")
        .args(args)
        .output()
        .expect("timeout and xvfb-run run");
    eprintln!(
        "tetwave view {}: {}\nstderr:\n{}",
        args.join(" "),
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs `tetwave view` under Xvfb with `script` (written to `dir/script.json`), `args` and
/// `--json`; asserts it succeeded and returns its JSON report.
fn view_script(dir: &Path, script: &serde_json::Value, args: &[&str]) -> serde_json::Value {
    let sp = dir.join("script.json");
    std::fs::write(&sp, script.to_string()).unwrap();
    let mut all = args.to_vec();
    all.extend(["--script", sp.to_str().unwrap(), "--json"]);
    json_report(&view_under_xvfb(&all, 240))
}

/// The JSON report of a `tetwave view … --json` run, which must have succeeded.
fn json_report(out: &Output) -> serde_json::Value {
    assert!(out.status.success(), "tetwave view failed: {}", out.status);
    let stdout = String::from_utf8_lossy(&out.stdout);
    serde_json::from_str(stdout.trim()).expect(&stdout)
}

fn png(path: &Path) -> Rgba8Image {
    Rgba8Image::load_png(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `tetwave render STORE --tf TF` (the offscreen GPU renderer, full level) for an orbit camera:
/// `auto` for a view of a store or a mesh file, `default` for a view of a stream (their defaults).
fn offscreen(store: &Path, tf: &str, az: f64, el: f64, size: (u32, u32), out: &Path) -> Rgba8Image {
    let o = Command::new(env!("CARGO_BIN_EXE_tetwave"))
        .arg("render")
        .arg(store)
        .args(["--tf", tf])
        .args([format!("--azimuth={az}"), format!("--elevation={el}")])
        .args(["--size", &format!("{}x{}", size.0, size.1)])
        .arg("-o")
        .arg(out)
        .output()
        .expect("tetwave render runs");
    assert!(
        o.status.success(),
        "tetwave render: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    png(out)
}

/// `tetwave view STORE --frames 1` (a level-2 store) with the environment changed by `env`
/// (`None`: removed): its exit and its standard error.
fn view_once(env: &[(&str, Option<&str>)]) -> (Output, String) {
    let (_d, s) = store(2);
    let mut c = Command::new(env!("CARGO_BIN_EXE_tetwave"));
    c.arg("view").arg(&s).args(["--frames", "1"]);
    for (k, v) in env {
        match v {
            Some(v) => c.env(k, v),
            None => c.env_remove(k),
        };
    }
    let out = c.output().expect("tetwave runs");
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    (out, err)
}

#[test]
fn view_without_a_display_fails_with_one_clear_line() {
    let (out, err) = view_once(&[("DISPLAY", None), ("WAYLAND_DISPLAY", None)]);
    assert!(!out.status.success(), "no display yet success: {err}");
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    assert!(err.contains("no display"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn view_with_an_unreachable_display_fails_with_one_clear_line() {
    // no X server listens on display 987
    let (out, err) = view_once(&[("DISPLAY", Some(":987")), ("WAYLAND_DISPLAY", None)]);
    assert_eq!(out.status.code(), Some(1), "{err}");
    // the GPU driver may print its own lines first (Mesa's Vulkan WSI complains about an unset
    // XDG_RUNTIME_DIR); the viewer's own message is one line, the last
    let ours: Vec<&str> = err.lines().filter(|l| l.contains("viewer")).collect();
    assert_eq!(ours.len(), 1, "one line: {err}");
    assert_eq!(err.trim().lines().last(), Some(ours[0]), "{err}");
    assert!(
        ours[0].starts_with("error: cannot open the viewer's window"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn view_without_a_gpu_adapter_fails_with_one_clear_line() {
    // a display is set (none needs to listen: the adapter is looked for first), and the
    // Vulkan loader finds no driver
    let (out, err) = view_once(&[
        ("DISPLAY", Some(":987")),
        ("WGPU_BACKEND", Some("vulkan")),
        ("VK_ICD_FILENAMES", Some("/nonexistent/icd.json")),
        ("VK_DRIVER_FILES", Some("/nonexistent/icd.json")),
    ]);
    assert_eq!(out.status.code(), Some(1), "{err}");
    // wgpu logs the loader's own complaints first; the viewer's message is the last line
    let last = err.trim().lines().last().unwrap_or_default();
    assert!(
        last.starts_with("error: cannot start the viewer: no GPU adapter found"),
        "{err}"
    );
    assert_eq!(err.matches("cannot start the viewer").count(), 1, "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// The window opens on the default dataset streamed from a server on loopback; the script waits
/// for the whole stream, screenshots, asks the server for its image of the same view, orbits and
/// screenshots again. Each screenshot agrees with the offscreen renderer's image of the same mesh
/// and camera, the server's image with the client's render, and the orbit changed the frame.
#[test]
fn view_streams_orbits_and_matches_offscreen_and_server_images() {
    let (d, s) = store(3);
    let srv = serve(&s);
    let dir = d.path();
    let (a, b, server, last) = (
        dir.join("a.png"),
        dir.join("b.png"),
        dir.join("server.png"),
        dir.join("last.png"),
    );
    let script = serde_json::json!([
        {"mode": "complete"},
        {"wait": "complete"},
        {"screenshot": a},
        {"server_image": true},
        {"screenshot": server},
        {"orbit": 70},
        {"wait": "complete"},
        {"screenshot": b},
        {"quit": true}
    ]);
    let r = view_script(
        dir,
        &script,
        &[
            srv.url(),
            "--size",
            "256x224",
            "--screenshot",
            last.to_str().unwrap(),
            "--frames",
            "5000",
        ],
    );
    eprintln!("{r}");
    assert_eq!(r["complete"], true, "{r}");
    assert!(r["nodes_total"].as_u64().unwrap() > 0);
    assert_eq!(r["nodes"], r["nodes_total"]);
    assert!(r["bytes_received"].as_u64().unwrap() > 0);
    assert_eq!(r["script_steps"], serde_json::json!([9, 9]), "{r}");
    assert_eq!(r["view"], serde_json::json!([256, 224]), "{r}");
    assert_eq!(r["screenshots"].as_array().unwrap().len(), 4, "{r}");
    // a grid-like synthetic store has no outside: nothing to clip
    assert_eq!(r["clipped"], false, "{r}");
    let server_psnr = r["server_psnr_db"].as_f64().expect("a server image");
    assert!(
        server_psnr >= 40.0,
        "server image vs client render {server_psnr:.2} dB"
    );

    let (ia, ib, is) = (png(&a), png(&b), png(&server));
    assert_eq!((ia.width, ia.height), (256, 224));
    let ra = offscreen(
        &s,
        "default",
        35.0,
        25.0,
        (256, 224),
        &dir.join("ref_a.png"),
    );
    let rb = offscreen(
        &s,
        "default",
        105.0,
        25.0,
        (256, 224),
        &dir.join("ref_b.png"),
    );
    let (pa, pb, ps, pab) = (
        psnr(&ia, &ra),
        psnr(&ib, &rb),
        psnr(&is, &ia),
        psnr(&ia, &ib),
    );
    eprintln!(
        "window vs offscreen: {pa:.2} dB (azimuth 35), {pb:.2} dB (azimuth 105); \
         server image shown vs client view {ps:.2} dB; frame before vs after the orbit {pab:.2} dB"
    );
    assert!(pa >= 40.0, "screenshot vs offscreen render: {pa:.2} dB");
    assert!(
        pb >= 40.0,
        "screenshot after the orbit vs offscreen: {pb:.2} dB"
    );
    assert!(
        ps >= 40.0,
        "the server image as shown vs the client's: {ps:.2} dB"
    );
    // the orbit changes the frame: the two differ far beyond the agreement threshold, on many
    // pixels
    let changed = ia
        .pixels
        .iter()
        .zip(&ib.pixels)
        .filter(|(p, q)| (0..3).any(|k| p[k].abs_diff(q[k]) > 8))
        .count();
    eprintln!(
        "pixels changed by the orbit: {changed} of {}",
        ia.pixels.len()
    );
    assert!(
        pab < 36.0 && changed > ia.pixels.len() / 20,
        "the orbit should change the frame: {pab:.2} dB, {changed} pixels changed"
    );
    // not blank: the volume covers a good part of the view
    let lit = ia.pixels.iter().filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(lit > ia.pixels.len() / 10, "{lit} lit pixels");
    // `--screenshot` at the end: the last view, after the orbit
    assert!(psnr(&png(&last), &ib) >= 40.0);
}

/// A store of a non-convex mesh (the box without its corner `[0.4,1]³`, planes on no level of the
/// lattice) is drawn clipped to its domain in the window too: the viewer fetches the level set's
/// near band beside the stream, and from three views its screenshots leave empty the pixels that
/// `tetwave render` of the store (which clips with the whole level set) leaves empty, and agree
/// with those images.
#[test]
fn view_clips_a_nonconvex_store_to_its_domain() {
    let d = tempfile::tempdir().unwrap();
    let dir = d.path();
    let mesh = dir.join("notched.vtk");
    std::fs::write(&mesh, tetwave_protocol::testing::notched_cube_vtk(0.4)).unwrap();
    let s = dir.join("notched.store");
    let mut o = PrepareOptions::new(&mesh.display().to_string(), &s);
    o.levels = Some(4);
    assert!(prepare(&o).unwrap().levelset_near_bytes > 0);
    let srv = serve(&s);
    let views = [(35.0, 25.0), (215.0, 20.0), (125.0, -30.0)];
    let mut script = vec![
        serde_json::json!({"mode": "complete"}),
        serde_json::json!({"wait": "complete"}),
    ];
    for (i, (az, el)) in views.iter().enumerate() {
        script.push(serde_json::json!({"camera": {"azimuth": az, "elevation": el}}));
        script.push(serde_json::json!({"wait": "complete"}));
        script.push(serde_json::json!({"screenshot": dir.join(format!("v{i}.png"))}));
    }
    script.push(serde_json::json!({"quit": true}));
    let r = view_script(
        dir,
        &serde_json::Value::Array(script),
        &[srv.url(), "--size", "192x160", "--frames", "5000"],
    );
    assert_eq!(r["complete"], true, "{r}");
    assert_eq!(r["clipped"], true, "{r}");
    let mut leaks_total = 0;
    for (i, &(az, el)) in views.iter().enumerate() {
        let shot = png(&dir.join(format!("v{i}.png")));
        let want = offscreen(
            &s,
            "default",
            az,
            el,
            (192, 160),
            &dir.join(format!("ref{i}.png")),
        );
        let black = |p: &[u8; 4]| p[..3] == [0, 0, 0];
        let empty = want.pixels.iter().filter(|p| black(p)).count();
        let leaks = want
            .pixels
            .iter()
            .zip(&shot.pixels)
            .filter(|(w, g)| black(w) && !black(g))
            .count();
        let p = psnr(&shot, &want);
        eprintln!(
            "view {az}/{el}: window vs clipped offscreen {p:.2} dB; {leaks} of {empty} empty pixels drawn"
        );
        assert!(empty > 1000, "the view shows background");
        assert!(p >= 45.0, "view {az}/{el}: {p:.2} dB");
        leaks_total += leaks;
    }
    // the band is quantized (1/32 of a finest tet), so a boundary pixel may flip; an unclipped
    // store draws the staircase over hundreds
    assert!(leaks_total <= 3, "{leaks_total} empty pixels drawn");
}

/// `tetwave stream` of the same kind of store says in its summary line that it clipped.
#[test]
fn stream_says_it_clipped_a_nonconvex_store() {
    let d = tempfile::tempdir().unwrap();
    let mesh = d.path().join("notched.vtk");
    std::fs::write(&mesh, tetwave_protocol::testing::notched_cube_vtk(0.4)).unwrap();
    let s = d.path().join("notched.store");
    let mut o = PrepareOptions::new(&mesh.display().to_string(), &s);
    o.levels = Some(3);
    prepare(&o).unwrap();
    let srv = serve(&s);
    let (out, _) = stream_cli(
        srv.url(),
        &[
            "--no-render",
            "--until-complete",
            "--frames",
            "4000",
            "--frame-ms",
            "5",
        ],
        &d.path().join("out"),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("clipped to the mesh's domain"), "{err}");
    // its accuracy figure compares with the whole store drawn clipped the same way: a complete
    // lossless stream at the finest level matches it
    let args = [
        "--cpu",
        "--psnr",
        "--until-complete",
        "--tol",
        "0",
        "--size",
        "64x64",
        "--frames",
        "4000",
        "--frame-ms",
        "5",
    ];
    let (out, psnr) = stream_cli(srv.url(), &args, &d.path().join("psnr"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let psnr = psnr.expect("a PSNR once complete");
    assert!(
        psnr > 60.0,
        "final frame {psnr} dB against the clipped store"
    );
}

/// `tetwave stream URL --headless ARGS --out OUT` (bounded by 120 s), and the last frame's PSNR
/// when it has one.
fn stream_cli(url: &str, args: &[&str], out: &Path) -> (std::process::Output, Option<f64>) {
    let output = Command::new("timeout")
        .arg("120")
        .arg(env!("CARGO_BIN_EXE_tetwave"))
        .args(["stream", url, "--headless"])
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .expect("tetwave runs");
    let psnr = std::fs::read_to_string(out.join("frames.jsonl"))
        .ok()
        .and_then(|f| f.lines().last().map(str::to_owned))
        .and_then(|l| serde_json::from_str::<serde_json::Value>(&l).ok())
        .and_then(|v| v["psnr_db"].as_f64());
    (output, psnr)
}

/// A store of no levels (the base mesh alone, no nodes) is complete as soon as its base mesh is
/// there, with an accuracy figure; and `--frames 0` is refused, not a silent success.
#[test]
fn a_store_without_nodes_streams_complete() {
    let (d, s) = store(0);
    let srv = serve(&s);
    let out_dir = d.path().join("out");
    let args = [
        "--cpu",
        "--size",
        "32x32",
        "--until-complete",
        "--psnr",
        "--frames",
        "400",
    ];
    let (out, psnr) = stream_cli(srv.url(), &args, &out_dir);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("0/0 nodes"), "{err}");
    assert!(psnr.expect("a PSNR once complete") > 60.0);
    let (out, _) = stream_cli(
        srv.url(),
        &["--cpu", "--frames", "0"],
        &d.path().join("none"),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("invalid value '0' for '--frames"), "{err}");
}

/// The tolerance drives refinement: a coarse tolerance draws fewer tets and a worse image, 0
/// draws the finest level, which agrees with the offscreen render.
#[test]
fn view_tolerance_coarsens_and_refines() {
    let (d, s) = store(3);
    let srv = serve(&s);
    let dir = d.path();
    let (coarse, fine) = (dir.join("coarse.png"), dir.join("fine.png"));
    let script = serde_json::json!([
        {"wait": "complete"},
        {"screenshot": coarse},
        {"tol": 0},
        {"wait": "complete"},
        {"screenshot": fine},
        {"quit": true}
    ]);
    let r = view_script(
        dir,
        &script,
        &[
            srv.url(),
            "--size",
            "160x160",
            "--mode",
            "progressive",
            "--tol",
            "1000",
            "--frames",
            "5000",
        ],
    );
    eprintln!("{r}");
    // 5 base tets × 8³ at the finest of 3 levels; fewer at the coarse tolerance
    assert_eq!(r["tets"], 2560, "{r}");
    let coarse_tets = r["screenshot_tets"][0].as_u64().unwrap();
    assert!(coarse_tets < 2560, "{r}");
    let reference = offscreen(&s, "default", 35.0, 25.0, (160, 160), &dir.join("ref.png"));
    let (pc, pf) = (
        psnr(&png(&coarse), &reference),
        psnr(&png(&fine), &reference),
    );
    eprintln!("tolerance 1000 px: {pc:.2} dB, 0 px: {pf:.2} dB against the finest level");
    assert!(pf >= 40.0, "tolerance 0: {pf:.2} dB");
    assert!(pc < pf && pc < 40.0, "tolerance 1000 px: {pc:.2} dB");
}

/// `--max-tets` holds in the window: at tolerance 0 the criterion wants every one of the 20,480
/// leaves, the selector never holds more than the budget, and the report says that it bound.
/// The panel's legend names the store's dataset and value range.
#[test]
fn view_never_exceeds_the_leaf_budget() {
    let (d, s) = store(4);
    let out = view_under_xvfb(
        &[
            s.to_str().unwrap(),
            "--size",
            "128x128",
            "--tol",
            "0",
            "--max-tets",
            "1000",
            "--frames",
            "60",
            "--json",
        ],
        180,
    );
    let r = json_report(&out);
    // the panel's legend names the dataset and the range the transfer function spans
    let m = tetwave_store::Store::open(&s).unwrap().manifest;
    assert_eq!(m.dataset, "harmonic");
    assert_eq!(
        r["legend"],
        tetwave_client::legend::legend_text("harmonic", m.display_value_range()),
        "{r}"
    );
    drop(d);
    eprintln!("{r}");
    assert_eq!(r["leaf_budget"], 1000, "{r}");
    let max = r["max_leaves"].as_u64().unwrap();
    assert!(max > 500 && max <= 1000, "{r}");
    assert!(r["frames_budget_bound"].as_u64().unwrap() > 0, "{r}");
}

/// A local store and a mesh file open too (no server), and `--frames` ends the run.
/// Opens `store` in the window in complete mode (128×128, 40 frames): every node arrives, and the
/// screenshot matches the offscreen render of the same view (≥ 40 dB).
fn view_matches_offscreen(store: &Path, dir: &Path, name: &str) {
    let shot = dir.join(format!("{name}.png"));
    let out = view_under_xvfb(
        &[
            store.to_str().unwrap(),
            "--size",
            "128x128",
            "--mode",
            "complete",
            "--frames",
            "40",
            "--screenshot",
            shot.to_str().unwrap(),
            "--json",
        ],
        120,
    );
    let r = json_report(&out);
    assert!(r["frames"].as_u64().unwrap() >= 40, "{r}");
    assert_eq!(r["nodes"], r["nodes_total"], "{r}");
    let img = png(&shot);
    assert_eq!((img.width, img.height), (128, 128));
    let reference = offscreen(
        store,
        "auto",
        35.0,
        25.0,
        (128, 128),
        &dir.join(format!("{name}-ref.png")),
    );
    let p = psnr(&img, &reference);
    eprintln!("{name} view vs offscreen: {p:.2} dB");
    assert!(p >= 40.0, "{name} view vs offscreen: {p:.2} dB");
}

#[test]
fn view_opens_a_store_and_a_mesh_file() {
    let (d, s) = store(2);
    view_matches_offscreen(&s, d.path(), "store");

    // a grid store with the axes predictor (values by grid point, apart from the mesh)
    let axes = d.path().join("axes");
    let mut o = PrepareOptions::new("synthetic:harmonic", &axes);
    o.levels = Some(3);
    o.base = tetwave_server::resample::BaseSpec::Box6;
    o.max_error = Some(tetwave_server::analysis::ErrorBound::OfRange(1e-3));
    assert_eq!(prepare(&o).unwrap().predictor, "axes");
    view_matches_offscreen(&axes, d.path(), "axes");

    let mesh = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../server/tests/fixtures/cube.mesh");
    let shot = d.path().join("mesh.png");
    let out = view_under_xvfb(
        &[
            mesh.to_str().unwrap(),
            "--size",
            "96x96",
            "--frames",
            "5",
            "--screenshot",
            shot.to_str().unwrap(),
            "--json",
        ],
        120,
    );
    assert!(out.status.success(), "mesh: {}", out.status);
    let img = png(&shot);
    let lit = img.pixels.iter().filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(lit > 0, "the mesh file's view is blank");
}

/// `--json` carries the run's frame times and input-to-frame latency: one latency per input step
/// of the script, and figures that agree with each other (p50 ≤ p95 ≤ max, the worst refinement
/// frame is the maximum of the refinement times, the worst frame the longest period).
#[test]
fn view_json_carries_latency_and_the_worst_refinement_frame() {
    let (d, s) = store(3);
    let srv = serve(&s);
    let dir = d.path();
    // 8 inputs (orbits, an elevation, a zoom, a tolerance, mode switches), due at fixed times
    let script = serde_json::json!([
        {"at": 0.2, "mode": "interactive"},
        {"at": 0.3, "orbit": 15},
        {"at": 0.4, "orbit": 15},
        {"at": 0.5, "elevate": -10},
        {"at": 0.6, "zoom": 0.8},
        {"at": 0.7, "tol": 0.5},
        {"at": 0.8, "mode": "complete"},
        {"wait": "complete"},
        {"at": 1.0, "mode": "progressive"},
        {"frames": 3},
        {"quit": true}
    ]);
    let r = view_script(
        dir,
        &script,
        &[srv.url(), "--size", "160x120", "--frames", "20000"],
    );
    eprintln!("{r}");
    let p = &r["perf"];
    let f = |v: &serde_json::Value| v.as_f64().unwrap_or_else(|| panic!("a number: {v} in {p}"));
    let frames = r["frames"].as_u64().unwrap();
    for k in [
        "latency_ms",
        "frame_ms",
        "ingest_ms",
        "refine_ms",
        "leaf_ms",
        "upload_ms",
        "render_ms",
        "work_ms",
        "paint_ms",
    ] {
        let s = &p[k];
        let n = s["n"].as_u64().unwrap();
        assert!(n > 0 && n <= frames, "{k}: {s}");
        assert!(
            0.0 <= f(&s["p50"]) && f(&s["p50"]) <= f(&s["p95"]) && f(&s["p95"]) <= f(&s["max"]),
            "{k}: {s}"
        );
    }
    // each of the 8 inputs is presented once; nothing else (no mouse on Xvfb) counts
    assert_eq!(p["latency_ms"]["n"], 8, "{p}");
    // a frame applies at most one script input, and its presentation is a frame later
    assert!(f(&p["latency_ms"]["max"]) > 0.0, "{p}");
    // every input was applied by the first frame that started after it: its latency is below the
    // period of the frame in flight when it came plus the applying frame's
    assert_eq!(p["inputs_past_bound"], 0, "{p}");
    let worst = &p["worst_refine"];
    assert_eq!(f(&worst["refine_ms"]), f(&p["refine_ms"]["max"]), "{p}");
    assert!(f(&worst["refine_ms"]) >= f(&p["refine_ms"]["p50"]), "{p}");
    assert!(f(&worst["refine_budget_ms"]) > 0.0, "{p}");
    assert!(worst["frame"].as_u64().unwrap() <= frames, "{p}");
    assert_eq!(
        f(&p["worst_frame"]["period_ms"]),
        f(&p["frame_ms"]["max"]),
        "{p}"
    );
    // the run's frames are all timed; the first has no period
    assert_eq!(p["frame_ms"]["n"].as_u64().unwrap(), frames - 1, "{p}");
    let drawn = p["frames_drawn"].as_u64().unwrap();
    assert!(drawn > 0 && drawn <= frames, "{p}");
    // the FPS of the volume counts only the frames that drew it
    let (fps, fps_drawn) = (f(&r["fps"]), f(&r["fps_drawn"]));
    assert!(fps_drawn > 0.0, "{r}");
    assert!(
        (fps_drawn / fps - drawn as f64 / frames as f64).abs() < 1e-6,
        "{fps_drawn} of {fps} FPS, {drawn} of {frames} frames"
    );
    assert!(p["refine_over_budget"].as_u64().unwrap() <= frames, "{p}");
    let complete_s = f(&r["complete_s"]);
    assert!(complete_s > 0.0, "{r}");
}

/// Fly mode: a scripted fly-in along the view puts the eye inside the volume (the harmonic field's
/// box is [0,30]³), where the frame differs from the orbit's, is neither blank nor one colour,
/// and agrees with the CPU reference integrator for the same eye (an orbit camera at the shorter
/// distance): tets behind the eye are left out, the near plane clips the rest.
#[test]
fn view_flies_into_the_volume_and_matches_the_reference() {
    let (d, s) = store(3);
    let dir = d.path();
    let (outside, inside) = (dir.join("orbit.png"), dir.join("fly.png"));
    let script = serde_json::json!([
        {"mode": "complete"},
        {"wait": "complete"},
        {"screenshot": outside},
        // from 1.6 diagonals away to 0.15, along the view
        {"fly": {"forward": 1.0}},
        {"fly": {"forward": 0.45}},
        {"wait": "complete"},
        {"screenshot": inside},
        {"quit": true}
    ]);
    let r = view_script(
        dir,
        &script,
        &[s.to_str().unwrap(), "--size", "160x120", "--frames", "5000"],
    );
    eprintln!("{r}");
    assert_eq!(r["fly"], true, "{r}");
    let eye: Vec<f64> = r["eye"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert!(
        eye.iter().all(|x| (0.0..=30.0).contains(x)),
        "the eye is not inside the volume: {eye:?}"
    );
    let dist = eye.iter().map(|x| (x - 15.0).powi(2)).sum::<f64>().sqrt();
    let diag = 30.0 * 3f64.sqrt();
    assert!((dist - 0.15 * diag).abs() < 1e-6 * diag, "{dist}");

    let (io, ii) = (png(&outside), png(&inside));
    assert_eq!((ii.width, ii.height), (160, 120));
    let changed = io
        .pixels
        .iter()
        .zip(&ii.pixels)
        .filter(|(p, q)| (0..3).any(|k| p[k].abs_diff(q[k]) > 8))
        .count();
    assert!(
        changed > io.pixels.len() / 4,
        "flying in should change the frame: {changed} pixels changed"
    );
    let lit = ii.pixels.iter().filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(
        lit > ii.pixels.len() / 2,
        "inside, most rays cross the volume: {lit} lit"
    );
    let colours: std::collections::HashSet<[u8; 3]> =
        ii.pixels.iter().map(|p| [p[0], p[1], p[2]]).collect();
    assert!(
        colours.len() > 50,
        "{} colours: not an image of the field",
        colours.len()
    );

    let reference = dir.join("ref.png");
    let o = Command::new(env!("CARGO_BIN_EXE_tetwave"))
        .arg("render")
        .arg(&s)
        .args([
            "--distance",
            &dist.to_string(),
            "--size",
            "160x120",
            "--reference",
            "-o",
        ])
        .arg(&reference)
        .output()
        .expect("tetwave render runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let p = psnr(&ii, &png(&reference));
    eprintln!("fly-in view vs the CPU reference at distance {dist:.3}: {p:.2} dB");
    assert!(p >= 45.0, "fly-in view vs the CPU reference: {p:.2} dB");
}

/// A `size` step resizes the window: the view takes the new size, the refinement and the
/// screenshot follow it, and the image at the new size agrees with the offscreen render at it.
#[test]
fn view_resizes_and_screenshots_at_the_new_size() {
    let (d, s) = store(2);
    let dir = d.path();
    let (small, large) = (dir.join("small.png"), dir.join("large.png"));
    let script = serde_json::json!([
        {"wait": "complete"},
        {"screenshot": small},
        {"size": "300x180"},
        {"wait": "complete"},
        {"screenshot": large},
        {"quit": true}
    ]);
    let r = view_script(
        dir,
        &script,
        &[
            s.to_str().unwrap(),
            "--size",
            "128x96",
            "--mode",
            "complete",
            "--frames",
            "5000",
        ],
    );
    eprintln!("{r}");
    assert_eq!(r["view"], serde_json::json!([300, 180]), "{r}");
    let (a, b) = (png(&small), png(&large));
    assert_eq!((a.width, a.height), (128, 96));
    assert_eq!((b.width, b.height), (300, 180));
    let reference = offscreen(&s, "auto", 35.0, 25.0, (300, 180), &dir.join("ref.png"));
    let p = psnr(&b, &reference);
    eprintln!("resized view vs offscreen at 300x180: {p:.2} dB");
    assert!(p >= 40.0, "resized view vs offscreen: {p:.2} dB");
}

/// A TCP relay to `upstream` that passes the server's bytes at most `bytes_per_s` (so that a
/// small stream lasts long enough to be cut in the middle) and counts them. A connection ends
/// on both sides when either side ends; a client that connects while the upstream refuses is
/// closed at once. It runs until the test ends.
fn slow_relay(upstream: std::net::SocketAddr, bytes_per_s: u64) -> (u16, Arc<AtomicU64>) {
    use std::io::{Read, Write};
    use std::net::{Shutdown, TcpListener, TcpStream};
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let passed = Arc::new(AtomicU64::new(0));
    let counter = passed.clone();
    std::thread::spawn(move || {
        for client in listener.incoming() {
            let Ok(mut client) = client else { continue };
            let Ok(mut server) = TcpStream::connect(upstream) else {
                continue;
            };
            let (mut c2, mut s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
            let counter = counter.clone();
            // the client's bytes go up unthrottled
            std::thread::spawn(move || {
                let _ = std::io::copy(&mut c2, &mut s2);
                let _ = s2.shutdown(Shutdown::Both);
                let _ = c2.shutdown(Shutdown::Both);
            });
            std::thread::spawn(move || {
                let mut buf = [0u8; 1024];
                loop {
                    let n = match server.read(&mut buf) {
                        Ok(0) | Err(_) => break,
                        Ok(n) => n,
                    };
                    if client.write_all(&buf[..n]).is_err() {
                        break;
                    }
                    counter.fetch_add(n as u64, Ordering::Relaxed);
                    std::thread::sleep(Duration::from_secs_f64(n as f64 / bytes_per_s as f64));
                }
                let _ = client.shutdown(Shutdown::Both);
                let _ = server.shutdown(Shutdown::Both);
            });
        }
    });
    (port, passed)
}

/// The server dies in the middle of the stream and comes back on the same port: the viewer
/// reconnects (with backoff, the panel saying so), resumes from what it holds (about the bytes
/// of an uncut stream arrive in all) and completes.
#[test]
fn view_reconnects_when_the_server_restarts_mid_stream() {
    let (d, s) = store(4);
    // small batches, one in flight: what the server has sent is never far ahead of what the
    // slow relay has passed, so the cut below falls in the middle of the stream
    let paced = || ServeConfig {
        batch: 64,
        max_batch: 64,
        window: 1,
        ..ServeConfig::default()
    };
    let srv = serve_with(&s, "127.0.0.1:0", paced());
    let addr: std::net::SocketAddr = srv.url().trim_start_matches("http://").parse().unwrap();
    let (port, passed) = slow_relay(addr, 40_000);
    let script = serde_json::json!([{"wait": "complete"}, {"quit": true}]);
    let sp = d.path().join("script.json");
    std::fs::write(&sp, script.to_string()).unwrap();
    let url = format!("http://127.0.0.1:{port}");
    let sp2 = sp.clone();
    let viewer = std::thread::spawn(move || {
        view_under_xvfb(
            &[
                &url,
                "--size",
                "128x96",
                "--mode",
                "complete",
                "--script",
                sp2.to_str().unwrap(),
                "--frames",
                "100000",
                "--json",
            ],
            240,
        )
    });
    // cut once the manifest, the base mesh and some batches have passed
    let t0 = std::time::Instant::now();
    while passed.load(Ordering::Relaxed) < 12_000 {
        assert!(
            t0.elapsed() < Duration::from_secs(900),
            "the viewer never streamed"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    drop(srv);
    let at_cut = passed.load(Ordering::Relaxed);
    std::thread::sleep(Duration::from_millis(1500));
    let srv = serve_with(&s, &addr.to_string(), paced());
    let out = viewer.join().unwrap();
    let after = passed.load(Ordering::Relaxed) - at_cut;
    // the same stream uncut, for its size
    let fresh = view_under_xvfb(
        &[
            srv.url(),
            "--size",
            "128x96",
            "--mode",
            "complete",
            "--script",
            sp.to_str().unwrap(),
            "--frames",
            "100000",
            "--json",
        ],
        240,
    );
    drop(srv);
    let fresh = json_report(&fresh);
    let r = json_report(&out);
    eprintln!("{r}\n{at_cut} bytes before the cut, {after} after");
    assert_eq!(r["complete"], true, "{r}");
    assert_eq!(r["nodes"], r["nodes_total"], "{r}");
    assert!(r["reconnects"].as_u64().unwrap() >= 1, "{r}");
    // the outage lasted 1.5 s: the panel said so in the frames meanwhile
    assert!(r["frames_reconnecting"].as_u64().unwrap() >= 1, "{r}");
    assert_eq!(fresh["frames_reconnecting"], 0, "{fresh}");
    // the stream went on after the restart (it had not finished before the cut)
    assert!(after > 1000, "{after} bytes after the restart");
    // resumed: the new connection's Hello listed what was held, so it came once, not twice
    let (cut, whole) = (
        r["bytes_received"].as_u64().unwrap(),
        fresh["bytes_received"].as_u64().unwrap(),
    );
    eprintln!("{cut} bytes received across the cut, {whole} uncut");
    assert!(
        (cut as f64) < 1.1 * whole as f64,
        "{cut} bytes with the cut against {whole} uncut: the stream restarted instead of resuming"
    );
    assert_eq!(r["errors"], serde_json::json!([]), "{r}");
}

/// Level of detail in motion (`--motion-lod`): with draws slower than `--motion-ms` (here every
/// draw, the target being 1 µs), the frames drawn while the camera moves draw a coarser mesh,
/// and at rest the finest level returns and matches the offscreen render; with `--motion-ms 0`
/// motion draws the finest level throughout.
#[test]
fn view_coarsens_in_motion_when_draws_are_slow_and_refines_at_rest() {
    let (d, s) = store(3);
    let dir = d.path();
    let mut steps = vec![serde_json::json!({"wait": "complete"})];
    for _ in 0..25 {
        steps.push(serde_json::json!({"orbit": 2}));
        steps.push(serde_json::json!({"frames": 2}));
    }
    let run = |motion_ms: &str, shot: &Path| {
        let mut steps = steps.clone();
        steps.push(serde_json::json!({"wait": "complete"}));
        steps.push(serde_json::json!({"screenshot": shot}));
        steps.push(serde_json::json!({"quit": true}));
        let r = view_script(
            dir,
            &serde_json::Value::Array(steps),
            &[
                s.to_str().unwrap(),
                "--size",
                "160x120",
                "--tol",
                "0",
                "--motion-lod",
                "--motion-ms",
                motion_ms,
                "--frames",
                "20000",
            ],
        );
        eprintln!("--motion-ms {motion_ms}: {}", r["perf"]);
        r
    };
    let f = |v: &serde_json::Value| v.as_f64().unwrap_or_else(|| panic!("a number: {v}"));
    let lod = run("0.001", &dir.join("lod.png"));
    let p = &lod["perf"];
    assert!(f(&p["max_tol_px"]) > 1.0, "{p}");
    assert!(f(&lod["motion_factor"]) > 1.0, "{lod}");
    assert!(p["tets_drawn_in_motion"]["n"].as_u64().unwrap() > 0, "{p}");
    assert!(f(&p["tets_drawn_in_motion"]["p50"]) < 2560.0, "{p}");
    // at rest: the finest level again, the same image as the offscreen render
    assert_eq!(lod["tets"], 2560, "{lod}");
    let az = f(&lod["azimuth"]);
    let reference = offscreen(&s, "auto", az, 25.0, (160, 120), &dir.join("ref.png"));
    let psnr_rest = psnr(&png(&dir.join("lod.png")), &reference);
    eprintln!("at rest after the motion vs offscreen: {psnr_rest:.2} dB");
    assert!(psnr_rest >= 40.0, "{psnr_rest:.2} dB");

    let off = run("0", &dir.join("off.png"));
    let p = &off["perf"];
    assert_eq!(f(&off["motion_factor"]), 1.0, "{off}");
    assert_eq!(f(&p["max_tol_px"]), 0.0, "{p}");
    assert_eq!(f(&p["tets_drawn_in_motion"]["p50"]), 2560.0, "{p}");
}

/// A script: complete, ten 3° orbit steps two frames apart, complete again, a screenshot to
/// `shot`, quit.
fn orbit_then_rest(shot: &Path) -> serde_json::Value {
    let mut steps = vec![serde_json::json!({"wait": "complete"})];
    for _ in 0..10 {
        steps.push(serde_json::json!({"orbit": 3}));
        steps.push(serde_json::json!({"frames": 2}));
    }
    steps.push(serde_json::json!({"wait": "complete"}));
    steps.push(serde_json::json!({"screenshot": shot}));
    steps.push(serde_json::json!({"quit": true}));
    serde_json::Value::Array(steps)
}

/// A store of `levels` levels viewed at 160×120 with `args` (e.g. `--motion-ms 0.001`: every
/// whole draw slow), orbited then at rest ([`orbit_then_rest`]).
struct RestRun {
    /// The store's directory (and the run's files).
    dir: tempfile::TempDir,
    store: PathBuf,
    script: serde_json::Value,
    /// The `--json` report.
    report: serde_json::Value,
    /// The view at rest, and its PSNR against the offscreen render of its camera.
    shot: Rgba8Image,
    at_rest_db: f64,
}

fn orbited_then_at_rest(levels: u8, args: &[&str]) -> RestRun {
    let (dir, store) = store(levels);
    let shot = dir.path().join("rest.png");
    let script = orbit_then_rest(&shot);
    let mut all = vec![
        store.to_str().unwrap(),
        "--size",
        "160x120",
        "--frames",
        "20000",
    ];
    all.extend_from_slice(args);
    let report = view_script(dir.path(), &script, &all);
    eprintln!("{}", report["perf"]);
    let az = report["azimuth"].as_f64().unwrap();
    let reference = offscreen(
        &store,
        "auto",
        az,
        25.0,
        (160, 120),
        &dir.path().join("ref.png"),
    );
    let shot = png(&shot);
    let at_rest_db = psnr(&shot, &reference);
    eprintln!("at rest vs offscreen: {at_rest_db:.2} dB");
    RestRun {
        dir,
        store,
        script,
        report,
        shot,
        at_rest_db,
    }
}

/// `--motion-scale 2` with draws slower than `--motion-ms` (every draw, at 1 µs): the frames
/// drawn while the camera moves use half the view's width and height, and at rest the view is
/// drawn whole again and matches the offscreen render. With `--motion-ms 0` none is scaled.
#[test]
fn view_draws_fewer_pixels_in_motion_and_all_at_rest() {
    let run = orbited_then_at_rest(3, &["--motion-scale", "2", "--motion-ms", "0.001"]);
    let p = &run.report["perf"];
    assert!(p["frames_drawn_scaled"].as_u64().unwrap() >= 5, "{p}");
    assert_eq!((run.shot.width, run.shot.height), (160, 120));
    let at_rest = run.at_rest_db;
    assert!(at_rest >= 40.0, "{at_rest:.2} dB");

    let r = view_script(
        run.dir.path(),
        &run.script,
        &[
            run.store.to_str().unwrap(),
            "--size",
            "160x120",
            "--motion-ms",
            "0",
            "--frames",
            "20000",
        ],
    );
    assert_eq!(r["perf"]["frames_drawn_scaled"], 0, "{r}");
    assert!(r["perf"]["frames_drawn"].as_u64().unwrap() >= 5, "{r}");
}

/// `--motion-tets 400` with draws slower than `--motion-ms`: the frames drawn while the camera
/// moves draw the leaf mesh merged to at most 400 tets (from 2,560), and at rest the whole leaf
/// mesh again, matching the offscreen render.
#[test]
fn view_draws_a_coarser_mesh_in_motion_and_the_leaf_mesh_at_rest() {
    let run = orbited_then_at_rest(3, &["--motion-ms", "0.001", "--motion-tets", "400"]);
    let (r, at_rest) = (&run.report, run.at_rest_db);
    let p = &r["perf"];
    let moving = &p["tets_drawn_in_motion"];
    assert!(moving["n"].as_u64().unwrap() >= 5, "{p}");
    assert!(moving["max"].as_f64().unwrap() <= 400.0, "{p}");
    assert_eq!(
        p["tets_drawn_at_rest"]["max"].as_f64().unwrap(),
        2560.0,
        "{p}"
    );
    assert_eq!(r["tets"], 2560, "{r}");
    assert!(at_rest >= 40.0, "{at_rest:.2} dB");
}

/// A whole draw slower than `--motion-ms` at rest is spread over frames, a range of its
/// triangles a frame, while the view keeps the last image (the window answers); the image it
/// ends with is the one a single draw makes.
#[test]
fn view_spreads_a_slow_draw_at_rest_over_frames() {
    let run = orbited_then_at_rest(4, &["--motion-ms", "0.001", "--motion-tets", "400"]);
    let (r, at_rest) = (&run.report, run.at_rest_db);
    let p = &r["perf"];
    let (draws, frames) = (
        p["spread_draws"].as_u64().unwrap(),
        p["spread_frames"].as_u64().unwrap(),
    );
    assert!(draws >= 1, "{p}");
    // 20,480 tets at a few thousand triangles a frame: several frames each
    assert!(frames >= 3 * draws, "{draws} draws in {frames} frames");
    assert_eq!(r["tets"], 20480, "{r}");
    assert!(at_rest >= 40.0, "{at_rest:.2} dB");
}

/// `auto` in the transfer-function list: a stream viewed with the `default` preset (its default)
/// switches to the function fitted to the store's histogram, the one `tetwave render` draws the
/// store with, and the server renders the same for its image.
#[test]
fn picking_auto_on_a_stream_draws_the_stores_fitted_function() {
    let (d, s) = store(3);
    let dir = d.path();
    let srv = serve(&s);
    let shot = dir.join("auto.png");
    let script = serde_json::json!([
        {"wait": "complete"},
        {"tf": "auto"},
        {"frames": 3},
        {"wait": "complete"},
        {"screenshot": shot},
        {"quit": true}
    ]);
    let r = view_script(
        dir,
        &script,
        &[
            srv.url(),
            "--size",
            "160x120",
            "--mode",
            "complete",
            "--frames",
            "20000",
        ],
    );
    assert_eq!(r["complete"], true, "{r}");
    let img = png(&shot);
    let auto = offscreen(
        &s,
        "auto",
        35.0,
        25.0,
        (160, 120),
        &dir.join("auto-ref.png"),
    );
    let preset = offscreen(
        &s,
        "default",
        35.0,
        25.0,
        (160, 120),
        &dir.join("default-ref.png"),
    );
    let (pa, pd) = (psnr(&img, &auto), psnr(&img, &preset));
    eprintln!("picked auto vs render auto {pa:.2} dB, vs render default {pd:.2} dB");
    assert!(pa >= 40.0 && pa > pd + 3.0, "{pa:.2} / {pd:.2} dB");
}

/// A mesh file has no coarser levels: with draws slower than `--motion-ms` (every draw, at 1 µs)
/// the viewer draws a Kuhn grid sampled from it while the camera moves (at most `--motion-tets`
/// tets, clipped to the mesh's domain), and the mesh itself at rest, matching `tetwave render`.
#[test]
fn view_moves_a_mesh_file_with_a_coarser_proxy_and_draws_it_whole_at_rest() {
    let d = tempfile::tempdir().unwrap();
    // 12³ Kuhn cells without the corner octant: 9,072 tets, a field with structure
    let (pts, tets) = tetwave_protocol::shapes::kuhn_boxes([0.0; 3], [1.0; 3], [12; 3]);
    let corner = |t: &[u32; 4]| (0..3).all(|a| t.iter().all(|&v| pts[v as usize][a] >= 0.5));
    let tets: Vec<[u32; 4]> = tets.into_iter().filter(|t| !corner(t)).collect();
    let mut vtk = format!(
        "# vtk DataFile Version 3.0\nnotched\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS {} double\n",
        pts.len()
    );
    for p in &pts {
        vtk += &format!("{} {} {}\n", p[0], p[1], p[2]);
    }
    vtk += &format!("CELLS {} {}\n", tets.len(), 5 * tets.len());
    for t in &tets {
        vtk += &format!("4 {} {} {} {}\n", t[0], t[1], t[2], t[3]);
    }
    vtk += &format!("CELL_TYPES {}\n", tets.len());
    vtk += &"10\n".repeat(tets.len());
    vtk += &format!(
        "POINT_DATA {}\nSCALARS f double 1\nLOOKUP_TABLE default\n",
        pts.len()
    );
    for p in &pts {
        vtk += &format!("{}\n", (6.0 * p[0]).sin() * p[1] + p[2] * p[2]);
    }
    let mesh = d.path().join("notched.vtk");
    std::fs::write(&mesh, vtk).unwrap();
    let shot = d.path().join("rest.png");
    let script = orbit_then_rest(&shot);
    let args = [
        mesh.to_str().unwrap(),
        "--size",
        "160x120",
        "--frames",
        "20000",
        "--motion-ms",
        "0.001",
        "--motion-tets",
        "1500",
    ];
    let r = view_script(d.path(), &script, &args);
    let p = &r["perf"];
    eprintln!("{p}");
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    assert!(p["tets_drawn_in_motion"]["n"].as_u64().unwrap() > 0, "{p}");
    assert!(f(&p["tets_drawn_in_motion"]["max"]) <= 1500.0, "{p}");
    assert_eq!(f(&r["tets"]), tets.len() as f64, "{r}");
    let az = r["azimuth"].as_f64().unwrap();
    let reference = offscreen(
        &mesh,
        "auto",
        az,
        25.0,
        (160, 120),
        &d.path().join("ref.png"),
    );
    let db = psnr(&png(&shot), &reference);
    eprintln!("at rest vs offscreen: {db:.2} dB");
    assert!(db >= 40.0, "{db:.2} dB");
}

/// A store read directly over HTTP, with no server (nginx serving its folder): the window fetches
/// blocks by range as its selection asks, completes in complete mode, and its screenshot agrees
/// with the offscreen renderer's image of the same store.
#[test]
fn view_reads_a_store_from_a_static_file_server() {
    let (d, s) = store(3);
    let dir = d.path();
    let root = s.parent().unwrap().display().to_string();
    let nginx = tetwave_tests::Nginx::start(&format!("root {root}; location / {{ }}"));
    let url = format!("http://127.0.0.1:{}/s", nginx.port);
    let shot = dir.join("http.png");
    let script = serde_json::json!([
        {"mode": "complete"},
        {"wait": "complete"},
        {"screenshot": shot},
        {"quit": true}
    ]);
    let r = view_script(
        dir,
        &script,
        &[&url, "--size", "256x224", "--frames", "5000"],
    );
    assert_eq!(r["complete"], true, "{r}");
    assert_eq!(r["nodes"], r["nodes_total"], "{r}");
    assert!(r["bytes_received"].as_u64().unwrap() > 0, "{r}");
    let reference = offscreen(&s, "default", 35.0, 25.0, (256, 224), &dir.join("ref.png"));
    let p = psnr(&png(&shot), &reference);
    eprintln!("window (store over HTTP) vs offscreen: {p:.2} dB");
    assert!(p >= 40.0, "screenshot vs offscreen render: {p:.2} dB");
}
