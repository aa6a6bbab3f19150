"""The study's graph: which policies it trains on what, and the configs it refuses."""

from __future__ import annotations

import collections

import pytest

from latentdrive.config import ConfigError
from latentdrive.experiments.graph import keyed_config
from latentdrive.experiments.steps import STEP_KINDS
from latentdrive.experiments.study import build_graph, load_reproduce_config


def test_the_tiny_graph_holds_every_experiment_with_the_right_inputs() -> None:
    g = build_graph(load_reproduce_config("tiny"))
    kinds = collections.Counter(s.kind for s in g.steps.values())
    # 3 scenarios: per representation 3 oracles + mix + 3 leave-one-out + 1 fine-tuned; 3 ablations;
    # the imitation reference.
    assert kinds["policy"] == 2 * 8 + 3 + 1 and kinds["evaluate"] == kinds["policy"] + 3
    imitation = g.steps["policy/imitation/mixed/s0"]
    assert imitation.inputs == {} and imitation.config["train"]["learner"] == "dagger"
    assert imitation.config["train"]["mode"] == "raw"
    assert "policy/imitation/mixed/s0" not in build_graph(
        load_reproduce_config("tiny", {"experiments": {"imitation": False}})).steps
    assert kinds["bnn"] == 3 and kinds["dataset"] == 1 and kinds["probes"] == 1
    ft = g.steps["policy/latent/roundabout-finetuned/s0"]
    assert ft.inputs == {"bnn": "bnn/d8", "init": "policy/latent/without-roundabout/s0"}
    assert ft.config["train"]["scenarios"] == ["roundabout"]
    assert ft.config["train"]["dqn"]["eps_start"] == 0.2  # fine-tuning explores less
    assert g.steps["policy/latent/roundabout/s0"].config["train"]["dqn"]["eps_start"] == 1.0
    assert g.steps["policy/latent/without-roundabout/s0"].config["train"]["scenarios"] == ["intersection", "merge"]
    assert g.steps["policy/latent-lam/mixed/s0"].inputs == {"bnn": "bnn/d8-lam0.01"}
    assert g.steps["policy/latent-lam/mixed/s0"].config["train"]["mode"] == "latent"
    assert "bnn" not in g.steps["policy/raw/mixed/s0"].inputs
    # The ablations take the policy BNN's architecture, whatever the study's channels.
    wide = build_graph(load_reproduce_config("tiny", {"bnn": {"channels": [8, 16]}}))
    for rep in ("latent-random", "end-to-end"):
        assert g.steps[f"policy/{rep}/mixed/s0"].inputs == {"bnn": "bnn/d8"}
        assert wide.keys[f"policy/{rep}/mixed/s0"] != g.keys[f"policy/{rep}/mixed/s0"]
    # Every policy and reference meets the same evaluation episodes.
    evals = [s.config["eval"] for s in g.steps.values() if s.kind == "evaluate"]
    assert len({(e["episodes"], e["envs"], e["seed_offset"], tuple(e["scenarios"])) for e in evals}) == 1


def test_more_seeds_add_policies_and_leave_the_first_seed_untouched() -> None:
    one = build_graph(load_reproduce_config("tiny"))
    two = build_graph(load_reproduce_config("tiny", {"seeds": 2}))
    assert all(two.keys[n] == k for n, k in one.keys.items())
    assert "policy/raw/mixed/s1" in two.steps and "policy/raw/mixed/s1" not in one.steps


@pytest.mark.parametrize(("override", "needle"), [
    ({"policy_bnn": 5}, "not among bnn.latent_dims"),
    ({"policy_bnn": 4}, "policy_bnn must be 8"),
    ({"experiments": {"transfer_target": "highway"}}, "not one of the scenarios"),
    ({"scenarios": ["merge", "merge"]}, "repeat a name"),
    ({"scenarios": ["merge", "moon"]}, "unknown scenario 'moon'"),
    ({"scenarios": ["merge", "latentdrive/scenarios/presets/exit.yaml"]}, "not spec files"),
    ({"evaluate": {"references": ["oracle"]}}, "unknown reference policy 'oracle'"),
    ({"policy": {"train": {"dqn": {"gamma": 0.999}}}}, "reward.mission"),
    ({"policy": {"by_kind": {"rawest": {}}}}, "unknown policy kind 'rawest'"),
    ({"policy": {"by_kind": {"raw": {"steps": 5}}}}, r"by_kind: raw.steps: set by the study \(policy.steps"),
    ({"policy": {"train": {"reward.speed": 1.0}}}, r"train: reward: set by the study \(reward\)"),
    ({"policy": {"finetune": {"seed": 3}}}, r"finetune: seed: set by the study \(seeds\)"),
    ({"policy": {"train": {"learner": "dagger"}}}, r"train: learner: set by the study \(the policy's kind\)"),
    ({"policy": {"by_kind": {"imitation": {"imitation": {"expert": "rule"}}}}},
     r"imitation.imitation.expert: set by the study"),
    ({"policy": {"by_kind": {"raw": {"vfan": {"reader": "eyes"}}}}}, "policy.by_kind.raw.*reader"),
    # A kind this study does not train is checked too: the report names its settings.
    ({"experiments": {"imitation": False}, "policy": {"by_kind": {"imitation": {"vfan": {"reader": "eyes"}}}}},
     "policy.by_kind.imitation.*reader"),
    ({"policy": {"by_kind": {"latent": {"dqn": {"gamma": 0.999}}}}}, "policy.by_kind.latent: reward.mission"),
])
def test_inconsistent_studies_are_refused_with_the_field_named(override: dict, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        build_graph(load_reproduce_config("tiny", override))


def test_finished_studies_keep_their_step_keys() -> None:
    # The keys the tiny preset's steps had before the BNN study's model section and
    # train.val_samples existed: a new setting at its default must not change them, or
    # every finished study would train its BNNs and latent policies again.
    keys = build_graph(load_reproduce_config("tiny")).keys
    assert {n: keys[n] for n in ("dataset", "bnn/d8", "bnn/report", "policy/latent/mixed/s0", "policy/raw/mixed/s0")} == {
        "dataset": "ef61ea451447", "bnn/d8": "a16aec1aea00", "bnn/report": "40c38c299ab5",
        "policy/latent/mixed/s0": "08d7c1464178", "policy/raw/mixed/s0": "94d4560f09e3"}


def test_a_bnn_model_section_reaches_the_bnn_steps_and_leaves_other_keys_alone() -> None:
    plain = build_graph(load_reproduce_config("tiny"))
    # An empty model section is the behaviour before the section existed: out of the keys.
    assert "model" not in keyed_config(plain.steps["bnn/d8"].config)
    assert "model" not in keyed_config(plain.steps["bnn/report"].config)["study"]
    paper = build_graph(load_reproduce_config("tiny", {"bnn": {"model": {"head_hidden": 0, "latent_norm": False}}}))
    assert paper.steps["bnn/d8"].config["model"] == {"head_hidden": 0, "latent_norm": False}
    assert paper.keys["dataset"] == plain.keys["dataset"]
    assert paper.keys["bnn/d8"] != plain.keys["bnn/d8"]
    assert paper.keys["policy/raw/mixed/s0"] == plain.keys["policy/raw/mixed/s0"]
    assert paper.keys["policy/latent/mixed/s0"] != plain.keys["policy/latent/mixed/s0"]


def test_a_later_setting_stays_out_of_keys_at_its_old_behaviour_only() -> None:
    plain = build_graph(load_reproduce_config("tiny"))
    name = "policy/raw/mixed/s0"
    assert plain.steps[name].config["train"]["reward"]["failure"] == 0.0
    assert "failure" not in keyed_config(plain.steps[name].config)["train"]["reward"]
    paid = build_graph(load_reproduce_config("tiny", {"reward": {"failure": -1.0}}))
    assert paid.keys[name] != plain.keys[name] and paid.keys["dataset"] == plain.keys["dataset"]
    # Only the end of a path matches, and only at the listed value.
    assert keyed_config({"a": {"reward": {"failure": 0.0, "x": 1}}, "failure": 0.0}) == {
        "a": {"reward": {"x": 1}}, "failure": 0.0}
    # A value of another type is not the old behaviour, even where Python calls it equal.
    assert keyed_config({"train": {"val_samples": False}}) == {"train": {"val_samples": False}}


@pytest.mark.parametrize(("model", "names"), [({"latent_dim": 8}, "latent_dim: set by the study"),
                                               ({"head_hiden": 0}, "head_hiden"),
                                               ({"head_hidden": -1}, "head_hidden")])
def test_a_bad_bnn_model_section_is_refused(model: dict[str, object], names: str) -> None:
    with pytest.raises(ConfigError, match=names):
        load_reproduce_config("tiny", {"bnn": {"model": model}})


def test_bnn_step_costs_follow_the_capped_epochs_and_the_scored_samples() -> None:
    g = build_graph(load_reproduce_config("quick"))
    # 600 episodes × 5 scenarios × 40 samples, 85% trained on: 102,000 samples, but epochs
    # capped at 250 steps of 16 (4,000 samples), 8 epochs at 80 samples/s.
    assert g.steps["bnn/d64"].cost == pytest.approx(8 * 4000 / 80)
    # 2,048 samples scored by 3 runs and the noisy input at 100 samples/s, after 30 s.
    assert g.steps["bnn/report"].cost == pytest.approx(30 + 4 * 2048 / 100)
    uncapped = build_graph(load_reproduce_config("quick", {"bnn": {"score_samples": 0, "train": {"epoch_steps": 0}}}))
    assert uncapped.steps["bnn/d64"].cost == pytest.approx(8 * 102_000 / 80)
    assert uncapped.steps["bnn/report"].cost == pytest.approx(30 + 4 * 18_000 / 100)
    # The cap is left out of the key at 0, so studies reported before it keep their keys.
    assert "score_samples" not in keyed_config(uncapped.steps["bnn/report"].config)["study"]


def test_policies_pinned_to_the_cpu_ask_a_scheduler_for_no_gpu() -> None:
    def wants(overrides: dict[str, object]) -> dict[str, bool]:
        graph = build_graph(load_reproduce_config("tiny", overrides))
        return {s.kind: STEP_KINDS[s.kind].wants_gpu(s) for s in graph.steps.values()}

    default = wants({})
    assert default["policy"] and default["bnn"] and not default["evaluate"] and not default["dataset"]
    pinned = wants({"policy": {"train": {"device": "cpu"}}})
    assert not pinned["policy"] and pinned["bnn"]


def test_settings_of_one_kind_reach_its_policies_only() -> None:
    plain = build_graph(load_reproduce_config("tiny"))
    objects = build_graph(load_reproduce_config("tiny", {"policy": {
        "train": {"dqn": {"lr": 3e-4}}, "by_kind": {"raw": {"vfan": {"reader": "objects"}, "dqn": {"n_step": 2}}}}}))
    raw = [n for n in objects.steps if n.startswith("policy/raw/")]
    assert len(raw) == 8  # 3 oracles, the mix, 3 leave-one-out and the fine-tuned one
    for name in raw:
        train = objects.steps[name].config["train"]
        # Merged over train: the kind's own settings and train's learner settings both hold.
        assert train["vfan"]["reader"] == "objects" and train["dqn"]["n_step"] == 2 and train["dqn"]["lr"] == 3e-4
    ft = objects.steps["policy/raw/roundabout-finetuned/s0"].config["train"]
    assert ft["dqn"]["eps_start"] == 0.2 and ft["dqn"]["n_step"] == 2  # fine-tuning still applies on top
    for name, step in objects.steps.items():
        if step.kind == "policy" and not name.startswith("policy/raw/"):
            assert step.config["train"]["vfan"]["reader"] == "conv" and step.config["train"]["dqn"]["n_step"] == 1
            assert step.config["train"]["dqn"]["lr"] == 3e-4
    # An empty entry is no change: the keys stay those of the study without it.
    empty = build_graph(load_reproduce_config("tiny", {"policy": {"by_kind": {"raw": {}}}}))
    assert empty.keys == plain.keys


def test_the_standard_preset_holds_every_experiment_for_three_seeds_with_one_learner() -> None:
    g = build_graph(load_reproduce_config("standard"))
    policies = {n: s.config["train"] for n, s in g.steps.items() if s.kind == "policy"}
    # Per seed: 12 policies of each of raw and latent (5 oracles, the mix, 5 leave-one-out,
    # the fine-tuned one) and 3 ablations.
    assert len(policies) == 3 * (2 * 12 + 3)
    def learner(train: dict) -> tuple:
        # End-to-end keeps the default replay ratio (its encoder's backward pass is the cost);
        # otherwise one learner for every kind.
        return {**train["dqn"], "updates_per_transition": None}, train["reward"], train["precision"]

    learners = [learner(t) for n, t in policies.items() if "finetuned" not in n]
    assert all(x == learners[0] for x in learners)
    assert {t["dqn"]["updates_per_transition"] for n, t in policies.items()
            if n.startswith("policy/end-to-end/")} == {0.125}
    dqn, reward, _ = learners[0]
    assert (dqn["lr"], dqn["gamma"], dqn["target_update"], dqn["n_step"]) == (3.5e-4, 0.92, 485, 2)
    assert {t["dqn"]["updates_per_transition"] for n, t in policies.items()
            if not n.startswith("policy/end-to-end/")} == {1.0}
    assert (reward["speed"], reward["failure"]) == (0.0625, -0.324)
    # Fine-tuning evaluates as often as training from scratch does, so its curve has points.
    ft = policies["policy/raw/roundabout-finetuned/s0"]
    assert ft["steps"] // ft["segment"] >= 4 and ft["dqn"]["eps_start"] == 0.2
    assert {t["vfan"]["reader"] for n, t in policies.items() if n.startswith("policy/raw/")} == {"objects"}
    assert {t["vfan"]["reader"] for n, t in policies.items() if not n.startswith("policy/raw/")} == {"conv"}
    assert {t["steps"] for n, t in policies.items() if "finetuned" not in n} == {100_000}
    assert {s.config["eval"]["episodes"] for s in g.steps.values() if s.kind == "evaluate" and "cross/" not in s.name} == {200}
