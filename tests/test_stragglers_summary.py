"""The issue's stuck case reaches a run's summary (issue 11, section 3: "A run that leaves them
without a warning is a bug; add a test built from the case above").

``test_convergence.py`` checks ``find_stragglers`` on the issue's numbers; this checks the run
layer's use of it: ``summary.json``'s ``stragglers`` block is computed from the sampler's own
final particles, also when ``--drop-stragglers`` replaced the reported ones, so the count and
the warning cannot be lost on the way to the file and the CLI (which prints
``convergence_warnings``, built from these warnings)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from test_convergence import LOWER, UPPER, issue_case

from treeinfer.runs.folder import _straggler_and_edge

LABELS = ("Kp[branch0]", "Kd[branch0]")


def _run_of(theta, ld, reported=None, dropped=False):
    run = SimpleNamespace(final_positions=theta, final_state=SimpleNamespace(logdensity=ld))
    problem = SimpleNamespace(labels=LABELS, lower=LOWER, upper=UPPER)
    posterior = SimpleNamespace(
        run=run,
        theta=theta if reported is None else reported,
        settings={"dropped_stragglers": dropped},
    )
    return problem, posterior


def test_issue_case_is_counted_and_warned_in_the_summary():
    theta, ld, truth = issue_case()
    strag, edge = _straggler_and_edge(*_run_of(theta, ld))
    assert strag["n_stragglers"] == 7 and strag["n_low_density"] == 7
    assert strag["n_outside_box"] == 7  # Kd 219-394 against the box [0.05, 10]
    assert strag["particles"] == np.flatnonzero(truth).tolist()
    assert any("7 of 32 particles are stuck" in w for w in strag["warnings"])
    # the stuck particles' Kd lies beyond the box's upper edge: that is warned too
    assert any("Kd[branch0]" in w and "upper edge" in w for w in edge["warnings"])


def test_dropped_stragglers_are_still_counted():
    theta, ld, truth = issue_case()
    problem, posterior = _run_of(theta, ld, reported=theta[~truth], dropped=True)
    strag, edge = _straggler_and_edge(problem, posterior)
    assert strag["n_stragglers"] == 7 and strag["dropped"]
    assert any("7 of 32 particles are stuck" in w for w in strag["warnings"])
    assert edge["warnings"] == []  # the reported (kept) particles sit inside the box


def test_a_clean_run_has_no_straggler_warning():
    theta, ld, truth = issue_case()
    strag, _ = _straggler_and_edge(*_run_of(theta[~truth], ld[~truth]))
    assert strag["n_stragglers"] == 0 and strag["warnings"] == []
