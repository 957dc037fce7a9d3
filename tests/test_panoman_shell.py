"""PanoMan's discrete-shell energy (bodyprior.panoman.shell_residuals / shell_energy)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from helpers import assert_jvp_matches_fd

import bodyprior as bp
from bodyprior import panoman as pm


@pytest.fixture(scope="module")
def mesh():
    m = trimesh.creation.icosphere(2)
    v = np.asarray(m.vertices) * np.array([1.0, 0.7, 1.3])
    return v, bp.Topology.from_faces(np.asarray(m.faces), v.shape[0])


def test_zero_at_integrable_targets_and_rigid_invariance(mesh):
    v, top = mesh
    rng = np.random.default_rng(0)
    x = v + 0.05 * rng.standard_normal(v.shape)
    rla = pm.rla_encode(x, v, top)
    R = np.asarray(bp.axis_angle_to_matrix(np.array([0.2, 0.9, -0.4])))
    for bending in ("fb", "printed"):
        s, b = pm.shell_residuals(x @ R.T + 0.3, v, rla, top, bending=bending)
        assert float(jnp.abs(s).max()) < 1e-12 and float(jnp.abs(b).max()) < 1e-12
    assert float(pm.shell_energy(v, v, rla, top)) > 0


def test_terms_as_printed(mesh):
    """Stretch = l/l_r − 1 − l̂*; bending weight l/√A (fb) or l/A (printed), A the two triangles'
    area (no 1/3); stiffness scales the bending energy."""
    v, top = mesh
    rng = np.random.default_rng(1)
    x = v + 0.02 * rng.standard_normal(v.shape)
    zero = pm.RLA(jnp.zeros(top.n_edges), jnp.zeros(top.n_edges))
    s, b_fb = pm.shell_residuals(x, v, zero, top)
    _, b_pr = pm.shell_residuals(x, v, zero, top, bending="printed")
    e = np.asarray(top.edges)
    lr = np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1)
    lx = np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
    np.testing.assert_allclose(s, lx / lr - 1, atol=1e-12)
    area = np.asarray(bp.face_areas(v, top.faces))
    ef = np.asarray(top.edge_faces)
    a_e = area[ef[:, 0]] + area[ef[:, 1]]
    d = np.asarray(
        pm.wrap_angle(pm.interior_dihedral_angles(x, top) - pm.interior_dihedral_angles(v, top))
    )
    np.testing.assert_allclose(b_fb, lr / np.sqrt(a_e) * d, atol=1e-12)
    np.testing.assert_allclose(b_pr, lr / a_e * d, atol=1e-10)
    e1 = pm.shell_energy(x, v, zero, top) - jnp.sum(s**2)
    e4 = pm.shell_energy(x, v, zero, top, bending_stiffness=4.0) - jnp.sum(s**2)
    assert float(e4) == pytest.approx(4 * float(e1), rel=1e-10)


def test_gradients_match_finite_differences(mesh, getkey):
    v, top = mesh
    rng = np.random.default_rng(2)
    x = jnp.asarray(v + 0.03 * rng.standard_normal(v.shape))
    rla = pm.rla_encode(v * 1.05, v, top)
    assert_jvp_matches_fd(lambda y: pm.shell_energy(y, v, rla, top), x, getkey, rtol=1e-5)
    # the Gauss–Newton Jacobian of the residuals, against central differences
    f = lambda y: jnp.concatenate(pm.shell_residuals(y, v, rla, top))  # noqa: E731
    assert_jvp_matches_fd(f, x, getkey, rtol=1e-5)
    # and through the rest shape (shape parameters are unknowns too)
    assert_jvp_matches_fd(lambda r: pm.shell_energy(x, r, rla, top), jnp.asarray(v), getkey,
                          rtol=1e-5)  # fmt: skip


def test_nan_free_at_flat_folded_and_zero_area_hinges():
    # a flat quad strip, one wing folded flat onto the other, one zero-area triangle
    verts = np.array(
        [[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [2, 0, 0], [1.5, 1, 0]], float
    )
    faces = np.array([[0, 1, 2], [1, 0, 3], [1, 4, 5], [2, 1, 5]])
    top = bp.Topology.from_faces(faces, 6)
    zero = pm.RLA(jnp.zeros(top.n_edges), jnp.zeros(top.n_edges))
    folded = verts.copy()
    folded[3] = [0.5, 1, 1e-12]  # wing 2 folded onto wing 1 (ψ → 0)
    degenerate = verts.copy()
    degenerate[5] = [1.5, 0, 0]  # triangle (1, 4, 5) collinear
    for x in (verts, folded, degenerate):
        for r in (verts, degenerate):
            g = jax.grad(lambda y: pm.shell_energy(y, r, zero, top))(jnp.asarray(x))
            assert bool(jnp.all(jnp.isfinite(g)))
            s, b = pm.shell_residuals(x, r, zero, top)
            assert bool(jnp.all(jnp.isfinite(s)) & jnp.all(jnp.isfinite(b)))
    # the folded hinge is guarded: zero bending residual although its angle is off by ~π
    hinge = int(np.flatnonzero(np.all(np.sort(np.asarray(top.edges), 1) == [0, 1], axis=1))[0])
    rla = pm.rla_encode(folded, verts, top)
    assert abs(float(rla.angles[hinge])) > math.pi - 0.1
    _, b = pm.shell_residuals(verts, verts, rla, top)
    assert float(b[hinge]) == 0.0


def test_no_recompile_and_vmap(mesh):
    v, top = mesh
    f = jax.jit(lambda y, r: pm.shell_energy(y, v, r, top))
    rng = np.random.default_rng(3)
    for _ in range(3):
        x = jnp.asarray(v + 0.01 * rng.standard_normal(v.shape))
        f(x, pm.rla_encode(x * 1.01, v, top))
    assert f._cache_size() == 1
    xs = jnp.asarray(v + 0.01 * rng.standard_normal((4,) + v.shape))
    rlas = jax.vmap(lambda y: pm.rla_encode(y, v, top))(xs)
    e = jax.vmap(lambda y, r: pm.shell_energy(y, v, r, top))(xs, rlas)
    np.testing.assert_allclose(e, 0.0, atol=1e-20)


@pytest.mark.bad_input
def test_bad_input(mesh):
    v, top = mesh
    rla = pm.rla_encode(v, v, top)
    with pytest.raises(ValueError, match="`bending`"):
        pm.shell_residuals(v, v, rla, top, bending="x")
    with pytest.raises(ValueError, match="`bending_stiffness`"):
        pm.shell_residuals(v, v, rla, top, bending_stiffness=-1.0)
    with pytest.raises(ValueError, match="`rest` must have shape"):
        pm.shell_residuals(v, v[:5], rla, top)
    with pytest.raises(ValueError, match="`fold_eps`"):
        pm.shell_energy(v, v, rla, top, fold_eps=0.0)
