#!/usr/bin/env python3
"""Accuracy against time and bytes, as SVG charts drawn with matplotlib (scripts/setup puts it in
the venv .venv; run this script with .venv/bin/python).

  scripts/charts.py progressive [out/bench-progressive.jsonl] [OUT_DIR]
      From the runs drawn with `--render-every` (scripts/bench-progressive's `l5-render`):
      progressive-psnr-vs-frame-ms.svg  mean PSNR against refine + render ms per frame, one point
                                        per tolerance, one line per run (the FPS column's
                                        speed/accuracy trade);
      progressive-psnr-by-step[-RUN].svg  PSNR of each drawn step, one line per tolerance (one
                                        chart per run when there are several).
  scripts/charts.py stream [out/frames/frames.jsonl] [OUT_DIR]
      From a `tetwave stream --psnr` run (scripts/demo):
      stream-psnr-vs-bytes.svg          PSNR against bytes received;
      stream-psnr-vs-ms.svg             PSNR against milliseconds since connecting.

PSNR is always against the CPU reference integrator's image of the full-resolution mesh from the
same camera. OUT_DIR defaults to out/charts.
"""
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def chart(path, title, xlabel, ylabel, series, labels=False, xlog=False):
    """One chart: `series` is [(name, [(x, y, label or None), ...]), ...], drawn as lines with
    markers; labels (e.g. tolerances) annotate their points; `xlog`: logarithmic x axis. Prints
    what it drew."""
    fig, ax = plt.subplots(figsize=(7.2, 4.5), dpi=100)
    points = 0
    for name, pts in series:
        if not pts:
            continue
        xs = [p[0] for p in pts]
        ys = [p[1] for p in pts]
        ax.plot(xs, ys, marker="o", markersize=4, linewidth=1.2, label=str(name))
        points += len(pts)
        if labels:
            for x, y, lab in pts:
                if lab is not None:
                    ax.annotate(str(lab), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    if xlog:
        ax.set_xscale("log")
    ax.set_title(title, fontsize=11)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if len(series) > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, format="svg")
    plt.close(fig)
    print(f"wrote {path}: {points} points in {len(series)} series", file=sys.stderr)


def progressive(src, outdir):
    runs = [json.loads(line) for line in open(src) if line.strip()]
    runs = [r for r in runs if r.get("render")]
    if not runs:
        raise SystemExit(f"{src}: no run drawn with --render-every")
    renderer = runs[0]["render"]["renderer"].split(" (")[0]
    by_run = {}
    for r in runs:
        by_run.setdefault(r.get("run", "run"), []).append(r)
    chart(
        os.path.join(outdir, "progressive-psnr-vs-frame-ms.svg"),
        f"Progressive run: accuracy against frame time ({renderer})",
        "refine + render time per frame (ms)",
        "mean PSNR vs full-resolution reference (dB)",
        [
            (name, sorted((1e3 / r["fps"], r["render"]["avg_psnr_db"], r["tol"]) for r in rs))
            for name, rs in by_run.items()
        ],
        labels=True,
    )
    for name, rs in by_run.items():
        suffix = "" if len(by_run) == 1 else f"-{name}"
        chart(
            os.path.join(outdir, f"progressive-psnr-by-step{suffix}.svg"),
            f"Progressive run {name}: PSNR of the drawn steps",
            "step (frames of refinement)",
            "PSNR vs full-resolution reference (dB)",
            [(r["tol"], [(f["step"], f["psnr_db"], None) for f in r["render"]["frames"]]) for r in rs],
        )


def stream(src, outdir):
    frames = [json.loads(line) for line in open(src) if line.strip()]
    frames = [f for f in frames if f.get("psnr_db") is not None]
    if not frames:
        raise SystemExit(f"{src}: no frame with a PSNR (stream with --psnr)")
    chart(
        os.path.join(outdir, "stream-psnr-vs-bytes.svg"),
        "Progressive stream: accuracy against bytes received",
        "bytes received (B)",
        "PSNR vs full-resolution reference (dB)",
        [("frames", [(f["bytes_received"], f["psnr_db"], None) for f in frames])],
    )
    chart(
        os.path.join(outdir, "stream-psnr-vs-ms.svg"),
        "Progressive stream: accuracy against time",
        "time since connecting (ms)",
        "PSNR vs full-resolution reference (dB)",
        [("frames", [(f["ms_since_connect"], f["psnr_db"], None) for f in frames])],
    )


def main():
    if len(sys.argv) < 2 or sys.argv[1] not in ("progressive", "stream"):
        raise SystemExit(__doc__)
    kind = sys.argv[1]
    default = "out/bench-progressive.jsonl" if kind == "progressive" else "out/frames/frames.jsonl"
    src = sys.argv[2] if len(sys.argv) > 2 else default
    outdir = sys.argv[3] if len(sys.argv) > 3 else "out/charts"
    os.makedirs(outdir, exist_ok=True)
    (progressive if kind == "progressive" else stream)(src, outdir)


if __name__ == "__main__":
    main()
