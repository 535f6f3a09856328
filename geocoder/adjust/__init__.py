"""Least-squares block adjustment (pure numpy / scipy.sparse); imports nothing from the simulator.

Modules, bottom up: :mod:`~geocoder.adjust.observations` (ground points, image observations,
weights), :mod:`~geocoder.adjust.sensor` (the ``SensorModel`` protocol and the numeric
Jacobian), :mod:`~geocoder.adjust.orbit` and :mod:`~geocoder.adjust.linescanner_geometry` (the
rigorous scanner; geodesy in :mod:`geocoder.geodesy`), :mod:`~geocoder.adjust.models` (one
module per model), :mod:`~geocoder.adjust.problem` (the data types), :mod:`~geocoder.adjust.layout`
and :mod:`~geocoder.adjust.normals` (the reduced normal equations),
:mod:`~geocoder.adjust.statistics`, :mod:`~geocoder.adjust.gauss_newton`,
:mod:`~geocoder.adjust.driver` (:func:`~geocoder.adjust.solver.adjust`), and at the top
:mod:`~geocoder.adjust.block`, :mod:`~geocoder.adjust.io` and :mod:`~geocoder.adjust.run` (files
in and out).  :mod:`~geocoder.adjust.solver` gathers the solver's public names.
"""
