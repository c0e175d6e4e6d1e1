"""Scenario and reference pytrees shared by the generators, the IK, the controllers and the simulator.

A :class:`Reference` holds the operational-space reference sampled at ``ts`` (SPEC section 5): sample
``k`` is held on ``[k ts, (k + 1) ts)`` (zero-order hold, E29). Arrays are padded to a fixed
length ``N`` with ``mask``; ``n_samples`` is the number of valid samples. After the last valid
sample the padding repeats the final sample at rest, so a padded reference is also a valid one.

A :class:`Scenario` is one generated environment: obstacles, goal pose, reference and the seed it
came from. Scenarios of one case share their shapes and stack along a leading batch axis.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._obstacles import ObstacleSet

__all__ = ["Reference", "Scenario", "CASES", "stack_scenarios", "reference_sample"]

CASES: tuple[str, ...] = ("agriculture", "warehouse", "inspection", "welding", "simple")


class Reference(eqx.Module):
    """Sampled reference, ``N`` samples (padded).

    * ``p``, ``v``, ``a`` ``(N, 3)``: position [m], velocity [m/s], acceleration [m/s^2].
    * ``quat`` ``(N, 4)``: orientation, unit quaternion ``(w, x, y, z)``.
    * ``omega``, ``omega_dot`` ``(N, 3)``: angular velocity [rad/s] and acceleration [rad/s^2].
    * ``rot`` ``(N,)`` float in {0, 1}: orientation control on for that sample (3.13-3.14).
    * ``mask`` ``(N,)`` bool: valid samples; ``n_samples`` int: their number.
    * ``ts``: sample time [s] (an array, so changing it never recompiles).
    """

    p: Float[Array, "N 3"]
    v: Float[Array, "N 3"]
    a: Float[Array, "N 3"]
    quat: Float[Array, "N 4"]
    omega: Float[Array, "N 3"]
    omega_dot: Float[Array, "N 3"]
    rot: Float[Array, " N"]
    mask: Bool[Array, " N"]
    n_samples: Int[Array, ""]
    ts: Float[Array, ""]

    @property
    def capacity(self) -> int:
        return self.p.shape[-2]


class Scenario(eqx.Module):
    """One generated environment (thesis 3.2; SPEC section 4).

    * ``obstacles``: :class:`~redman_jax.ObstacleSet`.
    * ``goal_p`` ``(3,)``, ``goal_quat`` ``(4,)``: goal pose (the last reference sample for
      trajectory cases; the target of the gradient-guided controller).
    * ``reference``: :class:`Reference`.
    * ``seed``: requested seed; ``seed_used``: the seed that produced a valid scene
      (``seed + 1000 k``, thesis 3.4).
    * ``valid``: the scene passed generation, planning (and, once validated, the IK check).
    * ``case``: static case name, one of :data:`CASES`.
    """

    obstacles: ObstacleSet
    goal_p: Float[Array, "3"]
    goal_quat: Float[Array, "4"]
    reference: Reference
    seed: Int[Array, ""]
    seed_used: Int[Array, ""]
    valid: Bool[Array, ""]
    case: str = eqx.field(static=True, default="custom")


def stack_scenarios(scenarios) -> Scenario:
    """Stack scenarios with identical shapes along a new leading axis (for ``vmap``)."""
    scenarios = list(scenarios)
    return jax.tree.map(lambda *xs: jnp.stack(xs), *scenarios)


def reference_sample(ref: Reference, k) -> Reference:
    """Sample ``k`` of a reference (clipped to the valid range), as a pytree of scalars/vectors."""
    k = jnp.clip(k, 0, ref.n_samples - 1)
    take = lambda x: x[k]
    return Reference(
        p=take(ref.p), v=take(ref.v), a=take(ref.a), quat=take(ref.quat), omega=take(ref.omega),
        omega_dot=take(ref.omega_dot), rot=take(ref.rot), mask=take(ref.mask),
        n_samples=ref.n_samples, ts=ref.ts,
    )
