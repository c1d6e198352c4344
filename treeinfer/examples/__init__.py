"""Built-in example trees (YAML), shipped with the package."""

from __future__ import annotations

from pathlib import Path

EXAMPLES_DIR = Path(__file__).resolve().parent


def example_path(name: str) -> Path:
    """Path of a built-in example tree: ``two_branch``, ``three_branch`` or ``fractal``."""
    path = EXAMPLES_DIR / f"{name}.yaml"
    if not path.exists():
        from ..errors import ConfigError

        names = sorted(p.stem for p in EXAMPLES_DIR.glob("*.yaml"))
        raise ConfigError(f"unknown example '{name}'; built-in examples: {', '.join(names)}")
    return path
