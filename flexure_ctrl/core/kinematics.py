"""
Forward map of the two-link flexure arm and its analytic Jacobian.

Frames (REP 103, planar): the rig frame has x horizontal away from the base and y up,
with its origin at the fixed root of flexure 1. Flexure 1 bends to tip pose
``(x_f1, y_f1, theta_1)`` at extension ``l01``. Link 1 carries the root of flexure 2
(and actuator 2, which rides on link 1) at ``(link1_length, link1_offset)`` in the
frame of flexure 1's tip. Flexure 2's tip pose ``(x_f2, y_f2, theta_2)`` at extension
``l02`` is therefore relative to link 1, and link 2 carries the end-point target at
``(link2_length, link2_offset)`` in the frame of flexure 2's tip::

    elbow = p1 + R(theta_1) (L1, h1)
    p2    = elbow + R(theta_1) (x_f2, y_f2)
    end   = p2 + R(theta_1 + theta_2) (L2, h2)

Everything is vectorised over arrays of extension pairs.
"""

import math
from typing import Tuple

from flexure_ctrl.core.design import Design, LinkGeometry
from flexure_ctrl.core.table import CharacterisationTable
import numpy as np

ABOVE = 1.0
BELOW = -1.0


def branch_sign(branch: str) -> float:
    """+1 for the ``above`` branch and -1 for ``below``."""
    if branch == 'above':
        return ABOVE
    if branch == 'below':
        return BELOW
    raise ValueError(f"branch must be 'above' or 'below', got {branch!r}")


class TwoLinkArm:
    """
    Two flexure joints in series with rigid links.

    :param joint1: characterisation of flexure 1 (fixed to the base).
    :param joint2: characterisation of flexure 2 (fixed to link 1).
    :param geometry: the rigid links, in metres.
    """

    def __init__(self, joint1: CharacterisationTable, joint2: CharacterisationTable,
                 geometry: LinkGeometry):
        self.joint1 = joint1
        self.joint2 = joint2
        self.geometry = geometry

    @classmethod
    def from_design(cls, design: Design) -> 'TwoLinkArm':
        """
        Arm whose joints follow the design's tables.

        Both follow the one table, as in the paper, unless the design holds a table of
        its own for joint 2 (a measured design).
        """
        table = CharacterisationTable(design.table)
        if design.table_joint_2 is None:
            return cls(table, table, design.geometry)
        return cls(table, CharacterisationTable(design.table_joint_2), design.geometry)

    def components(self, l01_m: np.ndarray, l02_m: np.ndarray) -> Tuple[np.ndarray, ...]:
        """
        Unchecked fast path over 1-D arrays of equal length.

        Returns ``(x_e, y_e, j11, j12, j21, j22, x_elbow, y_elbow)``: end point (m),
        Jacobian entries ``j_rc = d(coordinate r)/d(l0c)`` and elbow point (m).
        """
        return self._chain_with_jacobian(self.joint1.components(l01_m),
                                         self.joint2.components(l02_m), np)

    def point_components(self, l01_m: float, l02_m: float) -> Tuple[float, ...]:
        """
        Return :meth:`components` for one extension pair, as plain floats (no numpy).

        The streaming path of the inverse solver node, where numpy's per-call overhead
        on single values would dominate. Extensions are clamped to the tables.
        """
        return self._chain_with_jacobian(self.joint1.pose_and_slope_at(l01_m),
                                         self.joint2.pose_and_slope_at(l02_m), math)

    def _chain_with_jacobian(self, joint1, joint2, trig) -> Tuple:
        """Chain points and Jacobian from both tips' poses and slopes (arrays or floats)."""
        x1, y1, theta1, dx1, dy1, dtheta1 = joint1
        x2, y2, theta2, dx2, dy2, dtheta2 = joint2
        x_elbow, y_elbow, x_p2, y_p2, x_end, y_end = chain_points(
            self.geometry, x1, y1, theta1, x2, y2, theta2, trig=trig)
        cos1, sin1 = trig.cos(theta1), trig.sin(theta1)
        # A joint rotation swings everything beyond its tip about that tip.
        j11 = dx1 - dtheta1 * (y_end - y1)
        j21 = dy1 + dtheta1 * (x_end - x1)
        j12 = cos1 * dx2 - sin1 * dy2 - dtheta2 * (y_end - y_p2)
        j22 = sin1 * dx2 + cos1 * dy2 + dtheta2 * (x_end - x_p2)
        return x_end, y_end, j11, j12, j21, j22, x_elbow, y_elbow

    def forward_with_jacobian(
            self, l01_m, l02_m, check_range: bool = True
    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        End point, Jacobian and elbow point for extension pairs.

        :param l01_m: extensions of actuator 1 in metres, shape ``S``.
        :param l02_m: extensions of actuator 2 in metres, shape ``S``.
        :param check_range: raise if an extension lies outside its table.

        :returns: ``(end, jacobian, elbow)``: end points ``S + (2,)`` in metres;
            ``d(x_e, y_e)/d(l01, l02)`` as ``S + (2, 2)`` (row: coordinate, column:
            actuator), dimensionless; and the root of flexure 2, ``S + (2,)``, which
            tells the branch.
        """
        l01, l02 = np.broadcast_arrays(np.asarray(l01_m, float), np.asarray(l02_m, float))
        if check_range:
            self.joint1.check_in_range(l01)
            self.joint2.check_in_range(l02)
        x_end, y_end, j11, j12, j21, j22, x_elbow, y_elbow = self.components(
            l01.ravel(), l02.ravel())
        shape = l01.shape
        end = np.stack([x_end, y_end], axis=-1).reshape(shape + (2,))
        jacobian = np.stack([j11, j12, j21, j22], axis=-1).reshape(shape + (2, 2))
        elbow = np.stack([x_elbow, y_elbow], axis=-1).reshape(shape + (2,))
        return end, jacobian, elbow

    def forward(self, l01_m, l02_m, check_range: bool = True) -> np.ndarray:
        """End points ``S + (2,)`` in metres for extension pairs of shape ``S``."""
        return self.forward_with_jacobian(l01_m, l02_m, check_range)[0]

    @staticmethod
    def branch_of(end: np.ndarray, elbow: np.ndarray) -> np.ndarray:
        """+1 where the elbow is above (left of) the base-to-end line, -1 below."""
        return branch_of_components(end[..., 0], end[..., 1], elbow[..., 0], elbow[..., 1])


def chain_points(geometry: LinkGeometry, x1, y1, theta1, x2, y2, theta2,
                 trig=np) -> Tuple[np.ndarray, ...]:
    """
    Points of the chain from the two flexure tip poses (each relative to its root).

    :param trig: ``numpy`` for arrays, or ``math`` for plain floats (much faster there).
    :returns: ``(x_elbow, y_elbow, x_tip2, y_tip2, x_end, y_end)`` in metres, rig frame.
    """
    cos1, sin1 = trig.cos(theta1), trig.sin(theta1)
    cos12, sin12 = trig.cos(theta1 + theta2), trig.sin(theta1 + theta2)
    length1, offset1 = geometry.link1_length_m, geometry.link1_offset_m
    length2, offset2 = geometry.link2_length_m, geometry.link2_offset_m
    x_elbow = x1 + cos1 * length1 - sin1 * offset1
    y_elbow = y1 + sin1 * length1 + cos1 * offset1
    x_tip2 = x_elbow + cos1 * x2 - sin1 * y2
    y_tip2 = y_elbow + sin1 * x2 + cos1 * y2
    x_end = x_tip2 + cos12 * length2 - sin12 * offset2
    y_end = y_tip2 + sin12 * length2 + cos12 * offset2
    return x_elbow, y_elbow, x_tip2, y_tip2, x_end, y_end


def branch_of_components(x_end, y_end, x_elbow, y_elbow) -> np.ndarray:
    """+1 where the elbow is left of the base-to-end line (``above``), else -1."""
    return np.where(x_end * y_elbow - y_end * x_elbow >= 0.0, ABOVE, BELOW)
