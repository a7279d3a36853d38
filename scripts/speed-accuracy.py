#!/usr/bin/env python3
"""Speed against accuracy: time per frame against PSNR of the image against the EXACT image of the
full-resolution data, over a store's uniform levels, for our GPU projected tetrahedra (each
visibility order `tetwave render --order` offers) and VTK's vtkProjectedTetrahedraMapper on the
same level meshes, with the same camera, transfer function and image size.

Run through `scripts/bench-speed-accuracy` (or `scripts/demo`), which build the binaries and
install vtk into the checkout's venv; by hand:

  .venv/bin/python scripts/speed-accuracy.py --bin-dir target/release
      --export-bin target/release/tetwave-export-level --store out/harmonic
      [--levels 0,1,2,3,4,5] [--orders centroid,mpvo] [--size 512] [--repeats 3] [--vtk-frames 3]
      [--no-vtk] [--out out/speed-accuracy] [--charts out/charts] [--docs]

  exact image  `tetwave render STORE --reference` (the CPU reference integrator on the finest level,
               i.e. the full-resolution data), once;
  ours         per level L and order O: `tetwave render STORE --levels L --order O` (GPU PT on the
               level's uniform mesh), run --repeats times; time = the median of the `ms` each run
               reports (one frame after a warm-up frame: visibility sort, upload of the sorted
               order, rasterization and read-back); PSNR of its PNG against the exact image;
  VTK          the same level's mesh, written by tetwave-export-level (client/src/bin/
               tetwave-export-level.rs: the tets and vertex values `tetwave render --levels L` draws), drawn
               by vtkProjectedTetrahedraMapper offscreen (EGL) with scripts/bench-vs-vtk's camera and
               transfer function mapping (extinction per diagonal -> opacity per unit distance
               1 - exp(-extinction / diagonal)); time = median of --vtk-frames `Render()` calls after
               a warm-up, each after `camera.Modified()` (forcing the re-sort, as ours sorts every
               frame) and a read-back of its pixels (as ours reads its image back: the
               frame is finished when timed); PSNR of its image against the exact image.

Both renderers get the same transfer function: the points of the `default` preset written to
OUT/tf.json (explicit, so a change of the preset cannot make them differ), mapped over the value
range the store's image maps (`value_range` of `tetwave render --json`).

Writes OUT/points.jsonl (one JSON object per point), OUT/images/, CHARTS/speed-vs-accuracy.svg
(+ .png) and CHARTS/speed-vs-accuracy.jsonl; prints a markdown table. --docs also copies the PNG to
docs/images/speed-vs-accuracy.png. Fails when vtk cannot be imported, unless --no-vtk: then the
chart and the table say that VTK was NOT measured; no VTK point is ever made up.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time

import numpy as np



def fail(msg):
    raise SystemExit(f"speed-accuracy: {msg}")


def log(msg):
    print(f"speed-accuracy: {msg}", file=sys.stderr, flush=True)


def run_json(cmd):
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        fail(f"{' '.join(cmd)} exited with {p.returncode}:\n{p.stderr}")
    try:
        return json.loads(p.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        fail(f"{' '.join(cmd)} printed no JSON:\n{p.stdout}\n{p.stderr}")


def bench_fidelity():
    """scripts/bench-fidelity.py as a module: its camera, image PSNR, transfer-function points and
    VTK renderer (the same scene there and here)."""
    import importlib.util

    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bench-fidelity.py")
    spec = importlib.util.spec_from_file_location("bench_fidelity", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


BF = bench_fidelity()
read_png, psnr, camera = BF.read_png, BF.image_psnr, BF.camera


def vtk_render(vtk_path, value_range, cam, size, frames, out_png):
    """vtkProjectedTetrahedraMapper on a legacy .vtk grid (RenderMesh::write_vtk's, scalar `f`),
    by bench-fidelity's renderer. Returns (median ms, all ms, window class)."""
    import vtk

    r = vtk.vtkUnstructuredGridReader()
    r.SetFileName(vtk_path)
    r.Update()
    times, cls = BF.vtk_render(r.GetOutput(), "f", value_range, cam, BF.tf_points("default"), (size, size), out_png, frames)
    return statistics.median(times), times, cls


def chart(points, vtk_note, path_svg, path_png, title):
    """One line per series, each point labelled with its level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.6))
    series = {}
    for p in points:
        series.setdefault(p["series"], []).append(p)
    styles = {"ours GPU PT, centroid": ("tab:blue", "o"), "ours GPU PT, mpvo": ("tab:green", "s"),
              "VTK PT": ("tab:red", "^")}
    for name, ps in series.items():
        ps = sorted(ps, key=lambda p: p["level"])
        col, mk = styles.get(name, (None, "x"))
        ax.plot([p["ms"] for p in ps], [p["psnr_db"] for p in ps], marker=mk, color=col, label=name)
        for p in ps:
            ax.annotate(f"L{p['level']}", (p["ms"], p["psnr_db"]), textcoords="offset points",
                        xytext=(-16, 4) if name.endswith("centroid") else (5, -11), fontsize=8, color=col)
    ax.set_xscale("log")
    ax.set_xlabel("time per frame (ms, log scale)")
    ax.set_ylabel("PSNR against the exact full-resolution image (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right", fontsize=9)
    if vtk_note:
        ax.text(0.02, 0.98, vtk_note, transform=ax.transAxes, va="top", fontsize=9, color="tab:red")
    fig.tight_layout()
    fig.savefig(path_svg)
    fig.savefig(path_png, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin-dir", default="target/release")
    ap.add_argument("--export-bin", default=None, help="default: BIN_DIR/tetwave-export-level")
    ap.add_argument("--store", default="out/harmonic")
    ap.add_argument("--levels", default=None, help="comma-separated (default: 0 to the store's finest)")
    ap.add_argument("--orders", default="centroid,mpvo")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=3, help="`tetwave render` runs per point (median ms)")
    ap.add_argument("--vtk-frames", type=int, default=3, help="timed VTK frames per point (median ms)")
    ap.add_argument("--no-vtk", action="store_true")
    ap.add_argument("--out", default="out/speed-accuracy")
    ap.add_argument("--charts", default="out/charts")
    ap.add_argument("--docs", action="store_true", help="copy the chart's PNG to docs/images/")
    args = ap.parse_args()

    tw = os.path.join(args.bin_dir, "tetwave")
    if args.export_bin is None:
        args.export_bin = os.path.join(args.bin_dir, "tetwave-export-level")
    if not os.access(tw, os.X_OK):
        fail(f"{tw} is missing (cargo build --release --locked -p tetwave-client)")
    manifest = json.load(open(os.path.join(args.store, "manifest.json")))
    finest = int(manifest["levels"])
    levels = list(range(finest + 1)) if args.levels is None else [int(x) for x in args.levels.split(",")]
    if any(lv < 0 or lv > finest for lv in levels):
        fail(f"--levels {levels}: the store has levels 0 to {finest}")
    orders = args.orders.split(",")
    out, img_dir = args.out, os.path.join(args.out, "images")
    os.makedirs(img_dir, exist_ok=True)
    os.makedirs(args.charts, exist_ok=True)
    tf_path = os.path.join(out, "tf.json")
    json.dump({"name": "default (speed-accuracy)",
               "points": BF.tf_points("default")},
              open(tf_path, "w"), indent=1)
    size_arg = f"{args.size}x{args.size}"
    common = ["--size", size_arg, "--tf", tf_path, "--json"]

    vtk_error = None
    if args.no_vtk:
        vtk_error = "--no-vtk"
    else:
        try:
            import vtk  # noqa: F401
        except Exception as e:  # noqa: BLE001 (any import failure)
            fail(f"import vtk failed: {e} (install vtk into the venv, or give --no-vtk to measure ours only)")
        if not os.access(args.export_bin, os.X_OK):
            fail(f"{args.export_bin} is missing (cargo build --release --locked -p tetwave-client)")
    if vtk_error:
        log(f"VTK NOT MEASURED ({vtk_error}): the chart has no VTK points")

    log(f"exact image: CPU reference of level {finest} (full resolution)")
    exact_png = os.path.join(img_dir, "exact.png")
    exact = run_json([tw, "render", args.store, "--reference", "-o", exact_png] + common)
    exact_img = read_png(exact_png)
    value_range = exact["value_range"]

    points = []
    started = time.perf_counter()
    for lv in levels:
        for order in orders:
            png = os.path.join(img_dir, f"ours-{order}-L{lv}.png")
            runs = [run_json([tw, "render", args.store, "--levels", str(lv), "--order", order, "-o", png] + common)
                    for _ in range(args.repeats)]
            r = runs[-1]
            if not np.allclose(r["value_range"], value_range, rtol=1e-6, atol=0):
                fail(f"level {lv} maps the range {r['value_range']}, the exact image {value_range}")
            p = {"series": f"ours GPU PT, {order}", "renderer": r["renderer"], "order": order, "level": lv,
                 "tets": r["tets"], "ms": round(statistics.median(x["ms"] for x in runs), 2),
                 "ms_runs": [round(x["ms"], 2) for x in runs], "psnr_db": round(psnr(read_png(png), exact_img), 2)}
            points.append(p)
            log(json.dumps(p))
        if vtk_error is None:
            mesh_path = os.path.join(out, f"level{lv}.vtk")
            ex = run_json([args.export_bin, args.store, str(lv), mesh_path])
            if not np.allclose(ex["value_range"], value_range, rtol=1e-6, atol=0):
                fail(f"exported level {lv} has the range {ex['value_range']}, the exact image {value_range}")
            cam = camera(*ex["bounds"])
            png = os.path.join(img_dir, f"vtk-L{lv}.png")
            ms, times, cls = vtk_render(mesh_path, value_range, cam, args.size, args.vtk_frames, png)
            import vtk

            p = {"series": "VTK PT", "renderer": f"vtkProjectedTetrahedraMapper VTK {vtk.vtkVersion.GetVTKVersion()} ({cls})",
                 "order": "vtk", "level": lv, "tets": ex["tets"], "ms": round(ms, 2),
                 "ms_runs": [round(x, 2) for x in times], "psnr_db": round(psnr(read_png(png), exact_img), 2)}
            points.append(p)
            log(json.dumps(p))
    log(f"sweep took {time.perf_counter() - started:.1f} s")

    with open(os.path.join(out, "points.jsonl"), "w") as f:
        for p in points:
            f.write(json.dumps(p) + "\n")
    shutil.copy(os.path.join(out, "points.jsonl"), os.path.join(args.charts, "speed-vs-accuracy.jsonl"))
    renderers = sorted({p["renderer"] for p in points})
    title = (f"{manifest['dataset']} store, levels {levels[0]}-{levels[-1]}, {size_arg}, "
             f"exact = CPU reference of level {finest} ({exact['tets']:,} tets)\n"
             + "\n".join(renderers) + f"\n{os.cpu_count()} CPU cores")
    note = None if vtk_error is None else f"VTK NOT MEASURED: {vtk_error}"
    svg = os.path.join(args.charts, "speed-vs-accuracy.svg")
    png = os.path.join(args.charts, "speed-vs-accuracy.png")
    chart(points, note, svg, png, title)
    if args.docs:
        shutil.copy(png, "docs/images/speed-vs-accuracy.png")

    lines = [f"Exact image: CPU reference of level {finest} ({exact['tets']:,} tets), {exact['ms']:.0f} ms. "
             f"{os.cpu_count()} CPU cores. Renderers: " + "; ".join(renderers) + ".", "",
             "| level | tets | renderer | ms per frame (median) | PSNR dB vs exact |", "|---|---|---|---|---|"]
    for p in sorted(points, key=lambda p: (p["level"], p["series"])):
        lines.append(f"| {p['level']} | {p['tets']:,} | {p['series']} | {p['ms']:.1f} | {p['psnr_db']:.2f} |")
    if vtk_error:
        lines += ["", f"**VTK NOT MEASURED** ({vtk_error})."]
    md = "\n".join(lines) + "\n"
    open(os.path.join(out, "table.md"), "w").write(md)
    print(md)
    print(f"chart: {svg} (+ .png), points: {os.path.join(args.charts, 'speed-vs-accuracy.jsonl')}")


if __name__ == "__main__":
    main()
