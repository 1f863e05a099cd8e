"""Labels and the round trip of ``toolkit mesh`` under segmentation damage.

The phantom's clean surfaces (:func:`toolkit.mesh.phantom.phantom_surfaces`) are damaged one
kind at a time (:func:`toolkit.mesh.damage.damaged`: 30 % of each bone's triangles flipped in
patches, a 1 mm osteotomy kerf, holes, bones in pieces, bones coarser and finer, the tissue's
bone side 0-5 mm off the bone, and all of these but the resolution changes at once), meshed and
labelled by :func:`toolkit.mesh.mesh_face`, and compared with the clean surfaces' face:

- **labels**: every node set's count, and per segment the tissue boundary area (mm^2) lying on
  its bone and the part it carries, as ratios to the clean faces' mean (``segmentation_damage.csv``);
- **round trip**: the default plan (linear, mucosa+lip sliding, 3 increments) on the damaged face
  against the phantom's own hexahedral run: mean, 95th percentile and maximum skin difference
  (:func:`own_face.skin_difference`); and against the phantom's hexahedral run on the same damaged
  bones (``same_bones_*``: the bones standing off the tissue change the anatomy, not only its
  labels).

fTetWild meshes a surface differently from run to run, so the clean face is meshed ``--repeats``
times and the spread of its counts is reported beside the damage (``clean`` rows). Damage to the
bones alone leaves the tissue surface as it is: those faces reuse the first clean meshing's
tetrahedra (column ``draw``: ``clean``), so that their counts differ from the clean face's by
what the labelling does with the damaged bones and nothing else, and their ratios are to that
face; damage that moves the tissue is meshed anew (``own``), its ratios to the clean faces' mean.

Usage::

    python benchmarks/segmentation_damage.py                       # paper phantom, 5 mm tet10
    python benchmarks/segmentation_damage.py --kinds flipped off_bone --no-simulate
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result
from own_face import skin_difference

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

SETS = ("fixed", "maxilla", "mandible", "mucosa_lefort", "mucosa_distal", "mucosa_proximal_left",
        "mucosa_proximal_right", "mucosa_skull", "mucosa_sliding", "bone", "skin")


def main(argv=None):
    from toolkit.mesh.damage import DAMAGE

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", default="paper")
    ap.add_argument("--size", type=float, default=5.0, help="tetrahedron edge length, mm")
    ap.add_argument("--kinds", nargs="+", default=list(DAMAGE), choices=list(DAMAGE))
    ap.add_argument("--repeats", type=int, default=2, help="clean meshings (the mesher's own spread)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-simulate", action="store_true", help="labels only, no default-plan round trip")
    ap.add_argument("--out", type=Path, default=RESULTS / "segmentation_damage.csv")
    args = ap.parse_args(argv)

    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.mesh import mesh_face
    from toolkit.mesh.damage import damaged
    from toolkit.mesh.phantom import phantom_surfaces
    from toolkit.static import load_case
    from toolkit.static.simulate import simulate

    set_threads(1)
    draws = _reuse_draws()
    phantom = face_hex(args.resolution)
    clean = phantom_surfaces(phantom)
    case = load_case(resolution=args.resolution)
    reference = None if args.no_simulate else case.simulate(increments=3, material="linear", sliding="mucosa+lip")
    runs = [("clean", k) for k in range(args.repeats)] + [(kind, 0) for kind in args.kinds]
    rows = []
    for kind, repeat in runs:
        rng = np.random.default_rng(args.seed + repeat)
        tissue, bones = (clean.tissue, clean.bones) if kind == "clean" else damaged(clean.tissue, clean.bones, kind,
                                                                                   rng)
        same_tissue = kind != "clean" and tissue is clean.tissue
        row = {"damage": kind, "repeat": repeat, "size_mm": args.size, "draw": "clean" if same_tissue else "own"}
        t0 = time.perf_counter()
        try:
            draws.reuse = same_tissue or (kind, repeat) == ("clean", 0)  # the first clean draw is the one kept
            face = mesh_face(tissue, bones, clean.commissures, size_mm=args.size, order=2)
        except Exception as exc:  # noqa: BLE001 - recorded
            rows.append({**row, "status": f"{type(exc).__name__}: {str(exc)[:200]}"})
            print(rows[-1], flush=True)
            continue
        row.update(status="ok", nodes=face.report["nodes"], mesh_face_s=time.perf_counter() - t0,
                   **{f"n_{k}": face.report["node_sets"].get(k, 0) for k in SETS},
                   **{f"carried_{k}_mm2": v["attached_area_mm2"] for k, v in face.report["segments"].items()
                      if k in ("lefort", "distal")},
                   **{f"facing_{k}_mm2": v["facing_area_mm2"] for k, v in face.report["segments"].items()})
        if reference is not None:
            meshed = load_case(face.mesh, plan=case.plan, bones={k: v for k, v in face.bones.items() if k != "skull"})
            t1 = time.perf_counter()
            try:
                res = meshed.simulate(increments=3, material="linear", sliding="mucosa+lip")
                row.update(simulate_s=time.perf_counter() - t1,
                           **skin_difference(face.mesh, res.displacement, phantom.mesh, reference.displacement))
                # the phantom's own hexahedral run on the same (damaged) bones: what the labels and
                # the meshing account for, the anatomy being the same
                same = replace(phantom, segments={k: replace(v, surface=bones[k]) if k in bones else v
                                                  for k, v in phantom.segments.items()})
                ref_same = simulate(same, case.plan, 3, "linear", "mucosa+lip")
                diff = skin_difference(face.mesh, res.displacement, phantom.mesh, ref_same.displacement)
                row.update(same_bones_diff_mean_mm=diff["diff_mean_mm"], same_bones_diff_p95_mm=diff["diff_p95_mm"])
                # what the damaged bones alone change in the phantom's own run (its mesh and labels kept)
                skin = phantom.mesh.node_sets["skin"]
                own = np.linalg.norm(ref_same.displacement[skin] - reference.displacement[skin], axis=1)
                row.update(bones_alone_diff_mean_mm=float(own.mean()),
                           bones_alone_diff_p95_mm=float(np.percentile(own, 95)))
            except Exception as exc:  # noqa: BLE001 - recorded
                row.update(status=f"{type(exc).__name__}: {str(exc)[:200]}", simulate_s=time.perf_counter() - t1)
        rows.append(row)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    table = pd.DataFrame(rows)
    base = table[(table.damage == "clean") & (table.status == "ok")]
    first = base[base.repeat == 0]
    same = (table.draw == "clean").to_numpy()
    for col in [c for c in table.columns if c.startswith(("n_", "carried_", "facing_"))]:
        reference = np.where(same, first[col].mean() if len(first) else np.nan, base[col].mean())
        table[f"{col}_ratio"] = table[col] / reference
    write_result(args.out, table, argv=argv)
    ratios = [c for c in table.columns if c.endswith("_ratio")]
    worst = table.assign(worst_ratio=table[ratios].sub(1).abs().max(axis=1) + 1)
    with pd.option_context("display.width", 200):
        cols = ["damage", "repeat", "draw", "status", "nodes", "worst_ratio"] + (
            [] if args.no_simulate else ["diff_mean_mm", "diff_p95_mm"])
        print(worst[[c for c in cols if c in worst.columns]].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    return table


def _reuse_draws():
    """Make :func:`toolkit.mesh.mesh_face` reuse the tetrahedra of a surface it has meshed
    before, while the returned switch's ``reuse`` is True (its first meshing of a surface is
    kept only then); returns the switch."""
    import types

    import toolkit.mesh.face as face_module
    from toolkit.common.meshes.fingerprint import array_fingerprint, points_fingerprint

    tetrahedralize, kept = face_module.tetrahedralize, {}
    switch = types.SimpleNamespace(reuse=False)

    def drawn(points, triangles, size_mm, **kwargs):
        key = (points_fingerprint(points), array_fingerprint(triangles), float(size_mm))
        if switch.reuse and key in kept:
            return tuple(a.copy() for a in kept[key])
        result = tetrahedralize(points, triangles, size_mm, **kwargs)
        if switch.reuse:
            kept.setdefault(key, result)
        return result

    face_module.tetrahedralize = drawn
    return switch


if __name__ == "__main__":
    main()
