"""The paper's sim-to-sim studies: ``python experiments/<study>.py --size cpu|full|tiny``.

See ``experiments/README.md``; shared machinery in :mod:`experiments.common`.
"""
