"""Model-agnostic training utilities shared by the surrogates (impact LSTM, static PointNet++).

- :class:`MinMaxScaler` (``scaling``): features to [0, 1], JSON round trip;
- :func:`generators`, :func:`torch_seeded` (``seeding``): seed control without global side effects;
- :func:`resolve_device` (``device``): ``cpu`` / ``cuda`` / ``auto``;
- :func:`split_groups` (``splits``): splits that keep simulations (groups) whole;
- :func:`train`, :class:`TrainConfig`, :class:`TrainResult` (``loop``): Adam, any loss, early
  stopping, atomic checkpoints, resume, tqdm;
- :class:`ModelBundle` (``bundle``): ``model.pt`` + ``config.json`` model directories that refuse
  data or configurations they were not built for;
- :func:`extrapolation`, :func:`describe_extrapolation` (``extrapolation``): whether an input lies
  outside the training data's range, per parameter;
- :func:`calibrate`, :class:`ConformalBound` (``conformal``): split-conformal calibration of an
  error estimate to a stated coverage.
- :func:`decide` (``decision``): who answers within a tolerance, the surrogate or the FE;
- the resumable HDF5 job database of both workflows' learning data (``database``).

Importing this package imports torch lazily (only the functions that need it do).
"""

from toolkit.common.config_diff import IncompatibleError
from toolkit.common.training.bundle import BUNDLE_FORMAT, ModelBundle
from toolkit.common.training.conformal import ConformalBound, calibrate
from toolkit.common.training.device import resolve_device
from toolkit.common.training.extrapolation import describe_extrapolation, extrapolation
from toolkit.common.training.loop import LR_SCHEDULES, TrainConfig, TrainResult, evaluate_loss, stop_reason, train
from toolkit.common.training.scaling import MinMaxScaler
from toolkit.common.training.seeding import check_seed, generators, torch_seeded
from toolkit.common.training.splits import group_counts, split_groups

__all__ = [
    "MinMaxScaler",
    "generators",
    "torch_seeded",
    "check_seed",
    "resolve_device",
    "split_groups",
    "group_counts",
    "TrainConfig",
    "LR_SCHEDULES",
    "TrainResult",
    "stop_reason",
    "train",
    "evaluate_loss",
    "ModelBundle",
    "BUNDLE_FORMAT",
    "IncompatibleError",
    "extrapolation",
    "describe_extrapolation",
    "ConformalBound",
    "calibrate",
]
