"""``toolkit mesh`` from the command line: a run on the phantom's surfaces, and each bad input
refused before any meshing with the option to change."""

import json

import numpy as np
import pytest

from toolkit.cli import main
from toolkit.common import face_hex, read
from toolkit.mesh.phantom import phantom_surfaces, write_surfaces


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    return write_surfaces(tmp_path_factory.mktemp("surfaces"), phantom_surfaces(face_hex("coarse")))


def _args(files, out, *extra):
    bones = [f"--bone={name}={files[name]}" for name in ("lefort", "distal", "proximal_left", "proximal_right")]
    return ["mesh", "--tissue", str(files["tissue"]), *bones, "--out", str(out), *extra]


def test_mesh_command_writes_mesh_labels_and_image(files, tmp_path, capsys):
    out = tmp_path / "face.vtu"
    assert main(_args(files, out, "--size", "12", "--commissures", str(files["commissures"]))) == 0
    mesh = read(out)
    report = json.loads((tmp_path / "labels.json").read_text())
    assert mesh.volume_type == "tet10" and report["nodes"] == mesh.n_points
    assert report["mouth"]["duplicated_nodes"] > 0 and (tmp_path / "labels.png").stat().st_size > 10_000
    text = capsys.readouterr().out
    assert "min scaled Jacobian" in text and "wrote" in text


def test_commissures_given_inline_with_a_leading_minus(files, tmp_path):
    c = np.loadtxt(files["commissures"], delimiter=",")
    value = ":".join(",".join(f"{v:g}" for v in p) for p in c[::-1])  # the right corner (x < 0) first
    assert main(_args(files, tmp_path / "face.inp", "--size", "12", "--order", "1", "--no-preview",
                      f"--commissures={value}")) == 0
    assert read(tmp_path / "face.inp").node_sets["lip_sliding"].size > 0


@pytest.mark.parametrize("extra, match", [
    (["--size", "0.01"], "--size"),
    (["--commissures", "1,2:3,4,5"], "expected two points"),
    (["--rules", "missing.toml"], "missing.toml"),
])
def test_bad_options_are_refused_with_the_option(files, tmp_path, capsys, extra, match):
    code = main(_args(files, tmp_path / "face.vtu", *extra)) if "--commissures" not in extra else None
    if code is None:
        with pytest.raises(SystemExit):
            main(_args(files, tmp_path / "face.vtu", *extra))
    else:
        assert code == 2
    assert match in capsys.readouterr().err
    assert not (tmp_path / "face.vtu").exists()


def test_bad_files_are_refused_before_meshing(files, tmp_path, capsys):
    assert main(_args(files, tmp_path / "face.stl")) == 2
    assert ".vtu or .inp" in capsys.readouterr().err
    args = _args(files, tmp_path / "face.vtu")
    args[args.index("--tissue") + 1] = str(tmp_path / "nothing.stl")
    assert main(args) == 2 and "nothing.stl" in capsys.readouterr().err
    assert main(_args(files, tmp_path / "face.vtu", "--units", "m")) == 2
    assert "--units" in capsys.readouterr().err
    assert not (tmp_path / "face.vtu").exists()


@pytest.fixture(scope="module")
def lps_files(tmp_path_factory):
    """The coarse phantom's surfaces and commissures as DICOM/ITK-SNAP write them (LPS: y posterior)."""
    from toolkit.common.meshes.axes import mesh_to_toolkit, to_toolkit
    from toolkit.mesh.phantom import PhantomSurfaces

    s = phantom_surfaces(face_hex("coarse"))
    lps = PhantomSurfaces(mesh_to_toolkit(s.tissue, "LPS"), {k: mesh_to_toolkit(v, "LPS") for k, v in s.bones.items()},
                          to_toolkit(s.commissures, "LPS"))
    return write_surfaces(tmp_path_factory.mktemp("lps"), lps)


def test_surfaces_in_lps_are_refused_and_meshed_with_axes_lps(lps_files, tmp_path, capsys):
    """Without --axes the y-mirrored surfaces are refused before any meshing, naming the file, what
    the anatomy says and --axes LPS; with it the face is meshed and labelled as the phantom is."""
    out = tmp_path / "face.vtu"
    args = _args(lps_files, out, "--size", "10", "--order", "1", "--no-preview", "--commissures",
                 str(lps_files["commissures"]))
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "tissue.stl with its bones" in err and "not in the toolkit's axes" in err and "--axes LPS" in err
    assert not out.exists()
    assert main([*args, "--axes", "LPS"]) == 0
    mesh = read(out)
    assert mesh.node_sets["maxilla"].size > 0 and mesh.node_sets["mandible"].size > 0
    assert mesh.node_sets["lip_sliding"].size > 0
    assert json.loads((tmp_path / "labels.json").read_text())["axes"] == "LPS"
    assert mesh.points[mesh.node_sets["maxilla"], 1].mean() > 30.0  # anterior: y > 0 in the toolkit's axes
