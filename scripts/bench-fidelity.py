#!/usr/bin/env python3
"""Fidelity benchmark: image accuracy against the user's ORIGINAL mesh, not tetwave's resampling of it.

Run through `scripts/bench-fidelity` (which builds the binaries and installs numpy, gmsh,
scikit-fem, meshio, vtk, matplotlib and pillow into the checkout's venv .venv); by hand:

  .venv/bin/python scripts/bench-fidelity.py --bin-dir target/release
      [--shapes torus,cube-octant,ball-holes,heatsink,grid] [--levels 3,4,5,6] [--size 512]
      [--tets 100000] [--grid-level 5] [--side-levels 4,6] [--tf default|auto] [--out out/bench-fidelity]
      [--no-vtk] [--no-stream] [--docs] [--replot] [--quick | --look]

Shapes (non-convex domains meshed by gmsh's OpenCASCADE kernel, about --tets tetrahedra each: the
mesh size is scaled from a coarse trial mesh,
at most three meshes), each with a smooth point field from a scikit-fem
solve (P1 on the same tets, the solution at the mesh's nodes), written as .vtu by meshio:

  torus        major radius 1, minor radius 0.35;
  cube-octant  the cube [0,2]^3 without its octant [1,2]^3;
  ball-holes   the unit ball with three orthogonal through-holes of radius 0.3 (along x, y and z);
  heatsink     a 4 x 3 x 0.3 base plate with 9 fins 0.12 thick, 2 tall;
  grid         a raw grid, not a mesh: the embedded harmonic field sampled on (2^G+1)^3 points of
               [0,30]^3 (G = --grid-level), as scripts/bench-rd.py's harmonic_grid.

PDE (the meshes): -div grad u + c u = f. torus, cube-octant, ball-holes: c = 0, f = a positive and
a negative Gaussian source (width 0.08 x the bounding-box diagonal) at the mesh nodes nearest to
(0.3, 0.35, 0.6) and (0.7, 0.65, 0.35) of the bounding box, u = the normalized x coordinate on the
whole boundary. heatsink: a fin equation, c = 0.5, f = 0, u = 1 on the bottom face z = 0 and no flux
elsewhere (the temperature decays up the fins).

Every image is rendered with the same default view (azimuth 35, elevation 25, distance 1.6 x the
bounding-box diagonal, fov 40; a store frames the same view as the file it was prepared from),
transfer function --tf and --size, and its PSNR (RGB, 8-bit units) is measured against the EXACT
image of the original: `tetwave render <mesh.vtu> --reference` (the CPU reference integrator on the
original tets). For a raw grid the original is its own (2^G+1)^3 samples: a lossless store prepared
with `--base box6 --levels G`, whose vertices are exactly the grid points (piecewise linear on the
grid's Kuhn tets, which is not the trilinear interpolant of the grid: the two differ inside each
cell), rendered with `--reference`. Rows:

  store L      `tetwave-server prepare <input> --levels L --json` (box5 base; store bytes: `bytes`
               of its report), then `tetwave render <store>` (GPU projected tetrahedra, the default
               centroid order) and `tetwave render <store> --reference` (CPU): what resampling costs;
  store L, original's range
               the GPU image of the store again with a transfer function (.json) that gives each
               value the colour and extinction the original's transfer function gives it: `tetwave
               render` maps a store's own sample range to the transfer function's [0, 1], which lies
               inside the original's range, so the plain store image is also re-coloured; this row
               separates that from the geometry and sampling error;
  stream bytes every TCP payload byte `tetwave-server serve` sends (level order) until `tetwave
               stream --headless --no-render --until-complete` holds every node of the store,
               through scripts/bench-rd.py's counting relay (skip with --no-stream);
  ours GPU     `tetwave render <mesh.vtu>` (GPU, centroid and mpvo orders) on the original tets;
  VTK          vtkProjectedTetrahedraMapper on the original tets, in this process, with the camera
               and transfer function of scripts/bench-vs-vtk (extinction per diagonal -> opacity per
               unit distance 1 - exp(-extinction / diagonal)). For the grid: VTK's own
               tetrahedralization of the image data (vtkDataSetTriangleFilter).

Writes OUT/fidelity.json, OUT/fidelity.md (tables), OUT/psnr-vs-level.png (+ .svg) and
OUT/side-by-side-<shape>.png (original exact | store at the --side-levels | ours GPU on the original
| VTK); with --docs, small copies go to docs/images/fidelity-<shape>.png and
docs/images/fidelity-psnr-vs-level.png. Work files under OUT/work/.
"""

import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np

SHAPES = ("torus", "cube-octant", "ball-holes", "heatsink", "grid")
# --look: the share of domain pixels the default look must draw at luma >= LOOK_LUMA (Rec. 709 of
# the 8-bit RGB / 255), and the PSNR a level-6 store keeps against the original in that look
LOOK_LUMA, LOOK_BRIGHT, LOOK_DB = 0.2, 0.25, 40.0


def fail(msg):
    raise SystemExit(f"bench-fidelity: {msg}")


def log(msg):
    print(f"bench-fidelity: {msg}", file=sys.stderr, flush=True)


def run(cmd, what):
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if r.returncode != 0:
        fail(f"{what} failed (status {r.returncode}): {' '.join(map(str, cmd))}\n{r.stderr}{r.stdout}")
    return r


def run_json(cmd, what):
    return json.loads(run(cmd, what).stdout)


# ------------------------------------------------------------------------------------------ meshes


def gmsh_shape(shape, h):
    """The tets of `shape` meshed with element size `h`: (points (n,3), tets (m,4)), unreferenced
    nodes dropped."""
    import gmsh

    gmsh.initialize(["-noenv"], readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add(shape)
        occ = gmsh.model.occ
        if shape == "torus":
            occ.addTorus(0, 0, 0, 1.0, 0.35)
        elif shape == "cube-octant":
            a = occ.addBox(0, 0, 0, 2, 2, 2)
            b = occ.addBox(1, 1, 1, 1, 1, 1)
            occ.cut([(3, a)], [(3, b)])
        elif shape == "ball-holes":
            s = occ.addSphere(0, 0, 0, 1.0)
            cyl = [
                occ.addCylinder(-1.5, 0, 0, 3, 0, 0, 0.3),
                occ.addCylinder(0, -1.5, 0, 0, 3, 0, 0.3),
                occ.addCylinder(0, 0, -1.5, 0, 0, 3, 0.3),
            ]
            occ.cut([(3, s)], [(3, c) for c in cyl])
        elif shape == "heatsink":
            base = occ.addBox(0, 0, 0, 4.0, 3.0, 0.3)
            fins = [occ.addBox(0.1 + i * 0.42, 0, 0.3, 0.12, 3.0, 2.0) for i in range(9)]
            occ.fuse([(3, base)], [(3, f) for f in fins])
        else:
            fail(f"unknown shape {shape!r}")
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.3 * h)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 12)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, nodes = gmsh.model.mesh.getElementsByType(4)  # 4-node tetrahedra
    finally:
        gmsh.finalize()
    p = coords.reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    t = index[nodes.astype(np.int64)].reshape(-1, 4)
    if len(t) == 0 or (t < 0).any():
        fail(f"{shape}: gmsh returned no tetrahedra or unknown nodes")
    used = np.unique(t)
    remap = np.full(len(p), -1)
    remap[used] = np.arange(len(used))
    return p[used], remap[t]


def mesh_shape(shape, target):
    """Meshes `shape` with about `target` tets (within 15%, or the third try): from a coarse
    trial size, the size is scaled by the cube root of the count ratio."""
    h = {"torus": 0.2, "cube-octant": 0.3, "ball-holes": 0.2, "heatsink": 0.2}[shape]
    for _ in range(3):
        p, t = gmsh_shape(shape, h)
        if abs(len(t) / target - 1.0) < 0.15:
            break
        h *= (len(t) / target) ** (1.0 / 3.0)
    return p, t, h


def solve(shape, p, t):
    """P1 scikit-fem solution at the nodes (see the docstring for the problem of each shape)."""
    import skfem
    from skfem.helpers import dot, grad

    mesh = skfem.MeshTet(np.ascontiguousarray(p.T), np.ascontiguousarray(t.T))
    basis = skfem.Basis(mesh, skfem.ElementTetP1())
    lo, hi = p.min(axis=0), p.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if shape == "heatsink":
        c, sources = 0.5, []
        D = np.flatnonzero(p[:, 2] < lo[2] + 1e-9 * diag)
        g = np.ones(len(D))
    else:
        c = 0.0
        sig = 0.08 * diag
        sources = []
        for rel, amp in (((0.3, 0.35, 0.6), 1.0), ((0.7, 0.65, 0.35), -0.8)):
            want = lo + np.array(rel) * (hi - lo)
            at = p[np.argmin(((p - want) ** 2).sum(axis=1))]
            sources.append((at, amp * 3.0 / sig**2, sig))
        D = mesh.boundary_nodes()
        g = (p[D, 0] - lo[0]) / (hi[0] - lo[0])

    @skfem.BilinearForm
    def a(u, v, w):
        return dot(grad(u), grad(v)) + c * u * v

    @skfem.LinearForm
    def rhs(v, w):
        f = 0.0 * w.x[0]
        for at, amp, sig in sources:
            r2 = sum((w.x[i] - at[i]) ** 2 for i in range(3))
            f = f + amp * np.exp(-r2 / (2 * sig * sig))
        return f * v

    t0 = time.time()
    A = skfem.asm(a, basis)
    b = skfem.asm(rhs, basis)
    u = np.zeros(basis.N)
    u[D] = g
    u = skfem.solve(*skfem.condense(A, b, x=u, D=D), solver=skfem.solver_iter_pcg(rtol=1e-10))
    if not np.isfinite(u).all():
        fail(f"{shape}: the solve gave non-finite values")
    return u, {"dirichlet_nodes": int(len(D)), "reaction": c, "sources": len(sources), "solve_s": round(time.time() - t0, 2)}


def harmonic_grid(levels):
    """tetwave_protocol::fields::harmonic at the (2^L+1)^3 points of [0,30]^3: scripts/bench-rd.py's."""
    return bench_rd().harmonic_grid(levels)


# ------------------------------------------------------------------------------------------ images


def read_png(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)


def bright_share(img, mask):
    """The share of the `mask`'s pixels whose luma (Rec. 709 weights on RGB / 255) is >= LOOK_LUMA."""
    rgb = img[..., :3].astype(np.float64) / 255.0
    y = 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]
    return float((y[mask] >= LOOK_LUMA).mean()) if mask.any() else 0.0


def image_psnr(a, b):
    if a.shape != b.shape:
        fail(f"image shapes differ: {a.shape} and {b.shape}")
    rmse = math.sqrt(float(np.mean((a - b) ** 2)))
    return 99.0 if rmse == 0 else min(99.0, 20.0 * math.log10(255.0 / rmse))


def camera(lo, hi, az=35.0, el=25.0, fov=40.0):
    """tetwave's default orbit camera (protocol/src/view.rs Camera::orbit, render_cli.rs):
    centre of the bounds, distance 1.6 x the diagonal, up +z."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    center = (lo + hi) / 2
    diag = float(np.linalg.norm(hi - lo))
    a, e = math.radians(az), math.radians(el)
    d = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    eye = center + d * 1.6 * diag
    f = center - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0, 0, 1.0])
    r /= np.linalg.norm(r)
    up = np.cross(r, f)
    return {"eye": eye.tolist(), "target": center.tolist(), "up": up.tolist(), "fovy_deg": fov, "diagonal": diag}


def tf_points(spec):
    """The transfer function's points as render/src/transfer.rs defines its presets (read from a
    .json file, or the preset table below, kept in step with transfer.rs)."""
    if spec == "auto":  # fitted per input by `tetwave render`: known once the exact image is drawn
        return None
    if spec.endswith(".json"):
        return json.load(open(spec))["points"]
    presets = {
        "default": [(0.0, [0.1, 0.2, 0.9], 0.5), (0.45, [0.2, 0.6, 0.9], 1.0), (0.6, [0.9, 0.9, 0.8], 4.0),
                    (0.8, [1.0, 0.6, 0.2], 12.0), (1.0, [1.0, 0.3, 0.1], 20.0)],
        "transparent": [(0.0, [0.2, 0.4, 1.0], 0.05), (0.5, [0.6, 0.9, 0.6], 0.2), (1.0, [1.0, 0.8, 0.3], 0.6)],
        "opaque": [(0.0, [0.3, 0.3, 0.9], 10.0), (0.5, [0.9, 0.9, 0.9], 30.0), (1.0, [1.0, 0.4, 0.1], 60.0)],
    }
    if spec not in presets:
        fail(f"--tf {spec}: VTK needs the points; give default, transparent, opaque or a .json file")
    return [{"s": s, "rgb": rgb, "extinction": e} for s, rgb, e in presets[spec]]


def range_matched_tf(tf, orig, store, path):
    """A transfer function for the store that maps its values to the colours and extinctions the
    original's transfer function gives them: `tetwave render` maps a store's own sample range
    (`store`) to [0, 1], the original maps its range (`orig`); this composes the two (exact: the
    map between the normalized scalars is linear). Written as a .json transfer function."""
    (lo_o, hi_o), (lo_s, hi_s) = orig, store
    xs = np.array([q["s"] for q in tf], float)
    tab = np.array([[*q["rgb"], q["extinction"]] for q in tf], float)
    to_orig = lambda s: (lo_s + s * (hi_s - lo_s) - lo_o) / (hi_o - lo_o)  # noqa: E731
    if hi_s > lo_s:
        knots = [(x * (hi_o - lo_o) + lo_o - lo_s) / (hi_s - lo_s) for x in xs]
        ss = sorted({0.0, 1.0, *[k for k in knots if 0.0 < k < 1.0]})
    else:
        ss = [0.0]
    pts = []
    for sv in ss:
        so = to_orig(sv) if hi_s > lo_s else 0.5
        v = [float(np.interp(so, xs, tab[:, c])) for c in range(4)]
        pts.append({"s": sv, "rgb": [min(1.0, max(0.0, c)) for c in v[:3]], "extinction": max(0.0, v[3])})
    with open(path, "w") as f:
        json.dump({"name": "range-matched", "points": pts}, f)
    return path


def bench_rd():
    """scripts/bench-rd.py as a module: its server, byte-counting relay and complete stream."""
    import importlib.util

    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bench-rd.py")
    spec = importlib.util.spec_from_file_location("bench_rd", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def vtk_render(grid, scalar, value_range, cam, tf, size, out_png, frames=1):
    """vtkProjectedTetrahedraMapper, as scripts/bench-vs-vtk drives it (scripts/speed-accuracy.py
    uses it too): after a warm-up frame, `frames` timed frames, each re-sorted (as ours sorts every
    frame) and read back (the frame is finished). Returns (ms of each timed frame, window class)."""
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")  # no X server: EGL, silently
    import vtk

    grid.GetPointData().SetActiveScalars(scalar)
    lo, hi = value_range
    color = vtk.vtkColorTransferFunction()
    opacity = vtk.vtkPiecewiseFunction()
    for q in tf:
        s = lo + q["s"] * (hi - lo)
        color.AddRGBPoint(s, *q["rgb"])
        opacity.AddPoint(s, 1.0 - math.exp(-q["extinction"] / cam["diagonal"]))
    prop = vtk.vtkVolumeProperty()
    prop.SetColor(color)
    prop.SetScalarOpacity(opacity)
    prop.SetScalarOpacityUnitDistance(1.0)
    prop.SetInterpolationTypeToLinear()
    mapper = vtk.vtkProjectedTetrahedraMapper()
    mapper.SetInputData(grid)
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)
    ren = vtk.vtkRenderer()
    ren.AddVolume(volume)
    ren.SetBackground(0, 0, 0)
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.AddRenderer(ren)
    win.SetSize(size[0], size[1])
    c = ren.GetActiveCamera()
    c.SetPosition(*cam["eye"])
    c.SetFocalPoint(*cam["target"])
    c.SetViewUp(*cam["up"])
    c.SetViewAngle(cam["fovy_deg"])
    ren.ResetCameraClippingRange()
    win.Render()  # warm-up: uploads, first sort
    times = []
    pixels = vtk.vtkUnsignedCharArray()
    for _ in range(frames):
        c.Modified()  # forces the visibility re-sort
        t = time.perf_counter()
        win.Render()
        win.GetPixelData(0, 0, size[0] - 1, size[1] - 1, 0, pixels, 0)
        times.append((time.perf_counter() - t) * 1e3)
    w2i = vtk.vtkWindowToImageFilter()
    w2i.SetInput(win)
    w2i.SetInputBufferTypeToRGB()
    w2i.ReadFrontBufferOff()
    w2i.Update()
    png = vtk.vtkPNGWriter()
    png.SetFileName(out_png)
    png.SetInputConnection(w2i.GetOutputPort())
    png.Write()
    cls = win.GetClassName()
    win.Finalize()
    return times, cls


def vtk_grid_from_vtu(path):
    import vtk

    r = vtk.vtkXMLUnstructuredGridReader()
    r.SetFileName(path)
    r.Update()
    return r.GetOutput()


def vtk_grid_from_raw(arr, spacing):
    """VTK's own tetrahedralization of the image data (point scalar `u`)."""
    import vtk
    from vtk.util import numpy_support as ns

    n = arr.shape[0]
    img = vtk.vtkImageData()
    img.SetDimensions(n, n, n)
    img.SetSpacing(spacing, spacing, spacing)
    a = ns.numpy_to_vtk(np.ascontiguousarray(arr.ravel()), deep=1)
    a.SetName("u")
    img.GetPointData().SetScalars(a)
    tri = vtk.vtkDataSetTriangleFilter()
    tri.SetInputData(img)
    tri.Update()
    return tri.GetOutput()


def side_by_side(panels, path, panel_side=None, quantize=False):
    """Images left to right, each with its caption above; `panel_side` scales each panel."""
    from PIL import Image, ImageDraw, ImageFont

    ims = [Image.open(p).convert("RGB") for p, _ in panels]
    if panel_side is None and ims[0].width < 160:  # tiny (--quick) images: enlarge so captions fit
        ims = [im.resize((160, 160 * im.height // im.width), Image.NEAREST) for im in ims]
    elif panel_side:
        ims = [im.resize((panel_side, panel_side * im.height // im.width), Image.LANCZOS) for im in ims]
    w, h = ims[0].size
    font = ImageFont.load_default()
    lines = max(len(c.split("\n")) for _, c in panels)
    cap = 4 + 12 * lines
    out = Image.new("RGB", (w * len(ims) + 2 * (len(ims) - 1), h + cap), (255, 255, 255))
    d = ImageDraw.Draw(out)
    for i, (im, (_, caption)) in enumerate(zip(ims, panels)):
        x = i * (w + 2)
        d.multiline_text((x + 3, 2), caption, fill=(0, 0, 0), font=font, spacing=2)
        out.paste(im, (x, cap))
    if quantize:
        out = out.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    out.save(path, optimize=True)


# -------------------------------------------------------------------------------------------- main


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin-dir", required=True, help="directory holding tetwave-server and tetwave")
    ap.add_argument("--out", default="out/bench-fidelity")
    ap.add_argument("--shapes", default=",".join(SHAPES))
    ap.add_argument("--levels", default="3,4,5,6", help="store levels to prepare and draw")
    ap.add_argument("--side-levels", default="4,6", help="the two store levels in the side-by-side images")
    ap.add_argument("--size", default="512", help="image size: N (N x N) or WxH")
    ap.add_argument("--tets", type=int, default=100000, help="about this many tets per gmsh mesh")
    ap.add_argument("--grid-level", type=int, default=5, help="the raw grid has (2^G+1)^3 points")
    ap.add_argument("--tf", default="default", help="a preset, a .json file, or auto: no --tf, the default look "
                    "(a store's own fit to its manifest's histogram; VTK gets the points the exact image drew)")
    ap.add_argument("--no-vtk", action="store_true")
    ap.add_argument("--no-stream", dest="stream", action="store_false",
                    help="skip the complete stream of each store through the byte-counting relay")
    ap.add_argument("--docs", action="store_true", help="also write the small copies into docs/images/")
    ap.add_argument("--replot", action="store_true", help="only redraw the charts from OUT/fidelity.json (with --docs: its copy too)")
    ap.add_argument("--quick", action="store_true", help="~3,000-tet meshes, 17^3 grid, levels 2,3, 64x64: a smoke test "
                    "(fails unless every PSNR is finite and our GPU image of each original is >= 40 dB)")
    ap.add_argument("--look", action="store_true", help="the default look's check: the four meshes at ~3,000 tets, --tf auto, "
                    f"level 6, 128x128, no stream (fails unless each exact image of the original has >= {LOOK_BRIGHT:.0%} of its "
                    f"domain pixels at luma >= {LOOK_LUMA} and each level-6 store's GPU image is >= {LOOK_DB:.0f} dB against it)")
    args = ap.parse_args()
    if args.quick and args.look:
        fail("--quick and --look are two checks; give one")
    if args.quick:
        args.tets, args.grid_level, args.levels, args.side_levels, args.size = 3000, 4, "2,3", "2,3", "64"
    if args.look:
        args.tets, args.levels, args.side_levels, args.size, args.tf, args.stream = 3000, "6", "6", "128", "auto", False
        args.shapes = ",".join(s for s in SHAPES if s != "grid")
    size = tuple(int(x) for x in (args.size.lower().split("x") if "x" in args.size.lower() else (args.size, args.size)))
    size_arg = f"{size[0]}x{size[1]}"
    levels = [int(x) for x in args.levels.split(",")]
    side_levels = [int(x) for x in args.side_levels.split(",")]
    for L in side_levels:
        if L not in levels:
            fail(f"--side-levels {L} is not among --levels {args.levels}")
    shapes = args.shapes.split(",")
    for s in shapes:
        if s not in SHAPES:
            fail(f"unknown shape {s!r} ({', '.join(SHAPES)})")
    if args.replot:
        result = json.load(open(os.path.join(args.out, "fidelity.json")))
        chart(result, os.path.join(args.out, "psnr-vs-level"))
        if args.docs:
            chart(result, "docs/images/fidelity-psnr-vs-level", small=True)
        return
    bindir = args.bin_dir
    tw, tws = os.path.join(bindir, "tetwave"), os.path.join(bindir, "tetwave-server")
    for b in (tw, tws):
        if not os.access(b, os.X_OK):
            fail(f"{b} is missing")
    tf = tf_points(args.tf)
    vtk_error = None
    if args.no_vtk:
        vtk_error = "--no-vtk"
    else:
        try:
            import vtk  # noqa: F401
        except ImportError as e:
            vtk_error = f"import vtk failed: {e}"
            log(f"{vtk_error}; continuing without the VTK column")
    out = args.out
    work = os.path.join(out, "work")
    os.makedirs(work, exist_ok=True)
    t_start = time.time()
    results = []
    for shape in shapes:
        log(f"{shape}: meshing, solving")
        try:
            results.append(bench_shape(shape, args, levels, size, size_arg, tw, tws, tf, vtk_error, work, out))
        except SystemExit as e:
            log(f"{shape}: FAILED: {e}")
            results.append({"shape": shape, "error": str(e)})
    result = {
        "command": " ".join(sys.argv),
        "bin_dir": bindir,
        "size": size_arg,
        "tf": args.tf,
        "view": "azimuth 35, elevation 25, distance 1.6 x diagonal, fov 40",
        "levels": levels,
        "vtk": vtk_version() if vtk_error is None else vtk_error,
        "shapes": results,
        "seconds": round(time.time() - t_start, 1),
    }
    with open(os.path.join(out, "fidelity.json"), "w") as f:
        json.dump(result, f, indent=1)
    md = tables(result)
    with open(os.path.join(out, "fidelity.md"), "w") as f:
        f.write(md)
    print(md)
    chart(result, os.path.join(out, "psnr-vs-level"))
    if args.docs:
        os.makedirs("docs/images", exist_ok=True)
        chart(result, "docs/images/fidelity-psnr-vs-level", small=True)
        for r in results:
            if "error" not in r:
                docs_side_by_side(r, side_levels, os.path.join("docs/images", f"fidelity-{r['shape']}.png"))
    log(f"wrote {out}/fidelity.json, fidelity.md, psnr-vs-level.png and side-by-side images in {time.time() - t_start:.0f} s")
    if any("error" in r for r in results):
        sys.exit(1)
    if args.quick:  # the suite's smoke check (scripts/test): every figure finite, our GPU close to exact
        for r in results:
            for row in r["rows"]:
                for k in ("psnr_db", "gpu_psnr_db", "cpu_psnr_db", "gpu_range_matched_psnr_db"):
                    if k in row and not (math.isfinite(row[k]) and row[k] > 5.0):
                        fail(f"{r['shape']}: {row['what']}: {k} = {row[k]}")
            g = [row for row in r["rows"] if row["kind"] == "gpu-original"]
            if len(g) != 2 or min(x["psnr_db"] for x in g if x["order"] == "centroid") < 40.0:
                fail(f"{r['shape']}: our GPU image of the original is below 40 dB: {g}")
    if args.look:  # issue 34's acceptance: the default look shows each mesh, and level 6 stays faithful to it
        for r in results:
            exact, top = r["exact"], next(row for row in r["rows"] if row.get("level") == max(levels))
            if exact["tf"] != "auto":
                fail(f"{r['shape']}: the default look drew transfer function {exact['tf']!r}, not auto")
            if not exact["bright_share"] >= LOOK_BRIGHT:
                fail(f"{r['shape']}: {exact['bright_share']:.1%} of {exact['domain_pixels']:,} domain pixels at luma >= {LOOK_LUMA} "
                     f"in the default look (< {LOOK_BRIGHT:.0%})")
            if not top["gpu_psnr_db"] >= LOOK_DB:
                fail(f"{r['shape']}: store level {top['level']} GPU is {top['gpu_psnr_db']:.2f} dB against the original (< {LOOK_DB:.0f})")
            log(f"{r['shape']}: default look {exact['bright_share']:.1%} bright, store level {top['level']} {top['gpu_psnr_db']:.2f} dB: ok")


def vtk_version():
    import vtk

    return vtk.vtkVersion.GetVTKVersion()


def bench_shape(shape, args, levels, size, size_arg, tw, tws, tf, vtk_error, work, out):
    d = os.path.join(work, shape)
    os.makedirs(d, exist_ok=True)
    info = {"shape": shape}
    t0 = time.time()
    if shape == "grid":
        G = args.grid_level
        arr, spacing = harmonic_grid(G)
        n = arr.shape[0]
        src = os.path.join(d, f"harmonic-{n}.raw")
        arr.astype("<f4").tofile(src)
        grid_args = ["--dims", f"{n},{n},{n}", "--dtype", "f32", "--spacing", f"{spacing!r},{spacing!r},{spacing!r}"]
        # the original: a lossless store whose vertices are the grid points
        orig_store = os.path.join(d, "original-store")
        prep = run_json([tws, "prepare", src, *grid_args, "--base", "box6", "--levels", G, "--out", orig_store, "--json"], "prepare the grid's own store")
        original = orig_store
        info.update({"input": f"raw f32 grid {n}^3 (harmonic field on [0,30]^3)", "points": int(arr.size),
                     "original_tets": prep["leaves"], "original_bytes": int(arr.size * 4),
                     "original_is": f"lossless store --base box6 --levels {G} (vertices = the grid points)"})
        lo, hi = [0.0] * 3, [30.0] * 3
    else:
        import meshio

        p, t, h = mesh_shape(shape, args.tets)
        u, sol = solve(shape, p, t)
        src = os.path.join(d, f"{shape}.vtu")
        meshio.write(src, meshio.Mesh(p, [("tetra", t.astype(np.int64))], point_data={"u": u}))
        grid_args = []
        original = src
        info.update({"input": f"gmsh mesh + scikit-fem P1 solution, {src}", "points": int(len(p)), "original_tets": int(len(t)),
                     "mesh_size_h": round(h, 4), "solve": sol, "original_bytes": os.path.getsize(src),
                     "value_range_solution": [float(u.min()), float(u.max())]})
        lo, hi = p.min(axis=0).tolist(), p.max(axis=0).tolist()
    info["mesh_seconds"] = round(time.time() - t0, 1)
    log(f"{shape}: {info['original_tets']:,} tets, rendering the original")

    tf_arg = [] if args.tf == "auto" else ["--tf", args.tf]  # auto is render's default look: pass no --tf

    def render(inp, png, *extra):
        return run_json([tw, "render", inp, "--size", size_arg, *tf_arg, "-o", png, "--json", *extra], f"render {png}")

    exact_png = os.path.join(d, "original-exact.png")
    exact = render(original, exact_png, "--reference")
    ref = read_png(exact_png)
    if args.tf == "auto":  # the points the default look fitted to the original, for VTK and the range-matched row
        tf = exact["tf"]["points"]
    # the domain's pixels: the original drawn opaque white
    mask_tf = os.path.join(d, "mask-tf.json")
    with open(mask_tf, "w") as f:
        json.dump({"name": "mask", "points": [{"s": 0.0, "rgb": [1.0, 1.0, 1.0], "extinction": 1e5}]}, f)
    mask_png = os.path.join(d, "domain-mask.png")
    run([tw, "render", original, "--size", size_arg, "--tf", mask_tf, "-o", mask_png], "render the domain mask")
    mask = read_png(mask_png)[..., :3].max(axis=2) > 0
    info["exact"] = {"png": exact_png, "ms": round(exact["ms"]), "tets": exact["tets"], "value_range": exact["value_range"],
                     "tf": exact["tf"]["name"], "domain_pixels": int(mask.sum()), "bright_share": bright_share(ref, mask)}
    rows = []
    for order in ("centroid", "mpvo"):
        png = os.path.join(d, f"original-gpu-{order}.png")
        r = render(original, png, "--order", order)
        rows.append({"what": f"ours GPU on the original ({order})", "kind": "gpu-original", "order": order, "tets": r["tets"],
                     "psnr_db": image_psnr(read_png(png), ref), "bright_share": bright_share(read_png(png), mask), "ms": round(r["ms"]), "value_range": r["value_range"], "png": png})
    if vtk_error is None:
        cam = camera(lo, hi)
        png = os.path.join(d, "vtk.png")
        try:
            vg = vtk_grid_from_raw(arr, spacing) if shape == "grid" else vtk_grid_from_vtu(src)
            (ms,), window = vtk_render(vg, "u", exact["value_range"], cam, tf, size, png)
            rows.append({"what": "VTK vtkProjectedTetrahedraMapper on the original", "kind": "vtk", "tets": int(vg.GetNumberOfCells()),
                         "psnr_db": image_psnr(read_png(png), ref), "ms": round(ms), "window": window, "png": png})
        except Exception as e:  # VTK or its offscreen context failed: say so, keep the rest
            log(f"{shape}: VTK failed: {e}")
            info["vtk_error"] = str(e)
    for L in levels:
        store = os.path.join(d, f"store-l{L}")
        prep = run_json([tws, "prepare", src, *grid_args, "--levels", L, "--out", store, "--json"], f"prepare {store}")
        row = {"what": f"store level {L}", "kind": "store", "level": L, "store_bytes": prep["bytes"],
               "prepare_s": round(prep["seconds"], 2), "store_value_range": prep["value_range"],
               "outside_vertices": prep.get("outside_vertices"), "empty_base_tets": prep.get("empty_base_tets")}
        for mode, extra in (("gpu", []), ("cpu", ["--reference"])):
            png = os.path.join(d, f"store-l{L}-{mode}.png")
            r = render(store, png, *extra)
            row[f"{mode}_psnr_db"] = image_psnr(read_png(png), ref)
            row[f"{mode}_bright_share"] = bright_share(read_png(png), mask)
            row[f"{mode}_ms"] = round(r["ms"])
            row[f"{mode}_png"] = png
            row["tets"] = r["tets"]
            row["value_range"] = r["value_range"]
        # the same GPU image with the store's values coloured as the original colours them
        mtf = range_matched_tf(tf, exact["value_range"], row["value_range"], os.path.join(d, f"store-l{L}-tf.json"))
        png = os.path.join(d, f"store-l{L}-gpu-range-matched.png")
        r = run_json([tw, "render", store, "--size", size_arg, "--tf", mtf, "-o", png, "--json"], f"render {png}")
        row["gpu_range_matched_psnr_db"] = image_psnr(read_png(png), ref)
        if args.stream:
            st = bench_rd().stream(os.path.dirname(tw), store, "level", os.path.join(d, f"store-l{L}-stream"),
                                   ["--no-render", "--frames", "1000000"])
            row["stream_wire_bytes"] = st["wire_bytes_down"]
            row["stream_message_bytes"] = st["message_bytes"]
        log(f"{shape}: level {L}: {row['tets']:,} tets, {row['store_bytes']:,} B, GPU {row['gpu_psnr_db']:.2f} dB, CPU {row['cpu_psnr_db']:.2f} dB, "
            f"GPU with the original's value range {row['gpu_range_matched_psnr_db']:.2f} dB")
        rows.append(row)
    info["rows"] = rows
    panels = side_panels(info, [int(x) for x in args.side_levels.split(",")])
    path = os.path.join(out, f"side-by-side-{shape}.png")
    side_by_side(panels, path)
    info["side_by_side"] = path
    return info


def side_panels(info, side_levels):
    rows = info["rows"]
    panels = [(info["exact"]["png"], f"original, exact\n(CPU reference)\n{info['original_tets']:,} tets")]
    for L in side_levels:
        r = next(r for r in rows if r.get("level") == L)
        panels.append((r["gpu_png"], f"store level {L}, GPU\n{r['tets']:,} tets\n{r['gpu_psnr_db']:.1f} dB"))
    g = next(r for r in rows if r["kind"] == "gpu-original" and r["order"] == "centroid")
    panels.append((g["png"], f"ours GPU, original\n{g['tets']:,} tets\n{g['psnr_db']:.1f} dB"))
    v = [r for r in rows if r["kind"] == "vtk"]
    if v:
        panels.append((v[0]["png"], f"VTK projected tets\n{v[0]['tets']:,} tets\n{v[0]['psnr_db']:.1f} dB"))
    return panels


def docs_side_by_side(info, side_levels, path):
    for side in (200, 170, 140, 110):
        side_by_side(side_panels(info, side_levels), path, panel_side=side, quantize=True)
        if os.path.getsize(path) <= 150_000:
            return
    log(f"{path}: {os.path.getsize(path):,} B even at 110 px panels")


def fmt_db(x):
    return "—" if x is None else f"{x:.2f}"


def tables(result):
    out = [f"Image PSNR (dB, RGB, 8-bit) against the exact image of the original (`tetwave render <original> --reference`), "
           f"{result['size']}, transfer function `{result['tf']}`, view: {result['view']}. VTK {result['vtk']}.", ""]
    ok = [s for s in result["shapes"] if "error" not in s]
    levels = result["levels"]
    out += ["| shape | original tets | " + " | ".join(f"store L{L} GPU / CPU" for L in levels) +
            " | ours GPU, original (centroid / mpvo) | VTK PT, original |",
            "|---|---|" + "---|" * len(levels) + "---|---|"]
    for s in ok:
        by = {r.get("level"): r for r in s["rows"] if r["kind"] == "store"}
        g = {r["order"]: r for r in s["rows"] if r["kind"] == "gpu-original"}
        v = [r for r in s["rows"] if r["kind"] == "vtk"]
        out.append(f"| {s['shape']} | {s['original_tets']:,} | " +
                   " | ".join(f"{by[L]['gpu_psnr_db']:.2f} / {by[L]['cpu_psnr_db']:.2f}" for L in levels) +
                   f" | {g['centroid']['psnr_db']:.2f} / {g['mpvo']['psnr_db']:.2f} | {fmt_db(v[0]['psnr_db'] if v else None)} |")
    out += ["", "The store's GPU image with the original's value range (the same colours per value as the original; "
            "see the docstring): PSNR (dB) per level.", "",
            "| shape | " + " | ".join(f"store L{L}" for L in levels) + " |", "|---|" + "---|" * len(levels)]
    for s in ok:
        by = {r.get("level"): r for r in s["rows"] if r["kind"] == "store"}
        out.append(f"| {s['shape']} | " + " | ".join(f"{by[L]['gpu_range_matched_psnr_db']:.2f}" for L in levels) + " |")
    for s in ok:
        out += ["", f"**{s['shape']}**: {s['input']}; {s['points']:,} points, {s['original_tets']:,} tets, "
                f"original {s['original_bytes']:,} B; exact image {s['exact']['ms']:,} ms, value range "
                f"[{s['exact']['value_range'][0]:.6g}, {s['exact']['value_range'][1]:.6g}], transfer function "
                f"{s['exact']['tf']}, {s['exact']['bright_share']:.1%} of its {s['exact']['domain_pixels']:,} domain pixels "
                f"at luma >= {LOOK_LUMA}.", "",
                "| drawn | tets drawn | store bytes | stream bytes (wire) | value range mapped to the TF | PSNR GPU (dB) | PSNR CPU reference (dB) | PSNR GPU, original's range (dB) | ms GPU / CPU |",
                "|---|---|---|---|---|---|---|---|---|"]
        for r in s["rows"]:
            vr = r.get("value_range")
            vrs = f"[{vr[0]:.6g}, {vr[1]:.6g}]" if vr else "the original's"
            if r["kind"] == "store":
                wire = f"{r['stream_wire_bytes']:,}" if "stream_wire_bytes" in r else "—"
                out.append(f"| {r['what']} | {r['tets']:,} | {r['store_bytes']:,} | {wire} | {vrs} | {r['gpu_psnr_db']:.2f} | {r['cpu_psnr_db']:.2f} | {r['gpu_range_matched_psnr_db']:.2f} | {r['gpu_ms']:,} / {r['cpu_ms']:,} |")
            elif r["kind"] == "gpu-original":
                out.append(f"| {r['what']} | {r['tets']:,} | — | — | {vrs} | {r['psnr_db']:.2f} | (the reference) | — | {r['ms']:,} / {s['exact']['ms']:,} |")
            else:
                out.append(f"| {r['what']} | {r['tets']:,} | — | — | {vrs} | {r['psnr_db']:.2f} | — | — | {r['ms']:,} / — |")
    for s in result["shapes"]:
        if "error" in s:
            out += ["", f"**{s['shape']}**: failed: {s['error']}"]
        elif "vtk_error" in s:
            out += ["", f"**{s['shape']}**: VTK failed: {s['vtk_error']}"]
    out += ["", f"Command: `{result['command']}` ({result['seconds']} s)."]
    return "\n".join(out) + "\n"


def chart(result, stem, small=False):
    """Store PSNR against level per shape (colour): GPU solid, CPU reference dotted, GPU with the
    original's value range dash-dotted; VTK on the original as a dashed line; our GPU on the
    original (far above) in a note under the chart."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    ok = [s for s in result["shapes"] if "error" not in s]
    if not ok:
        return
    fig, ax = plt.subplots(figsize=(7.2, 4.6) if small else (9, 5.6), dpi=100)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    notes = []
    shape_handles = []
    for i, s in enumerate(ok):
        c = colors[i % len(colors)]
        st = [r for r in s["rows"] if r["kind"] == "store"]
        xs = [r["level"] for r in st]
        ax.plot(xs, [r["gpu_psnr_db"] for r in st], "o-", color=c)
        ax.plot(xs, [r["cpu_psnr_db"] for r in st], "x:", color=c, ms=9)
        ax.plot(xs, [r["gpu_range_matched_psnr_db"] for r in st], "+-.", color=c, ms=9, alpha=0.6)
        v = [r for r in s["rows"] if r["kind"] == "vtk"]
        if v:
            ax.axhline(v[0]["psnr_db"], color=c, lw=1, ls="--", alpha=0.6)
        g = {r["order"]: r["psnr_db"] for r in s["rows"] if r["kind"] == "gpu-original"}
        notes.append(f"{s['shape']} {g['centroid']:.1f}")
        shape_handles.append(Line2D([], [], color=c, lw=3, label=s["shape"]))
    kind_handles = [
        Line2D([], [], color="k", marker="o", ls="-", label="store, GPU"),
        Line2D([], [], color="k", marker="x", ls=":", ms=9, label="store, CPU reference"),
        Line2D([], [], color="k", marker="+", ls="-.", ms=9, alpha=0.6, label="store, GPU,\noriginal's value range"),
        Line2D([], [], color="k", ls="--", alpha=0.6, label="VTK PT on the original"),
    ]
    leg = ax.legend(handles=shape_handles, title="shape", fontsize=8, title_fontsize=8, loc="upper left",
                    bbox_to_anchor=(1.01, 1.0))
    ax.add_artist(leg)
    ax.legend(handles=kind_handles, title="drawn", fontsize=8, title_fontsize=8, loc="lower left",
              bbox_to_anchor=(1.01, 0.0))
    ax.set_xlabel("store level L (Bey refinements of the 5-tet base)")
    ax.set_ylabel("image PSNR vs exact image of the original (dB)")
    ax.set_xticks(result["levels"])
    ax.set_title(f"Fidelity against the original mesh, {result['size']}, TF {result['tf']}", fontsize=10)
    ax.grid(alpha=0.3)
    fig.text(0.01, 0.01, "ours GPU on the original, centroid order (dB): " + ", ".join(notes), fontsize=7.5)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(stem + ".png")
    if not small:
        fig.savefig(stem + ".svg")
    plt.close(fig)


if __name__ == "__main__":
    main()
