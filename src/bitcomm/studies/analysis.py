"""What a protocol means: how much each bit says about the goal its sender sees, and how much of the
goal survives the channel.

Samples come from playing the task in the vectorized env (`collect_messages`): every message sent,
paired with the goal its sender observed at that step, and every delivery (message x recipient),
paired with the bits the recipient read after the channel's flips and drops. Deliveries whose
episode ended before arrival are left out (they are never read).

Estimators are plug-in (empirical frequencies) over many samples; their upward bias is about
(|X| - 1)(|Y| - 1) / (2 N ln 2) bits when X and Y are independent, reported as `bias_scale_bits` for the
transmitted figure (an order of magnitude: a deterministic code has far less).
- Per bit k: I(bit_k; goal row), I(bit_k; goal column), I(bit_k; goal cell), from sent bits.
- I(goal; received message): the information that actually reaches the recipient, in bits, to be read
  against the channel's capacity K (1 - H(flip_prob)) and against H(goal) (log2(size^2) when goals
  are uniform). The oracle sends the cell index, so without noise it transmits all of H(goal).
- A lookup decoder (most frequent goal per received bit pattern) is fitted on the deliveries of half
  the episodes and scored on the other half's: its accuracy, and I(goal; decoded goal) on the held-out
  half, an estimate with no fitting bias. The halves split episodes, not deliveries, because a sender
  repeats itself within an episode: a pattern seen in both halves of one episode would be remembered,
  not decoded.
The goal a message is scored against is its *sender's observed goal*: in the paper's task that is the
recipient's own goal, the one thing it needs to hear.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from bitcomm.channel.core import bits_to_index
from bitcomm.config import TaskConfig
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.errors import bad_value
from bitcomm.policies.agent_policies import AgentPolicy, BatchedPolicy
from bitcomm.studies.tables import task_title


class MessageSamples(NamedTuple):
    """Messages and deliveries gathered from play."""

    sent_goal: np.ndarray  # (M,) cell index of the goal the sender observed
    sent_bits: np.ndarray  # (M, K) what it sent
    delivered_goal: np.ndarray  # (D,) sender's observed goal, one row per message x recipient
    received_bits: np.ndarray  # (D, K) what that recipient read (after flips and drops)
    delivered_episode: np.ndarray | None = None  # (D,) a key per episode (None: each delivery its own)


def collect_messages(
    policy: AgentPolicy, task: TaskConfig, samples: int = 200_000, num_envs: int = 1024, seed: int = 0
) -> MessageSamples:
    """Play until at least `samples` deliveries (message x recipient) were sent in time to arrive before play
    stops; vectorized over `num_envs` episodes. Those whose episode ends first are never delivered, so fewer are
    gathered: playing on until `samples` arrive would never stop where episodes end before the delay."""
    env = VecGoalExchange(task, num_envs, seed=seed)
    act = BatchedPolicy(policy)
    n, C, d = task.env.n_agents, task.env.cells, task.channel.delay
    receivers, slots = np.nonzero(task.slot_senders >= 0)  # every (recipient, input slot) that hears someone
    slot_sender = task.slot_senders[receivers, slots]
    per_step = num_envs * receivers.size
    steps = d + math.ceil(samples / per_step)
    sent_goal, sent_bits, deliv_goal, recv_bits, deliv_episode = [], [], [], [], []
    ring_goal = np.zeros((d, num_envs, n), dtype=np.int64)  # goals seen by the senders of messages in flight
    ring_episode = np.full((d, num_envs), -1, dtype=np.int64)
    episode = np.zeros(num_envs, dtype=np.int64)  # episodes finished per slot: tells a reset happened
    for step in range(steps):
        obs = env.observe()
        k = step % d  # the ring slot of messages sent d steps ago, which arrive now
        same = ring_episode[k] == episode
        if same.any():
            deliv_goal.append(ring_goal[k][same][:, slot_sender].ravel())
            recv_bits.append(obs.received[same][:, receivers, slots].reshape(-1, task.channel.bits))
            deliv_episode.append(np.repeat(np.flatnonzero(same) * (steps + 1) + episode[same], receivers.size))
        seen = obs.planes[:, :, 1].reshape(num_envs, n, C).argmax(-1)
        moves, bits = act(obs)
        sent_goal.append(seen.ravel())
        sent_bits.append(bits.reshape(-1, task.channel.bits))
        ring_goal[k], ring_episode[k] = seen, episode
        result, _ = env.step(moves, bits)
        episode[result.finished.env_index] += 1
    if not deliv_goal:  # every episode ended before a message sent in it arrived: nothing to measure
        raise bad_value(
            "delay",
            d,
            f"no message arrived in {steps} steps of play: every episode ended within {d} steps of each message "
            "sent in it; give a shorter --delay, or a policy whose episodes last longer",
        )
    return MessageSamples(
        np.concatenate(sent_goal), np.concatenate(sent_bits).astype(np.uint8),
        np.concatenate(deliv_goal), np.concatenate(recv_bits).astype(np.uint8), np.concatenate(deliv_episode),
    )  # fmt: skip


# ---------------------------------------------------------------------- estimators
def entropy(keys: np.ndarray) -> float:
    """Plug-in entropy in bits of the values in `keys` (any integers)."""
    _, counts = np.unique(keys, return_counts=True)
    p = counts / counts.sum()
    return float(-(p * np.log2(p)).sum())


def mutual_information(x: np.ndarray, y: np.ndarray) -> float:
    """Plug-in I(X; Y) = H(X) + H(Y) - H(X, Y) in bits, for non-negative integer samples."""
    x, y = np.asarray(x, dtype=np.int64), np.asarray(y, dtype=np.int64)
    joint = x * (int(y.max()) + 1) + y
    return max(0.0, entropy(x) + entropy(y) - entropy(joint))


def binary_entropy(p: float) -> float:
    if p <= 0.0 or p >= 1.0:
        return 0.0
    return float(-p * math.log2(p) - (1 - p) * math.log2(1 - p))


CAPACITY_WITH_DROPS = ", drops not counted (they lower it further)"
"""What summary.md adds to the capacity's row where messages are dropped: a drop reads as the all-zeros word, which
the figure does not count."""


def channel_capacity(bits: int, flip_prob: float) -> float:
    """K (1 - H(flip_prob)): K independent binary symmetric channels (drops lower it further)."""
    return bits * (1.0 - binary_entropy(flip_prob))


def fit_lookup_decoder(patterns: np.ndarray, goals: np.ndarray) -> tuple[dict[int, int], int]:
    """Most frequent goal per pattern, and the overall most frequent goal for unseen patterns."""
    pairs, counts = np.unique(np.stack([patterns, goals], axis=1), axis=0, return_counts=True)
    order = np.lexsort((-counts, pairs[:, 0]))  # by pattern, most frequent goal first
    pairs = pairs[order]
    first = np.ones(len(pairs), dtype=bool)
    first[1:] = pairs[1:, 0] != pairs[:-1, 0]
    table = {int(p): int(g) for p, g in pairs[first]}
    values, freq = np.unique(goals, return_counts=True)
    return table, int(values[freq.argmax()])


def split_by_episode(episodes: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the deliveries of a random half of the episodes (to fit on), and of the rest (to score on)."""
    keys, group = np.unique(episodes, return_inverse=True)
    held_out = np.zeros(keys.size, dtype=bool)
    held_out[np.random.default_rng(seed).permutation(keys.size)[keys.size // 2 :]] = True
    return np.flatnonzero(~held_out[group]), np.flatnonzero(held_out[group])


def check_split(fit: np.ndarray, test: np.ndarray, deliveries: int) -> None:
    """One line unless both halves hold deliveries: those of one episode (one slow episode side by side with no
    other, `--envs 1`) left nothing to fit the decoder on, an argmax of an empty sequence."""
    if fit.size == 0 or test.size == 0:
        raise bad_value(
            "deliveries",
            deliveries,
            "all from one episode; the lookup decoder is fitted on half the episodes and scored on the others, so "
            "it needs deliveries from 2 or more (give more --samples or --envs)",
        )


def decode(table: dict[int, int], default: int, patterns: np.ndarray) -> np.ndarray:
    return np.fromiter((table.get(int(p), default) for p in patterns), dtype=np.int64, count=len(patterns))


# ---------------------------------------------------------------------- report
@dataclass(frozen=True)
class BitReport:
    bit: int
    p_one: float
    mi_row: float
    mi_col: float
    mi_cell: float


@dataclass(frozen=True)
class ProtocolReport:
    """Summary figures of `analyze` (the `--json` output)."""

    policy: str
    task: str
    """The task played, as titles name it (`bitcomm.studies.tables.task_title`): summary.md named no agents or delay."""
    bits: int
    size: int
    flip_prob: float
    drop_prob: float
    messages: int
    deliveries: int
    goal_entropy_bits: float
    encoded_bits: float
    """I(observed goal; sent message): what the sender puts in, before the channel."""
    transmitted_bits: float
    """I(observed goal; received message): what reaches the recipient."""
    bias_scale_bits: float
    capacity_bits: float
    decoder_accuracy: float
    decoder_chance: float
    decoded_bits: float
    """I(goal; decoded goal) on the held-out half."""
    per_bit: tuple[BitReport, ...]

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


def analyze_samples(samples: MessageSamples, task: TaskConfig, policy: str = "", seed: int = 0) -> ProtocolReport:
    """Every figure of the report, from collected samples (pure: no play)."""
    S, K = task.env.size, task.channel.bits
    goal, sent = samples.sent_goal, samples.sent_bits
    row, col = np.divmod(goal, S)
    per_bit = tuple(
        BitReport(k, float(bit.mean()), *(mutual_information(bit, target) for target in (row, col, goal)))
        for k, bit in enumerate(sent.T)
    )
    dgoal, received = samples.delivered_goal, bits_to_index(samples.received_bits)
    D = len(dgoal)
    episodes = samples.delivered_episode if samples.delivered_episode is not None else np.arange(D)
    fit, test = split_by_episode(episodes, seed)
    check_split(fit, test, D)
    table, default = fit_lookup_decoder(received[fit], dgoal[fit])
    decoded = decode(table, default, received[test])
    n_goals, n_patterns = np.unique(dgoal).size, np.unique(received).size
    return ProtocolReport(
        policy=policy,
        task=task_title(task),
        bits=K,
        size=S,
        flip_prob=task.channel.flip_prob,
        drop_prob=task.channel.drop_prob,
        messages=len(goal),
        deliveries=D,
        goal_entropy_bits=entropy(dgoal),
        encoded_bits=mutual_information(goal, bits_to_index(sent)),
        transmitted_bits=mutual_information(dgoal, received),
        bias_scale_bits=(n_goals - 1) * (n_patterns - 1) / (2 * D * math.log(2)),
        capacity_bits=channel_capacity(K, task.channel.flip_prob),
        decoder_accuracy=float((decoded == dgoal[test]).mean()),
        decoder_chance=float((dgoal[test] == default).mean()),
        decoded_bits=mutual_information(dgoal[test], decoded),
        per_bit=per_bit,
    )


def bit_maps(samples: MessageSamples, task: TaskConfig) -> np.ndarray:
    """`(K, S, S)`: P(sent bit k = 1 | observed goal at that cell); NaN where no sample saw the cell."""
    C, S = task.env.cells, task.env.size
    count = np.bincount(samples.sent_goal, minlength=C).astype(np.float64)
    ones = np.stack([np.bincount(samples.sent_goal, weights=b, minlength=C) for b in samples.sent_bits.T])
    with np.errstate(invalid="ignore", divide="ignore"):
        return (ones / count).reshape(-1, S, S)


def save_heatmaps(maps: np.ndarray, path: str | Path, title: str = "") -> Path:
    """One PNG: a panel per bit, P(bit = 1) over the sender's observed goal cell (row down, column right)."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    K = maps.shape[0]
    cols = min(K, 4)
    rows = math.ceil(K / cols)
    fig = Figure(figsize=(2.6 * cols + 0.8, 2.5 * rows + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    image = None
    for k, ax in enumerate(axes):
        if k >= K:
            ax.set_axis_off()
            continue
        image = ax.imshow(maps[k], vmin=0.0, vmax=1.0, cmap="viridis")
        ax.set_title(f"bit {k}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if image is not None:
        fig.colorbar(image, ax=list(axes[:K]), shrink=0.8, label="P(bit = 1 | observed goal cell)")
    if title:
        fig.suptitle(title, fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


def markdown_summary(report: ProtocolReport, heatmap_name: str | None = None) -> str:
    """A short human-readable page: headline figures, per-bit table, heatmap link."""
    r = report
    lines = [
        f"# Protocol analysis: {r.policy}",
        "",
        f"Task: {r.task}. {r.messages} messages, {r.deliveries} deliveries (plug-in estimates).",
        "",
        "| figure | bits |",
        "| --- | --- |",
        f"| H(goal) | {r.goal_entropy_bits:.3f} |",
        f"| I(goal; sent message) | {r.encoded_bits:.3f} |",
        f"| I(goal; received message), transmitted | {r.transmitted_bits:.3f} "
        f"(plug-in bias scale {r.bias_scale_bits:.3f}) |",
        f"| channel capacity K(1 - H(flip_prob)){CAPACITY_WITH_DROPS if r.drop_prob else ''} | {r.capacity_bits:.3f} |",
        f"| I(goal; decoded goal), held out | {r.decoded_bits:.3f} |",
        "",
        f"Lookup decoder (most frequent goal per received pattern, fitted on half the episodes, scored on the rest): "
        f"accuracy {r.decoder_accuracy:.3f} (always guessing the most frequent goal: {r.decoder_chance:.3f}).",
        "",
        "| bit | P(bit=1) | I(bit; goal row) | I(bit; goal column) | I(bit; goal cell) |",
        "| --- | --- | --- | --- | --- |",
        *(f"| {b.bit} | {b.p_one:.3f} | {b.mi_row:.3f} | {b.mi_col:.3f} | {b.mi_cell:.3f} |" for b in r.per_bit),
        "",
        "Bit 0 is the most significant bit of the message index.",
    ]
    if heatmap_name:
        lines += ["", f"![P(bit = 1) over the observed goal cell]({heatmap_name})"]
    return "\n".join(lines) + "\n"
