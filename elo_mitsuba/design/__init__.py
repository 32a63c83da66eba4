"""Design of detector systems (issue 27): a design's geometry and constraints (:mod:`.geometry`),
the optimiser's spec (:mod:`.spec`), the evaluation of one design (:mod:`.evaluate`), the
optimiser itself on the sweeps' Dask engine (:mod:`.optimize`), its store (:mod:`.store`) and
what a builder takes away: the front as a plot, a design as a scene, Table 1 for comparison
(:mod:`.results`). The figure of merit is :mod:`elo_mitsuba.analysis.precision`.
"""
