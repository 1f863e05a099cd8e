"""The static surrogate (the PointNet++ paper): PointNet++ trained on the FE database, its evaluation and
its prediction of a surgical plan.

:func:`train_surrogate` reads a :class:`~toolkit.static.database.StaticDatabase`, encodes
every sample (:mod:`toolkit.static.features`), scales the inputs to [0, 1] (the scaler is
saved with the model) and the targets by one factor (so that exact boundary values stay
exact), splits by simulation (70/10/20: the increments of one plan never straddle two
splits) or holds out whole subjects, and trains with MSE and Adam through
:func:`toolkit.common.training.train` (early stopping on validation, checkpoints, resume,
seed control). The model directory (``model.pt`` + ``config.json``) carries everything
needed to predict: :class:`Surrogate` reloads it and refuses data or meshes of another
kind, naming the difference.

:func:`evaluate_surrogate` scores a model on the samples it did not train on: per-sample
mean Euclidean nodal error on all nodes, on free nodes and on the lips, summarised as mean,
median, 95th percentile and max; inference time per prediction against the FE time per
increment. The model records the identity of every simulation it trained on (its subject's
shape, plan parameters and Poisson's ratio), so that on another database it scores only what
it has not seen, and says which samples it scored (``metrics["scored"]``); a database of
another resolution, material, sliding model or increment count is refused.
:meth:`Surrogate.predict_plan` runs a plan increment by increment like the FE
(CLI ``toolkit static predict``); its summary records, per plan parameter, how far the plan
lies beyond what the training database's sampler spans (``"extrapolation"``).

With ``FeatureSpec(linear_prior=True)`` the network learns a residual: the linear
influence-matrix solution of each increment (:class:`~toolkit.static.baselines.InfluenceMatrix`,
built once per mesh from its boundary types) is an input and is added to the output, so
the network only has to learn what linear superposition misses (sliding, lip contact, the
geometry update between increments). Fixed and moving nodes then have a zero residual.
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from toolkit.common.analysis.metrics import nodal_errors
from toolkit.common.config_diff import require_same
from toolkit.common.meshes.fingerprint import array_fingerprint, mesh_fingerprint, points_fingerprint
from toolkit.common.meshes.io import atomic_path
from toolkit.common.outputs import check_output_dir
from toolkit.common.papers import TISSUE_NU
from toolkit.common.training import (
    LR_SCHEDULES,
    MinMaxScaler,
    ModelBundle,
    TrainConfig,
    extrapolation,
    resolve_device,
    split_groups,
    torch_seeded,
)
from toolkit.common.training import train as train_loop
from toolkit.common.training.evaluation import Evaluation
from toolkit.static.baselines import InfluenceMatrix
from toolkit.static.boundary import NodeType
from toolkit.static.checks import check_plan, with_answer_checks
from toolkit.static.database import PLAN_FEATURES, DatabaseConfig, StaticDatabase, bone_increment, jaw_side
from toolkit.static.features import FeatureSpec, channel_names, encode
from toolkit.static.plan import (
    PHYSIOLOGICAL_RANGES,
    SEGMENTS,
    PlanRangeWarning,
    dental_arch,
    sampled_parameters,
    sampling_hull,
)
from toolkit.static.pointnet2_config import PointNet2Config
from toolkit.static.simulate import IncrementReport, SimulationResult, boundary_conditions, face_mesh_and_segments
from toolkit.static.sliding_response import SlidingResponse

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from toolkit.static.database import StaticDatabase
    from toolkit.static.pointnet2 import PointHierarchy, PointNet2
    from toolkit.static.pointnet2_inference import HierarchyArrays, PointNet2Inference

__all__ = ["SurrogateConfig", "FEATURE_PRESETS", "Surrogate", "train_surrogate", "evaluate_surrogate", "network_config",
           "linear_prior", "MODEL_KIND", "NETWORK_PRESETS", "PLAN_PARAMETERS", "PlanPrediction",
           "plan_extrapolation", "MUST_MATCH"]

MODEL_KIND = "toolkit.static.pointnet2"
#: network sizes: ``paper`` (the PointNet++ paper's widths), ``small`` (a quarter of the widths; the
#: speed goal), ``tiny`` (tests on the coarse face)
NETWORK_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "small": {"sa_widths": ((16, 16, 32), (32, 32, 64), (64, 64, 128), (128, 128, 256)),
              "fp_widths": ((128, 128), (128, 128), (128, 64), (64, 64, 64)), "head_width": 64,
              "group_size": (16, 16, 16, 16)},
    "tiny": {"sa_widths": ((16, 32), (32, 64), (64, 64), (64, 128)),
             "fp_widths": ((64,), (64,), (64,), (64,)), "head_width": 32, "group_size": (16, 16, 16, 16)},
}


#: named input sets: ``best`` (the default: hard boundary values with the linear prior, the most
#: accurate measured, ``benchmarks/static_surrogate.py``) and ``paper`` (the PointNet++ paper's explicit
#: boundary types, no prior)
FEATURE_PRESETS = {"best": FeatureSpec("hard", linear_prior=True), "paper": FeatureSpec("explicit")}


@dataclass(frozen=True)
class SurrogateConfig:
    """How a surrogate is built and trained.

    The default is the most accurate configuration measured (``benchmarks/static_surrogate.py``:
    hard boundary values with the linear prior, a lower mean nodal error on the held-out plans
    than the PointNet++ paper's explicit inputs); ``features="paper"`` trains the PointNet++
    paper's inputs.

    Attributes
    ----------
    features : FeatureSpec (variant explicit / implicit / hard, extra and material channels,
        linear prior), or a name of :data:`FEATURE_PRESETS` (``best``, the default, or ``paper``)
    network : preset name (:data:`NETWORK_PRESETS`)
    coarse_radii : use :meth:`PointNet2Config.coarse` radii (meshes of ~800 nodes)
    split : ``plans`` (70/10/20 by simulation) or ``subjects`` (``test_subjects`` held out,
        the others split 80/20 by simulation into training and validation)
    test_subjects : subjects never seen in training (split ``subjects``)
    epochs, batch_size, lr, patience, seed, device, max_seconds : training (the PointNet++ paper: Adam
        lr 1e-5, batch 8, 100 epochs; the default lr 1e-3 with early stopping reaches its error in
        fewer epochs here)
    lr_schedule : ``constant`` (the PointNet++ paper) or ``cosine`` (decays to 1 % of ``lr`` over the
        epochs, or over ``max_seconds`` when set; :class:`~toolkit.common.training.TrainConfig`)
    split_seed : seed of the split into training, validation and test simulations (None: ``seed``);
        the members of a deep ensemble share it and differ in ``seed``
    """

    features: FeatureSpec = FEATURE_PRESETS["best"]
    network: str = "small"
    coarse_radii: bool = False
    split: str = "plans"
    test_subjects: tuple[int, ...] = ()
    epochs: int = 100
    batch_size: int = 8
    lr: float = 1e-3
    patience: int | None = 15
    seed: int = 0
    device: str = "cpu"
    max_seconds: float | None = None
    lr_schedule: str = "constant"
    split_seed: int | None = None

    def __post_init__(self):
        if isinstance(self.features, dict):
            object.__setattr__(self, "features", FeatureSpec(**self.features))
        elif isinstance(self.features, str):
            if self.features not in FEATURE_PRESETS:
                raise ValueError(f"features = {self.features!r}; expected a FeatureSpec or one of "
                                 f"{sorted(FEATURE_PRESETS)}")
            object.__setattr__(self, "features", FEATURE_PRESETS[self.features])
        if self.network not in NETWORK_PRESETS:
            raise ValueError(f"network = {self.network!r}; expected one of {sorted(NETWORK_PRESETS)}")
        if self.split not in ("plans", "subjects"):
            raise ValueError(f"split = {self.split!r}; expected 'plans' or 'subjects'")
        if self.split_seed is not None and (isinstance(self.split_seed, bool) or not isinstance(self.split_seed, int)):
            raise ValueError(f"split_seed = {self.split_seed!r}; expected an integer or None (the training seed)")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule = {self.lr_schedule!r}; expected one of {LR_SCHEDULES}")
        if self.split == "subjects" and not self.test_subjects:
            raise ValueError("split 'subjects' needs test_subjects=(...): the subjects held out for testing")
        object.__setattr__(self, "test_subjects", tuple(int(s) for s in self.test_subjects))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["features"] = asdict(self.features)
        return d


def network_config(config: SurrogateConfig):
    """The :class:`~toolkit.static.pointnet2_config.PointNet2Config` of a surrogate."""

    preset = dict(NETWORK_PRESETS[config.network])
    preset.update(in_channels=config.features.n_channels, hard_boundary=config.features.variant == "hard")
    return PointNet2Config.coarse(**preset) if config.coarse_radii else PointNet2Config(**preset)


def linear_prior(mesh, types: np.ndarray):
    """The influence matrix of ``mesh`` for boundary ``types (n,)``: moving nodes (1) driven,
    fixed nodes (2) held (:class:`~toolkit.static.baselines.InfluenceMatrix`, linear material)."""

    types = np.asarray(types)
    return InfluenceMatrix.build(mesh, np.flatnonzero(types == 1), np.flatnonzero(types == 2))


#: the plan parameters whose range over the plans a model trained or validated on it records, in the order of
#: :data:`toolkit.static.database.PLAN_FEATURES` (without its increment fraction)
PLAN_PARAMETERS = tuple(f"{seg}.{kind}_{axis}_{unit}" for seg in ("lefort", "distal")
                        for kind, unit in (("translation", "mm"), ("rotation", "deg")) for axis in "xyz")
#: database settings a model is scored on only when they equal its training database's
MUST_MATCH = ("resolution", "material", "sliding", "increments")


def _simulation_identities(db) -> dict:
    """Simulation key -> what the simulation is (hash of its subject's points, its plan parameters
    per increment and Poisson's ratio): equal for the same simulation in two databases, whatever
    its key there."""

    subject_keys = {int(sid): points_fingerprint(p) for sid, p in db.points.items()}
    out = {}
    for key, g in db.samples.groupby("key", sort=True):
        h = hashlib.sha1(subject_keys[int(g.subject.iloc[0])].encode())
        feats = np.round(g.sort_values("increment")[list(PLAN_FEATURES)].to_numpy(np.float64), 6) + 0.0  # no -0.0
        h.update(feats.tobytes())
        h.update(np.float64(round(float(g.poisson.iloc[0]), 9)).tobytes())
        out[str(key)] = h.hexdigest()[:20]
    return out


def plan_extrapolation(plan, hull: dict, arch: np.ndarray | None = None) -> dict:
    """How far ``plan`` lies beyond what the training database's sampler spans: each of its
    :func:`~toolkit.static.plan.sampled_parameters` (translation lengths and rotation angles per
    segment, out-of-plane motion, and with the face's dental ``arch`` ``(k, 3)`` mm the jaw
    closing) outside ``hull`` (:func:`training_hull`). The one verdict of ``static predict``,
    with or without a tolerance (:func:`~toolkit.static.trust.out_of_distribution`)."""

    return extrapolation(sampled_parameters(plan, arch), hull, "plans")


def training_hull(database: dict) -> dict:
    """:func:`~toolkit.static.plan.sampling_hull` of a training database's settings (its
    ``DatabaseConfig`` as a dict: ``mode``, ``max_jaw_closing_mm``), physiological ranges."""

    return sampling_hull(database.get("mode", "sagittal"), PHYSIOLOGICAL_RANGES, database.get("max_jaw_closing_mm"))


def arch_nodes(db) -> np.ndarray:
    """The nodes of a database's first subject nearest its dental arch (the jaw closing's
    points, on every subject of that topology), ``(k,)`` int64."""
    from scipy.spatial import cKDTree


    first = min(db.points)
    return cKDTree(db.points[first]).query(dental_arch(db.subject(first)))[1].astype(np.int64)


# ------------------------------------------------------------------ the model
#: summary keys of a FE run that a prediction does not compute (solver, contact, sliding and
#: regulation records)
FE_ONLY = ("max_penetration_mm", "max_mucosa_gap_mm", "mucosa_offset_mm", "far_mucosa_nodes", "release_width_mm",
           "freed_cut_nodes", "freed_mucosa_nodes", "substeps", "increments_cut", "regulated_nodes",
           "max_regulation_shift_mm")


@dataclass(frozen=True, eq=False)
class PlanPrediction(SimulationResult):
    """A surrogate's prediction of a plan: a SimulationResult whose summary also holds
    ``extrapolation`` (:func:`plan_extrapolation`: the plan parameters beyond what the training
    database's sampler spans) and reports only what the prediction computed (no :data:`FE_ONLY`
    key; per increment, its time and quality). ``prescribed`` ``(increments, n, 3)`` mm holds each
    increment's prescribed bone motion (zero off the bone-driven nodes), as the network saw it."""

    extrapolation: dict = field(default_factory=dict)
    prescribed: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))

    def summary(self) -> dict:
        summary = {k: v for k, v in super().summary().items() if k not in FE_ONLY}
        summary["increments_report"] = [{"increment": r.increment, "seconds": r.seconds_step1,
                                         "min_scaled_jacobian": r.min_scaled_jacobian,
                                         "worst_element": r.worst_element} for r in self.reports]
        return {**summary, "extrapolation": self.extrapolation}


def with_exact_attachment(U: np.ndarray, X: np.ndarray, bc, plan) -> np.ndarray:
    """Cumulative displacements ``U`` ``(increments + 1, n, 3)`` mm with every moving node set to
    where its segment's cumulative motion puts it at each increment (float64, exactly as the FE
    prescribes it); a prediction accumulated increment by increment (float32 networks, a baseline
    stepping from reached positions) drifts from it by micrometres. ``X`` ``(n, 3)`` mm."""
    import warnings as _warnings


    U = np.array(U, dtype=float)
    with _warnings.catch_warnings():  # the plan warned of its range where it was built
        _warnings.simplefilter("ignore", PlanRangeWarning)
        steps = plan.increments(U.shape[0] - 1)
    for name in bc.segment_names:
        nodes = bc.segment_nodes(NodeType.MOVING, name)
        if not nodes.size or name not in SEGMENTS:
            continue
        for k, p in enumerate(steps, start=1):
            U[k, nodes] = p.motion(name).apply(X[nodes]) - X[nodes]
    return U


def _face_module():
    import torch
    from torch import nn

    from toolkit.static.pointnet2 import BoundaryTargets, PointNet2

    class FaceSurrogate(nn.Module):
        """PointNet++ with one point hierarchy per subject and the targets' scale.

        ``forward(features (B, n, C) scaled, subject (B,), prescribed (B, n, 3) in the output
        unit, mask (B, n) bool)`` -> ``(B, n, 3)`` in the output unit; with hard boundaries the
        output is exactly ``prescribed`` where ``mask`` is set.
        """

        def __init__(self, net_config, hierarchies: dict):
            super().__init__()
            self.net = PointNet2(net_config)
            self.hierarchies = dict(hierarchies)

        def forward(self, features, subject, prescribed, mask):
            out = torch.empty(features.shape[:2] + (3,), dtype=features.dtype, device=features.device)
            for sid in torch.unique(subject).tolist():
                idx = (subject == sid).nonzero().flatten()
                boundary = BoundaryTargets(mask[idx], prescribed[idx]) if self.net.config.hard_boundary else None
                out[idx] = self.net(features[idx], self.hierarchies[sid], boundary).to(out.dtype)
            return out

    return FaceSurrogate


@dataclass(frozen=True, eq=False)
class _ArrayFace:
    """The inference half of ``FaceSurrogate`` in numpy: the network
    (:class:`~toolkit.static.pointnet2_inference.PointNet2Inference`) and the training subjects'
    hierarchies (:class:`~toolkit.static.pointnet2_inference.HierarchyArrays`)."""

    net: PointNet2Inference
    hierarchies: dict[int, HierarchyArrays]


class _TorchFace(Protocol):
    """What :class:`Surrogate` uses of the torch ``FaceSurrogate`` of :func:`_face_module`: the
    network and the training subjects' hierarchies."""

    net: PointNet2
    hierarchies: dict[int, PointHierarchy]


def _numpy_engine(device) -> bool:
    """Whether a model asked for on ``device`` runs in numpy: the CPU (``"cpu"``)."""
    return isinstance(device, str) and device.strip().lower() == "cpu"


@dataclass(eq=False)
class Surrogate:
    """A trained static surrogate (load one with :meth:`load`).

    Attributes
    ----------
    config : SurrogateConfig
    bundle : the ModelBundle (weights, scalers, data signature, training facts)
    module : the torch module (eval mode), or on the CPU its numpy counterpart (the network of
        :mod:`~toolkit.static.pointnet2_inference` and the subjects' hierarchies)
    device : torch device, or ``"cpu"`` for the numpy network
    directory : the model directory it was loaded from
    """

    config: SurrogateConfig
    bundle: ModelBundle
    module: _TorchFace | _ArrayFace
    device: str | torch.device
    directory: Path | None = None
    _hierarchy_cache: dict = field(default_factory=dict, repr=False)
    _prior_cache: dict = field(default_factory=dict, repr=False)
    _response_cache: dict = field(default_factory=dict, repr=False)

    @property
    def out_scale(self) -> float:
        """mm per output unit."""
        return float(self.bundle.extra["out_scale_mm"])

    @classmethod
    def load(cls, directory, device: str = "cpu") -> Surrogate:
        """Load a model directory written by :func:`train_surrogate`. On ``device="cpu"`` the
        network runs in numpy from ``weights.npz`` (no torch import; a directory without that
        file is read with torch); on ``"cuda"`` or ``"auto"``, in torch."""
        arrays = _numpy_engine(device) and ModelBundle.has_arrays(directory)
        bundle = ModelBundle.load(directory, kind=MODEL_KIND, arrays=arrays)
        config = SurrogateConfig(**bundle.config["surrogate"])
        if arrays:
            from toolkit.static.pointnet2_inference import HierarchyArrays, PointNet2Inference

            hierarchies = {int(k): HierarchyArrays.from_state(v) for k, v in bundle.state_dict["hierarchies"].items()}
            module = _ArrayFace(PointNet2Inference(network_config(config), bundle.state_dict["net"]), hierarchies)
            return cls(config, bundle, module, "cpu", Path(directory))
        from toolkit.static.pointnet2 import PointHierarchy

        dev = resolve_device(device)
        torch_hierarchies = {int(k): PointHierarchy.from_state_dict(v, device=dev)
                             for k, v in bundle.state_dict["hierarchies"].items()}
        module = _face_module()(network_config(config), torch_hierarchies)
        module.net.load_state_dict(bundle.state_dict["net"])
        module.to(dev).eval()
        module.net = module.net.fold_batch_norm()  # inference only: the batch norms become part of the weights
        return cls(config, bundle, module, dev, Path(directory))

    def check_mesh(self, points: np.ndarray, cells: dict) -> None:
        """Refuse a mesh of another node count or topology than the training meshes."""
        trained = self.bundle.data.get("database", {}).get("resolution")
        on = "" if trained is None else (f"the model was trained on the {trained!r} phantom: predict on it "
                                         f"(resolution={trained!r}; command line: --resolution {trained}), ")
        hint = (f"{on}train a model on a database of this mesh, or predict on it anyway (any_mesh=True; command "
                "line: --any-mesh)")
        self.bundle.check_data({**self.bundle.data, "mesh": mesh_fingerprint(points, cells)}, "this mesh", hint=hint)

    def hierarchy(self, points: np.ndarray, subject: int | None = None):
        """The point hierarchy of a training subject, or one built for ``points`` (cached; with
        torch, also for the numpy network)."""
        if subject is not None and subject in self.module.hierarchies:
            return self.module.hierarchies[subject]
        key = points_fingerprint(points)
        known = self.bundle.extra.get("subject_points", {})
        if key in known and int(known[key]) in self.module.hierarchies:  # a training subject's own mesh
            return self.module.hierarchies[int(known[key])]
        if key not in self._hierarchy_cache:
            from toolkit.static.pointnet2 import PointHierarchy

            built: HierarchyArrays | PointHierarchy
            if isinstance(self.module, _ArrayFace):
                from toolkit.static.pointnet2_inference import HierarchyArrays

                built = HierarchyArrays.from_hierarchy(PointHierarchy.build(points, network_config(self.config)))
            else:
                built = PointHierarchy.build(points, network_config(self.config), device=self.device)
            self._hierarchy_cache[key] = built
        return self._hierarchy_cache[key]

    def prior(self, mesh, types: np.ndarray):
        """The influence matrix of a mesh and its boundary types (built once, cached), for
        models with ``linear_prior``."""
        key = (points_fingerprint(mesh.points), array_fingerprint(types))
        if key not in self._prior_cache:
            self._prior_cache[key] = linear_prior(mesh, types)
        return self._prior_cache[key]

    def sliding_response(self, face, segments=None):
        """The :class:`~toolkit.static.sliding_response.SlidingResponse` of ``face`` (a
        FacePhantom, or a Mesh with ``segments``) under the training database's sliding model
        (built once per face and bone surfaces, cached)."""

        mesh, segments = face_mesh_and_segments(face, segments)
        key = (points_fingerprint(mesh.points),) + tuple(sorted((name, points_fingerprint(seg.surface.points))
                                                         for name, seg in segments.items()))
        if key not in self._response_cache:
            sliding = self.bundle.data["database"]["sliding"]
            self._response_cache[key] = SlidingResponse.build(mesh, sliding, segments)
        return self._response_cache[key]

    def predict(self, features: np.ndarray, prescribed: np.ndarray, mask: np.ndarray, hierarchy,
                prior: np.ndarray | None = None) -> np.ndarray:
        """Displacement ``(B, n, 3)`` mm from raw features ``(B, n, C)``, the prescribed
        displacement ``(B, n, 3)`` mm and the prescribed mask ``(B, n)``, on one mesh; a
        ``linear_prior`` model also needs the prior ``(B, n, 3)`` mm (the features' last three
        channels), which it adds to the network's residual."""
        if self.config.features.linear_prior:
            if prior is None:
                raise ValueError("this model learns a residual over the linear prior: pass prior=(B, n, 3) mm "
                                 "(Surrogate.prior(mesh, types).predict(s))")
            prescribed = np.asarray(prescribed) - np.asarray(prior)
        features = self.bundle.scalers["inputs"].transform(np.asarray(features, dtype=np.float64))
        out = self._network(features, np.asarray(prescribed) / self.out_scale, np.asarray(mask, dtype=bool), hierarchy)
        out = np.asarray(out, dtype=np.float64) * self.out_scale
        return out + np.asarray(prior) if self.config.features.linear_prior else out

    def _network(self, features: np.ndarray, values: np.ndarray, mask: np.ndarray, hierarchy) -> np.ndarray:
        """The network's output ``(B, n, 3)`` in its unit for scaled ``features``, with the
        prescribed ``values`` (its unit) exact where ``mask`` is set when it has hard boundaries."""
        module = self.module
        hard = module.net.config.hard_boundary
        if isinstance(module, _ArrayFace):
            return module.net(features, hierarchy, mask if hard else None, values if hard else None)
        import torch

        from toolkit.static.pointnet2 import BoundaryTargets

        as_tensor = lambda a, dtype: torch.as_tensor(a, dtype=dtype, device=self.device)  # noqa: E731
        with torch.no_grad():
            boundary = BoundaryTargets(as_tensor(mask, torch.bool), as_tensor(values, torch.float32)) if hard else None
            return module.net(as_tensor(features, torch.float32), hierarchy, boundary).double().cpu().numpy()

    def predict_plan(self, face, plan, *, segments=None, any_mesh: bool = False):
        """Run ``plan`` on a face like :func:`~toolkit.static.simulate.simulate`, increment by
        increment with the network, with the increments and sliding model of the training
        database.

        Parameters
        ----------
        face : FacePhantom, or a Mesh with the phantoms' node sets (then pass ``segments``)
        plan : SurgicalPlan
        segments : name -> BoneSegment (default the phantom's)
        any_mesh : predict on a mesh of another node count or topology than the training meshes
            (PointNet++ reads a point cloud; a face remeshed by ``toolkit mesh`` is measured in
            ``docs/own-face.md``); by default such a mesh is refused

        Returns
        -------
        PlanPrediction (``.write(out)`` gives the files of ``toolkit static simulate``; its summary's
        ``extrapolation`` names the plan parameters beyond what the training sampler spans, and
        ``checks`` holds :func:`~toolkit.static.checks.answer_checks`: a failed check is flagged there, not
        raised). The plan is checked against the face first (:func:`~toolkit.static.checks.check_plan`)
        """

        t0 = time.perf_counter()
        data = DatabaseConfig(**self.bundle.data["database"])
        mesh, segments = face_mesh_and_segments(face, segments)
        if not any_mesh:
            self.check_mesh(mesh.points, dict(mesh.cells))
        elif self.bundle.data.get("mesh") != mesh_fingerprint(mesh.points, dict(mesh.cells)):
            warnings.warn("predicting on a mesh of another topology than the training meshes: on a face remeshed "
                          "by `toolkit mesh`, a network trained on the phantoms was measured less accurate than its "
                          "linear prior alone (docs/own-face.md); train on a database of this face", stacklevel=2)
        bc, bc_all = boundary_conditions(mesh, segments, data.sliding)
        check_plan(mesh, bc_all, segments, plan)
        X = mesh.points
        h = self.hierarchy(X)
        sets = {k: mesh.node_sets[k] for k in ("upper_lip_face", "lower_lip_face") if k in mesh.node_sets}
        side = jaw_side(bc.segment, sets, X.shape[0], tuple(bc.segment_names))
        mask = np.isin(bc.types, (1, 2))
        im = self.prior(mesh, bc.types) if self.config.features.linear_prior else None
        reached, previous, quality, given = [np.zeros_like(X)], None, [], []
        with warnings.catch_warnings():  # the plan warned of its range where it was built
            warnings.simplefilter("ignore", PlanRangeWarning)
            steps = plan.increments(data.increments)
        for p in steps:
            x = X + reached[-1]
            bone = bone_increment(x, bc, p, previous)
            prescribed = np.where((bc.types == 1)[:, None], bone, 0.0)
            given.append(prescribed)
            prior = im.predict(prescribed) if im is not None else None
            feats = encode(self.config.features, x, bc.types, prescribed, bone, side, TISSUE_NU, prior)
            reached.append(reached[-1] + self.predict(feats[None], prescribed[None], mask[None], h,
                                                      None if prior is None else prior[None])[0])
            quality.append(mesh.with_points(X + reached[-1]).scaled_jacobian())
            previous = p
        wall = time.perf_counter() - t0
        reports = [IncrementReport(k, wall / len(quality), 0.0, 0, 0, 0, float(q.min()), int(np.argmin(q)),
                                   0.0, 0.0, 0.0, 0) for k, q in enumerate(quality, start=1)]
        U = with_exact_attachment(np.stack(reached), X, bc, plan)
        return with_answer_checks(
            PlanPrediction(mesh, U, bc, reports, wall, f"surrogate ({self.config.features.variant})", data.sliding,
                           extrapolation=self.extrapolation(plan, mesh), prescribed=np.stack(given)), plan)

    def extrapolation(self, plan, mesh=None) -> dict:
        """How far ``plan`` lies beyond what the training database's sampler spans
        (:func:`plan_extrapolation`); the jaw closing too on a ``mesh`` of the training topology."""
        nodes = self.bundle.extra.get("arch_nodes")
        same = mesh is not None and nodes is not None and mesh.n_points == self.bundle.data["mesh"]["nodes"]
        arch = mesh.points[np.asarray(nodes, np.int64)] if same else None
        return plan_extrapolation(plan, training_hull(self.bundle.data["database"]), arch)


# ------------------------------------------------------------------ data
@dataclass(frozen=True, eq=False)
class _Data:
    features: np.ndarray  # (m, n, C) raw
    prescribed: np.ndarray  # (m, n, 3) mm
    mask: np.ndarray  # (m, n) bool
    target: np.ndarray  # (m, n, 3) mm
    subject: np.ndarray  # (m,)
    types: np.ndarray  # (m, n)
    keys: np.ndarray  # (m,) simulation key
    prior: np.ndarray | None = None  # (m, n, 3) mm, the linear prior (linear_prior models)

    def net_targets(self, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """What the network sees: prescribed values and targets in the output unit (residuals
        over the prior when there is one)."""
        if self.prior is None:
            return self.prescribed / scale, self.target / scale
        return (self.prescribed - self.prior) / scale, (self.target - self.prior) / scale


def _subject_priors(db, subjects) -> dict:
    """Influence matrix of each phantom subject of a database (its mesh and boundary types)."""
    return {int(sid): linear_prior(db.subject_mesh(int(sid)), db.types[int(sid)]) for sid in subjects}


def _encode_database(db, spec: FeatureSpec, priors: dict | None = None) -> _Data:
    """Every sample's features, prescribed values, mask, FE target; with ``spec.linear_prior``,
    ``priors`` (subject -> InfluenceMatrix) gives each sample's prior."""
    if spec.linear_prior and priors is None:
        raise ValueError("linear_prior features need the subjects' influence matrices (priors=...)")
    feats, pres, mask, target, subject, types, keys, prior = [], [], [], [], [], [], [], []
    for i in range(len(db)):
        s = db.sample(i)
        p = priors[int(s["subject"])].predict(s["s"]) if spec.linear_prior and priors is not None else None
        feats.append(encode(spec, s["x"], s["types"], s["s"], s["bone"], s["side"], s["poisson"], p))
        prior.append(p)
        pres.append(s["s"])
        mask.append(np.isin(s["types"], (1, 2)))
        target.append(s["v"])
        subject.append(s["subject"])
        types.append(s["types"])
        keys.append(s["row"].key)
    f32 = lambda a: np.stack(a).astype(np.float32)  # noqa: E731
    return _Data(np.stack(feats), f32(pres), np.stack(mask), f32(target), np.array(subject), np.stack(types),
                 np.array(keys), f32(prior) if spec.linear_prior else None)


def _split(data: _Data, config: SurrogateConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    seed = config.seed if config.split_seed is None else config.split_seed
    if config.split == "plans":
        train, validation, test = split_groups(data.keys, (0.7, 0.1, 0.2), seed)
        return train, validation, test
    test = np.flatnonzero(np.isin(data.subject, config.test_subjects))
    rest = np.flatnonzero(~np.isin(data.subject, config.test_subjects))
    if not test.size or not rest.size:
        raise ValueError(f"test subjects {config.test_subjects} leave {rest.size} training and {test.size} test "
                         f"samples; the database has subjects {sorted(set(data.subject.tolist()))}")
    tr, va = split_groups(data.keys[rest], (0.8, 0.2), seed)
    return rest[tr], rest[va], test


def _check_training_inputs(db, config: SurrogateConfig) -> None:
    """Refuse, before the model directory is made, what the training could not use: a device
    torch does not see, held-out subjects the database lacks (or that leave none to train on),
    material channels on a database of one Poisson's ratio."""
    resolve_device(config.device)
    subjects = sorted(int(s) for s in db.samples.subject.unique())
    if config.split == "subjects":
        absent = [s for s in config.test_subjects if s not in subjects]
        if absent:
            raise ValueError(f"test_subjects {absent} are not in the database {db.path}: it holds subjects "
                             f"{subjects} (build more with `toolkit static database --subjects N`)")
        if not set(subjects) - set(config.test_subjects):
            raise ValueError(f"test_subjects {list(config.test_subjects)} are every subject of the database "
                             f"{db.path} ({subjects}): hold some out, not all")
    if config.features.material_channels and db.config.poisson_range is None:
        raise ValueError("material_channels needs a database whose simulations vary Poisson's ratio "
                         "(DatabaseConfig.poisson_range; command line: toolkit static database --poisson-range LO HI); "
                         f"this one uses {TISSUE_NU} throughout")


def train_surrogate(database, config: SurrogateConfig = SurrogateConfig(), *, out, resume: bool = False,
                    progress: bool = True) -> Surrogate:
    """Train a surrogate on a database and save it to the directory ``out`` (the impact
    workflow's :func:`toolkit.impact.train_surrogate` takes the same first arguments).

    Parameters
    ----------
    database : path of a static database, or a StaticDatabase
    config : SurrogateConfig (default: hard boundary values with the linear prior, the most
        accurate measured; ``SurrogateConfig(features="paper")`` for the PointNet++ paper's inputs)
    out : model directory (``model.pt``, ``config.json``; ``checkpoint.pt`` while training)
    resume : continue an interrupted training from ``out/checkpoint.pt``

    Returns
    -------
    Surrogate (the best validation weights), also written to ``out``
    """
    import torch

    from toolkit.static.pointnet2 import PointHierarchy

    out = check_output_dir(out, what="model directory")
    db = database if isinstance(database, StaticDatabase) else StaticDatabase.open(database)
    _check_training_inputs(db, config)
    out.mkdir(parents=True, exist_ok=True)
    t_prior = time.perf_counter()
    priors = _subject_priors(db, db.points) if config.features.linear_prior else None
    t_prior = time.perf_counter() - t_prior
    data = _encode_database(db, config.features, priors)
    train_idx, val_idx, test_idx = _split(data, config)
    scaler = MinMaxScaler.fit(data.features[train_idx], names=channel_names(config.features))
    out_scale = float(np.abs(data.net_targets(1.0)[1][train_idx]).max()) or 1.0
    prescribed_net, target_net = data.net_targets(out_scale)
    net_config = network_config(config)
    device = resolve_device(config.device)
    hierarchies = {s: PointHierarchy.build(db.points[s], net_config, device=device) for s in db.points}
    with torch_seeded(config.seed):
        module = _face_module()(net_config, hierarchies)

    def tensors(idx):
        f = scaler.transform(data.features[idx].astype(np.float64)).astype(np.float32)
        return ((f, data.subject[idx], prescribed_net[idx], data.mask[idx]), target_net[idx])

    tc = TrainConfig(epochs=config.epochs, batch_size=config.batch_size, lr=config.lr, patience=config.patience,
                     seed=config.seed, device=config.device, max_seconds=config.max_seconds, progress=progress,
                     lr_schedule=config.lr_schedule)
    signature = {"database": db.config.to_dict(), "mesh": mesh_fingerprint(db.points[0], db.cells),
                 "channels": list(channel_names(config.features))}
    # the training budget may grow on resume (TrainConfig.RESUMABLE); everything else must match
    resumable = {k: v for k, v in config.to_dict().items() if k not in TrainConfig.RESUMABLE}
    identity = {"surrogate": resumable, "data": signature, "samples": int(len(data.keys)),
                "train": [int(i) for i in train_idx[:5]]}
    result = train_loop(module, torch.nn.functional.mse_loss, tensors(train_idx), tensors(val_idx), tc,
                        checkpoint=out / "checkpoint.pt", resume=resume, identity=identity)
    module.eval()
    state = {"net": {k: v.detach().cpu() for k, v in module.net.state_dict().items()},
             "hierarchies": {str(s): {k: v.cpu() for k, v in h.state_dict().items()} for s, h in hierarchies.items()}}
    test_keys = sorted(set(data.keys[test_idx].tolist()))
    identities = _simulation_identities(db)
    seen_keys = set(data.keys[np.concatenate([train_idx, val_idx])].tolist())  # trained or validated on
    seen = sorted({identities[str(k)] for k in seen_keys})
    extra = {"out_scale_mm": out_scale, "train_seconds": result.seconds, "prior_seconds": t_prior,
             "best_epoch": result.best_epoch, "stopped": result.stopped, "stop_reason": result.stop_reason,
             "history": result.history.to_dict(orient="list"),
             "split": {"train": int(train_idx.size), "validation": int(val_idx.size), "test": int(test_idx.size)},
             "test_keys": test_keys, "parameters": int(sum(p.numel() for p in module.net.parameters())),
             "seen_simulations": seen,
             "subject_points": {points_fingerprint(pts): int(s) for s, pts in db.points.items()},
             "arch_nodes": arch_nodes(db).tolist()}
    bundle = ModelBundle(MODEL_KIND, {"surrogate": config.to_dict(), "network": net_config.to_dict()}, signature,
                         {"inputs": scaler}, state, extra)
    bundle.save(out)
    return Surrogate.load(out, device=config.device)


def evaluation_keys(model: Surrogate, db, keys=None) -> tuple[list, str]:
    """The simulations of ``db`` a model is scored (or calibrated) on, and how they were chosen
    in words: ``keys`` as given; the model's test simulations on its training database; on
    another database, every simulation the model did not train or validate on."""
    keys, how, _, _ = _scored_keys(model, db, keys)
    return list(keys), how


def check_database(model: Surrogate, db) -> None:
    """Refuse a database of other settings (:data:`MUST_MATCH`) or another mesh than the model's
    training database, with :class:`~toolkit.common.config_diff.IncompatibleError`."""

    trained_on = model.bundle.data["database"]
    asked = db.config.to_dict()
    require_same({k: trained_on.get(k) for k in MUST_MATCH}, {k: asked[k] for k in MUST_MATCH},
                 f"database {db.path}: the model's training database",
                 hint="Score the model on a database generated with its settings (`toolkit static database "
                      + " ".join(f"--{k} {trained_on.get(k)}" for k in MUST_MATCH) + "`)")
    model.check_mesh(db.points[0], db.cells)


def _scored_keys(model: Surrogate, db, keys=None):
    check_database(model, db)
    trained_on = model.bundle.data["database"]
    asked = db.config.to_dict()
    same = json.loads(json.dumps(asked)) == trained_on  # tuples as the stored lists
    seen = model.bundle.extra.get("seen_simulations")
    identities = _simulation_identities(db) if seen is not None else {}
    seen = set(seen) if seen is not None else None
    per_key = db.samples.key.value_counts()
    excluded = scored_training = None
    if keys is not None:
        scored = f"the {len(set(keys))} requested simulations of {db.path}"
        if seen is not None:
            scored_training = int(sum(per_key.get(k, 0) for k in set(keys) if identities.get(str(k)) in seen))
    elif same:
        keys = model.bundle.extra["test_keys"]
        scored = "test split of the training database"
        scored_training = 0
    elif seen is None:
        keys = sorted(db.samples.key.unique())
        scored = ("all samples of another database (the model does not record its training simulations: "
                  "some samples may be ones it trained on)")
    else:
        everything = sorted(db.samples.key.unique())
        keys = [k for k in everything if identities[str(k)] not in seen]
        excluded = int(sum(per_key[k] for k in everything if identities[str(k)] in seen))
        scored_training = 0
        if not keys:
            raise ValueError(f"every simulation of {db.path} ({len(everything)}) is one the model trained on; "
                             "nothing is left to score: generate a database with another --seed")
        scored = f"all samples of another database, {excluded} training samples excluded"
    return keys, scored, excluded, scored_training


# ------------------------------------------------------------------ evaluation
def evaluate_surrogate(surrogate: Surrogate, database, *, keys=None, inference_samples: int = 20) -> Evaluation:
    """Score ``surrogate`` on a database's samples it has not seen.

    By default: the model's test simulations when the database is the one it was trained on;
    on another database, every simulation except those the model trained or validated on (the
    same subject shape, plan parameters and Poisson's ratio, whatever their keys). ``keys``
    scores the given simulations as they are (training ones are counted, not excluded). A
    database of another resolution, material, sliding model or increment count than the
    training one is refused with :class:`~toolkit.common.config_diff.IncompatibleError`.

    Returns an :class:`~toolkit.common.training.evaluation.Evaluation`: ``per_sample`` DataFrame
    (key, subject, increment, errors in mm), ``metrics`` (mean/median/p95/max of the per-sample
    mean nodal error on all nodes, free nodes, lips; ``inference_ms`` per prediction; ``fe_ms`` FE
    time per increment; ``scored`` which samples were scored, in words;
    ``training_samples_excluded`` and ``training_samples_scored``, None where unknown),
    ``predicted`` ``(m, n, 3)`` mm with ``truth``, and ``items`` the database rows scored.
    """
    import pandas as pd


    db = database if isinstance(database, StaticDatabase) else StaticDatabase.open(database)
    keys, scored, excluded, scored_training = _scored_keys(surrogate, db, keys)
    rows = np.flatnonzero(db.samples.key.isin(list(keys)).to_numpy())
    if not rows.size:
        raise ValueError(f"no sample of {db.path} belongs to the requested simulations {sorted(keys)[:5]}...; "
                         f"it holds {db.samples.key.nunique()} simulations")
    subjects = np.unique(db.samples.subject.to_numpy()[rows])
    priors = None
    if surrogate.config.features.linear_prior:
        priors = {int(sid): surrogate.prior(db.subject_mesh(int(sid)), db.types[int(sid)]) for sid in subjects}
    data = _encode_database(_Subset(db, rows), surrogate.config.features, priors)
    preds = np.empty_like(data.target, dtype=np.float64)
    for sid in np.unique(data.subject):
        idx = np.flatnonzero(data.subject == sid)
        h = surrogate.hierarchy(db.points[sid], sid)
        for start in range(0, idx.size, 16):
            chunk = idx[start:start + 16]
            preds[chunk] = surrogate.predict(data.features[chunk], data.prescribed[chunk], data.mask[chunk], h,
                                         None if data.prior is None else data.prior[chunk])
    target = data.target.astype(np.float64)
    err = nodal_errors(preds.reshape(-1, 3), target.reshape(-1, 3)).reshape(target.shape[:2])
    lips = np.unique(np.concatenate([db.sets[k] for k in ("lip_sliding", "upper_lip_face", "lower_lip_face")
                                     if k in db.sets]))
    free = data.types == 0
    per_sample = pd.DataFrame({
        "key": data.keys, "subject": data.subject, "increment": db.samples.increment.to_numpy()[rows],
        "mean_error_mm": err.mean(axis=1),
        "free_mean_error_mm": np.array([e[f].mean() if f.any() else np.nan for e, f in zip(err, free)]),
        "lips_mean_error_mm": err[:, lips].mean(axis=1),
        "max_error_mm": err.max(axis=1),
        "mean_displacement_mm": np.linalg.norm(target, axis=-1).mean(axis=1)})
    # inference time of one prediction (batch 1, with the linear prior's product), after a warm-up
    sid = int(data.subject[0])
    h = surrogate.hierarchy(db.points[sid], sid)

    def one(i):
        prior = priors[sid].predict(data.prescribed[i])[None] if priors is not None else None
        return surrogate.predict(data.features[i:i + 1], data.prescribed[i:i + 1], data.mask[i:i + 1], h, prior)

    one(0)
    times = []
    for i in range(min(inference_samples, len(rows))):
        t0 = time.perf_counter()
        one(i)
        times.append(time.perf_counter() - t0)
    m = per_sample.mean_error_mm
    metrics = {"samples": int(len(rows)), "mean_error_mm": float(m.mean()), "median_error_mm": float(m.median()),
               "p95_error_mm": float(np.percentile(m, 95)), "max_error_mm": float(m.max()),
               "free_mean_error_mm": float(per_sample.free_mean_error_mm.mean()),
               "lips_mean_error_mm": float(per_sample.lips_mean_error_mm.mean()),
               "max_nodal_error_mm": float(per_sample.max_error_mm.max()),
               "mean_displacement_mm": float(per_sample.mean_displacement_mm.mean()),
               "inference_ms": 1e3 * float(np.median(times)),
               "fe_ms": 1e3 * float(db.samples.seconds.to_numpy()[rows].mean()),
               "train_seconds": float(surrogate.bundle.extra.get("train_seconds", np.nan)),
               "variant": surrogate.config.features.variant, "scored": scored,
               "training_samples_excluded": excluded, "training_samples_scored": scored_training}
    return Evaluation(metrics, rows, preds, target, per_sample)


@dataclass(eq=False)
class _Subset:
    """A view of some rows of a StaticDatabase (for encoding)."""

    db: StaticDatabase
    rows: np.ndarray

    def __len__(self):
        return len(self.rows)

    def sample(self, i):
        return self.db.sample(int(self.rows[i]))


def write_evaluation(result: Evaluation, out, mesh=None) -> Path:
    """``metrics.json``, ``per_sample.csv`` and (with a mesh) ``error_map.png`` in ``out``."""

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(result.metrics, indent=2))
    with atomic_path(out / "per_sample.csv") as tmp:
        result.per_sample.to_csv(tmp, index=False)
    if mesh is not None:
        from toolkit.common.plotting import render

        err = np.linalg.norm(result.predicted - result.truth, axis=-1).mean(axis=0)
        render(mesh, out / "error_map.png", scalars=err, camera="iso", cmap="magma",
               scalar_label="mean nodal error (mm)", title="surrogate error over the test samples")
    return out
