//! The CLI on bad input (`bench progressive`, camera arguments): a clear one-line error and a
//! failing exit status, never a panic; `render`'s warnings and its quiet headless start.

use std::process::Command;

/// `tetwave ARGS`, or `tetwave-bench REST` for `bench REST` (the benchmarks' own binary).
fn tetwave(args: &[&str]) -> (bool, String) {
    let (exe, args) = match args {
        ["bench", rest @ ..] => (env!("CARGO_BIN_EXE_tetwave-bench"), rest),
        _ => (env!("CARGO_BIN_EXE_tetwave"), args),
    };
    let out = Command::new(exe).args(args).output().expect("tetwave runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bench_progressive_bad_input_fails_clearly() {
    let (ok, err) = tetwave(&["bench", "progressive", "--store", "/nonexistent/store"]);
    assert!(!ok);
    let line = err.lines().find(|l| l.starts_with("error:")).expect(&err);
    assert!(line.contains("/nonexistent/store/manifest.json"), "{err}");
    // the cause once, not repeated by the error chain
    assert_eq!(line.matches("os error 2").count(), 1, "{err}");
    assert!(!err.contains("panicked"), "{err}");

    let (ok, err) = tetwave(&[
        "bench",
        "progressive",
        "--store",
        "/nonexistent/store",
        "--render-every",
        "0",
    ]);
    assert!(!ok);
    assert!(err.contains("at least 1"), "{err}");

    let (ok, err) = tetwave(&["bench", "progressive", "--store", "x", "--render-cpu"]);
    assert!(!ok);
    assert!(err.contains("--render-every"), "{err}");

    // viewport sides outside 1..=8192 (0 made the renderer panic, or gave nonsense tolerances)
    for (flag, v) in [("--width", "0"), ("--height", "0"), ("--width", "100000")] {
        let (ok, err) = tetwave(&["bench", "progressive", "--store", "x", flag, v]);
        assert!(!ok);
        assert!(err.contains("outside 1..=8192"), "{flag} {v}: {err}");
    }
}

/// Camera arguments that would give a blank or meaningless image are refused by `render`,
/// `stream` and `bench progressive` alike, before anything is read; so is an unbounded wait per
/// frame.
#[test]
fn camera_arguments_are_checked() {
    let cases: [(&[&str], &str); 7] = [
        (&["render", "x", "--azimuth", "nan"], "not finite"),
        (&["render", "x", "--elevation", "95"], "outside -90..=90"),
        (&["render", "x", "--distance=-5"], "not a positive distance"),
        (&["render", "x", "--fov", "0"], "outside (0, 180)"),
        (
            &["stream", "http://127.0.0.1:1", "--orbit", "inf"],
            "not finite",
        ),
        (
            &["stream", "http://127.0.0.1:1", "--frame-ms", "60001"],
            "not in 0..=60000",
        ),
        (
            &["bench", "progressive", "--store", "x", "--fovy", "180"],
            "outside (0, 180)",
        ),
    ];
    for (args, why) in cases {
        let (ok, err) = tetwave(args);
        assert!(!ok, "{args:?}");
        assert!(
            err.contains(why) && !err.contains("panicked"),
            "{args:?}: {err}"
        );
    }
}

/// `tetwave render --order mpvo` warns on a non-convex mesh (the 7-tet fixture `cube_ascii.vtu`,
/// a cube piece with a notch) and the default order does not; with no display and no
/// `XDG_RUNTIME_DIR`, neither run prints the line of Mesa's Wayland probe ("XDG_RUNTIME_DIR is
/// invalid or not set") that every headless GPU render printed before.
#[test]
fn render_warns_for_mpvo_on_non_convex_meshes_and_is_quiet_headless() {
    let mesh = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../server/tests/fixtures/cube_ascii.vtu");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.png");
    let render = |order: &str| {
        let o = Command::new(env!("CARGO_BIN_EXE_tetwave"))
            .args(["render", &mesh.display().to_string(), "--size", "16x16"])
            .args(["--order", order, "-o", &out.display().to_string()])
            .env_remove("DISPLAY")
            .env_remove("WAYLAND_DISPLAY")
            .env_remove("XDG_RUNTIME_DIR")
            .env_remove("NODEVICE_SELECT")
            .output()
            .expect("tetwave runs");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let mpvo = render("mpvo");
    assert!(mpvo.contains("--order mpvo on a non-convex mesh"), "{mpvo}");
    let centroid = render("centroid");
    assert!(!centroid.contains("non-convex"), "{centroid}");
    for err in [&mpvo, &centroid] {
        assert!(!err.contains("XDG_RUNTIME_DIR"), "{err}");
    }
}
