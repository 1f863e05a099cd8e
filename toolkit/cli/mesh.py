"""``toolkit mesh``: a labelled tetrahedral face mesh from a patient's segmented surfaces."""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

from toolkit.cli._common import Command, add_axes, positive_float, two_points, uninterruptible

FORMATS = (".vtu", ".inp")


def commissures(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """``X,Y,Z:X,Y,Z`` (mm), or a file of two lines ``X,Y,Z`` -> two points."""
    return two_points(text, "--commissures", "16.8,57.7,0.3:-16.8,57.7,0.3")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from toolkit.common.defaults import MESH
    from toolkit.mesh.backends import BACKENDS, DEFAULT

    parser.add_argument("--tissue", required=True, type=Path,
                        help="closed surface of the soft tissue (STL/OBJ/PLY/VTK/VTU/OFF), in the axes of --axes")
    parser.add_argument("--bone", action="append", default=[], metavar="SEGMENT=FILE", required=True,
                        help="bone surface of a segment after the virtual osteotomy (lefort, distal, proximal_left, "
                             "proximal_right, skull), e.g. --bone lefort=maxilla.stl; repeatable")
    parser.add_argument("--commissures", type=commissures, default=None, metavar="X,Y,Z:X,Y,Z",
                        help="the two corners of the mouth on the skin, mm in the surface files' axes, or a file of "
                             "two lines X,Y,Z: the lips are cut between them and slide (default: a closed mouth "
                             "without lip sliding)")
    parser.add_argument("--order", type=int, default=MESH["order"], choices=[1, 2],
                        help="element order: 1 tet4, 2 tet10 (linear tetrahedra lock at the tissue's nu = 0.47)")
    parser.add_argument("--size", type=positive_float, default=MESH["size_mm"], help="tetrahedron edge length, mm")
    parser.add_argument("--backend", default=DEFAULT, choices=list(BACKENDS), help="tetrahedral mesher")
    parser.add_argument("--rules", type=Path, default=None,
                        help="labelling rules (TOML) overriding the defaults (see docs/own-face.md)")
    parser.add_argument("--units", default="mm", choices=["mm", "m", "cm", "um"],
                        help="length unit of the surface files, converted to mm")
    add_axes(parser, "the surface files and --commissures")
    parser.add_argument("--max-hole-edges", type=int, default=60,
                        help="holes of the tissue surface bounded by up to this many edges are closed")
    parser.add_argument("--memory", type=positive_float, default=None, metavar="GIB",
                        help="memory meshing and simulating a plan may take, GiB (default: what the system has "
                             "available); a --size whose estimate exceeds it is refused before meshing")
    parser.add_argument("--no-preview", action="store_true", help="skip labels.png (the labels preview)")
    parser.add_argument("--out", required=True, type=Path,
                        help="output mesh (.vtu or .inp); labels.json and labels.png are written beside it")


def run(args: argparse.Namespace) -> int:
    from toolkit.cli.static import bones
    from toolkit.common.outputs import OutputError, check_output_file
    from toolkit.mesh.face import mesh_face, render_labels

    if args.out.suffix.lower() not in FORMATS:
        raise OutputError(f"--out {str(args.out)!r}: expected a mesh file name ending in {' or '.join(FORMATS)}")
    check_output_file(args.out, what="mesh file")
    for name in ("labels.json", "labels.png"):
        check_output_file(args.out.with_name(name), what=name)
    for path in [args.tissue, *bones(args.bone).values()] + ([args.rules] if args.rules else []):
        if not Path(path).is_file():
            raise FileNotFoundError(f"{str(path)!r} does not exist; expected a surface file "
                                    f"{'(--rules: TOML)' if path == args.rules else ''}".rstrip())
    face = mesh_face(args.tissue, bones(args.bone), args.commissures, size_mm=args.size, order=args.order,
                     backend=args.backend, rules=args.rules, units=args.units, axes=args.axes,
                     max_hole_edges=args.max_hole_edges, threads=1 if args.threads is None else args.threads,
                     memory_gib=args.memory)
    with tempfile.TemporaryDirectory() as tmp:  # the image first: a Ctrl-C while it renders leaves nothing
        image = None if args.no_preview else render_labels(face, Path(tmp) / "labels.png")
        with uninterruptible():  # then the files, all or none
            written = face.write(args.out, image=False)
            if image is not None:
                written["image"] = Path(shutil.move(image, args.out.with_name("labels.png")))
    r = face.report
    print(face.summary())
    print("seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in r["seconds"].items()))
    e = r["estimate"]
    print(f"estimated before meshing: {e['nodes']:,} nodes, {e['elements']:,} elements; memory to mesh "
          f"{e['mesher_gib']:.1f} GiB, to simulate a plan {e['simulation_gib']:.1f} GiB")
    repairs = {k: v for k, v in r["repair"].items() if v}
    print(f"tissue surface repairs: {repairs if repairs else 'none needed'}")
    print("wrote " + ", ".join(str(p) for p in written.values()))
    return 0


COMMAND = Command(
    help="a labelled tet mesh of a face from segmented surfaces",
    description="Mesh a patient's face: the tissue surface and the bony segments' surfaces (as a planning system "
                "exports them after the virtual osteotomy) -> a tetrahedral mesh with the node sets of the static "
                "workflow, labels.json and labels.png.",
    add_arguments=add_arguments,
    run=run,
    interrupted="nothing was written to {out}; rerun the same command",
)
