"""Demonstration collection and evaluation collectors (installed as ``tar_rl.collectors``).

Empty until the MetaWorld data and evaluation work lands (issue 3).
"""
