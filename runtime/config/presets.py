"""Presets: the names users know for a planner and a partition chosen together.

`planner.mode` (config) and `--planner` (command line) take a preset; `planner.algorithm` and
`partition` set the two choices one by one (runtime.modes.registry, runtime.perception.partition).
"""
from __future__ import annotations

#: preset -> (planner.algorithm, partition)
PRESETS: dict[str, tuple[str, str]] = {
    # The product: the MPC on the VLM partition's P_fix (the DCT paper's Algorithm 1).
    "dct": ("mpc", "vpp"),
    # The same MPC with every lidar point fixed: the NeuPAN-like baseline.
    "all-fixed": ("mpc", "all-fixed"),
    # Occupancy grid + A* + pure pursuit on every point: the Ellis22-like baseline.
    "grid-astar": ("grid-astar", "all-fixed"),
    # Straight at the goal, blind to obstacles: tests and benches only.
    "pure-pursuit": ("pure-pursuit", "all-fixed"),
}
#: When the config names neither a preset nor a planner nor a partition.
DEFAULT_PRESET = "dct"


def blind(preset: str) -> bool:
    """Whether the preset's planner reads no sensors (it drives through whatever is there)."""
    from runtime.modes.registry import planner_spec

    return not planner_spec(PRESETS[preset][0]).uses_lidar


def preset_of(algorithm: str, partition: str) -> str | None:
    """The preset naming this pair, None when none does."""
    for name, pair in PRESETS.items():
        if pair == (algorithm, partition):
            return name
    return None


def label(algorithm: str, partition: str) -> str:
    """The preset's name, or `algorithm+partition` for a pair no preset names (reports, logs)."""
    return preset_of(algorithm, partition) or f"{algorithm}+{partition}"


def resolve(mode: str | None, algorithm: str | None, partition: str | None) -> tuple[str, str]:
    """(algorithm, partition) from what the config set: a preset fills what is unset (no preset:
    the default's planner, and the partition that goes with the planner); a preset and a setting
    that disagree are an error naming both fields (ValueError)."""
    if mode is None:
        # Unset: the default preset's planner, and the partition of the first preset with that
        # planner (grid-astar alone is the grid-astar preset, mpc alone is dct).
        algorithm = algorithm or PRESETS[DEFAULT_PRESET][0]
        if partition is None:
            partition = next((pair[1] for pair in PRESETS.values() if pair[0] == algorithm),
                             PRESETS[DEFAULT_PRESET][1])
        return algorithm, partition
    if mode not in PRESETS:
        raise ValueError(f"planner.mode: unknown preset {mode!r}; known: {', '.join(PRESETS)}")
    preset_algorithm, preset_partition = PRESETS[mode]
    if algorithm is not None and algorithm != preset_algorithm:
        raise ValueError(f"planner.mode {mode} means planner.algorithm {preset_algorithm}, but planner.algorithm is "
                         f"{algorithm}: set one of them")
    if partition is not None and partition != preset_partition:
        raise ValueError(f"planner.mode {mode} means partition {preset_partition}, but partition is {partition}: "
                         "set one of them")
    return preset_algorithm, preset_partition
