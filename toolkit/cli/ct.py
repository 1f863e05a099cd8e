"""``toolkit ct``: the face's surfaces (soft tissue and osteotomy segments) from a head CT."""

from __future__ import annotations

import argparse
from pathlib import Path

from toolkit.cli._common import Command, positive_float


def _length(text: str) -> float:
    """A finite length in mm, of either sign (an argparse type)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if value != value or abs(value) == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a length in mm, e.g. 5, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from toolkit.mesh.ct_rules import CTRules

    d = CTRules()
    parser.add_argument("--volume", required=True, type=Path,
                        help="head CT as NRRD: .nrrd (attached header) or .nhdr (detached header with its data files)")
    parser.add_argument("--out", required=True, type=Path,
                        help="folder for tissue.stl, the five segments' STL files and ct.json (created when missing)")
    parser.add_argument("--skin", type=float, default=d.skin, help="skin threshold (air to soft tissue), CT units")
    parser.add_argument("--bone", type=float, default=d.bone, help="bone threshold, CT units")
    parser.add_argument("--teeth", type=float, default=None,
                        help="teeth threshold, CT units (default: air + 2.4 x (bone - air))")
    parser.add_argument("--axes", default=None, metavar="LPI",
                        help="the direction index axes 0, 1, 2 of the volume increase toward, one of L/R, A/P, S/I "
                             "each (default: found from the anatomy; left-right from the header's handedness)")
    planes = parser.add_argument_group("osteotomy planes (mm, relative to the landmarks found)")
    planes.add_argument("--lefort", type=positive_float, default=d.lefort_mm,
                        help="Le Fort I plane above the occlusal plane")
    planes.add_argument("--split", type=_length, default=d.split_mm,
                        help="sagittal split planes behind the last lower molar of each side")
    planes.add_argument("--tuberosity", type=_length, default=d.tuberosity_mm,
                        help="posterior limit of the Le Fort I segment behind the last upper molar")
    planes.add_argument("--occlusal-pitch", type=float, default=None, metavar="DEG",
                        help="the occlusal plane's tilt in the volume about the left-right axis, anterior end down "
                             "(default: found from the gap between the teeth)")
    planes.add_argument("--occlusal-shift", type=_length, default=d.occlusal_shift_mm,
                        help="the occlusal plane moved along its normal, superior positive")
    cuts = parser.add_argument_group("the tissue's cuts (mm)")
    cuts.add_argument("--superior", type=positive_float, default=d.superior_mm,
                      help="superior cut above the Le Fort I plane's highest point on the maxilla")
    cuts.add_argument("--posterior", type=_length, default=d.posterior_mm,
                      help="posterior cut in front of the condyles (negative: behind)")
    cuts.add_argument("--inferior", type=positive_float, default=d.inferior_mm,
                      help="inferior cut below the menton, parallel to the mandibular plane")
    cuts.add_argument("--depth", type=positive_float, default=d.depth_mm,
                      help="largest depth of the tissue below the skin")
    cuts.add_argument("--occlusal-tilt", type=float, default=d.occlusal_tilt_deg, metavar="DEG",
                      help="the occlusal plane's inclination in the output frame, anterior end down")


def rules_from(args: argparse.Namespace):
    """The :class:`~toolkit.mesh.ct_anatomy.CTRules` of the command line."""
    from toolkit.mesh.ct_rules import CTRules

    return CTRules(skin=args.skin, bone=args.bone, teeth=args.teeth, axes=args.axes, lefort_mm=args.lefort,
                   split_mm=args.split, tuberosity_mm=args.tuberosity, occlusal_pitch_deg=args.occlusal_pitch,
                   occlusal_shift_mm=args.occlusal_shift, superior_mm=args.superior, posterior_mm=args.posterior,
                   inferior_mm=args.inferior, depth_mm=args.depth, occlusal_tilt_deg=args.occlusal_tilt)


def next_command(files: dict[str, Path]) -> str:
    """The ``toolkit mesh`` command that meshes the written surfaces."""
    from toolkit.mesh.ct import SEGMENT_NAMES

    bones = " ".join(f"--bone {name}={files[name]}" for name in SEGMENT_NAMES)
    return f"toolkit mesh --tissue {files['tissue']} {bones} --out {files['tissue'].parent / 'face.vtu'}"


def run(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir
    from toolkit.mesh.ct import ct_surfaces
    from toolkit.mesh.volume import read_volume

    check_output_dir(args.out)
    rules = rules_from(args)
    volume = read_volume(args.volume).check(skin=rules.skin, bone=rules.bone)
    print(f"read {args.volume}: {volume.shape[0]} x {volume.shape[1]} x {volume.shape[2]} voxels of "
          f"{' x '.join(f'{s:g}' for s in volume.spacing)} mm")
    surfaces = ct_surfaces(volume, rules)
    written = surfaces.write(args.out)
    print(surfaces.summary())
    print("wrote " + ", ".join(str(p) for p in written.values()))
    print(f"next: {next_command(written)}")
    return 0


COMMAND = Command(
    help="the face's surfaces from a head CT (soft tissue and osteotomy segments)",
    description="Segment a head CT (NRRD) into the soft tissue's closed surface and the bone surfaces of a virtual "
                "osteotomy (lefort, distal, proximal_left, proximal_right, skull), with the anatomical axes, "
                "landmarks and cutting planes found from the anatomy, for `toolkit mesh`. The rules and their "
                "reasons: docs/ct.md.",
    add_arguments=add_arguments,
    run=run,
    interrupted="the files written to {out} before the interruption are complete; rerun the same command",
)
