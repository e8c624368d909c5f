"""Where does greedy play lose to sampled play? (issue 16's greedy target)

Evaluates one learned policy four ways on the same episodes: sampled moves and bits, greedy moves and bits
(`bitcomm eval --greedy`), and each half greedy with the other sampled. If greedy bits with sampled moves are
close to sampled play and greedy moves are not, the arg-max movement loops where the message leaves the goal
ambiguous (a reactive policy then needs randomness); `bitcomm analyze RUN --greedy` gives how ambiguous
(decoder accuracy, bits transmitted against the goal's entropy).

    python benchmarks/greedy_split.py RUN [--episodes 2000] [--seed 0]
"""

from __future__ import annotations

import argparse

import numpy as np


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


def main() -> None:
    import torch

    from bitcomm.policies.agent_policies import BatchedPolicy
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", help="run folder or checkpoint of a grid run")
    ap.add_argument("--episodes", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if a.episodes < 1:
        ap.error(f"--episodes {a.episodes}: must be >= 1")
    torch.set_num_threads(1)
    print("| moves | bits | mean episode length | success |\n| --- | --- | --- | --- |")
    for greedy_moves, greedy_bits in ((False, False), (True, True), (True, False), (False, True)):
        controller = Controller.load(a.run, seed=a.seed)  # the same sampling stream for every row
        policy = BatchedPolicy(MixedPlay(controller, greedy_moves, greedy_bits))
        r = evaluate(policy, controller.task, a.episodes, a.seed)
        names = ("greedy" if greedy_moves else "sampled", "greedy" if greedy_bits else "sampled")
        print(f"| {names[0]} | {names[1]} | {r.mean_episode_length:.2f} | {r.success_rate:.3f} |", flush=True)


if __name__ == "__main__":
    main()
