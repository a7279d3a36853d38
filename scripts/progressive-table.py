#!/usr/bin/env python3
"""Prints the README's Table 2 rows (level-5 runs without a budget) from out/bench-progressive.jsonl,
next to the thesis' figures (their 2007 machine), and one line per other run.

Usage: scripts/progressive-table.py [out/bench-progressive.jsonl]
"""
import json
import sys

# Thesis Table 2 (Harmonic, 182,819 tets): avg tets, vertices, edges, MB, refine ms per step,
# render ms per frame, FPS
THESIS = {
    "20%": (19383, 3757, 24753, 6.39, 26, 79, 8.502),
    "15%": (30913, 6474, 38399, 7.42, 37, 112, 6.108),
    "12.5%": (105940, 24130, 128792, 14.15, 235, 288, 1.836),
    "10%": (161683, 28213, 197454, 18.99, 399, 411, 1.193),
    "6.25%": (177744, 29083, 218458, 20.15, 296, 510, 1.205),
    "simple": (182819, 29759, 225449, 20.56, 183, 529, 1.365),
}

# Thesis Table 3 (Head256, the level-6 hierarchy size; another field, so other counts): the same
# columns. Its simple run kept only 23,405 details (ours keeps all 187,245).
THESIS3 = {
    "20%": (17286, 3649, 21938, 10.57, 21, 69, 9.732),
    "15%": (26392, 5284, 33072, 11.38, 34, 103, 6.481),
    "12.5%": (106112, 24594, 128888, 18.55, 260, 287, 1.718),
    "10%": (153945, 28252, 187605, 22.69, 421, 396, 1.158),
    "6.25%": (784857, 154413, 932437, 78.62, 8297, 1903, 0.097),
    "simple": (182819, 29759, 225449, 24.93, 183, 530, 1.364),
}


def header(*columns: str) -> None:
    """Prints a Markdown table header with these columns."""
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))


def table(title: str, *columns: str) -> None:
    """Prints a blank line, `title`, a blank line and the header of a table with these columns."""
    print()
    print(title)
    print()
    header(*columns)


def counts(r: dict, t) -> str:
    """The cells both thesis tables share: tets, vertices, edges, ours / thesis, and MB."""
    return (
        f"{r['avg_tets']:,.0f} / {t[0]:,} | {r['avg_vertices']:,.0f} / {t[1]:,} "
        f"| {r['avg_edges']:,.0f} / {t[2]:,} | {r['mb']:.2f}, {r['mb'] + r['sel_mb']:.2f} / {t[3]}"
    )


def row_name(r: dict) -> str:
    return "simple (all arrived)" if r["tol"] == "simple" else r["tol"]


def thesis_row(r: dict):
    """The thesis' row for run `r`: Table 3 (Head256 size) for level-6 runs, Table 2 otherwise."""
    return (THESIS3 if r["run"].startswith("l6") else THESIS).get(r["tol"])


def main() -> None:
    path = sys.argv[1] if len(sys.argv) > 1 else "out/bench-progressive.jsonl"
    runs = [json.loads(line) for line in open(path) if line.strip()]
    header(
        "tolerance", "avg tets ours / thesis", "vertices ours / thesis", "edges ours / thesis",
        "MB: mesh + buffer, + selector / thesis", "B per tet: mesh, selector",
        "refine ms per step: ours avg / max, thesis avg",
        "tets created+removed /s (end to end / mesh ops only)",
    )
    for r in runs:
        if r["run"] != "l5":
            continue
        t = thesis_row(r)
        if t is None:
            continue
        sel_b = r["sel_mb"] * 1e6 / max(r["avg_tets"], 1.0)
        name = row_name(r)
        print(
            f"| {name} | {counts(r, t)} "
            f"| {r['avg_bytes_per_tet']:.1f}, {sel_b:.1f} "
            f"| {r['avg_refine_ms']:.2f} / {r['max_refine_ms']:.2f}, {t[4]} "
            f"| {r['tets_per_s'] / 1e6:.2f} M / {r['op_tets_per_s'] / 1e6:.2f} M |"
        )
    level6 = [r for r in runs if r["run"] in ("l6-budget8", "l6")]
    if level6:
        table(
            "Level 6 (Head256 size) next to the thesis' Table 3 (Head256: another field, so other counts):",
            "tolerance", "run", "avg tets ours / thesis", "vertices ours / thesis",
            "edges ours / thesis", "MB: mesh + buffer, + selector / thesis",
            "refine ms per step: ours avg / max, thesis avg", "tets created+removed /s",
        )
        for r in level6:
            t = thesis_row(r)
            if t is None:
                continue
            name = row_name(r)
            print(
                f"| {name} | {r['run']} | {counts(r, t)} "
                f"| {r['avg_refine_ms']:.2f} / {r['max_refine_ms']:.2f}, {t[4]:,} "
                f"| {r['tets_per_s'] / 1e6:.2f} M |"
            )
    rendered = [r for r in runs if r.get("render")]
    if rendered:
        table(
            f"Rendering ({rendered[0]['render']['renderer']}; thesis: its 2007 GPU), "
            f"{len(rendered[0]['render']['frames'])} sampled steps per run; "
            "level 6 next to Table 3 (Head256), level 5 next to Table 2:",
            "tolerance", "run", "render ms per frame: ours avg (draw alone) / max, thesis avg",
            "FPS (refine + render) ours / thesis",
            "PSNR dB vs full-resolution reference: avg / min / last step",
        )
        for r in rendered:
            t = thesis_row(r) or (None,) * 7
            g = r["render"]
            name = row_name(r)
            print(
                f"| {name} | {r['run']} | {g['avg_ms']:.0f} ({g['avg_draw_ms']:.0f}) / {g['max_ms']:.0f}, {t[5]} "
                f"| {r['fps']:.2f} / {t[6]} "
                f"| {g['avg_psnr_db']:.2f} / {g['min_psnr_db']:.2f} / {g['frames'][-1]['psnr_db']:.2f} |"
            )
    memory = [r for r in runs if r["run"] in ("l5", "l6-budget8")]
    if memory:
        table(
            "Memory per average leaf tet (average bytes held over average tets, capacities), by part,\n"
            "next to the thesis' MB column over its average tets:",
            "tolerance", "run", "mesh B", "detail buffer B", "selector B", "client B (all three)",
            "mesh + buffer B / thesis B",
        )
        for r in memory:
            t = thesis_row(r)
            tets = max(r["avg_tets"], 1.0)
            mesh_b = r["mesh_mb"] * 1e6 / tets
            buf_b = (r["mb"] - r["mesh_mb"]) * 1e6 / tets
            sel_b = r["sel_mb"] * 1e6 / tets
            thesis_b = f"{t[3] * 1e6 / t[0]:.0f}" if t else "-"
            name = row_name(r)
            print(
                f"| {name} | {r['run']} | {mesh_b:.1f} | {buf_b:.1f} | {sel_b:.1f} "
                f"| {mesh_b + buf_b + sel_b:.1f} | {mesh_b + buf_b:.1f} / {thesis_b} |"
            )
    print()
    print("run, tol: M tets/s end to end; max / avg refine ms; mesh B per tet (avg), per leaf at the end;")
    print("          selector B per tet (avg); final = unbudgeted (settle frames)")
    for r in runs:
        sel_b = r["sel_mb"] * 1e6 / max(r["avg_tets"], 1.0)
        print(
            f"{r['run']:>11} {r['tol']:>6}: {r['tets_per_s'] / 1e6:.2f} M/s; "
            f"{r['max_refine_ms']:.2f} / {r['avg_refine_ms']:.2f} ms; "
            f"{r['avg_bytes_per_tet']:.1f}, {r['bytes_per_leaf']:.1f} B; {sel_b:.1f} B; "
            f"{r['final_same']} ({r['settle_frames']})"
        )


if __name__ == "__main__":
    main()
