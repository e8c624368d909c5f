"""Policies and how they are played: the networks (`networks.py`: policy and critic, with their
observation encoders) and message heads (`heads.py`), the MLP policy and critic for any wrapped
env's vector observations (`mlp.py`), the learned policy as a numpy-in/numpy-out
`Controller` and its ONNX form (`onnx_export.py`, `onnx_policy.py`), the reference policies
(`reference.py`: oracle, random), the per-agent view every runtime shares (`agent_policies.py`),
where a command's policy comes from (`source.py`), the one evaluator (`evaluation.py`) and the CPU's
denormal mode both training and evaluation run in (`denormals.py`).

May import: `bitcomm.config`, `bitcomm.errors`, `bitcomm.files`, `bitcomm.checkpoint`, `bitcomm.stats`,
`bitcomm.channel`, `bitcomm.envs`. Nothing here knows how a policy is trained. Importing the package imports
nothing (no torch).
"""
