"""The contact-tolerance backend chosen in the controller config (`vpp.backend`): the
config's errors name the field, the factory builds each kind, the sim-oracle is refused outside
the simulator, and a backend that is down degrades to no new masks (every point P_fix), never a
stall."""
from __future__ import annotations

import socket

import pytest
import yaml

from calibration.robot_description import load_robot_description
from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario
from models.vlm.factory import (
    GroundingRegionsConfig,
    OpenAICompatibleBackendConfig,
    ProposingBackend,
    SimOracleBackendConfig,
    SimulatorOnlyBackendError,
    build_backend,
)
from models.vlm.grounding_http import GroundingHttpProposer
from models.vlm.openai_compatible import OpenAICompatibleBackend
from models.vlm.regions import OpenCvProposer
from runtime.config import ConfigFileError, load_controller_config
from runtime.controller.navigation import NavigationController
from runtime.common.geometry import Pose2D
from runtime.perception.partition import AllFixedPartition, VppPartition

DEFAULT_YAML = "runtime/config/default.yaml"


def _config_file(tmp_path, backend: dict):
    data = yaml.safe_load(open(DEFAULT_YAML))
    data["vpp"] = {"backend": backend}
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def dead_url() -> str:
    """An http URL on a local port nothing listens on (bound, then closed)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return f"http://127.0.0.1:{port}/v1"


@pytest.mark.parametrize("backend, words", [
    ({"kind": "gpt"}, ["vpp.backend: kind must be one of: sim-oracle, openai-compatible"]),
    # no kind: the shipped default's (sim-oracle), whose fields these are not
    ({"base_url": "http://127.0.0.1:1/v1", "model": "m"}, ["vpp.backend.sim-oracle.base_url"]),
    ({"kind": "openai-compatible", "base_url": "http://127.0.0.1:1/v1"}, ["vpp.backend.openai-compatible.model"]),
    ({"kind": "openai-compatible", "base_url": "ftp://x", "model": "m"}, ["vpp.backend.openai-compatible.base_url"]),
    ({"kind": "sim-oracle", "recall": 1.5}, ["vpp.backend.sim-oracle.recall"]),
    ({"kind": "sim-oracle", "model": "m"}, ["vpp.backend.sim-oracle.model"]),  # a field of the other kind
    ({"kind": "openai-compatible", "base_url": "http://127.0.0.1:1/v1", "model": "m",
      "regions": {"kind": "grounding-http"}}, ["vpp.backend.openai-compatible.regions.grounding-http.base_url"]),
    ({"kind": "openai-compatible", "base_url": "http://127.0.0.1:1/v1", "model": "m",
      "regions": {"kind": "sam"}}, ["vpp.backend.openai-compatible.regions: kind must be one of: opencv, grounding-http"]),
])
def test_backend_config_errors_name_the_field(tmp_path, backend, words):
    with pytest.raises(ConfigFileError) as e:
        load_controller_config(_config_file(tmp_path, backend))
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg


def test_openai_compatible_config_loads_with_its_regions(tmp_path):
    cfg = load_controller_config(_config_file(tmp_path, {
        "kind": "openai-compatible", "base_url": "http://127.0.0.1:8000/v1/", "model": "qwen", "timeout_s": 3.0,
        "regions": {"kind": "grounding-http", "base_url": "http://127.0.0.1:8010", "phrases": ["box", "chair"]},
    }))
    b = cfg.vpp.backend
    assert isinstance(b, OpenAICompatibleBackendConfig) and b.base_url == "http://127.0.0.1:8000/v1"
    assert isinstance(b.regions, GroundingRegionsConfig) and b.regions.phrases == ("box", "chair")
    assert cfg.vpp.first_answer_timeout_s == 5.0  # the VPP stage's own settings beside it


def test_factory_builds_openai_compatible_with_each_region_proposer():
    opencv = build_backend(OpenAICompatibleBackendConfig(base_url="http://127.0.0.1:8000/v1", model="qwen"))
    assert isinstance(opencv, ProposingBackend) and opencv.name == "openai-compatible"
    assert isinstance(opencv.backend, OpenAICompatibleBackend) and opencv.backend.config.model == "qwen"
    assert isinstance(opencv.proposer, OpenCvProposer) and opencv.fallback is None

    grounding = build_backend(OpenAICompatibleBackendConfig.model_validate({
        "base_url": "http://127.0.0.1:8000/v1", "model": "qwen",
        "regions": {"kind": "grounding-http", "base_url": "http://127.0.0.1:8010", "phrases": ["Box", "chair"]}}))
    assert isinstance(grounding.proposer, GroundingHttpProposer)
    assert grounding.prompt == "box . chair ." and isinstance(grounding.fallback, OpenCvProposer)


def test_sim_oracle_config_offsets_the_episode_seed_and_is_refused_outside_the_simulator():
    cfg = SimOracleBackendConfig(seed=2, recall=0.8)
    oracle = cfg.oracle_config(episode_seed=5)
    assert oracle.seed == 7 and oracle.recall == 0.8 and not hasattr(oracle, "kind")
    with pytest.raises(SimulatorOnlyBackendError, match="only in HIL.*openai-compatible"):
        build_backend(cfg)


def test_controller_in_mode_dct_with_the_sim_oracle_and_no_simulator_fails_at_start():
    """The default config (mode dct, sim-oracle) on anything but the simulator: a clear error
    when the controller is built, not a silent all-fixed robot."""
    cfg = load_controller_config()
    with pytest.raises(SimulatorOnlyBackendError, match="vpp.backend.kind sim-oracle"):
        NavigationController(load_robot_description(), cfg, hardware=None, goal=Pose2D(1.0, 0.0, 0.0),
                             clock=lambda: 0.0)


def test_the_partition_stage_is_chosen_by_the_mode():
    robot, goal = load_robot_description(), Pose2D(1.0, 0.0, 0.0)
    backend = OpenAICompatibleBackendConfig(base_url=dead_url(), model="m")
    cfg = load_controller_config().model_copy(update={"vpp": load_controller_config().vpp.model_copy(
        update={"backend": backend})})
    dct = NavigationController(robot, cfg, hardware=None, goal=goal, clock=lambda: 0.0, lockstep=True)
    assert isinstance(dct.partition.inner, VppPartition) and dct.vpp is dct.partition.inner.vpp
    assert isinstance(dct.vpp.runner.backend, ProposingBackend)  # built from the config
    dct.partition.close()
    for mode in ("all-fixed", "pure-pursuit"):
        ctl = NavigationController(robot, cfg.with_planner_mode(mode), hardware=None, goal=goal, clock=lambda: 0.0)
        assert isinstance(ctl.partition.inner, AllFixedPartition) and ctl.vpp is None
        assert ctl.partition.update(0.0, (0.0, 0.0, 0.0), None, None) is None and ctl.partition.ready(0.0)


def test_openai_compatible_at_a_dead_port_degrades_to_every_point_fixed_and_the_robot_drives():
    """HIL, mode dct, the VLM server down: every request fails (connection refused), the stage
    stops waiting at the first failed answer, no point leaves P_fix, and the robot drives on as
    all-fixed would (case1's box is then an obstacle to pass beside, not to push)."""
    base = load_controller_config()
    backend = OpenAICompatibleBackendConfig(base_url=dead_url(), model="m", max_retries=0, timeout_s=2.0)
    cfg = base.model_copy(update={"vpp": base.vpp.model_copy(update={"backend": backend})})
    movable = []

    def observe(controller):
        frame = controller.vpp.last_frame
        movable.append(0 if frame is None else frame.movable_count)

    scenario = load_scenario("case1").model_copy(update={"time_limit_s": 3.5})
    result = run_episode(scenario, config=cfg, seed=0, observe=observe)
    vpp = result.controller["vpp"]
    assert vpp["requests"] >= 1 and vpp["answers"] >= 1 and vpp["failed_answers"] == vpp["answers"]
    assert not vpp["gave_up_waiting"]  # the failed answer ended the wait, not the 5 s timeout
    assert max(movable) == 0  # no masks: every point P_fix
    assert result.metrics["fixed_contacts"] == 0
    x, _, _ = result.controller["pose_odom"]
    assert x > 0.5, result.controller["pose_odom"]  # it drove: no stall on the dead backend
