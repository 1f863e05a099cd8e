"""A declarative description of an impact scene (the impact paper), loadable from TOML.

A :class:`Scene` says *what* is simulated; :func:`toolkit.impact.simulate.simulate`
builds only what it asks for (no ball mesh for a rigid ball, no return mapping for an
elastic material, no contact search while the bodies are apart).

Defaults reproduce the impact paper: face E = 0.015 MPa, nu = 0.49, density 1e-9 tonne/mm^3
with its yield table; rubber ball E = 0.38 MPa, nu = 0.39 with its table, radius
110 mm and 0.43 kg; the lower face fixed; the ball driven horizontally into the face at
30 mm/s for 1.8 s; Coulomb friction 0.2 with penalty tangential and "hard" (penalty)
normal contact; 10-node tetrahedra.

Units: mm, s, tonne, MPa.
"""

from __future__ import annotations

import difflib
import os
import tomllib
from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from toolkit.common import papers
from toolkit.common.errors import ToolkitError
from toolkit.common.meshes.axes import AXES
from toolkit.common.meshes.io import UNIT_SCALES, atomic_path, read, read_text
from toolkit.common.papers import BALL_YIELD, FACE_YIELD
from toolkit.common.phantoms.phantom import BALL_RESOLUTIONS, TET_RESOLUTIONS

__all__ = ["SceneError", "MaterialSpec", "FaceSpec", "BallSpec", "ContactSpec", "Fidelity", "Scene", "default_scene",
           "yielding_scene", "meshed_scene", "mesh_order", "MESH_ORDERS",
           "FACE_YIELD", "BALL_YIELD", "SUPPORTS", "YIELDING_DURATION", "INTEGRATORS"]


class SceneError(ToolkitError, ValueError):
    """An impact scene is invalid: a non-physical material, an unknown key, support or integrator,
    a ball that does not move, an unreadable scene file."""


@dataclass(frozen=True)
class MaterialSpec:
    """Elastoplastic material: ``E`` MPa, ``nu``, ``density`` tonne/mm^3, ``yield_table``
    ((MPa, plastic strain), ...) or ``None`` for purely elastic."""

    E: float
    nu: float
    density: float
    yield_table: tuple | None = None

    def __post_init__(self):
        if not (self.E > 0 and -1 < self.nu < 0.5 and self.density > 0):
            raise SceneError(f"bad material E={self.E} MPa, nu={self.nu}, density={self.density} tonne/mm^3")
        if self.density > 1e-6:
            raise SceneError(f"density {self.density} looks like kg/m^3 or g/cm^3; expected tonne/mm^3 "
                             f"(1000 kg/m^3 = 1e-9)")
        if self.yield_table is not None:
            object.__setattr__(self, "yield_table", tuple(tuple(float(x) for x in row) for row in self.yield_table))
            from toolkit.impact.plasticity import HardeningTable

            try:
                HardeningTable.from_pairs(self.yield_table)
            except ValueError as exc:
                raise SceneError(f"yield_table {[list(r) for r in self.yield_table]}: "
                                 f"{str(exc).removeprefix('HardeningTable: ')}") from exc


#: time integration of :class:`Fidelity`: explicit dynamics or quasi-static equilibrium
INTEGRATORS = ("quasi-static", "explicit")

#: how the face is held: ``band`` (the impact paper: only the lower band) or ``skull`` (also the bone-side surface)
SUPPORTS = ("band", "skull")

#: duration (s) of :func:`yielding_scene`: the impact paper's fastest ball (50 mm/s) travels 18 mm, short of the
#: ~21 mm of tissue between the first touch and the skull
YIELDING_DURATION = 0.36


@dataclass(frozen=True)
class FaceSpec:
    """The face: ``resolution`` (``coarse``/``paper``) or ``mesh`` (a tet4 or tet10 file,
    length unit ``units``, axes ``axes`` (:data:`toolkit.common.meshes.axes.AXES`, converted to the
    toolkit's on reading; the ball's target and direction are in the toolkit's), with node sets
    ``fixed_set`` and ``skin``, and ``bone`` for ``support = "skull"``, as ``toolkit mesh`` writes
    them; its element order must be the fidelity's), its material, the fraction of the height
    fixed at the bottom (phantoms only; 0.05 = the lowest 5 mm of the 100 mm phantom, so that the
    ball's path over the impact paper's velocities clears it, see :class:`BallSpec`), and how the
    face is held (``support``):

    - ``"band"`` (the impact paper): only node set ``fixed_set`` (the lower band) is fixed. The face is
      then a free flap: the ball turns it about the band almost rigidly, and the tissue never
      yields (its first yield, 0.015 MPa = E, needs a Hencky equivalent strain of ~1, far beyond
      what the flap reaches at the band).
    - ``"skull"``: the bone-side surface (node set ``bone``) is fixed too, as the skull and
      teeth hold the soft tissue. The ball then crushes the 17-21 mm of tissue in front of the
      maxilla; it yields once the ball has travelled part of that past the first touch
      (docs/impact.md, "A scene that yields") and the ball's path meets the skull after ~21 mm
      (see :func:`yielding_scene`). A scene whose
      ball would travel farther than the tissue allows is refused before it runs
      (:func:`toolkit.impact.simulate.check_travel`).
    """

    resolution: str = "paper"
    mesh: str | None = None
    material: MaterialSpec = MaterialSpec(papers.FACE_E, papers.FACE_NU, papers.FACE_DENSITY, FACE_YIELD)
    fixed_set: str = "fixed"
    lower_fixed_fraction: float = 0.05
    support: str = "band"
    units: str = "mm"
    axes: str = "toolkit"

    def __post_init__(self):

        if self.units not in UNIT_SCALES:
            raise SceneError(f"face units {self.units!r} is not one of {sorted(UNIT_SCALES)} (the length unit of "
                             "the mesh file, converted to mm)")
        if self.axes not in AXES:
            raise SceneError(f"face axes {self.axes!r} is not one of {list(AXES)} (the axes of the mesh file, "
                             "converted to the toolkit's: x left, y anterior, z superior)")
        if self.support not in SUPPORTS:
            raise SceneError(f"face support {self.support!r} is not one of {sorted(SUPPORTS)}")
        if isinstance(self.resolution, str) and self.mesh is None and self.resolution not in TET_RESOLUTIONS:
            raise SceneError(f"face resolution {self.resolution!r} is not one of {list(TET_RESOLUTIONS)}")
        if not 0 < self.lower_fixed_fraction < 1:
            raise SceneError(f"face lower_fixed_fraction {self.lower_fixed_fraction} must be in (0, 1): the fraction"
                             " of the face's height fixed at the bottom")


@dataclass(frozen=True)
class BallSpec:
    """The ball: rigid analytic sphere or deformable tet mesh, driven at a uniform velocity.

    Attributes
    ----------
    radius : mm (size-5 football: 110)
    rigid : True for an analytic rigid sphere
    resolution : ball mesh resolution when deformable (``coarse``/``paper``/``fine``)
    material : MaterialSpec of the rubber
    velocity : mm/s (the impact paper: 20-50)
    direction : (3,) unit vector of the motion (into the face: -y)
    target : (3,) mm point of the face the ball's centre line passes through, or None for the
        most anterior skin point (the nose tip of the phantom)
    target_offset : (3,) mm added to the target. The default aims 30 mm above the nose tip: a
        110 mm ball is twice as tall as the phantom, so aimed at the nose it sweeps the fixed
        chin band after ~58 mm of travel and crushes tissue against it until elements invert;
        30 mm higher its path never meets the fixed nodes, so
        the impact paper's fastest ball (50 mm/s x 1.8 s = 90 mm) can run, and it first touches the
        upper nose. :func:`toolkit.impact.simulate.build_model` warns
        (:class:`~toolkit.impact.simulate.SceneGeometryWarning`) when a path reaches fixed nodes.
    gap : mm between the ball and the face at t = 0
    driven_fraction : deformable ball: nodes farther than this fraction of the radius behind
        the centre (away from the face) are driven; the front deforms freely
    """

    radius: float = papers.BALL_RADIUS
    rigid: bool = False
    resolution: str = "coarse"
    material: MaterialSpec = MaterialSpec(papers.BALL_E, papers.BALL_NU, papers.ball_density(), BALL_YIELD)
    velocity: float = papers.BALL_VELOCITY
    direction: tuple = (0.0, -1.0, 0.0)
    target: tuple | None = None
    target_offset: tuple = (0.0, 0.0, 30.0)
    gap: float = 0.5
    driven_fraction: float = 0.5

    def __post_init__(self):
        d = np.asarray(self.direction, dtype=float)
        if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) == 0:
            raise SceneError(f"ball direction {self.direction} must be a non-zero 3-vector")
        object.__setattr__(self, "direction", tuple((d / np.linalg.norm(d)).tolist()))
        for name in ("target", "target_offset"):
            v = getattr(self, name)
            if v is None:
                continue
            a = np.asarray(v, dtype=float)
            if a.shape != (3,) or not np.isfinite(a).all():
                raise SceneError(f"ball {name} {v} must be a finite 3-vector (mm)")
            object.__setattr__(self, name, tuple(a.tolist()))
        if not 0 < self.radius < np.inf:
            raise SceneError(f"ball radius {self.radius} mm must be positive and finite (a football: 110 mm)")
        if not 0 <= self.gap < np.inf:
            raise SceneError(f"ball gap {self.gap} mm must be >= 0 (the ball starts clear of the face)")
        if not 0 <= self.driven_fraction < 1:
            raise SceneError(f"ball driven_fraction {self.driven_fraction} must be in [0, 1) (of the radius)")
        if isinstance(self.resolution, str) and self.resolution not in BALL_RESOLUTIONS:
            raise SceneError(f"ball resolution {self.resolution!r} is not one of {list(BALL_RESOLUTIONS)}")
        if not self.velocity > 0:
            raise SceneError(f"ball velocity {self.velocity} mm/s must be positive")
        if self.velocity > 1e4 or self.velocity < 1.0:
            raise SceneError(f"ball velocity {self.velocity} mm/s looks like it is not in mm/s "
                             f"(the impact paper: 20-50 mm/s = 0.02-0.05 m/s)")


@dataclass(frozen=True)
class ContactSpec:
    """Ball-skin contact: Coulomb ``friction``; penalty chosen so the stable step stays above
    ``dt_fraction`` of the structural one."""

    friction: float = papers.FRICTION
    dt_fraction: float = 0.9

    def __post_init__(self):
        if not 0 <= self.friction < np.inf:
            raise SceneError(f"contact friction {self.friction} must be >= 0 (Coulomb coefficient; the impact paper: "
                             f"{papers.FRICTION})")
        if not 0 < self.dt_fraction <= 1:
            raise SceneError(f"contact dt_fraction {self.dt_fraction} must be in (0, 1]")


@dataclass(frozen=True)
class Fidelity:
    """Speed/accuracy options: element ``order`` (1 tet4, 2 tet10) and the ``integrator``.

    ``"quasi-static"`` (the default; equilibrium per load step, :mod:`toolkit.impact.quasi_static`):
    ``load_steps`` over the duration at the start (cut and regrown adaptively) and the Newton
    ``tolerance`` (relative residual); no inertia, so a ``mass_scaling`` other than 1 or a ``dt``
    is refused (:class:`SceneError`).

    ``"explicit"`` (central differences, :mod:`toolkit.impact.explicit`; the impact paper's
    integrator): ``mass_scaling`` factor on every density (>= 1), time-step ``safety`` factor on the
    critical step, or a fixed ``dt`` (s), refused when above the stable limit unless
    ``allow_unstable_dt``. Give it with its options in one call:
    ``scene.with_fidelity(integrator="explicit", mass_scaling=100)``.
    """

    order: int = 2
    mass_scaling: float = 1.0
    safety: float = 0.9
    dt: float | None = None
    allow_unstable_dt: bool = False  # run a too-large dt anyway (the blow-up detector then stops it)
    integrator: str = "quasi-static"
    load_steps: int = 36
    tolerance: float = 3e-3

    def __post_init__(self):
        if self.order not in (1, 2):
            raise SceneError(f"order must be 1 or 2, got {self.order}")
        if self.integrator not in INTEGRATORS:
            raise SceneError(f"integrator {self.integrator!r} is not one of {list(INTEGRATORS)}")
        if int(self.load_steps) < 1 or not 0 < self.tolerance < 1:
            raise SceneError(f"quasi-static load_steps {self.load_steps} must be >= 1 and tolerance {self.tolerance} "
                             "in (0, 1)")
        if not self.mass_scaling >= 1.0:
            raise SceneError(f"mass_scaling must be >= 1, got {self.mass_scaling}")
        if not 0 < self.safety <= 1.0:
            raise SceneError(f"safety must be in (0, 1], got {self.safety}")
        if self.dt is not None and not 0 < self.dt < np.inf:
            raise SceneError(f"dt must be a positive time step (s) or None for the stable one, got {self.dt}")
        if self.integrator != "explicit" and (self.mass_scaling != 1.0 or self.dt is not None):
            given = ", ".join(f"{k}={v}" for k, v in (("mass_scaling", self.mass_scaling), ("dt", self.dt))
                              if v not in (1.0, None))
            raise SceneError(f"{given} applies to the explicit integrator only (the {self.integrator} one has no "
                             f"inertia and no time step): give integrator='explicit' with it (command line: "
                             f"--integrator explicit)")


@dataclass(frozen=True)
class Scene:
    """Everything an impact run needs. ``duration`` s, ``n_frames`` output frames."""

    face: FaceSpec = FaceSpec()
    ball: BallSpec = field(default_factory=BallSpec)
    contact: ContactSpec = ContactSpec()
    fidelity: Fidelity = Fidelity()
    duration: float = papers.IMPACT_DURATION
    n_frames: int = 18

    def __post_init__(self):
        if not self.duration > 0 or int(self.n_frames) < 1:
            raise SceneError(f"duration {self.duration} s must be > 0 and n_frames {self.n_frames} >= 1")

    def with_fidelity(self, **kw) -> Scene:
        return replace(self, fidelity=replace(self.fidelity, **kw))

    def with_fidelity_choice(self, choice) -> Scene:
        """This scene with the options of an impact
        :class:`~toolkit.common.fidelity.FidelityChoice` (element order, rigid or deformable
        ball, mass scaling, safety, integrator); the face, the ball's speed and the duration stay."""
        if choice.workflow != "impact":
            raise SceneError(f"fidelity was chosen for the {choice.workflow} workflow; expected an impact choice")
        o = choice.options
        return self.with_ball(rigid=o["ball"] == "rigid").with_fidelity(
            order=int(o["order"]), mass_scaling=float(o["mass_scaling"]), safety=float(o["safety"]),
            integrator=o["integrator"])

    def with_ball(self, **kw) -> Scene:
        return replace(self, ball=replace(self.ball, **kw))

    def with_face(self, **kw) -> Scene:
        return replace(self, face=replace(self.face, **kw))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        """Inverse of :meth:`to_dict`. An unknown key or a value of the wrong type raises a
        :class:`SceneError` naming the table and the key, e.g. ``[ball] velocity = 'fast':
        expected a number (mm/s)``, with the closest known key for a typo."""
        _check_table(d, cls, "")
        kw = dict(d)

        def mat(x):
            return MaterialSpec(**x) if isinstance(x, dict) else x

        if "face" in kw:
            f = dict(kw["face"])
            if "material" in f:
                f["material"] = mat(f["material"])
            kw["face"] = FaceSpec(**f)
        if "ball" in kw:
            b = dict(kw["ball"])
            if "material" in b:
                b["material"] = mat(b["material"])
            for k in ("direction", "target", "target_offset"):
                if b.get(k) is not None:
                    b[k] = tuple(b[k])
            kw["ball"] = BallSpec(**b)
        if "contact" in kw:
            kw["contact"] = ContactSpec(**kw["contact"])
        if "fidelity" in kw:
            kw["fidelity"] = Fidelity(**kw["fidelity"])
        return cls(**kw)

    @classmethod
    def read(cls, path: str | os.PathLike) -> Scene:
        """A scene from TOML (tables ``[face]``, ``[face.material]``, ``[ball]``, ``[contact]``, ``[fidelity]``)."""
        path = Path(path)
        if path.suffix.lower() != ".toml":
            raise SceneError(f"scenes are TOML files; got {str(path)!r}")
        if not path.is_file():
            raise FileNotFoundError(f"scene file {str(path)!r} does not exist; expected a TOML scene (command line: "
                                    "--scene FILE; Scene.write or `toolkit impact predict` writes one)")

        text = read_text(path, SceneError, "a TOML scene")
        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(f"{path}: not valid TOML: {exc}") from None
        try:
            return cls.from_dict(d)
        except (TypeError, ValueError) as exc:
            raise SceneError(f"{path}: {exc}") from exc

    def write(self, path: str | os.PathLike) -> Path:
        """Write as TOML (atomically)."""

        lines = [f"duration = {self.duration!r}", f"n_frames = {self.n_frames!r}", ""]

        def table(name, obj):
            out, sub = [f"[{name}]"], []
            for k, v in asdict(obj).items():
                if v is None:
                    continue
                if isinstance(v, dict):
                    sub.append((f"{name}.{k}", getattr(obj, k)))
                    continue
                out.append(f"{k} = {_toml_value(v)}")
            lines.extend(out + [""])
            for n, o in sub:
                table(n, o)

        for name in ("face", "ball", "contact", "fidelity"):
            table(name, getattr(self, name))
        with atomic_path(path) as tmp:
            tmp.write_text("\n".join(lines))
        return Path(path)


#: units of the scene's numeric keys, for messages
_UNITS = {"radius": "mm", "velocity": "mm/s", "direction": "a direction", "target": "mm", "target_offset": "mm",
          "gap": "mm", "driven_fraction": "a fraction of the radius", "E": "MPa", "nu": "Poisson's ratio",
          "density": "tonne/mm^3",
          "lower_fixed_fraction": "a fraction of the height", "friction": "Coulomb coefficient",
          "dt_fraction": "a fraction of the stable step", "mass_scaling": "a factor >= 1",
          "safety": "a factor in (0, 1]", "dt": "s", "tolerance": "relative residual", "duration": "s"}


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _is_vector(v) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == 3 and all(_is_number(x) for x in v)


def _is_table(v) -> bool:
    return isinstance(v, (list, tuple)) and all(
        isinstance(r, (list, tuple)) and len(r) == 2 and all(_is_number(x) for x in r) for r in v)


#: annotation of a scene field -> (what it accepts, predicate)
_KINDS = {
    "float": ("a number", _is_number),
    "int": ("an integer", lambda v: _is_number(v) and float(v).is_integer()),
    "bool": ("true or false", lambda v: isinstance(v, (bool, np.bool_))),
    "str": ("a string", lambda v: isinstance(v, str)),
    "tuple": ("3 numbers", _is_vector),
}


def _expected(annotation: str, key: str):
    """(description, predicate) of the values a field with this annotation accepts."""
    optional = annotation.endswith("| None")
    kind = annotation.replace("| None", "").strip()
    if key == "yield_table":
        what, ok = "a list of [stress MPa, plastic strain] pairs", _is_table
    else:
        what, ok = _KINDS.get(kind, ("a table", lambda v: isinstance(v, (dict, MaterialSpec))))
    unit = _UNITS.get(key)
    what = f"{what} ({unit})" if unit else what
    return what, (lambda v: v is None or ok(v)) if optional else ok


def _check_table(d, spec, table: str) -> None:
    """Refuse unknown keys and values of the wrong type in the scene table ``table`` (``""`` for the
    top level) of the dataclass ``spec``, recursing into nested tables."""
    where = f"[{table}] " if table else ""
    if not isinstance(d, dict):
        raise SceneError(f"{where or 'the scene '}is {d!r}; expected a table")
    known = {f.name: f for f in fields(spec)}
    required = [f.name for f in fields(spec) if f.default is MISSING and f.default_factory is MISSING]
    missing = [k for k in required if k not in d]
    if missing:
        raise SceneError(f"{where or 'the scene '}lacks {missing}; expected the keys "
                         f"{[f'{k} ({_UNITS[k]})' if k in _UNITS else k for k in required]}")
    for key, value in d.items():
        if key not in known:
            close = difflib.get_close_matches(key, list(known), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise SceneError(f"{where or 'the scene '}has no key {key!r}; expected one of {sorted(known)}{hint}")
        what, ok = _expected(str(known[key].type), key)
        if not ok(value):
            raise SceneError(f"{where}{key} = {value!r}: expected {what}")
        if isinstance(value, dict):
            nested = {"FaceSpec": FaceSpec, "BallSpec": BallSpec, "ContactSpec": ContactSpec, "Fidelity": Fidelity,
                      "MaterialSpec": MaterialSpec}[str(known[key].type)]
            _check_table(value, nested, f"{table}.{key}" if table else key)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(float(v)) if isinstance(v, float) else repr(v)


def default_scene(velocity: float = papers.BALL_VELOCITY) -> Scene:
    """The impact paper's scene: paper-resolution tet10 face (lower part fixed), deformable rubber ball
    driven at ``velocity`` mm/s (default 30) for 1.8 s."""
    return Scene().with_ball(velocity=velocity)


def yielding_scene(velocity: float = 50.0) -> Scene:
    """The impact paper's scene with the face held by the skull (``FaceSpec.support = "skull"``), for
    :data:`YIELDING_DURATION` = 0.36 s with a frame every 10 ms; the learning database's default.

    Why: held only at its lower band the face turns away from the ball as a flap and stays
    elastic; held by the skull it is squeezed between the ball and the maxilla and yields.
    Where the ball hits is the impact paper's default aim (30 mm above the nose tip: nose, upper lip and
    the infraorbital region first). The soft tissue in front of the bone is only ~21 mm thick
    along the ball's path, so a skull-held face cannot follow the impact paper's 1.8 s (36-90 mm of
    travel); 0.36 s keeps the impact paper's fastest ball (50 mm/s, 18 mm) clear of the skull. The tissue
    yields after part of that travel (docs/impact.md, "A scene that yields"), so over 0.36 s the
    faster balls yield and the slower ones stay elastic: the database holds both regimes.
    """
    scene = Scene(duration=YIELDING_DURATION, n_frames=36).with_ball(velocity=velocity)
    return scene.with_face(support="skull")


def meshed_scene(mesh: str | os.PathLike, units: str = "mm", velocity: float = papers.BALL_VELOCITY, *,
                 axes: str = "toolkit") -> Scene:
    """:func:`yielding_scene` on the face mesh file ``mesh`` (length unit ``units``, axes ``axes``)
    as ``toolkit mesh`` writes it, at ``velocity`` mm/s, in the mesh's element order: the face held by the
    tissue on its bones (node set ``bone``; ``fixed_set = "bone"``), the default aim (30 mm above
    the most anterior skin point), 0.36 s.

    Why the bones and not the mesh's ``fixed`` set: a meshed face has no lower band, and its
    ``fixed`` set (the truncation cuts) reaches the skin at the top front edge, in the path of a
    110 mm ball at any height: on the coarse meshed phantom the ball aimed by default meets it
    almost at once, while held by its bones the path meets the bone after about as much travel as
    on the skull-held phantom (:func:`toolkit.impact.simulate.check_travel` keeps the ball short of
    it).
    """
    scene = yielding_scene(velocity).with_face(mesh=str(mesh), units=units, axes=axes, fixed_set="bone")
    order = mesh_order(mesh, units)
    return scene.with_fidelity(order=order) if order else scene


#: element order of each tetrahedron type a face mesh file may hold
MESH_ORDERS = {"tet4": 1, "tet10": 2}


def mesh_order(path, units: str = "mm") -> int:
    """Element order (1: tet4, 2: tet10) of the face mesh file at ``path``, or 0 when it holds
    other cells (:func:`toolkit.impact.simulate.face_mesh` then says why)."""

    types = read(path, units=units).volume_types
    return MESH_ORDERS.get(types[0], 0) if len(types) == 1 else 0
