"""Pictures of one episode of a policy trained on a wrapped PettingZoo env (`bitcomm train --env`).

Each frame is the inner env's own picture after the step (built with `render_mode="rgb_array"` added to
the run's env kwargs) above a text panel: the step, the team reward and the return so far, and per agent
the bits it sent at that step (marked if the channel dropped them) and the bits it read at that step from
each sender it hears (sent `delay` steps earlier; marked if that message was dropped). Same frame
convention as the grid's pictures (`bitcomm.studies.render`): an episode of T steps gives T frames.

The episode is the one `bitcomm eval RUN --seed S --episodes 1` plays: env seeds from
`SeedSequence(S, spawn_key=(0,))`, sampling from `torch.Generator().manual_seed(S)`, one copy of the env.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from PIL import Image, ImageDraw

from bitcomm.channel.core import bits_to_index
from bitcomm.envs.vector import VecEnv, inner_action
from bitcomm.errors import ConfigError, bad_value
from bitcomm.learn.env_eval import chunk_seed, load_env_policy
from bitcomm.learn.env_rollout import env_factory, play
from bitcomm.studies.render import PALETTE, bit_string, load_font

NEEDS = "render needs an env whose factory takes render_mode='rgb_array' and whose render() returns an HxWx3 image"


class EnvEpisodeRecord(NamedTuple):
    """One played episode of a wrapped env, agents in `possible_agents` order; step t (0-based)."""

    env: str  # the env spec, "package.module:factory"
    agents: tuple[str, ...]
    slot_senders: np.ndarray  # (n, slots) sender of each received slot, -1 padding
    delay: int
    fixed: np.ndarray  # (n,) bool: the wrapper fixes this agent's inner action
    action_sizes: tuple[int, ...]
    discrete: bool
    actions: np.ndarray  # (T, n) int: the policy's index; (T, n, A) float: clipped to the bounds, as the env had them
    sent: np.ndarray  # (T, n, K) bits each agent sent at step t
    received: np.ndarray  # (T, n, slots, K) bits each agent read at step t (its input)
    dropped: np.ndarray  # (T, n) the message sent at step t was dropped
    alive: np.ndarray  # (T, n) the agent acted at step t
    team_rewards: np.ndarray  # (T,)
    images: list[np.ndarray]  # T pictures (H, W, 3) uint8, the env after each step
    action_spaces: tuple[Any, ...] = ()  # each agent's inner action space: a Discrete index shown as the env had it

    @property
    def length(self) -> int:
        return len(self.images)


def picture(env: Any, spec: str) -> np.ndarray:
    """`env.render()` as an (H, W, 3) uint8 array (a float one in [0, 1] scaled to [0, 255]), or one error line naming
    the env and what is needed."""
    try:
        image = env.render()
    except Exception as err:  # PettingZoo's default render raises NotImplementedError
        raise bad_value("env", spec, f"cannot be drawn: render() raised {type(err).__name__}; {NEEDS}") from None
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        got = f"an array of shape {image.shape}" if isinstance(image, np.ndarray) else repr(image)[:40]
        raise bad_value("env", spec, f"cannot be drawn: render() returned {got}; {NEEDS}")
    if image.dtype.kind == "f" and np.nanmax(image) <= 1.0:  # matplotlib's convention; cast, every pixel was 0 or 1
        image = np.nan_to_num(image).clip(0.0, 1.0) * 255.0
    return np.ascontiguousarray(np.rint(image) if image.dtype.kind == "f" else image, dtype=np.uint8)


def record_env_episode(
    path: Path | str, seed: int = 0, greedy: bool = False, drop_prob: float | None = None, max_frames: int = 1000
) -> EnvEpisodeRecord:
    """Play the first evaluation episode of seed `seed` with the policy of `path`, drawing the env after each step."""
    cfg, policy = load_env_policy(path)
    drawn = dataclasses.replace(cfg, env_kwargs={**cfg.env_kwargs, "render_mode": "rgb_array"})
    try:  # one copy, built here rather than by make_vec: the picture is read from the env object itself
        vec = VecEnv(env_factory(drawn, drop_prob), 1)  # type: ignore[arg-type]
    except ConfigError as err:
        raise bad_value("env", cfg.env, f"cannot be drawn with render_mode='rgb_array' ({err}); {NEEDS}") from None
    env = vec.envs[0]
    images: list[np.ndarray] = []

    def grab(_: object) -> None:
        if len(images) == max_frames:
            raise bad_value(
                "episode", f"> {max_frames} steps", f"render draws one frame per step, {max_frames} at most"
            )
        images.append(picture(env, cfg.env))

    try:
        ro = play(
            vec, policy, chunk_seed(seed, 0), torch.Generator().manual_seed(seed),
            greedy=greedy, on_step=grab,
        )  # fmt: skip
    finally:
        env.close()
    T, L = int(ro.length[0]), vec.layout
    actions = ro.actions[:T, 0].numpy()
    if not L.discrete:  # as the env received them
        actions = np.clip(actions, L.low, L.high)
    return EnvEpisodeRecord(
        cfg.env, L.agents, np.asarray(env.slot_senders), L.delay, L.fixed, L.action_sizes, L.discrete,
        actions, ro.bits[:T, 0].numpy(), ro.received[:T, 0].numpy(), ro.dropped[:T, 0].numpy(),
        ro.alive[:T, 0].numpy(), ro.rewards[:T, 0].numpy().astype(np.float64), images, L.action_spaces,
    )  # fmt: skip


def _action(record: EnvEpisodeRecord, t: int, i: int) -> str:
    if record.fixed[i]:
        return "fixed"
    if record.discrete:  # as the env received it: start added, a MultiDiscrete's entries unravelled
        index = record.actions[t, i]
        action = inner_action(record.action_spaces[i], index) if record.action_spaces else int(index)
        return " ".join(str(action).split())
    return "[" + " ".join(f"{x:+.2f}" for x in record.actions[t, i, : record.action_sizes[i]]) + "]"


def _absent(record: EnvEpisodeRecord, t: int, i: int) -> str:
    """Why agent i is not in the episode at step t: it left, or (PettingZoo lets an env add agents) it has not come."""
    return "gone" if record.alive[:t, i].any() else "not here yet"


def _heard(record: EnvEpisodeRecord, t: int, i: int) -> str:
    """The bits agent i read at step t from each sender it hears, with why a slot holds zeros."""
    out = []
    for k, j in enumerate(record.slot_senders[i]):
        if j < 0:
            continue
        s = t - record.delay  # the step the message read now was sent at
        note = ""
        if s < 0:
            note = " (none yet)"
        elif record.dropped[s, j]:
            note = " (dropped)"
        elif not record.alive[s, j]:
            note = f" ({_absent(record, s, j)})"
        out.append(f"{bit_string(record.received[t, i, k])}<-{record.agents[j]}{note}")
    return " ".join(out) or "-"


def step_lines(record: EnvEpisodeRecord, t: int) -> list[str]:
    """The text panel of step t (0-based): a header, then one line per agent."""
    returns = np.cumsum(record.team_rewards)
    header = f"step {t + 1}/{record.length}  team reward {record.team_rewards[t]:+.3f}  return so far {returns[t]:+.3f}"
    lines = [header]
    for i, name in enumerate(record.agents):
        if not record.alive[t, i]:
            lines.append(f"{name}  {_absent(record, t, i)}")
            continue
        sent = record.sent[t, i]
        drop = " (heard by no one)" if i not in record.slot_senders else " DROPPED" if record.dropped[t, i] else ""
        lines.append(
            f"{name}  action {_action(record, t, i)}  |  sent {bit_string(sent)} (={int(bits_to_index(sent))}){drop}"
            f"  |  received {_heard(record, t, i)}"
        )
    return lines


def render_env_frames(record: EnvEpisodeRecord) -> list[Image.Image]:
    """One RGB image per step: the env's picture after the step, the text panel of `step_lines` below it."""
    font = load_font(12)
    pad, line_h = 8, 17
    legend = f"{record.env}; received: bits read this step, sent {record.delay} step(s) earlier by the agent named"
    texts = [step_lines(record, t) for t in range(record.length)]
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    text_w = max(probe.textlength(s, font=font) for s in [legend, *(x for ls in texts for x in ls)])
    image_w = max(im.shape[1] for im in record.images)
    image_h = max(im.shape[0] for im in record.images)
    width = int(max(image_w, text_w)) + 2 * pad
    top = pad + image_h + pad
    height = top + (len(record.agents) + 2) * line_h + pad
    frames = []
    for image, lines in zip(record.images, texts, strict=True):
        frame = Image.new("RGB", (width, height), (255, 255, 255))
        frame.paste(Image.fromarray(image), ((width - image.shape[1]) // 2, pad))
        d = ImageDraw.Draw(frame)
        colours = [(0, 0, 0)] + [PALETTE[i % len(PALETTE)] for i in range(len(record.agents))]
        for row, (line, colour) in enumerate(zip(lines, colours, strict=True)):
            d.text((pad, top + row * line_h), line, fill=colour, font=font)
        d.text((pad, top + len(lines) * line_h), legend, fill=(110, 110, 110), font=font)
        frames.append(frame)
    return frames
