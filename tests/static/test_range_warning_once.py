"""A plan beyond the physiological range warns where it is built, once: running it (its
increments are fractions of it, some still beyond the range) does not repeat the warning from
the toolkit's own lines."""

import warnings

from toolkit.static.database import subject_phantom
from toolkit.static.plan import PlanRangeWarning, SurgicalPlan
from toolkit.static.simulate import simulate


def test_a_plan_beyond_the_range_warns_once_where_it_is_built():
    phantom = subject_phantom("coarse", 0)
    with warnings.catch_warnings(record=True) as built:
        warnings.simplefilter("always")
        plan = SurgicalPlan.from_dict({"distal": {"translation_mm": [0.0, -14.0, 0.0]}}, phantom=phantom)
    assert [w.category for w in built] == [PlanRangeWarning]
    with warnings.catch_warnings(record=True) as ran:
        warnings.simplefilter("always")
        simulate(phantom, plan, 3, options=None)
    assert [str(w.message) for w in ran if issubclass(w.category, PlanRangeWarning)] == []
