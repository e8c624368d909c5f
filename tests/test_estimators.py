"""The gradient estimators of SPEC section 4 (paper eq. 7 and 8).

Three kinds of check: numbers worked out by hand; unbiasedness against the exact policy gradient of
a tiny game enumerated in full; and the paper's claim that the improved estimator's message
gradient has lower variance than the standard one's.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import pytest
import torch

from bitcomm.errors import ConfigError
from bitcomm.learn.estimators import (
    ESTIMATORS,
    Advantages,
    EstimatorBatch,
    discounted_returns,
    get_estimator,
    improved,
    policy_gradient_loss,
    standard,
)


def _t(rows: list) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


def _batch(
    rewards: list,
    done: list,
    baseline_action: list,
    dropped: list | None = None,
    valid: list | None = None,
) -> EstimatorBatch:
    """Two agents, each sending to the other: the message baseline of sender j arriving at t is
    V2(s_t, a_t^j), which is the partner's action baseline, so baseline_message = baseline_action flipped."""
    ba = _t(baseline_action)
    return EstimatorBatch(
        rewards=_t(rewards),
        done=torch.tensor(done),
        valid=torch.ones(ba.shape[:2], dtype=torch.bool) if valid is None else torch.tensor(valid),
        baseline_action=ba,
        baseline_message=ba.flip(-1),
        dropped=torch.zeros(ba.shape, dtype=torch.bool) if dropped is None else torch.tensor(dropped),
    )


# ---------------------------------------------------------------------------------------------
# Hand-computed values. gamma = 0.5; one episode of three steps, rewards -1, -0.5, 0:
#   Q_2 = 0,  Q_1 = -0.5,  Q_0 = -1 + 0.5 * -0.5 = -1.25.
# Baselines (rows t, columns agent 0, agent 1):
#   baseline_action  = [[-1, -2], [-1.5, 0], [0.25, -0.25]]
#   baseline_message = [[-2, -1], [0, -1.5], [-0.25, 0.25]]   (the partner's V2)
# ---------------------------------------------------------------------------------------------

GAMMA = 0.5
REWARDS = [[-1.0], [-0.5], [0.0]]
DONE = [[False], [False], [True]]
BASELINE = [[[-1.0, -2.0]], [[-1.5, 0.0]], [[0.25, -0.25]]]


def test_returns_discount_to_the_end_of_the_episode() -> None:
    q = discounted_returns(_t(REWARDS), torch.tensor(DONE), torch.ones(3, 1, dtype=torch.bool), GAMMA)
    assert q.tolist() == [[-1.25], [-0.5], [0.0]]


def test_standard_uses_q_minus_v1_for_action_and_message() -> None:
    adv = standard(_batch(REWARDS, DONE, BASELINE), GAMMA, 1)
    # Q_t - V1: t=0: -1.25+1, -1.25+2; t=1: -0.5+1.5, -0.5-0; t=2: 0-0.25, 0+0.25.
    expected = [[[-0.25, 0.75]], [[1.0, -0.5]], [[-0.25, 0.25]]]
    assert adv.action.tolist() == expected
    assert adv.message.tolist() == expected
    assert adv.returns.tolist() == [[-1.25], [-0.5], [0.0]]


def test_standard_ignores_drops_like_the_paper() -> None:
    dropped = [[[True, True]], [[False, False]], [[False, False]]]
    adv = standard(_batch(REWARDS, DONE, BASELINE, dropped=dropped), GAMMA, 1)
    assert adv.message[0].tolist() == [[-0.25, 0.75]]


def test_improved_credits_a_message_with_the_recipients_next_advantage() -> None:
    adv = improved(_batch(REWARDS, DONE, BASELINE), GAMMA, 1)
    # Actions: Q_t - V2, the same numbers as the standard estimator with V1 := V2.
    assert adv.action.tolist() == [[[-0.25, 0.75]], [[1.0, -0.5]], [[-0.25, 0.25]]]
    # Messages sent at t arrive at t+1: gamma * (Q_{t+1} - baseline_message[t+1]).
    #   t=0: 0.5 * (-0.5 - 0) = -0.25,    0.5 * (-0.5 + 1.5) = 0.5
    #   t=1: 0.5 * (0 + 0.25) = 0.125,    0.5 * (0 - 0.25) = -0.125
    #   t=2: would arrive after the episode ended: 0.
    assert adv.message.tolist() == [[[-0.25, 0.5]], [[0.125, -0.125]], [[0.0, 0.0]]]


def test_improved_gives_a_dropped_message_no_credit() -> None:
    dropped = [[[False, True]], [[False, False]], [[False, False]]]
    adv = improved(_batch(REWARDS, DONE, BASELINE, dropped=dropped), GAMMA, 1)
    assert adv.message.tolist() == [[[-0.25, 0.0]], [[0.125, -0.125]], [[0.0, 0.0]]]


def test_improved_with_delay_two_looks_two_steps_ahead() -> None:
    adv = improved(_batch(REWARDS, DONE, BASELINE), GAMMA, 2)
    # t=0 arrives at t=2: 0.25 * (0 - [-0.25, 0.25]); t=1 and t=2 arrive after the end.
    assert adv.message.tolist() == [[[0.0625, -0.0625]], [[0.0, 0.0]], [[0.0, 0.0]]]
    # A delay as long as the batch: no message arrives at all.
    assert improved(_batch(REWARDS, DONE, BASELINE), GAMMA, 3).message.abs().sum() == 0


def test_two_episodes_in_a_column_and_padding() -> None:
    """Column 0 holds episode A (steps 0-1) then episode B (steps 2-4); column 1 holds a two-step
    episode then three padding steps whose rewards and baselines are garbage (nan).

    Column 0: Q = [-1 + 0.5 * -0.5, -0.5 | -2 + 0.5 * -1.25, -1 + 0.5 * -0.5, -0.5]
                = [-1.25, -0.5 | -2.625, -1.25, -0.5]
    Column 1: Q = [-0.5 + 0.5 * -1, -1, 0, 0, 0] = [-1, -1, 0, 0, 0]
    """
    nan = float("nan")
    rewards = [[-1.0, -0.5], [-0.5, -1.0], [-2.0, nan], [-1.0, nan], [-0.5, nan]]
    done = [[False, False], [True, True], [False, False], [False, True], [True, False]]
    valid = [[True, True], [True, True], [True, False], [True, False], [True, False]]
    zero, pad = [0.0, 0.0], [nan, nan]
    baseline = [[zero, zero], [zero, zero], [zero, pad], [zero, pad], [zero, pad]]
    batch = _batch(rewards, done, baseline, valid=valid)
    q = [[-1.25, -1.0], [-0.5, -1.0], [-2.625, 0.0], [-1.25, 0.0], [-0.5, 0.0]]

    adv = improved(batch, GAMMA, 1)
    assert adv.returns.tolist() == q
    assert adv.action.tolist() == [[[a, a], [b, b]] for a, b in q]
    # gamma * Q_{t+1} inside an episode; 0 when t+1 starts the next episode, is padding or lies beyond T.
    col0 = [0.5 * -0.5, 0.0, 0.5 * -1.25, 0.5 * -0.5, 0.0]
    col1 = [0.5 * -1.0, 0.0, 0.0, 0.0, 0.0]
    assert adv.message.tolist() == [[[a, a], [b, b]] for a, b in zip(col0, col1, strict=True)]

    adv = standard(batch, GAMMA, 1)
    assert adv.action.tolist() == [[[a, a], [b, b]] for a, b in q]
    assert adv.message.tolist() == adv.action.tolist()


def test_a_message_arriving_on_padding_gets_no_credit_even_where_no_step_says_done() -> None:
    """Padding ends an episode as `done` does (the module's contract): a column of two valid steps, no done flag,
    then padding with garbage (nan) rewards and baselines. Delay 2: the message of step 0 would arrive at step 2,
    which is padding, so it gets 0 (not gamma^2 * (0 - nan)); delay 1: step 0's arrives at step 1 and is credited.
    Q = [-1 + 0.5 * -0.5, -0.5, 0]."""
    nan = float("nan")
    rewards, done, valid = [[-1.0], [-0.5], [nan]], [[False], [False], [False]], [[True], [True], [False]]
    batch = _batch(rewards, done, [[[0.0, 0.0]], [[0.0, 0.0]], [[nan, nan]]], valid=valid)
    assert improved(batch, GAMMA, 2).message.tolist() == [[[0.0, 0.0]]] * 3
    assert improved(batch, GAMMA, 1).message.tolist() == [[[-0.25, -0.25]], [[0.0, 0.0]], [[0.0, 0.0]]]


def test_policy_gradient_loss_averages_over_valid_steps_and_detaches_advantages() -> None:
    logp_a = _t([[[-0.1, -0.2]], [[-5.0, -5.0]]]).requires_grad_()
    logp_m = _t([[[-1.0, -2.0]], [[float("nan"), -5.0]]]).requires_grad_()
    action = _t([[[1.0, 2.0]], [[3.0, 3.0]]]).requires_grad_()
    message = _t([[[0.5, -1.0]], [[3.0, 3.0]]]).requires_grad_()
    adv = Advantages(action=action, message=message, returns=torch.zeros(2, 1, dtype=torch.float64))
    valid = torch.tensor([[True], [False]])
    loss = policy_gradient_loss(logp_a, logp_m, adv, valid)
    # -(-0.1*1 - 0.2*2 - 1*0.5 - 2*-1) / 1 valid step = -(1.0)
    assert loss.item() == pytest.approx(-1.0)
    loss.backward()
    assert logp_a.grad is not None and logp_a.grad.tolist() == [[[-1.0, -2.0]], [[0.0, 0.0]]]
    assert action.grad is None and message.grad is None


def test_unknown_estimator_is_a_config_error_naming_the_value() -> None:
    assert get_estimator("standard") is standard and get_estimator("improved") is improved
    assert set(ESTIMATORS) == {"standard", "improved"}
    with pytest.raises(ConfigError, match="'vanilla'"):
        get_estimator("vanilla")


def test_delay_must_be_at_least_one() -> None:
    with pytest.raises(ConfigError, match="delay"):
        improved(_batch(REWARDS, DONE, BASELINE), GAMMA, 0)


# ---------------------------------------------------------------------------------------------
# A game small enough to enumerate: "swap the bits".
# Two agents; agent i has a goal bit g_i in {0, 1} but observes only its partner's bit g_{1-i}.
# Each step both act (a_i in {0, 1}) and send a 1-bit message to the partner, which arrives
# `delay` steps later (or is dropped with probability DROP); the input is 0 = nothing, 1 + bit.
# Team reward -0.5 - #(a_i != g_i); the episode ends when both are right, or after H steps.
# Policies are tabular softmaxes pi(a | obs, input) and Pm(m | obs, input), shared by both agents.
# ---------------------------------------------------------------------------------------------

H, G, DROP, N = 3, 0.8, 0.25, 200_000


class Game(NamedTuple):
    delay: int
    theta_a: torch.Tensor  # (2 obs, 3 inputs, 2 actions) logits
    theta_m: torch.Tensor  # (2 obs, 3 inputs, 2 messages) logits
    exact_grad: torch.Tensor  # (24,) dJ/d(theta_a, theta_m), J = E[sum_t G^t R_t]
    tables: dict[str, torch.Tensor]  # exact E[Q_t | key], (H, keys)
    traj: dict[str, torch.Tensor]  # N sampled episodes, (H, N, ...)
    cache: dict[tuple[str, str], tuple[torch.Tensor, torch.Tensor]]  # per-episode estimates, computed once


def _keys(g: torch.Tensor, inp: torch.Tensor, a: torch.Tensor) -> dict[str, torch.Tensor]:
    """Flat indices of what each baseline may see; `g`, `inp`, `a` end in the agent axis (size 2).

    v1_j: (state, partner's action, j's received input)  -- V1(s_t, a_t^{-j}, m_{t-1}^{-j})
    v2_j: (state, partner's action)                        -- V2(s_t, a_t^{-j})
    peek: (state, both actions) -- not allowed for a message baseline; used to show the test has power.
    """
    s = g[..., 0] * 2 + g[..., 1]
    keys = {"peek": s * 4 + a[..., 0] * 2 + a[..., 1]}
    for j in (0, 1):
        keys[f"v2_{j}"] = s * 2 + a[..., 1 - j]
        keys[f"v1_{j}"] = (s * 3 + inp[..., j]) * 2 + a[..., 1 - j]
    return keys


KEY_SIZES = {"peek": 16, "v2_0": 8, "v2_1": 8, "v1_0": 24, "v1_1": 24}


def _enumerate(theta_a: torch.Tensor, theta_m: torch.Tensor, delay: int) -> tuple[torch.Tensor, dict]:
    """Exact J (differentiable) and exact conditional expectations of Q_t, by dynamic programming.

    State: goals and the channel queue (input each agent receives 0..delay-1 steps from now).
    Outcome of a step: both actions, both messages, both drop events (64 outcomes).
    """
    states = list(itertools.product((0, 1), (0, 1), *[(0, 1, 2)] * (2 * delay)))
    index = {s: i for i, s in enumerate(states)}
    outcomes = list(itertools.product((0, 1), repeat=6))  # a0, a1, m0, m1, drop0, drop1
    nxt = [
        [index[(*s[:2], *s[4:], 0 if o[5] else o[3] + 1, 0 if o[4] else o[2] + 1)] for o in outcomes] for s in states
    ]
    nxt_t = torch.tensor(nxt)
    st, oc = torch.tensor(states), torch.tensor(outcomes)
    g, inp = st[:, None, :2].expand(-1, len(outcomes), 2), st[:, None, 2:4].expand(-1, len(outcomes), 2)
    a, m, drop = (oc[None, :, k : k + 2].expand(len(states), -1, 2) for k in (0, 2, 4))
    obs = g.flip(-1)
    pa, pm = theta_a.softmax(-1), theta_m.softmax(-1)
    prob = (pa[obs, inp, a] * pm[obs, inp, m]).prod(-1) * torch.where(drop == 1, DROP, 1 - DROP).prod(-1)
    right = (a == g).all(-1)
    reward = -0.5 - (a != g).sum(-1).double()

    p = torch.zeros(len(states), dtype=torch.float64)
    for gg in itertools.product((0, 1), (0, 1)):
        p[index[(*gg, *[0] * (2 * delay))]] = 0.25
    j_exact, flows = torch.zeros((), dtype=torch.float64), []
    for t in range(H):
        flow = p[:, None] * prob
        flows.append(flow.detach())
        j_exact = j_exact + G**t * (flow * reward).sum()
        done = right | (t == H - 1)
        p = torch.zeros_like(p).index_add(0, nxt_t.flatten(), (flow * ~done).flatten())

    # Expected return given (state, whole outcome), backwards; then E[Q_t | key] over the flow.
    keys = _keys(g, inp, a)
    tables = {k: torch.zeros(H, size, dtype=torch.float64) for k, size in KEY_SIZES.items()}
    w = torch.zeros(len(states), dtype=torch.float64)
    for t in reversed(range(H)):
        q = reward + G * ~(right | (t == H - 1)) * w[nxt_t]
        w = (prob.detach() * q).sum(1)
        for k, key in keys.items():
            num = torch.zeros(KEY_SIZES[k], dtype=torch.float64).index_add(0, key.flatten(), (flows[t] * q).flatten())
            den = torch.zeros(KEY_SIZES[k], dtype=torch.float64).index_add(0, key.flatten(), flows[t].flatten())
            tables[k][t] = torch.where(den > 0, num / den.clamp(min=1e-300), 0.0)
    return j_exact, tables


def _sample(theta_a: torch.Tensor, theta_m: torch.Tensor, delay: int, gen: torch.Generator) -> dict:
    """N episodes, all H steps simulated; steps after the end are marked invalid (their values are junk)."""
    pa, pm = theta_a.softmax(-1), theta_m.softmax(-1)
    g = torch.randint(0, 2, (N, 2), generator=gen)
    obs = g.flip(-1)
    queue = torch.zeros(N, delay, 2, dtype=torch.long)
    alive = torch.ones(N, dtype=torch.bool)
    rec: dict[str, list] = {k: [] for k in ("inp", "a", "m", "drop", "reward", "done", "valid")}
    for t in range(H):
        inp = queue[:, 0]
        a = (torch.rand(N, 2, generator=gen, dtype=torch.float64) < pa[obs, inp, 1]).long()
        m = (torch.rand(N, 2, generator=gen, dtype=torch.float64) < pm[obs, inp, 1]).long()
        drop = torch.rand(N, 2, generator=gen, dtype=torch.float64) < DROP
        done = (a == g).all(-1) | (t == H - 1)
        for k, v in zip(rec, (inp, a, m, drop, -0.5 - (a != g).sum(-1).double(), done, alive), strict=True):
            rec[k].append(v)
        alive = alive & ~done
        arriving = torch.where(drop, 0, m + 1).flip(-1)  # agent i receives from agent 1 - i
        queue = torch.cat([queue[:, 1:], arriving[:, None]], 1)
    traj = {k: torch.stack(v) for k, v in rec.items()}
    traj["g"] = g.expand(H, N, 2)
    traj["obs"] = obs.expand(H, N, 2)
    traj.update({f"key_{k}": key for k, key in _keys(traj["g"], traj["inp"], traj["a"]).items()})
    return traj


@pytest.fixture(scope="module", params=[1, 2], ids=["delay1", "delay2"])
def game(request: pytest.FixtureRequest) -> Game:
    """Policies midway through learning: receivers mostly follow the bit they receive, senders lean to telling."""
    delay = request.param
    gen = torch.Generator().manual_seed(1234 + delay)
    eye = torch.eye(2, dtype=torch.float64)
    theta_a = 0.5 * torch.randn(2, 3, 2, generator=gen, dtype=torch.float64)
    theta_a[:, 1:] += 1.5 * eye  # input 1 + b: favour action b
    theta_m = 0.5 * torch.randn(2, 3, 2, generator=gen, dtype=torch.float64) + 0.3 * eye[:, None, :]  # favour m = obs
    theta_a.requires_grad_(), theta_m.requires_grad_()
    j_exact, tables = _enumerate(theta_a, theta_m, delay)
    exact = torch.cat([x.flatten() for x in torch.autograd.grad(j_exact, [theta_a, theta_m])])
    traj = _sample(theta_a.detach(), theta_m.detach(), delay, gen)
    return Game(delay, theta_a.detach(), theta_m.detach(), exact, tables, traj, {})


def _baselines(game: Game, tables: dict[str, torch.Tensor], kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(baseline_action, baseline_message), each (H, N, 2), looked up in tables of E[Q_t | key]."""
    tr = game.traj
    steps = torch.arange(H)[:, None]
    look = {k: tables[k][steps, tr[f"key_{k}"]] for k in KEY_SIZES}
    if kind == "standard":
        action = torch.stack([look["v1_0"], look["v1_1"]], -1)
        return action, action
    action = torch.stack([look["v2_0"], look["v2_1"]], -1)
    if kind == "peek":
        return action, torch.stack([look["peek"], look["peek"]], -1)
    return action, action.flip(-1)  # the message of j arriving at t: V2(s_t, a_t^j), the partner's baseline


def _per_episode_gradient(game: Game, adv: Advantages, discount: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """(action part, message part) of sum_t G^t [score_a A^a + score_m A^m] over both agents; a row per episode.

    Weighting step t by G^t makes this an unbiased estimate of grad J for the discounted J (the
    trainer, like A3C, leaves the weight out; the advantages under test are the same).
    Tabular softmax: d log softmax(theta[o, i])[x] / d theta[o, i] = onehot(x) - softmax(theta[o, i]).
    """
    tr = game.traj
    n = tr["a"].shape[1]
    rows = (torch.arange(n)[:, None] * 6 + tr["obs"] * 3 + tr["inp"]).flatten()  # episode, then table cell
    disc = (G ** torch.arange(H, dtype=torch.float64) * discount + (1 - discount))[:, None, None]  # G^t or 1
    parts = []
    for theta, x, a in ((game.theta_a, tr["a"], adv.action), (game.theta_m, tr["m"], adv.message)):
        score = torch.nn.functional.one_hot(x, 2) - theta.softmax(-1)[tr["obs"], tr["inp"]]
        weighted = (score * (disc * a)[..., None]).reshape(-1, 2)
        parts.append(torch.zeros(n * 6, 2, dtype=torch.float64).index_add_(0, rows, weighted).reshape(n, 12))
    return parts[0], parts[1]


def _estimate(game: Game, name: str, quality: str = "ideal") -> tuple[torch.Tensor, torch.Tensor]:
    """Per-episode (action, message) gradient estimates of estimator `name` (or a test-only variant).

    quality: "ideal" (exact conditional expectations), "arbitrary" (random functions of the same
    inputs) or "peek" (ideal, but the message baseline also sees the recipient's action: not allowed).
    """
    if (name, quality) not in game.cache:
        tables = _arbitrary_tables(7) if quality == "arbitrary" else game.tables
        kind = "peek" if quality == "peek" else "standard" if name == "standard" else "improved"
        baseline_action, baseline_message = _baselines(game, tables, kind)
        tr = game.traj
        batch = EstimatorBatch(tr["reward"], tr["done"], tr["valid"], baseline_action, baseline_message, tr["drop"])
        estimator = _forgets_gamma_delay if name == "forgets_gamma_delay" else get_estimator(name)
        game.cache[name, quality] = _per_episode_gradient(game, estimator(batch, G, game.delay))
    return game.cache[name, quality]


def _forgets_gamma_delay(batch: EstimatorBatch, gamma: float, delay: int) -> Advantages:
    """A deliberately wrong improved estimator: message advantage without the gamma^delay factor."""
    adv = improved(batch, gamma, delay)
    return adv._replace(message=adv.message / gamma**delay)


def _z_scores(samples: torch.Tensor, exact: torch.Tensor) -> torch.Tensor:
    """|mean - exact| in standard errors of the mean, per component."""
    se = samples.std(0) / N**0.5
    return (samples.mean(0) - exact).abs() / (se + 1e-12)


def _arbitrary_tables(seed: int) -> dict[str, torch.Tensor]:
    """Baselines of the allowed form but no quality: random values per key, in [-4, 4]."""
    gen = torch.Generator().manual_seed(seed)
    return {k: 8 * torch.rand(H, size, generator=gen, dtype=torch.float64) - 4 for k, size in KEY_SIZES.items()}


@pytest.mark.parametrize("name", ["standard", "improved"])
@pytest.mark.parametrize("quality", ["ideal", "arbitrary"])
def test_estimators_are_unbiased(game: Game, name: str, quality: str) -> None:
    """Mean of N per-episode estimates = exact gradient within 4 standard errors (+1e-6), per component.

    ideal: baselines are the exact E[Q_t | allowed inputs]; arbitrary: random functions of the same
    inputs, so unbiasedness cannot come from baseline quality. Drops and early ends are in the game.
    """
    action, message = _estimate(game, name, quality)
    z = _z_scores(torch.cat([action, message], 1), game.exact_grad)
    assert game.exact_grad[:12].abs().max() > 0.03 and game.exact_grad[12:].abs().max() > 0.03  # worth estimating
    assert (z < 4 + 1e-6 * N**0.5).all(), f"z-scores {z}"


@pytest.mark.parametrize("wrong", ["peek", "forgets_gamma_delay"])
def test_the_unbiasedness_check_has_power(game: Game, wrong: str) -> None:
    """Two wrong message gradients are caught: a baseline that sees the recipient's action, and
    an advantage without its gamma^delay."""
    _, message = _estimate(game, *(("improved", "peek") if wrong == "peek" else ("forgets_gamma_delay", "ideal")))
    assert _z_scores(message, game.exact_grad[12:]).max() > 10


def test_improved_message_gradient_has_lower_variance(game: Game) -> None:
    """Paper III-C: with ideal baselines, trace Cov(message part) is lower for the improved estimator.

    Measured on this game: ratio 0.18 at delay 1, 0.02 at delay 2.
    """
    _, standard_message = _estimate(game, "standard")
    _, improved_message = _estimate(game, "improved")
    ratio = improved_message.var(0).sum() / standard_message.var(0).sum()
    assert ratio < 0.5, f"variance ratio improved/standard = {ratio:.3f}"


def test_action_parts_agree_in_mean(game: Game) -> None:
    """V1 and V2 are both allowed action baselines: the paired difference of the action parts has mean 0."""
    standard_action, _ = _estimate(game, "standard")
    improved_action, _ = _estimate(game, "improved")
    assert (_z_scores(standard_action - improved_action, torch.zeros(12, dtype=torch.float64)) < 4).all()


def test_policy_gradient_loss_is_minus_the_mean_score_sum(game: Game) -> None:
    """Autograd through the loss gives -(sum over episodes of sum_t score * advantage) / #valid steps."""
    tr, k = game.traj, 1000  # the first k episodes
    theta_a, theta_m = game.theta_a.clone().requires_grad_(), game.theta_m.clone().requires_grad_()
    obs, inp = tr["obs"][:, :k], tr["inp"][:, :k]
    logp_a = theta_a.log_softmax(-1)[obs, inp, tr["a"][:, :k]]
    logp_m = theta_m.log_softmax(-1)[obs, inp, tr["m"][:, :k]]
    baseline_action, baseline_message = (b[:, :k] for b in _baselines(game, game.tables, "improved"))
    batch = EstimatorBatch(
        tr["reward"][:, :k], tr["done"][:, :k], tr["valid"][:, :k], baseline_action, baseline_message, tr["drop"][:, :k]
    )
    adv = improved(batch, G, game.delay)
    loss = policy_gradient_loss(logp_a, logp_m, adv, batch.valid)
    grad = torch.cat([x.flatten() for x in torch.autograd.grad(loss, [theta_a, theta_m])])
    sub = game._replace(traj={key: v[:, :k] for key, v in tr.items()})
    action, message = _per_episode_gradient(sub, adv, discount=False)
    expected = -torch.cat([action, message], 1).sum(0) / batch.valid.sum()
    torch.testing.assert_close(grad, expected)
