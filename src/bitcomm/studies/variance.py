"""Variance of the two policy-gradient estimators at fixed policies (paper III-C, SPEC section 4).

At each stage of a run (one of its checkpoints) the policy is frozen. Two critics are fitted to the
Monte Carlo returns of fresh batches played by that policy, as the trainer fits its own (MSE to Q_t):
V1 with the received message for `standard` (eq. 7) and V2, masked, for `improved` (eq. 8). Then
they are frozen too, and many independent batches are drawn. Each batch gives one gradient estimate
per estimator, -grad `policy_gradient_loss`, split into its message part (through log Pm only) and
its action part (through log pi only), over all policy parameters. Per part and estimator:

    variance = trace Cov_batches(g)        ratio  = variance improved / variance standard
    cosine   = cos(mean g standard, mean g improved)

Both estimators are unbiased for the same gradient, so the cosine tends to 1 as batches grow; the
paper proves the improved message part has the lower variance. Both read the same batches (paired
samples), so a difference between them is not sampling luck. The estimates are eq. 7 and 8 as
written: no advantage normalisation, no clipping, one gradient per batch.

The critics, their loss, the baselines, the advantages and the log-probabilities are the trainer's
own (`Learner.critic_loss`, `Learner.baselines`, the estimator registry, `Learner.log_probs`), so what
is measured is what training uses.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bitcomm.checkpoint import checkpoints, load_grid_weights
from bitcomm.config import TaskConfig
from bitcomm.errors import ConfigError, bad_value
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.estimators import ESTIMATORS, Advantages, discounted_returns, policy_gradient_loss
from bitcomm.learn.learner import Learner
from bitcomm.learn.rollout import Collector, Rollout
from bitcomm.plotting import save_figure
from bitcomm.policies.networks import PolicyNet
from bitcomm.studies.tables import write_rows_csv

PARTS = ("message", "action", "total")
"""Gradient parts: through log Pm only, through log pi only, and their sum (the whole estimate)."""
CSV_FIELDS = (
    "episodes", "part", "var_standard", "var_improved", "ratio", "cosine", "norm_standard", "norm_improved",
    "critic_mse_standard", "critic_mse_improved", "fit_batches", "batches", "num_envs", "checkpoint",
)  # fmt: skip


@dataclass(frozen=True)
class VarianceConfig:
    """How hard to look at each stage; defaults give a clear answer on the paper's task in minutes."""

    batches: int = 64
    """Independent batches whose gradient estimates are compared."""
    num_envs: int = 32
    """Episodes per batch (one gradient estimate)."""
    fit_batches: int = 100
    """At most this many fresh batches to fit the critics on before measuring."""
    fit_steps: int = 4
    """Critic gradient steps (Adam, the run's critic learning rate) on each fit batch."""
    plateau: float = 0.01
    """Stop fitting early once the critics' held-out loss, averaged over the last `PLATEAU_WINDOW`
    batches, improved by less than this fraction on the window before (0: always fit `fit_batches`)."""
    seed: int = 0
    """Seeds the critics' initial weights, the episodes and the sampling; the same at every stage."""

    def __post_init__(self) -> None:
        for name in ("batches", "num_envs", "fit_batches", "fit_steps"):
            value = getattr(self, name)
            low = 2 if name == "batches" else 0 if name == "fit_batches" else 1
            if not isinstance(value, int) or value < low:
                raise bad_value(name.replace("_", "-"), value, f"must be an integer >= {low}")
        if not 0 <= self.plateau <= 1:  # 1: stop at the first window, however the loss falls (as --plateau takes)
            raise bad_value("plateau", self.plateau, "must be in [0, 1]")


PLATEAU_WINDOW = 5


@dataclass(frozen=True)
class Stage:
    """A frozen policy to measure: the weights of one checkpoint and the run's training config."""

    checkpoint: str
    episodes: int
    weights: dict[str, torch.Tensor]
    config: TrainConfig

    def on_task(self, task: TaskConfig) -> Stage:
        """The same policy measured on another task of the same input shapes (e.g. another delay)."""
        return dataclasses.replace(self, config=dataclasses.replace(self.config, task=task))


@dataclass(frozen=True)
class VarianceRow:
    """One stage x gradient part: the figures of the table."""

    episodes: int
    part: str
    var_standard: float
    var_improved: float
    ratio: float
    cosine: float
    norm_standard: float
    """Norm of the mean gradient estimate (the signal the variance is noise around)."""
    norm_improved: float
    critic_mse_standard: float
    """The frozen critics' MSE to Q_t on the measurement batches (held out from their fit)."""
    critic_mse_improved: float
    fit_batches: int
    batches: int
    num_envs: int
    checkpoint: str

    def to_dict(self) -> dict[str, Any]:
        """Fields by name; a ratio that does not exist (no variance at all) is None, so JSON stays valid."""
        return {
            k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in dataclasses.asdict(self).items()
        }


# ---------------------------------------------------------------------------------------------- stages
def parse_stages(text: str) -> str | int | tuple[int, ...]:
    """`all`, `latest`, `spread:N` (N checkpoints evenly spread from first to last) or `E1,E2,...` (episodes)."""
    text = text.strip()
    if text in ("all", "latest"):
        return text
    if text.startswith("spread:"):
        count = text.removeprefix("spread:")
        if count.isdecimal() and int(count) >= 1:  # not isdigit: "²" is a digit that int() refuses
            return int(count)
    else:
        values = [v.strip() for v in text.split(",") if v.strip()]
        if values and all(v.isdecimal() for v in values):
            episodes = tuple(int(v) for v in values)
            if len(set(episodes)) != len(episodes):  # the same stage measured twice, its rows printed twice
                raise bad_value("stages", text, "an episode count repeats; give each once")
            return episodes
    raise bad_value("stages", text, "expected all, latest, spread:N or a list of episode counts E1,E2,...")


def select_stages(path: str | Path, stages: str | int | tuple[int, ...]) -> list[Path]:
    """Checkpoint files of `path` (a run folder: its kept checkpoints; a file: itself) picked by `stages`."""
    p = Path(path)
    if p.is_file():
        return [p]
    kept = checkpoints(p)
    if not kept:
        raise bad_value("RUN", str(path), "the run has no complete checkpoint")
    if stages == "all":
        return [file for _, file in kept]
    if stages == "latest":
        return [kept[-1][1]]
    if isinstance(stages, int):
        picks = np.unique(np.round(np.linspace(0, len(kept) - 1, min(stages, len(kept)))).astype(int))
        return [kept[i][1] for i in picks]
    assert isinstance(stages, tuple)
    by_episodes = dict(kept)
    missing = [e for e in stages if e not in by_episodes]
    if missing:
        have = ", ".join(str(e) for e, _ in kept)
        raise bad_value("stages", ",".join(map(str, missing)), f"{path} has checkpoints at episodes {have}")
    return [by_episodes[e] for e in stages]


def load_stage(file: str | Path) -> Stage:
    """A checkpoint as a stage: its policy weights and the config it was trained with."""
    weights, info = load_grid_weights(file)
    try:
        cfg = TrainConfig.from_dict(info["config"])
    except (KeyError, TypeError) as err:
        raise ConfigError(f"invalid checkpoint={str(file)!r}: unreadable training config ({err})") from None
    return Stage(info["path"], info["episodes"], weights["policy"], cfg)


# ---------------------------------------------------------------------------------------------- pieces
def make_critics(cfg: TrainConfig, seed: int) -> dict[str, Learner]:
    """One fresh learner per estimator (V1 for standard, V2 for improved), seeded alike for both."""
    learners = {}
    for name in ESTIMATORS:
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            learners[name] = Learner(dataclasses.replace(cfg, estimator=name))
    return learners


def returns_of(ro: Rollout, cfg: TrainConfig) -> torch.Tensor:
    return discounted_returns(ro.rewards, ro.done, ro.valid, cfg.gamma)


def fit_critics(
    learners: dict[str, Learner],
    policy: PolicyNet,
    collector: Collector,
    vcfg: VarianceConfig,
    generator: torch.Generator,
) -> int:
    """Fit every learner's critic on fresh batches of the frozen `policy`; returns the batches used.

    Each batch is scored before the critics train on it (a held-out loss); fitting stops at
    `fit_batches` or when that loss has stopped falling for every critic (`VarianceConfig.plateau`).
    """
    held_out: dict[str, list[float]] = {name: [] for name in learners}
    w = PLATEAU_WINDOW
    for k in range(vcfg.fit_batches):
        ro = collector.collect(policy, np.random.SeedSequence(vcfg.seed, spawn_key=(0, k)), generator)
        it, ib = ro.valid.nonzero(as_tuple=True)
        for name, learner in learners.items():
            returns = returns_of(ro, learner.cfg)
            for step in range(vcfg.fit_steps):
                loss = learner.critic_loss(ro, it, ib, returns)
                if step == 0:
                    held_out[name].append(loss.item())
                learner.opt_critic.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(learner.critic.parameters(), learner.cfg.max_grad_norm)
                learner.opt_critic.step()
        if vcfg.plateau > 0 and k + 1 >= 2 * w:
            if all(np.mean(h[-w:]) > (1 - vcfg.plateau) * np.mean(h[-2 * w : -w]) for h in held_out.values()):
                return k + 1
    return vcfg.fit_batches


def gradient_parts(
    policy: PolicyNet, logp_move: torch.Tensor, logp_message: torch.Tensor, adv: Advantages, valid: torch.Tensor
) -> dict[str, torch.Tensor]:
    """The estimate -grad `policy_gradient_loss`, flattened over all policy parameters, by part.

    The message part weights only log Pm (action advantages zeroed), the action part only log pi.
    """
    params = list(policy.parameters())
    zero = torch.zeros_like(adv.action)

    def flat_grad(part: Advantages) -> torch.Tensor:
        loss = policy_gradient_loss(logp_move, logp_message, part, valid)
        grads = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
        return -torch.cat(
            [(torch.zeros_like(p) if g is None else g).flatten() for p, g in zip(params, grads, strict=True)]
        )

    message = flat_grad(Advantages(zero, adv.message, adv.returns))
    action = flat_grad(Advantages(adv.action, zero, adv.returns))
    return {"message": message, "action": action, "total": message + action}


class Moments:
    """Running sum and sum of squared norms of vectors (float64): trace of the covariance and the mean."""

    def __init__(self) -> None:
        self.count, self.sum_sq = 0, 0.0
        self.sum: torch.Tensor | None = None

    def add(self, g: torch.Tensor) -> None:
        g = g.double()
        self.count += 1
        self.sum_sq += float(g @ g)
        self.sum = g.clone() if self.sum is None else self.sum + g

    @property
    def mean(self) -> torch.Tensor:
        assert self.sum is not None, "no samples"
        return self.sum / self.count

    @property
    def trace_cov(self) -> float:
        """sum_i Var(g_i), unbiased: (sum ||g||^2 - count ||mean||^2) / (count - 1)."""
        m = self.mean
        return max(0.0, (self.sum_sq - self.count * float(m @ m)) / (self.count - 1))


def cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    denom = float(a.norm() * b.norm())
    return float(a @ b) / denom if denom > 0 else 0.0


# ---------------------------------------------------------------------------------------------- measure
def measure_stage(stage: Stage, vcfg: VarianceConfig) -> list[VarianceRow]:
    """Fit both critics at the stage's frozen policy, then compare the estimators on `batches` batches."""
    cfg = stage.config
    learners = make_critics(cfg, vcfg.seed)
    player = learners["standard"]  # holds the stage's policy: it plays, and its log-probabilities are differentiated
    player.policy.load_state_dict(stage.weights)
    policy = player.policy
    collector = Collector(cfg.task, vcfg.num_envs)
    generator = torch.Generator().manual_seed(vcfg.seed)
    fitted = fit_critics(learners, policy, collector, vcfg, generator)

    moments = {(name, part): Moments() for name in learners for part in PARTS}
    critic_mse: dict[str, list[float]] = {name: [] for name in learners}
    for k in range(vcfg.batches):
        # rollout: fresh episodes, the policy and the critics frozen
        ro = collector.collect(policy, np.random.SeedSequence(vcfg.seed, spawn_key=(1, k)), generator)
        it, ib = ro.valid.nonzero(as_tuple=True)
        logp_move, logp_message = player.log_probs(ro)
        for name, learner in learners.items():
            adv = learner.estimated(ro, it, ib)  # baselines and advantages, exactly as the trainer computes them
            with torch.no_grad():
                critic_mse[name].append(learner.critic_loss(ro, it, ib, adv.returns).item())
            for part, g in gradient_parts(policy, logp_move, logp_message, adv, ro.valid).items():
                moments[name, part].add(g)

    rows = []
    for part in PARTS:
        s, i = moments["standard", part], moments["improved", part]
        var_s, var_i = s.trace_cov, i.trace_cov
        rows.append(
            VarianceRow(
                episodes=stage.episodes,
                part=part,
                var_standard=var_s,
                var_improved=var_i,
                ratio=var_i / var_s if var_s > 0 else math.nan,
                cosine=cosine(s.mean, i.mean),
                norm_standard=float(s.mean.norm()),
                norm_improved=float(i.mean.norm()),
                critic_mse_standard=float(np.mean(critic_mse["standard"])),
                critic_mse_improved=float(np.mean(critic_mse["improved"])),
                fit_batches=fitted,
                batches=vcfg.batches,
                num_envs=vcfg.num_envs,
                checkpoint=stage.checkpoint,
            )
        )
    return rows


# ---------------------------------------------------------------------------------------------- report
def write_csv(rows: list[VarianceRow], path: str | Path) -> Path:
    return write_rows_csv((r.to_dict() for r in rows), CSV_FIELDS, path)


def run_of(row: VarianceRow) -> str:
    """The run a row was measured on: the folder holding its checkpoint's `checkpoints/`, else the file."""
    file = Path(row.checkpoint)
    return str(file.parent.parent) if file.parent.name == "checkpoints" else str(file)


def markdown_table(rows: list[VarianceRow], title: str = "") -> str:
    """The table across stages: one line per stage and part, and a run column when rows come from several
    runs (their episode counts alone would not tell them apart)."""
    several = len({run_of(r) for r in rows}) > 1
    lines = [f"# {title}", ""] if title else []
    lines += [
        "Variance = trace of the covariance of one batch's gradient estimate across batches; ratio = improved /"
        " standard (below 1: the improved estimator is less noisy); cosine between the two estimators' mean"
        " gradients (both are unbiased: near 1 when the batches are many).",
        "",
        ("| run " if several else "") + "| episodes trained | part | var standard | var improved | ratio | cosine |",
        ("| --- " if several else "") + "| ---: | --- | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        figures = f"{r.var_standard:.4g} | {r.var_improved:.4g} | {r.ratio:.3f} | {r.cosine:.3f}"
        lines.append(("| " + run_of(r) + " " if several else "") + f"| {r.episodes} | {r.part} | {figures} |")
    if rows:
        r = rows[0]
        lines += ["", f"{r.batches} batches of {r.num_envs} episodes per stage."]
    return "\n".join(lines) + "\n"


def short_names(runs: list[str]) -> dict[str, str]:
    """Each run's path without the folders all of them share (`study/runs/a`, `study/runs/b` -> `a`, `b`)."""
    parts = [Path(run).parts for run in runs]
    k = 0
    while len(runs) > 1 and all(len(p) > k + 1 for p in parts) and len({p[k] for p in parts}) == 1:
        k += 1
    return {run: str(Path(*p[k:])) for run, p in zip(runs, parts, strict=True)}


VarianceLines = dict[tuple[str, str, str], tuple[list[int], list[float]]]
"""(label, estimator, matplotlib line style) -> (episodes trained, variances): the lines of one panel."""


def variance_lines(rows: list[VarianceRow], part: str) -> VarianceLines:
    """The plot's lines for one part: one per estimator and run, so that the stages of different runs are
    never joined into one line (a run's line style tells the runs apart, the colour the estimators)."""
    runs = list(dict.fromkeys(run_of(r) for r in rows))
    names = short_names(runs)
    styles = ("o-", "s--", "^:", "D-.", "v-", "P--")
    lines: VarianceLines = {}
    for k, run in enumerate(runs):
        pts = sorted((r for r in rows if r.part == part and run_of(r) == run), key=lambda r: r.episodes)
        for estimator in ("standard", "improved"):
            label = f"{estimator}: {names[run]}" if len(runs) > 1 else estimator
            y = [getattr(r, f"var_{estimator}") for r in pts]
            lines[label, estimator, styles[k % len(styles)]] = ([r.episodes for r in pts], y)
    return lines


def plot_variance(rows: list[VarianceRow], path: str | Path, title: str = "") -> list[Path]:
    """Variance of each estimator against episodes trained, one panel per part (message, action), log y;
    written as `path` (PNG) and beside it as SVG; returns both paths."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    parts = ("message", "action")
    fig = Figure(figsize=(4.2 * len(parts) + 0.4, 3.6), layout="constrained")
    axes = fig.subplots(1, len(parts), squeeze=False)[0]
    for ax, part in zip(axes, parts, strict=True):
        for (label, estimator, style), (x, y) in variance_lines(rows, part).items():
            ax.plot(x, y, style, color="C0" if estimator == "standard" else "C1", label=label)
        ax.set_yscale("log")
        ax.set_xlabel("episodes trained")
        ax.set_ylabel("trace Cov(gradient estimate)")
        ax.set_title(f"{part} part", fontsize=10)
        ax.grid(alpha=0.3, which="both")
    if len({run_of(r) for r in rows}) > 1:  # a label per run and estimator: below the panels, off the data
        fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=2, fontsize=8)
    else:
        axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
