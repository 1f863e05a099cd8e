"""The impact learning database (the impact paper): one explicit simulation per imposed ball velocity.

The impact paper ran six velocities between 20 and 50 mm/s and learned per-node displacement and
von Mises time series. :func:`build_database` runs a scene (by default
:func:`~toolkit.impact.scene.yielding_scene`, in which the face yields) at each velocity
of ``velocities`` and of ``held_out`` (velocities between them whose simulations a
held-out split keeps out of training), on local processes, in this process, or on a
Dask cluster, and stores, per simulation:

- ``time`` ``(F,)`` s, ``displacement`` ``(F, N, 3)`` mm, ``von_mises`` ``(F, N)`` MPa,
  ``equivalent_plastic_strain`` ``(F, N)``, ``plastic_volume_fraction`` ``(F,)``;
- attributes: velocity (mm/s), held-out flag, maxima, energy error, FE wall time and
  time per output frame;

and once (``/shared``): the face's reference points ``(N, 3)`` mm (the items' initial
positions), its cells, a ``fixed`` mask (nodes held by the scene) and ``skin``/``bone``
masks, and the scene itself as TOML. Items for learning are the node time series
(inputs per frame: initial position, imposed velocity, time, fixed flag). The file is the
resumable :class:`toolkit.common.training.database.Database` (tag ``toolkit.impact.database``):
finished simulations survive a crash (after a Ctrl-C or a failure the ``.h5`` alone holds
them all), failures are recorded with their reason, and a rerun with the same scene does
only what is missing; more velocities grow the database. :func:`load_database` warns
"interrupted database FILE: N of M simulations done" on an unfinished one.

Units: mm, s, MPa, mm/s.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit.common import papers
from toolkit.common.meshes.fingerprint import points_fingerprint
from toolkit.common.training.database import (
    Database,
    Job,
    Record,
    RunReport,
    check_complete,
    check_workers,
    read_index,
    run_jobs,
)
from toolkit.impact.scene import Scene, yielding_scene
from toolkit.impact.simulate import ball_start, check_travel, face_mesh, fixed_nodes, simulate

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

__all__ = ["DATABASE_KIND", "DATABASE_VERSION", "PAPER_VELOCITIES", "default_held_out", "build_database",
           "ImpactDatabase", "load_database", "SimulationWorker", "velocity_key", "SceneInputs"]

DATABASE_KIND = "toolkit.impact.database"
DATABASE_VERSION = 1
#: the impact paper's six imposed velocities, mm/s (evenly spaced over 20-50)
PAPER_VELOCITIES = papers.BALL_VELOCITIES


def default_held_out(velocities) -> list[float]:
    """Midpoints of every other gap of the sorted ``velocities`` (mm/s): for the impact paper's
    20, 26, ..., 50 these are 23, 35 and 47, one near each end and one in the middle."""
    v = sorted(float(x) for x in velocities)
    return [0.5 * (v[i] + v[i + 1]) for i in range(0, len(v) - 1, 2)]


def velocity_key(velocity: float) -> str:
    """The record key of a velocity: ``v20``, ``v23.5`` (mm/s)."""
    return f"v{float(velocity):g}"


def _scene_config(scene: Scene) -> dict:
    """What makes two databases comparable: the scene with the velocity left out."""
    d = scene.to_dict()
    d["ball"] = {k: v for k, v in d["ball"].items() if k != "velocity"}
    if d["face"]["units"] == "mm":  # the phantoms and mm files: the configuration of databases without units
        del d["face"]["units"]
    if d["face"]["axes"] == "toolkit":  # the phantoms and files in the toolkit's axes: databases without axes
        del d["face"]["axes"]
    return d


@dataclass(frozen=True)
class SimulationWorker:
    """Picklable worker: runs the base ``scene`` (as a dict) at ``params["velocity"]`` mm/s and
    returns the fields as a :class:`~toolkit.common.training.database.Record` (float32 fields)."""

    scene: dict

    def __call__(self, params: dict) -> Record:

        scene = Scene.from_dict(self.scene).with_ball(velocity=float(params["velocity"]))
        r = simulate(scene, preview=False)
        s = r.summary()
        arrays = {
            "time": r.times,
            "displacement": r.displacement.astype(np.float32),
            "von_mises": r.von_mises.astype(np.float32),
            "equivalent_plastic_strain": r.equivalent_plastic_strain.astype(np.float32),
            "plastic_volume_fraction": r.plastic_volume_fraction,
            "energy_error": r.energies["balance_error"].to_numpy(),
        }
        attrs = {k: s[k] for k in ("velocity_mm_s", "max_displacement_mm", "max_von_mises_mpa",
                                   "max_equivalent_plastic_strain", "plastic_volume_fraction", "energy_error",
                                   "max_energy_error", "wall_time_s", "steps", "max_penetration_mm")}
        attrs["velocity_mm_s"] = float(attrs["velocity_mm_s"])
        attrs["fe_ms_per_frame"] = 1000.0 * s["wall_time_s"] / len(r.times)
        attrs["held_out"] = bool(params.get("held_out", False))
        return Record(arrays, attrs)


def build_database(out: str | os.PathLike, velocities=PAPER_VELOCITIES, held_out=None, scene: Scene | None = None,
                   *, workers: int = 1, executor=None, retry_failed: bool = False, progress: bool = True) -> RunReport:
    """Simulate ``scene`` at every velocity and store the fields in the HDF5 file ``out``.

    Parameters
    ----------
    out : the ``.h5`` database (created, or extended when it exists with the same scene)
    velocities : training velocities, mm/s (default the impact paper's six)
    held_out : velocities simulated for the held-out split, mm/s; default
        :func:`default_held_out` of ``velocities``; ``[]`` for none
    scene : base scene (its velocity is replaced); default :func:`yielding_scene`
    workers : local processes (0: run in this process)
    executor : a ``concurrent.futures`` executor or a ``dask.distributed.Client`` instead
    retry_failed : rerun velocities recorded as failed

    Returns
    -------
    RunReport (done, failed with reasons, skipped)
    """

    check_workers(workers)
    scene = scene or yielding_scene()
    train_v = [float(v) for v in velocities]
    held = default_held_out(train_v) if held_out is None else [float(v) for v in held_out]
    everything = train_v + held
    for v in everything:
        scene.with_ball(velocity=v)  # validates the range and units
    if len(set(everything)) != len(everything):
        raise ValueError(f"velocities {train_v} and held-out {held} repeat a value")
    face = face_mesh(scene)  # a mesh file: its node sets and element order
    ball_start(scene, face.points[face.node_set("skin")])  # a ball that misses the face is refused here
    check_travel(scene.with_ball(velocity=max(everything)), face)  # the fastest ball travels farthest
    masks = {}
    for name in ("skin", "bone"):
        if name in face.node_sets:
            m = np.zeros(face.n_points, dtype=bool)
            m[face.node_set(name)] = True
            masks[name] = m
    fixed = np.zeros(face.n_points, dtype=bool)
    fixed[fixed_nodes(scene, face)] = True
    db = Database(out, DATABASE_KIND, DATABASE_VERSION, {"scene": _scene_config(scene)})
    jobs = [Job(velocity_key(v), {"velocity": v, "held_out": v in held}) for v in everything]
    with db.locked():  # another command filling the same file is refused before anything is written
        db.create(shared={"points": face.points, "cells": face.volume_cells, "fixed": fixed, **masks},
                  shared_attrs={"cell_type": face.volume_type, "scene_toml": _scene_toml(scene),
                                "mesh_checksum": points_fingerprint(face.points)})
        return run_jobs(db, jobs, SimulationWorker(scene.to_dict()), workers=workers, executor=executor,
                        retry_failed=retry_failed, progress=progress)


def _scene_toml(scene: Scene) -> str:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        return scene.write(Path(d) / "scene.toml").read_text()


@dataclass(frozen=True, eq=False)
class SceneInputs:
    """What a scene defines for its items, whatever the velocity.

    Attributes
    ----------
    points : (N, 3) float64 mm, the face's reference (initial) positions
    fixed : (N,) bool, nodes the scene holds
    times : (F,) s, output frames
    ball_centre0 : (3,) mm, the ball's centre at t = 0; ball_direction : (3,) unit vector of its
        motion; ball_radius : mm (the centre is ``ball_centre0 + velocity * t * ball_direction``)
    """

    points: np.ndarray
    fixed: np.ndarray
    times: np.ndarray
    ball_centre0: np.ndarray
    ball_direction: np.ndarray
    ball_radius: float

    @classmethod
    def from_scene(cls, scene: Scene, face, times) -> SceneInputs:
        """From a scene and its face Mesh (node set ``skin``) at the frame ``times`` (s)."""

        fixed = np.zeros(face.n_points, dtype=bool)
        fixed[fixed_nodes(scene, face)] = True
        centre0 = ball_start(scene, face.points[face.node_set("skin")])
        return cls(face.points, fixed, np.asarray(times, dtype=float), centre0,
                   np.asarray(scene.ball.direction, dtype=float), float(scene.ball.radius))


@dataclass(frozen=True, eq=False)
class ImpactDatabase:
    """A database loaded for learning (simulations sorted by velocity).

    Attributes
    ----------
    path : the file
    scene : the base Scene (velocity of the first simulation)
    points : (N, 3) float64 mm, initial positions; cells : (E, k) int64; cell_type : str
    fixed : (N,) bool, nodes held by the scene; skin : (N,) bool, the outer surface
    times : (F,) s, the output frames (shared by every simulation)
    velocities : (S,) mm/s; held_out : (S,) bool
    displacement : (S, F, N, 3) float32 mm; von_mises : (S, F, N) float32 MPa
    index : DataFrame, one row per simulation (attributes of the records)
    """

    path: Path
    scene: Scene
    points: np.ndarray
    cells: np.ndarray
    cell_type: str
    fixed: np.ndarray
    skin: np.ndarray
    times: np.ndarray
    velocities: np.ndarray
    held_out: np.ndarray
    displacement: np.ndarray
    von_mises: np.ndarray
    index: pd.DataFrame

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def inputs(self) -> SceneInputs:
        """The scene's per-item inputs (positions, fixed flags, frames, the ball's path)."""

        return SceneInputs(self.points, self.fixed, self.times, ball_start(self.scene, self.points[self.skin]),
                           np.asarray(self.scene.ball.direction, dtype=float), float(self.scene.ball.radius))

    def signature(self) -> dict:
        """What a model trained on this database depends on (checked when it is reused)."""
        return {"kind": DATABASE_KIND, "n_nodes": self.n_nodes, "mesh_checksum": points_fingerprint(self.points),
                "times_s": [round(float(t), 9) for t in self.times], "scene": _scene_config(self.scene)}


def load_database(path: str | os.PathLike) -> ImpactDatabase:
    """Read every finished simulation of an impact database (refuses other kinds of file)."""
    import h5py

    path = Path(path)
    Database.verified_attrs(path, DATABASE_KIND, DATABASE_VERSION, "build one with `toolkit impact database`")
    check_complete(path, "`toolkit impact database` with the same options")
    with h5py.File(path, "r") as f:
        shared = f["shared"]
        scene = Scene.from_dict(_tomllib_loads(shared.attrs["scene_toml"]))
        keys = list(f["records"].keys())
        if not keys:
            raise ValueError(f"{path} holds no finished simulation yet; run `toolkit impact database` to fill it")
        params = {k: json.loads(f["records"][k].attrs["params"]) for k in keys}
        keys.sort(key=lambda k: params[k]["velocity"])
        times = f["records"][keys[0]]["time"][()]
        for k in keys[1:]:
            t = f["records"][k]["time"][()]
            if t.shape != times.shape or not np.allclose(t, times, rtol=1e-9, atol=1e-12):
                raise ValueError(f"{path}: simulation {k} has other output times than {keys[0]}")
        disp = np.stack([f["records"][k]["displacement"][()] for k in keys])
        vm = np.stack([f["records"][k]["von_mises"][()] for k in keys])
        db = ImpactDatabase(
            path, scene.with_ball(velocity=params[keys[0]]["velocity"]), shared["points"][()],
            shared["cells"][()].astype(np.int64), _str(shared.attrs["cell_type"]), shared["fixed"][()].astype(bool),
            shared["skin"][()].astype(bool), times, np.array([params[k]["velocity"] for k in keys], dtype=float),
            np.array([bool(params[k].get("held_out", False)) for k in keys]), disp, vm, None)
    index = read_index(path).set_index("key").loc[keys].reset_index()
    object.__setattr__(db, "index", index)
    return db


def _str(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def _tomllib_loads(text) -> dict:
    import tomllib

    return tomllib.loads(_str(text))

