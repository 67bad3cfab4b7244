"""KISS-ICP registration of the real HDL-32 pair (tests/data/real/hdl32_pair_small_gicp)."""
from pathlib import Path

import numpy as np
import pytest

from runtime.odometry.pair import OUTDOOR_PAIR_CONFIG, register_pair, transform_difference
from runtime.odometry.sequence import load_scan, read_transform

REAL = Path(__file__).resolve().parents[2] / "data" / "real" / "hdl32_pair_small_gicp"


@pytest.fixture(scope="module")
def pair():
    return load_scan(REAL / "source.ply").points, load_scan(REAL / "target.ply").points


def test_the_real_pair_registers_within_5_cm_and_half_a_degree_of_the_reference(pair):
    source, target = pair
    reference = read_transform(REAL / "T_target_source.txt")  # p_target = T p_source (README)
    T = register_pair(source, target, OUTDOOR_PAIR_CONFIG)
    dt, dr = transform_difference(T, reference)
    # Measured here: 0.76 cm, 0.20 deg (the two published references differ by 1.9 cm, 0.23 deg).
    assert dt < 0.05 and dr < 0.5
    # The transform is the direction the README says: the inverse is a metre off.
    assert transform_difference(np.linalg.inv(T), reference)[0] > 0.9


def test_an_initial_guess_from_a_text_file_is_used(pair):
    source, target = pair
    reference = read_transform(REAL / "T_target_source.txt")  # 6 digits: orthonormal to 1e-8 only
    T = register_pair(source, target, OUTDOOR_PAIR_CONFIG, initial_guess=reference)
    dt, dr = transform_difference(T, reference)
    assert dt < 0.05 and dr < 0.5
    far = np.eye(4)
    far[0, 3] = 5.0  # 4.5 m from the answer: out of reach of the 1.5 m correspondences, so it must show
    assert transform_difference(register_pair(source, target, OUTDOOR_PAIR_CONFIG, initial_guess=far), reference)[0] > 1.0


def test_register_pair_checks_its_inputs(pair):
    source, target = pair
    with pytest.raises(ValueError, match=r"source: expected \(N,3\) points"):
        register_pair(source[:, :2], target)
    bad = source.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="source: points must be finite"):
        register_pair(bad, target)
    with pytest.raises(ValueError, match="initial guess: pose 0: rotation is not orthonormal"):
        register_pair(source, target, initial_guess=np.diag([1.1, 1.0, 1.0, 1.0]))
