"""toolkit.common.analysis.symmetry: mirror images of a node set (the expected maps are written out)."""

import numpy as np
import pytest

from toolkit.common.analysis.symmetry import mirror_index, mirrored


def test_mirror_index_pairs_points_and_tells_coincident_ones_apart_by_label():
    p = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0.0, 2, 0], [0.0, 2, 0], [2.0, 1, 1], [-2.0, 1, 1]])
    labels = np.array([0, 0, 1, 2, 0, 0])
    np.testing.assert_array_equal(mirror_index(p, labels), [1, 0, 2, 3, 5, 4])
    assert mirror_index(p + [0.5, 0, 0], labels) is None  # not symmetric about x = 0
    np.testing.assert_array_equal(mirror_index(p[:, [1, 0, 2]], labels, axis=1), [1, 0, 2, 3, 5, 4])
    u = np.arange(18.0).reshape(6, 3)
    m = mirrored(u[None], mirror_index(p, labels))[0]
    np.testing.assert_array_equal(m[0], [-3.0, 4.0, 5.0])  # point 0 takes point 1's value, x negated
    np.testing.assert_array_equal(mirrored(m[None], mirror_index(p, labels))[0], u)
    with pytest.raises(ValueError, match=r"labels have shape \(2,\); expected \(6,\)"):
        mirror_index(p, labels[:2])
