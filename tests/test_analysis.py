"""`bitcomm analyze`: plug-in estimators against hand values, the oracle's protocol, the CLI's files."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest

from bitcomm.cli import build_parser, main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.policies.agent_policies import OracleAgent, RandomAgent
from bitcomm.provenance import RECORDED
from bitcomm.studies.analysis import (
    MessageSamples,
    analyze_samples,
    bit_maps,
    channel_capacity,
    collect_messages,
    entropy,
    fit_lookup_decoder,
    mutual_information,
    split_by_episode,
)


def test_estimators_on_hand_values() -> None:
    assert entropy(np.array([0, 1, 2, 3])) == pytest.approx(2.0)
    assert entropy(np.array([5, 5, 5])) == pytest.approx(0.0)
    x = np.array([0, 0, 1, 1])
    assert mutual_information(x, x) == pytest.approx(1.0)
    assert mutual_information(x, np.array([0, 1, 0, 1])) == pytest.approx(0.0)
    assert channel_capacity(7, 0.0) == pytest.approx(7.0)
    h = -(0.05 * math.log2(0.05) + 0.95 * math.log2(0.95))
    assert channel_capacity(7, 0.05) == pytest.approx(7 * (1 - h))
    assert channel_capacity(3, 0.5) == pytest.approx(0.0)
    table, default = fit_lookup_decoder(np.array([1, 1, 1, 2, 2]), np.array([7, 7, 3, 4, 4]))
    assert table == {1: 7, 2: 4} and default in (7, 4)


def test_oracle_transmits_the_whole_goal_without_noise() -> None:
    task = TaskConfig()
    samples = collect_messages(OracleAgent(task), task, samples=60_000, num_envs=512, seed=1)
    r = analyze_samples(samples, task, "oracle")
    assert r.transmitted_bits == pytest.approx(math.log2(100), abs=0.05)
    assert r.transmitted_bits == pytest.approx(r.goal_entropy_bits, abs=1e-6)
    assert r.decoder_accuracy == 1.0
    assert r.capacity_bits == 7.0
    # the last bit of row * 10 + column is the column's parity: one bit about the column, none about the row
    assert r.per_bit[-1].mi_col == pytest.approx(1.0, abs=0.01)
    assert r.per_bit[-1].mi_row < 0.01
    maps = bit_maps(samples, task)
    assert maps.shape == (7, 10, 10)
    assert set(np.unique(maps[~np.isnan(maps)])) <= {0.0, 1.0}  # a deterministic code


def test_the_summary_says_its_capacity_leaves_drops_out_where_messages_are_dropped() -> None:
    """summary.md read "channel capacity K(1 - H(flip_prob)) 4.000" at --drop-prob 0.5: it counts flips alone."""
    from bitcomm.studies.analysis import markdown_summary

    for drop, says in ((0.0, False), (0.5, True)):
        task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4, drop_prob=drop))
        r = analyze_samples(collect_messages(OracleAgent(task), task, 2_000, 64, seed=5), task)
        assert r.capacity_bits == 4.0
        assert ("| channel capacity K(1 - H(flip_prob)), drops not counted (they lower it further) |" in
                markdown_summary(r)) is says  # fmt: skip


def test_noise_lowers_what_gets_through_and_random_says_nothing() -> None:
    task = TaskConfig(channel=ChannelConfig(flip_prob=0.05))
    r = analyze_samples(collect_messages(OracleAgent(task), task, 60_000, 512, seed=2), task)
    assert r.transmitted_bits < r.capacity_bits < 7.0
    assert 3.5 < r.transmitted_bits < 6.0
    assert 0.3 < r.decoder_accuracy < 0.95
    tiny = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))
    r = analyze_samples(collect_messages(RandomAgent(tiny, 0), tiny, 20_000, 256, seed=3), tiny)
    assert r.transmitted_bits < 0.1 and max(b.mi_cell for b in r.per_bit) < 0.02


def test_the_decoder_is_scored_on_episodes_it_never_saw() -> None:
    """A sender that repeats a random pattern within each episode, whatever the goal, says nothing about the
    goal: a decoder that saw other deliveries of the same episode would remember the pattern and score high."""
    rng = np.random.default_rng(0)
    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=16))
    episodes, repeats = 4_000, 8
    goal = np.repeat(rng.integers(0, 16, episodes), repeats)
    bits = np.repeat(rng.integers(0, 2, (episodes, 16)), repeats, axis=0).astype(np.uint8)
    key = np.repeat(np.arange(episodes), repeats)
    r = analyze_samples(MessageSamples(goal, bits, goal, bits, key), task)
    assert r.decoder_accuracy < 0.1  # chance is 1/16; split by delivery it is about 0.96
    by_delivery = analyze_samples(MessageSamples(goal, bits, goal, bits), task)
    assert by_delivery.decoder_accuracy > 0.8
    fit, test = split_by_episode(key, seed=0)
    assert set(key[fit]).isdisjoint(key[test]) and len(fit) + len(test) == len(key)
    assert abs(len(fit) - len(test)) <= repeats


def test_collected_deliveries_carry_their_episode() -> None:
    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4, delay=2))
    samples = collect_messages(OracleAgent(task), task, 5_000, 64, seed=5)
    assert samples.delivered_episode is not None and len(samples.delivered_episode) == len(samples.delivered_goal)
    for key in np.unique(samples.delivered_episode)[:50]:  # one goal per episode and sender
        assert np.unique(samples.delivered_goal[samples.delivered_episode == key]).size <= task.env.n_agents


def test_samples_are_deliveries_sent_in_time_to_arrive_not_a_minimum_gathered() -> None:
    """`--samples 100` at delay 50 on a 2x2 grid gathered 14 deliveries where the help said "deliveries to collect"
    and the docstring "until at least `samples`": most episodes end before their messages arrive."""
    task = TaskConfig(EnvConfig(size=2), ChannelConfig(bits=2, delay=50))
    samples = collect_messages(OracleAgent(task), task, 100, 4, seed=0)
    assert 0 < len(samples.delivered_goal) < 100 <= len(samples.sent_goal) * task.slots
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    analyze = sub.choices["analyze"]
    help = next(a.help for a in analyze._actions if "--samples" in a.option_strings)
    assert help is not None and "to send in time to arrive; fewer arrive" in help
    assert collect_messages.__doc__ is not None and "never delivered" in collect_messages.__doc__


def test_delay_pairs_each_delivery_with_its_own_message() -> None:
    task = TaskConfig(EnvConfig(size=5), ChannelConfig(bits=5, delay=3))
    r = analyze_samples(collect_messages(OracleAgent(task), task, 20_000, 256, seed=4), task)
    assert r.decoder_accuracy == 1.0 and r.transmitted_bits == pytest.approx(r.goal_entropy_bits, abs=1e-6)


def test_cli_writes_heatmaps_summary_and_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "an"
    argv = ["analyze", "--policy", "oracle", "--size", "4", "--agents", "3", "--bits", "4", "--delay", "2"]
    assert main([*argv, "--samples", "5000", "--envs", "128", "--out", str(out), "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["transmitted_bits"] == pytest.approx(figures["goal_entropy_bits"], abs=1e-6)
    assert len(figures["per_bit"]) == 4 and figures["capacity_bits"] == 4.0
    assert (out / "bits.png").stat().st_size > 1000
    assert (out / "bits.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    record = json.loads((out / "provenance.json").read_text())  # what made the figures: flags, task, code, machine
    assert record["settings"]["samples"] == 5000 and record["settings"]["task"]["channel"]["bits"] == 4
    assert set(RECORDED) <= set(record)
    summary = (out / "summary.md").read_text()
    assert "# Protocol analysis" in summary and "bits.png" in summary and summary.count("\n| ") >= 4 + 5
    # the task in full: it named neither the agents nor the delay, so 3 agents at delay 2 read as the paper's two
    assert "Task: 4x4 grid, 3 agents, K = 4, delay 2, flip 0, drop 0. " in summary
    assert figures["task"] == "4x4 grid, 3 agents, K = 4, delay 2, flip 0, drop 0"


def test_deliveries_of_one_episode_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One random episode side by side with no other outlasts 100 deliveries: the decoder's fit half was empty, an
    argmax of an empty sequence (a traceback); the line says what to give more of."""
    argv = ["analyze", "--policy", "random", "--samples", "100", "--envs", "1", "--out", str(tmp_path / "an")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "bitcomm analyze: error: invalid deliveries=100: all from one episode; the lookup decoder is fitted on half "
        "the episodes and scored on the others, so it needs deliveries from 2 or more (give more --samples or --envs)"
    ], err


def test_play_in_which_no_message_arrives_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Random agents on a 2x2 grid end every episode in a few steps, long before a message sent with a delay of 200
    arrives: no delivery was gathered, and concatenating none was a traceback."""
    argv = ["analyze", "--policy", "random", "--size", "2", "--bits", "2", "--delay", "200", "--samples", "100",
            "--envs", "4", "--out", str(tmp_path / "an")]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bitcomm analyze: error: invalid delay=200: no message arrived"), err
    assert not (tmp_path / "an").exists()  # refused before anything is written
