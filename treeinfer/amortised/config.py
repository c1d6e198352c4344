"""The settings of an amortised posterior, validated once: the pull layout the model is trained
for (and refuses any other), the noise ranges of the training simulations, the network and the
training loop; and the tree's fingerprint (what the model belongs to)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any

from ..data.forces import DEFAULT_PEAK_RANGE, SET_KINDS, n_steps
from ..errors import ConfigError
from ..io.jsonio import jsonable

# Defaults of the pull family: those of `treeinfer simulate` (treeinfer.cli.simulate), the
# synthetic recordings a user's first runs are made of.
DEFAULT_N_PULLS = 8
DEFAULT_DURATION = 3.0  # s
DEFAULT_DT = 0.01  # s
# Training noise ranges, drawn log-uniformly per data set: displacement noise from a clean
# motion-capture recording (0.1 mm) to a noisy one (5 mm), as treeinfer's examples use (1-2 mm);
# force noise of a load cell, 5 mN to 0.2 N.
DEFAULT_SIGMA_X_RANGE = (1e-4, 5e-3)  # m
DEFAULT_SIGMA_F_RANGE = (5e-3, 0.2)  # N
# Share of the training data sets whose recorded force is noise-free. `treeinfer simulate`
# writes a clean force unless --noise-force is given (the README's recordings), and a filtered
# load cell is nearly so; a model trained on noisy forces only saw no such recording, and every
# one of them failed its domain check (force noise 8e-6 N outside 4e-3-0.24 N).
DEFAULT_CLEAN_FORCE_SHARE = 0.25
SPACES = ("probit", "box")
SUMMARIES = ("dynamics", "shapes")
BINS = 50  # samples per pull the embedding sees (bin means of the recording)


def _pair(v, name: str, positive: bool = True) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in v)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected two numbers LO,HI, got {v!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi or (positive and lo <= 0):
        raise ConfigError(
            f"{name}: expected finite {'0 < ' if positive else ''}LO <= HI, got ({lo:g}, {hi:g})"
        )
    return lo, hi


@dataclass(frozen=True)
class PullLayout:
    """The recordings a model is trained for: ``n_pulls`` pulls of ``duration`` s sampled every
    ``dt`` s at ``grasp_fraction`` of the grasped branch (None: the tree's), pulled down (along
    gravity), with force profiles of ``profile_kind`` (:data:`treeinfer.data.forces.SET_KINDS`)
    peaking in ``peak_range`` N. A recording of another layout is refused (exit 2)."""

    n_pulls: int = DEFAULT_N_PULLS
    duration: float = DEFAULT_DURATION
    dt: float = DEFAULT_DT
    grasp_fraction: float | None = None
    profile_kind: str = "mixed"
    peak_range: tuple[float, float] = DEFAULT_PEAK_RANGE

    def __post_init__(self):
        if isinstance(self.n_pulls, bool) or not isinstance(self.n_pulls, int) or self.n_pulls < 1:
            raise ConfigError(f"--n-traj: must be an integer >= 1, got {self.n_pulls!r}")
        n_steps(self.duration, self.dt)  # ConfigError naming duration and dt
        if self.grasp_fraction is not None and not 0 < float(self.grasp_fraction) <= 1:
            raise ConfigError(f"--grasp-fraction: must be in (0, 1], got {self.grasp_fraction}")
        if self.profile_kind not in SET_KINDS:
            raise ConfigError(
                f"--profile-kind: expected one of {', '.join(SET_KINDS)}, got {self.profile_kind!r}"
            )
        object.__setattr__(self, "peak_range", _pair(self.peak_range, "--peak-range"))

    @property
    def n_steps(self) -> int:
        return n_steps(self.duration, self.dt)

    @property
    def bins(self) -> int:
        return min(BINS, self.n_steps)


@dataclass(frozen=True)
class TrainConfig:
    """How a model is trained: ``simulations`` data sets drawn from the prior and the noise
    model (in chunks of ``chunk`` parameter sets sharing one set of pulls), a conditional masked
    autoregressive flow of ``flow_layers`` layers and ``width`` hidden units conditioned on a
    learned ``embedding``-dimensional summary, fitted by Adam for at most ``epochs`` epochs
    (early stop on a held-out tenth). ``clean_force_share`` of the data sets have a noise-free
    recorded force (the rest: noise log-uniform in ``sigma_f_range``)."""

    simulations: int = 20000
    chunk: int = 256
    sigma_x_range: tuple[float, float] = DEFAULT_SIGMA_X_RANGE
    sigma_f_range: tuple[float, float] = DEFAULT_SIGMA_F_RANGE
    clean_force_share: float = DEFAULT_CLEAN_FORCE_SHARE
    flow_layers: int = 5
    width: int = 64
    embedding: int = 16
    epochs: int = 200
    batch_size: int = 256
    learning_rate: float = 1e-3
    patience: int = 10
    seed: int = 0
    backend: str = "auto"
    # the flow's coordinates: "probit" (the prior's CDF, then the normal quantile: the prior a
    # standard normal; treeinfer.amortised.space) or "box" (the prior's box standardised
    # linearly, the models before session 13). Session 13, CPU size, two training seeds: the
    # largest coverage gap 3.6 / 3.4 points in probit against 3.8 / 7.3 in box (Kd[child] at
    # 50%: 0.43-0.46 in box), the mean log q of the truth alike
    space: str = "probit"
    # the per-pull features (treeinfer.amortised.simulations.features): "dynamics" (the shapes
    # plus hand-made summaries of the compliance and the ringing after release) or "shapes"
    # (the bin means' shapes only, the models before session 13)
    summary: str = "dynamics"

    def __post_init__(self):
        for name, lo in (
            ("simulations", 16),
            ("chunk", 1),
            ("flow_layers", 1),
            ("width", 2),
            ("embedding", 1),
            ("epochs", 1),
            ("batch_size", 1),
            ("patience", 0),
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ConfigError(f"{name}: must be an integer >= {lo}, got {v!r}")
        if not 0 <= float(self.clean_force_share) <= 1:
            raise ConfigError(
                f"clean_force_share: must be in [0, 1], got {self.clean_force_share!r}"
            )
        if self.summary not in SUMMARIES:
            raise ConfigError(
                f"summary: expected one of {', '.join(SUMMARIES)}, got {self.summary!r}"
            )
        if self.space not in SPACES:
            raise ConfigError(f"space: expected one of {', '.join(SPACES)}, got {self.space!r}")
        if not (math.isfinite(self.learning_rate) and self.learning_rate > 0):
            raise ConfigError(f"learning_rate: must be > 0, got {self.learning_rate!r}")
        for name in ("sigma_x_range", "sigma_f_range"):
            object.__setattr__(self, name, _pair(getattr(self, name), name))


@dataclass(frozen=True)
class AmortiseConfig:
    """Everything ``treeinfer amortise`` was given (recorded in the model's JSON)."""

    layout: PullLayout = field(default_factory=PullLayout)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_json(self) -> dict:
        return jsonable(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, d: dict) -> AmortiseConfig:
        try:
            lay = dict(d["layout"])
            lay["peak_range"] = tuple(lay["peak_range"])
            tr = dict(d["train"])
            for k in ("sigma_x_range", "sigma_f_range"):
                tr[k] = tuple(tr[k])
            tr.setdefault("space", "box")  # a model from before the probit space
            tr.setdefault("summary", "shapes")  # and before the hand-made summaries
            return cls(PullLayout(**lay), TrainConfig(**tr))
        except (KeyError, TypeError) as e:
            raise ConfigError(f"amortised model config: missing or unknown field ({e})") from None


# ---- the tree a model belongs to ---------------------------------------------------------------
# keys of a tree's dict that do not change its physics or its prior (how it was generated)
_NOT_PHYSICS = ("generator",)


def tree_identity(tree) -> dict:
    """The tree's description as a dict, less what does not change the model (its generator's
    record): the model is refused for any tree whose identity differs."""
    from ..tree.description import tree_to_dict

    d = jsonable(tree_to_dict(tree))
    return {k: v for k, v in d.items() if k not in _NOT_PHYSICS}


def fingerprint(identity: dict) -> str:
    """sha256 of a tree identity (:func:`tree_identity`), as recorded in the model's JSON."""
    blob = json.dumps(identity, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def differences(a: Any, b: Any, path: str = "", limit: int = 4) -> list[str]:
    """Up to ``limit`` paths (``branches[1].length``) where two JSON values differ, for the
    refusal of a model used with another tree."""
    out: list[str] = []
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            sub = f"{path}.{k}" if path else str(k)
            if k not in a or k not in b:
                out.append(sub)
            else:
                out += differences(a[k], b[k], sub, limit - len(out))
            if len(out) >= limit:
                break
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            out += differences(x, y, f"{path}[{i}]", limit - len(out))
            if len(out) >= limit:
                break
    elif a != b:
        out.append(path or "(the whole tree)")
    return out[:limit]
