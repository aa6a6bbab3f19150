"""Real learning, at the budget docs/learning.md reports (slow: about 15 minutes on 2 CPU cores).

The raw policy of ``scripts/learning.sh`` on intersection must fail significantly less
often than the random policy on the same 200 held-out episodes (McNemar's exact test).
"""

import pytest
import torch

from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.report import compare
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import greedy_policy, load_policy_network
from latentdrive.rl.train import train_policy

pytestmark = pytest.mark.slow


def test_raw_policy_fails_significantly_less_than_random_on_intersection(tmp_path):
    cfg = PolicyTrainConfig.model_validate({
        "mode": "raw", "scenarios": ["intersection"], "steps": 40_000, "segment": 5000, "eval_episodes": 50,
        "dqn": {"updates_per_transition": 0.5},
    })
    train_policy(cfg, tmp_path / "run", progress=False, say=lambda _l: None)
    net, _ = load_policy_network(tmp_path / "run")
    learned = evaluate_policy(greedy_policy(net, torch.device("cpu")), ["intersection"], 200)
    random = evaluate_policy(reference_policy("random"), ["intersection"], 200)
    test = compare(learned, random)["intersection"]["failed"]
    assert test.rate_a < test.rate_b and test.p_value < 0.05, test
