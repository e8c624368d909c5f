"""Message heads, networks and one learning update: shapes, probabilities and the channel's gradient."""

import dataclasses

import numpy as np
import pytest
import torch

from bitcomm.channel.core import bits_to_index
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from bitcomm.learn.config import make_train_config
from bitcomm.learn.learner import BatchFeatures, Learner
from bitcomm.learn.move_decay import MoveDecay
from bitcomm.learn.rollout import Collector
from bitcomm.learn.run_folder import oracle_level, training_oracle_level
from bitcomm.policies.heads import BitwiseHead, OneHotHead, make_head
from bitcomm.policies.networks import CriticNet, ModelConfig, PolicyNet

TINY = TaskConfig(EnvConfig(size=4, max_steps=20), ChannelConfig(bits=3))


def test_bitwise_log_prob_is_sum_over_independent_bits():
    head = BitwiseHead(3)
    logits = torch.tensor([[0.0, 2.0, -1.0]])
    bits = torch.tensor([[1, 0, 1]], dtype=torch.uint8)
    p = torch.sigmoid(logits)[0]
    expected = torch.log(p[0]) + torch.log(1 - p[1]) + torch.log(p[2])
    assert torch.allclose(head.log_prob(logits, bits), expected[None])


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
def test_heads_are_distributions_over_the_same_2k_messages(name):
    head = make_head(name, 3)
    logits = torch.randn(5, head.out_features)
    all_bits = torch.tensor([[(m >> (2 - k)) & 1 for k in range(3)] for m in range(8)], dtype=torch.uint8)
    logp = torch.stack([head.log_prob(logits, all_bits[m].expand(5, 3)) for m in range(8)], -1)
    assert torch.allclose(logp.exp().sum(-1), torch.ones(5), atol=1e-5)
    entropy = -(logp.exp() * logp).sum(-1)
    assert torch.allclose(head.entropy(logits), entropy, atol=1e-5)
    sample = head.sample(logits, torch.Generator().manual_seed(0))
    assert sample.shape == (5, 3) and sample.dtype == torch.uint8
    assert head.encode(sample).shape == (5, head.in_features)


def test_output_size_grows_linearly_for_bitwise_and_exponentially_for_onehot():
    assert [BitwiseHead(k).out_features for k in (7, 8, 10)] == [7, 8, 10]
    assert [OneHotHead(k).out_features for k in (7, 8, 10)] == [128, 256, 1024]


def test_unknown_head_is_a_config_error():
    with pytest.raises(ConfigError, match="messages='morse'"):
        make_head("morse", 3)


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
def test_straight_through_keeps_the_received_value_and_passes_gradient(name):
    head = make_head(name, 3)
    logits = torch.randn(4, head.out_features, requires_grad=True)
    received = torch.tensor([[1, 0, 1], [0, 0, 0], [1, 1, 1], [0, 1, 0]], dtype=torch.uint8)
    flips = torch.tensor([[0, 0, 1], [0, 0, 0], [1, 0, 0], [0, 0, 0]], dtype=torch.uint8)
    enc = head.straight_through(logits, received, flips)
    assert torch.allclose(enc, head.encode(received))
    enc.sum().backward() if name == "bitwise" else enc[torch.arange(4), bits_to_index(received)].sum().backward()
    assert logits.grad is not None and logits.grad.abs().sum() > 0


def test_policy_and_critics_shapes():
    task = TaskConfig(EnvConfig(size=5, n_agents=3), ChannelConfig(bits=4, recipients=((1, 2), (0,), (0,))))
    net = PolicyNet(task, ModelConfig(coords=True))
    planes = torch.zeros(6, 2, 5, 5)
    received = torch.zeros(6, task.slots, 4, dtype=torch.uint8)
    moves, msg = net(planes, received)
    assert moves.shape == (6, 5) and msg.shape == (6, 4)
    for with_message in (True, False):
        critic = CriticNet(task, ModelConfig(), with_message)
        feats = critic.state_features(torch.zeros(6, 6, 5, 5))
        given = torch.ones(6, 3, dtype=torch.bool)
        v = critic.value(feats, torch.zeros(6, dtype=torch.long), torch.zeros(6, 3, dtype=torch.long), given, received)
        assert v.shape == (6,)


@pytest.mark.parametrize("encoder", ["conv", "marginals"])
@pytest.mark.parametrize("with_message", [True, False])
def test_a_critic_answers_k_queries_per_state_as_it_answers_each_alone(encoder, with_message):
    """`value` computes a state's share of the first layer once for the k queries about it; the answers and
    the gradients are those of one state row per query."""
    task = TaskConfig(EnvConfig(size=5, n_agents=3), ChannelConfig(bits=4, recipients=((1, 2), (0,), (0,))))
    torch.manual_seed(0)
    critic = CriticNet(task, ModelConfig(encoder=encoder), with_message)
    M, k = 7, 4
    state = (torch.rand(M, 6, 5, 5) < 0.1).float()
    queries = (
        torch.tensor([0, 1, 2, 1]).repeat(M),
        torch.randint(0, 5, (M * k, 3)),
        torch.rand(M * k, 3) < 0.5,
        torch.randint(0, 2, (M * k, task.slots, 4), dtype=torch.uint8),
    )
    params = list(critic.parameters())
    shared = critic.value(critic.state_features(state), *queries)
    one_each = critic.value(critic.state_features(state).repeat_interleave(k, 0), *queries)
    assert shared.shape == (M * k,)
    torch.testing.assert_close(shared, one_each)
    grads = torch.autograd.grad(shared.square().sum(), params, allow_unused=True)
    expected = torch.autograd.grad(one_each.square().sum(), params, allow_unused=True)
    for g, e in zip(grads, expected, strict=True):
        assert (g is None) == (e is None)
        if g is not None:
            torch.testing.assert_close(g, e)


@pytest.mark.parametrize("size", [4, 5])
def test_decoded_maps_enter_the_first_convolution_as_a_matrix_product_with_the_same_values_and_gradients(size):
    task = TaskConfig(EnvConfig(size=size, n_agents=3), ChannelConfig(bits=4, recipients=((1, 2), (0,), (0,))))
    net = PolicyNet(task, ModelConfig(coords=True, message_map=True))
    torch.manual_seed(0)
    seen = torch.randn(6, 4, size, size)  # observed planes, then the coordinate planes
    maps = torch.softmax(torch.randn(6, task.slots, size * size), -1).view(6, task.slots, size, size).requires_grad_()
    weights = torch.randn(6, 8, (size + 1) // 2, (size + 1) // 2)
    conv = net.conv[0]
    planes = torch.cat([seen[:, :2], maps, seen[:, 2:]], 1)

    def result(out):
        return out.detach(), torch.autograd.grad((out * weights).sum(), [maps, conv.weight, conv.bias])

    want_out, want_grads = result(conv(planes))
    got_out, got_grads = result(net._first_conv(seen, maps))
    torch.testing.assert_close(got_out, want_out, rtol=1e-5, atol=1e-5)
    for got, want in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    with torch.no_grad():  # acting: the plain convolution
        torch.testing.assert_close(net._first_conv(seen, maps), want_out, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("recipe", ["paper", "reinforced", "supervised"])
@pytest.mark.parametrize("estimator", ["standard", "improved"])
def test_one_update_runs_and_changes_the_policy(recipe, estimator):
    torch.manual_seed(0)
    cfg = make_train_config(recipe, TINY, estimator=estimator, num_envs=8, mode="sync")
    learner, collector = Learner(cfg), Collector(TINY, 8)
    before = [p.detach().clone() for p in learner.policy.parameters()]
    rollout = collector.collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    stats = learner.update(rollout, torch.Generator().manual_seed(0))
    assert all(np.isfinite(v) for v in stats.values())
    assert any(not torch.equal(a, b) for a, b in zip(before, learner.policy.parameters(), strict=True))


@pytest.mark.parametrize("anneal", [True, False])
def test_anneal_lr_scales_every_learning_rate_by_the_budget_left(anneal):
    cfg = make_train_config("reinforced", TINY, num_envs=4, mode="sync", anneal_lr=anneal)
    learner, collector = Learner(cfg), Collector(TINY, 4)
    rollout = collector.collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    decoder = [cfg.map_lr] if cfg.model.message_map else []
    base = [cfg.lr, *decoder, cfg.critic_lr]  # policy, message-map decoder (if any), critic
    for progress in (0.25, 1.0):
        learner.update(rollout, torch.Generator().manual_seed(0), progress=progress)
        lrs = [g["lr"] for opt in (learner.opt_policy, learner.opt_critic) for g in opt.param_groups]
        assert lrs == pytest.approx([b * (1 - progress) if anneal else b for b in base])


def test_the_schedule_follows_anneal_episodes_when_a_run_is_trained_in_pieces():
    """solve.py trains in chunks, each resumed with a larger budget: `anneal_episodes` keeps one schedule."""
    whole = make_train_config("reinforced", TINY, episodes=1000, anneal_lr=True)
    piece = make_train_config("reinforced", TINY, episodes=250, anneal_lr=True, anneal_episodes=1000)
    assert piece.schedule_progress(200) == whole.schedule_progress(200) == 0.2
    assert make_train_config("reinforced", TINY, episodes=250, anneal_lr=True).schedule_progress(200) == 0.8
    assert piece.schedule_progress(5000) == 1.0  # played past the schedule: the rates stay at zero
    with pytest.raises(ConfigError, match="anneal-episodes"):
        make_train_config(  # nothing would anneal
            "reinforced", TINY, anneal_lr=False, anneal_move_entropy=False, anneal_episodes=1000
        )


MOVE_REGULARISERS = ("entropy_move", "uniform_move")
MESSAGE_REGULARISERS = ("entropy_message", "entropy_message_marginal")


@pytest.mark.parametrize(
    "schedules, decayed",
    [
        (dict(anneal_entropy=True, anneal_move_entropy=False), MOVE_REGULARISERS + MESSAGE_REGULARISERS),
        (dict(anneal_entropy=False, anneal_move_entropy=True), MOVE_REGULARISERS),  # the default's
        (dict(anneal_entropy=False, anneal_move_entropy=False), ()),
    ],
)
def test_entropy_schedules_scale_their_regularisers_by_the_budget_left(schedules, decayed):
    """`anneal_entropy` decays every regulariser, `anneal_move_entropy` the move ones alone; the
    policy-gradient term follows neither."""
    cfg = make_train_config("reinforced", TINY, num_envs=4, mode="sync", **schedules)
    learner, collector = Learner(cfg), Collector(TINY, 4)
    rollout = collector.collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    base = {name: getattr(cfg, name) for name in MOVE_REGULARISERS + MESSAGE_REGULARISERS}
    assert cfg.entropy_message_marginal > 0  # the default's: every regulariser is in the terms
    for progress in (0.25, 1.0):
        learner.update(rollout, torch.Generator().manual_seed(0), progress=progress)
        weights = {t.name: t.weight for t in learner.terms if t.name in base}
        assert weights == pytest.approx({k: w * (1 - progress) if k in decayed else w for k, w in base.items()})
        assert [t.name for t in learner.terms][0] == "policy_gradient"


@pytest.mark.parametrize(
    ("option", "term"), [("sharpen_messages", "entropy_message"), ("sharpen_moves", "entropy_move")]
)
def test_sharpening_turns_an_entropy_bonus_into_a_penalty_along_the_schedule(option: str, term: str):
    """`sharpen_messages` / `sharpen_moves` w: that head's entropy weight is its bonus less `w * progress`, a
    bonus at the start and a penalty by the schedule's end; every other term keeps its weight."""
    sharpened, plain = (
        Learner(
            make_train_config(
                "reinforced", TINY, num_envs=4, mode="sync", anneal_move_entropy=False, **{term: 0.01}, **extra
            )
        )
        for extra in ({option: 0.03}, {})
    )
    rollout = Collector(TINY, 4).collect(plain.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    for progress in (0.0, 0.25, 1.0):
        weights = []
        for learner in (sharpened, plain):
            learner.update(rollout, torch.Generator().manual_seed(0), progress=progress)
            weights.append({t.name: t.weight for t in learner.terms if hasattr(t, "weight")})
        assert weights[0].pop(term) == pytest.approx(0.01 - 0.03 * progress)
        assert weights[1].pop(term) == pytest.approx(0.01)
        assert weights[0] == pytest.approx(weights[1])


def test_the_protocol_s_level_is_the_oracle_s_over_episodes_cut_as_training_cuts_them():
    """A rolling training length counts a cut episode's steps up to the cut, so the level it must reach is the
    oracle's multiple over episodes cut the same way."""
    from bitcomm.learn.level_watch import SendersWait

    uncut = make_train_config(seed=0)  # 10x10 cut at 32 steps: no oracle episode is that long
    assert training_oracle_level(uncut) == oracle_level(uncut)
    assert SendersWait.from_config(uncut).threshold == pytest.approx(1.15 * oracle_level(uncut))
    cut = make_train_config(seed=0, train_max_steps=10)  # the oracle's mean 8.17 steps over these, 8.74 uncut
    assert training_oracle_level(cut) < oracle_level(cut)
    assert SendersWait.from_config(cut).threshold == pytest.approx(1.15 * training_oracle_level(cut))  # not 10.06


def test_a_move_decay_from_the_protocols_progress_waits_then_ends_with_the_schedule():
    """`move_decay_below`: whole until the rolling length reaches the threshold, then linear to zero at the
    schedule's end; without it, the budget's decay from the first episode (the default, unchanged)."""
    waiting = MoveDecay(threshold=10.0)
    assert waiting.scale(0.3) == 1.0
    waiting.watch(None, 0.1)  # before the first batch there is no rolling length
    waiting.watch(12.0, 0.2)
    assert waiting.start is None and waiting.scale(0.4) == 1.0
    waiting.watch(10.0, 0.5)
    assert waiting.start == 0.5
    assert [waiting.scale(p) for p in (0.5, 0.75, 1.0)] == pytest.approx([1.0, 0.5, 0.0])
    waiting.watch(30.0, 0.9)  # a relapse does not restart it
    assert waiting.start == 0.5
    from_start = MoveDecay(threshold=None)
    assert [from_start.scale(p) for p in (0.0, 0.25, 1.0)] == [1.0, 0.75, 0.0]

    task = dataclasses.replace(TINY, channel=ChannelConfig(bits=4))
    cfg = make_train_config("reinforced", task, num_envs=4, move_decay_below=2.0)
    learner, collector = Learner(cfg), Collector(task, 4)
    assert learner.move_decay.threshold == pytest.approx(2.0 * training_oracle_level(cfg))
    rollout = collector.collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    base = {name: getattr(cfg, name) for name in MOVE_REGULARISERS + MESSAGE_REGULARISERS}

    def weights() -> dict[str, float]:
        return {t.name: t.weight for t in learner.terms if t.name in base}

    stats = learner.update(rollout, torch.Generator().manual_seed(0), progress=0.5, rolling_length=1e6)
    assert weights() == pytest.approx(base) and stats["schedule/move_scale"] == 1.0
    learner.update(rollout, torch.Generator().manual_seed(0), progress=0.6, rolling_length=0.0)
    learner.update(rollout, torch.Generator().manual_seed(0), progress=0.8, rolling_length=1e6)
    half = {k: w * 0.5 if k in MOVE_REGULARISERS else w for k, w in base.items()}
    assert weights() == pytest.approx(half)


@pytest.mark.parametrize(
    "options, match",
    [
        (dict(move_decay_below=-1.0), "move-decay-below.*>= 0"),
        (dict(move_decay_below=2.0, anneal_move_entropy=False), "anneal-move-entropy"),
        (dict(move_decay_below=2.0, mode="a3c"), "sync mode"),
        (dict(move_decay_below=2.0), "needs the oracle.*bits"),  # 3 bits cannot name 16 cells: no oracle to measure by
    ],
)
def test_a_move_decay_threshold_is_refused_where_it_could_not_act(options, match):
    with pytest.raises(ConfigError, match=match):
        make_train_config("reinforced", TINY, **options)


def test_the_default_recipe_decays_its_learning_rates_over_the_budget():
    assert make_train_config("reinforced", TINY).anneal_lr
    assert not make_train_config("supervised", TINY).anneal_lr  # kept as measured


def test_rollout_holds_whole_first_episodes():
    cfg = make_train_config("paper", TINY, num_envs=16, mode="sync")
    ro = Collector(TINY, 16).collect(PolicyNet(TINY, cfg.model), np.random.SeedSequence(1), torch.Generator())
    assert (ro.valid.sum(0).numpy() == ro.length).all()
    assert (ro.done.sum(0) == 1).all()  # exactly one end per column, at its last valid step
    last = torch.from_numpy(ro.length - 1)
    assert ro.done[last, torch.arange(16)].all()
    assert np.allclose(ro.rewards.masked_fill(~ro.valid, 0).sum(0).numpy(), ro.team_return, atol=1e-4)


@pytest.mark.parametrize("messages", ["bitwise", "onehot"])
def test_the_rollout_records_what_the_policy_did_at_every_step_of_a_first_episode(messages):
    """The policy acts only for slots whose first episode is running; what it recorded at each valid step (the
    log-probabilities of the move and the message it sampled) is what the network gives those very steps."""
    small = TaskConfig(EnvConfig(size=3, max_steps=20), ChannelConfig(bits=3))  # random play often ends early
    cfg = make_train_config("reinforced", small, num_envs=64, messages=messages)
    learner = Learner(cfg)
    collector = Collector(cfg.training_task, 64)
    collector.collect(learner.policy, np.random.SeedSequence(2), torch.Generator())  # its buffers are reused
    ro = collector.collect(learner.policy, np.random.SeedSequence(3), torch.Generator())
    assert len(set(ro.length.tolist())) > 3  # first episodes end at many different steps
    with torch.no_grad():
        logp_move, logp_message = learner.log_probs(ro)
    valid = ro.valid
    assert torch.allclose(logp_move[valid], ro.logp_move[valid], atol=1e-5)
    assert torch.allclose(logp_message[valid], ro.logp_message[valid], atol=1e-5)
    assert (ro.moves[~valid] == 0).all() and (ro.bits[~valid] == 0).all()  # an ended slot stands still, silent


def test_training_episodes_are_truncated_at_train_max_steps_but_the_task_is_not():
    cfg = make_train_config("reinforced", TINY, num_envs=16, train_max_steps=3)
    assert cfg.training_task.env.max_steps == 3 and cfg.task.env.max_steps == 20
    ro = Collector(cfg.training_task, 16).collect(
        PolicyNet(TINY, cfg.model), np.random.SeedSequence(1), torch.Generator()
    )
    assert ro.length.max() <= 3 and ro.planes.shape[0] <= 3
    assert make_train_config("reinforced", TINY, train_max_steps=0).training_task == TINY


def test_a_move_or_message_that_lands_after_train_max_steps_is_refused_naming_train_max_steps():
    """A training episode must let a move take effect and a message arrive; the task's own max_steps (20) is not
    what is short, so the error names train_max_steps, not max_steps."""
    slow_moves = dataclasses.replace(TINY, env=dataclasses.replace(TINY.env, act_delay=5))
    with pytest.raises(ConfigError, match=r"^invalid act_delay=5: must be < train_max_steps \(5\)$"):
        make_train_config("reinforced", slow_moves, train_max_steps=5)
    slow_messages = dataclasses.replace(TINY, channel=dataclasses.replace(TINY.channel, delay=5))
    with pytest.raises(ConfigError, match=r"^invalid delay=5: must be < train_max_steps \(5\)$"):
        make_train_config("reinforced", slow_messages, train_max_steps=5)
    assert make_train_config("reinforced", slow_moves, train_max_steps=6).training_task.env.act_delay == 5


def test_a_max_steps_no_message_can_arrive_in_is_refused_naming_it_not_the_least_delay():
    """`train --max-steps 1` was refused as `invalid delay=1`, the default delay the user never typed and cannot
    lower: where delay is already the least it can be, the line names the episode's length."""

    with pytest.raises(ConfigError, match=r"^invalid max_steps=1: must be > delay \(1\): a message must arrive"):
        TaskConfig(EnvConfig(size=4, max_steps=1), ChannelConfig(bits=4))
    with pytest.raises(ConfigError, match=r"^invalid delay=3: must be < max_steps \(3\)"):
        TaskConfig(EnvConfig(size=4, max_steps=3), ChannelConfig(bits=4, delay=3))
    with pytest.raises(ConfigError, match=r"^invalid train_max_steps=1: must be > delay \(1\)"):
        make_train_config("reinforced", TINY, train_max_steps=1)


def test_uniform_move_pulls_a_move_the_policy_gave_up_back():
    """The entropy bonus cannot revive a move of probability ~0; KL(uniform || pi) can."""

    def stay_probability_after_one_update(uniform_move: float) -> tuple[float, float]:
        torch.manual_seed(0)
        cfg = make_train_config("reinforced", TINY, num_envs=8, uniform_move=uniform_move, lr=1e-2)
        learner = Learner(cfg)
        with torch.no_grad():
            learner.policy.move_logits.bias[0] = -12.0  # "stay" all but dead
        ro = Collector(TINY, 8).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
        planes, received = ro.planes[ro.valid].flatten(0, 1).float(), ro.received[ro.valid].flatten(0, 1)

        def p_stay() -> float:
            with torch.no_grad():
                return torch.softmax(learner.policy(planes, received)[0], -1)[:, 0].mean().item()

        before = p_stay()
        learner.update(ro, torch.Generator().manual_seed(0))
        return before, p_stay()

    before, with_pull = stay_probability_after_one_update(1.0)
    _, entropy_only = stay_probability_after_one_update(0.0)
    assert with_pull > 10 * before
    assert with_pull > 10 * entropy_only


def test_reused_clip_factors_make_the_same_step_in_one_backward_pass():
    """Each loss is clipped on its own; a later step of the batch reuses the factors in one backward."""
    torch.manual_seed(0)
    learner = Learner(make_train_config("reinforced", TINY, num_envs=8))
    params = list(learner.policy.parameters())
    planes = torch.randint(0, 2, (6, 2, 4, 4))
    received = torch.randint(0, 2, (6, TINY.slots, 3), dtype=torch.uint8)

    def losses() -> list[torch.Tensor]:
        move, message = learner.policy(planes, received)
        return [move.logsumexp(-1).mean(), 100.0 * message.square().mean()]  # the second one is clipped

    def grads_after(scales: list[float] | None) -> tuple[list[torch.Tensor], list[float]]:
        used = learner._clipped_step(torch.optim.SGD(params, lr=0.0), params, losses(), scales)
        return [p.grad.clone() if p.grad is not None else torch.zeros_like(p) for p in params], used

    measured, factors = grads_after(None)
    assert factors[0] == 1.0 and 0.0 < factors[1] < 1.0
    reused, same = grads_after(factors)
    assert same == factors
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(measured, reused, strict=True))


def test_the_cells_encoder_reads_a_one_hot_plane_as_its_row_its_column_and_its_cell():
    from bitcomm.policies.networks import Marginals

    plane = torch.zeros(1, 1, 3, 3)
    plane[0, 0, 1, 2] = 1.0
    row, column, cell = [0, 1, 0], [0, 0, 1], [0, 0, 0, 0, 0, 1, 0, 0, 0]
    assert Marginals()(plane).tolist() == [row + column]
    assert Marginals(cells=True)(plane).tolist() == [row + column + cell]


@pytest.mark.parametrize("encoder", ["conv", "marginals", "cells"])
@pytest.mark.parametrize("message_map", [False, True])
def test_every_encoder_trains_with_the_recipe(encoder, message_map):
    cfg = make_train_config("reinforced", TINY, num_envs=4, encoder=encoder, message_map=message_map)
    learner, collector = Learner(cfg), Collector(TINY, 4)
    rollout = collector.collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    stats = learner.update(rollout, torch.Generator().manual_seed(0))
    assert all(np.isfinite(v) for v in stats.values())


@pytest.mark.parametrize("encoder", ["conv", "marginals", "cells"])
def test_a_message_head_that_reads_the_observed_plane_ignores_where_the_sender_is_and_what_it_hears(encoder):
    """`message_reads="observed"`: a sender's message logits follow the goal it observes alone; its moves still
    read its position and what it hears."""
    torch.manual_seed(0)
    net = PolicyNet(TINY, ModelConfig(encoder=encoder, plane_coords=True, message_reads="observed"))
    n, cells = 16, TINY.env.size**2
    g = torch.Generator().manual_seed(0)

    def planes(own: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        one_hot = torch.nn.functional.one_hot(torch.stack([own, seen], 1), cells).float()
        return one_hot.view(n, 2, TINY.env.size, TINY.env.size)

    own, seen = torch.randint(cells, (2, n), generator=g)
    heard = torch.randint(2, (n, TINY.slots, TINY.channel.bits), generator=g).float()
    moves, messages = net(planes(own, seen), heard)
    moved_moves, moved_messages = net(planes((own + 1) % cells, seen), 1 - heard)
    assert torch.equal(moved_messages, messages)
    assert not torch.allclose(moved_moves, moves)
    assert not torch.allclose(net(planes(own, (seen + 1) % cells), heard)[1], messages)


@pytest.mark.parametrize(("message_reads", "sender_hidden"), [("all", 128), ("observed", 128), ("observed", 16)])
def test_the_update_reads_the_message_logits_the_agents_acted_on(message_reads, sender_hidden):
    """The learner's pass over a rollout gives every step the logits acting gave it, whatever the head reads and
    however wide its own layers are."""
    cfg = make_train_config("reinforced", TINY, num_envs=4, message_reads=message_reads, sender_hidden=sender_hidden)
    learner = Learner(cfg)
    width = sender_hidden if message_reads == "observed" else cfg.model.hidden
    assert learner.policy.message_logits.in_features == width
    ro = Collector(TINY, 4).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    with torch.no_grad():
        fw = learner._forward(ro, torch.arange(4))
        moves, messages = learner.policy(ro.planes[fw.it, fw.ib].flatten(0, 1), fw.received.flatten(0, 1))
    assert torch.allclose(fw.msg_logits, messages) and torch.allclose(fw.move_logits, moves)
    stats = learner.update(ro, torch.Generator().manual_seed(0))
    assert all(np.isfinite(v) for v in stats.values())


def test_a_seed_s_initial_message_head_is_what_it_was_before_its_width_became_an_option() -> None:
    """Runs are replayed by seed across versions (docs/tuning.md compares seeds run sessions apart): building the
    message head's layers in another order would give every seed other initial weights. Values from commit 8de3f1b."""
    torch.manual_seed(0)
    net = PolicyNet(
        TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4)),
        ModelConfig(encoder="marginals", plane_coords=True, message_reads="observed"),
    )
    assert net.message_trunk is not None
    expected = {"message_logits": [0.076503, -0.086138, -0.08263], "trunk": [-0.012881, -0.028237, 0.028326]}
    got = {"message_logits": net.message_logits.weight[0, :3], "trunk": net.message_trunk[2].weight[0, :3]}
    for name, values in expected.items():
        assert torch.allclose(got[name], torch.tensor(values), atol=1e-6), name


def test_a_message_head_of_its_own_is_the_only_one_with_a_width_to_set() -> None:
    assert ModelConfig(message_reads="observed", sender_hidden=32).sender_hidden == 32
    with pytest.raises(ConfigError, match="sender-hidden=32: acts only with --message-reads observed"):
        ModelConfig(sender_hidden=32)


@pytest.mark.parametrize(
    ("options", "refusal"),
    [
        ({"held_out_episodes": 500}, "held-out-episodes=500: acts only with --held-out-every > 0; leave it at 1000"),
        ({"held_out_greedy": False}, "held-out-greedy=False: acts only with --held-out-every > 0; leave it on"),
        ({"map_lr": 0.05}, "map-lr=0.05: acts only with --message-map; leave it at 0.01"),
    ],
)
def test_an_option_nothing_reads_in_its_run_is_refused_not_ignored(options, refusal):
    """The held-out evaluation's size and play act only where it is played, the map decoder's rate only where
    there is a map (before, `--map-lr 0.05` under the default recipe trained exactly as without it)."""
    with pytest.raises(ConfigError, match=refusal):
        make_train_config("reinforced", TINY, **options)
    make_train_config("reinforced", TINY, held_out_every=64, message_map=True, **options)  # where they act


@pytest.mark.parametrize("clip", [0.0, 0.2])
def test_the_policy_gradient_term_reads_its_minibatch_s_own_steps(clip):
    """A minibatch is a shuffled subset of the batch's episodes, and the term works on its valid steps alone: each
    step's log-probabilities are those acting recorded for that episode's step (the policy has not moved yet), and
    its advantages that episode's: the plain term is -(1/#steps) sum of log-probability times advantage, PPO's (its
    ratio at 1) -(1/#steps) sum of the advantages."""
    from bitcomm.learn.objectives import PolicyGradient

    cfg = make_train_config("reinforced", TINY, num_envs=8)
    learner = Learner(cfg)
    ro = Collector(TINY, 8).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    adv = learner.advantages(ro)
    cols = torch.tensor([5, 2, 7])
    with torch.no_grad():
        batch = learner._batch(
            ro,
            learner._forward(ro, cols, BatchFeatures(learner._policy_reads(ro)[0], learner._critic_features(ro))),
            adv,
        )
        loss, _ = PolicyGradient(clip)(batch)
        logp_move, logp_message = batch.step_log_probs
    valid = ro.valid[:, cols]
    it, ib = valid.nonzero(as_tuple=True)
    t, b = it, cols[ib]
    assert torch.allclose(logp_move, ro.logp_move[t, b], atol=1e-5)
    assert torch.allclose(logp_message, ro.logp_message[t, b], atol=1e-5)
    weights = (1.0, 1.0) if clip > 0 else (ro.logp_move[t, b], ro.logp_message[t, b])  # PPO's ratio is 1 here
    expected = -(weights[0] * adv.action[t, b] + weights[1] * adv.message[t, b]).sum() / valid.sum()
    assert loss.item() == pytest.approx(expected.item(), abs=1e-4)


@pytest.mark.parametrize("encoder", ["conv", "marginals", "cells"])
@pytest.mark.parametrize("estimator", ["standard", "improved"])
def test_reading_the_observations_once_per_update_makes_the_same_update(encoder, estimator, monkeypatch):
    """The parameter-free encoders are read once per batch (`Learner._policy_reads`, `_critic_features`): a
    speed-up, not a change."""

    def trained(read_once: bool) -> list[torch.Tensor]:
        torch.manual_seed(0)
        cfg = make_train_config("reinforced", TINY, num_envs=8, encoder=encoder, estimator=estimator)
        learner = Learner(cfg)
        if not read_once:  # each pass reads the planes itself
            reads = learner._policy_reads  # the message head's distinct inputs kept: they round otherwise
            monkeypatch.setattr(learner, "_policy_reads", lambda ro: (None, reads(ro)[1]))
            monkeypatch.setattr(learner, "_critic_features", lambda ro: None)
        generator = torch.Generator().manual_seed(0)
        learner.update(Collector(TINY, 8).collect(learner.policy, np.random.SeedSequence(0), generator), generator)
        return [p.detach().clone() for p in [*learner.policy.parameters(), *learner.critic.parameters()]]

    learner = Learner(make_train_config("reinforced", TINY, encoder=encoder, estimator=estimator))
    assert learner.policy.fixed_features == learner.critic.fixed_features == (encoder != "conv")
    assert all(torch.equal(a, b) for a, b in zip(trained(True), trained(False), strict=True))


@pytest.mark.parametrize("encoder", ["marginals", "cells"])
def test_a_batch_s_planes_read_in_chunks_of_steps_read_as_they_do_whole(encoder, monkeypatch):
    from bitcomm.learn import learner as learner_module

    learner = Learner(make_train_config("reinforced", TINY, num_envs=8, encoder=encoder))
    ro = Collector(TINY, 8).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    whole = *learner._policy_reads(ro), learner._critic_features(ro)
    assert learner_module.CHUNK_ELEMENTS >= ro.state[0, 0].numel() * ro.valid.sum()  # TINY's planes: one chunk
    monkeypatch.setattr(learner_module, "CHUNK_ELEMENTS", 3 * ro.state[0, 0].numel() - 1)  # 2 steps a chunk
    chunked = *learner._policy_reads(ro), learner._critic_features(ro)
    assert torch.allclose(whole[0], chunked[0]) and torch.allclose(whole[2], chunked[2])
    assert torch.equal(whole[1].rows[whole[1].row_of], chunked[1].rows[chunked[1].row_of])


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32, torch.float64, torch.bfloat16])
def test_distinct_rows_give_back_every_row_bit_for_bit(dtype, monkeypatch):
    from bitcomm.learn import distinct

    g = torch.Generator().manual_seed(0)
    x = torch.randint(0, 3, (200, 5), generator=g).to(dtype)
    rows, inverse = distinct.distinct_rows(x)
    assert torch.equal(rows[inverse], x)
    assert torch.equal(inverse[:, None] == inverse[None], (x[:, None] == x[None]).all(-1))  # equal rows share one
    # a collision of the hash (every row on one key here) is caught, and the rows are then sorted whole
    monkeypatch.setattr(distinct.torch, "randint", lambda low, high, size, **_: torch.zeros(size, dtype=torch.long))
    rows2, inverse2 = distinct.distinct_rows(x)
    assert torch.equal(rows2[inverse2], x) and len(rows2) == len(rows)


@pytest.mark.parametrize("messages", ["bitwise", "onehot"])
def test_a_message_head_of_its_own_reads_each_distinct_observation_once_with_the_same_losses_and_gradients(
    messages,
):
    """`message_reads` `observed` sees few distinct inputs (a goal per episode): the update runs its layers, the
    log-probabilities, the entropies and the marginal over those (`Learner._policy_reads`), each weighted by
    its share of the steps: a speed-up, not a change."""
    from bitcomm.learn.objectives import clip_groups

    torch.manual_seed(0)
    cfg = make_train_config("reinforced", TINY, num_envs=16, messages=messages, entropy_message=0.01)
    learner = Learner(cfg)
    ro = Collector(TINY, 16).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    adv = learner.advantages(ro)
    features, observed = learner._policy_reads(ro)
    assert observed is not None and len(observed.rows) <= 2 * 16  # a goal seen per agent and episode
    cols = torch.tensor([3, 0, 9, 12, 5])
    params = list(learner.policy.parameters())
    runs = []
    for distinct in (observed, None):
        fw = learner._forward(ro, cols, BatchFeatures(features, None, distinct))
        batch = learner._batch(ro, fw, adv)
        assert (batch.msg_rows is None) == (distinct is None)
        losses, figures = clip_groups(learner.terms, batch)
        grads = torch.autograd.grad(sum(losses), params, allow_unused=True)
        runs.append((batch.msg_logits, batch.step_log_probs[1], figures, grads))
    (logits, logp, figures, grads), (logits_, logp_, figures_, grads_) = runs
    assert torch.allclose(logits, logits_, atol=1e-6) and torch.allclose(logp, logp_, atol=1e-5)
    assert figures.keys() == figures_.keys() and all(
        figures[k] == pytest.approx(figures_[k], abs=1e-5) for k in figures
    )
    assert {"charts/entropy_message", "charts/entropy_message_marginal"} <= figures.keys()
    assert all((a is None) == (b is None) for a, b in zip(grads, grads_, strict=True))
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(grads, grads_, strict=True) if a is not None)
    assert Learner(make_train_config("reinforced", TINY, message_reads="all"))._policy_reads(ro)[1] is None
    assert Learner(make_train_config("reinforced", TINY, encoder="conv"))._policy_reads(ro) == (None, None)


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
@pytest.mark.parametrize("bits", [1, 4])
def test_a_weighted_marginal_over_distinct_rows_is_the_marginal_over_every_row(name, bits):
    from bitcomm.policies.heads import marginal_entropy, row_weights

    head = make_head(name, bits)
    g = torch.Generator().manual_seed(0)
    distinct = (2 * torch.randn(6, head.out_features, generator=g, dtype=torch.float64)).requires_grad_()
    rows = torch.tensor([0, 3, 3, 5, 0, 0, 2, 3, 5, 2, 0])  # row 1 and row 4 unused: weight 0
    every = marginal_entropy(head, distinct[rows])
    weighted = marginal_entropy(head, distinct, row_weights(rows, 6))
    assert torch.allclose(every, weighted)
    assert torch.allclose(*(torch.autograd.grad(h, distinct)[0] for h in (every, weighted)))
    sent = head.sample(distinct.detach()[rows], g)
    pair, pair_of_rows = (
        head.log_prob_and_entropy(distinct[rows], sent),
        head.log_prob_and_entropy_of_rows(distinct, rows, sent),
    )
    for a, b in zip(pair, pair_of_rows, strict=True):
        assert torch.allclose(a, b)
        assert torch.allclose(*(torch.autograd.grad(x.sum(), distinct, retain_graph=True)[0] for x in (a, b)))


@pytest.mark.parametrize("head", [OneHotHead(4), BitwiseHead(4)], ids=lambda h: h.name)
def test_log_prob_and_entropy_together_equal_each_alone_in_value_and_gradient(head):
    g = torch.Generator().manual_seed(0)
    logits = (3 * torch.randn(64, head.out_features, generator=g, dtype=torch.float64)).requires_grad_()
    bits = head.sample(logits.detach(), g)
    w_logp, w_entropy = torch.randn(2, 64, generator=g, dtype=torch.float64)

    def grad_of(logp: torch.Tensor, entropy: torch.Tensor) -> torch.Tensor:
        (grad,) = torch.autograd.grad((w_logp * logp).sum() + (w_entropy * entropy).sum(), logits)
        return grad

    together = head.log_prob_and_entropy(logits, bits)
    alone = head.log_prob(logits, bits), head.entropy(logits)
    assert torch.allclose(together[0], alone[0]) and torch.allclose(together[1], alone[1])
    assert torch.allclose(grad_of(*together), grad_of(*alone))
    few = logits[:4].detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: head.log_prob_and_entropy(x, bits[:4]), (few,))


@pytest.mark.parametrize("head", [OneHotHead(3), BitwiseHead(3)], ids=lambda h: h.name)
@pytest.mark.parametrize("slots", [1, 2])
def test_a_layer_reads_received_bits_as_it_would_read_their_encoding(head, slots):
    g = torch.Generator().manual_seed(0)
    received = torch.randint(0, 2, (32, slots, 3), generator=g, dtype=torch.uint8)
    weight = torch.randn(5, slots * head.in_features, generator=g, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(5, generator=g, dtype=torch.float64, requires_grad=True)
    upstream = torch.randn(32, 5, generator=g, dtype=torch.float64)
    dense = torch.nn.functional.linear(head.encode(received).flatten(1).double(), weight, bias)
    read = head.linear(received, weight, bias)
    assert torch.allclose(read, dense)
    grads = [torch.autograd.grad((upstream * out).sum(), (weight, bias)) for out in (read, dense)]
    assert all(torch.allclose(a, b) for a, b in zip(*grads, strict=True))


def test_onehot_samples_follow_the_softmax_including_messages_of_probability_zero():
    head = OneHotHead(3)
    logits = torch.tensor([[0.0, 1.0, -float("inf"), 2.0, -1.0, -float("inf"), 0.5, 0.0]]).expand(40_000, 8)
    index = bits_to_index(head.sample(logits, torch.Generator().manual_seed(0)))
    freq = torch.bincount(index, minlength=8).float() / len(index)
    p = torch.softmax(logits[0], -1)
    assert freq[2] == 0 and freq[5] == 0
    assert torch.allclose(freq, p, atol=4 * (p * (1 - p) / len(index)).sqrt().max().item())


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
def test_the_marginal_entropy_is_that_of_the_average_message_distribution(name):
    """By brute force over the 8 messages of K = 3: mean the rows' probabilities, take the entropy; a row alone
    gives its own entropy; two rows sure of two messages give log 2, sure of one message 0."""
    from bitcomm.policies.heads import marginal_entropy

    head = make_head(name, 3)
    logits = torch.randn(6, head.out_features, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    all_bits = torch.tensor([[(m >> (2 - k)) & 1 for k in range(3)] for m in range(8)], dtype=torch.uint8)
    p = torch.stack([head.log_prob(logits, all_bits[m].expand(6, 3)) for m in range(8)], -1).exp().mean(0)
    assert torch.allclose(marginal_entropy(head, logits), -(p * p.log()).sum())
    assert torch.allclose(marginal_entropy(head, logits[:1]), head.entropy(logits[:1])[0])
    sure = {"bitwise": 30.0 * (2.0 * all_bits[[1, 6]].double() - 1), "onehot": 60.0 * torch.eye(8)[[1, 6]].double()}
    assert marginal_entropy(head, sure[name]).item() == pytest.approx(np.log(2), abs=1e-6)
    assert marginal_entropy(head, sure[name][[0, 0]]).item() == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
@pytest.mark.parametrize("bits", [1, 2, 3, 4, 5])
def test_the_mean_message_probabilities_are_each_message_s_by_index_with_their_gradient(name, bits):
    """`head.mean_probabilities` against brute force: each message's log-probability by `log_prob` of its bits
    (index order, bit 0 most significant), exponentiated and averaged over the rows; same values, same gradient
    of a weighted sum (the bitwise head's split into two halves of bits must keep every message's place)."""
    head = make_head(name, bits)
    gen = torch.Generator().manual_seed(bits)
    logits = (3 * torch.randn(7, head.out_features, generator=gen, dtype=torch.float64)).requires_grad_()
    every = torch.arange(1 << bits)
    all_bits = torch.stack([(every >> (bits - 1 - k)) & 1 for k in range(bits)], -1).to(torch.uint8)
    brute = torch.stack([head.log_prob(logits, all_bits[m].expand(7, bits)) for m in every], -1).exp().mean(0)
    mean = head.mean_probabilities(logits)
    assert mean.shape == (1 << bits,)
    assert torch.allclose(mean, brute)
    weights = torch.randn(1 << bits, generator=gen, dtype=torch.float64)
    (expected,) = torch.autograd.grad((brute * weights).sum(), logits)
    (got,) = torch.autograd.grad((mean * weights).sum(), logits)
    assert torch.allclose(got, expected)


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
@pytest.mark.parametrize("bits", [1, 3, 4])
def test_the_pair_divergence_is_the_jensen_shannon_divergence_of_the_two_rows(name, bits):
    """`pair_divergence` against brute force over every message: H((p + q) / 2) - (H(p) + H(q)) / 2 of each pair's
    rows, with the same gradient; log 2 for two rows sure of two messages, 0 for one row with itself."""
    from bitcomm.policies.heads import pair_divergence

    head = make_head(name, bits)
    gen = torch.Generator().manual_seed(bits)
    logits = (2 * torch.randn(5, head.out_features, generator=gen, dtype=torch.float64)).requires_grad_()
    first, second = torch.tensor([0, 0, 1, 3, 2]), torch.tensor([1, 4, 3, 2, 2])
    every = torch.arange(1 << bits)
    all_bits = torch.stack([(every >> (bits - 1 - k)) & 1 for k in range(bits)], -1).to(torch.uint8)
    p = torch.stack([head.log_prob(logits, all_bits[m].expand(5, bits)) for m in every], -1).exp()

    def entropy(q: torch.Tensor) -> torch.Tensor:
        return -(q * q.log()).sum(-1)

    brute = entropy((p[first] + p[second]) / 2) - (entropy(p[first]) + entropy(p[second])) / 2
    got = pair_divergence(head, logits, first, second)
    assert torch.allclose(got, brute)
    assert got[-1].item() == pytest.approx(0.0, abs=1e-12)
    weights = torch.randn(5, generator=gen, dtype=torch.float64)
    (expected,) = torch.autograd.grad((brute * weights).sum(), logits)
    (grad,) = torch.autograd.grad((got * weights).sum(), logits)
    assert torch.allclose(grad, expected)
    sure = {"bitwise": 30.0 * (2.0 * all_bits[[0, -1]].double() - 1), "onehot": 60.0 * torch.eye(1 << bits)[[0, -1]]}
    apart = pair_divergence(head, sure[name].double(), torch.tensor([0]), torch.tensor([1]))
    assert apart.item() == pytest.approx(np.log(2), abs=1e-6)


def test_nearby_goals_are_every_pair_of_cells_within_the_radius_once():
    """On 3x3, 12 pairs of neighbours (radius 1), and with radius 2 also the 6 pairs two steps apart in a line and
    the 8 diagonal ones; each observation holds one goal, on the observed plane, at its cell."""
    from bitcomm.learn.objectives import nearby_goals
    from bitcomm.policies.networks import OBSERVED_PLANE

    planes, first, second = nearby_goals(3, 1)
    pairs = sorted(zip(first.tolist(), second.tolist(), strict=True))
    assert len(pairs) == 12 and (0, 1) in pairs and (0, 3) in pairs and (0, 4) not in pairs
    assert all(a < b for a, b in pairs)
    assert planes.shape == (9, 2, 3, 3) and planes.sum().item() == 9
    assert planes[5, OBSERVED_PLANE, 1, 2].item() == 1
    _, first, second = nearby_goals(3, 2)
    distance = (first // 3 - second // 3).abs() + (first % 3 - second % 3).abs()
    assert len(first) == 26 and distance.max().item() == 2


def test_the_nearby_divergence_is_logged_and_needs_a_head_that_reads_the_goal_alone():
    """Its weight must be a number >= 0; it acts only where each goal has a word distribution of its own, on at most
    2^12 messages, and its radius only with it: each a one-line error naming the value."""
    cfg = make_train_config("reinforced", TINY, num_envs=4, message_divergence=0.5, message_divergence_radius=2)
    learner = Learner(cfg)
    term = next(t for t in learner.terms if t.name == "message_divergence")
    assert (term.weight, term.radius) == (0.5, 2)
    with pytest.raises(ConfigError, match="message-divergence=0.5: acts only with --message-reads observed"):
        make_train_config("reinforced", TINY, message_divergence=0.5, message_reads="all")
    with pytest.raises(ConfigError, match="message-divergence-radius=2: acts only with --message-divergence > 0"):
        make_train_config("reinforced", TINY, message_divergence=0.0, message_divergence_radius=2)
    with pytest.raises(ConfigError, match="message-divergence-radius=0: must be an integer >= 1"):
        make_train_config("reinforced", TINY, message_divergence=0.5, message_divergence_radius=0)
    with pytest.raises(ConfigError, match="message-divergence=-1"):
        make_train_config("reinforced", TINY, message_divergence=-1.0)
    wide = TaskConfig(EnvConfig(size=4, max_steps=20), ChannelConfig(bits=13))
    with pytest.raises(ConfigError, match="message-divergence=0.5: .* K <= 12 bits \\(K = 13\\)"):
        make_train_config("reinforced", wide, message_divergence=0.5)


def test_the_marginal_entropy_bonus_needs_at_most_4096_messages():
    """Above 12 bits the default recipe trains with the per-message bonus instead; asked for, it is one line."""
    wide = TaskConfig(EnvConfig(size=4, max_steps=20), ChannelConfig(bits=13))
    assert make_train_config("reinforced", TINY).entropy_message_marginal == 0.1
    cfg = make_train_config("reinforced", wide)
    assert (cfg.entropy_message_marginal, cfg.entropy_message) == (0.0, 0.01)
    assert make_train_config("reinforced", wide, entropy_message=0.003).entropy_message == 0.003
    with pytest.raises(ConfigError, match="entropy-message-marginal=0.1: .* K <= 12 bits \\(K = 13\\)"):
        make_train_config("reinforced", wide, entropy_message_marginal=0.1)


def test_acting_reads_a_message_head_of_its_own_once_per_episode_as_each_step_would(monkeypatch):
    """The observed goal is the head's only input and an episode keeps it: the collector computes its logits at
    the first step (`PolicyNet.observed_message_logits`), and every step's recorded message log-probability is the
    one the whole network gives that step."""
    learner = Learner(make_train_config("reinforced", TINY, num_envs=8))
    net, calls = learner.policy, []
    real = net.observed_message_logits
    monkeypatch.setattr(net, "observed_message_logits", lambda planes: calls.append(len(planes)) or real(planes))
    ro = Collector(TINY, 8).collect(net, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    assert calls == [8 * TINY.env.n_agents] and ro.valid.sum(0).max() > 1
    it, ib = ro.valid.nonzero(as_tuple=True)
    with torch.no_grad():
        _, logits = net(ro.planes[it, ib].flatten(0, 1), ro.received[it, ib].flatten(0, 1))
    logp = net.head.log_prob(logits, ro.bits[it, ib].flatten(0, 1)).view(it.shape[0], -1)
    assert torch.allclose(logp, ro.logp_message[it, ib], atol=1e-6)


def test_the_divergence_and_the_logit_decay_share_one_pass_over_the_goal_cells(monkeypatch):
    """Both terms read every goal cell's message logits: each minibatch step computes them once, not once per term
    (`StepBatch.goal_message_logits`), and the update still moves the parameters."""
    cfg = make_train_config("reinforced", TINY, num_envs=8, message_divergence=1.0, message_logit_decay=0.01)
    learner = Learner(cfg)
    assert {"message_divergence", "message_logit_decay"} <= {t.name for t in learner.terms}
    ro = Collector(TINY, 8).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    net, calls = learner.policy, []
    real = net.observed_message_logits
    monkeypatch.setattr(net, "observed_message_logits", lambda planes: calls.append(len(planes)) or real(planes))
    before = net.message_logits.weight.detach().clone()
    learner.update(ro)
    assert calls == [TINY.env.size**2] * (cfg.epochs * cfg.minibatches)
    assert not torch.equal(before, net.message_logits.weight)


def test_a_clip_wider_than_float32_clips_nothing() -> None:
    """`--clip 1e300 --epochs 2` (a huge clip: no clipping) was a RuntimeError: 1 + 1e300 is no float32 bound."""
    from bitcomm.learn.estimators import Advantages
    from bitcomm.learn.objectives import clipped_policy_loss

    gen = torch.Generator().manual_seed(0)
    logp, old, a = (torch.randn(4, 3, 2, generator=gen) for _ in range(3))
    adv, valid = Advantages(a, a, torch.zeros(4, 3)), torch.ones(4, 3, dtype=torch.bool)
    unclipped = -((torch.exp(logp - old) * a) * 2).sum() / valid.sum()
    loss = clipped_policy_loss(logp, logp, old, old, adv, valid, clip=1e300)
    assert torch.isfinite(loss) and torch.allclose(loss, unclipped)


def test_the_logit_decay_pulls_a_saturated_word_where_the_entropy_no_longer_does():
    """`message_logit_decay` is n w times the mean square of every goal cell's message logits; on words whose bits
    have saturated (every goal on one word, logits of 30) the per-message entropy's gradient has all but vanished, and
    the decay's has not."""
    from types import SimpleNamespace
    from typing import cast

    from bitcomm.learn.objectives import MessageLogitDecay, StepBatch, goal_planes

    cfg = make_train_config("reinforced", TINY, num_envs=4, message_logit_decay=0.01)
    policy = Learner(cfg).policy
    assert next(t for t in Learner(cfg).terms if t.name == "message_logit_decay").weight == 0.01
    with torch.no_grad():  # every goal on one word, each bit saturated
        policy.message_logits.weight.zero_()
        policy.message_logits.bias.copy_(torch.tensor([30.0, -30.0, 30.0]))
    logits = policy.observed_message_logits(goal_planes(4))
    batch = cast(StepBatch, SimpleNamespace(goal_message_logits=logits, n=2))  # what it reads
    loss, figures = MessageLogitDecay(0.01)(batch)
    assert logits.abs().min().item() > 20
    assert loss.item() == pytest.approx(2 * 0.01 * logits.square().mean().item(), rel=1e-6)
    assert figures["charts/message_logit_abs"] == pytest.approx(logits.abs().mean().item(), rel=1e-6)
    decay_grad = torch.autograd.grad(loss, policy.message_logits.bias, retain_graph=True)[0]
    entropy = 2 * 0.01 * policy.head.entropy(logits).mean()
    entropy_grad = torch.autograd.grad(entropy, policy.message_logits.bias)[0]
    assert entropy_grad.abs().max().item() < 1e-6 < 1e-3 < decay_grad.abs().max().item()
    with pytest.raises(ConfigError, match="message-logit-decay=0.01: acts only with --message-reads observed"):
        make_train_config("reinforced", TINY, message_logit_decay=0.01, message_reads="all")
    with pytest.raises(ConfigError, match="message-logit-decay=-1"):
        make_train_config("reinforced", TINY, message_logit_decay=-1.0)
