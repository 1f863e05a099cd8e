"""``toolkit phantom``: write one phantom mesh."""

from __future__ import annotations

import argparse
from pathlib import Path

from toolkit.cli._common import RESOLUTIONS, Command

KINDS = ["face-hex", "face-tet4", "face-tet10", "ball-tet4", "ball-tet10"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("kind", choices=KINDS)
    parser.add_argument("--resolution", default="coarse", choices=RESOLUTIONS, help="phantom resolution")
    parser.add_argument("--seed", type=int, default=None,
                        help="draw a random subject (FaceShape.sample) instead of the nominal face "
                             "(default: the nominal face)")
    parser.add_argument("--mouth-open", type=float, default=None,
                        help="lip gap at the skin, mm (0-12) (default: the shape's own, 0 for the nominal face)")
    parser.add_argument("--out", required=True, type=Path, help="output mesh file")
    parser.add_argument("--preview", type=Path, default=None, help="also render a PNG here (default: no PNG)")


def run(args: argparse.Namespace) -> int:
    from toolkit.common.meshes.io import write
    from toolkit.common.outputs import check_output_file

    check_output_file(args.out, what="mesh file")
    if args.preview:
        check_output_file(args.preview, what="preview image", option="preview")
    mesh = build(args.kind, args.resolution, face_shape(args.seed, args.mouth_open) if args.kind.startswith("face")
                 else None)
    mesh.check()
    write(args.out, mesh)
    print(f"wrote {args.out}: {mesh}")
    if args.preview:
        from toolkit.common.plotting import render

        render(mesh, args.preview, title=f"{args.kind} ({args.resolution})")
        print(f"wrote {args.preview}")
    return 0


def face_shape(seed: int | None, mouth_open: float | None):
    """The FaceShape of ``--seed`` (``FaceShape.sample(seed)``; None: the nominal face) and
    ``--mouth-open`` (mm; None: the shape's own)."""
    from dataclasses import replace

    from toolkit.common.phantoms.phantom import FaceShape

    shape = FaceShape.sample(seed) if seed is not None else FaceShape()
    return shape if mouth_open is None else replace(shape, mouth_open=mouth_open)


def build(kind: str, resolution: str, shape=None):
    """The mesh of a phantom ``kind`` (one of :data:`KINDS`)."""
    from toolkit.common.phantoms.phantom import ball, face_hex, face_tet

    if kind == "face-hex":
        return face_hex(resolution, shape).mesh
    if kind.startswith("face-tet"):
        return face_tet(resolution, order=1 if kind.endswith("4") else 2, shape=shape)
    return ball(resolution=resolution, order=1 if kind.endswith("4") else 2)


COMMAND = Command(
    help="write one phantom mesh",
    description="Build one phantom and write it (format from the suffix: .vtu, .xdmf, .inp).",
    add_arguments=add_arguments,
    run=run,
)
