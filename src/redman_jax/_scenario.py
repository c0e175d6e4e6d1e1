"""Scenario and reference pytrees shared by the generators, the IK, the controllers and the simulator.

A :class:`Reference` holds the operational-space reference sampled at ``ts`` (SPEC section 5): sample
``k`` is held on ``[k ts, (k + 1) ts)`` (zero-order hold, E29). Arrays are padded to a fixed
length ``N`` with ``mask``; ``n_samples`` is the number of valid samples. After the last valid
sample the padding repeats the final sample at rest, so a padded reference is also a valid one.

A :class:`Scenario` is one generated environment: obstacles, goal pose, reference and the seed it
came from. Scenarios of one case share their shapes and stack along a leading batch axis
(:func:`stack_scenarios`; with ``pad=True`` scenes of several cases too).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._host import host_array, put
from ._math import check_finite, check_unit_quaternions, concrete
from ._obstacles import ObstacleSet

__all__ = ["Reference", "Scenario", "CASES", "stack_scenarios", "reference_sample"]

CASES: tuple[str, ...] = ("agriculture", "warehouse", "inspection", "welding", "simple")


def check_reference_values(ref, owner: str, batch: bool = False) -> None:
    """Where concrete (any leading batch axes), refuse a reference that cannot be run, naming
    ``owner.<field>``: ``1 <= n_samples <= capacity``; a finite sample time ``ts > 0``; finite
    ``p``, ``v``, ``a``, ``quat``, ``omega``, ``omega_dot``, ``rot``; ``rot`` flags of 0 or 1 (the
    controllers switch at 0.5: a NaN flag switched orientation control off unnoticed); unit
    quaternions on the valid samples (a zero quaternion made the orientation error 0, a scaled one
    scaled its gain). Before: 0 samples gave NaN errors, ``ts <= 0`` integrated nothing or made the
    IK NaN, both with no error; a zero ``quat`` with ``rot = 1`` gave a "valid" IK that ignored
    orientation.

    ``batch=True`` (a batch of runs): a non-finite value is that member's own failure (flagged
    in its result, its batch-mates intact), not an error; the finite values are checked as above.
    """
    n, ts = concrete(ref.n_samples), concrete(ref.ts)
    if n is not None and (np.any(n < 1) or np.any(n > ref.capacity)):
        raise ValueError(f"{owner}.n_samples: expected 1 to {ref.capacity} (the reference's capacity), got {n}")
    if ts is not None and not np.all(np.isfinite(ts) & (ts > 0)):
        raise ValueError(f"{owner}.ts: expected a finite sample time > 0, got {ts}")
    if not batch:
        for name in ("p", "v", "a", "quat", "omega", "omega_dot", "rot"):
            check_finite(f"{owner}.{name}", getattr(ref, name))
    rot = concrete(ref.rot)
    if rot is not None and not np.all((rot == 0) | (rot == 1) | np.isnan(rot)):
        raise ValueError(f"{owner}.rot: expected flags 0 or 1 (orientation control off / on), got "
                         f"{np.unique(rot)}")
    check_unit_quaternions(f"{owner}.quat", ref.quat, ref.mask)  # on the valid samples


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


def stack_scenarios(scenarios, pad: bool = False) -> Scenario:
    """Stack scenarios along a new leading axis (for ``vmap``, :func:`~redman_jax.simulate_batch`).

    They must share their shapes (reference capacity ``N``, obstacle capacities) and their case
    name, as the seeds of one case do. ``pad=True`` stacks scenes of different shapes or cases:
    each reference is padded to the largest ``N`` (invalid samples repeating the last one, as a
    padded reference is built), each obstacle family to its largest capacity (masked slots), and
    the case becomes ``"custom"`` where the cases differ (the simulator never reads it); the runs
    are those of the unpadded scenes, to rounding.

    **Raises** ``ValueError`` for an empty list, an entry that is not a :class:`Scenario` or already
    batched, or (``pad=False``) scenes whose shapes or cases differ, naming the first one.
    """
    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("scenarios: need at least one Scenario to stack")
    for i, s in enumerate(scenarios):
        if not isinstance(s, Scenario):
            raise ValueError(f"scenarios[{i}]: expected a Scenario, got {type(s).__name__}")
        if s.reference.p.ndim != 2:
            raise ValueError(f"scenarios[{i}]: already batched (reference.p of shape "
                             f"{tuple(s.reference.p.shape)}); stack single scenarios")

    def shapes(s):
        return s.reference.capacity, s.obstacles.capacities, s.case

    if pad:
        N = max(s.reference.capacity for s in scenarios)
        caps = tuple(max(c) for c in zip(*(s.obstacles.capacities for s in scenarios)))
        case = scenarios[0].case if len({s.case for s in scenarios}) == 1 else "custom"
        scenarios = [pad_scenario(s, N, caps, case) for s in scenarios]
    else:
        first = shapes(scenarios[0])
        for i, s in enumerate(scenarios[1:], 1):
            if shapes(s) != first:
                raise ValueError(
                    f"scenarios[{i}]: reference capacity {s.reference.capacity}, obstacle capacities "
                    f"{s.obstacles.capacities}, case {s.case!r} differ from scenarios[0]'s {first[0]}, "
                    f"{first[1]}, {first[2]!r}; stack_scenarios(..., pad=True) pads them to common shapes")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *scenarios)


def pad_rows(x, N: int, axis: int = 0, fill=None):
    """``x`` with its sample axis ``axis`` padded to ``N`` rows: ``fill``, or the last row repeated
    (unchanged if it has ``N`` or more). Concrete arrays are padded in NumPy (an eager ``jnp``
    operation compiles once per shape)."""
    x = put(x)
    extra = N - x.shape[axis]
    if extra <= 0:
        return x
    h = host_array(x)
    xp, v = (jnp, x) if h is None else (np, h)
    if fill is None:
        tail = xp.repeat(v[(slice(None),) * axis + (slice(-1, None),)], extra, axis=axis)
    else:
        tail = xp.full(v.shape[:axis] + (extra,) + v.shape[axis + 1:], fill, v.dtype)
    out = xp.concatenate([v, tail], axis=axis)
    return out if h is None else put(out)


def pad_scenario(s: Scenario, N: int, caps: tuple, case: str = "custom") -> Scenario:
    """``s`` (single or with a leading batch axis) with its reference padded to ``N`` samples (the
    last row repeated, ``mask`` False: invalid samples, where the simulator freezes the loop) and
    its obstacle families to the capacities ``caps`` (masked slots); its static case name ``case``."""
    from ._obstacles import pad_obstacles

    ref = s.reference
    ax = ref.p.ndim - 2  # the samples' axis

    def rows(x, fill=None):
        return pad_rows(x, N, ax, fill)

    ref = Reference(p=rows(ref.p), v=rows(ref.v), a=rows(ref.a), quat=rows(ref.quat), omega=rows(ref.omega),
                    omega_dot=rows(ref.omega_dot), rot=rows(ref.rot), mask=rows(ref.mask, False),
                    n_samples=ref.n_samples, ts=ref.ts)
    return Scenario(obstacles=pad_obstacles(s.obstacles, caps), goal_p=s.goal_p, goal_quat=s.goal_quat,
                    reference=ref, seed=s.seed, seed_used=s.seed_used, valid=s.valid, case=case)


def reference_sample(ref: Reference, k) -> Reference:
    """Sample ``k`` of a reference (clipped to the valid range), as a pytree of scalars/vectors."""
    k = jnp.clip(k, 0, ref.n_samples - 1)
    take = lambda x: x[k]
    return Reference(
        p=take(ref.p), v=take(ref.v), a=take(ref.a), quat=take(ref.quat), omega=take(ref.omega),
        omega_dot=take(ref.omega_dot), rot=take(ref.rot), mask=take(ref.mask),
        n_samples=ref.n_samples, ts=ref.ts,
    )
