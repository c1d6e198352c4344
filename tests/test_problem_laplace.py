"""The Laplace start of any problem (:func:`treeinfer.laplace.problem_laplace`): the MAP and the
Hessian of the log-density's values, checked on a Gaussian of known mean and covariance; the MH
proposal built from it; and ``--init laplace`` for the static model with a soft taper tie."""

from __future__ import annotations

import json
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.laplace import (
    mh_proposal,
    problem_laplace,
    problem_laplace_particles,
    value_hessian,
)


def _gaussian_problem(mean, cov, lower, upper):
    prec = jnp.asarray(np.linalg.inv(cov), jnp.float32)
    mu = jnp.asarray(mean, jnp.float32)

    def log_density(theta):
        d = jnp.asarray(theta, jnp.float32) - mu
        return -0.5 * jnp.einsum("pi,ij,pj->p", d, prec, d)

    def value_and_grad(theta):
        d = jnp.asarray(theta, jnp.float32) - mu
        return log_density(theta), -(d @ prec)

    return SimpleNamespace(
        lower=np.asarray(lower, float),
        upper=np.asarray(upper, float),
        log_density=log_density,
        value_and_grad=value_and_grad,
    )


def test_laplace_of_a_gaussian_recovers_its_mean_and_covariance():
    mean = np.array([1.0, -0.5, 0.2])
    a = np.array([[0.3, 0.0, 0.0], [0.1, 0.05, 0.0], [-0.02, 0.01, 0.2]])
    cov = a @ a.T  # correlated, stds 0.05 .. 0.3
    prob = _gaussian_problem(mean, cov, [-3, -3, -3], [3, 3, 3])
    lap = problem_laplace(prob, n_starts=16, seed=1, box_precision=False)
    np.testing.assert_allclose(lap.theta, mean, atol=1e-3)
    np.testing.assert_allclose(lap.cov, cov, rtol=2e-2, atol=2e-4)
    # the box's precision only adds 12 / width^2
    boxed = problem_laplace(prob, n_starts=16, seed=1)
    np.testing.assert_allclose(
        np.linalg.inv(boxed.cov) - np.linalg.inv(cov), np.diag([12 / 36.0] * 3), atol=0.05
    )
    # draws have that covariance; the MH proposal is 2.38 / sqrt(D) of its Cholesky factor
    x = np.asarray(problem_laplace_particles(jax.random.key(0), lap, 20000))
    np.testing.assert_allclose(np.cov(x.T), lap.cov, rtol=0.05, atol=5e-4)
    chol = mh_proposal(lap.cov)
    np.testing.assert_allclose(chol @ chol.T, 2.38**2 / 3 * lap.cov, rtol=1e-6, atol=1e-9)


def test_value_hessian_of_a_quadratic_is_exact():
    h = np.array([[-4.0, 1.0], [1.0, -2.0]])
    prob = SimpleNamespace(
        log_density=lambda th: 0.5 * jnp.einsum("pi,ij,pj->p", th, jnp.asarray(h), th) + 3.0
    )
    np.testing.assert_allclose(value_hessian(prob, [0.3, -0.2], [0.1, 0.2]), h, atol=1e-3)


@pytest.mark.slow
def test_init_laplace_runs_for_the_static_model_with_a_soft_tie(tmp_path, capsys):
    """``infer --model-kind static --tie taper --tie-scale 0.1 --init laplace``: the start is
    drawn around the MAP of the run's own log-density (logged), and the run completes."""
    import dataclasses

    from treeinfer.cli.main import main
    from treeinfer.csv_import import import_csv
    from treeinfer.synthetic_stem import Stem, branch_at_height, stem_tree, write_stem_logs
    from treeinfer.tree import dump_tree

    tree = dataclasses.replace(
        stem_tree(Stem(), n_links=2, kp_bounds=(0.05, 50.0)), pull_direction="horizontal"
    )
    dump_tree(tree, tmp_path / "stem.yaml")
    for path, push in write_stem_logs(tmp_path / "raw", Stem(), heights=(0.15, 0.35), seed=2):
        branch, dist = branch_at_height(tree, push.height)
        import_csv(
            [path],
            tmp_path / "data",
            time="millis",
            force="load_g",
            displacement="pos_mm",
            units="time=ms,force=gf,displacement=mm",
            dt=0.5,
            tare=True,
            zero_displacement="contact",
            trim=True,
            grasp_branch=branch,
            grasp_distance=dist,
            direction="horizontal",
            tree=tree,
        )
    run = tmp_path / "run"
    args = ["infer", "--tree", str(tmp_path / "stem.yaml"), "--data", str(tmp_path / "data")]
    args += ["--out", str(run), "--model-kind", "static", "--likelihood", "gaussian"]
    args += ["--tie", "taper", "--tie-scale", "0.1", "--init", "laplace", "--sampler", "mh"]
    args += ["--particles", "4", "--iterations", "3", "--no-progress", "--checkpoint-every", "0"]
    args += ["--allow-poor-fit"]
    rc = main(args)
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "Laplace start: MAP of the log-density" in err
    config = json.loads((run / "config.json").read_text())
    assert config["options"]["init"] == "laplace"
