"""The contact-tolerance backend of planner mode dct, from the controller config (`vpp.backend`).

The backend and its parameters are chosen in the controller config; a backend that is
down or slow degrades to no new masks (the runner turns it into error answers; the points fall
back to P_fix), never a stall. Two kinds:

* `sim-oracle` (models.vlm.sim_oracle): answers from the simulator's ground-truth segmentation.
  It needs the World's object table, so only the simulator can build it (hil_sim.episode.lockstep does,
  from these parameters, with its seed offset by the episode seed); anywhere else the
  controller refuses to start (`SimulatorOnlyBackendError`).
* `openai-compatible` (models.vlm.openai_compatible): a chat-completions server (hosted, or a
  local vLLM / llama-server). It answers about numbered candidate regions (Set-of-Mark), which
  a region proposer draws first, beside the tick: the classical OpenCV proposer
  (models.vlm.regions), or an open-set detector over HTTP (models.vlm.grounding_http) that
  falls back to OpenCV while the detector is down.

Example (controller config)::

    vpp:
      backend:
        kind: openai-compatible
        base_url: http://127.0.0.1:8000/v1
        model: Qwen2.5-VL-7B-Instruct
        timeout_s: 4.0
        max_retries: 0
        regions:
          kind: grounding-http
          base_url: http://127.0.0.1:8010
          phrases: [box, chair, curtain, plant]
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Annotated, Literal, Union

from pydantic import ConfigDict, Discriminator, Field, Tag

from models.vlm.grounding_http import GroundingHttpConfig, GroundingHttpProposer, detector_prompt
from models.vlm.interface import VlmAnswer, VlmBackend, VlmRequest
from models.vlm.openai_compatible import OpenAICompatibleBackend, OpenAICompatibleConfig
from models.vlm.regions import OpenCvProposer, OpenCvProposerConfig, RegionProposalError, RegionProposer
from models.vlm.sim_oracle import SimOracleConfig

logger = logging.getLogger(__name__)


class SimulatorOnlyBackendError(ValueError):
    """A backend that only the simulator can build was asked for elsewhere."""


def _kind(value):
    return value.get("kind") if isinstance(value, dict) else getattr(value, "kind", None)


def _by_kind(*members: type) -> Discriminator:
    """A union chosen by its `kind` field, whose error names the kinds there are (pydantic's own
    says only that it could not extract the tag)."""
    kinds = ", ".join(m.model_fields["kind"].default for m in members)
    return Discriminator(_kind, custom_error_type="unknown_kind", custom_error_message=f"kind must be one of: {kinds}")


# ------------------------------------------------------------------------------------ config
class SimOracleBackendConfig(SimOracleConfig):
    """`kind: sim-oracle`: the oracle's quality knobs (models.vlm.sim_oracle.SimOracleConfig).
    In HIL its `seed` is added to the episode seed (0: the oracle draws with the episode's seed)."""

    kind: Literal["sim-oracle"] = "sim-oracle"

    def oracle_config(self, episode_seed: int = 0) -> SimOracleConfig:
        return SimOracleConfig(**{**self.model_dump(exclude={"kind"}), "seed": self.seed + episode_seed})


class OpenCvRegionsConfig(OpenCvProposerConfig):
    """`regions: {kind: opencv, ...}`: the classical proposer (models.vlm.regions), no model."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["opencv"] = "opencv"


class GroundingRegionsConfig(GroundingHttpConfig):
    """`regions: {kind: grounding-http, ...}`: an open-set detector server
    (models.vlm.grounding_http); `phrases` is its text prompt."""

    kind: Literal["grounding-http"] = "grounding-http"
    phrases: tuple[str, ...] = Field(
        default=("box", "chair", "curtain", "plant", "bin", "bag", "ball", "table"), min_length=1,
        description="what the detector looks for (Grounding DINO prompt phrases)")
    #: While the detector is down (or answers garbage), propose with OpenCV instead of asking nothing.
    fallback_opencv: bool = True
    opencv: OpenCvProposerConfig = OpenCvProposerConfig()


RegionsConfig = Annotated[Union[Annotated[OpenCvRegionsConfig, Tag("opencv")],
                                Annotated[GroundingRegionsConfig, Tag("grounding-http")]],
                          _by_kind(OpenCvRegionsConfig, GroundingRegionsConfig)]


class OpenAICompatibleBackendConfig(OpenAICompatibleConfig):
    """`kind: openai-compatible`: the server (models.vlm.openai_compatible.OpenAICompatibleConfig)
    and the candidate regions its marks are drawn on."""

    kind: Literal["openai-compatible"] = "openai-compatible"
    regions: RegionsConfig = OpenCvRegionsConfig()

    def client_config(self) -> OpenAICompatibleConfig:
        return OpenAICompatibleConfig(**self.model_dump(exclude={"kind", "regions"}))


BackendConfig = Annotated[Union[Annotated[SimOracleBackendConfig, Tag("sim-oracle")],
                                Annotated[OpenAICompatibleBackendConfig, Tag("openai-compatible")]],
                          _by_kind(SimOracleBackendConfig, OpenAICompatibleBackendConfig)]


# ----------------------------------------------------------------------------------- backends
class ProposingBackend:
    """A backend that needs candidate regions, with a proposer in front: a request that comes
    without regions (the VPP stage sends only the image) gets them here, beside the tick, in the
    runner's thread. A proposer that fails falls back to `fallback`, or the answer is an error
    (no new masks)."""

    def __init__(self, backend: VlmBackend, proposer: RegionProposer, prompt: str = "",
                 fallback: RegionProposer | None = None) -> None:
        self.backend = backend
        self.proposer = proposer
        self.prompt = prompt
        self.fallback = fallback
        self.name = backend.name
        self.proposer_failures = 0

    def _regions(self, request: VlmRequest):
        prompt = self.prompt or request.prompt
        try:
            if isinstance(self.proposer, GroundingHttpProposer):  # it sends the capture stamp along
                return self.proposer.propose(request.image, prompt, stamp_s=request.stamp_s)
            return self.proposer.propose(request.image, prompt)
        except RegionProposalError as exc:
            self.proposer_failures += 1
            if self.fallback is None:
                raise
            logger.warning("%s failed (%s); proposing with %s", self.proposer.name, exc, self.fallback.name)
            return self.fallback.propose(request.image, prompt)

    def query(self, request: VlmRequest) -> VlmAnswer:
        if not request.regions:
            try:
                request = dataclasses.replace(request, regions=tuple(self._regions(request)))
            except Exception as exc:  # noqa: BLE001 - a proposer that fails is an error answer, not a crash
                return VlmAnswer(stamp_s=request.stamp_s, camera_pose_odom=request.camera_pose_odom, objects=(),
                                 backend=self.name, latency_s=0.0,
                                 error=f"region proposal failed: {type(exc).__name__}: {exc}")
        return self.backend.query(request)


def build_proposer(config: OpenCvRegionsConfig | GroundingRegionsConfig) -> tuple[RegionProposer, str, RegionProposer | None]:
    """(proposer, its prompt, its fallback) for a `regions:` section."""
    if isinstance(config, GroundingRegionsConfig):
        detector = GroundingHttpProposer(GroundingHttpConfig(
            **config.model_dump(exclude={"kind", "phrases", "fallback_opencv", "opencv"})))
        fallback = OpenCvProposer(config.opencv) if config.fallback_opencv else None
        return detector, detector_prompt(config.phrases), fallback
    return OpenCvProposer(OpenCvProposerConfig(**config.model_dump(exclude={"kind"}))), "", None


def build_backend(config: SimOracleBackendConfig | OpenAICompatibleBackendConfig) -> VlmBackend:
    """The backend a `vpp.backend` section asks for. Raises SimulatorOnlyBackendError for the
    sim-oracle (it needs the simulator's object table: hil_sim builds it and passes it in), and
    ValueError when the openai-compatible key's environment variable is not set."""
    if isinstance(config, SimOracleBackendConfig):
        raise SimulatorOnlyBackendError(
            "vpp.backend.kind sim-oracle answers from the simulator's ground truth and runs only in HIL "
            "(dct hil run builds it); outside the simulator set vpp.backend.kind: openai-compatible "
            "with its base_url and model in the controller config")
    if isinstance(config, OpenAICompatibleBackendConfig):
        proposer, prompt, fallback = build_proposer(config.regions)
        return ProposingBackend(OpenAICompatibleBackend(config.client_config()), proposer, prompt, fallback)
    raise ValueError(f"vpp.backend: unknown backend config {type(config).__name__}")


__all__ = [
    "BackendConfig",
    "GroundingRegionsConfig",
    "OpenAICompatibleBackendConfig",
    "OpenCvRegionsConfig",
    "ProposingBackend",
    "SimOracleBackendConfig",
    "SimulatorOnlyBackendError",
    "build_backend",
    "build_proposer",
]
