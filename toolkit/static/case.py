"""A static case: the face, the surgical plan and the bony segments one simulation needs.

:func:`load_case` is the recipe the command line, the notebooks and the README share:

- the face: the built-in hexahedral phantom (``mesh=None``) or a volume mesh read from a
  file with the phantom's node sets;
- the plan: a plan file, a :class:`~toolkit.static.plan.SurgicalPlan`, or the packaged
  bimaxillary plan (phantom only: a mesh has no segments' pivots to place it);
- the bony segments: the phantom's, or a mesh's own bone-side faces, with any segment
  replaced by a surface file (``bones``).

>>> case = load_case(resolution="coarse")
>>> result = case.simulate(increments=3)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from toolkit.common.defaults import STATIC_SIMULATION
from toolkit.common.fem.fibres import with_lip_fibres
from toolkit.common.meshes.axes import AxesError, axes_matrix, check_mesh_axes, mesh_to_toolkit
from toolkit.common.meshes.io import read
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.phantoms.phantom import FacePhantom, FaceShape
from toolkit.static.bones import segments_from_files
from toolkit.static.boundary import BoundaryError, segments_from_mesh
from toolkit.static.plan import SurgicalPlan
from toolkit.static.simulate import simulate

__all__ = ["StaticCase", "load_case"]


@dataclass(frozen=True, eq=False)
class StaticCase:
    """What :func:`toolkit.static.simulate` takes: a face, a plan and its bony segments.

    Attributes
    ----------
    subject : FacePhantom, or a Mesh (mm, ``points`` ``(n_nodes, 3)``) with the phantom's
        node sets (``fixed``, ``maxilla``, ``mandible``, ``mucosa_sliding``, ...)
    plan : SurgicalPlan — rigid motions of the segments, mm and degrees
    segments : dict segment name -> BoneSegment (triangulated bone surface in mm, pivot
        ``(3,)`` mm)
    """

    subject: FacePhantom | Mesh
    plan: SurgicalPlan
    segments: dict

    def __post_init__(self):
        if not isinstance(self.subject, FacePhantom | Mesh):
            raise TypeError(f"subject is a {type(self.subject).__name__}; expected a FacePhantom or a Mesh")
        if not isinstance(self.plan, SurgicalPlan):
            raise TypeError(f"plan is a {type(self.plan).__name__}; expected a SurgicalPlan")
        object.__setattr__(self, "segments", dict(self.segments))

    @property
    def mesh(self) -> Mesh:
        """The face mesh (the phantom's, or the subject itself), mm."""
        return self.subject.mesh if isinstance(self.subject, FacePhantom) else self.subject

    def simulate(self, fidelity=None, **kwargs):
        """Run the incremental simulation of this case.

        Keywords are those of :func:`toolkit.static.simulate`: ``increments`` (default 3),
        ``material`` (``linear``), ``sliding`` (``mucosa+lip``), ``options``
        (SimulationOptions).

        ``fidelity``: a :class:`~toolkit.common.fidelity.FidelityChoice` of the static ladder
        (:func:`~toolkit.common.fidelity.choose_fidelity`), whose ``increments``, ``material``
        and ``sliding`` the run takes and whose record the result's summary carries as
        ``fidelity``. A keyword that contradicts it, or a phantom of another resolution than the
        one chosen, is refused.

        Returns
        -------
        SimulationResult — displacements ``(increments + 1, n_nodes, 3)`` mm and diagnostics
        """
        from dataclasses import replace


        if fidelity is None:
            return simulate(self.subject, self.plan, segments=self.segments, **kwargs)
        kwargs = {**kwargs, **self._fidelity_keywords(fidelity, kwargs)}
        result = simulate(self.subject, self.plan, segments=self.segments, **kwargs)
        return replace(result, fidelity=fidelity.record())

    def _fidelity_keywords(self, fidelity, kwargs: dict) -> dict:
        """The simulate keywords of a static FidelityChoice, checked against ``kwargs`` and the face."""
        if fidelity.workflow != "static":
            raise ValueError(f"fidelity was chosen for the {fidelity.workflow} workflow; expected a static choice")
        chosen = {k: fidelity.options[k] for k in ("increments", "material", "sliding")}
        clash = {k: v for k, v in kwargs.items() if k in chosen and v != chosen[k]}
        if clash:
            k = next(iter(clash))
            raise ValueError(f"{k} = {clash[k]!r} contradicts the fidelity chosen ({k} = {chosen[k]!r}); give it to "
                             "choose_fidelity(..., fixed=...) instead")
        resolution = fidelity.options.get("resolution")
        if resolution is not None and isinstance(self.subject, FacePhantom) and self.subject.resolution != resolution:
            raise ValueError(f"the fidelity chosen is the {resolution} phantom, but this case is the "
                             f"{self.subject.resolution} one; load_case(resolution={resolution!r})")
        return chosen


def load_case(
    mesh: str | Path | Mesh | None = None,
    *,
    resolution: str | tuple[int, int, int] = STATIC_SIMULATION["resolution"],
    plan: str | Path | SurgicalPlan | None = None,
    bones: Mapping[str, str | Path | Mesh] | None = None,
    shape: FaceShape | None = None,
    force: bool = False,
    units: str = "mm",
    axes: str = "toolkit",
) -> StaticCase:
    """The face, plan and bony segments of a static simulation.

    Parameters
    ----------
    mesh : volume mesh file (``.inp``, ``.vtu``, ``.xdmf``; mm; node set ``fixed`` required)
        or a Mesh, or None for the built-in phantom
    resolution : phantom resolution (``coarse``, ``paper``, ``fine`` or ``(n_u, n_v, n_w)``;
        default ``coarse``, as on the command line: :data:`toolkit.common.defaults.STATIC_SIMULATION`);
        ignored with ``mesh``
    plan : plan file (``.toml``/``.json``), a SurgicalPlan, or None for the packaged
        bimaxillary plan (phantom only). A plan file read for the phantom takes the
        phantom's pivots for the segments it leaves out; for a mesh it must give
        ``pivot_mm`` for every rotating segment.
    bones : segment name (``lefort``, ``distal``, ``proximal_left``, ``proximal_right``,
        ``skull``) -> bone surface file (STL, OBJ, PLY, VTK, VTU, OFF) or tri3 Mesh, mm;
        replaces that segment's surface
    shape : FaceShape of the phantom (default the nominal subject); phantom only
    force : accept movements beyond twice the physiological range (they warn), also when a
        plan file does not say ``force = true``
    units : length unit of a mesh file (``mm``, ``m``, ``cm``, ``um``), converted to mm
    axes : axes of ``mesh`` and ``bones``, files or Meshes (``toolkit``: x left, y anterior, z
        superior; ``LPS``; ``RAS``: :data:`toolkit.common.meshes.axes.AXES`), converted to the toolkit's.
        The plan is in the toolkit's axes. A mesh whose anatomy says other axes is refused
        (:func:`toolkit.common.meshes.axes.check_mesh_axes`)

    Returns
    -------
    StaticCase

    Raises
    ------
    ValueError for a mesh without a plan, or a shape given with a mesh;
    BoundaryError when a mesh has no bone-side faces and no ``bones`` were given;
    AxesError for a mesh not in the toolkit's axes once converted from ``axes``, or ``axes`` other
    than ``toolkit`` for the phantom without bone files.
    """

    bones = dict(bones or {})
    axes_matrix(axes)
    if isinstance(plan, str | Path) and not Path(plan).is_file():
        raise FileNotFoundError(f"plan file {str(plan)!r} does not exist; expected a .toml or .json plan "
                                "(command line: --plan FILE)")
    if mesh is None:
        from toolkit.common.phantoms.phantom import face_hex
        from toolkit.static.plan import default_plan

        if axes != "toolkit" and not bones:
            raise AxesError(f"axes = {axes!r} for the built-in phantom, which is in the toolkit's axes; axes applies "
                            "to mesh and bone files: give mesh= or bones=, or leave it out (command line: --axes "
                            "with --mesh or --bone)")
        phantom = face_hex(resolution, shape)
        if plan is None:
            plan = default_plan(phantom, force=force)
        else:
            plan = plan if isinstance(plan, SurgicalPlan) else SurgicalPlan.read(plan, phantom=phantom, force=force)
            if force:
                plan = SurgicalPlan(plan.motions, force=True)
        segments = dict(phantom.segments)
        segments.update(segments_from_files(phantom.mesh, bones, {k: s.pivot for k, s in phantom.segments.items()},
                                            axes=axes))
        return StaticCase(phantom, plan, segments)

    if shape is not None:
        raise ValueError(f"shape {shape!r} was given with mesh {_name(mesh)}; a shape applies to the phantom only "
                         "(mesh=None)")
    if plan is None:
        raise ValueError(f"mesh {_name(mesh)} needs a plan (with pivot_mm for every rotating segment); got plan=None, "
                         "and only the phantom has a default plan: give plan= (command line: --plan FILE)")

    face = mesh if isinstance(mesh, Mesh) else read(mesh, units=units, require_node_sets=["fixed"])
    face = with_lip_fibres(mesh_to_toolkit(face, axes))
    plan = plan if isinstance(plan, SurgicalPlan) else SurgicalPlan.read(plan, force=force)
    if force:
        plan = SurgicalPlan(plan.motions, force=True)
    pivots = {k: m.pivot for k, m in plan.motions.items()}
    try:
        segments = segments_from_mesh(face, pivots)
    except BoundaryError:
        if not bones:
            raise
        segments = {}
    segments.update(segments_from_files(face, bones, pivots, axes=axes))
    check_mesh_axes(face, {k: s.surface for k, s in segments.items()}, axes=axes,
                    source=Path(mesh).name if isinstance(mesh, str | Path) else "the given mesh")
    return StaticCase(face, plan, segments)


def _name(mesh) -> str:
    return repr(str(mesh)) if isinstance(mesh, str | Path) else f"({mesh})"
