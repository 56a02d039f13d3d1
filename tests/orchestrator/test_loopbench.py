"""The bench loop: its arithmetic (episodes to reach an error, the headline ratios, mean and spread), its
configuration, and one tiny run of both arms through the CLI."""

from __future__ import annotations

import dataclasses as dc
import json
import math

import numpy as np
import pytest
import torch

from orchestrator.loopbench import OBJECT_COLOURS, LoopBenchConfig, _bench_id, object_colours, palette_of
from orchestrator.loopconfig import RunConfig
from orchestrator.loopsummary import ARMS, episodes_to_reach, summarize
from orchestrator.protocol import PHYSICS_RANGES, SHAPES
from storage.catalog import Catalog
from storage.records import Episode, EpisodeMeta
from tests.conftest import run_cli
from uncertainty.score import colour_mask, object_moving
from workers.env import AGENT_RGB, MARKER_RGB, SHAPE_PALETTE, PushSim, SimState, _background, scene_colours


def test_episodes_to_reach_interpolates_between_retrains():
    curve = [(16, 1.0), (32, 0.8), (48, 0.6)]
    assert episodes_to_reach(curve, 1.2) == 16
    assert episodes_to_reach(curve, 0.8) == 32
    assert episodes_to_reach(curve, 0.7) == pytest.approx(40.0)
    assert episodes_to_reach(curve, 0.5) == math.inf


def test_summary_headline_and_spread():
    cfg = LoopBenchConfig(seeds=(0, 1), budget=48, round_episodes=16)
    points = []
    for seed, shift in ((0, 0.0), (1, 0.1)):
        for ep, (a, u) in zip((16, 32, 48), ((1.0, 1.0), (0.7, 0.8), (0.5, 0.7))):
            points.append({"arm": "active", "seed": seed, "episodes": ep, "h1_mse": a + shift})
            points.append({"arm": "uniform", "seed": seed, "episodes": ep, "h1_mse": u + shift})
    s = summarize(points, cfg.seeds, "h1_mse")
    assert s["curves"]["active"]["48"] == {"mean": pytest.approx(0.55), "std": pytest.approx(0.05), "n": 2}
    h = s["headline"]
    # active reaches uniform's final 0.75 at 16 + 16 * (1.05 - 0.75) / (1.05 - 0.75) = 32 episodes
    assert h["active_episodes_to_match_uniform"] == pytest.approx(32.0)
    assert h["active_over_uniform_ratio"] == pytest.approx(32 / 48)
    assert h["uniform_episodes_to_match_active"] is None and h["uniform_over_active_ratio"] is None
    assert [p["seed"] for p in s["per_seed"]] == [0, 1]
    # per seed, active's final over uniform's, less 1: 0.5 / 0.7 and 0.6 / 0.8
    paired = s["paired"]
    assert paired["per_seed"] == pytest.approx([0.5 / 0.7 - 1, 0.6 / 0.8 - 1])
    assert paired["mean"] == pytest.approx((0.5 / 0.7 + 0.6 / 0.8) / 2 - 1)
    assert paired["std"] == pytest.approx(abs(0.5 / 0.7 - 0.6 / 0.8) / 2)
    assert (paired["active_behind"], paired["seeds"]) == (0, 2)


def test_a_stopped_runs_summary_compares_only_the_rounds_both_arms_of_a_seed_finished():
    cfg = LoopBenchConfig(seeds=(0, 1), budget=48, round_episodes=16)
    reached = {(0, "active"): (16, 32, 48), (0, "uniform"): (16, 32), (1, "active"): (16,), (1, "uniform"): ()}
    points = [{"arm": arm, "seed": seed, "episodes": ep, "h1_mse": 1.0 - ep / 100 + (arm == "active") * 0.01}
              for (seed, arm), eps in reached.items() for ep in eps]
    s = summarize(points, cfg.seeds, "h1_mse")
    assert list(s["curves"]["active"]) == list(s["curves"]["uniform"]) == ["16", "32"]
    assert s["curves"]["active"]["32"]["n"] == 1
    assert s["headline"]["budget"] == 32 and s["headline"]["active_final"] == pytest.approx(0.69)
    assert [p["seed"] for p in s["per_seed"]] == [0]
    assert s["paired"]["per_seed"] == pytest.approx([0.69 / 0.68 - 1])
    only_one_arm = summarize([p for p in points if p["arm"] == "active"], cfg.seeds, "h1_mse")
    assert only_one_arm["headline"] is None and only_one_arm["per_seed"] == [] and only_one_arm["paired"]["seeds"] == 0


def test_config_refuses_a_budget_of_less_than_two_rounds_and_unknown_signals():
    with pytest.raises(ValueError, match="budget"):
        LoopBenchConfig(budget=16, round_episodes=16)
    with pytest.raises(ValueError, match="signal"):
        LoopBenchConfig(signal="loss")


@pytest.mark.parametrize("signal", ["predicted", "total"])
def test_config_refuses_the_variance_heads_signals_without_one_or_past_horizon_1(signal):
    d = LoopBenchConfig()
    head = dc.replace(d.train, variance_head=True)
    with pytest.raises(ValueError, match=f"signal {signal} ranks by a variance head: it needs variance_head$"):
        LoopBenchConfig(signal=signal)
    with pytest.raises(ValueError, match="it needs signal_horizon 1, found 2"):
        LoopBenchConfig(signal=signal, train=head, signal_horizon=2)
    assert LoopBenchConfig(signal=signal, train=head).signal == signal


def test_bench_ids_sort_in_collection_order_and_repeat_across_runs():
    meta = EpisodeMeta(episode_id="x", task="push", shape="T", physics={}, seed=0, policy="push")
    ep = Episode(meta, np.zeros((3, 4, 4, 3), np.uint8), np.zeros((3, 2), np.float32), np.zeros((3, 11)))
    ids = [_bench_id(ep, 1, i).meta.episode_id for i in (2, 10, 100)]
    assert ids == sorted(ids) and ids == [_bench_id(ep, 1, i).meta.episode_id for i in (2, 10, 100)]
    assert ep.meta.episode_id == "x"  # the collected episode is left as it was


def test_object_moving_marks_the_steps_before_the_object_moves_or_turns():
    states = np.zeros((5, 11))
    states[2:, 4] = 10.0          # obj_x jumps between steps 1 and 2
    states[4, 6] = 0.1            # obj_theta turns between steps 3 and 4
    assert object_moving(states).tolist() == [False, True, False, True, False]
    assert object_moving(states, horizon=2).tolist() == [True, True, True, False, False]


def test_active_policy_and_within_policy_reach_only_the_active_arms_planner():
    assert not LoopBenchConfig().active.choose_policy and not LoopBenchConfig().active.within_policy
    cfg = LoopBenchConfig(active_policy=True, within_policy=True)
    assert cfg.active.choose_policy and cfg.to_json()["active"]["choose_policy"]
    assert cfg.active.within_policy and cfg.to_json()["within_policy"]
    assert cfg.uniform_config().policies == cfg.policies  # the uniform arm keeps the mix


@pytest.mark.parametrize("size", [8, 12, 20, 1032])
def test_both_loop_configs_refuse_a_frame_size_no_model_trains_on(tmp_path, size):
    with pytest.raises(ValueError, match=f"image_size must be a multiple of 8 from 16 to 1024, found {size}"):
        LoopBenchConfig(image_size=size)
    with pytest.raises(ValueError, match=f"image_size must be a multiple of 8 from 16 to 1024, found {size}"):
        RunConfig(data_dir=tmp_path, image_size=size)
    assert LoopBenchConfig(image_size=24).image_size == RunConfig(data_dir=tmp_path, image_size=24).image_size == 24


def test_random_physics_reaches_the_uniform_arm_and_the_seeds():
    assert not LoopBenchConfig().uniform_config().sample_physics
    cfg = LoopBenchConfig(random_physics=True)
    assert cfg.uniform_config().sample_physics and cfg.active.seed_uniform.sample_physics
    assert cfg.to_json()["random_physics"]


def test_shape_weights_reach_the_uniform_arm_and_the_seeds_and_palettes_are_checked():
    assert LoopBenchConfig().uniform_config().shape_weights == ()
    cfg = LoopBenchConfig(shape_weights=(7, 1, 1, 1))
    assert cfg.uniform_config().shape_weights == cfg.active.seed_uniform.shape_weights == (7.0, 1.0, 1.0, 1.0)
    assert cfg.to_json()["shape_weights"] == (7.0, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="shape_weights"):
        LoopBenchConfig(shape_weights=(1, 1))
    with pytest.raises(ValueError, match="palette must be one of"):
        LoopBenchConfig(palette="pastel")
    assert palette_of(LoopBenchConfig()) is None and object_colours(None) == OBJECT_COLOURS
    palette = palette_of(LoopBenchConfig(palette="per-shape"))
    assert palette == SHAPE_PALETTE
    assert set(object_colours(palette)) == {*SHAPE_PALETTE.values(), MARKER_RGB}


def test_bench_loop_with_a_skewed_mix_and_shapes_coloured_apart(tmp_path, capsys):
    """The uniform arm and the seeds draw by --shape-weights; the eval split keeps every shape, and
    --palette reaches every episode of both arms and the split."""
    out = tmp_path / "loop"
    rc, stdout, _ = run_cli(capsys, "bench", "loop", "--seeds", "1", "--budget", "4", "--round", "2",
                            "--steps", "12", "--image-size", "16", "--epochs", "1", "--members", "2",
                            "--shape-weights", "disk=1", "--palette", "per-shape", "--max-shape-share", "1",
                            "--json", "--out", str(out))
    assert rc == 0
    summary = json.loads(stdout)
    assert summary["config"]["shape_weights"] == [0.0, 0.0, 0.0, 1.0] and summary["config"]["palette"] == "per-shape"
    assert summary["config"]["active"]["max_shape_share"] == 1.0
    assert all(p["round_shapes"] == {"disk": 2} for p in summary["points"])
    gold = np.array(SHAPE_PALETTE["disk"])
    for arm in ARMS:
        catalog = Catalog(out / "seed0" / arm)
        assert catalog.eval_split().params["palette"]["disk"] == list(SHAPE_PALETTE["disk"])
        assert {r.shape for r in catalog.list(split="eval")} == set(SHAPES)  # the split keeps every shape
        for r in catalog.list(split="train"):
            assert r.shape == "disk"
            frames = catalog.load(r.episode_id).frames.astype(int)
            assert (np.abs(frames - gold).sum(axis=-1) <= 6).any()  # drawn in the disk's own colour


def test_bench_loop_shapes_by_progress_asks_for_shapes_the_last_round_did_not_have(tmp_path, capsys):
    """With --shapes-by-progress the active arm splits a round over every shape (equally while no progress is known),
    filling shapes without candidates with uniform starts of their own shape; the uniform arm keeps its mix."""
    rc, stdout, _ = run_cli(capsys, "bench", "loop", "--seeds", "1", "--budget", "12", "--round", "4",
                            "--steps", "12", "--image-size", "16", "--epochs", "1", "--members", "2",
                            "--shape-weights", "disk=1", "--shapes-by-progress", "--progress-floor", "0.5",
                            "--progress-horizon", "2", "--json",
                            "--out", str(tmp_path / "o"))
    assert rc == 0
    summary = json.loads(stdout)
    assert summary["config"]["shapes_by_progress"] and summary["config"]["active"]["shapes_by_progress"]
    assert summary["config"]["active"]["progress_floor"] == 0.5 and summary["config"]["active"]["progress_horizon"] == 2
    active = [p for p in summary["points"] if p["arm"] == "active"]
    assert active[0]["round_shapes"] == {"disk": 4}  # the seed round
    assert active[1]["round_shapes"] == {s: 1 for s in sorted(SHAPES)}  # no progress known yet: one of each
    assert active[1]["round_planners"]["shape-fill"] == 3  # only disks were collected: three shapes start uniform
    assert sum(active[2]["round_shapes"].values()) == 4
    assert all(p["round_shapes"] == {"disk": 4} for p in summary["points"] if p["arm"] == "uniform")


def test_bench_loop_min_per_shape_floors_the_active_arms_short_rounds(tmp_path, capsys):
    """--min-per-shape reaches the active arm's planner and the JSON; a round its picks leave short (at most two
    disks here, the only shape collected) gets every shape to the floor with uniform starts."""
    rc, stdout, _ = run_cli(capsys, "bench", "loop", "--seeds", "1", "--budget", "16", "--round", "8",
                            "--steps", "12", "--image-size", "16", "--epochs", "1", "--members", "2",
                            "--shape-weights", "disk=1", "--max-shape-share", "0.25", "--min-per-shape", "2",
                            "--json", "--out", str(tmp_path / "o"))
    assert rc == 0
    summary = json.loads(stdout)
    assert summary["config"]["active"]["min_per_shape"] == 2
    active = [p for p in summary["points"] if p["arm"] == "active"]
    assert active[0]["round_shapes"] == {"disk": 8}  # the seed round
    assert active[1]["round_shapes"] == {s: 2 for s in sorted(SHAPES)}
    picks = active[1]["round_planners"].get("active", 0)
    assert picks <= 2 and active[1]["round_planners"]["shape-floor"] == 8 - picks
    assert all(p["round_shapes"] == {"disk": 8} for p in summary["points"] if p["arm"] == "uniform")
    assert LoopBenchConfig().to_json()["active"]["min_per_shape"] == 0


@pytest.mark.parametrize("args, message", [
    (("--min-per-shape", "-1"), "argument --min-per-shape: expected an integer >= 0, found -1"),
    (("--min-per-shape", "2", "--shapes-by-progress"), "--min-per-shape and --shapes-by-progress exclude each other"),
])
def test_bench_loop_refuses_a_bad_min_per_shape(tmp_path, capsys, args, message):
    rc, _, err = run_cli(capsys, "bench", "loop", *args, "--out", str(tmp_path / "o"))
    assert rc == 2 and message in err and not (tmp_path / "o").exists()


def test_bench_loop_runs_both_arms_end_to_end_with_physics_in_the_task_space(tmp_path, capsys):
    out = tmp_path / "loop"
    rc, stdout, _ = run_cli(capsys, "bench", "loop", "--seeds", "1", "--budget", "4", "--round", "2",
                            "--steps", "12", "--image-size", "16", "--epochs", "1", "--members", "2",
                            "--random-physics", "--within-policy", "--json", "--out", str(out))
    assert rc == 0
    summary = json.loads(stdout)
    assert summary["config"]["random_physics"] and summary["config"]["within_policy"]
    assert (out / "loop.png").is_file()
    assert [(p["arm"], p["episodes"]) for p in summary["points"]] == [
        ("active", 2), ("active", 4), ("uniform", 2), ("uniform", 4)]
    assert all(math.isfinite(p["h1_mse"]) and math.isfinite(p["h5_mse"]) for p in summary["points"])
    defaults = {k: d for k, (_, _, d) in PHYSICS_RANGES.items()}
    for arm in ARMS:
        catalog = Catalog(out / "seed0" / arm)
        evals = [catalog.meta(r.episode_id).physics for r in catalog.list(split="eval")]
        assert catalog.eval_split().params["random_physics"]
        assert len({tuple(sorted(p.items())) for p in evals}) == len(evals)  # each eval episode its own draw
        train = [catalog.meta(r.episode_id) for r in sorted(catalog.list(split="train"), key=lambda r: r.episode_id)]
        assert len(train) == 4 and all(m.physics != defaults for m in train)
        first_round = [m.physics for m in train[:2]]
        kept = [m.physics in first_round for m in train[2:]]
        # The active arm plans its second round at states of the first, keeping their physics; the
        # uniform arm draws new physics for every episode.
        assert any(kept) if arm == "active" else not any(kept)


@pytest.mark.parametrize("size", range(8, 129, 8))
def test_object_pixels_are_the_objects_at_every_frame_size(size):
    scene = scene_colours(size)
    empty = torch.from_numpy(_background(size).copy()).permute(2, 0, 1).float() / 255
    assert not colour_mask(empty, OBJECT_COLOURS, scene).any()  # table, walls and their edges
    sim = PushSim(image_size=size)
    sim.reset(SimState(shape="T", agent=(100.0, 100.0), obj=(300.0, 300.0, 0.3)))
    frame = torch.from_numpy(sim.render()).permute(2, 0, 1).float() / 255
    mask = colour_mask(frame, OBJECT_COLOURS, scene)
    agent = sim.render().astype(int)
    pusher = (np.abs(agent - np.array(AGENT_RGB)).sum(axis=-1) == 0)  # the pusher's pure-colour pixels
    assert mask.any() and not mask.numpy()[pusher].any()


def test_the_random_signal_ranks_the_steps_disagreement_scores_at_random_and_alike_in_every_run(tmp_path):
    """``--signal random``: the ablation with the planner's structure and no model score."""
    import dataclasses as dc

    from orchestrator.champion import ChampionScorer
    from orchestrator.loopbench import SignalScorer
    from storage.models import ModelRegistry
    from tests.orchestrator.test_champion import _promoted
    from tests.uncertainty.synth import make_episode as synth_episode
    _promoted(ModelRegistry(tmp_path), 0, 0.02)
    champion = ChampionScorer(tmp_path)
    ep = synth_episode(0, steps=12, size=16)
    other = dc.replace(ep, meta=dc.replace(ep.meta, episode_id="another"))
    scores = SignalScorer(champion, "random", 1)(ep).per_step
    plain = SignalScorer(champion, "disagreement", 1)(ep).per_step
    assert np.array_equal(np.isnan(scores), np.isnan(plain)) and np.isnan(scores).any()
    valid = scores[~np.isnan(scores)]
    assert ((valid >= 0) & (valid < 1)).all() and not np.allclose(valid, plain[~np.isnan(plain)])
    assert np.array_equal(SignalScorer(ChampionScorer(tmp_path), "random", 1)(ep).per_step, scores, equal_nan=True)
    assert not np.array_equal(SignalScorer(champion, "random", 1)(other).per_step, scores, equal_nan=True)


def test_the_error_and_variance_head_signals_rank_by_what_they_name(tmp_path):
    """``--signal error``: the champion's actual error; ``predicted``/``total``: its variance head's."""
    from orchestrator.champion import ChampionScorer
    from orchestrator.loopbench import SignalScorer
    from storage.models import ModelRegistry
    from tests.uncertainty.synth import make_episode as synth_episode
    from uncertainty.checkpoint import save_candidate
    from uncertainty.ensemble import Ensemble
    from uncertainty.model import PredictorConfig
    from uncertainty.score import predicted_variance, prediction_error
    registry = ModelRegistry(tmp_path)
    ens = Ensemble(PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8, predict_variance=True),
                   members=2, seed=0)
    ens.set_action_stats([256.0, 250.0], [100.0, 90.0])
    assert registry.promote(save_candidate(registry, ens, {"h1_mse": 0.02}, "snap", "split")).promoted
    champion = ChampionScorer(tmp_path)
    ep = synth_episode(0, steps=12, size=16)
    assert champion.reload() is not None and champion.ensemble is not None
    error = SignalScorer(champion, "error", 1)(ep).per_step
    np.testing.assert_array_equal(error, prediction_error(champion.ensemble, ep.frames, ep.actions))
    assert not np.array_equal(
        error, SignalScorer(champion, "disagreement", 1)(ep).per_step, equal_nan=True)
    np.testing.assert_array_equal(SignalScorer(champion, "error", 3)(ep).per_step,
                                  prediction_error(champion.ensemble, ep.frames, ep.actions, horizon=3))
    predicted = SignalScorer(champion, "predicted", 1)(ep).per_step
    total = SignalScorer(champion, "total", 1)(ep).per_step
    np.testing.assert_array_equal(predicted, predicted_variance(champion.ensemble, ep.frames, ep.actions))
    np.testing.assert_array_equal(total, predicted_variance(champion.ensemble, ep.frames, ep.actions, total=True))
    valid = ~np.isnan(total)
    assert valid.any() and (total[valid] > predicted[valid]).all()


def test_bench_loop_prints_the_paired_difference_that_summary_json_holds(tmp_path, capsys):
    out = tmp_path / "loop"
    rc, stdout, err = run_cli(capsys, "bench", "loop", "--seeds", "2", "--budget", "4", "--round", "2", "--steps", "12",
                              "--image-size", "16", "--epochs", "1", "--members", "2", "--out", str(out))
    assert rc == 0, err
    summary = json.loads((out / "summary.json").read_text())
    for metric in ("h1", "h5"):
        paired = summary[metric]["paired"]
        finals = [(p["active_final"], p["uniform_final"]) for p in summary[metric]["per_seed"]]
        assert paired["per_seed"] == pytest.approx([a / u - 1 for a, u in finals]) and paired["seeds"] == 2
        assert paired["active_behind"] == sum(a > u for a, u in finals)
        line = (f"active's final over uniform's, per seed: {paired['mean']:+.2%} ± {paired['std']:.2%} "
                f"(active behind in {paired['active_behind']} of 2 seeds)")
        assert line in stdout
