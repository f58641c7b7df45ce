"""The simulator suites (installed as ``tar_rl.collectors``): what the recipe asks of a suite
(:mod:`.suite`), their registry (:mod:`.suites`) and one module or package per suite.

- :mod:`tar_rl.collectors.metaworld`: MetaWorld v3. ``tasks`` (the 50 tasks, the fixed task index,
  difficulty groups, instructions, variations), ``demos`` (scripted experts over worker processes),
  ``dataset`` (the demonstrations as a :mod:`tar_rl.data` dataset), ``envs`` and ``evaluate`` (TorchRL
  environments and the evaluation collector with its worker pool), ``render`` (camera images),
  ``suite`` (the :class:`~tar_rl.collectors.suite.Suite`).
- :mod:`tar_rl.collectors.dmc`: dm_control's point_mass and reacher with scripted experts.
- :mod:`tar_rl.collectors.libero`: LIBERO evaluation of imported LIBERO demonstrations.
"""
