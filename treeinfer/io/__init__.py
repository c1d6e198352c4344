"""Files in and out, for every layer: atomic writes that never destroy data, one bounded loader for
YAML and JSON, strict JSON, and provenance (file hashes, library versions, config hashes).

May import: treeinfer.errors only (the lowest layer; everything else may import it).

The public API is re-exported here name by name, imported lazily (on first use), so
importing one module of the package does not import the others (startup cost, and no
import order between them).

Submodules: atomic, atomic_write, interrupt, jsonio, limits, manifest, ownership, provenance,
safe_load, safe_parse."""

_EXPORTS = {
    "check_output_dir": "atomic",
    "clean_stale_staging": "atomic",
    "find_staging": "atomic",
    "is_treeinfer_output": "atomic",
    "mark_output_dir": "atomic",
    "publish_staged": "atomic",
    "staged_output_dir": "atomic",
    "OutputWriteError": "atomic_write",
    "atomic_save": "atomic_write",
    "atomic_write_bytes": "atomic_write",
    "atomic_write_json": "atomic_write",
    "atomic_write_text": "atomic_write",
    "output_error": "atomic_write",
    "CtrlC": "interrupt",
    "GRACE_S": "interrupt",
    "exit_if_interrupted": "interrupt",
    "install": "interrupt",
    "register": "interrupt",
    "unregister": "interrupt",
    "jsonable": "jsonio",
    "read_json": "jsonio",
    "write_json": "jsonio",
    "ENV": "limits",
    "MAX_BRANCHES": "limits",
    "MAX_TREE_DEPTH": "limits",
    "MAX_WORK": "limits",
    "allow_large": "limits",
    "check_tree_size": "limits",
    "check_work": "limits",
    "deep_recursion": "limits",
    "tree_depth": "limits",
    "ALGORITHM": "manifest",
    "MANIFEST": "manifest",
    "file_digest": "manifest",
    "read_manifest": "manifest",
    "verify_manifest": "manifest",
    "write_manifest": "manifest",
    "OLD_INFIX": "ownership",
    "claim_output_file": "ownership",
    "move_aside": "ownership",
    "old_name": "ownership",
    "refuse_overlap": "ownership",
    "refuse_unmovable": "ownership",
    "report": "ownership",
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
    "refuse_special_paths": "safe_load",
    "require_regular_file": "safe_load",
    "string": "safe_load",
    "loads_json": "safe_parse",
    "loads_yaml": "safe_parse",
}
_SUBMODULES = (
    "atomic",
    "atomic_write",
    "interrupt",
    "jsonio",
    "limits",
    "manifest",
    "ownership",
    "provenance",
    "safe_load",
    "safe_parse",
)

__all__ = sorted(_EXPORTS)


from .lazy import lazy_package  # noqa: E402 -- after the tables it reads

__getattr__, __dir__ = lazy_package(__name__, _EXPORTS, _SUBMODULES)
