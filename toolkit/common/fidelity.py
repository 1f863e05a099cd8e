"""Fidelity chosen by a tolerance: the cheapest measured option whose error is within it.

The speed/accuracy ladders of ``benchmarks/`` run every fidelity option of a workflow on a
phantom and measure its wall time and its error against the most faithful option. A copy of
their results ships with the package (``toolkit/common/data/ladders/``, written from
``benchmarks/results/`` by ``python benchmarks/report.py``, which also checks it), so
:func:`choose_fidelity` works from an installed package.

Every error is the quantity a ``--tolerance`` bounds everywhere in the toolkit: the 95th
percentile over the nodes (and over the frames, for impact) of the nodal displacement error, mm
(the predict commands bound the same quantity of a surrogate's answer).

Static (``static_ladder.csv``, ``static_convergence.csv``): each option is a resolution
(``coarse``, ``paper``), material, increment count and sliding model. Its error is the 95th
percentile over the nodes of its displacement difference (mm) to the Neo-Hookean, 10-increment,
mucosa + lip run of the same resolution, plus that resolution's 95th percentile skin difference
to the fine phantom (at the skin points the two meshes share): an estimate of its difference to
the most faithful model on the fine face, not a bound (a percentile of a sum can exceed the sum
of the percentiles). It assumes the resolution's difference to fine (measured with the default
model at full plan scale) holds for the ladder's half-scale plan and for the Neo-Hookean
reference. The most faithful option (paper, Neo-Hookean, 10 increments, mucosa + lip) has its
own discretization error, the paper face's difference to the fine one: a tolerance below it is
refused. On a mesh of the user's (``own_mesh=True``) the resolution is the user's: the options
are material, increments and sliding, their error is the paper phantom's within-resolution
difference alone (the mesh's own discretization error is not measured), and the refusal floor
stays the paper phantom's discretization error.

Impact (``impact_ladder.csv``): each option is an element order, a rigid or deformable ball,
a mass scaling, a time-step safety factor and the integrator, measured on the coarse face
(30 mm/s, 1.8 s). Its error is the 95th percentile over the corner nodes and the frames of its
displacement difference (mm) to the reference (tet10, deformable ball, no mass scaling,
explicit); the reference's own left-right asymmetry on the mirror-symmetric scene (the same
percentile against its mirror image) is its uncertainty, and a tolerance below it is refused.
The face's resolution is not an option: the ladder has no reference at another one.
"""

from __future__ import annotations

import json
import math
import numbers
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from toolkit.common.errors import ToolkitError

__all__ = ["FidelityError", "Ladder", "LadderSource", "FidelityChoice", "LADDER_FILES", "load_ladder",
           "ladder_from_tables", "choose_fidelity", "packaged_folder"]

#: the result tables each workflow's ladder is built from (``<stem>.csv`` and ``<stem>.json``)
LADDER_FILES = {"static": ("static_ladder", "static_convergence"), "impact": ("impact_ladder",)}
#: the phantom resolution whose ladder rows stand for a user's own mesh (the most faithful measured)
OWN_MESH_PHANTOM = "paper"
STATIC_OPTIONS = ("resolution", "material", "increments", "sliding")
IMPACT_OPTIONS = ("order", "ball", "mass_scaling", "safety", "integrator")


class FidelityError(ToolkitError, ValueError):
    """No measured option meets a tolerance, or the tolerance is below what the ladder can tell."""


@dataclass(frozen=True)
class LadderSource:
    """A result file a ladder rests on: its name, the commits and the date (ISO, last run) of
    the runs that measured it (its provenance sidecar)."""

    file: str
    commits: tuple[str, ...]
    date: str

    @classmethod
    def from_sidecar(cls, stem: str, sidecar: dict) -> LadderSource:
        prov = sidecar.get("provenance", {})
        runs = sidecar.get("runs") or [{"commit": prov.get("git", {}).get("commit", "unknown"),
                                        "date": prov.get("date", "")}]
        commits = tuple(dict.fromkeys(r["commit"][:7] for r in runs))
        return cls(f"{stem}.csv", commits, max(r["date"] for r in runs))


@dataclass(frozen=True, eq=False)
class Ladder:
    """The measured options of one workflow.

    Attributes
    ----------
    workflow : ``static`` or ``impact``
    options : the option names, columns of ``rows``
    rows : DataFrame, one measured option a row: the option columns, ``error_mm`` (mm, against
        the most faithful option) and ``wall_time_s`` (s, on the machine of the provenance)
    metric : what ``error_mm`` measures (one sentence)
    reference : option name -> value of the most faithful option
    uncertainty_mm : mm, the most faithful option's own error: the smallest tolerance accepted
    sources : the result files, with their commits and dates
    measured_on : where the ladder ran (the phantom, its scene)
    """

    workflow: str
    options: tuple[str, ...]
    rows: object  # pandas.DataFrame
    metric: str
    reference: dict
    uncertainty_mm: float
    sources: tuple[LadderSource, ...]
    measured_on: str


@dataclass(frozen=True)
class FidelityChoice:
    """The cheapest measured option within a tolerance.

    Attributes
    ----------
    workflow : ``static`` or ``impact``
    tolerance_mm : the tolerance asked, mm
    options : option name -> value chosen (static: ``resolution`` unless on a user's mesh,
        ``material``, ``increments``, ``sliding``; impact: ``order``, ``ball``, ``mass_scaling``,
        ``safety``, ``integrator``)
    error_mm : its measured error, mm (``metric``)
    metric : what ``error_mm`` measures
    reference : option name -> value of the most faithful option the error is measured against
    uncertainty_mm : the most faithful option's own error, mm
    wall_time_s : the wall time of its ladder row, s
    sources : the result files the choice rests on
    measured_on : where the ladder ran
    fixed : the options given by the user, which the choice kept
    """

    workflow: str
    tolerance_mm: float
    options: dict
    error_mm: float
    metric: str
    reference: dict
    uncertainty_mm: float
    wall_time_s: float
    sources: tuple[LadderSource, ...]
    measured_on: str
    fixed: dict = field(default_factory=dict)

    def describe(self) -> str:
        """One line for the console: the choice, its error and time, and what they rest on."""
        files = "; ".join(f"{s.file} at {', '.join(s.commits)}, {s.date[:10]}" for s in self.sources)
        return (f"fidelity for {self.tolerance_mm:g} mm: {_options_text(self.options)}; measured error "
                f"{self.error_mm:.3g} mm against {_options_text(self.reference)} (its own uncertainty "
                f"{self.uncertainty_mm:.3g} mm), {self.wall_time_s:.3g} s in the ladder, {self.measured_on} ({files})")

    def record(self) -> dict:
        """The ``fidelity`` block of a run's ``summary.json`` (JSON-ready; mm, s)."""
        return {"tolerance_mm": self.tolerance_mm, "options": dict(self.options), "fixed": dict(self.fixed),
                "error_mm": self.error_mm, "metric": self.metric, "reference": dict(self.reference),
                "uncertainty_mm": self.uncertainty_mm, "wall_time_s": self.wall_time_s,
                "measured_on": self.measured_on,
                "sources": [{"file": s.file, "commits": list(s.commits), "date": s.date} for s in self.sources]}


def _options_text(options: dict) -> str:
    return ", ".join(f"{k} {_plain(v):g}" if isinstance(v, float) else f"{k} {v}" for k, v in options.items())


def _plain(v):
    return v.item() if hasattr(v, "item") else v


def packaged_folder() -> Path:
    """The folder of the ladder copies shipped with the package."""
    return Path(str(resources.files("toolkit.common") / "data" / "ladders"))


def load_ladder(workflow: str, folder: str | Path | None = None, *, own_mesh: bool = False) -> Ladder:
    """The ladder of ``workflow`` from the result files in ``folder`` (default: the packaged
    copy; ``benchmarks/results`` reads the repository's). ``own_mesh``: the options that apply
    to a user's mesh (see the module's docstring)."""
    if workflow not in LADDER_FILES:
        raise ValueError(f"workflow {workflow!r}; expected one of {list(LADDER_FILES)}")
    import pandas as pd

    folder = packaged_folder() if folder is None else Path(folder)
    tables = {}
    for stem in LADDER_FILES[workflow]:
        csv = folder / f"{stem}.csv"
        if not csv.is_file():
            raise FileNotFoundError(f"ladder result {csv} does not exist; expected the results of "
                                    f"benchmarks/{stem}.py (python benchmarks/report.py copies them into the package)")
        side = csv.with_suffix(".json")
        tables[stem] = (pd.read_csv(csv), json.loads(side.read_text()) if side.is_file() else {})
    return ladder_from_tables(workflow, tables, own_mesh=own_mesh)


def ladder_from_tables(workflow: str, tables: dict, *, own_mesh: bool = False) -> Ladder:
    """The ladder of ``workflow`` from ``{stem: (DataFrame, sidecar)}`` of its result files."""
    sources = tuple(LadderSource.from_sidecar(stem, tables[stem][1]) for stem in LADDER_FILES[workflow])
    if workflow == "static":
        return _static_ladder(tables, sources, own_mesh)
    if workflow == "impact":
        return _impact_ladder(tables, sources, own_mesh)
    raise ValueError(f"workflow {workflow!r}; expected one of {list(LADDER_FILES)}")


def _static_ladder(tables: dict, sources, own_mesh: bool) -> Ladder:
    ladder, _ = tables["static_ladder"]
    convergence, _ = tables["static_convergence"]
    to_fine = {pair.split("-")[0]: float(p95) for pair, p95 in zip(convergence["pair"], convergence["p95_mm"])
               if pair.endswith("-fine")}
    rows = ladder[(ladder["status"] == "ok") & ladder["p95_diff_mm"].notna()
                  & ladder["resolution"].isin(list(to_fine))].copy()
    within = ("95th percentile over the nodes of the displacement difference (mm) to Neo-Hookean, 10 increments, "
              "mucosa+lip")
    if own_mesh:
        rows = rows[rows["resolution"] == OWN_MESH_PHANTOM]
        rows["error_mm"] = rows["p95_diff_mm"]
        options = STATIC_OPTIONS[1:]
        metric = f"{within} on the same mesh (measured on the {OWN_MESH_PHANTOM} phantom; the mesh's own " \
                 "discretization error is not included)"
        measured_on = f"measured on the {OWN_MESH_PHANTOM} phantom, not on this mesh"
    else:
        rows["error_mm"] = rows["p95_diff_mm"] + rows["resolution"].map(to_fine)
        options = STATIC_OPTIONS
        metric = (f"{within} of the same resolution, plus that resolution's 95th percentile skin difference to the "
                  "fine phantom: an estimate of the difference to the most faithful model on the fine face")
        measured_on = "measured on the phantom"
    rows = rows[[*options, "error_mm", "wall_time_s"]]
    best = rows.loc[rows["error_mm"].idxmin()]
    reference = {k: _plain(best[k]) for k in options}
    resolution = best["resolution"] if "resolution" in best else OWN_MESH_PHANTOM
    return Ladder("static", options, rows.reset_index(drop=True), metric, reference, to_fine[resolution], sources,
                  measured_on)


def _impact_ladder(tables: dict, sources, own_mesh: bool) -> Ladder:
    ladder, _ = tables["impact_ladder"]
    rows = ladder[(ladder["status"] == "ok") & ladder["p95_displacement_mm"].notna()].copy()
    rows["error_mm"] = rows["p95_displacement_mm"]
    best = rows.loc[rows["error_mm"].idxmin()]
    # each (face, speed, duration) of the ladder has its own reference: keep the one of ``best``
    rows = rows[(rows["resolution"] == best["resolution"]) & (rows["velocity"] == best["velocity"])
                & (rows["duration"] == best["duration"])]
    scene = f"the {best['resolution']} phantom face at {best['velocity']:g} mm/s for {best['duration']:g} s"
    metric = (f"95th percentile over the nodes and frames of the displacement difference (mm) to the reference, "
              f"on {scene}"
              + ("; the mesh's own discretization error is not included" if own_mesh else ""))
    measured_on = f"measured on {scene}" + (", not on this mesh" if own_mesh else "")
    reference = {k: _plain(best[k]) for k in IMPACT_OPTIONS}
    rows = rows[[*IMPACT_OPTIONS, "error_mm", "wall_time_s"]].reset_index(drop=True)
    return Ladder("impact", IMPACT_OPTIONS, rows, metric, reference, float(best["reference_asymmetry_p95_mm"]), sources,
                  measured_on)


def choose_fidelity(workflow: str, tolerance_mm: float, fixed: dict | None = None, *, own_mesh: bool = False,
                    ladder: Ladder | None = None) -> FidelityChoice:
    """The cheapest measured option of ``workflow`` whose error is within ``tolerance_mm``.

    Parameters
    ----------
    workflow : ``static`` or ``impact``
    tolerance_mm : mm, a finite number > 0, no smaller than the most faithful option's own
        uncertainty (:attr:`Ladder.uncertainty_mm`)
    fixed : option name -> value the user gave: the choice is among the rows with these values
    own_mesh : the run is on a user's mesh, not the phantom (static: the resolution is not an
        option; both: the error was measured on the phantom)
    ladder : default :func:`load_ladder` of the packaged copy

    Returns
    -------
    FidelityChoice — the row of least ``wall_time_s`` among those with ``error_mm <=
    tolerance_mm`` (ties: the smaller error). A looser tolerance never picks a slower row.

    Raises
    ------
    ValueError for a tolerance that is not a finite number > 0 or an option the ladder does not
    have; FidelityError for a tolerance below the uncertainty, a fixed value the ladder did not
    measure, or no row within the tolerance (each message gives the remedy).
    """
    tolerance = _checked_tolerance(tolerance_mm)
    ladder = ladder or load_ladder(workflow, own_mesh=own_mesh)
    if tolerance < ladder.uncertainty_mm:
        raise FidelityError(
            f"tolerance {tolerance:g} mm is below the uncertainty of the most faithful {workflow} option "
            f"({_options_text(ladder.reference)}): {ladder.uncertainty_mm:.3g} mm ({_uncertainty_text(workflow)}); "
            f"no measured option can be shown to be within it. Give a tolerance of at least "
            f"{_ceil(ladder.uncertainty_mm)} mm")
    fixed = {k: _plain(v) for k, v in (fixed or {}).items()}
    rows, applied = ladder.rows, {}
    for name, value in fixed.items():
        if name not in ladder.options:
            raise ValueError(f"{workflow} fidelity option {name!r} is not in the ladder; expected one of "
                             f"{list(ladder.options)}")
        measured = sorted({_plain(v) for v in rows[name]})
        before = _options_text(applied)
        rows, applied[name] = rows[rows[name] == value], value
        if rows.empty:
            raise FidelityError(f"the {workflow} ladder did not measure {name} = {value!r}"
                                f"{' with ' + before if before else ''} (measured: {', '.join(map(str, measured))}); "
                                f"give one of these, or leave {name} to the tolerance")
    within = rows[rows["error_mm"] <= tolerance]
    if within.empty:
        best = rows.loc[rows["error_mm"].idxmin()]
        given = f" with {_options_text(fixed)}" if fixed else ""
        raise FidelityError(
            f"no measured {workflow} option{given} is within {tolerance:g} mm: the most accurate, "
            f"{_options_text({k: _plain(best[k]) for k in ladder.options})}, has {best['error_mm']:.3g} mm. Give a "
            f"tolerance of at least {_ceil(best['error_mm'])} mm" + (", or leave those options to the tolerance"
                                                                      if fixed else ""))
    pick = within.sort_values(["wall_time_s", "error_mm"], kind="stable").iloc[0]
    return FidelityChoice(workflow, tolerance, {k: _plain(pick[k]) for k in ladder.options}, float(pick["error_mm"]),
                          ladder.metric, dict(ladder.reference), ladder.uncertainty_mm, float(pick["wall_time_s"]),
                          ladder.sources, ladder.measured_on, fixed)


def _uncertainty_text(workflow: str) -> str:
    if workflow == "static":
        return "its 95th percentile skin difference to the fine phantom"
    return "the reference's own left-right asymmetry on the mirror-symmetric scene"


def _ceil(value: float) -> str:
    """``value`` rounded up to two significant figures, as text."""
    if value <= 0:
        return "0"
    step = 10 ** (math.floor(math.log10(value)) - 1)
    return f"{math.ceil(value / step - 1e-9) * step:.10g}"


def _checked_tolerance(value) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"tolerance = {value!r}; expected a finite number of mm > 0, e.g. 0.5 "
                         "(command line: --tolerance 0.5)")
    return float(value)
