"""Whether a model's input lies outside its training data, parameter by parameter.

A model records the range ``[min, max]`` of each input parameter over its training data
(static: the plan parameters; impact: the ball's velocity); :func:`extrapolation` compares an
input with those ranges and :func:`describe_extrapolation` says the result in one line. The
predictions' ``summary.json`` hold the dict; the CLI prints the line.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["extrapolation", "describe_extrapolation"]


def extrapolation(values: Mapping[str, float], ranges: Mapping[str, list] | None, what: str = "inputs") -> dict:
    """Each parameter of ``values`` outside its training range in ``ranges`` (name -> [min, max]).

    Returns ``{"outside": bool, "parameters": {name: {"value", "train_range", "outside_by"}}}``
    listing only the parameters outside their range (``outside_by`` > 0, in the parameter's
    unit); ``{"outside": "unknown", ...}`` with a ``note`` when ``ranges`` is empty or None (a
    model that does not record them; ``what`` names them in the note).
    """
    if not ranges:
        return {"outside": "unknown", "parameters": {},
                "note": f"the model does not record the range of its training {what} (retrain it to record them)"}
    out = {}
    for name, value in values.items():
        if name not in ranges:
            raise KeyError(f"no training range for {name!r}; the model records {sorted(ranges)}")
        lo, hi = (float(v) for v in ranges[name])
        value = float(value)
        by = max(lo - value, value - hi, 0.0)
        if by > 1e-9 * max(1.0, abs(lo), abs(hi)):
            out[name] = {"value": value, "train_range": [lo, hi], "outside_by": by}
    return {"outside": bool(out), "parameters": out}


def describe_extrapolation(ex: Mapping) -> str:
    """One line: ``"inside the training data"``, or each parameter outside with its value,
    training range and distance, or why it is unknown."""
    if ex.get("outside") == "unknown":
        return f"training range unknown: {ex.get('note', 'the model does not record it')}"
    if not ex.get("outside"):
        return "inside the training data"
    parts = [f"{name} = {p['value']:.4g} (trained {p['train_range'][0]:.4g} to {p['train_range'][1]:.4g}, "
             f"{p['outside_by']:.3g} outside)" for name, p in ex["parameters"].items()]
    return "OUTSIDE the training data, the model extrapolates: " + "; ".join(parts)
