//! Tests of the Zarr reader: arrays whose chunks `zarrs` writes here (metadata written by hand
//! as zarr-python writes it), OME-Zarr groups, refusals, corrupted stores, and a store served
//! over HTTP on 127.0.0.1 by a server in the test.

use super::*;
use crate::volume::{open_reader, Volume};
use serde_json::json;
use std::io::{BufRead, BufReader, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use zarrs::array::Element;
use zarrs::filesystem::FilesystemStore;
use zarrs::storage::storage_adapter::performance_metrics::PerformanceMetricsStorageAdapter;

/// A fresh folder for one test's files.
fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir()
        .join(format!("tetwave-zarr-{}", std::process::id()))
        .join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The value at array index `ix` (C order): x + 10 y + 100 z + 1000 c ... (dims under 10).
fn val(ix: &[u64]) -> f64 {
    ix.iter()
        .rev()
        .enumerate()
        .map(|(k, &i)| i as f64 * 10f64.powi(k as i32))
        .sum()
}

/// Every index of `shape` in C order (the last fastest).
fn c_order(shape: &[u64]) -> Vec<Vec<u64>> {
    let mut out = vec![vec![]];
    for &n in shape {
        out = out
            .into_iter()
            .flat_map(|p| {
                (0..n).map(move |i| {
                    let mut q = p.clone();
                    q.push(i);
                    q
                })
            })
            .collect();
    }
    out
}

fn write_json(path: &Path, v: &Value) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, serde_json::to_vec_pretty(v).unwrap()).unwrap();
}

/// Writes the samples `f(index)` of the array at `node` of the store `dir` (its metadata
/// already there), chunk by chunk, with `zarrs`.
fn fill<T: Element>(dir: &Path, node: &str, f: impl Fn(&[u64]) -> T) {
    let store = Arc::new(FilesystemStore::new(dir).unwrap());
    let array = Array::open(store, node).unwrap();
    let shape = array.shape().to_vec();
    let data: Vec<T> = c_order(&shape).iter().map(|ix| f(ix)).collect();
    array.store_array_subset(&array.subset_all(), data).unwrap();
}

/// Fills with [`val`] in the sample type `dtype` ([`expect_val`]).
fn fill_val(dir: &Path, node: &str, dtype: DType) {
    let small = |ix: &[u64]| val(ix) as u64 % 127;
    match dtype {
        DType::U8 => fill(dir, node, |ix| small(ix) as u8 + 128),
        DType::I8 => fill(dir, node, |ix| -(small(ix) as i8)),
        DType::U16 => fill(dir, node, |ix| val(ix) as u16),
        DType::I16 => fill(dir, node, |ix| -(val(ix) as i16)),
        DType::U32 => fill(dir, node, |ix| val(ix) as u32 + 100_000),
        DType::I32 => fill(dir, node, |ix| -(val(ix) as i32)),
        DType::F32 => fill(dir, node, |ix| val(ix) as f32 + 0.5),
        DType::F64 => fill(dir, node, |ix| val(ix) - 0.25),
    }
}

/// What [`fill_val`] wrote at `ix`, as f64.
fn expect_val(dtype: DType, ix: &[u64]) -> f64 {
    let v = val(ix);
    let small = (v as u64 % 127) as f64;
    match dtype {
        DType::U8 => small + 128.0,
        DType::I8 => -small,
        DType::U16 => v,
        DType::I16 | DType::I32 => -v,
        DType::U32 => v + 100_000.0,
        DType::F32 => v + 0.5,
        DType::F64 => v - 0.25,
    }
}

/// A v3 array's `zarr.json`.
fn v3(shape: &[u64], chunks: &[u64], dtype: &str, codecs: Value) -> Value {
    json!({
        "zarr_format": 3,
        "node_type": "array",
        "shape": shape,
        "data_type": dtype,
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunks}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": 0,
        "codecs": codecs,
        "attributes": {},
    })
}

/// A v2 array's `.zarray`.
fn v2(shape: &[u64], chunks: &[u64], dtype: &str, order: &str, compressor: Value) -> Value {
    json!({
        "zarr_format": 2,
        "shape": shape,
        "chunks": chunks,
        "dtype": dtype,
        "compressor": compressor,
        "fill_value": 0,
        "order": order,
        "filters": null,
    })
}

fn bytes_le() -> Value {
    json!({"name": "bytes", "configuration": {"endian": "little"}})
}

fn zarr_name(t: DType) -> &'static str {
    match t {
        DType::U8 => "uint8",
        DType::I8 => "int8",
        DType::U16 => "uint16",
        DType::I16 => "int16",
        DType::U32 => "uint32",
        DType::I32 => "int32",
        DType::F32 => "float32",
        DType::F64 => "float64",
    }
}

fn opts(scalar: Option<&str>, frame: Option<usize>) -> VolumeOptions {
    VolumeOptions {
        scalar: scalar.map(ScalarChoice::parse),
        frame,
        ..Default::default()
    }
}

fn open_dir(dir: &Path, o: &VolumeOptions) -> Result<Box<dyn VolumeReader>, VolumeError> {
    open_reader(dir, VolumeFormat::Zarr, o)
}

/// Checks the box `lo..hi` of a reader of a 3D (z, y, x) array against `expect(z, y, x)`.
fn check_box(
    r: &mut dyn VolumeReader,
    lo: [usize; 3],
    hi: [usize; 3],
    expect: impl Fn(u64, u64, u64) -> f64,
) {
    let s = r.read_box(lo, hi).unwrap();
    let n: usize = (0..3).map(|a| hi[a] - lo[a]).product();
    assert_eq!(s.len(), n);
    let mut at = 0;
    for k in lo[2]..hi[2] {
        for j in lo[1]..hi[1] {
            for i in lo[0]..hi[0] {
                let want = expect(k as u64, j as u64, i as u64);
                assert_eq!(
                    s.get(at),
                    want,
                    "voxel ({i}, {j}, {k}) of box {lo:?}..{hi:?}"
                );
                at += 1;
            }
        }
    }
}

#[test]
fn v3_arrays_of_every_codec_and_type_read_exact_boxes() {
    let shape = [5u64, 6, 7];
    let chunks = [2u64, 4, 3];
    let codec_sets: Vec<(&str, Value)> = vec![
        ("bytes", json!([bytes_le()])),
        (
            "big-endian",
            json!([{"name": "bytes", "configuration": {"endian": "big"}}]),
        ),
        (
            "gzip",
            json!([bytes_le(), {"name": "gzip", "configuration": {"level": 5}}]),
        ),
        (
            "zstd+crc32c",
            json!([bytes_le(), {"name": "zstd", "configuration": {"level": 3, "checksum": true}},
                   {"name": "crc32c"}]),
        ),
        (
            "blosc",
            json!([bytes_le(), {"name": "blosc", "configuration":
                {"cname": "lz4", "clevel": 5, "shuffle": "shuffle", "typesize": 2, "blocksize": 0}}]),
        ),
        (
            "transpose",
            json!([{"name": "transpose", "configuration": {"order": [2, 0, 1]}}, bytes_le(),
                   {"name": "zstd", "configuration": {"level": 1, "checksum": false}}]),
        ),
    ];
    for (what, codecs) in codec_sets {
        for t in DType::ALL {
            if t.bytes() == 1 && what == "big-endian" {
                continue; // the bytes codec of 1-byte types has no endian
            }
            let dir = tmp(&format!("v3-{what}-{t}"));
            let mut codecs = codecs.clone();
            if t.bytes() == 1 {
                codecs = json!(codecs
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|c| if c["name"] == "bytes" {
                        json!({"name": "bytes"})
                    } else {
                        c.clone()
                    })
                    .collect::<Vec<_>>());
            }
            write_json(
                &dir.join("zarr.json"),
                &v3(&shape, &chunks, zarr_name(t), codecs),
            );
            fill_val(&dir, "/", t);
            let mut r = open_dir(&dir, &VolumeOptions::default())
                .unwrap_or_else(|e| panic!("{what} {t}: {e}"));
            let h = r.header().clone();
            assert_eq!(h.dims, [7, 6, 5], "{what} {t}");
            assert_eq!(h.dtype, t);
            assert_eq!(h.spacing, [1.0; 3]);
            assert_eq!(h.origin, [0.0; 3]);
            assert_eq!(
                h.axes.map(|m| (m.axis, m.flip)),
                [(0, false), (1, false), (2, false)]
            );
            let e = |z, y, x| expect_val(t, &[z, y, x]);
            check_box(r.as_mut(), [0, 0, 0], [7, 6, 5], e);
            check_box(r.as_mut(), [1, 2, 1], [6, 5, 4], e);
            check_box(r.as_mut(), [6, 5, 4], [7, 6, 5], e);
        }
    }
}

#[test]
fn v2_arrays_in_c_and_f_order_with_each_compressor() {
    let shape = [4u64, 5, 6];
    let chunks = [3u64, 2, 4];
    let compressors = [
        json!(null),
        json!({"id": "blosc", "cname": "lz4", "clevel": 5, "shuffle": 1, "blocksize": 0}),
        json!({"id": "blosc", "cname": "zstd", "clevel": 3, "shuffle": 2, "blocksize": 0}),
        json!({"id": "zstd", "level": 3}),
        json!({"id": "gzip", "level": 5}),
        json!({"id": "zlib", "level": 5}),
    ];
    for (n, comp) in compressors.iter().enumerate() {
        for order in ["C", "F"] {
            for (dtype, t) in [
                ("<u2", DType::U16),
                (">i4", DType::I32),
                ("<f8", DType::F64),
                ("|u1", DType::U8),
            ] {
                let dir = tmp(&format!("v2-{n}-{order}-{t}"));
                write_json(
                    &dir.join(".zarray"),
                    &v2(&shape, &chunks, dtype, order, comp.clone()),
                );
                fill_val(&dir, "/", t);
                let mut r = open_dir(&dir, &VolumeOptions::default())
                    .unwrap_or_else(|e| panic!("{comp} {order} {dtype}: {e}"));
                assert_eq!(r.header().dims, [6, 5, 4]);
                assert_eq!(r.header().dtype, t);
                assert!(
                    r.header().notes[0].contains("Zarr v2"),
                    "{:?}",
                    r.header().notes
                );
                let e = |z, y, x| expect_val(t, &[z, y, x]);
                check_box(r.as_mut(), [0, 0, 0], [6, 5, 4], e);
                check_box(r.as_mut(), [3, 1, 2], [5, 4, 3], e);
            }
        }
    }
}

#[test]
fn sharded_boxes_read_the_shard_index_and_their_inner_chunks_only() {
    let dir = tmp("sharded");
    let shape = [32u64, 32, 32];
    let codecs = json!([{
        "name": "sharding_indexed",
        "configuration": {
            "chunk_shape": [4, 4, 4],
            "codecs": [bytes_le()],
            "index_codecs": [bytes_le(), {"name": "crc32c"}],
            "index_location": "end",
        }
    }]);
    write_json(
        &dir.join("zarr.json"),
        &v3(&shape, &[16, 16, 16], "uint16", codecs),
    );
    let lin = |ix: &[u64]| (ix[0] * 1024 + ix[1] * 32 + ix[2]) as u16;
    fill(&dir, "/", lin);
    let shard_bytes = std::fs::metadata(dir.join("c/0/0/0")).unwrap().len();
    assert!(shard_bytes >= 16 * 16 * 16 * 2, "{shard_bytes}");
    let metrics = Arc::new(PerformanceMetricsStorageAdapter::new(Arc::new(
        FilesystemStore::new(&dir).unwrap(),
    )));
    let src = Source {
        name: dir.clone(),
        storage: metrics.clone(),
        remote: None,
    };
    let mut r = open_source(&src, &VolumeOptions::default()).unwrap();
    assert_eq!(r.header().dims, [32, 32, 32]);
    let e = |z: u64, y: u64, x: u64| lin(&[z, y, x]) as f64;
    // one inner chunk of one shard: its 128 bytes and the shard's index
    let before = metrics.bytes_read();
    check_box(r.as_mut(), [5, 6, 7], [8, 8, 8], e);
    let read = metrics.bytes_read() - before;
    let index = 4 * 4 * 4 * 16 + 4;
    assert!(
        read <= 4 * 4 * 4 * 2 + index,
        "{read} bytes read for one inner chunk of a shard of {shard_bytes}"
    );
    // a box across shards and inner chunks: the values, and still less than its shards
    let before = metrics.bytes_read();
    check_box(r.as_mut(), [14, 13, 15], [18, 19, 17], e);
    let read = metrics.bytes_read() - before;
    assert!(
        read < shard_bytes as usize,
        "{read} bytes for a box of 4×6×2 voxels"
    );
    check_box(r.as_mut(), [0, 0, 0], [32, 32, 32], e);
}

/// An OME-Zarr 0.4 image as zarr-python and ome-zarr-py write it: a v2 group whose `.zattrs`
/// hold the multiscales, two levels of (c, z, y, x) with blosc.
fn ome_04(dir: &Path) {
    write_json(&dir.join(".zgroup"), &json!({"zarr_format": 2}));
    write_json(
        &dir.join(".zattrs"),
        &json!({
            "multiscales": [{
                "version": "0.4",
                "name": "cells",
                "axes": [
                    {"name": "c", "type": "channel"},
                    {"name": "z", "type": "space", "unit": "micrometer"},
                    {"name": "y", "type": "space", "unit": "micrometer"},
                    {"name": "x", "type": "space", "unit": "micrometer"}
                ],
                "datasets": [
                    {"path": "0", "coordinateTransformations": [
                        {"type": "scale", "scale": [1.0, 2.0, 0.5, 0.25]},
                        {"type": "translation", "translation": [0.0, 10.0, 20.0, 30.0]}]},
                    {"path": "1", "coordinateTransformations": [
                        {"type": "scale", "scale": [1.0, 4.0, 1.0, 0.5]}]}
                ],
                "coordinateTransformations": [{"type": "scale", "scale": [1.0, 2.0, 2.0, 2.0]}]
            }],
            "omero": {"channels": [{"label": "DAPI"}, {"label": "GFP"}]}
        }),
    );
    let blosc = json!({"id": "blosc", "cname": "lz4", "clevel": 5, "shuffle": 1, "blocksize": 0});
    write_json(
        &dir.join("0/.zarray"),
        &v2(&[2, 4, 5, 6], &[1, 2, 3, 4], "<u2", "C", blosc.clone()),
    );
    write_json(
        &dir.join("1/.zarray"),
        &v2(&[2, 2, 5, 3], &[1, 2, 3, 4], "<u2", "C", blosc),
    );
    fill_val(dir, "/0", DType::U16);
    fill_val(dir, "/1", DType::U16);
}

#[test]
fn ome_zarr_04_gives_the_finest_levels_geometry_and_channels() {
    let dir = tmp("ome04.zarr");
    ome_04(&dir);
    assert_eq!(crate::volume::sniff(&dir), Some(VolumeFormat::Zarr));
    let e = open_dir(&dir, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("0 (DAPI), 1 (GFP)"), "{e}");
    let e = open_dir(&dir, &opts(Some("2"), None))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("--scalar 2"), "{e}");
    let e = open_dir(&dir, &opts(Some("RFP"), None))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("RFP") && e.contains("GFP"), "{e}");
    for (choice, c) in [("GFP", 1u64), ("0", 0)] {
        let mut r = open_dir(&dir, &opts(Some(choice), None)).unwrap();
        let h = r.header().clone();
        assert_eq!(h.dims, [6, 5, 4]);
        assert_eq!(h.dtype, DType::U16);
        // the dataset's scale and translation, then the multiscale's scale
        assert_eq!(h.spacing, [0.5, 1.0, 4.0]);
        assert_eq!(h.origin, [60.0, 40.0, 20.0]);
        assert_eq!(h.length_unit.as_deref(), Some("um"));
        assert!(
            h.notes.iter().any(|n| n.contains("OME-Zarr 0.4")),
            "{:?}",
            h.notes
        );
        assert!(
            h.notes.iter().any(|n| n.contains("channel")),
            "{:?}",
            h.notes
        );
        check_box(r.as_mut(), [1, 1, 1], [6, 5, 4], |z, y, x| {
            val(&[c, z, y, x])
        });
    }
    let mut r = open_dir(&dir, &opts(Some("mag"), None)).unwrap();
    assert_eq!(r.header().dtype, DType::F32);
    let s = r.read_box([0, 0, 0], [6, 5, 4]).unwrap();
    for (at, ix) in c_order(&[4, 5, 6]).iter().enumerate() {
        let (a, b) = (
            val(&[0, ix[0], ix[1], ix[2]]),
            val(&[1, ix[0], ix[1], ix[2]]),
        );
        assert_eq!(s.get(at), (a * a + b * b).sqrt() as f32 as f64);
    }
    // the world frame through Volume: x, y, z as named
    let mut v = Volume::open(&dir, None, &opts(Some("1"), None)).unwrap();
    assert_eq!(v.dims, [6, 5, 4]);
    let b = v.read_block(0..5, 2..3).unwrap();
    assert_eq!(b.get(0), val(&[1, 2, 0, 0]));
    assert_eq!(b.get(6 * 5 - 1), val(&[1, 2, 4, 5]));
}

#[test]
fn bioformats2raw_layouts_read_their_first_image() {
    let dir = tmp("bf2raw.zarr");
    write_json(&dir.join(".zgroup"), &json!({"zarr_format": 2}));
    write_json(&dir.join(".zattrs"), &json!({"bioformats2raw.layout": 3}));
    ome_04(&dir.join("0"));
    let mut r = open_dir(&dir, &opts(Some("DAPI"), None)).unwrap();
    let h = r.header().clone();
    assert_eq!(h.spacing, [0.5, 1.0, 4.0]);
    assert!(
        h.notes.iter().any(|n| n.contains("bioformats2raw")),
        "{:?}",
        h.notes
    );
    check_box(r.as_mut(), [0, 0, 0], [6, 5, 4], |z, y, x| {
        val(&[0, z, y, x])
    });
}

#[test]
fn a_level_opened_by_itself_takes_its_images_geometry() {
    let dir = tmp("ome-level.zarr");
    ome_04(&dir);
    let mut r = open_dir(&dir.join("0"), &opts(Some("1"), None)).unwrap();
    let h = r.header().clone();
    assert_eq!(h.spacing, [0.5, 1.0, 4.0]);
    assert_eq!(h.origin, [60.0, 40.0, 20.0]);
    assert!(h.notes.iter().any(|n| n.contains("GFP")), "{:?}", h.notes);
    check_box(r.as_mut(), [0, 0, 0], [6, 5, 4], |z, y, x| {
        val(&[1, z, y, x])
    });
    let r = open_dir(&dir.join("1"), &opts(Some("0"), None)).unwrap();
    assert_eq!(r.header().dims, [3, 5, 2]);
    assert_eq!(r.header().spacing, [1.0, 2.0, 8.0]);
}

/// An OME-Zarr 0.5 image: a v3 group, `ome` attributes, a sharded (t, z, y, x) level.
fn ome_05(dir: &Path) {
    write_json(
        &dir.join("zarr.json"),
        &json!({
            "zarr_format": 3,
            "node_type": "group",
            "attributes": {"ome": {
                "version": "0.5",
                "multiscales": [{
                    "axes": [
                        {"name": "t", "type": "time", "unit": "second"},
                        {"name": "z", "type": "space", "unit": "millimeter"},
                        {"name": "y", "type": "space", "unit": "millimeter"},
                        {"name": "x", "type": "space", "unit": "millimeter"}
                    ],
                    "datasets": [{"path": "s0", "coordinateTransformations": [
                        {"type": "scale", "scale": [1.0, 1.5, -1.5, 1.5]}]}]
                }]
            }}
        }),
    );
    let codecs = json!([{
        "name": "sharding_indexed",
        "configuration": {
            "chunk_shape": [1, 2, 2, 2],
            "codecs": [bytes_le(), {"name": "zstd", "configuration": {"level": 3, "checksum": false}}],
            "index_codecs": [bytes_le(), {"name": "crc32c"}],
            "index_location": "end",
        }
    }]);
    let mut meta = v3(&[3, 4, 5, 6], &[1, 4, 4, 4], "float32", codecs);
    meta["dimension_names"] = json!(["t", "z", "y", "x"]);
    write_json(&dir.join("s0/zarr.json"), &meta);
    fill_val(dir, "/s0", DType::F32);
}

#[test]
fn ome_zarr_05_with_time_reads_the_frame_chosen() {
    let dir = tmp("ome05.zarr");
    ome_05(&dir);
    let e = open_dir(&dir, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("3 frames") && e.contains("--frame"), "{e}");
    let e = open_dir(&dir, &opts(None, Some(3)))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("--frame 3"), "{e}");
    let mut r = open_dir(&dir, &opts(None, Some(2))).unwrap();
    let h = r.header().clone();
    assert_eq!(h.dims, [6, 5, 4]);
    assert_eq!(h.dtype, DType::F32);
    assert_eq!(h.spacing, [1.5, 1.5, 1.5]);
    assert_eq!(
        h.axes.map(|m| (m.axis, m.flip)),
        [(0, false), (1, true), (2, false)]
    );
    assert_eq!(h.length_unit.as_deref(), Some("mm"));
    assert!(
        h.notes.iter().any(|n| n.contains("OME-Zarr 0.5")),
        "{:?}",
        h.notes
    );
    assert!(
        h.notes.iter().any(|n| n.contains("frame 2 of 3")),
        "{:?}",
        h.notes
    );
    check_box(r.as_mut(), [0, 0, 0], [6, 5, 4], |z, y, x| {
        expect_val(DType::F32, &[2, z, y, x])
    });
    check_box(r.as_mut(), [3, 1, 1], [5, 4, 3], |z, y, x| {
        expect_val(DType::F32, &[2, z, y, x])
    });
    // the flipped y: the world's first row is the file's last
    let mut v = Volume::open(&dir, None, &opts(None, Some(0))).unwrap();
    assert_eq!(v.origin, [0.0, -6.0, 0.0]);
    let b = v.read_block(0..1, 0..1).unwrap();
    assert_eq!(b.get(0), expect_val(DType::F32, &[0, 0, 4, 0]));
}

#[test]
fn dimension_names_say_which_dim_is_which() {
    // x slowest: file axis 0 (the last dim) is z
    let dir = tmp("names-xyz");
    let mut meta = v3(&[4, 5, 6], &[4, 5, 6], "int16", json!([bytes_le()]));
    meta["dimension_names"] = json!(["x", "y", "z"]);
    write_json(&dir.join("zarr.json"), &meta);
    fill_val(&dir, "/", DType::I16);
    let r = open_dir(&dir, &VolumeOptions::default()).unwrap();
    assert_eq!(r.header().dims, [6, 5, 4]);
    assert_eq!(r.header().axes.map(|m| m.axis), [2, 1, 0]);
    let mut v = Volume::open(&dir, None, &VolumeOptions::default()).unwrap();
    assert_eq!(v.dims, [4, 5, 6]);
    let b = v.read_block(0..5, 0..6).unwrap();
    for (at, ix) in c_order(&[6, 5, 4]).iter().enumerate() {
        // world (x, y, z) = array (x, y, z)
        assert_eq!(b.get(at), -val(&[ix[2], ix[1], ix[0]]));
    }
    // names that say nothing: z, y, x by count
    let dir = tmp("names-dim_k");
    let mut meta = v3(&[4, 5, 6], &[4, 5, 6], "int16", json!([bytes_le()]));
    meta["dimension_names"] = json!(["dim_0", "dim_1", "dim_2"]);
    write_json(&dir.join("zarr.json"), &meta);
    let r = open_dir(&dir, &VolumeOptions::default()).unwrap();
    assert_eq!(r.header().axes.map(|m| m.axis), [0, 1, 2]);
    // v2 with xarray's _ARRAY_DIMENSIONS: (c, z, y, x)
    let dir = tmp("names-xarray");
    write_json(
        &dir.join(".zarray"),
        &v2(&[3, 2, 3, 4], &[1, 2, 3, 4], "|u1", "C", json!(null)),
    );
    write_json(
        &dir.join(".zattrs"),
        &json!({"_ARRAY_DIMENSIONS": ["c", "z", "y", "x"]}),
    );
    fill_val(&dir, "/", DType::U8);
    let e = open_dir(&dir, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("3 components"), "{e}");
    let mut r = open_dir(&dir, &opts(Some("2"), None)).unwrap();
    assert_eq!(r.header().dims, [4, 3, 2]);
    check_box(r.as_mut(), [0, 0, 0], [4, 3, 2], |z, y, x| {
        expect_val(DType::U8, &[2, z, y, x])
    });
}

#[test]
fn plain_groups_ambiguous_arrays_and_other_types_are_refused() {
    // a group without multiscales: its arrays listed
    let dir = tmp("plain-group");
    write_json(
        &dir.join("zarr.json"),
        &json!({"zarr_format": 3, "node_type": "group"}),
    );
    for a in ["b", "a10", "a2"] {
        write_json(
            &dir.join(a).join("zarr.json"),
            &v3(&[2, 2, 2], &[2, 2, 2], "uint8", json!([{"name": "bytes"}])),
        );
    }
    write_json(&dir.join("g/.zgroup"), &json!({"zarr_format": 2}));
    let e = open_dir(&dir, &VolumeOptions::default()).err().unwrap();
    assert!(matches!(e, VolumeError::Unsupported { .. }), "{e}");
    let e = e.to_string();
    assert!(e.contains("a2, a10, b, g (a group)"), "{e}");
    // 4D without axes or names
    let dir = tmp("4d");
    write_json(
        &dir.join("zarr.json"),
        &v3(
            &[2, 3, 4, 5],
            &[2, 3, 4, 5],
            "uint8",
            json!([{"name": "bytes"}]),
        ),
    );
    let e = open_dir(&dir, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("OME-Zarr") && e.contains("[2, 3, 4, 5]"), "{e}");
    // leading dims of size 1 are no ambiguity
    let dir = tmp("5d-ones");
    write_json(
        &dir.join("zarr.json"),
        &v3(
            &[1, 1, 3, 4, 5],
            &[1, 1, 2, 2, 2],
            "uint16",
            json!([bytes_le()]),
        ),
    );
    fill_val(&dir, "/", DType::U16);
    let mut r = open_dir(&dir, &VolumeOptions::default()).unwrap();
    assert_eq!(r.header().dims, [5, 4, 3]);
    check_box(r.as_mut(), [1, 1, 1], [5, 4, 3], |z, y, x| {
        val(&[0, 0, z, y, x])
    });
    // 2D
    let dir = tmp("2d");
    write_json(
        &dir.join("zarr.json"),
        &v3(&[4, 5], &[4, 5], "uint8", json!([{"name": "bytes"}])),
    );
    let e = open_dir(&dir, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("2D"), "{e}");
    // sample types other than the eight
    for t in ["int64", "uint64", "float16", "bool", "complex64"] {
        let dir = tmp(&format!("type-{t}"));
        let codecs = if t == "bool" {
            json!([{"name": "bytes"}])
        } else {
            json!([bytes_le()])
        };
        let mut meta = v3(&[2, 2, 2], &[2, 2, 2], t, codecs);
        meta["fill_value"] = match t {
            "bool" => json!(false),
            "complex64" => json!([0.0, 0.0]),
            _ => json!(0),
        };
        write_json(&dir.join("zarr.json"), &meta);
        let e = open_dir(&dir, &VolumeOptions::default()).err().unwrap();
        assert!(matches!(e, VolumeError::Unsupported { .. }), "{t}: {e}");
        assert!(e.to_string().contains(t), "{t}: {e}");
    }
    let dir = tmp("type-v2-i8");
    write_json(
        &dir.join(".zarray"),
        &v2(&[2, 2, 2], &[2, 2, 2], "<i8", "C", json!(null)),
    );
    let e = open_dir(&dir, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("int64") && e.contains("not supported"), "{e}");
    // not a Zarr at all
    let dir = tmp("empty");
    let e = open_dir(&dir, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("not a Zarr"), "{e}");
    // a box past the dims
    let dir = tmp("box");
    write_json(
        &dir.join("zarr.json"),
        &v3(&[2, 2, 2], &[2, 2, 2], "uint8", json!([{"name": "bytes"}])),
    );
    let mut r = open_dir(&dir, &VolumeOptions::default()).unwrap();
    assert!(r.read_box([0, 0, 0], [3, 2, 2]).is_err());
    assert!(r.read_box([1, 0, 0], [1, 2, 2]).is_err());
    // missing chunks are the fill value
    assert_eq!(
        r.read_box([0, 0, 0], [2, 2, 2]).unwrap(),
        Samples::U8(vec![0; 8])
    );
}

/// Truncations and byte substitutions of `file` at 100 places or every byte, with `try_it`
/// run on each: a refusal is fine, a panic (or one of zarrs's caught by the reader) is not.
fn corrupt(file: &Path, try_it: &dyn Fn() -> Result<(), VolumeError>) {
    let good = std::fs::read(file).unwrap();
    let step = good.len().div_ceil(100).max(1);
    let check = |what: String| {
        if let Err(e) = try_it() {
            let e = e.to_string();
            assert!(!e.contains("zarrs cannot"), "{what}: zarrs panicked: {e}");
        }
    };
    for cut in (0..good.len()).step_by(step) {
        std::fs::write(file, &good[..cut]).unwrap();
        check(format!("{} cut at {cut}", file.display()));
    }
    for at in (0..good.len()).step_by(step) {
        for x in [0u8, 0xff, b'9', b'"'] {
            let mut b = good.clone();
            b[at] = x;
            std::fs::write(file, &b).unwrap();
            check(format!("{} byte {at} = {x}", file.display()));
        }
    }
    std::fs::write(file, &good).unwrap();
}

/// Opens `dir` and reads a box of at most 3 voxels a side (whatever the dims now say).
fn open_and_read(dir: &Path, o: &VolumeOptions) -> Result<(), VolumeError> {
    let mut r = open_dir(dir, o)?;
    let hi = r.header().dims.map(|d| d.min(3));
    r.read_box([0; 3], hi)?;
    Ok(())
}

#[test]
fn broken_stores_are_refused_never_panic() {
    let d3 = tmp("broken-v3");
    let codecs = json!([bytes_le(), {"name": "gzip", "configuration": {"level": 5}}]);
    write_json(
        &d3.join("zarr.json"),
        &v3(&[3, 4, 5], &[2, 2, 5], "uint16", codecs),
    );
    fill_val(&d3, "/", DType::U16);
    let d2 = tmp("broken-v2");
    let blosc = json!({"id": "blosc", "cname": "lz4", "clevel": 5, "shuffle": 1, "blocksize": 0});
    write_json(
        &d2.join(".zarray"),
        &v2(&[3, 4, 5], &[2, 2, 5], "<f4", "C", blosc),
    );
    fill_val(&d2, "/", DType::F32);
    let d5 = tmp("broken-ome05.zarr");
    ome_05(&d5);
    let d4 = tmp("broken-ome04.zarr");
    ome_04(&d4);
    let zs = tmp("broken-zstd");
    let codecs =
        json!([bytes_le(), {"name": "zstd", "configuration": {"level": 3, "checksum": false}}]);
    write_json(
        &zs.join("zarr.json"),
        &v3(&[3, 4, 5], &[3, 4, 5], "int32", codecs),
    );
    fill_val(&zs, "/", DType::I32);
    let plain = VolumeOptions::default();
    let frame = opts(None, Some(1));
    let chan = opts(Some("mag"), None);
    // the metadata documents
    corrupt(&d3.join("zarr.json"), &|| open_and_read(&d3, &plain));
    corrupt(&d2.join(".zarray"), &|| open_and_read(&d2, &plain));
    corrupt(&d5.join("zarr.json"), &|| open_and_read(&d5, &frame));
    corrupt(&d5.join("s0/zarr.json"), &|| open_and_read(&d5, &frame));
    corrupt(&d4.join(".zattrs"), &|| open_and_read(&d4, &chan));
    // the chunks: gzip, blosc, zstd, a sharded zstd (its index and inner chunks)
    corrupt(&d3.join("c/0/0/0"), &|| open_and_read(&d3, &plain));
    corrupt(&d2.join("0.0.0"), &|| open_and_read(&d2, &plain));
    corrupt(&zs.join("c/0/0/0"), &|| open_and_read(&zs, &plain));
    corrupt(&d5.join("s0/c/1/0/0/0"), &|| open_and_read(&d5, &frame));
    // a corrupted chunk is an error naming the voxels, not wrong voxels
    let good = std::fs::read(d3.join("c/0/0/0")).unwrap();
    std::fs::write(d3.join("c/0/0/0"), &good[..good.len() / 2]).unwrap();
    let e = open_and_read(&d3, &plain).err().unwrap();
    assert!(
        matches!(e, VolumeError::Bad { .. }) && e.to_string().contains("voxels"),
        "{e}"
    );
    std::fs::write(d3.join("c/0/0/0"), &good).unwrap();
    open_and_read(&d3, &plain).unwrap();
}

/// A static file server on 127.0.0.1 for one test: GET (with a byte range or not) and HEAD
/// of the files under `root`; 403 for any path with `forbidden` in it, for the chunks of
/// `locked`, and for what is not there under `strict`; every request logged.
/// It stops when told, or by itself after two minutes.
struct Server {
    port: u16,
    stop: Arc<AtomicBool>,
    log: Arc<Mutex<Vec<String>>>,
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}

fn serve(root: PathBuf) -> Server {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.set_nonblocking(true).unwrap();
    let port = listener.local_addr().unwrap().port();
    let stop = Arc::new(AtomicBool::new(false));
    let log = Arc::new(Mutex::new(Vec::new()));
    let (stop2, log2) = (stop.clone(), log.clone());
    std::thread::spawn(move || {
        let until = std::time::Instant::now() + std::time::Duration::from_secs(120);
        while !stop2.load(Ordering::SeqCst) && std::time::Instant::now() < until {
            match listener.accept() {
                Ok((s, _)) => {
                    let (root, log) = (root.clone(), log2.clone());
                    std::thread::spawn(move || {
                        let _ = answer(s, &root, &log);
                    });
                }
                Err(_) => std::thread::sleep(std::time::Duration::from_millis(2)),
            }
        }
    });
    Server { port, stop, log }
}

/// Answers the requests of one connection.
fn answer(s: std::net::TcpStream, root: &Path, log: &Mutex<Vec<String>>) -> std::io::Result<()> {
    s.set_nonblocking(false)?;
    s.set_read_timeout(Some(std::time::Duration::from_secs(10)))?;
    let mut out = s.try_clone()?;
    let mut rd = BufReader::new(s);
    loop {
        let mut line = String::new();
        if rd.read_line(&mut line)? == 0 {
            return Ok(());
        }
        let mut parts = line.split_whitespace();
        let (method, target) = (
            parts.next().unwrap_or("").to_string(),
            parts.next().unwrap_or("/").to_string(),
        );
        let mut range = None;
        let mut body_len = 0usize;
        loop {
            let mut h = String::new();
            rd.read_line(&mut h)?;
            let h = h.trim_end();
            if h.is_empty() {
                break;
            }
            let (k, v) = h.split_once(':').unwrap_or((h, ""));
            match k.to_ascii_lowercase().as_str() {
                "range" => range = Some(v.trim().to_string()),
                "content-length" => body_len = v.trim().parse().unwrap_or(0),
                _ => {}
            }
        }
        let mut body = vec![0u8; body_len];
        rd.read_exact(&mut body)?;
        log.lock().unwrap().push(format!(
            "{method} {target} {}",
            range.clone().unwrap_or_default()
        ));
        let file = root.join(target.trim_start_matches('/'));
        let respond =
            |out: &mut std::net::TcpStream, status: &str, headers: String, body: &[u8]| {
                let head = format!(
                    "HTTP/1.1 {status}\r\n{headers}Content-Length: {}\r\n\r\n",
                    body.len()
                );
                out.write_all(head.as_bytes())?;
                if method != "HEAD" {
                    out.write_all(body)?;
                }
                out.flush()
            };
        if target.contains("forbidden") || (target.contains("locked") && target.contains("/c/")) {
            respond(&mut out, "403 Forbidden", String::new(), b"no")?;
            continue;
        }
        let Ok(data) = std::fs::read(&file).map_err(|_| ()).and_then(|d| {
            if file.is_file() {
                Ok(d)
            } else {
                Err(())
            }
        }) else {
            // like a bucket without the list permission: what is not there is refused
            let status = if target.contains("strict") {
                "403 Forbidden"
            } else {
                "404 Not Found"
            };
            respond(&mut out, status, String::new(), b"")?;
            continue;
        };
        let size = data.len();
        match range.as_deref().and_then(|r| r.strip_prefix("bytes=")) {
            Some(r) => {
                let (a, b) = r.split_once('-').unwrap_or((r, ""));
                let (start, end) = match (a.parse::<usize>().ok(), b.parse::<usize>().ok()) {
                    (Some(a), Some(b)) => (a, (b + 1).min(size)),
                    (Some(a), None) => (a, size),
                    (None, Some(n)) => (size.saturating_sub(n), size),
                    (None, None) => (0, size),
                };
                if start >= end {
                    respond(
                        &mut out,
                        "416 Range Not Satisfiable",
                        format!("Content-Range: bytes */{size}\r\n"),
                        b"",
                    )?;
                    continue;
                }
                respond(
                    &mut out,
                    "206 Partial Content",
                    format!("Content-Range: bytes {start}-{}/{size}\r\n", end - 1),
                    &data[start..end],
                )?;
            }
            None => respond(&mut out, "200 OK", String::new(), &data)?,
        }
    }
}

#[test]
fn http_urls_read_the_same_voxels_and_only_their_shard_parts() {
    let root = tmp("http");
    ome_05(&root.join("img.zarr"));
    let codecs = json!([{
        "name": "sharding_indexed",
        "configuration": {
            "chunk_shape": [4, 4, 4],
            "codecs": [bytes_le()],
            "index_codecs": [bytes_le(), {"name": "crc32c"}],
            "index_location": "end",
        }
    }]);
    write_json(
        &root.join("big.zarr/zarr.json"),
        &v3(&[16, 16, 16], &[16, 16, 16], "uint16", codecs),
    );
    let lin = |ix: &[u64]| (ix[0] * 256 + ix[1] * 16 + ix[2]) as u16;
    fill(&root.join("big.zarr"), "/", lin);
    let server = serve(root.clone());
    let url = |p: &str| PathBuf::from(format!("http://127.0.0.1:{}/{p}", server.port));

    // an OME-Zarr group: the same header and voxels as from the folder
    let o = opts(None, Some(1));
    let mut local = open_dir(&root.join("img.zarr"), &o).unwrap();
    let mut v = Volume::open(&url("img.zarr"), None, &o).unwrap();
    assert_eq!(v.header(), local.header());
    assert_eq!(v.dims, [6, 5, 4]);
    let b = v.read_block(0..5, 0..4).unwrap();
    let mut want = local.read_box([0, 0, 0], [6, 5, 4]).unwrap();
    want = want.reorient([6, 5, 4], local.header().axes);
    assert_eq!(b, want);
    // a v2 OME-Zarr where what is not there is refused, not missing
    ome_04(&root.join("strict.zarr"));
    std::fs::remove_file(root.join("strict.zarr/0/.zattrs")).ok();
    let mut r = open_reader(
        &url("strict.zarr"),
        VolumeFormat::Zarr,
        &opts(Some("1"), None),
    )
    .unwrap();
    assert_eq!(r.header().spacing, [0.5, 1.0, 4.0]);
    check_box(r.as_mut(), [0, 0, 0], [6, 5, 4], |z, y, x| {
        val(&[1, z, y, x])
    });
    // a level by its own URL takes the image's geometry from its parent
    let r = open_reader(&url("img.zarr/s0"), VolumeFormat::Zarr, &o).unwrap();
    assert_eq!(r.header().spacing, [1.5, 1.5, 1.5]);

    // a box inside one inner chunk of a shard: ranged reads only, none of the whole shard
    let mut r = open_reader(
        &url("big.zarr/"),
        VolumeFormat::Zarr,
        &VolumeOptions::default(),
    )
    .unwrap();
    server.log.lock().unwrap().clear();
    check_box(r.as_mut(), [4, 4, 4], [6, 7, 8], |z, y, x| {
        lin(&[z, y, x]) as f64
    });
    let log = server.log.lock().unwrap().clone();
    let gets: Vec<&String> = log.iter().filter(|l| l.starts_with("GET")).collect();
    assert!(
        !gets.is_empty() && gets.iter().all(|l| l.contains("bytes=")),
        "{log:?}"
    );
    assert!(gets.len() <= 2, "the index and one inner chunk: {log:?}");

    // refusals name the object
    let e = Volume::open(&url("nothing.zarr"), None, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("nothing.zarr") && e.contains("not a Zarr"),
        "{e}"
    );
    let e = Volume::open(&url("forbidden.zarr"), None, &VolumeOptions::default())
        .err()
        .unwrap();
    assert!(matches!(e, VolumeError::Io { .. }), "{e}");
    let e = e.to_string();
    assert!(
        e.contains("forbidden.zarr/zarr.json") && e.contains("access denied"),
        "{e}"
    );
    // a chunk refused once the metadata was read
    let dir = root.join("locked.zarr");
    write_json(
        &dir.join("zarr.json"),
        &v3(&[2, 2, 2], &[2, 2, 2], "uint8", json!([{"name": "bytes"}])),
    );
    fill(&dir, "/", |ix| val(ix) as u8);
    let mut r = open_reader(
        &url("locked.zarr"),
        VolumeFormat::Zarr,
        &VolumeOptions::default(),
    )
    .unwrap();
    let e = r.read_box([0; 3], [2; 3]).err().unwrap();
    assert!(matches!(e, VolumeError::Io { .. }), "{e}");
    let e = e.to_string();
    assert!(
        e.contains("locked.zarr/c/0/0/0") && e.contains("access denied"),
        "{e}"
    );
    let e = Volume::open(&PathBuf::from("s3://"), None, &VolumeOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("bucket"), "{e}");
    drop(server);
}
