"""Fidelity chosen by a tolerance: the fastest measured option within it.

The choice is checked against a brute-force scan of the committed ladder files, on a tiny
synthetic ladder whose answer is known by hand, for monotonicity (a looser tolerance never
picks a slower option), and for the refusals: below the most faithful option's own uncertainty,
a value the ladder did not measure, and tolerances that are not finite positive numbers.
"""

import math
from pathlib import Path

import pandas as pd
import pytest

from toolkit.common.fidelity import (
    FidelityError,
    Ladder,
    LadderSource,
    choose_fidelity,
    load_ladder,
    packaged_folder,
)

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
TOLERANCES = [0.13, 0.15, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 100.0]
#: the most faithful options' own uncertainties: the tolerances below them are refused
FLOORS = {w: load_ladder(w, RESULTS).uncertainty_mm for w in ("static", "impact")}


def _scan_static(tolerance):
    """The answer by hand from the CSV files: (ladder difference + resolution's difference to
    fine) within the tolerance, least wall time."""
    ladder = pd.read_csv(RESULTS / "static_ladder.csv")
    conv = pd.read_csv(RESULTS / "static_convergence.csv").set_index("pair")["p95_mm"]
    best = None
    for r in ladder.itertuples():
        if r.status != "ok" or math.isnan(r.p95_diff_mm):
            continue
        error = r.p95_diff_mm + conv[f"{r.resolution}-fine"]
        if error <= tolerance and (best is None or r.wall_time_s < best[0]):
            best = (r.wall_time_s, error, (r.resolution, r.material, r.increments, r.sliding))
    return best


def _scan_impact(tolerance):
    ladder = pd.read_csv(RESULTS / "impact_ladder.csv")
    rows = ladder[ladder.p95_displacement_mm.notna()]
    ok = rows[rows.p95_displacement_mm <= tolerance]
    if ok.empty:
        return None
    r = ok.loc[ok.wall_time_s.idxmin()]
    return r.wall_time_s, r.p95_displacement_mm, (r.order, r.ball, r.mass_scaling, r.integrator)


@pytest.fixture(scope="module")
def static_ladder():
    return load_ladder("static", RESULTS)


@pytest.fixture(scope="module")
def impact_ladder():
    return load_ladder("impact", RESULTS)


@pytest.mark.parametrize("tolerance", [t for t in TOLERANCES if t >= FLOORS["static"]])
def test_static_choice_is_the_brute_force_scan_of_the_results(static_ladder, tolerance):
    expected = _scan_static(tolerance)
    choice = choose_fidelity("static", tolerance, ladder=static_ladder)
    o = choice.options
    assert (o["resolution"], o["material"], o["increments"], o["sliding"]) == expected[2]
    assert choice.wall_time_s == expected[0] and choice.error_mm == pytest.approx(expected[1], rel=1e-12)
    assert choice.error_mm <= tolerance


@pytest.mark.parametrize("tolerance", [t for t in TOLERANCES if t >= FLOORS["impact"]])
def test_impact_choice_is_the_brute_force_scan_of_the_results(impact_ladder, tolerance):
    expected = _scan_impact(tolerance)
    choice = choose_fidelity("impact", tolerance, ladder=impact_ladder)
    o = choice.options
    assert (o["order"], o["ball"], o["mass_scaling"], o["integrator"]) == expected[2]
    assert choice.wall_time_s == expected[0] and choice.error_mm == expected[1] <= tolerance


@pytest.mark.parametrize("workflow, own_mesh", [("static", False), ("static", True), ("impact", False)])
def test_a_looser_tolerance_never_picks_a_slower_option(workflow, own_mesh):
    ladder = load_ladder(workflow, RESULTS, own_mesh=own_mesh)
    grid = [ladder.uncertainty_mm * (1 + k / 20) for k in range(200)]
    times = [choose_fidelity(workflow, t, ladder=ladder).wall_time_s for t in grid]
    assert all(b <= a for a, b in zip(times, times[1:])), times


def _tiny_ladder():
    """Three options: slow and exact, medium at 0.3 mm, fast at 1 mm; the reference's own 0.1 mm."""
    rows = pd.DataFrame({"speed": ["slow", "medium", "fast", "medium"], "mode": ["a", "a", "a", "b"],
                         "error_mm": [0.0, 0.3, 1.0, 0.2], "wall_time_s": [10.0, 2.0, 0.5, 3.0]})
    return Ladder("static", ("speed", "mode"), rows, "test metric", {"speed": "slow", "mode": "a"}, 0.1,
                  (LadderSource("tiny.csv", ("abc1234",), "2026-01-01"),), "on paper")


@pytest.mark.parametrize("tolerance, expected", [(0.1, ("slow", "a")), (0.25, ("medium", "b")),
                                                 (0.3, ("medium", "a")), (0.99, ("medium", "a")),
                                                 (1.0, ("fast", "a")), (50.0, ("fast", "a"))])
def test_tiny_ladder_choice(tolerance, expected):
    """medium/b (0.2 mm, 3 s) until medium/a (0.3 mm, 2 s) fits too, then the faster one."""
    choice = choose_fidelity("static", tolerance, ladder=_tiny_ladder())
    assert (choice.options["speed"], choice.options["mode"]) == expected


def test_a_given_option_is_kept_and_the_choice_is_among_its_rows():
    ladder = _tiny_ladder()
    assert choose_fidelity("static", 0.25, {"mode": "b"}, ladder=ladder).options == {"speed": "medium", "mode": "b"}
    choice = choose_fidelity("static", 2.0, {"mode": "a", "speed": "slow"}, ladder=ladder)
    assert choice.options == {"speed": "slow", "mode": "a"} and choice.fixed == {"mode": "a", "speed": "slow"}
    with pytest.raises(FidelityError, match=r"no measured static option with mode b is within 0.15 mm: the most "
                                            r"accurate, speed medium, mode b, has 0.2 mm. Give a tolerance of at "
                                            r"least 0.2 mm, or leave those options"):
        choose_fidelity("static", 0.15, {"mode": "b"}, ladder=ladder)
    with pytest.raises(FidelityError, match=r"did not measure mode = 'c' \(measured: a, b\); give one of these"):
        choose_fidelity("static", 1.0, {"mode": "c"}, ladder=ladder)
    with pytest.raises(ValueError, match="option 'colour' is not in the ladder"):
        choose_fidelity("static", 1.0, {"colour": "red"}, ladder=ladder)


def test_a_tolerance_below_the_reference_uncertainty_is_refused_with_it(static_ladder, impact_ladder):
    """The floors are the paper face's 95th percentile skin difference to the fine one (static) and
    the reference's against its own mirror image (impact); below them a tolerance is refused,
    naming the floor and the smallest tolerance accepted."""
    assert static_ladder.uncertainty_mm == pytest.approx(
        pd.read_csv(RESULTS / "static_convergence.csv").set_index("pair").loc["paper-fine", "p95_mm"])
    ladder = pd.read_csv(RESULTS / "impact_ladder.csv")
    reference = ladder[(ladder.integrator == "explicit") & (ladder.p95_displacement_mm == 0)]
    assert impact_ladder.uncertainty_mm == pytest.approx(float(reference.reference_asymmetry_p95_mm.iloc[0]))
    for workflow, ladder, text in (("static", static_ladder, "its 95th percentile skin difference to the fine"),
                                   ("impact", impact_ladder, "the reference's own left-right asymmetry")):
        floor = ladder.uncertainty_mm
        tolerance = float(f"{0.5 * floor:.2g}")
        with pytest.raises(FidelityError, match=rf"tolerance {tolerance:g} mm is below the uncertainty of the most "
                                                rf"faithful {workflow} option .*: {floor:.3g} mm \({text}.* at least"):
            choose_fidelity(workflow, tolerance, ladder=ladder)
    assert impact_ladder.reference == {"order": 2, "ball": "deformable", "mass_scaling": 1.0, "safety": 0.9,
                                       "integrator": "explicit"}


@pytest.mark.parametrize("bad", [0, 0.0, -1.0, float("nan"), float("inf"), "1", None, True])
def test_a_tolerance_that_is_not_a_finite_positive_number_is_refused(bad):
    with pytest.raises(ValueError, match=r"expected a finite number of mm > 0, e.g. 0.5"):
        choose_fidelity("static", bad, ladder=_tiny_ladder())


def test_own_mesh_chooses_among_the_paper_phantoms_options_without_the_resolution():
    """On a user's mesh the resolution is not an option; the error is the paper phantom's
    within-resolution difference, and the record says where it was measured."""
    choice = choose_fidelity("static", 0.5, own_mesh=True, ladder=load_ladder("static", RESULTS, own_mesh=True))
    assert set(choice.options) == {"material", "increments", "sliding"}
    ladder = pd.read_csv(RESULTS / "static_ladder.csv")
    paper = ladder[(ladder.resolution == "paper") & (ladder.p95_diff_mm <= 0.5)]
    fastest = paper.loc[paper.wall_time_s.idxmin()]
    assert (choice.options["material"], choice.options["increments"], choice.options["sliding"]) == (
        fastest.material, fastest.increments, fastest.sliding)
    assert "not on this mesh" in choice.measured_on and "not included" in choice.metric


def test_the_packaged_copy_is_the_results_and_the_record_names_its_sources():
    """The package's ladder files equal benchmarks/results (report.py --check also fails
    otherwise), and a choice's record carries the file, commits and date of its provenance."""
    for name in ("static_ladder.csv", "static_ladder.json", "static_convergence.csv", "impact_ladder.csv"):
        assert (packaged_folder() / name).read_bytes() == (RESULTS / name).read_bytes(), name
    record = choose_fidelity("static", 0.5).record()
    assert [s["file"] for s in record["sources"]] == ["static_ladder.csv", "static_convergence.csv"]
    assert all(s["commits"] and s["date"].startswith("20") for s in record["sources"])
    assert {"tolerance_mm", "options", "error_mm", "metric", "reference", "uncertainty_mm", "wall_time_s"} <= set(
        record)
    assert "fidelity for 0.5 mm" in choose_fidelity("static", 0.5).describe()
