"""The typed problem specification (issue 26): make_problem's options validated once, in one
dataclass, with the same problem whether given as a spec or as keywords."""

from __future__ import annotations

import numpy as np
import pytest

import treeinfer as ti
from treeinfer.errors import ConfigError
from treeinfer.inference.spec import ProblemSpec


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("gradient", "xx", "gradient: expected one of"),
        ("likelihood", "gauss", "likelihood: expected one of"),
        ("prior_space", "exp", "prior_space"),
        ("model_kind", "quasi", "model_kind"),
        ("backend", "cuda", "backend"),
        ("force_interp", "cubic", "force_interp"),
        ("prior_sigma", 0.0, "prior_sigma"),
        ("rel_step", -1e-3, "rel_step"),
        ("noise_displacement", float("nan"), "noise_displacement"),
        ("substeps", 0, "substeps"),
        ("shape_bucket", (3,), "shape_bucket"),
        ("eta", -1.0, "eta"),
        ("kT", 0.5, "likelihood='boltzmann'"),  # a kT without the Boltzmann loss
    ],
)
def test_each_field_is_checked_when_the_spec_is_made(field, value, words):
    with pytest.raises(ConfigError, match=words.replace("(", r"\(")):
        ProblemSpec(**{field: value})


def test_velocity_noise_needs_a_generative_likelihood():
    with pytest.raises(ConfigError, match="noise-velocity"):
        ProblemSpec(likelihood="boltzmann", noise_velocity=0.01)


def test_unknown_option_names_the_known_ones():
    with pytest.raises(ConfigError, match="unknown option.*likelihod.*known: backend"):
        ProblemSpec.from_options(None, likelihod="gaussian")


def test_replace_validates_again():
    spec = ProblemSpec(likelihood="boltzmann", kT=0.1)
    assert spec.replace(kT=0.2).kT == 0.2 and spec.kT == 0.1
    with pytest.raises(ConfigError):
        spec.replace(gradient="nope")


def test_spec_and_keywords_build_the_same_problem():
    tree = ti.load_tree(ti.example_path("two_branch"))
    sim = ti.make_simulator(tree, obs_dt=0.02, substeps=4)
    forces = np.linspace(0.0, 4.0, 40)[None]
    roll = ti.simulate(sim, np.array([[30.0, 60.0]]), np.array([[0.4, 0.8]]), forces)
    traj = ti.Trajectory(
        time=np.arange(40) * 0.02,
        force=forces[0],
        displacement=np.asarray(roll.tau[0, 0]),
    )
    spec = ProblemSpec(likelihood="gaussian", noise_displacement=0.001, noise_force=None)
    a = ti.make_problem(tree, [traj], spec, sim=sim)
    b = ti.make_problem(
        tree, [traj], sim=sim, likelihood="gaussian", noise_displacement=0.001, noise_force=None
    )
    assert a.spec == b.spec == spec
    assert a.settings == b.settings and a.labels == b.labels
    theta = np.log(np.array([[30.0, 60.0, 0.4, 0.8]]))
    np.testing.assert_allclose(a.log_density(theta), b.log_density(theta), rtol=1e-6)
    # keywords over a spec change only what they name
    c = ti.make_problem(tree, [traj], spec, sim=sim, nn_prior=False)
    assert c.spec == spec.replace(nn_prior=False) and not c.nn_prior
