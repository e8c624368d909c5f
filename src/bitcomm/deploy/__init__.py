"""The deploy runtime: the task played by separate processes, as robots would play it.

One world process (`world.py`: the grid, actuation noise, observations, moves) and one process per
agent (`agent.py`: its own policy only). Agents send their K-bit messages to each other as UDP
datagrams on loopback (`protocol.py`), each tagged with a run id, the episode, the step it belongs to
and a sequence number; a message that has not arrived by its deadline counts as lost (zeros), and a
seeded fraction of datagrams is dropped on purpose by the sender. `bitcomm deploy` is the command.

May import: `bitcomm.config`, `bitcomm.errors`, `bitcomm.channel`, `bitcomm.envs`, `bitcomm.policies`;
not `bitcomm.learn` (a robot runs a policy, it does not train one), `bitcomm.studies` or `bitcomm.commands`.
"""

from bitcomm.deploy.world import DeployError, DeployResult, EpisodeOutcome, episode_set, place_episode, run_deploy

__all__ = ["DeployError", "DeployResult", "EpisodeOutcome", "episode_set", "place_episode", "run_deploy"]
