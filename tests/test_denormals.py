"""Speed-ups for a nearly deterministic policy that must change no learning (docs/tuning.md, session 32).

Training flushes denormal floats to zero in every thread that computes (`bitcomm.policies.denormals`) and puts the
thread's mode back after; `probabilities` floors log-probabilities at e^-80 before `exp`, whose input below -87
takes the CPU's slow path, and a probability that small changes no sum it enters.
"""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from bitcomm.learn.beside import critic_beside_policy
from bitcomm.policies.denormals import ENV_VAR, denormals_flushed, flush_denormals
from bitcomm.policies.heads import SMALLEST_LOG_PROB, make_head, marginal_entropy, probabilities
from bitcomm.policies.reference import OraclePolicy


def _cpu_can_flush() -> bool:
    supported = torch.set_flush_denormal(True)
    torch.set_flush_denormal(False)
    return supported


needs_flushing = pytest.mark.skipif(not _cpu_can_flush(), reason="this CPU has no flush-to-zero mode")


@needs_flushing
def test_training_flushes_denormals_and_puts_the_thread_s_mode_back(monkeypatch):
    assert not denormals_flushed()
    with flush_denormals():
        assert denormals_flushed()
        assert torch.full((1,), 1e-39).mul(1.0).item() == 0.0  # a denormal reads as zero
    assert not denormals_flushed()
    torch.set_flush_denormal(True)  # a mode set before is the mode after
    try:
        with flush_denormals():
            pass
        assert denormals_flushed()
    finally:
        torch.set_flush_denormal(False)
    monkeypatch.setenv(ENV_VAR, "0")  # the opt-out leaves the CPU alone
    with flush_denormals():
        assert not denormals_flushed()


@needs_flushing
@pytest.mark.parametrize("flushing", [True, False])
def test_the_critic_s_helper_thread_computes_in_the_trainer_s_mode(flushing):
    """The critic's step runs on a helper thread (bitcomm.learn.beside); in another mode than the policy's it
    would make a two-thread run differ from the one-thread run wherever a denormal occurs. The helper takes the
    mode the trainer had when the pair was set up, not whatever its thread would inherit when it starts."""
    learner = types.SimpleNamespace(helper=None)
    torch.set_flush_denormal(flushing)
    try:
        with critic_beside_policy(learner, 2):
            assert learner.helper is not None
            torch.set_flush_denormal(not flushing)  # the helper's thread starts at its first task, after this
            assert learner.helper.submit(denormals_flushed).result() is flushing
    finally:
        torch.set_flush_denormal(False)


@needs_flushing
def test_evaluation_flushes_denormals_as_training_does():
    """`bitcomm eval` and every other measure go through `evaluate`: it plays in training's mode (so it measures
    what a run's own checks measured) and leaves the caller's mode as it found it."""
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.policies.evaluation import evaluate

    modes = []

    def policy(obs):
        modes.append(denormals_flushed())
        return OraclePolicy(task)(obs)

    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))
    evaluate(policy, task, episodes=8)
    assert modes and all(modes) and not denormals_flushed()


def test_probabilities_are_exp_down_to_e_minus_80_and_floored_below():
    logp = torch.tensor([0.0, -1.0, -79.9, -80.0, -87.5, -300.0, -1e9])
    p = probabilities(logp)
    assert torch.equal(p[:4], logp[:4].exp())
    assert torch.equal(p[4:], torch.full((3,), float(np.exp(SMALLEST_LOG_PROB)), dtype=torch.float32))
    assert (p > 0).all() and torch.isfinite(p).all()


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
def test_a_near_deterministic_head_s_entropies_are_what_they_were_without_the_floor(name):
    """Logits as sharp as a trained head's (tens): most of the 2^K messages have log-probabilities below -87,
    and the marginal entropy, each message's entropy and their gradients match float64 without any floor."""
    head = make_head(name, 7)
    gen = torch.Generator().manual_seed(0)
    logits = (40.0 * torch.randn(64, head.out_features, generator=gen)).requires_grad_()
    exact = logits.detach().double().requires_grad_()
    log_p = head.log_prob_of_terms(head.log_prob_terms(exact))
    assert (log_p < -87).float().mean() > 0.5  # the case the floor is for
    p = log_p.exp().mean(0)
    exact_marginal = -(p * p.clamp(min=1e-300).log()).sum()
    exact_entropy = -(log_p.exp() * log_p).sum(-1).mean()
    pairs = ((marginal_entropy(head, logits), exact_marginal), (head.entropy(logits).mean(), exact_entropy))
    for ours, theirs in pairs:
        (g_ours,) = torch.autograd.grad(ours, logits)
        (g_theirs,) = torch.autograd.grad(theirs, exact, retain_graph=True)
        assert ours.item() == pytest.approx(theirs.item(), abs=1e-5)
        assert torch.allclose(g_ours.double(), g_theirs, atol=1e-6)
