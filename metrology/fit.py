"""Geometric fits of plane, sphere, cylinder, 3-D circle and line to point clouds.

The implementation lives in the package :mod:`metrology.fits` (one robust loop,
:func:`metrology.fits.robust.robust_fit`, and a small model class per primitive); this module
keeps the public names (``metrology.fits.__all__``) where the rest of the code imports them
from. See :mod:`metrology.fits` for how a fit works.
"""

from __future__ import annotations

from metrology.fits import *  # noqa: F403  (the public names)
from metrology.fits import __all__ as __all__
from metrology.fits.geometry import DEGENERACY_RATIO as DEGENERACY_RATIO
from metrology.fits.robust import BAND_SIGMAS as BAND_SIGMAS
from metrology.fits.robust import CYLINDER_RANSAC_SUBSAMPLE as CYLINDER_RANSAC_SUBSAMPLE
from metrology.fits.robust import MAX_ROUNDS as MAX_ROUNDS
