"""The one controller interface shared by the simulator, the tuner and users' own code.

A controller is an :class:`AbstractController` (static options only: which projector, which
policies, orientation scaling mode...). Its numbers live in a separate gains pytree (an
``eqx.Module`` of arrays), so a sweep or a gradient over gains never recompiles:

``out = controller(gains, arm, state, ref, env)`` with

* ``state``: :class:`ControlState` (``t``, ``q``, ``qd`` and the controller's integrated state ``z``,
  a pytree it defines through ``init_state``, e.g. the velocity OSC's ``q_r``);
* ``ref``: :class:`RefSample`, the zero-order-held reference sample (operational and joint space);
* ``env``: :class:`Environment`, obstacles, goal and the virtual-obstacle buffer;
* ``out``: :class:`ControlOutput`: joint torques ``tau``, ``dz = dz/dt`` (same structure as ``z``) and
  a dict of diagnostics (e.g. ``"tau_null"``, the null-space part of the command).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PyTree

from ._obstacles import ObstacleSet

__all__ = ["ControlState", "RefSample", "Environment", "make_environment", "ControlOutput", "AbstractController"]


class ControlState(eqx.Module):
    t: Float[Array, ""]
    q: Float[Array, " n"]
    qd: Float[Array, " n"]
    z: PyTree


class RefSample(eqx.Module):
    """One held reference sample. Operational space: ``p, v, a`` (3,), ``quat`` (4,), ``omega,
    omega_dot`` (3,), ``rot`` in {0, 1}. Joint space (from the IK; zeros where unused):
    ``q, qd, qdd`` (n,)."""

    p: Float[Array, "3"]
    v: Float[Array, "3"]
    a: Float[Array, "3"]
    quat: Float[Array, "4"]
    omega: Float[Array, "3"]
    omega_dot: Float[Array, "3"]
    rot: Float[Array, ""]
    q: Float[Array, " n"]
    qd: Float[Array, " n"]
    qdd: Float[Array, " n"]


class Environment(eqx.Module):
    """What a controller may sense of the world: ``obstacles``, the goal pose and the buffer of
    virtual obstacles of the local-minima estimator (``virtual_p`` ``(B, 3)``, ``virtual_mask``
    ``(B,)``; empty for controllers that do not use it)."""

    obstacles: ObstacleSet
    goal_p: Float[Array, "3"]
    goal_quat: Float[Array, "4"]
    virtual_p: Float[Array, "B 3"]
    virtual_mask: Bool[Array, " B"]


def make_environment(obstacles: ObstacleSet, goal_p, goal_quat, buffer_size: int = 20) -> Environment:
    """What a controller sees of the world: the obstacles, the goal pose (``goal_p`` ``(3,)``,
    ``goal_quat`` ``(4,)``, w first, unit) and an empty buffer of ``buffer_size`` virtual obstacles.
    **Raises** ``ValueError`` naming the argument for a wrong shape or (where concrete) a
    non-finite goal or a quaternion that is not unit (a zero one turned orientation control off
    unnoticed, a longer one scaled its gain), or a ``buffer_size`` below 1."""
    from ._math import check_count, check_shape_finite, check_unit_quaternions, floating_dtype, is_floating_array

    check_shape_finite("goal_p", goal_p, (3,))
    check_shape_finite("goal_quat", goal_quat, (4,))
    check_unit_quaternions("goal_quat", goal_quat)
    check_count("buffer_size", buffer_size, 1)
    # one float type for the goal (integer goals: the default float); a goal_quat given as a list
    # takes goal_p's (it promoted a float32 environment, and every command, to float64)
    typed = [x for x in (goal_p, goal_quat) if is_floating_array(x)] or [jnp.asarray(goal_p)]
    dtype = floating_dtype(*typed)
    return Environment(
        obstacles=obstacles,
        goal_p=jnp.asarray(goal_p, dtype),
        goal_quat=jnp.asarray(goal_quat, dtype),
        virtual_p=jnp.zeros((buffer_size, 3), dtype),
        virtual_mask=jnp.zeros((buffer_size,), bool),
    )


class ControlOutput(eqx.Module):
    tau: Float[Array, " n"]
    dz: PyTree
    diag: dict


class AbstractController(eqx.Module):
    """Base of every controller. Concrete controllers are final and hold static options only."""

    @abc.abstractmethod
    def default_gains(self):
        """The thesis gains (a pytree of arrays)."""

    @abc.abstractmethod
    def init_state(self, arm, q0, qd0) -> PyTree:
        """Initial integrated state ``z`` (``()`` if none)."""

    @abc.abstractmethod
    def __call__(self, gains, arm, state: ControlState, ref: RefSample, env: Environment) -> ControlOutput:
        """Joint torques for this state; see the module docstring."""

    @property
    def needs_joint_reference(self) -> bool:
        """True for joint-space controllers, which need the IK's ``q, qd, qdd``."""
        return False

    @property
    def uses_guidance(self) -> bool:
        """True for the gradient-guided controller (the simulator runs the estimator for it)."""
        return False

    @property
    def auto_solver(self) -> str:
        """The solver ``SimParams(solver="auto")`` integrates this controller's closed loop with
        (a name of :data:`~redman_jax._sim.SOLVER_CHOICES`): Dopri5 unless a controller says
        otherwise (the acceleration-level OSCs, whose runs Dopri5 integrates less accurately at
        the default tolerances; measured in :mod:`redman_jax._sim`'s docstring)."""
        return "dopri5"

    @property
    def reads_obstacles(self) -> bool:
        """Whether the control law passes over the environment's obstacles (a null-space obstacle
        policy, a guidance field). True unless a controller says otherwise: the study shares one
        padded shape among all its cases only for a controller that does not
        (:func:`~redman_jax._pipeline.study_shapes`, ``every_case``); the simulator's collision
        flag passes over them in any case."""
        return True
