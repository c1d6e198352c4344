"""The statistics behind issue 27's measurement scripts (``experiments/sbc_default.py``,
``experiments/_study_stats.py``), checked where the answer is known in closed form:

* SBC's driver and summary on a conjugate Gaussian model, whose exact posterior gives uniform
  ranks, and on an over-confident posterior (half the std), which must fail the 1% test;
* records added over several calls (a time budget) summarise as one call does;
* the Cramer-Rao bound of a linear model equals ``sigma^2 (A^T A)^-1`` (Jacobian by jax.jacfwd)
  and, with correlated noise, the spread of the generalised least-squares estimate (Monte Carlo);
* Clopper-Pearson ends where the binomial has the closed form (k = 0, k = n);
* the default path's gain prior: the script's draws follow the density ``make_problem`` builds.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments import sbc_default
from experiments._study_stats import (
    append_jsonl,
    clopper_pearson,
    crb_from_jacobian,
    identified,
    rate_record,
    read_jsonl,
)

N_OBS, SIGMA = 5, 0.7  # conjugate toy: theta ~ N(0, 1), y_j ~ N(theta, SIGMA^2), j = 1..N_OBS


def _toy(over_confidence: float = 1.0, n_draws: int = 31):
    """``one(i)`` for :func:`sbc_default.run_sbc`: exact posterior draws of the conjugate toy
    (two independent parameters), their std divided by ``over_confidence``."""

    def one(i: int) -> dict:
        rng = np.random.default_rng([7, i])
        theta = rng.normal(size=2)
        y = theta[None] + SIGMA * rng.normal(size=(N_OBS, 2))
        prec = 1.0 + N_OBS / SIGMA**2
        mean, sd = y.sum(0) / SIGMA**2 / prec, 1.0 / np.sqrt(prec)
        draws = mean + sd / over_confidence * rng.normal(size=(n_draws, 2))
        return {
            "truth": {"a": theta[0], "b": theta[1]},
            "labels": ["a", "b"],
            "draws": draws.tolist(),
        }

    return one


def test_sbc_of_an_exact_posterior_is_uniform(tmp_path):
    rec = tmp_path / "records.jsonl"
    assert sbc_default.run_sbc(rec, range(300), _toy(), log=lambda m: None) == 300
    s = sbc_default.summarise(read_jsonl([rec]))
    assert s["n_ranked"] == 300 and s["n_failed"] == 0
    assert s["uniformity"]["pass"], s["uniformity"]
    cover95 = next(row for row in s["coverage"] if row["level"] == 0.95)
    for lab in ("a", "b"):
        assert cover95["band_99"][0] <= cover95[lab] <= cover95["band_99"][1]


def test_sbc_flags_an_over_confident_posterior(tmp_path):
    rec = tmp_path / "records.jsonl"
    sbc_default.run_sbc(rec, range(300), _toy(over_confidence=2.0), log=lambda m: None)
    s = sbc_default.summarise(read_jsonl([rec]))
    assert not s["uniformity"]["pass"]
    assert all(not v["pass"] for v in s["uniformity"]["parameters"].values())
    # a U-shaped histogram: the end bins hold far more than their share
    counts = np.asarray(s["uniformity"]["parameters"]["a"]["counts"])
    assert counts[0] + counts[-1] > 3 * 2 * 300 / len(counts)


def test_records_of_several_calls_add_up(tmp_path):
    """A call stopped by its budget, then another: the same records and summary as one call;
    a record cut short by a kill is skipped; a damaged line elsewhere names file and line."""
    one_go, split = tmp_path / "one.jsonl", tmp_path / "split.jsonl"
    sbc_default.run_sbc(one_go, range(60), _toy(), log=lambda m: None)
    sbc_default.run_sbc(split, range(25), _toy(), log=lambda m: None)
    assert sbc_default.run_sbc(split, range(60), _toy(), budget_s=1e-9, log=lambda m: None) == 0
    assert sbc_default.run_sbc(split, range(60), _toy(), log=lambda m: None) == 35
    a, b = read_jsonl([one_go]), read_jsonl([split])
    assert [r["index"] for r in b] == list(range(60))
    assert [r["draws"] for r in a] == [r["draws"] for r in b]
    assert sbc_default.summarise(a)["u"] == sbc_default.summarise(b)["u"]
    with open(split, "a") as f:
        f.write('{"index": 99, "draws": [[1')  # killed mid-write
    assert len(read_jsonl([split])) == 60
    # finished studies keep their records gzipped: the same records, the cut last line skipped too
    import gzip

    packed = tmp_path / "split.jsonl.gz"
    packed.write_bytes(gzip.compress(split.read_bytes()))
    assert read_jsonl([packed]) == read_jsonl([split])
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"index": 0}\nnot json\n{"index": 1}\n')
    with pytest.raises(ValueError, match="bad.jsonl:2"):
        read_jsonl([bad])


def test_failed_fits_are_counted_not_ranked(tmp_path):
    rec = tmp_path / "r.jsonl"
    toy = _toy()
    sbc_default.run_sbc(
        rec, range(30), lambda i: {"error": "boom"} if i == 3 else toy(i), log=lambda m: None
    )
    s = sbc_default.summarise(read_jsonl([rec]))
    assert (s["n_ranked"], s["n_failed"]) == (29, 1)
    assert s["failures"] == [{"index": 3, "error": "boom"}]


def test_crb_of_a_linear_model_is_the_closed_form():
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    a = rng.normal(size=(40, 3))
    jac = np.asarray(jax.jacfwd(lambda th: jnp.asarray(a) @ th)(jnp.ones(3)), float)
    np.testing.assert_allclose(jac, a, rtol=1e-6)
    sigma = 0.3
    closed = sigma * np.sqrt(np.diag(np.linalg.inv(a.T @ a)))
    np.testing.assert_allclose(crb_from_jacobian(jac, sigma), closed, rtol=1e-6)  # jac in float32
    # unidentified direction (a column of zeros): an infinite bound, not an error
    assert np.isinf(crb_from_jacobian(np.c_[a, np.zeros(40)], sigma)[-1])


def test_crb_with_correlated_noise_is_the_spread_of_the_gls_estimate():
    """y = A theta + e, e ~ N(0, C + s^2 I): the generalised least-squares estimate is unbiased
    and efficient, so its std over noise draws equals the bound (Monte Carlo, 4000 draws)."""
    rng = np.random.default_rng(1)
    n, d, s = 30, 2, 0.2
    a = rng.normal(size=(n, d))
    b = rng.normal(size=(n, 4)) * 0.3
    c = b @ b.T  # a low-rank correlated part, as the force-noise term
    crb = crb_from_jacobian(a, s, cov=c)
    sigma = c + s**2 * np.eye(n)
    chol = np.linalg.cholesky(sigma)
    w = np.linalg.solve(sigma, a)
    gls = np.linalg.solve(a.T @ w, w.T)  # [d, n]
    est = (chol @ rng.normal(size=(n, 4000))).T @ gls.T
    np.testing.assert_allclose(est.std(axis=0), crb, rtol=0.05)
    assert np.all(crb > crb_from_jacobian(a, s))  # correlated noise leaves less information


def test_clopper_pearson_closed_forms_and_rate_record():
    lo, hi = clopper_pearson(0, 10)
    assert lo == 0.0 and hi == pytest.approx(1 - 0.025 ** (1 / 10), rel=1e-9)
    lo, hi = clopper_pearson(10, 10)
    assert hi == 1.0 and lo == pytest.approx(0.025 ** (1 / 10), rel=1e-9)
    r = rate_record([True] * 57 + [False] * 3)
    assert (r["k"], r["n"]) == (57, 60) and r["nominal_inside_ci"]
    assert not rate_record([True] * 40 + [False] * 20)["nominal_inside_ci"]


def test_identified_uses_the_prior_width():
    w = np.log(100.0)  # Kp box 5-500 N m/rad: prior std 1.33 in log units
    assert identified(0.05, w) and not identified(0.5, w)


def test_jsonl_keeps_nan_and_appends(tmp_path):
    p = tmp_path / "x.jsonl"
    append_jsonl(p, {"index": 1, "v": float("nan")})
    append_jsonl(p, {"index": 0, "v": 2.0})
    recs = read_jsonl([p])
    assert [r["index"] for r in recs] == [0, 1] and np.isnan(recs[1]["v"])
    assert json.loads(p.read_text().splitlines()[0])["index"] == 1


@pytest.fixture(scope="module")
def two_branch():
    from treeinfer.examples import example_path
    from treeinfer.tree import load_tree

    return load_tree(example_path("two_branch"))


def test_gain_prior_density_is_make_problems(two_branch):
    """The script's prior (box + learned inequality prior, the default options) differs from
    the log prior of the problem the default path builds by a constant (the sigma_x term, flat
    where the noise column is held)."""
    from treeinfer.cli.infer_options import INFER_DEFAULTS
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference.problem import make_problem

    t = np.arange(20) * 0.02
    traj = Trajectory(t, np.clip(t / 0.2, 0, 1) * 4.0, 0.01 * np.clip(t / 0.2, 0, 1), None, "p")
    problem = make_problem(two_branch, [traj], substeps=4)
    prior = sbc_default.GainPrior(two_branch, INFER_DEFAULTS)
    assert prior.nn is not None  # NNSVGD, the default sampler, adds the inequality prior
    th = prior._box(np.random.default_rng(3), 64)
    full = np.c_[th, np.full(64, np.log(0.002))]
    diff = np.asarray(problem.log_prior(full), float) - prior.log_density(th)
    assert np.ptp(diff) < 1e-3, diff


def test_gain_prior_draws_follow_its_density(two_branch):
    """Rejection draws against self-normalised importance weights of box draws: the share of
    draws with the parent stiffer than the child, and the mean, agree."""
    from treeinfer.cli.infer_options import INFER_DEFAULTS

    prior = sbc_default.GainPrior(two_branch, INFER_DEFAULTS)
    rng = np.random.default_rng(5)
    draws = prior.draw(rng, 4000)
    box = prior._box(rng, 40000)
    w = np.exp(prior._nn(box) - prior.nn_max)
    w /= w.sum()
    r = two_branch.n_inferred
    parent, child = two_branch.inferred_pairs()[0]
    share = np.mean(draws[:, parent] >= draws[:, child])
    share_is = float(np.sum(w * (box[:, parent] >= box[:, child])))
    assert share == pytest.approx(share_is, abs=0.03)
    assert share > 0.8  # the learned prior does favour the stiffer parent
    np.testing.assert_allclose(draws.mean(0), w @ box, atol=0.08)
    assert draws.shape == (4000, 2 * r)


@pytest.mark.slow
def test_sbc_default_tiny_end_to_end(tmp_path):
    """One data set through the real default path; a second call adds nothing (resumed)."""
    argv = ["--size", "tiny", "--n-datasets", "1", "--out", str(tmp_path)]
    res = sbc_default.main(argv)
    s = res["summary"]
    assert (s["n_ranked"], s["n_failed"]) == (1, 0), s.get("failures")
    assert s["labels"][-1] == "sigma_x" and len(s["labels"]) == 5
    rec = read_jsonl([tmp_path / "records.jsonl"])[0]
    assert set(rec["truth"]) == set(rec["labels"]) and len(rec["draws"]) >= 2
    assert rec["stop_reason"] and rec["status"] in ("ok", "warning", "poor_fit")
    for f in ("results.json", "results.md", "rank_histograms.png"):
        assert (tmp_path / f).exists()
    assert res["config"]["infer_defaults"]["likelihood"] == "gaussian"
    again = sbc_default.main(argv)
    assert again["summary"]["n_records"] == 1


def test_workers_skip_what_another_file_holds(tmp_path):
    """Two workers' files (i mod 2) and a later single call: nothing fitted twice, every index
    once in the union."""
    w0, w1, single = (
        tmp_path / f for f in ("records_w0.jsonl", "records_w1.jsonl", "records.jsonl")
    )
    toy = _toy()
    sbc_default.run_sbc(w0, range(0, 20, 2), toy, log=lambda m: None)
    sbc_default.run_sbc(w1, range(1, 10, 2), toy, log=lambda m: None)
    added = sbc_default.run_sbc(single, range(20), toy, log=lambda m: None, done_in=[w0, w1])
    assert added == 5  # 11, 13, 15, 17, 19
    assert [r["index"] for r in read_jsonl([w0, w1, single])] == list(range(20))
