"""Which critic feeds which advantage (SPEC sections 3-4), and which gradients reach the policy heads (section 7).

The estimators' formulas are checked in test_estimators.py on hand-built baselines; here the baselines
come from the learner itself, through a probe critic whose value spells out what it was shown (the agent
it judges, the actions it was given, the bits that agent received). So a learner that fed the message
advantage the *sender's* V2 instead of the recipient's, or showed V1 another agent's messages or actions,
produces baselines that differ from the ones the spec names, and these tests fail.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from bitcomm.channel.core import bits_to_index
from bitcomm.checkpoint import load_weights
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from bitcomm.learn.config import ENTROPY_WEIGHTS, make_train_config, spare_words
from bitcomm.learn.estimators import Advantages, EstimatorBatch, get_estimator
from bitcomm.learn.learner import Learner
from bitcomm.learn.rollout import Collector, Rollout
from bitcomm.learn.run import train
from bitcomm.policies.heads import MAX_MARGINAL_BITS

BITS = 2
TWO = TaskConfig(EnvConfig(size=4, max_steps=12), ChannelConfig(bits=BITS))
FOUR = TaskConfig(EnvConfig(size=4, max_steps=12), ChannelConfig(bits=4))
"""TWO with enough bits for the oracle to name every cell."""
# three agents in a ring, agent 0 sending to both others: a message with two recipients
THREE = TaskConfig(
    EnvConfig(size=4, n_agents=3, max_steps=12), ChannelConfig(bits=BITS, recipients=((1, 2), (2,), (0,)), delay=2)
)
LOSSY = TaskConfig(EnvConfig(size=4, max_steps=12), ChannelConfig(bits=BITS, drop_prob=0.5))
"""TWO with half the messages dropped: the improved estimator must see which."""


class ProbeCritic(nn.Module):
    """V = a number that encodes (judged agent, given agents' actions, received bits) one to one."""

    def __init__(self, n: int, with_message: bool) -> None:
        super().__init__()
        self.n_agents, self.with_message = n, with_message
        self.zero = nn.Parameter(torch.zeros(()))  # so the critic's optimizer and loss still work

    def state_features(self, state: torch.Tensor) -> torch.Tensor:
        return torch.zeros(state.shape[0], 1)

    def value(
        self,
        features: torch.Tensor,
        viewpoint: torch.Tensor,
        moves: torch.Tensor,
        given: torch.Tensor,
        received: torch.Tensor | None = None,
    ) -> torch.Tensor:
        return probe_value(viewpoint, moves, given, received if self.with_message else None) + self.zero


def probe_value(
    viewpoint: torch.Tensor, moves: torch.Tensor, given: torch.Tensor, received: torch.Tensor | None
) -> torch.Tensor:
    """Base-6 digits for the given actions (0: not given, 1..5: the move), then the received slots and the agent."""
    n = moves.shape[-1]
    digits = torch.where(given, moves + 1, 0)
    code = (digits * 6 ** torch.arange(n)).sum(-1)
    if received is not None:
        heard = bits_to_index(received.long()).view(received.shape[0], -1)  # (N, slots)
        code = code + 6**n * (heard * (1 << BITS) ** torch.arange(heard.shape[1])).sum(-1)
    return (code * 8 + viewpoint).float()  # exact: well below 2^24


def learner_with_probe(task: TaskConfig, estimator: str, seed: int = 0) -> tuple[Learner, Rollout]:
    torch.manual_seed(seed)
    cfg = make_train_config("reinforced", task, estimator=estimator, num_envs=6, adv_norm=False)
    learner = Learner(cfg)
    learner.critic = ProbeCritic(task.env.n_agents, with_message=estimator == "standard")
    rollout = Collector(task, 6).collect(learner.policy, np.random.SeedSequence(seed), torch.Generator().manual_seed(1))
    return learner, rollout


def expected_advantages(learner: Learner, ro: Rollout, estimator: str) -> Advantages:
    """The advantages SPEC section 4 names, with the probe's values computed here, step by step."""
    task = learner.cfg.task
    n, T, B = task.env.n_agents, *ro.valid.shape
    recipients = task.recipient_lists
    b_action, b_message = torch.zeros(T, B, n), torch.zeros(T, B, n)
    for t, b in zip(*ro.valid.nonzero(as_tuple=True), strict=True):
        moves = ro.moves[t, b][None]
        for j in range(n):
            others = torch.tensor([[k != j for k in range(n)]])
            heard = ro.received[t, b, j][None] if estimator == "standard" else None  # j's own inbox
            b_action[t, b, j] = probe_value(torch.tensor([j]), moves, others, heard)[0]
            # the message j sent arrives with its recipients: their actions are not given
            not_recipients = torch.tensor([[k not in recipients[j] for k in range(n)]])
            b_message[t, b, j] = probe_value(torch.tensor([recipients[j][0]]), moves, not_recipients, None)[0]
    batch = EstimatorBatch(ro.rewards, ro.done, ro.valid, b_action, b_message, ro.dropped)
    return get_estimator(estimator)(batch, learner.cfg.gamma, task.channel.delay)


@pytest.mark.parametrize(
    "task", [TWO, THREE, LOSSY], ids=["two agents", "three agents, two recipients", "dropped messages"]
)
@pytest.mark.parametrize("estimator", ["standard", "improved"])
def test_each_advantage_comes_from_the_critic_query_the_spec_names(task: TaskConfig, estimator: str) -> None:
    learner, ro = learner_with_probe(task, estimator)
    assert ro.dropped.any() == (task.channel.drop_prob > 0)
    got, want = learner.advantages(ro), expected_advantages(learner, ro, estimator)
    torch.testing.assert_close(got.returns, want.returns)
    torch.testing.assert_close(got.action, want.action, rtol=0, atol=1e-3)
    torch.testing.assert_close(got.message, want.message, rtol=0, atol=1e-3)


def test_the_probe_tells_the_wrong_wirings_apart() -> None:
    """The two mistakes the tests above must catch change the baselines on this batch."""
    learner, ro = learner_with_probe(TWO, "improved")
    want = expected_advantages(learner, ro, "improved")
    it, ib = ro.valid.nonzero(as_tuple=True)
    b_action, _ = learner.baselines(ro, it, ib)
    # (a) the improved message advantage taking the sender's own V2 instead of the recipient's
    own = EstimatorBatch(ro.rewards, ro.done, ro.valid, b_action, b_action, ro.dropped)
    wrong = get_estimator("improved")(own, learner.cfg.gamma, TWO.channel.delay)
    assert not torch.allclose(wrong.message, want.message, atol=1e-3)
    # (b) V1 reading the other agent's inbox, or the agent's own action
    learner, ro = learner_with_probe(TWO, "standard")
    state, moves, received = ro.state[it, ib], ro.moves[it, ib], ro.received[it, ib]
    right = learner.critic_values(state, moves, received, *learner._action_queries())
    swapped = learner.critic_values(state, moves, received.flip(1), *learner._action_queries())
    own_action = learner.critic_values(state, moves, received, torch.arange(2), torch.ones(2, 2, dtype=torch.bool))
    assert not torch.equal(right, swapped) and not torch.equal(right, own_action)


@pytest.mark.parametrize(
    ("task", "estimator"),
    [(TWO, "standard"), (THREE, "improved"), (THREE, "standard")],
    ids=["V1", "V2, two recipients", "V1, two recipients"],
)
def test_the_critic_regresses_every_query_it_answers_on_the_return_of_its_step(
    task: TaskConfig, estimator: str
) -> None:
    """SPEC section 3: the critics are trained by mean squared error against Q_t. An update step on the episodes
    of some columns regresses every query of theirs (each agent's action baseline and, for V2 where a message has
    several recipients, each sender's message baseline; V1 is asked no message baseline, since the standard
    estimator reads none) on the return of the same step and episode."""
    learner, ro = learner_with_probe(task, estimator)
    adv = learner.advantages(ro)
    cols = torch.tensor([4, 1])
    recipients, n = task.recipient_lists, task.env.n_agents
    errors = []
    for t, b in zip(*ro.valid.nonzero(as_tuple=True), strict=True):
        if b not in cols:
            continue
        moves = ro.moves[t, b][None]
        for j in range(n):
            heard = ro.received[t, b, j][None] if estimator == "standard" else None
            v = probe_value(torch.tensor([j]), moves, torch.tensor([[k != j for k in range(n)]]), heard)
            errors.append(v - adv.returns[t, b])
        if estimator == "improved" and any(len(r) > 1 for r in recipients):
            for j in range(n):
                not_recipients = torch.tensor([[k not in recipients[j] for k in range(n)]])
                v = probe_value(torch.tensor([recipients[j][0]]), moves, not_recipients, None)
                errors.append(v - adv.returns[t, b])
    want = torch.cat(errors).double().pow(2).mean().item()
    got = learner._step(ro, adv, cols, None)[0]["losses/value"]
    assert got == pytest.approx(want, rel=1e-5)


def test_adv_norm_divides_each_head_s_advantages_by_their_own_spread() -> None:
    """`adv_norm`: the action and the message advantages are each divided by their standard deviation over the
    valid steps, so both reach the policy with spread 1 and their signs and ratios unchanged."""
    learner, ro = learner_with_probe(LOSSY, "improved")
    raw = learner.advantages(ro)
    learner.cfg = dataclasses.replace(learner.cfg, adv_norm=True)
    normed = learner.advantages(ro)
    for got, plain in ((normed.action, raw.action), (normed.message, raw.message)):
        std = plain[ro.valid].std()
        torch.testing.assert_close(got, plain / (std + 1e-8))
        assert got[ro.valid].std().item() == pytest.approx(1.0, rel=1e-4)
    assert not torch.allclose(raw.action[ro.valid].std(), raw.message[ro.valid].std())  # the check has power


# ------------------------------------------------------------------------------------------------ SPEC section 7


def policy_gradients_after_one_step(
    recipe: str, zero_advantages: bool, progress: float = 0.0, **weights: float
) -> dict[str, torch.Tensor]:
    """The policy's gradient of one update step at `progress` of the schedules, with every entropy-type weight at
    zero but `weights`."""
    torch.manual_seed(0)
    cfg = make_train_config(recipe, TWO, num_envs=8, **{**dict.fromkeys(ENTROPY_WEIGHTS, 0.0), **weights})
    learner = Learner(cfg)
    learner.progress = progress
    ro = Collector(TWO, 8).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    adv = learner.advantages(ro)
    if zero_advantages:
        adv = Advantages(torch.zeros_like(adv.action), torch.zeros_like(adv.message), adv.returns)
    learner._step(ro, adv, torch.arange(8), None)
    return {
        name: p.grad if p.grad is not None else torch.zeros_like(p) for name, p in learner.policy.named_parameters()
    }


@pytest.mark.parametrize("recipe", ["reinforced", "paper"])
def test_pure_recipes_give_the_policy_no_gradient_but_the_estimators(recipe: str) -> None:
    silent = policy_gradients_after_one_step(recipe, zero_advantages=True)
    assert all(torch.count_nonzero(g) == 0 for g in silent.values()), [n for n, g in silent.items() if g.any()]
    moved = policy_gradients_after_one_step(recipe, zero_advantages=False)
    for head in ("move_logits.weight", "message_logits.weight"):
        assert moved[head].abs().sum() > 0, head
    assert make_train_config(recipe).pure


@pytest.mark.parametrize(
    ("option", "weight"),
    [("entropy_message_marginal", 0.1), ("message_divergence", 1.0), ("message_logit_decay", 0.001)],
)
def test_the_bonuses_on_the_senders_code_reach_the_message_head_alone(option: str, weight: float) -> None:
    """The marginal message entropy, the nearby goals' divergence and the logit decay are terms of the senders' own
    message distributions: without advantages they move the message head and leave the movement head still, as
    the per-message entropy bonus does; the recipe stays pure."""
    grads = policy_gradients_after_one_step("reinforced", zero_advantages=True, **{option: weight})
    assert grads["message_logits.weight"].abs().sum() > 0
    assert torch.count_nonzero(grads["move_logits.weight"]) == 0
    assert make_train_config("reinforced", **{option: weight}).pure


@pytest.mark.parametrize(
    ("option", "head", "other"),
    [
        ("sharpen_messages", "message_logits.weight", "move_logits.weight"),
        ("sharpen_moves", "move_logits.weight", "message_logits.weight"),
    ],
)
def test_sharpening_reaches_its_own_head_alone(option: str, head: str, other: str) -> None:
    """The late entropy penalties (`sharpen_messages`, `sharpen_moves`) are entropy terms too: at the schedule's
    end, without advantages, each moves its own head and leaves the other still; the recipe stays pure."""
    grads = policy_gradients_after_one_step("reinforced", zero_advantages=True, progress=1.0, **{option: 0.03})
    assert grads[head].abs().sum() > 0
    assert torch.count_nonzero(grads[other]) == 0
    assert make_train_config("reinforced", **{option: 0.03}).pure


@pytest.mark.parametrize("reads", ["observed", "all"])
def test_either_message_head_is_taught_by_the_estimators_alone(reads: str) -> None:
    """`message_reads` `observed` (the recipe's) gives the message head layers of its own, `all` (the paper's
    Fig. 2) reads the layers the move head reads: either way the policy moves only with advantages, and then does."""
    silent = policy_gradients_after_one_step("reinforced", zero_advantages=True, message_reads=reads)
    assert all(torch.count_nonzero(g) == 0 for g in silent.values()), [n for n, g in silent.items() if g.any()]
    moved = policy_gradients_after_one_step("reinforced", zero_advantages=False, message_reads=reads)
    assert moved["message_logits.weight"].abs().sum() > 0
    assert ("message_trunk.0.weight" in moved) == (reads == "observed")
    assert make_train_config("reinforced", message_reads=reads).pure


def test_the_supervised_recipe_reaches_the_message_head_without_advantages() -> None:
    """The check above can fail: the auxiliary losses teach the sender with no advantage at all."""
    grads = policy_gradients_after_one_step("supervised", zero_advantages=True)
    assert grads["message_logits.weight"].abs().sum() > 0
    assert not make_train_config("supervised").pure


def test_greedy_senders_send_their_most_likely_message_and_teach_the_message_head_nothing() -> None:
    """`greedy_senders`: in the batch's first columns every sender sends its most likely bits (moves sampled), and
    those messages get no advantage, so the message head learns from sampled messages alone; the receivers' moves in
    those episodes keep theirs. With every column greedy and no entropy weight, the message head gets no gradient
    and the movement head does."""
    torch.manual_seed(0)
    cfg = make_train_config("reinforced", TWO, num_envs=8, **dict.fromkeys(ENTROPY_WEIGHTS, 0.0))
    learner = Learner(cfg)
    collector = Collector(TWO, 8)
    ro = collector.collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0), 3)
    assert ro.sent_greedy.tolist() == [True] * 3 + [False] * 5
    it, ib = ro.valid.nonzero(as_tuple=True)
    with torch.no_grad():
        _, logits = learner.policy(ro.planes[it, ib].flatten(0, 1), ro.received[it, ib].flatten(0, 1))
    mode = learner.policy.head.mode(logits).view(it.shape[0], -1, BITS)
    greedy = ro.sent_greedy[ib]
    assert torch.equal(ro.bits[it, ib][greedy], mode[greedy])
    assert not torch.equal(ro.bits[it, ib][~greedy], mode[~greedy])  # the others are samples
    adv, plain = learner.advantages(ro), learner.advantages(ro._replace(sent_greedy=torch.zeros(8, dtype=torch.bool)))
    assert (adv.message[:, :3] == 0).all() and torch.equal(adv.message[:, 3:], plain.message[:, 3:])
    assert torch.equal(adv.action, plain.action) and adv.action[:, :3].abs().sum() > 0

    every = collector.collect(learner.policy, np.random.SeedSequence(1), torch.Generator().manual_seed(1), 8)
    learner._step(every, learner.advantages(every), torch.arange(8), None)
    grads = {name: p.grad for name, p in learner.policy.named_parameters()}
    assert grads["message_logits.weight"] is None or torch.count_nonzero(grads["message_logits.weight"]) == 0
    assert grads["move_logits.weight"].abs().sum() > 0
    assert make_train_config("reinforced", greedy_senders=0.5).pure


def test_greedy_senders_start_at_their_point_of_the_schedule() -> None:
    cfg = make_train_config("reinforced", TWO, num_envs=8, episodes=1000, greedy_senders=0.25, greedy_senders_from=0.5)
    assert [cfg.greedy_sender_episodes(e) for e in (0, 499, 500, 1000)] == [0, 0, 2, 2]
    assert make_train_config("reinforced", TWO, greedy_senders=0.0).greedy_sender_episodes(10**9) == 0
    default = make_train_config("reinforced", TWO, episodes=1000)  # the recipe's: half of each batch from halfway
    assert [default.greedy_sender_episodes(e) for e in (499, 500)] == [0, default.num_envs // 2]
    assert make_train_config("paper", TWO).greedy_senders == make_train_config("supervised", TWO).greedy_senders == 0


def test_greedy_senders_and_held_words_wait_for_the_protocol_to_form() -> None:
    """`senders_wait_below`: until the protocol has formed (`formed` None) neither plays; once it has, each starts at
    the later of its own `_from` and the progress where it formed."""
    cfg = make_train_config(
        "reinforced", FOUR, num_envs=8, episodes=1000, greedy_senders=0.25, held_messages=0.25, held_messages_from=0.2
    )
    assert cfg.senders_wait_below == 1.15  # the recipe's
    for scheduled in (cfg.greedy_sender_episodes, cfg.held_message_episodes):
        assert [scheduled(e, None) for e in (0, 500, 1000)] == [0, 0, 0]
        assert [scheduled(e, 0.7) for e in (500, 699, 700)] == [0, 0, 2]
    assert [cfg.greedy_sender_episodes(e, 0.1) for e in (499, 500)] == [0, 2]  # formed early: from halfway, as before
    assert [cfg.held_message_episodes(e, 0.1) for e in (199, 200)] == [0, 2]


def test_the_recipe_waits_for_the_protocol_only_where_the_oracle_can_play() -> None:
    """The level is a multiple of the oracle's episode length: where the oracle cannot play the task (too few bits to
    name a cell) the recipe starts the senders at their `_from`, and an explicit wait is one error line."""
    assert make_train_config("reinforced", TWO).senders_wait_below == 0.0
    assert make_train_config("paper", FOUR).senders_wait_below == 0.0
    assert make_train_config("supervised", FOUR).senders_wait_below == 0.0
    with pytest.raises(ConfigError, match="invalid senders-wait-below=1.2: needs the oracle"):
        make_train_config("reinforced", TWO, senders_wait_below=1.2)
    with pytest.raises(ConfigError, match="invalid senders-wait-below=-1.0: must be a finite number >= 0"):
        make_train_config("reinforced", FOUR, senders_wait_below=-1.0)


@pytest.mark.parametrize(
    ("size", "bits", "spare"),
    [(10, 7, True), (4, 5, True), (16, 9, True), (4, 4, False), (16, 8, False), (32, 10, False), (4, 3, False)],
)
def test_the_recipe_tells_nearby_goals_apart_only_where_the_channel_has_words_to_spare(
    size: int, bits: int, spare: bool
) -> None:
    """The divergence, held words and logit decay are the recipe's where 2^K exceeds the grid's cells (the paper's
    task: 128 words, 100 cells); where every word must name a goal, or the head reads more than the goal, all three
    are off, and an explicit value still applies."""
    task = TaskConfig(EnvConfig(size=size), ChannelConfig(bits=bits))
    cfg = make_train_config("reinforced", task)
    trio = ("message_divergence", "held_messages", "message_logit_decay")
    assert tuple(getattr(cfg, name) for name in trio) == ((1.0, 0.25, 0.001) if spare else (0.0, 0.0, 0.0))
    assert spare_words(task) is spare
    reads_all = make_train_config("reinforced", task, message_reads="all")
    assert tuple(getattr(reads_all, name) for name in trio) == (0.0, 0.0, 0.0)
    for recipe in ("supervised", "paper"):
        assert not any(getattr(make_train_config(recipe, task), name) for name in trio)
    if bits <= MAX_MARGINAL_BITS:
        assert make_train_config("reinforced", task, message_divergence=0.5, held_messages=0.1).held_messages == 0.1


@pytest.mark.parametrize(
    ("size", "bits", "cut", "supervised"),
    [
        (4, 4, 32, 64),
        (10, 7, 32, 64),
        (16, 8, 32, 64),
        (17, 9, 32, 64),
        (18, 9, 54, 64),
        (32, 10, 96, 64),
        (34, 11, 102, 102),
    ],
)
def test_the_recipe_s_training_cut_lets_an_agent_cross_the_grid(
    size: int, bits: int, cut: int, supervised: int
) -> None:
    """A cut shorter than the corner-to-corner path (2 (size - 1) moves) ends episodes the oracle itself could not
    finish: there a recipe's cut is 3 steps per cell of the grid's side. A typed cut stands; `paper` plays whole
    episodes."""
    task = TaskConfig(EnvConfig(size=size), ChannelConfig(bits=bits))
    assert make_train_config("reinforced", task).train_max_steps == cut
    assert make_train_config("supervised", task).train_max_steps == supervised
    assert make_train_config("paper", task).train_max_steps == 0
    assert make_train_config("reinforced", task, train_max_steps=24).train_max_steps == 24


def test_greedy_senders_keep_their_fraction_of_the_run_where_a_batch_cannot_hold_it() -> None:
    one = make_train_config("reinforced", TWO, num_envs=1, minibatches=1, episodes=1000)  # the paper's batches
    assert [one.greedy_sender_episodes(e) for e in range(500, 506)] == [0, 1, 0, 1, 0, 1]
    odd = make_train_config("reinforced", TWO, num_envs=5, episodes=1000, greedy_senders=0.3, greedy_senders_from=0.0)
    played = [odd.greedy_sender_episodes(e) for e in range(0, 1000, 5)]
    assert set(played) == {1, 2} and sum(played) == 300


def test_held_messages_send_the_word_drawn_at_the_first_step_and_are_credited_like_any_sample() -> None:
    """`held_messages`: in the columns after the greedy senders' ones each sender draws a word at the episode's first
    step and sends it at every step; the recorded log-probability is the held word's under the head (so an update's
    first ratio is 1), and the estimator credits those messages as it credits sampled ones."""
    torch.manual_seed(0)
    cfg = make_train_config("reinforced", TWO, num_envs=8, **dict.fromkeys(ENTROPY_WEIGHTS, 0.0))
    learner = Learner(cfg)
    ro = Collector(TWO, 8).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0), 2, 3)
    assert ro.sent_greedy.tolist() == [True] * 2 + [False] * 6
    with torch.no_grad():
        logits = learner.policy.observed_message_logits(ro.planes[0].flatten(0, 1)).view(8, -1, BITS)
    head = learner.policy.head
    for b in range(8):
        sent = ro.bits[ro.valid[:, b], b]  # (steps, n, K)
        assert bool((sent == sent[0]).all()) == (b < 5), b  # greedy and held columns send one word; sampled do not
        logp = head.log_prob(logits[b].expand(len(sent), -1, -1), sent)
        assert torch.allclose(ro.logp_message[ro.valid[:, b], b], logp)
    held_words = ro.bits[0, 2:5]
    assert not torch.equal(held_words, head.mode(logits[2:5]))  # draws, not the most likely words
    adv, plain = learner.advantages(ro), learner.advantages(ro._replace(sent_greedy=torch.zeros(8, dtype=torch.bool)))
    assert torch.equal(adv.message[:, 2:], plain.message[:, 2:]) and adv.message[:, 2:5].abs().sum() > 0
    assert make_train_config("reinforced", held_messages=0.25).pure


def test_held_words_are_draws_of_the_message_policy() -> None:
    """Over many episodes of one goal, the held words' bits are 1 as often as the head says."""
    torch.manual_seed(1)
    learner = Learner(make_train_config("reinforced", TWO, num_envs=4000))
    ro = Collector(TWO, 4000).collect(
        learner.policy, np.random.SeedSequence(2), torch.Generator().manual_seed(2), 0, 4000
    )
    with torch.no_grad():
        p = torch.sigmoid(learner.policy.observed_message_logits(ro.planes[0].flatten(0, 1)))
    first = ro.bits[0].flatten(0, 1).float()  # (4000 * n, K)
    assert torch.allclose(first.mean(0), p.mean(0), atol=0.03)


def test_held_messages_follow_their_schedule_and_need_a_head_that_reads_the_goal_alone() -> None:
    cfg = make_train_config("reinforced", TWO, num_envs=8, episodes=1000, held_messages=0.25, held_messages_from=0.2)
    assert [cfg.held_message_episodes(e) for e in (0, 199, 200, 1000)] == [0, 0, 2, 2]
    assert make_train_config("reinforced", TWO).held_message_episodes(10**9) == 0  # off in the recipe
    for bad, flag in [
        (dict(held_messages=0.5, message_reads="all"), "held-messages"),
        (dict(held_messages=1.5), "held-messages"),
        (dict(held_messages_from=0.2), "held-messages-from"),
        (dict(held_messages=0.25, held_messages_from=-1.0), "held-messages-from"),
    ]:
        with pytest.raises(ConfigError, match=f"invalid {flag}="):
            make_train_config("reinforced", TWO, **bad)


@pytest.mark.parametrize("mode", ["sync", "a3c"])
def test_every_trainer_waits_for_the_protocol_before_its_greedy_senders(mode: str, tmp_path: Path) -> None:
    """`senders_wait_below`: a level no run reaches leaves every episode sampled; one any run reaches (100x the
    oracle's length) lets the greedy senders play after the first batches, in the a3c workers as in the sync
    trainer (the a3c main process watches the rolling length and tells its workers; Ray's driver passes it with
    each batch: tests/test_ray.py)."""
    import csv

    def sampled_everywhere(level: float) -> bool:
        cfg = make_train_config(
            "reinforced", FOUR, num_envs=8, episodes=128, mode=mode, workers=2, checkpoint_seconds=1e9,
            greedy_senders=1.0, greedy_senders_from=0.0, senders_wait_below=level,
        )  # fmt: skip
        out = tmp_path / str(level)
        train(cfg, out, progress=False)
        with (out / "metrics.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
        formed = [r["schedule/protocol_formed"] for r in rows]  # the log says from where they may play
        assert formed == sorted(formed) and (formed[-1] == "1.0") == (level > 1)
        return all(r["charts/episode_length_sampled_rolling"] == r["charts/episode_length_rolling"] for r in rows)

    assert sampled_everywhere(0.01)
    assert not sampled_everywhere(100.0)


@pytest.mark.parametrize("mode", ["sync", "a3c"])
def test_every_trainer_plays_the_greedy_senders_of_its_schedule(mode: str, tmp_path: Path) -> None:
    """With every sender greedy from the first batch and no entropy weight, a whole run leaves the message head as
    it began and trains the moves: the sync trainer and the a3c workers both hand the collector the schedule's
    greedy episodes (Ray's actors: tests/test_ray.py)."""
    cfg = make_train_config(
        "reinforced", TWO, num_envs=8, episodes=32, mode=mode, workers=2, checkpoint_seconds=1e9,
        greedy_senders=1.0, greedy_senders_from=0.0, **dict.fromkeys(ENTROPY_WEIGHTS, 0.0),
    )  # fmt: skip
    torch.manual_seed(cfg.seed)
    start = Learner(cfg).policy.state_dict()
    end = load_weights(train(cfg, tmp_path, progress=False))[0]["policy"]
    message = [k for k in start if k.startswith(("message_trunk", "message_logits"))]
    assert message and all(torch.equal(start[k], end[k]) for k in message)
    assert not torch.equal(start["move_logits.weight"], end["move_logits.weight"])
