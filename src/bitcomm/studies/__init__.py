"""Studies built on training and evaluation: the four-technique comparison (`compare.py`), gradient
variance (`variance.py`), scaling with the grid size (`scaling.py`), noise sweeps (`sweep.py`), what
the messages mean (`analysis.py`), episode pictures (`render.py`), and their tables
(`tables.py`; the intervals are `bitcomm.stats`).

May import: everything below it (`bitcomm.config`, `bitcomm.errors`, `bitcomm.files`, `bitcomm.checkpoint`,
`bitcomm.run_lock`, `bitcomm.plotting`, `bitcomm.stats`, `bitcomm.channel`, `bitcomm.envs`, `bitcomm.policies`,
`bitcomm.learn`), not `bitcomm.deploy` or `bitcomm.commands`.
"""
