#!/usr/bin/env python3
"""Scale benchmark: does a client model no more than the scene needs on large grids?

Run through `scripts/bench-scale` (which builds the release binaries and installs numpy,
scikit-fem and matplotlib into the checkout's venv .venv); by hand:

  .venv/bin/python scripts/bench-scale.py --bin-dir target/release [--levels 7,8]
      [--fields harmonic,fem] [--bounds lossless,0.1%] [--tol 2] [--size 512x512]
      [--criteria image,geometric] [--timeout 300] [--l9] [--out out/bench-scale]

For every field, level L and bound: one (2^L+1)^3 grid (harmonic: `synthetic:harmonic`, sampled at
the grid points by `prepare`; fem: bench-rd's scikit-fem solution evaluated at the grid points and
written as a raw f32 grid), prepared with `--base box6 --levels L [--max-error B]` (wall time and
peak RSS of `prepare`), served on 127.0.0.1 in view order (the stream starts once the server has
computed its view order, a one-time cost of its start: `view_order_ready_s`), and streamed by
`tetwave stream --headless --no-render --until-converged --tol T --size WxH --final-png`
once per selection criterion (`--criterion image|geometric`); a run ends at the first frame whose
mesh is final for the default camera, or is killed at --timeout seconds (the row says so):

  converge_s    the session's last frame, from connect (`ms_since_connect`);
  leaves, tets  what the client holds then (`leaves` is what --max-tets bounds), and tets per pixel;
  client_rss    the client process's peak RSS (its VmHWM, read every 50 ms), drawing --final-png included;
  psnr_db       the CPU reference image of the converged mesh (`--final-png`, same camera) against
                the CPU reference image of every leaf of the store (`tetwave render STORE
                --reference`, once per store), RGB in 8-bit units.

With --l9: a 513^3 u8 raw grid written by slabs (the harmonic field scaled to 0..255), prepared
at `--levels 9 --max-error 0.1%` (time, peak RSS), served in level order (serve's default), and
streamed to its first frame (`first_frame_s`, from connect).

With --serverless CASE: that case's store (run its case first) copied into a 3-node garage
cluster on loopback (`scripts/garage-cluster`, `tetwave-server copy`) and its folder served by
nginx; then, one after the other in one run, the same `tetwave stream` (image criterion) from a
server of the directory (view order), from `s3://…` directly and from `http://…` (nginx)
directly: bytes, time to the final view, first image, client peak RSS, PSNR of the final image.

With --view CASE: that case's store served in view order and orbited a full turn in `tetwave view`
under Xvfb (512², 2 px; once per --view-max-tets): frame period p50/p95/max, the most leaves held
against the budget, frames in which the budget bound.

Writes OUT/scale.jsonl (one object per run, appended as runs end) and OUT/scale.md (the table);
work files in OUT/work/.
"""

import argparse
import importlib.util
import json
import shutil
import os
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def load_bench_rd():
    """bench-rd.py's FEM grid and its loopback server (one copy of each)."""
    spec = importlib.util.spec_from_file_location("bench_rd", os.path.join(HERE, "bench-rd.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


rd = load_bench_rd()
fail = rd.fail


def peak_rss_mib(pid):
    """The largest peak RSS so far (VmHWM of /proc/PID/status), MiB, of the process and its
    descendants (a program run under xvfb-run is a grandchild); None once none is left."""
    children = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
                children.setdefault(ppid, []).append(int(d))
            except (OSError, ValueError, IndexError):
                pass
    best, todo = None, [pid]
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    if line.startswith("VmHWM:"):
                        v = int(line.split()[1]) / 1024.0
                        best = v if best is None else max(best, v)
        except OSError:
            pass
    return best


def run_measured(cmd, what, log, timeout=None):
    """Runs `cmd` with stdout and stderr into `log` (.out / .err); returns (stdout, wall seconds,
    peak RSS in MiB, timed out). The peak is the largest VmHWM of the program and its descendants, read every 50 ms until it
    exits (getrusage of a child would count this Python process's memory at the fork). A non-zero
    exit that is not a time-out fails the benchmark."""
    import subprocess

    t0 = time.time()
    with open(log + ".out", "w") as o, open(log + ".err", "w") as e:
        p = subprocess.Popen([str(c) for c in cmd], stdout=o, stderr=e)
        peak = [0.0]
        done = threading.Event()

        def watch():
            while not done.is_set():
                v = peak_rss_mib(p.pid)
                if v is not None:
                    peak[0] = max(peak[0], v)
                time.sleep(0.05)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        try:
            p.wait(timeout=timeout)
            killed = False
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
            killed = True
        done.set()
        watcher.join()
    wall = time.time() - t0
    out = open(log + ".out").read()
    if p.returncode != 0 and not killed:
        err = open(log + ".err").read()
        fail(f"{what} failed (status {p.returncode}): {' '.join(map(str, cmd))}\n{err[-4000:]}")
    return out, wall, peak[0], killed


def png_rgb(path):
    from PIL import Image
    import numpy as np

    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)


def psnr(a, b):
    import numpy as np

    mse = float(np.mean((png_rgb(a) - png_rgb(b)) ** 2))
    return 99.0 if mse == 0 else min(99.0, 10 * np.log10(255.0**2 / mse))


def grid_input(field, level, work):
    """prepare's input arguments for `field` on a (2^level+1)^3 grid."""
    n = (1 << level) + 1
    if field == "harmonic":
        return ["synthetic:harmonic"]
    path = os.path.join(work, f"fem-{n}.raw")
    if not os.path.exists(path):
        arr, _, _ = rd.fem_grid(level, 12)
        arr.tofile(path)
    return [path, "--dims", f"{n},{n},{n}", "--dtype", "f32"]


def write_l9_grid(path, n=513, slab=16):
    """bench-rd's harmonic field (tetwave_protocol::fields::harmonic on [0,30]^3) at n^3 points,
    scaled from its range [-1, 1.25] to u8 and written slab by slab (bounded memory)."""
    import numpy as np

    if os.path.exists(path) and os.path.getsize(path) == n**3:
        return
    s = np.linspace(0.0, 30.0, n)
    with open(path + ".part", "wb") as f:
        for z0 in range(0, n, slab):
            z, y, x = np.meshgrid(s[z0 : min(n, z0 + slab)], s, s, indexing="ij")
            u = [(c - 15.0) / 15.0 for c in (x, y, z)]
            r2 = u[0] ** 2 + u[1] ** 2 + u[2] ** 2
            v = np.exp(-2.0 * r2) * np.cos(4.0 * np.pi * np.sqrt(r2)) + 0.25 * np.sin(
                2.0 * np.pi * u[0]
            ) * np.sin(2.0 * np.pi * u[1]) * np.sin(2.0 * np.pi * u[2])
            f.write(np.clip((v + 1.0) / 2.25 * 255.0 + 0.5, 0, 255).astype(np.uint8).tobytes())
    os.replace(path + ".part", path)


def write_ct_grid(path, dims, dtype, slab=32):
    """A CT-like volume of `dims` (x fastest) written slab by slab (bounded memory): air around an
    elliptic body of soft tissue with two darker lungs, a dense bone shell and a spine, a smooth
    intensity drift, and noise at every voxel (a seeded Gaussian, ~1.5 % of the range). u8 maps
    -1000..1000 HU to 0..255; u16 stores HU + 1024 (0..3071)."""
    import numpy as np

    nx, ny, nz = dims
    itemsize = 1 if dtype == "u8" else 2
    if os.path.exists(path) and os.path.getsize(path) == nx * ny * nz * itemsize:
        return
    rng = np.random.default_rng(12345)
    x = np.linspace(-1.0, 1.0, nx, dtype=np.float32)[None, None, :]
    y = np.linspace(-1.0, 1.0, ny, dtype=np.float32)[None, :, None]
    with open(path + ".part", "wb") as f:
        for z0 in range(0, nz, slab):
            z = np.linspace(-1.0, 1.0, nz, dtype=np.float32)[z0 : min(nz, z0 + slab), None, None]
            body = (x / 0.8) ** 2 + (y / 0.6) ** 2
            hu = np.full((z.shape[0], ny, nx), -1000.0, dtype=np.float32)
            inside = body + 0.0 * z < 1.0
            hu = np.where(inside, 40.0 + 30.0 * z + 20.0 * np.sin(6.0 * x), hu)
            lungs = ((np.abs(x) - 0.35) / 0.25) ** 2 + (y / 0.35) ** 2 + (z / 0.7) ** 2 < 1.0
            hu = np.where(lungs & inside, -850.0, hu)
            bone = inside & (body > 0.8)
            spine = (x / 0.08) ** 2 + ((y + 0.45) / 0.08) ** 2 < 1.0
            hu = np.where(bone | spine, 700.0 + 200.0 * np.cos(9.0 * z), hu)
            hu = hu + rng.normal(0.0, 30.0, hu.shape).astype(np.float32)
            if dtype == "u8":
                v = np.clip((hu + 1000.0) / 2000.0 * 255.0 + 0.5, 0, 255).astype(np.uint8)
            else:
                v = np.clip(hu + 1024.0 + 0.5, 0, 3071).astype("<u2")
            f.write(v.tobytes())
    os.replace(path + ".part", path)


def write_ct_as(raw, dims, dtype, fmt, path, slab=64):
    """The raw CT grid `raw` written again as a volume file of format `fmt`, slab by slab
    (bounded memory): `tiff`, a BigTIFF stack of one page a plane (tifffile), or `zarr`, a Zarr
    v3 array of 64³ chunks in 256×256×256 shards, zstd (zarr-python). Both are read back by
    tetwave's readers with no --dims/--dtype."""
    import numpy as np

    nx, ny, nz = dims
    t = np.uint8 if dtype == "u8" else np.dtype("<u2")
    mm = np.memmap(raw, dtype=t, mode="r", shape=(nz, ny, nx))
    if os.path.exists(path):
        return
    tmp = path + ".part"
    if fmt == "tiff":
        import tifffile

        def pages():
            for z in range(nz):
                yield np.asarray(mm[z])

        tifffile.imwrite(tmp, pages(), shape=(nz, ny, nx), dtype=t, bigtiff=True, photometric="minisblack")
    elif fmt == "zarr":
        import shutil
        import zarr
        from zarr.codecs import ZstdCodec

        shutil.rmtree(tmp, ignore_errors=True)
        arr = zarr.create_array(store=tmp, shape=(nz, ny, nx), chunks=(64, 64, 64), shards=(256, 256, 256),
                                dtype=t, compressors=ZstdCodec(level=3), zarr_format=3)
        step = 256
        for z0 in range(0, nz, step):
            arr[z0:z0 + step] = np.asarray(mm[z0:z0 + step])
    else:
        raise SystemExit(f"bench-scale: unknown --ct-formats {fmt!r} (raw, tiff, zarr)")
    os.replace(tmp, path)


def same_store(a, b):
    """Whether two store directories hold the same files, byte for byte, but for the manifest's
    `source` (the input's path, which differs between a .tif and a .zarr of the same grid)."""
    import filecmp

    def manifest(d):
        with open(os.path.join(d, "manifest.json")) as f:
            m = json.load(f)
        m.pop("source", None)
        return m

    fa, fb = sorted(os.listdir(a)), sorted(os.listdir(b))
    return fa == fb and manifest(a) == manifest(b) and all(
        filecmp.cmp(os.path.join(a, f), os.path.join(b, f), shallow=False) for f in fa if f != "manifest.json")


def view_server(bindir, store, log):
    """`serve --order view` on loopback, once it is ready for view order (`/readyz`: the vertex
    values of the first levels, which view order ranks by, are built; a one-time cost of a
    server's start): returns the server and the seconds to /healthz and to /readyz."""
    import urllib.request
    t0 = time.time()
    srv = rd.Server(bindir, store, "view", log, extra=("--log", "tetwave_server=info"), ready_s=600)
    healthz = time.time() - t0
    while True:
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{srv.port}/readyz", timeout=2).read()
            break
        except OSError:
            if time.time() - t0 > 600:
                srv.close()
                fail(f"serve {store}: not ready within 600 s; see {log}")
            time.sleep(0.05)
    return srv, {"healthz_s": round(healthz, 2), "view_order_ready_s": round(time.time() - t0, 2)}


def serverless(a, bindir, server, client, work, emit):
    """--serverless CASE: the same stream from a server, from garage and from nginx (module doc)."""
    import shutil
    import subprocess
    case = a.serverless
    store = os.path.join(work, case)
    if not os.path.exists(os.path.join(store, "manifest.json")):
        fail(f"--serverless {case}: no store at {store} (run its case first)")
    ref = os.path.join(work, case + "-all-leaves.png")
    gdir = os.path.join(work, "garage")
    rd.garage_start(gdir)
    nginx = None
    try:
        url = f"s3://tetwave/{case}"
        out, wall, _, _ = run_measured([server, "copy", store, url], f"copy {case}", os.path.join(work, "copy"))
        emit({"run": "copy", "case": case, "copy_s": round(wall, 2)})
        nginx, port = rd.nginx_start(os.path.join(work, "nginx"),
                                     f"server {{ listen 127.0.0.1:{{port}}; root {os.path.abspath(work)}; location / {{ }} }}")
        srv, ready = view_server(bindir, store, os.path.join(work, case + "-serverless-serve.log"))
        push = None
        try:
            for source, where in (("push", f"http://127.0.0.1:{srv.port}"), ("s3", url),
                                  ("http", f"http://127.0.0.1:{port}/{case}")):
                name = f"{case}-serverless-{source}"
                final = os.path.join(work, name + "-converged.png")
                cmd = [client, "stream", where, "--headless", "--no-render", "--until-converged",
                       "--frames", "100000", "--tol", a.tol, "--size", a.size, "--criterion", "image",
                       "--final-png", final, "--out", os.path.join(work, name)]
                out, wall, rss, killed = run_measured(cmd, f"stream {name}", os.path.join(work, name),
                                                      timeout=a.timeout)
                frames = [json.loads(l) for l in out.splitlines() if l.startswith("{")]
                row = {"run": "serverless", "case": case, "source": source, "wall_s": round(wall, 2),
                       "client_rss_mib": round(rss), "timed_out": killed}
                if frames:
                    f = frames[-1]
                    row.update(converge_s=round(f["ms_since_connect"] / 1e3, 2), converged=f["view_complete"],
                               leaves=f["leaves"], tets=f["tets"], bytes=f["bytes_received"], nodes=f["nodes"],
                               first_image_s=round(frames[0]["ms_since_connect"] / 1e3, 3))
                    if source == "push":
                        push = row
                    elif push and push.get("bytes"):
                        row["bytes_vs_push"] = round(row["bytes"] / push["bytes"], 3)
                        row["time_vs_push"] = round(row["converge_s"] / push["converge_s"], 3)
                if not killed and os.path.exists(final) and os.path.exists(ref):
                    row["psnr_db"] = round(psnr(final, ref), 2)
                push_png = os.path.join(work, f"{case}-serverless-push-converged.png")
                if source != "push" and not killed and os.path.exists(final) and os.path.exists(push_png):
                    # the same final mesh draws the same image: 99 (capped) when identical
                    row["psnr_vs_push_db"] = round(min(psnr(final, push_png), 99.0), 2)
                emit(row)
        finally:
            srv.close()
    finally:
        if nginx:
            # SIGTERM: the master stops its workers (a killed master leaves them running)
            nginx.terminate()
            nginx.wait(timeout=10)
        rd.garage_stop(gdir)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin-dir", default="target/release")
    ap.add_argument("--levels", default="7,8")
    ap.add_argument("--fields", default="harmonic,fem")
    ap.add_argument("--bounds", default="lossless,0.1%")
    ap.add_argument("--criteria", default="image,geometric")
    ap.add_argument("--tol", default="2")
    ap.add_argument("--size", default="512x512")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds a stream may run")
    ap.add_argument("--skip", default="", help="comma-separated field-lL-bound-criterion runs to skip")
    ap.add_argument("--no-reference", action="store_true", help="skip the all-leaves images (no PSNR)")
    ap.add_argument("--l9", action="store_true", help="also prepare and stream a 513^3 grid")
    ap.add_argument("--view", default="", help="a case (e.g. harmonic-l8-0.1pc) to orbit in `tetwave view` under Xvfb")
    ap.add_argument("--view-max-tets", default="default,300000", help="--max-tets of each view run")
    ap.add_argument("--view-motion-lod", action="store_true", help="view runs with --motion-lod too")
    ap.add_argument("--view-motion-tets", default="0,4000",
                    help="--motion-tets of each view run (0: the whole leaf mesh in motion too)")
    ap.add_argument("--ct", default="", help="CT-like grids prepared out of core at the default --memory "
                    "and verified voxel by voxel: e.g. 1025-u8,1024x1024x1536-u16,2049-u16 (sizes XxYxZ or N)")
    ap.add_argument("--ct-bound", default="0.5%", help="--max-error of the --ct stores")
    ap.add_argument("--ct-only", action="store_true", help="run the --ct cases alone")
    ap.add_argument("--ct-formats", default="raw", help="the --ct grids as these files: raw (with --dims "
                    "and --dtype, and verify --input), tiff (a BigTIFF stack) and zarr (sharded Zarr v3), "
                    "each prepared without --dims; every store is compared byte for byte with the first")
    ap.add_argument("--ct-project", default="", help="a CT-like grid too long to prepare here (e.g. 2049-u16): "
                    "prepare a sample of its parts (--parts N --part K, each its own process) and project the total")
    ap.add_argument("--ct-project-levels", default="7")
    ap.add_argument("--ct-project-parts", default="128")
    ap.add_argument("--ct-project-sample", default="0,64", help="the parts to prepare")
    ap.add_argument("--serverless", default="", help="a case (e.g. harmonic-l8-0.1pc) streamed side by side "
                    "from a server, from a 3-node garage cluster directly, and from nginx directly")
    ap.add_argument("--out", default="out/bench-scale")
    a = ap.parse_args()

    bindir = a.bin_dir
    server = os.path.join(bindir, "tetwave-server")
    client = os.path.join(bindir, "tetwave")
    for b in (server,) if a.ct_only else (server, client):
        if not os.access(b, os.X_OK):
            fail(f"{b} is missing: build the release binaries first (scripts/bench-scale does)")
    work = os.path.join(a.out, "work")
    os.makedirs(work, exist_ok=True)
    jl = os.path.join(a.out, "scale.jsonl")
    skip = set(filter(None, a.skip.split(",")))
    w, h = (int(v) for v in a.size.lower().split("x"))
    rows = []

    def emit(row):
        rows.append(row)
        with open(jl, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)

    for level in ([] if a.ct_only else (int(v) for v in a.levels.split(","))):
        for field in a.fields.split(","):
            for bound in a.bounds.split(","):
                tag = f"{field}-l{level}-{bound.replace('%', 'pc')}"
                store = os.path.join(work, tag)
                prep = {"run": "prepare", "case": tag}
                if not os.path.exists(os.path.join(store, "manifest.json")):
                    cmd = [server, "prepare", *grid_input(field, level, work), "--base", "box6",
                           "--levels", level, "--out", store, "--json"]
                    if bound != "lossless":
                        cmd += ["--max-error", bound]
                    out, wall, rss, _ = run_measured(cmd, f"prepare {tag}", os.path.join(work, tag + "-prepare"))
                    summary = json.loads(out.strip().splitlines()[-1])
                    prep.update(prepare_s=round(wall, 2), prepare_rss_mib=round(rss), bytes=summary["bytes"],
                                leaves_total=summary["leaves"], nodes=summary["nodes"])
                    emit(prep)
                ref = os.path.join(work, tag + "-all-leaves.png")
                if not a.no_reference and not os.path.exists(ref):
                    _, wall, rss, _ = run_measured(
                        [client, "render", store, "--reference", "--tf", "default", "--size", a.size, "-o", ref],
                        f"render {tag}", os.path.join(work, tag + "-reference"))
                    emit({"run": "all-leaves image", "case": tag, "render_s": round(wall, 1),
                          "render_rss_mib": round(rss)})
                srv, ready = view_server(bindir, store, os.path.join(work, tag + "-serve.log"))
                emit({"run": "serve", "case": tag, **ready})
                try:
                    for crit in a.criteria.split(","):
                        name = f"{tag}-{crit}"
                        if name in skip:
                            continue
                        final = os.path.join(work, name + "-converged.png")
                        cmd = [client, "stream", f"http://127.0.0.1:{srv.port}", "--headless", "--no-render",
                               "--until-converged", "--frames", "100000", "--tol", a.tol, "--size", a.size,
                               "--criterion", crit, "--final-png", final, "--out", os.path.join(work, name)]
                        out, wall, rss, killed = run_measured(cmd, f"stream {name}", os.path.join(work, name),
                                                              timeout=a.timeout)
                        frames = [json.loads(l) for l in out.splitlines() if l.startswith("{")]
                        row = {"run": "stream", "case": tag, "criterion": crit, "tol_px": a.tol,
                               "size": a.size, "wall_s": round(wall, 2), "client_rss_mib": round(rss),
                               "timed_out": killed}
                        if frames:
                            f = frames[-1]
                            row.update(frames=len(frames), converge_s=round(f["ms_since_connect"] / 1e3, 2),
                                       converged=f["view_complete"], leaves=f["leaves"], tets=f["tets"],
                                       tets_per_px=round(f["tets"] / (w * h), 2),
                                       budget_bound=f["budget_bound"], bytes=f["bytes_received"],
                                       nodes=f["nodes"])
                        if not killed and os.path.exists(final) and os.path.exists(ref):
                            row["psnr_db"] = round(psnr(final, ref), 2)
                        emit(row)
                finally:
                    srv.close()

    if a.view:
        store = os.path.join(work, a.view)
        if not os.path.exists(os.path.join(store, "manifest.json")):
            fail(f"--view {a.view}: no store at {store} (run its case first)")
        # a full turn in 10-degree steps every 0.25 s after 3 s of streaming, then 2 s at rest
        steps = [{"at": 3.0 + 0.25 * k, "orbit": 10} for k in range(36)] + [{"at": 14.0, "quit": True}]
        script = os.path.join(work, "view-orbit.json")
        with open(script, "w") as f:
            json.dump(steps, f)
        srv, _ = view_server(bindir, store, os.path.join(work, "view-serve.log"))
        try:
            runs = [(mt, False, mot) for mt in a.view_max_tets.split(",")
                    for mot in a.view_motion_tets.split(",")]
            if a.view_motion_lod:
                runs.append(("default", True, "0"))
            for mt, lod, mot in runs:
                cmd = ["xvfb-run", "-a", "-s", "-screen 0 1280x800x24", client, "view",
                       f"http://127.0.0.1:{srv.port}", "--size", a.size, "--tol", a.tol, "--script", script,
                       "--json"]
                if mt != "default":
                    cmd += ["--max-tets", mt]
                if lod:
                    cmd += ["--motion-lod"]
                cmd += ["--motion-tets", mot]
                out, wall, rss, killed = run_measured(cmd, f"view {a.view}",
                                                      os.path.join(work, f"view-{mt}-{mot}{'-lod' if lod else ''}"),
                                                      timeout=120)
                r = json.loads([l for l in out.splitlines() if l.startswith("{")][-1])
                p = r["perf"]
                emit({"run": "view", "case": a.view, "max_tets": mt, "motion_lod": lod, "motion_tets": int(mot),
                      "tets_in_motion_p95": p["tets_drawn_in_motion"]["p95"],
                      "frame_ms_in_motion_p50": round(p["frame_ms_in_motion"]["p50"], 1),
                      "frame_ms_in_motion_p95": round(p["frame_ms_in_motion"]["p95"], 1),
                      "paint_drawn_ms_p95": round(p["paint_drawn_ms"]["p95"], 1),
                      "leaf_budget": r["leaf_budget"],
                      "max_leaves": r["max_leaves"], "frames_budget_bound": r["frames_budget_bound"],
                      "frames": r["frames"], "frame_ms_p50": round(p["frame_ms"]["p50"], 1),
                      "frame_ms_p95": round(p["frame_ms"]["p95"], 1), "frame_ms_max": round(p["frame_ms"]["max"], 1),
                      "latency_ms_p95": round(p["latency_ms"]["p95"], 1),
                      "refine_ms_p95": round(p["refine_ms"]["p95"], 1), "tets_last": r["tets"],
                      "client_rss_mib": round(rss), "timed_out": killed})
        finally:
            srv.close()

    def ct_case(case):
        """A --ct case (`SIZE-DTYPE`, SIZE `N` or `XxYxZ`): its dims, dtype and raw file, written
        if missing."""
        size, dtype = case.split("-")
        dims = [int(v) for v in size.split("x")] if "x" in size else [int(size)] * 3
        raw = os.path.join(work, f"ct-{case}.raw")
        t = time.time()
        write_ct_grid(raw, dims, dtype)
        print(f"bench-scale: {raw} ready ({time.time() - t:.0f} s)", file=sys.stderr)
        return dims, dtype, raw

    for case, fmt in [(c, f) for c in a.ct.split(",") if c for f in a.ct_formats.split(",")]:
        dims, dtype, raw = ct_case(case)
        store = os.path.join(work, f"ct-{case}" + ("" if fmt == "raw" else f"-{fmt}"))
        grid = ["--dims", ",".join(map(str, dims)), "--dtype", dtype]
        first = os.path.join(work, f"ct-{case}" + ("" if a.ct_formats.split(",")[0] == "raw"
                                                     else "-" + a.ct_formats.split(",")[0]))
        if fmt != "raw":
            path = os.path.join(work, f"ct-{case}.{'tif' if fmt == 'tiff' else 'zarr'}")
            t = time.time()
            write_ct_as(raw, dims, dtype, fmt, path)
            print(f"bench-scale: {path} ready ({time.time() - t:.0f} s)", file=sys.stderr)
            shutil.rmtree(store, ignore_errors=True)
            out, wall, rss, _ = run_measured(
                [server, "prepare", path, "--max-error", a.ct_bound, "--out", store, "--json"],
                f"prepare {case} {fmt}", os.path.join(work, f"ct-{case}-{fmt}-prepare"))
            summary = json.loads(out.strip().splitlines()[-1])
            emit({"run": "prepare out of core", "case": f"ct-{case}", "format": fmt, "bound": a.ct_bound,
                  "prepare_s": round(wall, 1), "prepare_rss_mib": round(rss), "levels": summary["levels"],
                  "bytes": summary["bytes"], "volume": summary.get("volume"),
                  "same_store_as": os.path.basename(first) if first != store and same_store(first, store) else None})
            continue
        out, wall, rss, _ = run_measured(
            [server, "prepare", raw, *grid, "--max-error", a.ct_bound, "--out", store, "--json"],
            f"prepare {case}", os.path.join(work, f"ct-{case}-prepare"))
        summary = json.loads(out.strip().splitlines()[-1])
        disk = sum(os.path.getsize(os.path.join(store, f)) for f in os.listdir(store))
        row = {"run": "prepare out of core", "case": f"ct-{case}", "bound": a.ct_bound,
               "raw_bytes": os.path.getsize(raw), "prepare_s": round(wall, 1), "prepare_rss_mib": round(rss),
               "levels": summary["levels"], "base": summary["base"], "bytes": summary["bytes"],
               "store_dir_bytes": disk, "max_abs_error": summary["max_abs_error"],
               "max_error_bound": summary["max_error_bound"]}
        out, wall, rss, _ = run_measured(
            [server, "verify", store, "--input", raw, *grid, "--json"],
            f"verify --input {case}", os.path.join(work, f"ct-{case}-verify"))
        v = json.loads(out.strip().splitlines()[-1])
        row.update({"verify_s": round(wall, 1), "verify_rss_mib": round(rss),
                    "verify_max_abs_error": v["input"]["max_abs_error"], "verify_voxels": v["input"]["points"]})
        emit(row)

    if a.ct_project:
        case = a.ct_project
        dims, dtype, raw = ct_case(case)
        store = os.path.join(work, f"ct-{case}-parts")
        n = int(a.ct_project_parts)
        grid = ["--dims", ",".join(map(str, dims)), "--dtype", dtype, "--levels", a.ct_project_levels,
                "--max-error", a.ct_bound, "--parts", str(n)]
        walls, peaks = [], []
        for k in a.ct_project_sample.split(","):
            out, wall, rss, _ = run_measured(
                [server, "prepare", raw, *grid, "--part", k, "--out", store, "--json"],
                f"prepare {case} part {k}", os.path.join(work, f"ct-{case}-part-{k}"))
            part = json.loads(out.strip().splitlines()[-1])
            walls.append(wall)
            peaks.append(rss)
            emit({"run": "prepare part", "case": f"ct-{case}", "part": int(k), "parts": n,
                  "levels": int(a.ct_project_levels), "wall_s": round(wall, 1), "analysis_s": round(part["seconds"], 1),
                  "rss_mib": round(rss), "nodes_bytes": part["nodes_bytes"], "raw_bytes": os.path.getsize(raw)})
        mean = sum(walls) / len(walls)
        emit({"run": "projection", "case": f"ct-{case}", "parts": n, "part_wall_s_mean": round(mean, 1),
              "part_rss_mib_max": round(max(peaks)), "projected_one_machine_s": round(n * mean),
              "note": "each part re-reads the whole file for its value range; the finish is not included"})

    if a.l9:
        raw = os.path.join(work, "harmonic-513.u8")
        write_l9_grid(raw)
        store = os.path.join(work, "harmonic-l9-0.1pc")
        if not os.path.exists(os.path.join(store, "manifest.json")):
            out, wall, rss, _ = run_measured(
                [server, "prepare", raw, "--dims", "513,513,513", "--dtype", "u8", "--base", "box6", "--levels", 9,
                 "--max-error", "0.1%", "--out", store, "--json"],
                "prepare 513^3", os.path.join(work, "l9-prepare"))
            summary = json.loads(out.strip().splitlines()[-1])
            emit({"run": "prepare", "case": "u8-513-l9-0.1pc", "prepare_s": round(wall, 1),
                  "prepare_rss_mib": round(rss), "bytes": summary["bytes"], "nodes": summary["nodes"]})
        t_serve = time.time()
        srv = rd.Server(bindir, store, "level", os.path.join(work, "l9-serve.log"), ready_s=600)
        serve_ready_s = time.time() - t_serve
        try:
            cmd = [client, "stream", f"http://127.0.0.1:{srv.port}", "--headless", "--frames", "1",
                   "--size", a.size, "--cpu", "--out", os.path.join(work, "l9-stream")]
            out, wall, rss, _ = run_measured(cmd, "stream 513^3", os.path.join(work, "l9-stream"))
            f = json.loads([l for l in out.splitlines() if l.startswith("{")][0])
            emit({"run": "first frame", "case": "u8-513-l9-0.1pc", "first_frame_s": round(f["ms_since_connect"] / 1e3, 3),
                  "tets": f["tets"], "bytes": f["bytes_received"], "client_rss_mib": round(rss),
                  "serve_ready_s": round(serve_ready_s, 1)})
        finally:
            srv.close()

    if a.serverless:
        serverless(a, bindir, server, client, work, emit)

    md = os.path.join(a.out, "scale.md")
    with open(md, "w") as f:
        f.write("| case | criterion | converge s | converged | leaves | tets/px | client RSS MiB | PSNR dB | budget bound |\n")
        f.write("|---|---|---|---|---|---|---|---|---|\n")
        for r in rows:
            if r["run"] == "stream":
                f.write(f"| {r['case']} | {r['criterion']} | {r.get('converge_s', '-')}"
                        f"{' (killed)' if r['timed_out'] else ''} | {r.get('converged', '-')} | "
                        f"{r.get('leaves', '-')} | {r.get('tets_per_px', '-')} | {r['client_rss_mib']} | "
                        f"{r.get('psnr_db', '-')} | {r.get('budget_bound', '-')} |\n")
        if any(r["run"] == "serverless" for r in rows):
            f.write("\n| case | source | converge s | first image s | bytes | bytes / push | time / push | leaves | "
                    "client RSS MiB | PSNR dB |\n|---|---|---|---|---|---|---|---|---|---|\n")
            for r in rows:
                if r["run"] == "serverless":
                    f.write(f"| {r['case']} | {r['source']} | {r.get('converge_s', '-')} | "
                            f"{r.get('first_image_s', '-')} | {r.get('bytes', '-')} | {r.get('bytes_vs_push', '-')} | "
                            f"{r.get('time_vs_push', '-')} | {r.get('leaves', '-')} | {r['client_rss_mib']} | "
                            f"{r.get('psnr_db', '-')} |\n")
    print(f"wrote {jl} and {md}", file=sys.stderr)


if __name__ == "__main__":
    main()
