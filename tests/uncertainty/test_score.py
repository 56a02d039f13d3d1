import json

import numpy as np
import pytest

from tests.uncertainty.synth import make_episode
from uncertainty.errors import ConfigError
from uncertainty.ensemble import Ensemble
from uncertainty.model import PredictorConfig
from uncertainty.score import (change_disagreement, colour_disagreement, pick_top, predicted_variance,
                               prediction_error, score_episode, state_dict)
from uncertainty.train import evaluate_episodes
from workers.env import SimState


def test_pick_top_keeps_states_apart():
    scores = np.array([np.nan, 9, 8.5, 8, 1, 2, 7, 6.5, 0, np.nan])
    assert pick_top(scores, 3, min_separation=3) == [1, 6]  # nothing else is 3 steps from both
    assert pick_top(scores, 3, min_separation=2) == [1, 3, 6]
    assert pick_top(scores, 10, min_separation=1)[:3] == [1, 2, 3]
    assert pick_top(np.full(4, np.nan), 2, 1) == []


def test_score_episode_gives_what_a_request_needs(trained):
    ens, _ = trained
    ep = make_episode(7, "disk", steps=12)
    result = score_episode(ens, ep, top_k=3, min_separation=3)
    assert result.per_step.shape == (12,) and np.isnan(result.per_step[0]) and np.isnan(result.per_step[-1])
    assert 1 <= len(result.top) <= 3
    steps = [s.step for s in result.top]
    assert all(abs(a - b) >= 3 for i, a in enumerate(steps) for b in steps[i + 1:])
    assert [s.score for s in result.top] == sorted((s.score for s in result.top), reverse=True)
    assert result.top[0].score == pytest.approx(np.nanmax(result.per_step))
    for s in result.top:
        assert len(s.action_prefix) == s.step
        np.testing.assert_allclose(s.action_prefix, ep.actions[:s.step])
        sim = SimState.from_dict(s.state)  # the simulator accepts it as a start state
        np.testing.assert_allclose(sim.to_vector()[:10], ep.states[s.step][:10])
        assert s.start_state == ep.meta.start_state and s.shape == "disk" and s.episode_id == ep.meta.episode_id
    json.dumps(result.to_json())  # JSON-able, NaN steps as null


def test_state_dict_matches_the_simulator_form():
    row = np.arange(11, dtype=float)
    d = state_dict(row, "T", {"mass": 1.0})
    assert d == {"shape": "T", "agent": [0.0, 1.0], "agent_vel": [2.0, 3.0], "object": [4.0, 5.0, 6.0],
                 "object_vel": [7.0, 8.0, 9.0], "physics": {"mass": 1.0}}


def test_bad_arguments_are_refused(trained):
    with pytest.raises(ConfigError):
        score_episode(trained[0], make_episode(0), top_k=-1)


def test_prediction_error_is_the_evals_h1_mse_step_by_step(trained):
    ens, _ = trained
    ep = make_episode(7, "disk", steps=12)
    error = prediction_error(ens, ep.frames, ep.actions)
    np.testing.assert_array_equal(np.isnan(error), np.isnan(ens.disagreement(ep.frames, ep.actions)))
    assert np.nanmean(error) == pytest.approx(evaluate_episodes(ens, [ep], "h", horizons=(1,))["h1_mse"], rel=1e-5)


def test_prediction_error_over_a_horizon_averages_the_mean_rollouts_error(trained):
    import torch
    from uncertainty.ensemble import frames_to_tensor
    ens, _ = trained
    ep = make_episode(7, "disk", steps=12)
    error = prediction_error(ens, ep.frames, ep.actions, horizon=3)
    np.testing.assert_array_equal(np.isnan(error), np.isnan(ens.disagreement(ep.frames, ep.actions, horizon=3)))
    step, c = 4, ens.config.context
    x = frames_to_tensor(ep.frames)
    actions = ens.normalize_actions(torch.as_tensor(ep.actions[step:step + 3], dtype=torch.float32))
    with torch.inference_mode():
        mean = ens.rollout(x[None, step - c + 1:step + 1], actions[None]).mean(dim=0)[0]  # (3, 3, H, W)
    assert error[step] == pytest.approx(float(((mean - x[step + 1:step + 4]) ** 2).mean()), rel=1e-5)


def test_predicted_variance_is_the_evals_step_by_step_and_total_adds_the_disagreement():
    ens = Ensemble(PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8, predict_variance=True),
                   members=3, seed=3)
    ep = make_episode(7, "disk", steps=12)
    predicted = predicted_variance(ens, ep.frames, ep.actions, batch_size=4)  # batches of 4: 10 steps in 3
    total = predicted_variance(ens, ep.frames, ep.actions, total=True)
    plain = ens.disagreement(ep.frames, ep.actions)
    assert np.array_equal(np.isnan(predicted), np.isnan(plain)) and np.isnan(predicted).any()
    assert (predicted[~np.isnan(predicted)] > 0).all()
    np.testing.assert_allclose(total, predicted + plain, rtol=1e-5)
    h1 = evaluate_episodes(ens, [ep], "h", horizons=(1,))
    assert np.nanmean(predicted) == pytest.approx(h1["h1_predicted_variance"], rel=1e-5)


def test_predicted_variance_needs_a_variance_head(trained):
    ep = make_episode(7, "disk", steps=12)
    with pytest.raises(ConfigError, match="no variance head"):
        predicted_variance(trained[0], ep.frames, ep.actions)


def test_change_disagreement_counts_only_pixels_that_move(trained):
    ens, _ = trained
    ep = make_episode(7, "disk", steps=12)
    plain = ens.disagreement(ep.frames, ep.actions)
    masked = change_disagreement(ens, ep.frames, ep.actions, threshold=0.1)
    assert masked.shape == plain.shape
    np.testing.assert_array_equal(np.isnan(masked), np.isnan(plain))  # the same steps have a score
    ok = ~np.isnan(plain)
    assert np.all(masked[ok] >= 0) and np.all(masked[ok] <= plain[ok] + 1e-12)  # a subset of the pixels
    everything = change_disagreement(ens, ep.frames, ep.actions, threshold=-1.0)  # every pixel "moves"
    np.testing.assert_allclose(everything[ok], plain[ok], rtol=1e-5)
    still = ep.frames.copy()
    still[:] = still[0]  # nothing moves in the recording
    assert np.nansum(change_disagreement(ens, still, ep.actions, threshold=1.1)) == 0.0


def test_colour_disagreement_counts_only_the_pixels_of_the_target_colours(trained):
    ens, _ = trained
    ep = make_episode(7, "disk", steps=12)
    plain = ens.disagreement(ep.frames, ep.actions)
    ok = ~np.isnan(plain)
    scene = [tuple(int(c) for c in rgb) for rgb in np.unique(ep.frames.reshape(-1, 3), axis=0)]
    # Every colour of the recording a target: every pixel counts, the plain disagreement.
    everything = colour_disagreement(ens, ep.frames, ep.actions, scene, [(0, 255, 0)], grow=0)
    np.testing.assert_array_equal(np.isnan(everything), np.isnan(plain))
    np.testing.assert_allclose(everything[ok], plain[ok], rtol=1e-5)
    # A colour the recording does not hold, nearer none of its pixels than the rest: nothing counts.
    nothing = colour_disagreement(ens, ep.frames, ep.actions, [(0, 255, 0)], scene)
    assert np.nansum(nothing) == 0.0
    # The background's colour alone (the most common one), grown or not: a part of the pixels.
    colours, counts = np.unique(ep.frames.reshape(-1, 3), axis=0, return_counts=True)
    background = [tuple(int(c) for c in colours[counts.argmax()])]
    rest = [c for c in scene if c != background[0]]
    part = colour_disagreement(ens, ep.frames, ep.actions, background, rest, grow=0)
    grown = colour_disagreement(ens, ep.frames, ep.actions, background, rest, grow=1)
    assert np.all(part[ok] <= grown[ok] + 1e-12) and np.all(grown[ok] <= plain[ok] + 1e-12)
    assert np.any(part[ok] < plain[ok])
    with pytest.raises(ConfigError, match="grow"):
        colour_disagreement(ens, ep.frames, ep.actions, background, rest, grow=-1)
