"""The type aliases every module shares: 3-vectors and NumPy arrays, defined once.

- :data:`Vec3`: a point, direction, velocity or force as three floats, SI units (m, m/s, N).
- :data:`FloatArray`: a float64 NumPy array of any shape (shapes are stated where it is used).
- :data:`IntArray`: an int64 index array (mesh vertices and faces).
- :data:`IndexArray`: a platform index array (``np.intp``, what NumPy's own indexing returns).

The wire protocol's vectors are stricter (finite, bounded) and live in :mod:`shared.protocol`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Vec3 = tuple[float, float, float]
FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
IndexArray = NDArray[np.intp]

__all__ = ["FloatArray", "IndexArray", "IntArray", "Vec3"]
