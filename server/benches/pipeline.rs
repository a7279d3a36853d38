//! Throughput of the server pipeline stages (`cargo bench -p tetwave-server --bench pipeline`, or
//! `scripts/bench-analysis`). Not a test: it prints one JSON object per measurement, the median of
//! several runs, measured in one process so ratios between them are meaningful on a noisy machine.

use std::time::Instant;
use tetwave_protocol::synthesis::synthesize_all;
use tetwave_server::analysis::{analyze_hierarchy, Precision};
use tetwave_server::resample::synthetic::{kuhn_cube_mesh, Synthetic};
use tetwave_server::resample::unstructured::{clean, Locator};
use tetwave_server::resample::{resample, BaseSpec, Resampled, Source};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

/// Analysis alone, repeated on copies of one resampled input: min and median seconds per level.
fn analysis_loop(source: &Source, threads: usize) {
    // TETWAVE_BENCH_LEVELS=5 (say) limits the loop to one level
    let only: Option<u8> = std::env::var("TETWAVE_BENCH_LEVELS")
        .ok()
        .and_then(|v| v.parse().ok());
    for (levels, runs) in [(5u8, 60), (6, 30), (7, 8)] {
        if only.is_some_and(|l| l != levels) {
            continue;
        }
        let r = resample(source, &BaseSpec::Box5, levels).unwrap();
        let vertices = r.samples.len();
        let mut times = Vec::new();
        for _ in 0..runs {
            let copy = Resampled {
                base: r.base.clone(),
                keys: r.keys.clone(),
                samples: r.samples.clone(),
                outside: r.outside,
            };
            let t = Instant::now();
            let a = analyze_hierarchy(copy, Precision::Lossless, false).unwrap();
            times.push(t.elapsed().as_secs_f64());
            drop(a);
        }
        let min = times.iter().copied().fold(f64::INFINITY, f64::min);
        let med = median(times);
        println!(
            "{{\"bench\":\"analysis_loop\",\"levels\":{levels},\"vertices\":{vertices},\"runs\":{runs},\"min_s\":{min:.5},\"median_s\":{med:.5},\"vertices_per_s_min\":{:.0},\"vertices_per_s_median\":{:.0},\"threads\":{threads}}}",
            vertices as f64 / min,
            vertices as f64 / med
        );
    }
}

fn main() {
    let runs = 5;
    // TETWAVE_BENCH=analysis runs only the analysis/synthesis part (for profiling);
    // TETWAVE_BENCH=analysis-loop runs only the analysis, many times on one resampled input
    let mode = std::env::var("TETWAVE_BENCH").unwrap_or_default();
    let only_analysis = mode == "analysis";
    let threads = rayon::current_num_threads();
    let source = Source::Synthetic(Synthetic::Harmonic);
    if mode == "analysis-loop" {
        analysis_loop(&source, threads);
        return;
    }
    for levels in [5u8, 6, 7] {
        let mut t_analysis = Vec::new();
        let mut t_synth = Vec::new();
        let mut vertices = 0;
        for _ in 0..runs {
            let r = resample(&source, &BaseSpec::Box5, levels).unwrap();
            vertices = r.samples.len();
            let t = Instant::now();
            let a = analyze_hierarchy(r, Precision::Lossless, false).unwrap();
            t_analysis.push(t.elapsed().as_secs_f64());
            let keys = a.base.vertex_keys();
            let nodes = a.nodes();
            let t = Instant::now();
            let v = synthesize_all(&a.base, &keys, nodes).unwrap();
            t_synth.push(t.elapsed().as_secs_f64());
            assert_eq!(v.len(), vertices);
        }
        let (ta, ts) = (median(t_analysis), median(t_synth));
        println!(
            "{{\"bench\":\"analysis\",\"levels\":{levels},\"vertices\":{vertices},\"seconds\":{ta:.5},\"vertices_per_s\":{:.0},\"threads\":{threads}}}",
            vertices as f64 / ta
        );
        println!(
            "{{\"bench\":\"synthesis\",\"levels\":{levels},\"vertices\":{vertices},\"seconds\":{ts:.5},\"vertices_per_s\":{:.0},\"threads\":1}}",
            vertices as f64 / ts
        );
    }
    if only_analysis {
        return;
    }
    // point location in a ~1M-tet unstructured mesh (55^3 jittered Kuhn cubes = 998,250 tets)
    let mesh = kuhn_cube_mesh(
        55,
        0.3,
        |_, _, _| true,
        tetwave_protocol::fields::harmonic_unit,
    );
    let tets = mesh.tets.len();
    let (m, _) = clean(mesh, None, None).unwrap();
    let t = Instant::now();
    let loc = Locator::new(&m);
    let build = t.elapsed().as_secs_f64();
    let source = Source::Mesh(Box::new(loc), ([0.0; 3], [1.0; 3]));
    let mut times = Vec::new();
    let mut points = 0;
    for _ in 0..runs {
        let t = Instant::now();
        let r = resample(&source, &BaseSpec::Box5, 7).unwrap();
        times.push(t.elapsed().as_secs_f64());
        points = r.samples.len();
        assert_eq!(r.outside, 0);
    }
    let tl = median(times);
    println!(
        "{{\"bench\":\"point_location\",\"input_tets\":{tets},\"index_build_s\":{build:.4},\"points\":{points},\"seconds\":{tl:.5},\"points_per_s\":{:.0},\"threads\":{threads}}}",
        points as f64 / tl
    );
}
