"""Inputs that once gave a wrong answer with exit 0, each run as a user would (``python -m toolkit
...`` in a fresh folder, coarse phantom): what the command does with them now.

Each case states the answer a correct toolkit gives (``expect``: refused with exit 2 and an error
naming the remedy, or answered with the motion the plan asked for) and records the exit code, the
``error:`` line and the measured figure. ``ok`` is whether the outcome is the expected one.

- ``labels-carry-nothing``: labelling rules under which the distal mandible carries almost no
  tissue (the real segmentation's one-node ``mandible``): ``toolkit mesh`` must refuse;
- ``mesh-one-node-mandible`` : a face mesh whose ``mandible`` set holds one node, and a 5 mm
  advance: ``toolkit static simulate`` must refuse before any solve;
- ``lps-surfaces`` / ``lps-surfaces-declared``: surfaces with y mirrored (DICOM/ITK-SNAP axes):
  ``toolkit mesh`` must refuse and name ``--axes LPS``, and with ``--axes LPS`` mesh a face whose
  ``maxilla`` is labelled;
- ``far-pivot``: 2 degrees about a pivot 10 m away: ``toolkit static simulate`` must refuse;
- ``advance-5mm``: the 5 mm advance on the meshed phantom: the chin must move (``chin_mm``).

Writes ``benchmarks/results/silent_cases.csv``.

    python benchmarks/silent_cases.py
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/__main__.py", "toolkit/cli/", "toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/",
            "toolkit/common/meshes/", "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py",
            "toolkit/common/papers.py", "toolkit/common/defaults.py")

PY = sys.executable


def toolkit(*args, cwd: Path) -> tuple[int, str, float]:
    t0 = time.perf_counter()
    p = subprocess.run([PY, "-m", "toolkit", *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=1800)
    line = next((ln for ln in p.stderr.splitlines() if "error:" in ln), "")
    return p.returncode, line, time.perf_counter() - t0


def _advance(path: Path, mm: float = 5.0) -> Path:
    path.write_text(f"[distal]\ntranslation_mm = [0.0, {mm}, 0.0]\n")
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=float, default=7.0, help="tetrahedron edge length of the meshed faces, mm")
    ap.add_argument("--resolution", default="paper")
    ap.add_argument("--out", type=Path, default=RESULTS / "silent_cases.csv")
    args = ap.parse_args(argv)

    from toolkit.common.meshes.io import read, write
    from toolkit.common.meshes.mesh import Mesh
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.mesh.phantom import PhantomSurfaces, phantom_surfaces, write_surfaces

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        surfaces = phantom_surfaces(face_hex(args.resolution))
        files = write_surfaces(tmp / "surfaces", surfaces)
        bones = [f"--bone={k}={files[k]}" for k in surfaces.bones]
        moving = [f"--bone={k}={files[k]}" for k in surfaces.bones if k != "skull"]
        mesh = ["mesh", "--tissue", files["tissue"], *bones, "--size", args.size, "--no-preview"]

        def add(case, expect, code, line, seconds, ok, **figures):
            rows.append({"case": case, "expect": expect, "exit": code, "error": line[:200], "seconds": seconds,
                         "ok": bool(ok), **figures})
            print(rows[-1], flush=True)

        # the meshed face every later case uses
        code, line, sec = toolkit(*mesh, "--out", tmp / "face.vtu", cwd=tmp)
        labels = json.loads((tmp / "labels.json").read_text()) if code == 0 else {}
        add("mesh-clean", "a labelled face", code, line, sec, code == 0,
            mandible_nodes=labels.get("node_sets", {}).get("mandible", 0),
            maxilla_nodes=labels.get("node_sets", {}).get("maxilla", 0))

        rules = tmp / "rules.toml"
        rules.write_text("[segments.distal]\nattach = \"anterior\"\nanterior_deg = 0.2\n")
        code, line, sec = toolkit(*mesh, "--rules", rules, "--out", tmp / "few" / "face.vtu", cwd=tmp)
        add("labels-carry-nothing", "refused naming the segment and min_carried_mm2", code, line, sec,
            code == 2 and "distal" in line and "min_carried_mm2" in line)

        face = read(tmp / "face.vtu")
        sets = dict(face.node_sets)
        sets["mandible"] = sets["mandible"][:1]
        write(tmp / "one.vtu", Mesh(face.points, face.cells, node_sets=sets, element_sets=face.element_sets,
                                    cell_data=face.cell_data))
        plan = _advance(tmp / "adv5.toml")
        code, line, sec = toolkit("static", "simulate", "--mesh", tmp / "one.vtu", *moving, "--plan", plan,
                                  "--out", tmp / "one-out", "--no-preview", cwd=tmp)
        add("mesh-one-node-mandible", "refused before the solve naming 'mandible'", code, line, sec,
            code == 2 and "mandible" in line)

        flip = np.array([1.0, -1.0, 1.0])

        def mirror(m):
            return Mesh(m.points * flip, {"tri3": m.cells["tri3"]})

        mirrored = PhantomSurfaces(mirror(surfaces.tissue), {k: mirror(b) for k, b in surfaces.bones.items()},
                                   surfaces.commissures * flip)
        lps = write_surfaces(tmp / "lps", mirrored)
        lps_mesh = ["mesh", "--tissue", lps["tissue"], *[f"--bone={k}={lps[k]}" for k in surfaces.bones],
                    "--size", args.size, "--no-preview"]
        code, line, sec = toolkit(*lps_mesh, "--out", tmp / "lps-out" / "face.vtu", cwd=tmp)
        add("lps-surfaces", "refused naming --axes LPS", code, line, sec, code == 2 and "LPS" in line)
        code, line, sec = toolkit(*lps_mesh, "--axes", "LPS", "--out", tmp / "lps-ok" / "face.vtu", cwd=tmp)
        n = json.loads((tmp / "lps-ok" / "labels.json").read_text())["node_sets"] if code == 0 else {}
        add("lps-surfaces-declared", "a face with maxilla and mandible labelled", code, line, sec,
            code == 0 and n.get("maxilla", 0) > 0 and n.get("mandible", 0) > 0, maxilla_nodes=n.get("maxilla", 0),
            mandible_nodes=n.get("mandible", 0))

        far = tmp / "far.toml"
        far.write_text("[lefort]\nrotation_vector_deg = [2.0, 0.0, 0.0]\npivot_mm = [0.0, 10000.0, 0.0]\n")
        code, line, sec = toolkit("static", "simulate", "--mesh", tmp / "face.vtu", *moving, "--plan", far,
                                  "--out", tmp / "far-out", "--no-preview", cwd=tmp)
        add("far-pivot", "refused naming the pivot's distance", code, line, sec, code == 2 and "pivot" in line)

        code, line, sec = toolkit("static", "simulate", "--mesh", tmp / "face.vtu", *moving, "--plan", plan,
                                  "--out", tmp / "adv-out", "--no-preview", cwd=tmp)
        chin, checks = np.nan, {}
        if code == 0:
            result = read(tmp / "adv-out" / "result.vtu")
            skin = result.node_sets["skin"] if "skin" in result.node_sets else np.arange(result.n_points)
            u = result.point_data["displacement"][skin]
            x = result.points[skin]
            front = x[:, 1] > np.percentile(x[:, 1], 90)
            lowest = np.argmin(np.where(front & (np.abs(x[:, 0]) < 10), x[:, 2], np.inf))
            chin = float(u[lowest, 1])
            checks = json.loads((tmp / "adv-out" / "summary.json").read_text()).get("checks", {})
        add("advance-5mm", "the chin moves forward (a few mm)", code, line, sec, code == 0 and chin > 1.0,
            chin_mm=chin, checks_passed=bool(code == 0 and checks.get("answer", {}).get("passed")))
    table = pd.DataFrame(rows)
    write_result(args.out, table, argv=argv)
    print(table[["case", "exit", "ok", "seconds"]].to_string(index=False))
    return table


if __name__ == "__main__":
    main()
