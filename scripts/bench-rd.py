#!/usr/bin/env python3
"""Rate-distortion benchmark: tetwave's stream and store next to zfp and SZ3 on the same samples.

Run through `scripts/bench-rd` (which builds the binaries and installs numpy, zfpy, pysz,
scikit-fem and matplotlib into the checkout's venv .venv); by hand:

  .venv/bin/python scripts/bench-rd.py --bin-dir target/release [--levels 5,6]
      [--fields harmonic,fem] [--bounds 1e-2,1e-3,1e-4] [--out out/bench-rd]
      [--image-level 5] [--image-field harmonic|fem] [--image-size 256x256] [--image-bounds 1e-3,1.5e-3,2e-3]
      [--image-preview 10%|none] [--no-image] [--quick]

For every field and level L, one (2^L+1)^3 grid of f32 samples, written as a raw grid and prepared
with `--base box6 --levels L`, so that the semi-regular mesh's vertices are exactly the grid
points (checked: the store's reference.f32 holds the grid's values, up to the last bit of values near 0
that trilinear interpolation at a grid point may round; rows record the difference as
samples_vs_grid). Fields:

  harmonic  the embedded default dataset's function (tetwave_protocol::fields::harmonic) on its
            box [0,30]^3, sampled at the grid points (in f64, stored as f32);
  fem       a scikit-fem solution of -div(k grad u) = f on the unit cube, k = 1 + 0.5 sin(2 pi x)
            cos(pi y), f = two Gaussian sources (+500 and -400), u = x/2 + z^2/4 on the boundary;
            quadratic (P2) tets on a graded 12^3-hex tensor mesh (10,368 tets, 15,625 dofs; not
            aligned with the grid), evaluated at the grid points.

For every bound b (a fraction of the samples' value range R; absolute bound E = b R):

  tetwave   `tetwave-server prepare <grid> --dims --dtype f32 --base box6 --levels L
            --max-error E --predictor P --json` (P from --predictor: axes by default; store bytes: the streamable files, `bytes` of its report),
            `tetwave-server verify --json` (max error and RMS error over every vertex),
            `tetwave-server serve` on 127.0.0.1 behind a byte-counting TCP relay and
            `tetwave stream --headless --no-render --until-complete`: wire bytes are every TCP
            payload byte the server sent for the complete stream (HTTP upgrade, WebSocket
            headers and tetwave frames); the client's own count of tetwave frame bytes is kept too;
  zfp       zfpy.compress_numpy(grid, tolerance=E) (fixed accuracy), bytes of its output;
  SZ3       pysz with errorBoundMode ABS, absErrorBound E, bytes of its output;

max error and PSNR = 20 log10(R / RMS error) measured against the f32 samples.

Image part (field --image-field, harmonic by default; level --image-level, the default view: azimuth 35, elevation 25,
distance 1.6 x the diagonal, fov 40), at every bound of --image-bounds (the first is the reference
bound, 1e-3): the reference image is the CPU integrator's image of the original samples (a
lossless store of the grid, `tetwave render --reference`); our curves are `tetwave stream`
(view-dependent order, GPU frames as it arrives) against bytes received, one per bound, and one
more per bound for the store prepared with `--preview` at --image-preview (10 %: a coarse copy
of the coarse levels that a new session gets first); SZ3's
points are its file sizes with the GPU image of the SZ3-decoded grid (prepared lossless, rendered
with `tetwave render`), one per bound. Image PSNR is over RGB in 8-bit units, as tetwave's. The
summary reads two points off the curves: the first frame, over every bound's stream, at or above
the image PSNR of SZ3 at the reference bound, with its bytes against SZ3's file; and the first
frame at or above 30 dB, with its bytes as a fraction of that file.

Writes OUT/rd.json, OUT/rd.md (the tables), OUT/rd-<field>-l<L>.svg (PSNR against bytes per
codec) and OUT/image-psnr-vs-bytes.svg; work files under OUT/work/.
"""

import argparse
import json
import math
import os
import re
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import charts  # noqa: E402


def fail(msg):
    raise SystemExit(f"bench-rd: {msg}")


def need(module):
    try:
        return __import__(module)
    except ImportError as e:
        fail(f"python module {module} is missing ({e}); scripts/bench-rd installs it into .venv")


# ---------------------------------------------------------------------------------------- fields


def harmonic_grid(levels):
    """tetwave_protocol::fields::harmonic at the (2^L+1)^3 points of [0,30]^3, [z, y, x] order."""
    n = (1 << levels) + 1
    s = np.linspace(0.0, 30.0, n)
    z, y, x = np.meshgrid(s, s, s, indexing="ij")
    u = [(c - 15.0) / 15.0 for c in (x, y, z)]
    r2 = u[0] ** 2 + u[1] ** 2 + u[2] ** 2
    r = np.sqrt(r2)
    f = np.exp(-2.0 * r2) * np.cos(4.0 * np.pi * r) + 0.25 * np.sin(2.0 * np.pi * u[0]) * np.sin(
        2.0 * np.pi * u[1]
    ) * np.sin(2.0 * np.pi * u[2])
    return f.astype(np.float32), 30.0 / (n - 1)


_FEM = {}


def fem_solution(cells):
    """The P2 solution (basis, dof vector, grading) on a graded `cells`^3-hex tensor mesh."""
    if cells in _FEM:
        return _FEM[cells]
    skfem = need("skfem")
    from skfem.helpers import dot, grad

    g = 0.5 * (1.0 - np.cos(np.pi * np.linspace(0.0, 1.0, cells + 1)))  # graded towards the faces
    mesh = skfem.MeshTet.init_tensor(g, g, g)
    basis = skfem.Basis(mesh, skfem.ElementTetP2())

    @skfem.BilinearForm
    def a(u, v, w):
        k = 1.0 + 0.5 * np.sin(2.0 * np.pi * w.x[0]) * np.cos(np.pi * w.x[1])
        return k * dot(grad(u), grad(v))

    @skfem.LinearForm
    def rhs(v, w):
        x = w.x
        f = 500.0 * np.exp(-40.0 * ((x[0] - 0.3) ** 2 + (x[1] - 0.35) ** 2 + (x[2] - 0.6) ** 2)) - 400.0 * np.exp(
            -30.0 * ((x[0] - 0.7) ** 2 + (x[1] - 0.65) ** 2 + (x[2] - 0.35) ** 2)
        )
        return f * v

    t0 = time.time()
    A = skfem.asm(a, basis)
    b = skfem.asm(rhs, basis)
    D = basis.get_dofs()
    u = np.zeros(basis.N)
    xd = basis.doflocs
    u[D] = 0.5 * xd[0, D] + 0.25 * xd[2, D] ** 2
    u = skfem.solve(*skfem.condense(A, b, x=u, D=D))
    info = {"tets": int(mesh.t.shape[1]), "dofs": int(basis.N), "solve_s": round(time.time() - t0, 3)}
    _FEM[cells] = (basis, u, g, info)
    return _FEM[cells]


def tensor_tet_finder(mesh, g):
    """Point location in a tensor-product tet mesh: the hex by bisection, then the tet of the hex
    whose barycentric coordinates are all (nearly) non-negative. scikit-fem's own finder tests every
    tet against every point at once, which does not fit in memory at 65^3 points."""
    p = mesh.p.T
    t = mesh.t.T
    nc = len(g) - 1
    cent = p[t].mean(axis=1)
    ci = [np.clip(np.searchsorted(g, cent[:, a]) - 1, 0, nc - 1) for a in range(3)]
    hexid = ci[0] + nc * (ci[1] + nc * ci[2])
    per = len(t) // nc**3
    if not (np.bincount(hexid, minlength=nc**3) == per).all():
        fail("tensor mesh: tets are not evenly split among hexes")
    tets_of = np.argsort(hexid, kind="stable").reshape(nc**3, per)
    v0 = p[t[:, 0]]
    Tinv = np.linalg.inv(np.stack([p[t[:, 1]] - v0, p[t[:, 2]] - v0, p[t[:, 3]] - v0], axis=2))

    def find(x, y, z):
        X = np.stack([x, y, z], axis=1)
        hi = [np.clip(np.searchsorted(g, X[:, a], side="right") - 1, 0, nc - 1) for a in range(3)]
        h = hi[0] + nc * (hi[1] + nc * hi[2])
        out = np.full(len(X), -1)
        best = np.full(len(X), -np.inf)
        for j in range(per):
            c = tets_of[h, j]
            lam = np.einsum("nij,nj->ni", Tinv[c], X - v0[c])
            m = np.minimum(lam.min(axis=1), 1.0 - lam.sum(axis=1))
            upd = m > best
            best[upd] = m[upd]
            out[upd] = c[upd]
        if best.min() < -1e-9:
            fail(f"point location failed (barycentric {best.min()})")
        return out

    return lambda mapping=None: find


def fem_grid(levels, cells):
    basis, u, g, info = fem_solution(cells)
    basis.mesh.element_finder = tensor_tet_finder(basis.mesh, g)
    n = (1 << levels) + 1
    s = np.linspace(0.0, 1.0, n)
    z, y, x = np.meshgrid(s, s, s, indexing="ij")
    pts = np.vstack([x.ravel(), y.ravel(), z.ravel()])
    v = basis.probes(pts) @ u
    return v.reshape(n, n, n).astype(np.float32), 1.0 / (n - 1), info


# ------------------------------------------------------------------------------------- processes


def run(cmd, what):
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if r.returncode != 0:
        fail(f"{what} failed (status {r.returncode}): {' '.join(map(str, cmd))}\n{r.stderr}{r.stdout}")
    return r


def garage_start(gdir):
    """A 3-node garage cluster in `gdir` (scripts/garage-cluster), its endpoint and credentials
    put into this process's environment (child processes inherit them)."""
    here = os.path.dirname(os.path.abspath(__file__))
    subprocess.run([os.path.join(here, "garage-cluster"), "start", gdir], check=True)
    for line in open(os.path.join(gdir, "env")):
        k, v = line.strip().removeprefix("export ").split("=", 1)
        os.environ[k] = v


def garage_stop(gdir):
    here = os.path.dirname(os.path.abspath(__file__))
    subprocess.run([os.path.join(here, "garage-cluster"), "stop", gdir])


def nginx_start(ndir, http_body):
    """nginx on a free loopback port with `http_body` inside `http { … }` (it may use `{port}`):
    returns the process and the port."""
    import shutil
    ndir = os.path.abspath(ndir)
    os.makedirs(ndir, exist_ok=True)
    port = free_port()
    conf = os.path.join(ndir, "nginx.conf")
    with open(conf, "w") as f:
        f.write(f"daemon off; user root; worker_processes 1; pid {ndir}/nginx.pid; error_log {ndir}/error.log;\n"
                f"events {{ worker_connections 1024; }}\n"
                f"http {{ access_log off; client_body_temp_path {ndir}/b; proxy_temp_path {ndir}/p;\n"
                f"fastcgi_temp_path {ndir}/f; uwsgi_temp_path {ndir}/u; scgi_temp_path {ndir}/s;\n"
                + http_body.replace("{port}", str(port)) + " }\n")
    proc = subprocess.Popen([shutil.which("nginx") or "/usr/sbin/nginx", "-p", ndir, "-c", conf],
                            stdout=subprocess.DEVNULL)
    time.sleep(0.5)
    return proc, port


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class Server:
    """`tetwave-server serve` on a free loopback port, until close()."""

    def __init__(self, bindir, store, order, log_path, extra=(), ready_s=60):
        self.port = free_port()
        self.log = open(log_path, "w")
        self.proc = subprocess.Popen(
            [os.path.join(bindir, "tetwave-server"), "serve", store, "--addr", f"127.0.0.1:{self.port}", "--order", order,
             *extra],
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.time() + ready_s
        while True:
            if self.proc.poll() is not None:
                fail(f"serve {store} exited with status {self.proc.returncode}; see {log_path}")
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{self.port}/healthz", timeout=2).read()
                return
            except OSError:
                if time.time() > deadline:
                    self.close()
                    fail(f"serve {store} did not answer /healthz within {ready_s} s")
                time.sleep(0.1)

    def close(self):
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


class CountingRelay:
    """A TCP relay on a free loopback port to `target`: counts the payload bytes delivered in each
    direction (what TCP carries, below WebSocket and HTTP framing)."""

    def __init__(self, target_port):
        self.target = target_port
        self.down = 0  # server -> client
        self.up = 0  # client -> server
        self.connections = 0
        self.lock = threading.Lock()
        self.threads = []
        self.ls = socket.socket()
        self.ls.bind(("127.0.0.1", 0))
        self.ls.listen(16)
        self.port = self.ls.getsockname()[1]
        self.acceptor = threading.Thread(target=self._accept, daemon=True)
        self.acceptor.start()

    def _accept(self):
        while True:
            try:
                c, _ = self.ls.accept()
            except OSError:
                return
            s = socket.create_connection(("127.0.0.1", self.target))
            with self.lock:
                self.connections += 1
            for src, dst, down in ((s, c, True), (c, s, False)):
                t = threading.Thread(target=self._pipe, args=(src, dst, down), daemon=True)
                t.start()
                self.threads.append(t)

    def _pipe(self, src, dst, down):
        try:
            while True:
                data = src.recv(1 << 16)
                if not data:
                    break
                dst.sendall(data)
                with self.lock:
                    if down:
                        self.down += len(data)
                    else:
                        self.up += len(data)
        except OSError:
            pass
        finally:
            for sock, how in ((dst, socket.SHUT_WR), (src, socket.SHUT_RD)):
                try:
                    sock.shutdown(how)
                except OSError:
                    pass

    def close(self):
        self.ls.close()
        for t in self.threads:
            t.join(timeout=5)


STREAM_SUMMARY = re.compile(
    r"stream: (\d+) frames, (\d+)/(\d+) nodes \((\d+) duplicates\), (\d+) bytes, (\d+) reconnects"
)


def stream(bindir, store, order, outdir, extra, serve_extra=()):
    """Serves `store` (`serve_extra`: more `serve` options), streams it completely through the
    counting relay, returns the counts."""
    os.makedirs(outdir, exist_ok=True)
    srv = Server(bindir, store, order, os.path.join(outdir, "server.log"), serve_extra)
    relay = CountingRelay(srv.port)
    try:
        t0 = time.time()
        r = run(
            [os.path.join(bindir, "tetwave"), "stream", f"http://127.0.0.1:{relay.port}", "--headless", "--until-complete", "--out", outdir]
            + extra,
            f"stream {store}",
        )
        seconds = time.time() - t0
    finally:
        srv.close()
        relay.close()
    m = STREAM_SUMMARY.search(r.stderr)
    if not m:
        fail(f"stream {store}: no summary line in\n{r.stderr}")
    frames_n, got, total, dups, msg_bytes, reconnects = map(int, m.groups())
    if got != total or reconnects != 0:
        fail(f"stream {store}: {got}/{total} nodes, {reconnects} reconnects")
    frames = [json.loads(line) for line in open(os.path.join(outdir, "frames.jsonl")) if line.strip()]
    return {
        "wire_bytes_down": relay.down,
        "wire_bytes_up": relay.up,
        "connections": relay.connections,
        "message_bytes": msg_bytes,
        "nodes": total,
        "duplicates": dups,
        "frames": frames,
        "seconds": round(seconds, 3),
    }


# --------------------------------------------------------------------------------------- metrics


def errors(a, b, value_range):
    d = a.astype(np.float64) - b.astype(np.float64)
    rms = float(np.sqrt(np.mean(d * d)))
    return float(np.max(np.abs(d))), psnr(value_range, rms), rms


def psnr(value_range, rms):
    return math.inf if rms == 0 else 20.0 * math.log10(value_range / rms)


def read_png(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)


def image_psnr(a, b):
    rmse = math.sqrt(float(np.mean((a - b) ** 2)))
    return math.inf if rmse == 0 else 20.0 * math.log10(255.0 / rmse)


def zfp_row(arr, e, value_range):
    zfpy = need("zfpy")
    c = zfpy.compress_numpy(arr, tolerance=e)
    d = zfpy.decompress_numpy(c)
    mx, p, rms = errors(arr, d, value_range)
    return {"codec": "zfp", "bytes": len(c), "max_abs_error": mx, "rms_error": rms, "psnr_db": p}, d


def sz3(arr, e):
    pysz = need("pysz")
    cfg = pysz.szConfig()
    cfg.errorBoundMode = pysz.szErrorBoundMode.ABS
    cfg.absErrorBound = float(e)
    c, _ = pysz.sz.compress(np.ascontiguousarray(arr), cfg)
    d, _ = pysz.sz.decompress(c, np.float32, arr.shape)
    return c, np.asarray(d, dtype=np.float32).reshape(arr.shape)


def sz3_row(arr, e, value_range):
    c, d = sz3(arr, e)
    mx, p, rms = errors(arr, d, value_range)
    return {"codec": "SZ3", "bytes": int(c.size), "max_abs_error": mx, "rms_error": rms, "psnr_db": p}, d, c


# ----------------------------------------------------------------------------------------- tetwave


def prepare(bindir, raw, n, spacing, levels, store, max_error=None, predictor="parent", preview=None):
    cmd = [
        os.path.join(bindir, "tetwave-server"),
        "prepare",
        raw,
        "--dims",
        f"{n},{n},{n}",
        "--dtype",
        "f32",
        "--spacing",
        f"{spacing!r},{spacing!r},{spacing!r}",
        "--base",
        "box6",
        "--levels",
        levels,
        "--out",
        store,
        "--predictor",
        predictor,
        # check_samples and verify compare with the samples the store keeps
        "--keep-reference",
        "--json",
    ]
    if max_error is not None:
        cmd += ["--max-error", repr(float(max_error))]
    if preview is not None:
        cmd += ["--preview", preview]
    return json.loads(run(cmd, f"prepare {store}").stdout)


def verify(bindir, store):
    return json.loads(run([os.path.join(bindir, "tetwave-server"), "verify", store, "--json"], f"verify {store}").stdout)


def check_samples(store, arr):
    """The store's vertices are the grid points: its samples are the grid's values (trilinear
    interpolation exactly at a grid point may round the last bit of a value near 0). Returns the
    largest difference between the sorted samples and the sorted grid values."""
    ref = np.fromfile(os.path.join(store, "reference.f32"), dtype="<f4")
    if ref.size != arr.size:
        fail(f"{store}: {ref.size} samples for {arr.size} grid points")
    dev = float(np.max(np.abs(np.sort(ref).astype(np.float64) - np.sort(arr.ravel()))))
    vr = float(arr.max()) - float(arr.min())
    if dev > 1e-6 * vr:
        fail(f"{store}: the store's samples are not the grid's values (differ by up to {dev:g})")
    return dev


def write_raw(arr, path):
    arr.astype("<f4").tofile(path)


# ------------------------------------------------------------------------------------------- main


def fmt_bytes(b):
    return f"{b:,}"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin-dir", required=True, help="directory holding tetwave-server and tetwave")
    ap.add_argument("--out", default="out/bench-rd")
    ap.add_argument("--levels", default="5,6")
    ap.add_argument("--fields", default="harmonic,fem")
    ap.add_argument("--bounds", default="1e-2,1e-3,1e-4", help="fractions of the value range")
    ap.add_argument("--fem-cells", type=int, default=12, help="hexes per side of the FEM mesh")
    ap.add_argument("--image-level", type=int, default=5)
    ap.add_argument("--image-field", default="harmonic", choices=("harmonic", "fem"))
    ap.add_argument("--image-size", default="256x256")
    ap.add_argument("--image-bounds", default="1e-3,1.5e-3,2e-3",
                    help="fractions of the value range; the first is the reference bound of SZ3's image")
    ap.add_argument("--image-preview", default="10%",
                    help="each image store is also streamed with a preview at this bound (prepare --preview); 'none': without only")
    ap.add_argument("--image-per-frame", type=int, default=0, help="nodes per frame (0: about 1/16 of them)")
    ap.add_argument("--image-max-batch", type=int, default=0,
                    help="the server's --max-batch for the image run (0: its default); smaller batches place the curve "
                         "finely at the cost of more, smaller coded blocks")
    ap.add_argument("--predictor", default="axes", choices=("axes", "parent"),
                    help="tetwave's predictor for the bounded stores (prepare --predictor)")
    ap.add_argument("--no-image", action="store_true")
    ap.add_argument("--quick", action="store_true", help="level 3, bound 1e-3, 64x64 image: a smoke test")
    args = ap.parse_args()
    if args.quick:
        args.levels, args.bounds, args.image_level, args.image_size, args.fem_cells = "3", "1e-3", 3, "64x64", 4
        args.image_bounds = "1e-3,2e-3"
    levels = [int(x) for x in args.levels.split(",")]
    fields = args.fields.split(",")
    bounds = [x.strip() for x in args.bounds.split(",")]
    for f in fields:
        if f not in ("harmonic", "fem"):
            fail(f"unknown field {f!r} (harmonic, fem)")
    bindir = args.bin_dir
    for b in ("tetwave-server", "tetwave"):
        if not os.access(os.path.join(bindir, b), os.X_OK):
            fail(f"{os.path.join(bindir, b)} is missing")
    out = args.out
    work = os.path.join(out, "work")
    os.makedirs(work, exist_ok=True)
    t_start = time.time()
    rows = []
    grids = {}
    fem_info = None
    for field in fields:
        for L in levels:
            n = (1 << L) + 1
            if field == "harmonic":
                arr, spacing = harmonic_grid(L)
            else:
                arr, spacing, fem_info = fem_grid(L, args.fem_cells)
            if not np.isfinite(arr).all():
                fail(f"{field} L{L}: non-finite samples")
            vr = float(arr.max()) - float(arr.min())
            raw = os.path.join(work, f"{field}-l{L}.raw")
            write_raw(arr, raw)
            grids[(field, L)] = (arr, spacing, raw, vr)
            raw_bytes = arr.size * 4
            for b in bounds:
                e = float(b) * vr
                key = {"field": field, "level": L, "grid": f"{n}^3", "bound": b, "abs_bound": e, "value_range": vr, "raw_f32_bytes": raw_bytes}
                print(f"bench-rd: {field} {n}^3 bound {b} x range = {e:.4g}", file=sys.stderr)
                store = os.path.join(work, f"{field}-l{L}-{b}")
                prep = prepare(bindir, raw, n, spacing, L, store, e, args.predictor)
                dev = check_samples(store, arr)
                ver = verify(bindir, store)
                st = stream(bindir, store, "level", os.path.join(work, f"{field}-l{L}-{b}-stream"), ["--no-render", "--frames", "1000000"])
                p = psnr(vr, ver["rms_error"])
                manifest = json.load(open(os.path.join(store, "manifest.json")))
                common = {"max_abs_error": ver["max_abs_error"], "rms_error": ver["rms_error"], "psnr_db": p,
                          "samples_vs_grid": dev}
                rows.append(
                    dict(key, codec="tetwave stream", bytes=st["wire_bytes_down"], **common,
                         message_bytes=st["message_bytes"], bytes_up=st["wire_bytes_up"],
                         connections=st["connections"], nodes=st["nodes"], stream_seconds=st["seconds"])
                )
                rows.append(
                    dict(key, codec="tetwave store", bytes=prep["bytes"], **common,
                         encoding=manifest.get("encoding"), max_error_bound=ver.get("max_error_bound"),
                         prepare_seconds=prep.get("seconds"),
                         files={k: v.get("bytes") for k, v in manifest.get("files", {}).items()})
                )
                zr, _ = zfp_row(arr, e, vr)
                rows.append(dict(key, **zr))
                sr, _, _ = sz3_row(arr, e, vr)
                rows.append(dict(key, **sr))
    image = None if args.no_image else image_part(args, bindir, work)
    result = {
        "command": " ".join(sys.argv),
        "predictor": args.predictor,
        "bin_dir": bindir,
        "fem": fem_info,
        "rows": rows,
        "image": image,
        "seconds": round(time.time() - t_start, 1),
    }
    with open(os.path.join(out, "rd.json"), "w") as f:
        json.dump(result, f, indent=1)
    md = tables(rows, image)
    with open(os.path.join(out, "rd.md"), "w") as f:
        f.write(md)
    print(md)
    rd_charts(rows, out)
    if image:
        series = [(f"tetwave at {st['bound']}{', preview ' + st['preview'] if st.get('preview') else ''} (view order)",
                   [(fr["bytes_received"], fr["image_psnr_db"], None) for fr in st["frames"]]) for st in image["streams"]]
        series.append(("SZ3: whole file, then render",
                       sorted((z["bytes"], z["image_psnr_db"], z["bound"]) for z in image["sz3"])))
        charts.chart(
            os.path.join(out, "image-psnr-vs-bytes.svg"),
            f"Default view, {image['field']} {image['grid']}: image PSNR against bytes received",
            "bytes received (B)",
            "image PSNR vs the original's reference image (dB)",
            series,
            labels=True,
        )
    print(f"bench-rd: wrote {out}/rd.json, {out}/rd.md and charts in {time.time() - t_start:.0f} s", file=sys.stderr)


def image_part(args, bindir, work):
    L = args.image_level
    n = (1 << L) + 1
    field = args.image_field
    if field == "harmonic":
        arr, spacing = harmonic_grid(L)
    else:
        arr, spacing, _ = fem_grid(L, args.fem_cells)
    vr = float(arr.max()) - float(arr.min())
    raw = os.path.join(work, f"image-{field}-l{L}.raw")
    write_raw(arr, raw)
    size = args.image_size
    tw = os.path.join(bindir, "tetwave")
    bounds = [x.strip() for x in args.image_bounds.split(",") if x.strip()]
    if not bounds:
        fail("--image-bounds names no bound")
    d = os.path.join(work, "image")
    os.makedirs(d, exist_ok=True)
    print(f"bench-rd: image part, {field} {n}^3, bounds {', '.join(bounds)} x range, {size}", file=sys.stderr)
    # reference: the CPU integrator on the original samples (a lossless store of the grid)
    lossless = os.path.join(d, "original")
    prepare(bindir, raw, n, spacing, L, lossless)
    check_samples(lossless, arr)
    ref_png = os.path.join(d, "reference.png")
    run([tw, "render", lossless, "--reference", "--tf", "default", "--size", size, "-o", ref_png, "--json"], "render reference")
    ref = read_png(ref_png)
    # the GPU image of the original: the renderer's own error, the ceiling of every curve
    orig_png = os.path.join(d, "original-gpu.png")
    run([tw, "render", lossless, "--tf", "default", "--size", size, "-o", orig_png, "--json"], "render original")
    nodes = 6 * ((8**L) - 1) // 7
    per = args.image_per_frame or max(1, nodes // 16)
    streams, sz3s = [], []
    previews = [None] if args.image_preview == "none" else [None, args.image_preview]
    for b in bounds:
        e = float(b) * vr
        for pv in previews:
            # ours: stream the bounded store in view order, a GPU frame as nodes arrive
            tag = b if pv is None else f"{b}-preview"
            store = os.path.join(d, f"tetwave-{tag}")
            prep = prepare(bindir, raw, n, spacing, L, store, e, args.predictor, pv)
            sdir = os.path.join(d, f"stream-{tag}")
            st = stream(bindir, store, "view", sdir,
                        ["--frames", "100000", "--per-frame", str(per), "--size", size, "--tol", "0",
                         "--tf", "default"],
                        ["--max-batch", str(args.image_max_batch)] if args.image_max_batch else [])
            frames = []
            for fr in st["frames"]:
                img = read_png(os.path.join(sdir, f"frame_{fr['frame']:04d}.png"))
                frames.append({"frame": fr["frame"], "bytes_received": fr["bytes_received"], "nodes": fr["nodes"],
                               "image_psnr_db": image_psnr(img, ref)})
            streams.append({"bound": b, "preview": pv, "store_bytes": prep["bytes"],
                            "preview_bytes": prep.get("preview_bytes", 0),
                            "stream_wire_bytes": st["wire_bytes_down"],
                            "stream_message_bytes": st["message_bytes"], "frames": frames})
        # SZ3 at the same bound: decode, prepare the decoded grid lossless, render the same view
        c, dec = sz3(arr, e)
        sraw = os.path.join(d, f"sz3-{b}-decoded.raw")
        write_raw(dec, sraw)
        sstore = os.path.join(d, f"sz3-{b}-decoded")
        prepare(bindir, sraw, n, spacing, L, sstore)
        spng = os.path.join(d, f"sz3-{b}.png")
        run([tw, "render", sstore, "--tf", "default", "--size", size, "-o", spng, "--json"], f"render SZ3-decoded grid at {b}")
        sz3s.append({"bound": b, "bytes": int(c.size), "image_psnr_db": image_psnr(read_png(spng), ref),
                     "value_range_decoded": float(dec.max()) - float(dec.min())})
    target = sz3s[0]

    def first(pred):
        """The frame with the fewest bytes, over every stream, that satisfies `pred`."""
        hits = [(fr["bytes_received"], s, fr) for s in streams for fr in s["frames"] if pred(fr)]
        if not hits:
            return None
        b, st, fr = min(hits, key=lambda h: h[0])
        return {"bound": st["bound"], "preview": st["preview"], "frame": fr["frame"], "bytes_received": b,
                "image_psnr_db": fr["image_psnr_db"], "of_sz3_bytes": b / target["bytes"]}

    return {
        "field": field,
        "grid": f"{n}^3",
        "level": L,
        "value_range": vr,
        "size": size,
        "view": "azimuth 35, elevation 25, distance 1.6 x diagonal, fov 40",
        "renderer": "GPU projected tetrahedra (tetwave stream / tetwave render); reference: CPU integrator",
        "per_frame": per,
        "max_batch": args.image_max_batch or None,
        "original_gpu_image_psnr_db": image_psnr(read_png(orig_png), ref),
        "streams": streams,
        "sz3": sz3s,
        "reaches_sz3": first(lambda fr: fr["image_psnr_db"] >= target["image_psnr_db"]),
        "usable_30db": first(lambda fr: fr["image_psnr_db"] >= 30.0),
    }


def with_preview(point):
    return f" with a {point['preview']} preview" if point.get("preview") else ""


def image_tables(image):
    """The image part's tables and its two read-off points, as markdown lines."""
    t = image["sz3"][0]
    out = ["", f"Image PSNR, default view, {image['field']} {image['grid']}, {image['size']} (against the CPU reference "
           f"image of the original samples; the GPU image of the original: {image['original_gpu_image_psnr_db']:.2f} dB):", ""]
    for s in image["streams"]:
        pv = f", preview at {s['preview']} ({fmt_bytes(s['preview_bytes'])} B)" if s.get("preview") else ""
        out += [f"tetwave stream prepared at {s['bound']} × range (store {fmt_bytes(s['store_bytes'])} B{pv}):", "",
                "| frame | nodes | bytes received | image PSNR (dB) |", "|---|---|---|---|"]
        for fr in s["frames"]:
            out.append(f"| {fr['frame']} | {fr['nodes']:,} | {fmt_bytes(fr['bytes_received'])} | {fr['image_psnr_db']:.2f} |")
        out.append("")
    out += ["SZ3 file, decoded, then rendered:", "", "| bound × range | bytes | image PSNR (dB) |", "|---|---|---|"]
    for z in image["sz3"]:
        out.append(f"| {z['bound']} | {fmt_bytes(z['bytes'])} | {z['image_psnr_db']:.2f} |")
    out.append("")
    r, u = image["reaches_sz3"], image["usable_30db"]
    out.append(f"- SZ3 at {t['bound']} × range: {t['image_psnr_db']:.2f} dB from {fmt_bytes(t['bytes'])} B. "
               + (f"tetwave reaches it first with the stream prepared at {r['bound']} × range{with_preview(r)}: "
                  f"{r['image_psnr_db']:.2f} dB after {fmt_bytes(r['bytes_received'])} B, {r['of_sz3_bytes']:.2f}× SZ3's file."
                  if r else "No tetwave stream reaches it."))
    out.append(f"- 30 dB: " + (f"first after {fmt_bytes(u['bytes_received'])} B ({u['image_psnr_db']:.2f} dB, stream at "
                                f"{u['bound']} × range{with_preview(u)}), {100 * u['of_sz3_bytes']:.1f} % of SZ3's file at {t['bound']}."
                                if u else "no frame reaches it."))
    return out


def tables(rows, image):
    out = ["| field | grid | bound × range | codec | bytes | raw f32 / bytes | max abs error | max error / bound | PSNR (dB) |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(
            f"| {r['field']} | {r['grid']} | {r['bound']} | {r['codec']} | {fmt_bytes(r['bytes'])} | "
            f"{r['raw_f32_bytes'] / r['bytes']:.2f} | {r['max_abs_error']:.3e} | {r['max_abs_error'] / r['abs_bound']:.3f} | {r['psnr_db']:.2f} |"
        )
    out += ["", "Gap to SZ3 (bytes ÷ SZ3's bytes at the same bound):", "",
            "| field | grid | bound × range | tetwave stream / SZ3 | tetwave store / SZ3 | zfp / SZ3 |", "|---|---|---|---|---|---|"]
    groups = {}
    for r in rows:
        groups.setdefault((r["field"], r["grid"], r["bound"]), {})[r["codec"]] = r
    for (f, g, b), c in groups.items():
        s = c["SZ3"]["bytes"]
        out.append(f"| {f} | {g} | {b} | {c['tetwave stream']['bytes'] / s:.2f} | {c['tetwave store']['bytes'] / s:.2f} | {c['zfp']['bytes'] / s:.2f} |")
    if image:
        out += image_tables(image)
    return "\n".join(out) + "\n"


def rd_charts(rows, out):
    groups = {}
    for r in rows:
        groups.setdefault((r["field"], r["level"], r["grid"]), []).append(r)
    for (field, L, grid), rs in groups.items():
        series = []
        for codec in ("tetwave stream", "tetwave store", "zfp", "SZ3"):
            pts = sorted((r["bytes"], r["psnr_db"], r["bound"]) for r in rs if r["codec"] == codec)
            series.append((codec, pts))
        charts.chart(
            os.path.join(out, f"rd-{field}-l{L}.svg"),
            f"Rate-distortion, {field} {grid} f32 samples",
            "bytes (B, log scale)",
            "PSNR of the samples vs value range (dB)",
            series,
            labels=True,
            xlog=True,
        )


if __name__ == "__main__":
    main()
