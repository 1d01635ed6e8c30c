"""Array type aliases of the package (numpy.typing): float64 and int64 arrays."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ['ArrayLike', 'FloatArray', 'IntArray']

#: Anything numpy converts to an array (public functions take it and convert once).
ArrayLike = npt.ArrayLike
#: A float64 array (SI values unless the name says otherwise).
FloatArray = npt.NDArray[np.float64]
#: An int64 array (stamps in ns, indices).
IntArray = npt.NDArray[np.int64]
