import subprocess
import sys

import pytest
import torch

from tests.conftest import REPO
from uncertainty.errors import ConfigError
from uncertainty.model import Predictor, PredictorConfig


def test_default_predictor_is_small_and_predicts_a_frame():
    cfg = PredictorConfig()
    net = Predictor(cfg)
    params = sum(p.numel() for p in net.parameters())
    assert 100_000 <= params <= 300_000
    out = net(torch.rand(2, cfg.context, 3, 64, 64), torch.zeros(2, cfg.action_dim))
    assert out.shape == (2, 3, 64, 64)


def test_rollout_feeds_predictions_back():
    cfg = PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8)
    net = Predictor(cfg)
    ctx = torch.rand(3, 2, 3, 16, 16)
    acts = torch.randn(3, 4, 2)
    out = net.rollout(ctx, acts)
    assert out.shape == (3, 4, 3, 16, 16)
    assert out.min() >= 0 and out.max() <= 1
    step2 = net(torch.stack([ctx[:, 1], out[:, 0]], dim=1), acts[:, 1]).clamp(0, 1)
    torch.testing.assert_close(out[:, 1], step2)


@pytest.mark.parametrize("kwargs", [{"image_size": 20}, {"context": 0}, {"widths": (8, 8)}, {"action_hidden": 0},
                                    {"predict_variance": "yes"}])
def test_config_refuses_bad_values(kwargs):
    with pytest.raises(ConfigError):
        PredictorConfig(**kwargs)


def test_config_round_trips_and_refuses_unknown_fields():
    cfg = PredictorConfig(image_size=32, widths=(8, 16, 32))
    assert PredictorConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match="unknown"):
        PredictorConfig.from_dict({**cfg.to_dict(), "depth": 3})
    with_head = PredictorConfig(image_size=32, predict_variance=True)
    assert PredictorConfig.from_dict(with_head.to_dict()) == with_head
    # a checkpoint written before the variance head existed has no such field: no head
    old = {k: v for k, v in cfg.to_dict().items() if k != "predict_variance"}
    assert PredictorConfig.from_dict(old) == cfg and not cfg.predict_variance


def test_variance_head_predicts_a_bounded_log_variance_and_the_same_kind_of_frame():
    net = Predictor(PredictorConfig(image_size=16, widths=(4, 8, 8), predict_variance=True))
    ctx, act = torch.rand(2, 2, 3, 16, 16), torch.randn(2, 2)
    frame, logvar = net(ctx, act, with_variance=True)
    assert frame.shape == logvar.shape == (2, 3, 16, 16)
    torch.testing.assert_close(frame, net(ctx, act))
    assert torch.all((logvar > -14) & (logvar < 0))


def test_wrong_context_shape_is_refused():
    net = Predictor(PredictorConfig(image_size=16, widths=(4, 8, 8)))
    with pytest.raises(ConfigError, match="context must be"):
        net(torch.rand(1, 3, 3, 16, 16), torch.zeros(1, 2))


def test_importing_the_model_turns_tf32_convolutions_off():
    """On CUDA, cuDNN's default TF32 made the fused pass differ from the members one by one by up to 7e-4 (an
    H100, tests/uncertainty/test_cuda.py); every process that loads a model of ours gets full float32."""
    code = "import torch; assert torch.backends.cudnn.allow_tf32; import uncertainty.model; " \
           "print(torch.backends.cudnn.allow_tf32)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr
