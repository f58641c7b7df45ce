"""MetaWorld tasks, demonstration collection and evaluation collectors (installed as ``tar_rl.collectors``).

- :mod:`tar_rl.collectors.tasks`: the 50 v3 tasks, the fixed task index, difficulty groups,
  instructions and task variations.
- :mod:`tar_rl.collectors.demos`: scripted-expert demonstrations over worker processes.
- :mod:`tar_rl.collectors.envs` and :mod:`tar_rl.collectors.evaluate`: TorchRL environments and
  the evaluation collector (success, steps, rho per rollout).
"""
