"""treeinfer.runs.background: work on a second thread (compiles a run needs later, its figures)
gives the caller the value or the error, and runs on the caller's thread, in the old order, with
TREEINFER_BACKGROUND=off."""

import threading

import pytest

from treeinfer.runs.background import Job, enabled, prefetch


def test_job_runs_on_another_thread_and_hands_back_value_and_error(monkeypatch):
    monkeypatch.delenv("TREEINFER_BACKGROUND", raising=False)
    assert enabled()
    caller = threading.get_ident()
    job = Job(lambda: threading.get_ident())
    assert job.result() != caller
    assert job.done()

    def fail():
        raise ValueError("drawn wrong")

    bad = Job(fail)
    with pytest.raises(ValueError, match="drawn wrong"):
        bad.result()


def test_off_runs_on_the_callers_thread_when_asked(monkeypatch):
    monkeypatch.setenv("TREEINFER_BACKGROUND", "off")
    assert not enabled()
    ran = []
    job = Job(lambda: ran.append(threading.get_ident()) or 7)
    assert ran == []  # nothing before result(): the old order
    assert job.result() == 7 and ran == [threading.get_ident()]
    assert job.result() == 7 and len(ran) == 1  # once
    started = []
    prefetch(lambda: started.append(1)).wait()
    assert started == []  # a prefetch is only worth it on a second thread


def test_prefetch_wait_waits_and_never_raises(monkeypatch):
    monkeypatch.delenv("TREEINFER_BACKGROUND", raising=False)
    gate, done = threading.Event(), []

    def slow():
        gate.wait(5)
        done.append(1)
        raise RuntimeError("unstable at the box's middle")

    p = prefetch(slow)
    assert done == []
    gate.set()
    p.wait()  # the error is swallowed: the main thread meets it again where it matters
    assert done == [1]
    p.wait()  # twice is fine


def test_an_error_while_a_compile_runs_on_the_second_thread_keeps_the_exit_code(tmp_path):
    """A daemon thread inside XLA when the interpreter exits aborts the process (SIGABRT):
    the jobs are not daemons, so the command's own exit code comes back."""
    import subprocess
    import sys

    code = (
        "import jax, jax.numpy as jnp\n"
        "from treeinfer.runs.background import prefetch\n"
        "def f(x):\n"
        "    for i in range(400):\n"
        "        x = jnp.sin(x) * 1.0001 + i\n"
        "    return x\n"
        "prefetch(lambda: jax.jit(f).lower(jnp.ones(3)).compile())\n"
        "raise SystemExit(2)\n"
    )
    env = {**__import__("os").environ, "JAX_PLATFORMS": "cpu", "TREEINFER_BACKGROUND": "on"}
    rc = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path).returncode
    assert rc == 2


def test_the_jacobian_prefetched_on_a_one_substep_simulator_is_the_runs_program():
    """runs.problem compiles the force Jacobian's program on a simulator at one substep while
    the accuracy-controlled step is chosen: the two simulators must share the program (same
    key, the cache's shared table of Jacobian programs), or the run compiles it twice."""
    import numpy as np

    from treeinfer.examples import example_path
    from treeinfer.runs.cache import SimulatorCache
    from treeinfer.tree.description import load_tree

    tree = load_tree(example_path("two_branch"))
    t = np.arange(80) * 0.01
    forces = np.stack([3.0 * np.minimum(t / 0.4, 1.0), 2.0 * np.minimum(t / 0.3, 1.0)])
    cache = SimulatorCache()
    early = cache.get(tree, 0.01, 1, "auto", force_interp="linear")
    sim = cache.get(tree, 0.01, None, "auto", force_interp="linear", forces=forces)
    assert sim.substeps > 1 and sim is not early
    assert early.program_key(True) == sim.program_key(True)
    assert early.derived["force_jacobian_programs"] is sim.derived["force_jacobian_programs"]


def test_the_rollout_program_prefetched_on_a_one_substep_simulator_is_the_evaluators():
    """runs.problem compiles the reference fits' rollout program on a one-substep simulator
    (its step count is an argument) while the run's step is chosen: the run's evaluator must
    find it in the command's cache already compiled (no second build, no second compile) and
    give the residuals a fresh evaluator gives."""
    import numpy as np
    from test_startup import _config, _pulls  # tests/ is on sys.path (pytest prepend)

    from treeinfer.inference.fast_evaluator import (
        BatchEvaluator,
        compile_rollout_program,
        held_evaluator,
    )
    from treeinfer.runs.cache import SimulatorCache
    from treeinfer.runs.problem import build_problem
    from treeinfer.sim.program_cache import ProgramCache
    from treeinfer.tree.generators import chain

    tree = chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0.0, 0.0, 1.5),
                 base_pitch_deg=20.0, levels=1, name="c1")  # fmt: skip
    cache = SimulatorCache()
    problem = build_problem(_config(problem={"substeps": 2}), tree, _pulls((50, 57)), cache)
    sim = problem.sim
    early = cache.get(tree, float(problem.obs.dt), 1, sim.backend, force_interp=sim.force_interp)
    assert early.substeps == 1 and sim.substeps == 2
    assert held_evaluator(problem, cache.programs, 3) is None  # nothing compiled yet
    compile_rollout_program(early, None, 3, problem.obs, None, cache.programs)
    ev = held_evaluator(problem, cache.programs, 3)  # held: the same key
    assert ev is not None
    theta = np.log([[40.0, 0.6], [25.0, 1.5]])
    r, ok, _ = ev.evaluate(theta)
    assert ev._run._cache_size() == 1  # the prefetch's compile, not a second one
    r0, ok0, _ = BatchEvaluator(problem, 3, ProgramCache()).evaluate(theta)
    np.testing.assert_array_equal(r, r0)
    np.testing.assert_array_equal(ok, ok0)
