"""Who answers a question asked within a tolerance: the surrogate or the FE.

Both workflows' ``answer`` (:func:`toolkit.static.trust.answer`, :func:`toolkit.impact.trust.answer`)
decide here, by the same rules in the same order: the FE answers when the inputs lie outside the
training data, when there is no error estimate (another face than the model's), when the
calibrated estimate exceeds the tolerance, or when the surrogate's answer fails its checks (run
last, only for an answer that would otherwise be given); the surrogate answers otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

__all__ = ["Decision", "decide", "check_tolerance"]


def check_tolerance(tolerance_mm, example: float) -> float:
    """``tolerance_mm`` as a float when it is a positive finite number of mm; ValueError naming it
    and an ``example`` value otherwise (before any computation)."""
    if isinstance(tolerance_mm, bool) or not isinstance(tolerance_mm, (int, float)) \
            or not math.isfinite(tolerance_mm) or tolerance_mm <= 0:
        raise ValueError(f"tolerance = {tolerance_mm!r} mm; expected a positive number of mm (e.g. {example:g})")
    return float(tolerance_mm)


@dataclass(frozen=True)
class Decision:
    """``surrogate``: whether the surrogate's answer stands; ``reason``: why, in one line."""

    surrogate: bool
    reason: str


def decide(tolerance_mm: float, ood: Mapping, estimate: Mapping, checks: Callable[[], Mapping], *,
           no_estimate: str) -> Decision:
    """The decision for one question.

    Parameters
    ----------
    tolerance_mm : mm, the largest error accepted (the 95th percentile of the nodal error)
    ood : the out-of-distribution verdict, ``{"outside": bool, "reasons": [str, ...]}``
    estimate : the calibrated error estimate, ``{"bound_mm": float, "coverage": float, ...}``, or
        empty when the surrogate could not be estimated
    checks : called only when everything else lets the surrogate answer; returns its answer's
        checks, ``{"passed": bool, "problems": [str, ...]}``
    no_estimate : the reason given when ``estimate`` is empty
    """
    if ood["outside"]:
        return Decision(False, "out of distribution: " + "; ".join(ood["reasons"]))
    if not estimate:
        return Decision(False, no_estimate)
    bound = f"estimated error {estimate['bound_mm']:.2f} mm (at {estimate['coverage']:.0%})"
    if estimate["bound_mm"] > tolerance_mm:
        return Decision(False, f"{bound} is above the tolerance {tolerance_mm:g} mm")
    result = checks()
    if not result["passed"]:
        return Decision(False, "the answer failed its checks: " + "; ".join(result["problems"]))
    return Decision(True, f"{bound} is within the tolerance {tolerance_mm:g} mm")
