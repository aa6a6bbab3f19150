"""The configuration of a policy training run (``latentdrive train-policy``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from latentdrive.config import Config, ConfigError, ObservationConfig
from latentdrive.models.objects import ROAD_POOL
from latentdrive.models.vfan import MODES, Mode, VFANConfig
from latentdrive.rl.dqn import DQNConfig
from latentdrive.rl.imitate import ImitationConfig
from latentdrive.runtime import PRECISIONS, Precision, check_device
from latentdrive.scenarios import (
    RewardConfig,
    ScenarioSpec,
    get_spec,
    resolve_specs,
)

__all__ = ["PolicyTrainConfig", "check_mission_pays"]


class PolicyTrainConfig(Config):
    """Everything that defines a policy training run; saved in the run's config.json."""

    mode: Mode = Field("latent", description=f"Input representation: {', '.join(MODES)}.")
    specs: dict[str, ScenarioSpec] = Field(default_factory=dict, description="The resolved spec of each of scenarios, keyed by its entry there. Filled from the presets and spec files when a run is configured and saved in its config.json, so the run trains, resumes and evaluates on these copies wherever its folder lies.")
    scenarios: tuple[str, ...] = Field(("merge",), min_length=1, description="Scenarios to train on. Environment slot i plays scenarios[i % len]: every vector step holds an equal mix.")
    steps: int = Field(50_000, ge=1, le=10**10, description="Budget in agent-transitions (one AV's one policy step), so budgets compare across AV counts.")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed of the weights, exploration, replay sampling and training episodes.")
    envs: int = Field(16, ge=1, le=4096, description="Environments stepped together.")
    backend: Literal["fast", "highway"] = Field("fast", description="Simulator backend.")
    bnn: str | None = Field(None, description="BNN run directory: the frozen encoder of mode 'latent'; for 'latent-random' and 'end-to-end' only its architecture is used (default architecture when omitted).")
    init_from: str | None = Field(None, description="Policy run directory whose final weights initialize this run (fine-tuning, transfer learning).")
    observation: ObservationConfig = Field(default_factory=ObservationConfig, description="VelocityMap settings; must match the BNN's input.")
    reward: RewardConfig = Field(default_factory=RewardConfig, description="Per-agent reward weights while training (evaluation rates do not depend on them).")
    learner: Literal["dqn", "dagger"] = Field("dqn", description="How the network learns: 'dqn', multi-agent double DQN on the reward (the paper's method); 'dagger', imitation of an expert's actions (the lookahead planner's, or the rule driver's: imitation.expert) on the states the policy visits (the imitation reference: what a policy reading this observation can reach; fast backend only). See latentdrive.rl.imitate.")
    dqn: DQNConfig = Field(default_factory=DQNConfig, description="Q-learning hyperparameters. Under learner 'dagger' only lr, adam_eps, batch_size, buffer_size (the labelled decisions kept), learning_starts, updates_per_transition and grad_clip apply.")
    imitation: ImitationConfig = Field(default_factory=ImitationConfig, description="DAgger settings (learner 'dagger' only).")
    vfan: VFANConfig = Field(default_factory=VFANConfig, description="VFAN body architecture.")
    segment: int = Field(10_000, ge=1, description="Agent-transitions between checkpoints. Every environment is reset at a segment boundary, from a seed fixed by (seed, segment index), so a resumed run continues exactly as an uninterrupted one.")
    eval_every: int = Field(2, ge=0, description="Evaluate on held-out seeds every this many segments, and at the end (0: only at the end).")
    eval_episodes: int = Field(30, ge=1, le=100_000, description="Evaluation episodes per scenario at each periodic evaluation.")
    eval_seeds: Literal["evaluation", "validation"] = Field("evaluation", description="Episodes of the periodic evaluation: 'evaluation' plays evaluation set TRAINING_EVAL_OFFSET (disjoint from the final evaluation's default set); 'validation' plays validation set 0, the range hyperparameter search scores on (latentdrive tune sets it), so that a tuned number is never a test number. See latentdrive.seeds.")
    keep: Literal["last", "best"] = Field("last", description="Which weights are the run's policy, for evaluate, the study and --init-from: 'last', those at the end of training (the paper's); 'best', those that failed least on the mix at a periodic evaluation (ties: the later), which plays held-out episodes (eval_seeds), never the test set. The checkpoint holds them beside the last weights, so a resumed run keeps its choice.")
    device: str = Field("auto", description="'auto' (CUDA when present), 'cpu', 'cuda' or 'cuda:N'.")
    precision: Precision = Field("auto", description=f"Compute precision of the networks' forward passes while training and acting ({', '.join(PRECISIONS)}): bf16 autocast, or fp32; 'auto' is bf16 on CPUs with AMX-BF16 whose oneDNN kernels pass a probe (runtime.cpu_bf16_gradients_sound), fp32 elsewhere, CUDA included (bf16 was no faster there: docs/performance.md). Covers the learner's updates, the frozen encoder's inference (latent modes), end-to-end training and acting; weights, optimizer state, targets and losses stay fp32.")
    threads: int = Field(1, ge=0, le=1024, description="CPU threads for torch (0: torch's default). One avoids oversubscribing the cores the simulator also uses; results are only bitwise reproducible at the same count.")

    @field_validator("scenarios")
    @classmethod
    def _known(cls, v: tuple[str, ...], info: ValidationInfo) -> tuple[str, ...]:
        if len(set(v)) != len(v):
            raise ValueError(f"scenarios repeat a name: {', '.join(v)}")
        stored = info.data.get("specs") or {}
        for name in v:
            if name not in stored:
                get_spec(name)  # a one-line error naming an unknown name or a missing spec file
        return v

    @model_validator(mode="after")
    def _complete_specs(self) -> PolicyTrainConfig:
        extra = sorted(set(self.specs) - set(self.scenarios))
        if extra:
            raise ValueError(f"specs: {extra[0]!r} is not one of scenarios")
        # The model is frozen, but its dict was built by this validation: completing it
        # here is what makes every validated config carry the specs it trains on.
        self.specs.update(resolve_specs([n for n in self.scenarios if n not in self.specs]))
        return self

    def scenario_specs(self) -> list[ScenarioSpec]:
        """The spec of each of ``scenarios``, in order."""
        return [self.specs[name] for name in self.scenarios]

    _check_device = field_validator("device")(check_device)

    @model_validator(mode="after")
    def _check_mode(self) -> PolicyTrainConfig:
        if self.mode == "latent" and not self.bnn:
            raise ValueError("mode 'latent' needs a trained BNN: give bnn (train-policy --bnn RUN)")
        if self.mode == "raw" and self.bnn:
            raise ValueError("mode 'raw' takes no BNN")
        if self.learner == "dagger" and self.backend != "fast":
            raise ValueError("learner 'dagger' needs backend 'fast': its experts read the fast backend's simulator "
                             "(the lookahead planner branches its state; the rule driver reads its specs)")
        if self.vfan.reader != "conv" and self.mode != "raw":
            raise ValueError(f"vfan.reader {self.vfan.reader!r} reads raw maps: mode {self.mode!r} feeds the body "
                             "latents (use it with mode 'raw')")
        if self.vfan.reader == "attention" and self.dqn.augment_shift > 0:
            raise ValueError("vfan.reader 'attention' queries the token that holds the observer: shifting the maps "
                             "(dqn.augment_shift) would move the observer off it")
        if self.vfan.reader == "objects" and self.dqn.augment_shift > 0:
            raise ValueError("vfan.reader 'objects' places each vehicle relative to the observer: shifting the maps "
                             "(dqn.augment_shift) would move every vehicle by the shift")
        if self.vfan.reader == "objects":
            self._check_objects_reader()
        if self.dqn.augment_shift > 0 and self.mode not in ("raw", "end-to-end"):
            raise ValueError(f"dqn.augment_shift shifts maps: mode {self.mode!r} learns from stored latents "
                             "(use it with mode 'raw' or 'end-to-end')")
        if self.learner == "dagger" and (self.dqn.n_step > 1 or self.dqn.prioritized):
            raise ValueError("learner 'dagger' fits labels, not returns: dqn.n_step must be 1 and dqn.prioritized "
                             "false")
        if self.dqn.aux_scale > 0 and (self.vfan.reader != "attention" or self.learner != "dqn"):
            raise ValueError("dqn.aux_scale trains the attention reader's summary beside the Q-learner: it needs "
                             "vfan.reader 'attention' (mode 'raw') and learner 'dqn'")
        if self.learner == "dagger" and (self.dqn.explore_rule > 0 or self.dqn.augment_shift > 0):
            raise ValueError("learner 'dagger' neither explores nor augments: dqn.explore_rule and "
                             "dqn.augment_shift must be 0")
        return self

    def _check_objects_reader(self) -> None:
        obs = self.observation
        if self.dqn.dueling:
            raise ValueError("vfan.reader 'objects' has no dueling head: dqn.dueling must be false")
        if obs.route > 0:
            raise ValueError("vfan.reader 'objects' reads the AV's speed as the MV channel's peak: "
                             f"observation.route={obs.route} draws the route there too (use route 0)")
        if obs.frames < 2:
            raise ValueError(f"vfan.reader 'objects' reads the AV's speed in two frames: observation.frames "
                             f"must be at least 2, got {obs.frames}")
        if self.vfan.objects_frames > obs.frames:
            raise ValueError(f"vfan.objects_frames={self.vfan.objects_frames} reads more frames than the "
                             f"observation stacks (observation.frames={obs.frames})")
        if obs.height % ROAD_POOL or obs.width % ROAD_POOL:
            raise ValueError(f"vfan.reader 'objects' averages the road over {ROAD_POOL} x {ROAD_POOL} cells: "
                             f"observation.height and width must be multiples of {ROAD_POOL}, got "
                             f"{obs.height} x {obs.width}")


def check_mission_pays(cfg: PolicyTrainConfig) -> None:
    """Refuse a reward under which the optimal policy never completes its mission.

    An AV stops earning when it completes its mission, and the learner bootstraps through
    the time limit: if cruising forever (``speed / (1 - γ)``) is worth more than arriving,
    arriving never pays. Checked when a run starts, not when a finished run is loaded, so
    runs trained before the check still evaluate.

    Raises:
        ConfigError: naming both numbers.
    """
    forever = cfg.reward.speed / (1.0 - cfg.dqn.gamma)
    if cfg.reward.speed > 0 and cfg.reward.mission <= forever:
        raise ConfigError(f"reward.mission ({cfg.reward.mission:g}) must exceed reward.speed / (1 - dqn.gamma) "
                          f"({forever:g}), what cruising forever is worth; otherwise the learner avoids "
                          "completing its mission")
