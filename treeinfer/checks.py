"""Plausibility checks before inference and fit checks after it: never a confident wrong answer.

Before inference, :func:`data_checks` looks at the tree and the training trajectories together
and returns :class:`Finding` s (``error`` where the data are certainly wrong, ``warning`` where
they are suspicious), each naming the file and the evidence:

- **scale**: the quasi-static compliance of the data (least-squares slope of displacement on
  force, m/N) against what the tree can do with its inferred joints anywhere in the prior box
  (:func:`static_compliance`, a lever-arm estimate, see below): centimetres or millimetres read
  as metres, kilonewtons read as newtons, or a stiffness outside the prior box show up as a
  compliance 10-1000x outside that range;
- **mixed units** between files (one file's compliance far from the others');
- **swapped columns** (the inverse hypothesis fits the tree where the recorded one cannot);
- **sign**: displacement that moves against the force;
- **reach**: displacement larger than the grasp point can move at all;
- **rest**: displacement that does not start near zero while the force does;
- **velocity**: a recorded velocity column that does not integrate to the displacement
  (negated, zero, random, or in other units);
- **time unit**: the displacement moving implausibly fast for a branch (time in minutes);
- **duplicates**: byte-identical files or identical arrays (the same evidence counted twice);
- **all-zero** force or displacement (the posterior would be the prior).

After inference, :func:`fit_checks` judges the training fit: residuals far beyond the noise
scale (fitted, or implied by kT through :func:`noise_from_kT`), the share of training points
outside the predictive band, posterior mass at a prior-box edge, and a posterior no narrower
than the prior (the data had no effect). It returns a :class:`FitVerdict` with ``status`` one
of ``ok | warning | poor_fit`` and the reasons. The command line ends a ``poor_fit`` run with
exit code 4 (:data:`POOR_FIT_EXIT_CODE`) unless ``--allow-poor-fit``.

Static compliance. A downward force ``f`` at the grasp point moves it ``f * C`` down once the
tree has settled, with ``C = s K^-1 s^T``: ``s`` the grasp site's Jacobian along gravity and
``K`` the joint stiffness matrix (springs plus gravity's geometric stiffness), both taken from
plain MuJoCo at the rest pose the branch sags to under its own weight
(:func:`static_compliance`). With stiff joints ``C`` reduces to the lever-arm sum
``sum_j s_j^2 / Kp_j`` (:func:`lever_arm_compliance`); with soft ones the sag changes the lever
arms several-fold, hence the settled form. Dynamics are left out: the flagged factors (3x to
1000x outside the prior box's range) are far beyond what a pull's inertia and damping change.
tests/test_checks.py checks ``C`` against settled MJX rollouts.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .tree import Tree, world_frames

__all__ = [
    "POOR_FIT_EXIT_CODE",
    "Finding",
    "FitVerdict",
    "data_checks",
    "errors_of",
    "fit_checks",
    "fit_verdict_from_run",
    "format_findings",
    "grasp_reach",
    "lever_arm_compliance",
    "noise_from_kT",
    "preflight",
    "simulation_cost_check",
    "static_compliance",
]

POOR_FIT_EXIT_CODE = 4

# thresholds (ratios are observed / allowed)
SCALE_WARN = 3.0  # compliance this far outside the prior box's range: warning
SCALE_ERROR = 30.0  # ... this far: error (a unit mistake, not a prior box a little too narrow)
MIXED_RATIO = 10.0  # files whose compliance differs from the median by this factor
REST_FRACTION = 0.25  # |x[0]| beyond this share of the displacement's range ...
REST_MIN = 0.01  # ... and beyond 1 cm is not "at rest"
REST_FORCE = 0.1  # "force near zero at the start": below this share of max |force|
VELOCITY_MISMATCH = 0.5  # relative misfit of integrated velocity vs displacement
MAX_BRANCH_SPEED = 2.0  # m/s; grasp-point speeds above this look like time in minutes
ZERO_ATOL = 1e-12


class Finding(NamedTuple):
    """One result of a check: ``severity`` ``"error"`` or ``"warning"``; ``file`` the file (or
    tree) it concerns; ``check`` a short id; ``message`` the evidence in words."""

    severity: str
    file: str
    check: str
    message: str

    def __str__(self) -> str:
        return f"{self.severity}: {self.file}: {self.message}"


def errors_of(findings: Sequence[Finding]) -> list[Finding]:
    return [f for f in findings if f.severity == "error"]


def format_findings(findings: Sequence[Finding]) -> str:
    """One line per finding, errors first (for the CLI)."""
    order = sorted(findings, key=lambda f: (f.severity != "error", f.file, f.check))
    return "\n".join(str(f) for f in order)


# ---- what the tree can do --------------------------------------------------------------------
def _lever_terms(tree: Tree, grasp_fraction: float | None = None) -> list[tuple[str, float]]:
    """``[(joint name, s_j)]``: downward motion of the grasp point per radian at each hinge
    between the root and the grasped branch (fixed branches have no hinge)."""
    frames = world_frames(tree)
    g = np.asarray(tree.gravity, float)
    g_hat = g / np.linalg.norm(g)
    frac = tree.grasp_fraction if grasp_fraction is None else float(grasp_fraction)
    gb = tree.branch(tree.grasp_branch)
    pos, rot = frames[gb.name]
    p = pos + rot @ np.array([frac * gb.length, 0.0, 0.0])
    out = []
    for name in tree.ancestors(tree.grasp_branch):
        if tree.branch(name).fixed:
            continue
        o, r = frames[name]
        axis = r[:, 1]  # hinge about the branch frame's y-axis
        out.append((name, float(g_hat @ np.cross(axis, p - o))))
    return out


def lever_arm_compliance(
    tree: Tree, kp: dict[str, float] | None = None, grasp_fraction: float | None = None
) -> float:
    """Small-rotation compliance (m/N) at the *unloaded geometric* pose, ignoring gravity:
    ``sum_j s_j^2 / Kp_j`` (module docstring). ``kp``: stiffness of inferred joints by name
    (N m/rad); other joints use the tree's fixed gains."""
    kp = kp or {}
    total = 0.0
    for name, s in _lever_terms(tree, grasp_fraction):
        k = kp.get(name, tree.fixed_gains(name)[0])
        total += s * s / float(k)
    return total


def static_compliance(
    tree: Tree, kp: dict[str, float] | None = None, grasp_fraction: float | None = None
) -> float:
    """Quasi-static compliance (m/N) of the grasp point along gravity at the tree's settled
    rest pose, gravity's stiffness included: ``s K^-1 s^T`` with ``s = g_hat . J_site`` (the
    site Jacobian) and ``K`` the Jacobian of the static joint torque (springs + gravity), both
    from plain MuJoCo at the pose :func:`treeinfer.simulator.settle_reference` finds. ``inf``
    when the pose is not stable (``K`` not positive definite).

    Why not only the lever-arm formula: a soft joint sags under the branch's own weight, which
    moves the grasp point and changes its lever arms several-fold (tested against MuJoCo).
    """
    import mujoco

    from .export import GRASP_SITE, to_mjmodel

    settle_reference = _sim_attr("settle_reference")

    kp = kp or {}
    m = to_mjmodel(tree)
    for name, k in kp.items():
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
        m.jnt_stiffness[j] = float(k)
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, GRASP_SITE)
    if grasp_fraction is not None:
        gb = tree.branch(tree.grasp_branch)
        m.site_pos[sid] = np.array([float(grasp_fraction) * gb.length, 0.0, 0.0])
    q0 = settle_reference(m)
    d = mujoco.MjData(m)

    def torque(q):
        d.qpos[:] = q
        d.qvel[:] = 0
        mujoco.mj_forward(m, d)
        return d.qfrc_passive - d.qfrc_bias

    h = 1e-6
    kmat = np.zeros((m.nv, m.nv))
    for i in range(m.nv):
        e = np.zeros(m.nq)
        e[i] = h
        kmat[:, i] = -(torque(q0 + e) - torque(q0 - e)) / (2 * h)
    kmat = 0.5 * (kmat + kmat.T)
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    jacp = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jacp, None, sid)
    g = np.asarray(tree.gravity, float)
    s = (g / np.linalg.norm(g)) @ jacp
    try:
        np.linalg.cholesky(kmat)
    except np.linalg.LinAlgError:
        return math.inf
    return float(s @ np.linalg.solve(kmat, s))


def _sim_attr(name: str):
    """``name`` from the simulator package (``treeinfer.sim`` after the restructuring, else
    ``treeinfer.simulator``)."""
    import importlib

    for mod in ("treeinfer.sim.reference", "treeinfer.sim", "treeinfer.simulator"):
        try:
            m = importlib.import_module(mod)
        except ImportError:
            continue
        if hasattr(m, name):
            return getattr(m, name)
    raise ImportError(f"treeinfer has no simulator attribute {name!r}")


MAX_SUBSTEPS = 2000  # simulation steps per observation beyond which a run cannot finish


def simulation_cost_check(
    tree: Tree,
    obs_dt: float,
    tree_file: str | os.PathLike | None = None,
    max_substeps: int = MAX_SUBSTEPS,
) -> list[Finding]:
    """An error if the prior box's stiffest corner needs more than ``max_substeps`` simulation
    steps per observation (the simulator's own rule, :func:`choose_substeps`): a tiny twig with
    a huge Kp bound would otherwise run for days. Names the Kp bound to lower."""
    import mujoco

    from .export import to_mjmodel

    choose_substeps = _sim_attr("choose_substeps")
    m = to_mjmodel(tree)
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in tree.inferred]
    kp_max = [tree.bounds[n].kp[1] for n in tree.inferred]
    n = int(choose_substeps(m, ids, kp_max, float(obs_dt)))
    if n <= max_substeps:
        return []
    name = str(tree_file) if tree_file is not None else f"tree '{tree.name}'"
    return [
        Finding(
            "error",
            name,
            "simulation-cost",
            f"the prior box's upper Kp bounds ({', '.join(f'{k:g}' for k in kp_max)} N m/rad) on "
            f"branches this light need {n} simulation steps per {obs_dt:g} s sample (limit "
            f"{max_substeps}); lower inference.prior.kp's upper bound or check the branch "
            "masses",
        )
    ]


def compliance_range(tree: Tree, grasp_fraction: float | None = None) -> tuple[float, float]:
    """(stiffest, softest) compliance in m/N over the prior box (all inferred Kp at the upper,
    then at the lower bound)."""
    hi = {n: tree.bounds[n].kp[1] for n in tree.inferred}
    lo = {n: tree.bounds[n].kp[0] for n in tree.inferred}
    return static_compliance(tree, hi, grasp_fraction), static_compliance(tree, lo, grasp_fraction)


def grasp_reach(tree: Tree, grasp_fraction: float | None = None) -> float:
    """Largest distance (m) from a hinge to the grasp point: the grasp point cannot move
    further than twice this."""
    frames = world_frames(tree)
    frac = tree.grasp_fraction if grasp_fraction is None else float(grasp_fraction)
    gb = tree.branch(tree.grasp_branch)
    pos, rot = frames[gb.name]
    p = pos + rot @ np.array([frac * gb.length, 0.0, 0.0])
    return max(float(np.linalg.norm(p - frames[n][0])) for n in tree.ancestors(tree.grasp_branch))


# ---- per-trajectory statistics ---------------------------------------------------------------
def _compliance(force: np.ndarray, disp: np.ndarray) -> float | None:
    """Least-squares slope of displacement on force through the start point (m/N); None when
    the force does not vary."""
    df = force - force[0]
    dx = disp - disp[0]
    den = float(df @ df)
    if den <= ZERO_ATOL:
        return None
    return float(df @ dx) / den


def _integrated(v: np.ndarray, dt: float) -> np.ndarray:
    """Trapezoidal integral of ``v`` from 0 (same length)."""
    out = np.zeros_like(v)
    out[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)
    return out


def _label(t, paths, i) -> str:
    if paths is not None and i < len(paths) and paths[i] is not None:
        return str(paths[i])
    return t.source or f"trajectory {i}"


def _sha256(path) -> str | None:
    try:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        return h.hexdigest()
    except OSError:
        return None


def _scale_causes(c: float, c_stiff: float, c_soft: float) -> list[str]:
    """Unit mistakes that would bring the compliance ``c`` (m/N) into the tree's range."""

    def fits(x):
        return c_stiff / SCALE_WARN <= x <= c_soft * SCALE_WARN

    out = []
    if fits(1.0 / c):
        out.append("the force and displacement columns were swapped")
    for factor, what in (
        (100.0, "displacement is in cm (not m)"),
        (1000.0, "displacement is in mm (not m), or force in kN (not N)"),
    ):
        if fits(c / factor):
            out.append(what)
    return out


def _ratio_text(r: float) -> str:
    return f"{r:.3g}x"


def data_checks(
    tree: Tree,
    trajectories: Sequence,
    paths: Sequence[str | os.PathLike | None] | None = None,
    grasp_fraction: float | None = None,
    tree_file: str | os.PathLike | None = None,
) -> list[Finding]:
    """Plausibility findings for training ``trajectories`` on ``tree`` (module docstring).

    Args:
      tree: the tree (with its prior box). trajectories: validated
        :class:`~treeinfer.trajectories.Trajectory` s (time s, force N, displacement m,
        optional velocity m/s, all positive downward). paths: their files (byte-identical
        duplicates; messages), default ``Trajectory.source``. grasp_fraction: where the data
        were recorded (None: the tree's). tree_file: named in tree findings.

    Returns:
      Findings, errors where the data are certainly wrong, warnings otherwise.
    """
    from .tree import tree_scale_warnings

    out: list[Finding] = []
    tname = str(tree_file) if tree_file is not None else f"tree '{tree.name}'"
    out += [Finding("warning", tname, "tree-scale", w) for w in tree_scale_warnings(tree)]
    c_stiff, c_soft = compliance_range(tree, grasp_fraction)
    # the compliance range is that of a pull down at the tree's grasp: no scale check for other
    # pull directions (the tree file's pull.direction), or where a down pull cannot move the
    # grasp point (a vertical stem: its compliance along gravity is zero)
    scale_ok = c_soft > 0 and c_stiff > 0 and getattr(tree, "pull_direction", "down") == "down"
    reach = grasp_reach(tree, grasp_fraction)
    comps: dict[int, float] = {}

    for i, t in enumerate(trajectories):
        name = _label(t, paths, i)
        f = np.asarray(t.force, float)
        x = np.asarray(t.displacement, float)
        dt = float(t.dt)
        fmax, xrange = float(np.max(np.abs(f))), float(np.ptp(x))
        if fmax <= ZERO_ATOL and float(np.max(np.abs(x))) <= ZERO_ATOL:
            out.append(
                Finding(
                    "error",
                    name,
                    "all-zero",
                    "force and displacement are all zero: nothing to learn from "
                    "(the posterior would be the prior)",
                )
            )
            continue
        if fmax <= ZERO_ATOL:
            out.append(
                Finding(
                    "error",
                    name,
                    "all-zero",
                    f"force is zero throughout while the displacement spans {xrange:.3g} m: "
                    "the force column is missing or was not recorded",
                )
            )
            continue
        if float(np.max(np.abs(x))) <= ZERO_ATOL:
            out.append(
                Finding(
                    "error",
                    name,
                    "all-zero",
                    f"displacement is zero throughout while the force reaches {fmax:.3g} N: "
                    "the displacement column is missing or was not recorded",
                )
            )
            continue

        # reach: the grasp point cannot move further than its lever arm allows
        xmax = float(np.max(np.abs(x)))
        if xmax > 2.0 * reach:
            out.append(
                Finding(
                    "error",
                    name,
                    "reach",
                    f"displacement reaches {xmax:.3g} m but the grasp point is {reach:.3g} m "
                    f"from the nearest hinge and cannot move more than {2 * reach:.3g} m: "
                    "displacement in cm/mm, swapped columns, or an offset?",
                )
            )

        # rest: displacement from the rest position starts near 0 when the force does
        x0 = float(x[0])
        if abs(x0) > max(REST_FRACTION * max(xrange, 1e-12), REST_MIN):
            sev = "error" if abs(f[0]) <= REST_FORCE * fmax else "warning"
            out.append(
                Finding(
                    sev,
                    name,
                    "rest",
                    f"displacement starts at {x0:.3g} m (its range is {xrange:.3g} m) while "
                    f"the force starts at {f[0]:.3g} N: displacement must be measured from "
                    "the branch's rest position (subtract the first sample?)",
                )
            )

        # sign and scale through the quasi-static compliance
        c = _compliance(f, x)
        if c is not None:
            comps[i] = c
            corr = float(np.corrcoef(f, x)[0, 1]) if np.ptp(x) > 0 else 0.0
            if c < 0 and corr < -0.3:
                out.append(
                    Finding(
                        "error",
                        name,
                        "sign",
                        f"displacement moves against the force (correlation {corr:.2f}, slope "
                        f"{c:.3g} m/N): both are positive downward; flip the sign of one "
                        "column (e.g. --force-sign -1 on import-bag)",
                    )
                )
            elif c > 0 and scale_ok:
                if c > c_soft * SCALE_WARN:
                    r = c / c_soft
                    causes = _scale_causes(c, c_stiff, c_soft)
                    sev = "error" if r > SCALE_ERROR or causes else "warning"
                    hint = (
                        "; ".join(causes)
                        if causes
                        else "displacement in cm or mm instead of m, or force in kN instead of N?"
                    )
                    out.append(
                        Finding(
                            sev,
                            name,
                            "scale",
                            f"displacement per newton is {c:.3g} m/N, {_ratio_text(r)} more than "
                            f"the tree allows at the softest prior stiffness ({c_soft:.3g} m/N, "
                            f"Kp at the prior box's lower bounds); it would fit if: {hint}",
                        )
                    )
                elif c < c_stiff / SCALE_WARN:
                    r = c_stiff / c
                    sev = "error" if r > SCALE_ERROR * 10 else "warning"
                    out.append(
                        Finding(
                            sev,
                            name,
                            "scale",
                            f"displacement per newton is {c:.3g} m/N, {_ratio_text(r)} less than "
                            f"the tree gives at the stiffest prior stiffness ({c_stiff:.3g} m/N, "
                            "Kp at the prior box's upper bounds): the branch may be stiffer than "
                            "the prior box allows (widen inference.prior.kp), or displacement "
                            "is in km / force in mN?",
                        )
                    )

        # velocity column against the displacement it should be the slope of
        if t.velocity is not None:
            v = np.asarray(t.velocity, float)
            dx = x - x[0]
            xi = _integrated(v, dt)
            scale = float(np.sqrt(np.mean(dx**2)))
            if scale > ZERO_ATOL:
                mis = float(np.sqrt(np.mean((xi - dx) ** 2))) / scale
                if mis > VELOCITY_MISMATCH:
                    den = float(xi @ xi)
                    a = float(xi @ dx) / den if den > ZERO_ATOL else 0.0
                    scaled_fit = float(np.sqrt(np.mean((a * xi - dx) ** 2))) / scale
                    if float(np.max(np.abs(v))) <= ZERO_ATOL:
                        why = "the velocity column is all zero"
                    elif scaled_fit > VELOCITY_MISMATCH:
                        why = (
                            "the velocity column does not follow the displacement "
                            "(noise or another signal?)"
                        )
                    elif a < -0.5 and abs(abs(a) - 1) < 0.3:
                        why = "the velocity column has the opposite sign"
                    elif abs(a) > 3 or (0 < abs(a) < 1 / 3):
                        why = (
                            "the velocity column is "
                            f"{1 / a if a else float('inf'):.3g}x the slope of "
                            "the displacement (another unit, or time in other units?)"
                        )
                    else:
                        why = (
                            "the velocity column does not follow the displacement "
                            "(noise or another signal?)"
                        )
                    out.append(
                        Finding(
                            "error",
                            name,
                            "velocity",
                            f"{why}: integrated, it misses the displacement by {mis:.0%} of its "
                            "RMS; drop the column to differentiate the displacement instead",
                        )
                    )

        # time unit: a branch grasp point does not move at metres per second
        if len(x) >= 3:
            speed = float(np.max(np.abs(np.diff(x)))) / dt
            # smooth over noise: the largest change over 10 samples
            k = min(10, len(x) - 1)
            speed_k = float(np.max(np.abs(x[k:] - x[:-k]))) / (k * dt)
            if speed_k > MAX_BRANCH_SPEED:
                out.append(
                    Finding(
                        "warning",
                        name,
                        "time-unit",
                        f"the grasp point moves at {speed_k:.3g} m/s (steps of {dt:.3g} s; peak "
                        f"single-step {speed:.3g} m/s), implausibly fast for a branch pull: "
                        "is time in minutes instead of seconds (or displacement not in metres)?",
                    )
                )

    # mixed units between files
    if len(comps) >= 2:
        med = float(np.median(list(comps.values())))
        for i, c in comps.items():
            if c > 0 and med > 0 and max(c / med, med / c) > MIXED_RATIO:
                name = _label(trajectories[i], paths, i)
                r = c / med
                out.append(
                    Finding(
                        "error",
                        name,
                        "mixed-units",
                        f"displacement per newton {c:.3g} m/N is {_ratio_text(max(r, 1 / r))} "
                        f"{'more' if r > 1 else 'less'} than the other files' median ({med:.3g} "
                        "m/N): one file in other units (cm vs m, kN vs N)?",
                    )
                )

    # duplicates: identical bytes or identical arrays
    seen: dict[str, int] = {}
    for i, t in enumerate(trajectories):
        key = None
        p = paths[i] if paths is not None and i < len(paths) else None
        if p is not None and Path(p).is_file():
            digest = _sha256(p)
            key = f"file:{digest}" if digest else None
        arr_key = (
            "arr:"
            + hashlib.sha256(
                np.ascontiguousarray(
                    np.stack([np.asarray(t.force, float), np.asarray(t.displacement, float)])
                ).tobytes()
            ).hexdigest()
        )
        for k in (key, arr_key):
            if k is None:
                continue
            if k in seen:
                j = seen[k]
                what = (
                    "byte-identical to"
                    if k.startswith("file:")
                    else "has the same force and displacement as"
                )
                out.append(
                    Finding(
                        "error",
                        _label(t, paths, i),
                        "duplicate",
                        f"{what} {_label(trajectories[j], paths, j)}: the same recording twice "
                        "counts its evidence twice (overconfident posterior); remove one",
                    )
                )
                break
            seen[k] = i
    return out


# ---- after inference -------------------------------------------------------------------------
def noise_from_kT(kT: float, n_steps: int, dt: float, omega2: float = 0.0) -> float:
    """Displacement noise sigma (m) for which :func:`treeinfer.likelihood.suggest_kT` gives
    ``kT``: its inverse, ``sigma = kT sqrt(T) / (1 + sqrt(2) dt omega2)``."""
    return float(kT) * math.sqrt(n_steps) / (1.0 + math.sqrt(2.0) * float(dt) * float(omega2))


class FitVerdict(NamedTuple):
    """``status``: ``ok``, ``warning`` or ``poor_fit``; ``reasons``: one sentence each;
    ``measures``: the numbers behind them (JSON-ready), for summary.json."""

    status: str
    reasons: list[str]
    measures: dict

    def as_dict(self) -> dict:
        return {
            "status": self.status,
            "reasons": list(self.reasons),
            "measures": dict(self.measures),
        }


RESIDUAL_WARN, RESIDUAL_POOR = 3.0, 10.0  # RMS residual / noise sigma
OUTSIDE_WARN, OUTSIDE_POOR = 3.0, 0.5  # x (1 - level); absolute fraction
EDGE_BAND = 0.05  # share of the log box width counted as "at the edge"
EDGE_SHARE = 0.5  # share of particles at/beyond one edge that is flagged
NO_EFFECT = 0.9  # posterior std / prior std (log space) above which the data had no effect


def fit_checks(
    *,
    residuals=None,
    mask=None,
    noise_sigma: float | None = None,
    fraction_outside: float | None = None,
    level: float = 0.95,
    theta=None,
    lower=None,
    upper=None,
    labels: Sequence[str] | None = None,
    valid=None,
) -> FitVerdict:
    """Judge a finished run's training fit.

    Args:
      residuals: [B, T] m, predictive mean minus observed displacement (or None).
      mask: [B, T] bool, real samples. noise_sigma: m, the fitted displacement noise, or
        :func:`noise_from_kT` of the run's kT.
      fraction_outside: share (0-1) of training points outside the ``level`` predictive band.
      theta: [P, D] final particles in log space; lower, upper: [D] log prior box;
        labels: D names; valid: [P] bool, particles to use.

    Returns:
      :class:`FitVerdict`.
    """
    poor: list[str] = []
    warn: list[str] = []
    m: dict = {}
    if residuals is not None and noise_sigma is not None and noise_sigma > 0:
        r = np.asarray(residuals, float)
        mk = np.ones(r.shape, bool) if mask is None else np.asarray(mask, bool)
        ok = mk & np.isfinite(r)
        if ok.any():
            rms = float(np.sqrt(np.mean(r[ok] ** 2)))
            ratio = rms / float(noise_sigma)
            m["residual_rms_m"], m["noise_sigma_m"], m["residual_to_noise"] = (
                rms,
                float(noise_sigma),
                ratio,
            )
            msg = (
                f"training residuals (RMS {rms:.3g} m) are {ratio:.3g}x the noise scale "
                f"({noise_sigma:.3g} m): the model does not explain the data"
            )
            if ratio > RESIDUAL_POOR:
                poor.append(msg)
            elif ratio > RESIDUAL_WARN:
                warn.append(msg)
    if fraction_outside is not None and math.isfinite(fraction_outside):
        expected = 1.0 - level
        m["fraction_outside"] = float(fraction_outside)
        msg = (
            f"{fraction_outside:.1%} of training points lie outside the {level:.0%} "
            "predictive band "
            f"(about {expected:.0%} expected)"
        )
        if fraction_outside > OUTSIDE_POOR:
            poor.append(msg)
        elif fraction_outside > OUTSIDE_WARN * expected:
            warn.append(msg)
    if theta is not None and lower is not None and upper is not None:
        th = np.asarray(theta, float)
        lo, hi = np.asarray(lower, float), np.asarray(upper, float)
        ok = np.all(np.isfinite(th), axis=1)
        if valid is not None:
            ok &= np.asarray(valid, bool)
        th = th[ok]
        labels = list(labels) if labels is not None else [f"theta[{j}]" for j in range(th.shape[1])]
        if len(th) >= 2:
            width = hi - lo
            prior_std = width / math.sqrt(12.0)  # uniform on the log box
            post_std = th.std(axis=0, ddof=1)
            ratio = post_std / prior_std
            m["posterior_to_prior_std"] = {lab: float(r) for lab, r in zip(labels, ratio)}
            at_lo = np.mean(th <= lo + EDGE_BAND * width, axis=0)
            at_hi = np.mean(th >= hi - EDGE_BAND * width, axis=0)
            med = np.median(th, axis=0)
            edge = {}
            for j, lab in enumerate(labels):
                for share, side, bound in ((at_lo[j], "lower", lo[j]), (at_hi[j], "upper", hi[j])):
                    if share >= EDGE_SHARE:
                        edge[lab] = side
                        beyond = med[j] < lo[j] if side == "lower" else med[j] > hi[j]
                        msg = (
                            f"{lab}: {share:.0%} of the posterior sits at or beyond the "
                            f"prior box's {side} bound ({math.exp(bound):.4g}; "
                            f"median {math.exp(med[j]):.4g}): the "
                            f"data may lie outside the prior; widen inference.prior"
                        )
                        (poor if beyond else warn).append(msg)
            m["at_prior_edge"] = edge
            flat = [lab for lab, r in zip(labels, ratio) if r > NO_EFFECT]
            if flat and len(flat) == len(labels):
                poor.append(
                    f"the posterior is as wide as the prior for every parameter (std ratio "
                    f"{float(ratio.min()):.2f}-{float(ratio.max()):.2f}): the data had no effect "
                    "(kT far too large, or no force/displacement signal?)"
                )
            elif flat:
                warn.append(
                    f"the data barely narrowed {', '.join(flat)} (posterior std > "
                    f"{NO_EFFECT:.0%} of the prior's)"
                )
    status = "poor_fit" if poor else "warning" if warn else "ok"
    return FitVerdict(status, poor + warn, m)


# ---- glue for the run layer ------------------------------------------------------------------
def preflight(
    tree: Tree,
    trajectories: Sequence,
    paths: Sequence | None = None,
    tree_file: str | os.PathLike | None = None,
    grasp_fraction: float | None = None,
) -> tuple[list[Finding], list[Finding]]:
    """(errors, warnings) of :func:`data_checks`, for ``infer`` to print before sampling: it
    stops with exit code 2 on errors, prints warnings and goes on."""
    found = data_checks(
        tree, trajectories, paths=paths, grasp_fraction=grasp_fraction, tree_file=tree_file
    )
    if trajectories:
        found += simulation_cost_check(tree, float(trajectories[0].dt), tree_file)
    return errors_of(found), [f for f in found if f.severity != "error"]


def fit_verdict_from_run(
    problem, posterior, fit: dict, noise_sigma: float | None = None, level: float = 0.95
) -> FitVerdict:
    """:func:`fit_checks` on what :func:`treeinfer.runs.run_inference` has at hand.

    Args:
      problem: the inference problem (``obs`` [B, T] training data, ``lower``/``upper`` log
        prior box [D], ``labels``). posterior: ``theta`` [P, D] log gains.
      fit: the run's training fit: ``stable`` [P], ``prediction`` (``mean`` [B, T] m; None if
        too few particles were stable), ``metrics`` (``fraction_outside``).
      noise_sigma: the fitted displacement noise (m) if the noise model has one; None: the
        residual test is skipped (kT is a temperature the user chose, not a measured noise, so
        the sigma it implies is no yardstick for residuals).
    """
    pred = fit.get("prediction")
    metrics = fit.get("metrics") or {}
    residuals = mask = None
    if pred is not None:
        residuals = np.asarray(pred.mean, float) - np.asarray(problem.obs.displacement, float)
        mask = np.asarray(problem.obs.mask, bool)
    frac = metrics.get("fraction_outside")
    verdict = fit_checks(
        residuals=residuals,
        mask=mask,
        noise_sigma=noise_sigma,
        fraction_outside=None if frac is None else float(frac),
        level=level,
        theta=np.asarray(posterior.theta, float),
        lower=problem.lower,
        upper=problem.upper,
        labels=list(problem.labels),
        valid=np.asarray(fit.get("stable"), bool) if fit.get("stable") is not None else None,
    )
    if pred is None:  # the unstable-share limit already judged this; do not fail twice
        status = verdict.status if verdict.status == "poor_fit" else "warning"
        return FitVerdict(
            status,
            ["too few stable particles to judge the training fit", *verdict.reasons],
            verdict.measures,
        )
    return verdict
