"""Dense QP solver (redman_jax._qp): against OSQP and exact active-set KKT solves, gradients against
finite differences, infeasibility, vmap and float32.

Reference: OSQP (eps 1e-12, polished) gives the active set; the reference solution is the exact
equality-constrained KKT solve on that set (NumPy, float64). Tolerance for ``x``: the polished
solution is itself an active-set KKT solve, so its error is the backward error of a dense LU on a
KKT matrix of condition <= ~1e6 (P's eigenvalues span 1e-4..~30 as in the IK): ~1e-16 * 1e6 =
1e-10 relative; we assert 1e-8 (measured worst 4e-11 over 300 problems).
"""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import osqp
import pytest
import scipy.sparse as sp

from redman_jax._qp import QPSettings, solve_qp

N_VAR, N_ROWS = 9, 16
X_TOL = 1e-8


def random_problem(rng, n=N_VAR, m=N_ROWS, w=1e-4, degenerate=False):
    """IK-like problem: P = J^T J + w I (rank-6 J), one-sided general rows, a box; feasible by
    construction (x0 satisfies everything)."""
    J = rng.normal(size=(6, n))
    P = J.T @ J + w * np.eye(n)
    c = -J.T @ rng.normal(size=6) * 3
    A = rng.normal(size=(m, n))
    x0 = rng.normal(size=n) * 0.3
    l = A @ x0 - rng.uniform(0, 0.5, m)
    h = np.full(m, np.inf)
    lb = x0 - rng.uniform(0, 0.5, n)
    ub = x0 + rng.uniform(0, 0.5, n)
    if degenerate:
        lb[0] = ub[0] = x0[0]  # a fixed variable (the IK's lb > ub -> mean case)
        l[1] = h[1] = A[1] @ x0  # an equality row
    return P, c, A, l, h, lb, ub


def reference_solution(P, c, A, l, h, lb, ub):
    n = P.shape[0]
    G = np.vstack([A, np.eye(n)])
    lo, hi = np.r_[l, lb], np.r_[np.minimum(h, 1e30), ub]
    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix(np.triu(P)), c, sp.csc_matrix(G), lo, hi, eps_abs=1e-12, eps_rel=1e-12,
                 max_iter=1_000_000, polishing=True, verbose=False)
    # the status is checked here; OSQP >= 1.0 warns unless told so (0.6 has no such argument)
    quiet = {"raise_error": False} if "raise_error" in inspect.signature(solver.solve).parameters else {}
    r = solver.solve(**quiet)
    assert r.info.status == "solved"
    act = np.abs(r.y) > 1e-7
    rhs = np.where(r.y > 0, hi, lo)[act]
    Ga = G[act]
    k = int(act.sum())
    K = np.block([[P, Ga.T], [Ga, np.zeros((k, k))]])
    sol = np.linalg.lstsq(K, np.r_[-c, rhs], rcond=None)[0]
    return sol[:n], r.x, int(act.sum())


solve_jit = jax.jit(jax.vmap(solve_qp))
solve_one = jax.jit(solve_qp)  # one compilation shared by the single-problem tests (n = 9, m = 16)


@pytest.mark.parametrize("degenerate", [False, True])
def test_matches_reference_on_random_problems(degenerate):
    rng = np.random.default_rng(7 + degenerate)
    probs = [random_problem(rng, degenerate=degenerate) for _ in range(40)]
    for i in range(0, 40, 4):  # a few badly scaled linear terms
        probs[i] = (probs[i][0], 100 * probs[i][1]) + probs[i][2:]
    batch = [np.stack(x) for x in zip(*probs)]
    sol = solve_jit(*batch)
    n_active = []
    for i, prob in enumerate(probs):
        x_ref, x_osqp, k = reference_solution(*prob)
        n_active.append(k)
        x = np.asarray(sol.x[i])
        assert np.abs(x - x_ref).max() <= X_TOL * (1 + np.abs(x_ref).max()), i
        P, c = prob[0], prob[1]
        obj = lambda v: 0.5 * v @ P @ v + c @ v
        assert obj(x) <= obj(x_osqp) + 1e-9 * (1 + abs(obj(x_osqp)))
    assert bool(np.all(sol.converged))
    assert float(np.max(sol.primal_residual)) <= 1e-9
    assert float(np.max(sol.dual_residual)) <= 1e-9
    # KKT: P x + c + A^T y + y_box = 0 with the returned duals
    P, c, A = batch[0], batch[1], batch[2]
    stat = np.einsum("bij,bj->bi", P, sol.x) + c + np.einsum("bji,bj->bi", A, sol.y) + sol.y_box
    assert np.abs(stat).max() <= 1e-8
    assert max(n_active) >= 3 and min(n_active) >= 1  # the tests exercise active constraints


def test_unconstrained_is_linear_solve():
    rng = np.random.default_rng(1)
    P, c, A, l, h, lb, ub = random_problem(rng)
    inf = np.full_like(l, np.inf)
    sol = solve_one(P, c, A, -inf, inf, -np.full_like(lb, np.inf), np.full_like(ub, np.inf))
    np.testing.assert_allclose(sol.x, np.linalg.solve(P, -c), rtol=1e-9, atol=1e-9)


def _grad_problem():
    rng = np.random.default_rng(3)
    n, m = N_VAR, N_ROWS
    J = rng.normal(size=(6, n))
    P = J.T @ J + 1e-2 * np.eye(n)
    c = -J.T @ rng.normal(size=6) * 3
    A = rng.normal(size=(m, n))
    l = -np.abs(rng.normal(size=m)) * 0.5
    h = np.full(m, np.inf)
    lb, ub = -0.4 * np.ones(n), 0.4 * np.ones(n)
    return P, c, A, l, h, lb, ub


def test_gradients_match_finite_differences():
    """Implicit differentiation at the solution vs central differences, forward and reverse mode,
    on a problem with active general rows and active box bounds (strictly complementary)."""
    P, c, A, l, h, lb, ub = _grad_problem()
    sol = solve_one(P, c, A, l, h, lb, ub)
    n_rows, n_box = int(np.sum(np.abs(sol.y) > 1e-6)), int(np.sum(np.abs(sol.y_box) > 1e-6))
    assert n_rows >= 1 and n_box >= 1 and n_rows + n_box >= 3
    # strict complementarity (else the derivative is one-sided and FD would straddle a kink)
    assert np.all((np.abs(sol.y) > 1e-4) | (np.asarray(A @ sol.x - l) > 1e-4))
    wx = np.arange(1.0, N_VAR + 1.0)

    @jax.jit
    def f(c, A, l, ub, P):
        s = solve_qp(P, c, A, l, h, lb, ub)
        return s.x @ wx + 0.3 * jnp.sum(s.y)

    from jax.test_util import check_grads

    # central differences with eps 1e-6 on a piecewise-smooth map: truncation ~eps^2 * curvature,
    # rounding ~1e-16 / 1e-6 = 1e-10; 1e-6 leaves margin and still catches a wrong active set.
    check_grads(f, (c, A, l, ub, P), order=1, modes=["fwd", "rev"], eps=1e-6, atol=1e-6, rtol=1e-6)


def test_infeasible_gives_flag_not_nan():
    P, c, A, l, h, lb, ub = _grad_problem()
    A = A.copy()
    A[0] = np.eye(N_VAR)[0]
    l = l.copy()
    l[0] = ub[0] + 1.0  # x_0 >= ub_0 + 1 contradicts the box
    sol = solve_one(P, c, A, l, h, lb, ub)
    assert not bool(sol.converged)
    assert np.all(np.isfinite(sol.x)) and np.all(np.isfinite(sol.y))
    assert float(sol.primal_residual) > 0.1


def test_float32_runs():
    P, c, A, l, h, lb, ub = _grad_problem()
    f32 = [np.asarray(v, np.float32) for v in (P, c, A, l, h, lb, ub)]
    s32 = jax.jit(solve_qp)(*f32)
    s64 = solve_one(P, c, A, l, h, lb, ub)
    assert s32.x.dtype == jnp.float32
    assert bool(s32.converged)
    # float32: tolerance 1e-6 on residuals (P's smallest eigenvalue ~1e-2): x to 1e-2 is a loose bound
    assert np.abs(np.asarray(s32.x, float) - np.asarray(s64.x)).max() < 1e-2


def test_bad_shapes_raise():
    P, c, A, l, h, lb, ub = _grad_problem()
    with pytest.raises(ValueError, match="A must have"):
        solve_qp(P, c, A[:, :3], l, h, lb, ub)
    with pytest.raises(ValueError, match="lb"):
        solve_qp(P, c, A, l, h, lb[:2], ub)


def test_nan_input_is_an_error_eagerly_and_not_converged_traced():
    """A NaN bound is masked out like an infinite one inside the solver; it must not pass for "no
    bound": called eagerly it is refused naming the argument, traced the result is not converged
    (where the same problem with -inf there converges)."""
    P, c, A, l, h, lb, ub = _grad_problem()
    bad = lambda v: jnp.asarray(v).at[0].set(jnp.nan)
    for name, args in (("l", (P, c, A, bad(l), h, lb, ub)), ("h", (P, c, A, l, bad(h), lb, ub)),
                       ("lb", (P, c, A, l, h, bad(lb), ub)), ("ub", (P, c, A, l, h, lb, bad(ub)))):
        with pytest.raises(ValueError, match=f"solve_qp: {name}: NaN bound"):
            solve_qp(*args)
    with pytest.raises(ValueError, match="solve_qp: c: expected finite"):
        solve_qp(P, bad(c), A, l, h, lb, ub)
    with pytest.raises(ValueError, match="solve_qp: P: expected finite"):
        solve_qp(jnp.asarray(P).at[0, 0].set(jnp.inf), c, A, l, h, lb, ub)
    traced = jax.jit(lambda lb: solve_qp(P, c, A, l, h, lb, ub))
    assert bool(traced(jnp.asarray(lb).at[0].set(-jnp.inf)).converged)
    assert not bool(traced(bad(lb)).converged)


def test_settings_change_without_recompile():
    P, c, A, l, h, lb, ub = _grad_problem()
    f = solve_one
    f(P, c, A, l, h, lb, ub, QPSettings(eps_abs=jnp.asarray(1e-6), eps_rel=jnp.asarray(1e-6)))
    n0 = f._cache_size()
    f(P, c, A, l, h, lb, ub, QPSettings(eps_abs=jnp.asarray(1e-10), eps_rel=jnp.asarray(1e-10)))
    assert f._cache_size() == n0
    # called eagerly (equinox.filter_jit inside), Python floats too: they were static leaves, and
    # every new value compiled the QP (and an IK around it) anew
    from redman_jax._qp import _solve_qp

    solve_qp(P, c, A, l, h, lb, ub, QPSettings(eps_abs=1e-8, eps_rel=1e-8))
    n1 = _solve_qp._cached._cache_size()
    solve_qp(P, c, A, l, h, lb, ub, QPSettings(eps_abs=1e-7, eps_rel=1e-7))
    solve_qp(P, c, A, l, h, lb, ub, QPSettings(eps_abs=jnp.asarray(1e-6), eps_rel=jnp.asarray(1e-6)))
    assert _solve_qp._cached._cache_size() == n1


def test_far_bound_does_not_activate_a_nearly_active_row():
    """A bound far away (|g| = 10..1e5) must not change which other rows are active: the nearly
    active x0 <= 1.0001 (slack 1e-4 at the optimum x0 = 1) stays inactive, so x is exact and
    dx0/dc0 = 1 (it was 0 with one slack scale for all rows)."""
    for ub1 in (np.inf, 10.0, 1e5):
        def x0_of(c0):
            return solve_qp(jnp.eye(2), jnp.stack([-c0, jnp.asarray(-1.0)]), ub=jnp.array([1.0001, ub1])).x[0]

        assert float(x0_of(1.0)) == pytest.approx(1.0, abs=1e-12), ub1
        assert float(jax.grad(x0_of)(1.0)) == pytest.approx(1.0, abs=1e-9), ub1


@pytest.mark.parametrize("w", [1e-2, 1e-4, 1e-6])
def test_narrow_bounds_pick_the_right_side(w):
    """min 1/2 x^2 + x on 0 <= x <= w: x* = 0 at the lower bound, y_box = -1, dx*/dlb = 1, however
    narrow the box (both sides looked active and the upper one won below w ~ 1e-5); likewise for a
    narrow general row 0 <= x0 + x1 <= w."""
    sol = lambda lb: solve_qp(jnp.eye(1), jnp.array([1.0]), lb=jnp.stack([lb]), ub=jnp.array([w]))
    s = sol(jnp.asarray(0.0))
    assert bool(s.converged)
    assert abs(float(s.x[0])) <= 1e-12 and float(s.y_box[0]) == pytest.approx(-1.0, abs=1e-9)
    assert float(jax.grad(lambda lb: sol(lb).x[0])(0.0)) == pytest.approx(1.0, abs=1e-9)
    r = solve_qp(jnp.eye(2), jnp.array([1.0, 1.0]), A=jnp.array([[1.0, 1.0]]), l=jnp.array([0.0]),
                 h=jnp.array([w]))
    assert np.abs(np.asarray(r.x)).max() <= 1e-12 and float(r.y[0]) == pytest.approx(-1.0, abs=1e-9)


def test_converged_means_optimal_after_any_iteration_count():
    """Stopped after 1..11 iterations, a result flagged converged is the optimum: the flag needs the
    complementarity gap unless an accepted polish (a KKT point) proves it (a primal-feasible iterate
    with duals z >= 0 has a zero dual residual without being optimal; such iterates were flagged
    0.2-0.6 away from the optimum). The bound: an iterate that meets the tolerances has an
    objective within the duality gap s'z <= M (eps_abs + eps_rel |f|) of the optimum (M = 8 rows)."""
    f = lambda P, c, x: 0.5 * x @ P @ x + c @ x
    rng = np.random.default_rng(0)
    for _ in range(30):
        J = rng.normal(size=(3, 4))
        P, c = J.T @ J + 1e-2 * np.eye(4), rng.normal(size=4) * 3
        lb, ub = -0.3 * np.ones(4), 0.3 * np.ones(4)
        ref = np.asarray(solve_qp(P, c, lb=lb, ub=ub).x)
        for polish in (False, True):
            for it in range(1, 12):
                s = solve_qp(P, c, lb=lb, ub=ub, settings=QPSettings(max_iter=it, polish=polish))
                if bool(s.converged):
                    x = np.asarray(s.x)
                    assert np.all(x >= lb - 1e-9) and np.all(x <= ub + 1e-9), (polish, it)
                    bound = 8 * (1e-9 + 1e-9 * abs(f(P, c, ref))) + 1e-12
                    assert f(P, c, x) - f(P, c, ref) <= bound, (polish, it)


def test_bad_settings_are_errors_naming_the_field():
    """A negative or NaN tolerance, no iterations or a step fraction outside (0, 1) would make the
    interior-point loop stop at once or step out of the cone; each is refused at construction."""
    for kw, match in [(dict(eps_abs=-1e-6), "QPSettings.eps_abs"), (dict(eps_rel=float("nan")), "QPSettings.eps_rel"),
                      (dict(max_iter=0), "QPSettings.max_iter"), (dict(max_iter=2.5), "QPSettings.max_iter"),
                      (dict(step_fraction=1.0), "QPSettings.step_fraction"),
                      (dict(step_fraction=0.0), "QPSettings.step_fraction")]:
        with pytest.raises(ValueError, match=match):
            QPSettings(**kw)
    QPSettings(eps_abs=jnp.asarray(0.0), eps_rel=jnp.asarray(1e-8), max_iter=1, step_fraction=0.5)
    # traced tolerances (a caller's jit) are the caller's
    assert float(jax.jit(lambda e: QPSettings(eps_abs=e).eps_abs)(jnp.asarray(1e-6))) == 1e-6


def test_returned_duals_satisfy_the_reported_dual_residual():
    """``dual_residual`` is ``|P x + c + A^T y + y_box|_inf`` of the returned duals, also where the
    polish was rejected (early iteration caps here): ``y_box`` was then rebuilt from the polish's
    guessed active set, off by up to 0.56 in 14 of 60 problems while 3.6e-3 was reported."""
    rng = np.random.default_rng(1)
    n, m = 7, 16
    for _ in range(60):
        J = rng.normal(size=(6, n))
        P, c = J.T @ J + 1e-4 * np.eye(n), -J.T @ rng.normal(size=6) * 10
        A, x0 = rng.normal(size=(m, n)), rng.normal(size=n) * 0.3
        l, h = A @ x0 - rng.uniform(0, 0.3, m), np.full(m, np.inf)
        lb, ub = x0 - rng.uniform(0, 0.5, n), x0 + rng.uniform(0, 0.5, n)
        s = solve_qp(P, c, A, l, h, lb, ub, settings=QPSettings(max_iter=int(rng.integers(4, 12))))
        x, y, yb = (np.asarray(v) for v in (s.x, s.y, s.y_box))
        assert np.abs(P @ x + c + A.T @ y + yb).max() <= 10 * float(s.dual_residual) + 1e-9


def test_stopping_the_interior_point_loop_of_one_batch_member():
    """``solve_qp(active=False)`` takes no iteration; ``active=True`` is the plain solve, and under
    ``vmap`` the members are independent (the IK's screening relies on both)."""
    P, c = jnp.diag(jnp.array([2.0, 1.0, 3.0])), jnp.array([1.0, -2.0, 0.5])
    A, lo = jnp.array([[1.0, 1.0, 0.0]]), jnp.array([1.5])
    lb, ub = -jnp.ones(3), jnp.ones(3)
    plain = solve_qp(P, c, A, lo, None, lb, ub)
    assert int(plain.iterations) > 0 and bool(plain.converged)
    both = jax.vmap(lambda act: solve_qp(P, c, A, lo, None, lb, ub, active=act))(jnp.array([True, False]))
    np.testing.assert_array_equal(np.asarray(both.x[0]), np.asarray(plain.x))
    assert int(both.iterations[0]) == int(plain.iterations) and int(both.iterations[1]) == 0
    assert not bool(both.converged[1])
