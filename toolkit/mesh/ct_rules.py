"""The values of the head-CT rules (:class:`CTRules`), their error (:class:`CTError`) and the
axes code of a volume (:func:`axes_code`): what the ``toolkit ct`` command line and the rules'
checks need, without the image processing of :mod:`toolkit.mesh.ct_anatomy`."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from toolkit.common.errors import ToolkitError

__all__ = ["CTError", "CTRules", "axes_code", "axes_text"]

_OPPOSITE = {"L": "R", "R": "L", "A": "P", "P": "A", "S": "I", "I": "S"}
_TOOLKIT = ("L", "A", "S")


class CTError(ToolkitError, ValueError):
    """A CT volume whose anatomy cannot be found, or rules that cannot apply to it."""


@dataclass(frozen=True)
class CTRules:
    """The values of the rules of :mod:`toolkit.mesh.ct` (lengths in mm, CT values in the
    volume's units).

    skin, bone : thresholds of the skin (air to soft tissue) and of bone
    teeth : threshold of the teeth; None: air + 2.4 (bone - air), air the volume's 1st percentile
    axes : the anatomical direction each index axis increases toward, e.g. ``"LPI"``; None: found
    lefort_mm : Le Fort I plane above the occlusal plane, parallel to it
    tuberosity_mm : tuberosity plane behind the last upper molar
    split_mm : sagittal split planes behind the last lower molar of each side
    occlusal_tilt_deg : the occlusal plane's inclination in the face's frame, anterior end down
        (its mean inclination to the Frankfort horizontal)
    occlusal_pitch_deg : the occlusal plane's tilt in the volume about the left-right axis
        (anterior end down positive); None: found from the teeth
    occlusal_shift_mm : the occlusal plane moved along its normal (superior positive)
    superior_mm : superior cut above the Le Fort I plane's highest point on the maxilla
    inferior_mm : inferior cut below the menton, parallel to the mandibular plane
    posterior_mm : posterior cut in front of the condyles (negative: behind them)
    depth_mm : largest depth of the tissue below the skin
    closing_mm : openings of the skin narrower than this are closed before cavities are filled
    lip_gap_mm : lips apart by less than this are closed
    tooth_gap_mm : gaps up to this tall between bone above and below (the incisors of a mouth
        slightly open) hide what lies behind them as bone does
    min_bone_piece : bone pieces smaller than this fraction of the largest are left out
    condyle_band_mm : the top of a proximal segment whose centre is its condyle
    """

    skin: float = 500.0
    bone: float = 1150.0
    teeth: float | None = None
    axes: str | None = None
    lefort_mm: float = 30.0
    tuberosity_mm: float = 5.0
    split_mm: float = 5.0
    occlusal_tilt_deg: float = 10.0
    occlusal_pitch_deg: float | None = None
    occlusal_shift_mm: float = 0.0
    superior_mm: float = 5.0
    inferior_mm: float = 10.0
    posterior_mm: float = 0.0
    depth_mm: float = 30.0
    closing_mm: float = 5.0
    lip_gap_mm: float = 10.0
    tooth_gap_mm: float = 12.0
    min_bone_piece: float = 0.05
    condyle_band_mm: float = 5.0

    def __post_init__(self):
        if self.axes is not None:
            axes_code(self.axes)
        for name in ("lefort_mm", "superior_mm", "inferior_mm", "depth_mm", "closing_mm", "lip_gap_mm",
                     "tooth_gap_mm", "condyle_band_mm"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise CTError(f"{name} = {value!r}; expected a length > 0 mm")
        for name in ("tuberosity_mm", "split_mm", "posterior_mm", "occlusal_shift_mm", "occlusal_tilt_deg"):
            if not np.isfinite(getattr(self, name)):
                raise CTError(f"{name} = {getattr(self, name)!r}; expected a finite number")
        if self.occlusal_pitch_deg is not None and not abs(self.occlusal_pitch_deg) < 60:
            raise CTError(f"occlusal_pitch_deg = {self.occlusal_pitch_deg!r}; expected a tilt of -60 to 60 degrees")
        if not self.bone > self.skin:
            raise CTError(f"bone threshold {self.bone!r} is not above the skin threshold {self.skin!r}; expected "
                          "skin < bone in the volume's units")
        if self.teeth is not None and not self.teeth > self.bone:
            raise CTError(f"teeth threshold {self.teeth!r} is not above the bone threshold {self.bone!r}; expected "
                          "the teeth denser than bone")
        if not 0 < self.min_bone_piece <= 1:
            raise CTError(f"min_bone_piece = {self.min_bone_piece!r}; expected a fraction in (0, 1]")

    def to_dict(self) -> dict:
        return asdict(self)


def axes_code(code: str) -> tuple[np.ndarray, np.ndarray]:
    """``"LPI"`` -> for each toolkit axis x, y, z: the index axis along it ``(3,)`` and its sign ``(3,)``."""
    text = str(code).upper()
    if len(text) != 3 or any(c not in _OPPOSITE for c in text) or \
            sorted(c if c in _TOOLKIT else _OPPOSITE[c] for c in text) != sorted(_TOOLKIT):
        raise CTError(f"axes = {code!r}; expected three letters, one of L/R, A/P, S/I each, naming the direction "
                      "index axes 0, 1, 2 increase toward (e.g. 'LPI' for headsq, 'LPS' for a DICOM series)")
    axis, sign = np.zeros(3, dtype=int), np.zeros(3)
    for i, c in enumerate(text):
        k = _TOOLKIT.index(c if c in _TOOLKIT else _OPPOSITE[c])
        axis[k], sign[k] = i, 1.0 if c in _TOOLKIT else -1.0
    return axis, sign


def axes_text(axis: np.ndarray, sign: np.ndarray) -> str:
    """The inverse of :func:`axes_code`: the index axis along each toolkit axis ``(3,)`` and its
    sign ``(3,)`` -> ``"LPI"``."""
    out = [""] * 3
    for k, c in enumerate(_TOOLKIT):
        out[axis[k]] = c if sign[k] > 0 else _OPPOSITE[c]
    return "".join(out)
