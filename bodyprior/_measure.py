"""Phenotypes from what people know: height in metres, weight in kilograms, age in years.

Conventions (those of anny's `Anthropometry`, so numbers agree with it on the same mesh):

- **height**: the vertical (Z) extent of the rest mesh, metres (top of the head to the soles; no
  hair, shoes or posture sag);
- **mass**: `980 kg/m³ x` the enclosed volume of the rest mesh (divergence theorem over its
  triangles; the MakeHuman body is closed except at the eyes, a few cm³);
- **BMI**: mass / height², kg/m²;
- **age**: years map to the phenotype `age` by anny's piecewise-linear "morphological age" table
  (years [0, 1, 4, 11, 16, 18, 64, 110] -> age [0, 0.05, 0.215, 0.415, 0.67, 0.77, 0.83, 1.0]), the
  table `sample_population` uses.

[`bodyprior.phenotypes_from_measurements`][] solves the `height`, `weight` (and unless given,
`muscle`) phenotype entries so that the rest mesh has the requested height and mass, by
Levenberg-Marquardt (optimistix) on those few variables; it refuses targets outside what the body
can reach at that age and gender, naming the reachable range.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from ._body import PHENOTYPES, DefaultBody, load_default_body, phenotype_vector, rest_shape
from ._store import register_type
from .assets import load_asset

BODY_DENSITY = 980.0
"""Body density of the mass convention, kg/m³ (anny's `Anthropometry.mass`)."""

_I_MUSCLE, _I_WEIGHT, _I_HEIGHT = (PHENOTYPES.index(k) for k in ("muscle", "weight", "height"))


def _age_table() -> tuple[np.ndarray, np.ndarray]:
    a = load_asset()
    years = np.asarray(a["calib_boys_morphological_age_mapping_morphological_age_anchors"], float)
    age = np.asarray(a["calib_boys_morphological_age_mapping_anny_age_anchors"], float)
    return years, age


def years_to_age(years: float) -> float:
    """The phenotype `age` of an age in years (module docstring; 0 to 110 years -> 0 to 1).

    **Raises:** `ValueError` for years outside [0, 110] or not finite.
    """
    y = float(years)
    if not 0.0 <= y <= 110.0:
        raise ValueError(f"`years` must lie in [0, 110], got {years!r}.")
    ty, ta = _age_table()
    return float(np.interp(y, ty, ta))


def age_to_years(age: float) -> float:
    """Years of a phenotype `age` in [0, 1] (the inverse of [`bodyprior.years_to_age`][]; ages
    below 0, MakeHuman's newborn range, have no entry in the table).

    **Raises:** `ValueError` for `age` outside [0, 1].
    """
    a = float(age)
    if not 0.0 <= a <= 1.0:
        raise ValueError(f"`age` must lie in [0, 1] (years are defined from 0), got {age!r}.")
    ty, ta = _age_table()
    return float(np.interp(a, ta, ty))


class Measurements(eqx.Module):
    """Height, volume, mass and BMI of one rest body (module docstring; batched under vmap)."""

    height_m: Float[Array, ""]
    volume_m3: Float[Array, ""]
    mass_kg: Float[Array, ""]
    bmi: Float[Array, ""]


register_type(Measurements)


def mesh_measurements(vertices: Float[ArrayLike, "V 3"], faces) -> Measurements:
    """[`bodyprior.Measurements`][] of a closed, outward-oriented mesh in metres, Z up (pure
    function, jittable)."""
    v = jnp.asarray(vertices)
    f = jnp.asarray(faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = jnp.abs(jnp.sum(jnp.einsum("fi,fi->f", jnp.cross(a, b), c)) / 6.0)
    height = jnp.max(v[:, 2]) - jnp.min(v[:, 2])
    mass = BODY_DENSITY * volume
    return Measurements(height, volume, mass, mass / height**2)


def measure(
    body: DefaultBody,
    phenotypes: Float[ArrayLike, " 11"],
    local_changes: Float[ArrayLike, " C"] | None = None,
) -> Measurements:
    """Height (m), volume (m³), mass (kg) and BMI of the default body's rest shape at these
    phenotypes (and local changes). Jittable; vmap over phenotypes for many bodies.

    **Example:** `bp.measure(body, bp.phenotype_vector(gender=1.0)).height_m`.
    """
    verts, _ = rest_shape(body, phenotypes, local_changes)
    return mesh_measurements(verts, body.faces)


@eqx.filter_jit
def _solve(body, base, target, free: tuple[int, ...]):
    """LM on the `free` phenotype entries (height first), each parametrised by a sine map onto
    [0, 1]; every free entry but height has a weak pull (1e-3 per unit) towards its given value,
    which picks the solution closest to it when more entries than targets are free."""
    free_idx = jnp.asarray(free)
    n_data = 1 if target.shape[0] == 1 else 2

    def params(u):  # the body's dtype; `u` float64 when x64 is on (the solver's precision)
        return base.at[free_idx].set((0.5 + 0.5 * jnp.sin(u)).astype(base.dtype))

    def residual(u, _):
        p = params(u)
        m = measure(body, p)
        r = [(m.height_m - target[0]) / 0.01]  # per centimetre
        if n_data == 2:
            r.append(m.mass_kg - target[1])  # per kilogram
        pull = 1e-3 * (p[free_idx[1:]] - base[free_idx[1:]])
        return jnp.concatenate([jnp.stack(r), pull]).astype(u.dtype)

    u0 = jnp.arcsin(2.0 * base[free_idx].astype(jnp.result_type(float)) - 1.0)
    solver = optx.LevenbergMarquardt(rtol=1e-9, atol=1e-9)
    sol = optx.least_squares(residual, solver, u0, max_steps=200, throw=False)
    return params(sol.value)


def phenotypes_from_measurements(
    *,
    height_m: float,
    weight_kg: float | None = None,
    age_years: float = 30.0,
    gender: float = 0.0,
    body: DefaultBody | None = None,
    **other: float,
) -> np.ndarray:
    """The phenotype vector `(11,)` of a body with this height, weight, age and gender.

    **Arguments:**

    - `height_m`: standing height, metres (module docstring).
    - `weight_kg`: body mass, kilograms; `None` solves the height alone (`weight` and `muscle`
      as given, default 0.5).
    - `age_years`: age in years (0-110), mapped by the morphological-age table.
    - `gender`: 0 = male, 1 = female (values between blend).
    - `body`: the default body (default `load_default_body("cmu_mb")`).
    - `other`: any other phenotype entry (`muscle=0.7`, `proportions=...`, ethnicity), as
      [`bodyprior.phenotype_vector`][]; `height` and, with `weight_kg`, `weight` may not be given.

    In MakeHuman's model the mass range of `weight` depends on `muscle`: at a 1.90 m young adult
    man, `weight` 0 -> 1 spans BMI 20.7-24.5 at `muscle=0.5` but 15.3-40.6 at `muscle=0`. So with
    `weight_kg` and no `muscle=`, `weight` and `muscle` are both solved, as close to the average
    (0.5, 0.5) as the target allows; pass `muscle=` to keep it fixed (a narrower mass range).

    **Returns:** NumPy `(11,)`; `measure(body, result)` matches `height_m` to 0.1 mm and
    `weight_kg` to 10 g (0.5 mm and 50 g with `jax_enable_x64` off).

    **Raises:** `ValueError` naming the argument for values out of range, and for a height or
    weight that the body cannot reach at this age and gender (with the reachable range).
    """
    if "age" in other:
        raise ValueError("give `age_years` (years), not the phenotype `age`.")
    if "height" in other or (weight_kg is not None and "weight" in other):
        raise ValueError(
            "`height` (and with `weight_kg`, `weight`) are solved for; do not pass them."
        )
    h = float(height_m)
    if not 0.3 <= h <= 2.5:
        raise ValueError(f"`height_m` must be a standing height in metres in [0.3, 2.5], got {h}.")
    if weight_kg is not None and not 2.0 <= float(weight_kg) <= 400.0:
        raise ValueError(f"`weight_kg` must lie in [2, 400] kg, got {weight_kg!r}.")
    base = phenotype_vector(gender=gender, age=years_to_age(age_years), **other)
    body = load_default_body("cmu_mb") if body is None else body
    dtype = body.template.dtype
    fit_weight = weight_kg is not None
    free = (_I_HEIGHT,)
    if fit_weight:
        free += (_I_WEIGHT,) if "muscle" in other else (_I_WEIGHT, _I_MUSCLE)
    target = jnp.asarray([h, float(weight_kg)] if fit_weight else [h], dtype)
    # Start inside (0, 1): the sine map has zero slope at the ends.
    start = (
        jnp.asarray(base, dtype)
        .at[jnp.asarray(free)]
        .set(jnp.clip(jnp.asarray(base[list(free)], dtype), 0.02, 0.98))
    )
    p = np.asarray(_solve(body, start, target, free), np.float64)
    m = measure(body, jnp.asarray(p, dtype))
    dh = abs(float(m.height_m) - h)
    dm = abs(float(m.mass_kg) - float(weight_kg)) if fit_weight else 0.0
    tol_h, tol_m = (1e-4, 1e-2) if dtype == jnp.float64 else (5e-4, 5e-2)
    if dh > tol_h or dm > tol_m:
        # Reachable masses at the reached height (the free entries at their extremes), and the
        # reachable heights (height entry 0 and 1).
        def at(**kv):
            q = p.copy()
            for k, v in kv.items():
                q[PHENOTYPES.index(k)] = v
            return measure(body, jnp.asarray(q, dtype))

        hs = [float(at(height=x).height_m) for x in (0.0, 1.0)]
        msg = f"heights {min(hs):.3f}-{max(hs):.3f} m"
        if fit_weight:
            mus = (0.0, 1.0) if len(free) == 3 else (p[_I_MUSCLE],)
            ms = [float(at(weight=w, muscle=u).mass_kg) for w in (0.0, 1.0) for u in mus]
            msg += f"; at {float(m.height_m):.3f} m masses {min(ms):.1f}-{max(ms):.1f} kg"
            if len(free) == 2:
                msg += " with `muscle` fixed (leave `muscle` out to solve it too)"
        what = f"height {h:.3f} m" + (
            f" and weight {float(weight_kg):.1f} kg" if fit_weight else ""
        )
        raise ValueError(
            f"`height_m`/`weight_kg`: {what} is out of reach at age {age_years} years, gender "
            f"{gender}: {msg} (closest reached: {float(m.height_m):.3f} m, "
            f"{float(m.mass_kg):.1f} kg)."
        )
    return p
