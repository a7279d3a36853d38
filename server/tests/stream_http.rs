//! `tetwave-server serve` over HTTP: manifest, base, node ranges, health, token enforcement, and the
//! fallback renderer (`/v1/render` validation and image fidelity, `/` page). Servers bind
//! 127.0.0.1:0; every request is bounded by a timeout.

mod stream_common;

use stream_common::*;
use tetwave_gpu::pt::PtRenderer;
use tetwave_gpu::GpuContext;
use tetwave_protocol::block::BlockCoder;
use tetwave_protocol::view::Orbit;
use tetwave_protocol::wire::{decode_server, ServerMsg};
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;
use tetwave_server::stream::ServeConfig;
use tetwave_store::{Manifest, Store};

/// Clients see the input's file name, not where it lies on the server; a store without a level
/// set has no `/v1/levelset`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_served_manifest_names_the_input_without_its_directories() {
    let (_d, dir) = make_store(2);
    let mpath = dir.join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["source"] = "/home/someone/private/run-7/input.vtu".into();
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    let r = get(addr, "/v1/manifest", &[]).await;
    assert_eq!(r.status, 200);
    let served: Manifest = serde_json::from_slice(&r.body).unwrap();
    assert_eq!(served.source, "input.vtu");
    assert!(!String::from_utf8_lossy(&r.body).contains("private"));
    let r = get(addr, "/v1/levelset", &[]).await;
    assert_eq!(r.status, 404);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn manifest_base_and_node_ranges_match_the_store() {
    let (_d, dir) = make_store(3);
    let store = Store::open(&dir).unwrap();
    let (addr, _) = start(&dir, ServeConfig::default()).await;

    let r = get(addr, "/healthz", &[]).await;
    assert_eq!(r.status, 200);
    let h: serde_json::Value = serde_json::from_slice(&r.body).unwrap();
    assert_eq!(h["status"], "ok");

    let r = get(addr, "/v1/manifest", &[]).await;
    assert_eq!(r.status, 200);
    assert_eq!(r.headers["content-type"], "application/json");
    let m: Manifest = serde_json::from_slice(&r.body).unwrap();
    // the store's manifest, less the sums of files only the server reads (this store has no
    // level-set band, the one file a client fetches)
    let mut want = store.manifest.clone();
    assert!(want.files.contains_key("blocks.bin"));
    want.files.clear();
    assert_eq!(m, want);

    let r = get(addr, "/v1/base", &[]).await;
    assert_eq!(r.status, 200);
    match decode_server(&r.body).unwrap() {
        ServerMsg::Base(b) => assert_eq!(*b, store.base),
        other => panic!("{other:?}"),
    }

    let n = store.manifest.counts.nodes;
    let coder = BlockCoder::new(&store.base, &store.manifest.encoding);
    for (a, b) in [(0, n), (0, 0), (1, 2), (n / 3, n / 2), (n - 1, n)] {
        let r = get(addr, &format!("/v1/nodes?from={a}&to={b}"), &[]).await;
        assert_eq!(r.status, 200, "{a}..{b}");
        match decode_server(&r.body).unwrap() {
            ServerMsg::Nodes { block, .. } => assert_eq!(
                coder.decode(&block).unwrap(),
                store.read_nodes(a, b).unwrap()
            ),
            other => panic!("{other:?}"),
        }
    }
    for q in [
        format!("from=0&to={}", n + 1),
        "from=5&to=2".into(),
        "from=x&to=2".into(),
        "to=2".into(),
        "from=-1&to=2".into(),
    ] {
        let r = get(addr, &format!("/v1/nodes?{q}"), &[]).await;
        assert_eq!(r.status, 400, "{q}");
    }
    // the range limit
    let (_d2, dir2) = make_store(4);
    let cfg = ServeConfig {
        max_range: 100,
        ..ServeConfig::default()
    };
    let (addr2, _) = start(&dir2, cfg).await;
    assert_eq!(get(addr2, "/v1/nodes?from=0&to=100", &[]).await.status, 200);
    assert_eq!(get(addr2, "/v1/nodes?from=0&to=101", &[]).await.status, 400);
}

/// `/readyz` answers a balancer's probe; `/healthz` counts the block cache's hits and reads, and
/// what it holds within its limit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_and_the_block_cache_are_reported() {
    let (_d, dir) = make_store(4);
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    let r = get(addr, "/readyz", &[]).await;
    assert_eq!((r.status, r.body.as_slice()), (200, &b"ready\n"[..]));
    for _ in 0..2 {
        assert_eq!(get(addr, "/v1/nodes?from=0&to=100", &[]).await.status, 200);
    }
    let r = get(addr, "/healthz", &[]).await;
    let h: serde_json::Value = serde_json::from_slice(&r.body).unwrap();
    let c = &h["block_cache"];
    // the first block is read at start (a corrupt one is refused there), then held
    assert_eq!(
        (c["reads"].as_u64(), c["hits"].as_u64()),
        (Some(1), Some(2)),
        "{h}"
    );
    assert_eq!(c["hit_ratio"].as_f64(), Some(2.0 / 3.0), "{h}");
    assert_eq!(c["held_blocks"].as_u64(), Some(1), "{h}");
    let held = c["held_bytes"].as_u64().unwrap();
    assert!(
        held > 0 && held <= c["limit_bytes"].as_u64().unwrap(),
        "{h}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn token_is_enforced_when_set() {
    let (_d, dir) = make_store(2);
    let cfg = ServeConfig {
        token: Some("s3cret".into()),
        ..ServeConfig::default()
    };
    let (addr, _) = start(&dir, cfg).await;
    for path in [
        "/v1/manifest",
        "/v1/base",
        "/v1/nodes?from=0&to=1",
        "/",
        "/v1/render?width=8&height=8",
    ] {
        assert_eq!(
            get(addr, path, &[]).await.status,
            401,
            "{path} without token"
        );
        let r = get(addr, path, &[("Authorization", "Bearer wrong")]).await;
        assert_eq!(r.status, 401, "{path} with a wrong token");
        let r = get(addr, path, &[("Authorization", "Bearer s3cret")]).await;
        assert_eq!(r.status, 200, "{path} with the token");
    }
    let sep = |p: &str| if p.contains('?') { '&' } else { '?' };
    for path in ["/v1/manifest", "/v1/nodes?from=0&to=1"] {
        let r = get(addr, &format!("{path}{}token=s3cret", sep(path)), &[]).await;
        assert_eq!(r.status, 200, "{path} with ?token=");
        let r = get(addr, &format!("{path}{}token=s3cre", sep(path)), &[]).await;
        assert_eq!(r.status, 401, "{path} with a wrong ?token=");
    }
    // health needs no token
    assert_eq!(get(addr, "/healthz", &[]).await.status, 200);

    // the stream: Hello without the token → Error 401 and close
    let mut ws = connect(addr, "").await;
    send(&mut ws, &hello(None, vec![])).await;
    match recv(&mut ws).await {
        Some(ServerMsg::Error { code, .. }) => assert_eq!(code, 401),
        other => panic!("expected Error 401, got {other:?}"),
    }
    assert!(recv(&mut ws).await.is_none(), "closed after the error");
    let mut ws = connect(addr, "").await;
    send(&mut ws, &hello(Some("nope"), vec![])).await;
    assert!(matches!(
        recv(&mut ws).await,
        Some(ServerMsg::Error { code: 401, .. })
    ));
    // a wrong token on the upgrade request itself is refused before the upgrade
    let url = format!("ws://{addr}/v1/stream?token=nope");
    let r = tokio::time::timeout(T, tokio_tungstenite::connect_async(url))
        .await
        .unwrap();
    assert!(r.is_err(), "upgrade with a wrong token must fail");
    // with the token: everything
    let s = session(addr, "", Some("s3cret")).await;
    assert_eq!(s.nodes.len() as u64, s.manifest.counts.nodes);
    let s = session(addr, "?token=s3cret", None).await;
    assert_eq!(s.nodes.len() as u64, s.manifest.counts.nodes);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn render_rejects_absurd_parameters() {
    let (_d, dir) = make_store(2);
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    for q in [
        "width=0",
        "width=4097",
        "height=100000",
        "width=-5",
        "width=abc",
        "height=1.5",
        "azimuth=nan",
        "azimuth=inf",
        "azimuth=1e300",
        "elevation=91",
        "elevation=-inf",
        "distance=0",
        "distance=-3",
        "distance=NaN",
        "fov=0",
        "fov=180",
        "tol=-1",
        "tol=nan",
        "level=3",
        "level=-1",
        "level=2&tol=1",
        "tf=nope",
        "tf=/etc/passwd",
        "tf=..%2F..%2Fetc%2Fpasswd.json",
        "renderer=vulkan",
        "bogus=1",
    ] {
        let r = get(addr, &format!("/v1/render?{q}"), &[]).await;
        assert_eq!(r.status, 400, "{q}: {}", String::from_utf8_lossy(&r.body));
        assert!(!r.body.is_empty(), "{q}: a message");
    }
    // the page
    let r = get(addr, "/", &[]).await;
    assert_eq!(r.status, 200);
    let page = String::from_utf8_lossy(&r.body);
    assert!(page.contains("/v1/render") && page.contains("mousedown") && page.contains("range"));
    assert!(
        !page.contains("http://") && !page.contains("https://"),
        "no external resources"
    );
}

fn decode_png(b: &[u8]) -> Rgba8Image {
    let img = image::load_from_memory(b).unwrap().to_rgba8();
    Rgba8Image {
        width: img.width(),
        height: img.height(),
        pixels: img.pixels().map(|p| p.0).collect(),
    }
}

/// `/v1/render` gives the same image (so the same PSNR against the reference) as a local render of
/// the same camera, on the CPU reference path and on the default (GPU when there is an adapter) path.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn render_matches_a_local_render_of_the_same_camera() {
    let (_d, dir) = make_store(3);
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    let (w, h, az, el, dist, level) = (64u32, 48u32, 30.0, 20.0, 3.5, 2u8);
    let local = Store::open(&dir).unwrap();
    let mesh = RenderMesh::uniform_level(
        &local.base,
        &local.synthesize_all().unwrap(),
        &local.empty_children().unwrap(),
        level,
    );
    let dist = dist * mesh.diagonal();
    let cam = Orbit {
        target: mesh.center(),
        distance: dist,
        azimuth: az,
        elevation: el,
        fov: 40.0,
    }
    .camera(w, h);
    let tf = TransferFunction::load("default").unwrap();
    let reference = render_reference(&mesh, &cam, &tf);

    for renderer in ["cpu", "auto"] {
        let q = format!(
            "/v1/render?width={w}&height={h}&azimuth={az}&elevation={el}&distance={dist}&level={level}&tf=default&renderer={renderer}"
        );
        let r = get(addr, &q, &[]).await;
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(r.headers["content-type"], "image/png");
        assert_eq!(r.headers["x-tetwave-level"], level.to_string());
        let got = decode_png(&r.body);
        assert_eq!((got.width, got.height), (w, h));
        let who = r.headers["x-tetwave-renderer"].clone();
        let local_img = if who.starts_with("gpu") {
            let ctx = GpuContext::new().unwrap();
            let pt = PtRenderer::new(&ctx);
            let data = pt.upload(&ctx, &mesh).unwrap();
            pt.render(&ctx, &data, &cam, &tf).unwrap().0
        } else {
            assert_eq!(who, "cpu-reference");
            render_reference(&mesh, &cam, &tf)
        };
        let (p_server, p_local) = (psnr(&got, &reference), psnr(&local_img, &reference));
        eprintln!(
            "renderer {who}: PSNR vs reference: server {p_server:.3} dB, local {p_local:.3} dB"
        );
        if p_local.is_infinite() {
            assert!(p_server.is_infinite());
        } else {
            assert!(
                (p_server - p_local).abs() < 0.05,
                "server {p_server} dB vs local {p_local} dB"
            );
        }
        assert!(got.coverage() > 0.05, "the volume is visible");
    }

    // tol picks a level: a huge tolerance gives level 0, tol=0 the finest
    let r = get(
        addr,
        "/v1/render?width=16&height=16&tol=100000&renderer=cpu",
        &[],
    )
    .await;
    assert_eq!(r.status, 200);
    assert_eq!(r.headers["x-tetwave-level"], "0");
    let r = get(
        addr,
        "/v1/render?width=16&height=16&tol=0&renderer=cpu",
        &[],
    )
    .await;
    assert_eq!(r.headers["x-tetwave-level"], "3");
}

/// The fallback page carries a colour legend: the dataset's name and display range (the legend
/// line every client draws) and each preset's colours as a CSS gradient for the bar.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn page_has_a_legend_with_the_name_the_range_and_the_colours() {
    let (_d, dir) = make_store(2);
    let (addr, _) = start(&dir, ServeConfig::default()).await;
    let r = get(addr, "/", &[]).await;
    assert_eq!(r.status, 200);
    let html = String::from_utf8(r.body).unwrap();
    let m = tetwave_store::Store::open(&dir).unwrap().manifest;
    let line = tetwave_render::legend::legend_text(&m.dataset, m.display_value_range());
    assert!(
        html.contains(&format!("<span id=\"ltext\">{line}</span>")),
        "{line}"
    );
    // `auto` fitted to the store's histogram, first in the list, then the presets
    assert!(m.value_histogram.is_some());
    let auto = TransferFunction::for_manifest("auto", &m).unwrap();
    assert_eq!(auto.name, "auto");
    assert!(html.contains("<select id=\"tf\"><option>auto</option>"));
    for (name, tf) in [("auto", auto)].into_iter().chain(
        ["default", "transparent", "opaque", "shells"]
            .map(|n| (n, TransferFunction::preset(n).unwrap())),
    ) {
        let g = tetwave_render::legend::css_gradient(&tf, 17);
        assert!(html.contains(&format!("\"{name}\": \"{g}\"")), "{name}");
    }
    assert!(!html.contains("{{"), "a placeholder was left");
}
