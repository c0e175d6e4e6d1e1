"""Gradient-guided closed loop (thesis 3.3.3, SPEC 9): the real ``gradient`` controller with the
local-minima estimator, integrated by the one-loop stepper (``mode="horizon"``) and by the scan of
per-sample solves (``mode="per_sample"``, the differentiable cross-check).

Small problems (7-DOF arm, one sphere, 1.5 s horizon, 0.2 s hold) keep the three compilations of
this file to about two minutes of CPU.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import redman_jax  # noqa: F401  (x64)
from conftest import DEFAULT_EMITTERS, run_under_default_emitters
from redman_jax._controllers import CONTROLLERS
from redman_jax._kinematics import end_effector_pose, poi_positions
from redman_jax._obstacles import make_obstacles
from redman_jax._robot import thesis_arm
from redman_jax._scenario import Reference, Scenario, stack_scenarios
from redman_jax._sim import SimParams, simulate, simulate_batch

ARM = thesis_arm(7)
CTRL = CONTROLLERS["gradient"]()
GAINS = CTRL.default_gains()
PARAMS = SimParams(guidance_samples=150, hold_samples=20)
TS = 0.01


def guided_scenario(offset, sphere_at=(0.0, 0.15, 0.3), radius=0.08, seed=0):
    """Goal = start end-effector position + ``offset``; one sphere at start + ``sphere_at``."""
    p0, quat0 = end_effector_pose(ARM, ARM.q0)
    goal = p0 + jnp.asarray(offset)
    c = np.asarray(p0) + np.asarray(sphere_at)
    obs = make_obstacles(spheres=[(np.eye(3), c, (radius,))], capacities=(2, 1, 1))
    cap = 2  # a guided run reads only the goal, the obstacles and ts from the scenario
    z = jnp.zeros((cap, 3))
    ref = Reference(p=jnp.broadcast_to(goal, (cap, 3)), v=z, a=z, quat=jnp.broadcast_to(quat0, (cap, 4)),
                    omega=z, omega_dot=z, rot=jnp.zeros(cap), mask=jnp.ones(cap, bool),
                    n_samples=jnp.asarray(cap), ts=jnp.asarray(TS))
    return Scenario(obstacles=obs, goal_p=goal, goal_quat=quat0, reference=ref, seed=jnp.asarray(seed),
                    seed_used=jnp.asarray(seed), valid=jnp.asarray(True), case="custom")


# the sphere sits 0.3 m to the side of the straight path, inside the field's range (0.75 m)
SCEN = guided_scenario((0.0, 0.35, -0.1))


@pytest.fixture(scope="module")
def horizon():
    return simulate(ARM, SCEN, CTRL, GAINS, params=PARAMS)


def test_sphere_is_clear_of_the_arm_at_start():
    d = np.linalg.norm(np.asarray(poi_positions(ARM, ARM.q0)) - (np.asarray(end_effector_pose(ARM, ARM.q0)[0])
                                                                + [0.0, 0.15, 0.3]), axis=1)
    assert d.min() > 0.08 + 0.10


def test_guided_run_reaches_the_goal_and_places_virtual_obstacles(horizon):
    r = horizon
    assert bool(r.success) and not bool(r.diverged) and int(r.status) == 0
    assert float(r.metrics.final_pos_err) < 0.10
    assert np.isfinite(float(r.time_to_goal)) and float(r.time_to_goal) < 1.3
    assert float(r.f_obs[-1]) == 0.0
    # the estimator ran at every sample start; its accepted estimates are the buffer's members
    ok = np.asarray(r.estimate_valid)
    assert ok.sum() >= 20 and np.asarray(r.virtual_mask).all()
    # close to the goal the Newton step lands on the field's minimum, i.e. next to the goal
    n = int(r.n_samples)
    est = np.asarray(r.estimates)[n - 5:n]
    assert np.all(np.linalg.norm(est - np.asarray(SCEN.goal_p), axis=1) < 0.05)


def test_one_loop_stepper_agrees_with_per_sample_solves(horizon):
    """The two drivers take different steps (the stepper carries the PID step size across sample
    ends, the per-sample solves restart from the previous mean step), so they agree to the
    tolerance's level (rtol 1e-5), not bit for bit."""
    per = simulate(ARM, SCEN, CTRL, GAINS, params=SimParams(guidance_samples=150, hold_samples=20,
                                                            mode="per_sample"))
    assert bool(per.success) == bool(horizon.success)
    n = int(per.n_samples)
    assert n == int(horizon.n_samples)
    # the stepper stops at the stop rule; the per-sample solves run on (the rows after n are unused)
    np.testing.assert_allclose(np.asarray(horizon.q)[:n], np.asarray(per.q)[:n], rtol=0, atol=1e-4)
    np.testing.assert_allclose(np.asarray(horizon.p)[:n], np.asarray(per.p)[:n], rtol=0, atol=2e-5)
    assert abs(float(horizon.metrics.final_pos_err) - float(per.metrics.final_pos_err)) < 2e-5
    np.testing.assert_array_equal(np.asarray(horizon.estimate_valid)[:n], np.asarray(per.estimate_valid)[:n])
    # the loop counts its steps like diffrax does: accepted + rejected
    assert int(horizon.n_steps) == int(horizon.n_accepted) + int(horizon.n_rejected)
    assert int(horizon.n_accepted) >= n


def test_stop_rule_bit_identity_holds_under_the_default_emitters():
    """The next test asserts bit identity between two separately compiled programs (stopping at the
    rule or stepping on), which XLA's default emitters keep and the older ones this suite compiles
    with do not always (conftest: one estimate 1 ulp apart): run it in a subprocess with the
    default emitters, as test_nullspace does for its bit identities."""
    if DEFAULT_EMITTERS:
        pytest.skip("the default emitters are in use: the test runs in this process")
    run_under_default_emitters(__file__, ["test_stopping_at_the_stop_rule_changes_nothing_reported"], 1)


@pytest.mark.skipif(not DEFAULT_EMITTERS, reason="bit identity of the default emitters: run in a "
                    "subprocess by test_stop_rule_bit_identity_holds_under_the_default_emitters")
def test_stopping_at_the_stop_rule_changes_nothing_reported(horizon):
    """The stepper stops a member once the goal has been held for ``hold_samples`` sample ends.
    Against the same run stepped on to the end of the horizon: every reported number is the same,
    the rows after the stop hold the stop state, and the steps after it are saved."""
    full = simulate(ARM, SCEN, CTRL, GAINS, params=SimParams(guidance_samples=150, hold_samples=20,
                                                             stop_early=False))
    r = horizon
    n = int(r.n_samples)
    assert bool(r.success) and n < PARAMS.guidance_samples  # the rule fired before 1.5 s
    assert int(r.status) == 0 and int(full.status) == 0
    assert int(full.n_samples) == n and bool(full.success)
    for name in ("time_to_goal", "path_length"):
        assert float(getattr(r, name)) == float(getattr(full, name)), name
    for a, b in zip(jax.tree.leaves(r.metrics), jax.tree.leaves(full.metrics)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(r.q)[:n], np.asarray(full.q)[:n])
    np.testing.assert_array_equal(np.asarray(r.estimates)[:n], np.asarray(full.estimates)[:n])
    np.testing.assert_array_equal(np.asarray(r.q)[n:], np.broadcast_to(np.asarray(r.q)[n - 1],
                                                                        np.asarray(r.q)[n:].shape))
    assert int(r.n_steps) < int(full.n_steps)


def test_guided_batch_equals_single_runs_and_nan_is_isolated(horizon, monkeypatch):
    """The batch is stepped from the host and its last member(s) still stepping move to a batch of
    just those (forced here after 16 iterations with at most half left; by default a quarter of the
    batch after 2048): each member takes the steps of its single run and equals it to rounding
    (separately compiled programs: about 3e-12 relative), a NaN member is flagged and isolated, and
    the switch is deterministic."""
    import redman_jax._sim as sim

    monkeypatch.setattr(sim, "_CHECK_ITERS", 8)
    monkeypatch.setattr(sim, "_RENT_ITERS", 16)
    monkeypatch.setattr(sim, "_COMPACT_FRACTION", 2)
    stats = {}
    orig = sim._simulate_guided_compacting
    monkeypatch.setattr(sim, "_simulate_guided_compacting", lambda *a, **k: orig(*a, stats=stats))
    scs = [SCEN, guided_scenario((0.1, -0.3, 0.0), seed=1), guided_scenario((-0.2, 0.2, 0.1), seed=2)]
    nan_goal = lambda sc: eqx.tree_at(lambda s: s.goal_p, sc, sc.goal_p.at[0].set(jnp.nan))
    bad = [scs[0], nan_goal(scs[1]), scs[2], nan_goal(scs[2]), nan_goal(scs[0])]
    batch = simulate_batch(ARM, stack_scenarios(bad), CTRL, GAINS, params=PARAMS)
    assert stats["small"] == 3, stats
    # the two members still stepping move on alone (the NaN ones stop at once): 2 rows, not 3
    assert stats["compacted"] == 2 and stats["sub_batch"] == 2, stats
    assert all(bool(batch.diverged[i]) and not bool(batch.metrics.success[i]) for i in (1, 3, 4))
    assert not bool(batch.diverged[0]) and not bool(batch.diverged[2])
    np.testing.assert_allclose(np.asarray(batch.q[0]), np.asarray(horizon.q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(batch.qd[0]), np.asarray(horizon.qd), rtol=1e-10, atol=1e-12)
    assert int(batch.n_steps[0]) == int(horizon.n_steps)
    single2 = simulate(ARM, scs[2], CTRL, GAINS, params=PARAMS)
    np.testing.assert_allclose(np.asarray(batch.q[2]), np.asarray(single2.q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(batch.estimates[2]), np.asarray(single2.estimates),
                               rtol=1e-10, atol=1e-12)
    assert int(batch.n_steps[2]) == int(single2.n_steps)
    assert bool(batch.success[2]) == bool(single2.success)
    np.testing.assert_array_equal(np.asarray(batch.mask[2]), np.asarray(single2.mask))
    again = simulate_batch(ARM, stack_scenarios(bad), CTRL, GAINS, params=PARAMS)
    np.testing.assert_array_equal(np.asarray(again.q), np.asarray(batch.q))
    # one program (compact=False) for the same batch gives the same run (what a caller's jit gets)
    one = simulate_batch(ARM, stack_scenarios(scs[::2]), CTRL, GAINS,
                         params=dataclasses.replace(PARAMS, compact=False))
    np.testing.assert_allclose(np.asarray(one.q[1]), np.asarray(single2.q), rtol=1e-10, atol=1e-12)
    # two members in two threads (simulate_batch's threads): each its single run's steps and path
    threaded = simulate_batch(ARM, stack_scenarios(scs[::2]), CTRL, GAINS, params=PARAMS, threads=2)
    assert [int(k) for k in threaded.n_steps] == [int(horizon.n_steps), int(single2.n_steps)]
    for i, single in enumerate((horizon, single2)):
        np.testing.assert_allclose(np.asarray(threaded.q[i]), np.asarray(single.q), rtol=0, atol=1e-12)


def test_cases_padded_to_common_shapes_share_one_compilation(horizon):
    """Guided runs of two "cases" with different obstacle capacities, padded to common shapes
    (``_pipeline.pad_case``, what the study does with its small cases): the second one reuses the
    first one's compiled programs, and the padded run equals the unpadded one (the masked slots add
    zeros to the field; separately compiled programs: to rounding)."""
    from conftest import backend_compiles

    from redman_jax._pipeline import pad_case

    shapes = (2, (2, 2, 3))
    other = guided_scenario((0.1, -0.3, 0.0), seed=1)
    p0 = np.asarray(end_effector_pose(ARM, ARM.q0)[0])
    other = eqx.tree_at(lambda s: s.obstacles, other, make_obstacles(
        boxes=[(np.eye(3), p0 + [0.0, 0.5, 0.4], (0.05, 0.05, 0.05))],
        cylinders=[(np.eye(3), p0 + [0.4, 0.0, 0.5], (0.04, 0.1))], capacities=(1, 2, 3)))
    n = ARM.n_dof
    ik = tuple(jnp.zeros((1, 2, n)) for _ in range(3))  # unused by a guided run; pad_case pads it
    runs = []
    for sc in (SCEN, other):
        padded, _ = pad_case(stack_scenarios([sc]), ik, shapes)
        assert padded.obstacles.capacities == (2, 2, 3)
        with backend_compiles() as compiles:
            runs.append(simulate_batch(ARM, padded, CTRL, GAINS, params=PARAMS))
            jax.block_until_ready(runs[-1].q)
    assert compiles == []  # the second case compiled nothing
    a, b = runs
    assert int(a.n_steps[0]) == int(horizon.n_steps) and bool(a.success[0])
    np.testing.assert_allclose(np.asarray(a.q[0]), np.asarray(horizon.q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(a.estimates[0]), np.asarray(horizon.estimates), rtol=1e-10, atol=1e-12)
    assert not bool(b.diverged[0]) and np.isfinite(np.asarray(b.q)).all()


def test_estimator_timing_times_the_update_the_simulation_runs(monkeypatch):
    """``t_lme_per_sample`` times ``estimator_update`` with the run's own settings (its field
    parameters, ``lme_mu``, ``lme_max_jump`` and buffer size, not the thesis defaults) along the
    end-effector positions of the batch's first run that did not diverge, its valid samples
    repeated up to the capacity; the timed scan is the update, sample after sample."""
    import types

    from redman_jax import _metrics, _pipeline
    from redman_jax._fields import FieldParams
    from redman_jax._guidance import VirtualBuffer, estimator_update

    seen = {}

    def fake_wall_time_per_sample(fn, *args, n_samples, repeats):
        seen.update(fn=fn, args=args, n_samples=n_samples, repeats=repeats)
        return 1.0

    monkeypatch.setattr(_metrics, "wall_time_per_sample", fake_wall_time_per_sample)
    field = FieldParams(a=0.002)
    params = dataclasses.replace(PARAMS, buffer_size=7, field=field, lme_mu=jnp.asarray(3e-5),
                                 lme_max_jump=jnp.asarray(0.5))
    scen = stack_scenarios([SCEN, SCEN])
    K = SCEN.reference.capacity
    rng = np.random.default_rng(0)
    p = np.asarray(SCEN.reference.p)[None] + rng.normal(0, 0.01, (2, K, 3))
    n_valid = min(K, 5)
    mask = np.zeros((2, K), bool)
    mask[1, :n_valid] = True
    res = types.SimpleNamespace(diverged=np.array([True, False]), mask=mask, p=p)
    assert _pipeline._lme_time(scen, res, 4, params, GAINS) == 1.0
    xs, goal, obs, buf, fp, mu, max_jump = seen["args"]
    assert seen["fn"] is _pipeline._lme_scan and seen["n_samples"] == K and seen["repeats"] == 4
    np.testing.assert_array_equal(np.asarray(xs), p[1][np.arange(K) % n_valid])
    assert buf.p.shape == (7, 3) and not np.any(np.asarray(buf.mask))
    assert fp is field
    assert float(mu) == 3e-5 and float(max_jump) == 0.5
    np.testing.assert_array_equal(np.asarray(goal), np.asarray(SCEN.goal_p))
    # the scan is the estimator's update at each position in turn, the buffer carried
    b = VirtualBuffer.empty(3, jnp.float64)
    fp0 = FieldParams()
    xs4 = np.asarray(SCEN.reference.p)[0] + rng.normal(0, 0.02, (4, 3))
    b_scan, (x_scan, ok_scan) = _pipeline._lme_scan(jnp.asarray(xs4), SCEN.goal_p, SCEN.obstacles, b, fp0,
                                                    jnp.asarray(1e-6), jnp.asarray(2.0))
    for k in range(4):
        b, x_min, ok = estimator_update(jnp.asarray(xs4[k]), SCEN.goal_p, SCEN.obstacles, b, fp0, 1e-6, 2.0)
        np.testing.assert_allclose(np.asarray(x_scan[k]), np.asarray(x_min), rtol=1e-12, atol=1e-12)
        assert bool(ok_scan[k]) == bool(ok)
    np.testing.assert_allclose(np.asarray(b_scan.p), np.asarray(b.p), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(b_scan.mask), np.asarray(b.mask))


def test_what_happens_after_the_stop_does_not_count():
    """The stop rule is applied after the fact in both modes, so the rows after the stop must not
    change the outcome: a run that held the goal and then (still integrating: ``mode="per_sample"``
    or ``stop_early=False``) ran out of steps or blew up is a success, as in the default mode. The
    same failure before the stop is a divergence. Synthetic rows through ``_guided_result`` (both
    modes hand it one solver status per sample): the arm sits at its start pose, the goal."""
    import diffrax

    from redman_jax._guidance import VirtualBuffer
    from redman_jax._sim import _guided_result, _initial_state

    N, hold = 60, 20
    params = dataclasses.replace(PARAMS, guidance_samples=N, hold_samples=hold)
    scen = guided_scenario((0.0, 0.0, 0.0))
    y0 = _initial_state(ARM, CTRL, None, None, jnp.float64)
    rows = jax.tree.map(lambda x: jnp.broadcast_to(x, (N,) + x.shape), y0)

    def outcome(bad_from, inf_rows=True, out_of_steps=True):
        bad = jnp.arange(N) >= bad_from
        ys = rows if not inf_rows else jax.tree.map(
            lambda x: jnp.where(bad.reshape((N,) + (1,) * (x.ndim - 1)), jnp.inf, x), rows)
        status = jnp.where(bad & out_of_steps, diffrax.RESULTS.max_steps_reached._value, 0)
        return _guided_result(ARM, scen, params, y0, N, jnp.asarray(TS), ys, jnp.zeros(3, jnp.int32),
                              status, jnp.zeros((N, 3)), jnp.zeros(N, bool), jnp.zeros(N),
                              VirtualBuffer.empty(4, jnp.float64))

    after = outcome(hold + 10)  # held over samples 0..hold-1, blew up 10 samples later
    assert int(after.n_samples) == hold and bool(after.metrics.success)
    assert not bool(after.diverged) and int(after.status) == 0 and int(after.metrics.cause) == 0
    assert not bool(after.metrics.collided) and not bool(after.metrics.joint_limit)
    before = outcome(hold // 2)  # blew up inside the hold
    assert bool(before.diverged) and not bool(before.metrics.success) and int(before.metrics.cause) == 3
    assert not bool(before.metrics.collided) and not bool(before.metrics.joint_limit)
    assert not bool(after.out_of_steps) and bool(before.out_of_steps)
    # the step budget used up inside the hold, the rows not reached holding the last (finite) state
    # as the stepper leaves them: diverged, out of steps; blown up with no solver status: not
    spent = outcome(hold // 2, inf_rows=False)
    assert bool(spent.diverged) and bool(spent.out_of_steps) and int(spent.metrics.cause) == 3
    blown = outcome(hold // 2, out_of_steps=False)
    assert bool(blown.diverged) and not bool(blown.out_of_steps) and int(blown.metrics.cause) == 3


def test_sim_params_field_drives_the_controller_and_the_estimator():
    """``SimParams.field`` went to the local-minima estimator only, while the controller's guidance
    velocity kept ``gains.field``: one run followed two fields (final positions 0.18 m apart). It
    is now the field of both: the run equals the one with that field in the gains."""
    from redman_jax._fields import FieldParams

    fp = FieldParams(a=0.05)
    P = dataclasses.replace(PARAMS, guidance_samples=30)
    via_params = simulate(ARM, SCEN, CTRL, GAINS, params=dataclasses.replace(P, field=fp))
    via_gains = simulate(ARM, SCEN, CTRL, dataclasses.replace(GAINS, field=fp), params=P)
    default = simulate(ARM, SCEN, CTRL, GAINS, params=P)
    for x, y in ((via_params.q, via_gains.q), (via_params.estimates, via_gains.estimates)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert float(jnp.max(jnp.abs(via_params.q - default.q))) > 1e-3  # the field matters here
    # a batch of gains gets it on every member, also where its static form is not the gains'
    fp2 = FieldParams(a=0.05, form="plus")
    G = jax.tree.map(lambda x: jnp.stack([x, x]), GAINS)
    batch = simulate_batch(ARM, stack_scenarios([SCEN, SCEN]), CTRL, G, batch_gains=True,
                           params=dataclasses.replace(P, field=fp2))
    single = simulate(ARM, SCEN, CTRL, dataclasses.replace(GAINS, field=fp2), params=P)
    np.testing.assert_allclose(np.asarray(batch.q[1]), np.asarray(single.q), rtol=0, atol=1e-12)
