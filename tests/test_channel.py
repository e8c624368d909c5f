"""The K-bit channel of SPEC section 2: delay queue, noise, drops, recipients, codecs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bitcomm.channel.core import Channel, bits_to_index, bits_to_onehot, index_to_bits, index_to_onehot
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.vec import VecGoalExchange


def task(n_agents: int = 2, **channel: object) -> TaskConfig:
    return TaskConfig(EnvConfig(n_agents=n_agents), ChannelConfig(**channel))  # type: ignore[arg-type]


def random_bits(rng: np.random.Generator, B: int, n: int, K: int = 7) -> np.ndarray:
    return rng.integers(0, 2, size=(B, n, K), dtype=np.uint8)


# ---------------------------------------------------------------- delay queue


def test_delay_one_delivers_next_step_to_the_default_recipient() -> None:
    ch = Channel.for_task(task(), num_envs=3, seed=0)
    assert ch.received().shape == (3, 2, 1, 7)
    assert not ch.received().any()  # nothing sent yet: zeros
    sent = random_bits(np.random.default_rng(0), 3, 2)
    dropped = ch.transmit(sent)
    assert dropped.shape == (3, 2) and not dropped.any()
    got = ch.received()
    # the default recipient of agent j is the agent whose goal j sees: 0 -> 1, 1 -> 0
    np.testing.assert_array_equal(got[:, 1, 0], sent[:, 0])
    np.testing.assert_array_equal(got[:, 0, 0], sent[:, 1])
    assert got.dtype == np.uint8


def test_delay_three_queue() -> None:
    ch = Channel.for_task(task(delay=3), num_envs=2, seed=0)
    rng = np.random.default_rng(1)
    history: list[np.ndarray] = []
    for t in range(8):
        got = ch.received()  # what arrives at step t: what was sent at t - 3
        if t < 3:
            assert not got.any()
        else:
            np.testing.assert_array_equal(got[:, 1, 0], history[t - 3][:, 0])
            np.testing.assert_array_equal(got[:, 0, 0], history[t - 3][:, 1])
        history.append(random_bits(rng, 2, 2))
        ch.transmit(history[-1])


def test_reset_mask_forgets_messages_in_flight_of_those_episodes_only() -> None:
    ch = Channel.for_task(task(delay=2), num_envs=2, seed=0)
    ones = np.ones((2, 2, 7), dtype=np.uint8)
    ch.transmit(ones)
    ch.transmit(ones)
    ch.reset(np.array([True, False]))
    got = ch.received()
    assert not got[0].any() and got[1].all()
    ch.transmit(ones)
    assert not ch.received()[0].any()  # the second message in flight was forgotten too
    ch.reset()
    assert not ch.received().any()


@pytest.mark.parametrize("delay", [1, 3])
def test_episode_reset_clears_the_channel(delay: int) -> None:
    """A message sent near the end of an episode never reaches the next one."""
    max_steps = delay + 2
    env = VecGoalExchange(TaskConfig(EnvConfig(max_steps=max_steps), ChannelConfig(delay=delay)), num_envs=1, seed=0)
    ones = np.ones((1, 2, 7), dtype=np.uint8)
    stay = np.zeros((1, 2), dtype=np.int64)
    for _episode in range(2):
        for t in range(max_steps):
            obs = env.observe()
            assert obs.t[0] == t
            assert obs.received.all() == (t >= delay) and obs.received.any() == (t >= delay)
            result, _ = env.step(stay, ones)
        assert result.truncated[0]


# ---------------------------------------------------------------- noise


def test_flip_rate_matches_flip_prob() -> None:
    B, p = 4096, 0.1
    ch = Channel.for_task(task(flip_prob=p), num_envs=B, seed=0)
    ch.transmit(np.zeros((B, 2, 7), dtype=np.uint8))
    rate = ch.received().mean()
    sigma = np.sqrt(p * (1 - p) / (B * 2 * 7))
    assert abs(rate - p) < 5 * sigma


def test_flip_prob_one_inverts_every_bit() -> None:
    ch = Channel.for_task(task(flip_prob=1.0), num_envs=4, seed=0)
    sent = random_bits(np.random.default_rng(2), 4, 2)
    ch.transmit(sent)
    np.testing.assert_array_equal(ch.received()[:, 1, 0], 1 - sent[:, 0])


def test_drop_rate_and_flags() -> None:
    B, p = 4096, 0.3
    ch = Channel.for_task(task(drop_prob=p), num_envs=B, seed=0)
    dropped = ch.transmit(np.ones((B, 2, 7), dtype=np.uint8))
    assert abs(dropped.mean() - p) < 5 * np.sqrt(p * (1 - p) / (B * 2))
    got = ch.received()
    # agent 0's message is heard by agent 1 and vice versa; dropped ones read all zeros
    np.testing.assert_array_equal(got[:, 1, 0].any(-1), ~dropped[:, 0])
    np.testing.assert_array_equal(got[:, 0, 0].any(-1), ~dropped[:, 1])
    assert got[:, 1, 0][~dropped[:, 0]].all()


def test_noise_is_seeded() -> None:
    def run(seed: int) -> np.ndarray:
        ch = Channel.for_task(task(flip_prob=0.2, drop_prob=0.2), num_envs=64, seed=seed)
        ch.transmit(np.zeros((64, 2, 7), dtype=np.uint8))
        return ch.received()

    np.testing.assert_array_equal(run(1), run(1))
    assert not np.array_equal(run(1), run(2))


# ---------------------------------------------------------------- recipients and slots


def test_multi_recipient_map_with_slots() -> None:
    # agent 0 -> agents 1 and 2; agents 1 and 2 -> agent 0, who so hears two senders
    t = task(n_agents=3, recipients=((1, 2), (0,), (0,)))
    np.testing.assert_array_equal(t.slot_senders, [[1, 2], [0, -1], [0, -1]])
    assert t.slots == 2
    ch = Channel.for_task(t, num_envs=1, seed=0)
    sent = np.array([[[1, 0, 0, 0, 0, 0, 1], [0, 1, 0, 0, 0, 1, 0], [0, 0, 1, 0, 1, 0, 0]]], dtype=np.uint8)
    ch.transmit(sent)
    got = ch.received()[0]
    assert got.shape == (3, 2, 7)
    np.testing.assert_array_equal(got[0], sent[0, [1, 2]])  # slots ordered by sender
    np.testing.assert_array_equal(got[1, 0], sent[0, 0])
    np.testing.assert_array_equal(got[2, 0], sent[0, 0])  # one message, two recipients
    assert not got[1, 1].any() and not got[2, 1].any()  # unused slots stay zero


def test_a_dropped_message_is_lost_for_every_recipient() -> None:
    t = task(n_agents=3, recipients=((1, 2), (0,), (0,)), drop_prob=0.5)
    B = 512
    ch = Channel.for_task(t, num_envs=B, seed=3)
    dropped = ch.transmit(np.ones((B, 3, 7), dtype=np.uint8))
    got = ch.received()
    assert dropped[:, 0].any() and not dropped[:, 0].all()
    for x in (1, 2):
        np.testing.assert_array_equal(got[:, x, 0].any(-1), ~dropped[:, 0])
    np.testing.assert_array_equal(got[:, 0, 0].any(-1), ~dropped[:, 1])
    np.testing.assert_array_equal(got[:, 0, 1].any(-1), ~dropped[:, 2])


# ---------------------------------------------------------------- codecs


def test_bit_order_is_most_significant_first() -> None:
    assert bits_to_index(np.array([1, 0, 0, 0, 0, 0, 1])) == 65
    np.testing.assert_array_equal(index_to_bits(np.array(6), 4), [0, 1, 1, 0])
    assert int(bits_to_index(torch.tensor([1, 0, 1]))) == 5


@pytest.mark.parametrize("K", [1, 3, 7])
def test_codec_round_trips_numpy(K: int) -> None:
    index = np.arange(1 << K).reshape(-1, 1)  # a batch dimension too
    bits = index_to_bits(index, K)
    assert bits.shape == (1 << K, 1, K) and bits.dtype == np.uint8
    assert set(np.unique(bits)) <= {0, 1}
    np.testing.assert_array_equal(bits_to_index(bits), index)
    onehot = index_to_onehot(index, K)
    assert onehot.shape == (1 << K, 1, 1 << K) and onehot.dtype == np.float32
    np.testing.assert_array_equal(onehot.argmax(-1), index)
    np.testing.assert_array_equal(onehot.sum(-1), 1.0)
    np.testing.assert_array_equal(bits_to_onehot(bits), onehot)


@pytest.mark.parametrize("K", [1, 3, 7])
def test_codec_round_trips_torch(K: int) -> None:
    index = torch.arange(1 << K).reshape(-1, 1)
    bits = index_to_bits(index, K)
    assert bits.shape == (1 << K, 1, K) and bits.dtype == torch.uint8
    assert torch.equal(bits_to_index(bits), index)
    assert torch.equal(bits_to_index(bits.float()), index)  # a sampled float bit vector reads the same
    onehot = index_to_onehot(index, K)
    assert onehot.shape == (1 << K, 1, 1 << K) and onehot.dtype == torch.float32
    assert torch.equal(onehot.argmax(-1), index)
    assert torch.equal(bits_to_onehot(bits), onehot)
    # numpy and torch agree
    np.testing.assert_array_equal(bits.numpy(), index_to_bits(index.numpy(), K))


def test_reset_returns_the_observation_and_a_hand_loop_runs() -> None:
    """`reset()` returns what `observe()` would; the loop of VecGoalExchange's docstring runs as written."""
    task = TaskConfig()
    n, K = task.env.n_agents, task.channel.bits
    env = VecGoalExchange(task, num_envs=8, seed=0)
    obs = env.reset()
    assert obs.planes.shape == (8, n, 2, task.env.size, task.env.size) and not obs.received.any()
    assert (obs.t == 0).all()
    for _ in range(100):
        result, dropped = env.step(np.zeros((8, n), dtype=np.int64), np.zeros((8, n, K), dtype=np.uint8))
        obs = env.observe()
    assert dropped.shape == (8, n) and result.team_reward.shape == (8,)
