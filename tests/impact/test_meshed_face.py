"""``toolkit impact simulate --mesh``: the impact workflow on a face made by ``toolkit mesh`` (the
coarse phantom's surfaces at 12 mm, tet4), and the mesh files it refuses before writing anything."""

import json
from dataclasses import replace

import numpy as np
import pytest

from toolkit.cli import main
from toolkit.common import face_hex
from toolkit.common.meshes.io import read, write
from toolkit.impact import Scene
from toolkit.impact.scene import SceneError, meshed_scene
from toolkit.impact.simulate import build_model, face_mesh
from toolkit.mesh import DEFAULT
from toolkit.mesh.face import mesh_face
from toolkit.mesh.surface import tissue_surface_of

#: the quickest impact runs: explicit dynamics with mass scaling 100
EXPLICIT = ["--integrator", "explicit", "--mass-scaling", "100"]


@pytest.fixture(scope="module")
def meshed(tmp_path_factory):
    """A tet4 face from ``toolkit mesh``'s pipeline on the coarse phantom's surfaces, as a VTU file."""
    phantom = face_hex("coarse")
    bones = {k: s.surface for k, s in phantom.segments.items()}
    face = mesh_face(tissue_surface_of(phantom.mesh), bones, size_mm=12.0, order=1, backend=DEFAULT)
    path = tmp_path_factory.mktemp("meshed") / "face.vtu"
    write(path, face.mesh)
    return path


def _run(*argv):
    return main(["impact", "simulate", *map(str, argv)])


def test_simulate_runs_on_a_meshed_face(meshed, tmp_path, capsys):
    out = tmp_path / "run"
    code = _run("--mesh", meshed, "--integrator", "quasi-static", "--ball", "rigid", "--duration", "0.1",
                "--no-preview", "--out", out)
    assert code == 0, capsys.readouterr().err
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "finished" and s["element"] == "tet4"  # the mesh's order, --order not given
    assert s["fixed_clearance_mm"] > 0  # held by its bones: the ball's path clears them
    # the rigid ball travels 3 mm, 0.5 mm of it before the first touch: a node it pushes moves about
    # 2.5 mm, and a node beside the ball may move farther (the nearly incompressible tissue bulges
    # around it, and carries on by its inertia) but not past the ball's whole travel. fTetWild's
    # meshes are never the same twice: six meshings of this 12 mm face gave 2.44-2.74 mm
    assert 0.0 < s["max_displacement_mm"] <= 30.0 * 0.1


def test_target_aims_the_ball_at_a_skin_point(meshed):
    face = read(meshed)
    skin = face.points[face.node_set("skin")]
    target = skin[np.argmax(skin[:, 2])]  # the highest skin point: the ball's centre line passes through it
    scene = meshed_scene(meshed).with_ball(rigid=True, target=tuple(target), target_offset=(0.0, 0.0, 0.0))
    built = build_model(scene)
    rel = target - built.ball_centre
    d = np.asarray(scene.ball.direction)
    assert np.linalg.norm(rel - (rel @ d) * d) < 1e-9  # on the line through the target along the direction


@pytest.mark.parametrize("argv, expected", [
    (["--order", "2"], "holds tet4 (order 1) and the scene asks for order 2; pass --order 1"),
    (["--target", "0,0,1000"], "misses the face"),
    (["--support", "skull", "--mesh-without", "bone"], "lacks the node sets ['bone']"),
    (["--mesh-without", "skin"], "lacks the node sets ['skin']"),
    (["--missing"], "does not exist"),
])
def test_bad_meshes_and_aims_are_refused_before_output(meshed, tmp_path, capsys, argv, expected):
    mesh = meshed
    if "--mesh-without" in argv:
        i = argv.index("--mesh-without")
        face = read(meshed)
        mesh = tmp_path / "cut.vtu"
        write(mesh, replace(face, node_sets={k: v for k, v in face.node_sets.items() if k != argv[i + 1]}))
        argv = argv[:i] + argv[i + 2:]
    if "--missing" in argv:
        mesh, argv = tmp_path / "nowhere.vtu", []
    out = tmp_path / "run"
    assert _run("--mesh", mesh, "--integrator", "quasi-static", "--ball", "rigid", *argv, "--out", out) == 2
    assert expected in capsys.readouterr().err
    assert not out.exists()


def test_the_order_check_holds_in_python(meshed):
    with pytest.raises(SceneError, match="remesh with `toolkit mesh --order 2`"):
        face_mesh(Scene().with_face(mesh=str(meshed)))


def test_database_takes_the_mesh_and_refuses_a_missed_aim_before_the_database(meshed, tmp_path, capsys):
    db = tmp_path / "db.h5"
    argv = ["impact", "database", "--mesh", str(meshed), "--ball", "rigid", "--velocities", "20", "--held-out", "",
            "--duration", "0.05", *EXPLICIT, "--workers", "0", "--out", str(db)]
    assert main(argv + ["--target", "0,0,1000"]) == 2
    assert "misses the face" in capsys.readouterr().err and not db.exists()
    assert main(argv) == 0, capsys.readouterr().err


def test_an_answer_within_a_tolerance_on_a_meshed_face(meshed, tmp_path, capsys):
    """A database, model and calibration on the meshed face (velocities 20-40 mm/s to train, nine
    others to calibrate): `predict --tolerance` answers by the LSTM at a loose tolerance, with an
    error estimate per node and frame, and by the quasi-static FE of the meshed face at a tight one."""
    from toolkit.common.meshes.io import read_time_series

    scene = ["--mesh", str(meshed), "--ball", "rigid", "--duration", "0.05", *EXPLICIT,
             "--workers", "0"]
    train, cal, model = tmp_path / "train.h5", tmp_path / "cal.h5", tmp_path / "model"
    assert main(["impact", "database", *scene, "--velocities", "20,30,40", "--held-out", "", "--out", str(train)]) == 0
    assert main(["impact", "database", *scene, "--velocities", "21,23,25,27,29,32,34,36,38", "--held-out", "",
                 "--out", str(cal)]) == 0
    assert main(["impact", "train", "--data", str(train), "--out", str(model), "--config", "baseline",
                 "--epochs", "3"]) == 0
    assert main(["impact", "calibrate", "--model", str(model), "--data", str(cal), "--train-data", str(train)]) == 0
    capsys.readouterr()
    for tolerance, who in (("1000", "surrogate"), ("0.000001", "fe")):
        out = tmp_path / f"answer-{who}"
        assert main(["impact", "predict", "--model", str(model), "--velocity", "33", "--tolerance", tolerance,
                     "--no-preview", "--out", str(out)]) == 0, capsys.readouterr().err
        summary = json.loads((out / "summary.json").read_text())
        assert summary["answer"]["answered_by"] == who, summary["answer"]["reason"]
        assert summary["element"] == "tet4" and summary["velocity_mm_s"] == 33.0
    series = read_time_series(tmp_path / "answer-surrogate" / "face.xdmf")
    assert series.point_data["error_estimate"].shape == series.point_data["displacement"].shape[:2]
