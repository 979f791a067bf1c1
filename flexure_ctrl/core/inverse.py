"""
Inverse of the two-link forward map: actuator extensions for desired end points.

:class:`InverseSolver` is the production solver. It seeds every point from a coarse
grid of the forward map restricted to the chosen branch, then runs a damped Newton
iteration on all points at once with the analytic Jacobian. Points that do not
converge get a bounded least-squares retry, which also tells *why* a point cannot be
reached (outside the workspace, or only beyond the stroke limits). No point is ever
silently clipped.

:class:`ContourReferenceSolver` is the paper's own method (Fig. 12), kept as the
reference: tabulate ``x_e = f(l01, l02)`` and ``y_e = g(l01, l02)`` on a grid, trace the
contours ``f = x_p`` and ``g = y_p``, and intersect them. It is slow and only as exact as
its grid, which is the point: the two are independent and must agree.

Branches: ``above`` keeps the elbow (the root of flexure 2) to the left of the line from
the base to the end point, i.e. above it for an arm reaching along +x; ``below`` keeps it
to the right. Because the solution on one branch is unique inside the stroke box, the
solution along a continuous path is continuous, with no jumps between branches.
"""

import math
from typing import Optional, Tuple

from flexure_ctrl.core.errors import UnreachablePointError
from flexure_ctrl.core.kinematics import branch_of_components, branch_sign, TwoLinkArm
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

DEFAULT_TOLERANCE_M = 1e-9
MAX_NEWTON_STEP_M = 5e-3
# A Newton step this short is the last one needed: convergence is quadratic, so the
# residual after it is about |J| * C * step**2 with C ~ 1/(table length scale) ~ 20 1/m
# here, i.e. ~1e-10 m. Accepting it saves a whole forward evaluation per solve.
FINAL_STEP_M = 1e-6
# A least-squares retry that ends farther than this from the point has failed.
REACHABLE_RESIDUAL_M = 1e-8


def _as_points(points_m) -> np.ndarray:
    points = np.asarray(points_m, dtype=float)
    if points.shape[-1:] != (2,):
        raise ValueError(f'end points must have shape (..., 2), got {points.shape}')
    if not np.all(np.isfinite(points)):
        index = int(np.flatnonzero(~np.all(np.isfinite(points.reshape(-1, 2)), axis=1))[0])
        raise UnreachablePointError(index, points.reshape(-1, 2)[index], 'not a finite number')
    return points


class InverseSolver:
    """
    Actuator extensions ``(l01, l02)`` for desired end points, on one branch.

    :param arm: the forward map.
    :param branch: ``'above'`` or ``'below'``.
    :param stroke_limit_m: symmetric actuator stroke limit; solutions satisfy
        ``|l0| <= stroke_limit_m``. Must lie inside both tables.
    :param tolerance_m: Newton stops once every end-point residual is below this.
    :param seed_grid_points: grid size per actuator for the fallback starting guesses.
    :param seed_map_points: grid size per axis of the precomputed inverse over the
        workspace, which gives each point a starting guess close enough for Newton
        to converge in one or two steps.
    :param max_iterations: Newton iterations before a point is retried.
    """

    def __init__(self, arm: TwoLinkArm, branch: str = 'above', stroke_limit_m: float = 0.045,
                 tolerance_m: float = DEFAULT_TOLERANCE_M, seed_grid_points: int = 61,
                 seed_map_points: int = 96, max_iterations: int = 30):
        self.arm = arm
        self.branch = branch
        self.sign = branch_sign(branch)
        self.stroke_limit_m = float(stroke_limit_m)
        for joint in (arm.joint1, arm.joint2):
            if -self.stroke_limit_m < joint.l0_min_m or self.stroke_limit_m > joint.l0_max_m:
                raise ValueError(
                    f'stroke limit +-{self.stroke_limit_m} m reaches outside the table '
                    f'[{joint.l0_min_m}, {joint.l0_max_m}] m')
        self.tolerance_m = float(tolerance_m)
        self.max_iterations = int(max_iterations)
        axis = np.linspace(-self.stroke_limit_m, self.stroke_limit_m, seed_grid_points)
        grid1, grid2 = np.meshgrid(axis, axis, indexing='ij')
        end, _, elbow = arm.forward_with_jacobian(grid1, grid2)
        on_branch = (TwoLinkArm.branch_of(end, elbow) == self.sign).ravel()
        if not np.any(on_branch):
            raise ValueError(f'no configuration inside the stroke lies on branch {branch!r}')
        self._seed_extensions = np.column_stack([grid1.ravel(), grid2.ravel()])[on_branch]
        reachable_ends = end.reshape(-1, 2)[on_branch]
        self._seed_tree = cKDTree(reachable_ends)
        self._build_seed_map(reachable_ends, seed_map_points)

    def _build_seed_map(self, reachable_ends: np.ndarray, points_per_axis: int) -> None:
        """Tabulate the inverse on a workspace grid; NaN where a node is unreachable."""
        low = reachable_ends.min(axis=0)
        high = reachable_ends.max(axis=0)
        self._map_origin = low
        self._map_step = (high - low) / (points_per_axis - 1)
        self._map_cells = points_per_axis - 1
        xs = low[0] + self._map_step[0] * np.arange(points_per_axis)
        ys = low[1] + self._map_step[1] * np.arange(points_per_axis)
        nodes = np.stack(np.meshgrid(xs, ys, indexing='ij'), axis=-1).reshape(-1, 2)
        solution, converged = self._newton(nodes, self._tree_seed(nodes))
        solution[~converged] = np.nan
        # Flat, one column per actuator: seed() gathers with 1-D indices.
        self._map_points = points_per_axis
        self._map_l01 = np.ascontiguousarray(solution[:, 0])
        self._map_l02 = np.ascontiguousarray(solution[:, 1])

    @classmethod
    def from_design(cls, design, **kwargs) -> 'InverseSolver':
        """Solver for a :class:`~flexure_ctrl.core.design.Design` with its branch and stroke."""
        kwargs.setdefault('branch', design.branch)
        kwargs.setdefault('stroke_limit_m', design.stroke_limit_m)
        return cls(TwoLinkArm.from_design(design), **kwargs)

    def _tree_seed(self, points: np.ndarray) -> np.ndarray:
        _, index = self._seed_tree.query(points)
        return self._seed_extensions[index]

    def seed(self, points_m) -> np.ndarray:
        """
        Return starting extensions ``(N, 2)`` in metres for points ``(N, 2)``, on the branch.

        Bilinear interpolation of the tabulated inverse where all four surrounding
        nodes are reachable; otherwise the nearest grid configuration on the branch.
        """
        points = np.asarray(points_m, float).reshape(-1, 2)
        scaled_x = (points[:, 0] - self._map_origin[0]) / self._map_step[0]
        scaled_y = (points[:, 1] - self._map_origin[1]) / self._map_step[1]
        i = np.floor(scaled_x).astype(np.intp)
        j = np.floor(scaled_y).astype(np.intp)
        inside = (i >= 0) & (i < self._map_cells) & (j >= 0) & (j < self._map_cells)
        np.clip(i, 0, self._map_cells - 1, out=i)
        np.clip(j, 0, self._map_cells - 1, out=j)
        fx = scaled_x - i
        fy = scaled_y - j
        corner = i * self._map_points + j
        w00 = (1.0 - fx) * (1.0 - fy)
        w01 = (1.0 - fx) * fy
        w10 = fx * (1.0 - fy)
        w11 = fx * fy
        seeds = np.empty_like(points)
        for column, grid in ((0, self._map_l01), (1, self._map_l02)):
            seeds[:, column] = (w00 * grid.take(corner) + w01 * grid.take(corner + 1)
                                + w10 * grid.take(corner + self._map_points)
                                + w11 * grid.take(corner + self._map_points + 1))
        fallback = ~inside | np.isnan(seeds[:, 0]) | np.isnan(seeds[:, 1])
        if np.any(fallback):
            seeds[fallback] = self._tree_seed(points[fallback])
        return seeds

    def solve(self, points_m, initial_m: Optional[np.ndarray] = None) -> np.ndarray:
        """
        Extensions for each desired end point.

        :param points_m: desired end points ``(x_p, y_p)`` in metres, shape ``(..., 2)``.
        :param initial_m: optional starting extensions of the same shape (e.g. the last
            solution of a streaming caller); the seed map is used otherwise.

        :returns: Extensions ``(l01, l02)`` in metres, same shape as ``points_m``, with
            ``|end(l) - p| <= tolerance`` (1e-9 m by default, always below 1e-8 m).

        :raises UnreachablePointError: naming the first point that is outside the reachable
            workspace, needs an extension beyond the stroke limits, or has no
            solution on the chosen branch.
        """
        points = _as_points(points_m)
        flat = points.reshape(-1, 2)
        if initial_m is None:
            extensions = self.seed(flat)
        else:
            extensions = np.clip(np.array(initial_m, dtype=float).reshape(-1, 2),
                                 -self.stroke_limit_m, self.stroke_limit_m)
        extensions, converged = self._newton(flat, extensions)
        for index in np.flatnonzero(~converged):
            extensions[index] = self._retry(index, flat[index])
        return extensions.reshape(points.shape)

    def solve_point(self, x_m: float, y_m: float, initial_m: Optional[Tuple[float, float]] = None,
                    velocity_m_s: Tuple[float, float] = (0.0, 0.0)) -> Tuple[float, ...]:
        """
        Solve one point warm-started from ``initial_m``: the streaming fast path.

        A few scalar Newton steps (no numpy) from the previous solution; if they do not
        converge on the branch inside the stroke, :meth:`solve` decides (and raises
        :class:`UnreachablePointError` for a point that cannot be reached).

        :param velocity_m_s: end-point velocity ``(dx/dt, dy/dt)`` to map to the actuators.
        :returns: ``(l01 m, l02 m, dl01/dt m/s, dl02/dt m/s)``.
        """
        limit = self.stroke_limit_m
        if initial_m is not None and all(math.isfinite(v) for v in (x_m, y_m)):
            l01, l02 = (min(max(float(v), -limit), limit) for v in initial_m)
            for _ in range(8):
                x_end, y_end, j11, j12, j21, j22, x_elbow, y_elbow = \
                    self.arm.point_components(l01, l02)
                rx, ry = x_end - x_m, y_end - y_m
                det = j11 * j22 - j12 * j21
                if rx * rx + ry * ry <= self.tolerance_m ** 2:
                    on_branch = (x_end * y_elbow - y_end * x_elbow >= 0.0) == (self.sign > 0)
                    if on_branch and det != 0.0:
                        vx, vy = velocity_m_s
                        return (l01, l02, (j22 * vx - j12 * vy) / det,
                                (j11 * vy - j21 * vx) / det)
                    break
                if det == 0.0:
                    break
                step1 = -(j22 * rx - j12 * ry) / det
                step2 = -(j11 * ry - j21 * rx) / det
                scale = min(1.0, MAX_NEWTON_STEP_M / max(math.hypot(step1, step2), 1e-300))
                l01 = min(max(l01 + scale * step1, -limit), limit)
                l02 = min(max(l02 + scale * step2, -limit), limit)
        l01, l02 = self.solve(np.array([x_m, y_m]))
        _, jacobian, _ = self.arm.forward_with_jacobian(l01, l02)
        dl01, dl02 = np.linalg.solve(jacobian, np.asarray(velocity_m_s, dtype=float))
        return float(l01), float(l02), float(dl01), float(dl02)

    def _newton(self, targets: np.ndarray, extensions: np.ndarray):
        """Damped Newton on all points at once; returns (extensions, converged mask)."""
        limit = self.stroke_limit_m
        extensions = extensions.copy()
        converged = np.zeros(len(targets), dtype=bool)
        active = np.arange(len(targets))
        l01 = extensions[:, 0].copy()
        l02 = extensions[:, 1].copy()
        x_target = targets[:, 0].copy()
        y_target = targets[:, 1].copy()
        for iteration in range(self.max_iterations + 1):
            x_end, y_end, j11, j12, j21, j22, x_elbow, y_elbow = self.arm.components(l01, l02)
            rx = x_end - x_target
            ry = y_end - y_target
            on_branch = branch_of_components(x_end, y_end, x_elbow, y_elbow) == self.sign
            done = (rx * rx + ry * ry <= self.tolerance_m ** 2) & on_branch
            if iteration < self.max_iterations:
                det = j11 * j22 - j12 * j21
                det = np.where(np.abs(det) < 1e-300, 1e-300, det)
                step1 = -(j22 * rx - j12 * ry) / det
                step2 = -(j11 * ry - j21 * rx) / det
                length = np.hypot(step1, step2)
                scale = np.minimum(1.0, MAX_NEWTON_STEP_M / np.maximum(length, 1e-300))
                next1 = np.clip(l01 + scale * step1, -limit, limit)
                next2 = np.clip(l02 + scale * step2, -limit, limit)
                final = ~done & on_branch & (length <= FINAL_STEP_M)
                final &= (np.abs(next1) < limit) & (np.abs(next2) < limit)
                l01 = np.where(final, next1, l01)
                l02 = np.where(final, next2, l02)
                done |= final
            else:
                next1, next2 = l01, l02
            converged[active[done]] = True
            extensions[active[done], 0] = l01[done]
            extensions[active[done], 1] = l02[done]
            keep = ~done
            active = active[keep]
            if active.size == 0 or iteration == self.max_iterations:
                l01, l02 = l01[keep], l02[keep]
                break
            l01, l02 = next1[keep], next2[keep]
            x_target, y_target = x_target[keep], y_target[keep]
        extensions[active, 0] = l01
        extensions[active, 1] = l02
        return extensions, converged

    def _least_squares(self, target: np.ndarray, start: np.ndarray, limit_m: float):
        def residual(ext):
            return self.arm.forward(ext[0], ext[1], check_range=False) - target

        def jacobian(ext):
            return self.arm.forward_with_jacobian(ext[0], ext[1], check_range=False)[1]

        result = least_squares(residual, np.clip(start, -limit_m, limit_m), jac=jacobian,
                               bounds=(-limit_m, limit_m), xtol=1e-15, ftol=1e-15, gtol=1e-15,
                               method='trf', max_nfev=200)
        end, _, elbow = self.arm.forward_with_jacobian(result.x[0], result.x[1],
                                                       check_range=False)
        distance = float(np.hypot(*(end - target)))
        on_branch = bool(TwoLinkArm.branch_of(end, elbow) == self.sign)
        return result.x, distance, on_branch

    def _retry(self, index: int, target: np.ndarray) -> np.ndarray:
        start = self._tree_seed(target[None])[0]
        solution, distance, on_branch = self._least_squares(target, start, self.stroke_limit_m)
        if distance <= REACHABLE_RESIDUAL_M and on_branch:
            # Polish to the Newton tolerance from the bounded solution.
            polished, converged = self._newton(target[None], solution[None].copy())
            if converged[0]:
                return polished[0]
            return solution
        if distance <= REACHABLE_RESIDUAL_M:
            raise UnreachablePointError(
                index, target, f'it has no solution on the {self.branch!r} branch within the '
                f'stroke limit +-{self.stroke_limit_m * 1e3:.3f} mm')
        table_limit = min(-max(j.l0_min_m for j in (self.arm.joint1, self.arm.joint2)),
                          min(j.l0_max_m for j in (self.arm.joint1, self.arm.joint2)))
        if table_limit > self.stroke_limit_m:
            wide, wide_distance, _ = self._least_squares(target, solution, table_limit)
            if wide_distance <= REACHABLE_RESIDUAL_M:
                actuator = int(np.argmax(np.abs(wide))) + 1
                raise UnreachablePointError(
                    index, target, f'actuator {actuator} would need {wide[actuator - 1]:.6f} m, '
                    f'beyond the stroke limit +-{self.stroke_limit_m} m')
        raise UnreachablePointError(
            index, target, f'it is outside the reachable workspace (the nearest reachable end '
            f'point within the stroke limits is {distance * 1e3:.3f} mm away)')


class ContourReferenceSolver:
    """
    The paper's look-up-table inverse (Fig. 12): intersect the x and y contours.

    :param arm: the forward map (tabulated once on the grid).
    :param branch: ``'above'`` or ``'below'``.
    :param stroke_limit_m: the grid spans ``[-stroke, +stroke]`` for both actuators.
    :param grid_step_m: spacing of the look-up tables; the answer is exact to
        O(grid_step**2).
    """

    def __init__(self, arm: TwoLinkArm, branch: str = 'above', stroke_limit_m: float = 0.045,
                 grid_step_m: float = 0.5e-3):
        import contourpy  # matplotlib's contouring engine; only the reference needs it.

        self._contourpy = contourpy
        self.arm = arm
        self.branch = branch
        self.sign = branch_sign(branch)
        count = int(round(2.0 * stroke_limit_m / grid_step_m)) + 1
        self.axis_m = np.linspace(-stroke_limit_m, stroke_limit_m, count)
        grid1, grid2 = np.meshgrid(self.axis_m, self.axis_m, indexing='xy')
        # Rows follow l02 and columns l01, as contourpy expects z[y, x].
        self.x_table_m, self.y_table_m = np.moveaxis(arm.forward(grid1, grid2), -1, 0)

    def _contour_segments(self, table: np.ndarray, level: float) -> np.ndarray:
        generator = self._contourpy.contour_generator(
            self.axis_m, self.axis_m, table, line_type=self._contourpy.LineType.Separate)
        lines = generator.lines(level)
        if not lines:
            return np.empty((0, 2, 2))
        return np.concatenate([np.stack([line[:-1], line[1:]], axis=1) for line in lines])

    def intersections(self, point_m) -> np.ndarray:
        """All contour crossings for one point, on both branches: ``(K, 2)`` metres."""
        x_segments = self._contour_segments(self.x_table_m, float(point_m[0]))
        y_segments = self._contour_segments(self.y_table_m, float(point_m[1]))
        if len(x_segments) == 0 or len(y_segments) == 0:
            return np.empty((0, 2))
        a0, da = x_segments[:, None, 0], x_segments[:, None, 1] - x_segments[:, None, 0]
        b0, db = y_segments[None, :, 0], y_segments[None, :, 1] - y_segments[None, :, 0]
        denominator = da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]
        offset = b0 - a0
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (offset[..., 0] * db[..., 1] - offset[..., 1] * db[..., 0]) / denominator
            u = (offset[..., 0] * da[..., 1] - offset[..., 1] * da[..., 0]) / denominator
        hit = (np.abs(denominator) > 0) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
        crossings = (a0 + t[..., None] * da)[hit]
        if len(crossings) <= 1:
            return crossings
        # A crossing at a shared vertex is found once per adjoining segment.
        order = np.lexsort(crossings.T[::-1])
        crossings = crossings[order]
        distinct = np.r_[True, np.any(np.abs(np.diff(crossings, axis=0)) > 1e-9, axis=1)]
        return crossings[distinct]

    def solve(self, points_m) -> np.ndarray:
        """Extensions for each point on the chosen branch; same shape as ``points_m``."""
        points = _as_points(points_m)
        flat = points.reshape(-1, 2)
        solutions = np.empty_like(flat)
        previous = None
        for index, point in enumerate(flat):
            crossings = self.intersections(point)
            if len(crossings):
                end, _, elbow = self.arm.forward_with_jacobian(crossings[:, 0], crossings[:, 1])
                crossings = crossings[TwoLinkArm.branch_of(end, elbow) == self.sign]
            if len(crossings) == 0:
                raise UnreachablePointError(
                    index, point, f'the x and y contours do not cross on the {self.branch!r} '
                    'branch inside the look-up tables')
            if previous is not None and len(crossings) > 1:
                crossings = crossings[np.argsort(np.hypot(*(crossings - previous).T))]
            solutions[index] = previous = crossings[0]
        return solutions.reshape(points.shape)
