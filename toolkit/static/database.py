"""The static surrogate's learning database (the PointNet++ paper): FE simulations of sampled plans.

Each *simulation* runs one plan of :func:`~toolkit.static.plan.sample_plans` on one
*subject* (a face phantom: subject 0 is the default :class:`~toolkit.common.phantoms.phantom.FaceShape`,
subject k > 0 is ``FaceShape.sample(k)``; or the one subject of a database on a meshed face,
``DatabaseConfig.for_mesh``, whose plans are placed by :func:`~toolkit.static.anatomy.face_anatomy`),
and each of its increments is one learning *sample*, as in the PointNet++ paper:

- the starting mesh ``x (n, 3)`` mm: the face at the start of the increment;
- the boundary types ``(n,)`` (``free=0, moving=1, fixed=2, mucosa_sliding=3, lip_sliding=4``);
- the prescribed displacement ``s (n, 3)`` mm of the increment: what the bone gives the
  moving nodes, zero elsewhere; ``bone (n, 3)`` also has, for the mucosa nodes, what their
  bone's rigid motion in this increment would do at their place (they slide on it instead);
- the FE displacement ``v (n, 3)`` mm of the increment (the target).

Storage (one HDF5 file through :mod:`toolkit.common.training.database`: crash-safe shards, resume,
failures recorded with their reason, a configuration check that refuses a foreign file):
``/shared/subject_<k>/`` holds each subject's pre-operative points, boundary types and
bone-segment ids (``/shared/cells/<type>`` and ``/shared/sets/<name>`` the topology and
node sets, common to all subjects; a meshed face's database also keeps every node set,
``/shared/element_sets/<name>`` and ``/shared/cell_data/<name>``, so that
:meth:`StaticDatabase.subject_mesh` rebuilds the mesh without its file); ``/records/<key>/``
each simulation's cumulative displacement ``displacements (increments + 1, n, 3)`` and the increments' bone
displacements ``bone (increments, n, 3)`` (float32, mm), and its own boundary types and segment ids
``types``, ``segment`` ``(n,)`` (int8): a plan that needed a wider release band or freed nodes of the
truncation cut (:func:`~toolkit.static.simulate.simulate`'s retries) has its own; ``/index`` one row per
simulation and ``/samples`` one row per increment (subject, plan, increment, plan
parameters, largest input displacement, solver diagnostics), both read as DataFrames with
``str`` strings by :func:`toolkit.common.training.database.read_index` (``read_index(path, "samples")``;
:func:`read_samples` also rebuilds ``/samples`` of an interrupted run from its records).

Generation runs on any ``concurrent.futures``-style executor (local processes by default,
a ``dask.distributed.Client`` for a cluster); CLI ``toolkit static database``.

Resuming and growing: rerunning :func:`build_database` on an existing file skips the finished
simulations; after an interrupt the file already holds every finished one (and its
``/samples``), and :meth:`StaticDatabase.open` warns "interrupted database FILE: N of M
simulations done". A larger ``plans`` grows the database: plan ``p`` of subject ``k`` depends
only on ``seed``, ``k`` and ``p``, so 30 then 32 plans hold the same 32 simulations as 32 at
once; likewise a larger ``subjects`` adds subjects (subject ``k`` draws from ``[seed, k]``).
The stored configuration records the largest numbers asked; the other settings must match
the file's.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit.common.defaults import STATIC_SIMULATION
from toolkit.common.fem.materials import LinearElastic, NeoHookean, TransverselyIsotropic
from toolkit.common.meshes.axes import axes_matrix, check_mesh_axes, mesh_to_toolkit, to_toolkit
from toolkit.common.meshes.fingerprint import file_fingerprint
from toolkit.common.meshes.io import atomic_path, read
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.surfaces import read_surface
from toolkit.common.papers import TISSUE_NU
from toolkit.common.phantoms.phantom import FACE_RESOLUTIONS, FaceShape, face_hex
from toolkit.common.training.database import (
    Database,
    Job,
    Record,
    RunReport,
    check_complete,
    check_workers,
    deferred_interrupt,
    read_index,
    run_jobs,
)
from toolkit.static.anatomy import face_anatomy
from toolkit.static.plan import MAX_JAW_CLOSING_MM, SAMPLING_MODES, SurgicalPlan, dental_arch, jaw_closing, sample_plans
from toolkit.static.simulate import (
    MATERIALS,
    SLIDING_MODELS,
    SimulationOptions,
    boundary_conditions,
    material_assignment,
    simulate,
)
from toolkit.static.stiffness import MaterialAssignment

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

__all__ = ["DatabaseConfig", "build_database", "load_database", "StaticDatabase", "read_samples", "subject_phantom",
           "database_subject",
           "subject_mesh", "bone_increment", "plan_features",
           "jaw_side", "material_for", "simulate_job",
           "DATABASE_KIND", "DATABASE_VERSION", "PLAN_FEATURES"]

DATABASE_KIND = "toolkit.static.database"
DATABASE_VERSION = 1
#: per-sample plan parameters (the increment's target position of each segment): pivot
#: translation (mm) and rotation vector (deg) of the Le Fort I and distal segments, and the
#: fraction of the plan reached
PLAN_FEATURES = ("lefort_tx", "lefort_ty", "lefort_tz", "lefort_rx", "lefort_ry", "lefort_rz",
                 "distal_tx", "distal_ty", "distal_tz", "distal_rx", "distal_ry", "distal_rz", "fraction")


@dataclass(frozen=True)
class DatabaseConfig:
    """What a database holds.

    Attributes
    ----------
    resolution : phantom resolution (``coarse``, ``paper``, ``fine``); None for a meshed face
    subjects : number of phantom subjects (0 = default shape, k = ``FaceShape.sample(k)``); 1
        for a meshed face
    plans : plans per subject
    mode : ``sagittal`` or ``full`` (:func:`~toolkit.static.plan.sample_plans`)
    increments : increments per simulation (the lip-sliding paper: 3); each is a sample
    material : ``linear`` or ``neo-hookean``
    sliding : ``mucosa+lip``, ``mucosa`` or ``none``
    seed : plan sampling seed (subject k draws from ``[seed, k]``)
    max_jaw_closing_mm : the sampler's bound (None: none)
    poisson_range : (lo, hi) — each simulation draws Poisson's ratio uniformly in it (the
        same for the whole face and the lip muscle; the lip-sliding paper's 0.47 when None), for models
        with material channels. A displacement-driven linear problem does not depend on E.
    mesh : absolute path of a meshed face (``.vtu``/``.inp``/``.xdmf``, e.g. from ``toolkit mesh``)
        to simulate instead of the phantoms, or None; ``mesh_sha1`` its content hash (a resumed
        database refuses a changed file)
    bones : ``((segment, absolute path, sha1), ...)`` bone surfaces replacing the mesh's own
        bone-side faces (:func:`~toolkit.static.anatomy.face_anatomy`)
    condyles : ``((x, y, z), (x, y, z))`` mm, left then right, instead of the anatomy's rule
    units : length unit of the mesh and bone files
    axes : axes of the mesh and bone files and of ``condyles`` (:data:`toolkit.common.meshes.axes.AXES`),
        converted to the toolkit's on reading
    """

    resolution: str | None = STATIC_SIMULATION["resolution"]
    subjects: int = 1
    plans: int = 10
    mode: str = "sagittal"
    increments: int = 3
    material: str = "linear"
    sliding: str = "mucosa+lip"
    seed: int = 0
    max_jaw_closing_mm: float | None = MAX_JAW_CLOSING_MM
    poisson_range: tuple[float, float] | None = None
    mesh: str | None = None
    mesh_sha1: str | None = None
    bones: tuple = ()
    condyles: tuple | None = None
    units: str = "mm"
    axes: str = "toolkit"

    def __post_init__(self):

        axes_matrix(self.axes)
        object.__setattr__(self, "bones", tuple(tuple(b) for b in self.bones))  # hashable, also from JSON lists
        if self.condyles is not None:
            object.__setattr__(self, "condyles", tuple(tuple(float(v) for v in c) for c in self.condyles))
        if self.mesh is not None:
            if self.subjects != 1:
                raise ValueError(f"subjects = {self.subjects!r} with mesh {self.mesh!r}; a database on a meshed "
                                 "face has one subject (command line: leave out --subjects)")
            object.__setattr__(self, "resolution", None)
        elif self.resolution not in FACE_RESOLUTIONS:
            raise ValueError(f"resolution = {self.resolution!r}; expected one of {list(FACE_RESOLUTIONS)}")
        for name, lo in (("subjects", 1), ("plans", 1), ("increments", 1)):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < lo:
                raise ValueError(f"{name} = {getattr(self, name)!r}; expected an integer >= {lo}")
        if self.mode not in SAMPLING_MODES:
            raise ValueError(f"mode = {self.mode!r}; expected one of {SAMPLING_MODES}")
        if self.material not in MATERIALS:
            raise ValueError(f"material = {self.material!r}; expected one of {MATERIALS}")
        if self.sliding not in SLIDING_MODELS:
            raise ValueError(f"sliding = {self.sliding!r}; expected one of {SLIDING_MODELS}")
        if self.poisson_range is not None:
            lo, hi = (float(v) for v in self.poisson_range)
            if not 0.0 <= lo <= hi < 0.5:
                raise ValueError(f"poisson_range = {self.poisson_range!r}; expected 0 <= lo <= hi < 0.5")
            object.__setattr__(self, "poisson_range", (lo, hi))

    def to_dict(self) -> dict:
        """The attributes; ``axes`` only when not ``toolkit`` (the configuration of databases
        without the key)."""
        d = asdict(self)
        if d["axes"] == "toolkit":
            del d["axes"]
        return d

    @classmethod
    def for_mesh(cls, mesh: str | os.PathLike, bones=None, condyles=None, units: str = "mm",
                 axes: str = "toolkit", **settings) -> DatabaseConfig:
        """A database on a meshed face: ``mesh`` and ``bones`` (segment -> surface file) are
        recorded by absolute path and content hash; ``settings`` are the other attributes."""
        bones = dict(bones or {})
        for what, path in (("mesh", mesh), *((f"bone {k}", v) for k, v in bones.items())):
            if not Path(path).is_file():
                raise FileNotFoundError(f"{what} file {str(path)!r} does not exist")
        return cls(**settings, mesh=str(Path(mesh).resolve()), mesh_sha1=file_fingerprint(mesh), units=units, axes=axes,
                   bones=tuple(sorted((k, str(Path(v).resolve()), file_fingerprint(v)) for k, v in bones.items())),
                   condyles=None if condyles is None else tuple(map(tuple, np.asarray(condyles, float).tolist())))


@lru_cache(maxsize=8)
def subject_phantom(resolution: str, subject: int):
    """The face phantom of ``subject`` (0: the default shape; k: ``FaceShape.sample(k)``)."""

    return face_hex(resolution, FaceShape() if subject == 0 else FaceShape.sample(int(subject)))


@lru_cache(maxsize=4)
def database_subject(config: DatabaseConfig, subject: int):
    """What the database's ``subject`` is simulated on: the phantom of :func:`subject_phantom`,
    or the meshed face's :class:`~toolkit.static.anatomy.FaceAnatomy` (both have ``mesh`` and
    ``segments``)."""
    if config.mesh is None:
        assert config.resolution is not None  # a phantom database has one (DatabaseConfig checks it)
        return subject_phantom(config.resolution, subject)

    for path, sha1 in ((config.mesh, config.mesh_sha1), *((p, h) for _, p, h in config.bones)):
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path} (a file of the database's configuration) does not exist; restore it "
                                    "or start a new database")
        if file_fingerprint(path) != sha1:
            raise ValueError(f"{path} changed since the database was made on it; restore it or start a new database")
    mesh = mesh_to_toolkit(read(config.mesh, units=config.units, require_node_sets=["fixed"]), config.axes)
    bones = {name: mesh_to_toolkit(read_surface(path, units=config.units), config.axes)
             for name, path, _ in config.bones}
    check_mesh_axes(mesh, bones, axes=config.axes, source=Path(config.mesh).name)
    condyles = None if config.condyles is None else to_toolkit(config.condyles, config.axes)
    return face_anatomy(mesh, bones, condyles=condyles)


def _boundary(phantom, sliding: str):
    """The boundary conditions a simulation of ``phantom`` uses (release bands, sliding model)."""

    return boundary_conditions(phantom.mesh, phantom.segments, sliding)[0]


def plan_features(plan, increments: int) -> np.ndarray:
    """Per-increment plan parameters ``(increments, 13)`` (see :data:`PLAN_FEATURES`)."""
    rows = []
    for k, p in enumerate(plan.increments(increments), start=1):
        row = []
        for name in ("lefort", "distal"):
            m = p.motion(name)
            row += list(m.translation) + list(m.rotation_vector_deg)
        rows.append(row + [k / increments])
    return np.array(rows)


def _jobs(config: DatabaseConfig) -> list[Job]:

    jobs = []
    for subject in range(config.subjects):
        phantom = database_subject(config, subject)
        plans = sample_plans(config.plans, np.random.default_rng([config.seed, subject]), config.mode,
                             phantom=phantom, max_jaw_closing_mm=config.max_jaw_closing_mm)
        nu_rng = np.random.default_rng([config.seed, subject, 1])
        for p, plan in enumerate(plans):
            nu = float(nu_rng.uniform(*config.poisson_range)) if config.poisson_range else None
            jobs.append(Job(f"s{subject:03d}-p{p:05d}", {"subject": subject, "plan": p, "config": config.to_dict(),
                                                          "motions": plan.to_dict(), "poisson": nu}))
    return jobs


def material_for(material: str, poisson: float | None, mesh):
    """The lip-sliding paper's material assignment, with Poisson's ratio ``poisson`` if given."""

    if poisson is None:
        return material
    if material == "neo-hookean":
        return MaterialAssignment(NeoHookean(nu=poisson))
    base = material_assignment("linear", mesh)
    regions = {name: TransverselyIsotropic(nu=poisson) for name in (base.regions or {})}
    return MaterialAssignment(LinearElastic(nu=poisson), regions)


def simulate_job(params: dict) -> Record:
    """Worker: run one simulation of the database (picklable, module level)."""

    cfg = DatabaseConfig(**params["config"])
    phantom = database_subject(cfg, int(params["subject"]))
    face = phantom if cfg.mesh is None else phantom.mesh
    motions = {k: v for k, v in params["motions"].items() if k != "force"}
    plan = SurgicalPlan.from_dict(motions)
    t0 = time.perf_counter()
    # the simulation's own retries (a wider release band, freed nodes of the truncation cut, freed
    # mucosa around a folding element) are allowed: the record keeps the boundary types the plan
    # ended with
    result = simulate(face, plan, cfg.increments, material_for(cfg.material, params.get("poisson"), phantom.mesh),
                      cfg.sliding, segments=phantom.segments, options=SimulationOptions())
    seconds = time.perf_counter() - t0
    U = result.displacements
    bc = result.boundary
    X = phantom.mesh.points
    # what following its bone would do to each bone-driven node in each increment: the
    # increment's rigid motion of the bone (M_k after M_{k-1}^-1) at the node's current place
    bone = np.zeros((cfg.increments, X.shape[0], 3))
    previous = None
    for k, p in enumerate(plan.increments(cfg.increments)):
        bone[k] = bone_increment(X + U[k], bc, p, previous)
        previous = p
    moving = bc.types == 1
    s = summary = result.summary()
    attrs = {"seconds": seconds, "min_scaled_jacobian": summary["min_scaled_jacobian"],
             "substeps": summary["substeps"], "regulated_nodes": summary["regulated_nodes"],
             "max_displacement_mm": summary["max_displacement_mm"], "max_penetration_mm": s["max_penetration_mm"],
             "jaw_closing_mm": jaw_closing(plan, dental_arch(phantom)),
             "poisson": TISSUE_NU if params.get("poisson") is None else float(params["poisson"]),
             "max_input_displacement_mm": float(np.linalg.norm(bone[:, moving], axis=-1).max(initial=0.0))}
    assert result.release_width is not None  # simulate() reports the release band it used
    attrs["release_width_mm"] = float(result.release_width)
    attrs["freed_cut_nodes"] = int(np.size(result.freed_cut))
    attrs["freed_mucosa_nodes"] = int(np.size(result.freed_mucosa))
    return Record({"displacements": U.astype(np.float32), "bone": bone.astype(np.float32),
                   "types": bc.types.astype(np.int8), "segment": bc.segment.astype(np.int8),
                   "seconds_per_increment": np.array(summary["seconds_per_increment"]),
                   "features": plan_features(plan, cfg.increments)}, attrs)


def bone_increment(x: np.ndarray, bc, step, previous=None) -> np.ndarray:
    """What following its bone does to each bone-driven node in one increment, ``(n, 3)`` mm:
    the rigid motion of the node's segment from plan increment ``previous`` (None: the start) to
    ``step``, at the node's current place ``x (n, 3)`` mm; zero for the nodes on no bone
    (``bc.segment < 0``)."""
    out = np.zeros_like(x)
    driven = np.flatnonzero(bc.segment >= 0)
    for s, name in enumerate(bc.segment_names):
        ids = driven[bc.segment[driven] == s]
        motion = step.motion(name) if previous is None else step.motion(name).after(previous.motion(name).inverted())
        out[ids] = motion.apply(x[ids]) - x[ids]
    return out


def _shared(config: DatabaseConfig, first_subject: int = 0) -> dict:
    """Arrays common to the database: topology, node sets, each subject's points and types
    (only the subjects from ``first_subject`` on, without topology and sets, when > 0)."""
    out = {}
    first = database_subject(config, 0)
    if first_subject == 0:
        for ctype, cells in first.mesh.cells.items():
            out[f"cells/{ctype}"] = cells
        kept = first.mesh.node_sets if config.mesh is not None else \
            ("skin", "lip_sliding", "upper_lip_face", "lower_lip_face", "mucosa_sliding", "bone")
        for name in kept:
            if name in first.mesh.node_sets:
                out[f"sets/{name}"] = first.mesh.node_sets[name]
        if config.mesh is not None:
            out.update({f"element_sets/{k}": v for k, v in first.mesh.element_sets.items()})
            out.update({f"cell_data/{k}": v for k, v in first.mesh.cell_data.items()})
    for subject in range(first_subject, config.subjects):
        ph = database_subject(config, subject)
        bc = _boundary(ph, config.sliding)
        out[f"subject_{subject:03d}/points"] = ph.mesh.points
        out[f"subject_{subject:03d}/types"] = bc.types
        out[f"subject_{subject:03d}/segment"] = bc.segment
        out[f"subject_{subject:03d}/shape"] = np.array([getattr(ph.shape, f) for f in _SHAPE_FIELDS]) \
            if config.mesh is None else np.full(len(_SHAPE_FIELDS), np.nan)
    return out


def subject_mesh(path: str | os.PathLike, subject: int = 0):
    """The pre-operative Mesh of a database's ``subject`` (mm), read from the file's ``/shared``
    for a meshed face (with its sets and cell data) or rebuilt for a phantom."""
    import h5py


    config = DatabaseConfig(**json.loads(Database.open_attrs(Path(path)).get("config", "{}")))
    if config.mesh is None:
        assert config.resolution is not None  # a phantom database has one (DatabaseConfig checks it)
        return subject_phantom(config.resolution, subject).mesh
    with h5py.File(path, "r") as f:
        sh = f["shared"]
        group = {name: {k: v[()] for k, v in sh[name].items()} if name in sh else {}
                 for name in ("cells", "sets", "element_sets", "cell_data")}
        points = sh[f"subject_{subject:03d}"]["points"][()]
    return Mesh(points, group["cells"], node_sets=group["sets"], element_sets=group["element_sets"],
                cell_data=group["cell_data"])


def _add_subjects(path: Path, config: DatabaseConfig, first_subject: int) -> None:
    """Add the shared arrays of subjects ``first_subject`` .. ``config.subjects - 1`` (copy-on-write)."""
    import shutil

    import h5py


    arrays = _shared(config, first_subject)
    with atomic_path(path) as tmp:
        shutil.copyfile(path, tmp)
        with h5py.File(tmp, "a") as f:
            for name, arr in arrays.items():
                f["shared"].create_dataset(name, data=np.asarray(arr))


_SHAPE_FIELDS = ("face_width", "face_height", "tissue_thickness", "lip_protrusion", "mouth_open", "nose_height")


def build_database(path: str | os.PathLike, config: DatabaseConfig, *, executor=None, workers: int = 1,
                   retry_failed: bool = False, progress: bool = True) -> RunReport:
    """Create or complete the database at ``path`` (resumes: finished simulations are skipped).

    Parameters
    ----------
    path : ``.h5`` file
    config : DatabaseConfig (an existing file made with another configuration is refused)
    executor : ``concurrent.futures`` executor or ``dask.distributed.Client``; default a pool of
        ``workers`` local processes (``workers=0``: in this process)
    retry_failed : rerun simulations recorded as failed

    Returns
    -------
    RunReport (``done``, ``failed`` with reasons, ``skipped``, ``seconds``)
    """
    check_workers(workers)
    stored = dict(config.to_dict())
    with Database(path, DATABASE_KIND, DATABASE_VERSION, stored).locked():
        return _generate(Path(path), config, stored, executor, workers, retry_failed, progress)


def _generate(path: Path, config: DatabaseConfig, stored: dict, executor, workers, retry_failed, progress) -> RunReport:
    if Path(path).exists():
        Database(path, DATABASE_KIND, DATABASE_VERSION, stored, grows=_GROWS).check()
        before = json.loads(Database.open_attrs(Path(path)).get("config", "{}"))
        for name in _GROWS:
            stored[name] = max(int(before.get(name, 0)), getattr(config, name))
        if config.subjects > int(before.get("subjects", 0)):
            _add_subjects(Path(path), config, int(before.get("subjects", 0)))
    db = Database(path, DATABASE_KIND, DATABASE_VERSION, stored, grows=_GROWS)
    if not Path(path).exists():
        db.create(_shared(config))
    try:
        report = run_jobs(db, _jobs(config), simulate_job, executor=executor, workers=workers,
                          retry_failed=retry_failed, progress=progress)
    finally:  # also after a Ctrl-C or a failure: the finished simulations are usable at once
        with deferred_interrupt():
            _write_samples(Path(path))
    return report


#: configuration keys a static database grows along (more plans and subjects from the same random streams)
_GROWS = ("plans", "subjects")
_REMEDY = "`toolkit static database` with the same options"


def _write_samples(path: Path) -> None:
    """(Re)write ``/samples`` (one row per increment) copy-on-write, like the database merges."""
    import shutil

    import h5py
    import pandas as pd


    table = _sample_table(path)
    with atomic_path(path) as tmp:
        shutil.copyfile(path, tmp)
        with h5py.File(tmp, "a") as f:
            if "samples" in f:
                del f["samples"]
            rec = table.to_records(index=False)
            dtype = [(n, h5py.string_dtype() if rec.dtype[n].kind in "OU" else rec.dtype[n]) for n in rec.dtype.names]
            f.create_dataset("samples", data=np.array([tuple(r) for r in rec], dtype=dtype))
    del pd


def _sample_table(path: Path):
    import h5py
    import pandas as pd

    rows = []
    with h5py.File(path, "r") as f:
        for key, g in f["records"].items():
            params = json.loads(g.attrs["params"])
            attrs = json.loads(g.attrs["attrs"])
            feats = g["features"][()]
            secs = g["seconds_per_increment"][()]
            types = g["types"] if "types" in g else f["shared"][f"subject_{params['subject']:03d}"]["types"]
            moving = types[()] == 1
            bone = g["bone"][()][:, moving]
            for k in range(feats.shape[0]):
                row = {"key": key, "subject": params["subject"], "plan": params["plan"], "increment": k + 1,
                       "status": "ok", "seconds": float(secs[k]),
                       "max_input_displacement_mm": float(np.linalg.norm(bone[k], axis=-1).max(initial=0.0)),
                       "min_scaled_jacobian": attrs["min_scaled_jacobian"], "substeps": attrs["substeps"],
                       "jaw_closing_mm": attrs["jaw_closing_mm"], "poisson": attrs["poisson"]}
                row.update(dict(zip(PLAN_FEATURES, feats[k].tolist())))
                rows.append(row)
        for key, g in f["failures"].items():
            params = json.loads(g.attrs["params"])
            reason = g.attrs["reason"]
            rows.append({"key": key, "subject": params["subject"], "plan": params["plan"], "increment": 0,
                         "status": "failed: " + (reason.decode() if isinstance(reason, bytes) else str(reason))[:200]})
    columns = ["key", "subject", "plan", "increment", "status", "seconds", "max_input_displacement_mm",
               "min_scaled_jacobian", "substeps", "jaw_closing_mm", "poisson", *PLAN_FEATURES]
    return pd.DataFrame(rows, columns=columns).sort_values(["subject", "plan", "increment"]).reset_index(drop=True)


#: segment ids of the phantoms' segments on the upper (+1) and lower (-1) jaw
_UPPER, _LOWER = ("lefort",), ("distal", "proximal_left", "proximal_right")


def jaw_side(segment: np.ndarray, sets: dict, n: int, names=("lefort", "distal", "proximal_left",
                                                              "proximal_right", "skull")) -> np.ndarray:
    """+1 for the upper lip face and the nodes on the Le Fort I segment, -1 for the lower lip
    face and the mandible's nodes, 0 elsewhere ``(n,)``; ``names`` orders the segment ids."""
    side = np.zeros(n)
    seg = np.asarray(segment)
    for k, name in enumerate(names):
        side[seg == k] = 1.0 if name in _UPPER else (-1.0 if name in _LOWER else 0.0)
    if "upper_lip_face" in sets:
        side[sets["upper_lip_face"]] = 1.0
    if "lower_lip_face" in sets:
        side[sets["lower_lip_face"]] = -1.0
    return side


def read_samples(path: str | os.PathLike):
    """The per-increment table ``/samples`` of a database as a DataFrame (strings decoded)."""
    import h5py

    Database.open_attrs(Path(path))
    with h5py.File(path, "r") as f:
        if "records" not in f:
            raise ValueError(f"{path} has no /records group: it is not a static database; "
                             f"create one with `toolkit static database`")
        stored = set(f["records"].keys()) | set(f["failures"].keys())
        has_samples = "samples" in f
    table = read_index(path, "samples") if has_samples else None
    if table is None or set(table["key"]) != stored:
        # interrupted before /samples was (re)written: the records are the truth
        return _sample_table(Path(path))
    return table


def load_database(path: str | os.PathLike) -> StaticDatabase:
    """The finished database at ``path`` in memory (:meth:`StaticDatabase.open`; the impact
    workflow's :func:`toolkit.impact.load_database` alike)."""
    return StaticDatabase.open(path)


@dataclass(eq=False)
class StaticDatabase:
    """A finished static database in memory, sample by sample.

    Attributes
    ----------
    path : the file
    config : DatabaseConfig it was made with
    samples : DataFrame, one row per successful increment (:func:`read_samples`)
    points : subject -> (n, 3) pre-operative points, mm
    types : subject -> (n,) boundary types (a simulation that needed a wider release band or freed
        cut nodes has its own: :meth:`simulation_types`); segment : subject -> (n,) bone segment or -1
    side : subject -> (n,) +1 upper jaw/lip, -1 lower, 0 elsewhere
    cells : cell type -> connectivity; sets : node set name -> ids
    """

    path: Path
    config: DatabaseConfig
    samples: pd.DataFrame
    points: dict
    types: dict
    segment: dict
    side: dict
    cells: dict
    sets: dict
    _U: dict = field(default_factory=dict, repr=False)
    _bone: dict = field(default_factory=dict, repr=False)
    _types: dict = field(default_factory=dict, repr=False)  # key -> (n,) the simulation's own boundary types
    _motions: dict = field(default_factory=dict, repr=False)  # key -> plan dict, drawn on first use

    @classmethod
    def open(cls, path: str | os.PathLike) -> StaticDatabase:
        """Read a database written by :func:`build_database` (refuses other files, naming what is wrong)."""
        import h5py

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"database {str(path)!r} does not exist; create it with `toolkit static database`")
        attrs = Database.verified_attrs(path, DATABASE_KIND, DATABASE_VERSION,
                                        "create one with `toolkit static database`")
        config = DatabaseConfig(**json.loads(attrs["config"]))
        check_complete(path, _REMEDY)
        samples = read_samples(path)
        samples = samples[samples.status == "ok"].reset_index(drop=True)
        points, types, segment, cells, sets, U, bone = {}, {}, {}, {}, {}, {}, {}
        with h5py.File(path, "r") as f:
            sh = f["shared"]
            for name in sh["cells"]:
                cells[name] = sh["cells"][name][()]
            for name in sh["sets"]:
                sets[name] = sh["sets"][name][()]
            for s in range(config.subjects):
                g = sh[f"subject_{s:03d}"]
                points[s], types[s], segment[s] = g["points"][()], g["types"][()], g["segment"][()]
            own = {}
            for key in samples.key.unique():
                g = f["records"][key]
                U[key] = g["displacements"][()].astype(np.float64)
                bone[key] = g["bone"][()].astype(np.float64)
                if "types" in g:
                    own[key] = g["types"][()].astype(np.int64)
        side = {s: jaw_side(segment[s], sets, points[s].shape[0]) for s in points}
        return cls(path, config, samples, points, types, segment, side, cells, sets, U, bone, own)

    def __len__(self) -> int:
        return len(self.samples)

    def subject_mesh(self, subject: int):
        """The pre-operative Mesh of ``subject`` (:func:`subject_mesh`)."""
        return subject_mesh(self.path, subject)

    def sample(self, i: int) -> dict:
        """Sample ``i``: ``x`` starting mesh (n, 3), ``types`` (n,), ``s`` prescribed (n, 3),
        ``bone`` (n, 3), ``v`` FE displacement of the increment (n, 3), all mm; and its row."""
        row = self.samples.iloc[int(i)]
        k, key, subject = int(row.increment), row.key, int(row.subject)
        U = self._U[key]
        types = self.simulation_types(key, subject)
        bone = self._bone[key][k - 1]
        s = np.where((types == 1)[:, None], bone, 0.0)
        return {"x": self.points[subject] + U[k - 1], "types": types, "s": s, "bone": bone,
                "v": U[k] - U[k - 1], "subject": subject, "side": self.side[subject], "poisson": float(row.poisson),
                "row": row}

    def simulation_types(self, key: str, subject: int) -> np.ndarray:
        """The boundary types ``(n,)`` simulation ``key`` of ``subject`` ran with: its own when
        stored, else the subject's."""
        return self._types.get(key, self.types[int(subject)])

    def displacements(self, key: str) -> np.ndarray:
        """Cumulative FE displacement of simulation ``key`` after each increment,
        ``(increments + 1, n, 3)`` mm (row 0 is zero)."""
        if key not in self._U:
            raise KeyError(f"no completed simulation {key!r} in {self.path}; it holds {len(self._U)}")
        return self._U[key]

    def plan(self, key: str):
        """The SurgicalPlan of simulation ``key`` (drawn again from the configuration's seed)."""

        if not self._motions:
            self._motions.update({j.key: j.params["motions"] for j in _jobs(self.config)})
        if key not in self._motions:
            raise KeyError(f"no simulation {key!r} in the configuration of {self.path}")
        return SurgicalPlan.from_dict({k: v for k, v in self._motions[key].items() if k != "force"})

    def subject(self, subject: int):
        """What ``subject`` is simulated on (:func:`database_subject`): ``mesh`` and ``segments``."""
        return database_subject(self.config, int(subject))

    def arrays(self, indices=None) -> dict:
        """Stacked samples: ``x``, ``s``, ``bone``, ``v`` (m, n, 3) mm, ``types`` (m, n), ``subject`` (m,)."""
        idx = range(len(self)) if indices is None else indices
        items = [self.sample(i) for i in idx]
        out = {k: np.stack([it[k] for it in items]) for k in ("x", "s", "bone", "v", "types")}
        out["subject"] = np.array([it["subject"] for it in items])
        return out

    def index(self):
        """The per-simulation index (:func:`toolkit.common.training.database.read_index`)."""
        return read_index(self.path)
