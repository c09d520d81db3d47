"""Readers of published calibration data sets, to check our calibration against others' results.

The data sets themselves are not part of the repository (see ``../shared/data/real/README.md``);
the tests and the benchmarks that use them read them through here.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["ZHANG_MSR_IMAGE_SIZE", "zhang_msr_corners"]

#: ``(width, height)`` of the five images of Zhang's data set.
ZHANG_MSR_IMAGE_SIZE = (640, 480)


def zhang_msr_corners(folder: str | os.PathLike[str]) -> tuple[NDArray, list[NDArray]]:
    """The corners published with Zhang's calibration data (1998).

    Parameters
    ----------
    folder : path
        The data set's folder, holding ``Model.txt`` and ``data1.txt`` to ``data5.txt``.

    Returns
    -------
    model : ndarray, shape (N, 3)
        The corners on the model plane (z = 0), in the file's units (inches).
    views : list of ndarray, shape (N, 2)
        The corners detected in each of the five images, same order, pixels.
    """
    root = Path(folder)
    model = np.loadtxt(root / "Model.txt").reshape(-1, 2)
    model_xyz = np.column_stack([model, np.zeros(len(model))])
    views = [np.loadtxt(root / f"data{i}.txt").reshape(-1, 2) for i in range(1, 6)]
    return model_xyz, views
