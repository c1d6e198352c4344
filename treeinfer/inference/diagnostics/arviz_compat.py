"""The one place treeinfer talks to ArviZ: the same calls on ArviZ 0.2x and ArviZ 1.x.

ArviZ 1.0 split the package into ``arviz_base`` (data: ``from_dict``, ``convert_to_dataset``),
``arviz_stats`` (``rhat``, ``ess``, ``summary``, PSIS) and ``arviz_plots``, and replaced
``InferenceData`` by ``xarray.DataTree``; its ``from_dict`` takes one dict of groups instead of
one keyword per group (``from_dict(posterior=...)`` fails there with a TypeError). ArviZ 1.x
needs Python >= 3.12, so a Python 3.11 install keeps 0.2x and both series must work. Every
ArviZ call of the package, tests, experiments, benchmarks and notebooks goes through here
(``docs/compatibility.md`` lists what each series was tested with).

What the two series return differs in type, not in use: :func:`from_dict` gives an
``InferenceData`` (0.2x) or a ``DataTree`` (1.x); both have ``.posterior`` / ``.sample_stats``
groups holding xarray data, ``.to_netcdf`` and attribute access by group name. :func:`rhat`,
:func:`ess` and :func:`convert_to_dataset` give an ``xarray.Dataset`` on both.

ArviZ is imported on first use (it takes 1.5-4 s to import on a small CPU; 0.2x also prints a
FutureWarning about the 1.0 refactor, silenced here). On 1.x only ``arviz_base`` and
``arviz_stats`` are imported: ``arviz_plots`` is not needed and slow to import.
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = [
    "add_group",
    "arviz_version",
    "convert_to_dataset",
    "ess",
    "from_dict",
    "group_names",
    "is_arviz1",
    "psis_log_weights",
    "read_netcdf",
    "rhat",
    "summary",
    "summary_table",
    "update_attrs",
    "write_netcdf",
    "SUMMARY_COLUMNS",
]

# The columns both series' ``summary`` give (0.2x adds HDI bounds, 1.x equal-tailed bounds).
SUMMARY_COLUMNS = ("mean", "sd", "mcse_mean", "mcse_sd", "ess_bulk", "ess_tail", "r_hat")


def arviz_version() -> str:
    """The installed ArviZ version (the ``arviz`` distribution, else ``arviz-base``), read from
    the package metadata without importing ArviZ."""
    from importlib import metadata

    for dist in ("arviz", "arviz-base"):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    raise ImportError(
        "treeinfer needs ArviZ (arviz>=0.20 on Python 3.11, 0.2x or 1.x on Python >= 3.12); "
        "install it with: pip install arviz"
    )


def is_arviz1() -> bool:
    """True for ArviZ >= 1 (the ``arviz_base`` / ``arviz_stats`` split)."""
    return int(arviz_version().split(".")[0]) >= 1


def _modules():
    """``(data module, stats module)``: ``(arviz, arviz)`` on 0.2x, ``(arviz_base,
    arviz_stats)`` on 1.x. Not memoised (no module keeps a cache: tests/test_architecture.py);
    Python's module table makes a repeated import a lookup."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # 0.2x: "ArviZ is undergoing a refactor"
        if is_arviz1():
            import arviz_base
            import arviz_stats

            return arviz_base, arviz_stats
        import arviz

        return arviz, arviz


# --------------------------------------------------------------------------- data


def from_dict(
    posterior: dict,
    *,
    sample_stats: dict | None = None,
    observed_data: dict | None = None,
    dims: dict | None = None,
    coords: dict | None = None,
    attrs: dict | None = None,
):
    """ArviZ's ``from_dict`` with groups ``posterior`` (arrays ``[chain, draw, ...]``), optional
    ``sample_stats`` (``[chain, draw, ...]``) and ``observed_data`` (no sample dimensions).

    ``attrs`` (strings/numbers) are set on every group (and on the root of a 1.x DataTree),
    so they survive a netCDF round trip on both series (1.x's ``from_dict(attrs=)`` does not
    put them on the groups). Returns an ``InferenceData`` (0.2x) or ``DataTree`` (1.x)."""
    data_mod, _ = _modules()
    groups = {"posterior": posterior}
    if sample_stats is not None:
        groups["sample_stats"] = sample_stats
    if observed_data is not None:
        groups["observed_data"] = observed_data
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        if is_arviz1():
            out = data_mod.from_dict(groups, dims=dims, coords=coords)
        else:
            out = data_mod.from_dict(**groups, dims=dims, coords=coords)
    if attrs:
        update_attrs(out, attrs)
    return out


def update_attrs(idata, attrs: dict) -> None:
    """Set ``attrs`` (strings/numbers) on every group of ``idata`` (from :func:`from_dict`), and
    on the root of a 1.x DataTree, in place: what :func:`from_dict`'s ``attrs`` does, for
    attributes known only once the data exist. (``idata.groups()`` is a method on 0.2x but a
    tuple property of a 1.x DataTree, so the loop goes through :func:`group_names`.)"""
    for name in group_names(idata):
        idata[name].attrs.update(attrs)
    if is_arviz1():
        idata.attrs.update(attrs)


def add_group(idata, name: str, variables: dict, *, coords=None, dims=None, attrs=None):
    """Add group ``name`` (arrays ``[chain, draw, ...]``, as the posterior's) to ``idata`` from
    :func:`from_dict`, in place; a group outside ArviZ's schema is allowed (0.2x warns about it,
    silenced here). Returns ``idata``."""
    ds = from_dict(variables, coords=coords, dims=dims, attrs=attrs).posterior
    if is_arviz1():
        idata[name] = ds.to_dataset()
        return idata
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        idata.add_groups({name: ds})
    return idata


def group_names(idata) -> list[str]:
    """The groups of an ``InferenceData`` (0.2x) or the child nodes of a ``DataTree`` (1.x)."""
    if is_arviz1():
        return list(idata.children)
    return list(idata.groups())


def convert_to_dataset(obj, group: str = "posterior"):
    """``obj`` as an ``xarray.Dataset``: a NumPy array ``[chain, draw, ...]`` becomes variable
    ``x`` (dims ``chain, draw, x_dim_0, ...``); a dict of such arrays one variable each; an
    ``InferenceData`` / ``DataTree`` gives its ``group``."""
    data_mod, _ = _modules()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        out = data_mod.convert_to_dataset(obj, group=group)
    return _as_dataset(out)


def _as_dataset(obj):
    """A 1.x DataTree node (what its stats functions return for a DataTree input) as a Dataset;
    anything else unchanged."""
    to_dataset = getattr(obj, "to_dataset", None)
    if to_dataset is not None and type(obj).__name__ == "DataTree":
        return to_dataset()
    return obj


def write_netcdf(idata, path) -> None:
    """Write ``idata`` (from :func:`from_dict`) to netCDF with the ``netCDF4`` engine (the same
    call on an ``InferenceData`` and a ``DataTree``)."""
    idata.to_netcdf(str(path), engine="netcdf4")


def read_netcdf(path):
    """Read a file written by :func:`write_netcdf` (by either ArviZ series) fully into memory and
    close it: an ``InferenceData`` on 0.2x, a ``DataTree`` on 1.x."""
    data_mod, _ = _modules()
    if is_arviz1():
        import xarray as xr

        # 1.x's from_netcdf is xarray's lazy open_datatree, which keeps the file open.
        with xr.open_datatree(str(path), engine="netcdf4") as tree:
            return tree.load()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        return data_mod.from_netcdf(str(path), engine="netcdf4")


# --------------------------------------------------------------------------- statistics


def _sample_data(data):
    """What the stats functions take: NumPy arrays ``[chain, draw, ...]`` converted to a
    Dataset (variable ``x``); xarray / ArviZ objects as they are."""
    if isinstance(data, (np.ndarray, list, tuple)):
        return convert_to_dataset(np.asarray(data, dtype=float))
    return data


def rhat(data, var_names=None):
    """Rank-normalised split R-hat (Vehtari et al. 2021) per variable element, an
    ``xarray.Dataset``. ``data``: ``InferenceData`` / ``DataTree`` (its posterior), a Dataset
    with ``chain, draw`` dims, or an array ``[chain, draw, ...]`` (variable ``x``)."""
    _, stats = _modules()
    return _as_dataset(stats.rhat(_sample_data(data), var_names=var_names))


def ess(data, method: str = "bulk", var_names=None):
    """Effective sample size (``method`` ``"bulk"`` or ``"tail"``, Vehtari et al. 2021) per
    variable element, an ``xarray.Dataset``; ``data`` as for :func:`rhat`."""
    _, stats = _modules()
    return _as_dataset(stats.ess(_sample_data(data), var_names=var_names, method=method))


def summary(data, var_names=None):
    """ArviZ's summary table (a ``pandas.DataFrame``, one row per variable element such as
    ``theta[Kp]``) with the columns both series give, unrounded: :data:`SUMMARY_COLUMNS`."""
    _, stats = _modules()
    table = stats.summary(_sample_data(data), var_names=var_names, round_to="none")
    return table[list(SUMMARY_COLUMNS)].astype(float)


def summary_table(data, *, kind: str = "all", hdi_prob: float = 0.94):
    """ArviZ's summary for display (``kind`` ``"all"`` or ``"stats"``) with the highest-density
    interval of probability ``hdi_prob``, its bounds named as on 0.2x on both series
    (``hdi_5%`` / ``hdi_95%`` for 0.9; 1.x calls them ``hdi90_lb`` / ``hdi90_ub``); 1.x also
    orders its columns differently. Values unrounded on 1.x, ArviZ's rounding on 0.2x."""
    _, stats = _modules()
    with warnings.catch_warnings():  # one chain of particles: the shape warning is moot
        warnings.simplefilter("ignore", UserWarning)
        if not is_arviz1():
            return stats.summary(data, kind=kind, hdi_prob=hdi_prob)
        table = stats.summary(data, kind=kind, ci_prob=hdi_prob, ci_kind="hdi", round_to="none")
    tag = f"hdi{round(100 * hdi_prob):g}"
    lo, hi = (100 * (1 - hdi_prob) / 2), (100 * (1 + hdi_prob) / 2)
    return table.rename(columns={f"{tag}_lb": f"hdi_{lo:g}%", f"{tag}_ub": f"hdi_{hi:g}%"})


def psis_log_weights(log_weights) -> tuple[np.ndarray, float]:
    """Pareto-smoothed importance sampling (Vehtari et al. 2024) by ArviZ: ``(smoothed log
    weights [M] normalised to sum 1 in exp, k_hat)`` for raw finite ``log_weights [M]``
    (``r_eff = 1``).

    The largest weights are replaced by the expected order statistics of a generalised Pareto
    tail fitted to them. The two series agree except for the tail length when
    ``3 sqrt(M)`` (``M > 225``) or ``M / 5`` is not a whole number: 0.2x rounds it up, 1.x down
    (e.g. 165 against 164 weights for M = 3000), which moves k_hat by about 0.01.
    k_hat is ``inf`` when no tail can be fitted (fewer than 5 tail weights, or the tail's first
    quartile equals its minimum; 1.x reports NaN or raises there): read it as "unreliable"."""
    x = np.array(log_weights, dtype=float)
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ValueError(
            f"psis_log_weights: expected a 1-d array of finite log weights, got shape {x.shape}"
        )
    _, stats = _modules()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if not is_arviz1():
            lw, k = stats.psislw(x, reff=1.0)
            return np.asarray(lw, dtype=float), float(k)
        from arviz_stats.base import array_stats

        n = x.size
        tail = np.floor(3 * n**0.5) if n > 225 else np.floor(n / 5)
        if tail < 5:
            return x - np.logaddexp.reduce(x), float("inf")
        # 1.x's psislw takes log-likelihood values (PSIS-LOO's ratios are their negatives)
        lw, k = array_stats.psislw(-x, r_eff=1.0)
    k = float(k)
    return np.asarray(lw, dtype=float), (k if np.isfinite(k) else float("inf"))
