"""``latentdrive tune``: the search resumes, refuses bad spaces and foreign storage, and its
best.yaml trains."""

import sqlite3
from pathlib import Path
from typing import Any

import pytest
import yaml

from latentdrive.cli import main
from latentdrive.config import ConfigError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: A trial of a few seconds: 200 agent-transitions on small maps, two 2-episode evaluations.
TINY_BASE: dict[str, Any] = {
    "scenarios": ["intersection"], "envs": 4, "segment": 100, "eval_every": 1, "eval_episodes": 2,
    "observation": {"height": 16, "width": 32, "frames": 2},
    "vfan": {"hidden": 32, "channels": [8, 16, 16]},
    "dqn": {"learning_starts": 50, "buffer_size": 1000, "batch_size": 16, "train_every": 4},
}
TINY_SPACE: dict[str, Any] = {
    "dqn.lr": {"type": "float", "low": 1e-4, "high": 3e-3, "log": True},
    "dqn.target_update": {"type": "int", "low": 10, "high": 100, "log": True},
    "dqn.double": {"type": "categorical", "choices": [True, False]},
}


def _space_file(tmp_path: Path, space: dict[str, Any] | None = None, base: dict[str, Any] | None = None) -> Path:
    path = tmp_path / "space.yaml"
    path.write_text(yaml.safe_dump({"base": TINY_BASE if base is None else base,
                                    "space": TINY_SPACE if space is None else space}))
    return path


def _tune(tmp_path: Path, out: Path, *extra: str, space: Path | None = None) -> int:
    return main(["tune", str(out), "--space", str(space or _space_file(tmp_path)), "--steps", "200", "--seeds", "1",
                 "-q", *extra])


def _error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("latentdrive: error: "), err
    return err[0]


def _trials(out: Path) -> list[Any]:
    import optuna

    return optuna.load_study(study_name="latentdrive-tune", storage=f"sqlite:///{out / 'study.db'}").get_trials()


def test_an_interrupted_search_resumes_to_n_trials_keeping_the_first(tmp_path, monkeypatch):
    from latentdrive.experiments import tune, tune_report

    monkeypatch.setattr(tune_report, "_plots", lambda *a: [])  # drawn in test_best_yaml_...; seconds each

    out = tmp_path / "out"
    real = tune.train_policy
    calls = {"n": 0}

    def interrupted_in_the_second_trial(cfg, run, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            on_eval = kw["on_eval"]

            def stop(transitions: int, rate: float) -> None:
                on_eval(transitions, rate)
                raise KeyboardInterrupt  # Ctrl-C after the second trial's first checkpoint

            kw = {**kw, "on_eval": stop}
        return real(cfg, run, **kw)

    monkeypatch.setattr(tune, "train_policy", interrupted_in_the_second_trial)
    assert _tune(tmp_path, out, "--trials", "2") == 130  # the command line's exit on Ctrl-C
    first, second = _trials(out)
    assert first.state.name == "COMPLETE" and second.state.name == "FAIL"
    assert (out / "trials" / "0001" / "seed-0" / "checkpoint.safetensors").exists()

    monkeypatch.setattr(tune, "train_policy", real)
    assert _tune(tmp_path, out, "--trials", "2") == 0
    trials = _trials(out)
    assert [t.state.name for t in trials] == ["COMPLETE", "FAIL", "COMPLETE"]
    kept, _, retry = trials
    # The first trial is kept as it was; the interrupted one is retried with its settings,
    # in its own folder, resuming its run from the checkpoint (its log keeps the first rows).
    assert (kept.number, kept.params, kept.value, kept.datetime_start) == \
        (first.number, first.params, first.value, first.datetime_start)
    assert retry.params == second.params and retry.system_attrs["failed_trial"] == 1
    assert retry.user_attrs["run"] == "0001" and not (out / "trials" / "0002").exists()
    assert 0.0 <= retry.value <= 1.0
    report = (out / "tune.md").read_text()
    assert "Trials: 2 of 2" in report and "retry of 1" in report
    # Nothing left to do: a third run changes nothing.
    assert _tune(tmp_path, out, "--trials", "2") == 0
    assert len(_trials(out)) == 3


def test_a_trial_left_running_by_a_killed_search_is_failed_and_retried(tmp_path):
    import optuna

    from latentdrive.experiments.tune import Search, open_study, run_search
    from latentdrive.experiments.tune_space import TuneSpace, base_config, check_space

    space = TuneSpace.model_validate({"base": TINY_BASE, "space": TINY_SPACE})
    base = base_config(space, 200, {})
    check_space(space, base)
    search = Search(out=tmp_path / "out", space=space, base=base, seeds=1, trials=1, prune=False)
    study = open_study(search)
    killed = study.ask({"dqn.double": optuna.distributions.CategoricalDistribution([True, False])})
    killed.suggest_categorical("dqn.double", [True, False])  # running, as a killed process leaves it
    run_search(search, progress=False, say=lambda _line: None)
    trials = study.get_trials()
    assert [t.state.name for t in trials] == ["FAIL", "COMPLETE"]
    assert trials[1].params["dqn.double"] == trials[0].params["dqn.double"]


@pytest.mark.parametrize("space, needle", [
    ({"dqn.lrr": {"type": "float", "low": 1e-4, "high": 1e-3}}, "space: dqn.lrr: dqn has no setting 'lrr'"),
    ({"dqn": {"type": "categorical", "choices": [1]}}, "space: dqn: a section"),
    ({"dqn.gamma": {"type": "float", "low": 0.9, "high": 1.5}}, "space: dqn.gamma: value 1.5"),
    ({"dqn.gamma": {"type": "float", "low": 0.9, "high": 0.99}}, "space: dqn.gamma: value 0.99: reward.mission"),
    ({"dqn.batch_size": {"type": "float", "low": 16, "high": 64}}, "space: dqn.batch_size: a float distribution"),
    ({"dqn.lr": {"type": "float", "low": 1e-3, "high": 1e-4}}, "space.dqn.lr.float: low"),
    ({"dqn.lr": {"type": "normal", "low": 1e-3, "high": 1e-4}}, "space.dqn.lr"),
    ({"seed": {"type": "int", "low": 0, "high": 3}}, "space: seed: set by the search itself"),
    ({}, "space: "),
])
def test_a_bad_space_is_one_line_naming_the_key(tmp_path, capsys, space, needle):
    out = tmp_path / "out"
    assert _tune(tmp_path, out, "--trials", "1", space=_space_file(tmp_path, space)) == 2
    assert needle in _error(capsys)
    assert not out.exists()


def test_bad_base_settings_are_refused(tmp_path, capsys):
    assert _tune(tmp_path, tmp_path / "out", "--set", "eval_seeds=evaluation") == 2
    assert "eval_seeds is set by the search itself" in _error(capsys)
    assert _tune(tmp_path, tmp_path / "out", "--set", "dqn.nope=1") == 2
    assert "dqn.nope: unknown key" in _error(capsys)


@pytest.mark.parametrize("preset, steps", [("raw", 50_000), ("raw-short", 25_000)])
def test_the_space_presets_are_valid_spaces(preset, steps):
    from latentdrive.experiments.tune_space import (
        CategoricalDist,
        base_config,
        check_space,
        load_space,
    )

    space = load_space(preset)
    base = base_config(space, None, {})
    check_space(space, base)
    assert base.mode == "raw" and len(base.scenarios) == 5 and base.eval_seeds == "validation"
    assert base.steps == steps
    if preset == "raw-short":  # the replay ratios a 2-core CPU runs in minutes
        ratio = space.space["dqn.updates_per_transition"]
        assert isinstance(ratio, CategoricalDist) and max(ratio.choices) == 0.5  # type: ignore[type-var]
    with pytest.raises(ConfigError, match="unknown preset"):
        load_space("nope")


@pytest.mark.parametrize("content, needle", [
    (b"this is not a database at all, just some bytes" * 20, "not an optuna study database"),
    (None, "an SQLite file with other tables"),
])
def test_a_foreign_storage_is_refused_and_left_alone(tmp_path, capsys, content, needle):
    out = tmp_path / "out"
    out.mkdir()
    db = out / "study.db"
    if content is None:
        with sqlite3.connect(db) as con:
            con.execute("CREATE TABLE mine (x INTEGER)")
        con.close()
    else:
        db.write_bytes(content)
    before = db.read_bytes()
    assert _tune(tmp_path, out, "--trials", "1") == 2
    assert needle in _error(capsys)
    assert db.read_bytes() == before


def test_a_study_of_another_search_is_refused(tmp_path, capsys):
    import optuna

    out = tmp_path / "out"
    out.mkdir()
    url = f"sqlite:///{out / 'study.db'}"
    optuna.create_study(study_name="someone-else", storage=url)
    assert _tune(tmp_path, out, "--trials", "1") == 2
    assert "without a latentdrive search" in _error(capsys)

    # A latentdrive study made under another space: its hash differs.
    other = tmp_path / "other"
    from latentdrive.experiments.tune import Search, open_study
    from latentdrive.experiments.tune_space import TuneSpace, base_config

    space = TuneSpace.model_validate({"base": TINY_BASE, "space": {"dqn.lr": TINY_SPACE["dqn.lr"]}})
    open_study(Search(out=other, space=space, base=base_config(space, 200, {}), seeds=1, trials=1))
    assert _tune(tmp_path, other, "--trials", "1") == 2
    assert "made by another search" in _error(capsys)
    # The same space with another budget is another search too.
    assert main(["tune", str(other), "--space", str(_space_file(tmp_path, {"dqn.lr": TINY_SPACE["dqn.lr"]})),
                 "--steps", "300", "--seeds", "1", "-q"]) == 2
    assert "made by another search" in _error(capsys)


def test_best_yaml_trains_with_train_policy(tmp_path, capsys):
    out = tmp_path / "out"
    assert _tune(tmp_path, out, "--trials", "1", "--no-prune") == 0
    best = yaml.safe_load((out / "best.yaml").read_text())
    trial, = _trials(out)
    assert best["dqn"]["lr"] == trial.params["dqn.lr"] and best["dqn"]["double"] == trial.params["dqn.double"]
    assert "seed" not in best and "eval_seeds" not in best
    import json

    # The trial's own run evaluated on validation episodes.
    assert json.loads((out / "trials" / "0000" / "seed-0" / "config.json").read_text())["train"]["eval_seeds"] == "validation"
    run = tmp_path / "run"
    assert main(["train-policy", str(run), "--config", str(out / "best.yaml"), "--steps", "100", "--seed", "3",
                 "-q"]) == 0
    saved = json.loads((run / "config.json").read_text())["train"]
    assert saved["dqn"]["target_update"] == trial.params["dqn.target_update"]
    assert saved["seed"] == 3 and saved["steps"] == 100 and saved["eval_seeds"] == "evaluation"
    assert "Not computed: needs at least 3 completed trials (have 1)" in (out / "tune.md").read_text()
    assert (out / "figures" / "history.png").exists()
    # --report-only rewrites the report from the trials so far and runs none, even with a
    # larger --trials; a folder without a search is a one-line error and gets no study.db.
    (out / "tune.md").unlink()
    assert _tune(tmp_path, out, "--trials", "5", "--no-prune", "--report-only") == 0
    assert len(_trials(out)) == 1 and "Not computed" in (out / "tune.md").read_text()
    capsys.readouterr()
    assert _tune(tmp_path, tmp_path / "empty", "--report-only") == 2
    assert "no search here to report on" in _error(capsys) and not (tmp_path / "empty" / "study.db").exists()


def test_train_policy_refuses_a_bad_config_file(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("dqn: {lr: -1}\n")
    assert main(["train-policy", str(tmp_path / "run"), "--config", str(bad), "--mode", "raw", "-q"]) == 2
    message = _error(capsys)
    assert "dqn.lr" in message and str(bad) in message  # names the file the setting may come from
    assert main(["train-policy", str(tmp_path / "run"), "--config", str(tmp_path / "none.yaml"), "-q"]) == 2
    assert "no such config file" in _error(capsys)
    assert not (tmp_path / "run").exists()


def test_an_interrupted_worker_exits_quietly(monkeypatch, capsys):
    from latentdrive.experiments import tune

    def interrupted(search, worker, on_trial=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(tune, "_work", interrupted)
    with pytest.raises(SystemExit) as info:
        tune._worker_main(None, 0)  # type: ignore[arg-type]
    assert info.value.code == 130
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out


def test_a_search_keeps_its_hash_when_a_setting_is_added() -> None:
    """The raw-short search's hash, as a search started before ``reward.failure`` existed
    stored it: adding a setting at its old behaviour must not orphan a running search."""
    from latentdrive.experiments.tune_space import base_config, load_space, search_hash

    space = load_space("raw-short")
    base = base_config(space, None, {})
    assert search_hash(space, base, 2) == "49234ff209901876"
    paid = base_config(space, None, {"reward.failure": -1.0})
    assert search_hash(space, paid, 2) != "49234ff209901876"


@pytest.mark.parametrize(("work_s", "grace_s", "exitcode"), [(60.0, 2.0, -15), (0.5, 20.0, 0)])
def test_a_stopped_search_stops_its_workers(monkeypatch, work_s, grace_s, exitcode):
    """A terminate reaches the search's parent only: the workers it started are given a
    grace period to stop on their own (as they do on Ctrl-C), then terminated, so none runs
    on orphaned. Regression: they used to keep training into OUT."""
    import multiprocessing as mp
    import time

    from latentdrive.errors import Terminated
    from latentdrive.experiments import tune

    monkeypatch.setattr(tune, "_WORKER_GRACE_S", grace_s)
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=time.sleep, args=(work_s,)) for _ in range(2)]
    for p in procs:
        p.start()

    def terminated() -> None:
        raise Terminated()

    t0 = time.monotonic()
    with pytest.raises(Terminated):
        tune._supervise(procs, terminated, every_s=0.05)
    assert time.monotonic() - t0 < 30
    assert [p.exitcode for p in procs] == [exitcode, exitcode]


def test_a_worker_watches_its_parent(monkeypatch):
    """A search killed outright (kill -9) cannot stop its workers; each worker watches its
    parent (tests/experiments/test_processes.py tests the watch) and stops with it."""
    from latentdrive.experiments import tune

    calls: list[str] = []
    monkeypatch.setattr(tune, "die_with_parent", lambda: calls.append("watch"))
    monkeypatch.setattr(tune, "_work", lambda search, worker: calls.append(f"work {worker}"))
    tune._worker_main(None, 3)  # type: ignore[arg-type]
    assert calls == ["watch", "work 3"]


_WORKER = """
import json, sys, time
from pathlib import Path
from latentdrive.experiments import tune
from latentdrive.experiments.tune_space import TuneSpace, base_config

out, space_json, trials, worker = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
space = TuneSpace.model_validate(json.loads(space_json))
search = tune.Search(out=out, space=space, base=base_config(space, 200, {}), seeds=1, trials=trials, prune=False)

def objective(search):
    def run(trial):
        with open(out / f"worker-{worker}.log", "a") as f:
            f.write(f"{trial.number}\\n")
        time.sleep(0.02)
        return 0.5
    return run

tune._objective = objective

# SQLite ignores the row lock optuna takes while it claims a queued trial.
from optuna.storages._rdb import models
find = models.TrialModel.find_or_raise_by_id.__func__

def slow_find(cls, trial_id, session, for_update=False):
    # Meet the other worker at the read of a queued trial (for a second at most): without
    # turns both read it as queued here and both claim it.
    trial = find(cls, trial_id, session, for_update)
    if for_update and trial.state.name == "WAITING":
        (out / f"read-{trial_id}-{worker}").touch()
        end = time.monotonic() + 0.5
        while not (out / f"read-{trial_id}-{1 - worker}").exists() and time.monotonic() < end:
            time.sleep(0.01)
    return trial

models.TrialModel.find_or_raise_by_id = classmethod(slow_find)
while not (out / "go").exists():
    time.sleep(0.01)
tune._work(search, worker)
"""


def test_two_workers_never_start_one_waiting_trial_twice(tmp_path):
    """Regression: SQLite ignores optuna's row lock, so two workers of one machine could both
    take the same queued trial (a retry on resumption); the second failed on the first's run
    folder, and the first then crashed ("Cannot tell a FAIL trial"), leaving one worker. And
    two workers that each counted one trial short both started one, past --trials."""
    import json
    import subprocess
    import sys
    import time

    from latentdrive.experiments.tune import Search, open_study
    from latentdrive.experiments.tune_space import TuneSpace, base_config

    raw = {"base": TINY_BASE, "space": TINY_SPACE}
    space = TuneSpace.model_validate(raw)
    out, n = tmp_path / "out", 8
    search = Search(out=out, space=space, base=base_config(space, 200, {}), seeds=1, trials=n, prune=False)
    study = open_study(search)
    for _ in range(n):
        study.enqueue_trial({"dqn.double": True})
    script = tmp_path / "worker.py"
    script.write_text(_WORKER)
    procs = [subprocess.Popen([sys.executable, str(script), str(out), json.dumps(raw), str(n), str(w)],
                              stderr=subprocess.PIPE, text=True) for w in range(2)]
    time.sleep(3)  # both import and wait
    (out / "go").touch()
    errs = [p.communicate(timeout=300)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    started = [int(x) for w in range(2) if (out / f"worker-{w}.log").exists()
               for x in (out / f"worker-{w}.log").read_text().split()]
    assert sorted(started) == list(range(n))
    assert all(t.state.name == "COMPLETE" for t in study.get_trials())
