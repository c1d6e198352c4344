"""An amortised posterior of one tree: train it on simulations (:func:`train`), store and load it
(:func:`save`, :func:`load`: ``model.msgpack`` + ``model.json`` in a folder built aside and
published whole, :func:`treeinfer.io.atomic.staged_output_dir`), refuse it for another tree or
another pull layout (:meth:`Amortised.check_tree`, :meth:`Amortised.check_recordings`), and
draw a recording's posterior in milliseconds (:meth:`Amortised.draw`)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import ConfigError
from ..io.jsonio import jsonable
from . import network, simulations
from .config import AmortiseConfig, differences, fingerprint, tree_identity
from .simulations import bin_matrix, features, simulate_training_set, theta_box

# 2: the features' noise floor (simulations.NOISE_FLOOR) and the clean-force share; a model of
# format 1 summarises a recording otherwise, and is refused with a word to retrain it.
# 3 (session 13): the training config's space and summary, and the features' standardisation
# (model.json's feature_norm); a treeinfer that reads format 2 only would build another
# network for it, so it refuses it by its format. A record without them is read as box / shapes.
FORMAT = "treeinfer-amortised/3"
READABLE_FORMATS = ("treeinfer-amortised/2", FORMAT)
WEIGHTS_FILE = "model.msgpack"
META_FILE = "model.json"
# the check's programs per model: a rollout program, the log-prior, the noise density and the
# Gauss-Newton terms per recording shape, with room for a second shape or chunk
PROGRAMS_PER_MODEL = 16


def _program_cache():
    from ..sim.program_cache import ProgramCache

    return ProgramCache(PROGRAMS_PER_MODEL)


# a recording's dt may differ from the layout's by float rounding of its time column only
DT_RTOL = 1e-3


@dataclass
class Amortised:
    """A trained estimator and its record (``meta``: the tree's identity and fingerprint, the
    layout, the training config, the features' scales, the parameter box, the training report,
    the treeinfer version). ``model``: the flowjax/equinox pytree (training, calibration);
    a loaded model leaves it None until :meth:`network_model` builds it (seconds: flowjax's
    modules are built op by op), since a recording's posterior needs only ``weights``, the
    stored arrays, evaluated in NumPy (:mod:`treeinfer.amortised.fastpath`). ``programs``: the
    compiled programs of the check against the simulator (:mod:`treeinfer.amortised.programs`),
    kept with the model so that a process checking many recordings of one shape compiles them
    once."""

    model: object
    meta: dict
    programs: object = field(default_factory=_program_cache, repr=False, compare=False)
    weights: list | None = field(default=None, repr=False, compare=False)

    @property
    def config(self) -> AmortiseConfig:
        return AmortiseConfig.from_json(self.meta["config"])

    @property
    def labels(self) -> list[str]:
        return list(self.meta["labels"])

    def _architecture(self) -> tuple:
        tr = self.config.train
        n_features = simulations.n_features(self.meta["layout"]["bins"], tr.summary)
        skip = network.skip_count(tr.summary)
        fn = self.meta.get("feature_norm")
        norm = None if fn is None else (fn["loc"], fn["scale"])
        return len(self.labels), n_features, tr.flow_layers, tr.width, tr.embedding, skip, norm

    def weight_leaves(self) -> list:
        """The stored arrays (:func:`treeinfer.amortised.network.leaves`'s order)."""
        if self.weights is None:
            self.weights = network.leaves(self.model)
        return self.weights

    def network_model(self):
        """The flowjax/equinox estimator, built from the stored arrays on first use."""
        if self.model is None:
            import jax

            skeleton = network.build(jax.random.key(0), *self._architecture())
            self.model = network.with_leaves(skeleton, self.weights, "amortised model")
        return self.model

    @property
    def fast(self):
        """The estimator in NumPy (:class:`treeinfer.amortised.fastpath.FastEstimator`)."""
        fe = self.__dict__.get("_fast")
        if fe is None:
            from .fastpath import from_leaves

            fe = self.__dict__["_fast"] = from_leaves(self.weight_leaves(), *self._architecture())
        return fe

    def _box(self):
        lo, hi = (np.asarray(self.meta["box"][k], float) for k in ("lower", "upper"))
        return (lo + hi) / 2, (hi - lo) / 2

    def _space(self):
        """The probit map of the prior (:class:`treeinfer.amortised.space.ProbitSpace`), or
        None for a model in the box's linear coordinates."""
        if self.config.train.space != "probit":
            return None
        sp = self.__dict__.get("_probit")
        if sp is None:
            from .space import ProbitSpace

            box = self.meta["box"]
            sp = self.__dict__["_probit"] = ProbitSpace(box["lower"], box["upper"], box["tail"])
        return sp

    def to_z(self, theta):
        """The flow's coordinates of ``theta`` [..., D]."""
        sp = self._space()
        if sp is not None:
            return sp.to_u(theta)
        c, h = self._box()
        return (np.asarray(theta, float) - c) / h

    def from_z(self, z):
        sp = self._space()
        if sp is not None:
            return sp.from_u(z)
        c, h = self._box()
        return np.asarray(z, float) * h + c

    def log_jacobian(self, theta) -> np.ndarray:
        """[n] log |d z / d theta| at ``theta`` [n, D]: ``log q(theta) = log q(z) +
        log_jacobian``."""
        sp = self._space()
        if sp is not None:
            return sp.log_abs_det(theta)
        return np.full(len(theta), -np.sum(np.log(self._box()[1])))

    def features(self, force, disp) -> np.ndarray:
        """[B, F] the summary features of one recording (``force``, ``disp`` [B, T]), in NumPy
        (float32 inputs, as the training's)."""
        lay = self.config.layout
        f = features(
            np.asarray(force, np.float32),
            np.asarray(disp, np.float32),
            bin_matrix(lay.n_steps, lay.bins).astype(np.float32),
            *self.meta["scales"],
            xp=np,
            summary=self.config.train.summary,
        )
        return np.asarray(f, np.float32)

    def draw(self, force, disp, n: int = 1024, seed: int = 0):
        """``(theta [n, D], log q(theta) [n])``: the amortised posterior of one recording
        (``force``, ``disp`` [B, T] on the layout's grid), in theta units (log Kp, log Kd, log
        sigma_x). The features, the summary and the flow in NumPy: milliseconds, nothing to
        compile (:mod:`treeinfer.amortised.fastpath`)."""
        return self.draw_from_features(self.features(force, disp), n, seed)

    def draw_from_features(self, feats, n: int = 1024, seed: int = 0):
        """:meth:`draw` of a recording's features [B, F]."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xD7]))
        z, lq = self.fast.sample_and_log_prob(rng, int(n), feats)
        theta = self.from_z(z)
        return theta, lq + self.log_jacobian(theta)

    def log_q(self, theta, feats) -> np.ndarray:
        """log q(theta [M, D] | one recording's features [B, F]) in theta units (NumPy)."""
        fe = self.fast
        theta = np.asarray(theta, float)
        return fe.log_prob(self.to_z(theta), fe.embed(feats)) + self.log_jacobian(theta)

    # ---- refusals ------------------------------------------------------------------------------
    def check_tree(self, tree, where: str = "--tree") -> None:
        """ConfigError (exit 2) if ``tree`` is not the one the model was trained for, naming the
        first fields that differ."""
        ident = tree_identity(tree)
        if fingerprint(ident) == self.meta["tree_fingerprint"]:
            return
        diff = differences(self.meta["tree"], ident)
        raise ConfigError(
            f"{where}: this amortised model was trained for another tree "
            f"('{self.meta['tree']['name']}', fingerprint {self.meta['tree_fingerprint'][:12]}); "
            "they differ in "
            f"{', '.join(diff) or 'their description'}. Train one for this tree with `treeinfer "
            "amortise`, or infer without --amortised"
        )

    def check_recordings(self, trajectories: Sequence, grasp_fraction=None, where: str = "--data"):
        """``(force [B, T], disp [B, T])`` of the recordings, or ConfigError (exit 2) naming how
        they differ from the layout the model was trained for (number of pulls, samples, time
        step, grasp point)."""
        lay = self.config.layout
        why = []
        if len(trajectories) != lay.n_pulls:
            why.append(f"{len(trajectories)} pulls (trained for {lay.n_pulls})")
        lengths = sorted({len(t.time) for t in trajectories})
        if lengths != [lay.n_steps]:
            why.append(
                f"{'/'.join(map(str, lengths))} samples per pull (trained for "
                f"{lay.n_steps}: {lay.duration:g} s at dt {lay.dt:g} s)"
            )
        dts = [float(np.median(np.diff(t.time))) for t in trajectories if len(t.time) > 1]
        if dts and max(abs(d - lay.dt) for d in dts) > DT_RTOL * lay.dt:
            why.append(f"time step {dts[0]:g} s (trained for {lay.dt:g} s)")
        g_model = lay.grasp_fraction
        if grasp_fraction is not None and not _same_grasp(grasp_fraction, g_model):
            why.append(
                f"grasp fraction {grasp_fraction} (trained for "
                f"{'the tree grasp' if g_model is None else g_model})"
            )
        if why:
            raise ConfigError(
                f"{where}: the recordings do not have the layout this amortised model was trained "
                f"for: {'; '.join(why)}. Train a model for this layout (`treeinfer amortise "
                "--n-traj --duration --dt --grasp-fraction`), or infer without --amortised"
            )
        force = np.stack([np.asarray(t.force, float) for t in trajectories])
        disp = np.stack([np.asarray(t.displacement, float) for t in trajectories])
        return force, disp


def _same_grasp(given, trained) -> bool:
    g = np.atleast_1d(np.asarray(given, float))
    return trained is not None and bool(np.allclose(g, float(trained), atol=1e-9))


# ---- training ----------------------------------------------------------------------------------
def train(
    tree,
    config: AmortiseConfig,
    log: Callable[[str], None] = lambda m: None,
    progress: bool = False,
    deadline: float | None = None,
) -> Amortised:
    """Simulate ``config.train.simulations`` data sets of ``tree`` under the layout's pulls and
    fit the estimator to them (module :mod:`treeinfer.amortised.network`). ``progress``: the
    epochs to ``log`` (every 10 s); ``deadline`` (a :func:`time.perf_counter` value): no epoch
    starts after it (``meta["training"]["stopped_at_deadline"]``)."""
    import jax

    t0 = time.perf_counter()
    tr, lay = config.train, config.layout
    data, scales = simulate_training_set(tree, lay, tr, log=log)
    t_sim = time.perf_counter() - t0
    if len(data.theta) < 16:
        raise ConfigError(
            f"amortise: only {len(data.theta)} of {tr.simulations} simulations were stable; "
            "check the tree's prior box"
        )
    lower, upper, tail = theta_box(tree, tr)
    labels = tree.parameter_labels() + ["sigma_x"]
    meta = {
        "format": FORMAT,
        "treeinfer_version": __version__,
        "tree": tree_identity(tree),
        "tree_fingerprint": fingerprint(tree_identity(tree)),
        "labels": labels,
        "columns": "log Kp and log Kd of the inferred joints (N m/rad, N m s/rad), log sigma_x (m)",
        "layout": {
            **jsonable(lay.__dict__),
            "n_steps": lay.n_steps,
            "bins": lay.bins,
            "direction": "down (along gravity)",
            "grasp_branch": tree.grasp_branch,
        },
        "config": config.to_json(),
        "scales": [float(s) for s in scales],
        "box": {"lower": lower.tolist(), "upper": upper.tolist(), "tail": tail.tolist()},
    }
    am = Amortised(None, meta)
    z = am.to_z(data.theta).astype(np.float32)
    key = jax.random.key(tr.seed)
    k_build, k_fit = jax.random.split(key)
    if tr.summary == "dynamics":  # features standardised by the training set's (network.build)
        flat = data.feats.reshape(-1, data.feats.shape[-1])  # float32; sums in float64 (no copy)
        am.meta["feature_norm"] = {
            "loc": flat.mean(axis=0, dtype=np.float64).tolist(),
            "scale": np.maximum(flat.std(axis=0, dtype=np.float64), 1e-3).tolist(),
        }
    model = network.build(k_build, *am._architecture())
    log(f"training the flow on {len(z)} simulated data sets ({data.n_unstable} unstable dropped)")
    t1 = time.perf_counter()
    model, losses = network.fit(
        model,
        z,
        data.feats,
        k_fit,
        tr.epochs,
        tr.batch_size,
        tr.learning_rate,
        tr.patience,
        progress,
        deadline,
        log,
    )
    am.model = model
    am.meta["training"] = {
        "n_datasets": int(len(z)),
        "n_unstable": int(data.n_unstable),
        "epochs_run": len(losses["train"]),
        "stopped_at_deadline": bool(losses["stopped_at_deadline"]),
        "best_val_loss": float(min(losses["val"])),
        "final_train_loss": float(losses["train"][-1]),
        "simulation_s": round(t_sim, 2),
        "training_s": round(time.perf_counter() - t1, 2),
        "feature_envelope": _envelope(data.feats),
        "noise_ratio_envelope": _quantiles(noise_ratio(data.theta[:, -1], data.feats, scales[1])),
    }
    return am


def _envelope(feats: np.ndarray) -> dict:
    """The training recordings' range (0.1-99.9% quantiles over pulls) of each summary that a
    new recording must share (:func:`~treeinfer.amortised.simulations.features`: the log
    amplitudes of force and displacement and their log noise estimates), for the check of a new
    recording's domain (:mod:`treeinfer.amortised.check`)."""
    out = {}
    for name, j in FEATURE_TAIL.items():
        v = feats[..., j]
        out[name] = [float(np.quantile(v, 0.001)), float(np.quantile(v, 0.999))]
    return out


def _quantiles(v) -> list[float]:
    return [float(np.quantile(v, 0.001)), float(np.quantile(v, 0.999))]


def noise_ratio(log_sigma_x, feats, disp_scale: float) -> np.ndarray:
    """``log sigma_x - log(the recording's own displacement noise estimate)`` (the median over
    its pulls of :func:`~treeinfer.amortised.simulations.features`' robust estimate, less the
    features' floor), per data set: ``log_sigma_x [N]``, ``feats [N, B, F]``. Near 0 for a
    recording the simulator explains up to white noise; a posterior whose ``sigma_x`` exceeds
    the recording's noise by more than the training sets ever did explains a misfit, not
    noise (:func:`treeinfer.amortised.check.predictive_reasons`)."""
    from .simulations import NOISE_FLOOR

    est = np.exp(np.asarray(feats, float)[..., FEATURE_TAIL["log_disp_noise"]]) - NOISE_FLOOR
    est = np.median(np.maximum(est, 1e-3 * NOISE_FLOOR), axis=-1) * disp_scale
    return np.asarray(log_sigma_x, float) - np.log(est)


# the summaries after the shapes, by their index from the end of the features
FEATURE_TAIL = {
    "log_force": -4,
    "log_displacement": -3,
    "log_force_noise": -2,
    "log_disp_noise": -1,
}


# ---- storage -----------------------------------------------------------------------------------
def save(am: Amortised, out, force: bool = False, inputs=(), log=None) -> Path:
    """Write ``out/`` (``model.msgpack``: the weights; ``model.json``: the record) atomically:
    built aside and moved into place whole; an existing folder is replaced only with ``force``
    and only if treeinfer wrote it (the old one kept as ``NAME.old-<time>``)."""
    from flax.serialization import msgpack_serialize

    from ..io.atomic import staged_output_dir
    from ..io.jsonio import write_json

    blob = msgpack_serialize({str(i): a for i, a in enumerate(am.weight_leaves())})
    import hashlib

    meta = {**am.meta, "weights_sha256": hashlib.sha256(blob).hexdigest()}
    with staged_output_dir(out, force, "amortised model", inputs, log) as stage:
        (stage / WEIGHTS_FILE).write_bytes(blob)
        write_json(stage / META_FILE, meta)
    am.meta = meta
    return Path(out)


def load(path) -> Amortised:
    """The model in folder ``path`` (ConfigError naming the file for a missing, corrupt or
    foreign one)."""
    import hashlib

    from ..io.jsonio import read_json

    path = Path(path)
    if not (path / META_FILE).is_file() or not (path / WEIGHTS_FILE).is_file():
        raise ConfigError(
            f"{path}: not an amortised model folder (needs {META_FILE} and {WEIGHTS_FILE}, as "
            "`treeinfer amortise --out` writes)"
        )
    meta = read_json(path / META_FILE, "amortised model record")
    if meta.get("format") not in READABLE_FORMATS:
        raise ConfigError(
            f"{path / META_FILE}: format {meta.get('format')!r}, expected one of "
            f"{', '.join(READABLE_FORMATS)} (a model "
            "from another treeinfer version: train it again with `treeinfer amortise`)"
        )
    blob = (path / WEIGHTS_FILE).read_bytes()
    if hashlib.sha256(blob).hexdigest() != meta.get("weights_sha256"):
        raise ConfigError(f"{path / WEIGHTS_FILE}: does not match the sha256 in {META_FILE}")
    try:
        stored = read_weights(blob)
        values = [stored[str(i)] for i in range(len(stored))]
    except Exception as e:  # noqa: BLE001 -- any decoding failure is a corrupt file
        raise ConfigError(f"{path / WEIGHTS_FILE}: cannot be read ({e})") from None
    am = Amortised(None, meta, weights=values)
    try:
        am.fast  # noqa: B018 -- the arrays' shapes checked against the recorded architecture now
    except ConfigError as e:
        raise ConfigError(f"{path / WEIGHTS_FILE}: {e}") from None
    return am


def read_weights(blob: bytes) -> dict:
    """``{"0": array, ...}`` of a ``model.msgpack`` (flax's ``msgpack_serialize`` of the leaves).

    Read with msgpack itself (flax's dependency) rather than flax's ``msgpack_restore``:
    importing ``flax.serialization`` costs 0.7 s on the 2-core CPU, more than the rest of a
    new recording's posterior, for a format of three fields per array (flax's ndarray
    extension: code 1, the msgpack of shape, dtype name and C-order bytes)."""
    import msgpack

    def ext(code, data):
        if code != 1:
            raise ValueError(f"msgpack extension {code} is not flax's ndarray")
        shape, dtype, buf = msgpack.unpackb(data, raw=True)
        return np.frombuffer(buf, dtype=np.dtype(dtype.decode())).reshape(shape)

    return msgpack.unpackb(blob, ext_hook=ext, raw=False, strict_map_key=False)


def summarize(theta, labels: Sequence[str]) -> list[dict]:
    """Per column the posterior mean and 95% interval in natural units (exp of the log column)."""
    with np.errstate(over="ignore"):  # a flow far outside its training (a recording the
        nat = np.exp(np.asarray(theta, float))  # check will refuse) may draw exp overflows
    out = []
    for j, lab in enumerate(labels):
        lo, hi = np.quantile(nat[:, j], [0.025, 0.975])
        out.append(
            {"label": lab, "mean": float(nat[:, j].mean()), "lower": float(lo), "upper": float(hi)}
        )
    return out


def _finite(x) -> bool:
    return all(math.isfinite(float(v)) for v in np.ravel(x))
