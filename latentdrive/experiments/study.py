"""The paper's study as a graph of steps: its config, presets and the graph builder.

Policies (per training seed and representation):

- ``policy/<rep>/<scenario>/s<k>``: trained on one scenario (the oracle of that scenario);
- ``policy/<rep>/mixed/s<k>``: trained on every scenario;
- ``policy/<rep>/without-<scenario>/s<k>``: every scenario but one (leave-one-out; the
  pretraining of transfer learning when the left-out one is the transfer target);
- ``policy/<rep>/<target>-finetuned/s<k>``: that pretraining fine-tuned on the target;
- ablations on the mix: ``latent-random``, ``end-to-end`` and ``latent-lam`` (the λ > 0 BNN);
- ``policy/imitation/mixed/s<k>`` (``experiments.imitation``): the imitation reference, the
  raw-mode network trained by DAgger from the lookahead planner on the mix
  (:mod:`latentdrive.rl.imitate`), with as many labelled decisions as a policy's budget.

Every policy is evaluated on every scenario (``evaluate/<policy>``), which gives the
train × test matrices; the reference policies (random, rule, the lookahead planner) on the
same episodes (``evaluate/ref/<name>``); the mixed policies again on both backends with the
same few episodes (``cross/<backend>/<policy>``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import Field, field_validator, model_validator

from latentdrive.config import (
    Config,
    ConfigError,
    ObservationConfig,
    dotted_items,
    load_preset,
    merge_overrides,
    validate,
)
from latentdrive.evaluate.planner import PlannerConfig
from latentdrive.evaluate.policies import REFERENCE_POLICIES
from latentdrive.experiments.bnn import BNNStudyConfig, run_name, study_runs
from latentdrive.experiments.estimate import scored_count
from latentdrive.experiments.graph import Graph, Step
from latentdrive.rl.config import PolicyTrainConfig, check_mission_pays
from latentdrive.rl.policy import scenario_hashes
from latentdrive.scenarios import (
    SCENARIOS,
    RewardConfig,
    ScenarioSpec,
    check_scenario_names,
    resolve_specs,
)

__all__ = ["IMITATION", "KINDS", "PRESETS", "ReproduceConfig", "build_graph", "load_reproduce_config", "policy_name", "reference_name"]

PRESETS = ("tiny", "quick", "rates", "standard", "paper")
PRESETS_DIR = Path(__file__).parent / "presets"
REPS = ("raw", "latent")
ABLATIONS = ("latent-random", "end-to-end", "latent-lam")
#: The imitation reference's policy kind (raw mode, learner dagger).
IMITATION = "imitation"
#: Every kind of policy the study trains, and the input mode each trains in.
KINDS = (*REPS, *ABLATIONS, IMITATION)
_MODE = {"latent-lam": "latent", IMITATION: "raw"}
# Agent-transitions per second of a whole policy step on one core (quick study, 2 workers on
# 2 cores); only for the progress display's ETA and the order in which steps start.
_RATE = {"raw": 45.0, "latent": 110.0, "latent-random": 110.0, "end-to-end": 45.0, "latent-lam": 110.0,
         IMITATION: 12.0}


class StudyPolicyConfig(Config):
    """How every policy of the study is trained."""

    steps: int = Field(40_000, ge=1, le=10**10, description="Agent-transitions per policy trained from scratch.")
    finetune_steps: int = Field(10_000, ge=1, le=10**10, description="Agent-transitions of fine-tuning on the transfer target.")
    train: dict[str, Any] = Field(default_factory=dict, description="Further train-policy settings for every policy (dqn, vfan, envs, segment, eval_every, eval_episodes, threads, device); checked when the study is built.")
    by_kind: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="Train-policy settings for the policies of one kind only (raw, latent, latent-random, end-to-end, "
                    "latent-lam, imitation), merged over train: for example {raw: {vfan: {reader: objects}}} has the raw "
                    "policies read the map through the objects reader while every kind keeps train's learner settings.")
    finetune: dict[str, Any] = Field(
        default_factory=lambda: {"dqn": {"eps_start": 0.2, "learning_starts": 500}},
        description="Settings that fine-tuning runs add to train: a pretrained policy needs less exploration, and a "
                    "short budget cannot wait for the default 2,000 transitions before learning.")

    @field_validator("train", "finetune")
    @classmethod
    def _not_the_studys(cls, v: dict[str, Any]) -> dict[str, Any]:
        return _without_study_settings(v, "")

    @field_validator("by_kind")
    @classmethod
    def _kinds(cls, v: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
        unknown = [k for k in v if k not in KINDS]
        if unknown:
            raise ValueError(f"unknown policy kind {unknown[0]!r}: choose from {', '.join(KINDS)}")
        for kind, settings in v.items():
            _without_study_settings(settings, f"{kind}.")
        return v


#: Train-policy settings that the study sets for each policy from its own fields.
_STUDY_SET = {"mode": "the policy's kind", "learner": "the policy's kind", "scenarios": "the experiment",
              "seed": "seeds", "steps": "policy.steps and policy.finetune_steps", "observation": "observation",
              "reward": "reward", "bnn": "the study's BNN", "init_from": "the experiment", "specs": "scenarios",
              "imitation.expert": "the imitation kind: the planner", "imitation.planner": "evaluate.planner"}


def _without_study_settings(settings: dict[str, Any], where: str) -> dict[str, Any]:
    """``settings``, refused where they hold one the study sets itself (a silent override
    would make one policy differ from the study's record of it)."""
    for name, _ in dotted_items(settings):
        parts = name.split(".")
        for prefix in (parts[0], ".".join(parts[:2])):
            if prefix in _STUDY_SET:
                raise ValueError(f"{where}{prefix}: set by the study ({_STUDY_SET[prefix]}), not here")
    return settings


class StudyEvalConfig(Config):
    """The held-out evaluation every policy and reference meets."""

    episodes: int = Field(200, ge=1, le=100_000, description="Episodes per scenario for every policy and reference.")
    envs: int = Field(16, ge=1, le=1024, description="Environments per scenario; part of the evaluation set's definition.")
    seed_offset: int = Field(0, ge=0, description="Which disjoint evaluation set (see latentdrive.seeds).")
    references: tuple[str, ...] = Field(("random", "rule", "plan"), description="Reference policies evaluated on the same episodes.")
    planner: PlannerConfig = Field(default_factory=PlannerConfig, description="Settings of the 'plan' reference.")
    cross_backend_episodes: int = Field(0, ge=0, le=10_000, description="Episodes per scenario on which the mixed policies are evaluated on both backends (0: skip; highway-env steps at 2-35 per second).")

    @field_validator("references")
    @classmethod
    def _known(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        unknown = [r for r in v if r not in REFERENCE_POLICIES]
        if unknown:
            raise ValueError(f"unknown reference policy {unknown[0]!r}: choose from {', '.join(REFERENCE_POLICIES)}")
        return v


class StudyExperimentsConfig(Config):
    """Which experiments beyond the oracle, mixed and matrix policies the study runs."""

    transfer_target: str | None = Field("roundabout", description="Scenario fine-tuned on after pretraining on the others (none: skip transfer learning).")
    leave_one_out: bool = Field(True, description="Train on all scenarios but one, test zero-shot on it, for every scenario.")
    ablations: bool = Field(True, description="latent-random, end-to-end and the λ > 0 BNN on the mix, beside latent and raw.")
    imitation: bool = Field(False, description="The imitation reference on the mix, per training seed: the raw-mode network trained by DAgger from the lookahead planner (evaluate.planner) with policy.steps labelled decisions, evaluated beside the planner as the failure rate shown reachable from the map. The planner labels every decision, so it trains several times slower per decision than a DQN policy.")
    probe_episodes: int = Field(20, ge=0, le=100_000, description="Episodes per scenario (rule driver) on which linear probes read driving quantities from raw, latent and random-encoder features (0: skip).")


class ReproduceConfig(Config):
    """Everything that defines a ``latentdrive reproduce`` study."""

    scenarios: tuple[str, ...] = Field(SCENARIOS, min_length=2, description="The scenarios (preset names); the mix is all of them.")
    seeds: int = Field(3, ge=1, le=100, description="Training seeds per policy (0 .. seeds-1); evaluation seeds are disjoint from them.")
    observation: ObservationConfig = Field(default_factory=ObservationConfig, description="VelocityMap of the dataset, the BNNs and every policy.")
    reward: RewardConfig = Field(default_factory=RewardConfig, description="Reward weights of training (rates do not depend on them).")
    bnn: BNNStudyConfig = Field(default_factory=BNNStudyConfig, description="The BNN study: its collect.scenarios and observation are the study's.")
    policy_bnn: int = Field(64, ge=1, description="Latent size d of the λ = 0 BNN that latent policies use; must be one of bnn.latent_dims.")
    policy: StudyPolicyConfig = Field(default_factory=StudyPolicyConfig, description="Policy training.")
    evaluate: StudyEvalConfig = Field(default_factory=StudyEvalConfig, description="Evaluation.")
    experiments: StudyExperimentsConfig = Field(default_factory=StudyExperimentsConfig, description="Optional experiments.")

    @field_validator("scenarios")
    @classmethod
    def _scenarios(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        check_scenario_names(v)
        # Results match episodes to scenarios by the spec's own name, which a spec file
        # need not share with its path: a study takes the named presets only.
        files = [n for n in v if n not in SCENARIOS]
        if files:
            raise ValueError(f"a study takes scenario names ({', '.join(SCENARIOS)}), not spec files: {files[0]}")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> ReproduceConfig:
        if self.policy_bnn not in self.bnn.latent_dims:
            raise ValueError(f"policy_bnn {self.policy_bnn} is not among bnn.latent_dims {self.bnn.latent_dims}")
        t = self.experiments.transfer_target
        if t is not None and t not in self.scenarios:
            raise ValueError(f"experiments.transfer_target {t!r} is not one of the scenarios")
        # Every kind's settings are checked here, also those of a kind this study does not
        # train (the report names them all).
        for kind in self.policy.by_kind:
            self.policy_config(kind, self.scenarios, 0, self.policy.steps)
        if self.experiments.ablations and not self.bnn.lambdas:
            raise ValueError("experiments.ablations needs a λ > 0 BNN (bnn.lambdas)")
        if self.experiments.ablations and self.policy_bnn != max(self.bnn.latent_dims):
            # The λ > 0 BNN is trained at the largest d: compared at another d, the ablation
            # would mix the effect of λ with that of d.
            raise ValueError(f"experiments.ablations compares the λ > 0 BNN (d = {max(self.bnn.latent_dims)}) with "
                             f"the latent policies' BNN: policy_bnn must be {max(self.bnn.latent_dims)}")
        return self

    def policy_config(self, kind: str, scenarios: tuple[str, ...], seed: int, steps: int,
                      finetune: bool = False) -> PolicyTrainConfig:
        """The train-policy config of one study policy of ``kind`` (one of :data:`KINDS`; its BNN
        and initial weights are inputs); for the imitation kind, the DAgger run whose expert is
        the study's planner."""
        mode = _MODE.get(kind, kind)
        data = merge_overrides({"mode": mode, "scenarios": list(scenarios), "seed": seed, "steps": steps,
                                "observation": self.observation.model_dump(), "reward": self.reward.model_dump()},
                               self.policy.train)
        where = "policy.train"
        if kind in self.policy.by_kind:
            data = merge_overrides(data, self.policy.by_kind[kind])
            where = f"policy.train and policy.by_kind.{kind}"
        if finetune:
            data = merge_overrides(data, self.policy.finetune)
        if kind == IMITATION:
            # The reference copies the study's own planner, whatever policy.train says.
            data = merge_overrides(data, {"learner": "dagger", "imitation.expert": "plan",
                                          "imitation.planner": self.evaluate.planner.model_dump()})
        if mode == "latent":
            data["bnn"] = "(the study's BNN)"  # a placeholder for validation; the step fills in the path
        try:
            cfg = validate(PolicyTrainConfig, data)
            check_mission_pays(cfg)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        return cfg


def load_reproduce_config(preset: str, overrides: dict[str, Any] | None = None) -> ReproduceConfig:
    """A named preset (one of :data:`PRESETS`) or a YAML file, with dotted overrides applied."""
    return load_preset(ReproduceConfig, preset, {p: PRESETS_DIR / f"reproduce-{p}.yaml" for p in PRESETS}, overrides)


def policy_name(rep: str, train_set: str, seed: int) -> str:
    """The step that trains representation ``rep`` on ``train_set`` (a scenario, ``mixed``,
    ``without-<scenario>``, ``<scenario>-finetuned``) from training seed ``seed``."""
    return f"policy/{rep}/{train_set}/s{seed}"


#: Rough samples a collected episode yields, for costs and estimates made before a dataset exists.
SAMPLES_PER_EPISODE = 40


def reference_name(ref: str) -> str:
    """The step that evaluates reference policy ``ref``."""
    return f"evaluate/ref/{ref}"


def build_graph(cfg: ReproduceConfig, specs_stored: Mapping[str, ScenarioSpec] | None = None) -> Graph:
    """Every step of the study, with its resolved config and inputs.

    Steps are keyed by the hashes of the scenarios' specs: those ``specs_stored`` holds (a
    study folder's record, so that it reports from the specs it ran on wherever it lies),
    else today's presets.
    """
    specs = scenario_hashes(resolve_specs(cfg.scenarios, specs_stored))
    steps: list[Step] = []
    obs = cfg.observation.model_dump(mode="json")
    collect = cfg.bnn.collect.model_dump(mode="json")
    collect.update(scenarios=list(cfg.scenarios), workers=1)
    collect["env"] = merge_overrides(collect.get("env") or {}, {"observation": obs})
    bnn_study = cfg.bnn.model_copy(update={"collect": cfg.bnn.collect.model_validate(collect)})
    samples = cfg.bnn.collect.episodes * len(cfg.scenarios) * SAMPLES_PER_EPISODE
    steps.append(Step("dataset", "dataset", {"collect": collect, "specs": specs}, cost=samples / 300))
    runs = study_runs(bnn_study)
    epochs = cfg.bnn.train.pretrain_epochs + cfg.bnn.train.mixed_epochs
    # Rough seconds on a 2-core CPU: ~80 training samples/s, ~100 scored samples/s per run
    # (and the noisy input). An epoch is capped at epoch_steps batches when that is set.
    trained = samples * (1 - cfg.bnn.val_fraction)
    per_epoch = min(trained, cfg.bnn.train.epoch_steps * cfg.bnn.train.batch_size) if cfg.bnn.train.epoch_steps else trained
    bnn_cost = epochs * per_epoch / 80
    held = samples * cfg.bnn.val_fraction
    scored = scored_count(held, cfg.bnn.score_samples)
    # Settings newer than finished studies stay out of the keys at their old behaviour
    # (graph.LATER_SETTINGS), so those studies keep their keys.
    for name, d, lam in runs:
        bnn_cfg = {"train": cfg.bnn.train.replace(lambda_distance=lam).model_dump(mode="json"),
                   "latent_dim": d, "channels": list(cfg.bnn.channels), "val_fraction": cfg.bnn.val_fraction,
                   "model": dict(cfg.bnn.model)}
        steps.append(Step(f"bnn/{name}", "bnn", bnn_cfg, {"dataset": "dataset"}, cost=bnn_cost))
    steps.append(Step("bnn/report", "bnn-report",
                      {"study": bnn_study.model_dump(mode="json"),
                       "runs": {n: [d, lam] for n, d, lam in runs}},
                      {"dataset": "dataset", **{f"run:{n}": f"bnn/{n}" for n, _, _ in runs}},
                      cost=30 + (len(runs) + 1) * scored / 100))
    policy_bnn = f"bnn/{run_name(cfg.policy_bnn)}"
    # latent-random and end-to-end take only the architecture of the policy BNN (not its
    # weights), so the ablations differ from latent in the weights alone.
    bnn_for = {"latent": policy_bnn, "latent-random": policy_bnn, "end-to-end": policy_bnn,
               "latent-lam": f"bnn/{runs[-1][0]}"}

    ev = cfg.evaluate
    eval_cfg = {"scenarios": list(cfg.scenarios), "episodes": ev.episodes, "envs": ev.envs, "backend": "fast",
                "seed_offset": ev.seed_offset, "observation": obs, "reward": cfg.reward.model_dump(mode="json"),
                "planner": None}
    eval_cost = ev.episodes * len(cfg.scenarios) * 0.05

    def policy(rep: str, train_set: str, scenarios: tuple[str, ...], seed: int, steps_: int, init: str | None = None) -> str:
        pcfg = cfg.policy_config(rep, scenarios, seed, steps_, finetune=init is not None).model_dump(mode="json")
        # The step's key holds the specs' hashes ("specs"); the run fills in the specs
        # themselves and stores them in its own config.json.
        pcfg.update(bnn=None, init_from=None)
        del pcfg["specs"]
        inputs = {"bnn": bnn_for[rep]} if rep in bnn_for else {}
        if init is not None:
            inputs["init"] = init
        name = policy_name(rep, train_set, seed)
        steps.append(Step(name, "policy", {"train": pcfg, "specs": specs}, inputs, cost=10 + steps_ / _RATE[rep]))
        steps.append(Step(f"evaluate/{name}", "evaluate", {"eval": eval_cfg, "specs": specs}, {"policy": name},
                          cost=eval_cost))
        return name

    exp = cfg.experiments
    for seed in range(cfg.seeds):
        for rep in REPS:
            for scen in cfg.scenarios:
                policy(rep, scen, (scen,), seed, cfg.policy.steps)
            policy(rep, "mixed", cfg.scenarios, seed, cfg.policy.steps)
            if exp.leave_one_out or exp.transfer_target:
                for scen in cfg.scenarios:
                    if exp.leave_one_out or scen == exp.transfer_target:
                        rest = tuple(s for s in cfg.scenarios if s != scen)
                        policy(rep, f"without-{scen}", rest, seed, cfg.policy.steps)
            if exp.transfer_target:
                t = exp.transfer_target
                policy(rep, f"{t}-finetuned", (t,), seed, cfg.policy.finetune_steps,
                       init=policy_name(rep, f"without-{t}", seed))
        if exp.ablations:
            for rep in ABLATIONS:
                policy(rep, "mixed", cfg.scenarios, seed, cfg.policy.steps)
        if exp.imitation:
            policy(IMITATION, "mixed", cfg.scenarios, seed, cfg.policy.steps)

    for ref in ev.references:
        planner = ev.planner.model_dump(mode="json") if ref == "plan" else None
        steps.append(Step(reference_name(ref), "evaluate", {"eval": {**eval_cfg, "planner": planner}, "reference": ref,
                                                              "specs": specs},
                          cost=eval_cost * (40 if ref == "plan" else 1)))
    if exp.probe_episodes:
        probe = {"scenarios": list(cfg.scenarios), "episodes": exp.probe_episodes, "observation": obs}
        steps.append(Step("probes", "probes", {"probe": probe, "kinds": ["raw", "latent", "latent-random"], "specs": specs},
                          {"bnn": bnn_for["latent"]}, cost=exp.probe_episodes * len(cfg.scenarios) * 0.6))
    if ev.cross_backend_episodes:
        for backend in ("fast", "highway"):
            small = {**eval_cfg, "episodes": ev.cross_backend_episodes, "envs": min(ev.envs, ev.cross_backend_episodes),
                     "backend": backend}
            per_step = 0.05 if backend == "fast" else 3.0
            for seed in range(cfg.seeds):
                for rep in REPS:
                    name = policy_name(rep, "mixed", seed)
                    steps.append(Step(f"cross/{backend}/{name}", "evaluate", {"eval": small, "specs": specs},
                                      {"policy": name}, cost=ev.cross_backend_episodes * len(cfg.scenarios) * 30 * per_step))
    return Graph(steps)
