"""Where the time goes: a profile summary of each simulation path.

Runs each path under ``cProfile`` (one thread) and keeps its top functions by own time, with
their share of the run:

- ``static-meshed``: the default plan (linear, mucosa and lip sliding, 3 increments) on the
  paper phantom's surfaces meshed by ``toolkit mesh`` at ``--size`` mm (tet10);
- ``static-phantom``: the same plan on the paper hexahedral phantom;
- ``impact-quasistatic``: the default impact scene at paper resolution, quasi-static, at
  ``--velocity`` mm/s.

Writes ``benchmarks/results/profiles.csv`` (path, rank, function, own seconds, share of the
run, cumulative seconds, calls; one row per function kept) with provenance.

Usage::

    python benchmarks/profiles.py                      # every path, the top 12 functions each
    python benchmarks/profiles.py --paths static-meshed --size 3 --top 20
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from pathlib import Path

import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/impact/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py",
            "toolkit/common/defaults.py")

PATHS = ("static-meshed", "static-phantom", "impact-quasistatic")


def _run(path: str, size: float, velocity: float):
    """A function of no argument that runs ``path`` (its set-up done outside the profile)."""
    if path == "static-phantom":
        from toolkit.static import load_case

        case = load_case(resolution="paper")
        return case.simulate
    if path == "static-meshed":
        from toolkit.common.phantoms.phantom import face_hex
        from toolkit.mesh import mesh_face
        from toolkit.mesh.phantom import phantom_surfaces
        from toolkit.static import load_case

        surfaces = phantom_surfaces(face_hex("paper"))
        face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=size, order=2)
        case = load_case(face.mesh, plan=load_case(resolution="paper").plan,
                         bones={k: v for k, v in face.bones.items() if k != "skull"})
        return case.simulate
    from toolkit.impact import default_scene, simulate

    scene = default_scene(velocity=velocity).with_face(resolution="paper").with_fidelity(integrator="quasi-static")
    return lambda: simulate(scene, preview=False)


def _label(key) -> str:
    file, line, name = key
    if file == "~":
        return name
    parts = Path(file).parts
    for anchor in ("toolkit", "site-packages"):
        if anchor in parts:
            parts = parts[parts.index(anchor) + (anchor == "site-packages"):]
            break
    return f"{'/'.join(parts)}:{line}({name})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paths", nargs="+", default=list(PATHS), choices=PATHS)
    ap.add_argument("--size", type=float, default=5.0, help="mm, the meshed face's element size")
    ap.add_argument("--velocity", type=float, default=30.0, help="mm/s, the impact scene's ball speed")
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--out", type=Path, default=RESULTS / "profiles.csv")
    args = ap.parse_args(argv)
    from toolkit.common.runtime import set_threads

    set_threads(1)
    rows = []
    for path in args.paths:
        run = _run(path, args.size, args.velocity)
        profile = cProfile.Profile()
        t0 = time.perf_counter()
        profile.runcall(run)
        total = time.perf_counter() - t0
        stats = pstats.Stats(profile).stats  # key -> (primitive calls, calls, own s, cumulative s, callers)
        top = sorted(stats.items(), key=lambda kv: kv[1][2], reverse=True)[:args.top]
        for rank, (key, (_, calls, own, cumulative, _)) in enumerate(top, 1):
            rows.append({"path": path, "total_s": total, "rank": rank, "function": _label(key), "own_s": own,
                         "share": own / total, "cumulative_s": cumulative, "calls": calls})
        print(f"{path}: {total:.1f} s", flush=True)
    table = pd.DataFrame(rows)
    print(table.round(3).to_string(index=False))
    write_result(args.out, table, extra={"size_mm": args.size, "velocity_mm_s": args.velocity})


if __name__ == "__main__":
    main()
