"""train-policy and evaluate: bad input is one line, exit 2, and nothing written."""

import json
import shutil

import pytest

from latentdrive.bnn.checkpoint import save_checkpoint
from latentdrive.cli import main
from latentdrive.config import ConfigError, ObservationConfig, validate
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import encoder_config
from latentdrive.rl.train import train_policy
from latentdrive.runlock import LOCK_NAME

from .conftest import TINY

TINY_SETS = [
    "--set", "observation.height=16", "--set", "observation.width=32", "--set", "observation.frames=2",
    "--set", "vfan.hidden=32", "--set", "vfan.channels=[8,16,16]", "--set", "segment=100", "--set", "eval_every=0", "--set", "eval_episodes=4",
    "--set", "dqn.learning_starts=50", "--set", "dqn.buffer_size=1000", "--envs", "4",
]


def _snapshot(root):
    return {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _fails(capsys, args, needle, root):
    before = _snapshot(root)
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("latentdrive: error:") and needle in err[0], err
    assert _snapshot(root) == before  # nothing written or changed


@pytest.fixture(scope="module")
def raw_run(tmp_path_factory):
    from latentdrive.rl.config import PolicyTrainConfig

    root = tmp_path_factory.mktemp("runs")
    cfg = PolicyTrainConfig.model_validate({**TINY, "mode": "raw", "steps": 100})
    train_policy(cfg, root / "raw", progress=False, say=lambda _l: None)
    return root / "raw"


def _bnn_run(path, obs_shape, observation=None):
    path.mkdir(parents=True)
    cfg = BottleneckConfig(input_shape=obs_shape, latent_dim=8, channels=(4,))
    config = {"model": cfg.model_dump(mode="json")}
    if observation is not None:
        config["observation"] = observation
    save_checkpoint(path / "checkpoint.safetensors", BottleneckNetwork(cfg), step=0, epoch=0, config=config)
    return path


#: The observation TINY_SETS configures, as a BNN run records it.
TINY_OBSERVATION = ObservationConfig(height=16, width=32, frames=2).model_dump(mode="json")


def test_latent_mode_needs_a_bnn(tmp_path, capsys):
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "latent", *TINY_SETS], "needs a trained BNN", tmp_path)
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "latent", "--bnn", str(tmp_path / "none"), *TINY_SETS],
           "no BNN checkpoint", tmp_path)
    assert not (tmp_path / "r").exists()


def test_a_bnn_of_another_observation_shape_is_refused(tmp_path, capsys):
    bnn = _bnn_run(tmp_path / "bnn", (4, 32, 64))  # the default grid, not the tiny one
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "latent", "--bnn", str(bnn), *TINY_SETS],
           "the BNN takes observations (4, 4, 32, 64) but the env gives (4, 2, 16, 32)", tmp_path)


def test_a_bnn_whose_maps_were_drawn_otherwise_is_refused(tmp_path, capsys):
    # The same shape with other content: the route drawn in the MV channel, which the
    # frozen code never saw. The error names the field.
    bnn = _bnn_run(tmp_path / "bnn", (2, 16, 32), TINY_OBSERVATION)
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "latent", "--bnn", str(bnn), *TINY_SETS,
                    "--steps", "10", "--set", "observation.route=1.0"], "observation.route (0.0 → 1.0)",
           tmp_path)
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "latent", "--bnn", str(bnn), *TINY_SETS,
                    "--steps", "10", "--set", "observation.beta=0.5"], "observation.beta (0.3 → 0.5)",
           tmp_path)


def test_a_bnn_of_the_same_maps_is_accepted_whatever_the_noise(tmp_path):
    bnn = _bnn_run(tmp_path / "bnn", (2, 16, 32), TINY_OBSERVATION)
    obs = {**TINY_OBSERVATION, "noise": {**TINY_OBSERVATION["noise"], "position_std": 2.0}}
    cfg = validate(PolicyTrainConfig, {"mode": "latent", "bnn": str(bnn), "observation": obs})
    enc = encoder_config(cfg)
    assert enc is not None and enc.observation_shape == (4, 2, 16, 32)
    # A BNN run that predates the record is checked by shape alone.
    old = _bnn_run(tmp_path / "old", (2, 16, 32))
    routed = validate(PolicyTrainConfig, {"mode": "latent", "bnn": str(old), "observation": {**obs, "route": 1.0}})
    enc = encoder_config(routed)
    assert enc is not None and enc.observation_shape == (4, 2, 16, 32)
    # A field this version does not know (a later one's) is left out of the comparison.
    newer = _bnn_run(tmp_path / "newer", (2, 16, 32), {**TINY_OBSERVATION, "lidar": True})
    enc = encoder_config(validate(PolicyTrainConfig, {"mode": "latent", "bnn": str(newer), "observation": obs}))
    assert enc is not None
    # A record with a field outside the schema still refuses what differs.
    bad = _bnn_run(tmp_path / "bad", (2, 16, 32), {**TINY_OBSERVATION, "alpha": -1})
    with pytest.raises(ConfigError, match=r"observation\.alpha \(-1 → 0\.5\)"):
        encoder_config(validate(PolicyTrainConfig, {"mode": "latent", "bnn": str(bad), "observation": obs}))


def test_unknown_scenarios_are_refused(tmp_path, capsys, raw_run):
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "raw", "--scenarios", "merge,lake", *TINY_SETS],
           "unknown scenario 'lake'", tmp_path)
    _fails(capsys, ["evaluate", str(raw_run), "--scenarios", "lake", "--episodes", "2"], "unknown scenario 'lake'", tmp_path)


def test_evaluating_a_run_without_checkpoint(tmp_path, capsys, raw_run):
    _fails(capsys, ["evaluate", str(tmp_path), "--episodes", "2"], "not a policy run", tmp_path)
    half = tmp_path / "half"
    half.mkdir()
    shutil.copy(raw_run / "config.json", half / "config.json")
    _fails(capsys, ["evaluate", str(half), "--episodes", "2", "--policy", "none"], "no checkpoint yet", tmp_path)


def test_a_checkpoint_of_another_mode_is_refused(tmp_path, capsys, raw_run):
    other = tmp_path / "other"
    shutil.copytree(raw_run, other)
    cfg = json.loads((other / "config.json").read_text())
    cfg["train"]["mode"] = "latent-random"
    cfg["encoder"] = BottleneckConfig(input_shape=(2, 16, 32)).model_dump(mode="json")
    (other / "config.json").write_text(json.dumps(cfg))
    _fails(capsys, ["evaluate", str(other), "--episodes", "2", "--policy", "none"], "architecture differs", tmp_path)
    # Resuming with another mode or another architecture is refused before anything runs.
    _fails(capsys, ["train-policy", str(raw_run.parent / "raw"), "--resume", "--mode", "end-to-end"],
           "mode", raw_run.parent)
    _fails(capsys, ["train-policy", str(raw_run), "--resume", "--set", "vfan.hidden=64"], "vfan", raw_run.parent)


def test_a_corrupt_checkpoint_is_refused(tmp_path, capsys, raw_run):
    bad = tmp_path / "bad"
    shutil.copytree(raw_run, bad)
    data = bytearray((bad / "checkpoint.safetensors").read_bytes())
    data[-10:] = b"\x00" * 10
    (bad / "checkpoint.safetensors").write_bytes(bytes(data))
    _fails(capsys, ["evaluate", str(bad), "--episodes", "2", "--policy", "none"], "corrupt checkpoint", tmp_path)


@pytest.mark.parametrize(("name", "content", "needle"), [
    ("eval.csv", bytes(range(256)) * 4, "eval.csv: evaluation log is not UTF-8"),
    ("metrics.csv", bytes(range(256)) * 4, "metrics.csv: training log is not UTF-8"),
    ("metrics.csv", b"step,loss\n1,2\n", "metrics.csv: not a training log"),
    ("eval.csv", b"transitions,scenario\n100,merge,extra\n", "eval.csv: line 2 of the evaluation log has 3 fields"),
    ("metrics.csv", b"transitions,updates\nabc,1\n", "has transitions 'abc', not a count"),
])
def test_resuming_with_a_damaged_log_changes_nothing(tmp_path, capsys, raw_run, name, content, needle):
    run = tmp_path / "run"
    shutil.copytree(raw_run, run)
    (run / name).write_bytes(content)
    _fails(capsys, ["train-policy", str(run), "--resume", "-q"], needle, tmp_path)
    _fails(capsys, ["train-policy", str(run), "--resume", "--steps", "200", "-q"], needle, tmp_path)


def test_resuming_with_a_huge_log_does_not_read_it(tmp_path, capsys, raw_run):
    run = tmp_path / "run"
    shutil.copytree(raw_run, run)
    with (run / "metrics.csv").open("wb") as f:  # sparse: takes no room
        f.truncate((256 << 20) + 1)

    def stats():  # not the bytes: holding them would take the memory the bound saves; the lock is retaken
        return {p: (p.stat().st_ino, p.stat().st_size, p.stat().st_mtime_ns) for p in run.rglob("*") if p.name != LOCK_NAME}

    before = stats()
    assert main(["train-policy", str(run), "--resume", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "metrics.csv: training log is larger than 256 MiB" in err[0], err
    assert stats() == before


def test_evaluate_writes_json_and_compares(tmp_path, capsys, raw_run):
    out = tmp_path / "e.json"
    assert main(["evaluate", str(raw_run), "--compare", str(raw_run), "--episodes", "4", "--envs", "2",
                 "--policy", "stop", "--json", str(out), "-q"]) == 0
    doc = json.loads(out.read_text())
    s = doc["scenarios"]["intersection"]
    assert {"crash_rate", "failure_rate", "success_rate", "episodes"} <= s.keys() and s["episodes"] == 4
    assert doc["policies"]["stop"]["mixed"]["crash_rate"]["n"] == 4
    # A run compared with itself: no discordant pairs, p = 1.
    assert doc["compare"]["tests"]["mixed"]["failed"]["p_value"] == 1.0
    assert doc["config"]["evaluation"]["reset_seed"] >= 2**30
    assert "causes" not in doc


def test_evaluate_causes_table_and_json(tmp_path, capsys, raw_run):
    out = tmp_path / "e.json"
    assert main(["evaluate", str(raw_run), "--episodes", "4", "--envs", "2", "--policy", "stop",
                 "--causes", "--json", str(out), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "how the episodes ended" in printed
    stop = json.loads(out.read_text())["causes"]["stop"]["intersection"]
    # Always braking never crashes here and never arrives: every episode is a time-out.
    assert stop == {"episodes": 4, "success": 0, "time-out": 4}
    assert any(line.split()[:4] == ["stop", "intersection", "4", "0.0"] for line in printed.splitlines())


def test_init_from_fine_tunes_the_same_architecture_only(tmp_path, capsys, raw_run):
    _fails(capsys, ["train-policy", str(tmp_path / "ft"), "--mode", "latent-random", "--init-from", str(raw_run),
                    *TINY_SETS], "cannot initialize", tmp_path)
    _fails(capsys, ["train-policy", str(tmp_path / "ft"), "--mode", "raw", "--init-from", str(raw_run),
                    *TINY_SETS, "--set", "vfan.hidden=16"], "architecture differs", tmp_path)
    assert not (tmp_path / "ft").exists()
    assert main(["train-policy", str(tmp_path / "ft"), "--mode", "raw", "--init-from", str(raw_run), "--steps", "60",
                 *TINY_SETS, "-q"]) == 0
    assert json.loads((tmp_path / "ft" / "config.json").read_text())["train"]["init_from"] == str(raw_run)


def test_compare_with_a_reference_policy(tmp_path, capsys, raw_run):
    out = tmp_path / "c.json"
    assert main(["evaluate", str(raw_run), "--compare", "stop", "--policy", "none", "--episodes", "4", "--envs", "2",
                 "--json", str(out), "-q"]) == 0
    doc = json.loads(out.read_text())
    assert doc["compare"]["b"] == "stop" and set(doc["policies"]) == {str(raw_run), "stop"}
    # Always-Decelerate fails every episode: the comparison's B rate says so.
    assert doc["compare"]["tests"]["mixed"]["failed"]["rate_b"] == 1.0


def test_compare_pairs_stored_evaluations_as_evaluate_compare_does(tmp_path, capsys, raw_run):
    both, run_only, stop_only = tmp_path / "both.json", tmp_path / "run.json", tmp_path / "stop.json"
    common = ["--episodes", "4", "--envs", "2", "-q"]
    assert main(["evaluate", str(raw_run), "--compare", "stop", "--policy", "none", "--json", str(both), *common]) == 0
    assert main(["evaluate", str(raw_run), "--policy", "none", "--json", str(run_only), *common]) == 0
    assert main(["evaluate", "--policy", "stop", "--scenarios", "intersection", "--json", str(stop_only), *common]) == 0
    online = json.loads(both.read_text())["compare"]["tests"]
    capsys.readouterr()
    out = tmp_path / "pair.json"
    # Two files, each with one policy: the run's file against the reference's.
    assert main(["compare", str(run_only), str(stop_only), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"A = {raw_run} ({run_only}), B = stop ({stop_only})" in printed and "McNemar" in printed
    assert json.loads(out.read_text())["tests"] == online
    # One file, two of its policies.
    assert main(["compare", str(both), str(both), "--b", "stop", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["tests"] == online


def test_compare_refuses_files_of_other_episodes_in_one_line(tmp_path, capsys, raw_run):
    four, two = tmp_path / "four.json", tmp_path / "two.json"
    assert main(["evaluate", "--policy", "stop", "--scenarios", "intersection", "--episodes", "4", "--envs", "2",
                 "--json", str(four), "-q"]) == 0
    assert main(["evaluate", "--policy", "stop", "--scenarios", "intersection", "--episodes", "2", "--envs", "2",
                 "--json", str(two), "-q"]) == 0
    capsys.readouterr()
    _fails(capsys, ["compare", str(four), str(two), "--json", str(tmp_path / "p.json")],
           "different evaluation sets (episodes_per_scenario: 4 against 2)", tmp_path)
    _fails(capsys, ["compare", str(four), str(four), "--b", "rule"], "no per-episode outcomes of policy 'rule'", tmp_path)
    _fails(capsys, ["compare", str(four), str(four)], "'stop' against itself", tmp_path)
    _fails(capsys, ["compare", str(four), str(two), "--json", str(two)], "is one of the files read", tmp_path)
    _fails(capsys, ["aggregate", str(four), "--json", str(four)], "is one of the files read", tmp_path)
    doc = json.loads(four.read_text())
    del doc["outcomes"]
    old = tmp_path / "old.json"
    old.write_text(json.dumps(doc))
    _fails(capsys, ["compare", str(old), str(four)], "holds no per-episode outcomes", tmp_path)
    _fails(capsys, ["compare", str(four), str(tmp_path / "absent.json")], "absent.json", tmp_path)


def test_compare_refuses_a_run_evaluated_on_its_own_version_of_a_spec(tmp_path, capsys, raw_run):
    run = tmp_path / "run"
    shutil.copytree(raw_run, run)
    cfg = json.loads((run / "config.json").read_text())
    cfg["train"]["specs"]["intersection"]["duration"] += 1.0  # the run stores another intersection than the preset
    (run / "config.json").write_text(json.dumps(cfg))
    ran, preset = tmp_path / "ran.json", tmp_path / "preset.json"
    common = ["--scenarios", "intersection", "--episodes", "2", "--envs", "2", "-q"]
    assert main(["evaluate", str(run), "--policy", "stop", "--json", str(ran), *common]) == 0
    assert main(["evaluate", "--policy", "stop", "--json", str(preset), *common]) == 0
    capsys.readouterr()
    _fails(capsys, ["compare", str(ran), str(preset)], "different scenario specs", tmp_path)
    # The references of the run's file met the run's version of the spec too.
    _fails(capsys, ["compare", str(ran), str(preset), "--a", "stop"], "different scenario specs", tmp_path)


def test_bad_evaluation_options_fail_before_any_work(tmp_path, capsys, raw_run):
    _fails(capsys, ["evaluate", str(raw_run), "--seed-offset", "-1", "--episodes", "2"], "offset", tmp_path)
    _fails(capsys, ["evaluate", str(raw_run), "--json", str(tmp_path), "--episodes", "2"], "--json", tmp_path)
    _fails(capsys, ["evaluate", "--scenarios", "merge,merge", "--episodes", "2"], "repeats", tmp_path)
    _fails(capsys, ["evaluate", "--policy", "rule", "--gif", str(tmp_path / "g.gif"), "--gif-episode", "-1"],
           "--gif-episode", tmp_path)
    # Past the evaluation's first environment's share: an episode the evaluation never played.
    _fails(capsys, ["evaluate", "--policy", "rule", "--episodes", "4", "--envs", "2", "--gif", str(tmp_path / "g.gif"),
                    "--gif-episode", "2"], "--gif-episode must be in [0, 2)", tmp_path)
    _fails(capsys, ["evaluate", "--policy", "rule", "--gif-episode", "1"], "--gif-episode needs --gif", tmp_path)
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "raw", "--scenarios", "merge,merge", *TINY_SETS],
           "repeat", tmp_path)


def test_resume_refuses_a_run_whose_scenario_spec_changed(tmp_path, capsys, raw_run):
    run = tmp_path / "old"
    shutil.copytree(raw_run, run)
    cfg = json.loads((run / "config.json").read_text())
    assert set(cfg["scenario_hashes"]) == {"intersection"}
    # As if trained on an earlier spec, by a version that stored only its hash.
    cfg["scenario_hashes"]["intersection"] = "0" * 16
    del cfg["train"]["specs"]
    (run / "config.json").write_text(json.dumps(cfg))
    _fails(capsys, ["train-policy", str(run), "--resume", "--steps", "200"], "scenario spec of intersection changed",
           tmp_path)


@pytest.mark.parametrize("args, needle", [
    (["--policy", "plan", "--set", "planner.depth=0"], "planner.depth"),
    (["--policy", "plan", "--backend", "highway"], "needs the fast backend"),
    (["--policy", "rule", "--set", "planner.depth=3"], "not evaluated"),
    (["--policy", "plan", "--set", "depth=3"], "planner.KEY=VALUE"),
])
def test_bad_planner_settings_are_one_line(capsys, tmp_path, args, needle):
    out = tmp_path / "out.json"
    _fails(capsys, ["evaluate", "--scenarios", "merge", "--episodes", "2", "--json", str(out), *args], needle, tmp_path)
    assert not out.exists()


def test_the_highway_backend_evaluates_every_reference_but_the_planner(capsys, tmp_path):
    out = tmp_path / "out.json"
    assert main(["evaluate", "--scenarios", "merge", "--episodes", "1", "--backend", "highway", "-q",
                 "--json", str(out)]) == 0
    assert sorted(json.loads(out.read_text())["policies"]) == ["idle", "random", "rule", "stop"]


def test_evaluating_a_run_whose_scenario_changed_warns(capsys, tmp_path, raw_run):
    run = tmp_path / "old"
    shutil.copytree(raw_run, run)
    cfg = json.loads((run / "config.json").read_text())
    scenario = cfg["train"]["scenarios"][0]
    cfg["scenario_hashes"][scenario] = "0" * 16
    # A run that stores its specs is evaluated on them: nothing to warn about.
    (run / "config.json").write_text(json.dumps(cfg))
    assert main(["evaluate", str(run), "--policy", "none", "--episodes", "1", "-q"]) == 0
    assert "as specified then" not in capsys.readouterr().err
    # One that predates stored specs is evaluated on today's, and says so.
    del cfg["train"]["specs"]
    (run / "config.json").write_text(json.dumps(cfg))
    assert main(["evaluate", str(run), "--policy", "none", "--episodes", "1", "-q"]) == 0
    assert f"trained on {scenario} as specified then" in capsys.readouterr().err


def test_latent_init_from_checks_the_bnn_by_its_weights_not_its_path(tmp_path, capsys):
    # Regression: the BNN was compared by path, so fine-tuning in a moved (or differently
    # mounted) study folder was refused although the weights were the same.
    import shutil

    import torch

    torch.manual_seed(0)
    bnn = _bnn_run(tmp_path / "bnn", (2, 16, 32))
    args = ["--mode", "latent", "--steps", "60", *TINY_SETS, "-q"]
    assert main(["train-policy", str(tmp_path / "src"), "--bnn", str(bnn), *args]) == 0
    moved = tmp_path / "moved-bnn"
    shutil.copytree(bnn, moved)
    assert main(["train-policy", str(tmp_path / "ft"), "--bnn", str(moved), "--init-from", str(tmp_path / "src"),
                 *args]) == 0
    torch.manual_seed(1)
    other = _bnn_run(tmp_path / "other", (2, 16, 32))
    capsys.readouterr()
    _fails(capsys, ["train-policy", str(tmp_path / "ft2"), "--bnn", str(other), "--init-from", str(tmp_path / "src"),
                    *args], "trained on another BNN", tmp_path)
    # Resuming in a moved study: the same weights at another path continue; others do not.
    longer = ["--mode", "latent", "--steps", "90", *TINY_SETS, "-q"]
    assert main(["train-policy", str(tmp_path / "src"), "--bnn", str(moved), "--resume", *longer]) == 0
    capsys.readouterr()
    _fails(capsys, ["train-policy", str(tmp_path / "src"), "--bnn", str(other), "--resume",
                    "--mode", "latent", "--steps", "120", *TINY_SETS, "-q"], "another BNN", tmp_path)


def test_a_moved_keep_best_latent_run_resumes_before_its_first_evaluation(tmp_path, monkeypatch):
    # Regression: resuming with another BNN path compared encoders through the policy's
    # weights, which a keep=best run has none of before its first evaluation.
    import shutil

    import torch

    from latentdrive.rl.learner import Learner

    torch.manual_seed(0)
    bnn = _bnn_run(tmp_path / "bnn", (2, 16, 32))
    args = ["--mode", "latent", "--steps", "250", *TINY_SETS, "--set", "eval_every=2", "--set", "keep=best", "-q"]
    save = Learner.save

    class Stop(Exception):
        pass

    def save_then_stop(self, run_dir, segment):
        save(self, run_dir, segment)
        raise Stop  # killed after the first checkpoint, before any evaluation

    with monkeypatch.context() as m:
        m.setattr(Learner, "save", save_then_stop)
        with pytest.raises(Stop):
            main(["train-policy", str(tmp_path / "run"), "--bnn", str(bnn), *args])
    moved = tmp_path / "moved-bnn"
    shutil.copytree(bnn, moved)
    assert main(["train-policy", str(tmp_path / "run"), "--bnn", str(moved), "--resume", *args]) == 0


def test_dagger_on_highway_env_is_one_line(tmp_path, capsys):
    _fails(capsys, ["train-policy", str(tmp_path / "r"), "--mode", "raw", "--learner", "dagger", "--backend", "highway",
                    *TINY_SETS], "learner 'dagger' needs backend 'fast'", tmp_path)


def test_train_policy_learner_dagger_trains_an_imitation_run(tmp_path, capsys):
    run = tmp_path / "imitation"
    assert main(["train-policy", str(run), "--mode", "raw", "--learner", "dagger", "--steps", "60", "-q",
                 "--scenarios", "intersection", "--set", "dqn.learning_starts=20", "--set", "imitation.planner.depth=3",
                 "--set", "imitation.planner.rounds=1", *TINY_SETS]) == 0
    assert json.loads((run / "config.json").read_text())["train"]["learner"] == "dagger"
    assert "done: " in capsys.readouterr().out


def test_runs_observing_different_maps_are_compared_on_the_same_episodes(tmp_path, capsys, raw_run, monkeypatch):
    # The same weights, once told to see the route (observation.route): each run is evaluated
    # with its own map, exactly as when it is evaluated alone.
    from latentdrive.experiments import policy as policy_module

    seen = []
    real = policy_module.evaluate_policy

    def spy(*args, **kw):
        seen.append(kw["observation"]["route"])
        return real(*args, **kw)

    monkeypatch.setattr(policy_module, "evaluate_policy", spy)
    routed = tmp_path / "routed"
    shutil.copytree(raw_run, routed)
    doc = json.loads((routed / "config.json").read_text())
    doc["train"]["observation"]["route"] = 0.5
    (routed / "config.json").write_text(json.dumps(doc))
    common = ["--episodes", "6", "--envs", "3", "--scenarios", "intersection,roundabout", "-q"]
    both, alone_a, alone_b = tmp_path / "both.json", tmp_path / "a.json", tmp_path / "b.json"
    assert main(["evaluate", str(raw_run), "--compare", str(routed), "--json", str(both), *common]) == 0
    assert "the runs observe different maps" in capsys.readouterr().err
    assert seen[:2] == [0.0, 0.5] and set(seen[2:]) <= {0.0}  # each run its own map; references the first's
    assert main(["evaluate", str(raw_run), "--json", str(alone_a), *common]) == 0
    assert main(["evaluate", str(routed), "--json", str(alone_b), *common]) == 0
    joint = json.loads(both.read_text())["policies"]
    assert joint[str(raw_run)] == json.loads(alone_a.read_text())["policies"][str(raw_run)]
    assert joint[str(routed)] == json.loads(alone_b.read_text())["policies"][str(routed)]
    assert json.loads(both.read_text())["compare"]["b"] == str(routed)
    # Labelled, each run still sees its own map (regression: the labelled run saw the first's).
    seen.clear()
    assert main(["evaluate", f"a={raw_run}", "--compare", f"b={routed}", "--policy", "none", *common]) == 0
    assert "b (" in capsys.readouterr().err and seen == [0.0, 0.5]


def test_the_actions_script_reports_the_runs_own_driving(raw_run, capsys):
    import runpy
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "actions.py"
    main_ = runpy.run_path(str(script), run_name="actions")["main"]
    assert main_([str(raw_run), "intersection", "--decisions", "30", "--envs", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    n = int(out[0].split(": ")[1].split()[0])
    assert n >= 30
    shares = [float(x) for x in out[1].split()[3::2]]
    assert len(shares) == 5 and abs(sum(shares) - 1.0) < 1e-3
    assert out[3].startswith("best - second  median ")


def test_the_gif_of_several_policies_plays_one_episode_under_each(tmp_path, capsys, raw_run):
    import imageio.v3 as iio

    from latentdrive.evaluate import gif
    from latentdrive.evaluate.policies import reference_policy
    from latentdrive.experiments.policy import EvaluationSet, play_episode

    out, doc = tmp_path / "side.gif", tmp_path / "e.json"
    assert main(["evaluate", str(raw_run), "--policy", "stop", "--scenarios", "intersection", "--episodes", "2",
                 "--envs", "1", "--gif", str(out), "--gif-episode", "1", "--json", str(doc), "-q"]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    frames = iio.imread(out, index=None)
    assert frames.shape[2] == round(2 * gif._PANEL_IN * gif._DPI)  # one panel per policy: the run and `stop`
    # The episode drawn is the evaluation's: the K-th its first environment played.
    outcomes = json.loads(doc.read_text())["outcomes"]
    rows = outcomes["policies"]["stop"]
    evaluated = {(r["env_index"], r["episode_index"]): r["seed"] for r in rows}
    eval_set = EvaluationSet(["intersection"], 2, 1, "fast", 0)
    for k in (0, 1):
        assert play_episode(reference_policy("stop"), "intersection", eval_set, episode=k).outcome.seed == evaluated[0, k]
    # Beside a run, the default references are not drawn: the run's own view (scene and map).
    assert main(["evaluate", str(raw_run), "--scenarios", "intersection", "--episodes", "1", "--envs", "1",
                 "--gif", str(tmp_path / "run.gif"), "-q"]) == 0
    assert iio.imread(tmp_path / "run.gif", index=None).shape[2] == round(gif._WIDTH_IN * gif._DPI)


def test_an_episodes_label_says_how_it_ended():
    import numpy as np

    from latentdrive.experiments.policy import outcome_label
    from latentdrive.outcome import EpisodeOutcome

    def ended(crashed, arrived, traffic=False):
        return EpisodeOutcome("merge", 0, 0, 1, 10, np.array(crashed), np.array(arrived), np.zeros(2), 5.0, traffic)

    assert outcome_label(ended([True, False], [False, True])) == "failed: 1 of 2 AVs crashed"
    assert outcome_label(ended([False, False], [True, False])) == "failed: time ran out (1 of 2 AVs arrived)"
    assert outcome_label(ended([False, False], [True, True])) == "success: all 2 AVs arrived"
    assert outcome_label(ended([False, False], [False, False], True)) == (
        "failed: time ran out (0 of 2 AVs arrived, HVs crashed among themselves)")


def test_evaluate_names_runs_by_their_labels(tmp_path, capsys, raw_run, monkeypatch):
    from latentdrive.experiments import policy

    out = tmp_path / "e.json"
    drawn: list[list[str]] = []
    monkeypatch.setattr(policy, "save_policies_gif", lambda path, makers, *a: drawn.append(list(makers)) or path)
    common = ["--scenarios", "intersection", "--episodes", "2", "--envs", "2", "-q"]
    assert main(["evaluate", f"mine={raw_run}", "--compare", "stop", "--policy", "none", "--json", str(out),
                 "--gif", str(tmp_path / "g.gif"), *common]) == 0
    printed = capsys.readouterr().out
    assert "paired on the same episodes: A = mine, B = stop" in printed
    assert any(line.split()[:2] == ["mine", "intersection"] for line in printed.splitlines())
    doc = json.loads(out.read_text())
    assert doc["policy"] == "mine" and set(doc["policies"]) == {"mine", "stop"}
    assert doc["compare"]["a"] == "mine" and doc["config"]["paths"] == {"mine": str(raw_run)}
    assert set(doc["config"]["runs"]) == {"mine"} and set(doc["outcomes"]["policies"]) == {"mine", "stop"}
    assert drawn == [["mine", "stop"]]  # the GIF's panels are titled by the same names
    # Without labels nothing changes: runs are named by their paths.
    assert main(["evaluate", str(raw_run), "--policy", "none", "--json", str(out), *common]) == 0
    doc = json.loads(out.read_text())
    assert set(doc["policies"]) == {str(raw_run)} and "paths" not in doc["config"]
    # A label that names a reference, or the run itself under a second label, is refused.
    _fails(capsys, ["evaluate", f"stop={raw_run}", "--policy", "stop", *common], "'stop' is a reference policy's name",
           tmp_path)
    _fails(capsys, ["evaluate", f"a={raw_run}", "--compare", f"b={raw_run}", *common], "the RUN itself, under another "
           "label", tmp_path)
    _fails(capsys, ["evaluate", f"={raw_run}", *common], "an empty label before '='", tmp_path)
    # Refused whether or not that reference is evaluated; only runs take a label.
    _fails(capsys, ["evaluate", f"rule={raw_run}", "--policy", "none", *common], "'rule' is a reference policy's name",
           tmp_path)
    _fails(capsys, ["evaluate", str(raw_run), "--compare", "x=stop", *common], "x=stop: neither a run folder nor "
           "LABEL=RUN", tmp_path)
    _fails(capsys, ["evaluate", "x=", *common], "(no folder '')", tmp_path)
    # The same folder written another way is the same run.
    assert main(["evaluate", f"a={raw_run}", "--compare", f"{raw_run}/.", "--policy", "none", "--json", str(out),
                 *common]) == 0
    doc = json.loads(out.read_text())
    assert doc["compare"]["b"] == "a" and doc["compare"]["tests"]["mixed"]["failed"]["p_value"] == 1.0
    _fails(capsys, ["evaluate", f"a={raw_run}", "--compare", f"b={raw_run}/.", *common], "the RUN itself, under "
           "another label", tmp_path)
    other = tmp_path / "x=y"
    shutil.copytree(raw_run, other)  # a folder with '=' in its name is a run, not LABEL=RUN
    assert main(["evaluate", str(other), "--policy", "none", "--json", str(out), *common]) == 0
    assert json.loads(out.read_text())["policy"] == str(other)
    _fails(capsys, ["evaluate", f"a={raw_run}", "--compare", f"a={other}", *common], "go by one name, 'a'", tmp_path)
