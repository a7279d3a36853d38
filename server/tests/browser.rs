//! The viewer page at `/` in a real browser: headless Chromium (Debian's `chromium`), driven over
//! the Chrome DevTools Protocol. The page loads, shows a non-blank image, and a mouse drag changes
//! the image. The server runs in-process on 127.0.0.1:0; Chromium is a child process in its own
//! process group with a temporary profile, killed on drop (also when the test fails). Every wait is
//! bounded.
//!
//! Chromium is required: when it is missing the test fails (run `scripts/setup`). `TETWAVE_CHROMIUM`
//! names another binary.

mod stream_common;

use futures_util::{SinkExt, StreamExt};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, Stdio};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};
use stream_common::{make_store, start};
use tetwave_server::stream::ServeConfig;
use tokio_tungstenite::tungstenite::Message;

/// Longest wait for one DevTools answer.
const CALL: Duration = Duration::from_secs(30);
/// Longest wait for an image to appear or change.
const IMAGE: Duration = Duration::from_secs(30);
/// Longest wait for the whole test.
const WHOLE: Duration = Duration::from_secs(180);

/// The browser binary: `TETWAVE_CHROMIUM`, else the first of the usual names on `PATH`.
fn chromium_binary() -> String {
    if let Ok(b) = std::env::var("TETWAVE_CHROMIUM") {
        if !b.is_empty() {
            return b;
        }
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    for name in [
        "chromium",
        "chromium-browser",
        "google-chrome",
        "google-chrome-stable",
    ] {
        if std::env::split_paths(&path).any(|d| d.join(name).is_file()) {
            return name.into();
        }
    }
    panic!(
        "headless Chromium is required for this test but none was found on PATH (tried chromium, \
         chromium-browser, google-chrome, google-chrome-stable): run scripts/setup (it installs \
         Debian's `chromium`), or set TETWAVE_CHROMIUM to a Chromium binary"
    );
}

/// A running Chromium: killed with its whole process group on drop.
struct Browser {
    child: Child,
    ws_url: String,
    stderr: Arc<Mutex<Vec<String>>>,
    _profile: tempfile::TempDir,
}

impl Browser {
    fn launch(bin: &str) -> Browser {
        let profile = tempfile::tempdir().unwrap();
        let mut child = Command::new(bin)
            .args([
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-background-networking",
                "--disable-extensions",
                "--disable-sync",
                "--mute-audio",
                "--window-size=1024,1024",
                "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0",
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg("about:blank")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .process_group(0)
            .spawn()
            .unwrap_or_else(|e| {
                panic!("cannot start {bin:?} ({e}); run scripts/setup or set TETWAVE_CHROMIUM")
            });
        // Drain stderr for the life of the process (a full pipe would stall Chromium); hand over
        // the DevTools URL when it appears.
        let stderr = Arc::new(Mutex::new(Vec::new()));
        let (tx, rx) = mpsc::channel();
        let pipe = child.stderr.take().unwrap();
        let lines = stderr.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(pipe).lines().map_while(Result::ok) {
                if let Some(i) = line.find("ws://") {
                    if line.contains("DevTools listening on") {
                        let _ = tx.send(line[i..].trim().to_string());
                    }
                }
                lines.lock().unwrap().push(line);
            }
        });
        let mut b = Browser {
            child,
            ws_url: String::new(),
            stderr,
            _profile: profile,
        };
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            match rx.recv_timeout(Duration::from_millis(200)) {
                Ok(url) => {
                    b.ws_url = url;
                    return b;
                }
                Err(mpsc::RecvTimeoutError::Timeout) if Instant::now() < deadline => {
                    if let Ok(Some(st)) = b.child.try_wait() {
                        panic!("{bin} exited ({st}) before DevTools listened:\n{}", b.log());
                    }
                }
                Err(_) => panic!("{bin} printed no DevTools URL within 60 s:\n{}", b.log()),
            }
        }
    }

    fn log(&self) -> String {
        self.stderr.lock().unwrap().join("\n")
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // SIGTERM first, so that Chromium stops (and reaps) its own zygote, renderer and utility
        // processes; then SIGKILL to the whole process group, whatever is left.
        let pid = self.child.id().to_string();
        let signal = |args: &[&str]| {
            let _ = Command::new("kill")
                .args(args)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status();
        };
        signal(&["-TERM", &pid]);
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline && matches!(self.child.try_wait(), Ok(None)) {
            std::thread::sleep(Duration::from_millis(50));
        }
        signal(&["-KILL", "--", &format!("-{pid}")]);
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// A minimal DevTools client: one page session over the browser's socket (flattened targets).
struct Cdp {
    ws: Ws,
    next_id: u64,
    session: Option<String>,
}

impl Cdp {
    async fn connect(url: &str) -> Cdp {
        let (ws, _) = tokio::time::timeout(CALL, tokio_tungstenite::connect_async(url))
            .await
            .expect("DevTools connect timed out")
            .expect("DevTools connect");
        Cdp {
            ws,
            next_id: 1,
            session: None,
        }
    }

    /// Sends a command (to the page session once attached) and returns its `result`; events
    /// arriving meanwhile are dropped.
    async fn call(&mut self, method: &str, params: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        let mut msg = json!({ "id": id, "method": method, "params": params });
        if let Some(s) = &self.session {
            msg["sessionId"] = json!(s);
        }
        let fut = async {
            self.ws
                .send(Message::Text(msg.to_string().into()))
                .await
                .unwrap();
            loop {
                match self.ws.next().await {
                    Some(Ok(Message::Text(t))) => {
                        let v: Value = serde_json::from_str(t.as_str()).unwrap();
                        if v["id"].as_u64() == Some(id) {
                            if let Some(e) = v.get("error") {
                                panic!("DevTools {method} failed: {e}");
                            }
                            return v["result"].clone();
                        }
                    }
                    Some(Ok(_)) => continue,
                    other => panic!("DevTools socket ended during {method}: {other:?}"),
                }
            }
        };
        tokio::time::timeout(CALL, fut)
            .await
            .unwrap_or_else(|_| panic!("DevTools {method} timed out"))
    }

    /// Evaluates an expression in the page and returns its value.
    async fn eval(&mut self, expr: &str) -> Value {
        let r = self
            .call(
                "Runtime.evaluate",
                json!({ "expression": expr, "returnByValue": true, "awaitPromise": true }),
            )
            .await;
        if let Some(e) = r.get("exceptionDetails") {
            panic!("page threw evaluating {expr:?}: {e}");
        }
        r["result"]["value"].clone()
    }

    async fn mouse(&mut self, kind: &str, x: f64, y: f64, buttons: u32) {
        let button = if kind == "mouseMoved" && buttons == 0 {
            "none"
        } else {
            "left"
        };
        self.call(
            "Input.dispatchMouseEvent",
            json!({ "type": kind, "x": x, "y": y, "button": button, "buttons": buttons,
                    "clickCount": if kind == "mouseMoved" { 0 } else { 1 } }),
        )
        .await;
    }

    /// A screenshot of the page's `<img id="view">` (CSS pixels at scale 1), decoded to RGBA8.
    async fn shot(&mut self, clip: &Value) -> image::RgbaImage {
        let r = self
            .call(
                "Page.captureScreenshot",
                json!({ "format": "png", "clip": clip, "fromSurface": true }),
            )
            .await;
        let png = base64_decode(r["data"].as_str().expect("screenshot data"));
        image::load_from_memory_with_format(&png, image::ImageFormat::Png)
            .expect("screenshot decodes")
            .to_rgba8()
    }
}

/// Standard base64 (the screenshot's encoding), padding optional.
fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => (c - b'A') as u32,
            b'a'..=b'z' => (c - b'a' + 26) as u32,
            b'0'..=b'9' => (c - b'0' + 52) as u32,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("bad base64 byte {c}"),
        }
    };
    let b: Vec<u8> = s.bytes().filter(|&c| c != b'=' && c != b'\n').collect();
    let mut out = Vec::with_capacity(b.len() * 3 / 4);
    for chunk in b.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= val(c) << (18 - 6 * i);
        }
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

/// Pixels in the screenshot of the 512 × 512 image.
const PIXELS: usize = 512 * 512;

/// Two colours differ: by more than 1 in some channel (the screenshot is lossless; the margin only
/// absorbs rounding).
fn differ(p: &image::Rgba<u8>, q: &image::Rgba<u8>) -> bool {
    (0..3).any(|c| p[c].abs_diff(q[c]) > 1)
}

/// Distinct colours, and pixels that differ from the top-left corner's (the background).
///
/// The page shows the server's PNG, transparent where the volume is thin, on a black background, so
/// a correct image can be dim: "not blank" means a varied, not a bright, image.
fn variety(img: &image::RgbaImage) -> (usize, usize) {
    let bg = *img.get_pixel(0, 0);
    let colours: std::collections::HashSet<[u8; 3]> =
        img.pixels().map(|p| [p[0], p[1], p[2]]).collect();
    let drawn = img.pixels().filter(|p| differ(p, &bg)).count();
    (colours.len(), drawn)
}

/// Pixels that differ between two screenshots.
fn changed(a: &image::RgbaImage, b: &image::RgbaImage) -> usize {
    assert_eq!(a.dimensions(), b.dimensions());
    a.pixels()
        .zip(b.pixels())
        .filter(|(p, q)| differ(p, q))
        .count()
}

/// Asserts that a screenshot is not blank: several colours, and at least 5 % of it drawn.
fn assert_not_blank(img: &image::RgbaImage, what: &str) {
    let (colours, drawn) = variety(img);
    assert!(
        colours >= 8 && drawn >= PIXELS / 20,
        "{what} looks blank: {colours} distinct colours, {drawn} of {PIXELS} pixels differ from \
         the background"
    );
}

/// With `TETWAVE_BROWSER_SHOTS=<dir>`, keeps a screenshot there (to look at after a failure).
fn save_shot(img: &image::RgbaImage, name: &str) {
    if let Some(dir) = std::env::var_os("TETWAVE_BROWSER_SHOTS") {
        let dir = std::path::PathBuf::from(dir);
        std::fs::create_dir_all(&dir).unwrap();
        img.save(dir.join(name)).unwrap();
    }
}

/// The page's `<img>` holds a decoded server image (a `blob:` URL, loaded).
const IMG_READY: &str = "(() => { const i = document.getElementById('view'); \
     return i.src.startsWith('blob:') && i.complete && i.naturalWidth > 0; })()";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn page_loads_shows_an_image_and_a_drag_changes_it() {
    let bin = chromium_binary(); // fail loudly before any work when the browser is missing
    let (_d, dir) = make_store(2);
    let (addr, _shared) = start(&dir, ServeConfig::default()).await;
    let browser = Browser::launch(&bin);
    let log = browser.stderr.clone();
    let run = async {
        let t0 = Instant::now();
        let mut cdp = Cdp::connect(&browser.ws_url).await;
        let target = cdp
            .call("Target.createTarget", json!({ "url": "about:blank" }))
            .await["targetId"]
            .as_str()
            .expect("targetId")
            .to_string();
        let session = cdp
            .call(
                "Target.attachToTarget",
                json!({ "targetId": target, "flatten": true }),
            )
            .await["sessionId"]
            .as_str()
            .expect("sessionId")
            .to_string();
        cdp.session = Some(session);
        cdp.call(
            "Emulation.setDeviceMetricsOverride",
            json!({ "width": 900, "height": 900, "deviceScaleFactor": 1, "mobile": false }),
        )
        .await;

        // 1. The page loads.
        let url = format!("http://{addr}/");
        let nav = cdp.call("Page.navigate", json!({ "url": url })).await;
        assert!(
            nav.get("errorText").is_none(),
            "navigation to {url} failed: {nav}"
        );
        let deadline = Instant::now() + IMAGE;
        while cdp.eval("document.readyState").await != "complete" {
            assert!(Instant::now() < deadline, "{url} did not finish loading");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let title = cdp.eval("document.title").await;
        assert!(
            title.as_str().is_some_and(|t| t.starts_with("tetwave: ")),
            "unexpected title {title}"
        );
        assert_eq!(cdp.eval("!!document.getElementById('view')").await, true);

        // 2. A non-blank image appears.
        let deadline = Instant::now() + IMAGE;
        while cdp.eval(IMG_READY).await != true {
            let info = cdp
                .eval("document.getElementById('info').textContent")
                .await;
            assert!(
                Instant::now() < deadline,
                "no image within {IMAGE:?}; page says {info}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let info = cdp
            .eval("document.getElementById('info').textContent")
            .await;
        assert!(
            info.as_str().is_some_and(|t| t.starts_with("level ")),
            "page reports {info}"
        );
        let rect = cdp
            .eval(
                "(() => { const r = document.getElementById('view').getBoundingClientRect(); \
                 return [r.x, r.y, r.width, r.height]; })()",
            )
            .await;
        let r: Vec<f64> = serde_json::from_value(rect).unwrap();
        assert_eq!((r[2], r[3]), (512.0, 512.0), "image box {r:?}");
        let clip = json!({ "x": r[0], "y": r[1], "width": r[2], "height": r[3], "scale": 1 });
        let before = cdp.shot(&clip).await;
        assert_eq!(before.dimensions(), (512, 512));
        save_shot(&before, "before.png");
        assert_not_blank(&before, "the first image");

        // 3. A drag (120 px right, 40 px down) orbits: azimuth 35 → -25, elevation 25 → 45.
        let (cx, cy) = (r[0] + r[2] / 2.0, r[1] + r[3] / 2.0);
        cdp.mouse("mouseMoved", cx, cy, 0).await;
        cdp.mouse("mousePressed", cx, cy, 1).await;
        for i in 1..=12 {
            let f = i as f64 / 12.0;
            cdp.mouse("mouseMoved", cx + 120.0 * f, cy + 40.0 * f, 1)
                .await;
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        cdp.mouse("mouseReleased", cx + 120.0, cy + 40.0, 1).await;
        let deadline = Instant::now() + IMAGE;
        let (after, diff) = loop {
            let info = cdp
                .eval("document.getElementById('info').textContent")
                .await;
            let text = info.as_str().unwrap_or_default().to_string();
            assert!(!text.starts_with("error"), "page reports {text}");
            if text.contains("azimuth -25.0, elevation 45.0") && cdp.eval(IMG_READY).await == true {
                let after = cdp.shot(&clip).await;
                let diff = changed(&before, &after);
                save_shot(&after, "after.png");
                if diff >= PIXELS / 100 {
                    break (after, diff);
                }
            }
            assert!(
                Instant::now() < deadline,
                "the image did not change enough (1 % of its pixels) within {IMAGE:?} of the drag; \
                 page says {text:?}"
            );
            tokio::time::sleep(Duration::from_millis(150)).await;
        };
        assert_not_blank(&after, "the image after the drag");
        eprintln!(
            "browser test ({bin}): first image {:?} (colours, drawn pixels), {diff} of {PIXELS} \
             pixels changed by the drag, {:.1} s",
            variety(&before),
            t0.elapsed().as_secs_f64()
        );
    };
    if tokio::time::timeout(WHOLE, run).await.is_err() {
        panic!(
            "browser test exceeded {WHOLE:?}; chromium said:\n{}",
            log.lock().unwrap().join("\n")
        );
    }
    drop(browser);
}
