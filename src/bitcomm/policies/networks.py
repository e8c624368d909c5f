"""Policy and critic networks (SPEC section 3, paper Fig. 2).

Policy: observation planes -> convolutions; received message -> one fully connected layer; the two
concatenated -> two fully connected layers -> move logits and message logits. One set of
parameters serves every agent. Critics see the full state, centred on the agent they judge
(its own position and goal first), plus the other agents' actions, each with a "given" flag so one
network answers with any subset of them masked (SPEC section 4, several recipients).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from bitcomm.config import TaskConfig, entries, plain_fields
from bitcomm.envs.core import N_MOVES
from bitcomm.errors import bad_value, check_int
from bitcomm.policies.heads import MessageHead, make_head

ENCODERS = ("conv", "marginals", "cells")
MESSAGE_READS = ("all", "observed")
OBSERVED_PLANE = 1
"""The observation plane of what an agent observes (SPEC section 1: its own position first, then the goal of the
agent it observes)."""


@dataclass(frozen=True)
class ModelConfig:
    """Network sizes; defaults are small enough for a laptop CPU to train in minutes."""

    messages: str = "bitwise"
    """Message head: `bitwise` (K Bernoulli bits) or `onehot` (categorical over 2^K)."""
    encoder: str = "conv"
    """How the policy and the critic read observation planes: `conv`, a stack of convolutions (the paper's
    Fig. 2); `marginals`, each plane's row sums and column sums (a one-hot plane's row and column, each as a
    one-hot vector) straight into the fully connected layers, which loses nothing of a plane that marks one
    cell and costs a fraction of a convolution on a CPU; `cells`, the marginals and every cell of each plane:
    each cell then has weights of its own, so a sender can give a cell any code, not only one composed of a
    code for its row and one for its column (which needs 8 bits on a 10x10 grid)."""
    conv_channels: tuple[int, ...] = (8, 16)
    """Channels of the 3x3 convolutions (each of stride `conv_stride`), with `encoder` `conv`."""
    conv_stride: int = 2
    """Stride of every convolution: 2 keeps updates cheap on a CPU and one-hot planes lose nothing to it (a
    kernel tells the offsets apart), but it halves the grid at each layer (10x10 -> 5x5 -> 3x3); 1 keeps the
    grid's resolution at about four times the cost per layer."""
    message_hidden: int = 64
    """Width of the fully connected layer over the received message (and the critics' extra inputs)."""
    hidden: int = 128
    """Width of the two fully connected layers after the concatenation."""
    coords: bool = False
    """Add row and column coordinate planes to the observation (CoordConv), so that comparing a
    decoded goal with one's own position is a linear read-out rather than a lookup. Only the `conv` encoder
    reads them (a coordinate plane's row and column sums are constant), so `make_train_config` refuses it typed
    with another encoder, and sets a recipe's value off there."""
    plane_coords: bool = False
    """Also give the fully connected layers each input plane's centre of mass (its row and column in
    [-1, 1]): the exact cell of a one-hot plane, the expected cell of a decoded message map. Moving
    toward a goal is then comparing two numbers, which convolutions of stride 2 learn only slowly
    on larger grids."""
    message_reads: str = "all"
    """What the message head reads: `all`, the hidden layers the move head reads too (the paper's Fig. 2: the
    observation and the received messages); `observed`, only the plane of what the agent observes (the goal it
    is to tell), through two fully connected layers of its own, so that a sender's code for that goal cannot
    depend on where the sender stands or on what it hears. A receiver then sees one code for its goal whatever
    the sender does. The code is still learned by the policy gradient alone. On the paper's task the protocol
    forms in about half the episodes (2x the oracle after 10-12k episodes on 5 seeds; docs/tuning.md session 28),
    and with `greedy_senders` greedy play ends within 1.10x of the oracle on every seed (session 34): the
    `reinforced` recipe's head since session 35 (`all` stays this config's default, the paper's head)."""
    sender_hidden: int = 128
    """Width of the message head's own two layers (`message_reads` `observed`). In acting they cost about as much as
    the policy's own trunk (each agent-step runs both); an update runs them once per distinct goal seen
    (`bitcomm.learn.distinct`), so there a narrower pair saves little."""
    message_map: bool = False
    """Also decode each received message into a map over the grid's cells (one linear layer; its most
    likely cell as a one-hot plane, with the softmax's gradient) stacked beside the observation planes:
    a message that names a cell then reaches the network the way a seen cell does, so moving toward it
    is the same skill as moving toward anything the agent sees. The decoder learns from the policy
    gradient through the map (and, in the `supervised` recipe, from the auxiliary goal loss)."""

    def __post_init__(self) -> None:
        plain_fields(self)
        if self.encoder not in ENCODERS:
            raise bad_value("encoder", self.encoder, f"choose one of {', '.join(ENCODERS)}")
        if self.message_reads not in MESSAGE_READS:
            raise bad_value("message_reads", self.message_reads, f"choose one of {', '.join(MESSAGE_READS)}")
        for name in ("conv_stride", "message_hidden", "hidden", "sender_hidden"):
            check_int(name, getattr(self, name), 1)
        width = ModelConfig.__dataclass_fields__["sender_hidden"].default  # the field's literal, which --help reads
        if self.sender_hidden != width and self.message_reads != "observed":
            raise bad_value(
                "sender-hidden", self.sender_hidden, f"acts only with --message-reads observed; leave it at {width}"
            )
        stride = ModelConfig.__dataclass_fields__["conv_stride"].default
        if self.conv_stride != stride and self.encoder != "conv":
            raise bad_value("conv-stride", self.conv_stride, f"acts only with --encoder conv; leave it at {stride}")
        channels = entries("conv_channels", self.conv_channels, "one or more integers >= 1")
        if not channels or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in channels):
            raise bad_value("conv_channels", self.conv_channels, "one or more integers >= 1")


def _conv_stack(in_channels: int, cfg: ModelConfig, size: int) -> tuple[nn.Sequential, int]:
    """The plane encoder and its output width: convolutions, or (`marginals`) row and column sums, or (`cells`)
    those and the planes' cells."""
    if cfg.encoder == "marginals":
        return nn.Sequential(Marginals()), in_channels * 2 * size
    if cfg.encoder == "cells":
        return nn.Sequential(Marginals(cells=True)), in_channels * (2 * size + size * size)
    layers: list[nn.Module] = []
    c, s, stride = in_channels, size, cfg.conv_stride
    for out in cfg.conv_channels:
        layers += [nn.Conv2d(c, out, 3, stride=stride, padding=1), nn.ReLU()]
        c, s = out, (s - 1) // stride + 1
    return nn.Sequential(*layers, nn.Flatten()), c * s * s


class Marginals(nn.Module):
    """`(N, P, S, S)` planes -> `(N, P * 2S)`: each plane's sums over columns (per row) and over rows; with
    `cells`, `(N, P * (2S + S * S))`: each plane's marginals followed by its cells."""

    def __init__(self, cells: bool = False) -> None:
        super().__init__()
        self.cells = cells

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        parts = [x.sum(3), x.sum(2), x.flatten(2)] if self.cells else [x.sum(3), x.sum(2)]
        return torch.cat(parts, 2).flatten(1)


def concat_linear(layer: nn.Module, shared: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
    """`layer(cat([shared, own], -1))` for `shared (M, a)` and `own (N, b)`, each row of `shared` standing for N // M
    consecutive rows of `own`: the sum of the two parts' products, so a part that needs no gradient (features read
    once per batch) costs the backward pass nothing, and a row shared by several queries (a critic's state) is
    multiplied once."""
    assert isinstance(layer, nn.Linear)
    a = shared.shape[1]
    out = nn.functional.linear(shared, layer.weight[:, :a], layer.bias)
    if len(own) != len(shared):
        out = out.repeat_interleave(len(own) // len(shared), 0)
    return out + nn.functional.linear(own, layer.weight[:, a:])


def _coord_planes(size: int) -> torch.Tensor:
    r = torch.linspace(-1.0, 1.0, size)
    return torch.stack([r[:, None].expand(size, size), r[None, :].expand(size, size)])


class PolicyNet(nn.Module):
    """pi(a | o, m_rec) and Pm(m | o, m_rec), sampled independently (paper IV)."""

    coords: torch.Tensor  # a buffer; declared so that type checkers see a tensor, not `Tensor | Module`

    def __init__(self, task: TaskConfig, cfg: ModelConfig) -> None:
        super().__init__()
        self.task, self.cfg = task, cfg
        self.head: MessageHead = make_head(cfg.messages, task.channel.bits)
        size = task.env.size
        self.register_buffer("coords", _coord_planes(size), persistent=False)
        maps = task.slots if cfg.message_map else 0
        self.coord_planes = cfg.coords and cfg.encoder == "conv"  # a marginal of a coordinate plane is constant
        self.conv, flat = _conv_stack(2 + 2 * self.coord_planes + maps, cfg, size)
        flat += 2 * (2 + maps) if cfg.plane_coords else 0
        self.message_map = nn.Linear(self.head.in_features, size * size) if cfg.message_map else None
        if self.message_map is not None:  # a uniform map until the decoder learns (TrainConfig.map_lr)
            nn.init.zeros_(self.message_map.weight)
            nn.init.zeros_(self.message_map.bias)
        self.message_in = nn.Sequential(nn.Linear(task.slots * self.head.in_features, cfg.message_hidden), nn.ReLU())
        self.fc1 = nn.Sequential(nn.Linear(flat + cfg.message_hidden, cfg.hidden), nn.ReLU())
        self.fc2 = nn.Sequential(nn.Linear(cfg.hidden, cfg.hidden), nn.ReLU())
        self.move_logits = nn.Linear(cfg.hidden, N_MOVES)
        own = cfg.message_reads == "observed"  # the message head reads what the agent observes, on layers of its own
        # created before those layers, so that a seed's initial weights are what they were before `sender_hidden`
        self.message_logits = nn.Linear(cfg.sender_hidden if own else cfg.hidden, self.head.out_features)
        self.message_trunk: nn.Sequential | None = None
        if own:
            self.observed_conv, observed = _conv_stack(1, cfg, size)
            observed += 2 if cfg.plane_coords else 0
            width = cfg.sender_hidden
            self.message_trunk = nn.Sequential(
                nn.Linear(observed, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU()
            )
        # moves start uniform whatever the hidden layers say (as CleanRL's actor head, std 0.01), so a
        # warm start that shapes the hidden layers does not leave the agents a strong random habit
        with torch.no_grad():
            self.move_logits.weight.mul_(0.01)
            self.move_logits.bias.zero_()
        # training-time read-out of the agent's own goal (row and column) from its first hidden layer;
        # used only by the optional goal-grounding loss, never by acting
        self.goal_logits = nn.Linear(cfg.hidden, 2 * size)
        # training-time read-out of the goal the agent observes (the one it should tell), for the
        # optional sender-grounding loss
        self.seen_logits = nn.Linear(cfg.hidden, 2 * size)

    @property
    def fixed_features(self) -> bool:
        """Whether `observation_features` has no parameters and ignores the received message (an encoder other
        than `conv`, no message map): a learner may then read a batch's observations once for all its passes."""
        return next(self.conv.parameters(), None) is None and self.message_map is None

    def observation_features(self, planes: torch.Tensor, received_encoded: torch.Tensor | None) -> torch.Tensor:
        """`(N, 2, S, S)` planes (any dtype) -> `(N, flat)` features; the received message enters here
        only with `message_map` (None will do without one)."""
        x = planes.float()
        seen = torch.cat([x, self.coords.expand(x.shape[0], -1, -1, -1)], 1) if self.coord_planes else x
        if self.message_map is None:
            features = self.conv(seen)
        elif self.cfg.encoder != "conv":  # marginals (and cells): no convolution to save
            maps = self._decoded_maps(received_encoded, x.shape)
            features = self.conv(torch.cat([seen, maps], 1))
        else:
            maps = self._decoded_maps(received_encoded, x.shape)
            features = self.conv[1:](self._first_conv(seen, maps))
        if not self.cfg.plane_coords:
            return features
        if self.message_map is not None:
            x = torch.cat([x, maps], 1)
        return torch.cat([features, self._centres(x)], 1)

    def _centres(self, x: torch.Tensor) -> torch.Tensor:
        """`(N, P, S, S)` planes -> `(N, P * 2)`: each plane's centre of mass (row, column in [-1, 1])."""
        mass = x.sum((2, 3)).clamp(min=1e-6)  # (N, planes)
        return (torch.einsum("npij,cij->npc", x, self.coords) / mass[..., None]).flatten(1)

    def message_state(
        self, planes: torch.Tensor | None, h2: torch.Tensor, observed: torch.Tensor | None = None
    ) -> torch.Tensor:
        """What the message logits are read from: the second hidden layer `h2`, or (`message_reads` `observed`)
        the message head's own layers over the observed plane of the `(N, 2, S, S)` planes (which only then are
        needed), or over its features `observed` where the caller has read them (`observed_features`)."""
        if self.message_trunk is None:
            return h2
        if observed is None:
            assert planes is not None, "a message head of its own reads the observation planes"
            observed = self.observed_features(planes, h2.dtype)
        return self.message_trunk(observed)

    def observed_features(self, planes: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """`(N, 2, S, S)` planes -> the message head's reading of the observed plane (`message_reads` `observed`) in
        `dtype`: parameter-free where `fixed_features` is, so a learner may read it once per batch."""
        x = planes[:, OBSERVED_PLANE : OBSERVED_PLANE + 1].to(dtype)
        features = self.observed_conv(x)
        if self.cfg.plane_coords:
            features = torch.cat([features, self._centres(x)], 1)
        return features

    def _decoded_maps(self, received_encoded: torch.Tensor | None, shape: torch.Size) -> torch.Tensor:
        """`(N, slots, S, S)`: each received message's most likely cell, one-hot, with the softmax's gradient."""
        assert received_encoded is not None, "the message map reads the received messages"
        soft = torch.softmax(self.map_logits(received_encoded), -1)  # (N, slots, S * S)
        hard = nn.functional.one_hot(soft.argmax(-1), soft.shape[-1]).to(soft.dtype)
        return (hard + soft - soft.detach()).view(shape[0], -1, *shape[2:])

    def _first_conv(self, seen: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
        """The first convolution over the input planes `[observed, maps, coords]`, with the decoded maps
        `(N, slots, S, S)` applied as a matrix product: they are the only input that needs a gradient,
        and a convolution's input gradient costs 10x its forward on these small planes on a CPU
        (docs/tuning.md, session 6), while over one plane it is a linear map from cells to outputs."""
        conv: nn.Conv2d = self.conv[0]  # type: ignore[assignment]
        observed, slots = 2, maps.shape[1]
        if not maps.requires_grad:  # acting, evaluation, ONNX export: the plain convolution
            return conv(torch.cat([seen[:, :observed], maps, seen[:, observed:]], 1))
        w = conv.weight  # (out, in, 3, 3), input channels in the order above
        out = nn.functional.conv2d(
            seen, torch.cat([w[:, :observed], w[:, observed + slots :]], 1), conv.bias, conv.stride, conv.padding
        )
        cells = maps.shape[2] * maps.shape[3]
        basis = torch.eye(cells, dtype=w.dtype).view(cells, 1, *maps.shape[2:])
        per_cell = nn.functional.conv2d(  # (cells, slots * out, ...): each map channel's output for each cell
            basis,
            w[:, observed : observed + slots].transpose(0, 1).reshape(-1, 1, *w.shape[2:]),
            None,
            conv.stride,
            conv.padding,
        )
        mapped = torch.einsum("nsc,csq->nq", maps.flatten(2), per_cell.view(cells, slots, -1))
        return out + mapped.view_as(out)

    def map_logits(self, received_encoded: torch.Tensor) -> torch.Tensor:
        """`(N, slots * in_features)` -> `(N, slots, S * S)`: each received message as logits over cells."""
        assert self.message_map is not None, "needs ModelConfig.message_map"
        return self.message_map(received_encoded.view(received_encoded.shape[0], self.task.slots, -1))

    def encode_received(self, received: torch.Tensor) -> torch.Tensor:
        """`(N, slots, K)` bits -> `(N, slots * in_features)` as this head's receiver reads them."""
        return self.head.encode(received).flatten(1)

    def read_received(self, received: torch.Tensor) -> torch.Tensor:
        """`(N, slots, K)` bits -> `(N, message_hidden)`: `message_in(encode_received(received))`, with the head's
        own product (`MessageHead.linear`: a one-hot is read by its weight's columns)."""
        layer: nn.Linear = self.message_in[0]  # type: ignore[assignment]
        return self.message_in[1:](self.head.linear(received, layer.weight, layer.bias))

    def trunk(self, obs_features: torch.Tensor, message_features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The first and second hidden layers, from the observation's features and the received messages'
        (`read_received`, or `message_in` of a soft encoding)."""
        h1 = self.fc1[1:](concat_linear(self.fc1[0], obs_features, message_features))
        return h1, self.fc2(h1)

    def hidden(self, planes: torch.Tensor, received: torch.Tensor) -> torch.Tensor:
        """The second hidden layer `h2` for `(N, 2, S, S)` planes and `(N, slots, K)` bits."""
        encoded = self.encode_received(received) if self.message_map is not None else None
        return self.trunk(self.observation_features(planes, encoded), self.read_received(received))[1]

    def forward(self, planes: torch.Tensor, received: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Move logits `(N, 5)` and message logits `(N, out)` for `(N, 2, S, S)` planes and `(N, slots, K)` bits."""
        h2 = self.hidden(planes, received)
        return self.move_logits(h2), self.message_logits(self.message_state(planes, h2))

    def observed_message_logits(self, planes: torch.Tensor) -> torch.Tensor:
        """A message head of its own (`message_reads` `observed`): its logits `(N, out)` from the observed plane of
        `(N, 2, S, S)` planes alone. That plane holds a goal, which an episode keeps, so an actor may compute them
        once per episode (`bitcomm.learn.rollout.Collector`)."""
        assert self.message_trunk is not None, "needs message_reads observed"
        return self.message_logits(self.message_trunk(self.observed_features(planes)))


def others_actions(moves: torch.Tensor, given: torch.Tensor) -> torch.Tensor:
    """One-hot actions of every agent, zeroed where not given, each with its "given" flag.

    `moves`, `given`: `(N, n)`; returns `(N, n * (5 + 1))`.
    """
    g = given.float()
    onehot = nn.functional.one_hot(moves, N_MOVES).float() * g[..., None]
    return torch.cat([onehot, g[..., None]], -1).flatten(1)


class CriticNet(nn.Module):
    """V(s, whose value, other agents' actions with a mask [, messages that agent received]).

    `with_message=True` is V1 (standard estimator); `False` is V2 (improved estimator). The state is
    convolved once per step; which agent is judged and which actions are given enter as a vector, so
    one network answers every query of SPEC section 4 (several recipients: mask their actions).
    """

    def __init__(self, task: TaskConfig, cfg: ModelConfig, with_message: bool) -> None:
        super().__init__()
        n, size = task.env.n_agents, task.env.size
        self.n_agents, self.with_message = n, with_message
        self.head = make_head(cfg.messages, task.channel.bits)
        self.conv, flat = _conv_stack(2 * n, cfg, size)
        extra = n + n * (N_MOVES + 1) + (task.slots * self.head.in_features if with_message else 0)
        self.extra_in = nn.Sequential(nn.Linear(extra, cfg.message_hidden), nn.ReLU())
        self.body = nn.Sequential(
            nn.Linear(flat + cfg.message_hidden, cfg.hidden),
            nn.ReLU(),
            nn.Linear(cfg.hidden, cfg.hidden),
            nn.ReLU(),
            nn.Linear(cfg.hidden, 1),
        )

    @property
    def fixed_features(self) -> bool:
        """Whether `state_features` has no parameters (an encoder other than `conv`), see `PolicyNet`."""
        return next(self.conv.parameters(), None) is None

    def state_features(self, state: torch.Tensor) -> torch.Tensor:
        """`(M, 2n, S, S)` state planes -> `(M, flat)`, shared by every query about that state."""
        return self.conv(state.float())

    def value(
        self,
        features: torch.Tensor,
        viewpoint: torch.Tensor,
        moves: torch.Tensor,
        given: torch.Tensor,
        received: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """`features (M, flat)`, `viewpoint (N,)`, `moves/given (N, n)`, `received (N, slots, K)` -> `(N,)`, for N
        queries about M states, each state's N // M queries consecutive. The state's share of the first layer is
        computed once per state, not once per query: the queries about one state (an agent's action baseline,
        its partner's, a message's) differ only in the small vector of who is judged and which actions are given."""
        small = torch.cat([nn.functional.one_hot(viewpoint, self.n_agents).float(), others_actions(moves, given)], -1)
        layer: nn.Linear = self.extra_in[0]  # type: ignore[assignment]
        a = small.shape[1]
        extra = nn.functional.linear(small, layer.weight[:, :a], layer.bias)
        if self.with_message:
            assert received is not None, "V1 conditions on the received message"
            extra = extra + self.head.linear(received, layer.weight[:, a:])  # the messages' columns of the layer
        return self.body[1:](concat_linear(self.body[0], features, self.extra_in[1:](extra)))[:, 0]
