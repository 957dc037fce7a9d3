"""The shipped S-SCAPE space on the registration template (`bodyprior/assets/sscape_caesar.sscape`).

A user who registers a scan needs a shape space on the registration template before anything else;
building one from a population costs minutes, so the package ships one:

- 2,000 adult bodies (18-65 years) sampled by [`bodyprior.sample_population`][] with the CAESAR
  phenotype scheme and random local changes (`load_default_body("cmu_mb", local_changes=True)`),
  key `jax.random.PRNGKey(2026)`, x64 on;
- posed exactly in the template's rest posture (`pose_jitter_deg=0`): the generator knows each
  body's pose, so this *is* the posture normalization, without the residual a scan-side method
  (NH, WSX) leaves;
- restricted to the 6,449 template vertices, rigidly Procrustes-aligned and learned by
  [`bodyprior.sscape.learn`][] with 50 components on the `cmu_mb` template rig.

The file's metadata records that provenance, the checksums of the assets it was built from and the
build command, `python -m bodyprior.sscape.build_space`; `load_model` verifies its checksum.
"""

from __future__ import annotations

import os
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..registration import template_sources
from ._learn import learn
from ._model import truncate
from ._serialize import load_model, save_model

SPACE_NAME = "sscape_caesar.sscape"
N_BODIES = 2000
N_COMPONENTS = 50
SEED = 2026
_REBUILD = "rebuild it with `python -m bodyprior.sscape.build_space`"


def space_path() -> str:
    """Path of the shipped S-SCAPE space file."""
    from ..assets import asset_path

    return os.path.join(os.path.dirname(asset_path()), SPACE_NAME)


def default_space(n_components: int = 20, *, return_info: bool = False):
    """The shipped S-SCAPE space on the default registration template (module docstring).

    **Arguments:**

    - `n_components`: keep the first this many of the file's 50 components (default 20, the
      size the registration results use; `docs/results_sscape.md`).
    - `return_info`: also return the file's provenance dict (seed, population, explained
      variance, source checksums, build time).

    **Returns:** an [`bodyprior.sscape.SScapeModel`][] on `registration_template()`'s 6,449
    vertices and `cmu_mb` rig (float64 arrays), or `(model, info)`.

    **Raises:** `ValueError` for `n_components` outside [1, 50] or a missing or corrupted file.
    A file built from other assets than the installed ones loads with a warning.
    """
    if isinstance(n_components, bool) or not isinstance(n_components, (int, np.integer)):
        raise ValueError(f"`n_components` must be an int in [1, 50], got {n_components!r}.")
    path = space_path()
    if not os.path.exists(path):
        raise ValueError(f"the shipped S-SCAPE space is missing at {path!r}; {_REBUILD}.")
    model, info = load_model(path, return_info=True)
    if not 1 <= n_components <= model.n_components:
        raise ValueError(
            f"`n_components` must be in [1, {model.n_components}], got {n_components!r}."
        )
    if info.get("sources") != template_sources():
        warnings.warn(
            f"{path!r} was built from other default-body assets than the installed ones; "
            f"{_REBUILD}.",
            stacklevel=2,
        )
    model = truncate(model, int(n_components))
    return (model, info) if return_info else model


def build_default_space(path: str | None = None, *, progress: bool = True, log=print) -> dict:
    """Builds the shipped space (module docstring) and writes it atomically to `path` (default:
    [`space_path`][]). About two minutes on 2 cores. **Returns:** the provenance dict."""
    from .. import load_default_body, sample_population
    from ..registration import registration_template

    path = os.path.abspath(path or space_path())
    t0 = time.perf_counter()
    with jax.enable_x64(True):
        body = load_default_body("cmu_mb", local_changes=True)
        tmpl = registration_template("cmu_mb", decimated=True)
        pop = sample_population(
            N_BODIES, body=body, scheme="caesar", pose_jitter_deg=0.0,
            key=jax.random.PRNGKey(SEED), progress=progress,
        )  # fmt: skip
        meshes = np.asarray(pop.vertices[:, np.asarray(tmpl.vertex_map)], np.float64)
        del pop
        model = learn(jnp.asarray(meshes), tmpl.faces, n_components=N_COMPONENTS, rig=tmpl.rig)
    ratio = np.asarray(model.explained_variance)
    info = {
        "built_by": "bodyprior.sscape._default.build_default_space "
        "(python -m bodyprior.sscape.build_space)",
        "population": {
            "n_bodies": N_BODIES,
            "scheme": "caesar",
            "age_range_years": [18.0, 65.0],
            "local_changes": True,
            "pose_jitter_deg": 0.0,
            "seed": SEED,
        },
        "template": {"rig": "cmu_mb", "decimated": True, "n_vertices": int(tmpl.n_vertices)},
        "n_components": N_COMPONENTS,
        "explained_variance_cumulative": [round(float(x), 6) for x in np.cumsum(ratio)],
        "stddev_mm_first": [round(float(x) * 1e3, 3) for x in np.asarray(model.stddev)[:5]],
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "sources": template_sources(),
        "build_seconds": round(time.perf_counter() - t0, 1),
    }
    save_model(path, model, info=info)
    log(
        f"{path}: {N_COMPONENTS} components from {N_BODIES} bodies, cumulative explained variance "
        f"{np.cumsum(ratio)[[9, 19, 49]].round(4).tolist()} at 10/20/50 "
        f"({info['build_seconds']} s, {os.path.getsize(path) / 2**20:.1f} MiB)"
    )
    return info
