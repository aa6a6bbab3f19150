"""Hyperparameter search over train-policy settings with Optuna (``latentdrive tune``).

A trial draws settings from the space (TPE), trains one policy per training seed and is
scored by their mean mixed failure rate on validation episodes (never an evaluation set:
:mod:`latentdrive.seeds`). Each periodic evaluation is reported to the trial, and a median
pruner stops trials that trail the others at the same point of the same seed.

The study lives in an SQLite file, ``OUT/study.db``, or at ``--storage URL``, which several
machines can share. Its user attributes record the hash of the space and the base config,
so a study is never continued under other settings. A search that is killed resumes:

- with the local file, ``OUT`` is locked while a search runs, so a trial still marked
  running when a search starts was interrupted; it is marked failed;
- with a shared storage, trials send heartbeats, and one silent for :data:`GRACE_S` is
  marked failed by the next trial any worker starts;
- an interrupted trial is retried (:data:`MAX_RETRY` times) with the same settings. Its
  runs live in the folder of the first attempt and resume from their checkpoints, which a
  policy run reproduces bit for bit. A trial that failed for a reason in its settings
  (an invalid combination) is recorded, with its error, and not retried.
"""

from __future__ import annotations

import multiprocessing as mp
import sqlite3
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from latentdrive.config import ConfigError
from latentdrive.errors import LatentDriveError, first_line
from latentdrive.experiments.tune_space import TuneSpace, search_hash, trial_config
from latentdrive.fileio import read_log
from latentdrive.lifetime import die_with_parent
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import CHECKPOINT
from latentdrive.rl.runfolder import EVAL_COLUMNS, EVALS
from latentdrive.rl.train import train_policy

if TYPE_CHECKING:
    import optuna

__all__ = ["GRACE_S", "HEARTBEAT_S", "MAX_RETRY", "STUDY_DB", "STUDY_NAME", "TRIALS_DIR", "Search",
           "counted_trials", "open_study", "run_search", "seed_failure_rate"]

STUDY_DB = "study.db"
STUDY_NAME = "latentdrive-tune"
TRIALS_DIR = "trials"
#: The user attribute that holds the search's hash (space, base config, seeds).
HASH_ATTR = "latentdrive_search_hash"
#: Seconds between a running trial's heartbeats, and of silence before it counts as dead.
HEARTBEAT_S = 60
GRACE_S = 300
#: Retries of an interrupted trial.
MAX_RETRY = 2
#: The lock file in OUT that the workers of one machine take in turn to claim a trial.
TURN_LOCK = ".tune-turn.lock"


@dataclass(frozen=True)
class Search:
    """One search: what it trains, where it is stored and how it samples."""

    out: Path
    space: TuneSpace
    base: PolicyTrainConfig
    seeds: int
    trials: int
    storage: str | None = None  # a database URL; None: OUT/study.db
    sampler_seed: int = 0
    prune: bool = True

    @property
    def url(self) -> str:
        return self.storage or f"sqlite:///{(self.out / STUDY_DB).resolve()}"

    @property
    def key(self) -> str:
        return search_hash(self.space, self.base, self.seeds)


def _optuna() -> Any:
    import optuna

    # ERROR, not WARNING: optuna logs every failed trial with its traceback, an interrupted
    # one included; the trials table (tune.md) records each failure's error instead.
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    return optuna


def _check_local_db(path: Path) -> None:
    """Refuse a file at OUT/study.db that is not an optuna study database, read-only, before
    optuna would create its tables in it."""
    if not path.exists():
        return
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        finally:
            con.close()
    except sqlite3.Error as exc:
        raise ConfigError(f"{path}: not an optuna study database ({first_line(exc)})") from None
    if not {"studies", "trials", "version_info"} <= tables:
        raise ConfigError(f"{path}: not an optuna study database (an SQLite file with other tables)")


def _retry(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
    """Queue an interrupted trial again with the same settings (and its run folder)."""
    optuna = _optuna()
    optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY, inherit_intermediate_values=True)(study, trial)


def open_study(search: Search, create: bool = True) -> optuna.Study:
    """The search's study, created when missing; one-line errors for a foreign or corrupt
    storage and for a study made by another search (another space, base config or seeds)."""
    optuna = _optuna()
    local = search.storage is None
    if local:
        _check_local_db(search.out / STUDY_DB)
        search.out.mkdir(parents=True, exist_ok=True)
    where = search.out / STUDY_DB if local else f"--storage {search.storage}"
    try:
        kwargs = {"connect_args": {"timeout": 60}} if search.url.startswith("sqlite") else {}
        storage = optuna.storages.RDBStorage(search.url, engine_kwargs=kwargs, heartbeat_interval=HEARTBEAT_S,
                                             grace_period=GRACE_S, heartbeat_stale_trial_callback=_retry)
    except LatentDriveError:
        raise
    except Exception as exc:  # sqlalchemy's and optuna's errors: a bad URL, an unreachable server, old schema
        raise ConfigError(f"{where}: cannot open the study storage ({first_line(exc)})") from None
    pruner = optuna.pruners.MedianPruner(n_startup_trials=4, n_warmup_steps=search.base.steps // 2) \
        if search.prune else optuna.pruners.NopPruner()
    names = {s.study_name for s in storage.get_all_studies()}
    if STUDY_NAME not in names:
        if local and names:
            raise ConfigError(f"{where}: an optuna database without a latentdrive search (studies: "
                              f"{', '.join(sorted(names))})")
        if not create:
            raise ConfigError(f"{where}: holds no search yet")
        study = optuna.create_study(study_name=STUDY_NAME, storage=storage, direction="minimize",
                                    pruner=pruner, load_if_exists=True)
        if HASH_ATTR not in study.user_attrs:
            study.set_user_attr(HASH_ATTR, search.key)
            study.set_user_attr("space", {k: d.model_dump(mode="json") for k, d in search.space.space.items()})
            study.set_user_attr("base", search.base.model_dump(mode="json"))
            study.set_user_attr("seeds", search.seeds)
    else:
        study = optuna.load_study(study_name=STUDY_NAME, storage=storage, pruner=pruner)
    found = study.user_attrs.get(HASH_ATTR)
    if found != search.key:
        what = "not made by latentdrive tune" if found is None else \
            "made by another search (another space, base config or --seeds)"
        raise ConfigError(f"{where}: its study was {what}; give another OUT (or --storage) for this one")
    return study


def _state(name: str) -> Any:
    return getattr(_optuna().trial.TrialState, name)


def _retried(trials: list[optuna.trial.FrozenTrial]) -> set[int]:
    return {n for t in trials for n in t.system_attrs.get("retry_history", [])}


def counted_trials(trials: list[optuna.trial.FrozenTrial]) -> int:
    """Trials toward ``--trials``: finished, running or queued, not counting an interrupted
    one whose retry is queued (the retry counts in its place)."""
    retried = _retried(trials)
    return sum(1 for t in trials if t.number not in retried)


def _finished(trials: list[optuna.trial.FrozenTrial]) -> int:
    retried = _retried(trials)
    done = (_state("COMPLETE"), _state("PRUNED"), _state("FAIL"))
    return sum(1 for t in trials if t.state in done and t.number not in retried)


def _recover(study: optuna.Study, local: bool) -> list[int]:
    """Mark interrupted trials failed and queue their retries; returns their numbers.

    Interrupted: still running in the local file that this process has locked (so no
    search is running it), or failed without a recorded error (a Ctrl-C, a crash)."""
    optuna = _optuna()
    storage = study._storage
    study_id = storage.get_study_id_from_name(STUDY_NAME)
    trials = study.get_trials(deepcopy=False)
    retried = _retried(trials)
    out = []
    for t in trials:
        if local and t.state == _state("RUNNING"):
            storage.set_trial_state_values(storage.get_trial_id_from_study_id_trial_number(study_id, t.number),
                                           state=optuna.trial.TrialState.FAIL)
        elif not (t.state == _state("FAIL") and "error" not in t.user_attrs and t.number not in retried):
            continue
        before = len(study.get_trials(deepcopy=False))
        _retry(study, study.get_trials(deepcopy=False)[t.number])
        if len(study.get_trials(deepcopy=False)) > before:  # not when its retries are spent
            out.append(t.number)
    return out


def seed_failure_rate(run: Path, steps: int) -> float:
    """The mixed failure rate of a finished run's final evaluation (its eval.csv)."""
    rows = read_log(run / EVALS, columns=EVAL_COLUMNS, key="transitions", what="evaluation log")
    final = [r for r in rows if r["scenario"] == "mixed" and int(r["transitions"]) >= steps]
    if not final:
        raise ConfigError(f"{run / EVALS}: no final evaluation (the run stopped before {steps} agent-transitions)")
    return float(final[-1]["failure_rate"])


def _objective(search: Search) -> Callable[[optuna.Trial], float]:
    pruned = _optuna().TrialPruned
    from latentdrive.experiments.tune_space import FloatDist, IntDist

    def objective(trial: optuna.Trial) -> float:
        params: dict[str, Any] = {}
        for key, d in search.space.space.items():
            if isinstance(d, FloatDist):
                params[key] = trial.suggest_float(key, d.low, d.high, log=d.log)
            elif isinstance(d, IntDist):
                params[key] = trial.suggest_int(key, d.low, d.high, step=d.step, log=d.log)
            else:
                params[key] = trial.suggest_categorical(key, list(d.choices))
        # A retry keeps its first attempt's folder (user attributes are carried over) and
        # resumes its runs there.
        if "run" not in trial.user_attrs:
            trial.set_user_attr("run", f"{trial.number:04d}")
        folder = search.out / TRIALS_DIR / str(trial.user_attrs["run"])
        rates: list[float] = []
        t0 = time.perf_counter()
        try:
            for k in range(search.seeds):
                cfg = trial_config(search.base, params, seed=k)
                run = folder / f"seed-{k}"

                def report(transitions: int, rate: float, k: int = k) -> None:
                    # Seeds run one after another: seed k's evaluations are steps k·budget +
                    # transitions, so the pruner compares trials at the same seed and point.
                    trial.report(rate, k * search.base.steps + transitions)
                    if trial.should_prune():
                        raise pruned(f"failure rate {rate:.3f} at {transitions} agent-transitions of seed {k}")

                train_policy(cfg, run, resume=(run / CHECKPOINT).exists(), progress=False, say=lambda _line: None,
                             on_eval=report)
                rates.append(seed_failure_rate(run, cfg.steps))
                trial.set_user_attr("seed_failure_rates", rates)
        except LatentDriveError as exc:
            trial.set_user_attr("error", str(exc))  # a reason in the settings: not retried
            raise
        finally:
            trial.set_user_attr("minutes", round(float(trial.user_attrs.get("minutes", 0.0))
                                                 + (time.perf_counter() - t0) / 60, 3))
        return float(np.mean(rates))

    return objective


def _sampler(search: Search, worker: int, n: int) -> Any:
    # Seeded per trial from (search seed, worker, trials so far): a resumed search does not
    # redraw its first trial's settings, and one worker's search is reproducible.
    seed = int(np.random.SeedSequence([search.sampler_seed, worker, n]).generate_state(1)[0])
    return _optuna().samplers.TPESampler(seed=seed, constant_liar=True)


def _work(search: Search, worker: int, on_trial: Callable[[], None] | None = None) -> None:
    """Run trials until the study counts ``search.trials`` of them."""
    from latentdrive.runlock import Turn

    study = open_study(search, create=False)
    # Counting the trials and taking one (a queued retry, or a new one) is one worker's turn
    # at a time. SQLite ignores the row lock optuna takes to claim a queued trial, so two
    # workers could both claim one (the second then failed on the first's run folder, and
    # the first, told its trial had failed, crashed), and two workers that both counted
    # one trial short both started one. The turn passes on once the trial is taken.
    turn = Turn(search.out / TURN_LOCK)
    while True:
        with turn:
            trials = study.get_trials(deepcopy=False)
            waiting = any(t.state == _state("WAITING") for t in trials)
            if not waiting and counted_trials(trials) >= search.trials:
                return
            study.sampler = _sampler(search, worker, len(trials))
            objective = _objective(search)

            def taken(trial: optuna.Trial, objective: Callable[[optuna.Trial], float] = objective) -> float:
                turn.release()
                return objective(trial)

            study.optimize(taken, n_trials=1, catch=(LatentDriveError,), gc_after_trial=True)
        if on_trial is not None:
            on_trial()


#: Seconds an interrupted search gives its workers to stop on their own before terminating them.
_WORKER_GRACE_S = 10.0


def _worker_main(search: Search, worker: int) -> None:
    die_with_parent()  # a search killed outright (kill -9) takes its workers with it
    try:
        _work(search, worker)
    except KeyboardInterrupt:
        # Ctrl-C reaches every worker with the parent, which reports it once; a traceback
        # from each worker would only bury that line.
        raise SystemExit(130) from None


def _supervise(procs: list[Any], tick: Callable[[], None], every_s: float = 2.0) -> None:
    """Call ``tick`` every ``every_s`` seconds until the started ``procs`` have ended.

    Should this loop end by an exception (Ctrl-C, a terminate, an error in ``tick``), the
    workers still running after a grace period are terminated before it propagates.
    """
    try:
        while any(p.is_alive() for p in procs):
            time.sleep(every_s)
            tick()
    except BaseException:
        # Ctrl-C reaches the workers with the parent, and they stop on their own; a
        # terminate (or an error here) does not, and a worker left running would go on
        # training into OUT with no search waiting for it. Their trials are retried on
        # resumption.
        deadline = time.monotonic() + _WORKER_GRACE_S
        for p in procs:
            p.join(max(0.0, deadline - time.monotonic()))
        for p in procs:
            if p.is_alive():
                p.terminate()
        raise
    finally:
        for p in procs:
            p.join()


@contextmanager
def _bar(total: int, initial: int, progress: bool) -> Iterator[Any]:
    from tqdm import tqdm

    with tqdm(total=total, initial=min(initial, total), unit="trial", desc="tune", disable=not progress,
              dynamic_ncols=True) as bar:
        yield bar


def run_search(search: Search, workers: int = 1, progress: bool = True,
               say: Callable[[str], None] = print) -> optuna.Study:
    """Run (or resume) ``search`` to ``search.trials`` trials with ``workers`` processes."""
    from latentdrive.runlock import dir_lock

    with dir_lock(search.out, "tune"):
        study = open_study(search)
        again = _recover(study, local=search.storage is None)
        if again:
            say(f"retrying interrupted trial(s) {', '.join(map(str, again))} with their settings")
        trials = study.get_trials(deepcopy=False)
        with _bar(search.trials, _finished(trials), progress) as bar:
            def tick() -> None:
                now = study.get_trials(deepcopy=False)
                bar.n = min(_finished(now), search.trials)
                done = [t for t in now if t.state == _state("COMPLETE")]
                if done:
                    bar.set_postfix(best=f"{min(float(t.value) for t in done if t.value is not None):.3f}")
                bar.refresh()

            if workers == 1:
                _work(search, 0, tick)
            else:
                ctx = mp.get_context("spawn")
                procs = [ctx.Process(target=_worker_main, args=(search, w), daemon=False) for w in range(workers)]
                for p in procs:
                    p.start()
                _supervise(procs, tick)
                bad = [w for w, p in enumerate(procs) if p.exitcode != 0]
                if bad:
                    raise LatentDriveError(f"tune worker(s) {', '.join(map(str, bad))} failed (exit code "
                                           f"{procs[bad[0]].exitcode}); rerun the command to resume")
            tick()
    return study
