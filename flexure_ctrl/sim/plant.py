"""
The simulated arm's true static response, which the controller's table does not know.

The paper names why its feedforward misses (the section after Eq. 7): the static table
was measured without the rigid bodies attached, so in the assembled arm the joints sag
under the links' weight; and each joint differs a little from the characterised one.
This plant has exactly those two differences from the design's table:

* each joint's tip angle is ``scale * theta_table(l0) + offset``;
* each joint bends further by ``compliance * M_gravity``, where ``M_gravity`` is the
  moment of the links' weight beyond it about its tip (gravity along -y, rig frame).

``gravity_sag_scale`` multiplies the sag (0 turns it off).
"""

from dataclasses import dataclass, field
import math
from typing import Tuple

from flexure_ctrl.core.design import Design
from flexure_ctrl.core.kinematics import chain_points
from flexure_ctrl.core.table import CharacterisationTable
import numpy as np

STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class PlantParameters:
    """
    Knobs of the true arm (``plant:`` in the simulator YAML).

    The defaults give the uncorrected errors of the paper's Table 1 order: a few mm in x
    and 10 to 25 mm in y on its path.
    """

    gravity_sag_scale: float = 1.0
    joint_offset_rad: Tuple[float, float] = (0.004, -0.003)
    joint_scale: Tuple[float, float] = (1.02, 0.985)
    # Link 1 carries actuator 2 and the joint-2 clamp; link 2 carries the end target.
    link_mass_kg: Tuple[float, float] = (0.8, 0.5)
    # Rotational compliance of flexure plus linkage with the actuator rod held.
    joint_compliance_rad_per_n_m: Tuple[float, float] = field(default=(0.003, 0.003))


class SimulatedArm:
    """
    True end point of the arm for true actuator rod positions.

    :param design: the design whose table the controller uses; the true joints deviate
        from it as set by ``parameters``.
    :param parameters: the deviations.
    """

    def __init__(self, design: Design, parameters: PlantParameters = PlantParameters()):
        self.design = design
        self.parameters = parameters
        self.table = CharacterisationTable(design.table)

    def joint_poses(self, l01_m, l02_m) -> Tuple[np.ndarray, ...]:
        """Return the tip poses ``(x1, y1, theta1, x2, y2, theta2)`` the table predicts."""
        return (*self._joint_pose(l01_m), *self._joint_pose(l02_m))

    def _joint_pose(self, l0_m) -> Tuple[np.ndarray, ...]:
        """Table pose at rod positions, continued along the end slopes beyond the table."""
        # Rods can overrun the characterised range up to the end stops. A real flexure
        # goes on bending smoothly there: continue the table along its end tangents (a
        # flat continuation would put a kink at the ends that no flexure has).
        l0 = np.asarray(l0_m, float).ravel()
        inside = np.clip(l0, self.table.l0_min_m, self.table.l0_max_m)
        x, y, theta, dx, dy, dtheta = self.table.components(inside)
        beyond = l0 - inside
        return x + dx * beyond, y + dy * beyond, theta + dtheta * beyond

    def end_point(self, l01_m, l02_m) -> np.ndarray:
        """Return the true end points (m), ``S + (2,)``, for rod positions of shape ``S``."""
        shape = np.broadcast(np.asarray(l01_m), np.asarray(l02_m)).shape
        x1, y1, theta1, x2, y2, theta2 = self.joint_poses(
            np.broadcast_to(l01_m, shape), np.broadcast_to(l02_m, shape))
        p = self.parameters
        theta1 = p.joint_scale[0] * theta1 + p.joint_offset_rad[0]
        theta2 = p.joint_scale[1] * theta2 + p.joint_offset_rad[1]
        if p.gravity_sag_scale:
            sag1, sag2 = self._sag(x1, y1, theta1, x2, y2, theta2)
            theta1 = theta1 - sag1
            theta2 = theta2 - sag2
        *_, x_end, y_end = chain_points(self.design.geometry, x1, y1, theta1, x2, y2, theta2)
        return np.stack([x_end, y_end], axis=-1).reshape(shape + (2,))

    def end_point_at(self, l01_m: float, l02_m: float) -> Tuple[float, float]:
        """Return the true end point ``(x, y)`` (m) for one pair of rod positions, fast."""
        x1, y1, theta1, x2, y2, theta2 = self.true_joint_poses_at(l01_m, l02_m)
        *_, x_end, y_end = chain_points(self.design.geometry, x1, y1, theta1, x2, y2, theta2,
                                        trig=math)
        return x_end, y_end

    def true_joint_poses_at(self, l01_m: float, l02_m: float) -> Tuple[float, ...]:
        """
        Return both joints' true tip poses for one pair of rod positions, fast.

        ``(x1, y1, theta1, x2, y2, theta2)`` (m, m, rad), each relative to its own root as
        in the table (joint 1 in the rig frame, joint 2 in link 1's frame), with the
        plant's scale, offset and sag: what a characterisation should measure.
        """
        x1, y1, theta1 = self._joint_pose_at(l01_m)
        x2, y2, theta2 = self._joint_pose_at(l02_m)
        p = self.parameters
        theta1 = p.joint_scale[0] * theta1 + p.joint_offset_rad[0]
        theta2 = p.joint_scale[1] * theta2 + p.joint_offset_rad[1]
        if p.gravity_sag_scale:
            sag1, sag2 = self._sag(x1, y1, theta1, x2, y2, theta2, trig=math)
            theta1 -= sag1
            theta2 -= sag2
        return x1, y1, theta1, x2, y2, theta2

    def _joint_pose_at(self, l0_m: float) -> Tuple[float, float, float]:
        """Scalar :meth:`_joint_pose`: the table pose, along the end tangents beyond it."""
        x, y, theta, dx, dy, dtheta = self.table.pose_and_slope_at(l0_m)
        beyond = l0_m - min(max(l0_m, self.table.l0_min_m), self.table.l0_max_m)
        if beyond:
            return x + dx * beyond, y + dy * beyond, theta + dtheta * beyond
        return x, y, theta

    def output_bodies_at(self, l01_m: float, l02_m: float) -> Tuple[Tuple[float, ...], ...]:
        """
        Return the rig-frame poses of both joints' output bodies and the end point.

        ``((x1, y1, theta1), (x2, y2, theta1 + theta2), (x_end, y_end))``: each joint's tip
        position and absolute tip angle in the rig frame (m, rad), then the end point (m).
        """
        x1, y1, theta1, x2, y2, theta2 = self.true_joint_poses_at(l01_m, l02_m)
        _, _, x_tip2, y_tip2, x_end, y_end = chain_points(
            self.design.geometry, x1, y1, theta1, x2, y2, theta2, trig=math)
        return (x1, y1, theta1), (x_tip2, y_tip2, theta1 + theta2), (x_end, y_end)

    def _sag(self, x1, y1, theta1, x2, y2, theta2, trig=np):
        """Extra bending of each joint under the links' weight (rad, downward positive)."""
        p = self.parameters
        geometry = self.design.geometry
        x_elbow, _, x_tip2, _, x_end, _ = chain_points(geometry, x1, y1, theta1, x2, y2,
                                                       theta2, trig=trig)
        # Centres of mass halfway along each link.
        x_mass1 = 0.5 * (x1 + x_elbow)
        x_mass2 = 0.5 * (x_tip2 + x_end)
        mass1, mass2 = p.link_mass_kg
        moment2 = STANDARD_GRAVITY_M_S2 * mass2 * (x_mass2 - x_tip2)
        moment1 = STANDARD_GRAVITY_M_S2 * (mass1 * (x_mass1 - x1) + mass2 * (x_mass2 - x1))
        compliance1, compliance2 = p.joint_compliance_rad_per_n_m
        scale = p.gravity_sag_scale
        return scale * compliance1 * moment1, scale * compliance2 * moment2
