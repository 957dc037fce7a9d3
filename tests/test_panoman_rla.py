"""PanoMan RLA features and the decoder g (bodyprior.panoman)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import bodyprior as bp
from bodyprior import panoman as pm


def _kabsch_err(x, y):
    x, y = np.asarray(x), np.asarray(y)
    sim = bp.umeyama(x, y, with_scale=False)
    return float(np.abs(np.asarray(sim.apply(x)) - y).max())


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(3)
    v = np.asarray(m.vertices) * np.array([1.0, 0.7, 1.3])
    top = bp.Topology.from_faces(np.asarray(m.faces), v.shape[0])
    return v, top


@pytest.fixture(scope="module")
def body():
    b = bp.load_default_body(rig="game_engine", facial_actions=True, dtype=np.float64)
    top = bp.Topology.from_faces(b.faces, b.template.shape[0])
    rest, _ = bp.evaluate(b, bp.phenotype_vector())
    dec = pm.prepare_decoder(rest, top)
    return b, top, np.asarray(rest), dec


# ------------------------------------------------------------------------------------------ RLA


def test_rla_conventions_and_rigid_invariance(sphere):
    v, top = sphere
    z = pm.rla_encode(v, v, top)
    assert np.all(np.asarray(z.lengths) == 0) and np.all(np.asarray(z.angles) == 0)
    psi = np.asarray(pm.interior_dihedral_angles(v, top))
    # a closed convex surface: every interior angle below π, equal to π − the signed bending angle
    assert np.all(psi < math.pi)
    np.testing.assert_allclose(psi, math.pi - np.asarray(bp.dihedral_angles(v, top)))
    rng = np.random.default_rng(0)
    x = v * (1 + 0.1 * rng.standard_normal(v.shape))
    r = pm.rla_encode(x, v, top)
    R = np.asarray(bp.axis_angle_to_matrix(np.array([0.3, -1.2, 0.5])))
    r2 = pm.rla_encode(x @ R.T + np.array([1.0, 2.0, 3.0]), v, top)
    np.testing.assert_allclose(r2.lengths, r.lengths, atol=1e-12)
    np.testing.assert_allclose(r2.angles, r.angles, atol=1e-12)
    e = np.asarray(top.edges)
    lx = np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
    lv = np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1)
    np.testing.assert_allclose(r.lengths, lx / lv - 1, rtol=1e-12)
    # the paper's sign: â = ψ − ψ_r = −(θ − θ_r) for bodyprior's signed bending angle θ
    dth = np.asarray(bp.dihedral_angles(x, top)) - np.asarray(bp.dihedral_angles(v, top))
    np.testing.assert_allclose(r.angles, pm.wrap_angle(-dth), atol=1e-12)
    np.testing.assert_allclose(pm.RLA.from_concat(r.concat()).angles, r.angles)


def test_wrap_angle():
    x = jnp.array([-7.0, -math.pi, -1.0, 0.0, 1.0, math.pi - 1e-9, math.pi, 7.0])
    w = np.asarray(pm.wrap_angle(x))
    assert np.all(w >= -math.pi) and np.all(w < math.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(np.asarray(x)), atol=1e-12)
    np.testing.assert_allclose(jax.vmap(jax.grad(pm.wrap_angle))(x), 1.0)


def test_unwrapping_through_a_fold():
    """A hinge folded from flat by 3.5 rad: a single mesh gives the wrapped value, the path the
    true one, and the fold mask marks it."""
    faces = np.array([[0, 1, 2], [1, 0, 3]])

    # an open two-triangle hinge along the x axis; rotate the second wing about it
    def wing(phi):
        return np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -np.cos(phi), np.sin(phi)]])

    top = bp.Topology.from_faces(faces, 4)
    hinge = int(np.flatnonzero(np.asarray(top.interior))[0])
    ref = wing(0.0)
    phi = 3.5
    x = wing(phi)
    wrapped = float(pm.rla_encode(x, ref, top).angles[hinge])
    path = np.stack([wing(p) for p in np.linspace(0, phi, 20)])
    unwrapped = float(pm.rla_encode_path(path, top).angles[hinge])
    assert abs(unwrapped) == pytest.approx(phi, abs=1e-9)
    assert abs(wrapped) == pytest.approx(2 * math.pi - phi, abs=1e-9)
    assert np.sign(wrapped) == -np.sign(unwrapped)
    # the straight vertex path between the two meshes is not the rotation: no claim there, but
    # unwrapping it must agree with the wrapped value modulo 2π
    lin = float(pm.rla_encode_unwrapped(x, ref, top, n_steps=64).angles[hinge])
    assert math.cos(lin) == pytest.approx(math.cos(wrapped), abs=1e-9)
    mask = np.asarray(pm.fold_mask(pm.rla_encode_path(path, top), ref, top, eps=0.2))
    assert mask[hinge]
    assert not np.asarray(pm.fold_mask(pm.rla_encode(wing(1.0), ref, top), ref, top))[hinge]


def test_facial_fold_edges_are_unwrapped(body):
    """eyeBlink folds eyelid edges past ±π (panoman_v2 §6.3): unwrapping along the blend-shape
    path differs from the wrapped difference there by 2π, and agrees elsewhere."""
    from bodyprior.assets._source import FACIAL_ACTION_LABELS

    b, top, rest, _ = body
    fa = np.zeros(52)
    fa[FACIAL_ACTION_LABELS.index("eyeBlinkLeft")] = 1.0
    face, _ = bp.evaluate(b, bp.phenotype_vector(), facial_actions=fa)
    w = np.asarray(pm.rla_encode(face, rest, top).angles)
    u = np.asarray(pm.rla_encode_unwrapped(face, rest, top).angles)
    diff = u - w
    assert np.abs(u).max() > math.pi  # real folds
    np.testing.assert_allclose(np.round(diff / (2 * math.pi)) * 2 * math.pi, diff, atol=1e-6)
    assert 1 <= np.sum(np.abs(diff) > 1) <= 50


@pytest.mark.bad_input
def test_rla_bad_input(sphere):
    v, top = sphere
    with pytest.raises(ValueError, match="`vertices` must have shape"):
        pm.rla_encode(v[:10], v, top)
    with pytest.raises(ValueError, match="`topology`"):
        pm.rla_encode(v, v, np.asarray(top.faces))
    with pytest.raises(ValueError, match="at least 2"):
        pm.rla_encode_path(v[None], top)
    with pytest.raises(ValueError, match="`eps`"):
        pm.fold_mask(pm.rla_encode(v, v, top), v, top, eps=2.0)
    with pytest.raises(ValueError, match="`rla.lengths`"):
        pm.rla_decode(pm.RLA(jnp.zeros(3), jnp.zeros(3)), v, top)
    with pytest.raises(ValueError, match="`anchor_face`"):
        pm.prepare_decoder(v, top, anchor_face=10**6)
    with pytest.raises(ValueError, match="`reference` is required"):
        pm.rla_decode(pm.rla_encode(v, v, top), None, top)


# -------------------------------------------------------------------------------------- decoder


def test_decode_exact_on_a_small_mesh_and_differentiable(sphere):
    v, top = sphere
    rng = np.random.default_rng(1)
    x = v + 0.03 * rng.standard_normal(v.shape)
    rla = pm.rla_encode(x, v, top)
    dec = pm.prepare_decoder(v, top)
    sol = pm.rla_decode(rla, v, top, decoder=dec)
    assert _kabsch_err(sol.value.vertices, x) < 1e-11
    assert int(sol.stats["frame_cg_steps"]) == 0  # the tree start is the solution
    assert float(jnp.abs(sol.value.holonomy).max()) < 1e-10
    placed = pm.rla_decode(rla, None, top, decoder=dec, align_to=x).value.vertices
    assert float(jnp.abs(placed - x).max()) < 1e-11
    # default placement: the anchor face keeps the reference's frame and its first corner
    av = dec.anchor_vertex
    np.testing.assert_allclose(sol.value.vertices[av], v[av], atol=1e-12)

    # differentiable: implicit-function gradient against central differences
    def loss(s):
        r = pm.RLA(rla.lengths * s, rla.angles * s)
        out = pm.rla_decode(r, None, top, decoder=dec, throw=False)
        return jnp.sum(out.value.vertices[:50] ** 2)

    g = float(jax.grad(loss)(1.0))
    h = 1e-6
    fd = float((loss(1 + h) - loss(1 - h)) / (2 * h))
    assert g == pytest.approx(fd, rel=1e-5)
    assert np.isfinite(g)


def test_decode_batched_matches_single(sphere):
    v, top = sphere
    rng = np.random.default_rng(2)
    xs = v + 0.02 * rng.standard_normal((3,) + v.shape)
    dec = pm.prepare_decoder(v, top)
    rlas = jax.vmap(lambda x: pm.rla_encode(x, v, top))(jnp.asarray(xs))
    out = jax.vmap(lambda r: pm.rla_decode(r, None, top, decoder=dec, throw=False).value.vertices)(
        rlas
    )
    for k in range(3):
        one = pm.rla_decode(jax.tree.map(lambda a: a[k], rlas), None, top, decoder=dec)
        np.testing.assert_allclose(out[k], one.value.vertices, atol=1e-12)
        assert _kabsch_err(out[k], xs[k]) < 1e-11


def test_decode_non_integrable_blend_reports_residuals(sphere):
    """A blend of two RLA vectors has no exact mesh: g returns the least-squares one, with
    non-zero residuals and holonomy, and it is closer to both targets than either source mesh."""
    v, top = sphere
    x1 = v.copy()
    x1[:, 2] += 0.25 * np.sin(4 * v[:, 0])
    x2 = v * np.array([1.2, 0.9, 1.0])
    r1, r2 = pm.rla_encode(x1, v, top), pm.rla_encode(x2, v, top)
    blend = pm.RLA(0.5 * (r1.lengths + r2.lengths), 0.5 * (r1.angles + r2.angles))
    sol = pm.rla_decode(blend, v, top)
    m = sol.value
    assert float(jnp.abs(m.holonomy).max()) > 1e-3
    assert float(jnp.abs(m.length_residual).max()) > 1e-4
    rb = pm.rla_encode(m.vertices, v, top)
    err = float(jnp.mean((rb.lengths - blend.lengths) ** 2))
    for r in (r1, r2):
        assert err < float(jnp.mean((r.lengths - blend.lengths) ** 2))
    np.testing.assert_allclose(
        m.length_residual, (1 + rb.lengths) / (1 + blend.lengths) - 1, atol=1e-12
    )


def test_decode_guards_impossible_lengths(sphere):
    v, top = sphere
    rla = pm.rla_encode(v, v, top)
    bad = pm.RLA(rla.lengths.at[np.asarray(top.face_edges)[0, 0]].set(5.0), rla.angles)
    sol = pm.rla_decode(bad, v, top)
    assert int(sol.stats["n_guarded_faces"]) >= 1
    assert bool(jnp.all(jnp.isfinite(sol.value.vertices)))
    neg = pm.RLA(rla.lengths.at[0].set(-2.0), rla.angles)
    assert bool(jnp.all(jnp.isfinite(pm.rla_decode(neg, v, top).value.vertices)))


def test_nearest_rotation():
    rng = np.random.default_rng(3)
    m = rng.standard_normal((20, 3, 3)) * 0.1 + np.eye(3)
    r = np.asarray(pm.nearest_rotation(m))
    np.testing.assert_allclose(
        r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12
    )
    assert np.all(np.linalg.det(r) > 0)
    u, _, vt = np.linalg.svd(m)
    np.testing.assert_allclose(r, u @ vt, atol=1e-10)
    g = jax.grad(lambda a: jnp.sum(pm.nearest_rotation(a) * jnp.arange(9.0).reshape(3, 3)))(
        jnp.eye(3)
    )
    assert bool(jnp.all(jnp.isfinite(g)))
    refl = np.diag([1.0, 1.0, -1.0])
    rr = np.asarray(pm.nearest_rotation(refl))
    assert np.linalg.det(rr) == pytest.approx(1.0)


def test_decode_default_body_posed_face_and_fingers(body):
    """Exactness on the closed 13,380-vertex body: a posed body, a facial action, a finger pose
    (≤ 1e-9 m after rigid alignment, in float64)."""
    from bodyprior.assets._source import FACIAL_ACTION_LABELS

    b, top, rest, dec = body
    assert top.n_edges == 40134
    ph = bp.phenotype_vector()
    names = list(b.joint_names)
    rng = np.random.default_rng(4)
    pose = 0.3 * rng.standard_normal((b.n_joints, 3))
    pose[0] = 0
    posed, _ = bp.evaluate(b, ph, pose)
    fa = np.zeros(52)
    fa[FACIAL_ACTION_LABELS.index("jawOpen")] = 0.8
    fa[FACIAL_ACTION_LABELS.index("eyeBlinkRight")] = 1.0
    face, _ = bp.evaluate(b, ph, facial_actions=fa)
    fingers = np.zeros((b.n_joints, 3))
    for n in names:
        if any(f in n for f in ("index", "middle", "ring", "pinky")):
            fingers[names.index(n)] = [0.0, 0.0, 1.2] if n.endswith("_l") else [0.0, 0.0, -1.2]
    hand, _ = bp.evaluate(b, ph, fingers)
    # the anchor is a torso face, not vertex 0's (right eye corner)
    assert dec.anchor_vertex != 0 and abs(float(rest[dec.anchor_vertex, 0])) < 0.1
    for x, enc in ((posed, pm.rla_encode), (face, pm.rla_encode_unwrapped), (hand, pm.rla_encode)):
        sol = pm.rla_decode(enc(x, rest, top), None, top, decoder=dec)
        assert _kabsch_err(sol.value.vertices, x) < 1e-9
        assert float(jnp.abs(sol.value.length_residual).max()) < 1e-9
