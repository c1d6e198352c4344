"""Where to add a sensor (issue 30): rank candidate markers and inclinometers on the tree by how
much they would have narrowed a run's posterior on the pulls it already has.

For a candidate channel ``g`` (the displacement of a point, or the rotation of a link, along
world axes) recorded on the training pulls with white noise ``sigma``, the linearised (Laplace)
update of the posterior of the log gains is

    Sigma_new = (Sigma^-1 + J^T J / sigma^2)^-1,   J = d g / d theta at the posterior mean

with ``Sigma`` the particles' covariance and ``J`` by central differences of the batched
simulator (:func:`treeinfer.sim.observe.simulate_features`: one call for every candidate and
every difference). The score is the expected information gain ``1/2 log det Sigma / Sigma_new``
(nats); each parameter's std ratio ``sqrt(Sigma_jj / Sigma_new_jj)`` says which joints it
teaches. Linearised at one point: a posterior far from Gaussian (a damping at the edge of its
prior box) is only roughly described; ``experiments/observations_anywhere.py`` measures the real
shrinkage of one candidate.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from ..errors import ConfigError

DEFAULT_FRACTIONS = (0.25, 0.5, 0.75, 1.0)
DEFAULT_NOISE = {"position": 1e-3, "angle": 1e-3}  # m, rad: a camera marker, an inclinometer


class SensorScore(NamedTuple):
    """A ranked candidate: ``kind``, ``link``, ``fraction``, ``components``, ``noise`` (SI),
    ``gain`` (nats), ``std_ratio`` {label: sd now / sd with the sensor}."""

    kind: str
    link: str
    fraction: float
    components: str
    noise: float
    gain: float
    std_ratio: dict

    def label(self) -> str:
        at = f"{self.fraction:g}" if self.kind == "position" else "link"
        return f"{self.kind} {self.components} at {self.link}@{at}"


def candidate_sensors(links: Sequence[str], fractions=DEFAULT_FRACTIONS, noise=None) -> list:
    """``(kind, link, fraction, components, noise)`` for a marker (x, y, z) at every fraction
    of every link and an inclinometer (about x, y, z) on every link."""
    noise = {**DEFAULT_NOISE, **(noise or {})}
    out = [("position", n, float(f), "xyz", noise["position"]) for n in links for f in fractions]
    out += [("angle", n, 0.5, "xyz", noise["angle"]) for n in links]
    return out


def rank_sensors(
    sim,
    theta,
    labels: Sequence[str],
    forces,
    candidates=None,
    rel_step: float = 1e-2,
    model=None,
    grasp_fraction=None,
) -> list[SensorScore]:
    """Candidates (default :func:`candidate_sensors` on every link of ``sim``) ranked by expected
    information gain for the run's particles ``theta [P, D]`` (gain columns first) on the pulls
    ``forces [B, T]`` (N, at the tree's grasp point, or each at its own branch, point and
    direction with ``model``: a :class:`treeinfer.inference.static.Model`, static or dynamic,
    whose gain columns are ``model.layout.dim``; None: the paper's ``[log Kp, log Kd]``)."""
    from ..inference.static.channels import model_features
    from ..sim.observe import feature_for

    d = 2 * sim.n_joints if model is None else model.layout.dim
    theta = np.atleast_2d(np.asarray(theta, float))[:, :d]
    if len(theta) < d + 2:
        raise ConfigError(f"rank_sensors: need at least {d + 2} particles, got {len(theta)}")
    cov = np.cov(theta, rowvar=False) + 1e-12 * np.eye(d)
    mean = theta.mean(0)
    cands = candidate_sensors(list(sim.branches)) if candidates is None else list(candidates)
    feats = tuple(feature_for(sim, k, link, f) for k, link, f, _, _ in cands)
    pts = np.concatenate([mean[None], mean + rel_step * np.eye(d), mean - rel_step * np.eye(d)])
    feat, ok = model_features(sim, model, pts, np.atleast_2d(forces), feats, grasp_fraction)
    if not np.all(np.asarray(ok)):
        raise ConfigError("rank_sensors: unstable simulations at the posterior mean's neighbours")
    f = np.asarray(feat, float)  # [1 + 2D, B, T, F, 3]
    jac = (f[1 : 1 + d] - f[1 + d :]) / (2 * rel_step)  # [D, B, T, F, 3]
    prec0 = np.linalg.inv(cov)
    _, logdet0 = np.linalg.slogdet(cov)
    gain_labels = list(labels)[:d]
    out = []
    for i, (kind, link, frac, comps, sigma) in enumerate(cands):
        axes = ["xyz".index(c) for c in comps]
        j = jac[:, :, :, i][..., axes].reshape(d, -1).T  # [N, D]
        new = np.linalg.inv(prec0 + j.T @ j / sigma**2)
        _, logdet = np.linalg.slogdet(new)
        ratio = np.sqrt(np.diag(cov) / np.diag(new))
        out.append(
            SensorScore(
                kind,
                link,
                frac,
                comps,
                float(sigma),
                0.5 * float(logdet0 - logdet),
                dict(zip(gain_labels, ratio.tolist())),
            )  # fmt: skip
        )
    return sorted(out, key=lambda s: -s.gain)


def sensors_table(scores: Sequence[SensorScore], top: int = 10) -> list[str]:
    """Printable lines of the ranking."""
    if not scores:
        return []
    labs = list(scores[0].std_ratio)
    lines = [f"{'sensor':34s} {'gain':>7s}  " + "  ".join(f"{lab:>12s}" for lab in labs)]
    for s in scores[:top]:
        lines.append(
            f"{s.label():34s} {s.gain:7.2f}  "
            + "  ".join(f"{s.std_ratio[lab]:11.2f}x" for lab in labs)
        )
    return lines
