"""The late-sharpening experiment of docs/tuning.md, session 17 (refuted, not merged).

The default recipe (`reinforced`), with the move entropy bonus and the uniform-move pull switched off once
the schedule has played a fraction FROM of the budget (the message entropy bonus kept): does a receiver that
is nearly deterministic by the end make greedy play follow sampled play? It is a schedule on the
regularisers, so the run stays pure (every gradient that reaches a policy head comes from the estimator and
the one remaining entropy term). To rerun it on a checkout:

    python docs/experiments/late_move_sharpening.py --from 0.75 --seed 0 --out runs/sharpen75-s0
    bitcomm eval runs/sharpen75-s0 --episodes 2000 --seed 0 [--greedy]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from bitcomm.learn import learner
from bitcomm.learn.config import make_train_config
from bitcomm.learn.objectives import Term, policy_terms
from bitcomm.learn.run import train


def sharpen_from(start: float) -> None:
    """Make every Learner's terms drop the move entropy and the uniform-move pull from progress `start` on."""
    cache: dict[bool, list[Term]] = {}

    def terms(self: learner.Learner) -> list[Term]:
        sharp = self.progress >= start
        if sharp not in cache:
            cfg = dataclasses.replace(self.cfg, entropy_move=0.0, uniform_move=0.0) if sharp else self.cfg
            cache[sharp] = policy_terms(cfg, self.codebook, 1.0)
        return cache[sharp]

    learner.Learner.terms = property(terms)  # type: ignore[method-assign,assignment]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--from", dest="start", type=float, default=0.75, help="fraction of the budget (default 0.75)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=200_000)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    sharpen_from(args.start)
    train(make_train_config("reinforced", episodes=args.episodes, seed=args.seed), args.out, progress=False)


if __name__ == "__main__":
    main()
