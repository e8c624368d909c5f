"""Named recipes: each a set of learning options (fields of TrainConfig and ModelConfig).

Plain data with no heavy imports, so the command line can list the names without importing torch.

- `reinforced` (the default): the paper's system, messages learned by reinforcement alone (SPEC
  section 7). Every gradient that reaches the movement or the message head comes from the chosen
  estimator's policy-gradient term plus the entropy terms; critics see the full state (as the
  paper's V1/V2 do). What it adds to the paper is engineering that leaves the estimators' role
  intact: batched synchronous updates with PPO-style reuse and clipping, advantage normalisation,
  gamma 0.5, shorter training episodes (32 steps; from 18x18, 3 per cell of the grid's side), learning
  rates decayed to zero over the budget (`anneal_lr`), observation features and a network shaped for
  the grid, in place of the per-message entropy bonus one on the batch's average message distribution
  (`entropy_message_marginal`, session 18), which keeps two goals from sharing a code, and the move
  regularisers decayed to zero with the rates (`anneal_move_entropy`, session 19), so that greedy
  moves end as good as sampled ones; since session 35 a message head that reads only the goal the
  sender observes (`message_reads` `observed`, session 28) and, from halfway, half of each batch played
  with every sender's most likely message (`greedy_senders`, session 34), so that greedy play sends
  the words the receivers learned; since session 46 those start only once the protocol has formed (the rolling
  length at most 1.15x the oracle's, `senders_wait_below`), so that on grids where it forms late they do not
  teach words about to change; since session 49, where the channel has words to spare (2^K above the grid's
  cells, as on the paper's task), a bonus for telling nearby goals apart (`message_divergence`, session 43) and
  a quarter of each batch sending one held word per episode (`held_messages`, session 44), so that no two nearby
  goals end on one word, which stalls greedy play, and since session 56, where those are on, a pull of every goal's
  message logits toward 0 (`message_logit_decay`), so that a word two goals share still has a gradient (each option
  named and measured in docs/tuning.md).
- `supervised`: `reinforced` plus three auxiliary losses that hand the sender a protocol (a
  self-labelled code book, a privileged goal label for the receiver's message decoder, and the
  sender's grounding in the goal it sees). Fast, but its messages are supervised: it bypasses both
  estimators and never serves a study of the paper's claims.
- `paper`: the paper's own training as written: asynchronous actor-critic, one-episode batches,
  Monte Carlo returns, one gradient step per batch, the paper's network.
"""

from __future__ import annotations

from typing import Any

DEFAULT_RECIPE = "reinforced"

_REINFORCED: dict[str, Any] = dict(
    mode="sync",
    num_envs=128,
    train_max_steps=32,
    lr=3e-3,
    gamma=0.5,
    epochs=4,
    minibatches=4,
    clip=0.2,
    adv_norm=True,
    entropy_message=0.0,
    entropy_message_marginal=0.1,
    goal_coef=0.0,
    seen_coef=0.0,
    code_coef=0.0,
    uniform_move=0.01,
    encoder="marginals",
    coords=False,
    plane_coords=True,
    message_map=False,
    anneal_lr=True,
    anneal_move_entropy=True,
    message_reads="observed",
    greedy_senders=0.5,
    senders_wait_below=1.15,
    message_divergence=1.0,
    message_logit_decay=0.001,
    held_messages=0.25,
)

_SUPERVISED: dict[str, Any] = dict(
    _REINFORCED,
    num_envs=64,
    train_max_steps=64,
    lr=1e-3,
    entropy_message=0.001,
    entropy_message_marginal=0.0,
    goal_coef=1.0,
    seen_coef=1.0,
    code_coef=1.0,
    encoder="conv",
    coords=True,
    message_map=True,
    anneal_lr=False,
    anneal_move_entropy=False,
    message_reads="all",
    greedy_senders=0.0,
    senders_wait_below=0.0,
    message_divergence=0.0,
    message_logit_decay=0.0,
    held_messages=0.0,
)
"""The former `fast` recipe, as measured in docs/tuning.md sessions 1-7."""

RECIPES: dict[str, dict[str, Any]] = {
    "reinforced": _REINFORCED,
    "supervised": _SUPERVISED,
    "paper": dict(
        mode="a3c",
        num_envs=1,
        train_max_steps=0,
        lr=1e-3,
        gamma=0.95,
        epochs=1,
        minibatches=1,
        clip=0.0,
        adv_norm=False,
        goal_coef=0.0,
        seen_coef=0.0,
        code_coef=0.0,
        uniform_move=0.0,
        entropy_message=0.001,
        entropy_message_marginal=0.0,
        anneal_lr=False,
        anneal_move_entropy=False,
        encoder="conv",
        coords=False,
        plane_coords=False,
        message_map=False,
        message_reads="all",
        greedy_senders=0.0,
        senders_wait_below=0.0,
        message_divergence=0.0,
        message_logit_decay=0.0,
        held_messages=0.0,
    ),
}
"""Each recipe's values for the learning options; any option given explicitly overrides them. Every recipe names
the same options, so that two recipes compare key by key (`benchmarks/ablation.py` sets one to the other's)."""

WIDE_MESSAGES: dict[str, Any] = dict(entropy_message_marginal=0.0, entropy_message=0.01)
"""What a recipe's marginal message entropy bonus gives way to on messages of more than 12 bits, where the
exact sum over all 2^K messages is out of reach: the per-message bonus (`reinforced`'s of sessions 8-17)."""

NO_SPARE_WORDS: dict[str, Any] = dict(message_divergence=0.0, held_messages=0.0, message_logit_decay=0.0)
"""What a recipe's bonus for telling nearby goals apart, its held words and its logit decay give way to where the
channel has no word to spare (2^K at most the grid's cells: every word must name a goal) or the message head reads
more than the goal: with no free word the bonus can only push a shared word onto another goal's, and there both cost
play (docs/tuning.md sessions 45 and 49); the decay, which keeps a shared word's bits movable, was measured only
beside the other two (session 56)."""

AUXILIARY = ("goal_coef", "seen_coef", "code_coef")
"""Options whose losses reach a policy head with a target other than the return (SPEC section 7)."""
