"""The `bodyprior` CLI's jobs: `register`, `learn`, `pose`, `render` (see `bodyprior.cli`).

Each `cmd_*` takes the parsed `argparse` namespace and returns the exit code: 0 success, 1 when a
fit did not converge (results are still written), 2 for bad input (a `ValueError`, printed as one
line naming the argument or file). The CLI module imports this one only when a job runs.
"""

from __future__ import annotations

import glob
import os
import sys
import time

import numpy as np

SCAN_EXTENSIONS = (".ply", ".obj")
MESH_EXTENSIONS = (".ply", ".obj")

REGISTER_PRESETS = {
    # The measured best on simulated laser scans (docs/results_sscape.md): S-SCAPE fit with the
    # landmark term and pose prior, anchored NRD without the head rule.
    "default": ("default", "anchored"),
    # CAESAR-like scans: as default, plus humanshape's head rule (CAESAR heads are dummies).
    "caesar": ("default", "caesar"),
    # The paper / humanshape code: landmarks only for the similarity, the paper's NRD schedule.
    "paper": ("humanshape", "paper"),
}
"""The CLI presets of `register`: (FitConfig preset, NRDConfig preset)."""


def _files(paths, extensions, what: str) -> list[str]:
    """Files named in `paths` (a directory contributes its files with those extensions, sorted)."""
    out = []
    for p in paths:
        if os.path.isdir(p):
            found = sorted(
                f for f in glob.glob(os.path.join(p, "*")) if f.lower().endswith(extensions)
            )
            if not found:
                raise ValueError(f"`{what}`: directory {p!r} holds no {'/'.join(extensions)} file.")
            out.extend(found)
        elif os.path.isfile(p):
            if not p.lower().endswith(extensions):
                raise ValueError(f"`{what}`: {p!r} must end in {' or '.join(extensions)}.")
            out.append(p)
        else:
            raise ValueError(f"`{what}`: no such file or directory {p!r}.")
    if len(set(map(os.path.abspath, out))) != len(out):
        raise ValueError(f"`{what}`: a file is named twice.")
    return out


def _stem(path: str) -> str:
    return os.path.splitext(os.path.basename(path))[0]


def _landmark_file(scan_path: str, explicit: str | None) -> str | None:
    if explicit is not None:
        return explicit
    for ext in (".lnd", ".LND"):
        cand = os.path.splitext(scan_path)[0] + ext
        if os.path.isfile(cand):
            return cand
    return None


def _error_stats(err_mm: np.ndarray, valid: np.ndarray) -> dict:
    e = err_mm[valid]
    return dict(
        mean_mm=round(float(e.mean()), 3) if e.size else None,
        median_mm=round(float(np.median(e)), 3) if e.size else None,
        within_10mm=round(float((e <= 10.0).mean()), 4) if e.size else None,
        coverage=round(float(valid.mean()), 4),
    )


def cmd_register(args) -> int:
    """`bodyprior register`: S-SCAPE fit with the shipped space + refinement, per scan."""
    import jax

    jax.config.update("jax_enable_x64", True)  # NRD and the fit's solves run in float64

    from . import registration, sscape
    from ._io import atomic_write_json, write_ply
    from ._validate import as_device_array

    t_start = time.perf_counter()
    scan_paths = _files(args.scans, SCAN_EXTENSIONS, "scans")
    if args.landmarks is not None and len(scan_paths) != 1:
        raise ValueError("`--landmarks` names one file, so give exactly one scan (or none and put "
                         "SCAN.lnd next to each scan).")  # fmt: skip
    if args.components < 1:
        raise ValueError(f"`--components` must be >= 1, got {args.components}.")
    if args.points is not None and 0 < args.points < 100:
        raise ValueError(f"`--points` must be >= 100 (0 = all), got {args.points}.")
    fit_name, nrd_name = REGISTER_PRESETS[args.preset]
    fit_over = {} if args.max_passes is None else dict(max_passes=args.max_passes)
    fit_config = sscape.FitConfig.preset(fit_name, **fit_over)
    nrd_config = registration.NRDConfig.preset(nrd_name)
    os.makedirs(args.out, exist_ok=True)

    tmpl = registration.registration_template()
    model = sscape.default_space(args.components) if args.model is None else _load_space(args)
    if model.n_vertices != tmpl.n_vertices:
        raise ValueError(
            f"`--model`: the space has {model.n_vertices} vertices, the registration template "
            f"{tmpl.n_vertices}; learn it on the template (`bodyprior learn`)."
        )
    scans, infos = [], []
    for p in scan_paths:
        lnd = _landmark_file(p, args.landmarks)
        if lnd is None:
            raise ValueError(
                f"`scans`: {p!r} has no landmarks: pass `--landmarks F.lnd` or put "
                f"{_stem(p)}.lnd next to it (the alignment needs them)."
            )
        n_points = None if args.points in (None, 0) else args.points
        scan, info = registration.read_scan(
            p, landmarks_path=lnd, units=args.units, n_points=n_points, return_info=True
        )
        n_lm = int(np.asarray(scan.landmark_mask).sum())
        if n_lm < 4:
            raise ValueError(
                f"`landmarks`: {lnd!r} matches only {n_lm} of the template's landmark names "
                "(need >= 4 for the similarity)."
            )
        info.update(landmarks_file=lnd, landmarks_used=n_lm, points_used=int(scan.points.shape[0]))
        scans.append(scan)
        infos.append(info)
    t_read = time.perf_counter() - t_start
    batch = registration.pad_scans(scans)
    t0 = time.perf_counter()
    reg = sscape.register_sscape_nrd(
        model, batch, tmpl, fit_config=fit_config,
        nrd_config=None if args.no_refine else nrd_config, progress=not args.no_progress,
    )  # fmt: skip
    t_fit = time.perf_counter() - t0
    final = reg.fit_vertices if args.no_refine else reg.vertices
    faces = np.asarray(tmpl.faces)
    reports = []
    for i, (p, scan, info) in enumerate(zip(scan_paths, scans, infos)):
        stem = _stem(p)
        fe_fit = registration.fitting_error(as_device_array(reg.fit_vertices[i]), scan, faces=faces)
        fe = registration.fitting_error(as_device_array(final[i]), scan, faces=faces)
        err, valid = np.asarray(fe.error_mm), np.asarray(fe.valid)
        lm = np.asarray(scan.landmark_mask)
        lm_d = np.linalg.norm(
            final[i][np.asarray(tmpl.landmark_index)][lm] - np.asarray(scan.landmarks)[lm], axis=1
        )
        mesh_path = os.path.join(args.out, f"{stem}.registered.ply")
        write_ply(mesh_path, final[i], faces)
        png_path = os.path.join(args.out, f"{stem}.error.png")
        registration.error_colormap_png(
            png_path, final[i], faces, np.where(valid, err, np.nan), vmax=args.vmax_mm,
            title=f"{stem}: fitting error [mm], mean {err[valid].mean():.2f}",
        )  # fmt: skip
        rep = dict(
            scan=os.path.abspath(p),
            registered_mesh=os.path.abspath(mesh_path),
            error_map=os.path.abspath(png_path),
            units=info["units"],
            scale_to_m=info["scale"],
            normals=info["normals"],
            landmarks_file=os.path.abspath(info["landmarks_file"]),
            landmark_units=info.get("landmark_units"),
            landmarks_used=info["landmarks_used"],
            unmatched_landmarks=info["unmatched_landmarks"],
            points_in_file=info["n_points_file"],
            points_used=info["points_used"],
            successful=bool(reg.successful[i]),
            fitting_error=_error_stats(err, valid),
            sscape_fitting_error=_error_stats(
                np.asarray(fe_fit.error_mm), np.asarray(fe_fit.valid)
            ),
            landmark_rms_mm=round(float(np.sqrt(np.mean(lm_d**2)) * 1e3), 3),
            similarity_scale=round(float(np.exp(np.asarray(reg.similarities.log_scale)[i])), 5),
            shape_coeffs=[round(float(c), 5) for c in reg.coeffs[i]],
        )
        atomic_write_json(os.path.join(args.out, f"{stem}.json"), rep)
        reports.append(rep)
    summary = dict(
        preset=args.preset,
        fit_config=repr(fit_config),
        nrd_config=None if args.no_refine else repr(nrd_config),
        model="shipped sscape_caesar.sscape" if args.model is None else os.path.abspath(args.model),
        components=int(model.n_components),
        n_scans=len(reports),
        n_failed=int(sum(not r["successful"] for r in reports)),
        seconds=dict(
            read=round(t_read, 2),
            fit_and_refine=round(t_fit, 2),
            total=round(time.perf_counter() - t_start, 2),
        ),  # fmt: skip
        scans=reports,
    )
    atomic_write_json(os.path.join(args.out, "report.json"), summary)
    if args.json:
        import json

        print(json.dumps(summary, indent=1))
    else:
        for r in reports:
            fe = r["fitting_error"]
            print(
                f"{os.path.basename(r['scan'])}: fitting error {fe['mean_mm']:.2f} mm mean, "
                f"{fe['median_mm']:.2f} median, coverage {fe['coverage']:.1%}, landmark RMS "
                f"{r['landmark_rms_mm']:.1f} mm ({r['units']})"
                + ("" if r["successful"] else " FAILED")
            )
        print(f"{len(reports)} scan(s) in {summary['seconds']['total']:.1f} s -> {args.out}")
    return 1 if summary["n_failed"] else 0


def _load_space(args):
    from . import sscape

    model = sscape.load_model(args.model)
    if args.components < model.n_components:
        model = sscape.truncate(model, args.components)
    return model


def _rig_for(n_vertices: int):
    """The rig of the default body or the registration template with this vertex count, else
    `None` (a single root joint)."""
    from ._body import load_default_body
    from .registration import registration_template

    tmpl = registration_template()
    if n_vertices == tmpl.n_vertices:
        return tmpl.rig, "registration template (cmu_mb)"
    body = load_default_body("cmu_mb")
    if n_vertices == body.n_vertices:
        return body.rig, "default body (cmu_mb)"
    return None, "single root joint"


def cmd_learn(args) -> int:
    """`bodyprior learn`: meshes in correspondence -> S-SCAPE space + G/S/C report + mode images."""
    import jax
    import jax.numpy as jnp

    from . import sscape
    from ._io import atomic_write_json, read_mesh
    from ._render import contact_sheet, save_png

    t0 = time.perf_counter()
    paths = _files(args.meshes, MESH_EXTENSIONS, "meshes")
    if len(paths) < 3:
        raise ValueError(f"`meshes`: need at least 3 meshes, got {len(paths)}.")
    verts, faces = [], None
    progress = not getattr(args, "no_progress", False)
    from tqdm.auto import tqdm

    for p in tqdm(paths, desc="reading meshes", unit="mesh", disable=not progress):
        v, f, _ = read_mesh(p)
        if f is None:
            raise ValueError(f"`meshes`: {p!r} has no faces (a point cloud); meshes are needed.")
        if faces is None:
            faces = f
        elif v.shape[0] != verts[0].shape[0] or not np.array_equal(f, faces):
            raise ValueError(
                f"`meshes`: {p!r} is not in correspondence with {paths[0]!r} "
                f"({v.shape[0]} vs {verts[0].shape[0]} vertices or other faces)."
            )
        verts.append(v)
    x = np.stack(verts)
    rig, rig_name = _rig_for(x.shape[1])
    k = min(args.components, len(paths) - 1)
    aligned, _ = sscape.procrustes_align(jnp.asarray(x))
    model = sscape.learn(aligned, faces, n_components=k, align=False, rig=rig)
    sscape.save_model(args.out, model, info=dict(
        built_by="bodyprior learn", meshes=[os.path.abspath(p) for p in paths], rig=rig_name,
    ))  # fmt: skip
    comp = sscape.compactness(model)
    ms = tuple(m for m in (1, 2, 5, 10, 20, 50) if m <= k) or (k,)
    report = dict(
        model=os.path.abspath(args.out),
        n_meshes=len(paths),
        n_vertices=int(x.shape[1]),
        components=k,
        rig=rig_name,
        compactness=[round(float(c), 5) for c in np.asarray(comp.ratio)],
    )
    if not args.no_measures and len(paths) >= k + 2:
        gen = sscape.generalization(aligned, ms, progress=progress)
        spec = sscape.specificity(
            model, aligned, ms, key=jax.random.PRNGKey(args.seed), n_samples=args.samples,
            progress=progress,
        )  # fmt: skip
        report["generalization_mm"] = dict(zip(map(str, ms), _mm_list(gen.mean)))
        report["specificity_mm"] = dict(zip(map(str, ms), _mm_list(spec.mean)))
    base = os.path.splitext(args.out)[0]
    n_modes = min(args.modes, k)
    if n_modes:
        meshes, labels = [], []
        for m in range(n_modes):
            for s in (-3.0, 0.0, 3.0):
                c = jnp.zeros(k).at[m].set(s)
                meshes.append(np.asarray(sscape.shape_vertices(model, c)))
                labels.append(f"PC{m + 1} {s:+.0f} sd")
        sheet = contact_sheet(meshes, np.asarray(faces), ncols=3, labels=labels,
                              cell_size=(240, 160))  # fmt: skip
        save_png(base + ".modes.png", sheet)
        report["mode_picture"] = os.path.abspath(base + ".modes.png")
    report["seconds"] = round(time.perf_counter() - t0, 2)
    atomic_write_json(base + ".report.json", report)
    if args.json:
        import json

        print(json.dumps(report, indent=1))
    else:
        msg = f"{k} components from {len(paths)} meshes ({rig_name}) -> {args.out}"
        if "generalization_mm" in report:
            msg += (f"; generalization {report['generalization_mm']} mm, specificity "
                    f"{report['specificity_mm']} mm")  # fmt: skip
        print(msg)
    return 0


def _mm_list(x) -> list:
    return [round(float(v), 3) for v in np.asarray(x)]


def _phenotypes(pairs) -> np.ndarray:
    from ._body import phenotype_vector

    values = {}
    for item in pairs or ():
        if "=" not in item:
            raise ValueError(f"`--phenotype` must be NAME=VALUE, got {item!r}.")
        k, v = item.split("=", 1)
        try:
            values[k.strip()] = float(v)
        except ValueError:
            raise ValueError(f"`--phenotype {item}`: {v!r} is not a number.") from None
    return phenotype_vector(**values)


def cmd_pose(args) -> int:
    """`bodyprior pose`: one BVH frame on the default body -> posed mesh + PNG, root motion kept."""
    from ._body import PHENOTYPES, evaluate, load_default_body
    from ._bvh import read_bvh
    from ._io import atomic_write_json, write_obj, write_ply
    from ._mocap import retarget
    from ._render import render_mesh, save_png

    phen = _phenotypes(args.phenotype)
    bvh = read_bvh(args.bvh)
    n = bvh.n_frames
    if not -n <= args.frame < n:
        raise ValueError(
            f"`--frame` must lie in [{-n}, {n - 1}] for {args.bvh!r}, got {args.frame}."
        )
    frame = args.frame % n
    body = load_default_body("cmu_mb")
    pose, trans = retarget(bvh, body, [frame], keep_root_rotation=True,
                           keep_root_translation=not args.no_root_motion)  # fmt: skip
    verts, joints = evaluate(body, phen, pose[0], trans[0])
    verts, joints = np.asarray(verts), np.asarray(joints)
    faces = np.asarray(body.faces)
    report = {}
    if args.model == "panoman":
        verts, faces, report = _panoman_pose(args, joints)
    os.makedirs(args.out, exist_ok=True)
    stem = f"{_stem(args.bvh)}_{frame:05d}"
    mesh_path = os.path.join(args.out, f"{stem}.{args.format}")
    (write_ply if args.format == "ply" else write_obj)(mesh_path, verts, faces)
    png_path = os.path.join(args.out, f"{stem}.png")
    views = [render_mesh(verts, faces, view=v, size=(args.size, args.size * 3 // 4))
             for v in ("front", "side")]  # fmt: skip
    save_png(png_path, np.concatenate(views, axis=1))
    atomic_write_json(os.path.join(args.out, f"{stem}.json"), dict(
        bvh=os.path.abspath(args.bvh), frame=frame, n_frames=n, model=args.model,
        phenotypes=dict(zip(PHENOTYPES, np.round(phen, 5).tolist())),
        root_translation_m=np.round(trans[0], 5).tolist(),
        pose_axis_angle=np.round(pose[0], 6).tolist(), joint_names=list(body.joint_names),
        joints_m=np.round(joints, 5).tolist(), mesh=os.path.abspath(mesh_path),
        n_vertices=int(verts.shape[0]), image=os.path.abspath(png_path), **report,
    ))  # fmt: skip
    print(f"{args.bvh} frame {frame}/{n} ({args.model}) -> {mesh_path}, {png_path}")
    return 0


def _panoman_pose(args, joints: np.ndarray):
    """`pose --model panoman`: the kit reconstructed from the frame's exact `cmu_mb` joints
    (`bodyprior.panoman.reconstruct`); returns its vertices, faces and a report (fit statistics,
    the joint residual of the kit's regressor on the result, mm)."""
    import time

    import jax

    jax.config.update("jax_enable_x64", True)  # the shell solve needs float64
    from . import panoman as pm
    from ._solution import RESULTS

    if args.max_steps < 1:
        raise ValueError(f"`--max-steps` must be >= 1, got {args.max_steps}.")
    blocks = tuple(b.strip() for b in args.blocks.split(",") if b.strip())
    if not blocks or any(b not in pm.PARTS for b in blocks):
        raise ValueError(f"`--blocks` must be a comma-separated subset of {pm.PARTS}, got "
                         f"{args.blocks!r}.")  # fmt: skip
    kit = pm.load_kit(args.kit) if args.kit else pm.default_panoman()
    t0 = time.perf_counter()
    rec = pm.reconstruct(kit, joints, max_steps=args.max_steps, blocks=blocks)
    seconds = time.perf_counter() - t0
    v = np.asarray(rec.value.vertices)
    if not np.all(np.isfinite(v)):
        raise ValueError("the PanoMan reconstruction is not finite; try --model skinning.")
    res = 1e3 * np.linalg.norm(np.asarray(kit.regressor(v)) - joints, axis=1)
    res_ik = 1e3 * np.linalg.norm(np.asarray(rec.stats["ik"]["joints"]) - joints, axis=1)
    report = dict(
        kit=os.path.abspath(args.kit) if args.kit else "shipped: bodyprior.panoman.default_panoman",
        seconds=round(seconds, 2),
        joint_residual_mm=dict(mean=round(float(res.mean()), 3), max=round(float(res.max()), 3)),
        ik_joint_residual_mm=dict(mean=round(float(res_ik.mean()), 3),
                                  max=round(float(res_ik.max()), 3)),
        blocks=[{k: b[k] for k in ("part", "steps", "cg_steps", "energy0", "energy", "seconds")}
                for b in rec.stats["blocks"]],
        successful=bool(rec.result == RESULTS.successful),
    )  # fmt: skip
    return v, np.asarray(kit.model.topology.faces), report


def cmd_render(args) -> int:
    """`bodyprior render`: a mesh file -> shaded PNG (one or more views side by side)."""
    from ._io import read_mesh
    from ._render import render_mesh, save_png

    v, f, _ = read_mesh(args.mesh)
    if f is None:
        raise ValueError(f"`mesh`: {args.mesh!r} has no faces (a point cloud); give a mesh.")
    ext = np.ptp(v, axis=0).max()
    if ext > 10.0:  # millimetres: the renderer is unit-free, but report it
        print(f"note: {args.mesh} spans {ext:.0f} units (millimetres?); rendered as is",
              file=sys.stderr)  # fmt: skip
    views = [render_mesh(v, f, view=w, size=(args.size, args.size * 3 // 4)) for w in args.view]
    save_png(args.out, np.concatenate(views, axis=1))
    print(f"{args.mesh} ({v.shape[0]} vertices, {f.shape[0]} faces) -> {args.out}")
    return 0
