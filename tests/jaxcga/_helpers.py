"""Shared helpers of the kernel tests: hypothesis settings and small numpy conversions."""

import numpy as np
from hypothesis import settings
from hypothesis import strategies as st

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
seeds = st.integers(0, 2**32 - 1)


def _a(x):
    return np.asarray(x, dtype=np.float64)


def _unit(v):
    v = _a(v)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
