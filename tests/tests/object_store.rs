//! Stores in object storage, with real components on loopback, started here and stopped at the
//! end: a 3-node garage cluster (S3-compatible, replication factor 3; `scripts/garage-cluster`)
//! and nginx serving a store folder over HTTP with range requests. Fails, never skips, when
//! garage or nginx is missing (`scripts/setup` installs both).
//!
//! One test function: the AWS_* variables it sets are the process's own.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;
use tetwave_server::analysis::ErrorBound;
use tetwave_server::prepare::{parts, prepare, verify, PartsArgs, PrepareOptions};
use tetwave_store::{Location, OpenOptions, Store};

mod common;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// A garage cluster under a temporary folder, stopped when dropped.
struct Garage {
    dir: tempfile::TempDir,
}

impl Garage {
    fn start() -> Garage {
        tetwave_tests::need(
            "garage",
            "scripts/setup runs `cargo install garage --version 2.5.0 --locked`",
        );
        let dir = tempfile::tempdir().unwrap();
        let script = repo().join("scripts/garage-cluster");
        let st = Command::new(&script)
            .arg("start")
            .arg(dir.path())
            .status()
            .unwrap();
        assert!(st.success(), "scripts/garage-cluster start failed");
        let env = std::fs::read_to_string(dir.path().join("env")).unwrap();
        for line in env.lines() {
            let (k, v) = line
                .trim_start_matches("export ")
                .split_once('=')
                .expect("KEY=VALUE");
            std::env::set_var(k, v);
        }
        Garage { dir }
    }

    fn node(&self, how: &str, k: u32) {
        let st = Command::new(repo().join("scripts/garage-cluster"))
            .arg(how)
            .arg(self.dir.path())
            .arg(k.to_string())
            .status()
            .unwrap();
        assert!(st.success(), "garage-cluster {how} {k}");
    }
}

impl Drop for Garage {
    fn drop(&mut self) {
        let _ = Command::new(repo().join("scripts/garage-cluster"))
            .arg("stop")
            .arg(self.dir.path())
            .status();
    }
}

#[test]
fn stores_in_a_bucket_and_over_http() {
    let garage = Garage::start();
    let work = tempfile::tempdir().unwrap();
    let local = work.path().join("www/h6");
    let mut o = PrepareOptions::new("synthetic:harmonic", &local);
    o.levels = Some(6);
    o.max_error = Some(ErrorBound::parse("0.1%").unwrap());
    let here = prepare(&o).unwrap();
    // the same store written to the bucket (through a staging folder, manifest last)
    let url = "s3://tetwave/stores/h6";
    let o3 = PrepareOptions {
        out: url.into(),
        stage: Some(work.path().join("stage")),
        ..o.clone()
    };
    let there = prepare(&o3).unwrap();
    assert_eq!(there.store, url);
    assert_eq!(there.bytes, here.bytes);
    assert!(
        !work.path().join("stage").read_dir().unwrap().any(|_| true),
        "the staging folder is emptied"
    );
    // every file the same bytes as the directory's: read back and checksummed
    let s3 = Store::open_with(
        Path::new(url),
        OpenOptions {
            verify_checksums: true,
            ..Default::default()
        },
    )
    .unwrap();
    let dir = Store::open(&local).unwrap();
    assert_eq!(s3.manifest.files, dir.manifest.files);
    assert_eq!(s3.synthesize_all().unwrap(), dir.synthesize_all().unwrap());
    verify(Path::new(url)).unwrap();

    // served from the bucket, read directly from it, and from nginx: one final mesh
    let srv = common::serve(Path::new(url), "view");
    let push = common::converged(srv.url(), &work.path().join("push")).unwrap();
    drop(srv);
    let direct = common::converged(url, &work.path().join("direct")).unwrap();
    let root = work.path().join("www").display().to_string();
    let nginx = tetwave_tests::Nginx::start(&format!("root {root}; location / {{ }}"));
    let http_url = format!("http://127.0.0.1:{}/h6", nginx.port);
    let http = common::converged(&http_url, &work.path().join("http")).unwrap();
    let want = common::leaves(&push);
    assert!(push.report.frames.last().unwrap().view_complete);
    for (name, s) in [("s3", &direct), ("http", &http)] {
        assert!(s.report.frames.last().unwrap().view_complete, "{name}");
        assert_eq!(common::leaves(s), want, "{name}: another final mesh");
        s.mesh.as_ref().unwrap().check_conformity().unwrap();
        // what was fetched: some of the store, within 1.5× what the push stream sent
        assert!(
            s.report.bytes_received as f64 <= 1.5 * push.report.bytes_received as f64,
            "{name}: {} bytes against the push stream's {}",
            s.report.bytes_received,
            push.report.bytes_received
        );
    }
    eprintln!(
        "bytes: push {}, s3 {}, http {}; nodes: push {}, s3 {}",
        push.report.bytes_received,
        direct.report.bytes_received,
        http.report.bytes_received,
        push.report.nodes_received,
        direct.report.nodes_received
    );

    // a garage node lost mid-stream (replication 3: the others answer)
    let killer = {
        let dir = garage.dir.path().to_path_buf();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(150));
            let st = Command::new(repo().join("scripts/garage-cluster"))
                .arg("kill")
                .arg(&dir)
                .arg("2")
                .status()
                .unwrap();
            assert!(st.success());
        })
    };
    let lossy = common::converged(url, &work.path().join("lossy")).unwrap();
    killer.join().unwrap();
    assert_eq!(common::leaves(&lossy), want, "a node lost mid-stream");
    garage.node("restart", 2);

    // a missing object: one error naming it, from every reader
    let broken = "s3://tetwave/stores/broken";
    prepare(&PrepareOptions {
        out: broken.into(),
        ..o3.clone()
    })
    .unwrap();
    tetwave_store::delete_file(&Location::parse(broken).unwrap(), "blocks.bin").unwrap();
    let e = Store::open(Path::new(broken)).err().unwrap().to_string();
    assert!(e.contains("s3://tetwave/stores/broken/blocks.bin"), "{e}");
    let e = common::converged(broken, &work.path().join("broken"))
        .err()
        .unwrap();
    assert!(e.contains("s3://tetwave/stores/broken/blocks.bin"), "{e}");
    let e = Store::open(Path::new("s3://tetwave/stores/none"))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("s3://tetwave/stores/none/manifest.json"), "{e}");

    // by parts into the bucket: each part's files go up as it ends; the finish fetches them,
    // writes the store there and removes them; the store is the one-process store's
    let dims = [33usize, 17, 65];
    let raw = work.path().join("grid.f32");
    let v: Vec<u8> = (0..dims[0] * dims[1] * dims[2])
        .flat_map(|i| ((i % 97) as f32 * 0.5 + (i / 1000) as f32).to_le_bytes())
        .collect();
    std::fs::write(&raw, v).unwrap();
    let mut g = PrepareOptions::new(raw.to_str().unwrap(), &work.path().join("whole"));
    g.read.grid.dims = Some(dims);
    g.read.grid.dtype = "f32".into();
    g.levels = Some(4);
    g.max_error = Some(ErrorBound::parse("0.5%").unwrap());
    prepare(&g).unwrap();
    let parted = "s3://tetwave/stores/parted";
    let part = |k: Option<u32>| PrepareOptions {
        out: parted.into(),
        stage: Some(work.path().join("stage")),
        by_parts: PartsArgs {
            parts: Some(3),
            part: k,
            finish: k.is_none(),
        },
        ..g.clone()
    };
    parts::prepare_part(&part(Some(0)), 3, 0).unwrap();
    parts::prepare_part(&part(Some(2)), 3, 2).unwrap();
    let e = prepare(&part(None)).err().unwrap().to_string();
    assert!(e.contains("(part 1)"), "a missing part is named: {e}");
    parts::prepare_part(&part(Some(1)), 3, 1).unwrap();
    prepare(&part(None)).unwrap();
    let whole = Store::open(&work.path().join("whole")).unwrap();
    let there = Store::open(Path::new(parted)).unwrap();
    assert_eq!(
        there.manifest.files, whole.manifest.files,
        "not the one-process store"
    );
    let loc = Location::parse(parted).unwrap();
    let probe = work.path().join("probe");
    assert!(
        !tetwave_store::download_file(&loc.join("parts/part-1-of-3"), "part.json", &probe).unwrap(),
        "the parts are removed once the store is written"
    );

    // wrong credentials: one clear error, no secret in it
    let secret = std::env::var("AWS_SECRET_ACCESS_KEY").unwrap();
    std::env::set_var("AWS_SECRET_ACCESS_KEY", "0".repeat(64));
    let e = Store::open(Path::new(url)).err().unwrap().to_string();
    std::env::set_var("AWS_SECRET_ACCESS_KEY", &secret);
    assert!(e.contains("manifest.json"), "{e}");
    assert!(!e.contains(&secret), "a secret in an error: {e}");
    assert!(e.contains("access denied") || e.contains("403"), "{e}");

    // Zarr volumes read chunk by chunk from the bucket and from nginx, with no copy on disk:
    // each prepares into the store of its local folder, byte for byte
    let vf = work.path().join("www/vf");
    let python = repo().join(".venv-volumes/bin/python");
    let out = Command::new(&python)
        .arg(repo().join("scripts/volume-fixtures.py"))
        .arg(&vf)
        .output()
        .unwrap_or_else(|e| panic!("{} ({e}): run scripts/setup", python.display()));
    assert!(
        out.status.success(),
        "volume-fixtures.py: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    for (name, scalar) in [("zarr3_sharded", None), ("ome05", Some("1"))] {
        let folder = vf.join(format!("{name}.zarr"));
        let bucket = format!("s3://tetwave/volumes/{name}.zarr");
        let to = Location::parse(&bucket).unwrap();
        let mut files = vec![folder.clone()];
        while let Some(d) = files.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    files.push(p);
                } else {
                    let rel = p
                        .strip_prefix(&folder)
                        .unwrap()
                        .to_str()
                        .unwrap()
                        .to_string();
                    tetwave_store::upload_file(&p, &to, &rel).unwrap();
                }
            }
        }
        let http = format!("http://127.0.0.1:{}/vf/{name}.zarr", nginx.port);
        let prepared = |input: &str, dir: &str| {
            let mut o = PrepareOptions::new(input, &work.path().join(dir));
            o.read.scalar = scalar.map(str::to_string);
            o.max_error = Some(ErrorBound::parse("0.5%").unwrap());
            prepare(&o).unwrap_or_else(|e| panic!("{input}: {e}"));
            Store::open(&work.path().join(dir)).unwrap()
        };
        let here = prepared(folder.to_str().unwrap(), &format!("{name}-here"));
        for (input, dir) in [(&bucket, "s3"), (&http, "http")] {
            let there = prepared(input, &format!("{name}-{dir}"));
            assert_eq!(
                there.manifest.files, here.manifest.files,
                "{input}: another store than the folder's"
            );
        }
    }
    // a missing array, and wrong credentials: one error naming the object, no secret in it
    let e = prepare(&PrepareOptions::new(
        "s3://tetwave/volumes/none.zarr",
        &work.path().join("none"),
    ))
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("s3://tetwave/volumes/none.zarr"), "{e}");
    std::env::set_var("AWS_SECRET_ACCESS_KEY", "0".repeat(64));
    let e = prepare(&PrepareOptions::new(
        "s3://tetwave/volumes/zarr3_sharded.zarr",
        &work.path().join("denied"),
    ))
    .err()
    .unwrap()
    .to_string();
    std::env::set_var("AWS_SECRET_ACCESS_KEY", &secret);
    assert!(
        e.contains("s3://tetwave/volumes/zarr3_sharded.zarr/"),
        "{e}"
    );
    assert!(!e.contains(&secret), "a secret in an error: {e}");
    assert!(e.contains("access denied") || e.contains("403"), "{e}");
}
