"""
Large-deflection (elastica) model of the plain flexure coupling and its actuator linkage.

This module implements the plain flexure (PF) model of Bailey, Lusty & Keogh,
"Iterative Feedforward Control for Bearing-Free Multibody Systems", Eqs. (1)-(6).
All quantities are SI: metres, radians, newtons, newton-metres, pascals.

Plain flexure (paper Eqs. 1-4)
------------------------------
A strip of length ``l_f`` is clamped at ``s = 0`` along +x.  A dead load
``F_f = (F_fx, F_fy, F_ftheta)`` acts at the tip ``s = l_f``.  With ``z1 = theta`` and
``z2 = dtheta/ds``::

    z1' = z2,   z2' = (F_fx sin z1 - F_fy cos z1) / EI,   x' = cos z1,   y' = sin z1
    z1(0) = 0,  x(0) = 0,  y(0) = 0,  z2(l_f) = F_ftheta / EI

is solved with :func:`scipy.integrate.solve_bvp`: fourth-order collocation with
cubic C1 splines, which is the three-stage Lobatto IIIA formula the paper uses, plus
residual control and mesh refinement.  Angles are counter-clockwise positive.
Internally the problem is scaled by ``l_f`` (``u = s / l_f``, lengths in units of
``l_f``, curvature in units of ``1 / l_f``) so every state is of order one.

The load-to-deflection map is many-to-many: for ``F_f = (10 N, -1000 N, 10 N m)`` on
the paper's strip, different initial estimates converge to different equilibria
(paper Fig. 2); :func:`distinct_tip_deflections` collects them.

Actuator linkage (paper Fig. 4, Eqs. 5-6)
-----------------------------------------
The output body is rigid to the flexure tip ``P = (x_f, y_f)``.  With the tip
tangent ``t = (cos theta_f, sin theta_f)`` and normal ``n = (-sin theta_f, cos theta_f)``
the hinge B of the rigid link sits at::

    B = P + b_t t - l_v n            b_t = l_p - l_2 (paper symbols)

The actuator rod runs horizontally at height ``y = -l_v``; its end hinge is
``A = (l0 - kappa, -l_v)``.  The link A-B has length ``l_1`` and angle ``phi`` to the
horizontal, so closing the loop gives (this *is* paper Eq. 6)::

    l_1 sin(phi) = B_y + l_v
    l0           = kappa + B_x - l_1 cos(phi)

The link is a massless two-force member, so the horizontal actuator force ``F0``
(positive pushes the rod out, towards +x) arrives at B as ``F = (F0, F0 tan phi)``.
Moving it to the tip adds the moment ``M = (B - P) x F``::

    F_fx     = F0
    F_fy     = F0 tan(phi)
    F_ftheta = F0 (b_t sin(phi - theta_f) + l_v cos(theta_f - phi)) / cos(phi)

Expanding ``b_t = l_p - l_2`` gives the paper's printed Eq. 5,
``F0 (l_2 sin(theta_f - phi) + l_v cos(theta_f - phi)) / cos(phi)
+ F_fy l_p cos(theta_f) - F_fx l_p sin(theta_f)``; the printed text reads
``cos phi (theta_f - phi)`` for ``cos(theta_f - phi)`` and ``F_fp`` for ``F_fy``
(OCR damage).  ``kappa`` is chosen so that ``l0 = 0`` when ``theta_f = 0`` (the
paper's reference extension); then ``phi = 0`` and ``kappa = l_1 - l_f - b_t``.

The linkage dimensions of the paper's rig are not published, so
:data:`DEFAULT_LINKAGE` uses ``l_1 = 100 mm``, ``b_t = -4 mm`` (hinge B 4 mm behind
the tip, towards the clamp) and ``l_v = 64 mm``, giving ``kappa = 74 mm``.  With
them the PF sweeps ``theta_f = -0.748 .. +0.746 rad`` over ``l0 = -45 .. +45 mm``,
``theta_f`` increasing monotonically in ``l0``, with ``F0`` between about -16 N and
+14 N (far below the 85 N Euler load of the strip).  A shorter link steepens ``phi``
until ``F0`` peaks (a fold: e.g. ``l_1 = 70 mm, b_t = 15 mm, l_v = 60 mm`` folds at
``l0`` of about 50 mm), beyond which a sweep in ``F0`` cannot continue; with the
default 100 mm link ``F0`` stays monotone in ``l0`` beyond +-70 mm.

Because the tip load depends on the tip pose through ``phi``, the coupled problem
is one boundary-value problem with ``phi`` as an unknown parameter of
``solve_bvp`` (and, for a prescribed extension, ``F0`` as a second unknown).
"""

from dataclasses import dataclass, replace
import math
from typing import Callable, Optional, Sequence, Union

from flexure_ctrl.core.errors import ElasticaError
import numpy as np
from scipy.integrate import solve_bvp, solve_ivp
from scipy.interpolate import PchipInterpolator

# Collocation tolerance on the scaled problem; lengths are in units of l_f, so
# 1e-9 * 30 mm keeps the tip position well inside the 1e-9 m table resolution.
DEFAULT_TOLERANCE = 1e-9
DEFAULT_MAX_NODES = 20000
DEFAULT_INITIAL_NODES = 41
# Sweeps stay on smooth shapes that need a few hundred nodes; a low cap makes a step
# that Newton cannot converge (near a fold) fail fast instead of refining for seconds.
SWEEP_MAX_NODES = 5000
# Continuation restarts from at most this many nodes of the previous solution.
CONTINUATION_MAX_NODES = 201
# A secant d(theta_f)/dF0 this many times the straight-strip value signals a fold.
FOLD_COMPLIANCE_RATIO = 10.0


@dataclass(frozen=True)
class FlexureStrip:
    """
    Rectangular spring-steel strip; defaults are the paper's 301 stainless PF.

    :ivar length_m: free length l_f between the clamps [m].
    :ivar width_m: width w [m].
    :ivar thickness_m: thickness t [m].
    :ivar youngs_modulus_pa: Young's modulus E [Pa].
    """

    length_m: float = 0.030
    width_m: float = 0.030
    thickness_m: float = 0.0004
    youngs_modulus_pa: float = 193.0e9

    @property
    def second_moment_m4(self) -> float:
        """Second moment of area I = w t^3 / 12 [m^4]."""
        return self.width_m * self.thickness_m ** 3 / 12.0

    @property
    def flexural_rigidity_nm2(self) -> float:
        """Flexural rigidity EI [N m^2]."""
        return self.youngs_modulus_pa * self.second_moment_m4


PAPER_STRIP = FlexureStrip()


@dataclass(frozen=True)
class TipLoad:
    """
    Dead load at the flexure tip, F_f of paper Eq. 2.

    :ivar force_x_n: F_fx, horizontal force [N], fixed in direction.
    :ivar force_y_n: F_fy, vertical force [N], fixed in direction.
    :ivar moment_nm: F_ftheta, moment about the tip [N m], counter-clockwise positive.
    """

    force_x_n: float
    force_y_n: float
    moment_nm: float


@dataclass(frozen=True)
class ElasticaSolution:
    """
    Equilibrium shape of a loaded strip.

    :ivar strip: the strip solved for.
    :ivar load: the tip load the shape is in equilibrium with.
    :ivar s_m: arc-length nodes of the final collocation mesh [m].
    :ivar theta_rad: tangent angle theta(s) [rad].
    :ivar curvature_per_m: dtheta/ds [1/m].
    :ivar x_m: horizontal centreline coordinate x(s) [m].
    :ivar y_m: vertical centreline coordinate y(s) [m].
    :ivar max_rms_residual: largest relative collocation residual reported by solve_bvp [-].
    :ivar n_iterations: Newton iterations used by solve_bvp.
    :ivar message: solve_bvp termination message.
    """

    strip: FlexureStrip
    load: TipLoad
    s_m: np.ndarray
    theta_rad: np.ndarray
    curvature_per_m: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    max_rms_residual: float
    n_iterations: int
    message: str

    @property
    def tip_x_m(self) -> float:
        """Tip horizontal position x_f [m]."""
        return float(self.x_m[-1])

    @property
    def tip_y_m(self) -> float:
        """Tip vertical position y_f [m]."""
        return float(self.y_m[-1])

    @property
    def tip_theta_rad(self) -> float:
        """Tip angle theta_f [rad]."""
        return float(self.theta_rad[-1])

    @property
    def tip_deflection(self) -> tuple[float, float, float]:
        """Tip deflection (x_f [m], y_f [m], theta_f [rad])."""
        return (self.tip_x_m, self.tip_y_m, self.tip_theta_rad)

    @property
    def n_nodes(self) -> int:
        """Count the nodes of the final collocation mesh."""
        return int(self.s_m.size)

    def curvature_bc_residual(self) -> float:
        """Scaled residual l_f * |z2(l_f) - F_ftheta / EI| of the free-end BC [-]."""
        expected = self.load.moment_nm / self.strip.flexural_rigidity_nm2
        return abs(float(self.curvature_per_m[-1]) - expected) * self.strip.length_m

    def shooting_mismatch(self) -> float:
        """
        Largest scaled tip-state difference to an independent initial-value solve [-].

        Eq. 3 is integrated from the clamp with the solution's root curvature by an
        explicit Runge-Kutta method (DOP853), independently of the collocation mesh;
        theta and l_f dtheta/ds are compared in rad, x and y in units of l_f.
        """
        length = self.strip.length_m
        rigidity = self.strip.flexural_rigidity_nm2
        rhs, _ = _plain_rhs(self.load.force_x_n * length ** 2 / rigidity,
                            self.load.force_y_n * length ** 2 / rigidity)
        root = np.array((self.theta_rad[0], self.curvature_per_m[0] * length,
                         self.x_m[0] / length, self.y_m[0] / length))
        tip = np.array((self.theta_rad[-1], self.curvature_per_m[-1] * length,
                        self.x_m[-1] / length, self.y_m[-1] / length))
        shot = solve_ivp(lambda u, z: rhs(u, z[:, None])[:, 0], (0.0, 1.0), root,
                         method='DOP853', rtol=1e-12, atol=1e-12)
        return float(np.max(np.abs(shot.y[:, -1] - tip)))

    def is_verified(self, tolerance: float = 1e-6) -> bool:
        """
        Check that the shape satisfies the BVP to within a scaled tolerance.

        The collocation residual, the clamp conditions and the free-end curvature
        condition z2(l_f) = F_ftheta / EI must all be below ``tolerance`` (lengths
        scaled by l_f).
        """
        length = self.strip.length_m
        clamp_residual = max(abs(float(self.theta_rad[0])),
                             abs(float(self.x_m[0])) / length,
                             abs(float(self.y_m[0])) / length)
        return bool(self.max_rms_residual < tolerance
                    and clamp_residual < tolerance
                    and self.curvature_bc_residual() < tolerance)


# An initial estimate is one of: None (arc of the pure-moment curvature), a uniform
# curvature [1/m], a callable theta(s) [rad] of s [m], or a previous solution.
InitialEstimate = Union[None, float, Callable[[np.ndarray], np.ndarray], ElasticaSolution]


def _scaled_state_from_theta(u: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Build a consistent scaled state (theta, l theta', x/l, y/l) from theta(u)."""
    curvature = np.gradient(theta, u, edge_order=2)
    du = np.diff(u)
    cos_mid = 0.5 * (np.cos(theta[1:]) + np.cos(theta[:-1]))
    sin_mid = 0.5 * (np.sin(theta[1:]) + np.sin(theta[:-1]))
    x = np.concatenate(([0.0], np.cumsum(cos_mid * du)))
    y = np.concatenate(([0.0], np.cumsum(sin_mid * du)))
    return np.vstack((theta, curvature, x, y))


def _scaled_initial_state(strip: FlexureStrip, load: TipLoad, estimate: InitialEstimate,
                          n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Turn a user initial estimate into a scaled mesh and state for solve_bvp."""
    length = strip.length_m
    if isinstance(estimate, ElasticaSolution):
        u = estimate.s_m / estimate.strip.length_m
        state = np.vstack((estimate.theta_rad,
                           estimate.curvature_per_m * estimate.strip.length_m,
                           estimate.x_m / estimate.strip.length_m,
                           estimate.y_m / estimate.strip.length_m))
        return u, state
    u = np.linspace(0.0, 1.0, n_nodes)
    if callable(estimate):
        theta = np.asarray(estimate(u * length), dtype=float)
        if theta.shape != u.shape:
            raise ValueError('initial theta(s) estimate must return one angle per node')
        return u, _scaled_state_from_theta(u, theta)
    if estimate is None:
        scaled_curvature = load.moment_nm * length / strip.flexural_rigidity_nm2
    else:
        scaled_curvature = float(estimate) * length
    return u, _scaled_state_from_theta(u, scaled_curvature * u)


def _plain_rhs(a_x: float, a_y: float):
    """Scaled Eq. 3; a_x, a_y are F_fx l^2 / EI and F_fy l^2 / EI."""
    def rhs(u, z):
        theta = z[0]
        return np.vstack((z[1],
                          a_x * np.sin(theta) - a_y * np.cos(theta),
                          np.cos(theta),
                          np.sin(theta)))

    def jac(u, z):
        theta = z[0]
        n = theta.size
        dfdz = np.zeros((4, 4, n))
        dfdz[0, 1] = 1.0
        dfdz[1, 0] = a_x * np.cos(theta) + a_y * np.sin(theta)
        dfdz[2, 0] = -np.sin(theta)
        dfdz[3, 0] = np.cos(theta)
        return dfdz
    return rhs, jac


def _solution_from_bvp(strip: FlexureStrip, load: TipLoad, result) -> ElasticaSolution:
    length = strip.length_m
    return ElasticaSolution(
        strip=strip,
        load=load,
        s_m=result.x * length,
        theta_rad=result.y[0].copy(),
        curvature_per_m=result.y[1] / length,
        x_m=result.y[2] * length,
        y_m=result.y[3] * length,
        max_rms_residual=float(np.max(result.rms_residuals)),
        n_iterations=int(result.niter),
        message=str(result.message))


def solve_elastica(load: TipLoad,
                   initial_estimate: InitialEstimate = None,
                   strip: FlexureStrip = PAPER_STRIP,
                   *,
                   tolerance: float = DEFAULT_TOLERANCE,
                   max_nodes: int = DEFAULT_MAX_NODES,
                   n_initial_nodes: int = DEFAULT_INITIAL_NODES) -> ElasticaSolution:
    """
    Solve the plain-flexure BVP (paper Eqs. 3-4) for a dead tip load.

    :param load: tip load F_f [N, N, N m].
    :param initial_estimate: None for the pure-moment arc, a uniform curvature [1/m], a
        callable returning theta [rad] at arc lengths s [m], or a previous
        :class:`ElasticaSolution` (continuation).
    :param strip: the strip; defaults to the paper's PF.
    :param tolerance: solve_bvp collocation and boundary tolerance on the scaled problem.
    :param max_nodes: largest collocation mesh solve_bvp may refine to.
    :param n_initial_nodes: mesh size used unless the estimate is a previous solution.
    :returns: The converged equilibrium shape.
    :raises ElasticaError: solve_bvp did not converge.
    """
    length = strip.length_m
    rigidity = strip.flexural_rigidity_nm2
    a_x = load.force_x_n * length ** 2 / rigidity
    a_y = load.force_y_n * length ** 2 / rigidity
    moment = load.moment_nm * length / rigidity
    rhs, jac = _plain_rhs(a_x, a_y)

    def bc(z0, z1):
        return np.array((z0[0], z0[2], z0[3], z1[1] - moment))

    def bc_jac(z0, z1):
        d0 = np.zeros((4, 4))
        d1 = np.zeros((4, 4))
        d0[0, 0] = 1.0
        d0[1, 2] = 1.0
        d0[2, 3] = 1.0
        d1[3, 1] = 1.0
        return d0, d1

    u, state = _scaled_initial_state(strip, load, initial_estimate, n_initial_nodes)
    result = solve_bvp(rhs, bc, u, state, fun_jac=jac, bc_jac=bc_jac, tol=tolerance,
                       bc_tol=tolerance, max_nodes=max_nodes)
    if result.status != 0:
        raise ElasticaError(f'elastica did not converge for {load}: {result.message}')
    return _solution_from_bvp(strip, load, result)


def distinct_tip_deflections(load: TipLoad,
                             initial_estimates: Sequence[InitialEstimate],
                             strip: FlexureStrip = PAPER_STRIP,
                             *,
                             distinct_tolerance: float = 1e-4,
                             verify_tolerance: float = 1e-6,
                             tolerance: float = DEFAULT_TOLERANCE) -> list[ElasticaSolution]:
    """
    Collect the distinct equilibria reached from several initial estimates.

    Estimates that fail to converge or whose result is not verified (see
    :meth:`ElasticaSolution.is_verified`) are skipped.  Two solutions are the same
    when their tip positions differ by at most ``distinct_tolerance * l_f`` and their
    tip angles by at most ``distinct_tolerance`` rad.

    :param load: tip load F_f [N, N, N m].
    :param initial_estimates: estimates as accepted by :func:`solve_elastica`.
    :param strip: the strip; defaults to the paper's PF.
    :param distinct_tolerance: scaled tip-deflection difference that counts as distinct.
    :param verify_tolerance: scaled residual below which a solution is accepted.
    :param tolerance: solve_bvp tolerance for each solve.
    :returns: One verified solution per distinct tip deflection, in order of discovery.
    """
    length = strip.length_m
    found: list[ElasticaSolution] = []
    for estimate in initial_estimates:
        try:
            solution = solve_elastica(load, estimate, strip, tolerance=tolerance)
        except ElasticaError:
            continue
        if not solution.is_verified(verify_tolerance):
            continue
        tip = np.array(solution.tip_deflection) / np.array((length, length, 1.0))
        is_new = all(
            np.max(np.abs(tip - np.array(other.tip_deflection)
                          / np.array((length, length, 1.0)))) > distinct_tolerance
            for other in found)
        if is_new:
            found.append(solution)
    return found


@dataclass(frozen=True)
class ActuatorLinkage:
    """
    Lead-screw actuator linkage of paper Fig. 4 (see module docstring).

    :ivar link_length_m: l_1, length of the rigid link A-B [m].
    :ivar hinge_along_m: b_t = l_p - l_2, position of hinge B along the tip tangent [m].
    :ivar hinge_offset_m: l_v, distance of hinge B below the flexure centreline
        (along -n) and depth of the actuator rod below the clamp [m].
    """

    link_length_m: float = 0.100
    hinge_along_m: float = -0.004
    hinge_offset_m: float = 0.064

    def bearing_offset_m(self, strip: FlexureStrip = PAPER_STRIP) -> float:
        """Offset kappa [m] that makes l0 = 0 at theta_f = 0 (phi = 0)."""
        return self.link_length_m - strip.length_m - self.hinge_along_m

    def hinge_position_m(self, tip_x_m: float, tip_y_m: float,
                         tip_theta_rad: float) -> tuple[float, float]:
        """Hinge B = tip + b_t t - l_v n [m]."""
        cos_t, sin_t = math.cos(tip_theta_rad), math.sin(tip_theta_rad)
        return (tip_x_m + self.hinge_along_m * cos_t + self.hinge_offset_m * sin_t,
                tip_y_m + self.hinge_along_m * sin_t - self.hinge_offset_m * cos_t)

    def link_angle_rad(self, tip_x_m: float, tip_y_m: float, tip_theta_rad: float) -> float:
        """Link angle phi [rad] from l_1 sin(phi) = B_y + l_v (paper Eq. 6)."""
        _, hinge_y = self.hinge_position_m(tip_x_m, tip_y_m, tip_theta_rad)
        sin_phi = (hinge_y + self.hinge_offset_m) / self.link_length_m
        if abs(sin_phi) >= 1.0:
            raise ElasticaError('linkage cannot close: hinge B out of reach of the link')
        return math.asin(sin_phi)

    def extension_m(self, tip_x_m: float, tip_y_m: float, tip_theta_rad: float,
                    strip: FlexureStrip = PAPER_STRIP) -> float:
        """Actuator extension l0 = kappa + B_x - l_1 cos(phi) [m] (paper Eq. 6)."""
        hinge_x, _ = self.hinge_position_m(tip_x_m, tip_y_m, tip_theta_rad)
        phi = self.link_angle_rad(tip_x_m, tip_y_m, tip_theta_rad)
        return self.bearing_offset_m(strip) + hinge_x - self.link_length_m * math.cos(phi)

    def closure_residual_m(self, tip_x_m: float, tip_y_m: float, tip_theta_rad: float,
                           link_angle_rad: float, extension_m: float,
                           strip: FlexureStrip = PAPER_STRIP) -> tuple[float, float]:
        """Residuals of both rows of paper Eq. 6 [m]; zero for a consistent pose."""
        cos_t, sin_t = math.cos(tip_theta_rad), math.sin(tip_theta_rad)
        kappa = self.bearing_offset_m(strip)
        l_1, b_t, l_v = self.link_length_m, self.hinge_along_m, self.hinge_offset_m
        row_x = (extension_m - kappa + l_1 * math.cos(link_angle_rad)
                 - (tip_x_m + b_t * cos_t + l_v * sin_t))
        row_y = (l_1 * math.sin(link_angle_rad) + l_v * cos_t
                 - (tip_y_m + b_t * sin_t + l_v))
        return (row_x, row_y)

    def tip_load(self, actuator_force_n: float, tip_theta_rad: float,
                 link_angle_rad: float) -> TipLoad:
        """Tip load F_f from the actuator force F0 [N] (paper Eq. 5, corrected)."""
        f_0, phi = actuator_force_n, link_angle_rad
        moment = f_0 * (self.hinge_along_m * math.sin(phi - tip_theta_rad)
                        + self.hinge_offset_m * math.cos(tip_theta_rad - phi)) / math.cos(phi)
        return TipLoad(force_x_n=f_0, force_y_n=f_0 * math.tan(phi), moment_nm=moment)


DEFAULT_LINKAGE = ActuatorLinkage()


@dataclass(frozen=True)
class LinkageSolution:
    """
    Equilibrium of the flexure driven through the linkage by a force F0.

    :ivar actuator_force_n: horizontal actuator force F0 [N], positive pushing (+x).
    :ivar link_angle_rad: link angle phi [rad].
    :ivar extension_m: actuator extension l0 [m].
    :ivar elastica: the flexure shape, with the tip load the linkage imposes.
    :ivar linkage: the linkage solved for.
    """

    actuator_force_n: float
    link_angle_rad: float
    extension_m: float
    elastica: ElasticaSolution
    linkage: ActuatorLinkage


def _linkage_problem(strip: FlexureStrip, linkage: ActuatorLinkage,
                     actuator_force_n: Optional[float], extension_m: Optional[float]):
    """Scaled coupled BVP; unknown parameters are phi and, if F0 is None, F0 l^2 / EI."""
    length = strip.length_m
    rigidity = strip.flexural_rigidity_nm2
    l_1 = linkage.link_length_m / length
    b_t = linkage.hinge_along_m / length
    l_v = linkage.hinge_offset_m / length
    kappa = linkage.bearing_offset_m(strip) / length
    force_given = actuator_force_n is not None
    fixed_force = actuator_force_n * length ** 2 / rigidity if force_given else 0.0
    target_extension = 0.0 if force_given else extension_m / length

    def unpack(p):
        return (p[0], fixed_force) if force_given else (p[0], p[1])

    def rhs(u, z, p):
        phi, force = unpack(p)
        theta = z[0]
        return np.vstack((z[1],
                          force * (np.sin(theta) - math.tan(phi) * np.cos(theta)),
                          np.cos(theta),
                          np.sin(theta)))

    def rhs_jac(u, z, p):
        phi, force = unpack(p)
        theta = z[0]
        n = theta.size
        tan_phi = math.tan(phi)
        dfdz = np.zeros((4, 4, n))
        dfdz[0, 1] = 1.0
        dfdz[1, 0] = force * (np.cos(theta) + tan_phi * np.sin(theta))
        dfdz[2, 0] = -np.sin(theta)
        dfdz[3, 0] = np.cos(theta)
        dfdp = np.zeros((4, 1 if force_given else 2, n))
        dfdp[1, 0] = -force * np.cos(theta) / math.cos(phi) ** 2
        if not force_given:
            dfdp[1, 1] = np.sin(theta) - tan_phi * np.cos(theta)
        return dfdz, dfdp

    def bc(z0, z1, p):
        phi, force = unpack(p)
        theta_f, kappa_f, x_f, y_f = z1
        lever = b_t * math.sin(phi - theta_f) + l_v * math.cos(theta_f - phi)
        hinge_x = x_f + b_t * math.cos(theta_f) + l_v * math.sin(theta_f)
        hinge_y = y_f + b_t * math.sin(theta_f) - l_v * math.cos(theta_f)
        residuals = [z0[0], z0[2], z0[3],
                     kappa_f - force * lever / math.cos(phi),
                     l_1 * math.sin(phi) - hinge_y - l_v]
        if not force_given:
            residuals.append(kappa + hinge_x - l_1 * math.cos(phi) - target_extension)
        return np.array(residuals)

    def bc_jac(z0, z1, p):
        phi, force = unpack(p)
        theta_f = z1[0]
        n_bc = 5 if force_given else 6
        n_p = 1 if force_given else 2
        d0 = np.zeros((n_bc, 4))
        d1 = np.zeros((n_bc, 4))
        dp = np.zeros((n_bc, n_p))
        d0[0, 0] = 1.0
        d0[1, 2] = 1.0
        d0[2, 3] = 1.0
        cos_phi = math.cos(phi)
        lever = b_t * math.sin(phi - theta_f) + l_v * math.cos(theta_f - phi)
        dlever_dtheta = -b_t * math.cos(phi - theta_f) - l_v * math.sin(theta_f - phi)
        dlever_dphi = b_t * math.cos(phi - theta_f) + l_v * math.sin(theta_f - phi)
        d1[3, 0] = -force * dlever_dtheta / cos_phi
        d1[3, 1] = 1.0
        dp[3, 0] = -force * (dlever_dphi * cos_phi + lever * math.sin(phi)) / cos_phi ** 2
        d1[4, 0] = -(b_t * math.cos(theta_f) + l_v * math.sin(theta_f))
        d1[4, 3] = -1.0
        dp[4, 0] = l_1 * cos_phi
        if not force_given:
            dp[3, 1] = -lever / cos_phi
            d1[5, 0] = -b_t * math.sin(theta_f) + l_v * math.cos(theta_f)
            d1[5, 2] = 1.0
            dp[5, 0] = l_1 * math.sin(phi)
        return d0, d1, dp

    return rhs, rhs_jac, bc, bc_jac


def _initial_linkage_guess(strip: FlexureStrip, previous: Optional[LinkageSolution],
                           n_nodes: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Scaled mesh, state, phi and scaled F0 to start the coupled solve from."""
    length = strip.length_m
    rigidity = strip.flexural_rigidity_nm2
    if previous is None:
        u = np.linspace(0.0, 1.0, n_nodes)
        state = np.vstack((np.zeros_like(u), np.zeros_like(u), u, np.zeros_like(u)))
        return u, state, 0.0, 0.0
    shape = previous.elastica
    u = shape.s_m / length
    state = np.vstack((shape.theta_rad, shape.curvature_per_m * length,
                       shape.x_m / length, shape.y_m / length))
    if u.size > CONTINUATION_MAX_NODES:
        # solve_bvp only ever adds nodes; restarting every step from an inherited
        # fine mesh makes later (and failing) solves needlessly slow.
        coarse = np.linspace(0.0, 1.0, CONTINUATION_MAX_NODES)
        state = np.vstack([np.interp(coarse, u, row) for row in state])
        u = coarse
    return (u, state, previous.link_angle_rad,
            previous.actuator_force_n * length ** 2 / rigidity)


def _linkage_solution(strip: FlexureStrip, linkage: ActuatorLinkage, result,
                      actuator_force_n: float) -> LinkageSolution:
    phi = float(result.p[0])
    theta_f = float(result.y[0, -1])
    load = linkage.tip_load(actuator_force_n, theta_f, phi)
    shape = _solution_from_bvp(strip, load, result)
    extension = (linkage.bearing_offset_m(strip)
                 + linkage.hinge_position_m(shape.tip_x_m, shape.tip_y_m, theta_f)[0]
                 - linkage.link_length_m * math.cos(phi))
    return LinkageSolution(actuator_force_n=actuator_force_n, link_angle_rad=phi,
                           extension_m=extension, elastica=shape, linkage=linkage)


def solve_linkage(actuator_force_n: float,
                  previous: Optional[LinkageSolution] = None,
                  linkage: ActuatorLinkage = DEFAULT_LINKAGE,
                  strip: FlexureStrip = PAPER_STRIP,
                  *,
                  tolerance: float = DEFAULT_TOLERANCE,
                  max_nodes: int = DEFAULT_MAX_NODES) -> LinkageSolution:
    """
    Solve the flexure and linkage for a given actuator force F0 [N].

    The link angle phi is an unknown parameter of the BVP, fixed by the extra
    boundary condition l_1 sin(phi) = B_y + l_v; the free-end curvature uses the
    moment the linkage imposes at the end state.

    :param actuator_force_n: horizontal actuator force F0 [N], positive pushing.
    :param previous: a nearby solution used as the initial estimate (continuation);
        None starts from the straight, unloaded strip.
    :param linkage: linkage dimensions.
    :param strip: the strip.
    :param tolerance: solve_bvp tolerance on the scaled problem.
    :param max_nodes: largest collocation mesh.
    :returns: The coupled equilibrium.
    :raises ElasticaError: solve_bvp did not converge.
    """
    rhs, rhs_jac, bc, bc_jac = _linkage_problem(strip, linkage, actuator_force_n, None)
    u, state, phi, _ = _initial_linkage_guess(strip, previous, DEFAULT_INITIAL_NODES)
    result = solve_bvp(rhs, bc, u, state, p=[phi], fun_jac=rhs_jac, bc_jac=bc_jac,
                       tol=tolerance, bc_tol=tolerance, max_nodes=max_nodes)
    if result.status != 0:
        raise ElasticaError(
            f'linkage problem did not converge for F0 = {actuator_force_n} N: {result.message}')
    return _linkage_solution(strip, linkage, result, float(actuator_force_n))


def solve_linkage_at_extension(extension_m: float,
                               previous: Optional[LinkageSolution] = None,
                               linkage: ActuatorLinkage = DEFAULT_LINKAGE,
                               strip: FlexureStrip = PAPER_STRIP,
                               *,
                               tolerance: float = DEFAULT_TOLERANCE,
                               max_nodes: int = DEFAULT_MAX_NODES) -> LinkageSolution:
    """
    Solve the flexure and linkage for a prescribed actuator extension l0 [m].

    Both phi and F0 are unknown parameters of the BVP; the extra boundary condition
    is the first row of paper Eq. 6.  A nearby ``previous`` solution is needed for
    large extensions.

    :raises ElasticaError: solve_bvp did not converge.
    """
    rhs, rhs_jac, bc, bc_jac = _linkage_problem(strip, linkage, None, extension_m)
    u, state, phi, force = _initial_linkage_guess(strip, previous, DEFAULT_INITIAL_NODES)
    result = solve_bvp(rhs, bc, u, state, p=[phi, force], fun_jac=rhs_jac, bc_jac=bc_jac,
                       tol=tolerance, bc_tol=tolerance, max_nodes=max_nodes)
    if result.status != 0:
        raise ElasticaError(
            f'linkage problem did not converge for l0 = {extension_m} m: {result.message}')
    force_n = float(result.p[1]) * strip.flexural_rigidity_nm2 / strip.length_m ** 2
    return _linkage_solution(strip, linkage, result, force_n)


@dataclass(frozen=True)
class ForceSweep:
    """
    Coupled equilibria along a sweep of actuator force, sorted by increasing F0.

    :ivar actuator_force_n: F0 [N].
    :ivar extension_m: actuator extension l0 [m].
    :ivar tip_x_m: x_f [m].
    :ivar tip_y_m: y_f [m].
    :ivar tip_theta_rad: theta_f [rad].
    :ivar link_angle_rad: phi [rad].
    :ivar solutions: the full solutions, same order.
    """

    actuator_force_n: np.ndarray
    extension_m: np.ndarray
    tip_x_m: np.ndarray
    tip_y_m: np.ndarray
    tip_theta_rad: np.ndarray
    link_angle_rad: np.ndarray
    solutions: tuple[LinkageSolution, ...]


def _sweep_from_solutions(solutions: Sequence[LinkageSolution]) -> ForceSweep:
    ordered = tuple(sorted(solutions, key=lambda sol: sol.actuator_force_n))
    return ForceSweep(
        actuator_force_n=np.array([sol.actuator_force_n for sol in ordered]),
        extension_m=np.array([sol.extension_m for sol in ordered]),
        tip_x_m=np.array([sol.elastica.tip_x_m for sol in ordered]),
        tip_y_m=np.array([sol.elastica.tip_y_m for sol in ordered]),
        tip_theta_rad=np.array([sol.elastica.tip_theta_rad for sol in ordered]),
        link_angle_rad=np.array([sol.link_angle_rad for sol in ordered]),
        solutions=ordered)


def sweep_actuator_force(forces_n: Sequence[float],
                         linkage: ActuatorLinkage = DEFAULT_LINKAGE,
                         strip: FlexureStrip = PAPER_STRIP) -> ForceSweep:
    """
    Solve the coupled problem along given forces F0 [N] with continuation.

    The forces are visited outwards from the one nearest zero, each solve starting
    from the neighbouring solution, so both push and pull branches stay on the
    equilibrium connected to the straight strip.

    :raises ElasticaError: a solve failed (steps too large for continuation).
    """
    forces = np.unique(np.asarray(forces_n, dtype=float))
    start = int(np.argmin(np.abs(forces)))
    solutions = [solve_linkage(forces[start], None, linkage, strip)]
    for direction in (np.arange(start + 1, forces.size), np.arange(start - 1, -1, -1)):
        previous = solutions[0]
        for index in direction:
            previous = solve_linkage(forces[index], previous, linkage, strip)
            solutions.append(previous)
    return _sweep_from_solutions(solutions)


def _fold_error(near: LinkageSolution) -> ElasticaError:
    return ElasticaError(
        f'actuator force sweep stalled at F0 = {near.actuator_force_n:.6g} N, '
        f'l0 = {near.extension_m:.6g} m: F0 appears to have a fold (maximum) there, so a '
        'longer link l_1 is needed to reach further')


def sweep_to_extension(extension_limit_m: float,
                       linkage: ActuatorLinkage = DEFAULT_LINKAGE,
                       strip: FlexureStrip = PAPER_STRIP,
                       *,
                       angle_step_rad: float = 0.05,
                       max_steps: int = 400,
                       max_nodes: int = SWEEP_MAX_NODES) -> ForceSweep:
    """
    Sweep F0 both ways from zero until |l0| exceeds ``extension_limit_m`` [m].

    The force step is adapted from the secant stiffness d(theta_f)/dF0 so that each
    step turns the tip by about ``angle_step_rad``; this keeps continuation steps
    small where the flexure is soft and the sweep short where it is stiff.  A step
    that fails to converge, or jumps to a distant equilibrium, is retried at half
    the size.

    :raises ElasticaError: the limit was not reached within ``max_steps`` steps per side,
        or the force passes a fold (maximum) before the limit, so a sweep in
        F0 cannot reach it.
    """
    rigidity = strip.flexural_rigidity_nm2
    # Linear estimate at theta_f = 0: only the lever l_v acts, theta_f = F0 l_v l_f / EI.
    compliance = linkage.hinge_offset_m * strip.length_m / rigidity
    origin = solve_linkage(0.0, None, linkage, strip, max_nodes=max_nodes)
    solutions = [origin]
    for sign in (1.0, -1.0):
        previous = origin
        force_step = angle_step_rad / compliance
        for _ in range(max_steps):
            current = None
            while current is None:
                try:
                    current = solve_linkage(previous.actuator_force_n + sign * force_step,
                                            previous, linkage, strip, max_nodes=max_nodes)
                    turned = current.elastica.tip_theta_rad - previous.elastica.tip_theta_rad
                    # Past a fold in F0 Newton lands on a distant equilibrium; a turn
                    # far beyond the requested step (or backwards) exposes the jump.
                    if not 0.0 < sign * turned < 4.0 * angle_step_rad:
                        current = None
                except ElasticaError:
                    current = None
                if current is None:
                    force_step *= 0.5
                    if force_step * compliance < 1e-3 * angle_step_rad:
                        raise _fold_error(previous)
            # d(theta_f)/dF0 diverges at a fold; stop early instead of creeping at it
            # with ever smaller, ever more expensive steps.
            if abs(turned) / force_step > FOLD_COMPLIANCE_RATIO * compliance:
                raise _fold_error(current)
            force_step = angle_step_rad * force_step / abs(turned)
            solutions.append(current)
            previous = current
            if sign * current.extension_m > extension_limit_m:
                break
        else:
            raise ElasticaError(
                f'extension {sign * extension_limit_m} m not reached in {max_steps} steps')
    return _sweep_from_solutions(solutions)


PAPER_EXTENSION_GRID_M = np.round(np.linspace(-0.045, 0.045, 19), 12)


@dataclass(frozen=True)
class PlainFlexureTable:
    """
    Flexure tip deflection against actuator extension (paper Fig. 5).

    :ivar extension_m: l0 [m], strictly increasing.
    :ivar tip_x_m: x_f [m].
    :ivar tip_y_m: y_f [m].
    :ivar tip_theta_rad: theta_f [rad].
    :ivar actuator_force_n: F0 [N] needed at each extension.
    """

    extension_m: np.ndarray
    tip_x_m: np.ndarray
    tip_y_m: np.ndarray
    tip_theta_rad: np.ndarray
    actuator_force_n: np.ndarray


def characterisation_table(extensions_m: Sequence[float] = PAPER_EXTENSION_GRID_M,
                           linkage: ActuatorLinkage = DEFAULT_LINKAGE,
                           strip: FlexureStrip = PAPER_STRIP,
                           *,
                           refine: bool = True) -> PlainFlexureTable:
    """
    Tip deflection of the PF on a grid of actuator extensions l0 [m].

    A force sweep reaching past the largest ``|l0|`` is interpolated in ``l0`` with
    monotone (PCHIP) interpolants.  With ``refine`` each row is then solved exactly
    at its extension (phi and F0 unknown), starting from the interpolated force and
    the nearest swept shape, so the rows are model solutions, not interpolants.

    :raises ElasticaError: the sweep or a refinement failed, or l0 is not monotone in F0.
    """
    extensions = np.asarray(extensions_m, dtype=float)
    if extensions.ndim != 1 or np.any(np.diff(extensions) <= 0.0):
        raise ValueError('extensions_m must be a strictly increasing 1-D sequence')
    limit = float(np.max(np.abs(extensions)))
    sweep = sweep_to_extension(limit, linkage, strip)
    if np.any(np.diff(sweep.extension_m) <= 0.0):
        raise ElasticaError('actuator extension is not monotone in actuator force')

    def along_extension(values):
        return PchipInterpolator(sweep.extension_m, values)(extensions)

    forces = along_extension(sweep.actuator_force_n)
    link_angles = along_extension(sweep.link_angle_rad)
    tip_x = along_extension(sweep.tip_x_m)
    tip_y = along_extension(sweep.tip_y_m)
    tip_theta = along_extension(sweep.tip_theta_rad)
    if refine:
        nearest = np.searchsorted(sweep.extension_m, extensions).clip(
            0, sweep.extension_m.size - 1)
        for row, extension in enumerate(extensions):
            # The nearest swept shape with interpolated F0 and phi starts Newton close.
            seed = replace(sweep.solutions[nearest[row]],
                           actuator_force_n=float(forces[row]),
                           link_angle_rad=float(link_angles[row]))
            exact = solve_linkage_at_extension(float(extension), seed, linkage, strip)
            forces[row] = exact.actuator_force_n
            tip_x[row], tip_y[row], tip_theta[row] = exact.elastica.tip_deflection
    return PlainFlexureTable(extension_m=extensions, tip_x_m=tip_x, tip_y_m=tip_y,
                             tip_theta_rad=tip_theta, actuator_force_n=forces)
