"""redman-jax: a differentiable, vectorised JAX simulator for redundant arms among obstacles.

Importing the package enables float64 (``jax_enable_x64``), as the thesis used double precision
and the contact model is stiff. Set the environment variable ``REDMAN_JAX_X64=0`` before the
import to keep JAX's float32 default; every public function also runs in float32.
"""

import os as _os

import jax as _jax

if _os.environ.get("REDMAN_JAX_X64", "1") != "0":
    _jax.config.update("jax_enable_x64", True)

from ._robot import Arm as Arm, thesis_arm as thesis_arm, JOINT_SEQUENCES as JOINT_SEQUENCES
from ._kinematics import (
    Kinematics as Kinematics,
    kinematics as kinematics,
    forward_kinematics as forward_kinematics,
    end_effector_frame as end_effector_frame,
    end_effector_pose as end_effector_pose,
    space_jacobian as space_jacobian,
    jacobian as jacobian,
    jacobian_from as jacobian_from,
    point_jacobian as point_jacobian,
    link_jacobians as link_jacobians,
    poi_positions as poi_positions,
    poi_positions_from as poi_positions_from,
    poi_jacobians as poi_jacobians,
    poi_jacobians_from as poi_jacobians_from,
    poi_link_index as poi_link_index,
    jdot_qdot as jdot_qdot,
)
from ._dynamics import (
    LimitContact as LimitContact,
    mass_matrix as mass_matrix,
    mass_matrix_lagrange as mass_matrix_lagrange,
    bias_forces as bias_forces,
    bias_forces_lagrange as bias_forces_lagrange,
    gravity_forces as gravity_forces,
    coriolis_matrix as coriolis_matrix,
    rnea as rnea,
    dynamics_terms as dynamics_terms,
    forward_dynamics as forward_dynamics,
    kinetic_energy as kinetic_energy,
    potential_energy as potential_energy,
    joint_limit_torque as joint_limit_torque,
    state_derivative as state_derivative,
)


from ._obstacles import (
    Shapes as Shapes,
    ObstacleSet as ObstacleSet,
    make_obstacles as make_obstacles,
    empty_obstacles as empty_obstacles,
    pad_obstacles as pad_obstacles,
    stack_obstacles as stack_obstacles,
    obstacle_distances as obstacle_distances,
    min_distance as min_distance,
)
from ._scenario import (
    Reference as Reference,
    Scenario as Scenario,
    CASES as CASES,
    stack_scenarios as stack_scenarios,
    reference_sample as reference_sample,
)
from ._control_types import (
    ControlState as ControlState,
    RefSample as RefSample,
    Environment as Environment,
    make_environment as make_environment,
    ControlOutput as ControlOutput,
    AbstractController as AbstractController,
)
__version__ = "0.1.0"
