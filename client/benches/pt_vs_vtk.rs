//! Our projected tetrahedra on an N³ Kuhn cube (6 tets per cell) with a smooth analytic field: mean
//! frame time over several frames and PSNR against our CPU reference; writes the mesh, camera and
//! transfer function for `scripts/bench-vs-vtk`, which renders the same scene with VTK's
//! `vtkProjectedTetrahedraMapper` in the same run.
//!
//! `TETWAVE_BENCH_N` (default 32), `TETWAVE_BENCH_SIZE` (512), `TETWAVE_BENCH_FRAMES` (5),
//! `TETWAVE_BENCH_OUT` (out/bench-vs-vtk), `TETWAVE_BENCH_ONLY` (e.g. `mpvo-best`: only the
//! configurations named; default all). Besides means, each line has the fastest frame's wall and
//! CPU time (`min_ms`, `min_cpu_ms`), steadier on a shared machine.

use std::time::Instant;
use tetwave_gpu::pt::{Accumulation, PtRenderer, VisibilityOrder};
use tetwave_gpu::GpuContext;
use tetwave_protocol::view::Orbit;
use tetwave_render::image_metrics::psnr;
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;

fn env(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The smooth analytic field of the benchmark, on `[0,1]^3`.
fn field(p: [f64; 3]) -> f64 {
    let r2 = (p[0] - 0.5).powi(2) + (p[1] - 0.5).powi(2) + (p[2] - 0.5).powi(2);
    (-6.0 * r2).exp() * (1.0 + 0.5 * (6.0 * p[0]).sin() * (5.0 * p[1]).cos())
}

/// CPU time (user + system, all threads, lavapipe's included) of this process in ms, from
/// /proc/self/stat: less sensitive than wall time to other jobs on a shared machine.
fn cpu_ms() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let rest = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<f64> = rest
        .split_whitespace()
        .map(|x| x.parse().unwrap_or(0.0))
        .collect();
    // fields 14 and 15 (utime, stime) are at 11 and 12 after the ')'; clock ticks of 10 ms
    f.get(11)
        .zip(f.get(12))
        .map_or(0.0, |(u, s)| (u + s) * 10.0)
}

/// CPU time of all threads of this process in ms, in nanosecond resolution (sum of the threads'
/// run times in /proc/self/task/*/schedstat); for per-frame minima.
fn cpu_ms_fine() -> f64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    dir.filter_map(|e| std::fs::read_to_string(e.ok()?.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        / 1e6
}

fn main() {
    let n = env("TETWAVE_BENCH_N", 32);
    let size = env("TETWAVE_BENCH_SIZE", 512) as u32;
    let frames = env("TETWAVE_BENCH_FRAMES", 5);
    let out = std::path::PathBuf::from(
        std::env::var("TETWAVE_BENCH_OUT").unwrap_or("out/bench-vs-vtk".into()),
    );
    std::fs::create_dir_all(&out).expect("output directory");
    let mesh = RenderMesh::kuhn_cube(n, 1.0, field);
    let tf = TransferFunction::preset("default").unwrap();
    let cam = Orbit::around(mesh.center(), 1.6 * mesh.diagonal()).camera(size, size);
    let ctx =
        GpuContext::new().expect("a GPU adapter (lavapipe: apt-get install mesa-vulkan-drivers)");
    let r = PtRenderer::new(&ctx);
    let t = Instant::now();
    let data = r.upload_with(&ctx, &mesh, true).unwrap();
    let upload_ms = t.elapsed().as_secs_f64() * 1e3;
    let t = Instant::now();
    let reference = render_reference(&mesh, &cam, &tf);
    let reference_ms = t.elapsed().as_secs_f64() * 1e3;
    reference.save_png(&out.join("reference.png")).unwrap();
    let fast = PtRenderer::with_accumulation(&ctx, Accumulation::U8);
    let only = std::env::var("TETWAVE_BENCH_ONLY").unwrap_or_default();
    for (order, acc) in [
        (VisibilityOrder::Centroid, Accumulation::Best),
        (VisibilityOrder::Mpvo, Accumulation::Best),
        (VisibilityOrder::Mpvo, Accumulation::U8),
    ] {
        if !only.is_empty() && !only.contains(&format!("{order:?}-{acc:?}").to_lowercase()) {
            continue;
        }
        let r = if acc == Accumulation::U8 { &fast } else { &r };
        r.render_ordered(&ctx, &data, &cam, &tf, order).unwrap(); // warm-up
        let mut times = Vec::new();
        let mut last = None;
        let cpu0 = cpu_ms();
        let mut min_cpu = f64::INFINITY;
        for _ in 0..frames {
            let c0 = cpu_ms_fine();
            let (img, ft) = r.render_ordered(&ctx, &data, &cam, &tf, order).unwrap();
            min_cpu = min_cpu.min(cpu_ms_fine() - c0);
            times.push(ft);
            last = Some(img);
        }
        let cpu = (cpu_ms() - cpu0) / frames as f64;
        let img = last.unwrap();
        let order_name = format!("{order:?}").to_lowercase();
        let acc_name = format!("{acc:?}").to_lowercase();
        let name = if acc == Accumulation::Best {
            format!("ours-{order_name}.png")
        } else {
            format!("ours-{order_name}-{acc_name}.png")
        };
        img.save_png(&out.join(&name)).unwrap();
        let mean = |f: &dyn Fn(&tetwave_gpu::pt::FrameTimes) -> f64| {
            times.iter().map(f).sum::<f64>() / times.len() as f64
        };
        println!(
            "{{\"bench\":\"pt\",\"order\":{order_name:?},\"accumulation\":{acc_name:?},\"n\":{n},\"tets\":{},\"size\":{size},\"frames\":{frames},\"mean_ms\":{:.2},\"cpu_ms\":{cpu:.0},\"min_ms\":{:.2},\"min_cpu_ms\":{min_cpu:.1},\"sort_ms\":{:.2},\"gpu_ms\":{:.2},\"readback_ms\":{:.2},\"psnr_db\":{:.2},\"tets_per_s\":{:.0},\"upload_ms\":{upload_ms:.1},\"reference_ms\":{reference_ms:.0},\"adapter\":{:?},\"image\":{:?}}}",
            mesh.tets.len(),
            mean(&|t| t.total_ms),
            times.iter().map(|t| t.total_ms).fold(f64::INFINITY, f64::min),
            mean(&|t| t.sort_ms),
            mean(&|t| t.gpu_ms),
            mean(&|t| t.readback_ms),
            psnr(&img, &reference).min(99.0),
            mesh.tets.len() as f64 / (mean(&|t| t.total_ms) / 1e3),
            ctx.describe(),
            name
        );
    }
    mesh.write_vtk(&out.join("mesh.vtk")).unwrap();
    let (r0, r1) = mesh.value_range;
    let scene = serde_json::json!({
        "eye": cam.eye.to_array(), "target": cam.target.to_array(), "up": cam.basis().1.to_array(),
        "fovy_deg": cam.fovy_deg, "near": cam.near, "size": [size, size], "value_range": [r0, r1],
        "diagonal": mesh.diagonal(), "tf": tf, "frames": frames,
    });
    std::fs::write(
        out.join("scene.json"),
        serde_json::to_string_pretty(&scene).unwrap(),
    )
    .unwrap();
}
