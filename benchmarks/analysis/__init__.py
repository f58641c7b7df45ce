"""Analyses of the studies' runs, from their tables: the phases of a demonstration and TAR's weight mass in them
(:mod:`.phases`) and the figures (:mod:`.figures`)."""
