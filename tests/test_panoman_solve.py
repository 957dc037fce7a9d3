"""PanoMan's shell solver (bodyprior.panoman.shell_solve): recovery, constraints, no recompile."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import bodyprior as bp
from bodyprior import panoman as pm

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def mesh():
    m = trimesh.creation.icosphere(3)
    v = np.asarray(m.vertices) * np.array([1.0, 0.7, 1.3])
    top = bp.Topology.from_faces(np.asarray(m.faces), v.shape[0])
    x = v.copy()
    x[:, 2] += 0.3 * np.sin(2 * x[:, 0])
    return v, x, top, pm.prepare_shell_solver(top)


class _Blend(eqx.Module):
    basis: jax.Array  # (K, 2E)

    def __call__(self, p):
        return pm.RLA.from_concat(p @ self.basis)


def test_handles_recover_known_body_vertices_only(mesh):
    v, x, top, solver = mesh
    rla = pm.rla_encode(x, v, top)
    h = np.random.default_rng(0).choice(v.shape[0], 8, replace=False)
    cons = pm.shell_constraints(handles=(h, x[h]))
    targets = _Blend(rla.concat()[None])
    sol = pm.shell_solve(lambda p: targets(jnp.ones(1)), v, (), v, top, cons, solver=solver)
    assert bool(sol.stats["converged"])
    assert float(jnp.abs(sol.value.vertices - x).max()) < 1e-9
    assert float(sol.value.energy) < 1e-20


def test_joint_params_and_vertices_recovered(mesh):
    """Targets from a callable of parameters: from p = 0 and the rest mesh, handles taken from a
    known body realised by p* = (1, 0) give back both the body and p*."""
    v, x, top, solver = mesh
    y = v * 1.1 + 0.05 * np.sin(3 * v)
    basis = jnp.stack([pm.rla_encode(x, v, top).concat(), pm.rla_encode(y, v, top).concat()])
    h = np.random.default_rng(1).choice(v.shape[0], 8, replace=False)
    cons = pm.shell_constraints(handles=(h, x[h]))
    sol = pm.shell_solve(_Blend(basis), v, jnp.zeros(2), v, top, cons, solver=solver)
    np.testing.assert_allclose(sol.value.params, [1.0, 0.0], atol=1e-8)
    assert float(jnp.abs(sol.value.vertices - x).max()) < 1e-8
    # Editing constraints (eqs. 9-10) pull a parameter to its value against the handles.
    cons2 = pm.shell_constraints(handles=(h, x[h]), params=(np.array([1]), np.array([0.5])))
    sol2 = pm.shell_solve(_Blend(basis), v, jnp.zeros(2), v, top, cons2, solver=solver)
    assert float(sol2.value.params[1]) > 0.05
    assert float(sol2.value.constraint_energy) > 0


def test_joints_and_surface_constraints_and_no_recompile(mesh):
    v, x, top, solver = mesh
    rla = pm.rla_encode(x, v, top)
    targets = _Blend(rla.concat()[None])
    rng = np.random.default_rng(2)
    idx = rng.choice(v.shape[0], (3, 6), replace=False)
    coef = np.full((3, 6), 1 / 6)
    joints = (idx, coef, np.einsum("jm,jmd->jd", coef, x[idx]))
    f = rng.choice(top.n_faces, 40, replace=False)
    bary = rng.dirichlet(np.ones(3), 40)
    pts = np.einsum("sa,sad->sd", bary, x[np.asarray(top.faces)[f]])
    nrm = np.asarray(bp.face_normals(x, top.faces))[f]
    h = np.array([0, 5])
    cons = pm.shell_constraints(handles=(h, x[h]), joints=joints, surface=(f, bary, pts, nrm))
    before = pm._solve._solve_jit._cached._cache_size()
    sol = pm.shell_solve(lambda p: targets(jnp.ones(1)), v, (), v, top, cons, solver=solver)
    assert float(jnp.abs(sol.value.vertices - x).max()) < 1e-7
    # New constraint values, same sizes: no new compilation.
    cons_b = pm.shell_constraints(
        handles=(h, x[h] + 0.01), joints=joints, surface=(f, bary, pts, nrm)
    )
    fn = sol  # keep the first result alive
    del fn
    tg = lambda p: targets(jnp.ones(1))  # noqa: E731
    pm.shell_solve(tg, v, (), v, top, cons, solver=solver, max_steps=2)
    n = pm._solve._solve_jit._cached._cache_size()
    pm.shell_solve(tg, v, (), v, top, cons_b, solver=solver, max_steps=3, weight=1e5, ftol=0.0)
    assert pm._solve._solve_jit._cached._cache_size() == n  # new values, budget, weight
    assert n >= before


def _handles_and_surface_points(mesh, rng):
    """8 handle vertices and 10 surface points (faces, barycentrics, points, normals) of `x`."""
    v, x, top, _ = mesh
    h = rng.choice(v.shape[0], 8, replace=False)
    f = rng.choice(top.n_faces, 10, replace=False)
    bary = rng.dirichlet(np.ones(3), 10)
    pts = np.einsum("sa,sad->sd", bary, x[np.asarray(top.faces)[f]])
    return h, f, bary, pts, np.asarray(bp.face_normals(x, top.faces))[f]


def test_gauss_newton_jacobian_and_exact_preconditioner(mesh):
    """The residual the LM linearises (shell rows + constraint rows) has JVPs equal to central
    differences in float64; without parameters the sparse LDLᵀ preconditioner (shell, handle,
    surface and joint rows: the joint regressor's couplings extend its pattern) is the exact
    Gauss–Newton matrix, so every inner PCG solve ends in one step."""
    v, x, top, solver = mesh
    y = v * 1.1 + 0.05 * np.sin(3 * v)
    basis = jnp.stack([pm.rla_encode(x, v, top).concat(), pm.rla_encode(y, v, top).concat()])
    rng = np.random.default_rng(3)
    h, f, bary, pts, nrm = _handles_and_surface_points(mesh, rng)
    cons = pm.shell_constraints(
        handles=(h, x[h]), params=(np.array([0]), np.array([0.3])), surface=(f, bary, pts, nrm)
    )
    cfg = pm._solve._Config("fb", *map(jnp.asarray, (1.0, 0.1, 1e3, 1, 0.0, 1e-8, 1e-4)), 10)
    V0 = jnp.asarray(0.5 * (v + x))
    p0 = jnp.array([0.4, 0.2])

    def resid(u):
        V, p = u[:-2].reshape(-1, 3), u[-2:]
        return jnp.concatenate(
            pm._solve._parts(V, p, _Blend(basis), v, cons, top, cfg, lambda q: q)
        )

    u = jnp.concatenate([V0.ravel(), p0])
    for k in range(3):
        d = jnp.asarray(rng.standard_normal(u.shape))
        jv = jax.jvp(resid, (u,), (d,))[1]
        eps = 1e-6
        fd = (resid(u + eps * d) - resid(u - eps * d)) / (2 * eps)
        np.testing.assert_allclose(jv, fd, rtol=1e-6, atol=1e-6 * float(jnp.abs(jv).max()))
    rla = pm.rla_encode(x, v, top)
    idx = rng.choice(v.shape[0], (3, 7), replace=False)
    coef = rng.dirichlet(np.ones(7), 3)
    coef[0, 2] = 0.0  # a zero entry: not part of the pattern
    joints = (idx, coef, np.einsum("jm,jmd->jd", coef, x[idx]))
    vcons = pm.shell_constraints(handles=(h, x[h]), surface=(f, bary, pts, nrm), joints=joints)
    sol = pm.shell_solve(lambda p: rla, v, (), V0, top, vcons, solver=solver, max_steps=4, ftol=0.0)
    assert int(sol.stats["cg_steps"]) <= int(sol.stats["steps"]), sol.stats
    assert float(jnp.abs(sol.value.vertices - x).max()) < 1e-5  # 4 Gauss-Newton steps


def test_free_vertices_and_the_region_sub_mesh_solve_the_same_problem(mesh):
    """Fixed vertices stay where they start; a solve on a region's sub-mesh (the faces within
    two rings of its free vertices, `fit_panoman`'s face and hand blocks) gives the vertices of
    the masked whole-mesh solve: every residual that reads a free vertex is on the sub-mesh."""
    from bodyprior.panoman._fit import _make_region

    v, x, top, solver = mesh
    e = np.asarray(top.edges)
    region = _make_region(top, v[e].mean(1)[:, 0] > 0.6, rings=1)
    sv, free = np.asarray(region.vertices), np.asarray(region.free)
    assert free.sum() < sv.size < top.n_vertices
    full_free = np.zeros(top.n_vertices, bool)
    full_free[sv[free]] = True
    rla = pm.rla_encode(x, v, top)
    h = sv[free][:: max(1, int(free.sum()) // 6)]
    opts = dict(max_steps=4, ftol=0.0)
    whole = pm.shell_solve(lambda p: rla, v, (), v, top, pm.shell_constraints(handles=(h, x[h])),
                           solver=solver, free=full_free, **opts).value.vertices  # fmt: skip
    np.testing.assert_array_equal(np.asarray(whole)[~full_free], v[~full_free])
    assert float(jnp.abs(whole[full_free] - v[full_free]).max()) > 1e-2
    sub_rla = pm.RLA(rla.lengths[region.edges], rla.angles[region.edges])
    hs = np.asarray(region.vertex_map)[h]
    sub = pm.shell_solve(lambda p: sub_rla, v[sv], (), v[sv], region.topology,
                         pm.shell_constraints(handles=(hs, x[h])), solver=region.solver,
                         free=free, **opts).value.vertices  # fmt: skip
    np.testing.assert_allclose(sub, np.asarray(whole)[sv], atol=1e-9)


@pytest.mark.bad_input
def test_free_bad_input(mesh):
    v, x, top, solver = mesh
    rla = pm.rla_encode(x, v, top)
    with pytest.raises(ValueError, match="free"):
        pm.shell_solve(lambda p: rla, v, (), v, top, solver=solver, free=np.ones(5, bool))
    with pytest.raises(ValueError, match="free"):
        pm.shell_solve(lambda p: rla, v, (), v, top, solver=solver, free=np.ones(v.shape[0]))


class _RestScaled(eqx.Module):
    rest: jax.Array

    def __call__(self, p):
        return self.rest * (1.0 + p["s"][0]) + p["s"][1] * jnp.sin(self.rest)


def _two_leaf_problem(mesh):
    """Targets reading the leaf `b` of the parameters, a rest mesh reading the leaf `s`."""
    v, x, top, _ = mesh
    y = v * 1.1 + 0.05 * np.sin(3 * v)
    basis = jnp.stack([pm.rla_encode(x, v, top).concat(), pm.rla_encode(y, v, top).concat()])
    blend = _Blend(basis)
    params0 = {"b": jnp.array([0.4, 0.2]), "s": jnp.array([0.05, 0.01])}
    return (lambda p: blend(p["b"])), _RestScaled(jnp.asarray(v)), params0


def test_parameter_gram_equals_the_dense_jacobian_gram(mesh):
    """The preconditioner's parameter block (targets read `b`, the rest mesh reads `s`, editing
    rows on both) equals `JᵀJ` of the whole residual's dense Jacobian over the parameters, and the
    static analysis finds the leaf the rest mesh reads."""
    v, x, top, solver = mesh
    targets, rest, params0 = _two_leaf_problem(mesh)
    assert pm._solve._leaves_read(rest, params0) == [False, True]
    h = np.random.default_rng(5).choice(v.shape[0], 8, replace=False)
    cons = pm.shell_constraints(handles=(h, x[h]), params=(np.array([0, 3, 3]), np.zeros(3)))
    cfg = pm._solve._Config("fb", *map(jnp.asarray, (1.0, 0.1, 1e3, 1, 0.0, 1e-8, 1e-4)), 10)
    from jax.flatten_util import ravel_pytree

    p0, unravel = ravel_pytree(params0)
    V0 = jnp.asarray(0.5 * (v + x))

    def resid(p):
        return jnp.concatenate(pm._solve._parts(V0, p, targets, rest, cons, top, cfg, unravel))

    @jax.jit
    def grams(p0, V0):
        J = jax.jacfwd(resid)(p0)
        G = pm._solve._param_gram(targets, rest, params0, p0, V0, cons, top, cfg, unravel)
        return G, J.T @ J

    G, ref = grams(p0, V0)
    np.testing.assert_allclose(G, ref, rtol=1e-10, atol=1e-10 * float(jnp.abs(G).max()))


@pytest.mark.parametrize("bending", ["fb", "printed"])
def test_explicit_jacobian_rows_equal_the_residuals_jacobian(mesh, bending):
    """The per-edge gradients `_jacobian_rows` (what the factorisation and the PCG's product
    read) equal the shell residuals' full Jacobian in the vertices, on a mesh with flat, folded
    and fold-guarded hinges, a degenerate (zero-length) edge and a boundary, and vanish
    outside each row's stencil."""
    v, x, top, _ = mesh
    # an open mesh (boundary edges) with a collapsed edge and a flattened fan
    faces = np.asarray(top.faces)[np.asarray(top.faces).min(1) > 3]
    used = np.unique(faces)
    remap = np.full(v.shape[0], -1)
    remap[used] = np.arange(used.size)
    topo = bp.Topology.from_faces(remap[faces], used.size)
    r, X = v[used], x[used].copy()
    e0 = np.asarray(topo.edges)[0]
    X[e0[1]] = X[e0[0]]  # zero-length edge
    X[:12, 2] = 0.0  # flattened fan: flat and folded hinges
    rla = pm.rla_encode(x[used], r, topo)
    rla = pm.RLA(rla.lengths, rla.angles.at[:5].set(3.1))  # fold-guarded targets
    args = (jnp.asarray(r), rla, topo, bending, 1.7, 0.1)
    J = jax.jacfwd(lambda V: jnp.concatenate(pm._shell._residuals(V, *args)))(jnp.asarray(X))
    lr_safe, coef, _ = pm._shell._shell_terms(*args)
    js, jb = pm._shell._jacobian_rows(jnp.asarray(X), lr_safe, coef, topo)
    E, nV = topo.n_edges, used.size
    st = np.asarray(pm.prepare_shell_solver(topo).stencils)
    ref_s = np.zeros((E, nV, 3))
    np.add.at(ref_s, (np.arange(E)[:, None], st[:, :2]), np.asarray(js).reshape(E, 2, 3))
    ref_b = np.zeros((E, nV, 3))
    np.add.at(ref_b, (np.arange(E)[:, None], st), np.asarray(jb).reshape(E, 4, 3))
    J = np.asarray(J)
    assert np.isfinite(J).all() and np.isfinite(np.asarray(jb)).all()
    scale = np.abs(J).max()
    np.testing.assert_allclose(ref_s, J[:E], atol=1e-10 * scale)
    np.testing.assert_allclose(ref_b, J[E:], atol=1e-10 * scale)
    assert np.abs(J[E:]).max(axis=(1, 2)).min() == 0.0  # guarded / boundary hinges: zero rows


def test_host_factor_reused_for_the_same_matrix_only(mesh):
    """After a rejected LM step (same vertices, more damping) the host returns the live
    factorisation of the same matrix instead of refactoring; any other matrix is factored anew,
    and each factorisation solves its own (damped) system."""
    v, x, top, solver = mesh
    host = solver.host
    E, nV = top.n_edges, v.shape[0]
    rng = np.random.default_rng(11)
    jb, js = rng.standard_normal((E, 12)), rng.standard_normal((E, 6))
    none = (np.zeros(0, np.int64), np.zeros((0, 3, 3)), np.ones(3 * nV),
            np.zeros((0, 1), np.int64), np.zeros((0, 1)))  # fmt: skip
    f1, d1 = host.factor(jb, js, *none, 1e-4)
    f2, d2 = host.factor(jb, js, *none, 1e-2)  # same matrix, more damping: reused
    f3, _ = host.factor(jb * 1.01, js, *none, 1e-4)  # another matrix: a new factorisation
    assert f2 == f1 and f3 != f1
    np.testing.assert_array_equal(d1, d2)
    pat, data = host.assemble(jb, js, *none)
    A = host.matrix(pat, data).toarray()  # upper triangle
    A = A + A.T - np.diag(np.diag(A))
    b = rng.standard_normal(3 * nV)
    A1 = A + np.diag(1e-4 * np.diag(A) + 1e-12 * np.diag(A).mean())
    np.testing.assert_allclose(A1 @ host.solve(f1, b), b, atol=1e-6 * np.abs(b).max())


def test_gauss_newton_product_from_explicit_rows_equals_the_linearised_one(mesh):
    """The PCG's product `JᵀJ z` built from the shell rows' explicit vertex Jacobian rows (the
    ones the colouring JVPs extract) equals the product through the whole linearised residual,
    with parameters the targets and the rest mesh read and every constraint type."""
    v, x, top, solver = mesh
    targets, rest, params0 = _two_leaf_problem(mesh)
    rng = np.random.default_rng(7)
    h, f, bary, pts, nrm = _handles_and_surface_points(mesh, rng)
    ji = rng.choice(v.shape[0], (3, 5), replace=False)
    jc = rng.dirichlet(np.ones(5), 3)
    cons = pm.shell_constraints(
        handles=(h, x[h]), params=(np.array([0, 3]), np.zeros(2)), surface=(f, bary, pts, nrm),
        joints=(ji, jc, rng.normal(size=(3, 3))),
    )  # fmt: skip
    cfg = pm._solve._Config("fb", *map(jnp.asarray, (1.0, 0.1, 1e3, 1, 0.0, 1e-8, 1e-4)), 10)
    from jax.flatten_util import ravel_pytree

    p0, unravel = ravel_pytree(params0)
    nV = v.shape[0]
    V0 = jnp.asarray(0.5 * (v + x))

    def parts(V, p):
        return pm._solve._parts(V, p, targets, rest, cons, top, cfg, unravel)

    def resid(u):
        return jnp.concatenate(parts(u[: 3 * nV].reshape(nV, 3), u[3 * nV :]))

    u = jnp.concatenate([V0.ravel(), p0])
    E = top.n_edges
    st = np.asarray(solver.stencils)

    @jax.jit
    def both(u, z):  # (3, n) directions -> the two products, each (3, n)
        V = u[: 3 * nV].reshape(nV, 3)
        Js = jax.jacfwd(lambda V: jnp.concatenate(parts(V, p0)[:2]))(V)  # (2E, V, 3)
        js = Js[np.arange(E)[:, None], st[:, :2]].reshape(E, 6)
        jb = Js[E + np.arange(E)[:, None], st].reshape(E, 12)
        prod = pm._solve._gauss_newton_product(parts, u, nV, solver.stencils, jb, js)
        _, jvp = jax.linearize(resid, u)
        ref = jax.vmap(lambda z: jax.linear_transpose(jvp, u)(jvp(z))[0])(z)
        return jax.vmap(prod)(z), ref

    new_, ref = both(u, jnp.asarray(rng.standard_normal((3,) + u.shape)))
    np.testing.assert_allclose(new_, ref, rtol=1e-9, atol=1e-9 * float(jnp.abs(ref).max()))


def test_solve_nan_free_from_flat_and_degenerate_starts(mesh):
    """Starts with a collapsed (zero-area) fan and with a flattened mesh (folded hinges) stay
    finite and reach the target body."""
    v, x, top, solver = mesh
    rla = pm.rla_encode(x, v, top)
    h = np.random.default_rng(4).choice(v.shape[0], 12, replace=False)
    cons = pm.shell_constraints(handles=(h, x[h]))
    collapsed = x.copy()
    ring = np.asarray(top.one_ring[0])
    collapsed[ring[ring >= 0]] = collapsed[0]  # every face around vertex 0 has zero area
    flat = x * np.array([1.0, 1.0, 1e-9])  # every hinge folded flat or opened flat
    for start in (collapsed, flat):
        sol = pm.shell_solve(
            lambda p: rla, v, (), start, top, cons, solver=solver, max_steps=40, throw=False
        )
        assert bool(jnp.all(jnp.isfinite(sol.value.vertices))), "non-finite"
        assert float(sol.stats["energy"]) < float(sol.stats["energy0"])
    assert float(jnp.abs(sol.value.vertices - x).max()) < 1e-3


@pytest.mark.bad_input
def test_bad_input(mesh):
    v, x, top, solver = mesh
    rla = pm.rla_encode(x, v, top)
    with pytest.raises(ValueError, match="handles"):
        pm.shell_constraints(handles=(np.array([0, 1]), np.zeros((3, 3))))
    with pytest.raises(ValueError, match="vertices0"):
        pm.shell_solve(lambda p: rla, v, (), v[:-1], top, solver=solver)
    with pytest.raises(ValueError, match="handle_index"):
        cons = pm.shell_constraints(handles=(np.array([10**6]), np.zeros((1, 3))))
        pm.shell_solve(lambda p: rla, v, (), v, top, cons, solver=solver)
