"""Obstacle distances and potential fields (SPEC section 3; thesis 3.2.4, 3.3.3).

References are independent: signed distances against brute-force nearest surface samples (scipy
KD-tree), gradients against central finite differences and ``jax.grad``, Hessians against finite
differences of the gradient, the virtual-obstacle gradient against the derivative of 3.25 with the
amplitude held fixed.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from redman_jax._math import cast_floating
from redman_jax._fields import (
    FieldParams,
    guidance_velocity,
    obstacle_field_gradient,
    obstacle_field_gradients,
    obstacle_field_potential,
    obstacle_potential,
    obstacle_potential_d2r,
    obstacle_potential_dr,
    obstacle_sdf_and_normals,
    points_sdf_and_normals,
    total_gradient,
    total_gradient_batch,
    total_hessian,
    total_potential,
    total_potential_batch,
    virtual_gradient,
    virtual_potential,
)
from redman_jax._obstacles import make_obstacles, obstacle_distances, pad_obstacles, stack_obstacles

# Brute-force surface sampling spacing [m]; the nearest sample to the true closest point on a face
# is at most H_SURF/sqrt(2) away on a square grid (and the curved grids below are finer than
# H_SURF along the arc), so |brute - true| <= H_SURF/sqrt(2) (distance is 1-Lipschitz).
H_SURF = 0.004
SDF_TOL = H_SURF / np.sqrt(2) + 1e-9
# Central differences with step 1e-6 on functions whose third derivative is O(1e3) (a = 5e-4,
# r >= 0.1): truncation ~ eps^2 |f'''| ~ 1e-9, round-off ~ 1e-16 |f| / eps ~ 1e-10.
FD_RTOL = 1e-6
FD_ATOL = 1e-7


# Jitted, point-vectorised versions (compiled once per static structure) keep the test fast.
_P = (0, None, None, None, None, None)
_ofg_v = jax.jit(jax.vmap(obstacle_field_gradient, in_axes=(None, 0, None, None, None)),
                 static_argnums=4)
_ofp_v = jax.jit(jax.vmap(obstacle_field_potential, in_axes=(None, 0, None, None, None)),
                 static_argnums=4)
_ofp_grad_v = jax.jit(jax.vmap(jax.grad(obstacle_field_potential, 1),
                               in_axes=(None, 0, None, None, None)), static_argnums=4)
_tg_v = jax.jit(jax.vmap(total_gradient, in_axes=_P))
_tp_v = jax.jit(jax.vmap(total_potential, in_axes=_P))
_tgrad_v = jax.jit(jax.vmap(jax.grad(total_potential), in_axes=_P))
_th_v = jax.jit(jax.vmap(total_hessian, in_axes=_P))
_thess_v = jax.jit(jax.vmap(jax.hessian(total_potential), in_axes=_P))


def _fd_points(f_v, xs, eps=1e-6):
    """Central differences of a point-vectorised ``f_v: (N, 3) -> (N, ...)`` at every row of
    ``xs``: ``(N, ..., 3)``, in one call."""
    xs = np.asarray(xs)
    E = np.eye(3) * eps
    X = np.concatenate([xs[:, None, :] + E[None], xs[:, None, :] - E[None]], 1).reshape(-1, 3)
    F = np.asarray(f_v(jnp.asarray(X)))
    F = F.reshape((xs.shape[0], 2, 3) + F.shape[1:])
    d = (F[:, 0] - F[:, 1]) / (2 * eps)  # (N, 3, ...)
    return np.moveaxis(d, 1, -1)


def _rot(seed):
    return Rotation.random(random_state=seed).as_matrix()


def _grid(a, b, h):
    return np.linspace(a, b, max(2, int(np.ceil((b - a) / h)) + 1))


def _box_surface(b, h=H_SURF):
    pts = []
    for ax in range(3):
        o1, o2 = [i for i in range(3) if i != ax]
        u, v = np.meshgrid(_grid(-b[o1], b[o1], h), _grid(-b[o2], b[o2], h), indexing="ij")
        for sgn in (-1, 1):
            p = np.zeros(u.shape + (3,))
            p[..., ax] = sgn * b[ax]
            p[..., o1], p[..., o2] = u, v
            pts.append(p.reshape(-1, 3))
    return np.concatenate(pts)


def _cylinder_surface(r, hh, h=H_SURF):
    th = np.linspace(0, 2 * np.pi, int(np.ceil(2 * np.pi * r / h)) + 1)
    z = _grid(-hh, hh, h)
    T, Z = np.meshgrid(th, z, indexing="ij")
    side = np.stack([r * np.cos(T), r * np.sin(T), Z], -1).reshape(-1, 3)
    caps = []
    for rr in _grid(0, r, h):
        n = max(1, int(np.ceil(2 * np.pi * rr / h)) + 1)
        t = np.linspace(0, 2 * np.pi, n)
        for zc in (-hh, hh):
            caps.append(np.stack([rr * np.cos(t), rr * np.sin(t), np.full(n, zc)], -1))
    return np.concatenate([side] + caps)


def _sphere_surface(r, h=H_SURF):
    n = int(4 * np.pi * r**2 / (h**2 * 0.5)) + 1  # Fibonacci lattice, area per point < h^2 / 2
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5**0.5) * i
    return r * np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], -1)


def _inside(kind, dims, xl):
    if kind == "spheres":
        return np.linalg.norm(xl, axis=-1) < dims[0]
    if kind == "boxes":
        return np.all(np.abs(xl) < dims, axis=-1)
    return (np.linalg.norm(xl[:, :2], axis=-1) < dims[0]) & (np.abs(xl[:, 2]) < dims[1])


SHAPES = [
    ("spheres", np.array([0.12, 0, 0]), _sphere_surface),
    ("boxes", np.array([0.10, 0.06, 0.15]), _box_surface),
    ("cylinders", np.array([0.07, 0.12, 0]), _cylinder_surface),
]


@pytest.mark.parametrize("kind,dims,surface", SHAPES, ids=[s[0] for s in SHAPES])
def test_sdf_matches_brute_force_surface_sampling(kind, dims, surface, rng):
    R = _rot(3)
    p = np.array([0.3, -0.2, 0.8])
    need = {"spheres": 1, "boxes": 3, "cylinders": 2}[kind]
    obs = make_obstacles(**{kind: [(R, p, dims[:need])]})
    local = surface(dims[0]) if kind == "spheres" else surface(dims) if kind == "boxes" else \
        surface(dims[0], dims[1])
    tree = cKDTree(local @ R.T + p)
    # query points: a shell around the shape (outside) and points inside
    half = np.where(dims > 0, dims, 0.0)
    half = {"spheres": np.full(3, dims[0]), "boxes": half, "cylinders": dims[[0, 0, 1]]}[kind]
    xl = rng.uniform(-1.8, 1.8, size=(400, 3)) * half
    x = xl @ R.T + p
    inside = _inside(kind, dims, xl)
    assert inside.sum() > 20 and (~inside).sum() > 20
    sdf = np.asarray(_distances(obs, jnp.asarray(x)))[:, 0]
    brute, _ = tree.query(x)
    # sign: negative inside, positive outside
    assert np.all(sdf[inside] <= 0) and np.all(sdf[~inside] > 0)
    # magnitude: brute force over surface samples overestimates by at most SDF_TOL
    err = brute - np.abs(sdf)
    assert err.min() >= -1e-12, err.min()
    assert err.max() <= SDF_TOL, err.max()


@pytest.mark.parametrize("kind,dims,surface", SHAPES, ids=[s[0] for s in SHAPES])
def test_sdf_normals_are_unit_and_match_finite_differences(kind, dims, surface, rng):
    R = _rot(7)
    p = np.array([-0.1, 0.4, 0.5])
    need = {"spheres": 1, "boxes": 3, "cylinders": 2}[kind]
    obs = make_obstacles(**{kind: [(R, p, dims[:need])]})
    xl = rng.uniform(-2.0, 2.0, size=(60, 3)) * np.max(dims)
    x = xl @ R.T + p
    d, n = jax.jit(jax.vmap(obstacle_sdf_and_normals, in_axes=(None, 0)))(obs, jnp.asarray(x))
    sdf = lambda q: np.asarray(_distances(obs, jnp.asarray(q)))[:, 0]
    eps = 1e-6
    fd = np.stack([(sdf(x + eps * e) - sdf(x - eps * e)) / (2 * eps) for e in np.eye(3)], -1)
    np.testing.assert_allclose(d[:, 0], sdf(x), rtol=1e-14, atol=1e-15)  # same sdf, other fusion
    # skip the measure-zero ridges where the sdf is not differentiable (FD straddles a kink)
    smooth = np.abs(np.linalg.norm(fd, axis=1) - 1) < 1e-6
    assert smooth.sum() > 40
    np.testing.assert_allclose(np.linalg.norm(n[smooth, 0], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(n[smooth, 0], fd[smooth], atol=1e-6)


def test_radial_potential_forms():
    a, D = 0.0005, 0.5
    r = jnp.linspace(0.02, 0.7, 200)
    for form in ("minus", "plus"):
        dv = obstacle_potential_dr(r, a, D, form)
        ad = jax.vmap(jax.grad(lambda s: obstacle_potential(s, a, D, form)))(r)
        np.testing.assert_allclose(dv, ad, rtol=1e-12)
        d2 = obstacle_potential_d2r(r, a, D, form)
        ad2 = jax.vmap(jax.grad(lambda s: obstacle_potential_dr(s, a, D, form)))(r)
        np.testing.assert_allclose(d2, ad2, rtol=1e-12)
    # "minus" (E4): continuous and zero at D, non-negative and decreasing on (0, D]
    rin = r[r <= D]
    vm = obstacle_potential(rin, a, D, "minus")
    assert np.all(vm >= 0) and np.all(np.diff(vm) < 0)
    assert abs(float(obstacle_potential(D, a, D, "minus"))) < 1e-15
    # gradient jump a/D^4 at D (SPEC section 3)
    np.testing.assert_allclose(-obstacle_potential_dr(D, a, D, "minus"), a / D**4, rtol=1e-12)
    # "plus": thesis 3.8/3.9 literally, jump 2a/D^3 in V at D; 3.9 in vector form
    np.testing.assert_allclose(obstacle_potential(D, a, D, "plus"), 2 * a / D**3, rtol=1e-12)
    rr = 0.2
    thesis_39 = -a * rr * (2 / (D * rr**4) + 3 / rr**5)  # -a x_d (2/(d x_d^4) + 3/x_d^5) along n
    np.testing.assert_allclose(obstacle_potential_dr(rr, a, D, "plus"), thesis_39, rtol=1e-12)
    # the "plus" force is (3D + 2r)/(3D - 2r) times the "minus" one: 1.2-1.7x at r = 0.1-0.3 m
    # for the null-space range D = 0.75 (SPEC E4)
    r2 = jnp.array([0.1, 0.3])
    ratio = obstacle_potential_dr(r2, a, 0.75, "plus") / obstacle_potential_dr(r2, a, 0.75, "minus")
    np.testing.assert_allclose(ratio, (2.25 + 2 * r2) / (2.25 - 2 * r2), rtol=1e-12)
    assert 1.19 < ratio[0] < ratio[1] < 1.73


def _scene():
    return make_obstacles(
        spheres=[(np.eye(3), [0.45, 0.0, 0.6], [0.08])],
        boxes=[(_rot(1), [0.0, 0.45, 0.7], [0.10, 0.05, 0.08])],
        cylinders=[(_rot(2), [-0.35, -0.1, 0.5], [0.05, 0.15])],
        capacities=(2, 3, 2),
    )


_distances = jax.jit(jax.vmap(obstacle_distances, in_axes=(None, 0)))


def _outside_points(obs, rng, n, dmin=0.06, dmax=0.45):
    x = rng.uniform([-0.8, -0.6, 0.2], [0.9, 0.9, 1.1], size=(40 * n, 3))
    d = np.asarray(_distances(obs, jnp.asarray(x)))
    # well outside every obstacle, inside some range, and away from the cut-off D = 0.5 / 0.75
    keep = (d.min(1) > dmin) & (d.min(1) < dmax) & np.all(np.abs(d - 0.5) > 0.01, axis=1) & \
        np.all(np.abs(d - 0.75) > 0.01, axis=1)
    assert keep.sum() >= n
    return x[keep][:n]


@pytest.mark.parametrize("form", ["minus", "plus"])
def test_obstacle_gradient_matches_grad_and_finite_differences(form, rng):
    obs = _scene()
    xs = _outside_points(obs, rng, 8)
    for a, D in ((0.0005, 0.5), (0.05, 0.75)):
        g = np.asarray(_ofg_v(obs, jnp.asarray(xs), a, D, form))
        ag = np.asarray(_ofp_grad_v(obs, jnp.asarray(xs), a, D, form))
        fd = _fd_points(lambda X: _ofp_v(obs, X, a, D, form), xs)
        scale = np.abs(g).max(axis=1, keepdims=True)
        np.testing.assert_allclose(g, ag, rtol=1e-12, atol=1e-14 * scale.max())
        assert np.all(np.abs(g - fd) <= FD_RTOL * np.abs(g) + FD_ATOL * np.maximum(1, scale))


def test_obstacle_gradients_over_points_and_padding(rng):
    obs = _scene()
    xs = jnp.asarray(_outside_points(obs, rng, 6))
    f = jax.jit(obstacle_field_gradients, static_argnums=4)
    G = f(obs, xs, 0.05, 0.75, "minus")
    Gp = f(pad_obstacles(obs, (5, 5, 5)), xs, 0.05, 0.75, "minus")
    np.testing.assert_allclose(G, _ofg_v(obs, xs, 0.05, 0.75, "minus"), rtol=1e-14)
    np.testing.assert_allclose(G, Gp, rtol=1e-14)  # masked slots contribute nothing


def test_points_sdf_and_normals_equal_per_point_autodiff(rng):
    """The IK's all-pairs structure-of-arrays evaluation (analytic normals) equals the per-point
    ``vmap`` of :func:`obstacle_sdf_and_normals` (autodiff normals), padded slots included."""
    from redman_jax._fields import obstacle_sdf_and_normals, points_sdf_and_normals

    obs = pad_obstacles(_scene(), (3, 4, 3))
    centres = np.concatenate([np.asarray(f.p)[np.asarray(f.mask)] for f in (obs.spheres, obs.boxes, obs.cylinders)])
    near = (centres[:, None, :] + rng.uniform(-0.12, 0.12, (len(centres), 40, 3))).reshape(-1, 3)
    xs = jnp.asarray(np.concatenate([_outside_points(obs, rng, 30), rng.uniform(-0.8, 0.8, (300, 3)), near]))
    D, N = jax.jit(points_sdf_and_normals)(obs, xs)
    Dr, Nr = jax.jit(jax.vmap(lambda x: obstacle_sdf_and_normals(obs, x)))(xs)
    assert (np.asarray(Dr) < 0).any() and D.shape == Dr.shape and N.shape == Nr.shape
    np.testing.assert_allclose(D, Dr, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(N, Nr, rtol=1e-12, atol=1e-13)


def test_points_min_distance_equals_per_point_minimum(rng):
    """The fused running minimum of the simulator's collision flag equals ``min`` over
    :func:`obstacle_distances` at points outside, inside and on ridges, ignores padded slots, and
    runs in float32."""
    from redman_jax import points_min_distance

    obs = _scene()
    xs = np.concatenate([_outside_points(obs, rng, 40), rng.uniform(-0.8, 0.8, (200, 3)),
                         np.asarray(obs.boxes.p[:1]), np.asarray(obs.cylinders.p[:1])])
    ref = np.asarray(_distances(obs, jnp.asarray(xs))).min(axis=1)
    assert (ref < 0).any() and (ref > 0).any()
    f = jax.jit(points_min_distance)
    np.testing.assert_allclose(np.asarray(f(obs, jnp.asarray(xs))), ref, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(np.asarray(f(pad_obstacles(obs, (5, 5, 5)), jnp.asarray(xs))), ref,
                               rtol=1e-13, atol=1e-15)
    obs32 = cast_floating(obs, jnp.float32)
    d32 = np.asarray(f(obs32, jnp.asarray(xs, jnp.float32)))
    assert d32.dtype == np.float32
    np.testing.assert_allclose(d32, ref, atol=1e-5)
    # float32 points with the float64 obstacles (the scan's carry changed dtype): float64 distances
    mixed = np.asarray(f(obs, jnp.asarray(xs, jnp.float32)))
    assert mixed.dtype == np.float64
    np.testing.assert_allclose(mixed, ref, atol=1e-6)


@pytest.mark.parametrize("kind, dims, x, normal", [
    ("boxes", (1.0, 1.0, 1.0), (0.2, 0.3, 1.0), (0.0, 0.0, 1.0)),  # on a face
    ("boxes", (0.5, 0.2, 0.3), (-0.5, 0.1, 0.0), (-1.0, 0.0, 0.0)),
    ("cylinders", (0.3, 0.5, 0.0), (0.3, 0.0, 0.1), (1.0, 0.0, 0.0)),  # on the mantle
    ("cylinders", (0.3, 0.5, 0.0), (0.1, 0.1, -0.5), (0.0, 0.0, -1.0)),  # on a cap
])
def test_normal_on_the_surface_is_the_unit_face_normal(kind, dims, x, normal):
    """Exactly on a face the normal (autodiff of the sdf) is the unit face normal, as just outside
    and just inside: min(m, 0) split its derivative at m = 0 and gave half of it, halving the
    repulsive force there. The structure-of-arrays normals agree."""
    from redman_jax._fields import points_sdf_and_normals

    obs = make_obstacles(**{kind: [(np.eye(3), np.zeros(3), np.asarray(dims)[:3 if kind == "boxes" else 2])]})
    for dx in (0.0, 1e-9, -1e-9):
        xx = jnp.asarray(x) + dx * jnp.asarray(normal)
        d, n = obstacle_sdf_and_normals(obs, xx)
        k = int(np.argmin(np.asarray(d)))
        assert float(d[k]) == pytest.approx(dx, abs=1e-12)
        np.testing.assert_allclose(np.asarray(n[k]), normal, atol=1e-12)
    d2, n2 = points_sdf_and_normals(obs, jnp.asarray(x)[None])
    k = int(np.argmin(np.asarray(d2[0])))
    np.testing.assert_allclose(np.asarray(n2[0, k]), normal, atol=1e-12)


@pytest.mark.parametrize("kind, dims, x", [
    ("boxes", (0.1, 0.1, 0.1), (0.1, 0.1, 0.05)),  # on an edge
    ("boxes", (0.1, 0.1, 0.1), (0.1, -0.1, 0.1)),  # on a corner
    ("boxes", (0.1, 0.1, 0.1), (0.02, 0.02, 0.0)),  # inside, equidistant from two faces
    ("cylinders", (0.1, 0.1, 0.0), (0.1, 0.0, 0.1)),  # on the rim
])
def test_normal_at_a_tie_is_unit_and_the_analytic_one(kind, dims, x):
    """Where two faces are equally near (edges, corners, rims, interior medial points) ``jnp.max``
    shared its derivative among them: the autodiff normal was 0.71 (0.58) long, and ``jax.grad``
    of the field potential that much short of the analytic gradient. Now one face takes it, the
    one the structure-of-arrays normals pick, and the two field gradients agree."""
    from redman_jax._fields import points_sdf_and_normals

    obs = make_obstacles(**{kind: [(np.eye(3), np.zeros(3), np.asarray(dims)[:3 if kind == "boxes" else 2])]})
    xx = jnp.asarray(x)
    _, n = obstacle_sdf_and_normals(obs, xx)
    _, n2 = points_sdf_and_normals(obs, xx[None])
    np.testing.assert_allclose(np.linalg.norm(np.asarray(n[0])), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(n[0]), np.asarray(n2[0, 0]), atol=1e-12)
    g_ad = jax.grad(lambda y: obstacle_field_potential(obs, y, 0.05, 0.75))(xx)
    g = obstacle_field_gradient(obs, xx, 0.05, 0.75)
    np.testing.assert_allclose(np.asarray(g_ad), np.asarray(g), rtol=1e-9)


@pytest.mark.parametrize("kind", ["spheres", "boxes", "cylinders"])
def test_clamp_inside_obstacle_gives_finite_outward_force(kind):
    R = _rot(4)
    c = np.array([0.2, 0.1, 0.7])
    dims = {"spheres": [0.1], "boxes": [0.1, 0.08, 0.12], "cylinders": [0.1, 0.12]}[kind]
    obs = make_obstacles(**{kind: [(R, c, dims)]}, capacities=(2, 3, 2))
    a, D, eps = 0.05, 0.75, 1e-3
    x = jnp.asarray(c + R @ np.array([0.04, 0.01, -0.02]))  # inside, off every sdf ridge
    slot = {"spheres": 0, "boxes": 2, "cylinders": 5}[kind]
    d, n = jax.jit(obstacle_sdf_and_normals)(obs, x)
    d, n = d[slot], n[slot]
    assert d < 0
    g = _ofg_v(obs, x[None], a, D, "minus")[0]
    assert np.all(np.isfinite(g)) and np.linalg.norm(g) > 0
    # magnitude of V'(eps), along the unclamped sdf gradient; the force -g points outward (+n)
    np.testing.assert_allclose(g, obstacle_potential_dr(eps, a, D) * n, rtol=1e-12)
    assert float(-g @ n) > 0
    # jax.grad of the clamped potential gives the same force (custom JVP), not zero
    np.testing.assert_allclose(_ofp_grad_v(obs, x[None], a, D, "minus")[0], g, rtol=1e-12)
    # Hessian: finite; equals the derivative of the gradient (no radial term inside)
    params = FieldParams(a=a, D=D)
    zero_buf = (jnp.zeros((3, 3)), jnp.zeros(3, bool))
    H = _th_v(x[None], x + 1.0, obs, *zero_buf, params)
    assert np.all(np.isfinite(H))
    fd = _fd_points(lambda X: _tg_v(X, x + 1.0, obs, *zero_buf, params), x[None], eps=1e-7)
    # round-off of a difference of two gradients of size |g| over 2 eps, with margin 10
    noise = 10 * np.linalg.norm(g) * np.finfo(float).eps / 1e-7
    np.testing.assert_allclose(H, fd, rtol=1e-5, atol=1e-5 * np.abs(H).max() + noise)


def test_potential_derivatives_in_its_parameters_match_finite_differences():
    """d/d(a, D, clamp) of the obstacle potential, inside (the clamp holds: the value is V_o(clamp))
    and outside an obstacle: the clamp's derivative was left 0 (central differences: -1.5e11 at
    clamp 1e-3, -77 at 0.2, for a point 5 cm inside a sphere)."""
    R = _rot(4)
    c = np.array([0.2, 0.1, 0.7])
    obs = make_obstacles(spheres=[(R, c, [0.1])], capacities=(2, 3, 2))
    f = jax.jit(lambda x, a, D, eps: obstacle_field_potential(obs, x, a, D, "minus", eps))
    grad = jax.jit(jax.grad(lambda a, D, eps, x: obstacle_field_potential(obs, x, a, D, "minus", eps),
                            argnums=(0, 1, 2)))
    for x, eps in [(c + np.array([0.0, 0.0, 0.05]), 0.2), (c + np.array([0.0, 0.0, 0.05]), 0.01),
                   (c + np.array([0.0, 0.3, 0.0]), 0.01)]:
        x = jnp.asarray(x)
        theta = np.array([0.05, 0.75, eps])
        ad = np.array([float(g) for g in grad(*theta, x)])
        fd = np.zeros(3)
        for i in range(3):
            h = 1e-6 * theta[i]
            up, dn = theta.copy(), theta.copy()
            up[i] += h
            dn[i] -= h
            fd[i] = (float(f(x, *up)) - float(f(x, *dn))) / (2 * h)
        np.testing.assert_allclose(ad, fd, rtol=1e-6)
    assert ad[2] == 0.0  # outside: the clamp does not enter


def _field_inputs():
    obs = _scene()  # capacities (2, 3, 2); buffers of 3 everywhere, so the jitted helpers compile once
    goal = jnp.array([0.3, 0.3, 0.9])
    vp = jnp.array([[0.1, 0.2, 0.8], [0.25, 0.1, 0.7], [9.0, 9.0, 9.0]])
    vm = jnp.array([True, True, False])
    return obs, goal, vp, vm


@pytest.mark.parametrize("form", ["minus", "plus"])
def test_total_gradient_and_hessian(form, rng):
    obs, goal, vp, vm = _field_inputs()
    params = FieldParams(form=form)
    xs = _outside_points(obs, rng, 12, dmax=0.4)
    # stay off the virtual-obstacle range edge d_v = 0.25 where the gradient jumps
    rho = np.linalg.norm(xs[:, None, :] - np.asarray(vp)[None], axis=-1)
    xs = jnp.asarray(xs[np.all(np.abs(rho - 0.25) > 0.01, axis=1)][:6])
    g = _tg_v(xs, goal, obs, vp, vm, params)
    np.testing.assert_allclose(_tgrad_v(xs, goal, obs, vp, vm, params), g, rtol=1e-12, atol=1e-12)
    H = np.asarray(_th_v(xs, goal, obs, vp, vm, params))
    fd = _fd_points(lambda X: _tg_v(X, goal, obs, vp, vm, params), xs)
    for Hi, fdi in zip(H, fd):
        np.testing.assert_allclose(Hi, fdi, rtol=1e-6, atol=1e-6 * np.abs(Hi).max())
        np.testing.assert_allclose(Hi, Hi.T, rtol=1e-12, atol=1e-12 * np.abs(Hi).max())
    if form == "minus":  # one form suffices for jax.hessian through the custom JVP (slow compile)
        np.testing.assert_allclose(H, _thess_v(xs, goal, obs, vp, vm, params), rtol=1e-10,
                                   atol=1e-10 * np.abs(H).max())


def _empty():
    return make_obstacles(capacities=(2, 3, 2))  # same structure as _scene(): no recompilation


@pytest.mark.parametrize("slots", ["masked", "none"])
def test_goal_only_field_is_exact_quadratic(slots):
    """Only the goal's quadratic: every slot masked, or a set without any slot (``make_obstacles()``,
    whose gradient, Hessian and guidance raised "need at least one array to concatenate")."""
    obs = _empty() if slots == "masked" else make_obstacles()
    goal = jnp.array([0.2, -0.1, 0.5])
    xs = jnp.array([[0.7, 0.3, 0.2], [-0.4, 0.1, 1.3]])
    vp, vm = jnp.zeros((3, 3)), jnp.zeros(3, bool)
    p = FieldParams()
    np.testing.assert_allclose(_tp_v(xs, goal, obs, vp, vm, p), np.sum((xs - goal) ** 2, -1))
    g = _tg_v(xs, goal, obs, vp, vm, p)
    H = _th_v(xs, goal, obs, vp, vm, p)
    np.testing.assert_allclose(g, 2 * (xs - goal))
    np.testing.assert_allclose(H, np.broadcast_to(2 * np.eye(3), H.shape), atol=1e-15)
    # a Newton step (3.24) lands exactly on the goal
    xmin = xs - jnp.linalg.solve(H, g[..., None])[..., 0]
    np.testing.assert_allclose(xmin, np.broadcast_to(goal, xs.shape), atol=1e-15)
    v = jax.vmap(guidance_velocity, in_axes=(0, None, None, None, None, None))(xs, goal, obs, vp, vm, p)
    assert np.all(np.isfinite(np.asarray(v)))
    d, n = points_sdf_and_normals(obs, xs)
    K = sum(obs.capacities)
    assert d.shape == (2, K) and n.shape == (2, K, 3)


_vg_v = jax.jit(jax.vmap(virtual_gradient, in_axes=(0, None, None, None, None)))
_vp_v = jax.jit(jax.vmap(virtual_potential, in_axes=(0, None, None, None, None)))


def test_virtual_obstacle_gradient_matches_derivative_with_constant_amplitude():
    goal = jnp.array([0.5, 0.0, 0.8])
    xv = jnp.array([[0.1, 0.1, 0.9], [0.0, 0.0, 0.0], [0.3, 0.3, 0.3]])
    vm = jnp.array([True, False, False])
    x0 = np.array([0.2, 0.05, 0.95])  # rho ~ 0.12 < d_v
    p = FieldParams()
    A0 = 0.1 * np.sum((x0 - np.asarray(goal)) ** 2)

    def vv_fixed_amp(X):  # 3.25 with A frozen at its value at x0 (NumPy, independent)
        rho = np.linalg.norm(np.asarray(X) - np.asarray(xv[0]), axis=-1)
        return A0 * (1 / (rho + 1) - 1 / (0.25 + 1))

    g = np.asarray(_vg_v(jnp.asarray(x0[None]), goal, xv, vm, p))[0]
    np.testing.assert_allclose(g, _fd_points(vv_fixed_amp, x0[None])[0], rtol=1e-7)
    # 3.26 corrected (E14): -A (x - x_v) / (rho (rho + 1)^2)
    d = x0 - np.asarray(xv[0])
    rho = np.linalg.norm(d)
    np.testing.assert_allclose(g, -A0 * d / (rho * (rho + 1) ** 2), rtol=1e-12)
    # amp_exact: the full derivative of A(x) phi(rho)
    pe = FieldParams(amp_exact=True)
    fd_full = _fd_points(lambda X: _vp_v(X, goal, xv, vm, pe), x0[None])[0]
    np.testing.assert_allclose(_vg_v(jnp.asarray(x0[None]), goal, xv, vm, pe)[0], fd_full, rtol=1e-7)
    # "site" amplitude: A_j from the obstacle's own distance to the goal; zero for a site at the goal
    ps = FieldParams(vo_amp="site")
    xv2 = xv.at[1].set(goal)
    vm2 = jnp.array([True, True, False])
    fd_site = _fd_points(lambda X: _vp_v(X, goal, xv2, vm2, ps), x0[None])[0]
    np.testing.assert_allclose(_vg_v(jnp.asarray(x0[None]), goal, xv2, vm2, ps)[0], fd_site, rtol=1e-7)
    only_goal_site = jnp.array([False, True, False])
    at_goal = _vg_v((goal + 0.01)[None], goal, xv2, only_goal_site, ps)
    np.testing.assert_array_equal(at_goal, np.zeros((1, 3)))
    # on top of a virtual obstacle: finite (rho floor) and zero; finite Jacobian
    on = _vg_v(xv[:1], goal, xv, vm, p)
    assert np.all(np.isfinite(on)) and np.allclose(on, 0)
    assert np.all(np.isfinite(jax.jit(jax.jacfwd(virtual_gradient))(xv[0], goal, xv, vm, p)))
    # out of range (rho > d_v) and masked slots contribute nothing
    far = jnp.asarray(x0) + jnp.array([0.5, 0.0, 0.0])
    np.testing.assert_array_equal(_vg_v(far[None], goal, xv, vm, p), np.zeros((1, 3)))


_gv_v = jax.jit(jax.vmap(guidance_velocity, in_axes=_P + (None, None)))


def test_guidance_velocity_magnitude_and_direction():
    obs, goal, vp, vm = _field_inputs()
    p = FieldParams()
    x = jnp.array([[0.0, -0.3, 1.0]])
    v = np.asarray(_gv_v(x, goal, obs, vp, vm, p, 0.5, 0.1))[0]
    g = np.asarray(_tg_v(x, goal, obs, vp, vm, p))[0]
    dist = float(jnp.linalg.norm(x[0] - goal))
    # |v| = a tanh(|x - x_g| / b) |g| / (|g| + 1e-9): relative deviation 1e-9 / |g|
    np.testing.assert_allclose(np.linalg.norm(v), 0.5 * np.tanh(dist / 0.1),
                               rtol=2e-9 / np.linalg.norm(g))
    np.testing.assert_allclose(v / np.linalg.norm(v), -g / np.linalg.norm(g), rtol=1e-12)
    # empty scene: straight to the goal, slowing within b of it, zero (not NaN) at the goal
    empty = _empty()
    offs = np.array([0.5, 0.02])
    xs = goal + jnp.asarray(offs)[:, None] * jnp.array([1.0, 0.0, 0.0])
    vv = _gv_v(jnp.concatenate([xs, goal[None]]), goal, empty, vp, vm * False, p, 0.5, 0.1)
    expect = 0.5 * np.tanh(offs / 0.1)
    g_norm = 2 * offs  # |g| = 2 |x - x_g|
    np.testing.assert_allclose(-vv[:2, 0], expect * g_norm / (g_norm + 1e-9), rtol=1e-12)
    np.testing.assert_array_equal(vv[:2, 1:], 0.0)
    assert np.all(vv[2] == 0)


def test_points_and_scenario_batches(rng):
    obs, goal, vp, vm = _field_inputs()
    p = FieldParams()
    xs = jnp.asarray(_outside_points(obs, rng, 5))
    # two scenarios with different obstacle counts, stacked (padding to common capacities)
    other = make_obstacles(spheres=[(np.eye(3), [0.0, 0.0, 0.5], [0.1])], capacities=(2, 3, 2))
    stacked = stack_obstacles([obs, other])
    goals = jnp.stack([goal, goal + 0.1])
    G = total_gradient_batch(jnp.stack([xs, xs]), goals, stacked, jnp.stack([vp, vp]),
                             jnp.stack([vm, vm]), p)
    V = total_potential_batch(jnp.stack([xs, xs]), goals, stacked, jnp.stack([vp, vp]),
                              jnp.stack([vm, vm]), p)
    np.testing.assert_allclose(G[0], _tg_v(xs, goal, obs, vp, vm, p), rtol=1e-13)
    np.testing.assert_allclose(G[1], _tg_v(xs, goals[1], other, vp, vm, p), rtol=1e-13)
    np.testing.assert_allclose(V[1], _tp_v(xs, goals[1], other, vp, vm, p), rtol=1e-13)


def test_float32_runs():
    obs, goal, vp, vm = _field_inputs()
    f32 = lambda t: cast_floating(t, jnp.float32)
    x = jnp.array([[0.0, -0.3, 1.0]])
    p = FieldParams()
    g64 = _tg_v(x, goal, obs, vp, vm, p)
    g32 = _tg_v(*f32((x, goal, obs, vp, vm, p)))
    H32 = _th_v(*f32((x, goal, obs, vp, vm, p)))
    assert g32.dtype == jnp.float32 and H32.dtype == jnp.float32
    assert np.all(np.isfinite(H32))
    np.testing.assert_allclose(g32, g64, rtol=1e-4)


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="form"):
        FieldParams(form="exp")
    with pytest.raises(ValueError, match="vo_amp"):
        FieldParams(vo_amp="goal")
    with pytest.raises(ValueError, match="FieldParams.D"):
        FieldParams(D=0.0)
    with pytest.raises(ValueError, match="FieldParams.a"):
        FieldParams(a=-1.0)
    with pytest.raises(ValueError, match="FieldParams.amp"):
        FieldParams(amp=float("nan"))
    with pytest.raises(ValueError, match="form"):
        obstacle_field_gradient(_scene(), jnp.zeros(3), 0.05, 0.75, form="minus2")


def test_obstacle_sizes_are_checked_naming_the_entry():
    """Too many sizes named the entry nowhere (a NumPy broadcasting error); too few or bad ones did."""
    with pytest.raises(ValueError, match=r"boxes\[0\]\.dims: at most 3"):
        make_obstacles(boxes=[(np.eye(3), np.zeros(3), [0.1, 0.1, 0.1, 0.1])])
    with pytest.raises(ValueError, match=r"cylinders\[1\]\.dims"):
        make_obstacles(cylinders=[(np.eye(3), np.zeros(3), [0.1, 0.2]), (np.eye(3), np.zeros(3), [0.1])])
