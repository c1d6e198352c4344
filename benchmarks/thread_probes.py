"""Two probes behind session 14's thread changes (BENCHMARKS.md, "Session 14"), on the standard
tree's rollout program (three_branch, 3 pulls of 3 s at 10 ms, 14 substeps):

* ``chunks``: 8 chunks of 104 rollouts one after another, dispatched asynchronously, and on a
  pool of 2 threads (``treeinfer.sim.threads``: JAX releases Python's lock while a program
  runs): wall and CPU seconds of each;
* ``eigh``: NumPy's ``eigh`` of 3 [300, 300] covariances (the force-noise basis) idle and while
  a second thread keeps a rollout program busy, with the OpenBLAS thread count of the
  environment (run it with ``OPENBLAS_NUM_THREADS=1`` and ``=2`` to compare).

    JAX_PLATFORMS=cpu OPENBLAS_NUM_THREADS=2 python -m benchmarks.thread_probes
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np


def main() -> None:
    import jax
    import jax.numpy as jnp

    from treeinfer.examples import example_path
    from treeinfer.model.gains import gains_from_theta
    from treeinfer.sim import make_simulator, simulate
    from treeinfer.tree.description import load_tree

    sim = make_simulator(load_tree(example_path("three_branch")), obs_dt=0.01, substeps=14)
    rng = np.random.default_rng(0)
    t = np.arange(300) * 0.01
    forces = rng.uniform(5, 15, 3)[:, None] * np.clip(t / 1.2, 0, 1)[None]
    forces = jnp.asarray(forces, jnp.float32)
    lo, hi = (np.log(np.asarray(b, float)) for b in sim.prior_box)
    run = jax.jit(lambda th: simulate(sim, *gains_from_theta(th, sim.n_joints), forces).tau)
    chunks = [jnp.asarray(rng.uniform(lo, hi, (104, lo.size)), jnp.float32) for _ in range(8)]
    jax.block_until_ready(run(chunks[0]))

    def timed(label, fn):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        load = os.getloadavg()[0]
        print(f"{label:34s} wall {wall:6.2f} s, CPU {cpu:6.2f} s (load {load:.1f})", flush=True)

    timed("chunks one after another", lambda: [np.asarray(run(x)) for x in chunks])
    timed("chunks dispatched asynchronously", lambda: [np.asarray(o) for o in map(run, chunks)])
    with ThreadPoolExecutor(2) as pool:
        timed("chunks on 2 threads", lambda: list(pool.map(lambda x: np.asarray(run(x)), chunks)))

    a = rng.normal(size=(3, 300, 300))
    cov = a @ a.transpose(0, 2, 1)

    def eighs(label):
        walls = []
        for _ in range(5):
            w0 = time.perf_counter()
            np.linalg.eigh(cov)
            walls.append(time.perf_counter() - w0)
        print(f"eigh {label}: " + " ".join(f"{w:.3f}" for w in walls) + " s", flush=True)

    threads = os.environ.get("OPENBLAS_NUM_THREADS", "(default)")
    print(f"OPENBLAS_NUM_THREADS={threads}")
    eighs("idle")
    stop = threading.Event()

    def busy():
        while not stop.is_set():
            np.asarray(run(chunks[0]))

    worker = threading.Thread(target=busy)
    worker.start()
    time.sleep(0.5)
    c0 = time.process_time()
    eighs("beside a busy rollout thread")
    print(f"process CPU meanwhile {time.process_time() - c0:.2f} s")
    stop.set()
    worker.join()


if __name__ == "__main__":
    main()
