"""The MetaWorld v3 suite (``data.suite=metaworld``, the default): tasks, scripted-expert demonstrations,
their dataset, TorchRL environments, the evaluation collector and camera images; :mod:`.suite` holds the
:class:`~tar_rl.collectors.suite.Suite` the recipe uses."""
