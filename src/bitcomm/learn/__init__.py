"""Learning: the rollout (`rollout.py`: the per-agent tensors of a batch of whole episodes, the contract
of everything below), the gradient estimators (`estimators.py`, SPEC section 4), the objective terms
(`objectives.py`: policy gradient, critic, entropy, and the auxiliary terms), the learner that sums, clips
and steps them (`learner.py`), the configs and recipes (`config.py`, `recipes.py`, `options.py`), and
the trainers: `run.py` (the entry point and the sync trainer), `a3c.py`, with the run folder both
write (`run_folder.py`). The same core on any channel-wrapped PettingZoo env: `env_config.py`,
`env_rollout.py`, `env_learner.py` (multi-recipient credit), `env_run.py`, `env_eval.py`, and
`env_controller.py`: `bitcomm.EnvController`, such a run's policy acting in a loop of its user's (here, not
beside `Controller` in `policies`, as it reads the run through `env_eval.load_env_policy`).

May import: `bitcomm.config`, `bitcomm.errors`, `bitcomm.files`, `bitcomm.checkpoint`, `bitcomm.run_lock`,
`bitcomm.plotting`, `bitcomm.stats`, `bitcomm.channel`, `bitcomm.envs`, `bitcomm.policies`. Importing the package
imports nothing (no torch): the CLI reads `options.py` to build its flags.
"""
