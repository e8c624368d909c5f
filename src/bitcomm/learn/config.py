"""`TrainConfig`: everything a training run needs, with named recipes.

A recipe is a named set of learning options (`bitcomm.learn.recipes`): `reinforced` (the default,
messages learned by reinforcement alone), `supervised` (plus auxiliary losses that teach the sender
a protocol) and `paper` (the paper's training as written). Options that use privileged
training-time information, or hand a policy head a target other than the return, say so below.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field
from typing import Any

from bitcomm.config import MAX_EVAL_EPISODES, TaskConfig, check_arrival, check_seed, critic_passes, plain_fields
from bitcomm.errors import ConfigError, bad_value, check_instance, check_int, check_number, check_rate, is_number
from bitcomm.learn.estimators import ESTIMATORS
from bitcomm.learn.precision import UPDATE_DTYPES
from bitcomm.learn.recipes import AUXILIARY, DEFAULT_RECIPE, NO_SPARE_WORDS, RECIPES, WIDE_MESSAGES
from bitcomm.policies.heads import MAX_MARGINAL_BITS, MESSAGE_HEADS, check_marginal_bits
from bitcomm.policies.networks import ModelConfig
from bitcomm.policies.reference import OraclePolicy

MODES = ("sync", "a3c")
BACKENDS = ("local", "ray")
TASK_ALLOWED = "a bitcomm.TaskConfig, e.g. TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))"


ENTROPY_WEIGHTS = (
    "entropy_move",
    "entropy_message",
    "entropy_message_marginal",
    "message_divergence",
    "message_logit_decay",
    "sharpen_messages",
    "sharpen_moves",
    "uniform_move",
)
"""The learning options that weight an entropy-type term of the policy (`bitcomm.learn.objectives`): terms of the
agents' own distributions, so a run with any of them stays pure."""


@dataclass(frozen=True)
class TrainConfig:
    task: TaskConfig = field(default_factory=TaskConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    recipe: str = DEFAULT_RECIPE
    """The named recipe these options came from (for the record; the fields below are what counts)."""
    estimator: str = "improved"
    """`standard` (paper eq. 7) or `improved` (paper eq. 8)."""
    mode: str = "sync"
    """`sync`: batches of vectorized episodes, the same run bit for bit for a seed; `a3c`: the paper's asynchronous
    workers, whose updates race, so two runs differ."""
    backend: str = "local"
    """`local`: train in this process (`mode`); `ray`: rollout actors on a Ray cluster and one learner here
    (bitcomm.learn.ray_backend, docs/distributed.md). How a run is executed, not what it learns: a run resumes
    on either."""
    workers: int = 2
    """Worker processes in `a3c` mode, rollout actors on Ray."""
    staleness: int = 0
    """On Ray: 0 waits for every actor's batch and makes one update on them all (synchronous); S > 0 updates on
    each batch as it arrives and drops one collected with weights more than S updates old (asynchronous)."""
    episodes: int = 100_000
    """Budget: environment episodes to play."""
    train_max_steps: int = 0
    """Truncate training episodes after this many steps (0: the task's `max_steps`; where a recipe's cut is shorter
    than a corner-to-corner path, from 18x18 under reinforced, it is 3 steps per cell of the grid's side: 96 at
    32x32). Evaluation keeps the task's own limit. Early on every episode runs to the limit, so a short one buys more
    updates per second; with a small gamma the returns it cuts short lose little."""
    seed: int = 0
    num_envs: int = 128
    """Episodes per batch (per worker in `a3c` mode)."""
    lr: float = 1e-3
    critic_lr: float = 1e-3
    gamma: float = 0.95
    entropy_move: float = 0.01
    entropy_message: float = 0.001
    entropy_message_marginal: float = 0.0
    """Weight of the entropy of the minibatch's average message distribution, H(mean_s Pm(m | s)): a bonus
    for senders' states that use different messages, where `entropy_message` rewards each message for being
    random. An entropy term on the sender's own distribution (no label, no receiver, no channel), so a run
    with it is pure; it splits codes that two goals share (docs/tuning.md, session 18). Needs K <= 12: above,
    a recipe's bonus gives way to the per-message one (`recipes.WIDE_MESSAGES`)."""
    uniform_move: float = 0.0
    """Weight of KL(uniform || move policy), a pull of (p - 1/5) on each move logit. The entropy
    bonus's pull, -p (log p + H), vanishes with an action's probability, so an action the penalties
    drive to zero early (staying, penalised off the goal) never comes back when it becomes the right
    one (on the goal, while the partner walks); this pull keeps every move sampled now and then."""
    max_grad_norm: float = 1.0
    epochs: int = 1
    """Passes over each batch (PPO-style reuse when > 1)."""
    critic_epochs: int = 0
    """Passes of the critics over each batch, in the first of the `epochs` (0: every epoch). Fewer buy throughput
    where the critics' step cannot run beside the policy's (one thread, an A3C worker): it is about a third of an
    update (docs/tuning.md, session 64)."""
    minibatches: int = 1
    """Minibatches per pass, split by whole episodes."""
    clip: float = 0.0
    """PPO ratio clipping for reused batches; 0 is the plain policy gradient."""
    adv_norm: bool = False
    """Divide the advantages of a batch by their standard deviation."""
    goal_coef: float = 0.0
    """Auxiliary, privileged (training time only; `supervised` recipe): weight of a loss that makes each agent's first
    hidden layer predict its own goal (row and column) from what it observes and hears (with `message_map`: makes
    the received message's decoded map name that goal). Centralised training uses the true goal as the label; acting
    never sees it. Without `message_map` its gradient reaches the sender through the channel (see `channel_noise`),
    so the sender learns to say what lets the receiver name its goal."""
    seen_coef: float = 0.0
    """Auxiliary (`supervised` recipe): weight of a loss that makes each agent's first hidden layer predict the goal it
    observes (its own observation, so not privileged): the message head then has the goal at hand to tell."""
    channel_noise: float = 1.0
    """How the goal-grounding loss reaches the sender: > 0, through a relaxed channel, the receiver reading
    sigmoid(sender logit + channel_noise * N(0, 1)) (DIAL); 0, straight through the sampled bits. Acting and the
    channel itself stay discrete either way. It acts only where that loss reaches the sender (`goal_coef` > 0
    without `message_map`); elsewhere a value other than 1 is refused, as it would change nothing."""
    code_coef: float = 0.0
    """Auxiliary (`supervised` recipe): weight of a loss that trains each sender toward a code word of the goal it
    observes (its own observation, so not privileged), the words matched to goals one to one by the sender's own
    running preference (bitcomm.learn.codebook): a code with no two goals on one message, which a relaxed channel
    does not find (one goal per message where 2^bits >= size * size)."""
    anneal_lr: bool = False
    """Decay every learning rate linearly to zero over the budget (`episodes`), as CleanRL's PPO does
    (on in the `reinforced` recipe): the last updates are then too small to undo a converged policy (the
    late relapses of docs/results.md). The schedule follows `episodes`, so resuming with a larger budget
    raises it again."""
    anneal_entropy: bool = False
    """Decay the entropy bonuses and the uniform-move pull linearly to zero on `anneal_lr`'s schedule: the
    policies end nearer deterministic, so greedy play can follow what sampled play learned."""
    anneal_move_entropy: bool = False
    """Decay the move entropy bonus and the uniform-move pull (not the message regularisers) linearly to zero on
    `anneal_lr`'s schedule (on in the `reinforced` recipe): greedy moves then follow what sampled moves learned,
    while the message bonuses keep the senders' codes apart to the end (`anneal_entropy` decays those too)."""
    sharpen_messages: float = 0.0
    """A per-message entropy penalty that grows with the schedule: the per-message entropy weight goes linearly
    from `entropy_message` at the start to `entropy_message - sharpen_messages` at the schedule's end (off: 0).
    Each sender's most likely message then becomes the message it sends, so the codes greedy play sends are the
    codes sampled play was trained on; an entropy term of the sender's own distribution, so a run stays pure. On the
    paper's task (0.03) it moved greedy play's failures between seeds rather than removing them (docs/tuning.md
    session 27), so it is off by default."""
    sharpen_moves: float = 0.0
    """The same for the movement head: the move entropy weight goes linearly from `entropy_move` (times its decay)
    at the start to that less `sharpen_moves` at the schedule's end (off: 0), so that each agent's most likely
    move becomes the move it plays and sampled play trains the moves greedy play will make; pure like
    `sharpen_messages`. With both on the paper's task (16 runs, three pairs of weights) greedy play ended within
    1.05x of the oracle on 3 runs, no more often than without (docs/tuning.md session 28), so it is off."""
    move_decay_below: float = 0.0
    """Start the move regularisers' decay (`anneal_move_entropy`, `anneal_entropy`) only once the rolling training
    episode length is at most this multiple of the oracle's (over episodes cut at `train_max_steps`, as the rolling
    length's are: `bitcomm.learn.level_watch`), then decay them linearly to zero by the schedule's end
    (0: from the first episode). Where the protocol forms late in the budget (32x32), a decay from the start slows
    it; at 10x10 the decay from the start is the better one (docs/tuning.md session 23). Sync mode only, where one
    learner sees the rolling length."""
    greedy_senders: float = 0.0
    """Fraction of each batch's episodes in which every sender sends its most likely message (moves still sampled), from
    `greedy_senders_from` of the schedule on, once the protocol has formed (`senders_wait_below`) (off: 0). Those
    episodes' message advantages are zero, so the message head learns from sampled messages alone, while the receivers
    also learn to act on the words greedy play sends; every gradient still comes from the estimator's term, so a run
    stays pure. The episodes are the first columns of the batch (in `a3c` mode and on Ray, of each worker's batch, by
    the episodes played before it). With `message_reads` `observed` (one word distribution per goal) 0.5 from halfway
    brought greedy play within 1.05x of the oracle on 11 of 16 seeds of the paper's task and within 1.10x on all (the
    head that reads everything, without it: about one in four, worst 1.3-1.8x); with that head it changes little
    (docs/tuning.md session 34). On (0.5) in the `reinforced` recipe since session 35."""
    greedy_senders_from: float = 0.5
    """The schedule's progress (0 to 1) from which `greedy_senders` plays its episodes."""
    held_messages: float = 0.0
    """Fraction of each batch's episodes in which each sender draws its message once, at the episode's first step,
    and sends that word at every step (moves sampled), from `held_messages_from` of the schedule on (off: 0). Unlike
    `greedy_senders`' words these are samples of the message policy, and the estimator credits them as usual (each
    step's log-probability is the held word's), so a run stays pure. Why: a bit its sender leaves near p = 0.5 costs
    sampled play little, since the receiver hears both values within an episode, and stalls greedy play where the
    word it rounds to is another goal's (docs/tuning.md session 43); an episode that hears one word throughout pays
    for that word. Needs `message_reads` `observed`, whose word distribution an episode keeps. The episodes are the
    batch's columns after the greedy senders' ones (as many as are left where the two fractions fill a batch). With
    `message_divergence` 1, 0.25 brought greedy play within 1.05x of the oracle on 26 of 28 seeds of the paper's task
    (on 24 of them the divergence alone: 19); alone, on four of the default's misses, 2 of 4 (docs/tuning.md session
    44). On (0.25) in the `reinforced` recipe since session 49 where the channel has words to spare (`spare_words`);
    off where every word names a goal, as at 16x16 with 8 bits, where held words from halfway cost sampled play 2.7-2.9
    steps (session 45, before they waited for the protocol)."""
    held_messages_from: float = 0.5
    """The schedule's progress (0 to 1) from which `held_messages` plays its episodes."""
    senders_wait_below: float = 0.0
    """Start the greedy senders and held words (`greedy_senders`, `held_messages`) only once the rolling training
    episode length has been at most this multiple of the oracle's (over episodes cut as training's are), and not
    before their own `_from` (0: at their
    `_from`, whatever the play). Their episodes teach the receivers the words greedy play sends; where those words
    have not formed by halfway (16x16, 32x32) they teach words the senders are about to change, and the sampled play of
    every default run was set back there (docs/tuning.md sessions 38 and 46). On (1.15) in the `reinforced` recipe
    since session 46; where the oracle cannot play the task the recipe leaves it at 0."""
    message_divergence: float = 0.0
    """Weight of a bonus for words that tell nearby goals apart: the mean, over every pair of goal cells at most
    `message_divergence_radius` apart, of the Jensen-Shannon divergence between the sender's message distributions
    for the two goals (log 2 once they put their mass on different words), for a message head that reads only the
    goal it observes (`message_reads` `observed`), evaluated on every goal cell (off: 0). Two nearby goals on one
    most likely word cost sampled play a step or two, which the policy gradient barely sees, and stall greedy play
    (docs/tuning.md sessions 37 and 43); the marginal bonus counts a shared word the same wherever the goals lie. An
    information term of the senders' own distributions, no target word, so a run stays pure. At 1 (radius 3) on the
    paper's task greedy play ended within 1.05x of the oracle on 19 of 24 seeds (the default: 10 of 16), with misses
    of 1.31-1.51x on hedged bits, at about 0.82x the throughput (docs/tuning.md session 43). With `held_messages`
    0.25, 22 of the same 24 (session 44), 26 of 28 in all, and the 10x10 study's four techniques learn quicker. On
    (1) in the `reinforced` recipe since session 49 where the channel has words to spare (`spare_words`): where every
    word names a goal (4x4 with 4 bits, 16x16 with 8) it cost greedy play and sampled play (session 45), as a word two
    goals share can only move onto a third's; after the words have formed it splits none (sessions 47 and 49)."""
    message_divergence_radius: int = 3
    """How far apart (Manhattan, in cells) two goals may be for `message_divergence` to count their pair; where a grid
    has more than 1,024 such pairs, a uniform draw of 1,024 of them enters each step."""
    message_logit_decay: float = 0.0
    """Weight of a pull of the message logits toward 0: the mean square of every goal cell's message logits, for a
    message head that reads only the goal it observes (`message_reads` `observed`; off: 0). Why: once two nearby goals
    put nearly all their mass on one word, every term of the probabilities (the policy gradient, the entropies, the
    divergence) has a vanishing gradient through the saturated bits, and greedy play stalls between the two goals for
    good (docs/tuning.md sessions 49 and 55); this pull does not fade as a bit saturates, so the logits stay where the
    policy gradient still moves them. A term of the senders' own logits with no target word, so a run stays pure. On
    (0.001) in the `reinforced` recipe since session 56 where the divergence and held words are (`spare_words`): on the
    paper's task it took greedy play within 1.05x of the oracle on 28 of 28 seeds, against 24 of 28 without it on
    the same machine (docs/tuning.md session 56). Over a budget of about 60,000 episodes a third of it (0.0003) ends
    greedy play shorter (9.00 against 12.32 steps on 5 seeds), but at 200,000 it met that target on 27 of 28 seeds
    (sessions 57-58)."""
    anneal_episodes: int = 0
    """Episodes over which the schedules (`anneal_lr`, `anneal_entropy`, `anneal_move_entropy`) decay (0: the
    budget, `episodes`): a run trained in pieces (each resumed with a larger budget, as benchmarks/solve.py does)
    keeps one schedule."""
    update_dtype: str = "float32"
    """Precision of the update's network passes, `float32` or `bfloat16` (bitcomm.learn.precision): bfloat16
    matrix products under `torch.autocast`, about half the cost on CPUs with native bfloat16 (AVX512-BF16,
    AMX) and more on others; acting, log-probabilities, weights and optimizer stay float32."""
    map_lr: float = 0.01
    """Adam learning rate of the message-map decoder (ModelConfig.message_map), which starts at zero
    (a uniform map); a decoder is a small linear read-out that the policy's rate would fit slowly."""
    checkpoint_seconds: float = 60.0
    """Write a checkpoint at most this often (and at the end)."""
    keep_checkpoints: int = 3
    """Checkpoints kept on disk: the last this many, and the best (lowest rolling mean episode length, or with
    `held_out_every` the best held-out evaluation), which `checkpoints/best.json` names."""
    held_out_every: int = 0
    """Every this many training episodes and at the end (0: never), play `held_out_episodes` held-out episodes with
    the current policy and checkpoint it ranked by their mean length, so that retention keeps, and
    `checkpoints/best.json` names, the checkpoint that played them best (Stable-Baselines3's EvalCallback keeps
    its `best_model` so). Held out: the episode set of `bitcomm.learn.held_out.held_out_seed(seed)`, which no
    training batch plays; the figure is logged as `eval/episode_length` and its seconds count in `wall_s`.
    Model selection, not learning: no gradient sees it, so a run stays pure. Sync mode on the local backend."""
    held_out_episodes: int = 1000
    """Held-out episodes each `held_out_every` evaluation plays."""
    held_out_greedy: bool = True
    """Whether `held_out_every`'s evaluation plays the most likely move and message (greedy play, which a deployed
    robot may use) or samples them (how the policy was trained)."""

    def __post_init__(self) -> None:
        plain_fields(self)
        check_instance("task", self.task, TaskConfig, TASK_ALLOWED)
        if self.estimator not in ESTIMATORS:
            raise bad_value("estimator", self.estimator, f"choose one of {', '.join(ESTIMATORS)}")
        if self.model.messages not in MESSAGE_HEADS:
            raise bad_value("messages", self.model.messages, f"choose one of {', '.join(MESSAGE_HEADS)}")
        if self.mode not in MODES:
            raise bad_value("mode", self.mode, f"choose one of {', '.join(MODES)}")
        if self.update_dtype not in UPDATE_DTYPES:
            raise bad_value("update_dtype", self.update_dtype, f"choose one of {', '.join(UPDATE_DTYPES)}")
        if self.backend not in BACKENDS:
            raise bad_value("backend", self.backend, f"choose one of {', '.join(BACKENDS)}")
        if self.backend == "ray" and self.mode != "sync":
            raise bad_value("mode", self.mode, "on --backend ray leave it at sync (--staleness picks sync or async)")
        if self.recipe not in RECIPES:
            raise bad_value("recipe", self.recipe, f"choose one of {', '.join(RECIPES)}")
        check_seed(self.seed)
        check_int("train_max_steps", self.train_max_steps, 0)  # 0: the task's max_steps
        check_int("staleness", self.staleness, 0)
        check_int("anneal_episodes", self.anneal_episodes, 0)
        if self.anneal_episodes and not self.anneals:
            raise bad_value(
                "anneal-episodes",
                self.anneal_episodes,
                "acts only with --anneal-lr, --anneal-entropy or --anneal-move-entropy; leave it at 0",
            )
        check_number("move_decay_below", self.move_decay_below, 0.0)
        if self.move_decay_below:
            self._check_move_decay_below()
        check_number("senders_wait_below", self.senders_wait_below, 0.0)
        if self.senders_wait_below:
            self._check_oracle("senders-wait-below", self.senders_wait_below)
        if self.staleness and self.backend != "ray":
            raise bad_value("staleness", self.staleness, "acts only on --backend ray; leave it at 0")
        check_int("held_out_every", self.held_out_every, 0)
        if isinstance(self.held_out_episodes, int) and self.held_out_episodes > MAX_EVAL_EPISODES:
            raise bad_value("held-out-episodes", self.held_out_episodes, f"must be at most {MAX_EVAL_EPISODES:,}")
        if self.held_out_every and (self.mode != "sync" or self.backend != "local"):
            raise bad_value(
                "held-out-every", self.held_out_every, "acts only in sync mode on the local backend; leave it at 0"
            )
        self._check_greedy_senders()
        for name in (
            "workers",
            "episodes",
            "num_envs",
            "epochs",
            "minibatches",
            "keep_checkpoints",
            "held_out_episodes",
        ):
            check_int(name, getattr(self, name), 1)
        if self.minibatches > self.num_envs:
            raise bad_value("minibatches", self.minibatches, f"at most num_envs ({self.num_envs})")
        critic_passes(self.critic_epochs, self.epochs)
        for name in ("lr", "critic_lr", "map_lr"):
            check_rate(name, getattr(self, name))
        self._check_idle_options()
        check_number("max_grad_norm", self.max_grad_norm, 0.0, strict=True)
        if not (is_number(self.gamma) and 0.0 < self.gamma <= 1.0):
            raise bad_value("gamma", self.gamma, "must be in (0, 1]")
        for name in (
            *ENTROPY_WEIGHTS,
            "clip",
            "goal_coef",
            "seen_coef",
            "code_coef",
            "channel_noise",
            "checkpoint_seconds",
        ):
            check_number(name, getattr(self, name), 0.0)
        check_marginal_bits(self.entropy_message_marginal, self.task.channel.bits)
        self._check_message_divergence()
        self._check_observed_head("message_logit_decay", "a word distribution per goal")
        if self.train_max_steps > 0:  # 0: the task's max_steps, checked by TaskConfig
            check_arrival(self.task.channel.delay, self.train_max_steps, "train_max_steps")
        if 0 < self.train_max_steps <= self.task.env.act_delay:  # else training_task's EnvConfig blames max_steps
            raise bad_value("act_delay", self.task.env.act_delay, f"must be < train_max_steps ({self.train_max_steps})")
        relaxed = self.goal_coef > 0 and not self.model.message_map
        if self.channel_noise != 1.0 and not relaxed:
            raise bad_value(
                "channel-noise",
                self.channel_noise,
                "acts only where the goal loss reaches the sender (goal-coef > 0 with --no-message-map); leave it at 1",
            )

    def _check_idle_options(self) -> None:
        """One line for an option given another value than its default where nothing reads it: the held-out
        evaluation's size and play without `held_out_every`, the map decoder's rate without `message_map`."""
        idle = {
            "held_out_episodes": ("--held-out-every > 0", not self.held_out_every),
            "held_out_greedy": ("--held-out-every > 0", not self.held_out_every),
            "map_lr": ("--message-map", not self.model.message_map),
        }
        for name, (needs, unread) in idle.items():
            value, default = getattr(self, name), TrainConfig.__dataclass_fields__[name].default
            if unread and value != default:
                leave = ("on" if default else "off") if isinstance(default, bool) else f"at {default:g}"
                raise bad_value(name.replace("_", "-"), value, f"acts only with {needs}; leave it {leave}")

    def _check_greedy_senders(self) -> None:
        """`greedy_senders` and `held_messages`, the two ways of sending a batch's episodes other than sampling."""
        for name in ("greedy_senders", "greedy_senders_from", "held_messages", "held_messages_from"):
            value = getattr(self, name)
            if not (is_number(value) and 0.0 <= value <= 1.0):
                raise bad_value(name.replace("_", "-"), value, "must be in [0, 1]")
        for name in ("greedy_senders", "held_messages"):
            start = getattr(self, f"{name}_from")
            if start != 0.5 and not getattr(self, name):
                flag = name.replace("_", "-")
                raise bad_value(f"{flag}-from", start, f"acts only with --{flag} > 0; leave it at 0.5")
        self._check_observed_head("held_messages", "a word distribution an episode keeps")

    def _check_observed_head(self, name: str, why: str) -> None:
        """One line for option `name` set with a message head that reads more than the goal its sender observes."""
        value = getattr(self, name)
        if value and self.model.message_reads != "observed":
            flag = name.replace("_", "-")
            raise bad_value(flag, value, f"acts only with --message-reads observed ({why}); leave it at 0")

    def _check_message_divergence(self) -> None:
        check_int("message_divergence_radius", self.message_divergence_radius, 1)
        if not self.message_divergence:
            if self.message_divergence_radius != 3:
                raise bad_value(
                    "message-divergence-radius",
                    self.message_divergence_radius,
                    "acts only with --message-divergence > 0; leave it at 3",
                )
            return
        check_marginal_bits(self.message_divergence, self.task.channel.bits, "message-divergence")
        self._check_observed_head("message_divergence", "a word distribution per goal")

    def greedy_sender_episodes(self, episodes: int, formed: float | None = 0.0) -> int:
        """How many of the next batch's episodes (its first columns) `greedy_senders` plays, `episodes` played and
        the protocol formed at progress `formed` (`senders_wait_below`; None: not yet).

        The count keeps the run's running total at `greedy_senders` of its episodes rather than rounding each batch,
        so a fraction a batch cannot hold still plays: one-episode batches at 0.5 alternate 0, 1, 0, 1."""
        return self._scheduled_episodes(self.greedy_senders, self.greedy_senders_from, episodes, formed)

    def held_message_episodes(self, episodes: int, formed: float | None = 0.0) -> int:
        """How many of the next batch's episodes `held_messages` plays (after the greedy senders'), as above."""
        return self._scheduled_episodes(self.held_messages, self.held_messages_from, episodes, formed)

    def _scheduled_episodes(self, fraction: float, start: float, episodes: int, formed: float | None) -> int:
        if not fraction or formed is None or self.schedule_progress(episodes) < max(start, formed):
            return 0
        return math.floor(fraction * (episodes + self.num_envs)) - math.floor(fraction * episodes)

    def _check_move_decay_below(self) -> None:
        """`move_decay_below` set: it needs a move decay to start, the sync trainer's rolling length, and the oracle."""
        value = self.move_decay_below
        if not (self.anneal_move_entropy or self.anneal_entropy):
            raise bad_value(
                "move-decay-below", value, "acts only with --anneal-move-entropy or --anneal-entropy; leave it at 0"
            )
        if self.mode != "sync":
            raise bad_value("move-decay-below", value, "acts only in sync mode; leave it at 0")
        self._check_oracle("move-decay-below", value)

    def _check_oracle(self, flag: str, value: float) -> None:
        """A threshold that is a multiple of the oracle's episode length needs an oracle that can play the task."""
        refusal = oracle_refusal(self.task)
        if refusal is not None:
            raise bad_value(flag, value, f"needs the oracle, which cannot play this task ({refusal})")

    @property
    def training_task(self) -> TaskConfig:
        """The task episodes are collected on: the task, truncated at `train_max_steps` if set."""
        limit = self.train_max_steps
        if limit == 0 or limit >= self.task.env.max_steps:
            return self.task
        return dataclasses.replace(self.task, env=dataclasses.replace(self.task.env, max_steps=limit))

    @property
    def anneals(self) -> bool:
        """Whether anything follows the schedule (`anneal_lr`, `anneal_entropy`, `anneal_move_entropy`), so that
        its horizon matters."""
        return self.anneal_lr or self.anneal_entropy or self.anneal_move_entropy

    def schedule_progress(self, episodes: int) -> float:
        """The fraction of the schedules (`anneal_lr`, `anneal_*entropy`) done after `episodes` episodes, at most 1."""
        return min(1.0, episodes / (self.anneal_episodes or self.episodes))

    @property
    def pure(self) -> bool:
        """Messages and moves learned by reinforcement alone: no auxiliary loss reaches a policy head
        (SPEC section 7)."""
        return all(getattr(self, name) == 0 for name in AUXILIARY)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        d = dict(d)
        task = d.pop("task")
        model = dict(d.pop("model"))
        model["conv_channels"] = tuple(model["conv_channels"])
        return cls(
            task=TaskConfig.from_dict(task),
            model=ModelConfig(**model),
            **d,
        )


MODEL_OPTIONS = {f.name for f in dataclasses.fields(ModelConfig)}


def oracle_refusal(task: TaskConfig) -> ConfigError | None:
    """Why the oracle cannot play `task` (too few bits to name a cell, an agent that never hears its goal), or None
    where it can."""
    try:
        OraclePolicy(task)
    except ConfigError as e:
        return e
    return None


LONG_GRID_STEPS_PER_SIDE = 3
"""Where a recipe's training cut is shorter than the corner-to-corner path, 2 (size - 1) moves (so that it ends
episodes the oracle itself could not finish: from 18x18 with the default's 32 steps), the cut becomes this many steps
per cell of the grid's side, 96 at 32x32, what the 32x32 study trained with. Sampled play on seeds 0 / 1 (1,000
evaluation episodes, `benchmarks/training_cut.py`): 32x32 (K = 10, 200,000 episodes) 47.1 / 40.1 at 96 steps against
153.6 / 145.6 at 32 (60.3 at 64 on seed 0); 24x24 24.6 / 26.8 at 72 against 37.7 / 41.2; 18x18 17.8 / 18.5 at 54
against 19.2 / 20.8. At 16x16 the default's 32 stays (48 was 2-3% longer sampled on seeds 0 and 1, and slower):
docs/tuning.md sessions 53 and 54."""


def spare_words(task: TaskConfig) -> bool:
    """Whether the channel has more words than the grid has goal cells (2^K > size^2, K at most
    MAX_MARGINAL_BITS, where the bonus for telling nearby goals apart can be evaluated): where it has none, every
    word must name a goal, and that bonus can only move a word two goals share onto a third's."""
    bits = task.channel.bits
    return bits <= MAX_MARGINAL_BITS and 2**bits > task.env.size**2


def recipe_values(recipe: str, task: TaskConfig, message_reads: str | None = None) -> dict[str, Any]:
    """A recipe's learning options on `task` (with `message_reads` where one is given over the recipe's): where
    an option of the recipe cannot serve the task, what stands in for it. An option given explicitly is not
    changed here, and is still refused where it cannot serve."""
    if recipe not in RECIPES:
        raise bad_value("recipe", recipe, f"choose one of {', '.join(RECIPES)}")
    values = dict(RECIPES[recipe])
    if values.get("entropy_message_marginal", 0.0) > 0 and task.channel.bits > MAX_MARGINAL_BITS:
        values.update(WIDE_MESSAGES)
    if values.get("senders_wait_below", 0.0) > 0 and oracle_refusal(task) is not None:
        values["senders_wait_below"] = 0.0  # no level to wait for
    if not spare_words(task) or (message_reads or values.get("message_reads")) != "observed":
        values.update(NO_SPARE_WORDS)
    if 0 < values.get("train_max_steps", 0) < 2 * (task.env.size - 1):
        values["train_max_steps"] = LONG_GRID_STEPS_PER_SIDE * task.env.size
    return values


TRAIN_OPTIONS = {f.name for f in dataclasses.fields(TrainConfig)} - {"task", "model", "recipe"}
"""The learning options `make_train_config` takes by name besides `MODEL_OPTIONS` (the task and the recipe are its
own arguments; the model is built from its options)."""


def check_option_names(overrides: dict[str, Any]) -> None:
    """One line for a name that is not a learning option (a typo), naming the closest ones, rather than a TypeError
    from the dataclass that names no option it takes."""
    known = TRAIN_OPTIONS | MODEL_OPTIONS
    for name in overrides:
        if name not in known:
            close = [] if name == "model" else difflib.get_close_matches(name, sorted(known), n=3)
            hint = f"; did you mean {' or '.join(close)}?" if close else ""
            raise bad_value(
                "option",
                name,
                f"not a learning option: a field of TrainConfig, or of ModelConfig given by name (hidden=64){hint}",
            )


def make_train_config(recipe: str = DEFAULT_RECIPE, task: TaskConfig | None = None, **overrides: Any) -> TrainConfig:
    """A TrainConfig from a recipe plus explicit options (None means "the recipe's value")."""
    task = TaskConfig() if task is None else task
    check_instance("task", task, TaskConfig, TASK_ALLOWED)
    check_option_names(overrides)
    values = recipe_values(recipe, task, overrides.get("message_reads"))
    values.update({k: v for k, v in overrides.items() if v is not None})
    if overrides.get("minibatches") is None and isinstance(values["num_envs"], int):  # a batch splits into as many
        values["minibatches"] = min(
            values["minibatches"], values["num_envs"]
        )  # minibatches at most: the recipe's follow
    if values.get("coords") and values.get("encoder", ModelConfig.encoder) != "conv":
        if overrides.get("coords") is not None:  # typed: it would do nothing (a recipe's value just stands down)
            raise bad_value(
                "coords", True, "acts only with --encoder conv (the other encoders already read each plane's row and "
                "column); leave it off",
            )  # fmt: skip
        values["coords"] = False
    model = ModelConfig(**{k: values.pop(k) for k in list(values) if k in MODEL_OPTIONS})
    return TrainConfig(task=task, model=model, recipe=recipe, **values)
