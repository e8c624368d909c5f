"""The marginal-message-entropy experiment of docs/tuning.md, session 18 (not merged).

Greedy play trails sampled play because about a fifth of the goals share their arg-max code with another
(docs/tuning.md, session 10). The default recipe's message entropy bonus rewards each message for being
random given what its sender sees, H(Pm(. | s)); this experiment adds a bonus on the entropy of the
minibatch's *average* message distribution, H(mean_s Pm(. | s)), which grows when different senders' states
put their mass on different codes (a code shared by two goals lowers it). It is an entropy term on the
sender's own distribution: no label, no target, no receiver, no channel. To rerun it on a checkout:

    python docs/experiments/marginal_message_entropy.py --weight 0.01 --seed 0 --out runs/marginal01-s0
    bitcomm eval runs/marginal01-s0 --episodes 2000 --seed 0 [--greedy]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import torch

from bitcomm.learn import learner
from bitcomm.learn.config import make_train_config
from bitcomm.learn.objectives import StepBatch, Term, policy_terms
from bitcomm.learn.run import train


@dataclass(frozen=True)
class MarginalMessageEntropy:
    """-n w H(p), p the mean over the minibatch's sent messages of Pm(. | s): every code's probability."""

    weight: float
    name: str = "entropy_message_marginal"
    auxiliary: bool = False

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        head = b.policy.head
        p = head.log_prob_of_terms(head.log_prob_terms(b.msg_logits)).exp().mean(0)  # (2^K,)
        h = -(p * p.clamp(min=1e-12).log()).sum()
        return -(b.n * self.weight) * h, {f"charts/{self.name}": h.item()}


def add_marginal_entropy(weight: float) -> None:
    """Make every Learner's terms end with the marginal message entropy bonus."""

    def terms(self: learner.Learner) -> list[Term]:
        scale = max(0.0, 1.0 - self.progress) if self.cfg.anneal_entropy else 1.0
        return [*policy_terms(self.cfg, self.codebook, scale), MarginalMessageEntropy(weight * scale)]

    learner.Learner.terms = property(terms)  # type: ignore[method-assign,assignment]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weight", type=float, default=0.01, help="weight of the bonus (default 0.01)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=200_000)
    p.add_argument("--size", type=int, default=None, help="grid size (default: the paper's task)")
    p.add_argument("--bits", type=int, default=None)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    add_marginal_entropy(args.weight)
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig

    task = TaskConfig()
    if args.size is not None:
        task = TaskConfig(EnvConfig(size=args.size), ChannelConfig(bits=args.bits or task.channel.bits))
    cfg = make_train_config("reinforced", task, episodes=args.episodes, seed=args.seed)
    train(cfg, args.out, progress=False)


if __name__ == "__main__":
    main()
