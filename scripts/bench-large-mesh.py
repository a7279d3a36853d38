"""Large meshes drawn whole: see scripts/bench-large-mesh (its wrapper) for what is measured."""

import argparse
import importlib.util
import json
import math
import os
import subprocess
import sys
import time

import numpy as np
from PIL import Image

here = os.path.dirname(os.path.abspath(__file__))
spec = importlib.util.spec_from_file_location("bench_fidelity", os.path.join(here, "bench-fidelity.py"))
fidelity = importlib.util.module_from_spec(spec)
spec.loader.exec_module(fidelity)


def fail(msg):
    print(f"bench-large-mesh: {msg}", file=sys.stderr)
    sys.exit(1)


def timed(cmd, what):
    """Runs `cmd`; returns (stdout, wall seconds, peak RSS in MiB of that process alone). The RSS
    comes from GNU time, a small process between: a child forked from this (large) Python process
    would report this process's own high-water mark as its start."""
    import tempfile

    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.time()
        p = subprocess.run(["/usr/bin/time", "-f", "TETWAVE_MAXRSS_KIB=%M", *cmd], stdout=out, stderr=err, text=True)
        wall = time.time() - t0
        out.seek(0)
        err.seek(0)
        errs = err.read()
        if p.returncode != 0:
            fail(f"{what} failed:\n{errs[-3000:]}")
        kib = [int(l.split("=")[1]) for l in errs.splitlines() if l.startswith("TETWAVE_MAXRSS_KIB=")]
        if not kib:
            fail(f"{what}: GNU time reported no peak RSS")
        return out.read(), wall, kib[-1] / 1024.0


def psnr(a, b):
    a = np.asarray(Image.open(a).convert("RGB"), dtype=np.float64)
    b = np.asarray(Image.open(b).convert("RGB"), dtype=np.float64)
    if a.shape != b.shape:
        fail(f"image shapes differ: {a.shape} and {b.shape}")
    rmse = math.sqrt(float(np.mean((a - b) ** 2)))
    return 99.0 if rmse == 0 else 20.0 * math.log10(255.0 / rmse)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--bin-dir", required=True)
    ap.add_argument("--tets", type=float, default=8e6)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--out", default="out/bench-large-mesh")
    ap.add_argument("--view-frames", type=int, default=60)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    target = int(args.tets)
    vtu = os.path.join(args.out, f"torus-{target}.vtu")
    info_path = vtu + ".json"
    if not os.path.exists(vtu):
        import meshio

        t0 = time.time()
        print(f"bench-large-mesh: meshing a torus with about {target:,} tets (gmsh)", file=sys.stderr)
        p, t, h = fidelity.mesh_shape("torus", target)
        mesh_s = time.time() - t0
        print(f"bench-large-mesh: {len(t):,} tets, {len(p):,} points in {mesh_s:.0f} s; solving", file=sys.stderr)
        u, solve = fidelity.solve("torus", p, t)
        meshio.write(vtu, meshio.Mesh(p, [("tetra", t.astype(np.int64))], point_data={"u": u}))
        json.dump({"tets": int(len(t)), "points": int(len(p)), "h": h, "mesh_s": round(mesh_s, 1), **solve}, open(info_path, "w"))
    info = json.load(open(info_path))
    tw = os.path.join(args.bin_dir, "tetwave")
    size = f"{args.size}x{args.size}"
    rows = {"mesh": info, "vtu_bytes": os.path.getsize(vtu)}
    for name, extra in (("gpu", []), ("gpu-sorted-on-gpu", ["--order", "gpu"]), ("cpu-reference", ["--reference"])):
        png = os.path.join(args.out, f"{name}.png")
        out, wall, rss = timed([tw, "render", vtu, "--size", size, "--json", "-o", png, *extra], f"tetwave render ({name})")
        r = json.loads(out)
        rows[name] = {"image_ms": round(r["ms"], 1), "wall_s": round(wall, 1), "peak_rss_mib": round(rss), "renderer": r["renderer"],
                      "upload_ms": r.get("upload_ms"), "gpu_chunks": r.get("gpu_chunks"), "sort_ms": r.get("sort_ms"), "cpu_ms": r.get("cpu_ms")}
        print(f"bench-large-mesh: {name}: {json.dumps(rows[name])}", file=sys.stderr)
    # the viewer under Xvfb: opens the mesh, draws frames (spread over several window frames when
    # a draw is slow) until --frames, and reports
    shot = os.path.join(args.out, "view.png")
    out, wall, rss = timed(["timeout", "1800", "xvfb-run", "-a", "-s", "-screen 0 1024x768x24", tw, "view", vtu,
                            "--size", size, "--frames", str(args.view_frames), "--screenshot", shot, "--json"], "tetwave view")
    v = json.loads(out.strip().splitlines()[-1])
    rows["view"] = {"wall_s": round(wall, 1), "peak_rss_mib": round(rss), "frames": v["frames"], "fps": v["fps"],
                    "fps_drawn": v["fps_drawn"], "upload_ms": v["upload_ms"], "render_ms": v["render_ms"], "tets": v["tets"]}
    print(f"bench-large-mesh: view: {json.dumps(rows['view'])}", file=sys.stderr)
    ref = os.path.join(args.out, "cpu-reference.png")
    for name in ("gpu", "gpu-sorted-on-gpu"):
        rows[name]["psnr_db_vs_reference"] = round(psnr(os.path.join(args.out, f"{name}.png"), ref), 2)
    print(json.dumps(rows))
    json.dump(rows, open(os.path.join(args.out, "results.json"), "w"), indent=1)


if __name__ == "__main__":
    main()
