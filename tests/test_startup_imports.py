"""A cold start pays only for what the ``--init importance`` path uses (issue 15).

``treeinfer infer --init importance`` (and ``benchmarks/_ttp_child.py``'s ``importance`` path)
import the modules below; none of them may pull in the libraries that only other paths need
(samplers: blackjax, optax; NN-prior training and loading: flax; other likelihoods: numpyro,
scipy.stats; writing the run folder: arviz, matplotlib). Each costs 0.05-1.5 s of a process
start that should be about jax + numpy + mujoco (``BENCHMARKS.md``, issue 15). Structural checks
in a fresh interpreter, not timings: ``python -X importtime`` lists every module imported, and
a failure names the chain that imported the offender.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# what the importance path imports: the library's problem and fast posterior, the run layer and
# the CLI command that drive it, the benchmark child
ENTRY = (
    "treeinfer.inference.problem",
    "treeinfer.inference.fast",
    "treeinfer.inference.importance",
    "treeinfer.sim.startup",
    "treeinfer.tree.description",
    "treeinfer.data.trajectories",
    "treeinfer.runs",
    "treeinfer.runs.problem",
    "treeinfer.runs.start",
    "treeinfer.cli.infer",
    "benchmarks._ttp_child",
)
HEAVY = (
    "flax",
    "blackjax",
    "optax",
    "arviz",
    "arviz_base",  # ArviZ 1.x
    "arviz_stats",
    "numpyro",
    "scipy.stats",
    "scipy.optimize",
    "matplotlib",
    "pandas",
    "xarray",
)


def _env() -> dict:
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, "JAX_PLATFORMS": "cpu"}


def _import_tree(stderr: str) -> list[tuple[int, str]]:
    """``(depth, module)`` rows of ``-X importtime`` output, in completion order."""
    rows = []
    for line in stderr.splitlines():
        m = re.match(r"import time:\s+\d+ \|\s+\d+ \|( *)(\S+)", line)
        if m:
            rows.append((len(m.group(1)) // 2, m.group(2)))
    return rows


def _chains(rows: list[tuple[int, str]], wanted) -> dict[str, str]:
    """For each module in ``wanted`` that was imported: the chain of importers (innermost
    first). A row's importer is the next completed row one level shallower."""
    out = {}
    for i, (depth, name) in enumerate(rows):
        hit = next((w for w in wanted if name == w or name.startswith(w + ".")), None)
        if hit is None or hit in out:
            continue
        chain, d = [name], depth
        for dj, nj in rows[i + 1 :]:
            if dj < d:
                chain.append(nj)
                d = dj
        out[hit] = " <- ".join(chain)
    return out


def test_the_importance_path_modules_import_no_heavy_library():
    code = "; ".join(f"import {m}" for m in ENTRY)
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=_env(),
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = _import_tree(proc.stderr)
    names = {n for _, n in rows}
    assert "treeinfer.inference.fast" in names and "jax" in names  # the parse saw the imports
    found = _chains(rows, HEAVY)
    assert not found, "heavy imports on the importance path:\n" + "\n".join(
        f"  {k}: {v}" for k, v in found.items()
    )


def test_the_chain_parser_names_the_importer():
    """The parser on ``-X importtime`` output of a known nesting (so the check above cannot
    pass because it reads nothing)."""
    text = textwrap.dedent(
        """\
        import time: self [us] | cumulative | imported package
        import time:        10 |         10 |     scipy.stats._x
        import time:        10 |         20 |   scipy.stats
        import time:        10 |         30 | treeinfer.model.noise
        import time:        10 |         10 | flax
        """
    )
    rows = _import_tree(text)
    assert rows[0] == (2, "scipy.stats._x")
    found = _chains(rows, ("scipy.stats", "flax", "arviz"))
    assert found == {"scipy.stats": "scipy.stats._x <- scipy.stats <- treeinfer.model.noise",
                     "flax": "flax"}  # fmt: skip


@pytest.mark.slow
def test_a_fast_posterior_run_imports_no_heavy_library(tmp_path):
    """Running the path, not only importing it: problem, screen, LM fit and importance weights
    on a one-joint tree (no inequality prior: its network is flax) leave the heavy libraries
    unimported."""
    code = textwrap.dedent(
        """
        import sys
        import numpy as np
        from treeinfer.inference.fast import fast_posterior
        from treeinfer.tree.generators import chain
        from treeinfer.inference.problem import make_problem
        from treeinfer.data.trajectories import Trajectory

        tree = chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0, 0, 1.5),
                     base_pitch_deg=20.0, levels=1, name="c1")
        t = np.arange(40) * 0.01
        f = 5.0 * np.clip(t / 0.1, 0.0, 1.0) * (t < 0.25)
        x = 0.01 * np.clip(t / 0.1, 0.0, 1.0) * (t < 0.25)
        # the paper's loss, explicitly (the API's default became the Gaussian likelihood, whose
        # noise densities are numpyro's)
        problem = make_problem(tree, [Trajectory(t, f, x, None, "p")], substeps=2,
                               nn_prior=False, kT=0.05, likelihood="boltzmann")
        res = fast_posterior(problem, 16, n_starts=2, n_draws=64, max_iterations=3)
        assert res.theta.shape == (16, 2)
        print(" ".join(sorted(sys.modules)))
        """
    )
    env = {**_env(), "TREEINFER_JAX_CACHE": str(tmp_path / "cc")}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env,
        timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    loaded = set(proc.stdout.split())
    assert "treeinfer.inference.fast" in loaded
    bad = sorted(m for m in loaded for h in HEAVY if m == h or m.startswith(h + "."))
    assert not bad, bad


def test_the_bundled_inequality_network_loads_and_runs_without_flax():
    """NNSVGD's default prior on the start-up path: the bundled network is read with msgpack and
    applied in jax.numpy, so a cold process never imports flax (only training does)."""
    code = textwrap.dedent(
        """
        import sys
        import jax.numpy as jnp
        from treeinfer.model.priors import inequality_prior, load_or_train_inequality_network
        net = load_or_train_inequality_network(0.0, 1.0)
        assert net.loaded
        print(float(inequality_prior(net, [(0, 1)])(jnp.array([[0.2, 0.7]]))[0]))
        print(" ".join(sorted(sys.modules)))
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=_env(),
        timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    value, modules = proc.stdout.splitlines()[:2]
    assert float(value) < 0  # the inequality is violated there: a penalty
    assert not [m for m in modules.split() if m == "flax" or m.startswith("flax.")]
