"""Side-by-side agreement with anny 0.6.2 (needs the optional `compare` extra; skipped otherwise).

Mapping: anny's `cmu_mb` rig has the same 31 bones in the same depth-first order as ours; its
`anny-noeyes-notongue` topology keeps 13,348 of our 13,380 body vertices (`base_mesh_vertex_indices`
maps
them; the others are unattached vertices anny removes). Poses: anny's `local-ref` parameterisation
with
`root_identity_orientation` equals ours (rotations in world-aligned axes at each bone head); anny
places the
root head at its delta translation, so we pass it the rest root head to keep the body in place.
"""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
anny = pytest.importorskip("anny")
roma = pytest.importorskip("roma")

import jax.numpy as jnp  # noqa: E402

import bodyprior as bp  # noqa: E402

pytestmark = pytest.mark.compare


@pytest.fixture(scope="module")
def models():
    m = anny.Anny(rig="cmu_mb", topology="anny-noeyes-notongue", skinning_method="lbs").to(
        torch.float64
    )
    return m, bp.load_default_body("cmu_mb", dtype=np.float64)


def test_same_rig(models):
    m, body = models
    assert list(m.bone_labels) == list(body.joint_names)
    assert [int(p) for p in m.bone_parents] == list(body.parents)


def test_rest_and_posed_vertices_match_anny(models):
    m, body = models
    idx = m.base_mesh_vertex_indices.numpy()
    rng = np.random.default_rng(0)
    B = 6
    phen = {
        k: torch.as_tensor(rng.uniform(0, 1, B), dtype=torch.float64) for k in m.phenotype_labels
    }
    aa = torch.as_tensor(rng.normal(0, 0.4, (B, 31, 3)), dtype=torch.float64)
    with torch.no_grad():
        rest = m(pose_parameters=None, phenotype_kwargs=phen)
        pose = torch.eye(4, dtype=torch.float64).repeat(B, 31, 1, 1)
        pose[..., :3, :3] = roma.rotvec_to_rotmat(aa)
        pose[:, 0, :3, 3] = rest["rest_bone_poses"][:, 0, :3, 3]
        posed = m(pose_parameters=pose, phenotype_kwargs=phen)
    for b in range(B):
        p = bp.phenotype_vector(**{k: float(v[b]) for k, v in phen.items()})
        v, j = bp.rest_shape(body, p)
        assert np.abs(np.asarray(v)[idx] - rest["rest_vertices"][b].numpy()).max() <= 1e-5
        vp, jp = bp.evaluate(body, p, jnp.asarray(aa[b].numpy()))
        assert np.abs(np.asarray(vp)[idx] - posed["vertices"][b].numpy()).max() <= 1e-4
        assert np.abs(np.asarray(jp) - posed["bone_poses"][b, :, :3, 3].numpy()).max() <= 1e-4
