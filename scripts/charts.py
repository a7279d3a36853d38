#!/usr/bin/env python3
"""Accuracy against time and bytes, as SVG charts (no plotting library needed).

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
import math
import os
import sys

W, H = 640, 400
ML, MR, MT, MB = 70, 150, 40, 55
COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf"]


def nice_ticks(lo, hi, n=5):
    if hi <= lo:
        hi = lo + 1.0
    step = 10 ** math.floor(math.log10((hi - lo) / n))
    for m in (1, 2, 5, 10):
        if (hi - lo) / (step * m) <= n:
            step *= m
            break
    t = math.floor(lo / step) * step
    ticks = [round(t, 10)]
    while ticks[-1] < hi - step * 1e-9:
        t += step
        ticks.append(round(t, 10))
    return ticks


def fmt(v):
    if abs(v) >= 1e6:
        return f"{v / 1e6:g} M"
    if abs(v) >= 1e3:
        return f"{v / 1e3:g} k"
    return f"{v:g}"


def esc(s):
    return str(s).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def chart(path, title, xlabel, ylabel, series, labels=False):
    """series: [(name, [(x, y, point_label or None), ...])]; lines join a series' points."""
    pts = [(x, y) for _, s in series for x, y, _ in s]
    if not pts:
        raise SystemExit(f"{path}: nothing to chart")
    xt = nice_ticks(min(0.0, min(p[0] for p in pts)), max(p[0] for p in pts))
    yt = nice_ticks(min(p[1] for p in pts), max(p[1] for p in pts))
    x0, x1, y0, y1 = xt[0], xt[-1], yt[0], yt[-1]
    pw, ph = W - ML - MR, H - MT - MB

    def sx(x):
        return ML + (x - x0) / (x1 - x0) * pw

    def sy(y):
        return MT + ph - (y - y0) / (y1 - y0) * ph

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" '
        f'font-family="sans-serif" font-size="12">',
        f'<rect width="{W}" height="{H}" fill="white"/>',
        f'<text x="{W / 2}" y="22" text-anchor="middle" font-size="14">{esc(title)}</text>',
    ]
    for t in xt:
        out.append(f'<line x1="{sx(t):.1f}" y1="{MT}" x2="{sx(t):.1f}" y2="{MT + ph}" stroke="#ddd"/>')
        out.append(f'<text x="{sx(t):.1f}" y="{MT + ph + 16}" text-anchor="middle">{fmt(t)}</text>')
    for t in yt:
        out.append(f'<line x1="{ML}" y1="{sy(t):.1f}" x2="{ML + pw}" y2="{sy(t):.1f}" stroke="#ddd"/>')
        out.append(f'<text x="{ML - 6}" y="{sy(t) + 4:.1f}" text-anchor="end">{fmt(t)}</text>')
    out.append(f'<rect x="{ML}" y="{MT}" width="{pw}" height="{ph}" fill="none" stroke="black"/>')
    out.append(f'<text x="{ML + pw / 2}" y="{H - 12}" text-anchor="middle">{esc(xlabel)}</text>')
    out.append(
        f'<text x="16" y="{MT + ph / 2}" text-anchor="middle" '
        f'transform="rotate(-90 16 {MT + ph / 2})">{esc(ylabel)}</text>'
    )
    for i, (name, s) in enumerate(series):
        c = COLORS[i % len(COLORS)]
        if len(s) > 1:
            d = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y, _ in s)
            out.append(f'<polyline points="{d}" fill="none" stroke="{c}" stroke-width="1.5"/>')
        for x, y, lab in s:
            out.append(f'<circle cx="{sx(x):.1f}" cy="{sy(y):.1f}" r="3" fill="{c}"/>')
            if labels and lab:
                out.append(f'<text x="{sx(x) + 6:.1f}" y="{sy(y) - 6:.1f}">{esc(lab)}</text>')
        ly = MT + 14 + 18 * i
        out.append(f'<rect x="{ML + pw + 12}" y="{ly - 9}" width="12" height="10" fill="{c}"/>')
        out.append(f'<text x="{ML + pw + 30}" y="{ly}">{esc(name)}</text>')
    out.append("</svg>")
    with open(path, "w") as f:
        f.write("\n".join(out) + "\n")
    print(f"wrote {path}", file=sys.stderr)


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
        "refine + render ms per frame",
        "mean PSNR dB vs full-resolution reference",
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
            "step",
            "PSNR dB vs full-resolution reference",
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
        "bytes received",
        "PSNR dB vs full-resolution reference",
        [("frames", [(f["bytes_received"], f["psnr_db"], None) for f in frames])],
    )
    chart(
        os.path.join(outdir, "stream-psnr-vs-ms.svg"),
        "Progressive stream: accuracy against time",
        "ms since connecting",
        "PSNR dB vs full-resolution reference",
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
