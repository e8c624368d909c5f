"""Pictures of one episode: the grid, each agent (coloured), its goal, its path, and its bits.

Frame convention: one frame per step, showing the state *after* that step, so an episode of length
T gives T frames (frame t = 1..T). Each frame shows every agent's start (hollow ring), path so far,
position (filled disc with its number) and goal (square outline in its colour), and under the grid,
per agent: the move it chose at step t, the K bits it sent at step t, and the bits it received at
step t (the input its move was chosen from; zeros until the first message arrives after `delay`).

Rendering lives here and only reads an `EpisodeRecord`; recording plays the episode with the same
`AgentPolicy` the other runtimes use. Pillow draws the frames (fast, no figure machinery).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from bitcomm.channel.core import bits_to_index
from bitcomm.config import TaskConfig
from bitcomm.envs.core import MOVE_NAMES
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.files import write_atomic
from bitcomm.policies.agent_policies import AgentPolicy, BatchedPolicy

# tab10: distinct on white, and the colours matplotlib users know
PALETTE = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
)  # fmt: skip


class EpisodeRecord(NamedTuple):
    """One played episode; step t (0-based) maps positions[t] to positions[t + 1]."""

    task: TaskConfig
    goals: np.ndarray  # (n,) goal cell of each agent
    positions: np.ndarray  # (T + 1, n) cell of each agent: start, then after each step
    moves: np.ndarray  # (T, n) chosen moves (what was executed may differ under actuation noise)
    sent: np.ndarray  # (T, n, K) bits each agent sent at each step
    received: np.ndarray  # (T, n, slots, K) bits that arrived at each step, the input of that step's move
    team_rewards: np.ndarray  # (T,)
    success: bool  # every agent on its goal before truncation

    @property
    def length(self) -> int:
        return int(self.moves.shape[0])


def record_episode(policy: AgentPolicy, task: TaskConfig, seed: int = 0) -> EpisodeRecord:
    """Play one episode of `task` (picked by `seed`) with `policy` and keep everything a picture needs.

    The vectorized env resets an episode the moment it ends, so its last positions are read as the
    goals (termination means every agent is on its goal) and truncation is handled here: the env runs
    with one more step of budget and this loop stops at `max_steps`.
    """
    T = task.env.max_steps
    roomy = TaskConfig(dataclasses.replace(task.env, max_steps=T + 1), task.channel)
    env = VecGoalExchange(roomy, 1, seed=seed)
    act = BatchedPolicy(policy)
    goals = env.core.goal[0].copy()
    positions, moves, sent, received, rewards = [env.core.pos[0].copy()], [], [], [], []
    success = False
    for _ in range(T):
        obs = env.observe()
        received.append(obs.received[0].copy())
        move, bits = act(obs)
        result, _ = env.step(move, bits)
        moves.append(move[0].copy())
        sent.append(bits[0].copy())
        rewards.append(float(result.team_reward[0]))
        if result.terminated[0]:
            positions.append(goals.copy())
            success = True
            break
        positions.append(env.core.pos[0].copy())
    return EpisodeRecord(
        task, goals, np.stack(positions), np.stack(moves), np.stack(sent), np.stack(received),
        np.asarray(rewards, dtype=np.float64), success,
    )  # fmt: skip


LEGEND = "ring: start   line: path   disc: position   square: goal   (state after the step)"


def load_font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """Pillow's built-in font at `size` where this Pillow can scale it (>= 10.1), else its bitmap font."""
    try:
        return ImageFont.load_default(size=size)
    except TypeError:
        return ImageFont.load_default()


def bit_string(bits: np.ndarray) -> str:
    return "".join(str(int(b)) for b in bits)


def _agent_line(record: EpisodeRecord, t: int, i: int) -> str:
    """What agent i chose, sent and received at step t (0-based)."""
    slots = record.task.slot_senders[i]
    heard = [f"{bit_string(record.received[t, i, k])}<-A{j}" for k, j in enumerate(slots) if j >= 0] or ["-"]
    sent = record.sent[t, i]
    return (
        f"A{i}  move {MOVE_NAMES[int(record.moves[t, i])]}  |  sent {bit_string(sent)} (={int(bits_to_index(sent))})"
        f"  |  received {' '.join(heard)}"
    )


def render_frames(record: EpisodeRecord, cell_px: int | None = None) -> list[Image.Image]:
    """One RGB image per step, state after the step (see the module docstring)."""
    task = record.task
    S, n = task.env.size, task.env.n_agents
    cell = cell_px or max(14, min(48, 480 // S))
    font = load_font(12)
    pad, line_h = 8, 17
    returns = np.cumsum(record.team_rewards)
    header = [
        f"step {t + 1}/{record.length}  team reward {record.team_rewards[t]:+.1f}  return {returns[t]:+.1f}"
        for t in range(record.length)
    ]
    header[-1] += "  all on goal" if record.success else "  truncated"
    lines = [[_agent_line(record, t, i) for i in range(n)] for t in range(record.length)]
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    text_w = max(probe.textlength(s, font=font) for s in [*header, LEGEND, *(x for ls in lines for x in ls)])
    grid_w = S * cell
    width = int(max(grid_w, text_w)) + 2 * pad
    top = pad + line_h + 4
    height = top + grid_w + pad + (n + 1) * line_h + pad
    x0 = (width - grid_w) // 2

    def centre(c: int, i: int) -> tuple[float, float]:
        """Cell centre, nudged per agent so paths and discs on one cell stay apart."""
        r, col = divmod(int(c), S)
        off = (i - (n - 1) / 2) * cell * 0.5 / max(n, 2)
        return x0 + (col + 0.5) * cell + off, top + (r + 0.5) * cell + off

    frames = []
    for t in range(record.length):
        img = Image.new("RGB", (width, height), (255, 255, 255))
        d = ImageDraw.Draw(img)
        d.text((pad, pad), header[t], fill=(0, 0, 0), font=font)
        for k in range(S + 1):
            d.line([(x0 + k * cell, top), (x0 + k * cell, top + grid_w)], fill=(200, 200, 200))
            d.line([(x0, top + k * cell), (x0 + grid_w, top + k * cell)], fill=(200, 200, 200))
        for i in range(n):
            colour = PALETTE[i % len(PALETTE)]
            gr, gc = divmod(int(record.goals[i]), S)
            inset = 2 + i % 3
            gx, gy = x0 + gc * cell, top + gr * cell
            d.rectangle([gx + inset, gy + inset, gx + cell - inset, gy + cell - inset], outline=colour, width=3)
            path = [centre(c, i) for c in record.positions[: t + 2, i]]
            if len(path) > 1:
                d.line(path, fill=colour, width=2)
            sx, sy = path[0]
            ring = cell * 0.15
            d.ellipse([sx - ring, sy - ring, sx + ring, sy + ring], outline=colour, width=2)
            px, py = path[-1]
            rad = cell * 0.3
            d.ellipse([px - rad, py - rad, px + rad, py + rad], fill=colour)
            d.text((px, py), str(i), fill=(255, 255, 255), font=font, anchor="mm")
            d.text((pad, top + grid_w + pad + i * line_h), lines[t][i], fill=colour, font=font)
        d.text((pad, top + grid_w + pad + n * line_h), LEGEND, fill=(110, 110, 110), font=font)
        frames.append(img)
    return frames


def save_gif(frames: list[Image.Image], path: str | Path, fps: float = 2.0) -> Path:
    """An animated GIF that loops, one frame per step (frames differ at least in their step counter,
    so no encoder merges two of them), written whole or not at all: `render` stopped as it wrote left half a GIF."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    duration = int(round(1000 / fps))
    write_atomic(
        path,
        lambda tmp: frames[0].save(
            tmp, format="GIF", save_all=True, append_images=frames[1:], duration=duration, loop=0, optimize=False
        ),
    )
    return path


def save_png_frames(frames: list[Image.Image], folder: str | Path) -> list[Path]:
    """`frame_001.png`, ... (numbered by step) in `folder`, each written whole or not at all: `render` stopped as it
    wrote one left that frame half written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    width = max(3, len(str(len(frames))))
    paths = []
    for t, frame in enumerate(frames, start=1):
        p = folder / f"frame_{t:0{width}d}.png"
        write_atomic(p, functools.partial(frame.save, format="PNG"))  # the temporary name says no format
        paths.append(p)
    return paths
