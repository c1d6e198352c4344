"""Recordings: force-deformation trajectories and their files, where and in which direction each
pull acted, plausibility checks of data against a tree, force profiles, and the importers (CSV,
ROS bags).

May import: treeinfer.tree.description, treeinfer.io, treeinfer.errors.

The public API is re-exported here name by name, imported lazily (on first use), so
importing one module of the package does not import the others (startup cost, and no
import order between them).

Submodules: bag_messages, bags, checks, csv_format, direction, forces, import_bag, import_csv,
kortex, noise_estimate, pull_checks, pulls, side_files, trajectories, true_params, types."""

_EXPORTS = {
    "KNOWN_TYPES": "bag_messages",
    "open_bag_reader": "bag_messages",
    "valid_msgtype": "bag_messages",
    "valid_topic": "bag_messages",
    "BagStreams": "bags",
    "Pull": "bags",
    "find_pulls": "bags",
    "read_bag_streams": "bags",
    "resample": "bags",
    "data_checks": "checks",
    "speed_limit": "checks",
    "parse_units": "csv_format",
    "read_columns": "csv_format",
    "DEFAULT_PEAK_RANGE": "forces",
    "MIN_STEPS": "forces",
    "ProfileSpec": "forces",
    "SET_KINDS": "forces",
    "SHAPES": "forces",
    "SPEC_KEYS": "forces",
    "format_spec": "forces",
    "from_spec": "forces",
    "n_steps": "forces",
    "parse_spec": "forces",
    "piecewise_linear": "forces",
    "profile_set": "forces",
    "ramp": "forces",
    "ramp_hold": "forces",
    "ramp_release": "forces",
    "random_specs": "forces",
    "sample_times": "forces",
    "smooth_step": "forces",
    "FORCE_TYPES": "import_bag",
    "KORTEX_TYPE": "import_bag",
    "POSE_TYPES": "import_bag",
    "rest_level": "import_bag",
    "sign_agreement": "import_bag",
    "DISPLACEMENT_UNITS": "import_csv",
    "FORCE_UNITS": "import_csv",
    "ImportResult": "import_csv",
    "TIME_UNITS": "import_csv",
    "convert_file": "import_csv",
    "bag_topics": "kortex",
    "kortex_typestore": "kortex",
    "missing_force_message": "kortex",
    "read_kortex_streams": "kortex",
    "NoiseEstimate": "noise_estimate",
    "Upsampling": "noise_estimate",
    "detect_upsampling": "noise_estimate",
    "estimate_white_noise": "noise_estimate",
    "quantisation_step": "noise_estimate",
    "check_pull_moves": "pull_checks",
    "check_same_pull": "pull_checks",
    "pull_leverage": "pull_checks",
    "DIRECTION_WORDS": "pulls",
    "PULLS_FILE": "pulls",
    "PullSpec": "pulls",
    "PullsFile": "pulls",
    "ResolvedPull": "pulls",
    "data_grasp_fractions": "pulls",
    "load_data_pulls": "pulls",
    "parse_direction": "pulls",
    "parse_tree_pull": "pulls",
    "pull_direction": "pulls",
    "pull_spec": "pulls",
    "pulls_from_dict": "pulls",
    "read_pulls": "pulls",
    "resolve_pull": "pulls",
    "resolve_pulls": "pulls",
    "spec_to_dict": "pulls",
    "stack_resolved": "pulls",
    "write_pulls": "pulls",
    "band_csv_text": "side_files",
    "write_band_csv": "side_files",
    "write_provenance": "side_files",
    "OPTIONAL_COLUMNS": "trajectories",
    "REQUIRED_COLUMNS": "trajectories",
    "add_noise": "trajectories",
    "ground_truth_velocity": "trajectories",
    "read_trajectory": "trajectories",
    "read_trajectory_dir": "trajectories",
    "stack_trajectories": "trajectories",
    "velocity_from_displacement": "trajectories",
    "write_trajectory": "trajectories",
    "check_positive_params": "true_params",
    "read_true_params": "true_params",
    "true_params_record": "true_params",
    "write_true_params": "true_params",
    "Observations": "types",
    "Trajectory": "types",
    "validate_trajectory": "types",
}
_SUBMODULES = (
    "bag_messages",
    "bags",
    "checks",
    "csv_format",
    "direction",
    "forces",
    "import_bag",
    "import_csv",
    "kortex",
    "noise_estimate",
    "pull_checks",
    "pulls",
    "side_files",
    "trajectories",
    "true_params",
    "types",
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
