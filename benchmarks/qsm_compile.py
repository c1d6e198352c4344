"""Program size and compile cost of the fused simulator for a QSM-converted chain against
hand-written trees (docs/qsm.md, "Simulation and inference cost").

    JAX_PLATFORMS=cpu python -m benchmarks.qsm_compile [--compile] [--qsm FILE]

For each tree: bodies and joints of the MuJoCo model, the StableHLO lines of the forward
``simulate`` program (4 parameter sets x 2 pulls x 50 samples, the stability step) and, with
``--compile``, the process CPU seconds of XLA's compile and the seconds of one call. Trees:
``three_branch``; an 8-joint chain bending in one plane and the same chain turning 37 degrees
about each parent (3-D); the chain from the sapling's grasp point to its base with joints
every 0.5 m (8 joints) and every 1.0 m (4 joints). The QSM is ``--qsm`` or the shared TreeQSM
file (``shared/data/qsm/treeqsm_QSM.mat`` beside the repository or a folder above it).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

GRASP = (1.693, -16.09, 256.03)  # the shared sapling's grasp point (tests/test_qsm_shared.py)


def chain(n: int, azimuth_deg: float):
    from treeinfer.tree import make_tree
    from treeinfer.tree.types import Branch

    br = [Branch("l0", None, 0.5, 0.03)] + [
        Branch(f"l{i}", f"l{i - 1}", 0.4, 0.02, angle_deg=-10.0, azimuth_deg=azimuth_deg * i)
        for i in range(1, n)
    ]
    names = [f"l{i}" for i in range(n - 1, -1, -1)]
    return make_tree(br, grasp_branch=names[0], inferred=names, base_pitch_deg=20.0)


def trees(qsm: Path):
    from treeinfer.examples import example_path
    from treeinfer.tree import load_tree, tree_from_qsm

    yield "three_branch", load_tree(example_path("three_branch"))
    yield "chain, 8 joints, planar", chain(8, 0.0)
    yield "chain, 8 joints, 3-D", chain(8, 37.0)
    for spacing in (0.5, 1.0):
        res = tree_from_qsm(qsm, grasp_point=GRASP, joint_spacing=spacing)
        yield f"QSM chain, joints every {spacing} m", res.tree


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--compile", action="store_true", help="also compile and run each program")
    root = Path(__file__).resolve().parents[1]
    found = [p / "shared/data/qsm/treeqsm_QSM.mat" for p in (root, *root.parents)]
    default = next((f for f in found if f.is_file()), None)
    ap.add_argument("--qsm", type=Path, default=default, required=default is None)
    args = ap.parse_args()

    import jax
    import jax.numpy as jnp
    import numpy as np

    from treeinfer.sim import make_simulator, simulate

    for label, tree in trees(args.qsm):
        sim = make_simulator(tree, accuracy="coarse")
        r = len(sim.joint_names)
        lo, hi = tree.bounds_array()
        kp = jnp.asarray(np.sqrt(lo[:r] * hi[:r]))[None].repeat(4, 0)
        kd = jnp.asarray(np.sqrt(lo[r:] * hi[r:]))[None].repeat(4, 0)
        forces = jnp.asarray(np.linspace(0.0, 5.0, 50))[None].repeat(2, 0)
        lowered = jax.jit(lambda a, b, f=forces, s=sim: simulate(s, a, b, f).tau).lower(kp, kd)
        m = sim.mj_model
        line = (
            f"{label}: {m.nbody - 1} bodies, {m.njnt} joints, {r} inferred, "
            f"{sim.substeps} substeps; {lowered.as_text().count(chr(10))} StableHLO lines"
        )
        if args.compile:
            cpu = time.process_time()
            compiled = lowered.compile()
            cpu = time.process_time() - cpu
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(kp, kd))
            line += f"; compile {cpu:.1f} CPU-s, run {time.perf_counter() - t0:.2f} s"
        print(line, flush=True)


if __name__ == "__main__":
    main()
