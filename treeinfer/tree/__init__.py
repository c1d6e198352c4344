"""Trees: the tree description (branches, grasp point, inferred joints, prior boxes), its types and
checks, generators (chains, fractals, L-systems, the stem), trees from QSMs (point-cloud
reconstructions), export to MJCF/URDF and users' own URDF/MJCF models.

May import: treeinfer.io and treeinfer.errors.

The public API is re-exported here name by name, imported lazily (on first use), so
importing one module of the package does not import the others (startup cost, and no
import order between them).

Submodules: checks, description, export, generators, geometry, lsystem, model_paths,
model_section, options, plausibility, qsm (QSM cylinder tables), qsm_convert (QSM -> tree),
qsm_geometry, qsm_plot, qsm_wood, stem, types, urdf, usermodel."""

_EXPORTS = {
    "check_tie": "checks",
    "default_inferred": "description",
    "dump_tree": "description",
    "load_tree": "description",
    "make_tree": "description",
    "read_tree_file": "description",
    "tree_from_dict": "description",
    "to_mjcf": "export",
    "to_mjmodel": "export",
    "write_mjcf": "export",
    "chain": "generators",
    "describe": "generators",
    "dump_generated": "generators",
    "explicit": "generators",
    "fractal": "generators",
    "fractal_name": "generators",
    "generate": "generators",
    "stem_push_points": "generators",
    "link_axis": "geometry",
    "TurtleSegment": "lsystem",
    "interpret": "lsystem",
    "pipe_radii": "lsystem",
    "rewrite": "lsystem",
    "MAX_INCLUDE_DEPTH": "model_paths",
    "check_model_paths": "model_paths",
    "file_sha256": "model_section",
    "parse_model_section": "model_section",
    "parse_direction": "options",
    "parse_parameters": "options",
    "parse_tie": "options",
    "parse_tie_shape": "options",
    "parse_tree_pull": "options",
    "resolve_tie_shape": "options",
    "Finding": "plausibility",
    "compliance_range": "plausibility",
    "errors_of": "plausibility",
    "format_findings": "plausibility",
    "grasp_reach": "plausibility",
    "lever_arm_compliance": "plausibility",
    "response_range": "plausibility",
    "simulation_cost_check": "plausibility",
    "static_compliance": "plausibility",
    "Stem": "stem",
    "StemProfile": "stem",
    "StemPush": "stem",
    "branch_at_height": "stem",
    "cantilever_displacement": "stem",
    "compliance": "stem",
    "fit_cantilever": "stem",
    "matched_hinges": "stem",
    "push_recording": "stem",
    "stem_tree": "stem",
    "write_stem_logs": "stem",
    "Bounds": "types",
    "Branch": "types",
    "Tree": "types",
    "base_rotation": "types",
    "branch_density": "types",
    "cylinder_inertia": "types",
    "local_offset": "types",
    "local_rotation": "types",
    "quat_from_matrix": "types",
    "rot_x": "types",
    "rot_y": "types",
    "rot_z": "types",
    "tree_scale_warnings": "types",
    "tree_to_dict": "types",
    "world_frames": "types",
    "Cylinders": "qsm",
    "read_qsm": "qsm",
    "QsmTree": "qsm_convert",
    "tree_from_qsm": "qsm_convert",
    "plot_qsm": "qsm_plot",
    "Wood": "qsm_wood",
    "load_model_file": "urdf",
    "mjmodel_from_urdf": "urdf",
    "rpy_from_matrix": "urdf",
    "to_urdf": "urdf",
    "write_urdf": "urdf",
    "PreparedModel": "usermodel",
    "attach_model": "usermodel",
    "describe_report": "usermodel",
    "prepare_user_model": "usermodel",
    "tree_from_model": "usermodel",
}
_SUBMODULES = (
    "_generate",
    "checks",
    "description",
    "export",
    "generators",
    "geometry",
    "lsystem",
    "model_paths",
    "model_section",
    "options",
    "plausibility",
    "qsm",
    "qsm_convert",
    "qsm_geometry",
    "qsm_plot",
    "qsm_wood",
    "stem",
    "types",
    "urdf",
    "usermodel",
)

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
