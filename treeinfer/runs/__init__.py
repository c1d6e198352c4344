"""Run folders (the ``runs`` package): what ``treeinfer infer`` writes, how it checkpoints and
resumes, and how ``predict`` / ``evaluate`` read it back.

A finished run is one folder ``RUN/``::

    config.json      every option, the seed, treeinfer/jax/mujoco versions, the data files with
                     their sha256, the problem and sampler settings (enough to reproduce the run)
    tree.yaml        the tree that was inferred (a copy, so the run stands on its own)
    posterior.nc     ArviZ InferenceData: group ``posterior`` in natural units (``Kp``, ``Kd`` over
                     ``joint``; ``units`` and the prior box as attributes; likelihood and noise
                     model as group attributes), ``log_posterior`` (``theta``, log units, the
                     labels as ``param``); MCMC: every chain after its warm-up, thinned;
                     SVGD/NNSVGD/importance: the usable particles as one chain of draws (old
                     folders: ``posterior`` holds ``theta`` in log units)
    particles.csv    one row per final particle: Kp/Kd in natural units, log_density, stable
    trace.npz        positions [n, P, D], log_density [n, P], iterations [n], final theta [P, D],
                     per-iteration sampler diagnostics (``diag_<name>``, at ``diag_iterations``)
    summary.json     diagnostics, convergence warnings, unstable particles, posterior table,
                     fit to the training data (95% band width, share of points outside)
    plots/           trace.png (log density and parameters), pairs.png (natural units on log axes,
                     prior box, truth if known), bands_train.png

Atomicity: the folder is built in a hidden staging sibling and renamed into place at the very
end (:func:`treeinfer.io.atomic.staged_output_dir`), so ``RUN/`` appears complete or not at all.

Checkpoints live *beside* the run, in ``RUN.partial/`` (never inside ``RUN/``)::

    RUN.partial/config.json      the run's config (written before sampling starts)
    RUN.partial/tree.yaml        the tree copy
    RUN.partial/checkpoint.npz   sampler state after the last completed checkpoint

``checkpoint.npz`` holds the sampler state pytree flattened with ``jax.tree_util``
(``leaf_<i>``; PRNG key leaves as ``jax.random.key_data``), the completed iteration count and
the config hash (in the JSON string ``meta``), and a coarse trace (state positions and
log-densities at every checkpoint so far). It is replaced atomically every ``checkpoint_every``
iterations and once more when sampling ends. ``RUN.partial/`` is removed once ``RUN/`` is in
place. ``treeinfer infer --resume RUN`` reads ``RUN.partial/``, refuses if a data file changed
(sha256) or the settings the code derives from the config changed, and continues with
``infer(..., initial_state=state, start_iteration=k)``: the final particles equal those of an
uninterrupted run bit for bit (the driver keys iteration ``i`` by ``fold_in(key, i)``).

A resumed run's trace has the coarse checkpoint entries up to the resume point and every
iteration after it (``trace.npz['iterations']`` says which); its per-iteration sampler
diagnostics cover the resumed part only.

Modules: :mod:`.config` (the run configuration, validated once, hashed for resume),
:mod:`.provenance` (hashes, versions, JSON), :mod:`.checkpoint` (``RUN.partial``),
:mod:`.folder` (save and load ``RUN/``), :mod:`.cache` (the cache a command owns: simulators and
compiled sampler programs),
:mod:`.problem` (the inference problem of a config, checks before sampling), :mod:`.posterior`
(the reported posterior, merged traces), :mod:`.service` (run, resume, k-fold: the only module
that orchestrates the others).
"""

from ..io.jsonio import read_json, write_json
from ..io.provenance import config_hash, data_manifest, file_sha256, versions
from ..sim.program_cache import ProgramCache
from .cache import SimulatorCache, simulator_for
from .checkpoint import (
    CHECKPOINT_FILE,
    CHECKPOINT_FORMAT,
    PARTIAL_SUFFIX,
    Checkpoint,
    Checkpointer,
    flatten_state,
    load_checkpoint,
    partial_dir,
    read_checkpoint_info,
    save_checkpoint,
    state_template,
    unflatten_state,
)
from .config import (
    RUN_FORMAT,
    RunConfig,
    RunInputs,
    check_data_unchanged,
    infer_config,
    load_run_inputs,
    read_true_params,
    sampler_settings,
)
from .folder import (
    LoadedRun,
    load_run,
    particles_csv,
    posterior_table,
    save_run,
    simulation_line,
    simulation_summary,
)
from .folds import FoldResult, kfold
from .service import (
    InferOutcome,
    build_problem,
    infer_posterior,
    run_inference,
)

__all__ = [
    "CHECKPOINT_FILE",
    "CHECKPOINT_FORMAT",
    "PARTIAL_SUFFIX",
    "RUN_FORMAT",
    "Checkpoint",
    "Checkpointer",
    "FoldResult",
    "InferOutcome",
    "LoadedRun",
    "RunConfig",
    "ProgramCache",
    "SimulatorCache",
    "build_problem",
    "check_data_unchanged",
    "config_hash",
    "data_manifest",
    "file_sha256",
    "flatten_state",
    "infer_config",
    "load_run_inputs",
    "RunInputs",
    "infer_posterior",
    "kfold",
    "load_checkpoint",
    "load_run",
    "partial_dir",
    "particles_csv",
    "posterior_table",
    "read_checkpoint_info",
    "read_json",
    "read_true_params",
    "run_inference",
    "sampler_settings",
    "save_checkpoint",
    "save_run",
    "simulation_line",
    "simulation_summary",
    "simulator_for",
    "state_template",
    "unflatten_state",
    "versions",
    "write_json",
]
