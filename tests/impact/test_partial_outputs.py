"""A failed or interrupted impact run leaves a readable partial result marked as such.

``summary.json`` says ``"status"``: ``"finished"``, ``"failed"`` (with the error and its reason)
or ``"interrupted"`` (Ctrl-C), with the last finished frame; the frames written so far open with
:func:`toolkit.common.meshes.io.read_time_series` and with meshio, also when the run stopped before its
first frame; ``history.h5`` holds the finished frames.
"""

import importlib
import json
import warnings

import meshio
import numpy as np
import pytest

from toolkit.common.meshes.io import TimeSeriesWriter, read_time_series
from toolkit.common.phantoms.phantom import face_tet
from toolkit.impact import BallSpec, FaceSpec, Scene, simulate
from toolkit.impact.explicit import InstabilityError

sim = importlib.import_module("toolkit.impact.simulate")  # the module (toolkit.impact.simulate is also the function)


def _fast(scene: Scene) -> Scene:
    return scene.with_fidelity(order=1, integrator="explicit", mass_scaling=100.0)


def _quick_scene(n_frames: int = 6) -> Scene:
    return _fast(Scene(face=FaceSpec(resolution="coarse"), ball=BallSpec(rigid=True, velocity=50.0), duration=0.3,
                       n_frames=n_frames))


def _meshio_frames(path) -> tuple[int, int]:
    """(points, frames) of an XDMF time series read by meshio."""
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, _ = reader.read_points_cells()
        for k in range(reader.num_steps):
            reader.read_data(k)
        return points.shape[0], reader.num_steps


def test_a_finished_run_says_finished(tmp_path):
    """A run that completes writes ``"status": "finished"`` with the usual summary keys."""
    simulate(_quick_scene(3), out=tmp_path, preview=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["velocity_mm_s"] == 50.0
    assert read_time_series(tmp_path / "face.xdmf").times.size == 3


def test_a_failed_run_leaves_its_frames_and_a_failed_summary(tmp_path):
    """Aimed at the nose tip with the lowest 10 % of the coarse face fixed, a 50 mm/s ball crushes the
    tissue against the fixed band and an element inverts at t ~ 1.66 s of 1.8 s: the run raises
    InstabilityError, and the folder holds summary.json (status failed, the error and its reason,
    the frames written of those planned, the last frame's time and the time it stopped at), the
    finished frames readable by read_time_series and meshio, and history.h5 of those frames."""
    import h5py

    scene = _fast(Scene(face=FaceSpec(resolution="coarse", lower_fixed_fraction=0.1),
                        ball=BallSpec(rigid=True, velocity=50.0, target_offset=(0.0, 0.0, 0.0)), duration=1.8,
                        n_frames=18))
    with warnings.catch_warnings(), pytest.raises(InstabilityError):
        warnings.simplefilter("ignore", sim.SceneGeometryWarning)
        simulate(scene, out=tmp_path, preview=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["error"] == "InstabilityError"
    assert "inverted" in summary["reason"]
    n = summary["frames_written"]
    assert 0 < n < summary["frames_planned"] == 18
    assert summary["last_frame_time_s"] < summary["stopped_at_time_s"] < 1.8
    series = read_time_series(tmp_path / "face.xdmf")
    assert series.times.size == n and series.times[-1] == pytest.approx(summary["last_frame_time_s"])
    assert np.isfinite(series.point_data["displacement"]).all()
    assert _meshio_frames(tmp_path / "face.xdmf") == (series.mesh.n_points, n)
    with h5py.File(tmp_path / "history.h5", "r") as h5:
        np.testing.assert_allclose(h5["time_s"][()], series.times)
    assert not (tmp_path / "preview.png").exists()


@pytest.mark.parametrize("after", [0, 2])
def test_an_interrupted_run_leaves_its_frames_and_an_interrupted_summary(tmp_path, monkeypatch, after):
    """A KeyboardInterrupt (Ctrl-C) after ``after`` frames of 6 propagates, and leaves summary.json
    with status interrupted and the frames written; the series opens with read_time_series and
    meshio with those frames, also with none (the index then holds the mesh alone)."""
    real = sim.run_explicit

    def interrupted(model, duration, n_frames, on_frame=None, progress=False):
        count = [0]

        def stop_after(frame, fields):
            if count[0] == after:
                raise KeyboardInterrupt
            on_frame(frame, fields)
            count[0] += 1

        if after == 0:
            raise KeyboardInterrupt
        return real(model, duration, n_frames, on_frame=stop_after, progress=progress)

    monkeypatch.setattr(sim, "run_explicit", interrupted)
    with pytest.raises(KeyboardInterrupt):
        simulate(_quick_scene(6), out=tmp_path, preview=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["frames_written"] == after
    assert summary["frames_planned"] == 6
    series = read_time_series(tmp_path / "face.xdmf")
    assert series.times.size == after
    assert (summary["last_frame_time_s"] is None) == (after == 0)
    assert _meshio_frames(tmp_path / "face.xdmf") == (series.mesh.n_points, after)
    assert (tmp_path / "history.h5").exists() == (after > 0)


def test_a_series_without_frames_opens_in_meshio(tmp_path):
    """A TimeSeriesWriter closed before its first frame leaves an XDMF that meshio and
    read_time_series open (the mesh, zero frames); after frames, both read every frame."""
    mesh = face_tet("coarse", order=1).without_fields()
    with TimeSeriesWriter(tmp_path / "face.xdmf", mesh) as w:
        assert _meshio_frames(tmp_path / "face.xdmf") == (mesh.n_points, 0)
        w.append(0.1, displacement=np.zeros((mesh.n_points, 3)))
    assert _meshio_frames(tmp_path / "face.xdmf") == (mesh.n_points, 1)
    assert read_time_series(tmp_path / "face.xdmf").times.tolist() == [0.1]
