"""``_jaxcga_shared.broadcast``: numpy's rank promotion made explicit gives numpy's broadcast, checked against numpy
itself, and leaves arrays of as many axes or more unchanged."""

import numpy as np
import pytest

from _jaxcga_shared.broadcast import lift_rank, same_rank


@pytest.mark.parametrize(("shape", "other"), [((), (2, 3)), ((3,), (2, 3)), ((4, 1), (5, 4, 3)), ((2, 3), (3,))])
def test_same_rank_then_broadcast_equals_numpys_broadcast(shape, other):
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=shape), rng.normal(size=other)
    lifted_a, lifted_b = same_rank(a, b)
    assert lifted_a.ndim == lifted_b.ndim == max(a.ndim, b.ndim)
    np.testing.assert_array_equal(np.asarray(lifted_a * lifted_b), a * b)


def test_lift_rank_adds_leading_axes_only():
    a = np.arange(6.0).reshape(2, 3)
    assert lift_rank(a, 4).shape == (1, 1, 2, 3)
    assert lift_rank(a, 2).shape == lift_rank(a, 1).shape == (2, 3)
    np.testing.assert_array_equal(np.asarray(lift_rank(a, 3))[0], a)
