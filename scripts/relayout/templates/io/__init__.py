"""Files in and out, for every layer: atomic writes that never destroy data, one bounded loader for
YAML and JSON, strict JSON, and provenance (file hashes, library versions, config hashes).

May import: treeinfer.errors only (the lowest layer; everything else may import it).

The public API is re-exported here name by name, imported lazily (on first use), so
importing one module of the package does not import the others (startup cost, and no
import order between them).

Submodules: atomic, jsonio, provenance, safe_load, safe_parse."""

_EXPORTS = {
    "OutputWriteError": "atomic",
    "atomic_save": "atomic",
    "atomic_write_bytes": "atomic",
    "atomic_write_json": "atomic",
    "atomic_write_text": "atomic",
    "check_output_dir": "atomic",
    "clean_stale_staging": "atomic",
    "find_staging": "atomic",
    "is_treeinfer_output": "atomic",
    "mark_output_dir": "atomic",
    "output_error": "atomic",
    "publish_staged": "atomic",
    "staged_output_dir": "atomic",
    "jsonable": "jsonio",
    "read_json": "jsonio",
    "write_json": "jsonio",
    "config_hash": "provenance",
    "data_manifest": "provenance",
    "file_sha256": "provenance",
    "tree_to_dict_json": "provenance",
    "versions": "provenance",
    "MAX_ALIASES": "safe_load",
    "MAX_BYTES": "safe_load",
    "MAX_DEPTH": "safe_load",
    "MAX_NODES": "safe_load",
    "boolean": "safe_load",
    "list_data_files": "safe_load",
    "load_file": "safe_load",
    "number": "safe_load",
    "read_regular_file": "safe_load",
    "require_regular_file": "safe_load",
    "string": "safe_load",
    "loads_json": "safe_parse",
    "loads_yaml": "safe_parse",
}
_SUBMODULES = ("atomic", "jsonio", "provenance", "safe_load", "safe_parse")

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    import importlib

    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS) | set(_SUBMODULES))
