"""RRT planning in operational space and the smoothing / quartic time-scaling pipeline.

Thesis 3.2.3 (Figure 3.3) and SPEC section 5 (U19, U20, E24). Everything is JAX with static
capacities, so the 20 seeds of a case plan at once: ``jit(vmap(plan))`` over PRNG keys.

1. **RRT** (:func:`plan_rrt`). A tree rooted at the start grows in a node buffer of fixed size
   inside one ``lax.while_loop``; every iteration draws one sample (the goal with probability
   ``goal_bias``, otherwise uniform in the box ``AABB(start, goal, obstacles) + box_margin``),
   finds the nearest node by a masked brute-force search, steers ``step`` towards the sample and
   adds the new node if the edge keeps ``safety`` clearance from every obstacle (checked at points
   at most ``edge_res`` apart; obstacles are "inflated" by the safety radius). A node within
   ``goal_tol`` of the goal with a free edge to it connects the goal. The thesis calls its planner
   "RRT*" but describes goal-biased RRT (E24), the default here; ``rrt_star=True`` adds
   choose-parent and rewiring over the ``k_near`` nearest nodes within ``near_radius`` (costs are
   re-propagated after a rewire by pointer jumping, so they stay exact). Failure (node buffer full,
   iteration budget spent, goal or start blocked, path longer than the path buffer) returns
   ``success=False``, never an exception.
2. **Smoothing** (:func:`smooth_path`): centred moving average (window 5), edge-padded, endpoints
   pinned.
3. **Down-sampling** (:func:`subsample_path`): every 4th point plus both endpoints.
4. **Quartic segments** (:func:`quartic_trajectory`), per axis, with durations
   ``T_k = |P_{k+1} - P_k| / v_init`` (``v_init = 0.5`` m/s) and conditions ``p(0) = P_k``,
   ``p'(0) = v_k``, ``p''(0) = a_k`` (inherited), ``p(T) = P_{k+1}``, ``p'(T) = v_{k+1}`` with
   ``v_{k+1} = (P_{k+2} - P_k)/(T_k + T_{k+1})``, ``v_0 = v_end = 0``, ``a_0 = 0``. Writing
   ``Delta = P_{k+1} - P_k - v_k T - a_k T^2/2`` and ``dv = v_{k+1} - v_k - a_k T``::

       p(tau) = P_k + v_k tau + a_k tau^2/2 + c3 tau^3 + c4 tau^4,
       c3 = 4 Delta / T^3 - dv / T^2,     c4 = dv / T^3 - 3 Delta / T^4,
       a_{k+1} = a_k + 6 (v_k + v_{k+1}) / T - 12 (P_{k+1} - P_k) / T^2.

   Velocity and acceleration are continuous at every joint between segments.
5. **Time scaling** (:func:`time_scale`): the curve is sampled densely and every duration is
   multiplied by ``c = max(1, vmax_hat / v_max, sqrt(amax_hat / a_max))`` (an exact re-timing:
   speeds scale by 1/c, accelerations by 1/c^2).
6. **Resampling** (:func:`sample_reference`) at ``k ts`` plus the end point into a padded
   :class:`~redman_jax.Reference`: constant goal orientation, ``omega = 0``, ``rot = 1`` from the
   first sample within ``rot_radius`` of the goal on (latched). The final sample and the padding
   are the goal at rest (``v = a = 0``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from ._math import check_positive, check_unit_quaternions, concrete, safe_norm
from ._obstacles import ObstacleSet, min_distance
from ._scenario import Reference

__all__ = [
    "RRTParams",
    "RRTResult",
    "QuarticTrajectory",
    "PlanResult",
    "sampling_box",
    "plan_rrt",
    "plan_rrt_batch",
    "smooth_path",
    "subsample_path",
    "quartic_trajectory",
    "time_scale",
    "evaluate_trajectory",
    "trajectory_extrema",
    "sample_reference",
    "plan_reference",
    "rrt_reference",
    "rrt_reference_batch",
    "reference_from_path",
    "plan_reference_batch",
]

_TINY = 1e-9  # [m] two points closer than this are the same point


def _check_integral(name: str, v) -> None:
    """Refuse a concrete count that is not a whole number (a bool, 2.5, NaN); None passes."""
    a = None if v is None else concrete(v)
    if a is None:
        return
    if a.dtype.kind not in "iuf" or (a.dtype.kind == "f" and not np.all(np.isfinite(a) & (a == np.round(a)))):
        raise ValueError(f"{name}: expected a whole number, got {a}")


class RRTParams(eqx.Module):
    """Planner and trajectory parameters (SPEC U19, U20; thesis 3.2.3).

    Arrays (changing them never recompiles):

    * ``step`` 0.05 m: steering step; ``goal_bias`` 0.10: probability of sampling the goal;
    * ``safety`` 0.15 m: clearance every tree edge keeps from every obstacle (inflation) at its
      check points; between them at least ``safety - edge_res / 2`` (so ``safety > edge_res / 2``);
    * ``box_margin`` 0.3 m: the sampling box is ``AABB(start, goal, obstacles)`` grown by it;
    * ``edge_res`` 0.01 m: largest spacing of the edge collision checks;
    * ``goal_tol`` 0.05 m: a node this close to the goal (with a free edge) connects it;
    * ``max_iter`` 20 000: iteration budget;
    * ``near_radius`` 0.15 m, ``refine_iters`` 0: RRT* neighbourhood and extra iterations after
      the first solution (``rrt_star=True`` only);
    * ``v_init`` 0.5 m/s (initial segment speed), ``v_max`` 1 m/s, ``a_max`` 2 m/s^2;
    * ``end_factor`` 1.0: the first and last initial durations are multiplied by it (1 = SPEC;
      2 makes a rest-to-cruise segment consistent with the chord speed, see
      :func:`quartic_trajectory`).

    Static sizes and choices: ``max_nodes`` (node buffer, 4096), ``path_capacity`` (512),
    ``edge_points`` / ``near_points`` (check points per steering / neighbour edge; by default the
    fewest for which the spacing is at most ``edge_res``), ``k_near`` (16), ``rrt_star`` (False),
    ``window`` (5), ``subsample`` (4), ``dense`` (64 samples per segment for the time scaling).

    Raises:
        ValueError: a non-positive or non-finite number, ``goal_bias`` outside [0, 1],
            ``goal_tol > step``, ``near_radius < step``, check points too sparse for ``edge_res``,
            or a bad size, naming the field.
    """

    step: Float[Array, ""]
    goal_bias: Float[Array, ""]
    safety: Float[Array, ""]
    box_margin: Float[Array, ""]
    edge_res: Float[Array, ""]
    goal_tol: Float[Array, ""]
    max_iter: Int[Array, ""]
    near_radius: Float[Array, ""]
    refine_iters: Int[Array, ""]
    v_init: Float[Array, ""]
    v_max: Float[Array, ""]
    a_max: Float[Array, ""]
    end_factor: Float[Array, ""]
    max_nodes: int = eqx.field(static=True)
    path_capacity: int = eqx.field(static=True)
    edge_points: int = eqx.field(static=True)
    near_points: int = eqx.field(static=True)
    k_near: int = eqx.field(static=True)
    rrt_star: bool = eqx.field(static=True)
    window: int = eqx.field(static=True)
    subsample: int = eqx.field(static=True)
    dense: int = eqx.field(static=True)

    def __init__(self, step=0.05, goal_bias=0.10, safety=0.15, box_margin=0.3, edge_res=0.01,
                 goal_tol=0.05, max_iter=20000, near_radius=0.15, refine_iters=0, v_init=0.5,
                 v_max=1.0, a_max=2.0, end_factor=1.0, *, max_nodes=4096, path_capacity=512, edge_points=None,
                 near_points=None, k_near=16, rrt_star=False, window=5, subsample=4, dense=64):
        def npoints(length, res, name):
            lv, rv = concrete(length), concrete(res)
            if lv is None or rv is None:
                raise ValueError(f"RRTParams.{name}: give it explicitly when step/radius are traced")
            if not (np.all(np.isfinite(lv)) and np.all(np.isfinite(rv)) and np.all(rv > 0)):
                raise ValueError(f"RRTParams.edge_res: expected a finite positive value, got {rv}")
            return int(math.ceil(float(np.max(lv)) / float(np.min(rv)) - 1e-9)) + 1

        # counts: int() and jnp.asarray(., int) would truncate 2.5 to 2 without a word
        for name, v in (("max_iter", max_iter), ("refine_iters", refine_iters), ("max_nodes", max_nodes),
                        ("path_capacity", path_capacity), ("edge_points", edge_points),
                        ("near_points", near_points), ("k_near", k_near), ("window", window),
                        ("subsample", subsample), ("dense", dense)):
            _check_integral(f"RRTParams.{name}", v)
        self.step = jnp.asarray(step, float)
        self.goal_bias = jnp.asarray(goal_bias, float)
        self.safety = jnp.asarray(safety, float)
        self.box_margin = jnp.asarray(box_margin, float)
        self.edge_res = jnp.asarray(edge_res, float)
        self.goal_tol = jnp.asarray(goal_tol, float)
        self.max_iter = jnp.asarray(max_iter, int)
        self.near_radius = jnp.asarray(near_radius, float)
        self.refine_iters = jnp.asarray(refine_iters, int)
        self.v_init = jnp.asarray(v_init, float)
        self.v_max = jnp.asarray(v_max, float)
        self.a_max = jnp.asarray(a_max, float)
        self.end_factor = jnp.asarray(end_factor, float)
        self.max_nodes = int(max_nodes)
        self.path_capacity = int(path_capacity)
        self.edge_points = int(edge_points) if edge_points is not None else max(
            2, npoints(step, edge_res, "edge_points"))
        self.near_points = int(near_points) if near_points is not None else max(
            2, npoints(near_radius, edge_res, "near_points"))
        self.k_near = int(k_near)
        self.rrt_star = bool(rrt_star)
        self.window = int(window)
        self.subsample = int(subsample)
        self.dense = int(dense)

    def __check_init__(self):
        for name in ("step", "safety", "box_margin", "edge_res", "goal_tol", "near_radius",
                     "v_init", "v_max", "a_max", "end_factor"):
            check_positive(f"RRTParams.{name}", getattr(self, name))
        gb = concrete(self.goal_bias)
        if gb is not None and (not np.all(np.isfinite(gb)) or np.any(gb < 0) or np.any(gb > 1)):
            raise ValueError(f"RRTParams.goal_bias: expected a probability in [0, 1], got {gb}")
        for name in ("max_iter", "refine_iters"):
            v = concrete(getattr(self, name))
            if v is not None and np.any(v < 0):
                raise ValueError(f"RRTParams.{name}: expected a non-negative count, got {v}")
        for name, low in (("max_nodes", 2), ("path_capacity", 2), ("edge_points", 2),
                          ("near_points", 2), ("k_near", 1), ("window", 1), ("subsample", 1),
                          ("dense", 2)):
            if getattr(self, name) < low:
                raise ValueError(f"RRTParams.{name}: expected an integer >= {low}, "
                                 f"got {getattr(self, name)}")
        if self.window % 2 == 0:
            raise ValueError(f"RRTParams.window: expected an odd window, got {self.window}")
        step, tol, rad, res = (concrete(v) for v in (self.step, self.goal_tol, self.near_radius,
                                                      self.edge_res))
        if step is not None and tol is not None and np.any(tol > step):
            raise ValueError(f"RRTParams.goal_tol: must not exceed step ({tol} > {step}); the goal "
                             "edge is checked with edge_points points")
        if step is not None and res is not None and np.any(step / (self.edge_points - 1) > res * (1 + 1e-9)):
            raise ValueError(f"RRTParams.edge_points: {self.edge_points} points check a {step} m "
                             f"edge more sparsely than edge_res = {res} m")
        safety = concrete(self.safety)
        if safety is not None and res is not None and np.any(safety <= res / 2):
            raise ValueError(f"RRTParams.safety: must exceed edge_res / 2 ({safety} <= {res} / 2): an "
                             "edge is checked at points edge_res apart, so between them it keeps only "
                             "safety - edge_res / 2, and a thinner wall could fall between two points")
        if self.rrt_star and step is not None and rad is not None:
            if np.any(rad < step):
                raise ValueError(f"RRTParams.near_radius: must be >= step ({rad} < {step})")
            if res is not None and np.any(rad / (self.near_points - 1) > res * (1 + 1e-9)):
                raise ValueError(f"RRTParams.near_points: {self.near_points} points check a {rad} m "
                                 f"edge more sparsely than edge_res = {res} m")


class RRTResult(eqx.Module):
    """Result of :func:`plan_rrt`.

    * ``path`` ``(P, 3)``: start ... goal (``n_path`` valid points, padded with the last one);
    * ``n_path``, ``success``: number of path points and the success flag;
    * ``cost``: path length [m]; ``n_nodes``, ``n_iter``: tree size and iterations used;
    * ``nodes`` ``(max_nodes, 3)``, ``parent`` ``(max_nodes,)``, ``node_cost`` ``(max_nodes,)``:
      the tree (first ``n_nodes`` entries; the root is node 0, its own parent) and the
      cost-to-root of every node.
    """

    path: Float[Array, "P 3"]
    n_path: Int[Array, ""]
    success: Bool[Array, ""]
    cost: Float[Array, ""]
    n_nodes: Int[Array, ""]
    n_iter: Int[Array, ""]
    nodes: Float[Array, "M 3"]
    parent: Int[Array, " M"]
    node_cost: Float[Array, " M"]


class QuarticTrajectory(eqx.Module):
    """Piecewise quartic curve: ``p(t) = sum_i coeffs[k, :, i] (t - t_start[k])^i`` on segment
    ``k`` of duration ``durations[k]``; ``n_seg`` valid segments (padding has zero duration)."""

    coeffs: Float[Array, "S 3 5"]
    durations: Float[Array, " S"]
    n_seg: Int[Array, ""]

    @property
    def t_start(self):
        return jnp.concatenate([jnp.zeros((1,), self.durations.dtype), jnp.cumsum(self.durations)[:-1]])

    @property
    def total_time(self):
        return jnp.sum(self.durations)


class PlanResult(eqx.Module):
    """Everything :func:`plan_reference` computed: the tree result, the smoothed and down-sampled
    paths, the time-scaled trajectory, the scale factor and the reference."""

    rrt: RRTResult
    smoothed: Float[Array, "P 3"]
    waypoints: Float[Array, "W 3"]
    n_waypoints: Int[Array, ""]
    trajectory: QuarticTrajectory
    scale: Float[Array, ""]
    reference: Reference
    success: Bool[Array, ""]


# ----------------------------------------------------------------------------------------------
# Geometry helpers
# ----------------------------------------------------------------------------------------------


def _shape_extents(obs: ObstacleSet):
    """Centres ``(K, 3)``, half extents ``(K, 3)`` of the world AABBs and masks ``(K,)``."""
    s, b, c = obs.spheres, obs.boxes, obs.cylinders
    ext_s = jnp.broadcast_to(s.dims[:, :1], s.p.shape)
    ext_b = jnp.einsum("kij,kj->ki", jnp.abs(b.R), b.dims)
    axis = c.R[:, :, 2]  # cylinder axis in the world
    ext_c = c.dims[:, 1:2] * jnp.abs(axis) + c.dims[:, :1] * jnp.sqrt(jnp.clip(1.0 - axis**2, 0.0))
    centres = jnp.concatenate([s.p, b.p, c.p])
    ext = jnp.concatenate([ext_s, ext_b, ext_c])
    mask = jnp.concatenate([s.mask, b.mask, c.mask])
    return centres, ext, mask


def sampling_box(obs: ObstacleSet, start: Float[Array, "3"], goal: Float[Array, "3"], margin):
    """``AABB(start, goal, active obstacles)`` grown by ``margin`` (SPEC U19): ``(lo, hi)``."""
    centres, ext, mask = _shape_extents(obs)
    lo = jnp.minimum(start, goal)
    hi = jnp.maximum(start, goal)
    lo_o = jnp.where(mask[:, None], centres - ext, lo)
    hi_o = jnp.where(mask[:, None], centres + ext, hi)
    lo = jnp.minimum(lo, jnp.min(lo_o, axis=0, initial=jnp.inf)) - margin  # initial: no slots at all
    hi = jnp.maximum(hi, jnp.max(hi_o, axis=0, initial=-jnp.inf)) + margin
    return lo, hi


def _clearance(obs: ObstacleSet, pts: Float[Array, "m 3"]) -> Float[Array, " m"]:
    return jax.vmap(lambda x: min_distance(obs, x))(pts)


def _edge_free(obs, xa, xb, safety, n_points: int):
    """True if the points ``xa + t (xb - xa)``, ``t = j/(n_points - 1)``, ``j = 1..n_points-1``
    all keep ``safety`` from every obstacle (``xa`` itself is a tree node, already checked)."""
    t = jnp.arange(1, n_points, dtype=xa.dtype) / (n_points - 1)
    pts = xa[None, :] + t[:, None] * (xb - xa)[None, :]
    return jnp.all(_clearance(obs, pts) >= safety)


def _tree_costs(nodes, parent, valid, rounds: int):
    """Cost-to-root of every node by pointer jumping (``rounds`` rounds of gathers, exact for
    trees of depth < 2**rounds). ``nodes`` is ``(3, M)``."""
    edge = safe_norm((nodes - nodes[:, parent]).T)
    acc = jnp.where(valid, edge, 0.0)
    anc = parent
    for _ in range(rounds):
        acc = acc + acc[anc]
        anc = anc[anc]
    return acc


_BLOCK = 256  # node-buffer block of the nearest-neighbour search


def _block_size(M: int) -> int:
    return min(_BLOCK, M)


def _block_sq_dists(nodes, n, x, b, blk: int):
    """Squared distances from ``x`` to block ``b`` (``blk`` nodes) of the node buffer ``(3, M)`` and
    their indices; nodes at or beyond ``n``, and those an overlapping last block repeats, get ``inf``."""
    M = nodes.shape[1]
    start = jnp.minimum(b * blk, M - blk)
    T = jax.lax.dynamic_slice(nodes, (0, start), (3, blk))
    d2 = (T[0] - x[0]) ** 2 + (T[1] - x[1]) ** 2 + (T[2] - x[2]) ** 2
    ids = start + jnp.arange(blk)
    return jnp.where((ids < n) & (ids >= b * blk), d2, jnp.inf), ids


def _nearest(nodes, n, x):
    """Index of the node nearest to ``x`` among the first ``n`` of ``nodes`` ``(3, M)``.

    Brute force, block by block over the filled part of the buffer only (a ``while_loop`` over
    ``ceil(n / block)`` blocks), so the cost follows the tree size, not the buffer size. Ties go
    to the lowest index.
    """
    M = nodes.shape[1]
    blk = _block_size(M)
    n_blocks = (n + blk - 1) // blk

    def body(c):
        b, best_d, best_i = c
        d2, ids = _block_sq_dists(nodes, n, x, b, blk)
        m = jnp.min(d2)
        i = jnp.min(jnp.where(d2 == m, ids, M))
        better = m < best_d
        return b + 1, jnp.where(better, m, best_d), jnp.where(better, i, best_i)

    init = (jnp.asarray(0), jnp.asarray(jnp.inf, nodes.dtype), jnp.asarray(0))
    return jax.lax.while_loop(lambda c: c[0] < n_blocks, body, init)[2]


def _k_nearest(nodes, n, x, k: int):
    """The ``k`` nodes nearest to ``x`` among the first ``n``: ``(squared distances, indices)``,
    ascending; missing entries have distance ``inf``. Block-wise like :func:`_nearest`."""
    M = nodes.shape[1]
    blk = _block_size(M)
    n_blocks = (n + blk - 1) // blk

    def body(c):
        b, best_d, best_i = c
        d2, ids = _block_sq_dists(nodes, n, x, b, blk)
        all_d = jnp.concatenate([best_d, d2])
        all_i = jnp.concatenate([best_i, ids])
        neg, sel = jax.lax.top_k(-all_d, k)
        return b + 1, -neg, all_i[sel]

    init = (jnp.asarray(0), jnp.full((k,), jnp.inf, nodes.dtype), jnp.zeros((k,), int))
    _, d2, idx = jax.lax.while_loop(lambda c: c[0] < n_blocks, body, init)
    return d2, idx


# ----------------------------------------------------------------------------------------------
# RRT
# ----------------------------------------------------------------------------------------------


class _TreeState(NamedTuple):
    it: Array
    n: Array
    nodes: Array
    parent: Array
    cost: Array
    found: Array
    found_it: Array
    goal_idx: Array
    stop: Array


def _check_point(name, x):
    x_shape = np.shape(x)  # lists too (jnp.shape warns on them)
    if x_shape != (3,):  # a (2, 3) start failed inside the planner with a broadcasting error
        raise ValueError(f"{name}: expected a 3-vector, got shape {x_shape}")
    v = concrete(x)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected finite coordinates, got {v}")


def plan_rrt(key: PRNGKeyArray, obs: ObstacleSet, start: Float[Array, "3"], goal: Float[Array, "3"],
             params: RRTParams = None) -> RRTResult:
    """Goal-biased RRT (or RRT* with ``params.rrt_star``) from ``start`` to ``goal`` (thesis
    3.2.3, SPEC U19, E24). Pure and jittable; ``jit(vmap(plan_rrt, (0, 0, 0, 0, None)))`` plans
    many seeds at once (see :func:`plan_rrt_batch`). The same key gives the same tree bit for bit.

    Arguments:
        key: PRNG key (one per seed).
        obs: obstacle set; every tree edge keeps ``params.safety`` clearance from it at its check
            points (at least ``safety - edge_res / 2`` between them).
        start, goal: ``(3,)`` positions [m].
        params: :class:`RRTParams` (defaults if None).

    Returns:
        :class:`RRTResult`; ``success`` is False (and the path is the start alone) when no path was
        found within the node, iteration or path budgets, or when the start or goal is blocked.
        A free start at the goal (within 1e-9 m) succeeds at once with the start alone
        (``n_path = 1``, ``cost = 0``).
    """
    params = RRTParams() if params is None else params
    _check_point("start", start)
    _check_point("goal", goal)
    # integer points (``[0, 0, 1]``) are promoted to the default float dtype
    dtype = jnp.result_type(jnp.asarray(start).dtype, jnp.asarray(goal).dtype, float)
    start = jnp.asarray(start, dtype)
    goal = jnp.asarray(goal, dtype)
    M = params.max_nodes
    step = params.step.astype(dtype)
    safety = params.safety.astype(dtype)
    tol = params.goal_tol.astype(dtype)
    bias = params.goal_bias.astype(dtype)
    radius = params.near_radius.astype(dtype)
    # in the points' dtype (float32 points with float64 obstacles keep a float32 tree)
    lo, hi = (v.astype(dtype) for v in sampling_box(obs, start, goal, params.box_margin.astype(dtype)))
    idx_all = jnp.arange(M)

    goal_clear = min_distance(obs, goal) >= safety
    start_clear = min_distance(obs, start) >= safety

    nodes0 = jnp.broadcast_to(start[:, None], (3, M)).astype(dtype)  # (3, M): coordinates first
    # a start at the goal is a path of the start alone (the root is the goal node), not a detour
    at_goal = goal_clear & start_clear & (safe_norm(start - goal) <= _TINY)
    init = _TreeState(
        it=jnp.asarray(0), n=jnp.asarray(1), nodes=nodes0, parent=jnp.zeros(M, int),
        cost=jnp.zeros(M, dtype), found=at_goal, found_it=jnp.asarray(0),
        goal_idx=jnp.asarray(0), stop=~(goal_clear & start_clear) | at_goal,
    )

    def cond(st):
        return (st.it < params.max_iter) & ~st.stop

    def body(st: _TreeState) -> _TreeState:
        u = jax.random.uniform(jax.random.fold_in(key, st.it), (4,), dtype)
        x_rand = jnp.where(u[0] < bias, goal, lo + u[1:] * (hi - lo))
        j = _nearest(st.nodes, st.n, x_rand)
        x_near = st.nodes[:, j]
        diff = x_rand - x_near
        dist = safe_norm(diff)
        seg = jnp.minimum(dist, step)
        x_new = x_near + diff * (seg / jnp.where(dist > 0, dist, 1.0))
        room = st.n < M
        free_near = _edge_free(obs, x_near, x_new, safety, params.edge_points)
        par = j
        c_new = st.cost[j] + seg
        ok = (dist > _TINY) & room & free_near
        new = jnp.minimum(st.n, M - 1)
        parent = st.parent
        cost = st.cost

        if params.rrt_star:
            # choose-parent among the k nearest nodes within near_radius of x_new
            k = min(params.k_near, M)
            d2n, nb = _k_nearest(st.nodes, st.n, x_new, k)
            dn = jnp.sqrt(jnp.where(jnp.isfinite(d2n), d2n, 0.0))
            within = jnp.isfinite(d2n) & (dn <= radius) & (dn > _TINY)
            free_nb = jax.vmap(lambda xa: _edge_free(obs, xa, x_new, safety, params.near_points))(
                st.nodes[:, nb].T)
            usable = within & free_nb
            cand = jnp.where(usable, st.cost[nb] + dn, jnp.inf)
            b = jnp.argmin(cand)
            better = cand[b] < jnp.where(free_near, c_new, jnp.inf)
            par = jnp.where(better, nb[b], j)
            c_new = jnp.where(better, cand[b], c_new)
            ok = (dist > _TINY) & room & (free_near | jnp.any(usable))
            nodes = st.nodes.at[:, new].set(jnp.where(ok, x_new, st.nodes[:, new]))
            parent = parent.at[new].set(jnp.where(ok, par, parent[new]))
            cost = cost.at[new].set(jnp.where(ok, c_new, cost[new]))
            # rewire: neighbours reached more cheaply through the new node
            rewire = ok & usable & (c_new + dn < st.cost[nb])
            nb_w = jnp.where(within, nb, M)  # missing entries write nowhere
            parent = parent.at[nb_w].set(jnp.where(rewire, new, parent[nb]), mode="drop")
            # exact for any tree the buffer holds (depth <= max_nodes - 1 < 2**rounds); the path
            # buffer does not bound the tree's depth
            rounds = max(1, math.ceil(math.log2(M)))
            cost = jnp.where(jnp.any(rewire),
                             _tree_costs(nodes, parent, idx_all < st.n + ok, rounds), cost)
        else:
            nodes = st.nodes.at[:, new].set(jnp.where(ok, x_new, st.nodes[:, new]))
            parent = parent.at[new].set(jnp.where(ok, par, parent[new]))
            cost = cost.at[new].set(jnp.where(ok, c_new, cost[new]))
        n = st.n + ok

        # goal connection
        dg = safe_norm(x_new - goal)
        near_goal = ok & (dg <= tol) & ~st.found
        exact = dg <= _TINY
        connect = near_goal & (exact | ((n < M) & _edge_free(obs, x_new, goal, safety,
                                                              params.edge_points)))
        add_goal = connect & ~exact
        slot = jnp.minimum(n, M - 1)
        nodes = nodes.at[:, slot].set(jnp.where(add_goal, goal, nodes[:, slot]))
        parent = parent.at[slot].set(jnp.where(add_goal, new, parent[slot]))
        cost = cost.at[slot].set(jnp.where(add_goal, cost[new] + dg, cost[slot]))
        goal_idx = jnp.where(connect, jnp.where(exact, new, n), st.goal_idx)
        n = n + add_goal
        found = st.found | connect
        found_it = jnp.where(connect, st.it, st.found_it)
        it = st.it + 1
        if params.rrt_star:
            done = found & (it - found_it > params.refine_iters)
        else:
            done = found
        stop = done | (n >= M)
        return _TreeState(it, n, nodes, parent, cost, found, found_it, goal_idx, stop)

    st = jax.lax.while_loop(cond, body, init)

    # path extraction: follow parents from the goal node to the root
    P = params.path_capacity

    def walk(cur, _):
        return st.parent[cur], cur

    _, seq = jax.lax.scan(walk, st.goal_idx, None, length=P)  # goal, parent, ..., root, root...
    is_root = seq == 0
    reached_root = jnp.any(is_root)
    n_path = jnp.argmax(is_root) + 1
    success = st.found & reached_root
    n_path = jnp.where(success, n_path, 1)
    k = jnp.arange(P)
    src = jnp.clip(n_path - 1 - k, 0, P - 1)
    path = st.nodes[:, seq[src]].T
    path = jnp.where((k < n_path)[:, None], path, path[n_path - 1][None, :])
    path = jnp.where(success, path, jnp.broadcast_to(start, path.shape))
    cost = jnp.where(success, st.cost[st.goal_idx], 0.0)
    return RRTResult(path=path, n_path=n_path, success=success, cost=cost, n_nodes=st.n,
                     n_iter=st.it, nodes=st.nodes.T, parent=st.parent, node_cost=st.cost)


_BATCH_MODES = ("map", "vmap")


def _check_batch(batch: str) -> None:
    if batch not in _BATCH_MODES:
        raise ValueError(f"batch: expected one of {_BATCH_MODES}, got {batch!r}")


def _map_seeds(fn, args, batch: str):
    """Apply ``fn`` over the leading axis of ``args``: ``lax.map`` (sequential inside one
    compiled program) or ``vmap``. A vmapped ``while_loop`` runs until the slowest seed is done
    and selects the whole carried state (the node buffer) for every seed at every iteration, so
    on CPU the sequential map is several times faster; both give bit-identical results."""
    if batch == "vmap":
        return jax.vmap(lambda a: fn(*a))(args)
    return jax.lax.map(lambda a: fn(*a), args)


def plan_rrt_batch(keys, obs: ObstacleSet, start, goal, params: RRTParams = None,
                   batch: str = "map") -> RRTResult:
    """:func:`plan_rrt` over a batch of seeds, jitted: ``keys`` ``(S,)``, stacked ``obs``,
    ``start``/``goal`` ``(S, 3)``. ``batch="map"`` (default, fastest on CPU) or ``"vmap"``."""
    params = RRTParams() if params is None else params
    _check_batch(batch)
    return _plan_rrt_batch(keys, obs, start, goal, params, batch)


@eqx.filter_jit
def _plan_rrt_batch(keys, obs, start, goal, params, batch):
    return _map_seeds(lambda k, o, s, g: plan_rrt(k, o, s, g, params), (keys, obs, start, goal),
                      batch)


# ----------------------------------------------------------------------------------------------
# Smoothing and down-sampling (SPEC section 5 steps 2-3)
# ----------------------------------------------------------------------------------------------


def smooth_path(path: Float[Array, "P 3"], n_path, window: int = 5) -> Float[Array, "P 3"]:
    """Centred moving average of width ``window`` (odd) over the ``n_path`` valid points; the ends
    are edge-padded and the two endpoints pinned. Padding repeats the last point."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window: expected an odd positive integer, got {window}")
    P = path.shape[0]
    h = window // 2
    k = jnp.arange(P)
    idx = jnp.clip(k[:, None] + jnp.arange(-h, h + 1)[None, :], 0, n_path - 1)
    sm = jnp.mean(path[idx], axis=1)
    last = path[n_path - 1]
    sm = jnp.where((k == 0)[:, None], path[0][None, :], sm)
    sm = jnp.where((k >= n_path - 1)[:, None], last[None, :], sm)
    return sm


def subsample_path(path: Float[Array, "P 3"], n_path, every: int = 4):
    """Keep points ``0, every, 2 every, ...`` and the last one: ``(waypoints (W, 3), n_w)`` with
    ``W = ceil((P - 1)/every) + 1``; padding repeats the last point."""
    if every < 1:
        raise ValueError(f"every: expected a positive integer, got {every}")
    P = path.shape[0]
    W = (P - 1 + every - 1) // every + 1
    n_w = (n_path - 1 + every - 1) // every + 1
    src = jnp.minimum(jnp.arange(W) * every, n_path - 1)
    return path[src], n_w


# ----------------------------------------------------------------------------------------------
# Quartic segments and time scaling (SPEC section 5 steps 4-5)
# ----------------------------------------------------------------------------------------------


def quartic_trajectory(waypoints: Float[Array, "W 3"], n_way, v_init=0.5,
                       end_factor=1.0) -> QuarticTrajectory:
    """Quartic segments through ``waypoints[:n_way]`` with continuous velocity and acceleration,
    starting and ending at zero velocity and starting at zero acceleration (module docstring, step
    4). Segment durations ``T_k = |P_{k+1} - P_k| / v_init`` (floored at 1e-6 s); the first and
    last are multiplied by ``end_factor``.

    Why ``end_factor``: the end acceleration of a segment is inherited by the next one,
    ``a_{k+1} = a_k + 6 (v_k + v_{k+1}) / T_k - 12 (P_{k+1} - P_k) / T_k^2``, so any mismatch persists
    along the chain. From rest to ``v_1 ~ v_init`` in ``T_0 = |dP| / v_init`` it is
    ``a_1 ~ -6 v_init / T_0`` (about -11 m/s^2 for a 0.14 m segment) and stays; with
    ``end_factor = 2`` (the mean speed of a rest-to-cruise ramp is half the cruise speed) the
    first and last joints are consistent and the time scaling slows the curve much less.
    """
    waypoints = jnp.asarray(waypoints)
    if waypoints.ndim != 2 or waypoints.shape[1] != 3:
        raise ValueError(f"quartic_trajectory: waypoints must have shape (W, 3), got {waypoints.shape}")
    check_positive("quartic_trajectory: v_init", v_init)
    check_positive("quartic_trajectory: end_factor", end_factor)
    W = waypoints.shape[0]
    dtype = waypoints.dtype
    S = max(W - 1, 1)
    k = jnp.arange(S)
    P0 = waypoints[:S]
    P1 = waypoints[jnp.minimum(k + 1, W - 1)]
    seg_valid = k < n_way - 1
    T = jnp.where(seg_valid, jnp.maximum(safe_norm(P1 - P0) / v_init, 1e-6), 0.0).astype(dtype)
    ends = seg_valid & ((k == 0) | (k == n_way - 2))
    T = jnp.where(ends, T * end_factor, T)
    # interior waypoint velocities v_j = (P_{j+1} - P_{j-1}) / (T_{j-1} + T_j), j = 1..n_way-2
    j = jnp.arange(W)
    Tm = T[jnp.clip(j - 1, 0, S - 1)]
    Tp = T[jnp.clip(j, 0, S - 1)]
    Pm = waypoints[jnp.clip(j - 1, 0, W - 1)]
    Pp = waypoints[jnp.clip(j + 1, 0, W - 1)]
    interior = (j >= 1) & (j <= n_way - 2)
    denom = jnp.where(interior, Tm + Tp, 1.0)
    V = jnp.where(interior[:, None], (Pp - Pm) / denom[:, None], 0.0)

    def seg(a0, inp):
        p0, p1, v0, v1, Tk, valid = inp
        Ts = jnp.where(valid, Tk, 1.0)
        delta = p1 - p0 - v0 * Ts - 0.5 * a0 * Ts**2
        dv = v1 - v0 - a0 * Ts
        c3 = 4.0 * delta / Ts**3 - dv / Ts**2
        c4 = dv / Ts**3 - 3.0 * delta / Ts**4
        a1 = a0 + 6.0 * c3 * Ts + 12.0 * c4 * Ts**2
        coeff = jnp.stack([p0, v0, 0.5 * a0, c3, c4], axis=-1)  # (3, 5)
        const = jnp.stack([p0, jnp.zeros_like(p0), jnp.zeros_like(p0), jnp.zeros_like(p0),
                           jnp.zeros_like(p0)], axis=-1)
        coeff = jnp.where(valid, coeff, const)
        return jnp.where(valid, a1, a0), coeff

    V0 = V[:S]
    V1 = V[jnp.minimum(k + 1, W - 1)]
    _, coeffs = jax.lax.scan(seg, jnp.zeros(3, dtype), (P0, P1, V0, V1, T, seg_valid))
    n_seg = jnp.maximum(n_way - 1, 0)
    return QuarticTrajectory(coeffs=coeffs, durations=T, n_seg=n_seg)


def _poly(coeff, tau):
    """Position, velocity, acceleration of one quartic segment at local time ``tau``."""
    c0, c1, c2, c3, c4 = (coeff[..., i] for i in range(5))
    p = c0 + tau * (c1 + tau * (c2 + tau * (c3 + tau * c4)))
    v = c1 + tau * (2 * c2 + tau * (3 * c3 + tau * 4 * c4))
    a = 2 * c2 + tau * (6 * c3 + tau * 12 * c4)
    return p, v, a


def evaluate_trajectory(traj: QuarticTrajectory, t):
    """Position, velocity and acceleration ``(3,)`` at time ``t`` (clamped to ``[0, T_total]``)."""
    t0 = traj.t_start
    S = traj.durations.shape[0]
    last = jnp.maximum(traj.n_seg - 1, 0)
    t = jnp.clip(t, 0.0, traj.total_time)
    k = jnp.sum((t >= t0[1:]) & (jnp.arange(1, S) <= last))  # segment index, no search loop
    tau = jnp.clip(t - t0[k], 0.0, traj.durations[k])
    return _poly(traj.coeffs[k], tau)


def trajectory_extrema(traj: QuarticTrajectory, dense: int = 64):
    """Largest speed and acceleration norm over ``dense`` samples per valid segment."""
    s = jnp.linspace(0.0, 1.0, dense, dtype=traj.durations.dtype)
    tau = traj.durations[:, None] * s[None, :]  # (S, dense)
    _, v, a = jax.vmap(lambda c, t: jax.vmap(lambda tt: _poly(c, tt))(t))(traj.coeffs, tau)
    valid = (jnp.arange(traj.durations.shape[0]) < traj.n_seg)[:, None]
    vmax = jnp.max(jnp.where(valid, safe_norm(v), 0.0))
    amax = jnp.max(jnp.where(valid, safe_norm(a), 0.0))
    return vmax, amax


def time_scale(traj: QuarticTrajectory, v_max=1.0, a_max=2.0, dense: int = 64):
    """Uniform re-timing ``T -> c T`` with ``c = max(1, vmax_hat / v_max, sqrt(amax_hat / a_max))``
    (SPEC section 5 step 5): ``(scaled trajectory, c)``. Coefficient ``i`` scales by ``c^-i``."""
    vmax, amax = trajectory_extrema(traj, dense)
    c = jnp.maximum(jnp.maximum(1.0, vmax / v_max), jnp.sqrt(amax / a_max))
    powers = c ** -jnp.arange(5, dtype=traj.coeffs.dtype)
    return QuarticTrajectory(coeffs=traj.coeffs * powers, durations=traj.durations * c,
                             n_seg=traj.n_seg), c


def sample_reference(traj: QuarticTrajectory, goal_p, goal_quat, rot_radius, ts, capacity: int):
    """Resample at ``t_k = k ts`` (``k ts < T``) plus the end point into a padded
    :class:`~redman_jax.Reference` of ``capacity`` samples: ``(reference, fits)`` where ``fits``
    is False when the trajectory needs more than ``capacity`` samples (it is then truncated).

    The last valid sample and the padding hold the end point at rest (``v = a = 0``); the
    orientation is the constant ``goal_quat`` with zero angular velocity; ``rot`` latches on at
    the first sample within ``rot_radius`` of ``goal_p``.
    """
    dtype = traj.coeffs.dtype
    ts = jnp.asarray(ts, dtype)
    T = traj.total_time
    n_needed = jnp.ceil(T / ts - 1e-6).astype(int) + 1
    n = jnp.minimum(n_needed, capacity)
    k = jnp.arange(capacity)
    t = jnp.minimum(k * ts, T)
    p, v, a = jax.vmap(lambda tt: evaluate_trajectory(traj, tt))(t)
    end = evaluate_trajectory(traj, T)[0]
    at_end = k >= n_needed - 1
    p = jnp.where(at_end[:, None], end[None, :], p)
    v = jnp.where(at_end[:, None], 0.0, v)
    a = jnp.where(at_end[:, None], 0.0, a)
    # padding beyond a truncated reference: hold the last valid sample at rest. A gather of row
    # n - 1 (not a select against p[n - 1]): every padded row is then that row's own value, bit for
    # bit (with a select, XLA computed `end` in two fusions that rounded 1 ulp apart)
    pad = k >= n
    p = p[jnp.minimum(k, n - 1)]
    v = jnp.where(pad[:, None], 0.0, v)
    a = jnp.where(pad[:, None], 0.0, a)
    near = safe_norm(p - goal_p) <= rot_radius
    rot = (jnp.cumsum(near.astype(int)) > 0).astype(dtype)
    quat = jnp.broadcast_to(jnp.asarray(goal_quat, dtype), (capacity, 4))
    zeros = jnp.zeros((capacity, 3), dtype)
    ref = Reference(p=p, v=v, a=a, quat=quat, omega=zeros, omega_dot=zeros, rot=rot, mask=k < n,
                    n_samples=n, ts=ts)
    return ref, n_needed <= capacity


def _hold_reference(p0, goal_p, goal_quat, rot_radius, ts, capacity, dtype):
    """A one-sample reference holding ``p0`` at rest (the result of a failed plan)."""
    p = jnp.broadcast_to(p0, (capacity, 3)).astype(dtype)
    zeros = jnp.zeros((capacity, 3), dtype)
    rot = jnp.broadcast_to((safe_norm(p0 - goal_p) <= rot_radius).astype(dtype), (capacity,))
    return Reference(p=p, v=zeros, a=zeros, quat=jnp.broadcast_to(jnp.asarray(goal_quat, dtype),
                                                                    (capacity, 4)),
                     omega=zeros, omega_dot=zeros, rot=rot, mask=jnp.arange(capacity) < 1,
                     n_samples=jnp.asarray(1), ts=jnp.asarray(ts, dtype))


def _validate_reference_args(rot_radius, ts, goal_quat, capacity) -> int:
    # capacity sizes the reference: 100.5 was truncated to 100 samples without a word
    if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)) or capacity < 1:
        raise ValueError(f"capacity: expected a positive int (number of samples), got {capacity!r}")
    check_positive("rot_radius", rot_radius, allow_zero=True)
    check_positive("ts", ts)
    if jnp.shape(goal_quat)[-1:] != (4,):
        raise ValueError(f"goal_quat: expected a 4-vector, got shape {jnp.shape(goal_quat)}")
    # a NaN or zero goal orientation went into every sample of the reference
    check_unit_quaternions("goal_quat", goal_quat, allow_nan=False)
    return int(capacity)


def reference_from_path(res: RRTResult, start_p, goal_p, goal_quat, rot_radius, ts, capacity: int,
                        params: RRTParams = None) -> PlanResult:
    """Steps 2-6 of SPEC section 5 on a planned path: smoothing, down-sampling, quartic segments,
    time scaling and resampling (see :func:`rrt_reference`)."""
    params = RRTParams() if params is None else params
    capacity = _validate_reference_args(rot_radius, ts, goal_quat, capacity)
    start_p = jnp.asarray(start_p)
    dtype = start_p.dtype
    goal_p = jnp.asarray(goal_p, dtype)
    sm = smooth_path(res.path, res.n_path, params.window)
    wp, n_w = subsample_path(sm, res.n_path, params.subsample)
    traj = quartic_trajectory(wp, n_w, params.v_init.astype(dtype), params.end_factor.astype(dtype))
    traj, c = time_scale(traj, params.v_max.astype(dtype), params.a_max.astype(dtype), params.dense)
    ref, fits = sample_reference(traj, goal_p, goal_quat, rot_radius, ts, capacity)
    ok = res.success & fits & (n_w >= 2) & jnp.isfinite(c)
    # the start alone (failed plan, or a start at the goal): hold it at rest
    held = _hold_reference(start_p, goal_p, goal_quat, rot_radius, ts, capacity, dtype)
    ref = jax.tree.map(lambda good, bad: jnp.where(ok, good, bad), ref, held)
    at_goal = res.success & (res.n_path == 1)
    return PlanResult(rrt=res, smoothed=sm, waypoints=wp, n_waypoints=n_w, trajectory=traj,
                      scale=c, reference=ref, success=ok | at_goal)


def plan_reference(key: PRNGKeyArray, obs: ObstacleSet, start_p, goal_p, goal_quat, rot_radius, ts,
                   capacity: int, params: RRTParams = None) -> PlanResult:
    """The whole RRT pipeline of SPEC section 5 (steps 1-6) with every intermediate result; see
    :func:`rrt_reference`."""
    params = RRTParams() if params is None else params
    _validate_reference_args(rot_radius, ts, goal_quat, capacity)
    res = plan_rrt(key, obs, start_p, goal_p, params)
    return reference_from_path(res, start_p, goal_p, goal_quat, rot_radius, ts, capacity, params)


def rrt_reference(key: PRNGKeyArray, obs: ObstacleSet, start_p: Float[Array, "3"],
                  goal_p: Float[Array, "3"], goal_quat: Float[Array, "4"], rot_radius, ts,
                  capacity: int, params: RRTParams = None):
    """Plan with RRT and turn the path into a sampled reference (thesis 3.2.3, SPEC section 5).

    Arguments:
        key: PRNG key; obs: obstacle set; start_p, goal_p: ``(3,)`` [m]; goal_quat: ``(4,)``
            constant orientation; rot_radius: orientation switches on (latched) within this
            distance of the goal [m]; ts: sample time [s]; capacity: static number of samples;
        params: :class:`RRTParams`.

    Returns:
        ``(reference, success)``. On failure (no path, or more than ``capacity`` samples needed)
        the reference holds the start at rest (``n_samples = 1``) and ``success`` is False; no
        exception is raised under ``jit``. A free start at the goal gives the same held reference
        with ``success`` True.

    Raises:
        ValueError: bad shapes, a non-positive ``ts`` or ``capacity``, or bad parameters (host side).
    """
    out = plan_reference(key, obs, start_p, goal_p, goal_quat, rot_radius, ts, capacity, params)
    return out.reference, out.success


def plan_reference_batch(keys, obs: ObstacleSet, start_p, goal_p, goal_quat, rot_radius, ts,
                         capacity: int, params: RRTParams = None, batch: str = "map") -> PlanResult:
    """:func:`plan_reference` over a batch of seeds, jitted: ``keys`` ``(S,)``, stacked ``obs``,
    ``start_p``/``goal_p`` ``(S, 3)``, ``goal_quat`` ``(S, 4)``; ``rot_radius`` and ``ts`` shared;
    ``capacity`` static. The planner runs per ``batch`` (``"map"``/``"vmap"``, see
    :func:`plan_rrt_batch`), the rest of the pipeline is vmapped."""
    params = RRTParams() if params is None else params
    _check_batch(batch)
    capacity = _validate_reference_args(rot_radius, ts, goal_quat, capacity)
    # numbers as arrays: a new ts or rot_radius never recompiles
    rot_radius, ts = jnp.asarray(rot_radius, float), jnp.asarray(ts, float)
    return _plan_reference_batch(keys, obs, start_p, goal_p, goal_quat, rot_radius, ts, capacity,
                                 params, batch)


@eqx.filter_jit
def _plan_reference_batch(keys, obs, start_p, goal_p, goal_quat, rot_radius, ts, capacity, params,
                          batch):
    res = _map_seeds(lambda k, o, s, g: plan_rrt(k, o, s, g, params),
                     (keys, obs, start_p, goal_p), batch)
    post = lambda r, s, g, q: reference_from_path(r, s, g, q, rot_radius, ts, capacity, params)
    return jax.vmap(post)(res, start_p, goal_p, goal_quat)


def rrt_reference_batch(keys, obs: ObstacleSet, start_p, goal_p, goal_quat, rot_radius, ts,
                        capacity: int, params: RRTParams = None, batch: str = "map"):
    """:func:`rrt_reference` over a batch of seeds (see :func:`plan_reference_batch`):
    ``(references (stacked), success (S,))``."""
    out = plan_reference_batch(keys, obs, start_p, goal_p, goal_quat, rot_radius, ts, capacity,
                               params, batch)
    return out.reference, out.success
