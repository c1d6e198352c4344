"""Bring your own model: a user's URDF or MJCF file prepared for the simulator.

The tree description names the inferred joints, the grasped branch and the grasp fraction; its
``model:`` section names the file and how the model's names relate to the branch names::

    model:
      file: tree.urdf                 # relative to the tree file
      sha256: ...                     # written by treeinfer; checked when the run is rebuilt
      joints: {branch_name: joint_name}   # only where they differ (URDF: joint != child link)
      bodies: {branch_name: link_name}
      grasp_position: [0, 0, 0.3]     # m, in the grasped link's frame (default: along its axis)
      repair_inertia: geometry        # null (refuse degenerate inertias), geometry or floor
      limits: refuse                  # refuse joint limits narrower than +-pi, or ignore them
      gains: tree                     # tree: the tree's fixed kp/kd on every non-inferred hinge;
                                      # model: keep the model's own (error where it has none)

Without explicit maps a branch matches a joint of its name (its body: the joint's child link),
else a body of its name (its joint: the body's one hinge). :func:`prepare_user_model` renames the
matched joints and bodies to the branch names, so the simulator sees the same names as for a
tree it builds itself, sets the gains, places the ``grasp`` site along the grasped link's real
axis, checks inertias and joint limits, and compiles.

Link axis (where fraction f of a branch lies): the longest cylinder/capsule geom of the link
(from the end nearer the joint to the far end), else the link's farthest child joint, else twice
its centre of mass; ``grasp_position`` overrides it for the grasped link.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import TreeFileError
from .geometry import (  # noqa: F401 -- re-exported: the old import path keeps working
    _CYLINDERS,
    MIN_MASS,
    _degenerate,
    _geom_inertials,
    _load_spec,
    _probe,
    _repair,
    _spec_inertia,
    link_axis,
)
from .model_section import (  # noqa: F401 -- re-exported: the section's fields and parser
    GAIN_POLICIES,
    LIMIT_POLICIES,
    MODEL_KEYS,
    MODEL_SUFFIXES,
    REPAIRS,
    file_sha256,
    parse_model_section,
)

_WIDE = math.pi - 1e-6  # rad: a range at least +-pi never acts on a branch (to_urdf writes +-pi)


def attach_model(
    tree,
    model_file: str | Path | None = None,
    repair_inertia: str | None = None,
    keep_sha256: bool = False,
):
    """``tree`` with its ``model:`` section pointing at ``model_file`` (absolute, with its
    sha256), keeping the section's name maps; ``repair_inertia`` (``geometry``/``floor``) set
    when given. ``model_file`` None keeps the tree's file (and adds its sha256);
    ``keep_sha256``: the recorded sha256 stays (the file moved, its content must not change)."""
    from dataclasses import replace

    sec = dict(tree.model or {})
    if model_file is not None:
        sec["file"] = str(model_file)
        if not keep_sha256:
            sec.pop("sha256", None)
    if "file" not in sec:
        raise TreeFileError("--repair-inertia: the tree has no model file (give --model FILE)")
    sec = parse_model_section(sec, "--model", base_dir=Path.cwd())
    p = Path(sec["file"])
    if not p.is_file():
        raise TreeFileError(f"{p}: no such model file")
    sec.setdefault("sha256", file_sha256(p))
    if repair_inertia is not None:
        if repair_inertia not in REPAIRS:
            raise TreeFileError(
                f"--repair-inertia: one of {', '.join(REPAIRS)}, got {repair_inertia!r}"
            )
        sec["repair_inertia"] = repair_inertia
    return replace(tree, model=sec)


@dataclass
class PreparedModel:
    """A user model ready for the simulator.

    Attributes:
      mj_model: compiled model; joints and bodies renamed to the branch names.
      axes: {branch name: (start [3], end [3])} m, each link's axis in its body frame.
      report: what was matched, set and repaired (JSON-able): ``file``, ``sha256``,
        ``joints``/``bodies`` (branch -> name in the file), ``fixed_gains`` (joints set),
        ``repaired`` ({link: what}), ``limits_ignored`` ([joint]).
    """

    mj_model: Any
    axes: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)


def _match(tree, m, sec, path) -> tuple[dict[str, str], dict[str, str]]:
    import mujoco

    jnames = {m.joint(j).name: j for j in range(m.njnt)}
    bnames = {m.body(b).name: b for b in range(1, m.nbody)}
    jmap, bmap = dict(sec.get("joints", {})), dict(sec.get("bodies", {}))
    unknown = [f"{k} -> joint '{v}'" for k, v in jmap.items() if v not in jnames]
    unknown += [f"{k} -> body '{v}'" for k, v in bmap.items() if v not in bnames]
    names = set(tree.names)
    unknown += [f"'{k}' (not a branch)" for k in list(jmap) + list(bmap) if k not in names]
    joints, bodies, missing = {}, {}, []
    for b in tree.branches:
        j = jmap.get(b.name)
        body = bmap.get(b.name)
        if body is None:
            if b.name in bnames and not (j is None and b.name in jnames):
                body = b.name
            elif (j or b.name) in jnames:
                body = m.body(int(m.jnt_bodyid[jnames[j or b.name]])).name
            elif b.name in bnames:
                body = b.name
        if j is None and not b.fixed:
            if b.name in jnames:
                j = b.name
            elif body in bnames:
                hinge = [
                    i
                    for i in range(m.njnt)
                    if m.jnt_bodyid[i] == bnames[body]
                    and m.jnt_type[i] == mujoco.mjtJoint.mjJNT_HINGE
                ]
                j = m.joint(hinge[0]).name if len(hinge) == 1 else None
        if body is None or (j is None and not b.fixed):
            missing.append(b.name)
            continue
        bodies[b.name] = body
        if j is not None:
            joints[b.name] = j
    if unknown or missing:
        msg = f"{path}: names of the tree do not match the model."
        if missing:
            msg += (
                f" Unmatched branch(es) {missing[:20]}{' ...' if len(missing) > 20 else ''}"
                f" ({len(missing)} of {len(tree.branches)})."
            )
        if unknown:
            msg += f" Map entries naming nothing: {unknown[:20]}."
        msg += (
            f" The model has joints {list(jnames)[:10]}{' ...' if len(jnames) > 10 else ''} "
            f"and bodies {list(bnames)[:10]}{' ...' if len(bnames) > 10 else ''}; map them "
            "with model: {joints: {branch: joint}, bodies: {branch: link}}"
        )
        raise TreeFileError(msg)
    return joints, bodies


def prepare_user_model(tree, model_file=None) -> PreparedModel:
    """Load, check, complete and compile the user model of ``tree`` (its ``model:`` section, or
    ``model_file`` given directly with the section's other settings or their defaults).

    Raises:
      TreeFileError: the file is missing, changed (sha256), or MuJoCo cannot load it; names do
        not match (all unmatched listed); a moving link has a degenerate mass/inertia and no
        repair was asked for (the links named); joint limits narrower than +-pi under
        ``limits: refuse`` (the joints named); ``gains: model`` and joints without stiffness.
    """
    import mujoco

    from .export import GRASP_SITE

    sec = dict(tree.model or {})
    if model_file is not None:
        sec = parse_model_section({**sec, "file": str(model_file), "sha256": None}, "model_file")
    if "file" not in sec:
        raise TreeFileError("model: no model file (tree has no model: section)")
    path = Path(sec["file"])
    spec = _load_spec(path)
    digest = file_sha256(path)
    if sec.get("sha256") and sec["sha256"] != digest:
        raise TreeFileError(
            f"{path}: the model file changed since it was recorded (sha256 "
            f"{digest[:12]}..., recorded {sec['sha256'][:12]}...)"
        )
    probe = _probe(spec, path)
    joints, bodies = _match(tree, probe, sec, path)
    report: dict[str, Any] = {
        "file": str(path),
        "sha256": digest,
        "joints": joints,
        "bodies": bodies,
    }

    # inertias of moving links (a joint on the body or an ancestor)
    moving = [bool(probe.body_jntnum[i]) for i in range(probe.nbody)]
    for i in range(1, probe.nbody):
        moving[i] = moving[i] or moving[int(probe.body_parentid[i])]
    bad, repaired = [], {}
    from_geoms = _geom_inertials(spec, path)
    for i in range(1, probe.nbody):
        if not moving[i]:
            continue
        b = spec.body(probe.body(i).name)
        if b.explicitinertial:
            why = _degenerate(float(b.mass), _spec_inertia(b))
        else:  # MuJoCo computes it from the geoms
            why = _degenerate(*from_geoms[b.name])
        if why is None:
            continue
        if sec.get("repair_inertia") is None:
            bad.append(f"{probe.body(i).name}: {why}")
        else:
            repaired[probe.body(i).name] = _repair(b, probe, i, sec["repair_inertia"], tree.density)
    if bad:
        raise TreeFileError(
            f"{path}: {len(bad)} link(s) have a degenerate mass or inertia (MuJoCo needs positive "
            f"mass and a positive-definite inertia on moving bodies): {'; '.join(bad[:10])}"
            f"{' ...' if len(bad) > 10 else ''}. Fix the file or repair them: --repair-inertia "
            "(model: {repair_inertia: ...}) geometry (solid cylinder of the link's geometry) "
            "or floor"
        )
    report["repaired"] = repaired

    # joint limits: the simulator runs without the constraint solver, so they cannot act
    hinge = mujoco.mjtJoint.mjJNT_HINGE
    limited = []
    for j in range(probe.njnt):
        if probe.jnt_type[j] == hinge and probe.jnt_limited[j]:
            lo, hi = (float(x) for x in probe.jnt_range[j])
            if lo > -_WIDE or hi < _WIDE:
                limited.append((probe.joint(j).name, lo, hi))
    if limited and sec.get("limits", "refuse") == "refuse":
        lst = "; ".join(f"{n} [{lo:.3g}, {hi:.3g}] rad" for n, lo, hi in limited[:10])
        raise TreeFileError(
            f"{path}: {len(limited)} joint(s) have limits the simulator does not model (it runs "
            f"without MuJoCo's constraint solver): {lst}{' ...' if len(limited) > 10 else ''}. "
            "Widen them to +-pi or set model: {limits: ignore} to simulate without them"
        )
    report["limits_ignored"] = [n for n, _, _ in limited]
    for j in spec.joints:
        j.limited = mujoco.mjtLimited.mjLIMITED_FALSE

    # gains: the tree's fixed gains on every non-inferred hinge (the inferred are overwritten)
    by_joint = {v: k for k, v in joints.items()}
    gains_mode = sec.get("gains", "tree")
    no_stiff, set_gains = [], 0
    for j in range(probe.njnt):
        if probe.jnt_type[j] != hinge:
            continue
        name = probe.joint(j).name
        sj = spec.joint(name)
        branch = by_joint.get(name)
        if gains_mode == "tree":
            kp, kd = tree.fixed_gains(branch) if branch else (tree.fixed_kp, tree.fixed_kd)
            sj.stiffness = [kp] + [0.0] * (len(sj.stiffness) - 1)
            sj.damping = [kd] + [0.0] * (len(sj.damping) - 1)
            sj.springref = 0.0
            set_gains += 1
        elif branch not in tree.inferred and float(sj.stiffness[0]) <= 0:
            no_stiff.append(name)
    if no_stiff:
        raise TreeFileError(
            f"{path}: {len(no_stiff)} non-inferred joint(s) have no stiffness and would swing "
            f"freely: {no_stiff[:20]}{' ...' if len(no_stiff) > 20 else ''}; set model: "
            "{gains: tree} to give them the tree's fixed kp/kd"
        )
    report["fixed_gains"] = {"mode": gains_mode, "joints": set_gains}

    # rename matched joints/bodies to branch names (two passes: no clash with names in use)
    for kind, mapping in (("joint", joints), ("body", bodies)):
        items = [(getattr(spec, kind)(v), k) for k, v in mapping.items() if k != v]
        for k_, (el, _) in enumerate(items):
            el.name = f"__treeinfer_tmp_{k_}"
        for el, k in items:
            clash = getattr(spec, kind)(k)
            if clash is not None:
                clash.name = f"{k}__model"
            el.name = k

    axes = {}
    for b in tree.branches:
        ax = link_axis(probe, int(probe.body(bodies[b.name]).id))
        if ax is not None:
            axes[b.name] = (ax[0], ax[1])
    g = tree.grasp_branch
    if sec.get("grasp_position") is not None:
        site_pos = np.asarray(sec["grasp_position"], float)
        axes[g] = (np.zeros(3), site_pos / tree.grasp_fraction)
    elif g in axes:
        a, e = axes[g]
        site_pos = a + tree.grasp_fraction * (e - a)
    else:
        raise TreeFileError(
            f"{path}: cannot tell the axis of the grasped link '{bodies[g]}' (no cylinder or "
            "capsule geom, no child link); give model: {grasp_position: [x, y, z]} (m, in the "
            "link's frame)"
        )
    old = spec.site(GRASP_SITE)
    if old is not None:
        spec.delete(old)
    spec.body(g).add_site(name=GRASP_SITE, pos=site_pos, size=[0.01, 0.01, 0.01])
    report["grasp_site"] = [float(x) for x in site_pos]

    spec.option.disableflags |= (
        mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    )
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.gravity = np.asarray(tree.gravity, float)
    try:
        mj_model = spec.compile()
    except Exception as e:
        raise TreeFileError(f"{path}: MuJoCo cannot compile this model: {e}") from None
    return PreparedModel(mj_model=mj_model, axes=axes, report=report)


def describe_report(report: dict) -> list[str]:
    """Human-readable lines of a :class:`PreparedModel` report (CLI output)."""
    out = [
        f"model: {report['file']} (sha256 {report['sha256'][:12]}...), "
        f"{len(report['joints'])} joints matched, fixed gains "
        f"{report['fixed_gains']['mode']} on {report['fixed_gains']['joints']} joints"
    ]
    if report.get("repaired"):
        out.append(f"  repaired inertia of {len(report['repaired'])} link(s):")
        out += [f"    {k}: {v}" for k, v in list(report["repaired"].items())[:20]]
        if len(report["repaired"]) > 20:
            out.append(f"    ... ({len(report['repaired']) - 20} more)")
    if report.get("limits_ignored"):
        out.append(f"  joint limits ignored (model: limits: ignore): {report['limits_ignored']}")
    return out


def _fork(
    f_parent: np.ndarray, xmat_parent, xmat_child, d_world
) -> tuple[float, float, np.ndarray]:
    """(angle_deg, azimuth_deg, child frame [3, 3]) in treeinfer's convention (child frame =
    parent frame @ rot_x(azimuth) @ rot_y(-angle), x along the branch) for a child link whose
    axis points along ``d_world`` [3]. Exact frames when the model's own frames already follow
    the convention (trees treeinfer exports); otherwise the same branch directions, with the
    bending plane chosen by the direction alone."""
    from .description import rot_x, rot_y

    rel = xmat_parent.T @ xmat_child
    if (
        np.allclose(xmat_parent, f_parent, atol=1e-9)
        and np.allclose(xmat_child[:, 0], d_world, atol=1e-6)
        and abs(rel[0, 1]) < 1e-9
    ):
        ang = -math.atan2(rel[0, 2], rel[0, 0])
        az = math.atan2(rel[2, 1], rel[1, 1])
        return math.degrees(ang), math.degrees(az), np.asarray(xmat_child, float)
    v = f_parent.T @ d_world
    ang = math.acos(float(np.clip(v[0], -1.0, 1.0)))
    az = math.atan2(-v[1], v[2]) if math.sin(ang) > 1e-9 else 0.0
    return math.degrees(ang), math.degrees(az), f_parent @ rot_x(az) @ rot_y(-ang)


def tree_from_model(
    model_file: str | Path,
    *,
    name: str | None = None,
    grasp: str | None = None,
    grasp_fraction: float = 1.0,
    levels: int | None = None,
    bounds=None,
    repair_inertia: str | None = None,
    **tree_kwargs: Any,
):
    """A tree description of a user's URDF/MJCF: one branch per link below the first jointed
    one (named like the link; ``fixed`` where it has no hinge), with its length and radius from
    the link's axis and cylinder (:func:`link_axis`), its fork angles from the link frames, and a
    ``model:`` section with the file, its sha256 and the joint names where they differ from the
    link names. The simulator runs the file itself; the branch geometry is for summaries and
    default prior scales. ``grasp`` defaults to the last link; ``levels`` to 1."""
    import mujoco

    from .description import Branch, make_tree, rot_y, rot_z

    path = Path(model_file).resolve()
    spec = _load_spec(path)
    m = _probe(spec, path)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    hinge = mujoco.mjtJoint.mjJNT_HINGE
    jointed = [
        any(
            m.jnt_type[j] == hinge
            for j in range(m.body_jntadr[i], m.body_jntadr[i] + m.body_jntnum[i])
        )
        for i in range(m.nbody)
    ]
    under = [False] * m.nbody
    for i in range(1, m.nbody):
        under[i] = jointed[i] or under[int(m.body_parentid[i])]
    roots = [i for i in range(1, m.nbody) if under[i] and not under[int(m.body_parentid[i])]]
    if len(roots) != 1:
        raise TreeFileError(
            f"{path}: a tree needs exactly one jointed root link, found "
            f"{[m.body(i).name for i in roots]}"
        )
    joints: dict[str, str] = {}
    branches, info, frames = [], {}, {}
    for i in range(1, m.nbody):
        if not under[i]:
            continue
        bname = m.body(i).name
        ax = link_axis(m, i)
        if ax is None:
            raise TreeFileError(
                f"{path}: link '{bname}' has no cylinder/capsule geom and no child "
                "link: its length is unknown"
            )
        a, e, r = ax
        length = float(np.linalg.norm(e - a))
        radius = min(r if r else length / 20, length)
        hinges = [
            j
            for j in range(m.body_jntadr[i], m.body_jntadr[i] + m.body_jntnum[i])
            if m.jnt_type[j] == hinge
        ]
        if hinges and m.joint(hinges[0]).name != bname:
            joints[bname] = m.joint(hinges[0]).name
        info[i] = (a, e, length)
        parent = int(m.body_parentid[i])
        xmat = d.xmat[i].reshape(3, 3)
        d_world = xmat @ (e - a) / length
        kw: dict[str, Any] = {}
        if i == roots[0]:
            pitch = math.degrees(math.asin(float(np.clip(d_world[2], -1, 1))))
            yaw = math.degrees(math.atan2(d_world[1], d_world[0]))
            frames[i] = rot_z(math.radians(yaw)) @ rot_y(-math.radians(pitch))
        else:
            pa, pe, plen = info[parent]
            kw["angle_deg"], kw["azimuth_deg"], frames[i] = _fork(
                frames[parent], d.xmat[parent].reshape(3, 3), xmat, d_world
            )
            kw["attach"] = float(
                np.clip((np.asarray(m.body_pos[i]) - pa) @ (pe - pa) / plen**2, 1e-6, 1.0)
            )
        branches.append(
            Branch(
                name=bname,
                parent=None if i == roots[0] else m.body(parent).name,
                length=length,
                radius=radius,
                fixed=not hinges,
                **kw,
            )
        )
    ra = info[roots[0]][0]
    sec = {"file": str(path), "sha256": file_sha256(path)}
    if joints:
        sec["joints"] = joints
    if repair_inertia is not None:
        sec["repair_inertia"] = repair_inertia
    tree_kwargs.setdefault(
        "base_position",
        tuple(float(x) for x in d.xpos[roots[0]] + d.xmat[roots[0]].reshape(3, 3) @ ra),
    )
    tree_kwargs.setdefault("base_pitch_deg", pitch)
    tree_kwargs.setdefault("base_yaw_deg", yaw)
    tree_kwargs.setdefault("gravity", tuple(float(x) for x in spec.option.gravity))
    return make_tree(
        branches,
        grasp_branch=grasp or branches[-1].name,
        grasp_fraction=grasp_fraction,
        levels=levels or 1,
        bounds=bounds,
        name=name or path.stem,
        model=parse_model_section(sec, str(path)),
        **tree_kwargs,
    )
