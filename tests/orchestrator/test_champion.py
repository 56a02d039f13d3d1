"""The champion in service: a damaged one is reported once, kept out, and picked up when restored."""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

import orchestrator.report
from orchestrator.champion import ChampionScorer, FramesSource
from orchestrator.report import frames_png
from storage.catalog import Catalog
from storage.errors import RegistryUnavailableError
from storage.models import ModelRegistry
from storage.rows import Snapshot
from tests.conftest import failing_reads_of
from tests.uncertainty.synth import make_episode
from uncertainty.checkpoint import save_candidate
from uncertainty.ensemble import Ensemble
from uncertainty.model import PredictorConfig
from uncertainty.score import prediction_error

CFG = PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8)


def _promoted(registry: ModelRegistry, seed: int, h1_mse: float) -> str:
    ens = Ensemble(CFG, members=2, seed=seed)
    ens.set_action_stats([256.0, 250.0], [100.0, 90.0])
    version = save_candidate(registry, ens, {"h1_mse": h1_mse}, "snap", "split")
    assert registry.promote(version).promoted
    return version


def _busy_once(monkeypatch) -> None:
    """The registry's next load of weights meets its database locked (past the dashboard's busy timeout)."""
    busy = [True]
    real = ModelRegistry.load_weights

    def load_weights(self, v):
        if busy.pop() if busy else False:
            raise RegistryUnavailableError("database is locked")
        return real(self, v)

    monkeypatch.setattr(ModelRegistry, "load_weights", load_weights)


def test_a_damaged_champion_is_reported_once_and_loaded_once_restored(tmp_path, caplog):
    registry = ModelRegistry(tmp_path)
    first = _promoted(registry, 0, 0.02)
    scorer = ChampionScorer(tmp_path)
    episode = make_episode(0, size=16)
    assert scorer(episode).model_version == first and scorer.problem is None
    second = _promoted(registry, 1, 0.01)
    weights = registry.get(second).weights_path
    good = weights.read_bytes()
    weights.write_bytes(good[:-7])
    assert registry.weights_problem(second).startswith(f"checkpoint {second}: weights sha256 mismatch")
    assert registry.weights_problem(first) is None

    with caplog.at_level(logging.ERROR, logger="orchestrator.champion"):
        for _ in range(3):
            scores = scorer(episode)
            assert scores.model_version == first and np.isfinite(scores.per_step).any()
    assert [r.getMessage().split(",")[0] for r in caplog.records] == [f"could not load champion {second}"]
    assert scorer.problem.startswith(f"cannot load champion {second}: ") and "sha256" in scorer.problem

    weights.write_bytes(good)  # restored from a backup
    assert registry.weights_problem(second) is None
    assert scorer(episode).model_version == second and scorer.problem is None


def test_with_error_the_scores_carry_the_error_and_whether_the_champion_trained_on_the_episode(tmp_path, monkeypatch):
    registry = ModelRegistry(tmp_path)
    seen, unseen = make_episode(0, size=16), make_episode(1, size=16)
    snap = Snapshot.of([(seen.meta.episode_id, "0" * 64)])
    ens = Ensemble(CFG, members=2, seed=0)
    ens.set_action_stats([256.0, 250.0], [100.0, 90.0])
    version = save_candidate(registry, ens, {"h1_mse": 0.02}, snap.snapshot_id, "split", snapshot=snap)
    assert registry.promote(version).promoted
    plain = ChampionScorer(tmp_path)(seen)
    assert plain.error is None and plain.trained is None  # not asked for: not computed
    scorer = ChampionScorer(tmp_path, with_error=True)
    scores = scorer(seen)
    assert scores.trained is True and scorer(unseen).trained is False
    np.testing.assert_allclose(scores.error, prediction_error(scorer.ensemble, seen.frames, seen.actions))
    np.testing.assert_array_equal(np.isnan(scores.error), np.isnan(scores.per_step))
    longer = ChampionScorer(tmp_path, with_error=True, error_horizon=2)(seen).error
    np.testing.assert_allclose(longer, prediction_error(scorer.ensemble, seen.frames, seen.actions, horizon=2))
    path = registry.get(version).path / "snapshot.json"
    good = path.read_bytes()
    path.write_bytes(good[:-5])  # damaged: the weights still serve; what it trained on is unknown
    damaged = ChampionScorer(tmp_path, with_error=True)
    assert damaged(seen).trained is None and damaged(seen).error is not None
    path.write_bytes(good)
    assert damaged(seen).trained is None  # a lasting failure is not read again for this champion
    real, reads = ModelRegistry.snapshot, []

    def busy_once(self, v):  # the database busy at the first read, as a passing failure is
        reads.append(v)
        if len(reads) == 1:
            raise RegistryUnavailableError("database is locked")
        return real(self, v)

    with monkeypatch.context() as m:
        m.setattr(ModelRegistry, "snapshot", busy_once)
        waits = ChampionScorer(tmp_path, with_error=True)
        assert waits(seen).trained is None and waits(seen).trained is None and len(reads) == 1  # not before RETRY_S
        reads.clear()
        retries = ChampionScorer(tmp_path, with_error=True)
        retries.RETRY_S = 0.0
        assert retries(seen).trained is None and retries(seen).trained is True and len(reads) == 2  # read again
    older = _promoted(registry, 1, 0.01)  # registered without its episodes: not known
    assert scorer(seen).model_version == older and scorer(seen).trained is None
    assert scorer(seen).error is not None


def test_a_read_error_is_not_remembered_as_damage(tmp_path, monkeypatch):
    registry = ModelRegistry(tmp_path)
    version = _promoted(registry, 0, 0.02)
    failing_reads_of(registry.get(version).weights_path, monkeypatch)
    assert "Input/output error" in registry.weights_problem(version)
    assert registry.weights_problem(version) is None  # the same file, read again: it was the disk, not the bytes


def test_the_scorer_tries_again_after_a_read_error(tmp_path, monkeypatch):
    registry = ModelRegistry(tmp_path)
    version = _promoted(registry, 0, 0.02)
    scorer = ChampionScorer(tmp_path)
    scorer.RETRY_S = 0.0  # (a minute in service)
    failing_reads_of(registry.get(version).weights_path, monkeypatch)
    assert scorer.reload() is None and "Input/output error" in scorer.problem
    assert scorer.reload() == version and scorer.problem is None



def test_a_registry_busy_now_is_tried_again_soon_and_not_called_damage(tmp_path, monkeypatch, caplog):
    """The dashboard reads with a 2 s busy timeout: a load that met the database locked was logged as an ERROR and
    not tried again for RETRY_S (a minute of the old champion's frames after a promotion)."""
    registry = ModelRegistry(tmp_path)
    version = _promoted(registry, 0, 0.02)
    scorer = ChampionScorer(tmp_path)
    scorer.BUSY_RETRY_S = 0.0  # (5 s in service; RETRY_S, a minute, still holds for damage)
    _busy_once(monkeypatch)
    with caplog.at_level(logging.INFO, logger="orchestrator.champion"):
        assert scorer.reload() is None and scorer.problem.startswith(f"cannot load champion {version} now")
    assert [r.levelname for r in caplog.records if "could not load" in r.getMessage()] == ["WARNING"]
    assert scorer.reload() == version and scorer.problem is None

THREADS_PROBE = """
import sys, threading, torch
from orchestrator.champion import ChampionScorer
from tests.uncertainty.synth import make_episode
scorer = ChampionScorer(sys.argv[1], threads=int(sys.argv[2]))
seen = {}
def default():  # (each thread takes torch's setting on its first call: the main thread is kept for the end)
    seen["default"] = torch.get_num_threads()
def score():  # the service scores in its planner's thread, not the main one
    seen["version"] = scorer(make_episode(0, size=16)).model_version
    seen["scoring"] = torch.get_num_threads()
def later():
    seen["later"] = torch.get_num_threads()
for target in (default, score, later):
    thread = threading.Thread(target=target)
    thread.start()
    thread.join()
print(seen["default"], seen["version"], seen["scoring"], seen["later"], torch.get_num_threads())
"""


def test_threads_sets_torchs_threads_for_the_whole_process_when_the_champion_loads_and_zero_leaves_them(tmp_path):
    version = _promoted(ModelRegistry(tmp_path), 0, 0.02)
    root = Path(__file__).resolve().parents[2]
    for threads in (3, 0):  # (3: a count torch would not pick by itself on this 2-core machine or a 1-core one)
        proc = subprocess.run([sys.executable, "-c", THREADS_PROBE, str(tmp_path), str(threads)], cwd=root,
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr[-2000:]
        default, loaded, *after = proc.stdout.split()
        assert loaded == version
        assert after == [str(threads or default)] * 3  # the scoring thread, one started later, the main one


def test_threads_must_not_be_negative(tmp_path):
    with pytest.raises(ValueError, match="threads must be >= 0, found -1"):
        ChampionScorer(tmp_path, threads=-1)


class _WatchedLock:
    """The scorer's lock, telling ``waiting`` when a thread has to wait for it."""

    def __init__(self, waiting: threading.Event) -> None:
        self._lock = threading.Lock()
        self.waiting = waiting

    def __enter__(self) -> "_WatchedLock":
        if not self._lock.acquire(blocking=False):
            self.waiting.set()
            self._lock.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self._lock.release()


def test_a_reload_that_read_the_champion_before_a_promotion_does_not_switch_back_to_it(tmp_path, monkeypatch):
    registry = ModelRegistry(tmp_path)
    first = _promoted(registry, 0, 0.02)
    ens = Ensemble(CFG, members=2, seed=1)
    ens.set_action_stats([256.0, 250.0], [100.0, 90.0])
    second = save_candidate(registry, ens, {"h1_mse": 0.01}, "snap", "split")
    scorer = ChampionScorer(tmp_path)
    settled = threading.Event()  # the other reload has finished, or waits for the lock
    scorer._lock = _WatchedLock(settled)
    real, others, read = ModelRegistry.champion, [], []

    def other() -> None:
        scorer.reload()
        settled.set()

    def champion(self):  # thread "a"'s first read: a promotion and another thread's reload land right after it
        value = real(self)
        if threading.current_thread().name == "a" and not others:
            read.append(value)
            assert ModelRegistry(tmp_path).promote(second).promoted
            others.append(threading.Thread(target=other, name="b"))
            others[0].start()
            assert settled.wait(30)
        return value

    monkeypatch.setattr(ModelRegistry, "champion", champion)
    a = threading.Thread(target=scorer.reload, name="a")
    a.start()
    a.join(30)
    others[0].join(30)
    assert not a.is_alive() and not others[0].is_alive() and read == [first]
    assert registry.champion() == second and scorer.problem is None
    assert scorer.version == second and scorer.ensemble.version == second  # not back on the retired first


def test_the_frames_are_cached_under_the_version_of_the_ensemble_that_drew_them(tmp_path, monkeypatch):
    catalog = Catalog(tmp_path)
    catalog.pin_eval_split([catalog.add_episode(make_episode(50, size=16), split="eval").episode_id])
    registry = ModelRegistry(tmp_path)
    first = _promoted(registry, 0, 0.02)
    scorer = ChampionScorer(tmp_path)
    real_split, drawn = catalog.eval_split, []

    def eval_split():  # a promotion, and a reload by another caller, land while the picture is being drawn
        if not drawn:
            _promoted(registry, 1, 0.01)
            scorer.reload()
        return real_split()

    def recording(ensemble, episodes):
        drawn.append(ensemble.version)
        return frames_png(ensemble, episodes)

    monkeypatch.setattr(catalog, "eval_split", eval_split)
    monkeypatch.setattr(orchestrator.report, "frames_png", recording)
    assert scorer.reload() == first
    source = FramesSource(scorer, catalog)
    picture = source()
    second = registry.champion()
    assert picture.startswith(b"\x89PNG") and drawn == [second]
    assert source() == picture and drawn == [second]  # cached
    assert registry.rollback() == first
    assert source() != picture and drawn == [second, first]  # not the second's picture, cached as the first's


def test_frames_png_gives_the_ensemble_actions_on_its_own_device():
    """No GPU here: an ensemble on the meta device stands for one on CUDA (a CPU tensor would not be on it)."""
    ensemble = Ensemble(CFG, members=2, seed=0).to("meta")
    seen = []

    class Seen(Exception):
        pass

    def normalize_actions(actions):
        seen.append(actions.device)
        raise Seen  # (a meta tensor holds no values to draw)

    ensemble.normalize_actions = normalize_actions
    with pytest.raises(Seen):
        frames_png(ensemble, [make_episode(0, size=16)])
    assert seen == [torch.device("meta")] == [ensemble.device]


def test_damage_found_after_a_busy_registry_is_still_an_error(tmp_path, monkeypatch, caplog):
    """The first try met the database locked (a WARNING), the next one damaged weights: that one was logged at DEBUG
    as a repeat of the same failure, so the damage was never said at ERROR (a review's reproduction)."""
    registry = ModelRegistry(tmp_path)
    version = _promoted(registry, 0, 0.02)
    weights = registry.get(version).weights_path
    weights.write_bytes(weights.read_bytes()[:-7])
    scorer = ChampionScorer(tmp_path)
    scorer.BUSY_RETRY_S = 0.0
    _busy_once(monkeypatch)
    with caplog.at_level(logging.DEBUG, logger="orchestrator.champion"):
        for _ in range(3):
            assert scorer.reload() is None
    said = [(r.levelname, "sha256" in r.getMessage()) for r in caplog.records if "could not load" in r.getMessage()]
    assert said[:2] == [("WARNING", False), ("ERROR", True)], said
    assert all(level == "DEBUG" for level, _ in said[2:]), said
    assert "sha256" in scorer.problem
