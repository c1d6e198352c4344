"""A run's configuration (``config.json``): built and validated once from the options, read
back from old and new run folders, hashed for resume.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from ..data.channel_files import channel_manifest as _channel_manifest
from ..data.trajectories import (
    TRUE_PARAMS_FILE,
)
from ..errors import ConfigError, check_positive
from ..inference.problem import DEFAULT_ETA, DEFAULT_PRIOR_SIGMA
from ..inference.samplers import sampler_spec
from ..io.provenance import file_sha256, versions
from ..model.boltzmann import DEFAULT_KT
from ..model.noise import KINDS as LIKELIHOODS
from ..model.noise import NOISE_KINDS, check_sigma
from ..sim import BACKENDS, FORCE_INTERPS
from ..tree.description import tree_to_dict
from .checkpoint import CHECKPOINT_FILE, partial_dir
from .inputs import (  # noqa: F401 -- re-exported: their old home
    RunInputs,
    check_data_unchanged,
    load_run_inputs,
    load_run_tree,
    read_true_params,
)
from .sampler_record import LAPLACE_WARMUP, laplace_mh_proposal, sampler_settings  # noqa: F401

RUN_FORMAT = 1
# --reinit-stragglers' default: stuck particles are moved next to the bulk up to this iteration
# (the first half of the default 200-iteration cap: the warm-up)
DEFAULT_REINIT = 100
# The defaults before issue 27 (the paper's Boltzmann loss, uniform start, fixed iteration
# count): an option a config.json does not give takes these, so a run folder written before
# reads back (and resumes, and hashes) with the values it was made with.
LEGACY_DEFAULTS = {
    "likelihood": "boltzmann",
    "noise_force": None,
    "init": "uniform",
    "reinit_stragglers": 0,
    "stop_when_converged": False,
}
GRADIENT_CHOICES = ("fd", "jvp")
INIT_CHOICES = ("auto", "uniform", "laplace", "importance")


def _count(flag: str, v, minimum: int, why: str = "") -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
        raise ConfigError(f"{flag}: must be an integer >= {minimum}{why}, got {v!r}")
    return int(v)


# float32 log-densities: losses of ~1e-3 or more over kT must stay below ~1e38
MIN_KT = 1e-30


def _positive(flag: str, v, what: str = "a positive number") -> float:
    """:func:`treeinfer.errors.check_positive` naming the flag."""
    return check_positive(v, f"{flag}:", what)


def check_share(s, flag: str = "--max-unstable-share") -> float | None:
    if s is not None and not (math.isfinite(s) and 0.0 <= s <= 1.0):
        raise ConfigError(f"{flag}: must be a fraction in [0, 1], got {s:g}")
    return None if s is None else float(s)


@dataclass(frozen=True)
class RunConfig:
    """A run's ``config.json``: the options of one ``treeinfer infer`` run, validated once
    (ConfigError naming the flag), and the run's record.

    ``RunConfig.from_json(config.json)`` reads a run's file (old and new run folders) and
    ``to_json()`` writes it; the file keeps its layout (the options in ``"options"``, the same
    keys as before this class existed, so old run folders read back and hash the same). Every
    option but ``out``, ``force`` and ``max_unstable_share`` enters the resume hash
    (:func:`~.provenance.config_hash`). ``RunConfig(tree=..., data=..., out=..., **options)``
    validates options alone (the record fields stay None).

    Defaults (issue 27): the calibrated measurement model, ``likelihood="gaussian"`` with
    ``noise_force="default"`` (``"auto"`` where the model offers the term and the recorded
    force's noise can be estimated, else off:
    :func:`treeinfer.inference.problem.default_noise_force`), ``init="auto"`` (the start pipeline,
    :mod:`treeinfer.inference.start_pipeline`), ``reinit_stragglers=DEFAULT_REINIT`` and
    ``stop_when_converged=True``. A ``config.json`` that leaves one of these options out was written
    before them and reads back with
    :data:`LEGACY_DEFAULTS` (the paper's Boltzmann loss, uniform start, every iteration).

    Attributes: tree, data, out (absolute paths as strings); sampler (a registry name);
    particles (>= 2); iterations (>= 1); backend ("auto", "fused", "mjx"); kT (loss units per
    nat, > 0, or "auto": from the data's noise estimate); likelihood ("boltzmann", "gaussian",
    "student_t", "ar1": :func:`treeinfer.model.likelihood.likelihood_terms`); noise_displacement (m,
    None: inferred / estimated); noise_force (None: off; N, "P%" or "auto": the recorded force's
    noise as an errors-in-variables term, gaussian only, :mod:`treeinfer.model.force_noise`);
    noise_velocity (None: velocity term off, the default; m/s: the velocity residual's noise
    std, generative likelihoods only); seed (>= 0); eta (nats per unit of log gain, > 0);
    grasp_fraction (None or in (0, 1]); max_unstable_share (in [0, 1]); checkpoint_every (>= 0;
    0: at the end only); force;
    prior_from (None or an earlier run folder, absolute: its posterior becomes this run's prior on
    the joints both infer, :mod:`treeinfer.inference.sequential`); allow_modified (use a
    ``prior_from`` run whose files changed since it was written, ``--allow-modified``: what
    changed is recorded in the problem's ``prior_from`` settings and summary.json).
    prior_tail (smoothed-box tail width, share of each log-box width, > 0); reinit_stragglers
    (>= 0: re-initialise stuck particles near the bulk after every chunk up to this iteration;
    0: off); drop_stragglers (leave stuck final particles out of the summaries);
    stop_when_converged (stop early, :class:`treeinfer.inference.diagnostics.ConvergenceCriterion`);
    mcmc_warmup (share of an MCMC trace discarded, in [0, 1)); mcmc_thin (>= 0; 0: thin to at
    most 1024 post-warm-up draws). model_kind ("dynamic": the rollout; "static": equilibria
    under each force sample, stiffness only, :mod:`treeinfer.inference.static`).
    force_interp ("linear": forces interpolated between samples, "hold"; folders written before it
    existed were simulated with "hold", which their recorded ``problem`` settings say);
    max_sim_dt (s, None: the simulator's 5 ms) and sim_tolerance (m, None: 0.1 mm), the bounds of
    the accuracy-controlled simulation step chosen on the training forces; model (None or the
    absolute path of the user's own URDF/MJCF, ``--model``) and repair_inertia (None,
    ``"geometry"``, ``"floor"``), see :mod:`treeinfer.tree.usermodel`.
    """

    tree: str
    data: str
    out: str
    sampler: str = "nnsvgd"
    particles: int = 64
    iterations: int = 200
    backend: str = "auto"
    kT: float = DEFAULT_KT
    seed: int = 0
    eta: float = DEFAULT_ETA
    grasp_fraction: float | None = None
    max_unstable_share: float = 0.5
    checkpoint_every: int = 25
    force: bool = False
    prior_from: str | None = None
    prior_tail: float = DEFAULT_PRIOR_SIGMA
    reinit_stragglers: int = DEFAULT_REINIT
    drop_stragglers: bool = False
    stop_when_converged: bool = True
    mcmc_warmup: float = 0.5
    mcmc_thin: int = 0
    gradients: str = "fd"
    init: str = "auto"
    model_kind: str = "dynamic"
    force_interp: str = "linear"
    max_sim_dt: float | None = None
    sim_tolerance: float | None = None
    likelihood: str = "gaussian"
    noise_displacement: float | None = None
    noise_force: float | str | None = "default"
    noise_velocity: float | None = None
    model: str | None = None
    repair_inertia: str | None = None
    tie: str | None = None
    tie_scale: float | None = None
    shape_buckets: str = "on"
    allow_modified: bool = False
    # ---- the record: config.json beyond the options (None until known; JSON key in brackets)
    command: str = "infer"
    versions: dict | None = None
    created_utc: str | None = None
    tree_record: dict | None = None  # ["tree"]: file, sha256, name, labels
    tree_dict: dict | None = None
    data_record: dict | None = None  # ["data"]: dir, files (name, sha256), dt, n_steps
    checkpoint: dict | None = None
    problem: dict | None = None  # the settings the code derived (added by run_inference)
    sampler_record: dict | None = None  # ["sampler"]: name and options
    config_hash: str | None = None
    posterior_settings: dict | None = None
    finished_utc: str | None = None
    extra: dict = field(default_factory=dict)  # other top-level keys, kept as they are
    # option keys a read file gave (None: a new config, every option is written)
    given: frozenset | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)
        from ..inference.static import parse_model_kind

        set_("model_kind", parse_model_kind(self.model_kind))
        from ..tree.types import parse_tie

        if self.tie is not None or self.tie_scale is not None:  # --tie-scale alone: the file's
            name = "taper" if self.tie is None else self.tie
            tie, tau = parse_tie(name, self.tie_scale, "", ("--tie", "--tie-scale"))
            set_("tie", tie if self.tie is not None else None)
            set_("tie_scale", tau)
        sampler_spec(self.sampler)
        set_(
            "particles",
            _count(
                "--particles",
                self.particles,
                2,
                " (SVGD's kernel needs pairs of particles and a 95% interval needs two)",
            ),
        )
        set_("iterations", _count("--iterations", self.iterations, 1))
        set_("checkpoint_every", _count("--checkpoint-every", self.checkpoint_every, 0))
        set_("seed", _count("--seed", self.seed, 0))
        if not (isinstance(self.kT, str) and self.kT == "auto"):
            set_(
                "kT", _positive("--kT", self.kT, "a positive number (loss units per nat) or 'auto'")
            )
            if (
                self.kT < MIN_KT
            ):  # the log-likelihood -L/kT would overflow float32 to -inf everywhere
                raise ConfigError(
                    f"--kT: {self.kT:g} is so small that every particle's log-likelihood -L/kT "
                    f"overflows (below {MIN_KT:g}); a loss of L costs L/kT nats: typical values "
                    "are 1e-3 to 10 (see treeinfer.model.likelihood.suggest_kT)"
                )
        if self.likelihood not in LIKELIHOODS:
            raise ConfigError(
                f"--likelihood: must be one of {', '.join(LIKELIHOODS)}, got {self.likelihood!r}"
            )
        if self.noise_displacement is not None:
            set_("noise_displacement", check_sigma(self.noise_displacement, "--noise-displacement"))
        if isinstance(self.noise_force, str) and self.noise_force == "default":
            # the default force-noise term: with the Gaussian likelihood and no velocity term,
            # resolved with the data and model (treeinfer.inference.problem.default_noise_force)
            if self.likelihood != "gaussian" or self.noise_velocity is not None:
                set_("noise_force", None)
        elif self.noise_force is not None:
            from ..model.force_noise import check_noise_force

            try:
                set_("noise_force", check_noise_force(self.noise_force))
            except ConfigError as e:
                raise ConfigError(str(e).replace("noise_force", "--noise-force", 1)) from None
            if self.likelihood != "gaussian":
                raise ConfigError(
                    "--noise-force: the force-noise term needs --likelihood gaussian, got "
                    f"{self.likelihood!r}"
                )
        if self.noise_velocity is not None:
            set_("noise_velocity", check_sigma(self.noise_velocity, "--noise-velocity"))
            if self.likelihood not in NOISE_KINDS:
                raise ConfigError(
                    "--noise-velocity: the velocity term belongs to a generative likelihood "
                    f"(--likelihood {'|'.join(NOISE_KINDS)}), got {self.likelihood!r}"
                )
            if self.noise_force not in (None, "default"):
                raise ConfigError(
                    "--noise-velocity: not available with --noise-force (the errors-in-variables "
                    "term covers the displacement only); leave one out"
                )
        set_("eta", _positive("--eta", self.eta))
        g = self.grasp_fraction
        if g is not None and not (math.isfinite(g) and 0.0 < g <= 1.0):
            raise ConfigError(
                f"--grasp-fraction: must be in (0, 1] (a fraction of the branch length), got {g:g}"
            )
        set_("grasp_fraction", None if g is None else float(g))
        set_("max_unstable_share", check_share(self.max_unstable_share))
        if self.backend not in BACKENDS:
            raise ConfigError(
                f"--backend: must be one of {', '.join(BACKENDS)}, got {self.backend!r}"
            )
        if self.gradients not in GRADIENT_CHOICES:
            raise ConfigError(
                f"--gradients: must be one of {', '.join(GRADIENT_CHOICES)}, got {self.gradients!r}"
            )
        if self.init not in INIT_CHOICES:
            raise ConfigError(
                f"--init: must be one of {', '.join(INIT_CHOICES)}, got {self.init!r}"
            )
        if self.shape_buckets not in ("on", "off"):
            raise ConfigError(f"--shape-buckets: must be 'on' or 'off', got {self.shape_buckets!r}")
        if self.force_interp not in FORCE_INTERPS:
            raise ConfigError(
                f"--force-interp: must be one of {', '.join(FORCE_INTERPS)}, got "
                f"{self.force_interp!r}"
            )
        for k, flag in (("max_sim_dt", "--max-sim-dt"), ("sim_tolerance", "--sim-tolerance")):
            v = getattr(self, k)
            set_(k, None if v is None else _positive(flag, v, "a positive number"))
        for k in ("tree", "data", "out"):
            set_(k, str(getattr(self, k)))
        if self.model is not None:
            set_("model", str(self.model))
        set_("force", bool(self.force))
        if self.prior_from is not None:
            prior = Path(self.prior_from)
            if str(self.prior_from) and not (prior / "config.json").is_file():
                raise ConfigError(
                    f"--prior-from: {prior} is not a run folder (no config.json); give a folder "
                    "`treeinfer infer` wrote"
                )
            set_("prior_from", str(prior.resolve()) if str(self.prior_from) else None)
        set_("allow_modified", bool(self.allow_modified))
        set_("prior_tail", _positive("--prior-tail", self.prior_tail))
        set_("reinit_stragglers", _count("--reinit-stragglers", self.reinit_stragglers, 0))
        set_("drop_stragglers", bool(self.drop_stragglers))
        set_("stop_when_converged", bool(self.stop_when_converged))
        w = float(self.mcmc_warmup)
        if not 0.0 <= w < 1.0:
            raise ConfigError(f"--mcmc-warmup: must be a share in [0, 1), got {self.mcmc_warmup!r}")
        set_("mcmc_warmup", w)
        set_("mcmc_thin", _count("--mcmc-thin", self.mcmc_thin, 0))

    def options_json(self) -> dict:
        """``config.json``'s ``"options"`` object: every option (``gradients``/``init``/
        ``model_kind`` only when not default); for a config read from a file, the keys it gave."""
        out = {k: getattr(self, k) for k in OPTION_FIELDS}
        for k, default in (
            ("gradients", "fd"),
            ("init", LEGACY_DEFAULTS["init"]),
            ("model_kind", "dynamic"),
            ("tie", None),
            ("tie_scale", None),
            ("shape_buckets", "on"),
            ("noise_velocity", None),  # off: config.json as before the option existed
            ("allow_modified", False),
        ):
            if out[k] == default:
                del out[k]
        if self.given is not None:
            out = {k: getattr(self, k) for k in OPTION_FIELDS if k in self.given}
        return out

    def to_json(self) -> dict:
        """The whole ``config.json`` (record fields that are None are left out)."""
        out = {
            "command": self.command,
            "format": RUN_FORMAT,
            "versions": self.versions,
            "created_utc": self.created_utc,
            "options": self.options_json(),
            "seed": int(self.seed),
        }
        for key, attr in _RECORD_KEYS.items():
            out[key] = getattr(self, attr)
        out = {k: v for k, v in out.items() if v is not None}
        return {**out, **self.extra}

    @classmethod
    def from_json(cls, config: dict) -> RunConfig:
        """From a ``config.json`` (a run's, old or new; or only its ``"options"`` object). Folders
        written before an option existed get its default (``backend`` "auto", ...); option keys
        this version does not know are refused; ``--prior-from`` is not looked up again (the
        earlier run may have moved since)."""
        if not isinstance(config, dict):
            raise ConfigError(f"config.json: expected a JSON object, got {type(config).__name__}")
        whole = isinstance(config.get("options"), dict)
        options = config["options"] if whole else config
        unknown = sorted(set(options) - set(OPTION_FIELDS))
        if unknown:
            raise ConfigError(f"config.json options: unknown field(s) {unknown}")
        record = {}
        if whole:
            if config.get("format", RUN_FORMAT) != RUN_FORMAT:
                raise ConfigError(
                    f"config.json: format {config.get('format')!r} is not {RUN_FORMAT}"
                )
            plain = {"command", "versions", "created_utc", "format", "options", "seed"}
            record = {k: config[k] for k in ("command", "versions", "created_utc") if k in config}
            record.update({a: config[k] for k, a in _RECORD_KEYS.items() if k in config})
            record["extra"] = {
                k: v for k, v in config.items() if k not in plain and k not in _RECORD_KEYS
            }
        missing = [k for k in ("tree", "data", "out") if k not in options]
        if missing:
            raise ConfigError(f"config.json options: missing field(s) {missing}")
        prior_from = options.get("prior_from")
        # an option the file leaves out has the value it had when the file was written
        legacy = {k: v for k, v in LEGACY_DEFAULTS.items() if k not in options}
        cfg = cls(
            **{**legacy, **options, "prior_from": None},
            **record,
            given=frozenset(options),
        )
        object.__setattr__(cfg, "prior_from", prior_from)
        return cfg


_NAMES = [f.name for f in fields(RunConfig)]
# the options: the fields before the record
OPTION_FIELDS = tuple(_NAMES[: _NAMES.index("command")])
_RECORD_KEYS = {  # config.json key -> RunConfig attribute, in the file's order
    "tree": "tree_record",
    "tree_dict": "tree_dict",
    "data": "data_record",
    "checkpoint": "checkpoint",
    "problem": "problem",
    "sampler": "sampler_record",
    "config_hash": "config_hash",
    "posterior_settings": "posterior_settings",
    "finished_utc": "finished_utc",
}


# ==== config ======================================================================================
def infer_config(
    tree_path: str | os.PathLike,
    data_dir: str | os.PathLike,
    out: str | os.PathLike,
    *,
    sampler: str,
    particles: int,
    iterations: int,
    kT: float,
    seed: int,
    eta: float,
    grasp_fraction: float | None,
    max_unstable_share: float,
    checkpoint_every: int,
    force: bool = False,
    command: str = "infer",
    backend: str = "auto",
    prior_from: str | os.PathLike | None = None,
    gradients: str = "fd",
    init: str = "uniform",
    force_interp: str = "linear",
    max_sim_dt: float | None = None,
    sim_tolerance: float | None = None,
    likelihood: str = "boltzmann",
    noise_displacement: float | None = None,
    model: str | os.PathLike | None = None,
    repair_inertia: str | None = None,
    inputs: RunInputs | None = None,
    **more,
) -> dict:
    """The config of a new run (validated options; data and tree hashed), as the JSON form of
    its :class:`RunConfig` (``RunConfig.from_json`` reads it back). The problem and sampler
    settings are added by :func:`run_inference` once the problem is built.

    ``inputs``: the tree and data already read by :func:`load_run_inputs` (pass the same to
    :func:`run_inference`, so a command reads them once); read here if None."""
    tree_path, data_dir, out = Path(tree_path), Path(data_dir), Path(out)
    if inputs is None:
        inputs = load_run_inputs(
            tree_path,
            data_dir,
            model,
            repair_inertia,
            more.get("model_kind", "dynamic"),
            more.get("tie"),
            more.get("tie_scale"),
        )
    tree, trajs, files = inputs.tree, inputs.trajectories, inputs.files
    cfg = RunConfig(
        tree=str(tree_path.resolve()),
        data=str(data_dir.resolve()),
        out=str(out.resolve()),
        sampler=sampler,
        particles=particles,
        iterations=iterations,
        backend=str(backend),
        kT=kT,
        seed=seed,
        eta=eta,
        grasp_fraction=grasp_fraction,
        max_unstable_share=max_unstable_share,
        checkpoint_every=checkpoint_every,
        force=force,
        prior_from=None if prior_from is None else str(prior_from),
        gradients=gradients,
        init=init,
        force_interp=force_interp,
        max_sim_dt=max_sim_dt,
        sim_tolerance=sim_tolerance,
        likelihood=likelihood,
        noise_displacement=noise_displacement,
        model=None if model is None else str(Path(model).resolve()),
        repair_inertia=repair_inertia,
        command=command,
        versions=versions(),
        created_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        tree_record={
            "file": str(tree_path.resolve()),
            "sha256": file_sha256(tree_path),
            "name": tree.name,
            "labels": tree.parameter_labels(),
        },
        tree_dict=tree_to_dict(tree),
        data_record={
            "dir": str(data_dir.resolve()),
            "files": files,
            "dt": trajs[0].dt,
            "n_steps": [t.n_steps for t in trajs],
            "true_params": TRUE_PARAMS_FILE if (data_dir / TRUE_PARAMS_FILE).is_file() else None,
            **({"channel_files": ch} if (ch := _channel_manifest(data_dir)) else {}),
        },
        checkpoint={
            "every": int(checkpoint_every),
            "dir": str(partial_dir(out).resolve()),
            "file": CHECKPOINT_FILE,
        },
        **more,
    )
    return cfg.to_json()
