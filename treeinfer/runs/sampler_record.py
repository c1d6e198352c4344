"""The sampler record of a run (``config.json``'s ``"sampler"``): the sampler's options, with
the changes a fitted start (``--init laplace``, ``importance``, ``auto``) needs."""

from __future__ import annotations

import numpy as np

from ..inference.samplers import sampler_options

# Particles from --init laplace/importance already have the posterior's spread: full-size Adam
# steps in the first iterations scatter them, so SVGD/NNSVGD ramp the step up over this many
# iterations.
LAPLACE_WARMUP = 10


def laplace_mh_proposal(start) -> list:
    """MH's proposal for ``--init laplace``: the Cholesky factor of ``(2.38^2 / D)`` times the
    covariance of the Laplace start's particles ``[P, D]``
    (:func:`treeinfer.inference.laplace.mh_proposal`), as nested lists (config.json records it, so a
    resumed run moves the same way)."""
    from ..inference.laplace import mh_proposal

    x = np.asarray(start, float)
    cov = np.atleast_2d(np.cov(x.T)) if len(x) > 1 else np.zeros((x.shape[1],) * 2)
    ridge = 1e-10 * max(float(np.trace(cov)) / len(cov), 1e-12)
    return mh_proposal(cov + ridge * np.eye(len(cov))).tolist()


def sampler_settings(config: dict, start=None) -> dict:
    """The sampler record of a run (``config.json``'s ``"sampler"``). With ``--init laplace``:
    SVGD/NNSVGD ramp their step up; MH's proposal is shaped by the start's covariance
    (:func:`laplace_mh_proposal` of ``start``, the Laplace particles; without ``start``, the one
    the config recorded)."""
    name = config["options"]["sampler"]
    options = dict(sampler_options(name))
    init = config["options"].get("init", "uniform")
    # Both fitted starts (Laplace, importance) begin near the posterior: ramp the step up.
    laplace = init in ("laplace", "importance", "auto")
    if laplace and name in ("svgd", "nnsvgd"):
        options["warmup"] = LAPLACE_WARMUP
    if laplace and name == "mh":
        if start is not None:
            options["proposal_scale"] = laplace_mh_proposal(start)
        else:
            recorded = (config.get("sampler") or {}).get("options", {}).get("proposal_scale")
            if isinstance(recorded, list):
                options["proposal_scale"] = recorded
    return {"name": name, "options": options}
