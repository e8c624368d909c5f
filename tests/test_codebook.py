"""The self-labelled code book (`code_coef`), the message map and the centre-of-mass features."""

import numpy as np
import pytest
import torch

from bitcomm.channel.core import bits_to_index, index_to_bits
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.learn.codebook import CodeBook, greedy_matching
from bitcomm.learn.config import make_train_config
from bitcomm.learn.learner import Learner
from bitcomm.learn.rollout import Collector
from bitcomm.policies.heads import make_head
from bitcomm.policies.networks import ModelConfig, PolicyNet


def test_matching_gives_each_row_its_best_free_column_most_confident_first():
    scores = torch.tensor([[5.0, 4.0, 0.0], [9.0, 1.0, 0.0], [3.0, 2.0, 1.0]])
    # row 1 (best 9) takes column 0; row 0 (best 5) then takes its next best, 1; row 2 gets 2
    assert greedy_matching(scores).tolist() == [1, 0, 2]


def test_matching_shares_columns_evenly_when_rows_outnumber_them():
    word = greedy_matching(torch.zeros(5, 2))
    assert sorted(torch.bincount(word, minlength=2).tolist()) == [2, 3]


@pytest.mark.parametrize("name", ["bitwise", "onehot"])
def test_log_prob_terms_give_the_log_prob_of_each_message(name):
    head = make_head(name, 3)
    logits = torch.randn(4, head.out_features)
    every = torch.stack([head.log_prob(logits, index_to_bits(torch.full((4,), m), 3)) for m in range(8)], -1)
    assert torch.allclose(head.log_prob_of_terms(head.log_prob_terms(logits)), every, atol=1e-5)


def test_code_words_are_distinct_and_follow_the_senders_preference():
    book = CodeBook(4, make_head("bitwise", 2))
    # the sender already leans toward message index 3 (bits 1, 1) for goal 2, clearly
    logits = torch.tensor([[0.1, 0.0], [0.0, 0.1], [5.0, 5.0], [-0.1, 0.0]])
    words = bits_to_index(book.targets(torch.tensor([0, 1, 2, 3]), logits))
    assert words[2] == 3
    assert sorted(words.tolist()) == [0, 1, 2, 3]
    # a later batch with only goal 0 keeps every goal's word (the book remembers the others)
    again = bits_to_index(book.targets(torch.tensor([0, 0]), logits[[0, 0]]))
    assert again.tolist() == [words[0].item()] * 2


def test_message_map_starts_uniform_and_decodes_to_a_one_hot_plane():
    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))
    net = PolicyNet(task, ModelConfig(message_map=True, plane_coords=True))
    received = net.encode_received(torch.randint(0, 2, (3, 1, 4), dtype=torch.uint8))
    assert torch.equal(net.map_logits(received), torch.zeros(3, 1, 16))
    with torch.no_grad():
        net.message_map.weight.normal_()
    planes = torch.zeros(3, 2, 4, 4)
    planes[:, 0, 1, 2] = 1
    planes[:, 1, 3, 0] = 1
    feats = net.observation_features(planes, received)
    centre = feats[:, -6:].view(3, 3, 2)
    step = 2 / 3  # coordinates run from -1 to 1 over 4 cells
    assert torch.allclose(centre[:, 0], torch.tensor([-1 + step, -1 + 2 * step]).expand(3, 2))
    assert torch.allclose(centre[:, 1], torch.tensor([1.0, -1.0]).expand(3, 2))
    decoded = net.map_logits(received)[:, 0].argmax(-1)  # the map's plane is that cell, exactly
    assert torch.allclose(centre[:, 2, 0], torch.linspace(-1, 1, 4)[decoded // 4])


def test_supervised_update_teaches_codes_and_trains_the_decoder_faster():
    task = TaskConfig(EnvConfig(size=3, max_steps=8), ChannelConfig(bits=4))
    torch.manual_seed(0)
    learner = Learner(make_train_config("supervised", task, num_envs=16))
    assert [g["lr"] for g in learner.opt_policy.param_groups] == [1e-3, 1e-2]
    rollout = Collector(task, 16).collect(learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    stats = learner.update(rollout, torch.Generator().manual_seed(0))
    assert {"losses/code", "losses/goal", "losses/seen"} <= set(stats)
    assert learner.codebook is not None and learner.codebook.seen.any()
