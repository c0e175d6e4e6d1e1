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
    points_min_distance as points_min_distance,
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
from ._urdf import (
    from_urdf as from_urdf,
    from_urdf_string as from_urdf_string,
    to_urdf as to_urdf,
)
from ._fields import (
    FieldParams as FieldParams,
    obstacle_potential as obstacle_potential,
    obstacle_field_potential as obstacle_field_potential,
    obstacle_field_gradient as obstacle_field_gradient,
    obstacle_field_gradients as obstacle_field_gradients,
    goal_potential as goal_potential,
    goal_gradient as goal_gradient,
    virtual_potential as virtual_potential,
    virtual_gradient as virtual_gradient,
    total_potential as total_potential,
    total_gradient as total_gradient,
    total_hessian as total_hessian,
    guidance_velocity as guidance_velocity,
)
from ._planning import (
    RRTParams as RRTParams,
    RRTResult as RRTResult,
    plan_rrt as plan_rrt,
    plan_rrt_batch as plan_rrt_batch,
    smooth_path as smooth_path,
    subsample_path as subsample_path,
    quartic_trajectory as quartic_trajectory,
    time_scale as time_scale,
    rrt_reference as rrt_reference,
    rrt_reference_batch as rrt_reference_batch,
)
from ._trajectories import (
    trapezoid_profile as trapezoid_profile,
    line_segment as line_segment,
    arc_segment as arc_segment,
    assemble_reference as assemble_reference,
)
from ._cases import (
    CaseParams as CaseParams,
    make_scenario as make_scenario,
    make_scenarios as make_scenarios,
    make_valid_scenario as make_valid_scenario,
    obstacle_capacities as obstacle_capacities,
)
from ._nullspace import (
    PolicyGains as PolicyGains,
    ik_policy_gains as ik_policy_gains,
    damped_pinv as damped_pinv,
    damped_solve as damped_solve,
    nullspace_projector as nullspace_projector,
    oblique_projector as oblique_projector,
    task_priority as task_priority,
    obstacle_policy as obstacle_policy,
    joint_limit_policy as joint_limit_policy,
    damping_policy as damping_policy,
    nullspace_policy as nullspace_policy,
)
from ._controllers import (
    JointSpaceGains as JointSpaceGains,
    PIDGains as PIDGains,
    VelocityGains as VelocityGains,
    AccelerationGains as AccelerationGains,
    ImpedanceGains as ImpedanceGains,
    GradientGains as GradientGains,
    JointSpaceID as JointSpaceID,
    PID as PID,
    VelocityOSC as VelocityOSC,
    VelocityOSCOriginal as VelocityOSCOriginal,
    AccelerationOSC as AccelerationOSC,
    Impedance as Impedance,
    GradientGuided as GradientGuided,
    CONTROLLERS as CONTROLLERS,
    make_controller as make_controller,
)
from ._qp import (
    QPSettings as QPSettings,
    QPSolution as QPSolution,
    solve_qp as solve_qp,
    solve_box_qp as solve_box_qp,
)
from ._ik import (
    IKParams as IKParams,
    IKResult as IKResult,
    ik_reference as ik_reference,
    ik_trajectory as ik_trajectory,
    validate_ik as validate_ik,
    validated_scenarios as validated_scenarios,
)
from ._math import cast_floating as cast_floating
from ._sim import (
    SimParams as SimParams,
    SimResult as SimResult,
    JointReference as JointReference,
    simulate as simulate,
    simulate_batch as simulate_batch,
    simulate_dense as simulate_dense,
    joint_reference as joint_reference,
)
from ._guidance import (
    VirtualBuffer as VirtualBuffer,
    estimate_local_minimum as estimate_local_minimum,
    estimator_update as estimator_update,
    goal_field_minimum as goal_field_minimum,
    PerfectParams as PerfectParams,
    PerfectResult as PerfectResult,
    perfect_controller as perfect_controller,
    perfect_controller_batch as perfect_controller_batch,
)
from ._metrics import (
    RunMetrics as RunMetrics,
    run_metrics as run_metrics,
    position_errors as position_errors,
    orientation_errors as orientation_errors,
    pooled_mean as pooled_mean,
    per_run_mean as per_run_mean,
    failure_rate as failure_rate,
    controller_time_per_sample as controller_time_per_sample,
    controller_call_time as controller_call_time,
)
from ._study import (
    SweepConfig as SweepConfig,
    run_sweep as run_sweep,
    load_runs as load_runs,
)
from ._report import (
    make_report as make_report,
    headline_table as headline_table,
)
from ._tuning import (
    tune_gains as tune_gains,
    tune_gains_batch as tune_gains_batch,
    step_response as step_response,
    settling_time as settling_time,
    soft_settling_time as soft_settling_time,
    TuneResult as TuneResult,
)

__version__ = "0.1.0"

# The figures' functions load matplotlib (and select its Agg backend) when first asked for, not at
# ``import redman_jax``: 1.95-2.10 s with them, 1.57-1.64 s without (``python -X importtime``, the two
# alternating, three times each), in every process that never plots (the sweep's workers, --help).
_LAZY = {"plot_scenario": "._plots", "plot_field_slice": "._plots"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
