"""One agent of the deploy runtime, as its own process: `python -m bitcomm.deploy.agent --world HOST:PORT --agent I`.

It holds only its own policy (built from the config the world sends) and two sockets: TCP to the
world (its observation and step in, its move out) and UDP to its peers (K-bit messages). Per step:
1. wait for the messages that belong to this step (sent `delay` steps ago by the agents it hears) until
   the deadline; one that has not arrived by then reads as zeros, as a dropped message does;
2. choose a move and K bits with its policy;
3. send the bits to each recipient as a datagram, after the wire's seeded bit flips and on-purpose drops (a send
   the system refuses is a lost datagram, counted as `send_failed`);
4. reply the move to the world.
It exits when the world says stop, when the world's connection closes (the world ended or died), or
at the run's time bound, whichever comes first.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from typing import Any

import numpy as np

from bitcomm.config import TaskConfig
from bitcomm.deploy.protocol import LineSocket, PeerGone, decode_array, pack_datagram, unpack_datagram
from bitcomm.errors import ConfigError, bad_value
from bitcomm.policies.source import PolicySource


class Inbox:
    """Datagrams from peers, kept by (sender, episode, step) until their step is played. One this agent cannot
    read (another run's, one of `bits` bits other than the task's, one from a sender it does not hear) is counted
    as foreign and dropped: a stray or garbled datagram never stops an agent. A second copy of a message it holds
    (a radio may repeat one) is counted as duplicate, so `received` counts messages; one whose step was played
    already is counted as late."""

    def __init__(self, sock: socket.socket, run_id: int, bits: int, senders: list[int]) -> None:
        self.sock, self.run_id, self.bits, self.senders = sock, run_id, bits, set(senders)
        self.messages: dict[tuple[int, int, int], np.ndarray] = {}
        self.played: tuple[int, int] = (-1, -1)  # (episode, step) of the latest messages read
        self.stats = {"received": 0, "late": 0, "duplicate": 0, "foreign": 0}

    def drain(self, timeout: float, until: float) -> None:
        """Take every waiting datagram, waiting up to `timeout` seconds for the first; past `until` (a
        `time.monotonic()` time) it stops after the datagram in hand, so a flood cannot hold the agent there."""
        self.sock.settimeout(timeout if timeout > 0 else 0.0)  # 0: non-blocking
        while True:
            try:
                data = self.sock.recv(2048)
            except (BlockingIOError, TimeoutError):
                return
            self.sock.settimeout(0.0)
            d = unpack_datagram(data)
            if d is None or d.run_id != self.run_id or d.bits.size != self.bits or d.sender not in self.senders:
                self.stats["foreign"] += 1
            elif (d.episode, d.step) <= self.played:
                self.stats["late"] += 1  # its step was already played without it
            elif (d.sender, d.episode, d.step) in self.messages:
                self.stats["duplicate"] += 1
            else:
                self.stats["received"] += 1
                self.messages[(d.sender, d.episode, d.step)] = d.bits
            if time.monotonic() >= until:
                return

    def take(self, senders: list[int], episode: int, step: int, deadline: float) -> dict[int, np.ndarray]:
        """The messages of `senders` for (episode, step), waiting until `deadline` for missing ones."""
        while True:
            self.drain(0.0, deadline)
            if all((j, episode, step) in self.messages for j in senders):
                break
            left = deadline - time.monotonic()
            if left <= 0:
                break
            self.drain(left, deadline)
        got = {j: self.messages[(j, episode, step)] for j in senders if (j, episode, step) in self.messages}
        self.played = (episode, step)
        self.messages = {k: v for k, v in self.messages.items() if (k[1], k[2]) > self.played}
        return got


def run_agent(world: tuple[str, int], agent: int, token: str) -> int:
    """The agent's whole life; the exit status is 0 after a clean stop."""
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    ctl = LineSocket(socket.create_connection(world, timeout=30))
    ctl.send({"type": "hello", "agent": agent, "token": token, "udp_port": udp.getsockname()[1]})
    cfg: dict[str, Any] = ctl.recv(time.monotonic() + 60)
    stop_at = time.monotonic() + float(cfg["time_left_s"])
    task = TaskConfig.from_dict(cfg["task"])
    K, S, delay = task.channel.bits, task.env.size, task.channel.delay
    seeds = np.random.SeedSequence(int(cfg["seed"]), spawn_key=(agent,)).spawn(2)
    policy = PolicySource.from_dict(cfg["policy"]).build(task, seed=seeds[0])
    wire = np.random.default_rng(seeds[1])  # this agent's radio: flips and on-purpose drops
    flip_prob, drop_prob = float(cfg["flip_prob"]), float(cfg["drop_prob"])
    peers = [("127.0.0.1", int(p)) for p in cfg["peers"]]  # my recipients' UDP ports
    slot_senders = [int(j) for j in cfg["slot_senders"]]  # who I hear, per input slot (-1: nobody)
    hears = [j for j in slot_senders if j >= 0]
    deadline_s = float(cfg["deadline_ms"]) / 1000.0
    inbox = Inbox(udp, int(cfg["run_id"]), K, hears)
    stats = {"sent": 0, "dropped": 0, "send_failed": 0, "missing": 0}
    seq = 0
    ctl.send({"type": "ready", "agent": agent})
    while True:
        msg = ctl.recv(stop_at)
        if msg["type"] == "stop":
            inbox.drain(0.0, time.monotonic() + deadline_s)  # count what arrived for steps never played
            ctl.send({"type": "stats", "agent": agent, **stats, **inbox.stats})
            return 0
        episode, t = int(msg["episode"]), int(msg["t"])
        planes = decode_array(msg["planes"], (2, S, S))
        received = np.zeros((len(slot_senders), K), dtype=np.uint8)
        if t >= delay:  # messages sent at t - delay of this episode belong to this step
            got = inbox.take(hears, episode, t - delay, time.monotonic() + deadline_s)
            stats["missing"] += len(hears) - len(got)
            for k, j in enumerate(slot_senders):
                if j in got:
                    received[k] = got[j]
        move, bits = policy.act(planes[None], received[None], np.array([t]), np.array([agent]))
        out = np.asarray(bits[0], dtype=np.uint8)
        if flip_prob > 0.0:
            out = out ^ (wire.random(K) < flip_prob).astype(np.uint8)
        for peer in peers:
            if drop_prob > 0.0 and wire.random() < drop_prob:
                stats["dropped"] += 1
                continue
            try:
                udp.sendto(pack_datagram(inbox.run_id, agent, episode, t, seq, out), peer)
            except OSError:  # no buffer space, the link down: on a radio, a lost datagram, not a lost agent
                stats["send_failed"] += 1
                continue
            stats["sent"] += 1
        seq += 1
        ctl.send({"type": "move", "agent": agent, "episode": episode, "t": t, "move": int(move[0])})


def world_address(text: str) -> tuple[str, int]:
    """`HOST:PORT` as `(host, port)`, or one error line."""
    host, _, port = text.rpartition(":")
    if not host or not (port.isascii() and port.isdigit()) or not 0 < int(port) < 65536:
        raise bad_value("world", text, "give HOST:PORT, PORT in 1..65535 (the world's control socket)")
    return host, int(port)


def main(argv: list[str] | None = None) -> int:
    prog = "python -m bitcomm.deploy.agent"
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    p.add_argument("--world", required=True, help="HOST:PORT of the world's control socket")
    p.add_argument("--agent", type=int, required=True, help="this agent's index")
    p.add_argument("--token", default="", help="the run's token, proving to the world who started us")
    args = p.parse_args(argv)
    try:
        return run_agent(world_address(args.world), args.agent, args.token)
    except ConfigError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return 2
    except socket.gaierror as err:  # before ConnectionError's OSError kin: a host name that does not resolve
        print(f"agent {args.agent}: world host of {args.world!r} not found ({err.strerror}); exiting", file=sys.stderr)
        return 1
    except (PeerGone, TimeoutError, ConnectionError) as err:
        print(f"agent {args.agent}: world gone or silent ({err}); exiting", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
