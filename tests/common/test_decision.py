"""Who answers within a tolerance, by one rule for both workflows: out of distribution, no
estimate, an estimate above the tolerance and failed checks each give the FE, in that order; the
checks run only when nothing else sends the question to the FE."""

import pytest

from toolkit.common.training.decision import check_tolerance, decide

INSIDE = {"outside": False, "reasons": []}
ESTIMATE = {"bound_mm": 0.4, "coverage": 0.9}
PASSED = {"passed": True, "problems": []}


def _decide(ood=INSIDE, estimate=ESTIMATE, checks=PASSED, tolerance=0.5):
    ran = []

    def run():
        ran.append(True)
        return checks

    return decide(tolerance, ood, estimate, run, no_estimate="another face"), bool(ran)


def test_the_surrogate_answers_within_the_tolerance():
    decision, ran = _decide()
    assert decision.surrogate and ran
    assert decision.reason == "estimated error 0.40 mm (at 90%) is within the tolerance 0.5 mm"


@pytest.mark.parametrize("kwargs, reason, ran", [
    (dict(ood={"outside": True, "reasons": ["velocity 60 mm/s beyond 20-50"]}, estimate={}),
     "out of distribution: velocity 60 mm/s beyond 20-50", False),
    (dict(estimate={}), "another face", False),
    (dict(tolerance=0.3), "estimated error 0.40 mm (at 90%) is above the tolerance 0.3 mm", False),
    (dict(checks={"passed": False, "problems": ["an element is inverted"]}),
     "the answer failed its checks: an element is inverted", True),
])
def test_each_reason_for_the_fe_in_order(kwargs, reason, ran):
    decision, checked = _decide(**kwargs)
    assert not decision.surrogate and decision.reason == reason and checked is ran


@pytest.mark.parametrize("value", [0, -1, float("nan"), float("inf"), True, "0.5", None])
def test_a_tolerance_that_is_not_a_positive_number_is_refused(value):
    with pytest.raises(ValueError, match=r"expected a positive number of mm \(e\.g\. 0\.5\)"):
        check_tolerance(value, 0.5)
    assert check_tolerance(2, 0.5) == 2.0
