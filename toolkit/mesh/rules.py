"""The labelling rules of :func:`toolkit.mesh.label_face`: defaults and TOML overrides.

The defaults follow the phantom's anatomy (``docs/phantom.md``) in terms any segmented face
has: where the tissue faces a bone, which segments carry it, which mucosa slides, and where
the model was truncated. A TOML file overrides any of them, e.g.::

    contact_mm = 4.0              # tissue up to 4 mm off a bone counts as lying on it
    lip_muscle_mm = 15.0          # the orbicularis oris reaches 15 mm above and below the mouth

    [cuts]
    directions = [[0, -1, 0], [0, 0, 1]]   # posterior and superior truncation planes
    margin_mm = 3.0

    [segments.distal]
    attach = "inferior"           # anterior | inferior | all | none
    inferior_fraction = 0.4

Every key is checked: an unknown key or a value of the wrong kind raises
:class:`RulesError` naming the file and the key.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from toolkit.common.defaults import MIN_CARRIED_MM2, MIN_CARRIED_SHARE
from toolkit.common.errors import ToolkitError

__all__ = ["RulesError", "SegmentRule", "CutRule", "LabelRules", "read_rules", "ATTACH_MODES", "SEGMENTS"]

#: bony segments a face can be labelled against, in the order their sets are claimed
SEGMENTS = ("lefort", "distal", "proximal_left", "proximal_right", "skull")
#: how a segment holds the tissue facing it
ATTACH_MODES = ("anterior", "inferior", "all", "none", "fixed")


class RulesError(ToolkitError, ValueError):
    """A labelling rule file or value that cannot be used."""


@dataclass(frozen=True)
class SegmentRule:
    """Which tissue facing a segment's bone is carried by it (the rest slides on it).

    attach : ``anterior`` (within ``anterior_deg`` of the midline, seen from above, about the
        centre of the circle fitted to the segment's bone surface: its dental arch),
        ``inferior`` (the lowest ``inferior_fraction`` of the height of the tissue facing
        it), ``all``, ``none`` (all slides), or ``fixed`` (held
        in place with the ``fixed`` set: an immobile segment)
    border_mm : carried tissue lies at least this far from the tissue on every other moving
        segment's bone (the osteotomy line as the tissue sees it); nearer, it slides (the
        vestibule at the occlusal level, the degloved borders)
    """

    attach: str = "none"
    anterior_deg: float = 40.0
    inferior_fraction: float = 0.3
    border_mm: float = 10.0


@dataclass(frozen=True)
class CutRule:
    """Truncation planes of the model, held ``fixed``: boundary faces whose outward normal is
    within ``max_angle_deg`` of one of ``directions`` and that lie within ``margin_mm`` of the
    mesh's extreme in that direction (x left, y anterior, z superior). A cut face is held only
    if it lies at least ``clear_of_moving_mm`` from the tissue on every moving bone (nearer, as
    behind the ramus, the tissue follows the bone it covers)."""

    directions: tuple[tuple[float, float, float], ...] = ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0))
    margin_mm: float = 3.0
    max_angle_deg: float = 35.0
    clear_of_moving_mm: float = 10.0


def _default_segments() -> dict[str, SegmentRule]:
    return {"lefort": SegmentRule("anterior"), "distal": SegmentRule("inferior", border_mm=0.0),
            "proximal_left": SegmentRule("none"), "proximal_right": SegmentRule("none"),
            "skull": SegmentRule("none")}


@dataclass(frozen=True)
class LabelRules:
    """All labelling rules (see the module for the TOML form).

    contact_mm : a tissue boundary face within this distance of a bone, parallel to it (within
        ``facing_deg``) with the bone on its outer side, lies on that bone (``bone`` set). A
        segmentation leaves the tissue's inner surface up to 5 mm off the bone (the periosteum
        and submucosa fall between the two thresholds, smoothing lifts the surface off concave
        bone); the skin, 10 mm or more from the jaws, never faces a bone
    facing_deg : largest angle between the tissue face's plane and the bone's at its closest
        point (either winding of the bone)
    touch_mm : how far behind a tissue face its bone may lie and the face still lie on it
        (a face sunk into the bone by the segmentation's voxel staircase); the skin, with the
        bone its whole thickness behind it, never does
    segments : per bony segment, its :class:`SegmentRule`
    cuts : the truncation planes held fixed
    lip_muscle_mm : with commissures, elements within this distance above or below the
        mouth slit (and in front of the commissures' line) form ``lip_muscle``, the
        orbicularis oris (the phantom's: 18 mm for its 90 mm face height)
    lip_muscle_lateral : how far ``lip_muscle`` reaches beyond each commissure, as a fraction
        of the mouth's width (the phantom's: 0.125)
    min_carried_mm2 : the least tissue boundary area (mm^2, lumped nodal area) that the Le Fort I
        and distal segments must carry when ruled to carry any (``attach`` other than ``none``
        and ``fixed``); less fails the labelling (see
        :data:`toolkit.common.defaults.MIN_CARRIED_MM2` for how it was set)
    min_carried_share : the least share of the tissue lying on such a segment's bone that it
        must carry (``carried_share`` in ``labels.json``); less fails the labelling (see
        :data:`toolkit.common.defaults.MIN_CARRIED_SHARE`)
    """

    contact_mm: float = 6.0
    facing_deg: float = 60.0
    touch_mm: float = 1.0
    segments: dict[str, SegmentRule] = field(default_factory=_default_segments)
    cuts: CutRule = field(default_factory=CutRule)
    lip_muscle_mm: float = 18.0
    lip_muscle_lateral: float = 0.125
    min_carried_mm2: float = MIN_CARRIED_MM2
    min_carried_share: float = MIN_CARRIED_SHARE

    def __post_init__(self):
        for key in ("contact_mm", "touch_mm", "lip_muscle_mm"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise RulesError(f"{key} = {v!r}; expected a positive number of mm")
        if not (isinstance(self.min_carried_mm2, (int, float)) and self.min_carried_mm2 >= 0):
            raise RulesError(f"min_carried_mm2 = {self.min_carried_mm2!r}; expected an area >= 0 mm^2")
        if not (isinstance(self.min_carried_share, (int, float)) and 0 <= self.min_carried_share <= 1):
            raise RulesError(f"min_carried_share = {self.min_carried_share!r}; expected a share in [0, 1]")
        if not (isinstance(self.lip_muscle_lateral, (int, float)) and 0 <= self.lip_muscle_lateral <= 1):
            raise RulesError(f"lip_muscle_lateral = {self.lip_muscle_lateral!r}; expected a fraction of the mouth's "
                             "width in [0, 1]")
        if not 0 < self.facing_deg <= 90:
            raise RulesError(f"facing_deg = {self.facing_deg!r}; expected an angle in (0, 90] degrees")
        for name, rule in self.segments.items():
            if name not in SEGMENTS:
                raise RulesError(f"segments.{name}: unknown segment; expected one of {list(SEGMENTS)}")
            if rule.attach not in ATTACH_MODES:
                raise RulesError(f"segments.{name}.attach = {rule.attach!r}; expected one of {list(ATTACH_MODES)}")
            if rule.attach not in ("none", "fixed") and name not in ("lefort", "distal"):
                raise RulesError(f"segments.{name}.attach = {rule.attach!r}: only lefort and distal carry tissue "
                                 "(sets maxilla, mandible); expected 'none' (slides) or 'fixed'")
            if not 0 < rule.inferior_fraction <= 1:
                raise RulesError(f"segments.{name}.inferior_fraction = {rule.inferior_fraction!r}; expected (0, 1]")
            if not 0 < rule.anterior_deg <= 180:
                raise RulesError(f"segments.{name}.anterior_deg = {rule.anterior_deg!r}; expected (0, 180] degrees")
        for d in self.cuts.directions:
            if len(d) != 3 or math.hypot(*d) == 0:
                raise RulesError(f"cuts.directions: {list(d)!r}; expected non-zero [x, y, z] vectors")

    def to_dict(self) -> dict:
        out = asdict(self)
        out["cuts"]["directions"] = [list(d) for d in self.cuts.directions]
        return out


def _typed(value, default, where: str):
    """``value`` checked against the type of ``default``."""
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, (int, float)):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(default, str):
        ok = isinstance(value, str)
    elif isinstance(default, tuple):
        ok = isinstance(value, list) and all(isinstance(v, list) and len(v) == 3 and all(
            isinstance(c, (int, float)) for c in v) for v in value)
        value = tuple(tuple(float(c) for c in v) for v in value) if ok else value
    else:
        ok = True
    if not ok:
        kind = "a list of [x, y, z]" if isinstance(default, tuple) else type(default).__name__
        raise RulesError(f"{where} = {value!r}; expected {kind}")
    return value


def _apply(obj, table: dict, where: str):
    known = {f.name: f for f in fields(obj)}
    changes = {}
    for key, value in table.items():
        if key not in known:
            raise RulesError(f"unknown key {where + key!r}; expected one of {sorted(where + k for k in known)}")
        changes[key] = _typed(value, getattr(obj, key), f"{where}{key}")
    return replace(obj, **changes)


def read_rules(source: str | Path | dict | None = None) -> LabelRules:
    """Labelling rules: the defaults, overridden by a TOML file (or an already-parsed dict)."""
    if source is None:
        return LabelRules()
    if isinstance(source, dict):
        table, name = source, "rules"
    else:
        import tomllib

        from toolkit.common.meshes.io import read_text

        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"labelling rules {str(path)!r} do not exist; expected a TOML file")
        text = read_text(path, RulesError, "TOML labelling rules", name=path.name)
        try:
            table = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise RulesError(f"labelling rules {path.name}: {exc}; expected TOML (see toolkit.mesh.rules)") from None
        name = path.name
    base = LabelRules()
    top = {k: v for k, v in table.items() if k not in ("segments", "cuts")}
    try:
        rules = _apply(base, top, "")
        if "cuts" in table:
            rules = replace(rules, cuts=_apply(base.cuts, _table(table["cuts"], "cuts"), "cuts."))
        if "segments" in table:
            segments = dict(rules.segments)
            for seg, sub in _table(table["segments"], "segments").items():
                if seg not in SEGMENTS:
                    raise RulesError(f"segments.{seg}: unknown segment; expected one of {list(SEGMENTS)}")
                segments[seg] = _apply(segments.get(seg, SegmentRule()), _table(sub, f"segments.{seg}"),
                                       f"segments.{seg}.")
            rules = replace(rules, segments=segments)
    except RulesError as exc:
        raise RulesError(f"{name}: {exc}") from None
    return rules


def _table(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise RulesError(f"{where} = {value!r}; expected a table")
    return value
