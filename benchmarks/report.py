"""Generate the documentation's benchmark tables from the committed results.

Every table of figures in ``README.md`` and ``docs/*.md`` sits between two markers::

    <!-- results: NAME -->
    ...generated: a table and the line saying where, how and from what it was measured...
    <!-- /results -->

This script rewrites the content between the markers of every block it knows (:data:`BLOCKS`)
from ``benchmarks/results/NAME.csv`` and its provenance sidecar ``NAME.json`` (written by
:mod:`_provenance`), and writes ``docs/benchmarks.md`` whole (every block, what it measures,
and each result's machine, versions, commit and command). A result that is missing renders as
one line saying the command that measures it and how long that takes, so no page quotes a
figure that was not measured.

    python benchmarks/report.py            # rewrite the blocks and docs/benchmarks.md
    python benchmarks/report.py --check    # exit 1 naming each block (or file) that differs
    python benchmarks/report.py --stale    # exit 1 naming each result its measured code has changed since

``--stale`` reads, for every result, the commits of the runs that measured it (its sidecar) and
the code its benchmark measures (the script's ``MEASURES``), and names the results measured on a
modified tree, or before a later commit changed that code (``git diff``); such a figure is due to
be measured again. It needs the repository's history (a shallow clone cannot tell).

It also copies the ladder results :mod:`toolkit.common.fidelity` chooses from into the package
(:data:`PACKAGE_COPIES`, ``toolkit/common/data/ladders/``), so that an installed toolkit has them;
``--check`` fails when a copy differs from its result.

``--root`` and ``--results`` point at another tree (the tests use a temporary one).
"""

from __future__ import annotations

import argparse
import ast
import json
import math
import re
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
MACHINE = "a 2-core x86-64 CPU"
MARKER = re.compile(r"(?P<open><!-- results: (?P<name>[\w-]+) -->)(?P<body>.*?)(?P<close><!-- /results -->)",
                    re.DOTALL)
BENCHMARKS_PAGE = Path("docs") / "benchmarks.md"


@dataclass(frozen=True)
class Source:
    """A result file a block reads, and how to measure it when it is missing."""

    stem: str  #: ``benchmarks/results/<stem>.csv``
    command: str  #: the command that writes it
    minutes: float  #: its expected duration on a 2-core x86-64 CPU (AMD EPYC or Intel Xeon), min


@dataclass(frozen=True)
class Block:
    """One generated table: its sources and how they render."""

    name: str
    title: str
    about: str
    sources: tuple[Source, ...]
    render: Callable[[dict], str]  #: ``{stem: (DataFrame, sidecar)}`` of the present sources -> Markdown


# ----------------------------------------------------------------------------------------------
# formatting


def _number(v, spec: str | None = None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, str):
        return v.replace("|", "\\|").replace("\n", " ")
    if spec is not None:
        return spec.format(v)
    if isinstance(v, int):
        return f"{v:,}"
    a = abs(float(v))
    if a >= 1000:
        return f"{v:,.0f}"
    if a >= 100:
        return f"{v:.0f}"
    if a >= 0.01:
        return f"{v:#.3g}"
    return "0" if a == 0 else f"{v:.2e}"


def table(df: pd.DataFrame, columns: list[tuple] | None = None) -> str:
    """Markdown table of ``df``.

    ``columns`` lists ``(column, header)`` or ``(column, header, format)`` (a ``str.format``
    spec such as ``"{:.4f}"``); columns ``df`` lacks are left out. Default: every column.
    """
    if columns is None:
        columns = [(c, c) for c in df.columns]
    columns = [c if len(c) == 3 else (*c, None) for c in columns if c[0] in df.columns]
    lines = ["| " + " | ".join(h for _, h, _ in columns) + " |",
             "|" + "|".join("---:" if pd.api.types.is_numeric_dtype(df[c]) else "---" for c, _, _ in columns) + "|"]
    for _, row in df.iterrows():
        lines.append("| " + " | ".join(_number(_plain(row[c]), f) for c, _, f in columns) + " |")
    return "\n".join(lines)


def _plain(v):
    if hasattr(v, "item"):
        return v.item()
    return v


def _cpu(prov: dict) -> str:
    m = prov.get("machine", {})
    threads = m.get("threads", {})
    n = threads.get("env", {}).get("TOOLKIT_NUM_THREADS") or threads.get("torch")
    thread_text = f", {n} thread{'s' if str(n) != '1' else ''}" if n else ""
    family = f" (family {m['cpu_family']}, model {m['cpu_model']})" if m.get("cpu_family") else ""
    return f"{m.get('cpu', 'unknown CPU')}{family}, {m.get('cores', '?')} cores{thread_text}"


def _provenance_text(side: dict) -> str:
    """Machine, commit, date and command(s) (with their wall time) of a result."""
    if not side:
        return "provenance not recorded."
    prov = side["provenance"]
    runs = side.get("runs") or [{"command": prov["command"], "date": prov["date"], "commit": prov["git"]["commit"],
                                 "dirty": prov["git"]["dirty"]}]
    commits = sorted({r["commit"][:7] + (" with uncommitted changes" if r["dirty"] else "") for r in runs})
    dates = sorted({r["date"][:10] for r in runs})
    commands = "; ".join(f"`{r['command']}`" + (f" ({r['elapsed_s'] / 60:.1f} min)" if "elapsed_s" in r else "")
                         for r in runs)
    return (f"{_cpu(prov)}; commit {', '.join(commits)}; {', '.join(dates)}; "
            f"{'commands' if len(runs) > 1 else 'command'}: {commands}.")


def versions_line(side: dict) -> str:
    v = side.get("provenance", {}).get("versions", {})
    return ", ".join(f"{k} {val}" for k, val in v.items())


def _minutes(limit) -> str:
    """A training time limit as words: 'at most 1 min' or 'no time limit'."""
    return f"at most {float(limit):g} min" if limit else "no time limit on"


def not_measured(source: Source) -> str:
    return f"not measured: run `{source.command}` (about {source.minutes:g} min on {MACHINE})."


def _sources_footer(data: dict, sources) -> str:
    """One line per provenance: results measured by the same command share a line."""
    groups: dict[str, list[str]] = {}
    for s in sources:
        if s.stem in data:
            groups.setdefault(_provenance_text(data[s.stem][1]), []).append(f"`{s.stem}`")
    return "\n".join(f"- {', '.join(stems)}: {text}" for text, stems in groups.items())


# ----------------------------------------------------------------------------------------------
# the blocks


def _headline(data: dict) -> str:
    rows = []
    conv = data.get("static_convergence_runs")
    if conv is not None:
        df = conv[0]
        cells = [f"{r.resolution} ({r.nodes:,} nodes) {r.seconds:.1f} s" for r in df.itertuples()]
        rows.append(("Static", "FE time per simulation (default plan: 3 increments, linear, mucosa + lip sliding)",
                     "; ".join(cells), "~30 min per incremental simulation (the PointNet++ paper)"))
    else:
        rows.append(("Static", "FE time per simulation", not_measured(_source("static_convergence_runs")),
                     "~30 min per incremental simulation (the PointNet++ paper)"))
    surrogate = next((s for s in ("static_surrogate", "static_surrogate_coarse") if s in data), None)
    if surrogate:
        df, side = data[surrogate]
        one = df[df.test == "one subject"]
        size = side.get("extra", {})
        where = (f"{size.get('resolution', '?')} face, {size.get('plans', '?')} plans, "
                 f"at most {size.get('max_minutes', '?'):g} min training per model, CPU")
        pn = one[one.method == "PointNet++ explicit"]
        best = one.loc[one.mean_error_mm.idxmin()]
        err = f"PointNet++ explicit {pn.mean_error_mm.iloc[0]:.3g} mm; " if len(pn) else ""
        rows.append(("Static", "surrogate mean nodal error on test plans",
                     f"{err}best method: {best.method} {best.mean_error_mm:.3g} mm ({where})", "0.159-0.642 mm"))
        ms = f"PointNet++ explicit {pn.inference_ms.iloc[0]:.3g} ms" if len(pn) else f"{best.inference_ms:.3g} ms"
        rows.append(("Static", "surrogate inference per prediction", f"{ms} (CPU, batch 1)", "< 700 ms (GPU)"))
    else:
        rows.append(("Static", "surrogate mean nodal error", not_measured(_source("static_surrogate_coarse")),
                     "0.159-0.642 mm"))
    ladder = data.get("impact_ladder")
    fe = None
    if ladder is not None:
        df = ladder[0]
        hit = df[(df.resolution == "paper") & (df.integrator == "quasi-static") & (df.order == 2)
                 & (df.ball == "deformable") & (df.status == "ok")]
        if "velocity" in df:
            hit = hit[hit.velocity == 30]
        if len(hit):
            r = hit.iloc[0]
            nodes = (f", {int(r.face_nodes):,} nodes, {int(r.face_elements):,} elements"
                     if "face_nodes" in hit and pd.notna(r.face_nodes) else "")
            fe = (f"{r.wall_time_s:.1f} s (quasi-static, paper face{nodes}, tet10, deformable ball, 30 mm/s, "
                  f"{int(r.newton_iterations)} Newton iterations)")
    rows.append(("Impact", "FE time per run", fe or not_measured(_source("impact_ladder")),
                 "~45 s (Abaqus, ~30,000 C3D10)"))
    surrogate = next((s for s in ("impact_surrogate", "impact_surrogate_coarse") if s in data), None)
    if surrogate:
        df, side = data[surrogate]
        size = side.get("extra", {})
        where = (f"{size.get('resolution', '?')} face, tet{4 if size.get('order') == 1 else 10}, "
                 f"{size.get('ball', '?')} ball, mass scaling {size.get('mass_scaling', '?'):g}, "
                 f"{_minutes(size.get('max_minutes'))} training per model, random split")
        rnd = df[df.split == "random"].set_index("config")
        for cfg in ("paper", "strong"):
            if cfg not in rnd.index:
                continue
            r = rnd.loc[cfg]
            rows.append(("Impact", f"LSTM `{cfg}`: displacement RMSE / Pearson; von Mises RMSE / Pearson",
                         f"{r.displacement_rmse_mm:.3g} mm / {r.displacement_pearson:.3f}; "
                         f"{r.von_mises_rmse_mpa:.2e} MPa / {r.von_mises_pearson:.3f} ({where})",
                         "3.13 mm / 0.98; 0.001 MPa / 0.94"))
            rows.append(("Impact", f"LSTM `{cfg}`: training; inference per frame",
                         f"{r.train_seconds:.0f} s; {r.inference_ms:.3g} ms (CPU)", "~3 h training"))
    else:
        rows.append(("Impact", "LSTM accuracy", not_measured(_source("impact_surrogate_coarse")),
                     "3.13 mm / 0.98; 0.001 MPa / 0.94"))
    cpus = sorted({side.get("provenance", {}).get("machine", {}).get("cpu", "") for _, side in data.values()} - {""})
    measured_on = f"{cpus[0]}, 2 cores" if len(cpus) == 1 else "2 cores; each machine below"
    out = [table(pd.DataFrame(rows, columns=["Workflow", "Measure", f"This toolkit ({measured_on})", "Source paper"]))]
    missing = [s for s in (_source("static_surrogate"), _source("impact_surrogate")) if s.stem not in data]
    for s in missing:
        out.append(f"Paper-size `{s.stem}`: {not_measured(s)}")
    footer = _sources_footer(data, [_source(s) for s in ("static_convergence_runs", "static_surrogate",
                                                          "static_surrogate_coarse", "impact_ladder",
                                                          "impact_surrogate", "impact_surrogate_coarse")])
    return "\n\n".join([*out, footer] if footer else out)


def _phantoms(data):
    df, side = data["phantoms"]
    return table(df, [("phantom", "phantom"), ("resolution", "resolution"), ("nodes", "nodes"),
                      ("elements", "elements"), ("min_scaled_jacobian", "min scaled Jacobian", "{:.3f}"),
                      ("p01_scaled_jacobian", "1st percentile", "{:.3f}"), ("build_s", "build (s)"),
                      ("peak_mib", "peak memory (MiB)")])


def _mixed(data):
    df, side = data["mixed_elements"]
    piv = df.pivot_table(index=["mesh", "nu"], columns="h_mm", values="max_error_rel", sort=False)
    piv = piv[sorted(piv.columns, reverse=True)]
    slopes = df.groupby(["mesh", "nu"], sort=False).slope.first()
    out = piv.reset_index()
    out.columns = ["mesh", "nu", *[f"h = {h:g} mm" for h in piv.columns]]
    out["slope"] = slopes.to_numpy()
    cols = [("mesh", "mesh"), ("nu", "nu", "{:g}"), *[(c, c, "{:.2e}") for c in out.columns[2:-1]],
            ("slope", "log-log slope", "{:.2f}")]
    return table(out, cols)


def _convergence(data):
    parts = []
    if "static_convergence_runs" in data:
        parts.append(table(data["static_convergence_runs"][0], [
            ("resolution", "resolution"), ("nodes", "nodes"), ("elements", "elements"), ("seconds", "FE time (s)"),
            ("min_scaled_jacobian", "min scaled Jacobian", "{:.3f}"),
            ("mean_skin_displacement_mm", "mean skin displacement (mm)", "{:.3f}")]))
    if "static_convergence" in data:
        parts.append(table(data["static_convergence"][0], [
            ("pair", "resolutions"), ("points", "skin points"), ("mean_mm", "mean (mm)", "{:.3f}"),
            ("p95_mm", "95th percentile (mm)", "{:.3f}"), ("max_mm", "max (mm)", "{:.3f}")]))
    return "\n\n".join(parts)


def _solvers(data):
    df = data["static_solvers"][0].copy()
    df["status"] = df["status"].astype(str).str.split(":").str[0]  # the reason of an unavailable solver is long
    return table(df, [
        ("mesh", "mesh"), ("method", "method"), ("used", "used"), ("dofs", "dofs"), ("status", "status"),
        ("solve_s", "solve (s)"),
        ("iterations", "iterations"), ("reuse_s", "next solve, reused factor (s)"),
        ("reuse_iterations", "its iterations"), ("peak_rss_mib", "peak memory (MiB)"), ("auto_choice", "auto picks")])


def _meshed_speed(data, stems=("static_meshed_speed", "static_meshed_speed_ct")):
    t = pd.concat([data[k][0] for k in stems if k in data], ignore_index=True)
    t["face"] = t["face"].map(lambda f: "head CT" if f == "ct" else "phantom's surfaces")
    runs = table(t, [
        ("face", "face"), ("size_mm", "size (mm)", "{:g}"), ("nodes", "nodes"), ("code", "code"),
        ("repeat", "run"), ("seconds", "time (s)", "{:.1f}"), ("solves", "linear solves"),
        ("cg_iterations", "CG iterations"), ("solve_s", "in solves (s)", "{:.1f}"),
        ("peak_memory_mib", "peak memory (MiB)", "{:,.0f}"), ("max_difference_mm", "max difference (mm)", "{:.1e}"),
        ("max_skin_difference_mm", "on the skin (mm)", "{:.1e}")])
    ok = t[t.status == "ok"]
    mean = ok.groupby(["face", "size_mm", "code"], sort=False)["seconds"].mean().reset_index()
    first = mean.groupby(["face", "size_mm"], sort=False)["seconds"].transform("first")
    mean["ratio"] = mean["seconds"] / first
    ratios = table(mean, [("face", "face"), ("size_mm", "size (mm)", "{:g}"), ("code", "code"),
                          ("seconds", "mean time (s)", "{:.1f}"), ("ratio", "ratio to the first code", "{:.2f}")])
    return runs + "\n\n" + ratios


def _predict_speed(data):
    t = data["predict_speed"][0]
    med = t.groupby(["resolution", "run"], sort=False).agg(
        nodes=("nodes", "max"), runs=("wall_s", "size"), wall_s=("wall_s", "median"),
        in_process_s=("in_process_s", "median")).reset_index()
    fe = med[med.run == "simulate"].set_index("resolution")["wall_s"]
    med["ratio"] = [w / fe[r] if run in ("simulate", "predict") else float("nan")
                    for r, run, w in zip(med.resolution, med.run, med.wall_s)]
    return table(med, [("resolution", "resolution"), ("nodes", "nodes", "{:,.0f}"), ("run", "run"),
                       ("runs", "runs"), ("wall_s", "median wall time (s)", "{:.2f}"),
                       ("in_process_s", "in the process's work (s)", "{:.3f}"),
                       ("ratio", "wall time / the FE's", "{:.2f}")])


def _slow_modes(data):
    t = data["slow_modes"][0].copy()
    t["face"] = t["face"].map(lambda f: "head CT" if f == "ct" else "phantom's surfaces")
    return table(t, [
        ("face", "face"), ("dofs", "dofs"), ("cg_iterations", "CG iterations"), ("mode", "mode"),
        ("relative", "eigenvalue / mean diagonal", "{:.1e}"), ("nodes_95", "nodes holding 95 %"),
        ("centre_mm", "centre (mm)"), ("extent_mm", "extent (mm)"), ("sliding_nodes", "sliding on a bone"),
        ("skin_nodes", "on the skin"), ("elements_inside", "elements inside"),
        ("elements_joining", "elements joining the rest"), ("coherence", "coherence", "{:.2f}")])


_PEER_SIZES = {"7": "phantom 7 mm", "3.5": "phantom 3.5 mm", "ct": "head CT 3 mm"}


def _peers(data):
    t = data["peers"][0].copy()
    t["size"] = t["size"].map(lambda s: _PEER_SIZES.get(str(s).removesuffix(".0"), s))  # 7 reads as 7.0
    t["status"] = t["status"].astype(str)
    main = table(t, [("problem", "problem"), ("size", "mesh"), ("code", "code"), ("method", "method"),
                     ("version", "version"), ("nodes", "nodes"), ("dofs", "free dofs"),
                     ("assemble_s", "assemble (s)"), ("setup_s", "setup (s)"), ("solve_s", "solve (s)"),
                     ("total_s", "total (s)"), ("iterations", "iterations", "{:.0f}"),
                     ("peak_rss_mib", "peak memory (MiB)", "{:,.0f}"), ("rel_diff", "rel. diff. to toolkit"),
                     ("status", "status")])
    ok = t[t["status"] == "ok"]
    rows = []
    for (problem, size), g in ok.groupby(["problem", "size"], sort=False):
        own, peers = g[g["code"] == "toolkit"], g[g["code"] != "toolkit"]
        if own.empty or peers.empty:
            continue
        best = peers.loc[peers["total_s"].idxmin()]
        rows.append({"problem": problem, "size": size, "toolkit_s": own["total_s"].iloc[0],
                     "peer": f"{best['code']} {best['method']}", "peer_s": best["total_s"],
                     "ratio": own["total_s"].iloc[0] / best["total_s"]})
    if not rows:
        return main
    ratio = table(pd.DataFrame(rows), [("problem", "problem"), ("size", "mesh"), ("toolkit_s", "toolkit total (s)"),
                                       ("peer", "fastest peer"), ("peer_s", "its total (s)"),
                                       ("ratio", "toolkit / fastest peer", "{:.2f}")])
    return main + "\n\n" + ratio


def _mesh_convergence(data):
    t = data["mesh_convergence"][0]
    return table(t, [("size_mm", "size (mm)", "{:g}"), ("nodes", "nodes"), ("mesh_s", "meshing (s)", "{:.0f}"),
                     ("simulate_s", "default plan (s)", "{:.0f}"), ("linear_solves", "linear solves"),
                     ("peak_memory_gib", "peak memory (GiB)", "{:.1f}"),
                     ("diff_mean_mm", "skin vs finest: mean (mm)", "{:.3f}"),
                     ("diff_p95_mm", "p95 (mm)", "{:.3f}"), ("diff_max_mm", "max (mm)", "{:.2f}"),
                     ("hex_diff_p95_mm", "p95 vs the hexahedral phantom (mm)", "{:.3f}")])


def _profiles(data):
    t = data["profiles"][0].copy()
    t = t[t["rank"] <= 6]
    return table(t, [("path", "path"), ("total_s", "run (s)", "{:.1f}"), ("rank", "rank"), ("function", "function"),
                     ("own_s", "own time (s)", "{:.2f}"), ("share", "share", "{:.0%}"), ("calls", "calls")])


def _ladder(data):
    df = data["static_ladder"][0]
    return table(df, [
        ("resolution", "resolution"), ("material", "material"), ("increments", "increments"), ("sliding", "sliding"),
        ("status", "status"), ("wall_time_s", "time (s)"), ("peak_rss_mib", "peak memory (MiB)"),
        ("p95_diff_mm", "p95 nodal difference (mm)", "{:.3f}"),
        ("skin_mean_diff_mm", "mean skin difference (mm)", "{:.3f}"),
        ("skin_max_diff_mm", "max skin difference (mm)", "{:.3f}"),
        ("min_scaled_jacobian", "min scaled Jacobian", "{:.3f}")])


def _robustness(data):
    return table(data["static_robustness"][0], [
        ("resolution", "resolution"), ("material", "material"), ("sliding", "sliding"), ("mode", "plans drawn"),
        ("plans", "plans"), ("completed", "completed"), ("median_s", "median time (s)"), ("max_s", "max time (s)"),
        ("min_sj", "min scaled Jacobian", "{:.3f}"), ("wider_band", "wider release band"),
        ("freed_cut", "cut nodes freed")])


def _surrogate_static(data):
    parts = []
    for stem, label in (("static_surrogate", "Paper size"), ("static_surrogate_coarse", "Coarse size")):
        if stem not in data:
            parts.append(f"{label}: {not_measured(_source(stem))}")
            continue
        df, side = data[stem]
        x = side.get("extra", {})
        parts.append(f"{label}: {x.get('resolution', '?')} face, {x.get('plans', '?')} plans ({x.get('mode', '?')}), "
                     f"{x.get('subjects', 1)} subject(s), network `{x.get('network', '?')}`, "
                     f"at most {x.get('max_minutes', '?'):g} min training per model.")
        parts.append(table(df, [
            ("method", "method"), ("test", "test"), ("samples", "samples"),
            ("mean_error_mm", "mean error (mm)", "{:.3f}"), ("median_error_mm", "median (mm)", "{:.3f}"),
            ("p95_error_mm", "95th percentile (mm)", "{:.3f}"), ("free_mean_error_mm", "free nodes (mm)", "{:.3f}"),
            ("train_seconds", "training (s)"), ("inference_ms", "inference (ms)"), ("fe_ms", "FE (ms)"),
            ("speedup_vs_fe", "speed-up")]))
        ab = x.get("ablation")
        if ab:
            parts.append(f"Explicit vs implicit boundary input: {ab['explicit_mean_mm']:.3f} mm vs "
                         f"{ab['implicit_mean_mm']:.3f} mm on {ab['n']} paired test samples, Wilcoxon signed-rank "
                         f"p = {ab['wilcoxon_p']:.3g}.")
    return "\n\n".join(parts)


def _impact_columns(extra: list[tuple] = ()):
    return [("resolution", "resolution"), ("velocity", "velocity (mm/s)", "{:g}"), ("integrator", "integrator"),
            *extra, ("order", "order"), ("ball", "ball"), ("mass_scaling", "mass scaling", "{:g}"),
            ("status", "status"), ("steps", "steps"), ("wall_time_s", "time (s)"),
            ("peak_rss_mib", "peak memory (MiB)"), ("max_displacement_mm", "max displacement (mm)", "{:.2f}"),
            ("max_von_mises_mpa", "max von Mises (MPa)", "{:.4f}"),
            ("p95_displacement_mm", "p95 nodal difference (mm)", "{:.3f}"),
            ("rmse_displacement_mm", "RMSE to reference (mm)", "{:.3f}"),
            ("pearson_displacement", "Pearson", "{:.4f}"), ("rmse_mirrored_mm", "RMSE mirrored (mm)", "{:.3f}")]


def _impact_ladder(data):
    df = data["impact_ladder"][0]
    return table(df, _impact_columns())


def _quasi_static(data):
    df = data["impact_ladder"][0]
    df = df[df.integrator == "quasi-static"] if "integrator" in df else df.iloc[:0]
    if not len(df):
        return not_measured(Source("impact_ladder", "python benchmarks/impact_ladder.py --resolutions coarse "
                                   "--orders 2 --integrators quasi-static", 3))
    return table(df, _QUASI_STATIC_COLUMNS)


_QUASI_STATIC_COLUMNS = [
    ("resolution", "resolution"), ("velocity", "velocity (mm/s)", "{:g}"), ("tolerance", "tolerance", "{:g}"),
    ("order", "order"), ("ball", "ball"), ("status", "status"), ("steps", "load steps"),
    ("newton_iterations", "Newton iterations"), ("step_cuts", "cuts"), ("wall_time_s", "time (s)"),
    ("peak_rss_mib", "peak memory (MiB)"), ("max_displacement_mm", "max displacement (mm)", "{:.2f}"),
    ("max_von_mises_mpa", "max von Mises (MPa)", "{:.4f}"), ("rmse_displacement_mm", "RMSE to explicit (mm)", "{:.3f}"),
    ("pearson_displacement", "Pearson", "{:.4f}")]


def _velocities(data):
    df = data["impact_ladder_velocities"][0]
    if "rmse_displacement_mm" in df and df.rmse_displacement_mm.isna().all():  # no explicit run at these speeds
        df = df.drop(columns=["rmse_displacement_mm", "pearson_displacement"])
    return table(df, _QUASI_STATIC_COLUMNS)


def _yielding(data):
    df = data["impact_ladder_yielding"][0].copy()
    df["status"] = [s if s == "ok" else f"{s}: {e.split(': ', 1)[-1]}" for s, e in zip(df.status, df.error.fillna(""))]
    ref = df[(df.integrator == "explicit") & (df.status == "ok")].set_index("velocity")
    df = df[~df.index.isin(df.index[(df.integrator == "explicit") & (df.status == "ok")])].sort_values("velocity")
    df["explicit_s"] = df.velocity.map(ref.wall_time_s)
    df["displacement_rmse_pct"] = 100 * df.rmse_displacement_mm / df.velocity.map(ref.max_displacement_mm)
    df["von_mises_rmse_pct"] = 100 * df.rmse_von_mises_mpa / df.velocity.map(ref.max_von_mises_mpa)
    return table(df, [("velocity", "velocity (mm/s)", "{:g}"), ("integrator", "integrator"), ("status", "status"),
                      ("wall_time_s", "time (s)", "{:.0f}"), ("explicit_s", "explicit reference (s)", "{:.0f}"),
                      ("max_displacement_mm", "max displacement (mm)", "{:.2f}"),
                      ("max_von_mises_mpa", "max von Mises (MPa)", "{:.4f}"),
                      ("displacement_rmse_pct", "displacement RMSE (% of peak)", "{:.2f}"),
                      ("pearson_displacement", "Pearson", "{:.4f}"),
                      ("von_mises_rmse_pct", "von Mises RMSE (% of peak)", "{:.2f}"),
                      ("pearson_von_mises", "Pearson", "{:.4f}")])


def _surrogate_impact(data):
    parts = []
    for stem, label in (("impact_surrogate", "Paper size"), ("impact_surrogate_coarse", "Quick size")):
        if stem not in data:
            parts.append(f"{label}: {not_measured(_source(stem))}")
            continue
        df, side = data[stem]
        x = side.get("extra", {})
        parts.append(f"{label}: {x.get('resolution', '?')} face, tet{4 if x.get('order') == 1 else 10}, "
                     f"{x.get('ball', '?')} ball, mass scaling {x.get('mass_scaling', '?'):g}, "
                     f"{_minutes(x.get('max_minutes'))} training per model; the impact paper: "
                     "3.13 mm / 0.98 (displacement), 0.001 MPa / 0.94 (von Mises), ~3 h training.")
        parts.append(table(df, [
            ("config", "configuration"), ("split", "split"), ("displacement_rmse_mm", "displacement RMSE (mm)"),
            ("displacement_pearson", "Pearson", "{:.4f}"), ("displacement_nrmse", "NRMSE", "{:.3f}"),
            ("von_mises_rmse_mpa", "von Mises RMSE (MPa)", "{:.2e}"), ("von_mises_pearson", "Pearson", "{:.4f}"),
            ("train_seconds", "training (s)"), ("inference_ms", "inference (ms/frame)"),
            ("fe_ms_per_frame", "FE (ms/frame)")]))
    return "\n\n".join(parts)


def _of(flags: pd.Series) -> str:
    """'N of M': the true values among the recorded ones (empty cells: not applicable)."""
    known = flags.dropna().astype(str).str.lower() == "true"
    return f"{int(known.sum())} of {len(known)}"


def _bad_inputs(data):
    df = data["bad_inputs"][0]
    side = data["bad_inputs"][1]
    order = list(dict.fromkeys(df["command"]))
    g = df.groupby("command", sort=False)
    out = pd.DataFrame({
        "command": [f"`toolkit {c}`" for c in order],
        "cases": g.size().reindex(order).to_numpy(),
        "clear": g["clear"].sum().reindex(order).astype(int).to_numpy(),
        "option": [_of(d["names_option"]) for _, d in g],
        "left": g["left_files"].sum().reindex(order).astype(int).to_numpy(),
        "median_s": g["seconds"].median().reindex(order).to_numpy(),
        "max_s": g["seconds"].max().reindex(order).to_numpy(),
        "import_s": g["import_s"].first().reindex(order).to_numpy(),
        "slow": g["slow"].sum().reindex(order).astype(int).to_numpy(),
    })
    total = (f"{int(df['clear'].sum())} of {len(df)} bad inputs give a clear error (exit code 2, one `error:` "
             f"line, no traceback, naming the file, key, value or option); the time to the error is flagged slow "
             f"above {side.get('extra', {}).get('slow_factor', 3)}x the command's import time.")
    unclear = df[~df["clear"].astype(bool)]
    lines = [table(out, [("command", "command"), ("cases", "bad inputs"), ("clear", "clear errors"),
                         ("option", "option named as typed"), ("left", "left files behind"),
                         ("median_s", "median time to error (s)", "{:.2f}"), ("max_s", "max (s)", "{:.2f}"),
                         ("import_s", "import time (s)", "{:.2f}"), ("slow", "slow (> 3x import)")]), "", total]
    if len(unclear):
        lines += ["", "Not clear:", ""] + [f"- `toolkit {r.command}`, {r.case}: {r.not_clear_because} "
                                           f"(`{_number(r.error)}`)" for r in unclear.itertuples()]
    return "\n".join(lines)


def _interrupts(data):
    df = data["bad_inputs_interrupts"][0]
    unit = df["command"].map(lambda c: "simulations" if c.endswith("database") else "epochs")
    out = df.assign(command=[f"`toolkit {c}`" for c in df["command"]], unit=unit,
                    before=[f"{b} of {f}" for b, f in zip(df["done_before"], df["full"])],
                    after=[f"{a} of {f}" for a, f in zip(df["done_after_rerun"], df["full"])],
                    rerun=["same command + `--resume`" if "--resume" in r.split() else "same command"
                           for r in df["rerun"]])
    text = table(out, [("command", "command"), ("unit", "work"), ("full_run_s", "uninterrupted run (s)"),
                       ("interrupt_s", "Ctrl-C at (s)"), ("interrupted", "stopped by it"),
                       ("exit_code", "exit code"), ("traceback", "traceback"),
                       ("before", "finished at the interrupt"),
                       ("after", "finished after the rerun"), ("nothing_lost", "nothing lost"),
                       ("rerun_completes", "rerun completes"), ("rerun", "rerun")])
    said = df[df["interrupted"].astype(bool)].drop_duplicates("command")
    lines = [text, "", "The interrupted command's own last line (at its earliest interrupt):", ""]
    lines += [f"- `toolkit {r.command}`: `{_number(r.message)}`" for r in said.itertuples()]
    if "other_output" in df and df["other_output"].notna().any():
        other = df[df["other_output"].notna()]
        lines += ["", "Other output on the way out (warnings, tracebacks):", ""]
        lines += [f"- `toolkit {r.command}`, Ctrl-C at {r.interrupt_s:g} s: `{_number(r.other_output)}`"
                  for r in other.itertuples()]
    return "\n".join(lines)


def _impact_database(data):
    df, side = data["impact_surrogate_yield_quasistatic"]
    x = side.get("extra", {})
    text = table(df, [("velocity", "velocity (mm/s)", "{:g}"), ("held_out", "held out"), ("steps", "load steps"),
                      ("wall_time_s", "time (s)", "{:.1f}"), ("max_displacement_mm", "max displacement (mm)", "{:.2f}"),
                      ("max_von_mises_mpa", "max von Mises (MPa)", "{:.4f}")])
    failed = x.get("failed", [])
    lines = [text, "", f"{len(df)} simulations finished and {len(failed)} failed; the build took "
             f"{x.get('database_s', float(df['wall_time_s'].sum())) / 60:.1f} min."]
    lines += [f"- `{f['key']}`: {_number(f['reason'][:300])}" for f in failed]
    return "\n".join(lines)


def _threads(data):
    df = data["threads"][0]
    wide = df.pivot(index="kernel", columns="threads", values="seconds")
    counts = sorted(wide.columns)
    out = pd.DataFrame({"kernel": wide.index})
    for n in counts:
        out[f"t{n}"] = wide[n].to_numpy()
    cols = [("kernel", "kernel")] + [(f"t{n}", f"{n} thread{'s' if n > 1 else ''} (s)", "{:.3g}") for n in counts]
    if len(counts) > 1:
        out["ratio"] = wide[counts[-1]].to_numpy() / wide[counts[0]].to_numpy()
        cols.append(("ratio", f"{counts[-1]} threads / 1", "{:.2f}"))
    return table(out, cols)


def _interrupt_stress(data):
    df, side = data["interrupt_stress"]
    hit = df[~df["ended_before"].astype(bool)]
    x = side.get("extra", {})
    codes = ", ".join(f"{int(c)} ({n} tries)" for c, n in hit["exit_code"].value_counts().sort_index().items())
    return (f"{len(df)} tries, SIGINT between {df['interrupt_s'].min():.2f} and {df['interrupt_s'].max():.2f} s after "
            f"the start ({len(df) - len(hit)} had ended before it): {int(df['hung'].sum())} hung; exit codes "
            f"{codes}; {int((~hit['interrupted_line'].astype(bool)).sum())} without the `interrupted:` line, "
            f"{int(hit['traceback'].astype(bool).sum())} with a traceback; the slowest ended "
            f"{hit['exit_after_s'].max():.2f} s after the signal (median {hit['exit_after_s'].median():.2f} s)."
            if len(hit) else f"{x.get('tries', len(df))} tries, none interrupted before it ended.")


#: (text of the failure, its short name in the table), the first that matches names it
_MESHER_FAILURES = (("needs a closed surface", "refused: not closed"),
                    ("contain self-intersections", "self-intersections"),
                    ("Failed to tetrahedralize", "not manifold"), ("Wrong topology", "wrong topology"),
                    ("HXT 3D mesh failed", "3D meshing failed"), ("points has shape", "repair left no surface"),
                    ("timeout", "timeout"), ("crash", "crash"))


def _mesher_outcome(row) -> str:
    status = str(row["status"])
    if status == "ok":
        return f"ok: {row['wall_s']:.3g} s, min SJ {row['min_sj']:.3f}, off {row['in_to_out_max_mm']:.2f} mm"
    return next((short for key, short in _MESHER_FAILURES if key in status), status.split(":")[0])


def _meshers(data):
    df = data["meshers"][0].copy()
    if "threads" not in df:
        df["threads"] = 1
    clean = df[df["input"] == "clean"]
    damaged = df[df["input"] != "clean"].copy()
    damaged["outcome"] = damaged.apply(_mesher_outcome, axis=1)
    grid = damaged.pivot_table(index=["input", "repair"], columns="mesher", values="outcome", aggfunc="first",
                               sort=False).fillna("").reset_index()
    return "\n\n".join([table(clean, [
        ("mesher", "mesher"), ("size_mm", "size (mm)", "{:g}"), ("threads", "threads"), ("nodes", "nodes"),
        ("tets", "tetrahedra"), ("mean_edge_mm", "mean edge (mm)", "{:.2f}"), ("wall_s", "time (s)"),
        ("cpu_s", "CPU time (s)"), ("min_sj", "min scaled Jacobian", "{:.3f}"),
        ("p01_sj", "1st percentile", "{:.3f}"), ("min_dihedral_deg", "min dihedral (deg)", "{:.1f}"),
        ("max_dihedral_deg", "max dihedral (deg)", "{:.1f}"), ("sliver_share", "slivers (< 10 deg)", "{:.2%}"),
        ("out_to_in_max_mm", "boundary to surface, max (mm)", "{:.2f}"),
        ("in_to_out_max_mm", "surface to boundary, max (mm)", "{:.2f}"),
        ("boundary_closed_manifold", "closed boundary")]),
        "Damaged copies of the paper surface at 3 mm: time, min scaled Jacobian (SJ) and the largest distance of "
        "the undamaged surface to the mesh's boundary (off; the self-intersection moves vertices through the "
        "tissue, so its off is the damage), or why it failed.",
        table(grid, [("input", "damaged input"), ("repair", "repair"),
                     *[(m, m) for m in ("ftetwild", "wildmeshing", "tetgen", "gmsh") if m in grid]])])


def _off_bone(data):
    parts = []
    for stem in ("off_bone", "off_bone_far"):
        if stem in data:
            parts.append(table(data[stem][0], [
                ("resolution", "resolution"), ("case", "case"), ("max_mucosa_offset_mm", "max_mucosa_offset (mm)"),
                ("material", "material"), ("plans", "plans"), ("completed", "completed"),
                ("median_s", "median time (s)"), ("max_s", "max time (s)"),
                ("min_sj", "min scaled Jacobian", "{:.3f}"), ("wider_band", "wider release band"),
                ("max_drift_mm", "offset drift (mm)", "{:.2g}"), ("offset_median_mm", "offset median (mm)", "{:.2f}"),
                ("offset_max_mm", "offset max (mm)", "{:.2f}"), ("far_mucosa_nodes", "far mucosa nodes")]))
    return "\n\n".join(parts)


def _segmentation_damage(data):
    t = pd.concat([data[k][0] for k in ("segmentation_damage", "segmentation_damage_3mm") if k in data],
                  ignore_index=True)
    counts = [c for c in t.columns if c.startswith("n_") and c.endswith("_ratio")]
    t["worst_count"] = (t[counts] - 1).abs().max(axis=1)
    areas = [c for c in t.columns if c.startswith(("facing_", "carried_")) and c.endswith("_ratio")]
    t["worst_area"] = (t[areas] - 1).abs().max(axis=1)
    t["run"] = t["run"].fillna(1).astype(int) if "run" in t.columns else 1
    # damaged bones labelled on the first clean meshing's tetrahedra, or a meshing of their own
    t["draw"] = t.get("draw", pd.Series("own", index=t.index)).fillna("own").map({"clean": "first clean", "own": "own"})
    return table(t, [
        ("size_mm", "size (mm)", "{:g}"), ("run", "run"), ("damage", "damage"), ("draw", "tetrahedra"),
        ("nodes", "nodes"),
        ("worst_count", "largest set count change", "{:.0%}"),
        ("worst_area", "largest area change", "{:.0%}"), ("carried_lefort_mm2_ratio", "Le Fort I carried", "{:.2f}"),
        ("carried_distal_mm2_ratio", "distal carried", "{:.2f}"), ("diff_mean_mm", "skin difference mean (mm)",
                                                                     "{:.2f}"),
        ("diff_p95_mm", "p95 (mm)", "{:.2f}"), ("same_bones_diff_mean_mm", "same bones: mean (mm)", "{:.2f}"),
        ("same_bones_diff_p95_mm", "p95 (mm)", "{:.2f}"),
        ("bones_alone_diff_mean_mm", "the bones alone: mean (mm)", "{:.2f}"), ("simulate_s", "simulate (s)", "{:.0f}")])


def _meshed_database(data):
    t = pd.concat([data[k][0] for k in ("meshed_database", "meshed_database_ct", "meshed_database_ct_tet10")
                   if k in data], ignore_index=True)
    if "resolution" in t.columns:  # tables written before the CT face was measured name the phantom only
        t["face"] = t["face"].fillna(t.pop("resolution")) if "face" in t.columns else t.pop("resolution")
    t["face"] = t["face"].map(lambda f: "head CT" if f == "ct" else f"{f} phantom's surfaces")
    t["order"] = t["order"].fillna(2).astype(int).map({1: "tet4", 2: "tet10"}) if "order" in t else "tet10"
    # results measured before the mucosa could be freed have no such column
    t["freed_mucosa_nodes"] = t.get("freed_mucosa_nodes", pd.Series(0, index=t.index)).fillna(0)
    g = t.groupby(["face", "size_mm", "order", "nodes", "mode"], sort=False).agg(
        plans=("status", "size"), completed=("status", lambda s: int((s == "ok").sum())),
        failed=("status", lambda s: int((s == "failed").sum())),
        not_run=("status", lambda s: int((s == "not run").sum())),
        median_s=("seconds", "median"), wider_band=("release_width_mm", lambda s: int((s > 10).sum())),
        freed=("freed_cut_nodes", lambda s: int((s > 0).sum())),
        mucosa=("freed_mucosa_nodes", lambda s: int((s > 0).sum())),
        min_sj=("min_scaled_jacobian", "min")).reset_index()
    return table(g, [("face", "face"), ("size_mm", "size (mm)"), ("order", "elements"), ("nodes", "nodes"),
                     ("mode", "mode"),
                     ("plans", "plans"), ("completed", "completed"), ("failed", "failed"), ("not_run", "not run"),
                     ("median_s", "median time (s)", "{:.0f}"),
                     ("wider_band", "wider release band"), ("freed", "freed cut nodes"),
                     ("mucosa", "freed mucosa nodes"), ("min_sj", "min scaled Jacobian", "{:.2g}")])


def _silent_cases(data):
    t = data["silent_cases"][0].copy()
    t["measured"] = [", ".join(f"{k} {row[k]:.3g}" for k in ("chin_mm", "maxilla_nodes", "mandible_nodes")
                               if k in row and pd.notna(row[k])) for _, row in t.iterrows()]
    return table(t, [("case", "case"), ("expect", "expected"), ("exit", "exit"), ("ok", "as expected"),
                     ("measured", "measured"), ("seconds", "time (s)", "{:.1f}")])


def _own_face(data):
    parts = []
    if "own_face" in data:
        df = data["own_face"][0].copy()
        df["lip_muscle"] = df["lip_muscle"].map({"fibres": "transversely isotropic", "none": "none (isotropic)"}).where(
            df["simulate_s"].notna(), "–")
        df["stages"] = df.apply(lambda r: ", ".join(f"{k} {r[k + '_s']:.1f}" for k in
                                                     ("read_repair", "mesh", "mouth", "label", "order", "quality")),
                                axis=1)
        parts.append(table(df, [
            ("size_mm", "size (mm)", "{:g}"), ("order", "order"), ("labels", "labels"),
            ("lip_muscle", "lip muscle"), ("nodes", "nodes"), ("elements", "elements"),
            ("mesh_face_s", "toolkit mesh (s)", "{:.1f}"), ("stages", "stages (s)"),
            ("min_scaled_jacobian", "min scaled Jacobian", "{:.3f}"),
            ("min_dihedral_deg", "min dihedral (deg)", "{:.1f}"),
            ("simulate_s", "simulation (s)", "{:.0f}"), ("phantom_simulate_s", "phantom hex (s)", "{:.1f}"),
            ("phantom_mean_mm", "phantom skin mean |u| (mm)", "{:.2f}"),
            ("diff_mean_mm", "difference mean (mm)", "{:.2f}"), ("diff_p95_mm", "p95 (mm)", "{:.2f}"),
            ("diff_max_mm", "max (mm)", "{:.2f}")]))
        failed = df[df.get("status", pd.Series("ok", index=df.index)).fillna("ok") != "ok"]
        if len(failed):
            parts.append("Simulations that did not complete: " + "; ".join(
                f"{r.size_mm:g} mm, order {r.order}, {r.labels} labels, lip muscle {r.lip_muscle}: "
                f"{str(r.status).split(' (')[0]}"
                for r in failed.itertuples()) + ".")
    if "own_face_labels" in data:
        parts.append("Labels against the phantom's own sets: the share of the meshed face's nodes of each set "
                     "whose nearest phantom node carries it, and the other way round.")
        parts.append(table(data["own_face_labels"][0], [
            ("size_mm", "size (mm)", "{:g}"), ("set", "set"), ("nodes", "nodes"), ("phantom_nodes", "phantom nodes"),
            ("agree_meshed_to_phantom", "meshed -> phantom", "{:.0%}"),
            ("agree_phantom_to_meshed", "phantom -> meshed", "{:.0%}")]))
    if "own_face_robustness" in data:
        df = data["own_face_robustness"][0]
        df = df.assign(ok=df.status == "ok")
        summary = df.groupby(["size_mm", "order", "mode"], sort=False).agg(
            plans=("ok", "size"), completed=("ok", "sum"), median_s=("seconds", "median"),
            max_s=("seconds", "max"), min_sj=("min_scaled_jacobian", "min")).reset_index()
        parts.append("Plans drawn by `sample_plans` (both modes, the physiological ranges) on the meshed face:")
        parts.append(table(summary, [
            ("size_mm", "size (mm)", "{:g}"), ("order", "order"), ("mode", "mode"), ("plans", "plans"),
            ("completed", "completed"), ("median_s", "median time (s)", "{:.0f}"), ("max_s", "max time (s)", "{:.0f}"),
            ("min_sj", "min scaled Jacobian", "{:.3f}")]))
    return "\n\n".join(parts)


def _own_face_impact(data):
    df = data["own_face_impact"][0]
    failed = [f"{r.velocity_mm_s:g} mm/s {face}: {status.split(' (')[0]}" for r in df.itertuples()
              for face, status in (("phantom", r.phantom_status), ("meshed", r.meshed_status)) if status != "ok"]
    note = ("\n\nRuns that did not finish: " + "; ".join(failed) + ".") if failed else ""
    return table(df, [
        ("velocity_mm_s", "velocity (mm/s)", "{:g}"), ("phantom_nodes", "phantom nodes"),
        ("meshed_nodes", "meshed nodes"), ("phantom_s", "phantom (s)", "{:.0f}"), ("meshed_s", "meshed (s)", "{:.0f}"),
        ("phantom_max_skin_displacement_mm", "phantom max skin |u| (mm)", "{:.2f}"),
        ("meshed_max_skin_displacement_mm", "meshed max skin |u| (mm)", "{:.2f}"),
        ("phantom_peak_force_n", "phantom peak force (N)", "{:.2f}"),
        ("meshed_peak_force_n", "meshed peak force (N)", "{:.2f}"),
        ("phantom_yielded_share", "phantom yielded", "{:.1%}"), ("meshed_yielded_share", "meshed yielded", "{:.1%}"),
        ("diff_mean_mm", "skin difference mean (mm)", "{:.2f}"), ("diff_p95_mm", "p95 (mm)", "{:.2f}"),
        ("diff_max_mm", "max (mm)", "{:.2f}")]) + note


def _surrogate_remeshed(data):
    df = data["surrogate_remeshed"][0]
    ok = df[df.status == "ok"]
    summary = ok.groupby(["mesh", "method"], sort=False).agg(
        nodes=("nodes", "first"), plans=("plan", "size"), mean=("mean_error_mm", "mean"),
        p95=("p95_error_mm", "mean"), lips=("lips_mean_error_mm", "mean"),
        displacement=("fe_mean_displacement_mm", "mean"), seconds=("seconds", "median")).reset_index()
    failed = df[(df.status != "ok")]
    parts = [table(summary, [
        ("mesh", "test face"), ("nodes", "nodes"), ("method", "method"), ("plans", "plans"),
        ("mean", "mean error (mm)", "{:.2f}"), ("p95", "p95 error (mm)", "{:.2f}"),
        ("lips", "lips mean error (mm)", "{:.2f}"), ("displacement", "FE mean |u| (mm)", "{:.2f}"),
        ("seconds", "median time per plan (s)", "{:.2f}")])]
    if len(failed):
        parts.append("FE runs that did not complete (their plan is not scored on that face): " + ", ".join(
            f"{r.mesh} plan {r.plan} ({r.status})" for r in failed.itertuples()) + ".")
    return "\n\n".join(parts)


def _surrogate_trust(data):
    df, side = data["surrogate_trust_static"]
    extra = side.get("extra", {})
    d = df[df.scale == "disagreement"].assign(ok=lambda x: x.fe_status == "ok")
    net, base = d[d.answerer == "network"], d[d.answerer == "baseline"]
    kinds = net.groupby("kind", sort=False).agg(
        cases=("case", "size"), fe_ok=("ok", "sum"), error=("error_mm", "median"),
        error_max=("error_mm", "max"), flagged=("ood", "mean"), bound=("bound_90_mm", "median"),
        network_s=("network_s", "median"), baseline_s=("baseline_s", "median"), fe_s=("fe_s", "median")).reset_index()
    b = base.groupby("kind", sort=False).agg(base_error=("error_mm", "median"), base_max=("error_mm", "max"),
                                             base_bound=("bound_90_mm", "median")).reset_index()
    kinds = kinds.merge(b, on="kind", how="left")
    ens = df[df.scale == "ensemble"]
    ensemble_cols = []
    if len(ens):
        kinds = kinds.merge(ens.groupby("kind", sort=False).agg(ens_error=("error_mm", "median"),
                                                                 ens_bound=("bound_90_mm", "median")).reset_index(),
                            on="kind", how="left")
        ensemble_cols = [("ens_error", "ensemble median error (mm)", "{:.2f}"),
                         ("ens_bound", "its median bound (mm)", "{:.2f}")]
    parts = ["Cases by kind (error: 95th percentile over nodes against the FE of the case; bound: the "
             "disagreement estimate at 90 % of that answer's error, the spread's for the ensemble):",
             table(kinds, [("kind", "cases"), ("cases", "plans"), ("fe_ok", "FE completed"),
                           ("error", "PointNet++ median error (mm)", "{:.2f}"), ("error_max", "max (mm)", "{:.2f}"),
                           ("bound", "median bound (mm)", "{:.2f}"),
                           ("base_error", "baseline median error (mm)", "{:.2f}"), ("base_max", "max (mm)", "{:.2f}"),
                           ("base_bound", "median bound (mm)", "{:.2f}"), *ensemble_cols,
                           ("flagged", "flagged out of distribution", "{:.0%}"),
                           ("network_s", "network (s)", "{:.2f}"), ("baseline_s", "baseline (s)", "{:.3f}"),
                           ("fe_s", "FE (s)", "{:.2f}")])]
    cal = dict(extra.get("calibration", {}))
    ensemble = cal.pop("ensemble", None)
    if cal:
        parts.append("Calibration: " + "; ".join(
            f"{k} on {v['plans']} held-out plans, factor {v['factor_90_network']:.3g} (PointNet++) and "
            f"{v['factor_90_baseline']:.3g} (baseline) at 90 %" for k, v in cal.items())
            + (f"; the deep ensemble of {ensemble['members']} PointNet++ (the default model and more trained with "
               f"other seeds on its split), its spread on the same plans, factor {ensemble['factor_90']:.3g}"
               if ensemble else "") + "."
            + (" Without a tolerance the defaults (`auto`) keep the {scale} scale and the {answerer}'s answers; "
               "with one, the pair marked `default` below.".format(**extra["auto"])
               if extra.get("auto") else ""))
    if extra.get("warm_start"):
        parts.append("Warm start: the FE of the {cases} Neo-Hookean cases started from the baseline's answer "
                     "(`simulate(initial_guess=)`) took {warm_s:.1f} s and {warm_newton:.0f} Newton iterations on "
                     "average, against {cold_s:.1f} s and {cold_newton:.0f} from each increment's previous "
                     "equilibrium; the two answers agree to {max_diff_mm:.1g} mm."
                     .format(**extra["warm_start"]))
    if extra.get("methods"):
        parts.append("Estimates (coverage: share of cases whose error is within the bound; AUROC: flagging errors "
                     "above 0.5, 1, 2 and 4 mm where both classes occur):")
        parts.append(table(pd.DataFrame(extra["methods"]), [
            ("scale", "scale"), ("answerer", "answer of"), ("coverage_90_in", "coverage 90 %, in", "{:.0%}"),
            ("coverage_90_out", "90 %, out", "{:.0%}"), ("coverage_95_in", "95 %, in", "{:.0%}"),
            ("coverage_95_out", "95 %, out", "{:.0%}"), ("width_90_in_mm", "mean bound 90 %, in (mm)", "{:.2f}"),
            ("auroc_0.5mm", "AUROC 0.5 mm", "{:.2f}"), ("auroc_1mm", "1 mm", "{:.2f}"),
            ("auroc_2mm", "2 mm", "{:.2f}"), ("auroc_4mm", "4 mm", "{:.2f}"),
            ("estimate_s", "estimate (s)", "{:.3f}")]))
    if extra.get("policies"):
        parts.append("`predict --tolerance` over every case (the FE answers out-of-distribution inputs and "
                     "estimates above the tolerance; its answer is the reference):")
        policies = pd.DataFrame(extra["policies"])
        if "default" in policies:
            policies["default"] = ["default" if d is True else "" for d in policies["default"]]
        parts.append(table(policies, [
            ("tolerance_mm", "tolerance (mm)", "{:g}"), ("scale", "scale"), ("answerer", "answer of"),
            ("coverage", "coverage", "{:.0%}"), *([("default", "chosen")] if "default" in policies else []),
            ("cases", "cases"),
            ("answered_by_surrogate", "answered without the FE", "{:.0%}"),
            ("in_distribution_answered_by_surrogate", "in-distribution answered without it", "{:.0%}"),
            ("delivered_within_tolerance", "answers within tolerance", "{:.0%}"),
            ("mean_answer_s", "mean time per answer (s)", "{:.2f}"), ("mean_fe_s", "mean FE (s)", "{:.2f}"),
            ("speedup_vs_fe", "speed-up vs FE", "{:.2f}"),
            ("in_distribution_speedup_vs_fe", "speed-up, in-distribution", "{:.1f}")]))
    parts.append("![Estimated bound against true error](figures/surrogate_trust_static.png)")
    return "\n\n".join(parts)


def _surrogate_trust_impact(data):
    parts = []
    for stem in ("surrogate_trust_impact", "surrogate_trust_impact_paper"):
        if stem in data:
            parts.append(_surrogate_trust_impact_one(data[stem]))
        else:
            parts.append(f"{'Paper' if stem.endswith('paper') else 'Coarse'} face: {not_measured(SOURCES[stem])}")
    return "\n\n".join(parts)


def _surrogate_trust_impact_one(result):
    df, side = result
    extra = side.get("extra", {})
    d = df[df.scale == "interpolation"].assign(ok=lambda x: x.fe_status == "ok")
    kinds = d.groupby("kind", sort=False).agg(
        cases=("velocity_mm_s", "size"), lo=("velocity_mm_s", "min"), hi=("velocity_mm_s", "max"),
        fe_ok=("ok", "sum"), error=("error_mm", "median"), error_max=("error_mm", "max"),
        interpolation=("interpolation_error_mm", "median"), flagged=("ood", "mean"),
        bound=("bound_90_mm", "median"), network_s=("surrogate_s", "median"), fe_s=("fe_s", "median")).reset_index()
    kinds["velocities"] = [f"{a:.0f}-{b:.0f}" for a, b in zip(kinds.lo, kinds.hi)]
    face = "Paper" if extra.get("resolution") == "paper" else "Coarse"
    parts = [f"{face} face (tet10, deformable ball, quasi-static, {extra.get('duration_s')} s), the strong LSTM "
             f"trained {extra.get('train_seconds') or 0:.0f} s on the six training velocities. Cases by kind (error: "
             "95th percentile over nodes and frames against the FE of the case; interpolation: the training "
             "simulations interpolated in velocity, alone; bound: the interpolation estimate at 90 %):",
             table(kinds, [("kind", "cases"), ("velocities", "velocities (mm/s)"), ("cases", "runs"),
                           ("fe_ok", "FE completed"), ("error", "LSTM median error (mm)", "{:.3f}"),
                           ("error_max", "LSTM max error (mm)", "{:.3f}"),
                           ("interpolation", "interpolation median error (mm)", "{:.3f}"),
                           ("bound", "median bound (mm)", "{:.3f}"),
                           ("flagged", "flagged out of distribution", "{:.0%}"),
                           ("network_s", "LSTM (s)", "{:.3f}"), ("fe_s", "FE (s)", "{:.2f}")])]
    failed = df[(df.scale == "interpolation") & (df.fe_status != "ok")]
    if len(failed):
        parts.append("FE runs that did not complete (no reference; the fallback fails the same way): " + ", ".join(
            f"{r.kind} {r.velocity_mm_s:g} mm/s ({str(r.fe_status).split(':')[0]})" for r in failed.itertuples())
            + ".")
    cal = extra.get("calibration", {})
    if cal:
        parts.append("Calibration: " + "; ".join(f"{k} on {v['velocities']} velocities, factor {v['factor_90']:.3g} "
                                                 "at 90 %" for k, v in cal.items()) + ".")
    if extra.get("methods"):
        parts.append("Estimates (coverage: share of cases whose error is within the bound; AUROC where both "
                     "classes occur):")
        parts.append(table(pd.DataFrame(extra["methods"]), [
            ("scale", "scale"), ("coverage_90_in", "coverage 90 %, in", "{:.0%}"),
            ("coverage_90_out", "90 %, out", "{:.0%}"), ("coverage_95_in", "95 %, in", "{:.0%}"),
            ("coverage_95_out", "95 %, out", "{:.0%}"), ("width_90_in_mm", "mean bound 90 %, in (mm)", "{:.3f}"),
            ("auroc_0.5mm", "AUROC 0.5 mm", "{:.2f}"), ("auroc_1mm", "1 mm", "{:.2f}"),
            ("estimate_s", "estimate (s)", "{:.4f}")]))
    if extra.get("warm_start"):
        parts.append("Warm start: the quasi-static FE of the {cases} out-of-distribution cases started from the "
                     "LSTM's prediction (`simulate(initial_guess=)`) took {warm_s:.2f} s and {warm_newton:.0f} Newton "
                     "iterations on average, against {cold_s:.2f} s and {cold_newton:.0f} from each load step's "
                     "previous increment, run back to back; Newton failed from the prediction in {guess_failures} "
                     "load steps (which then started from the previous increment); the two answers agree to "
                     "{max_diff_mm:.2g} mm.".format(**extra["warm_start"]))
    if extra.get("policies"):
        parts.append("`impact predict --tolerance` over the cases whose FE completed (the FE answers "
                     "out-of-distribution inputs and estimates above the tolerance; its answer is the reference):")
        parts.append(table(pd.DataFrame(extra["policies"]), [
            ("tolerance_mm", "tolerance (mm)", "{:g}"), ("scale", "scale"), ("coverage", "coverage", "{:.0%}"),
            ("cases", "cases"),
            ("answered_by_surrogate", "answered by the surrogate", "{:.0%}"),
            ("in_distribution_answered_by_surrogate", "in-distribution answered by it", "{:.0%}"),
            ("delivered_within_tolerance", "answers within tolerance", "{:.0%}"),
            ("mean_answer_s", "mean time per answer (s)", "{:.2f}"), ("mean_fe_s", "mean FE (s)", "{:.2f}"),
            ("speedup_vs_fe", "speed-up vs FE", "{:.2f}"),
            ("in_distribution_speedup_vs_fe", "speed-up, in-distribution", "{:.1f}")]))
    parts.append(f"![Estimated bound against true error, {face.lower()} face]"
                 f"(figures/{Path(side.get('name', 'surrogate_trust_impact')).name}.png)")
    return "\n\n".join(parts)


#: tolerances (mm) of the generated table of the fidelity chosen per tolerance
FIDELITY_TOLERANCES = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


def _fidelity_table(workflow: str, data: dict, cases: list[tuple[str, bool]]) -> str:
    """The option :func:`toolkit.common.fidelity.choose_fidelity` picks at each tolerance, from
    the results in ``data`` (the same code the command line runs on the packaged copy)."""
    from toolkit.common.fidelity import FidelityError, choose_fidelity, ladder_from_tables

    rows = []
    for label, own_mesh in cases:
        ladder = ladder_from_tables(workflow, data, own_mesh=own_mesh)
        for tol in FIDELITY_TOLERANCES:
            try:
                c = choose_fidelity(workflow, tol, ladder=ladder)
            except FidelityError:
                rows.append({"case": label, "tolerance": tol,
                             "choice": f"refused: below the reference's own {ladder.uncertainty_mm:.3g} mm"})
                continue
            rows.append({"case": label, "tolerance": tol,
                         "choice": ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}"
                                             for k, v in c.options.items()),
                         "error": c.error_mm, "time": c.wall_time_s})
    return table(pd.DataFrame(rows), [("case", "run on"), ("tolerance", "tolerance (mm)", "{:g}"),
                                      ("choice", "chosen"), ("error", "measured error (mm)", "{:.3f}"),
                                      ("time", "ladder time (s)", "{:.2f}")])


def _static_fidelity(data):
    return _fidelity_table("static", data, [("phantom (`--resolution` chosen)", False),
                                            ("own mesh (`--mesh`)", True)])


def _impact_fidelity(data):
    return _fidelity_table("impact", data, [("phantom, or a tet10 `--mesh`", False)])


def _source(stem: str) -> Source:
    return SOURCES[stem]


SOURCES = {s.stem: s for s in (
    Source("static_convergence_runs", "python benchmarks/static_convergence.py", 2),
    Source("static_convergence", "python benchmarks/static_convergence.py", 2),
    Source("static_surrogate", "python benchmarks/static_surrogate.py --plans 100 --subjects 4 --subject-plans 25 "
           "--max-minutes 7", 70),
    Source("static_surrogate_coarse", "python benchmarks/static_surrogate.py --resolution coarse --plans 30 "
           "--subjects 1 --max-minutes 1 --variants explicit implicit hard+prior --suffix _coarse", 5),
    Source("impact_ladder", "python benchmarks/impact_ladder.py --resolutions paper --orders 2 --balls deformable "
           "--mass-scaling 1 --integrators quasi-static --tolerances 3e-3", 1),
    Source("impact_ladder_velocities", "python benchmarks/impact_ladder.py --resolutions coarse --orders 2 "
           "--balls deformable --integrators quasi-static --velocities 20 30 50 --mass-scaling 1 "
           "--out benchmarks/results/impact_ladder_velocities.csv", 2),
    Source("impact_ladder_yielding", "python benchmarks/impact_ladder.py --scene yielding --resolutions coarse "
           "--orders 2 --balls deformable --mass-scaling 1 --integrators quasi-static explicit --velocities 20 23 26 "
           "32 35 38 44 47 50 --out benchmarks/results/impact_ladder_yielding.csv", 60),
    Source("impact_surrogate", "python benchmarks/impact_surrogate.py --max-minutes 6 --strong-minutes 14", 130),
    Source("impact_surrogate_coarse", "python benchmarks/impact_surrogate.py --resolution coarse --order 1 "
           "--ball rigid --mass-scaling 100 --max-minutes 1 --suffix _coarse", 8),
    Source("phantoms", "python benchmarks/phantoms.py", 2),
    Source("bad_inputs", "python benchmarks/bad_inputs.py", 4),
    Source("bad_inputs_interrupts", "python benchmarks/bad_inputs.py --interrupts", 5),
    Source("interrupt_stress", "python benchmarks/interrupt_stress.py", 8),
    Source("threads", "python benchmarks/threads.py", 1),
    Source("impact_surrogate_yield_quasistatic", "python benchmarks/impact_surrogate.py --integrator quasi-static "
           "--stages database --suffix _quasistatic", 10),
    Source("mixed_elements", "python benchmarks/mixed_elements.py", 1),
    Source("static_meshed_speed_ct", "python benchmarks/static_meshed_speed.py --face ct --code /tmp/before . "
           "--repeats 1 --out benchmarks/results/static_meshed_speed_ct.csv", 50),
    Source("regulation_speed", "python benchmarks/static_meshed_speed.py --code /tmp/before . --repeats 1 "
           "--out benchmarks/results/regulation_speed.csv", 6),
    Source("regulation_speed_ct", "python benchmarks/static_meshed_speed.py --face ct --code /tmp/before . "
           "--repeats 1 --out benchmarks/results/regulation_speed_ct.csv", 15),
    Source("slow_modes", "python benchmarks/slow_modes.py", 10),
    Source("predict_speed", "python benchmarks/predict_speed.py", 5),
    Source("static_meshed_speed", "python benchmarks/static_meshed_speed.py --code /tmp/before . --repeats 2", 12),
    Source("static_solvers", "python benchmarks/static_solvers.py --meshes coarse paper paper-tet4 bulk-tet4 "
           "meshed-5mm meshed-3mm --methods superlu pardiso amg amg-sa auto", 10),
    Source("mesh_convergence", "python benchmarks/mesh_convergence.py", 25),
    Source("peers", "python benchmarks/peers.py", 40),
    Source("profiles", "python benchmarks/profiles.py", 5),
    Source("static_ladder", "python benchmarks/static_ladder.py --resolutions coarse paper --increments 1 3 10", 5),
    Source("meshers", "python benchmarks/meshers.py", 25),
    Source("off_bone", "python benchmarks/off_bone.py --plans 5", 8),
    Source("off_bone_far", "python benchmarks/off_bone.py --resolution coarse --median 5 --p90 15 --max-offset 20 "
           "--modes full --plans 8 --materials linear --thresholds inf 10 5 3 "
           "--out benchmarks/results/off_bone_far.csv", 1),
    Source("own_face", "python benchmarks/own_face.py --sizes 7 5 3.5 --orders 1 2 --simulate-sizes 7 5 "
           "--labels rules phantom", 25),
    Source("own_face_labels", "python benchmarks/own_face.py --sizes 7 5 3.5 --orders 1 2 --simulate-sizes 7 5 "
           "--labels rules phantom", 25),
    Source("own_face_robustness", "python benchmarks/own_face.py --sizes 7 --plans 25 --no-simulate", 55),
    Source("surrogate_remeshed", "python benchmarks/surrogate_remeshed.py", 40),
    Source("segmentation_damage", "python benchmarks/segmentation_damage.py --size 5 --repeats 2", 9),
    Source("segmentation_damage_3mm", "python benchmarks/segmentation_damage.py --size 3 --kinds off_bone all "
           "--repeats 2 --out benchmarks/results/segmentation_damage_3mm.csv", 25),
    Source("meshed_database", "python benchmarks/meshed_database.py --size 3 --plans 4", 30),
    Source("meshed_database_ct", "python benchmarks/meshed_database.py --ct --size 3 --order 1 --plans 10 "
           "--out benchmarks/results/meshed_database_ct.csv", 40),
    Source("meshed_database_ct_tet10", "python benchmarks/meshed_database.py --ct --size 3 --order 2 --plans 1 "
           "--modes sagittal full --out benchmarks/results/meshed_database_ct_tet10.csv", 90),
    Source("silent_cases", "python benchmarks/silent_cases.py", 2),
    Source("own_face_impact", "python benchmarks/own_face_impact.py", 20),
    Source("surrogate_trust_static", "python benchmarks/surrogate_trust.py --cases 40", 15),
    Source("surrogate_trust_impact", "python benchmarks/surrogate_trust.py --workflow impact --cases 40", 16),
    Source("surrogate_trust_impact_paper", "python benchmarks/surrogate_trust.py --workflow impact --resolution paper "
           "--cases 20 --out benchmarks/results/surrogate_trust_impact_paper.csv", 60),
    Source("static_robustness", "python benchmarks/static_robustness.py --resolutions coarse paper --materials "
           "linear --slidings mucosa+lip --modes full --plans 20", 2),
)}

BLOCKS = {b.name: b for b in (
    Block("headline", "Headline: this toolkit beside the source papers",
          "Per workflow, the FE time of one simulation and the surrogate's accuracy and speed, measured here, "
          "beside the figures the source papers report (their machines, meshes and data differ: a GPU for the "
          "PointNet++ paper, Abaqus on ~30,000 C3D10 elements for the impact paper). The surrogate rows say the "
          "size they were measured at.",
          tuple(SOURCES[s] for s in ("static_convergence_runs", "static_surrogate", "static_surrogate_coarse",
                                     "impact_ladder", "impact_surrogate", "impact_surrogate_coarse")), _headline),
    Block("phantoms", "Phantoms", "Time and peak traced memory to build each procedural phantom at each resolution, "
          "with its node and element counts and element quality (scaled Jacobian).", (SOURCES["phantoms"],),
          _phantoms),
    Block("mixed_elements", "Element types against a closed form",
          "Max nodal error relative to max |u| for Lame's pressurised-cavity field prescribed on the boundary of a "
          "box of hex8, wedge6 or tet4 cells and of the mixed bar, at three cell sizes, and the log-log slope "
          "(2: the O(h^2) of linear elements; about 0: volumetric locking).", (SOURCES["mixed_elements"],), _mixed),
    Block("static_convergence", "Static FE under mesh refinement",
          "The packaged default plan (3 increments, linear, mucosa + lip sliding) on the coarse, paper and fine "
          "faces: the time of each simulation (one thread), then the differences of the skin displacement "
          "between resolutions at common skin points.",
          (SOURCES["static_convergence_runs"], SOURCES["static_convergence"]), _convergence),
    Block("static_solvers", "Linear solvers on the static system",
          "Time and peak memory of one solve of the first increment's constrained system with each solver, the "
          "automatic choice, and the next lip-contact solve that reuses the factorization.",
          (SOURCES["static_solvers"],), _solvers),
    Block("static_meshed_speed", "Time per plan on a meshed face",
          "The default plan (linear, mucosa and lip sliding, 3 increments) on the paper phantom's surfaces, and the "
          "5 mm mandibular advance on the head CT's, meshed by `toolkit mesh` at its default 3 mm (tet10), run by "
          "two checkouts of the toolkit in turn, each run a "
          "fresh single-threaded process, so that each pair shares the machine's load of the same minutes: commit "
          "92b24f7, whose linear steps precondition every system of a step with a stored AMG hierarchy and start "
          "each increment from zero, and the current code, which builds a hierarchy for each reduction and starts "
          "each increment's first solve from the step before it. The difference is the largest nodal difference "
          "to the first code's answer of the same run.",
          (SOURCES["static_meshed_speed"], SOURCES["static_meshed_speed_ct"]), _meshed_speed),
    Block("regulation_speed", "Time per plan with the quadratic untangling",
          "The default plan (linear, mucosa and lip sliding, 3 increments) on the paper phantom's surfaces, and the "
          "5 mm mandibular advance on the head CT's, meshed by `toolkit mesh` at its default 3 mm (tet10), run by "
          "two checkouts of the toolkit in turn, each run a fresh single-threaded process: commit 201dd26, whose "
          "mesh regulation untangles a tet10 by its corner tetrahedron only, and the current code, which then "
          "untangles a still folded tet10 on its quadratic Jacobian. The difference is the largest nodal "
          "difference to the first code's answer of the same run.",
          (SOURCES["regulation_speed"], SOURCES["regulation_speed_ct"]),
          lambda data: _meshed_speed(data, ("regulation_speed", "regulation_speed_ct"))),
    Block("predict_speed", "`static predict` beside `static simulate`, end to end",
          "The default plan on a phantom, each command a fresh process of one thread from start to exit, the "
          "two commands and the two imports in turn; the surrogate is the default network (its inference time "
          "does not depend on its training). `in the process's work` is the time the summary reports: the "
          "increments for the FE, the prediction with its influence matrix for the surrogate.",
          (SOURCES["predict_speed"],), _predict_speed),
    Block("slow_modes", "The slowest modes of a face's static system",
          "The first reduced system of the default plan (on the head CT, the 5 mm advance) on faces meshed at "
          "3 mm (tet10): the CG iterations of the solver's AMG hierarchy to 1e-9, and the smallest eigenpairs "
          "(LOBPCG): each mode's eigenvalue over the mean diagonal, the nodes holding 95 % of its energy, where "
          "they are, how many slide on a bone or lie on the skin, the elements among them and joining them to "
          "the rest, and the coherence of their motion (1: a rigid translation).",
          (SOURCES["slow_modes"],), _slow_modes),
    Block("peers", "Peer FE codes",
          "The same linear-elastic Dirichlet problem solved by the toolkit and by scikit-fem, NGSolve and SfePy: "
          "the same face mesh from `toolkit mesh` (tet10, straight edges; the paper phantom's surfaces at 7 and "
          "3.5 mm, the head CT's at 3 mm), the same homogeneous material (E 0.003 MPa, nu 0.47), the same "
          "conditions (fixed nodes held, bone nodes carried by the first of 3 increments of a plan, every other "
          "node free) and the same 4-point quadrature, so every code solves one discrete system. Each run is a "
          "fresh single-threaded process: CPU seconds to assemble the reduced system, to factorize or set up "
          "the preconditioner, and to solve it (iterative methods to a relative residual of 1e-9), its peak "
          "resident memory, and the relative difference of its nodal displacements to the toolkit's. The "
          "`neo-hookean` rows are one load step of the toolkit's compressible Neo-Hookean solid beside NGSolve's "
          "Newton on the same energy density (the whole solve, assembly included, under solve). SciPy's SuperLU "
          "is not run above 200,000 free dofs. The second table is each size's toolkit total over the fastest "
          "peer's. `pip install .[peers]` installs NGSolve and SfePy.",
          (SOURCES["peers"],), _peers),
    Block("static_ladder", "Static speed/accuracy ladder",
          "The packaged plan at half scale for every material x increments x sliding model, each in a fresh "
          "process; differences are to the highest-fidelity run of the same resolution (Neo-Hookean, 10 "
          "increments, mucosa + lip sliding).", (SOURCES["static_ladder"],), _ladder),
    Block("static_fidelity", "Static fidelity chosen by a tolerance",
          "`toolkit static simulate --tolerance MM` (`toolkit.common.fidelity.choose_fidelity`): the fastest option "
          "of the static ladder whose error is within the tolerance. On the phantom the error is the ladder's mean "
          "skin difference to the most faithful model of the same resolution plus that resolution's mean skin "
          "difference to the fine face (a bound, by the triangle inequality); on a user's mesh, the paper "
          "phantom's ladder difference alone. Tolerances below the paper face's own difference to the fine one "
          "are refused.", (SOURCES["static_ladder"], SOURCES["static_convergence"]), _static_fidelity),
    Block("static_robustness", "Static robustness over the plan space",
          "Plans drawn from the lip-sliding paper's ranges (both segments moved): how many complete, how long they "
          "take, the worst element quality, and how many needed a wider release band or freed cut nodes.",
          (SOURCES["static_robustness"],), _robustness),
    Block("static_surrogate", "Static surrogate",
          "PointNet++ variants and the baselines on the same held-out test plans: mean nodal Euclidean error per "
          "sample (mm), time per prediction at batch 1 on the CPU, and the FE time of the same increments.",
          (SOURCES["static_surrogate"], SOURCES["static_surrogate_coarse"]), _surrogate_static),
    Block("impact_ladder", "Impact speed/accuracy ladder",
          "The impact paper's scene (ball at 30 mm/s for 1.8 s) at each fidelity, each run in a fresh process; "
          "accuracy is the skin displacement series against the highest-fidelity explicit run of the same "
          "resolution (RMSE, Pearson; mirrored: after reflecting across the midsagittal plane, for a run that "
          "slid to the other side).", (SOURCES["impact_ladder"],), _impact_ladder),
    Block("impact_fidelity", "Impact fidelity chosen by a tolerance",
          "`toolkit impact simulate --tolerance MM` (`toolkit.common.fidelity.choose_fidelity`): the fastest option "
          "of the impact ladder (coarse face, 30 mm/s) whose displacement RMSE to the explicit reference is within "
          "the tolerance. Tolerances below the reference's own left-right asymmetry are refused.",
          (SOURCES["impact_ladder"],), _impact_fidelity),
    Block("impact_quasi_static", "Quasi-static impact path",
          "The quasi-static (Newton) runs of the impact ladder: load steps, Newton iterations, step cuts, "
          "time and memory, and the agreement with the explicit reference where one was run.",
          (SOURCES["impact_ladder"],), _quasi_static),
    Block("impact_yielding", "Quasi-static against explicit in the learning database's scene",
          "The skull-held yielding scene (0.36 s, 36 frames) on the coarse face (tet10, deformable ball) at the "
          "database's velocities, quasi-static against the unscaled explicit run at the same velocity: "
          "skin displacement and von Mises series, RMSE as a share of the explicit run's peak. A velocity without an "
          "explicit row was not run explicitly; a run that failed the answer checks is listed with the check.",
          (SOURCES["impact_ladder_yielding"],), _yielding),
    Block("impact_velocities", "Impact across the impact paper's velocities",
          "The quasi-static path at 20, 30 and 50 mm/s (the impact paper's range) on the coarse face: load steps, "
          "Newton iterations, time and memory, and the peak displacement and stress.",
          (SOURCES["impact_ladder_velocities"],), _velocities),
    Block("impact_surrogate", "Impact surrogate",
          "The impact paper's LSTM (`paper`), the stronger LSTM (`strong`) and the non-recurrent baseline on the "
          "random split and on held-out velocities: RMSE and Pearson correlation of displacement and von Mises "
          "stress, training time and inference per face frame.",
          (SOURCES["impact_surrogate"], SOURCES["impact_surrogate_coarse"]), _surrogate_impact),
    Block("meshers", "Tetrahedral meshers",
          "Each mesher of `toolkit.mesh.backends` on the closed tissue surface of the paper phantom (4 and 3 mm "
          "mean edge) and of the fine phantom (2 mm), one thread, in a fresh process per case, then on copies of "
          "the paper surface damaged as segmentation exports hold them, each without repair and after the "
          "toolkit's, trimesh's or MeshFix's repair: time, counts, element quality, the distance between the "
          "mesh's boundary and the undamaged surface both ways, and whether the boundary is closed.",
          (SOURCES["meshers"],), _meshers),
    Block("own_face", "A meshed face against the phantom",
          "`toolkit mesh` on the paper phantom's own surfaces (fTetWild, tet10, one thread): the stage times and "
          "element quality at each size, and the packaged plan (linear, mucosa and lip sliding, 3 increments) on "
          "the meshed face against the phantom's hexahedral run: its time, and the skin displacement differences "
          "at the phantom's skin nodes.",
          (SOURCES["own_face"], SOURCES["own_face_labels"], SOURCES["own_face_robustness"]), _own_face),
    Block("own_face_impact", "The impact on a meshed face against the phantom",
          "The ball impact (deformable ball, quasi-static path) on the paper phantom's surfaces meshed by "
          "`toolkit mesh` (tet10, 7 mm, held by the tissue on its bones) and on the skull-held phantom (tet10), "
          "same aim, at each velocity: the largest skin displacement, the peak contact force, the yielded share "
          "of the volume at the end, and the skin displacement at the last frame at the phantom's skin nodes.",
          (SOURCES["own_face_impact"],), _own_face_impact),
    Block("surrogate_remeshed", "A surrogate on a face it has never seen",
          "PointNet++ (hard boundary values over the linear prior) trained on four paper phantom subjects, "
          "predicting sampled plans on an unseen subject as its hexahedral phantom and as its surfaces meshed by "
          "`toolkit mesh` (tet10, 7 mm), against the FE of the same mesh, beside the influence matrix of that mesh "
          "alone: errors of the post-operative displacement per plan, averaged over the plans.",
          (SOURCES["surrogate_remeshed"],), _surrogate_remeshed),
    Block("surrogate_trust", "Static answers within a tolerance",
          "The default PointNet++ trained on four paper phantom subjects (25 sagittal plans each), its error "
          "estimate calibrated on its 20 test plans, then run on new cases: in-range plans on the training "
          "subjects, plans with translations 1.2-2 times the physiological range, an unseen subject beyond the "
          "training shapes, and Neo-Hookean FE for the linear-trained model.",
          (SOURCES["surrogate_trust_static"],), _surrogate_trust),
    Block("surrogate_trust_impact", "Impact answers within a tolerance",
          "The strong LSTM trained on the impact paper's six velocities (20-50 mm/s, held-out-velocity split), its "
          "error estimate calibrated on 20 other velocities of the same scene, then run on new cases: velocities "
          "drawn over 20-50 mm/s, slower (10-15) and faster (55-70) balls, and the ball aimed 20 mm lower.",
          (SOURCES["surrogate_trust_impact"], SOURCES["surrogate_trust_impact_paper"]), _surrogate_trust_impact),
    Block("off_bone", "Mucosa off the bone",
          "The paper phantom with its bone surfaces moved away from the tissue (`toolkit.common.phantoms.off_bone`, "
          "mucosa 2.3 mm median and 4.3 mm at most off its bone): a 5 mm mandibular advance and plans drawn by "
          "`sample_plans` in both modes, 3 increments, mucosa and lip sliding. The offset drift is the largest "
          "change of a sliding mucosa node's distance to its moved bone over the increments. Then, on the coarse "
          "phantom with the mucosa farther off (4.8 mm median, 8.4 mm at most), each `max_mucosa_offset`.",
          (SOURCES["off_bone"], SOURCES["off_bone_far"]), _off_bone),
    Block("segmentation_damage", "Labels under segmentation damage",
          "The paper phantom's surfaces damaged one kind at a time (`toolkit.mesh.damage`), meshed at 5 mm (tet10) "
          "and labelled by `toolkit mesh`, against the clean surfaces meshed twice (the mesher's own spread), in "
          "two runs (fTetWild meshes every face anew): the largest change of a node set's count and of a "
          "segment's tissue area (lying on its bone, or carried), and the round trip: the default plan's skin "
          "displacement against the phantom's own hexahedral run, against that run on the same damaged bones, "
          "and what the damaged bones alone change in the phantom's run (bones standing off the tissue, or with "
          "holes, change the anatomy the sliding follows).",
          (SOURCES["segmentation_damage"], SOURCES["segmentation_damage_3mm"]), _segmentation_damage),
    Block("meshed_database", "Learning databases on a meshed face",
          "`toolkit static database --mesh` on faces meshed by `toolkit mesh` (the paper phantom's surfaces, and "
          "the head CT's from `toolkit ct`): sampled plans of each mode, with the simulation's retries (wider "
          "release band, freed cut nodes) stored per plan.",
          (SOURCES["meshed_database"], SOURCES["meshed_database_ct"], SOURCES["meshed_database_ct_tet10"]),
          _meshed_database),
    Block("silent_cases", "Inputs that once gave a wrong answer",
          "Each run as a user would on the paper phantom's surfaces meshed at 7 mm: labelling rules under which the "
          "distal mandible carries almost nothing, a mesh whose mandible set holds one node under a 5 mm advance, "
          "surfaces in LPS axes (undeclared, then declared), a rotation about a pivot 10 m away, and the 5 mm "
          "advance itself (the chin's forward displacement, mm).", (SOURCES["silent_cases"],), _silent_cases),
    Block("bad_inputs", "Bad input on the command line",
          "A catalogue of mistakes per command (bad output locations, missing, garbage, empty, binary and metres "
          "meshes, bad plans and scenes, bad option values, a database or model of the other workflow or of "
          "another configuration), each run as `python -m toolkit ...` on the coarse sizes in a fresh folder: "
          "how many give a clear error, whether the error names the option as typed, whether the failed command "
          "left files behind, and the wall time to the error against the command's import time.",
          (SOURCES["bad_inputs"],), _bad_inputs),
    Block("mesh_convergence", "Meshed-face size",
          "The paper phantom's surfaces meshed by `toolkit mesh` (tet10) at each size and the default plan on each "
          "(linear, mucosa and lip sliding, 3 increments, one thread, each size in its own process): nodes, times, "
          "peak memory, and the skin displacement at the phantom's skin points against the finest size's and "
          "against the hexahedral phantom's.", (SOURCES["mesh_convergence"],), _mesh_convergence),
    Block("profiles", "Where the time goes",
          "Each simulation path under cProfile (one thread): its six functions of largest own time and their share "
          "of the run. `static-meshed`: the default plan on the paper phantom's surfaces meshed at 5 mm (tet10); "
          "`static-phantom`: the same plan on the paper hexahedral phantom; `impact-quasistatic`: the default impact "
          "scene at paper resolution, 30 mm/s.", (SOURCES["profiles"],), _profiles),
    Block("interrupts", "Ctrl-C in the long commands",
          "Each long command, tiny, run once to its end, then afresh and interrupted (SIGINT to its process "
          "group, as Ctrl-C) at several times, and rerun: the finished simulations or epochs on disk at the "
          "interrupt and after the rerun, whether any was lost, and whether the rerun completes the job.",
          (SOURCES["bad_inputs_interrupts"],), _interrupts),
    Block("impact_database", "The impact learning database, quasi-static",
          "`toolkit impact database`'s defaults: the skull-held yielding scene on the paper face (tet10, deformable "
          "ball, 0.36 s) at the impact paper's six velocities and the held-out 23, 35 and 47 mm/s, on the "
          "quasi-static integrator, one process; per velocity its load steps and time, and the whole build.",
          (SOURCES["impact_surrogate_yield_quasistatic"],), _impact_database),
    Block("threads", "One thread or two",
          "Kernels the toolkit leans on, each in a fresh interpreter limited to that many threads "
          "(`toolkit.set_threads`), median seconds.", (SOURCES["threads"],), _threads),
    Block("interrupt_stress", "Ctrl-C at random times in a database run",
          "`toolkit static database --resolution coarse --plans 300 --workers 1`, started afresh for each try in its "
          "own process group and sent SIGINT (to the worker too) at a time drawn uniformly over its first seconds, "
          "when the worker may be anywhere in a simulation (its METIS ordering included); a try that has not ended "
          "a minute later counts as hung.", (SOURCES["interrupt_stress"],), _interrupt_stress),
)}
#: blocks whose table needs every source (the others render what is present, the rest as one line)
_PARTIAL = {"headline", "static_surrogate", "impact_surrogate", "static_convergence", "own_face",
            "surrogate_trust_impact", "meshed_database", "static_meshed_speed", "regulation_speed",
            "segmentation_damage"}


# ----------------------------------------------------------------------------------------------
# generation


def load(results: Path) -> dict:
    """``{stem: (DataFrame, sidecar)}`` of every ``*.csv`` in ``results``."""
    data = {}
    for csv in sorted(Path(results).glob("*.csv")):
        side = csv.with_suffix(".json")
        data[csv.stem] = (pd.read_csv(csv), json.loads(side.read_text()) if side.exists() else {})
    return data


def render(name: str, data: dict) -> str:
    """The Markdown between the markers of block ``name``."""
    block = BLOCKS[name]
    present = {s.stem: data[s.stem] for s in block.sources if s.stem in data}
    if name not in _PARTIAL:
        missing = [s for s in block.sources if s.stem not in data]
        if missing:
            return not_measured(missing[0])
        body = block.render(present)
        return body + "\n\n" + _sources_footer(present, block.sources)
    if not present and name != "headline":
        return not_measured(block.sources[-1])
    body = block.render(present)
    if name != "headline":
        body += "\n\n" + _sources_footer(present, block.sources)
    return body


def fill(text: str, blocks: dict[str, str]) -> tuple[str, list[str], list[str]]:
    """``text`` with every known block's content replaced; the names that changed; unknown names."""
    changed, unknown = [], []

    def sub(m):
        name = m.group("name")
        if name not in blocks:
            unknown.append(name)
            return m.group(0)
        body = "\n\n" + blocks[name] + "\n\n"
        if m.group("body") != body:
            changed.append(name)
        return m.group("open") + body + m.group("close")

    return MARKER.sub(sub, text), changed, unknown


def benchmarks_page(blocks: dict[str, str], data: dict) -> str:
    """``docs/benchmarks.md``: every block with what it measures and its results' versions."""
    out = ["# Benchmarks", "",
           "Every table here is generated by `python benchmarks/report.py` from the files committed in "
           "`benchmarks/results/` (a table `NAME.csv` and its provenance `NAME.json`: CPU, cores, threads, "
           "library versions, commit, command, date). The same tables fill the blocks of the README and the "
           "other pages. To measure again, run the command under a table (each takes the time it says on "
           f"{MACHINE}), then `python benchmarks/report.py`; `python benchmarks/report.py --check` fails when a "
           "page differs from the results, and `python benchmarks/report.py --stale` names each result whose "
           "measured code (its benchmark's `MEASURES`) changed after the commit it was measured on.", ""]
    for name, block in BLOCKS.items():
        out += [f"## {block.title}", "", block.about, "", f"<!-- results: {name} -->", "", blocks[name], "",
                "<!-- /results -->", ""]
        versions: dict[str, list[str]] = {}
        for src in block.sources:
            if src.stem in data and data[src.stem][1]:
                versions.setdefault(versions_line(data[src.stem][1]), []).append(f"`{src.stem}`")
        if len(versions) == 1:
            out += [f"Versions: {next(iter(versions))}.", ""]
        elif versions:
            out += ["Versions: " + "; ".join(f"{', '.join(st)}: {v}" for v, st in versions.items()) + ".", ""]
    return "\n".join(out).rstrip("\n") + "\n"


def pages(root: Path) -> list[Path]:
    """README.md and docs/*.md under ``root`` (those that exist), without the generated page."""
    found = [root / "README.md", *sorted((root / "docs").glob("*.md"))]
    return [p for p in found if p.exists() and p != root / BENCHMARKS_PAGE]


#: the results copied into the package for :mod:`toolkit.common.fidelity` (``<stem>.csv`` and ``.json``)
PACKAGE_COPIES = ("static_ladder", "static_convergence", "impact_ladder")
PACKAGE_FOLDER = Path("toolkit") / "common" / "data" / "ladders"


def copy_into_package(root: Path, results: Path, check: bool) -> list[str]:
    """Copy each of :data:`PACKAGE_COPIES` present in ``results`` byte for byte into
    ``root/PACKAGE_FOLDER`` (with ``check``, only compare); the copies that differed, as messages."""
    problems = []
    for stem in PACKAGE_COPIES:
        for suffix in (".csv", ".json"):
            source = Path(results) / f"{stem}{suffix}"
            if not source.exists():
                continue
            target = root / PACKAGE_FOLDER / source.name
            if not target.exists() or target.read_bytes() != source.read_bytes():
                problems.append(f"{PACKAGE_FOLDER / source.name}: differs from benchmarks/results/{source.name}")
                if not check:
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(source.read_bytes())
    return problems


def run(root: Path, results: Path, check: bool) -> list[str]:
    """Rewrite (or, with ``check``, compare) the pages and the package's copies of the ladders;
    the differences found, as messages."""
    data = load(results)
    blocks = {name: render(name, data) for name in BLOCKS}
    problems = []
    for page in pages(root):
        text = page.read_text()
        new, changed, unknown = fill(text, blocks)
        rel = page.relative_to(root)
        problems += [f"{rel}: block '{n}' differs from benchmarks/results" for n in changed]
        problems += [f"{rel}: unknown block '{n}' (known: {', '.join(BLOCKS)})" for n in unknown]
        if not check and new != text:
            page.write_text(new)
    target = root / BENCHMARKS_PAGE
    page_text = benchmarks_page(blocks, data)
    if not target.exists() or target.read_text() != page_text:
        problems.append(f"{BENCHMARKS_PAGE}: differs from benchmarks/results")
        if not check:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(page_text)
    return problems + copy_into_package(root, results, check)


def measured_paths(script: Path) -> tuple[str, ...]:
    """The ``MEASURES`` tuple of a benchmark script (read without importing it); ``()`` when it
    states none."""
    for node in ast.parse(script.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "MEASURES" for t in node.targets):
            return tuple(ast.literal_eval(node.value))
    return ()


def _changed_since(root: Path, commit: str, paths: tuple[str, ...]) -> list[str] | None:
    """Files among ``paths`` that differ between ``commit`` and HEAD, or None when git does not
    know ``commit`` (a shallow clone, another repository)."""
    known = subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=root, capture_output=True)
    if known.returncode != 0:
        return None
    out = subprocess.run(["git", "diff", "--name-only", commit, "HEAD", "--", *paths], cwd=root,
                         capture_output=True, text=True, check=True)
    return out.stdout.split()


def stale_results(root: Path, results: Path) -> list[str]:
    """One line per result due to be measured again: measured on a modified tree, by a script that
    states no ``MEASURES``, on a commit git does not know, or before a later commit changed the
    code it measures (naming up to three of the files)."""
    problems = []
    for sidecar in sorted(Path(results).glob("*.json")):
        try:
            doc = json.loads(sidecar.read_text())
        except json.JSONDecodeError:
            continue
        runs = doc.get("runs") or ([doc["provenance"]] if "provenance" in doc else [])
        if not runs:
            continue
        name = sidecar.stem
        words = [str(r.get("command", "")).split() for r in runs]
        commands = {w[1] for w in words if len(w) > 1 and w[1].startswith("benchmarks/")}
        scripts = [root / c for c in commands if (root / c).exists()]
        paths = tuple(sorted({p for s in scripts for p in measured_paths(s)}))
        if not paths:
            problems.append(f"{name}: its benchmark ({', '.join(sorted(commands)) or 'unknown'}) states no MEASURES")
            continue
        if any(r.get("dirty") for r in runs):
            problems.append(f"{name}: measured on a modified tree")
            continue
        for commit in sorted({r.get("commit") for r in runs if r.get("commit")}):
            changed = _changed_since(root, commit, paths)
            if changed is None:
                problems.append(f"{name}: commit {commit[:9]} is not in this repository's history")
            elif changed:
                more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
                problems.append(f"{name}: measured on {commit[:9]}; since then {', '.join(changed[:3])}{more} changed")
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare only; exit 1 naming each block that differs")
    ap.add_argument("--stale", action="store_true",
                    help="name each result whose measured code changed after the commit it was measured on; exit 1 "
                         "if any")
    ap.add_argument("--root", type=Path, default=ROOT, help="repository root holding README.md and docs/")
    ap.add_argument("--results", type=Path, default=None, help="results folder (default: ROOT/benchmarks/results)")
    args = ap.parse_args(argv)
    results = args.results or args.root / "benchmarks" / "results"
    if args.stale:
        stale = stale_results(args.root, results)
        for line in stale:
            print(line)
        names = {line.split(":")[0] for line in stale}
        print(f"{len(names)} of {len(list(results.glob('*.json')))} results due to be measured again", file=sys.stderr)
        return 1 if stale else 0
    problems = run(args.root, results, args.check)
    if args.check:
        for p in problems:
            print(p, file=sys.stderr)
        return 1 if problems else 0
    unknown = [p for p in problems if "unknown block" in p]
    for p in unknown:
        print(p, file=sys.stderr)
    updated = [p for p in problems if "unknown block" not in p]
    print(f"updated {len(updated)} block(s)/page(s)" + "".join(f"\n  {p}" for p in updated))
    return 1 if unknown else 0


if __name__ == "__main__":
    raise SystemExit(main())
