"""Is this Python and this set of installed packages one treeinfer supports?

:func:`check_environment` compares the installed versions with treeinfer's own requirements (the
``Requires-Dist`` lines of its installed metadata, i.e. ``pyproject.toml``'s dependencies and
``requires-python``), without importing any of them. The command line calls it before a command
runs, so an old JAX or a missing netCDF4 is one line naming the package, the version found and
the version needed (exit 2), not an internal error deep in a run.
"""

from __future__ import annotations

import sys

from ..errors import TreeinferError

__all__ = ["UnsupportedEnvironment", "check_environment", "environment_problems"]


class UnsupportedEnvironment(TreeinferError):
    """This Python or an installed dependency is outside what treeinfer supports."""


def environment_problems(distribution: str = "treeinfer") -> list[str]:
    """One line per unmet requirement of ``distribution``'s installed metadata (Python version,
    missing package, version out of range); empty when all are met, or when the metadata cannot
    be read (a source checkout that was never installed: nothing to compare against)."""
    from importlib import metadata

    try:
        from packaging.markers import default_environment
        from packaging.requirements import InvalidRequirement, Requirement
        from packaging.specifiers import SpecifierSet
        from packaging.version import InvalidVersion, Version
    except ImportError:  # packaging comes with pip, matplotlib and xarray; without it, no check
        return []
    try:
        meta = metadata.metadata(distribution)
        requires = metadata.requires(distribution) or []
    except metadata.PackageNotFoundError:
        return []
    problems = []
    python = ".".join(map(str, sys.version_info[:3]))
    needs_python = meta.get("Requires-Python")
    if needs_python and not SpecifierSet(needs_python).contains(python, prereleases=True):
        problems.append(
            f"Python {python} ({sys.executable}): {distribution} needs Python {needs_python}"
        )
    env = default_environment()
    for line in requires:
        try:
            req = Requirement(line)
        except InvalidRequirement:
            continue
        if req.marker is not None and not req.marker.evaluate({**env, "extra": ""}):
            continue  # an optional extra (dev) or another platform's requirement
        want = str(req.specifier) or "any version"
        try:
            found = metadata.version(req.name)
        except metadata.PackageNotFoundError:
            problems.append(
                f"{req.name} is not installed; {distribution} needs {req.name} {want} "
                f"(pip install '{req.name}{req.specifier}')"
            )
            continue
        try:
            ok = req.specifier.contains(Version(found), prereleases=True)
        except InvalidVersion:
            continue  # a local build with a non-standard version: trust it
        if not ok:
            problems.append(
                f"{req.name} {found} is installed; {distribution} needs {req.name} {want} "
                f"(pip install '{req.name}{req.specifier}')"
            )
    return problems


def check_environment(distribution: str = "treeinfer") -> None:
    """Raise :class:`UnsupportedEnvironment` listing every unmet requirement
    (:func:`environment_problems`); return None when all are met."""
    problems = environment_problems(distribution)
    if problems:
        raise UnsupportedEnvironment("unsupported environment:\n  " + "\n  ".join(problems))
