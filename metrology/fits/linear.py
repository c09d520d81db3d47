"""First-order change of a least-squares fit when its points move a little.

For a fit ``theta`` minimising ``sum r_i(theta)^2`` over points ``p_i``, small moves ``dp_i``
change the residuals by ``dr_i = n_i . dp_i`` (``n_i`` the surface normal at the point: the
gradient of the distance for a plane, sphere and cylinder) and the optimum by

    dtheta = -(J^T J)^-1 J^T dr,        J = d r / d theta at the fit,

one small solve instead of a new fit. The uncertainty budgets move points by a calibration's
sigma, a robot's miss or a flipped residual: tens of micrometres on features tens of
millimetres across, where the first order is exact to far below the values' own scatter
(``tests/metrology/fits/test_linear.py`` holds it against refits).

Plane, sphere and cylinder are linearised; other kinds return None (refit them).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from metrology.fits.results import CylinderFit, Fit, PlaneFit, SphereFit

__all__ = ["GroupFlips", "LinearisedFit", "linearise"]


def _basis(unit: NDArray) -> tuple[NDArray, NDArray]:
    """Two unit vectors completing ``unit`` to an orthonormal frame."""
    helper = np.eye(3)[int(np.argmin(np.abs(unit)))]
    e1 = np.cross(unit, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(unit, e1)


def _unit(v: NDArray) -> NDArray:
    return v / np.linalg.norm(v)


@dataclass(frozen=True, eq=False)
class LinearisedFit:
    """A fit and the first-order map from moves of its points to its new parameters.

    Attributes
    ----------
    fit : Fit
        The fit at its points (plane, sphere or cylinder).
    points : ndarray, shape (M, 3)
        The points it is linearised at.
    normals : ndarray, shape (M, 3)
        Unit gradient of each point's residual.
    residuals : ndarray, shape (M,)
    jacobian : ndarray, shape (M, P)
        ``d r / d theta`` in the fit's local parameters.
    solve : ndarray, shape (P, M)
        ``-(J^T J)^-1 J^T``.
    frame : tuple of ndarray
        The local parameters' reference (centre point and basis vectors).
    """

    fit: Fit
    points: NDArray
    normals: NDArray
    residuals: NDArray
    jacobian: NDArray
    solve: NDArray
    frame: tuple[NDArray, ...]

    @functools.cached_property
    def centroid(self) -> NDArray:
        """The unmoved points' mean, ``(3,)``."""
        return self.points.mean(axis=0)

    def moved(self, points: NDArray) -> Fit:
        """The fit to ``points`` (the same points, moved a little: ``(M, 3)``), to first order.

        Its parameters, residuals, RMS and range follow; the minimum zone, when the fit has
        one, moves with the range (a minimum-zone solve would cost more than all the rest).
        The parameters' covariance, standard deviations and inlier mask are the original
        fit's, and the unit vectors keep their sign (no re-orientation: a signed distance
        stays on the same side).
        """
        if points.shape != self.points.shape:
            raise ValueError(f"points: expected shape {self.points.shape}, got {points.shape}")
        return self.shifted(np.einsum("ij,ij->i", self.normals, points - self.points), points)

    def shifted(self, dr: NDArray, points: NDArray | None = None) -> Fit:
        """The fit after each point moved by ``dr`` ``(M,)`` along its normal, to first order
        (``points``, when given, are the moved points; a plane's centroid follows them)."""
        if dr.shape != self.residuals.shape:
            raise ValueError(f"dr: expected shape {self.residuals.shape}, got {dr.shape}")
        dtheta = self.solve @ dr
        residuals = self.residuals + dr + self.jacobian @ dtheta
        centroid = self.centroid if points is None else points.mean(axis=0)
        if points is None and isinstance(self.fit, PlaneFit):
            centroid = centroid + self.fit.normal * float(dr.mean())  # one normal for all
        return self._updated(
            dtheta,
            centroid,
            float(residuals.max() - residuals.min()),
            float(np.sqrt(residuals @ residuals / len(residuals))),
            residuals,
        )

    def groups(self, group: NDArray) -> GroupFlips:
        """The response to the residuals of whole groups (``group`` ``(M,)`` ints: a point's
        robot stop) changing sign together, prepared once for many draws."""
        if group.shape != self.residuals.shape:
            raise ValueError(f"group: expected shape {self.residuals.shape}, got {group.shape}")
        ids, inverse = np.unique(group, return_inverse=True)
        k = len(ids)
        r = self.residuals

        def per_group(values: NDArray) -> NDArray:
            """Sums over each group of ``values`` ``(M,)`` or ``(M, P)``."""
            if values.ndim == 1:
                return np.bincount(inverse, values, minlength=k)
            return np.stack([per_group(v) for v in values.T], axis=1)

        order = np.lexsort((r, inverse))  # by group, then by residual
        first = np.searchsorted(inverse[order], np.arange(k))
        last = np.append(first[1:], len(r)) - 1
        return GroupFlips(
            self,
            ids,
            per_group(self.solve.T * r[:, None]).T,
            self.solve @ r,
            per_group(self.jacobian * r[:, None]),
            float(r @ r),
            self.jacobian.T @ self.jacobian,
            per_group(r),
            order[last],
            order[first],
        )

    def _updated(
        self,
        dtheta: NDArray,
        centroid: NDArray,
        spread: float,
        rms: float,
        residuals: NDArray | None,
    ) -> Fit:
        """The fit with its parameters moved by ``dtheta`` and the new residuals' figures."""
        fit = self.fit
        if isinstance(fit, SphereFit):
            params: dict = {
                "center_mm": fit.center_mm + dtheta[:3],
                "radius_mm": fit.radius_mm + dtheta[3],
            }
        elif isinstance(fit, PlaneFit):
            centre, e1, e2 = self.frame
            normal = _unit(fit.normal + dtheta[0] * e1 + dtheta[1] * e2)
            offset = float(fit.normal @ centre + fit.d_mm + dtheta[2])
            params = {
                "normal": normal,
                "d_mm": offset - float(normal @ centre),
                "centroid_mm": centroid,
            }
        else:  # CylinderFit
            centre, e1, e2 = self.frame
            axis = _unit(fit.axis + dtheta[2] * e1 + dtheta[3] * e2)
            point = centre + dtheta[0] * e1 + dtheta[1] * e2
            # the axis point nearest the points' centroid, as a fit gives it
            params = {
                "point_mm": point + ((centroid - point) @ axis) * axis,
                "axis": axis,
                "radius_mm": fit.radius_mm + dtheta[4],
            }
        if fit.min_zone_mm is not None:
            params["min_zone_mm"] = (
                fit.min_zone_mm + spread - (float(self.residuals.max() - self.residuals.min()))
            )
        return dataclasses.replace(
            fit,
            **params,
            residuals_mm=np.zeros(0) if residuals is None else residuals,  # none: not formed
            rms_mm=rms,
            range_mm=spread,
        )


@dataclass(frozen=True, eq=False)
class GroupFlips:
    """A linearised fit's response to whole groups of residuals flipping sign (the wild
    bootstrap clustered by robot stop), in sums over the groups: a draw costs O(groups), not
    O(points), whatever the feature's size.

    With the residuals ``r`` scaled by ``c`` and group ``g``'s sign ``s_g``, the moves along the
    normals are ``dr = (c s_g - 1) r`` and, exactly to first order,

        dtheta = c A s - b,          A[:, g] = sum_(i in g) solve[:, i] r_i,  b = solve r,
        sum r'^2 = c^2 r.r + 2 c (s C) . dtheta + dtheta' J'J dtheta,   C[g] = sum r_i J_i.

    The range is taken over each group's largest and smallest residual (where a flipped
    group's extremes are): exact but for the smooth ``J dtheta`` (micrometres) moving another
    point of a group past its extreme.
    """

    linear: LinearisedFit
    ids: NDArray
    a: NDArray
    b: NDArray
    c: NDArray
    rr: float
    jtj: NDArray
    sums: NDArray
    top: NDArray
    bottom: NDArray

    def flipped(self, sign: NDArray, scale: float = 1.0) -> Fit:
        """The fit after each group's residuals became ``scale * sign[group] * r``.

        ``sign`` is indexed by the group ids given to :meth:`LinearisedFit.groups` (``+-1``).
        """
        lin = self.linear
        s = sign[self.ids]
        dtheta = scale * (self.a @ s) - self.b
        m = len(lin.residuals)
        sumsq = (
            scale**2 * self.rr + 2.0 * scale * (s @ self.c) @ dtheta + dtheta @ self.jtj @ dtheta
        )
        ends = np.concatenate([self.top, self.bottom])
        s_ends = np.concatenate([s, s])
        at_ends = scale * s_ends * lin.residuals[ends] + lin.jacobian[ends] @ dtheta
        centroid = lin.centroid
        if isinstance(lin.fit, PlaneFit):
            mean_dr = (scale * (s @ self.sums) - self.sums.sum()) / m
            centroid = centroid + lin.fit.normal * mean_dr
        return lin._updated(
            dtheta,
            centroid,
            float(at_ends.max() - at_ends.min()),
            float(np.sqrt(max(sumsq, 0.0) / m)),
            None,
        )


def linearise(fit: Fit, points: NDArray) -> LinearisedFit | None:
    """The fit's first-order response to moves of ``points`` ``(M, 3)``, or None for a kind
    not linearised here (circle, line) or a failed fit."""
    if not fit or len(points) < 4:
        return None
    points = np.asarray(points, dtype=np.float64)
    if isinstance(fit, SphereFit):
        q = points - fit.center_mm
        dist = np.linalg.norm(q, axis=1)
        normals = q / dist[:, None]
        residuals = dist - fit.radius_mm
        jacobian = np.hstack([-normals, -np.ones((len(points), 1))])
        frame: tuple[NDArray, ...] = (fit.center_mm,)
    elif isinstance(fit, PlaneFit):
        centre = points.mean(axis=0)
        e1, e2 = _basis(fit.normal)
        q = points - centre
        normals = np.broadcast_to(fit.normal, points.shape)
        residuals = points @ fit.normal + fit.d_mm
        jacobian = np.column_stack([q @ e1, q @ e2, np.ones(len(points))])
        frame = (centre, e1, e2)
    elif isinstance(fit, CylinderFit):
        axis = fit.axis
        # the axis point nearest the points' centroid: the tilt and shift decouple there
        centre = fit.point_mm + ((points.mean(axis=0) - fit.point_mm) @ axis) * axis
        e1, e2 = _basis(axis)
        q = points - centre
        along = q @ axis
        radial = q - np.outer(along, axis)
        dist = np.linalg.norm(radial, axis=1)
        normals = radial / dist[:, None]
        residuals = dist - fit.radius_mm
        m1, m2 = normals @ e1, normals @ e2
        jacobian = np.column_stack([-m1, -m2, -along * m1, -along * m2, -np.ones(len(points))])
        frame = (centre, e1, e2)
    else:
        return None
    normal_matrix = jacobian.T @ jacobian
    if np.linalg.cond(normal_matrix) > 1e12:
        return None
    solve = -np.linalg.solve(normal_matrix, jacobian.T)
    return LinearisedFit(fit, points, normals, residuals, jacobian, solve, frame)
