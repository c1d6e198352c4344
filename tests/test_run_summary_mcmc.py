"""The run summary's MCMC R-hat/ESS use the run's own ``--mcmc-warmup`` (issue 11, section 3:
"MCMC baselines summarise the post-warm-up trace ..., R-hat/ESS computed on that"). Before,
the summaries cut the trace at ``--mcmc-warmup`` while R-hat/ESS always cut it at half."""

from __future__ import annotations

import numpy as np
import pytest

from treeinfer.inference import diagnostics as dg
from treeinfer.runs.folder import _diagnostics


def _chains(S=400, C=8, start=40.0, seed=0):
    """AR(1) chains (rho 0.9) started at ``start``: the first ~60 draws are the approach."""
    rng = np.random.default_rng(seed)
    x = np.empty((S, C, 1))
    x[0] = start * rng.uniform(0.5, 1.5, (C, 1))
    for t in range(1, S):
        x[t] = 0.9 * x[t - 1] + np.sqrt(1 - 0.81) * rng.standard_normal((C, 1))
    return {"positions": x, "log_density": -0.5 * x[..., 0] ** 2, "resumed_from": None}


@pytest.mark.parametrize("warmup", [0.2, 0.5, 0.75])
def test_rhat_and_ess_use_the_runs_warmup(warmup):
    trace = _chains()
    kind, diag, _ = _diagnostics("mh", trace, ["a"], warmup)
    assert kind == "mcmc"
    S = trace["positions"].shape[0]
    assert diag["n_burn_in"] == int(np.floor(warmup * S))
    # the same numbers as the summary's own statistics on its post-warm-up draws
    ref = dg.mcmc_diagnostics(trace["positions"], ["a"], burn_in=warmup)
    assert diag["parameters"]["a"]["rhat"] == pytest.approx(ref["parameters"]["a"]["rhat"])
    assert diag["n_draws"] == S - int(np.floor(warmup * S))


def test_no_warmup_keeps_the_approach_in_rhat():
    """With the approach left in (warm-up 0), R-hat sees the chains' different starts; with
    the default half it does not: the option changes what is diagnosed, as it should."""
    trace = _chains(S=120)
    _, none, _ = _diagnostics("mh", trace, ["a"], 0.0)
    _, half, _ = _diagnostics("mh", trace, ["a"], 0.5)
    assert none["parameters"]["a"]["rhat"] > half["parameters"]["a"]["rhat"]
