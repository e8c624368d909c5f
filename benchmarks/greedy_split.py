"""Where does greedy play lose to sampled play? (issue 16's greedy target)

Evaluates one learned policy four ways on the same episodes: sampled moves and bits, greedy moves and bits
(`bitcomm eval --greedy`), and each half greedy with the other sampled. If greedy bits with sampled moves are
close to sampled play and greedy moves are not, the arg-max movement loops where the message leaves the goal
ambiguous (a reactive policy then needs randomness); `bitcomm analyze RUN --greedy` gives how ambiguous
(decoder accuracy, bits transmitted against the goal's entropy).

Then a census of the greedy episodes that never end. Greedy play is deterministic and, with the channel's
delay of one step and no noise, the positions and the messages arriving make the whole state: once that
joint state repeats, the episode cycles until it is cut (with a longer delay or a noisy channel, a repeat of
what is seen is not yet a cycle). Each such episode is put down with its period (1: the agents stand still,
or push against a wall, on fixed messages; 2: agents step back and forth), whether the messages arriving
change along the cycle, and which agents choose a move in it.

`--stalls N` then shows the first N greedy episodes still running a few steps before the limit, as each agent
sees them there: its cell and goal, the bits arriving, its move probabilities, and the probability of each bit it
sends being 1; a bit near 0.5 is a code the sender hedges between two words, which greedy play rounds to one
(docs/tuning.md, session 33).

    python benchmarks/greedy_split.py RUN [--episodes 2000] [--seed 0] [--max-period 64] [--census-only] [--detail]
        [--stalls N] [--words]

`--words` first counts the goals whose most likely word (the observed head's) another goal shares, and the
neighbouring pairs and the pairs at most 3 cells apart among them.
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch


class MixedPlay:
    """An `AgentPolicy` acting greedily in moves and/or bits, sampling the rest."""

    def __init__(self, controller: object, greedy_moves: bool, greedy_bits: bool) -> None:
        self.controller, self.greedy_moves, self.greedy_bits = controller, greedy_moves, greedy_bits
        self.task = controller.task  # type: ignore[attr-defined]

    def act(
        self, planes: np.ndarray, received: np.ndarray, t: np.ndarray, agent: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        greedy = self.controller.act(planes, received, greedy=True)  # type: ignore[attr-defined]
        sampled = self.controller.act(planes, received, greedy=False)  # type: ignore[attr-defined]
        moves = (greedy if self.greedy_moves else sampled)[0]
        bits = (greedy if self.greedy_bits else sampled)[1]
        n = planes.shape[0]
        return np.asarray(moves, np.int64).reshape(n), np.asarray(bits, np.uint8).reshape(n, self.task.channel.bits)


def cycle_census(
    policy: Callable[[Any], tuple[np.ndarray, np.ndarray]], task: Any, episodes: int, seed: int, max_period: int
) -> tuple[int, Counter[tuple]]:
    """A deterministic `policy` (greedy play) on the seeded episode set: how many first episodes are cut at
    the step limit, and of those,
    `(period or None, messages change along the cycle, agents that choose a move in it, each agent's (nearest,
    farthest) distance to its goal along it)` -> count. The period is found on the last steps of the episode
    (None: no repeat within `max_period` steps; the agents' distances are then those of the last step)."""
    from bitcomm.policies.evaluation import play_first_episodes, seeded_episode_envs

    cut, census, n = 0, Counter[tuple](), task.env.n_agents
    for _, env in seeded_episode_envs(task, episodes, seed):
        positions, arriving, moved = [], [], []
        goals = env.observe().state[:, n : 2 * n].reshape(env.num_envs, n, -1).argmax(-1)  # fixed in an episode
        length = np.zeros(env.num_envs, dtype=np.int64)
        for step in play_first_episodes(env, policy):
            after = env.observe()  # the state after this step (the buffers are live)
            positions.append(after.state[:, :n].reshape(env.num_envs, n, -1).argmax(-1))
            arriving.append(np.packbits(after.received.reshape(env.num_envs, -1), axis=1))
            moved.append(step.moves != 0)
            fin = step.result.finished
            first = step.active[fin.env_index]
            length[fin.env_index[first]] = np.where(fin.success[first], 0, fin.length[first])  # 0: it ended
        pos, msg, mov = np.stack(positions, 1), np.stack(arriving, 1), np.stack(moved, 1)
        (row, col), (goal_row, goal_col) = np.divmod(pos, task.env.size), np.divmod(goals[:, None], task.env.size)
        distance = np.abs(row - goal_row) + np.abs(col - goal_col)  # (B, T, n) cells from each agent's goal
        for b in np.flatnonzero(length):
            last = length[b] - 2  # the state after the episode's second-to-last step; the last one resets it
            key = np.concatenate([pos[b, : last + 1].astype(np.int64), msg[b, : last + 1].astype(np.int64)], 1)
            repeats = (p for p in range(1, min(max_period, last) + 1) if np.array_equal(key[last], key[last - p]))
            period = next(repeats, None)
            span = slice(last + 1 - (period or 1), last + 1)
            changes = period is not None and len({m.tobytes() for m in msg[b, span]}) > 1
            movers = tuple(int(a) for a in np.flatnonzero(mov[b, span].any(0))) if period else ()
            near, far = distance[b, span].min(0), distance[b, span].max(0)
            census[(period, changes, movers, tuple(zip(near.tolist(), far.tolist(), strict=True)))] += 1
            cut += 1
    return cut, census


def watching_stalls(
    policy: Callable[[Any], tuple[np.ndarray, np.ndarray]], task: Any, count: int
) -> tuple[Callable[[Any], tuple[np.ndarray, np.ndarray]], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """`policy`, recording as it plays (in `cycle_census`, say) the inputs of the first `count` first episodes it has
    not ended `STALL_MARGIN` steps before the limit: each one's `(planes (n, 2, S, S), received (n, slots, K), state)`
    at that step. A first episode's step is the play's step, the largest `t` of any slot while one is still running;
    a slot's later episodes are younger, so they are not taken."""
    at = task.env.max_steps - STALL_MARGIN
    caught: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def watching(obs: Any) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(obs.t)
        if len(caught) < count and t.max() == at:
            for b in np.flatnonzero(t == at)[: count - len(caught)]:
                caught.append((obs.planes[b].copy(), obs.received[b].copy(), obs.state[b].copy()))
        return policy(obs)

    return watching, caught


STALL_MARGIN = 6
"""`--stalls` looks at an episode this many steps before the limit, well inside a cycle that never ends."""


def print_stalls(controller: Any, stalls: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """Each stalled episode's agents as they see it: cell, goal, bits arriving, move probabilities (stay, up, down,
    left, right) and each sent bit's probability of being 1 (either head: the sum over the messages with that bit)."""
    import torch

    from bitcomm.channel.core import index_to_bits

    task, net = controller.task, controller.policy
    n, size, bits = task.env.n_agents, task.env.size, task.channel.bits
    words = index_to_bits(torch.arange(1 << bits), bits).float()  # (2^K, K)
    for planes, received, state in stalls:
        with torch.no_grad():
            move_logits, msg_logits = net(torch.from_numpy(planes).float(), torch.from_numpy(received))
            head = net.head
            p_bits = head.log_prob_of_terms(head.log_prob_terms(msg_logits)).exp() @ words  # (n, K)
        moves = torch.softmax(move_logits, -1)
        cells = state[:n].reshape(n, -1).argmax(-1), state[n : 2 * n].reshape(n, -1).argmax(-1)
        print()
        for a in range(n):
            (r, c), (gr, gc) = divmod(int(cells[0][a]), size), divmod(int(cells[1][a]), size)
            arriving = " ".join("".join(map(str, slot)) for slot in received[a].tolist())
            print(f"agent {a}: at ({r}, {c}), goal ({gr}, {gc}), {abs(r - gr) + abs(c - gc)} cells off; bits arriving "
                  f"{arriving}; moves {' '.join(f'{p:.2f}' for p in moves[a].tolist())}; "
                  f"p(sent bit = 1) {' '.join(f'{p:.2f}' for p in p_bits[a].tolist())}")  # fmt: skip


def print_split(run: str, episodes: int, seed: int) -> None:
    """The four-way table: sampled and greedy moves crossed with sampled and greedy bits."""
    from bitcomm.policies.agent_policies import BatchedPolicy
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate

    print("| moves | bits | mean episode length | success |\n| --- | --- | --- | --- |")
    for greedy_moves, greedy_bits in ((False, False), (True, True), (True, False), (False, True)):
        controller = Controller.load(run, seed=seed)  # the same sampling stream for every row
        policy = BatchedPolicy(MixedPlay(controller, greedy_moves, greedy_bits))
        r = evaluate(policy, controller.task, episodes, seed)
        names = ("greedy" if greedy_moves else "sampled", "greedy" if greedy_bits else "sampled")
        print(f"| {names[0]} | {names[1]} | {r.mean_episode_length:.2f} | {r.success_rate:.3f} |", flush=True)


def period_class(period: int | None, max_period: int) -> str:
    """A cycle's period as a row of the summary: 1 and 2 alone, longer ones in two bands."""
    if period is None:
        return f"no repeat in {max_period} steps"
    return str(period) if period <= 2 else "3-8" if period <= 8 else f"9-{max_period}"


def print_census(census: Counter[tuple], max_period: int, detail: bool) -> None:
    """The census as one row per period class and whether the messages change along the cycle, with how many of
    its episodes keep every agent within a cell of its goal somewhere on the cycle (a neighbouring cell read as
    the goal); `detail`: one row per kind of cycle (many on a large grid)."""
    rows: Counter[tuple[str, bool]] = Counter()
    near: Counter[tuple[str, bool]] = Counter()
    for (period, changes, _, distances), count in census.items():
        row = (period_class(period, max_period), changes)
        rows[row] += count
        near[row] += count * all(lo <= 1 for lo, _ in distances)
    print("\n| period of the joint state | messages arriving change | episodes | of which every agent comes within a "
          "cell of its goal |\n| --- | --- | --- | --- |")  # fmt: skip
    for (where, changes), count in sorted(rows.items(), key=lambda kv: -kv[1]):
        print(f"| {where} | {'yes' if changes else 'no'} | {count} | {near[(where, changes)]} |")
    if not detail:
        return
    print("\n| period of the joint state | messages arriving change | agents choosing a move | each agent's cells from "
          "its goal along the cycle | episodes |")  # fmt: skip
    print("| --- | --- | --- | --- | --- |")
    for (period, changes, movers, distances), count in sorted(census.items(), key=lambda kv: (-kv[1], str(kv[0]))):
        where = period_class(period, max_period) if period is None else str(period)
        moving = ", ".join(map(str, movers)) or "none"
        cells = ", ".join(str(lo) if lo == hi else f"{lo}-{hi}" for lo, hi in distances)
        print(f"| {where} | {'yes' if changes else 'no'} | {moving if period else '-'} | {cells} | {count} |")


NEARBY = 3
"""How far apart (Manhattan, in cells) two goals on one word count as nearby (`message_divergence_radius`'s default)."""


HEDGED = 0.2
"""A bit sent with a probability between HEDGED and 1 - HEDGED is hedged: sampled play sends both values, greedy play
always the one it rounds to, which may be another goal's word (docs/tuning.md sessions 43-44)."""


def goal_observations(controller: Any) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
    """`(S*S, 2, S, S)` planes that show each goal cell once, and the pairs of goal cells at most `NEARBY` apart, for a
    message head that reads only the observed goal (`message_reads` `observed`, the default); one error line for a
    run whose head reads more, so that a goal has no word of its own."""
    from bitcomm.errors import ConfigError
    from bitcomm.learn.objectives import nearby_goals

    model = controller.config.get("model", {})
    if model.get("message_reads") != "observed":
        raise ConfigError(
            f"invalid run: its message head reads {model.get('message_reads')!r}, not only the observed goal, so a "
            "goal has no word of its own; --words needs --message-reads observed"
        )
    goal_planes, first, second = nearby_goals(controller.task.env.size, NEARBY)  # `message_divergence`'s pairs
    planes = goal_planes.numpy().astype(np.uint8)
    planes[:, 0, 0, 0] = 1  # where the sender stands: the head does not read it
    return planes, first, second


def shared_words(controller: Any) -> tuple[int, int, int, int]:
    """The most likely word a sender sends for each goal it can observe: (distinct words, goals that share their word
    with another, pairs of neighbouring goals that share one, pairs at most `NEARBY` cells apart that share one). Two
    nearby goals on one word cost sampled play little (the word's bits still vary) and can stall greedy play
    (docs/tuning.md, sessions 37 and 43)."""
    from bitcomm.channel.core import bits_to_index

    planes, first, second = goal_observations(controller)
    task = controller.task
    S, K, cells = task.env.size, task.channel.bits, task.env.size**2
    _, bits = controller.act(planes, np.zeros((cells, task.slots, K), np.uint8), greedy=True)
    word = bits_to_index(bits)
    _, index, counts = np.unique(word, return_inverse=True, return_counts=True)
    shared = word[first.numpy()] == word[second.numpy()]
    apart = (first // S - second // S).abs() + (first % S - second % S).abs()
    return len(counts), int((counts[index] > 1).sum()), int(shared[apart.numpy() == 1].sum()), int(shared.sum())


def hedged_bits(controller: Any) -> tuple[int, int]:
    """(bits, goals): how many of the K bits of every goal's word the senders send with a probability between
    `HEDGED` and 1 - `HEDGED`, and how many goals have one. Each bit's probability is its marginal under the message
    head (for a one-hot head, the sum over the words that set it)."""
    import torch

    from bitcomm.channel.core import index_to_bits

    planes, _, _ = goal_observations(controller)
    policy, K = controller.policy, controller.task.channel.bits
    with torch.no_grad():
        logits = policy.observed_message_logits(torch.from_numpy(planes))
        words = policy.head.log_prob_of_terms(policy.head.log_prob_terms(logits)).exp()  # (S*S, 2^K)
        p = words @ index_to_bits(torch.arange(1 << K), K).to(words.dtype)  # (S*S, K) P(bit = 1)
    hedged = (p >= HEDGED) & (p <= 1 - HEDGED)
    return int(hedged.sum()), int(hedged.any(1).sum())


def main() -> None:
    import torch

    from bitcomm.errors import ConfigError
    from bitcomm.policies.agent_policies import BatchedPolicy, ControllerAgent
    from bitcomm.policies.controller import Controller

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="run folder or checkpoint of a grid run")
    ap.add_argument("--episodes", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-period", type=int, default=64, help="longest cycle looked for (default %(default)s)")
    ap.add_argument("--census-only", action="store_true", help="skip the four-way table (cheaper on large grids)")
    ap.add_argument("--detail", action="store_true", help="also list the census by kind of cycle")
    ap.add_argument("--stalls", type=int, default=0, help="show this many stalled greedy episodes (default 0)")
    ap.add_argument("--words", action="store_true", help="also count the goals that share a most likely word")
    a = ap.parse_args()
    if a.episodes < 1:
        ap.error(f"--episodes {a.episodes}: must be >= 1")
    if a.max_period < 1:
        ap.error(f"--max-period {a.max_period}: must be >= 1")
    if a.stalls < 0:
        ap.error(f"--stalls {a.stalls}: must be >= 0")
    torch.set_num_threads(1)
    try:  # a missing or damaged run is one line, before anything is played
        controller = Controller.load(a.run, seed=a.seed)
    except ConfigError as err:
        ap.error(str(err))
    if a.words:
        try:
            distinct, sharing, pairs, nearby = shared_words(controller)
        except ConfigError as err:
            ap.error(str(err))
        cells = controller.task.env.size**2
        hedged, hedging = hedged_bits(controller)
        print(
            f"most likely words: {distinct} for {cells} goals; {sharing} goals share theirs; "
            f"{pairs} neighbouring pairs, {nearby} pairs at most {NEARBY} cells apart"
        )
        print(f"hedged bits (sent with probability {HEDGED}-{1 - HEDGED:g}): {hedged}, on {hedging} of {cells} goals")
    if not a.census_only:
        print_split(a.run, a.episodes, a.seed)
    greedy, stalls = watching_stalls(BatchedPolicy(ControllerAgent(controller, greedy=True)), controller.task, a.stalls)
    cut, census = cycle_census(greedy, controller.task, a.episodes, a.seed, a.max_period)
    print(f"\ngreedy episodes cut at the step limit: {cut} of {a.episodes}")
    print_census(census, a.max_period, a.detail)
    if a.stalls:
        print(f"\n{len(stalls)} stalled greedy episode(s), {STALL_MARGIN} steps before the limit:")
        print_stalls(controller, stalls)


if __name__ == "__main__":
    main()
